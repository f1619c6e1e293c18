"""Student versions and grading with nbgrader's markers (vpr_nb.assignments)."""
import copy
from pathlib import Path

import nbformat
import pytest

from vpr_nb.assignments import (BEGIN_HIDDEN, BEGIN_SOLUTION, CODE_STUB, exercises, generate, grade,
                                student_version)

ROOT = Path(__file__).resolve().parents[1]


def build(cells) -> nbformat.NotebookNode:
    """A notebook from ``(kind, source[, grade_id[, points]])`` tuples; kinds ``md``, ``code``, ``solution``
    and ``tests`` (the last two get nbgrader's cell metadata, as the course notebooks carry it)."""
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    for kind, src, *grading in cells:
        cell = nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src)
        if kind == "solution":
            cell.metadata["nbgrader"] = {"solution": True, "grade": False, "locked": False,
                                         "grade_id": grading[0], "schema_version": 3}
        elif kind == "tests":
            cell.metadata["nbgrader"] = {"solution": False, "grade": True, "locked": True,
                                         "grade_id": f"{grading[0]}-tests", "points": grading[1], "schema_version": 3}
        nb.cells.append(cell)
    return nb

SOLUTION = """def square(x):
    ### BEGIN SOLUTION
    return x * x
    ### END SOLUTION"""
TESTS = f"""assert square(3) == 9
{BEGIN_HIDDEN}
assert square(-2) == 4
### END HIDDEN TESTS"""


def _tiny(tmp_path):
    nb = build([("md", "# tiny"), ("code", "import math"), ("solution", SOLUTION, "ex-square"),
           ("tests", TESTS, "ex-square", 2), ("md", "done")])
    path = tmp_path / "instructor" / "99_tiny.ipynb"
    path.parent.mkdir()
    nbformat.write(nb, path)
    return path


def test_student_version_strips_solutions_and_hidden_tests(tmp_path):
    src = _tiny(tmp_path)
    out = generate(src.parent, tmp_path / "students")
    assert [p.name for p in out] == ["99_tiny.ipynb"]
    stu = nbformat.read(out[0], as_version=4)
    text = "\n".join(c.source for c in stu.cells)
    assert "x * x" not in text and "square(-2)" not in text and BEGIN_SOLUTION not in text
    assert f"    {CODE_STUB}" in stu.cells[2].source and "assert square(3) == 9" in stu.cells[3].source
    assert all(c.get("outputs", []) == [] for c in stu.cells if c.cell_type == "code")
    assert exercises(stu) == [("ex-square-tests", 3, 2.0)]


def test_grades_instructor_full_student_zero_pasted_back_full(tmp_path):
    src = _tiny(tmp_path)
    assert [g.points for g in grade(src, src)] == [2.0]
    stu_path = generate(src.parent, tmp_path / "students")[0]
    zero = grade(stu_path, src)
    assert [g.points for g in zero] == [0.0] and "NotImplementedError" in zero[0].error
    stu = nbformat.read(stu_path, as_version=4)
    stu.cells[2].source = stu.cells[2].source.replace(CODE_STUB, "return x ** 2")
    stu.cells[3].source = "pass  # a student deleting the visible tests changes nothing"
    nbformat.write(stu, tmp_path / "pasted.ipynb")
    assert [g.points for g in grade(tmp_path / "pasted.ipynb", src)] == [2.0]
    wrong = copy.deepcopy(stu)
    wrong.cells[2].source = stu.cells[2].source.replace("return x ** 2", "return abs(x) * 3")
    nbformat.write(wrong, tmp_path / "wrong.ipynb")
    assert [g.points for g in grade(tmp_path / "wrong.ipynb", src)] == [0.0]


def test_malformed_markers_and_missing_files(tmp_path):
    nb = build([("solution", "### BEGIN SOLUTION\nx = 1", "ex-bad")])
    with pytest.raises(ValueError, match="without"):
        student_version(nb, "98_bad")
    with pytest.raises(FileNotFoundError):
        grade(tmp_path / "nope.ipynb", tmp_path / "nope.ipynb")
    with pytest.raises(FileNotFoundError, match="no notebooks"):
        generate(tmp_path, tmp_path / "out")


@pytest.mark.parametrize("path", sorted((ROOT / "notebooks").glob("0[2-9]_*.ipynb")), ids=lambda p: p.name)
def test_every_notebook_from_02_has_a_gradable_exercise(path):
    nb = nbformat.read(path, as_version=4)
    ex = exercises(nb)
    assert ex, f"{path.name} has no exercise with nbgrader metadata"
    stu = student_version(nb, path.name)
    for cell in stu.cells:
        assert BEGIN_SOLUTION not in cell.source and BEGIN_HIDDEN not in cell.source
        if cell.cell_type == "code":
            compile(cell.source.replace("%matplotlib inline", ""), path.name, "exec")


@pytest.mark.slow
def test_real_notebook_instructor_full_student_zero_pasted_back_full(tmp_path):
    """The whole loop on a real course notebook (06, the quickest with an exercise)."""
    src = ROOT / "notebooks" / "06_gds.ipynb"
    full = grade(src, src)
    assert full and all(g.points == g.max_points for g in full), [g.error for g in full]
    stu_path = generate(ROOT / "notebooks", tmp_path / "students", pattern="06_gds.ipynb")[0]
    assert all(g.points == 0 for g in grade(stu_path, src, cwd=src.parent))
    instructor = nbformat.read(src, as_version=4)
    stu = nbformat.read(stu_path, as_version=4)
    for k, cell in enumerate(instructor.cells):          # paste each solution back where the stub is
        if cell.metadata.get("nbgrader", {}).get("solution"):
            stu.cells[k].source = cell.source
    nbformat.write(stu, tmp_path / "pasted.ipynb")
    back = grade(tmp_path / "pasted.ipynb", src, cwd=src.parent)
    assert all(g.points == g.max_points for g in back), [g.error for g in back]
