"""Classroom assignments from the course notebooks, with nbgrader's markers.

An exercise is two code cells in an instructor notebook:

* a **solution cell** whose code between ``### BEGIN SOLUTION`` and ``### END SOLUTION`` is the
  answer (metadata ``nbgrader.solution = true``, ``grade_id = "<id>"``);
* a **test cell** right after it (metadata ``nbgrader.grade = true``, ``grade_id = "<id>-tests"``,
  ``points``) with visible asserts and, optionally, asserts between ``### BEGIN HIDDEN TESTS`` and
  ``### END HIDDEN TESTS``.

These are nbgrader's own markers and cell metadata, so nbgrader (``nbgrader generate_assignment``)
and otter users can take the notebooks unchanged. This module is the small stand-alone converter
and grader the course uses (nbgrader itself pulls a database and a server extension):

* ``python -m vpr_nb.assignments generate notebooks assignments`` writes student versions: each
  solution replaced by ``raise NotImplementedError()`` (markdown solutions by "YOUR ANSWER HERE"),
  hidden tests removed, all outputs and execution counts cleared;
* ``python -m vpr_nb.assignments grade STUDENT.ipynb --source notebooks/NN.ipynb`` executes the
  student's notebook with the instructor's test cells (hidden tests included) put back, and prints
  the points of every exercise: a test cell that runs without an error earns its points.
"""
from __future__ import annotations

import argparse
import copy
import sys
from dataclasses import dataclass
from pathlib import Path

import nbformat

BEGIN_SOLUTION, END_SOLUTION = "### BEGIN SOLUTION", "### END SOLUTION"
BEGIN_HIDDEN, END_HIDDEN = "### BEGIN HIDDEN TESTS", "### END HIDDEN TESTS"
CODE_STUB = "raise NotImplementedError()"
MD_STUB = "YOUR ANSWER HERE"


def _meta(cell) -> dict:
    return cell.get("metadata", {}).get("nbgrader", {})


def is_solution(cell) -> bool:
    return bool(_meta(cell).get("solution")) or BEGIN_SOLUTION in cell.source


def is_test(cell) -> bool:
    return cell.cell_type == "code" and bool(_meta(cell).get("grade")) and not _meta(cell).get("solution")


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
    """The student notebook of an instructor notebook (solutions stubbed, hidden tests removed, outputs cleared)."""
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
    return nb


def exercises(nb: nbformat.NotebookNode) -> list[tuple[str, int, float]]:
    """(grade_id, cell index, points) of every test cell."""
    out = []
    for i, cell in enumerate(nb.cells):
        if is_test(cell):
            meta = _meta(cell)
            if "grade_id" not in meta:
                raise ValueError(f"test cell {i} has no nbgrader grade_id")
            out.append((meta["grade_id"], i, float(meta.get("points", 1))))
    return out


def generate(source_dir, out_dir, pattern: str = "[0-9][0-9]_*.ipynb") -> list[Path]:
    """Write the student version of every notebook in ``source_dir`` that has an exercise into ``out_dir``."""
    source_dir, out_dir = Path(source_dir), Path(out_dir)
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


@dataclass
class Grade:
    grade_id: str
    points: float
    max_points: float
    error: str = ""


def grade(student_path, source_path, timeout: int = 600, cwd=None) -> list[Grade]:
    """Execute the student's notebook with the instructor's test cells and score each exercise.

    The student's test cells are matched to the instructor's by ``grade_id`` and replaced by the
    instructor's (so edited or deleted visible tests do not matter and hidden tests run). Every cell
    is executed even after an error; an exercise earns its points when its test cell raises nothing.
    """
    from nbclient import NotebookClient

    student_path, source_path = Path(student_path), Path(source_path)
    for p in (student_path, source_path):
        if not p.is_file():
            raise FileNotFoundError(f"notebook not found: {p}")
    student = nbformat.read(student_path, as_version=4)
    source = nbformat.read(source_path, as_version=4)
    tests = {gid: source.cells[i] for gid, i, _ in exercises(source)}
    if not tests:
        raise ValueError(f"{source_path} has no graded test cells (nbgrader metadata grade=true)")
    seen = set()
    for k, cell in enumerate(student.cells):
        gid = _meta(cell).get("grade_id")
        if is_test(cell) and gid in tests:
            student.cells[k] = copy.deepcopy(tests[gid])
            seen.add(gid)
    missing = sorted(set(tests) - seen)
    if missing:
        raise ValueError(f"{student_path} lacks the test cells {missing}; regenerate it from {source_path}")
    client = NotebookClient(student, timeout=timeout, allow_errors=True, kernel_name="python3",
                            resources={"metadata": {"path": str(cwd or source_path.parent)}})
    client.execute()
    grades = []
    for gid, i, pts in exercises(source):
        k = next(j for j, c in enumerate(student.cells) if _meta(c).get("grade_id") == gid and is_test(c))
        errors = [o for o in student.cells[k].get("outputs", []) if o.get("output_type") == "error"]
        err = f"{errors[0].get('ename')}: {errors[0].get('evalue')}"[:200] if errors else ""
        grades.append(Grade(gid, 0.0 if errors else pts, pts, err))
    return grades


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.assignments", description="student versions and grading")
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write student versions of the notebooks")
    g.add_argument("source_dir", type=Path)
    g.add_argument("out_dir", type=Path)
    r = sub.add_parser("grade", help="grade a student's notebook")
    r.add_argument("student", type=Path)
    r.add_argument("--source", type=Path, required=True, help="the instructor notebook it was generated from")
    r.add_argument("--timeout", type=int, default=600)
    args = ap.parse_args(argv)
    try:
        if args.cmd == "generate":
            for p in generate(args.source_dir, args.out_dir):
                print("wrote", p)
            return 0
        grades = grade(args.student, args.source, args.timeout)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for gr in grades:
        print(f"{gr.grade_id:32s} {gr.points:g} / {gr.max_points:g}" + (f"   ({gr.error})" if gr.error else ""))
    total, best = sum(g.points for g in grades), sum(g.max_points for g in grades)
    print(f"{'total':32s} {total:g} / {best:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
