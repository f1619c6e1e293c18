"""docs/teaching.md is a page for teachers: the four steps of a graded assignment, the commands as the grader
takes them, each graded exercise's points and chance score as the grader computes them, and no development
history (commit hashes, issue numbers, paths or notes of one machine)."""
import contextlib
import io
import re
import subprocess
from fractions import Fraction
from pathlib import Path

import nbformat
import pytest

from vpr_nb.assignments import exercise_specs, main

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "teaching.md"
TEXT = PAGE.read_text(encoding="utf-8")
FLAT = re.sub(r"\s+", " ", TEXT)
COURSE = sorted((ROOT / "notebooks").glob("0[2-9]_*.ipynb"))
STEPS = ("Hand out", "Collect", "Grade", "Return feedback")


def _is_git_object(word: str) -> bool:
    if not (ROOT / ".git").exists():
        return False
    proc = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", f"{word}^{{object}}"],
                          capture_output=True, text=True)
    return proc.returncode == 0


def test_no_commit_hash():
    words = set(re.findall(r"(?<![\w-])[0-9a-f]{7,40}(?![\w-])", TEXT))
    hashes = [w for w in words if _is_git_object(w) or (re.search(r"\d", w) and re.search(r"[a-f]", w))]
    assert not hashes, f"docs/teaching.md names commits (development history, not for teachers): {hashes}"


def test_no_issue_numbers_and_no_notes_of_one_machine():
    issues = re.findall(r"\b(?:[Ii]ssues?|PR|[Pp]ull request) ?#?\d+|(?<![\w&])#\d+\b", TEXT)
    assert not issues, f"docs/teaching.md cites issues: {issues}"
    paths = re.findall(r"(?<![\w.~])/(?:(?:root|home|work|mnt|Users)\b|(?:tmp|opt|srv|var|data)/\w)[\w./+-]*", TEXT)
    assert not paths, f"docs/teaching.md names paths of one machine: {paths}"
    notes = re.findall(r"(?i)\b(?:on this machine|the course machine|the shared \d-core machine|as here)\b", FLAT)
    assert not notes, f"docs/teaching.md holds notes about the machine it was written on: {notes}"


def test_the_four_steps_are_named_in_order():
    headings = re.findall(r"^#{2,4} (.+?)\s*$", TEXT, flags=re.M)
    at = []
    for n, step in enumerate(STEPS, 1):
        found = [i for i, h in enumerate(headings) if re.fullmatch(rf"{n}\. {step}", h)]
        assert found, f"docs/teaching.md has no heading '### {n}. {step}' (the steps: {STEPS}); headings: {headings}"
        at.append(found[0])
    assert at == sorted(at), f"the four steps are out of order: {at}"


def _blocks() -> list[str]:
    """The shell blocks of the page (fenced blocks marked bash or sh, or unmarked)."""
    return [body for lang, body in re.findall(r"^```(\w*)\n(.*?)^```$", TEXT, flags=re.M | re.S)
            if lang in ("bash", "sh", "")]


def _help(sub: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main([sub, "--help"])
    return out.getvalue()


def test_every_grading_command_of_the_page_is_one_the_grader_takes():
    commands = [re.sub(r"\\\n\s*", " ", b) for b in _blocks()]
    lines = [ln.split("#")[0] for b in commands for ln in b.splitlines() if "-m vpr_nb.assignments" in ln]
    assert any(" grade-class " in ln for ln in lines) and any(" grade " in ln for ln in lines), lines
    for line in lines:
        sub = line.split("-m vpr_nb.assignments", 1)[1].split()[0]
        helptext = _help(sub)
        for opt in re.findall(r"(?<!\S)--[\w-]+", line):
            assert opt in helptext, f"`{line.strip()}`: `python -m vpr_nb.assignments {sub}` takes no {opt}"
    options = set(re.findall(r"^\| `(--[\w-]+)", TEXT, flags=re.M))
    assert options, "the page's table of grade-class options is missing"
    assert all(o in _help("grade-class") for o in options), options
    assert "make assignments" in TEXT


def test_nbgrader_is_set_up_one_way_into_the_course_environment():
    installs = re.findall(r"([\w./-]*pip) install (?:-\w+ )*nbgrader", TEXT)
    assert installs and set(installs) == {".venv/bin/pip"}, f"nbgrader installed in more than one way: {installs}"
    outside = re.search(r"(?i)[^.]*outside (?:the|its|this) (?:venv|environment)[^.]*", FLAT)
    assert not outside, f"docs/teaching.md also runs nbgrader outside the course environment: {outside.group(0)!r}"


def _fraction(cell: str) -> Fraction:
    return Fraction(cell.strip())


def test_the_points_and_chance_scores_of_the_page_are_the_graders():
    rows = re.findall(r"^\| (\d\d) \| `(ex-[\w-]+)` \| ([\d/.]+) \| ([\d/.]+) \|", TEXT, flags=re.M)
    page = {ex: (_fraction(p), _fraction(c)) for _, ex, p, c in rows}
    graded = {}
    for path in COURSE:
        for e in exercise_specs(nbformat.read(path, as_version=4), path.name):
            graded[e.id] = (Fraction(e.points).limit_denominator(1000), Fraction(e.chance).limit_denominator(1000))
    assert page == graded, f"docs/teaching.md's points and chance scores differ from the grader's:\n{page}\n{graded}"
    per_nb = {}
    for ex, (p, c) in graded.items():
        nb = ex.split("-")[1]
        per_nb.setdefault(nb, [0, 0])
        per_nb[nb][0] += p
        per_nb[nb][1] += c
    m = re.search(r"earn ([\d.]+) of its (\d+) points on average, ([\d.]+) of the (\d+) points", FLAT)
    assert m, "docs/teaching.md no longer states what random answers earn per notebook and in all"
    assert {(round(float(c), 2), int(p)) for p, c in per_nb.values()} == {(float(m.group(1)), int(m.group(2)))}
    assert float(m.group(3)) == round(float(sum(c for _, c in graded.values())), 2)
    assert int(m.group(4)) == sum(p for p, _ in graded.values())
