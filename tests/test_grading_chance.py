"""What a random answer earns: each graded exercise's chance score, in the grader's reports and the CSV, and
the optional weighting of choice items (``--weigh-choices``)."""
import csv
from pathlib import Path

import nbformat
import pytest
from grading_fixtures import NAME, answer, build, submission, two_exercises, write

from vpr_nb.assignments import (BEGIN_HIDDEN, END_HIDDEN, exercise_specs, guess_chance, main,
                                one_of, weigh_choices)
from vpr_nb.grading.spec import collect

ROOT = Path(__file__).resolve().parents[1]
COURSE = sorted((ROOT / "notebooks").glob("0[2-9]_*.ipynb"))

PREDICT = '''PREDICTION = "falls"'''
PREDICT_TESTS = f"""from vpr_nb.assignments import Case, check, one_of

check("PREDICTION", [Case("your prediction", rubric=one_of("rises", "falls", "stays"))], call=False)
{BEGIN_HIDDEN}
check("PREDICTION", [Case("R@1 when the radius shrinks", expect="falls")], call=False)
{END_HIDDEN}"""


def _with_choice() -> nbformat.NotebookNode:
    """The two exercises of the shared fixture (square: 2 points, cube: 1) and a three-way prediction (1 point)."""
    nb = two_exercises()
    extra = build([("dep", "import math", "ex-predict"), ("solution", PREDICT, "ex-predict"),
                   ("tests", PREDICT_TESTS, "ex-predict", 1)])
    nb.cells.extend(extra.cells)
    return nb


def _answered(square_body="return x * x"):
    """A student's submission of :func:`_with_choice`: square as given, cube right, the prediction right."""
    return answer(submission(_with_choice(), square_body), "ex-predict", '@cell\nPREDICTION = "falls"')


def _specs(source: str):
    return collect(source, "a test cell")


# --- the chance of one exercise -----------------------------------------------------------------------------

def test_a_choice_among_k_with_one_right_answer_is_passed_by_one_guess_in_k():
    assert guess_chance(_specs(PREDICT_TESTS.replace(BEGIN_HIDDEN, "").replace(END_HIDDEN, ""))) == pytest.approx(1 / 3)


def test_what_only_the_stated_choices_check_any_guess_among_them_passes():
    visible = 'from vpr_nb.assignments import Case, check, one_of\n' \
              'check("P", [Case("p", rubric=one_of("a", "b"))], call=False)'
    assert guess_chance(_specs(visible)) == 1.0


def test_two_right_answers_among_four_and_two_values_multiply():
    cell = ('from vpr_nb.assignments import Case, check, one_of\n'
            'check("P", [Case("p", rubric=one_of("a", "b", "c", "d")), '
            'Case("ok", rubric=lambda x: None if x in ("a", "b") else "no")], call=False)\n'
            'check("Q", [Case("q", rubric=one_of("x", "y")), Case("right", expect="y")], call=False)')
    assert guess_chance(_specs(cell)) == pytest.approx(0.5 * 0.5)


@pytest.mark.parametrize("cell", [
    'check("square", [Case("3", (3,), expect=9)])',                                       # a function to write
    'check("VALUE", [Case("v", expect=0.25)], call=False)',                               # a free answer
    'check("P", [Case("p", rubric=one_of("a", "b"))], call=False)\ncheck("f", [Case("f", (1,), expect=1)])',
])
def test_functions_and_free_answers_are_never_guessed(cell):
    assert guess_chance(_specs("from vpr_nb.assignments import Case, check, one_of\n" + cell)) == 0.0


def test_one_of_refuses_a_choice_listed_twice_and_keeps_its_choices():
    with pytest.raises(ValueError, match="twice"):
        one_of("a", "a", "b")
    rubric = one_of("a", "b")
    assert rubric.choices == ("a", "b") and rubric("b") is None and "expected one of 'a', 'b'" in rubric("c")


def test_the_exercise_holds_its_chance_and_weighing_keeps_one_minus_one_over_k():
    specs = {e.id: e for e in exercise_specs(_with_choice())}
    assert {i: (e.points, round(e.chance, 4)) for i, e in specs.items()} == {
        "ex-square": (2.0, 0.0), "ex-cube": (1.0, 0.0), "ex-predict": (1.0, 0.3333)}
    weighed = {e.id: e for e in weigh_choices(list(specs.values()))}
    assert weighed["ex-predict"].points == pytest.approx(2 / 3)
    assert weighed["ex-predict"].chance == pytest.approx(2 / 9)
    assert weighed["ex-square"].points == 2.0 and weighed["ex-cube"] is specs["ex-cube"]


