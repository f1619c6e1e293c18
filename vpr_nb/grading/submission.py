"""Grading one submitted notebook: read it as untrusted bytes, set the sandbox's limits and grade each exercise.

Every exercise is graded on its own (:func:`vpr_nb.grading.exercise.grade_exercise`): one that fails, runs
out of time or memory, or kills its process scores 0 with the reason, and the others are still graded.
Only in the OS sandbox, which hides the instructor's notebook and its folder, unless the teacher says the
work is trusted (:mod:`vpr_nb.grading.isolation`).
"""
from __future__ import annotations

from pathlib import Path

import nbformat

from . import sandbox
from .exercise import Grade, Source, grade_exercise, weigh_choices
from .isolation import choose_backend

DEFAULT_TIMEOUT = 120   # seconds per exercise
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


def limits_for(timeout: float) -> sandbox.Limits:
    """The sandbox's limits for a wall-clock ``timeout`` per exercise (a positive number of seconds)."""
    if not timeout or timeout <= 0:
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    # the wall-clock limit decides; the per-process CPU limit is a backstop a little above it (a process
    # with several busy threads gathers CPU time faster than wall time, and with equal limits an endless
    # loop could end with either message)
    return sandbox.Limits(wall_s=float(timeout), cpu_s=float(timeout) + CPU_MARGIN_S)


def grade(student_path, source_path, timeout: float = DEFAULT_TIMEOUT, only=None, backend: str | None = None,
          source: Source | None = None, trusted: bool = False, private=(), weigh: bool = False) -> list[Grade]:
    """Grade each exercise of a student's notebook against the instructor's.

    For each exercise the grader checks the own-code rule on the submitted solution source, then runs
    the instructor's setup cells (tagged ``grade-deps:<id>``) and the student's solution cell(s) in a
    sandbox (``vpr_nb.grading.sandbox``: a throwaway folder holding only the submission, limits, every
    process killed at the end), calls the student's function there on the instructor's inputs, gets the
    answers back as data and compares them here with the references of the test cell's ``check(...)``
    calls. An exercise earns its points when every case passes; otherwise it scores 0 with the first
    failing case's message, a timeout after ``timeout`` seconds or how the process ended; the other
    exercises are still graded. Each :class:`Grade` also holds its chance score (``chance``: the points a random
    guess earns on average; above 0 only for a choice among stated options).

    Args:
        student_path: the submitted notebook.
        source_path: the instructor notebook it was generated from.
        timeout: wall-clock and CPU seconds per exercise.
        only: grade only these exercise ids or test grade_ids (default: all).
        backend: ``"bwrap"`` or ``"process"`` (default: ``$VPR_NB_SANDBOX``, else ``"bwrap"``).
        source: the instructor notebook already read (``grade_class`` reads each one once).
        trusted: the teacher trusts this work: without a working bubblewrap it is graded without an OS
            sandbox (the ``process`` backend; each :class:`Grade` says so in ``backend``) instead of refused.
        private: more of the teacher's paths the sandbox must hide (``grade_class``: the class folder and the
            grades file's folder); the instructor notebook and its folder always are.
        weigh: a choice among k options is worth ``1 - 1/k`` of its points (:func:`~vpr_nb.grading.exercise.weigh_choices`);
            default: the points of the notebook's metadata, as nbgrader gives them.

    Raises:
        vpr_nb.grading.isolation.NoSandboxError: no OS sandbox works here and ``trusted`` is false (or
            ``backend="process"`` without ``trusted``); nothing is graded.
    """
    student_path = Path(student_path)
    limits = limits_for(timeout)
    source = source or Source.read(source_path)
    specs = weigh_choices(source.exercises) if weigh else source.exercises
    if only is not None:
        only = set(only)
        specs = [e for e in specs if e.grade_id in only or e.id in only]
        if not specs:
            raise ValueError(f"none of {sorted(only)} is an exercise of {source.path}")
    student, raw = _read_submission(student_path)
    backend = choose_backend(backend, trusted)
    private = (source.path, source.path.parent, *private)
    if backend == "bwrap":
        sandbox.check_private(private)
    return [grade_exercise(ex, student, raw, limits, backend, trusted, private) for ex in specs]
