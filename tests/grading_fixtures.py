"""A tiny instructor notebook and its submissions, shared by the grading tests (not a test module)."""
import copy
import re

import nbformat

from vpr_nb.assignments import BEGIN_HIDDEN, CODE_STUB, DEPS_TAG, END_HIDDEN, is_solution, student_version


def build(cells) -> nbformat.NotebookNode:
    """A notebook from ``(kind, source[, grade_id[, points]])`` tuples; kinds ``md``, ``code``, ``dep`` (a code
    cell tagged ``grade-deps:<grade_id>``; ``params`` also tagged ``parameters``), ``solution`` and ``tests``
    (the last two get nbgrader's cell metadata, as the course notebooks carry it)."""
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
        elif kind in ("dep", "params"):
            cell.metadata["tags"] = [f"{DEPS_TAG}{g}" for g in grading] + (["parameters"] if kind == "params" else [])
        nb.cells.append(cell)
    return nb


SQUARE = """def square(x):
    ### BEGIN SOLUTION
    return x * x
    ### END SOLUTION"""
SQUARE_TESTS = f"""from vpr_nb.assignments import Case, check

check("square", [Case("square(3)", (3,), expect=9)])
{BEGIN_HIDDEN}
check("square", [Case("square(-2)", (-2,), expect=4), Case("square(1.5)", (1.5,), expect=2.25)])
{END_HIDDEN}"""
CUBE = """def cube(x):
    ### BEGIN SOLUTION
    return x ** 3
    ### END SOLUTION"""
# own_code=False: nothing static stands between the cube answer and the sandbox (the attack tests use it)
CUBE_TESTS = f"""from vpr_nb.assignments import Case, check

check("cube", [Case("cube(2)", (2,), expect=8)], own_code=False)
{BEGIN_HIDDEN}
check("cube", [Case("cube(-3)", (-3,), expect=-27)], own_code=False)
{END_HIDDEN}"""
NAME = "98_two.ipynb"


def two_exercises() -> nbformat.NotebookNode:
    """Two exercises with grade-deps, and an untagged cell that must never run when grading."""
    return build([("params", "SCALE = 1", "ex-square", "ex-cube"),
                  ("dep", "import math", "ex-square", "ex-cube"),
                  ("code", "raise RuntimeError('an expensive training cell: grading must not run it')"),
                  ("solution", SQUARE, "ex-square"), ("tests", SQUARE_TESTS, "ex-square", 2),
                  ("solution", CUBE, "ex-cube"), ("tests", CUBE_TESTS, "ex-cube", 1)])


def write(nb, path):
    path.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, path)
    return path


def answer(nb, grade_id, body):
    """``nb`` with the stub of solution ``grade_id`` replaced by ``body`` (indented like the stub); a body
    starting with ``@cell`` replaces the whole solution cell instead."""
    nb = copy.deepcopy(nb)
    cell = next(c for c in nb.cells if is_solution(c) and c.metadata["nbgrader"]["grade_id"] == grade_id)
    if body.startswith("@cell\n"):
        cell.source = body[len("@cell\n"):]
        return nb
    indent = re.search(rf"^([ \t]*){re.escape(CODE_STUB)}", cell.source, re.M).group(1)
    cell.source = cell.source.replace(indent + CODE_STUB, "\n".join(indent + line for line in body.split("\n")))
    return nb


def submission(instructor, square_body="return x * x", cube_body="return x ** 3"):
    return answer(answer(student_version(instructor), "ex-square", square_body), "ex-cube", cube_body)
