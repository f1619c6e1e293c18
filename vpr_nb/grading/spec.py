"""How a test cell declares what the grader checks: :class:`Case` and :func:`check`.

A test cell (nbgrader ``grade: true``) imports what it needs, builds the instructor's inputs and calls
:func:`check` with the name of the student's function and the cases, visible ones above ``### BEGIN
HIDDEN TESTS`` and hidden ones below it::

    import torch
    from vpr_nb.assignments import Case, check

    check("square", [Case("square(3)", (3,), expect=9)])
    ### BEGIN HIDDEN TESTS
    check("square", [Case("square(-2)", (-2,), expect=4)])
    ### END HIDDEN TESTS

In a kernel (the student's own run, the instructor's notebook under nbval, nbgrader's autograde)
:func:`check` calls the function there and asserts. The course grader instead runs the whole test cell
in the trusted grader process with :func:`collect`, where :func:`check` only records the cases: the
inputs go to the sandboxed student process as data, the answers come back as data (``vpr_nb.grading.data``)
and are compared here, so nothing the student's process does can change a verdict.

A case's ``rubric`` is a function of the decoded answer, run in the grader, returning ``None`` when it
passes or the feedback; use it for answers that a tolerance does not express (a direction, a choice, a
range, a prediction within a band of the measured value).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Any, Callable

from .data import DataError, compare, encode, roundtrip
from .owncode import assert_own_code

NO_EXPECT = object()


@dataclass
class Case:
    """One call of the student's function and what it must return.

    Args:
        name: what the feedback calls it, e.g. ``"square(3)"`` or ``"5 queries x 2 negatives, margin 2"``.
        args, kwargs: the inputs (data only: numbers, strings, lists, dicts, numpy arrays, torch tensors).
        expect: the reference answer (data only; omit it when ``rubric`` alone decides).
        atol, rtol: tolerance for numbers: ``|got - expect| <= atol + rtol * |expect|``.
        rubric: ``rubric(answer) -> None | str``, run by the grader on the decoded answer.
    """
    name: str
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    expect: Any = NO_EXPECT
    atol: float = 1e-6
    rtol: float = 1e-6
    rubric: Callable[[Any], str | None] | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("a Case needs a name (what the feedback calls it)")
        if not isinstance(self.args, (tuple, list)) or not isinstance(self.kwargs, dict):
            raise ValueError(f"case {self.name!r}: args must be a tuple and kwargs a dict")
        if self.expect is NO_EXPECT and self.rubric is None:
            raise ValueError(f"case {self.name!r}: give expect= (the reference) or rubric= (a check of the answer)")
        if not (self.atol >= 0 and self.rtol >= 0) or math.isnan(self.atol + self.rtol):
            raise ValueError(f"case {self.name!r}: atol and rtol must be >= 0")
        try:
            encode((tuple(self.args), self.kwargs))
            if self.expect is not NO_EXPECT:
                self.expect = roundtrip(self.expect)     # as the grader will hold it: tensors as TensorValue
        except DataError as err:
            raise ValueError(f"case {self.name!r}: its inputs and reference must be data, but one is {err}") from err

    def verdict(self, answer) -> str | None:
        """None when the decoded ``answer`` passes, else the feedback (prefixed by the case's name)."""
        if self.expect is not NO_EXPECT:
            msg = compare(answer, self.expect, self.atol, self.rtol)
            if msg:
                return f"{self.name}: {msg}"
        if self.rubric is not None:
            try:
                msg = self.rubric(answer)
            except Exception as err:          # an answer of an unexpected shape: say so, do not crash
                msg = f"the answer {answer!r:.80} could not be checked ({type(err).__name__}: {err})"
            if msg:
                return f"{self.name}: {msg}"
        return None


def one_of(*choices: str) -> Callable[[Any], str | None]:
    """A rubric for a prediction: the answer must be one of ``choices`` (exactly, as strings).

    The rubric keeps the choices (``rubric.choices``), so the grader knows what a guess at random among them
    earns (:func:`guess_chance`)."""
    if not choices or not all(isinstance(c, str) for c in choices):
        raise ValueError(f"one_of needs the choices as strings, got {choices!r}")
    if len(set(choices)) != len(choices):
        raise ValueError(f"one_of: a choice is listed twice in {choices!r}")

    def rubric(answer):
        return None if answer in choices else f"expected one of {', '.join(map(repr, choices))}, got {answer!r:.80}"
    rubric.choices = tuple(choices)
    return rubric


def guess_chance(checks: list["Check"]) -> float:
    """The probability that answering at random passes every check of one exercise.

    A value (``call=False``) whose cases state its choices (:func:`one_of`; the fewest, where several do) is
    guessed uniformly among them and passes with the share of choices that pass all its cases: 1/k for a
    choice among k with one right answer. A function to write, or a free answer, is taken as never guessed
    (0). An exercise of several values: the product."""
    if not checks or any(c.call for c in checks):
        return 0.0
    chance = 1.0
    for name in dict.fromkeys(c.function for c in checks):
        cases = [case for c in checks if c.function == name for case in c.cases]
        stated = [set(case.rubric.choices) for case in cases if hasattr(case.rubric, "choices")]
        if not stated:
            return 0.0
        choices = sorted(min(stated, key=len))          # the fewest the student is offered
        chance *= sum(all(case.verdict(c) is None for case in cases) for c in choices) / len(choices)
    return chance


@dataclass
class Check:
    """The cases of one name of the student's solution (a function to call, or a value to read)."""
    function: str
    cases: list[Case]
    own_code: bool = True
    forbid: tuple[str, ...] = ()
    call: bool = True


_collecting: list[Check] | None = None


def check(function: str, cases, *, own_code: bool = True, forbid=(), call: bool = True) -> None:
    """Declare (grader) or run (kernel) the cases of the student's ``function``.

    Args:
        function: the name the solution cell defines.
        cases: a list of :class:`Case`.
        own_code: the answer must not use ``vpr_nb`` (checked on the submitted source by the grader).
        forbid: further names the answer must not use (e.g. ``("TripletMarginLoss",)``).
        call: False when ``function`` names a value (a prediction, a choice) rather than a function; its
            cases then have no inputs and check the value itself.
    """
    if not isinstance(function, str) or not function.isidentifier():
        raise ValueError(f"check needs the name of the student's function as a string, got {function!r}")
    cases = list(cases)
    if not cases or not all(isinstance(c, Case) for c in cases):
        raise ValueError(f"check({function!r}, ...) needs a non-empty list of Case")
    if not call and any(c.args or c.kwargs for c in cases):
        raise ValueError(f"check({function!r}, call=False): the cases of a value take no inputs")
    spec = Check(function, cases, bool(own_code), tuple(forbid), bool(call))
    if _collecting is not None:
        _collecting.append(spec)
        return
    _run_in_kernel(spec, sys._getframe(1).f_globals)


def _run_in_kernel(spec: Check, namespace: dict) -> None:
    if spec.function not in namespace:
        raise AssertionError(f"{spec.function} is not defined: run your solution cell first")
    target = namespace[spec.function]
    if spec.own_code and spec.call:
        assert_own_code(target, forbid_names=spec.forbid)
    for case in spec.cases:
        value = target(*case.args, **case.kwargs) if spec.call else target
        try:
            answer = roundtrip(value)
        except DataError as err:
            raise AssertionError(f"{case.name}: {spec.function} gave {err}") from None
        msg = case.verdict(answer)
        assert msg is None, msg


def collect(source: str, where: str = "a test cell") -> list[Check]:
    """The checks a test cell declares, by running it (trusted instructor code) with :func:`check` recording.

    Raises:
        ValueError: the cell fails, calls the student's code directly, or declares no check.
    """
    global _collecting
    previous, _collecting = _collecting, []
    try:
        namespace = {"__name__": "__vpr_nb_grading__"}
        exec(compile(source, where, "exec"), namespace)
        found = _collecting
    except NameError as err:
        raise ValueError(f"{where} uses {err.name!r}, which it does not define: a test cell imports what it "
                         "needs itself and reaches the student's answer only through check(...)") from err
    except Exception as err:
        raise ValueError(f"{where} fails when the grader builds its cases: {type(err).__name__}: {err}") from err
    finally:
        _collecting = previous
    if not found:
        raise ValueError(f"{where} declares no check(...): the grader runs the student's code only through "
                         "check(function_name, [Case(...), ...]) (see vpr_nb.grading.spec)")
    return found
