"""Student versions and grading with nbgrader's markers (vpr_nb.assignments, vpr_nb.grading)."""
import ast
import csv
import os
import re
from pathlib import Path

import nbformat
import numpy as np
import pytest
import torch
from grading_fixtures import NAME, SQUARE, SQUARE_TESTS, answer, build, submission, two_exercises, write

from vpr_nb.assignments import (BEGIN_HIDDEN, BEGIN_SOLUTION, CODE_STUB, END_SOLUTION, Case,
                                assert_own_code, check, deps_of, exercise_id, exercise_specs, exercises, generate,
                                grade, grade_class, is_solution, library_references, main, student_version)
from vpr_nb.grading import data, sandbox
from vpr_nb.grading.owncode import source_violations
from vpr_nb.grading.spec import collect

ROOT = Path(__file__).resolve().parents[1]
COURSE = sorted((ROOT / "notebooks").glob("0[2-9]_*.ipynb"))
BACKENDS = ["process"] + (["bwrap"] if sandbox.backend_works("bwrap") else [])
# The grading tests below grade the tests' own notebooks, trusted work: ``trusted=True`` / ``--trusted`` grades
# them in bubblewrap where it works and without a sandbox elsewhere (the process backend always needs it);
# untrusted work without bubblewrap is refused (tests/test_grading_isolation.py).


def _tiny(tmp_path):
    nb = build([("md", "# tiny"), ("dep", "import math", "ex-square"), ("solution", SQUARE, "ex-square"),
                ("tests", SQUARE_TESTS, "ex-square", 2), ("md", "done")])
    nb.cells[1].metadata["execution"] = {"iopub.execute_input": "2026-01-01T00:00:00Z"}   # as nbconvert records
    return write(nb, tmp_path / "instructor" / "99_tiny.ipynb")


def _two(tmp_path):
    return write(two_exercises(), tmp_path / "instructor" / NAME)


# --- student versions ----------------------------------------------------------------------------------

def test_student_version_strips_solutions_hidden_tests_and_locks_read_only_cells(tmp_path):
    src = _tiny(tmp_path)
    out = generate(src.parent, tmp_path / "students")
    assert [p.name for p in out] == ["99_tiny.ipynb"]
    stu = nbformat.read(out[0], as_version=4)
    text = "\n".join(c.source for c in stu.cells)
    assert "x * x" not in text and "square(-2)" not in text and BEGIN_SOLUTION not in text
    assert f"    {CODE_STUB}" in stu.cells[2].source and 'Case("square(3)"' in stu.cells[3].source
    assert all(c.get("outputs", []) == [] and "execution" not in c.metadata for c in stu.cells if c.cell_type == "code")
    assert exercises(stu) == [("ex-square-tests", 3, 2.0)]
    assert stu.cells[3].metadata["editable"] is False and stu.cells[3].metadata["deletable"] is False
    assert stu.cells[1].metadata["editable"] is False                 # a setup cell
    assert "editable" not in stu.cells[2].metadata            # the solution cell stays editable
    two = student_version(two_exercises())
    assert "editable" not in two.cells[0].metadata, "the parameters cell must stay editable"
    assert two.cells[1].metadata["editable"] is False and two.cells[1].metadata["deletable"] is False


# --- grading: verdicts and feedback --------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_grades_instructor_full_student_zero_pasted_back_full_wrong_with_feedback(tmp_path, backend):
    src = _tiny(tmp_path)
    assert [g.points for g in grade(src, src, backend=backend, trusted=True)] == [2.0]
    stu_path = generate(src.parent, tmp_path / "students")[0]
    zero = grade(stu_path, src, backend=backend, trusted=True)
    assert [g.points for g in zero] == [0.0] and "NotImplementedError" in zero[0].error
    stu = answer(nbformat.read(stu_path, as_version=4), "ex-square", "return x ** 2")
    stu.cells[3].source = "pass  # a student deleting the visible tests changes nothing"
    assert [g.points for g in grade(write(stu, tmp_path / "pasted.ipynb"), src, backend=backend, trusted=True)] == [2.0]
    wrong = answer(nbformat.read(stu_path, as_version=4), "ex-square", "return abs(x) * 3")
    got = grade(write(wrong, tmp_path / "wrong.ipynb"), src, backend=backend, trusted=True)
    assert got[0].points == 0.0 and got[0].error == "square(-2): expected 4, got 6", got[0].error


