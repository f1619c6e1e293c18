"""Classroom assignments from the course notebooks, with nbgrader's markers.

An exercise is cells of an instructor notebook marked with nbgrader's cell metadata:

* a **solution cell** whose code between ``### BEGIN SOLUTION`` and ``### END SOLUTION`` is the
  answer (metadata ``nbgrader.solution = true``, ``grade_id = "<id>"``);
* a **test cell** after it (metadata ``nbgrader.grade = true``, ``grade_id = "<id>-tests"``,
  ``points``) with visible asserts and, optionally, asserts between ``### BEGIN HIDDEN TESTS`` and
  ``### END HIDDEN TESTS``; every assert carries a message saying what was expected and what came out;
* its **dependencies**: the read-only cells the solution and the tests need (imports, parameters), each
  tagged ``grade-deps:<id>``. Grading an exercise runs only these cells, the student's solution cell(s)
  and the instructor's test cell, in a fresh kernel; an exercise without such tags runs every cell above
  its test cell.

These are nbgrader's own markers and cell metadata, so nbgrader (``nbgrader generate_assignment``)
and otter users can take the notebooks unchanged. This module is the small stand-alone converter
and grader the course uses (nbgrader itself pulls a database and a server extension):

* ``python -m vpr_nb.assignments generate notebooks assignments`` writes student versions: each
  solution replaced by ``raise NotImplementedError()`` (markdown solutions by "YOUR ANSWER HERE"),
  hidden tests removed, all outputs and execution counts cleared, test cells and read-only cells
  locked (``editable: false``, ``deletable: false``, as nbgrader does);
* ``python -m vpr_nb.assignments grade STUDENT.ipynb --source notebooks/NN.ipynb`` grades one
  submission and prints the points of every exercise, with the failing assertion's message;
* ``python -m vpr_nb.assignments grade-class SUBMISSIONS/ --source notebooks/ --csv scores.csv``
  grades every ``SUBMISSIONS/<student>/**/NN_*.ipynb`` and writes one CSV row per student and exercise.

One exercise that fails, loops (``--timeout`` seconds per exercise) or kills its kernel scores 0 with
the reason; the other exercises are still graded, each in its own kernel.

Hidden tests use :func:`assert_own_code` to reject an answer that calls into ``vpr_nb`` where the
exercise is to write the computation.
"""
from __future__ import annotations

import argparse
import copy
import csv
import functools
import inspect
import math
import sys
import time
import types
from dataclasses import dataclass
from pathlib import Path

