"""Re-execute a course notebook in place, the way its stored outputs are committed.

    python -m vpr_nb.authoring notebooks/06_gds.ipynb [more notebooks ...]     (or: make notebook NB=06)

For each notebook: sync it with its jupytext pair (``notebooks/NN_name.py``; the newer side wins),
execute it top to bottom from a fresh kernel in the notebook's folder (``PROFILE`` as stored, i.e. the
``ci`` profile), then :func:`clean` it and write it back. Stored notebooks must not carry what changes
from run to run without saying anything: ipywidgets' saved widget state (40-66 KB of JSON per
notebook, a new random model id on every run) and the widget view outputs that point at it, which a
front end without that state shows as a raw ``interactive(children=...)`` text. A widget appears when
the student runs its cell; nbval skips it (its cell is marked ``NBVAL_IGNORE_OUTPUT``). Nor the kernel's
Python version (``metadata.language_info.version``): saved under 3.12 or 3.13 the same notebook would differ.
Jupyter writes it on every save, so ``make venv`` (and Binder's ``postBuild``) also install
:func:`pre_save_hook` into the environment's Jupyter server (``python -m vpr_nb.authoring --install-save-hook``):
a notebook saved from JupyterLab then carries no version either, and ``git status`` stays clean.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .atomic import atomic_write_text
from .kernels import pin_this_process

WIDGET_VIEW = "application/vnd.jupyter.widget-view+json"
SAVE_HOOK = "vpr_nb.authoring.pre_save_hook"
SAVE_HOOK_CONFIG = "jupyter_server_config.json"      # under <prefix>/etc/jupyter (a .d folder holds extensions only)


def strip_python_version(metadata) -> None:
    """Drop ``language_info.version`` from a notebook's ``metadata`` (edited in place): the only field of the
    course notebooks' metadata that differs between the Pythons they run on."""
    info = metadata.get("language_info") if isinstance(metadata, dict) else None
    if isinstance(info, dict):
        info.pop("version", None)


def pre_save_hook(model, **_kwargs) -> None:
    """A Jupyter server ``ContentsManager.pre_save_hook``: a notebook is saved without the kernel's Python
    version (:func:`strip_python_version`); any other file is left alone."""
    if isinstance(model, dict) and model.get("type") == "notebook" and isinstance(model.get("content"), dict):
        strip_python_version(model["content"].get("metadata", {}))


def install_save_hook(prefix: str | None = None) -> Path:
    """Write the Jupyter server config that runs :func:`pre_save_hook` into ``<prefix>/etc/jupyter`` (default:
    this Python's ``sys.prefix``, i.e. the venv); return its path. Only servers of that environment read it,
    and there ``vpr_nb`` is importable."""
    path = Path(sys.prefix if prefix is None else prefix) / "etc" / "jupyter" / SAVE_HOOK_CONFIG
    config = {}
    if path.is_file():           # keep what else the environment configures there
        try:
            config = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path} is not a JSON config ({exc}); fix or remove it, then run again") from None
        if not isinstance(config, dict):
            raise ValueError(f"{path} holds {type(config).__name__}, not a JSON object; fix or remove it")
    section = config.setdefault("ContentsManager", {})
    if not isinstance(section, dict):
        raise ValueError(f"{path}: 'ContentsManager' must be a JSON object; fix or remove it")
    section["pre_save_hook"] = SAVE_HOOK
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(path, json.dumps(config, indent=2) + "\n")


def clean(nb):
    """Drop the widget state and the Python version from ``nb.metadata`` and every widget-view output; return
    ``nb`` (edited in place)."""
    if "cells" not in nb or "metadata" not in nb:
        raise ValueError("clean() expects an nbformat notebook (with 'cells' and 'metadata'); "
                         "read it with nbformat.read(path, as_version=4)")
    nb["metadata"].pop("widgets", None)
    strip_python_version(nb["metadata"])
    for cell in nb["cells"]:
        if cell.get("cell_type") == "code":
            cell["outputs"] = [o for o in cell.get("outputs", []) if WIDGET_VIEW not in o.get("data", {})]
    return nb


def has_widget_state(nb) -> bool:
    """True if ``nb`` still carries saved widget state or a widget-view output (see :func:`clean`)."""
    return "widgets" in nb["metadata"] or any(
        WIDGET_VIEW in o.get("data", {}) for c in nb["cells"] if c.get("cell_type") == "code" for o in c.get("outputs", []))


def execute_in_place(path, timeout: int = 600) -> float:
    """Sync ``path`` with its jupytext pair, execute it, clean it, write it; return the seconds it ran."""
    import jupytext
    import nbformat
    from jupytext.cli import jupytext as jupytext_cli
    from nbclient import NotebookClient

    path = Path(path)
    if path.suffix != ".ipynb" or not path.is_file():
        raise FileNotFoundError(f"no notebook at {path}: pass a notebooks/NN_name.ipynb file")
    if not path.with_suffix(".py").is_file():
        raise FileNotFoundError(f"{path.name} has no jupytext pair {path.with_suffix('.py').name}: create it with "
                                f"`jupytext --set-formats ipynb,py:percent {path}`")
    jupytext_cli(["--sync", "--quiet", str(path)])
    pin_this_process()       # the kernel computes what nbval's kernels compute (vpr_nb.kernels)
    nb = jupytext.read(path)  # the synced notebook, outputs and cell ids kept
    t0 = time.perf_counter()
    # store_widget_state=True although clean() drops the state: with False, nbclient 0.11's Output-widget hook
    # raises KeyError (widget_state[comm_id]) whenever a widget's output arrives through it
    NotebookClient(nb, timeout=timeout, kernel_name="python3", store_widget_state=True,
                   resources={"metadata": {"path": str(path.parent)}}).execute()
    seconds = time.perf_counter() - t0
    nbformat.write(clean(nb), path)
    jupytext_cli(["--sync", "--quiet", str(path)])  # the script's timestamp follows the notebook's
    return seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.authoring", description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", help="notebooks/NN_name.ipynb files to re-execute in place")
    parser.add_argument("--install-save-hook", action="store_true",
                        help="install the Jupyter save hook that keeps the Python version out of saved notebooks "
                             "into this environment (sys.prefix/etc/jupyter) and exit")
    parser.add_argument("--timeout", type=int, default=600, help="seconds allowed per cell (default 600)")
    args = parser.parse_args(argv)
    if args.install_save_hook:
        print(f"Jupyter save hook installed: {install_save_hook()}")
        return 0
    if not args.notebooks:
        parser.error("name the notebooks to re-execute, e.g. notebooks/06_gds.ipynb")
    for nb in args.notebooks:
        try:
            seconds = execute_in_place(nb, args.timeout)
        except FileNotFoundError as exc:
            parser.error(str(exc))
        print(f"{nb}: executed in {seconds:.1f} s, cleaned, written", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
