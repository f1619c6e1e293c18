"""vpr_nb.authoring: stored notebooks carry no widget state; re-execution in place keeps the jupytext pair."""
import nbformat
import pytest

from vpr_nb import authoring


def _widget_notebook():
    nb = nbformat.v4.new_notebook()
    nb.metadata["widgets"] = {"application/vnd.jupyter.widget-state+json": {"state": {"abc": {}}}}
    cell = nbformat.v4.new_code_cell("# NBVAL_IGNORE_OUTPUT\nwidgets.interact(f, x=1)")
    cell.outputs = [nbformat.v4.new_output("display_data", data={
        authoring.WIDGET_VIEW: {"model_id": "abc", "version_major": 2, "version_minor": 0},
        "text/plain": "interactive(children=(IntSlider(value=1),))"}),
        nbformat.v4.new_output("stream", text="kept\n")]
    nb.cells = [nbformat.v4.new_markdown_cell("# t"), cell]
    return nb


def test_clean_drops_widget_state_and_views_only():
    nb = _widget_notebook()
    assert authoring.has_widget_state(nb)
    authoring.clean(nb)
    assert not authoring.has_widget_state(nb)
    assert [o["output_type"] for o in nb.cells[1].outputs] == ["stream"]
    with pytest.raises(ValueError, match="nbformat notebook"):
        authoring.clean({"cells": []})


def test_execute_in_place_syncs_pair_executes_and_cleans(tmp_path):
    import jupytext
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.metadata["jupytext"] = {"formats": "ipynb,py:percent"}
    nb.cells = [nbformat.v4.new_code_cell("x = 6 * 7\nprint(x)", metadata={"tags": ["keep"]})]
    path = tmp_path / "01_t.ipynb"
    nbformat.write(nb, path)
    jupytext.write(nb, tmp_path / "01_t.py", fmt="py:percent")
    authoring.execute_in_place(path, timeout=60)
    out = nbformat.read(path, as_version=4)
    assert out.cells[0].outputs[0]["text"] == "42\n" and out.cells[0].metadata["tags"] == ["keep"]
    assert "x = 6 * 7" in (tmp_path / "01_t.py").read_text()
    with pytest.raises(FileNotFoundError, match="jupytext pair"):
        (tmp_path / "02_lonely.ipynb").write_text(nbformat.writes(nb))
        authoring.execute_in_place(tmp_path / "02_lonely.ipynb")