import nbformat

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
    cleared, test cells and read-only cells (nbgrader ``locked`` or ``grade-deps`` tagged) locked."""
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
        if not is_solution(cell) and (is_test(cell) or _meta(cell).get("locked") or deps_of(cell)):
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
# hidden-test helper: an answer must not call into the library


def library_references(fn, package: str = "vpr_nb", forbid_names=()) -> list[str]:
    """How a function written in a notebook reaches ``package`` (or one of ``forbid_names``).

    Follows the function's code (nested functions and lambdas included), the globals it names, its
    closure and default arguments, and recursively every helper function or class defined in the
    notebook (module ``__main__``); reports each module, function, class or object of ``package`` it
    reaches, an ``import`` of it, a string naming it, and every name in ``forbid_names`` it uses.
    """
    if not callable(fn):
        raise ValueError(f"library_references needs a function, got {type(fn).__name__}")
    found, seen = [], set()

    def of_package(obj) -> str | None:
        mod = obj.__name__ if isinstance(obj, types.ModuleType) else getattr(obj, "__module__", None)
        if not isinstance(mod, str) and not isinstance(obj, (type, types.FunctionType)):
            mod = getattr(type(obj), "__module__", None)
        if isinstance(mod, str) and (mod == package or mod.startswith(package + ".")):
            return mod
        return None

    def visit_code(code, globs, owner):
        for name in code.co_names:
            if name == package or name.startswith(package + ".") or name in forbid_names:
                found.append(f"{owner} uses {name!r}")
            elif name in globs:
                visit_obj(globs[name], name, owner)
        for const in code.co_consts:
            if isinstance(const, types.CodeType):
                visit_code(const, globs, owner)
            elif isinstance(const, str) and package in const:
                found.append(f"{owner} names {package!r} in the string {const[:40]!r}")

    def visit_obj(obj, name, owner):
        if id(obj) in seen:
            return
        seen.add(id(obj))
        mod = of_package(obj)
        if mod is not None:
            found.append(f"{owner} uses {name} (from {mod})")
        elif isinstance(obj, types.FunctionType) and obj.__module__ == "__main__":
            visit_function(obj)
        elif isinstance(obj, functools.partial):
            visit_obj(obj.func, name, owner)
        elif isinstance(obj, type) and obj.__module__ == "__main__":
            for attr, value in vars(obj).items():
                visit_obj(value, f"{obj.__name__}.{attr}", obj.__name__)
            for base in obj.__mro__[1:]:
                visit_obj(base, base.__name__, obj.__name__)

    def visit_function(f):
        f = inspect.unwrap(f)
        if isinstance(f, (types.MethodType, staticmethod, classmethod)):
            f = f.__func__
        if not isinstance(f, types.FunctionType):
            return
        owner = f.__name__
        visit_code(f.__code__, f.__globals__, owner)
        for cell in f.__closure__ or ():
            try:
                visit_obj(cell.cell_contents, "a closure variable", owner)
            except ValueError:            # an empty cell
                pass
        for value in (f.__defaults__ or ()) + tuple((f.__kwdefaults__ or {}).values()):
            visit_obj(value, "a default argument", owner)

    seen.add(id(fn))
    if of_package(fn) is not None:
        return [f"{getattr(fn, '__name__', fn)!s} is {of_package(fn)}'s own"]
    visit_function(fn)
    return found


def assert_own_code(fn, package: str = "vpr_nb", forbid_names=()) -> None:
    """Hidden-test check: ``fn`` computes its answer itself, without calling into ``package``.

    Raises:
        AssertionError: naming what the answer uses, with the fix.
    """
    refs = library_references(fn, package, forbid_names)
    name = getattr(fn, "__name__", "the answer")
    assert not refs, (f"{name} must compute its result itself (plain Python, numpy or torch), but "
                      + "; ".join(dict.fromkeys(refs)) + f"; remove the use of {package}"
                      + (f" and of {', '.join(forbid_names)}" if forbid_names else ""))


# ---------------------------------------------------------------------------------------------------
# grading


@dataclass
class Grade:
    grade_id: str
    points: float
    max_points: float
    error: str = ""
    seconds: float = 0.0


def _error_text(cell, limit: int = 600) -> str:
    for o in cell.get("outputs", []):
        if o.get("output_type") == "error":
            if o.get("ename") == "NotImplementedError" and not o.get("evalue"):
                return "NotImplementedError: the answer is not written yet (the solution cell still raises the stub)"
            text = f"{o.get('ename')}: {o.get('evalue')}".strip()
            return text if len(text) <= limit else text[: limit - 3] + "..."
    return ""


def _exercise_cells(student, source, test_index: int, ex_id: str) -> tuple[list, list[str], str]:
    """The cells that grade one exercise, their roles, and a note for the report ('' or why it fails)."""
    test_cell = copy.deepcopy(source.cells[test_index])
    deps = [i for i, c in enumerate(source.cells[:test_index]) if ex_id in deps_of(c)]
    solutions = [copy.deepcopy(c) for c in student.cells
                 if is_solution(c) and c.cell_type == "code" and _meta(c).get("grade_id") == ex_id]
    if not deps:                       # untagged: every cell above the test cell, as the student left them
        gid = _meta(test_cell).get("grade_id")
        k = next((j for j, c in enumerate(student.cells) if is_test(c) and _meta(c).get("grade_id") == gid), None)
        if k is None:
            return [], [], f"the test cell {gid!r} was deleted from the submission and the exercise has no grade-deps"
        cells = [copy.deepcopy(c) for c in student.cells[:k] if not is_test(c)]
        return cells + [test_cell], ["cell"] * len(cells) + ["test"], ""
    if not solutions:
        return [], [], f"the solution cell {ex_id!r} is missing from the submission"
    cells = [copy.deepcopy(source.cells[i]) for i in deps] + solutions + [test_cell]
    return cells, ["dependency"] * len(deps) + ["solution"] * len(solutions) + ["test"], ""


def _run_exercise(cells, roles, kernel_name: str, timeout: float, cwd: Path) -> tuple[bool, str]:
    """Execute ``cells`` in a fresh kernel; (passed, reason)."""
    from nbclient import NotebookClient
    from nbclient.exceptions import CellTimeoutError, DeadKernelError

    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": kernel_name, "display_name": kernel_name, "language": "python"}
    nb.cells = cells
    for c in nb.cells:
        if c.cell_type == "code":
            c.outputs, c.execution_count = [], None
    client = NotebookClient(nb, timeout=max(1, int(math.ceil(timeout))), allow_errors=True,
                            kernel_name=kernel_name, resources={"metadata": {"path": str(cwd)}})
    start = time.monotonic()
    try:
        with client.setup_kernel():
            for i, cell in enumerate(nb.cells):
                if cell.cell_type != "code":
                    continue
                remaining = timeout - (time.monotonic() - start)
                if remaining <= 0:
                    raise CellTimeoutError("out of time")
                client.timeout = max(1, int(math.ceil(remaining)))
                client.execute_cell(cell, i)
    except CellTimeoutError:
        return False, f"timed out after {timeout:g} s (an endless loop? the exercise's limit is {timeout:g} s)"
    except DeadKernelError:
        return False, "the kernel died while running this exercise (DeadKernelError); it was restarted for the next one"
    except Exception as err:  # a kernel that does not start, a broken cell: this exercise only
        return False, f"grading failed: {type(err).__name__}: {err}"[:600]
    for cell, role in zip(nb.cells, roles):
        err = _error_text(cell)
        if err and role != "test":
            what = {"dependency": "a read-only cell it depends on", "solution": "your solution cell",
                    "cell": "a cell above the tests"}[role]
            return False, f"{what} raised {err}"
        if err:
            return False, err
    return True, ""


def grade(student_path, source_path, timeout: float = DEFAULT_TIMEOUT, cwd=None, only=None) -> list[Grade]:
    """Grade each exercise of a student's notebook against the instructor's.

    Each exercise runs in a fresh kernel: the instructor's cells tagged ``grade-deps:<id>``, the
    student's solution cell(s) of that id and the instructor's test cell (hidden tests included), so an
    edited or deleted test cell changes nothing. An exercise earns its points when nothing raises;
    otherwise it scores 0 with the reason (the failing assertion's message, a timeout after ``timeout``
    seconds, a dead kernel); the other exercises are still graded.

    Args:
        student_path: the submitted notebook.
        source_path: the instructor notebook it was generated from.
        timeout: seconds per exercise (all its cells together).
        cwd: working directory of the kernel (default: the instructor notebook's folder).
        only: grade only these exercise ids or test grade_ids (default: all).
    """
    student_path, source_path = Path(student_path), Path(source_path)
    for p in (student_path, source_path):
        if not p.is_file():
            raise FileNotFoundError(f"notebook not found: {p}")
    if not timeout or timeout <= 0:
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    try:
        student = nbformat.read(student_path, as_version=4)
    except Exception as err:
        raise ValueError(f"cannot read the submission {student_path} as a notebook ({err}); "
                         "ask the student to re-save it from JupyterLab") from err
    source = nbformat.read(source_path, as_version=4)
    tests = exercises(source)
    if not tests:
        raise ValueError(f"{source_path} has no graded test cells (nbgrader metadata grade=true)")
    if only is not None:
        only = set(only)
        tests = [t for t in tests if t[0] in only or exercise_id(t[0]) in only]
        if not tests:
            raise ValueError(f"none of {sorted(only)} is an exercise of {source_path}")
    kernel = source.metadata.get("kernelspec", {}).get("name", "python3")
    grades = []
    for gid, i, pts in tests:
        start = time.monotonic()
        cells, roles, note = _exercise_cells(student, source, i, exercise_id(gid))
        ok, reason = (False, note) if note else _run_exercise(cells, roles, kernel, timeout,
                                                              Path(cwd or source_path.parent))
        grades.append(Grade(gid, pts if ok else 0.0, pts, reason, round(time.monotonic() - start, 1)))
    return grades


def _student_notebooks(folder: Path, names: set[str]):
    """(student, notebook path) of every submission: ``folder/<student>/**/<name>``."""
    for student in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for path in sorted(student.rglob("*.ipynb")):
            if path.name in names and ".ipynb_checkpoints" not in path.parts:
                yield student.name, path


def grade_class(folder, source_dir, csv_path=None, timeout: float = DEFAULT_TIMEOUT, log=print) -> list[dict]:
    """Grade every submission under ``folder/<student>/`` against the notebooks of ``source_dir``.

    Returns one row per student, notebook and exercise (``student, notebook, exercise, points,
    max_points, seconds, reason``) and writes them to ``csv_path`` when given. A submission that cannot
    be read scores 0 on each of its exercises, with the reason.
    """
    folder, source_dir = Path(folder), Path(source_dir)
    for p in (folder, source_dir):
        if not p.is_dir():
            raise FileNotFoundError(f"folder not found: {p}")
    sources = {p.name: p for p in sorted(source_dir.glob("*.ipynb"))
               if exercises(nbformat.read(p, as_version=4))}
    if not sources:
        raise FileNotFoundError(f"no instructor notebook with graded exercises in {source_dir}")
    subs = list(_student_notebooks(folder, set(sources)))
    if not subs:
        raise FileNotFoundError(f"no submissions in {folder}: expected {folder}/<student>/<notebook>.ipynb "
                                f"named as one of {sorted(sources)}")
    rows = []
    for student, path in subs:
        src = sources[path.name]
        try:
            grades = grade(path, src, timeout=timeout)
        except (ValueError, FileNotFoundError) as err:
            grades = [Grade(gid, 0.0, pts, str(err)[:600]) for gid, _, pts in
                      exercises(nbformat.read(src, as_version=4))]
        for g in grades:
            rows.append({"student": student, "notebook": path.name, "exercise": exercise_id(g.grade_id),
                         "points": g.points, "max_points": g.max_points, "seconds": g.seconds, "reason": g.error})
            log(f"{student:20s} {exercise_id(g.grade_id):24s} {g.points:g} / {g.max_points:g}  ({g.seconds:.1f} s)"
                + (f"   {g.error}" if g.error else ""))
    if csv_path is not None:
        csv_path = Path(csv_path)
        csv_path.parent.mkdir(parents=True, exist_ok=True)
        with open(csv_path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.assignments", description="student versions and grading")
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write student versions of the notebooks")
    g.add_argument("source_dir", type=Path)
    g.add_argument("out_dir", type=Path)
    r = sub.add_parser("grade", help="grade a student's notebook")
    r.add_argument("student", type=Path)
    r.add_argument("--source", type=Path, required=True, help="the instructor notebook it was generated from")
    r.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="seconds per exercise")
    c = sub.add_parser("grade-class", help="grade every FOLDER/<student>/**/NN_*.ipynb, write a CSV")
    c.add_argument("folder", type=Path)
    c.add_argument("--source", type=Path, required=True, help="the folder of instructor notebooks")
    c.add_argument("--csv", type=Path, default=Path("scores.csv"))
    c.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="seconds per exercise")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "generate":
            for p in generate(args.source_dir, args.out_dir):
                print("wrote", p)
            return 0
        if args.cmd == "grade-class":
            rows = grade_class(args.folder, args.source, args.csv, args.timeout)
            total = sum(r["points"] for r in rows)
            print(f"{len({r['student'] for r in rows})} students, {len(rows)} exercises graded, "
                  f"{total:g} points in all; wrote {args.csv}")
            return 0
        grades = grade(args.student, args.source, args.timeout)
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
