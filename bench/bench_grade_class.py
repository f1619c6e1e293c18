"""Grade a generated class with ``grade-class`` and check its grades file.

    python bench/bench_grade_class.py                       # 50 submissions of notebook 06, 2 jobs
    python bench/bench_grade_class.py --quick               # 8 submissions
    python bench/bench_grade_class.py --notebook 02 --students 50 --jobs 2 --sandbox process

The class is a mix (by student number): correct answers (the instructor's solutions), wrong answers
(every function returns 0.0, every prediction the wrong choice), cheats (builtins and numpy patched,
tracebacks hidden, the own-code check replaced by a no-op, a library import), crashes (a solution
cell raises or exits, an endless loop, a memory hog) and unanswered student
versions. Every submission's expected points follow from its kind; the script checks the CSV against
them (fails on a mismatch, never on time) and prints the wall time, the time per submission, the
load average before and after, and the ratio to the process backend's time on a few submissions when
``--compare`` is given.
"""
from __future__ import annotations

import argparse
import copy
import csv
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vpr_nb.assignments import BEGIN_SOLUTION, END_SOLUTION, exercise_specs, is_solution, student_version  # noqa: E402

KINDS = ["correct", "correct", "wrong", "cheat-abs", "correct", "crash-exit", "cheat-traceback", "wrong",
         "correct", "stub", "cheat-own-code", "crash-raise", "correct", "cheat-numpy", "crash-loop", "correct",
         "crash-memory", "correct", "wrong", "correct"]


def _answer(solution_cell) -> str:
    """The instructor's solution cell with the solution markers removed."""
    return "\n".join(ln for ln in solution_cell.source.split("\n") if ln.strip() not in (BEGIN_SOLUTION, END_SOLUTION))


def _signature(source: str) -> tuple[str, str]:
    """(name, 'def' or 'value') of what a solution cell defines."""
    m = re.search(r"^def (\w+)\(", source, re.M)
    if m:
        return m.group(1), "def"
    m = re.search(r"^(\w+)\s*=", source.split(BEGIN_SOLUTION)[-1].strip(), re.M)
    return (m.group(1) if m else "ANSWER"), "value"


def submission(instructor, kind: str):
    """A student's notebook of ``kind``; each solution cell rewritten as that kind would write it."""
    stu = student_version(instructor)
    by_id = {c.metadata["nbgrader"]["grade_id"]: c for c in instructor.cells if is_solution(c) and c.cell_type == "code"}
    if kind == "stub":
        return stu
    for cell in stu.cells:
        if not (is_solution(cell) and cell.cell_type == "code"):
            continue
        ref = by_id[cell.metadata["nbgrader"]["grade_id"]]
        name, what = _signature(ref.source)
        header = ref.source.split(BEGIN_SOLUTION)[0]          # "def f(...):\n    " or ""
        right = _answer(ref)
        if kind == "correct":
            cell.source = right
        elif kind == "wrong":
            cell.source = header + ("    return 0.0" if what == "def" else f'{name} = "not one of the choices"')
        elif kind == "cheat-abs":
            cell.source = "import builtins\nbuiltins.abs = lambda v: 0.0\n" + (
                header + "    return 0.0" if what == "def" else f'{name} = "?"')
        elif kind == "cheat-numpy":
            cell.source = ("import numpy as np\nnp.isclose = lambda *a, **k: True\nnp.allclose = lambda *a, **k: True\n"
                           + (header + "    return 0.0" if what == "def" else f'{name} = "?"'))
        elif kind == "cheat-traceback":
            cell.source = "get_ipython().showtraceback = lambda *a, **k: None\n" + right
        elif kind == "cheat-own-code":
            cell.source = "import vpr_nb.assignments\nvpr_nb.assignments.assert_own_code = lambda *a, **k: None\n" + right
        elif kind == "crash-exit":
            cell.source = "raise SystemExit(3)" if what == "value" else header + "    raise SystemExit(3)"
        elif kind == "crash-raise":
            cell.source = 'raise RuntimeError("my notebook is broken")\n' + right
        elif kind == "crash-loop":
            cell.source = "while True:\n    pass" if what == "value" else header + "    while True:\n        pass"
        elif kind == "crash-memory":
            hog = "blocks = []\nwhile True:\n    blocks.append(bytearray(2 ** 28))"
            cell.source = hog if what == "value" else header + "\n".join("    " + ln for ln in hog.split("\n"))
        else:
            raise ValueError(f"unknown kind {kind!r}")
    return stu