@pytest.mark.slow
def test_only_dependency_cells_run_and_deleted_or_edited_tests_change_nothing(tmp_path):
    src = _two(tmp_path)
    assert [(g.grade_id, g.points) for g in grade(src, src, trusted=True)] == [("ex-square-tests", 2.0), ("ex-cube-tests", 1.0)]
    stu = submission(two_exercises(), "return x * x", "return x * x * x")
    del stu.cells[4]                                          # the square tests, deleted
    stu.cells[5].source = "assert False"                      # the cube tests, edited
    stu.cells[0].source = "SCALE = 1000"                      # the parameters cell: the instructor's copy is used
    got = grade(write(stu, tmp_path / "edited.ipynb"), src, trusted=True)
    assert [g.points for g in got] == [2.0, 1.0], [g.error for g in got]


def test_feedback_names_expected_and_got_per_exercise(tmp_path, capsys):
    src = _two(tmp_path)
    path = write(submission(two_exercises(), "return x + x", "return x * x * x"), tmp_path / "wrong.ipynb")
    assert main(["grade", str(path), "--source", str(src), "--trusted"]) == 0
    out = capsys.readouterr().out
    assert "square(3): expected 9, got 6" in out and "ex-cube-tests" in out and "total" in out and "1 / 3" in out
    assert "sandbox:" in out


def test_type_errors_and_raised_errors_say_what_came_back(tmp_path):
    src = _two(tmp_path)
    cases = {"return str(x * x)": "square(3): expected a number (9), got a str '9'",
             "return {'x': x}": "square(3): expected a number (9), got a dict",
             "return object()": "square(3): square returned a builtins.object (only numbers",
             "raise ValueError('no squares today')": "square(3): square raised ValueError: no squares today"}
    for body, want in cases.items():
        got = grade(write(submission(two_exercises(), body), tmp_path / "t.ipynb"), src, only=["ex-square"], trusted=True)
        assert got[0].points == 0.0 and got[0].error.startswith(want), (body, got[0].error)
    stu = submission(two_exercises())
    stu.cells[3].source = "def squared(x):\n    return x * x"
    got = grade(write(stu, tmp_path / "t.ipynb"), src, only=["ex-square"], trusted=True)
    assert "does not define square" in got[0].error
    stu.cells[3].source = "def square(x)\n    return x"
    got = grade(write(stu, tmp_path / "t.ipynb"), src, only=["ex-square"], trusted=True)
    assert "does not parse" in got[0].error


@pytest.mark.slow
def test_endless_loop_times_out_and_the_other_exercise_is_graded(tmp_path):
    src = _two(tmp_path)
    stu = submission(two_exercises(), "return x * x", "while True:\n    pass")
    got = grade(write(stu, tmp_path / "loop.ipynb"), src, timeout=4, trusted=True)
    assert got[0].points == 2.0, got[0].error
    assert got[1].points == 0.0 and "timed out after 4 s" in got[1].error, got[1].error


@pytest.mark.slow
def test_dead_process_scores_zero_and_the_next_exercise_gets_a_fresh_one(tmp_path):
    src = _two(tmp_path)
    stu = submission(two_exercises(), "return x * x", "import os\nos._exit(1)")
    stu.cells[3].source = "import os\nos._exit(1)\n" + stu.cells[3].source      # refused before it runs
    got = grade(write(stu, tmp_path / "dead.ipynb"), src, timeout=60, trusted=True)
    assert got[0].points == 0.0 and "imports os" in got[0].error, got[0].error
    assert got[1].points == 0.0 and "ended before it answered (exit code 1)" in got[1].error, got[1].error
    fine = submission(two_exercises(), "return x * x", "import os\nos._exit(1)")
    got = grade(write(fine, tmp_path / "dead.ipynb"), src, timeout=60, trusted=True)
    assert got[0].points == 2.0 and got[1].points == 0.0, [g.error for g in got]


def test_missing_solution_cell_scores_zero_with_the_reason(tmp_path):
    src = _two(tmp_path)
    stu = submission(two_exercises())
    del stu.cells[5]                                          # the cube solution cell
    got = grade(write(stu, tmp_path / "missing.ipynb"), src, trusted=True)
    assert got[0].points == 2.0 and got[1].points == 0.0 and "missing" in got[1].error


