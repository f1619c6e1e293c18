"""A fine-tune run a few epochs at a time: every task of a round is a **segment** of at most
:data:`SEGMENT_EPOCHS` epochs, so no task holds a worker for long, and a run killed part-way loses at most one
segment of each fine-tune.

:func:`run_segment` trains one segment of a :class:`~vpr_nb.recipe.task.FineTuneTask` and returns either its
:class:`~vpr_nb.recipe.task.FineTuneResult` (the fine-tune ended: its epochs are done or patience stopped it) or
a :class:`Segment` that carries the training state (the bytes of ``last.pt``,
:func:`vpr_nb.training.checkpoints.training_state`) to the next one, which may run on another worker.
:func:`run_round` runs a round of tasks segment by segment on an engine, each segment round logged
(:func:`vpr_nb.engine.timed_map`). The training loop's exact resume (:func:`vpr_nb.training.train`,
``tests/test_training.py``) makes a segmented fine-tune the same bits as one run whole
(``tests/test_segments.py``), so the task's key and its stored result are the same either way.

With a task store (``$VPR_NB_TASK_STORE``) each segment's state is also kept under the task's **partial key**
(:func:`partial_key`), and a fine-tune started again (a run killed and restarted) goes on from it. A partial
entry is read like any other (its bytes' SHA-256, ``weights_only=True``); one that does not resume (written by
other code) is set aside with a warning and the fine-tune starts from the beginning.
"""
from __future__ import annotations

import functools
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from .._checks import check_int
from ..engine import timed_map
from ..task_store import key_digest
from .task import FineTuneResult, FineTuneTask, _finish, _prepare, _train, run_task

SEGMENT_EPOCHS = 10    # a course epoch takes up to about 25 s on one core (07's longest task: 44 epochs, 17.9 min)


@dataclass(eq=False)
class Segment:
    """``task`` after ``epochs`` epochs: ``state`` the bytes of its ``last.pt``; ``seconds`` the segment that
    ended here took, ``total`` all its segments so far."""

    task: FineTuneTask
    state: bytes | None = None
    epochs: int = 0
    seconds: float = 0.0
    total: float = 0.0
    reused: bool = False


def partial_key(task: FineTuneTask) -> str:
    """The task store key of ``task``'s latest segment (its own key, marked)."""
    return key_digest({"partial of": task.key()})


def _stored_state(store, task: FineTuneTask, start_digest: str) -> Segment | None:
    got = store.get(partial_key(task), warn=False) if store is not None else None
    if got is None:
        return None
    tensors, data = got
    try:
        state = tensors["last"]
        if state.dtype != torch.uint8 or state.dim() != 1 or data.get("start") != start_digest:
            return None
        return Segment(task, state.numpy().tobytes(), int(data["epochs"]), 0.0, float(data["seconds"]))
    except (KeyError, TypeError, ValueError):
        return None


def run_segment(item: FineTuneTask | Segment, *, epochs: int = SEGMENT_EPOCHS) -> FineTuneResult | Segment:
    """Train the next ``epochs`` epochs (at most) of ``item``: a task (from its start, or from its stored partial
    state) or the :class:`Segment` an earlier call returned. Returns the task's result when it has ended, else
    the :class:`Segment` to continue; a finished task is stored as :func:`~vpr_nb.recipe.task.run_task` stores
    it, and a stored one is returned without training."""
    epochs = check_int(epochs, "epochs", minimum=1)
    if not isinstance(item, (FineTuneTask, Segment)):
        raise ValueError(f"item must be a FineTuneTask or a Segment, got {type(item).__name__}")
    task = item.task if isinstance(item, Segment) else item
    t0 = time.perf_counter()
    store, model, start, start_digest, reused = _prepare(task)
    if reused is not None:
        return reused
    seg = item if isinstance(item, Segment) else (_stored_state(store, task, start_digest) or Segment(task))
    limit = task.stop_after or task.recipe.max_epochs
    if seg.state is None and epochs >= limit:          # one segment holds the whole task: no state to keep
        history = _train(task, model, progress=False, stop_after=task.stop_after)
        return _finish(task, store, model, history, start, start_digest, time.perf_counter() - t0)
    with tempfile.TemporaryDirectory(prefix="vpr_nb-segment-") as tmp:
        if seg.state is not None:
            (Path(tmp) / "last.pt").write_bytes(seg.state)
        try:
            history = _train(task, model, progress=False, stop_after=min(epochs, max(limit - seg.epochs, 1)),
                             checkpoint_dir=tmp)
        except ValueError as exc:
            if isinstance(item, Segment) or seg.state is None:
                raise
            warnings.warn(f"task store: the partial state of {task.label()} does not resume ({exc}); it trains "
                          f"from its start", stacklevel=2)
            store.put(partial_key(task), {}, {"set aside": str(exc)[:200]})
            return run_segment(task, epochs=epochs)
        done, seconds = len(history.epochs), time.perf_counter() - t0
        if history.stopped_early or done >= limit:
            return _finish(task, store, model, history, start, start_digest, seconds, seg.total + seconds)
        state = (Path(tmp) / "last.pt").read_bytes()
    if store is not None:
        store.put(partial_key(task), {"last": torch.frombuffer(bytearray(state), dtype=torch.uint8)},
                  {"epochs": done, "seconds": round(seg.total + seconds, 3), "start": start_digest,
                   "label": task.label()})
    return Segment(task, state, done, seconds, seg.total + seconds)


def run_round(engine, tasks, segment_epochs: int | None = SEGMENT_EPOCHS) -> list[FineTuneResult]:
    """Run ``tasks`` on ``engine`` and return their results in order: whole (``segment_epochs=None``, one logged
    round) or in segments of ``segment_epochs`` epochs, one logged round per segment, each round holding the
    tasks not yet ended."""
    tasks = list(tasks)
    if segment_epochs is None:
        return timed_map(engine, run_task, tasks)
    fn = functools.partial(run_segment, epochs=check_int(segment_epochs, "segment_epochs", minimum=1))
    items: list = list(tasks)
    out: list = [None] * len(tasks)
    todo = list(range(len(tasks)))
    while todo:
        got = timed_map(engine, fn, [items[i] for i in todo])
        left = []
        for i, r in zip(todo, got):
            if isinstance(r, Segment):
                items[i] = r
                left.append(i)
            else:
                out[i] = r
        todo = left
    return out
