"""Grading one exercise of a submission: its spec read from the instructor notebook, the student's code run in
the sandbox, and the verdict on the answers that come back.

The grader (trusted) builds every case's inputs and reference from the instructor's test cell once
(:func:`exercise_specs`, :class:`Source`); for a submission it checks the "own code" rule on the submitted
source (:mod:`vpr_nb.grading.owncode`), runs the setup cells and the student's solution cells in a throwaway
folder in a sandbox (:mod:`vpr_nb.grading.sandbox`, where :mod:`vpr_nb.grading.runner` calls the student's
function), reads the answers back as data only (:mod:`vpr_nb.grading.data`) and judges them here
(:func:`grade_exercise`). Nothing the student's process does is a pass signal.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import nbformat

from . import sandbox
from .data import DataError
from .data import read as read_data
from .data import write as write_data
from .isolation import choose_backend
from .markers import deps_of, exercise_id, exercises, is_solution, is_test, nbgrader_meta
from .owncode import own_code_message, source_violations
from .spec import Check, collect, guess_chance


@dataclass
class Grade:
    grade_id: str
    points: float
    max_points: float
    error: str = ""
    seconds: float = 0.0
    backend: str = ""             # the sandbox backend that graded it ("bwrap"; "process" only for trusted work)
    chance: float = 0.0           # the points a random guess earns on average (the exercise's chance score)


@dataclass
class Exercise:
    """What the grader holds of one exercise, read once from the instructor notebook."""
    grade_id: str                 # the test cell's grade_id
    points: float
    setup: list[str]              # instructor cells run before the solution (grade-deps, or all cells above)
    checks: list[Check]           # what the test cell declares (visible and hidden)
    guess: float = 0.0            # the probability that a random answer passes (a choice among k: 1/k)

    @property
    def id(self) -> str:
        return exercise_id(self.grade_id)

    @property
    def chance(self) -> float:
        """The points a random guess earns on average: ``points * guess``."""
        return self.points * self.guess

    def failed(self, reason: str) -> Grade:
        """0 points, with the reason (a submission that could not be graded at all)."""
        return Grade(self.grade_id, 0.0, self.points, reason, chance=self.chance)


def weigh_choices(specs: list[Exercise]) -> list[Exercise]:
    """The exercises with each one a random guess can pass worth ``points * (1 - guess)``: a choice among k
    options keeps ``1 - 1/k`` of its points (2/3 of a point for a three-way choice worth 1), an exercise no
    guess passes keeps all of its points."""
    return [dataclasses.replace(e, points=e.points * (1 - e.guess)) if e.guess else e for e in specs]


def exercise_specs(nb: nbformat.NotebookNode, name: str = "notebook") -> list[Exercise]:
    """The exercises of an instructor notebook, with their checks built from the test cells (instructor
    code, run here in the grader with :func:`vpr_nb.grading.spec.collect`)."""
    out = []
    for gid, i, pts in exercises(nb):
        eid = exercise_id(gid)
        deps = [c.source for c in nb.cells[:i] if c.cell_type == "code" and eid in deps_of(c)]
        if not deps:                          # untagged: the instructor's code cells above its solution
            first = next((j for j, c in enumerate(nb.cells)
                          if is_solution(c) and nbgrader_meta(c).get("grade_id") == eid), i)
            deps = [c.source for c in nb.cells[:first]
                    if c.cell_type == "code" and not is_solution(c) and not is_test(c)]
        checks = collect(nb.cells[i].source, f"{name}: the test cell {gid!r}")
        out.append(Exercise(gid, pts, deps, checks, guess_chance(checks)))
    return out


@dataclass
class Source:
    """An instructor notebook as read at the start of grading: bytes, hash and exercises."""
    path: Path
    digest: str
    exercises: list[Exercise]

    @classmethod
    def read(cls, path) -> "Source":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"notebook not found: {path}")
        raw = path.read_bytes()
        nb = nbformat.reads(raw.decode("utf-8"), as_version=4)
        specs = exercise_specs(nb, path.name)
        if not specs:
            raise ValueError(f"{path} has no graded test cells (nbgrader metadata grade=true)")
        return cls(path, hashlib.sha256(raw).hexdigest(), specs)

    def unchanged(self) -> bool:
        try:
            return hashlib.sha256(self.path.read_bytes()).hexdigest() == self.digest
        except OSError:
            return False


def _stub_error(err: dict) -> bool:
    return err.get("ename") == "NotImplementedError" and not err.get("evalue")


STUB_MESSAGE = "NotImplementedError: the answer is not written yet (the solution cell still raises the stub)"


def _err_text(err, limit: int = 600) -> str:
    if not isinstance(err, dict):
        return "an error"
    if _stub_error(err):
        return STUB_MESSAGE
    text = f"{str(err.get('ename'))[:80]}: {str(err.get('evalue'))}".strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _ended_without_answer(outcome: sandbox.Outcome, limits: sandbox.Limits) -> str:
    code = outcome.returncode
    if code is not None and code < 0:
        sig = -code
        why = {signal.SIGXCPU: f"its CPU-time limit of {limits.cpu_s:g} s", signal.SIGKILL: "SIGKILL (out of "
               f"memory: limit {limits.memory_mb} MB, or the CPU-time limit)", signal.SIGSEGV: "a segmentation fault",
               signal.SIGXFSZ: f"writing a file larger than {limits.file_mb} MB"}.get(sig, f"signal {sig}")
        return f"the grading process was killed by {why} before it answered"
    tail = " ".join(outcome.log.strip().splitlines()[-2:])[-300:]
    return f"the grading process ended before it answered (exit code {code})" + (f": {tail}" if tail else "")


def _judge(ex: Exercise, result, outcome: sandbox.Outcome, limits: sandbox.Limits) -> str:
    """'' when every case passes, else the reason; ``result`` is untrusted data from the sandbox."""
    if outcome.timed_out:
        return (f"timed out after {limits.wall_s:g} s (an endless loop, or a process that never ends? "
                f"the exercise's limit is {limits.wall_s:g} s)")
    if isinstance(result, str):
        return result
    malformed = "the grading process returned a malformed result (did the submission tamper with it?)"
    if not isinstance(result, dict) or result.get("stage") not in ("cell", "done"):
        return malformed if isinstance(result, dict) and "stage" in result else _ended_without_answer(outcome, limits)
    if result["stage"] == "cell":
        role = result.get("role")
        what = {"setup": "a read-only cell it depends on", "solution": "your solution cell"}.get(role)
        if what is None:
            return malformed
        err = result.get("error")
        return STUB_MESSAGE if isinstance(err, dict) and _stub_error(err) else f"{what} raised {_err_text(err)}"
    entries = result.get("checks")
    if not isinstance(entries, list) or len(entries) != len(ex.checks):
        return malformed
    for check_, entry in zip(ex.checks, entries):
        if not isinstance(entry, dict) or entry.get("function") != check_.function:
            return malformed
        if entry.get("defined") is not True:
            return f"your solution cell does not define {check_.function}"
        results = entry.get("results")
        if not isinstance(results, list) or len(results) != len(check_.cases):
            return malformed
        for case, res in zip(check_.cases, results):
            if not isinstance(res, dict) or len(res) != 1:
                return malformed
            (kind, body), = res.items()
            if kind == "error":
                return STUB_MESSAGE if isinstance(body, dict) and _stub_error(body) else \
                    f"{case.name}: {check_.function} raised {_err_text(body)}"
            if kind == "refused":
                return f"{case.name}: {check_.function} returned {str(body)[:300]}"
            if kind != "value":
                return malformed
            msg = case.verdict(body)
            if msg:
                return msg
    return ""


def _own_code_reason(ex: Exercise, solutions: list[str]) -> str:
    """The static own-code rule on the submitted solution source ('' when it holds)."""
    ruled = [c for c in ex.checks if c.own_code]
    if not ruled:
        return ""
    forbid = tuple(dict.fromkeys(n for c in ruled for n in c.forbid))
    try:
        found = source_violations(solutions, forbid_names=forbid, setup_sources=ex.setup)
    except SyntaxError as err:
        return f"your solution cell does not parse: line {err.lineno}: {err.msg}"
    return own_code_message(ruled[0].function, found, forbid_names=forbid) if found else ""


def _font_cache() -> list[Path]:
    """matplotlib's font list, copied into each sandbox so an import does not rebuild it (seconds)."""
    try:
        import matplotlib
        return sorted(Path(matplotlib.get_cachedir()).glob("fontlist-*.json"))
    except Exception:
        return []