@pytest.mark.slow
def test_grade_class_writes_a_csv_per_student_and_exercise_atomically(tmp_path, capsys):
    src = _two(tmp_path)
    write(submission(two_exercises()), tmp_path / "sub" / "alice" / NAME)
    write(student_version(two_exercises()), tmp_path / "sub" / "bob" / "98_two" / NAME)   # nbgrader's layout
    (tmp_path / "sub" / "carol").mkdir()
    (tmp_path / "sub" / "carol" / NAME).write_text("{not json")
    out = tmp_path / "grades" / "scores.csv"
    assert main(["grade-class", str(tmp_path / "sub"), "--source", str(src.parent), "--csv", str(out),
                 "--jobs", "2", "--trusted"]) == 0
    rows = list(csv.DictReader(out.open()))
    got = {(r["student"], r["exercise"]): float(r["points"]) for r in rows}
    assert got == {("alice", "ex-square"): 2.0, ("alice", "ex-cube"): 1.0, ("bob", "ex-square"): 0.0,
                   ("bob", "ex-cube"): 0.0, ("carol", "ex-square"): 0.0, ("carol", "ex-cube"): 0.0}
    assert [r["student"] for r in rows] == ["alice"] * 2 + ["bob"] * 2 + ["carol"] * 2
    assert all(r["reason"] for r in rows if r["student"] == "carol") and "cannot read" in rows[-1]["reason"]
    assert sorted(p.name for p in out.parent.iterdir()) == ["scores.csv"], "a temporary grades file was left"
    assert {r["sandbox"] for r in rows} == {"bubblewrap" if "bwrap" in BACKENDS else "graded WITHOUT a sandbox (--trusted)"}
    assert "3 students" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError, match="no submissions"):
        grade_class(tmp_path / "instructor", src.parent)


def test_malformed_markers_test_cells_missing_files_and_bad_arguments(tmp_path):
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
    old_style = build([("solution", SQUARE, "ex-square"),
                       ("tests", "assert square(3) == 9, 'expected 9'", "ex-square", 1)])
    with pytest.raises(ValueError, match="uses 'square'"):       # it calls the student's code itself
        exercise_specs(old_style)
    no_check = build([("solution", SQUARE, "ex-square"), ("tests", "x = 1", "ex-square", 1)])
    with pytest.raises(ValueError, match="declares no check"):
        exercise_specs(no_check)
    with pytest.raises(ValueError, match="must be data"):
        Case("an object as input", (object(),), expect=1)
    with pytest.raises(ValueError, match="expect= .* or rubric="):
        Case("nothing to compare")
    assert main(["grade", str(tmp_path / "nope.ipynb"), "--source", str(src)]) == 2


def test_check_in_a_kernel_asserts_with_the_graders_message():
    ns = {"__name__": "__main__", "Case": Case, "check": check}
    exec("def square(x):\n    return x + x", ns)
    with pytest.raises(AssertionError, match=r"square\(3\): expected 9, got 6"):
        exec('check("square", [Case("square(3)", (3,), expect=9)], own_code=False)', ns)
    exec("def square(x):\n    return x * x", ns)
    exec('check("square", [Case("square(3)", (3,), expect=9)])', ns)
    exec("import vpr_nb\ndef square(x):\n    return vpr_nb and x * x", ns)
    with pytest.raises(AssertionError, match="vpr_nb"):
        exec('check("square", [Case("square(3)", (3,), expect=9)])', ns)
    specs = collect(SQUARE_TESTS)
    assert [(s.function, [c.name for c in s.cases]) for s in specs] == [
        ("square", ["square(3)"]), ("square", ["square(-2)", "square(1.5)"])]


# --- answers as data -------------------------------------------------------------------------------------

