"""Classroom assignments from the course notebooks, with nbgrader's markers, graded in a sandbox.

An exercise is cells of an instructor notebook marked with nbgrader's cell metadata:

* a **solution cell** whose code between ``### BEGIN SOLUTION`` and ``### END SOLUTION`` is the
  answer (metadata ``nbgrader.solution = true``, ``grade_id = "<id>"``);
* a **test cell** after it (metadata ``nbgrader.grade = true``, ``grade_id = "<id>-tests"``,
  ``points``) that imports what it needs and declares the cases with
  :func:`~vpr_nb.grading.spec.check` (``check("fn", [Case(name, args, expect=..., atol=...), ...])``):
  visible cases for the student above ``### BEGIN HIDDEN TESTS``, hidden ones between it and
  ``### END HIDDEN TESTS``. In a kernel ``check`` runs the cases and asserts (the student's own run,
  nbval, nbgrader's autograde); the course grader only reads them;
* its **dependencies**: the setup cells the solution needs (imports, parameters), each tagged
  ``grade-deps:<id>``; an exercise without such tags uses every instructor code cell above its solution.

These are nbgrader's own markers and cell metadata, so nbgrader (``nbgrader generate_assignment``)
users can take the notebooks unchanged. This module is the small stand-alone converter and grader the
course uses:

* ``python -m vpr_nb.assignments generate notebooks assignments`` writes student versions: each
  solution replaced by ``raise NotImplementedError()`` (markdown solutions by "YOUR ANSWER HERE"),
  hidden tests removed, all outputs and execution counts cleared, test cells and read-only cells
  locked (``editable: false``, ``deletable: false``, as nbgrader does; the ``parameters`` cell stays
  editable);
* ``python -m vpr_nb.assignments grade STUDENT.ipynb --source notebooks/NN.ipynb`` grades one
  submission and prints the points of every exercise, with the first failing case's message;
* ``python -m vpr_nb.assignments grade-class SUBMISSIONS/ --source notebooks/ --csv scores.csv``
  grades every ``SUBMISSIONS/<student>/**/NN_*.ipynb`` and writes one CSV row per student and exercise.

Grading treats a submission as hostile. The grader (trusted) reads the instructor notebooks once and
builds every case's inputs and reference; checks the "own code" rule on the submitted source
(:mod:`vpr_nb.grading.owncode`); runs the setup cells and the student's solution cells in a throwaway
folder in a sandbox (:mod:`vpr_nb.grading.sandbox`), where :mod:`vpr_nb.grading.runner` calls the
student's function on the inputs; reads the answers back as data only (:mod:`vpr_nb.grading.data`) and
compares them itself. Nothing the student's process does (patching builtins, numpy, torch, ``vpr_nb`` or
IPython, hiding its errors) is a pass signal. An exercise that fails, runs out of time or memory, or
kills its process scores 0 with the reason; the others are still graded.
"""
from __future__ import annotations

import argparse
import copy
import csv
import hashlib
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import nbformat

from .grading import sandbox
from .grading.data import DataError
from .grading.data import read as read_data
from .grading.data import write as write_data
from .grading.owncode import assert_own_code, library_references, own_code_message, source_violations
from .grading.spec import Case, Check, check, collect, one_of

__all__ = ["Case", "Grade", "assert_own_code", "check", "exercises", "generate", "grade", "grade_class",
           "library_references", "one_of", "student_version"]

BEGIN_SOLUTION, END_SOLUTION = "### BEGIN SOLUTION", "### END SOLUTION"
BEGIN_HIDDEN, END_HIDDEN = "### BEGIN HIDDEN TESTS", "### END HIDDEN TESTS"
CODE_STUB = "raise NotImplementedError()"
MD_STUB = "YOUR ANSWER HERE"
DEPS_TAG = "grade-deps:"
DEFAULT_TIMEOUT = 120   # seconds per exercise


def _meta(cell) -> dict:
    return cell.get("metadata", {}).get("nbgrader", {})