def expected(instructor, kind: str) -> dict:
    """{exercise id: points} that a submission of ``kind`` must get."""
    out = {}
    for ex in exercise_specs(instructor):
        full = ex.points
        out[ex.id] = full if kind == "correct" else 0.0
    return out


def make_class(instructor_path: Path, folder: Path, students: int) -> dict:
    """Write ``folder/<student>/<notebook>`` for ``students`` students; return {student: (kind, expected)}."""
    instructor = nbformat.read(instructor_path, as_version=4)
    plan = {}
    for k in range(students):
        kind = KINDS[k % len(KINDS)]
        name = f"s{k:03d}_{kind}"
        path = folder / name / instructor_path.name
        path.parent.mkdir(parents=True, exist_ok=True)
        nbformat.write(submission(copy.deepcopy(instructor), kind), path)
        plan[name] = (kind, expected(instructor, kind))
    return plan


def check_csv(csv_path: Path, plan: dict) -> list[str]:
    rows = list(csv.DictReader(csv_path.open()))
    got: dict = {}
    for r in rows:
        got.setdefault(r["student"], {})[r["exercise"]] = (float(r["points"]), r["reason"])
    problems = []
    for student, (kind, want) in plan.items():
        have = {e: p for e, (p, _) in got.get(student, {}).items()}
        if have != want:
            problems.append(f"{student} ({kind}): expected {want}, got {got.get(student)}")
        for e, (p, reason) in got.get(student, {}).items():
            if p == 0.0 and not reason:
                problems.append(f"{student} {e}: a zero without a reason")
    return problems


def grade_class(folder: Path, source_dir: Path, csv_path: Path, jobs: int, timeout: float, sandbox: str | None) -> float:
    cmd = [sys.executable, "-m", "vpr_nb.assignments", "grade-class", str(folder), "--source", str(source_dir),
           "--csv", str(csv_path), "--jobs", str(jobs), "--timeout", str(timeout)]
    if sandbox:
        cmd += ["--sandbox", sandbox]
    if sandbox == "process":        # the bench's own generated submissions: trusted work, graded without bubblewrap
        cmd += ["--trusted"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"grade-class failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    print(proc.stdout.splitlines()[0])                        # the sandbox line
    return seconds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--notebook", default="06", help="NN of the course notebook (default 06)")
    ap.add_argument("--students", type=int, default=50)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=30.0, help="seconds per exercise (the endless loops use it up)")
    ap.add_argument("--sandbox", choices=("bwrap", "process"), default=None)
    ap.add_argument("--quick", action="store_true", help="8 students")
    args = ap.parse_args(argv)
    students = 8 if args.quick else args.students
    source = next(iter(sorted((ROOT / "notebooks").glob(f"{args.notebook}_*.ipynb"))), None)
    if source is None:
        print(f"error: no notebook {args.notebook}_*.ipynb in notebooks/", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="vpr_nb_class_") as tmp:
        tmp = Path(tmp)
        src_dir = tmp / "source"
        src_dir.mkdir()
        (src_dir / source.name).write_bytes(source.read_bytes())
        plan = make_class(source, tmp / "submitted", students)
        kinds = sorted({k for k, _ in plan.values()})
        n_ex = len(next(iter(plan.values()))[1])
        load0 = os.getloadavg()
        seconds = grade_class(tmp / "submitted", src_dir, tmp / "scores.csv", args.jobs, args.timeout, args.sandbox)
        load1 = os.getloadavg()
        problems = check_csv(tmp / "scores.csv", plan)
    print(f"{students} submissions of {source.name} ({n_ex} exercises each; kinds: {', '.join(kinds)}), "
          f"{args.jobs} jobs: {seconds:.0f} s wall, {seconds / students:.1f} s per submission")
    print(f"load average (1, 5, 15 min) before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
          f"after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}; {os.cpu_count()} CPUs")
    if problems:
        print("CSV check FAILED:\n  " + "\n  ".join(problems))
        return 1
    print("CSV check: every student's points are as expected, and every zero has a reason")
    return 0


if __name__ == "__main__":
    sys.exit(main())