def test_data_round_trips_numbers_strings_containers_arrays_and_tensors(tmp_path):
    value = {"n": 3, "x": 0.5, "big": 2 ** 70, "flag": True, "none": None, "s": "hi", "l": [1, 2.5], "t": (1, "a"),
             "a": np.arange(6.0).reshape(2, 3), "b": np.array([True, False]), "ten": torch.tensor([1.5, 2.0]),
             "half": torch.tensor([1.0], dtype=torch.float16), "np": np.float32(0.25)}
    data.write(value, tmp_path, "v")
    got = data.read(tmp_path, "v")
    assert got["n"] == 3 and got["big"] == 2 ** 70 and got["flag"] is True and got["none"] is None
    assert got["t"] == (1, "a") and got["l"] == [1, 2.5] and got["np"] == 0.25 and isinstance(got["np"], float)
    assert isinstance(got["ten"], data.TensorValue) and got["ten"].array.tolist() == [1.5, 2.0]
    assert isinstance(got["a"], np.ndarray) and got["a"].shape == (2, 3)
    for bad in (object(), {1: 2}, np.array(["a"]), np.array([object()], dtype=object), lambda: 1):
        with pytest.raises(data.DataError):
            data.encode(bad)


def test_data_files_with_pickles_or_junk_are_refused(tmp_path):
    np.savez(tmp_path / "p.npz", a0=np.array([{"x": 1}], dtype=object))
    (tmp_path / "p.json").write_text('{"$array": "a0"}')
    with pytest.raises(data.DataError, match="not a plain numpy archive"):
        data.read(tmp_path, "p")
    np.savez(tmp_path / "q.npz")
    for junk in ('{"$call": "os.system"}', "not json", '{"$array": "a9"}'):
        (tmp_path / "q.json").write_text(junk)
        with pytest.raises(data.DataError):
            data.read(tmp_path, "q")
    os.symlink(tmp_path / "q.json", tmp_path / "r.json")
    (tmp_path / "r.npz").write_bytes((tmp_path / "q.npz").read_bytes())
    with pytest.raises(data.DataError, match="not a plain file"):
        data.read(tmp_path, "r")


def test_compare_says_what_differs():
    c = data.compare
    t = data.roundtrip
    assert c(t(torch.tensor(0.5)), t(torch.tensor(0.5 + 1e-8))) is None
    assert "expected a torch tensor of shape ()" in c(0.5, t(torch.tensor(0.5)))
    assert c(t(torch.ones(3)), t(torch.ones(2))) == "expected shape (2,), got shape (3,)"
    assert "expected 0.5, got 0.6" in c(0.6, 0.5)
    assert c(np.float64(0.5), 0.5) is None and c(np.array([0.5]), 0.5) is None
    assert "expected a number" in c(True, 1.0)
    assert c(float("nan"), float("nan")) is None and c(float("nan"), 1.0) is not None
    assert "missing ['b']" in c({"a": 1}, {"a": 1, "b": 2})
    assert "at [1]" in c([1, 3], [1, 2])
    assert "2 of 100 values differ" in c(np.r_[np.zeros(98), 1, 1], np.zeros(100))
    assert c("falls", "falls") is None and "expected 'falls'" in c("rises", "falls")


# --- the own-code rule, statically on the source -----------------------------------------------------------

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
OBFUSCATED = {   # ways around a name check: each must still be refused (statically)
    "__import__": "def f(x):\n    return __import__('vp' + 'r_nb').losses",
    "sys.modules": "import numpy as np\ndef f(x):\n    return np.sys.modules['vp' + 'r_nb']",
    "getattr": "import torch\ndef f(x):\n    return getattr(torch, 'nn')",
    "eval": "def f(x):\n    return eval('1')",
    "exec": "exec('import vp' + 'r_nb')",
    "globals": "def f(x):\n    return globals()['triplet_loss'](x)",
    "dunder walk": "def f(x):\n    return ().__class__.__bases__[0].__subclasses__()",
    "builtins": "import builtins\nbuiltins.abs = None",
    "open": "def f(x):\n    return open('/etc/passwd').read()",
    "ipython": "get_ipython().run_line_magic('run', 'other.ipynb')",
    "a magic": "%run other.ipynb",
    "os": "import os\nos.system('true')",
    "the setup's import": "def f(q, p, n, m):\n    return triplet_loss(q, p, n, m)",
}


@pytest.mark.parametrize("how", sorted(LIBRARY_CALLS))
def test_source_rule_and_assert_own_code_reject_every_way_into_the_library(how):
    assert any("vpr_nb" in v for v in source_violations([LIBRARY_CALLS[how]])), how
    f = _ns(LIBRARY_CALLS[how])["f"]
    with pytest.raises(AssertionError, match="vpr_nb"):
        assert_own_code(f)


