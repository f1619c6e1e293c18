"""Each notebook is a jupytext pair (``notebooks/NN_name.ipynb`` + ``notebooks/NN_name.py``, percent format,
see ``notebooks/jupytext.toml``): the script is what a teacher edits and lints, the notebook what
students open and nbval checks. They must hold the same cells."""
from pathlib import Path

import jupytext
import nbformat
import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
IPYNBS = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))
KEPT_METADATA = ("tags", "nbgrader")          # the cell metadata the pair carries (jupytext.toml)


def _cells(nb):
    return [(c.cell_type, c.source.strip("\n"), {k: c.metadata[k] for k in KEPT_METADATA if k in c.metadata})
            for c in nb.cells]


def test_every_notebook_has_a_pair_and_no_orphan_script():
    assert IPYNBS, "no notebooks found"
    scripts = {p.stem for p in NOTEBOOKS.glob("[0-9][0-9]_*.py")}
    notebooks = {p.stem for p in IPYNBS}
    assert scripts == notebooks, (f"notebooks without a paired script: {sorted(notebooks - scripts)}; "
                                  f"scripts without a notebook: {sorted(scripts - notebooks)} "
                                  "(pair with `jupytext --set-formats ipynb,py:percent notebooks/NN_name.ipynb`)")


@pytest.mark.parametrize("ipynb", IPYNBS, ids=lambda p: p.stem)
def test_pair_in_sync(ipynb):
    nb = nbformat.read(ipynb, as_version=4)
    py = jupytext.read(ipynb.with_suffix(".py"))
    assert nb.metadata.get("jupytext", {}).get("formats") == "ipynb,py:percent", \
        f"{ipynb.name} is not paired (run `jupytext --set-formats ipynb,py:percent {ipynb.name}`)"
    a, b = _cells(nb), _cells(py)
    assert len(a) == len(b), (f"{ipynb.name} has {len(a)} cells, its script {len(b)}: run "
                              f"`jupytext --sync notebooks/{ipynb.name}` and re-execute the notebook")
    for k, (x, y) in enumerate(zip(a, b)):
        assert x == y, (f"cell {k} of {ipynb.name} differs from its script (notebook: {x[0]} {x[2]} "
                        f"{x[1][:80]!r}...; script: {y[0]} {y[2]} {y[1][:80]!r}...): run "
                        f"`jupytext --sync notebooks/{ipynb.name}` and re-execute the notebook")


def test_all_code_cells_executed_in_order():
    """Stored outputs come from one top-to-bottom run (what nbval compares against)."""
    for ipynb in IPYNBS:
        counts = [c.execution_count for c in nbformat.read(ipynb, as_version=4).cells if c.cell_type == "code"]
        assert all(n is not None for n in counts), f"{ipynb.name} has unexecuted code cells: re-execute it"
        assert counts == sorted(counts), f"{ipynb.name} was not executed top to bottom: re-execute it"


def test_no_widget_state_stored():
    """Saved ipywidgets state changes on every run and shows as raw text without it (`make notebook` strips it)."""
    from vpr_nb.authoring import has_widget_state
    dirty = [p.name for p in IPYNBS if has_widget_state(nbformat.read(p, as_version=4))]
    assert not dirty, f"{dirty} carry widget state: re-execute them with `make notebook NB=NN`"
