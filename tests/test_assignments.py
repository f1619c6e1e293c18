"""Student versions and grading with nbgrader's markers (vpr_nb.assignments)."""
import ast
import copy
import csv
import re
from pathlib import Path

import nbformat
import pytest

from vpr_nb.assignments import (BEGIN_HIDDEN, BEGIN_SOLUTION, CODE_STUB, DEPS_TAG, END_HIDDEN, assert_own_code,
                                deps_of, exercise_id, exercises, generate, grade, grade_class, is_solution,
                                library_references, main, student_version)

ROOT = Path(__file__).resolve().parents[1]
COURSE = sorted((ROOT / "notebooks").glob("0[2-9]_*.ipynb"))


def build(cells) -> nbformat.NotebookNode:
    """A notebook from ``(kind, source[, grade_id[, points]])`` tuples; kinds ``md``, ``code``, ``dep`` (a code
    cell tagged ``grade-deps:<grade_id>``), ``solution`` and ``tests`` (the last two get nbgrader's cell
    metadata, as the course notebooks carry it)."""
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
        elif kind == "dep":
            cell.metadata["tags"] = [f"{DEPS_TAG}{g}" for g in grading]
        nb.cells.append(cell)
    return nb


SOLUTION = """def square(x):
    ### BEGIN SOLUTION
    return x * x
    ### END SOLUTION"""
TESTS = f"""assert square(3) == 9, f"square(3): expected 9, got {{square(3)}}"
{BEGIN_HIDDEN}
assert square(-2) == 4, f"square(-2): expected 4, got {{square(-2)}}"
{END_HIDDEN}"""
CUBE = """def cube(x):
    ### BEGIN SOLUTION
    return x ** 3
    ### END SOLUTION"""
CUBE_TESTS = 'assert cube(2) == 8, f"cube(2): expected 8, got {cube(2)}"'


def _write(nb, path):
    path.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, path)
    return path


def _tiny(tmp_path):
    nb = build([("md", "# tiny"), ("code", "import math"), ("solution", SOLUTION, "ex-square"),
                ("tests", TESTS, "ex-square", 2), ("md", "done")])
    nb.cells[1].metadata["execution"] = {"iopub.execute_input": "2026-01-01T00:00:00Z"}   # as nbconvert records
    return _write(nb, tmp_path / "instructor" / "99_tiny.ipynb")


def _two(tmp_path):
    """Two exercises with grade-deps, and an untagged cell that must never run when grading."""
    nb = build([("dep", "import math\nSCALE = 1", "ex-square", "ex-cube"),
                ("code", "raise RuntimeError('an expensive training cell: grading must not run it')"),
                ("solution", SOLUTION, "ex-square"), ("tests", TESTS, "ex-square", 2),
                ("solution", CUBE, "ex-cube"), ("tests", CUBE_TESTS, "ex-cube", 1)])
    return _write(nb, tmp_path / "instructor" / "98_two.ipynb")


def _answer(nb, grade_id, body):
    """``nb`` with the stub of solution ``grade_id`` replaced by ``body`` (indented like the stub)."""
    nb = copy.deepcopy(nb)
    cell = next(c for c in nb.cells if is_solution(c) and c.metadata["nbgrader"]["grade_id"] == grade_id)
    indent = re.search(rf"^([ \t]*){re.escape(CODE_STUB)}", cell.source, re.M).group(1)
    cell.source = cell.source.replace(indent + CODE_STUB, "\n".join(indent + line for line in body.split("\n")))
    return nb


def test_student_version_strips_solutions_hidden_tests_and_locks_read_only_cells(tmp_path):
    src = _tiny(tmp_path)
    out = generate(src.parent, tmp_path / "students")
    assert [p.name for p in out] == ["99_tiny.ipynb"]
    stu = nbformat.read(out[0], as_version=4)
    text = "\n".join(c.source for c in stu.cells)
    assert "x * x" not in text and "square(-2)" not in text and BEGIN_SOLUTION not in text
    assert f"    {CODE_STUB}" in stu.cells[2].source and "assert square(3) == 9" in stu.cells[3].source
    assert all(c.get("outputs", []) == [] and "execution" not in c.metadata for c in stu.cells if c.cell_type == "code")
    assert exercises(stu) == [("ex-square-tests", 3, 2.0)]
    assert stu.cells[3].metadata["editable"] is False and stu.cells[3].metadata["deletable"] is False
    assert "editable" not in stu.cells[2].metadata            # the solution cell stays editable
    two = student_version(nbformat.read(_two(tmp_path), as_version=4))
    assert two.cells[0].metadata["editable"] is False and two.cells[0].metadata["deletable"] is False


