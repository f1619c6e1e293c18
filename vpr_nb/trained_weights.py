"""Trained weights committed beside a notebook's results, so that its figures show the trained model.

A notebook's CI profile trains for one epoch (it must run in a minute), but its figures illustrate the
model its text describes: the one trained in the reproduce profile. So the reproduce run keeps, for the
runs a figure needs, the **trained part** of the model (the entries of its ``state_dict`` that differ from
the model it started from, and every aggregator entry) in ``notebooks/results/<notebook>.<label>.pt``,
next to ``<notebook>.json``, whose record names the file with its sha256:

    entry = save_trained("04_netvlad", "netvlad-seed0", model, start)    # in the reproduce profile
    results.save("04_netvlad", EXPERIMENT, {..., "trained weights": {"netvlad-seed0": entry}})

    committed = results.load("04_netvlad", EXPERIMENT)                  # in every profile
    model = load_trained(committed, "netvlad-seed0", make_start_model())

:func:`load_trained` rebuilds the model as the run started it (the caller's model: same backbone, same
aggregator, same initialisation), checks the file's size and sha256 against the record, reads it with
``torch.load(..., weights_only=True)`` (no code runs), checks every key and shape, copies the entries in and
finally checks the sha256 of the whole resulting ``state_dict`` against the one the run recorded, so the
figure shows exactly the trained model, or the notebook stops with an error saying how to fix it. The
results record itself is keyed on the experiment config, the course backbone and the world
(:func:`vpr_nb.results.load`), so stale weights cannot be shown silently either.
"""
from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Mapping
from pathlib import Path

import torch

from .package_data import committed_results_dir
from .results import results_path

_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")
_FIX = "re-run the notebook with PROFILE = 'reproduce' and commit its results"


def _check_label(label) -> str:
    if not isinstance(label, str) or not _LABEL.match(label):
        raise ValueError(f"label must be 1-64 letters, digits, '-' or '_' (a file-name part such as 'netvlad-seed0'), "
                         f"got {label!r}")
    return label


def _check_module(model, what: str) -> torch.nn.Module:
    if not isinstance(model, torch.nn.Module):
        raise ValueError(f"{what} must be a torch.nn.Module, got {type(model).__name__}")
    return model


def state_sha256(state: Mapping[str, torch.Tensor]) -> str:
    """sha256 of a ``state_dict``: every key, dtype, shape and the tensor's bytes, in key order."""
    h = hashlib.sha256()
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def trained_part(model: torch.nn.Module, start: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The entries of ``model.state_dict()`` that differ from ``start``'s, and every ``aggregator.`` entry."""
    model, start = _check_module(model, "model"), _check_module(start, "start")
    now, before = model.state_dict(), start.state_dict()
    if set(now) != set(before):
        raise ValueError(f"model and start have different state_dict keys ({sorted(set(now) ^ set(before))[:5]}); "
                         f"start must be the same model before training")
    return {k: v.detach().cpu().clone() for k, v in now.items()
            if k.startswith("aggregator.") or v.shape != before[k].shape or not torch.equal(v.cpu(), before[k].cpu())}


def save_trained(name: str, label: str, model: torch.nn.Module, start: torch.nn.Module, *, results_dir=None) -> dict:
    """Write the trained part of ``model`` (:func:`trained_part` against ``start``, the same model before
    training) to ``<results dir>/<name>.<label>.pt``, atomically; return the entry for the results record
    (``file``, ``bytes``, ``sha256``, ``keys``, ``state sha256`` of the whole trained model)."""

    label = _check_label(label)
    json_path = results_path(name, results_dir, write=True)
    part = trained_part(model, start)
    path = json_path.with_name(f"{name}.{label}.pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(part, tmp)
    os.replace(tmp, path)
    data = path.read_bytes()
    return {"file": path.name, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest(), "keys": len(part),
            "state sha256": state_sha256(model.state_dict())}


def load_trained(committed: Mapping, label: str, model: torch.nn.Module, *, results_dir=None) -> torch.nn.Module:
    """Copy the committed trained weights ``label`` into ``model`` (built as the run started it) and return it.

    ``committed`` is what :func:`vpr_nb.results.load` returned for the notebook; its ``results["trained
    weights"][label]`` entry names the file. Raises ``FileNotFoundError`` when the file is missing and
    ``ValueError`` when the record has no such entry, the file's size or sha256 differs from the record,
    it is not a weights-only ``state_dict`` of ``model``'s keys and shapes, or the loaded model is not the
    one the run trained (``model`` was built differently)."""
    label = _check_label(label)
    model = _check_module(model, "model")
    if not isinstance(committed, Mapping) or not isinstance(committed.get("results"), Mapping):
        raise ValueError("committed must be the record vpr_nb.results.load returned (with a 'results' entry)")
    name = committed.get("notebook", "?")
    entries = committed["results"].get("trained weights")
    if not isinstance(entries, Mapping) or not isinstance(entries.get(label), Mapping):
        have = sorted(entries) if isinstance(entries, Mapping) else []
        raise ValueError(f"the committed results of {name} record no trained weights {label!r} (recorded: "
                         f"{have or 'none'}); {_FIX}")
    entry = entries[label]
    file = entry.get("file")
    if not isinstance(file, str) or Path(file).name != file or not file.endswith(".pt"):
        raise ValueError(f"the committed results of {name} name a weights file {file!r} that is not a plain "
                         f"'.pt' file name; {_FIX}")
    path = Path(results_dir) / file if results_dir is not None else committed_results_dir() / file
    if not path.is_file():
        raise FileNotFoundError(f"the trained weights {file} that the committed results of {name} record are "
                                f"missing from {path.parent}; restore them (git checkout -- notebooks/results/{file}) "
                                f"or {_FIX}")
    data = path.read_bytes()
    if len(data) != entry.get("bytes") or hashlib.sha256(data).hexdigest() != entry.get("sha256"):
        raise ValueError(f"{file} is not the file the committed results of {name} record (size or sha256 differs: "
                         f"changed or truncated); restore it (git checkout -- notebooks/results/{file}) or {_FIX}")
    try:
        part = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means the file is not weights only
        raise ValueError(f"{file} is not a weights-only state_dict ({type(exc).__name__}: {exc}); {_FIX}") from None
    state = model.state_dict()
    if not isinstance(part, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in part.items()):
        raise ValueError(f"{file} does not hold a state_dict (names -> tensors); {_FIX}")
    unknown = sorted(set(part) - set(state))
    if unknown:
        raise ValueError(f"{file} holds entries the model has not ({unknown[:5]}): the model is built differently "
                         f"from the trained one; {_FIX}")
    wrong = [k for k, v in part.items() if v.shape != state[k].shape or v.dtype != state[k].dtype]
    if wrong:
        raise ValueError(f"{file}: entries {wrong[:5]} have other shapes or dtypes than the model's "
                         f"({[tuple(part[k].shape) for k in wrong[:5]]} vs {[tuple(state[k].shape) for k in wrong[:5]]}); "
                         f"the model is built differently from the trained one; {_FIX}")
    model.load_state_dict({**state, **part})
    if state_sha256(model.state_dict()) != entry.get("state sha256"):
        raise ValueError(f"the model built here with {file} is not the model the run trained (the entries not in "
                         f"the file, the untrained part, differ: build it as the run did); {_FIX}")
    return model
