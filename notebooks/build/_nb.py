"""Shared by the notebook builders: turn a list of cells into an nbformat v4 notebook file.

A builder defines ``CELLS = [("md" | "code", source[, tags]), ...]`` and calls ``write(NAME, CELLS)``;
exercises use ``("solution", source, grade_id)`` (code with ``### BEGIN SOLUTION`` / ``### END SOLUTION``)
followed by ``("tests", source, grade_id, points)`` (asserts, optionally ``### BEGIN HIDDEN TESTS`` /
``### END HIDDEN TESTS``), which get nbgrader's cell metadata (see ``vpr_nb.assignments``);
``python notebooks/build/NN_name.py`` then writes ``notebooks/NN_name.ipynb`` (unexecuted; execute it in
place with ``jupyter nbconvert --to notebook --execute --inplace``).
"""
from pathlib import Path

import nbformat


def build(name: str, cells) -> nbformat.NotebookNode:
    """Assemble the notebook from ``cells``; cell ids are stable so rebuilds give small diffs."""
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.metadata["language_info"] = {"name": "python"}
    for cell in cells:
        kind, src = cell[0], cell[1].strip("\n")
        if kind not in ("md", "code", "solution", "tests"):
            raise ValueError(f"cell kind must be 'md', 'code', 'solution' or 'tests', got {kind!r}")
        new = nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src)
        if kind == "solution":
            new.metadata["nbgrader"] = {"solution": True, "grade": False, "locked": False,
                                        "grade_id": cell[2], "schema_version": 3}
        elif kind == "tests":
            new.metadata["nbgrader"] = {"solution": False, "grade": True, "locked": True,
                                        "grade_id": f"{cell[2]}-tests", "points": cell[3], "schema_version": 3}
        elif len(cell) > 2:
            new.metadata["tags"] = list(cell[2])
        nb.cells.append(new)
    for k, c in enumerate(nb.cells):
        c["id"] = f"{name[:2]}-{k:02d}"
    return nb


def write(name: str, cells) -> Path:
    """Write ``notebooks/<name>.ipynb`` and return its path."""
    out = Path(__file__).resolve().parents[1] / f"{name}.ipynb"
    nbformat.write(build(name, cells), out)
    print("wrote", out.name)
    return out