def test_the_course_choices_are_the_seven_three_way_predictions():
    """Every course exercise: 1 point; the seven predictions (one per notebook 02–08) are choices among three,
    the fourteen functions are never passed by a guess."""
    chances = {}
    for path in COURSE:
        for e in exercise_specs(nbformat.read(path, as_version=4), path.name):
            chances[e.id] = (e.points, round(e.guess, 4))
    assert len(chances) == 21 and {p for p, _ in chances.values()} == {1.0}
    choices = sorted(i for i, (_, g) in chances.items() if g)
    assert choices == sorted(i for i in chances if i.endswith("-predict")) and len(choices) == 7
    assert {g for i, (_, g) in chances.items() if i in choices} == {0.3333}


# --- the reports ------------------------------------------------------------------------------------------

def test_grade_prints_each_exercises_points_and_chance_and_the_chance_score(tmp_path, capsys):
    src = write(_with_choice(), tmp_path / "instructor" / NAME)
    path = write(_answered("return x + x"), tmp_path / "alice.ipynb")   # square wrong, cube and prediction right
    assert main(["grade", str(path), "--source", str(src), "--trusted"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {ln.split()[0]: ln.split() for ln in lines if ln.startswith("ex-")}
    assert rows["ex-square-tests"][:5] == ["ex-square-tests", "0", "/", "2", "chance"] and rows["ex-square-tests"][5] == "0"
    assert rows["ex-predict-tests"][1:6] == ["1", "/", "1", "chance", "0.33"], rows
    assert lines[-2].split()[:5] == ["chance", "score", "0.33", "/", "4"], lines
    assert lines[-1].split()[:4] == ["total", "2", "/", "4"], lines
    assert main(["grade", str(path), "--source", str(src), "--trusted", "--weigh-choices"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[1:4] for ln in lines if ln.startswith("ex-predict")] == [["0.67", "/", "0.67"]], lines
    assert lines[-2].split()[2:5] == ["0.22", "/", "3.67"] and lines[-1].split()[1:4] == ["1.67", "/", "3.67"], lines


@pytest.mark.slow
def test_grade_class_writes_the_chance_column_and_the_chance_per_notebook(tmp_path, capsys):
    src = write(_with_choice(), tmp_path / "instructor" / NAME)
    write(_answered(), tmp_path / "submitted" / "alice" / NAME)
    (tmp_path / "submitted" / "bob").mkdir()
    (tmp_path / "submitted" / "bob" / NAME).write_text("{not json")              # unreadable: 0 with the chance
    out = tmp_path / "grades" / "scores.csv"
    assert main(["grade-class", str(tmp_path / "submitted"), "--source", str(src.parent), "--csv", str(out),
                 "--trusted", "--feedback", str(tmp_path / "feedback")]) == 0
    printed = capsys.readouterr().out
    assert f"{NAME}: 4 points, chance score 0.33 (random answers, on average)" in printed
    assert sorted(p.name for p in (tmp_path / "feedback").iterdir()) == ["alice.txt", "bob.txt"], printed
    alice = (tmp_path / "feedback" / "alice.txt").read_text().splitlines()
    assert alice[0] == "Grades of alice" and alice[2] == NAME and alice[-1].split()[:4] == ["total", "4", "/", "4"]
    assert "random answers earn 0.33 on average" in alice[-1]
    bob = (tmp_path / "feedback" / "bob.txt").read_text()
    assert "cannot read the submission" in bob and "total                        0 / 4" in bob, bob
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["student", "notebook", "exercise", "points", "max_points", "chance", "seconds", "reason",
                             "sandbox"]
    got = {(r["student"], r["exercise"]): (float(r["points"]), float(r["max_points"]), float(r["chance"]))
           for r in rows}
    assert got[("alice", "ex-predict")] == (1.0, 1.0, 0.3333) and got[("bob", "ex-predict")] == (0.0, 1.0, 0.3333)
    assert got[("alice", "ex-square")] == (2.0, 2.0, 0.0)
    assert main(["grade-class", str(tmp_path / "submitted"), "--source", str(src.parent), "--csv", str(out),
                 "--trusted", "--weigh-choices"]) == 0
    assert f"{NAME}: 3.67 points, chance score 0.22" in capsys.readouterr().out
    rows = {(r["student"], r["exercise"]): r for r in csv.DictReader(out.open())}
    assert float(rows[("alice", "ex-predict")]["points"]) == pytest.approx(2 / 3)
    assert float(rows[("bob", "ex-predict")]["max_points"]) == pytest.approx(2 / 3)