@pytest.mark.slow
def test_grades_instructor_full_student_zero_pasted_back_full(tmp_path):
    src = _tiny(tmp_path)
    assert [g.points for g in grade(src, src)] == [2.0]
    stu_path = generate(src.parent, tmp_path / "students")[0]
    zero = grade(stu_path, src)
    assert [g.points for g in zero] == [0.0] and "NotImplementedError" in zero[0].error
    stu = _answer(nbformat.read(stu_path, as_version=4), "ex-square", "return x ** 2")
    stu.cells[3].source = "pass  # a student deleting the visible tests changes nothing"
    assert [g.points for g in grade(_write(stu, tmp_path / "pasted.ipynb"), src)] == [2.0]
    wrong = _answer(nbformat.read(stu_path, as_version=4), "ex-square", "return abs(x) * 3")
    got = grade(_write(wrong, tmp_path / "wrong.ipynb"), src)
    assert [g.points for g in got] == [0.0]
    assert "square(3): expected 9, got 9" not in got[0].error and "expected 4, got 6" in got[0].error, got[0].error


@pytest.mark.slow
def test_only_dependency_cells_run_and_deleted_or_edited_tests_change_nothing(tmp_path):
    src = _two(tmp_path)
    assert [(g.grade_id, g.points) for g in grade(src, src)] == [("ex-square-tests", 2.0), ("ex-cube-tests", 1.0)]
    stu = student_version(nbformat.read(src, as_version=4))
    stu = _answer(_answer(stu, "ex-square", "return x * x"), "ex-cube", "return x * x * x")
    del stu.cells[3]                                          # the square tests, deleted
    stu.cells[4].source = "assert False"                      # the cube tests, edited
    got = grade(_write(stu, tmp_path / "edited.ipynb"), src)
    assert [g.points for g in got] == [2.0, 1.0], [g.error for g in got]


def test_feedback_names_expected_and_got_per_exercise(tmp_path, capsys):
    src = _two(tmp_path)
    stu = student_version(nbformat.read(src, as_version=4))
    stu = _answer(_answer(stu, "ex-square", "return x + x"), "ex-cube", "return x * x * x")
    path = _write(stu, tmp_path / "wrong.ipynb")
    assert main(["grade", str(path), "--source", str(src)]) == 0
    out = capsys.readouterr().out
    assert "square(3): expected 9, got 6" in out and "ex-cube-tests" in out and "total" in out and "1 / 3" in out


@pytest.mark.slow
def test_endless_loop_times_out_and_the_other_exercise_is_graded(tmp_path):
    src = _two(tmp_path)
    stu = student_version(nbformat.read(src, as_version=4))
    stu = _answer(_answer(stu, "ex-square", "return x * x"), "ex-cube", "while True:\n    pass")
    got = grade(_write(stu, tmp_path / "loop.ipynb"), src, timeout=3)
    assert got[0].points == 2.0, got[0].error
    assert got[1].points == 0.0 and "timed out after 3 s" in got[1].error, got[1].error


@pytest.mark.slow
def test_dead_kernel_scores_zero_and_the_next_exercise_gets_a_fresh_kernel(tmp_path):
    src = _two(tmp_path)
    stu = student_version(nbformat.read(src, as_version=4))
    stu = _answer(_answer(stu, "ex-square", "return x * x"), "ex-cube", "return x * x * x")
    stu.cells[2].source = "import os\nos._exit(1)\n" + stu.cells[2].source     # kills the kernel
    got = grade(_write(stu, tmp_path / "dead.ipynb"), src, timeout=60)
    assert got[0].points == 0.0 and "kernel died" in got[0].error, got[0].error
    assert got[1].points == 1.0, got[1].error