@pytest.mark.parametrize("how", sorted(OBFUSCATED))
def test_source_rule_refuses_indirect_routes(how):
    setup = ["import numpy as np\nfrom vpr_nb.losses import triplet_loss"]
    assert source_violations([OBFUSCATED[how]], setup_sources=setup), how


def test_source_rule_accepts_plain_torch_and_forbids_named_shortcuts():
    plain = ("import torch\nimport numpy as np\nfrom math import sqrt\nclass A:\n    def __init__(self):\n"
             "        self.x = 1\ndef f(q, p, n, m):\n    return torch.relu((q - p).pow(2).sum(-1) + m).sum() + np.pi + sqrt(2)")
    assert source_violations([plain], setup_sources=["import torch\nfrom vpr_nb.losses import triplet_loss"]) == []
    shortcut = "import torch\ndef g(q, p, n, m):\n    return torch.nn.TripletMarginLoss(m)(q, p, n)"
    assert source_violations([shortcut], forbid_names=("TripletMarginLoss",))
    with pytest.raises(SyntaxError):
        source_violations(["def f(:"])


def _ns(code):
    """Functions defined as in a notebook (module ``__main__``)."""
    ns = {"__name__": "__main__"}
    exec(compile(code, "<cell>", "exec"), ns)
    return ns


def test_assert_own_code_accepts_plain_torch_and_forbids_named_shortcuts():
    ns = _ns("import torch\ndef sq(x):\n    return x * x\n"
             "def f(q, p, n, m):\n    return torch.relu(sq(q - p).sum(-1) - sq(q - n).sum(-1) + m).sum()\n"
             "def g(q, p, n, m):\n    return torch.nn.TripletMarginLoss(m)(q, p, n)")
    assert library_references(ns["f"]) == []
    assert_own_code(ns["f"])
    with pytest.raises(AssertionError, match="TripletMarginLoss"):
        assert_own_code(ns["g"], forbid_names=("TripletMarginLoss",))


# --- the course's exercises ------------------------------------------------------------------------------

def _solution_of(nb, eid):
    return [c for c in nb.cells if is_solution(c) and c.metadata["nbgrader"].get("grade_id") == eid]


def _answer_lines(cell) -> list[str]:
    answer = cell.source.split(BEGIN_SOLUTION)[1].split(END_SOLUTION)[0]
    return [ln.strip() for ln in answer.split("\n") if ln.strip() and not ln.strip().startswith("#")]


def _code_lines(text: str) -> set[str]:
    return {ln.split("#")[0].strip() for ln in text.split("\n")}


@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_every_course_exercise_is_gradable_cheaply_and_its_cases_build_in_the_grader(path):
    nb = nbformat.read(path, as_version=4)
    ex = exercises(nb)
    assert ex, f"{path.name} has no exercise with nbgrader metadata"
    stu = student_version(nb, path.name)
    for cell in stu.cells:
        assert BEGIN_SOLUTION not in cell.source and BEGIN_HIDDEN not in cell.source
        if cell.cell_type == "code":
            compile(cell.source.replace("%matplotlib inline", ""), path.name, "exec")
    specs = {e.grade_id: e for e in exercise_specs(nb, path.name)}   # each test cell, run in a fresh namespace
    for gid, i, _ in ex:
        eid = exercise_id(gid)
        deps = [c for c in nb.cells[:i] if eid in deps_of(c)]
        assert deps, f"{path.name}: {eid} has no grade-deps:{eid} cells (grading would run the whole notebook)"
        assert not any("train(" in c.source for c in deps), f"{path.name}: a dependency of {eid} trains"
        source = nb.cells[i].source
        assert "check(" in source.split(BEGIN_HIDDEN)[-1], f"{path.name}: {eid}'s hidden tests declare no check"
        assert sum(len(c.cases) for c in specs[gid].checks) >= 2, f"{path.name}: {eid} has fewer than 2 cases"
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Assert):
                assert node.msg is not None, f"{path.name} {gid}: `{ast.unparse(node)[:60]}` has no message"


