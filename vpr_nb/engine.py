"""Where tasks run: local processes by default, a Dask cluster when given its address; results in the order
given, whatever ran where.

- :class:`LocalEngine` ``(workers)``: one worker runs the tasks in this process, one after another; more run
  them in that many forked processes (:class:`concurrent.futures.ProcessPoolExecutor`). Nothing to start.
- :class:`DaskEngine` ``(address)``: the tasks go to a running Dask distributed scheduler
  (``pip install vpr_nb[cluster]``; docs/reproduction.md says how to start the scheduler and its workers).

:func:`engine_from_env` picks one: ``$VPR_NB_DASK`` (an address such as ``tcp://10.0.0.5:8786``) gives a
:class:`DaskEngine`; otherwise ``$VPR_NB_WORKERS`` local processes (default: the caller's ``workers``).
Both give ``map`` (a round of tasks, results in order) and ``executor()`` (a
:class:`concurrent.futures.Executor` whose ``submit`` returns futures, for a caller that schedules by itself,
e.g. the report starting a notebook when one ends). Every task is seeded on its own, so what an engine returns
does not depend on the engine or on its number of workers; a task that needs pinned kernels calls
:func:`require_kernels` where it runs, so a worker started without them refuses instead of computing other
numbers.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager

from .kernels import NATIVE_ENV, apply_in_process, is_pinned

DASK_ENV = "VPR_NB_DASK"
WORKERS_ENV = "VPR_NB_WORKERS"
TIMES_ENV = "VPR_NB_TASK_TIMES"     # a JSON-lines file: one line per round of tasks (the report sets it)
PROCESS_TOKEN = os.urandom(6).hex()  # marks the rounds this process logs (a run started again logs beside them)


class KernelsNotPinned(RuntimeError):
    """A worker was asked for a pinned task but its process started without the pinned kernels."""


def require_kernels(pinned: bool) -> None:
    """Refuse (:class:`KernelsNotPinned`) to compute a task submitted with pinned kernels in a process that
    does not have them; then set this process's torch to one thread and, when pinned, route convolutions
    around oneDNN and NNPACK (:func:`vpr_nb.kernels.apply_in_process`), as the submitting process does."""
    if pinned and not is_pinned():
        raise KernelsNotPinned(
            "this worker's CPU kernels are not pinned, so it would compute other numbers than the process that "
            "submitted the task; start the worker as `python -m vpr_nb.kernels --run dask worker ADDRESS` "
            "(or set " + NATIVE_ENV + "=1 in the submitting process to use native kernels everywhere)")
    threads = _dask_worker_threads()
    if threads not in (None, 1):
        raise KernelsNotPinned(f"this Dask worker runs {threads} tasks at once in one process, which share its "
                               f"torch and its frozen-block cache; start it with --nthreads 1")
    import torch   # at call time: a worker imports torch only after its environment is set

    torch.set_num_threads(1)
    if pinned:
        apply_in_process()


def _dask_worker_threads() -> int | None:
    """The threads of the Dask worker this runs in, or None outside one."""
    import sys
    if "distributed" not in sys.modules:
        return None
    try:
        return int(sys.modules["distributed"].get_worker().state.nthreads)
    except (ValueError, AttributeError):
        return None


class InlineExecutor(Executor):
    """An executor that runs each submitted call at once, in this process (a one-worker :class:`LocalEngine`)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        """Call ``fn`` with the given arguments now; a finished future holds its result or its error."""
        fut = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:    # noqa: BLE001 - handed to the caller through the future, as a pool does
            fut.set_exception(exc)
        return fut