def is_solution(cell) -> bool:
    return bool(_meta(cell).get("solution")) or BEGIN_SOLUTION in cell.source


def is_test(cell) -> bool:
    return cell.cell_type == "code" and bool(_meta(cell).get("grade")) and not _meta(cell).get("solution")


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


def _strip_region(source: str, begin: str, end: str, stub: str | None, where: str) -> str:
    """Replace each begin..end region (marker lines included) by ``stub`` at the marker's indent."""
    out, inside, indent = [], False, ""
    for line in source.split("\n"):
        stripped = line.strip()
        if stripped == begin:
            if inside:
                raise ValueError(f"{where}: nested {begin!r}")
            inside, indent = True, line[: len(line) - len(line.lstrip())]
            if stub is not None:
                out.append(indent + stub)
        elif stripped == end:
            if not inside:
                raise ValueError(f"{where}: {end!r} without {begin!r}")
            inside = False
        elif not inside:
            out.append(line)
    if inside:
        raise ValueError(f"{where}: {begin!r} without {end!r}")
    return "\n".join(out)


def student_version(nb: nbformat.NotebookNode, name: str = "notebook") -> nbformat.NotebookNode:
    """The student notebook of an instructor notebook: solutions stubbed, hidden tests removed, outputs
    cleared, test cells and read-only cells (nbgrader ``locked`` or ``grade-deps`` tagged, except the
    ``parameters`` cell) locked."""
    nb = copy.deepcopy(nb)
    for i, cell in enumerate(nb.cells):
        where = f"{name} cell {i}"
        if is_solution(cell):
            stub = CODE_STUB if cell.cell_type == "code" else MD_STUB
            if BEGIN_SOLUTION in cell.source:
                cell.source = _strip_region(cell.source, BEGIN_SOLUTION, END_SOLUTION, stub, where)
            else:
                cell.source = stub
        if cell.cell_type == "code":
            cell.source = _strip_region(cell.source, BEGIN_HIDDEN, END_HIDDEN, None, where)
            cell.outputs, cell.execution_count = [], None
        cell.metadata.pop("execution", None)            # the instructor run's timestamps
        if not is_solution(cell) and (is_test(cell) or _meta(cell).get("locked") or (deps_of(cell) and not is_parameters(cell))):
            cell.metadata["editable"] = False
            cell.metadata["deletable"] = False
    return nb


def exercises(nb: nbformat.NotebookNode) -> list[tuple[str, int, float]]:
    """(grade_id, cell index, points) of every test cell."""
    out = []
    for i, cell in enumerate(nb.cells):
        if is_test(cell):
            meta = _meta(cell)
            if "grade_id" not in meta:
                raise ValueError(f"test cell {i} has no nbgrader grade_id: add one to its nbgrader metadata")
            out.append((meta["grade_id"], i, float(meta.get("points", 1))))
    return out