def test_missing_solution_cell_scores_zero_with_the_reason(tmp_path):
    src = _two(tmp_path)
    stu = student_version(nbformat.read(src, as_version=4))
    stu = _answer(stu, "ex-square", "return x * x")
    del stu.cells[4]                                          # the cube solution cell
    got = grade(_write(stu, tmp_path / "missing.ipynb"), src)
    assert got[0].points == 2.0 and got[1].points == 0.0 and "missing" in got[1].error


@pytest.mark.slow
def test_grade_class_writes_a_csv_per_student_and_exercise(tmp_path, capsys):
    src = _two(tmp_path)
    stu = student_version(nbformat.read(src, as_version=4))
    good = _answer(_answer(stu, "ex-square", "return x * x"), "ex-cube", "return x * x * x")
    _write(good, tmp_path / "sub" / "alice" / "98_two.ipynb")
    _write(stu, tmp_path / "sub" / "bob" / "98_two" / "98_two.ipynb")        # nbgrader's submitted/<student>/<assignment>/
    (tmp_path / "sub" / "carol").mkdir()
    (tmp_path / "sub" / "carol" / "98_two.ipynb").write_text("{not json")
    out = tmp_path / "scores.csv"
    assert main(["grade-class", str(tmp_path / "sub"), "--source", str(src.parent), "--csv", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    got = {(r["student"], r["exercise"]): float(r["points"]) for r in rows}
    assert got == {("alice", "ex-square"): 2.0, ("alice", "ex-cube"): 1.0, ("bob", "ex-square"): 0.0,
                   ("bob", "ex-cube"): 0.0, ("carol", "ex-square"): 0.0, ("carol", "ex-cube"): 0.0}
    assert all(r["reason"] for r in rows if r["student"] == "carol") and "cannot read" in rows[-1]["reason"]
    assert "3 students" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError, match="no submissions"):
        grade_class(tmp_path / "instructor", src.parent)


def test_malformed_markers_missing_files_and_bad_arguments(tmp_path):
    nb = build([("solution", "### BEGIN SOLUTION\nx = 1", "ex-bad")])
    with pytest.raises(ValueError, match="without"):
        student_version(nb, "98_bad")
    with pytest.raises(FileNotFoundError):
        grade(tmp_path / "nope.ipynb", tmp_path / "nope.ipynb")
    with pytest.raises(FileNotFoundError, match="no notebooks"):
        generate(tmp_path, tmp_path / "out")
    src = _tiny(tmp_path)
    with pytest.raises(ValueError, match="timeout"):
        grade(src, src, timeout=0)
    with pytest.raises(ValueError, match="none of"):
        grade(src, src, only=["ex-nope"])
    with pytest.raises(ValueError, match="needs a function"):
        library_references(3)


# --- the library check of the hidden tests ------------------------------------------------------------

def _ns(code):
    """Functions defined as in a notebook (module ``__main__``)."""
    ns = {"__name__": "__main__"}
    exec(compile(code, "<cell>", "exec"), ns)
    return ns


LIBRARY_CALLS = {
    "direct": "from vpr_nb.losses import triplet_loss\ndef f(q, p, n, m):\n    return triplet_loss(q, p, n, m)",
    "module alias": "import vpr_nb.losses as L\ndef f(q, p, n, m):\n    return L.triplet_loss(q, p, n, m)",
    "dotted import inside": "def f(q, p, n, m):\n    import vpr_nb.losses\n    return 0.0",
    "import inside": "def f(q, p, n, m):\n    import vpr_nb\n    return vpr_nb.losses.triplet_loss(q, p, n, m)",
    "helper": "from vpr_nb.losses import triplet_loss as t\ndef h(q):\n    return t(q, q, q)\ndef f(q, p, n, m):\n    return h(q)",
    "default argument": "from vpr_nb.losses import triplet_loss\ndef f(q, p, n, m, g=triplet_loss):\n    return g(q, p, n, m)",
    "closure": "from vpr_nb.losses import triplet_loss\ndef mk(g):\n    def f(q, p, n, m):\n        return g(q, p, n, m)\n    return f\nf = mk(triplet_loss)",
    "partial": "import functools\nfrom vpr_nb.losses import triplet_loss\ng = functools.partial(triplet_loss, margin=0.1)\ndef f(q, p, n, m):\n    return g(q, p, n)",
    "lambda": "from vpr_nb.losses import triplet_loss\nf = lambda q, p, n, m: triplet_loss(q, p, n, m)",
    "string import": "import importlib\ndef f(q, p, n, m):\n    return importlib.import_module('vpr_nb.losses').triplet_loss(q, p, n, m)",
    "the library itself": "from vpr_nb.losses import triplet_loss as f",
}


@pytest.mark.parametrize("how", sorted(LIBRARY_CALLS))
def test_assert_own_code_rejects_every_way_into_the_library(how):
    f = _ns(LIBRARY_CALLS[how])["f"]
    with pytest.raises(AssertionError, match="vpr_nb"):
        assert_own_code(f)


def test_assert_own_code_accepts_plain_torch_and_forbids_named_shortcuts():
    ns = _ns("import torch\ndef sq(x):\n    return x * x\n"
             "def f(q, p, n, m):\n    return torch.relu(sq(q - p).sum(-1) - sq(q - n).sum(-1) + m).sum()\n"
             "def g(q, p, n, m):\n    return torch.nn.TripletMarginLoss(m)(q, p, n)")
    assert library_references(ns["f"]) == []
    assert_own_code(ns["f"])
    with pytest.raises(AssertionError, match="TripletMarginLoss"):
        assert_own_code(ns["g"], forbid_names=("TripletMarginLoss",))


# --- the course's exercises ------------------------------------------------------------------------------

@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_every_course_exercise_is_gradable_cheaply_with_messages_and_a_library_check(path):
    nb = nbformat.read(path, as_version=4)
    ex = exercises(nb)
    assert ex, f"{path.name} has no exercise with nbgrader metadata"
    stu = student_version(nb, path.name)
    for cell in stu.cells:
        assert BEGIN_SOLUTION not in cell.source and BEGIN_HIDDEN not in cell.source
        if cell.cell_type == "code":
            compile(cell.source.replace("%matplotlib inline", ""), path.name, "exec")
    for gid, i, _ in ex:
        eid = exercise_id(gid)
        deps = [c for c in nb.cells[:i] if eid in deps_of(c)]
        assert deps, f"{path.name}: {eid} has no grade-deps:{eid} cells (grading would run the whole notebook)"
        assert not any("train(" in c.source for c in deps), f"{path.name}: a dependency of {eid} trains"
        source = nb.cells[i].source
        assert "assert_own_code(" in source.split(BEGIN_HIDDEN)[-1], f"{path.name}: {eid}'s hidden tests lack assert_own_code"
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Assert):
                assert node.msg is not None, f"{path.name} {gid}: `{ast.unparse(node)[:60]}` has no message"
        solution = next(c for c in nb.cells if is_solution(c) and c.metadata["nbgrader"].get("grade_id") == eid)
        answer = solution.source.split(BEGIN_SOLUTION)[1].split("### END SOLUTION")[0]
        last = [ln.strip() for ln in answer.split("\n") if ln.strip()][-1]
        above = [c.source for c in nb.cells[:i] if c is not solution and c.cell_type == "code"]
        assert not any(last in s for s in above), f"{path.name}: {eid}'s answer `{last}` is printed above it"