class LocalEngine:
    """Run tasks here (``workers`` = 1) or in ``workers`` forked processes; results in input order."""

    def __init__(self, workers: int = 1):
        if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.workers = workers

    def __repr__(self) -> str:
        return f"LocalEngine(workers={self.workers})"

    def map(self, fn: Callable, items: Sequence) -> list:
        items = list(items)
        if self.workers == 1 or len(items) <= 1:
            return [fn(x) for x in items]
        with self.executor(min(self.workers, len(items))) as pool:
            return list(pool.map(fn, items))

    @contextmanager
    def executor(self, workers: int | None = None) -> Iterator[Executor]:
        """An executor for ``workers`` (default: the engine's) calls at once: :class:`InlineExecutor` for one,
        else a pool of forked processes."""
        workers = self.workers if workers is None else workers
        if workers == 1:
            yield InlineExecutor()
            return
        if "fork" not in mp.get_all_start_methods():
            raise ValueError(f"{workers} local workers need the 'fork' start method (Linux, macOS); set "
                             f"{WORKERS_ENV}=1 or use a Dask cluster ({DASK_ENV})")
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as pool:
            yield pool


class DaskEngine:
    """Run tasks on the Dask distributed scheduler at ``address`` (or on a ``distributed.Client`` given as
    ``client``); results in input order."""

    def __init__(self, address: str | None = None, *, client=None):
        if client is None:
            if not isinstance(address, str) or not address.strip():
                raise ValueError(f"a Dask scheduler address such as tcp://127.0.0.1:8786, got {address!r}")
            try:
                from distributed import Client   # optional library: pip install vpr_nb[cluster]
            except ImportError:
                raise ValueError(f"{DASK_ENV}={address} asks for a Dask cluster, but dask.distributed is not "
                                 f"installed: pip install 'vpr_nb[cluster]'") from None
            client = Client(address.strip(), set_as_default=False)
        self.client = client

    def __repr__(self) -> str:
        return f"DaskEngine({self.client.scheduler.address})"

    def map(self, fn: Callable, items: Sequence) -> list:
        items = list(items)
        if not items:
            return []
        futures = self.client.map(fn, items, pure=False)
        return self.client.gather(futures)

    @contextmanager
    def executor(self) -> Iterator[Executor]:
        """The cluster as a :class:`concurrent.futures.Executor` (every call run anew, never cached)."""
        with self.client.get_executor(pure=False) as pool:
            yield pool


def log_round(t0: float, t1: float, seconds: Sequence[float], reused: Sequence[bool],
              environ: Mapping | None = None) -> None:
    """Append one round of tasks to ``$VPR_NB_TASK_TIMES`` (nothing when unset): its start and end (epoch seconds)
    and each task's own run time (a reused task: the time it took when it ran), for the report's idle share and
    its simulated schedule (:mod:`vpr_nb.schedule`), marked with this process's :data:`PROCESS_TOKEN`."""
    path = (os.environ if environ is None else environ).get(TIMES_ENV, "").strip()
    if not path:
        return
    line = json.dumps({"t0": round(t0, 3), "t1": round(t1, 3), "seconds": [round(float(x), 3) for x in seconds],
                       "reused": [bool(r) for r in reused], "process": PROCESS_TOKEN})
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(line + "\n")


def timed_map(engine, fn: Callable, items: Sequence) -> list:
    """``engine.map(fn, items)``, logged as one round (:func:`log_round`) from each result's ``seconds`` and
    ``reused``."""
    t0 = time.time()
    results = engine.map(fn, items)
    log_round(t0, time.time(), [getattr(r, "seconds", 0.0) for r in results],
              [getattr(r, "reused", False) for r in results])
    return results


def engine_from_env(workers: int = 1, environ: Mapping | None = None):
    """The engine this process should use: :class:`DaskEngine` at ``$VPR_NB_DASK`` if set, else
    :class:`LocalEngine` with ``$VPR_NB_WORKERS`` workers if set, else ``workers``."""
    env = os.environ if environ is None else environ
    address = env.get(DASK_ENV, "").strip()
    if address:
        return DaskEngine(address)
    text = env.get(WORKERS_ENV, "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise ValueError(f"{WORKERS_ENV} must be a whole number >= 1, got {text!r}")
        workers = int(text)
    return LocalEngine(workers)