def grade_exercise(ex: Exercise, student: nbformat.NotebookNode, raw: bytes, limits: sandbox.Limits,
                   backend: str | None = None, trusted: bool = False, private=()) -> Grade:
    """One exercise of one submission: static own-code rule here, the student's code in a sandbox, the
    comparison here. ``backend``, ``trusted``: as :func:`vpr_nb.grading.isolation.choose_backend` takes them
    (no OS sandbox only for trusted work); ``private``: the teacher's paths the sandbox must hide."""
    start = time.monotonic()
    backend = choose_backend(backend, trusted)
    solutions = [c.source for c in student.cells
                 if is_solution(c) and c.cell_type == "code" and nbgrader_meta(c).get("grade_id") == ex.id]

    def done(reason: str) -> Grade:
        return Grade(ex.grade_id, 0.0 if reason else ex.points, ex.points, reason[:900],
                     round(time.monotonic() - start, 1), backend, ex.chance)

    if not solutions:
        return done(f"the solution cell {ex.id!r} is missing from the submission")
    reason = _own_code_reason(ex, solutions)
    if reason:
        return done(reason)
    with sandbox.Workdir(backend=backend) as wd:
        cells = ([{"role": "setup", "source": s} for s in ex.setup]
                 + [{"role": "solution", "source": s} for s in solutions])
        (wd.path / "job.json").write_text(json.dumps(
            {"cells": cells, "checks": [{"function": c.function, "call": c.call} for c in ex.checks]}))
        write_data([[[list(case.args), case.kwargs] for case in c.cases] for c in ex.checks], wd.path, "inputs")
        (wd.path / "submission.ipynb").write_bytes(raw)
        mpl = wd.path / ".matplotlib"
        mpl.mkdir()
        for f in _font_cache():
            shutil.copy(f, mpl / f.name)
        wd.hand_over()
        outcome = sandbox.run([], wd, limits, backend, private=private)
        try:
            result = read_data(wd.path / "out", "result")
        except DataError as err:
            out = wd.path / "out" / "result.json"
            result = f"the grading process's answer was refused: {err}" if out.exists() else None
    return done(_judge(ex, result, outcome, limits))
