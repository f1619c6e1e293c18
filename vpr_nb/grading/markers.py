"""nbgrader's markers in an instructor notebook: which cells are solutions, tests, dependencies and parameters.

* a **solution cell**: metadata ``nbgrader.solution = true`` and ``grade_id = "<id>"``, or code between
  ``### BEGIN SOLUTION`` and ``### END SOLUTION``;
* a **test cell**: metadata ``nbgrader.grade = true``, ``grade_id = "<id>-tests"``, ``points``; hidden
  cases between ``### BEGIN HIDDEN TESTS`` and ``### END HIDDEN TESTS``;
* a **dependency** of exercise ``<id>``: a setup cell tagged ``grade-deps:<id>``;
* the **parameters** cell: tagged ``parameters``.

Both the student versions (:mod:`vpr_nb.assignments`) and the grader (:mod:`vpr_nb.grading.exercise`)
read the notebooks through these functions.
"""
from __future__ import annotations

import nbformat

BEGIN_SOLUTION, END_SOLUTION = "### BEGIN SOLUTION", "### END SOLUTION"
BEGIN_HIDDEN, END_HIDDEN = "### BEGIN HIDDEN TESTS", "### END HIDDEN TESTS"
DEPS_TAG = "grade-deps:"


def nbgrader_meta(cell) -> dict:
    """The cell's ``nbgrader`` metadata (empty when it has none)."""
    return cell.get("metadata", {}).get("nbgrader", {})


def is_solution(cell) -> bool:
    return bool(nbgrader_meta(cell).get("solution")) or BEGIN_SOLUTION in cell.source


def is_test(cell) -> bool:
    meta = nbgrader_meta(cell)
    return cell.cell_type == "code" and bool(meta.get("grade")) and not meta.get("solution")


def exercise_id(test_grade_id: str) -> str:
    """The exercise a test cell grades: its ``grade_id`` without the ``-tests`` suffix."""
    return test_grade_id[: -len("-tests")] if test_grade_id.endswith("-tests") else test_grade_id


def is_parameters(cell) -> bool:
    """The parameters cell (tag ``parameters``): students change it (``PROFILE``, paths), so it stays editable;
    grading uses the instructor's copy of it anyway."""
    return "parameters" in cell.get("metadata", {}).get("tags", [])


def deps_of(cell) -> set[str]:
    """Exercise ids whose grading needs this cell (its ``grade-deps:<id>`` tags)."""
    return {t[len(DEPS_TAG):] for t in cell.get("metadata", {}).get("tags", []) if t.startswith(DEPS_TAG)}


def exercises(nb: nbformat.NotebookNode) -> list[tuple[str, int, float]]:
    """(grade_id, cell index, points) of every test cell."""
    out = []
    for i, cell in enumerate(nb.cells):
        if is_test(cell):
            meta = nbgrader_meta(cell)
            if "grade_id" not in meta:
                raise ValueError(f"test cell {i} has no nbgrader grade_id: add one to its nbgrader metadata")
            out.append((meta["grade_id"], i, float(meta.get("points", 1))))
    return out