@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_no_graded_solution_appears_line_for_line_elsewhere_in_the_student_notebook(path):
    nb = nbformat.read(path, as_version=4)
    stu = student_version(nb, path.name)
    text = [_code_lines(c.source) | {ln.strip() for ln in c.source.split("\n")} for c in stu.cells]
    for gid, _, _ in exercises(nb):
        for cell in _solution_of(nb, exercise_id(gid)):
            for line in _answer_lines(cell):
                code = line.split("#")[0].strip()
                if len(code) < 12 or code.startswith(("return ", "def ")) and len(code) < 24:
                    continue                            # too short to give anything away
                where = [k for k, lines in enumerate(text) if code in lines]
                assert not where, f"{path.name}: the answer line `{code}` of {gid} appears in student cell(s) {where}"


UNDERSTANDING = {   # notebook: the graded exercises in which the student predicts or measures (docs/teaching.md lists them)
    "02_triplet_baseline.ipynb": ["ex-02-radius-predict", "ex-02-radius-measure"],
    "03_distance_ranking_weighted_loss.ipynb": ["ex-03-step-predict", "ex-03-equal-step"],
    "04_netvlad.ipynb": ["ex-04-zero-predict", "ex-04-zero-descriptor"],
    "05_salad.ipynb": ["ex-05-dustbin-predict", "ex-05-dustbin-mass"],
    "06_gds.ipynb": ["ex-06-cap-predict", "ex-06-r1-cap"],
    "07_clique_mining.ipynb": ["ex-07-tau-predict", "ex-07-pick-batch"],
    "08_reproduction.ipynb": ["ex-08-convention-predict", "ex-08-conventions"],
}


def test_every_graded_notebook_has_understanding_exercises_checked_by_tolerance_or_rubric():
    """Each notebook: a prediction graded by a rubric (a choice), then a measurement graded with a tolerance."""
    assert sorted(UNDERSTANDING) == [p.name for p in COURSE]
    for path in COURSE:
        specs = {e.id: e for e in exercise_specs(nbformat.read(path, as_version=4), path.name)}
        predict, measure = UNDERSTANDING[path.name]
        for eid in (predict, measure):
            assert eid in specs, f"{path.name}: no graded exercise {eid}"
        cases = [c for chk in specs[predict].checks for c in chk.cases]
        assert all(not chk.call for chk in specs[predict].checks), f"{path.name} {predict}: not a prediction"
        assert all(c.rubric is not None or isinstance(c.expect, str) for c in cases), f"{path.name} {predict}"
        cases = [c for chk in specs[measure].checks for c in chk.cases]
        assert all(chk.call for chk in specs[measure].checks), f"{path.name} {measure}: not a measurement"
        assert any(c.rubric is not None or not isinstance(c.expect, (str, bool)) for c in cases), f"{path.name} {measure}"


