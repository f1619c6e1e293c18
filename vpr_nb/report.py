"""Results report: notebooks ``record`` their headline numbers; ``make reproduce`` gathers them.

Inside a notebook, ``record("03_dw_triplet", {"T-Loss R@1": 0.71, ...})`` is a no-op unless the
environment variable ``VPR_NB_RESULTS`` names a JSON-lines file, which the report runner
(``python -m vpr_nb.report``) sets while it executes the notebook sequence with papermill.
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping

RESULTS_ENV = "VPR_NB_RESULTS"


def _jsonable(value):
    """Numbers, strings, lists and dicts of them (numpy scalars/arrays are converted)."""
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"record() stores numbers, strings, lists and dicts; got {type(value).__name__}")


def record(notebook: str, results: Mapping) -> None:
    """Append ``results`` (a flat or nested dict of numbers/strings) under the key ``notebook``.

    Does nothing (and prints nothing) when ``VPR_NB_RESULTS`` is unset, so notebooks can call it
    unconditionally and stay identical under nbval.
    """
    if not isinstance(notebook, str) or not notebook:
        raise ValueError("record() needs a non-empty notebook key such as '01_retrieval_and_recall'")
    if not isinstance(results, Mapping) or not results:
        raise ValueError("record() needs a non-empty dict of results, e.g. {'R@1': 0.71}")
    payload = {"notebook": notebook, "results": _jsonable(results)}
    path = os.environ.get(RESULTS_ENV)
    if not path:
        return
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(payload) + "\n")