# one library route per exercise, pasted as the student's answer: each must score 0 because of vpr_nb
SHORTCUTS = {
    "02_triplet_baseline.ipynb": ("ex-02-sq-triplet", "return triplet_loss(q, p, n, margin)"),
    "03_distance_ranking_weighted_loss.ipynb": (
        "ex-03-ce-tau", "return ce_triplet_loss(torch.zeros(d_p.numel(), 1), (d_p / tau).reshape(-1, 1), "
                        "(d_n / tau).reshape(-1, 1, 1))"),
    "04_netvlad.ipynb": (
        "ex-04-soft-share", "import vpr_nb.aggregation\ncos = descs @ (cents / np.linalg.norm(cents, axis=1, keepdims=True)).T\n"
                            "top2 = np.sort(cos, axis=1)[:, -2:]\nreturn float(np.mean(alpha * (top2[:, 1] - top2[:, 0]) < np.log(ratio)))"),
    "05_salad.ipynb": ("ex-05-cluster-means", "return (f @ p.T) / p.sum(dim=1) if salad_aggregate else None"),
    "06_gds.ipynb": ("ex-06-misorder-empirical", 'return misordering_probability(x1, 0.0, 10.0, method="empirical")'),
    "06_gds.ipynb, right numbers": (
        "ex-06-misorder-empirical", "x1, x2 = np.asarray(x1)[:, None], np.asarray(x2)[None, :]\n"
                                    "return float(np.mean((x2 < x1) + 0.5 * (x2 == x1))) if gds_profile else 0.0"),
    "07_clique_mining.ipynb": (
        "ex-07-close-pairs", "d = np.linalg.norm(utm[batch][:, None, :, None] - utm[batch][None, :, None, :], axis=-1)\n"
                             "return int((d[np.triu(np.ones((len(batch),) * 2, dtype=bool), 1)] < tau).sum()) "
                             "if clique_batches else 0"),
    "08_reproduction.ipynb": (
        "ex-08-overrides-between",
        "return sorted(f'{s}.{k}={v if isinstance(v, str) else json.dumps(v)}' for s, sec in target.items() "
        "if isinstance(sec, dict) for k, v in sec.items() if base[s][k] != v and resolve_config)"),
}