def generate(source_dir, out_dir, pattern: str = "[0-9][0-9]_*.ipynb") -> list[Path]:
    """Write the student version of every notebook in ``source_dir`` that has an exercise into ``out_dir``."""
    source_dir, out_dir = Path(source_dir), Path(out_dir)
    if not source_dir.is_dir():
        raise FileNotFoundError(f"source folder not found: {source_dir}")
    paths = sorted(source_dir.glob(pattern))
    if not paths:
        raise FileNotFoundError(f"no notebooks matching {pattern!r} in {source_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for path in paths:
        nb = nbformat.read(path, as_version=4)
        if not exercises(nb):
            continue
        target = out_dir / path.name
        nbformat.write(student_version(nb, path.name), target)
        written.append(target)
    return written


# ---------------------------------------------------------------------------------------------------
# grading


@dataclass
class Grade:
    grade_id: str
    points: float
    max_points: float
    error: str = ""
    seconds: float = 0.0


@dataclass
class Exercise:
    """What the grader holds of one exercise, read once from the instructor notebook."""
    grade_id: str                 # the test cell's grade_id
    points: float
    setup: list[str]              # instructor cells run before the solution (grade-deps, or all cells above)
    checks: list[Check]           # what the test cell declares (visible and hidden)

    @property
    def id(self) -> str:
        return exercise_id(self.grade_id)


def exercise_specs(nb: nbformat.NotebookNode, name: str = "notebook") -> list[Exercise]:
    """The exercises of an instructor notebook, with their checks built from the test cells (instructor
    code, run here in the grader with :func:`vpr_nb.grading.spec.collect`)."""
    out = []
    for gid, i, pts in exercises(nb):
        eid = exercise_id(gid)
        deps = [c.source for c in nb.cells[:i] if c.cell_type == "code" and eid in deps_of(c)]
        if not deps:                          # untagged: the instructor's code cells above its solution
            first = next((j for j, c in enumerate(nb.cells) if is_solution(c) and _meta(c).get("grade_id") == eid), i)
            deps = [c.source for c in nb.cells[:first]
                    if c.cell_type == "code" and not is_solution(c) and not is_test(c)]
        checks = collect(nb.cells[i].source, f"{name}: the test cell {gid!r}")
        out.append(Exercise(gid, pts, deps, checks))
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
                   backend: str) -> Grade:
    """One exercise of one submission: static own-code rule here, the student's code in a sandbox, the
    comparison here."""
    start = time.monotonic()
    solutions = [c.source for c in student.cells
                 if is_solution(c) and c.cell_type == "code" and _meta(c).get("grade_id") == ex.id]

    def done(reason: str) -> Grade:
        return Grade(ex.grade_id, 0.0 if reason else ex.points, ex.points, reason[:900],
                     round(time.monotonic() - start, 1))

    if not solutions:
        return done(f"the solution cell {ex.id!r} is missing from the submission")
    reason = _own_code_reason(ex, solutions)
    if reason:
        return done(reason)
    with sandbox.Workdir(backend=backend) as wd:
        cells = [{"role": "setup", "source": s} for s in ex.setup] + [{"role": "solution", "source": s} for s in solutions]
        (wd.path / "job.json").write_text(json.dumps(
            {"cells": cells, "checks": [{"function": c.function, "call": c.call} for c in ex.checks]}))
        write_data([[[list(case.args), case.kwargs] for case in c.cases] for c in ex.checks], wd.path, "inputs")
        (wd.path / "submission.ipynb").write_bytes(raw)
        mpl = wd.path / ".matplotlib"
        mpl.mkdir()
        for f in _font_cache():
            shutil.copy(f, mpl / f.name)
        wd.hand_over()
        outcome = sandbox.run([], wd, limits, backend)
        try:
            result = read_data(wd.path / "out", "result")
        except DataError as err:
            out = wd.path / "out" / "result.json"
            result = f"the grading process's answer was refused: {err}" if out.exists() else None
    return done(_judge(ex, result, outcome, limits))


MAX_SUBMISSION_BYTES = 64 * 2 ** 20


def _read_submission(path: Path) -> tuple[nbformat.NotebookNode, bytes]:
    if not path.is_file():
        raise FileNotFoundError(f"notebook not found: {path}")
    if path.stat().st_size > MAX_SUBMISSION_BYTES:
        raise ValueError(f"the submission {path} is larger than {MAX_SUBMISSION_BYTES >> 20} MB; ask the student "
                         "to clear its outputs and re-save it")
    raw = path.read_bytes()
    try:
        return nbformat.reads(raw.decode("utf-8"), as_version=4), raw
    except Exception as err:
        raise ValueError(f"cannot read the submission {path} as a notebook ({err}); "
                         "ask the student to re-save it from JupyterLab") from err


CPU_MARGIN_S = 5.0   # seconds of CPU time a graded process may use beyond the wall-clock timeout


def _limits(timeout: float) -> sandbox.Limits:
    if not timeout or timeout <= 0:
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    # the wall-clock limit decides; the per-process CPU limit is a backstop a little above it (a process
    # with several busy threads gathers CPU time faster than wall time, and with equal limits an endless
    # loop could end with either message)
    return sandbox.Limits(wall_s=float(timeout), cpu_s=float(timeout) + CPU_MARGIN_S)


