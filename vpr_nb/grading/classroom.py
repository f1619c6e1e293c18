"""Grading a class: every ``FOLDER/<student>/**/NN_*.ipynb`` against the instructor notebooks, into one CSV.

The instructor notebooks are read once, before any submission runs; each submission is graded as
:func:`vpr_nb.grading.submission.grade` does (in the OS sandbox, which also hides the class folder and the
grades file, or refused, unless the work is trusted), and the grades file is rewritten atomically after
each one.
"""
from __future__ import annotations

import csv
import os
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import nbformat

from . import sandbox
from .exercise import Source, weigh_choices
from .isolation import choose_backend, describe, label
from .markers import exercise_id, exercises
from .submission import DEFAULT_TIMEOUT, grade, limits_for


def _student_notebooks(folder: Path, names: set[str]):
    """(student, notebook path) of every submission: ``folder/<student>/**/<name>``."""
    for student in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for path in sorted(student.rglob("*.ipynb")):
            if path.name in names and ".ipynb_checkpoints" not in path.parts and not path.is_symlink():
                yield student.name, path


CSV_FIELDS = ["student", "notebook", "exercise", "points", "max_points", "chance", "seconds", "reason", "sandbox"]


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


def _pts(x: float) -> str:
    return f"{round(float(x), 2):g}"


def feedback_text(student: str, rows: list[dict]) -> str:
    """What one student gets back: per notebook, each exercise's points, the reason of each zero and the total
    beside the chance score (what random answers earn on average)."""
    lines = [f"Grades of {student}"]
    for nb in dict.fromkeys(r["notebook"] for r in rows):
        mine = [r for r in rows if r["notebook"] == nb]
        lines += ["", nb]
        for r in mine:
            lines.append(f"  {r['exercise']:28s} {_pts(r['points'])} / {_pts(r['max_points'])}")
            if r["reason"]:
                lines.append(f"      {r['reason']}")
        got, best, chance = (sum(r[k] for r in mine) for k in ("points", "max_points", "chance"))
        lines.append(f"  {'total':28s} {_pts(got)} / {_pts(best)}  (random answers earn {_pts(chance)} on average)")
    return "\n".join(lines) + "\n"


def write_feedback(rows: list[dict], folder) -> list[Path]:
    """One text file per student, ``folder/<student>.txt`` (:func:`feedback_text`), written atomically."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for student in dict.fromkeys(r["student"] for r in rows):
        target = folder / f"{student}.txt"
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=folder)
        with os.fdopen(fd, "w") as fh:
            fh.write(feedback_text(student, [r for r in rows if r["student"] == student]))
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
        written.append(target)
    return written


def grade_class(folder, source_dir, csv_path=None, timeout: float = DEFAULT_TIMEOUT, log=print, jobs: int = 1,
                backend: str | None = None, trusted: bool = False, weigh: bool = False) -> list[dict]:
    """Grade every submission under ``folder/<student>/`` against the notebooks of ``source_dir``.

    The instructor notebooks are read once, before any submission runs (their cases are built then);
    each submission is graded as :func:`grade` does, ``jobs`` at a time, in the OS sandbox, which hides
    the instructor notebooks, ``source_dir``, ``folder`` and the grades file's folder. Returns one row per
    student, notebook and exercise (``student, notebook, exercise, points, max_points, chance, seconds, reason,
    sandbox``; ``chance``: the points a random guess earns on average, :class:`~vpr_nb.grading.exercise.Grade`;
    ``weigh``: a choice among k options worth ``1 - 1/k`` of its points) and, when ``csv_path`` is given, rewrites that file atomically after every submission, so a
    grading that is interrupted leaves the grades so far. A submission that cannot be read scores 0 on each
    of its exercises, with the reason.

    Without a working bubblewrap it raises :class:`vpr_nb.grading.isolation.NoSandboxError` before any
    submission runs, unless ``trusted``: then it grades without an OS sandbox and every row's ``sandbox``
    says so (``graded WITHOUT a sandbox (--trusted)``).
    """
    folder, source_dir = Path(folder), Path(source_dir)
    for p in (folder, source_dir):
        if not p.is_dir():
            raise FileNotFoundError(f"folder not found: {p}")
    limits = limits_for(timeout)
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
    backend = choose_backend(backend, trusted)
    csv_path = Path(csv_path) if csv_path is not None else None
    private = (source_dir, folder) + ((csv_path.parent,) if csv_path is not None else ())
    if backend == "bwrap":
        sandbox.check_private(private + tuple(src.path for src in sources.values()))
    log(f"sandbox: {describe(backend)}")
    done: dict[int, list[dict]] = {}
    lock = threading.Lock()

    def one(k: int) -> None:
        student, path = subs[k]
        src = sources[path.name]
        specs = weigh_choices(src.exercises) if weigh else src.exercises
        try:
            grades = grade(path, src.path, timeout=limits.wall_s, backend=backend, source=src, trusted=trusted,
                           private=private, weigh=weigh)
        except (ValueError, FileNotFoundError) as err:
            grades = [e.failed(str(err)[:600]) for e in specs]
        except Exception as err:      # a grader bug must not lose the class's other grades
            grades = [e.failed(f"grading failed: {type(err).__name__}: {err}"[:600]) for e in specs]
        rows = [{"student": student, "notebook": path.name, "exercise": exercise_id(g.grade_id), "points": g.points,
                 "max_points": g.max_points, "chance": round(g.chance, 4), "seconds": g.seconds, "reason": g.error,
                 "sandbox": label(backend)} for g in grades]
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
