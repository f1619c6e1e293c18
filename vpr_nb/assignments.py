"""The front door to the course's assignments: student versions of the notebooks and the grading CLI.

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
  grades every ``SUBMISSIONS/<student>/**/NN_*.ipynb`` and writes one CSV row per student and exercise
  (and, with ``--feedback FOLDER``, one text file per student to hand back).

Both state each exercise's **chance score**, the points a random answer earns on average (a choice among
k stated options: its points / k; a function to write: 0), and the total of a notebook; ``--weigh-choices``
makes a choice among k options worth ``1 - 1/k`` of its points (default: the notebook's points, as nbgrader
gives them).

Grading treats a submission as hostile. The grader (trusted) reads the instructor notebooks once and
builds every case's inputs and reference; checks the "own code" rule on the submitted source
(:mod:`vpr_nb.grading.owncode`); runs the setup cells and the student's solution cells in a throwaway
folder in a sandbox (:mod:`vpr_nb.grading.sandbox`), where :mod:`vpr_nb.grading.runner` calls the
student's function on the inputs; reads the answers back as data only (:mod:`vpr_nb.grading.data`) and
compares them itself. Nothing the student's process does (patching builtins, numpy, torch, ``vpr_nb`` or
IPython, hiding its errors) is a pass signal. An exercise that fails, runs out of time or memory, or
kills its process scores 0 with the reason; the others are still graded. The sandbox is bubblewrap;
without it grading refuses (``error: no sandbox for untrusted submissions: ...``, exit 2) unless the
teacher passes ``--trusted`` for work they trust, which every report then states
(:mod:`vpr_nb.grading.isolation`).

This module writes the student versions and holds the CLI; the grading itself lives in
:mod:`vpr_nb.grading` (:mod:`~vpr_nb.grading.markers`, :mod:`~vpr_nb.grading.exercise` for one exercise,
:mod:`~vpr_nb.grading.submission` for one notebook, :mod:`~vpr_nb.grading.classroom` for a class), whose
public names (and the test cells' :class:`Case`, :func:`check`, :func:`one_of`) are importable from here.
"""
from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import nbformat

from .grading import isolation, sandbox
from .grading.classroom import CSV_FIELDS, feedback_text, grade_class, write_csv_atomically, write_feedback
from .grading.exercise import STUB_MESSAGE, Exercise, Grade, Source, exercise_specs, grade_exercise, weigh_choices
from .grading.isolation import NO_SANDBOX, NoSandboxError
from .grading.markers import (BEGIN_HIDDEN, BEGIN_SOLUTION, DEPS_TAG, END_HIDDEN, END_SOLUTION, deps_of, exercise_id,
                              exercises, is_parameters, is_solution, is_test, nbgrader_meta)
from .grading.owncode import assert_own_code, library_references
from .grading.spec import Case, check, guess_chance, one_of
from .grading.submission import CPU_MARGIN_S, DEFAULT_TIMEOUT, MAX_SUBMISSION_BYTES, grade

__all__ = ["BEGIN_HIDDEN", "BEGIN_SOLUTION", "CODE_STUB", "CPU_MARGIN_S", "CSV_FIELDS", "Case", "DEFAULT_TIMEOUT",
           "DEPS_TAG", "END_HIDDEN", "END_SOLUTION", "Exercise", "Grade", "MAX_SUBMISSION_BYTES", "MD_STUB",
           "NO_SANDBOX", "NoSandboxError", "STUB_MESSAGE", "Source", "assert_own_code", "check", "deps_of",
           "exercise_id", "exercise_specs", "exercises", "feedback_text", "generate", "grade", "grade_class",
           "grade_exercise", "guess_chance", "is_parameters", "is_solution", "is_test", "library_references", "main",
           "one_of", "student_version", "weigh_choices", "write_csv_atomically", "write_feedback"]

CODE_STUB = "raise NotImplementedError()"
MD_STUB = "YOUR ANSWER HERE"


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
        read_only = is_test(cell) or nbgrader_meta(cell).get("locked") or (deps_of(cell) and not is_parameters(cell))
        if not is_solution(cell) and read_only:
            cell.metadata["editable"] = False
            cell.metadata["deletable"] = False
    return nb


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


def _pts(x: float) -> str:
    return f"{round(x, 2):g}"


def _chance_lines(rows: list[dict]) -> list[str]:
    """Per notebook of a class's rows: its points and its chance score (what random answers earn on average)."""
    per: dict[str, dict[str, tuple[float, float]]] = {}
    for r in rows:
        per.setdefault(r["notebook"], {})[r["exercise"]] = (r["max_points"], r["chance"])
    return [f"{nb}: {_pts(sum(m for m, _ in ex.values()))} points, chance score "
            f"{_pts(sum(c for _, c in ex.values()))} (random answers, on average)" for nb, ex in sorted(per.items())]


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
    c.add_argument("--feedback", type=Path, default=None,
                   help="also write FOLDER/<student>.txt: each exercise's points and the reason of each zero")
    for q in (r, c):
        q.add_argument("--weigh-choices", action="store_true",
                       help="a choice among k options is worth 1 - 1/k of its points (default: the notebook's points)")
        q.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="wall-clock and CPU seconds per exercise")
        q.add_argument("--sandbox", choices=sandbox.BACKENDS, default=None,
                       help="bwrap (bubblewrap, the default) or process (no OS sandbox: needs --trusted)")
        q.add_argument("--trusted", action="store_true",
                       help="the work is trusted: without bubblewrap, grade it WITHOUT a sandbox (every report "
                            "says so) instead of refusing")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "generate":
            for p in generate(args.source_dir, args.out_dir):
                print("wrote", p)
            return 0
        if args.cmd == "grade-class":
            rows = grade_class(args.folder, args.source, args.csv, args.timeout, jobs=args.jobs, backend=args.sandbox,
                               trusted=args.trusted, weigh=args.weigh_choices)
            for line in _chance_lines(rows):
                print(line)
            if args.feedback is not None:
                print(f"wrote {len(write_feedback(rows, args.feedback))} feedback files into {args.feedback}")
            total = sum(r["points"] for r in rows)
            unsandboxed = isolation.TRUSTED_LABEL in {r["sandbox"] for r in rows}
            print(f"{len({r['student'] for r in rows})} students, {len(rows)} exercises graded, "
                  f"{total:g} points in all; wrote {args.csv}" + (f"; {isolation.TRUSTED_LABEL}" if unsandboxed else ""))
            return 0
        backend = isolation.choose_backend(args.sandbox, args.trusted)
        print(f"sandbox: {isolation.describe(backend)}")
        grades = grade(args.student, args.source, args.timeout, backend=backend, trusted=args.trusted,
                       weigh=args.weigh_choices)
    except (ValueError, FileNotFoundError, NoSandboxError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for gr in grades:
        print(f"{gr.grade_id:32s} {_pts(gr.points)} / {_pts(gr.max_points)}  chance {_pts(gr.chance)}  "
              f"({gr.seconds:.1f} s)" + (f"\n    {gr.error}" if gr.error else ""))
    total, best = sum(g.points for g in grades), sum(g.max_points for g in grades)
    print(f"{'chance score':32s} {_pts(sum(g.chance for g in grades))} / {_pts(best)}  (random answers, on average)")
    print(f"{'total':32s} {_pts(total)} / {_pts(best)}" + (f"  ({isolation.TRUSTED_LABEL})" if backend != "bwrap" else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