# one library route per exercise, pasted as the student's answer: each must score 0 because of vpr_nb
SHORTCUTS = {
    "02_triplet_baseline.ipynb": ("ex-02-sq-triplet", "return triplet_loss(q, p, n, margin)"),
    "02_triplet_baseline.ipynb, radius": (
        "ex-02-radius-measure", "from vpr_nb.evaluation import evaluate_descriptors\n"
                                "return float(evaluate_descriptors(db, q, db_utm, q_utm, radius, (1,), "
                                "no_positive='all')[1])"),
    "03_distance_ranking_weighted_loss.ipynb": (
        "ex-03-ce-tau", "return ce_triplet_loss(torch.zeros(d_p.numel(), 1), (d_p / tau).reshape(-1, 1), "
                        "(d_n / tau).reshape(-1, 1, 1))"),
    "04_netvlad.ipynb": (
        "ex-04-soft-share", "import vpr_nb.aggregation\ncos = descs @ (cents / np.linalg.norm(cents, axis=1, keepdims=True)).T\n"
                            "top2 = np.sort(cos, axis=1)[:, -2:]\nreturn float(np.mean(alpha * (top2[:, 1] - top2[:, 0]) < np.log(ratio)))"),
    "05_salad.ipynb": ("ex-05-cluster-means", "return (f @ p.T) / p.sum(dim=1) if salad_aggregate else None"),
    "05_salad.ipynb, dustbin": ("ex-05-dustbin-mass", "import torch\nfrom vpr_nb.aggregation import sinkhorn\n"
                                                      "plan = sinkhorn(torch.as_tensor(scores)[None], z, iters)[0].exp()\n"
                                                      "return float(plan[:-1].sum()), float(plan[-1].sum())"),
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


def test_every_graded_notebook_has_a_shortcut_below():
    assert sorted({k.split(",")[0] for k in SHORTCUTS}) == [p.name for p in COURSE]


@pytest.mark.slow
@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_course_exercise_instructor_full_stub_zero_library_shortcut_zero(path, tmp_path):
    """Each course exercise: the instructor's answer earns its points (running only its dependencies, in
    the sandbox); the student version scores 0; the library route scores 0 and the report says it used vpr_nb."""
    full = grade(path, path, timeout=120, trusted=True)
    assert all(g.points == g.max_points for g in full), [(g.grade_id, g.error) for g in full]
    stub = student_version(nbformat.read(path, as_version=4))
    zero = grade(write(stub, tmp_path / "stub" / path.name), path, timeout=120, trusted=True)
    assert all(g.points == 0.0 and g.error for g in zero), [(g.grade_id, g.error) for g in zero]
    for key in (k for k in SHORTCUTS if k.split(",")[0] == path.name):
        gid, body = SHORTCUTS[key]
        stu = answer(student_version(nbformat.read(path, as_version=4)), gid, body)
        got = grade(write(stu, tmp_path / path.name), path, timeout=120, only=[gid], trusted=True)
        assert [g.points for g in got] == [0.0] and "vpr_nb" in got[0].error, (key, got[0].error)


# --- cells an exercise tells the student to edit ---------------------------------------------------------

EDIT = re.compile(r"\b(?:[Ss]ets?|run with|[Cc]hange)\s+(?:`|<code>)?([A-Z][A-Z_0-9]+)\s*=")


def _assigned(cell, name: str) -> bool:
    try:
        tree = ast.parse(cell.source.replace("%matplotlib inline", ""))
    except SyntaxError:
        return False
    return any(isinstance(n, (ast.Assign, ast.AnnAssign)) and any(
        isinstance(t, ast.Name) and t.id == name
        for target in (n.targets if isinstance(n, ast.Assign) else [n.target]) for t in ast.walk(target))
        for n in tree.body)


@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_every_cell_an_exercise_tells_the_student_to_edit_is_editable(path, tmp_path):
    out = generate(path.parent, tmp_path, pattern=path.name)
    stu = nbformat.read(out[0], as_version=4)
    named = 0
    for text in (c for c in stu.cells if c.cell_type in ("markdown", "code")):
        for item in re.split(r"\n\s*\d+\.\s", text.source):
            for name in EDIT.findall(item):
                named += 1
                cells = [c for c in stu.cells if c.cell_type == "code" and _assigned(c, name)]
                assert cells, f"{path.name}: an exercise says to set {name}, which no cell defines"
                locked = [c for c in cells if c.metadata.get("editable") is False]
                assert not locked or "new cell" in item, (
                    f"{path.name}: an exercise says to set {name}, but the cell that defines it is locked in the "
                    f"student version and the exercise does not say to do it in a new cell: {item[:160]!r}")
    assert named or path.name not in ("02_triplet_baseline.ipynb", "03_distance_ranking_weighted_loss.ipynb",
                                      "08_reproduction.ipynb")


@pytest.mark.slow
def test_grade_class_on_a_generated_class_of_a_course_notebook(tmp_path):
    """bench/bench_grade_class.py's class, smaller: correct, wrong, cheating, crashing and unanswered
    submissions of notebook 06, graded by grade-class; every student's points as their kind says."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_grade_class", ROOT / "bench" / "bench_grade_class.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    source = next((ROOT / "notebooks").glob("06_*.ipynb"))
    (tmp_path / "source").mkdir()
    (tmp_path / "source" / source.name).write_bytes(source.read_bytes())
    plan = bench.make_class(source, tmp_path / "submitted", 10)
    assert {"correct", "wrong", "cheat-abs", "crash-exit", "cheat-traceback", "stub"} <= {k for k, _ in plan.values()}
    rows = grade_class(tmp_path / "submitted", tmp_path / "source", tmp_path / "scores.csv", timeout=30, jobs=2,
                       log=lambda *_: None, trusted=True)
    assert len(rows) == 10 * 3
    assert bench.check_csv(tmp_path / "scores.csv", plan) == []


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