# where the library refuses the student's inputs, the report shows the library's own error
REFUSED = {"06_gds.ipynb": "GDSProfile"}


def test_every_graded_notebook_has_a_shortcut_below():
    assert sorted({k.split(",")[0] for k in SHORTCUTS}) == [p.name for p in COURSE]


@pytest.mark.slow
@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_course_exercise_instructor_full_library_shortcut_zero(path, tmp_path):
    """Each course exercise: the instructor's answer earns its points (running only its dependencies); the
    library route scores 0, and the report says it used vpr_nb (or shows the library refusing the inputs)."""
    full = grade(path, path, timeout=120)
    assert all(g.points == g.max_points for g in full), [g.error for g in full]
    for key in (k for k in SHORTCUTS if k.split(",")[0] == path.name):
        gid, body = SHORTCUTS[key]
        stu = _answer(student_version(nbformat.read(path, as_version=4)), gid, body)
        got = grade(_write(stu, tmp_path / path.name), path, timeout=120, only=[gid])
        want = REFUSED.get(key, "vpr_nb")
        assert [g.points for g in got] == [0.0] and want in got[0].error, (key, got[0].error)


@pytest.mark.slow
def test_nbgrader_generate_assignment_accepts_the_instructor_notebooks(tmp_path):
    """nbgrader itself (where it installs; it is not in environment.txt) takes the course notebooks unchanged."""
    pytest.importorskip("nbgrader", reason="nbgrader is not installed (optional: .venv/bin/pip install nbgrader)")
    import os
    import shutil
    import subprocess
    import sys

    source = tmp_path / "source" / "course"
    source.mkdir(parents=True)
    for path in COURSE:
        shutil.copy(path, source / path.name)
    bindir = str(Path(sys.executable).parent)           # nbgrader runs `alembic` from the environment's bin
    env = {**os.environ, "PATH": bindir + os.pathsep + os.environ.get("PATH", "")}
    proc = subprocess.run([sys.executable, "-m", "nbgrader", "generate_assignment", "course", "--force",
                           f"--CourseDirectory.root={tmp_path}", f"--CourseDirectory.db_url=sqlite:///{tmp_path}/gradebook.db"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    released = sorted(p.name for p in (tmp_path / "release" / "course").glob("*.ipynb"))
    assert released == [p.name for p in COURSE], proc.stderr[-2000:]
    for name in released:
        text = (tmp_path / "release" / "course" / name).read_text()
        assert BEGIN_SOLUTION not in text and BEGIN_HIDDEN not in text and "assert_own_code" not in text, name
