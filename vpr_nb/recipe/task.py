"""One task = one fine-tune: :class:`FineTuneTask`, its key, and :func:`run_task`, which runs it where an engine
puts it and reuses a stored result only when the whole key matches.

A task is a method, the recipe, the training and validation splits, a seed, a learning rate and, for successive
halving's first rung, the epochs after which it stops. Its **key** (:meth:`FineTuneTask.key_parts`) holds:

- the method as data (:meth:`Method.to_dict`) and a digest of its pickled loss and batch source (a sampler's
  settings and images), the recipe's every field, the seed, the lr and the rung;
- a content digest of each split (:func:`split_digest`: every array's bytes, every setting; an on-disk image
  set by its file names, sizes and modification times);
- how the kernels run (pinned or native, and the processor when native), the Python, torch, numpy, scipy and
  faiss versions;
- the package code it runs (:func:`package_digest`): the source of this module, of the modules that define
  the classes and functions inside its method and splits (a sampler, a loss, a split type), of everything
  those import (followed statically, :mod:`vpr_nb.code_digest`) and of the package's data files (its
  weights). A change to one of them re-runs the task; a change to another module (a report, a plot, a
  grader, an experiment that does not build this task's objects) or to a notebook's text changes nothing.

Where it could still miss a change (documented in docs/reproduction.md): code outside the package that a
task calls by name (a function defined in a notebook and passed as a method's batch source pickles as its
name, not its body), code reached without an import statement, libraries other than those named, and files
on disk rewritten with the same size and time. A user notices through ``make reproduce``'s comparison with the
committed numbers, or by running with the store switched off (``STORE=off``), which gives the same bits when
nothing was missed.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import inspect
import os
import pickle
import platform
import sys
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .._checks import check_int, check_positive
from ..code_digest import code_digest, import_graph
from ..engine import require_kernels
from ..feature_cache import FrozenFeatureCache, detach
from ..kernels import cpu_description, is_pinned
from ..task_store import key_digest, store_from_env
from ..training import History, train
from .method import Method, _check_method
from .protocol import Recipe, _check_recipe
from .start import build_start, make_source

KEY_FORMAT = 3                 # 3: the package part covers the code the task runs, by syntax tree


def code_modules(*objects) -> set[str]:
    """The package modules that define the classes and functions found inside ``objects`` (their fields, items,
    attributes, partials' functions and arguments; arrays are not entered), with this module: the starting
    points of :func:`package_digest`."""
    found, seen, todo = {__name__}, set(), list(objects)
    known = import_graph()
    while todo:
        value = todo.pop()
        if value is None or isinstance(value, (bool, int, float, str, bytes, np.ndarray, np.generic, torch.Tensor)):
            continue
        if id(value) in seen:
            continue
        seen.add(id(value))
        for owner in (value, type(value)):
            module = getattr(owner, "__module__", None)
            if isinstance(module, str) and module in known:
                found.add(module)
        if isinstance(value, type):
            continue
        if isinstance(value, dict):
            todo.extend(value.values())
        elif isinstance(value, (list, tuple, set, frozenset)):
            todo.extend(value)
        elif isinstance(value, functools.partial):
            todo.extend([value.func, *value.args, *value.keywords.values()])
        elif hasattr(value, "__self__") and hasattr(value, "__func__"):      # a bound method
            todo.extend([value.__self__, value.__func__])
        elif dataclasses.is_dataclass(value):
            todo.extend(getattr(value, f.name, None) for f in dataclasses.fields(value))
        elif hasattr(value, "__dict__") and not inspect.isroutine(value) and not inspect.ismodule(value):
            todo.extend(vars(value).values())
    return found


def package_digest(modules=(__name__,), root=None) -> str:
    """SHA-256 over the package code that ``modules`` run (:func:`vpr_nb.code_digest.code_digest`: their source,
    what they import, the package's data files). ``root``: a package folder (default: this installed package,
    read once per process: a kernel runs the code it imported until it restarts)."""
    return code_digest(modules, root)


def _value_digest(h, value, seen=None) -> None:
    """Feed ``value`` to the hash ``h`` by content: arrays by their bytes, containers and objects field by field,
    functions and classes by their qualified name; never by an ``id``-bearing ``repr``, so that the same value
    gives the same digest in every process."""
    seen = set() if seen is None else seen
    if isinstance(value, (np.ndarray, torch.Tensor)):
        arr = np.ascontiguousarray(value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value)
        h.update(f"array {arr.dtype.str} {arr.shape}".encode())
        h.update(arr.tobytes())
        return
    if value is None or isinstance(value, (bool, int, float, str, bytes, np.generic)):
        h.update(repr(value).encode())
        return
    if id(value) in seen:
        h.update(b"<cycle>")
        return
    seen.add(id(value))
    if isinstance(value, (list, tuple)):
        h.update(f"seq {len(value)}".encode())
        for v in value:
            _value_digest(h, v, seen)
    elif isinstance(value, (set, frozenset)):
        h.update(f"set {sorted(repr(v) for v in value)}".encode())
    elif isinstance(value, dict):
        h.update(f"dict {len(value)}".encode())
        for k in sorted(value, key=str):
            h.update(repr(k).encode())
            _value_digest(h, value[k], seen)
    elif hasattr(value, "paths") and hasattr(value, "size"):          # an on-disk image set (ImageArray)
        h.update(f"files {value.size}".encode())
        for p in value.paths:
            st = os.stat(p)
            h.update(f"{p} {st.st_size} {st.st_mtime_ns}".encode())
    elif isinstance(value, type) or callable(value) and hasattr(value, "__qualname__"):
        h.update(f"{getattr(value, '__module__', '')}.{value.__qualname__}".encode())
    elif dataclasses.is_dataclass(value):
        h.update(type(value).__qualname__.encode())
        for f in dataclasses.fields(value):
            h.update(f.name.encode())
            _value_digest(h, getattr(value, f.name), seen)
    elif hasattr(value, "__dict__"):
        h.update(type(value).__qualname__.encode())
        _value_digest(h, vars(value), seen)
    elif isinstance(getattr(value, "data", None), np.ndarray):   # a k-d tree: the points it was built on (its
        h.update(type(value).__qualname__.encode())              # pickle holds uninitialised bytes)
        _value_digest(h, value.data, seen)
    else:                      # its pickled state, never its repr (an address)
        try:
            h.update(pickle.dumps(value, protocol=4))
        except Exception:      # noqa: BLE001 - unpicklable: its type is all a key can hold of it
            h.update(type(value).__qualname__.encode())


def split_digest(split) -> str:
    """A content digest of a split: every field (arrays by their bytes), and the class-level settings a split
    type carries (``recall_convention``, regions, paths)."""
    h = hashlib.sha256(type(split).__qualname__.encode())
    names = [f.name for f in dataclasses.fields(split)] if dataclasses.is_dataclass(split) else sorted(vars(split))
    for name in sorted(set(names) | {"recall_convention", "db_region", "q_region", "db_paths", "q_paths"}):
        h.update(name.encode())
        _value_digest(h, getattr(split, name, None))
    return h.hexdigest()


def _object_digest(obj) -> str | None:
    """A content digest of a loss or batch-source object (its settings and arrays; functions by their qualified
    name, :func:`_value_digest`), or None when there is none."""
    if obj is None or isinstance(obj, str):
        return None
    h = hashlib.sha256()
    _value_digest(h, obj)
    return h.hexdigest()


def runtime_parts() -> dict:
    """How this process computes: kernels, library versions (part of every task key)."""
    try:
        import faiss
        faiss_version = getattr(faiss, "__version__", "unknown")
    except ImportError:
        faiss_version = None
    import scipy
    pinned = is_pinned()
    return {"pinned": pinned, "machine": platform.machine(), "cpu": None if pinned else cpu_description(),
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "scipy": scipy.__version__, "faiss": faiss_version}


@dataclass(eq=False)
class FineTuneTask:
    """One fine-tune: ``method`` trained with ``recipe`` on ``train`` at ``lr`` from ``seed``, selected on ``val``;
    ``stop_after`` epochs end it early (successive halving's rung; None: the whole run)."""

    method: Method
    train: object
    val: object
    recipe: Recipe
    seed: int
    lr: float
    stop_after: int | None = None
    pinned: bool = dataclasses.field(default_factory=is_pinned)

    def __post_init__(self):
        self.method, self.recipe = _check_method(self.method), _check_recipe(self.recipe)
        self.seed = check_int(self.seed, "seed", minimum=0)
        self.lr = float(check_positive(self.lr, "lr"))
        if self.stop_after is not None:
            self.stop_after = check_int(self.stop_after, "stop_after")
        self._key = None

    def key_parts(self) -> dict:
        """Everything the result depends on, as plain data (see the module docstring)."""
        return {"format": KEY_FORMAT, "task": "fine-tune",
                "method": self.method.to_dict(), "loss": _object_digest(self.method.loss),
                "batches": _object_digest(self.method.batches),
                "recipe": dataclasses.asdict(self.recipe), "seed": self.seed, "lr": self.lr,
                "stop_after": self.stop_after, "train": split_digest(self.train), "val": split_digest(self.val),
                "runtime": {**runtime_parts(), "pinned": self.pinned},
                "package": package_digest(sorted(code_modules(self.method, self.train, self.val)))}

    def key(self) -> str:
        if self._key is None:
            self._key = key_digest(self.key_parts())
        return self._key

    def label(self) -> str:
        rung = "" if self.stop_after is None else f", first {self.stop_after} epochs"
        return f"{self.method.name}, seed {self.seed}, lr {self.lr:g}{rung}"


@dataclass
class FineTuneResult:
    """One fine-tuning run: ``model`` (the selected weights), its :class:`History`, the ``lr`` it ran at and
    ``start``, the same model before any step (the epoch-0 candidate, for the control of
    :func:`vpr_nb.verdict.control_gate`); ``seconds`` the task took where it ran and whether it came from the
    task store (``reused``)."""

    method: str
    seed: int
    lr: float
    model: torch.nn.Module
    history: History
    start: torch.nn.Module
    search: object = None
    seconds: float = 0.0
    reused: bool = False

    @property
    def best_epoch(self) -> int:
        """The selected epoch, 1-based; 0 = the starting weights won (``history.initial_won``)."""
        return self.history.best_epoch + 1

    @property
    def epochs_run(self) -> int:
        return len(self.history.epochs)


_CACHES: dict[str, FrozenFeatureCache] = {}


def _cache(recipe: Recipe) -> FrozenFeatureCache | None:
    """This process's frozen-block cache (one per storage type, bounded; keyed inside by images and frozen
    weights, so tasks of any world share it safely)."""
    if not recipe.frozen_cache:
        return None
    return _CACHES.setdefault(recipe.cache_dtype, FrozenFeatureCache(recipe.cache_dtype))


def _state_digest(model) -> str:
    h = hashlib.sha256()
    for k, v in model.state_dict().items():
        h.update(k.encode())
        _value_digest(h, v)
    return h.hexdigest()


def _from_entry(task: FineTuneTask, model, start, tensors: dict, data: dict) -> FineTuneResult | None:
    """The stored result of ``task`` on ``model`` (its start), or None with a warning when the entry's weights or
    history do not fit (a store written by other code, or by hand): the task then trains again."""
    fresh = copy.deepcopy(model)
    detach(fresh.backbone)
    try:
        history = History.from_dict(data["history"])
        seconds = float(data["seconds"])
        fresh.load_state_dict(tensors)
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as exc:
        warnings.warn(f"task store: the entry of {task.label()} does not fit this task ({type(exc).__name__}); "
                      f"it trains again", stacklevel=3)
        return None
    return FineTuneResult(task.method.name, task.seed, task.lr, fresh, history, start, seconds=seconds, reused=True)


def _prepare(task: FineTuneTask):
    """What running ``task`` here starts from: ``(store, model, start, start digest, stored result or None)``."""
    if not isinstance(task, FineTuneTask):
        raise ValueError(f"task must be a FineTuneTask, got {type(task).__name__}")
    require_kernels(task.pinned)
    store = store_from_env()
    model = build_start(task.method, task.train, task.recipe, task.seed, _cache(task.recipe))
    start = copy.deepcopy(model)
    detach(start.backbone)
    start_digest = _state_digest(start)
    entry = store.get(task.key()) if store is not None else None
    reused = None
    if entry is not None and entry[1].get("start") == start_digest:
        reused = _from_entry(task, model, start, *entry)
    return store, model, start, start_digest, reused


def _train(task: FineTuneTask, model, *, progress: bool, stop_after: int | None, checkpoint_dir=None) -> History:
    """Train ``model`` (``task``'s start, or resumed from ``checkpoint_dir/last.pt``) for ``stop_after`` epochs of
    this call at most (None: to the end)."""
    try:
        return train(model, make_source(task.method, task.train, task.recipe), task.val,
                     task.recipe.train_config(task.lr, task.seed), progress=progress, stop_after=stop_after,
                     checkpoint_dir=checkpoint_dir, resume=checkpoint_dir is not None)
    finally:
        detach(model.backbone)


def _finish(task: FineTuneTask, store, model, history: History, start, start_digest: str, seconds: float,
            total_seconds: float | None = None) -> FineTuneResult:
    """The result of a trained ``task``, kept in ``store`` (when there is one) with ``total_seconds`` (default:
    ``seconds``), what the whole task took."""
    total = seconds if total_seconds is None else total_seconds
    if store is not None:
        store.put(task.key(), model.state_dict(), {"history": history.to_dict(), "start": start_digest,
                                                   "seconds": round(total, 3), "label": task.label(),
                                                   "python": sys.version.split()[0]})
    return FineTuneResult(task.method.name, task.seed, task.lr, model, history, start, seconds=seconds)


def run_task(task: FineTuneTask, *, progress: bool = False) -> FineTuneResult:
    """Run ``task`` here: from the task store (``$VPR_NB_TASK_STORE``) when it holds this key and the start this
    process builds is the one stored, else by training; a trained result is stored. Refuses to run a task
    submitted with pinned kernels in an unpinned process (:func:`vpr_nb.engine.require_kernels`).
    :func:`vpr_nb.recipe.segments.run_segment` runs it a few epochs at a time, to the same bits."""
    t0 = time.perf_counter()
    store, model, start, start_digest, reused = _prepare(task)
    if reused is not None:
        return reused
    history = _train(task, model, progress=progress, stop_after=task.stop_after)
    return _finish(task, store, model, history, start, start_digest, time.perf_counter() - t0)