def grade(student_path, source_path, timeout: float = DEFAULT_TIMEOUT, only=None, backend: str | None = None,
          source: Source | None = None) -> list[Grade]:
    """Grade each exercise of a student's notebook against the instructor's.

    For each exercise the grader checks the own-code rule on the submitted solution source, then runs
    the instructor's setup cells (tagged ``grade-deps:<id>``) and the student's solution cell(s) in a
    sandbox (``vpr_nb.grading.sandbox``: a throwaway folder holding only the submission, limits, every
    process killed at the end), calls the student's function there on the instructor's inputs, gets the
    answers back as data and compares them here with the references of the test cell's ``check(...)``
    calls. An exercise earns its points when every case passes; otherwise it scores 0 with the first
    failing case's message, a timeout after ``timeout`` seconds or how the process ended; the other
    exercises are still graded.

    Args:
        student_path: the submitted notebook.
        source_path: the instructor notebook it was generated from.
        timeout: wall-clock and CPU seconds per exercise.
        only: grade only these exercise ids or test grade_ids (default: all).
        backend: ``"bwrap"`` or ``"process"`` (default: :func:`vpr_nb.grading.sandbox.default_backend`).
        source: the instructor notebook already read (``grade_class`` reads each one once).
    """
    student_path = Path(student_path)
    limits = _limits(timeout)
    source = source or Source.read(source_path)
    specs = source.exercises
    if only is not None:
        only = set(only)
        specs = [e for e in specs if e.grade_id in only or e.id in only]
        if not specs:
            raise ValueError(f"none of {sorted(only)} is an exercise of {source.path}")
    student, raw = _read_submission(student_path)
    backend = backend or sandbox.default_backend()
    return [grade_exercise(ex, student, raw, limits, backend) for ex in specs]


def _student_notebooks(folder: Path, names: set[str]):
    """(student, notebook path) of every submission: ``folder/<student>/**/<name>``."""
    for student in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for path in sorted(student.rglob("*.ipynb")):
            if path.name in names and ".ipynb_checkpoints" not in path.parts and not path.is_symlink():
                yield student.name, path


CSV_FIELDS = ["student", "notebook", "exercise", "points", "max_points", "seconds", "reason"]


def write_csv_atomically(rows: list[dict], csv_path: Path) -> None:
    """Write the grades file in one step (a temporary file in the same folder, then ``os.replace``)."""
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{csv_path.name}.", dir=csv_path.parent)
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
            w.writeheader()
            w.writerows(rows)
        os.chmod(tmp, 0o644)
        os.replace(tmp, csv_path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def grade_class(folder, source_dir, csv_path=None, timeout: float = DEFAULT_TIMEOUT, log=print, jobs: int = 1,
                backend: str | None = None) -> list[dict]:
    """Grade every submission under ``folder/<student>/`` against the notebooks of ``source_dir``.

    The instructor notebooks are read once, before any submission runs (their cases are built then);
    each submission is graded as :func:`grade` does, ``jobs`` at a time. Returns one row per student,
    notebook and exercise (``student, notebook, exercise, points, max_points, seconds, reason``) and,
    when ``csv_path`` is given, rewrites that file atomically after every submission, so a grading that
    is interrupted leaves the grades so far. A submission that cannot be read scores 0 on each of its
    exercises, with the reason.
    """
    folder, source_dir = Path(folder), Path(source_dir)
    for p in (folder, source_dir):
        if not p.is_dir():
            raise FileNotFoundError(f"folder not found: {p}")
    limits = _limits(timeout)
    if not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    sources = {}
    for p in sorted(source_dir.glob("*.ipynb")):
        if exercises(nbformat.read(p, as_version=4)):
            sources[p.name] = Source.read(p)
    if not sources:
        raise FileNotFoundError(f"no instructor notebook with graded exercises in {source_dir}")
    subs = list(_student_notebooks(folder, set(sources)))
    if not subs:
        raise FileNotFoundError(f"no submissions in {folder}: expected {folder}/<student>/<notebook>.ipynb "
                                f"named as one of {sorted(sources)}")
    backend = backend or sandbox.default_backend()
    log(f"sandbox: {sandbox.describe(backend)}")
    csv_path = Path(csv_path) if csv_path is not None else None
    done: dict[int, list[dict]] = {}
    lock = threading.Lock()

    def one(k: int) -> None:
        student, path = subs[k]
        src = sources[path.name]
        try:
            grades = grade(path, src.path, timeout=limits.wall_s, backend=backend, source=src)
        except (ValueError, FileNotFoundError) as err:
            grades = [Grade(e.grade_id, 0.0, e.points, str(err)[:600]) for e in src.exercises]
        except Exception as err:      # a grader bug must not lose the class's other grades
            grades = [Grade(e.grade_id, 0.0, e.points, f"grading failed: {type(err).__name__}: {err}"[:600])
                      for e in src.exercises]
        rows = [{"student": student, "notebook": path.name, "exercise": exercise_id(g.grade_id), "points": g.points,
                 "max_points": g.max_points, "seconds": g.seconds, "reason": g.error} for g in grades]
        with lock:
            done[k] = rows
            for g in grades:
                log(f"{student:20s} {exercise_id(g.grade_id):24s} {g.points:g} / {g.max_points:g}  ({g.seconds:.1f} s)"
                    + (f"   {g.error}" if g.error else ""))
            if csv_path is not None:
                write_csv_atomically([r for i in sorted(done) for r in done[i]], csv_path)

    if jobs == 1:
        for k in range(len(subs)):
            one(k)
    else:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            list(pool.map(one, range(len(subs))))
    for src in sources.values():
        if not src.unchanged():
            log(f"warning: {src.path} changed on disk while grading; the grades use the copy read at the start")
    return [r for k in sorted(done) for r in done[k]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.assignments", description="student versions and grading")
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write student versions of the notebooks")
    g.add_argument("source_dir", type=Path)
    g.add_argument("out_dir", type=Path)
    r = sub.add_parser("grade", help="grade a student's notebook")
    r.add_argument("student", type=Path)
    r.add_argument("--source", type=Path, required=True, help="the instructor notebook it was generated from")
    c = sub.add_parser("grade-class", help="grade every FOLDER/<student>/**/NN_*.ipynb, write a CSV")
    c.add_argument("folder", type=Path)
    c.add_argument("--source", type=Path, required=True, help="the folder of instructor notebooks")
    c.add_argument("--csv", type=Path, default=Path("scores.csv"))
    c.add_argument("--jobs", type=int, default=1, help="submissions graded at the same time (one per core)")
    for q in (r, c):
        q.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="wall-clock and CPU seconds per exercise")
        q.add_argument("--sandbox", choices=sandbox.BACKENDS, default=None,
                       help="bwrap (bubblewrap) or process (no OS sandbox); default: bwrap where it works")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "generate":
            for p in generate(args.source_dir, args.out_dir):
                print("wrote", p)
            return 0
        if args.cmd == "grade-class":
            rows = grade_class(args.folder, args.source, args.csv, args.timeout, jobs=args.jobs, backend=args.sandbox)
            total = sum(r["points"] for r in rows)
            print(f"{len({r['student'] for r in rows})} students, {len(rows)} exercises graded, "
                  f"{total:g} points in all; wrote {args.csv}")
            return 0
        backend = args.sandbox or sandbox.default_backend()
        print(f"sandbox: {sandbox.describe(backend)}")
        grades = grade(args.student, args.source, args.timeout, backend=backend)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for gr in grades:
        print(f"{gr.grade_id:32s} {gr.points:g} / {gr.max_points:g}  ({gr.seconds:.1f} s)"
              + (f"\n    {gr.error}" if gr.error else ""))
    total, best = sum(g.points for g in grades), sum(g.max_points for g in grades)
    print(f"{'total':32s} {total:g} / {best:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
