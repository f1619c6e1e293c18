"""Fine-tuning runs of a method and the choice of its learning rate on validation, one method or many in parallel."""
from __future__ import annotations

import copy
import dataclasses
import math
import multiprocessing as mp
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .._checks import check_int, check_positive
from ..feature_cache import FrozenFeatureCache, detach
from ..training import History, train
from .method import Method, _check_method
from .protocol import RECIPE, Recipe, _check_recipe
from .start import build_start, make_source


@dataclass
class FineTuneResult:
    """One fine-tuning run: ``model`` (the selected weights), its :class:`History`, the ``lr`` it ran at and
    ``start``, the same model before any step (the epoch-0 candidate, for the control of
    :func:`vpr_nb.results.gated_verdict`)."""

    method: str
    seed: int
    lr: float
    model: torch.nn.Module
    history: History
    start: torch.nn.Module
    search: "LRSearch | None" = None

    @property
    def best_epoch(self) -> int:
        """The selected epoch, 1-based; 0 = the starting weights won (``history.initial_won``)."""
        return self.history.best_epoch + 1

    @property
    def epochs_run(self) -> int:
        return len(self.history.epochs)


def _run(method, train_split, val_split, recipe, seed, lr, cache, progress, checkpoint_dir=None,
         stop_after=None) -> FineTuneResult:
    """One run; with ``checkpoint_dir`` it continues the run saved there (``train``'s resume, the same weights as
    an uninterrupted run) and ``stop_after`` epochs of this call end it early (successive halving's rung)."""
    model = build_start(method, train_split, recipe, seed, cache)
    start = copy.deepcopy(model)
    detach(start.backbone)
    try:
        history = train(model, make_source(method, train_split, recipe), val_split, recipe.train_config(lr, seed),
                        progress=progress, checkpoint_dir=checkpoint_dir, stop_after=stop_after)
    finally:
        detach(model.backbone)
    return FineTuneResult(method.name, seed, float(lr), model, history, start)


def ladder_step(lr: float, up: bool) -> float:
    """The next learning rate above (``up``) or below ``lr`` on the 1-3 ladder ..., 1e-4, 3e-4, 1e-3, 3e-3, ...
    (a rate off the ladder steps to the nearest ladder value beyond it)."""
    lr = check_positive(lr, "lr")
    exp = math.floor(math.log10(lr))
    ladder = sorted(float(f"{m * 10.0 ** e:.6g}") for e in range(exp - 2, exp + 3) for m in (1, 3))
    return (next(v for v in ladder if v > lr * (1 + 1e-9)) if up
            else next(v for v in reversed(ladder) if v < lr * (1 - 1e-9)))


def _recall_after(history, epochs: int, n: int) -> float:
    """The best validation Recall@``n`` of a run over its start and its first ``epochs`` epochs."""
    recalls = history.recalls(n)[:epochs] + ([float(history.initial["val"][n])] if history.initial else [])
    return max(recalls, default=-1.0)


def _best(val_recall: dict, candidates) -> float:
    """The lr with the highest mean validation recall among ``candidates``; ties: the smaller lr."""
    return min(candidates, key=lambda lr: (-float(np.mean(val_recall[lr])), lr))


@dataclass
class LRSearch:
    """The learning-rate choice of :func:`lr_search`: ``lr`` (chosen), ``grid``, ``val_recall[lr]`` = the
    selected validation Recall@``ns[0]`` per search seed, ``runs[seed]`` = the :class:`FineTuneResult` at the
    chosen lr for every seed, ``histories[lr][seed]`` every run's history, and the size of the choice
    (queries, ``search_seeds``: the seeds it was made on; the other ``seeds`` ran at the chosen lr only)."""

    method: str
    lr: float
    grid: tuple[float, ...]
    seeds: tuple[int, ...]
    search_seeds: tuple[int, ...]
    val_queries: int
    val_recall: dict
    runs: dict
    histories: dict
    cache: dict | None = None
    halved: dict = dataclasses.field(default_factory=dict)
    extended: tuple[float, ...] = ()

    @property
    def interior(self) -> bool:
        """The chosen lr has a tried lr on each side (or the grid has one point: nothing was chosen)."""
        return len(self.grid) == 1 or self.grid[0] < self.lr < self.grid[-1]

    def table(self) -> str:
        """One line per lr: mean ± std of the selected val Recall over the search seeds, best epochs, the
        choice."""
        lines = [f"{self.method}: lr chosen on validation ({self.val_queries} queries, "
                 f"mean over seeds {list(self.search_seeds)}; grid {[float(f'{v:g}') for v in self.grid]}"
                 + (f", extended by {[float(f'{v:g}') for v in self.extended]}" if self.extended else "") + ")"]
        for lr in self.grid:
            vals = self.val_recall[lr]
            sd = float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0
            epochs = [self.histories[lr][s].best_epoch + 1 for s in self.search_seeds]
            lines.append(f"  lr {lr:.2g}: val R@1 {np.mean(vals):.3f} ± {sd:.3f}, best epoch {epochs}"
                         + (f"   (stopped after {self.halved[lr]} epochs: halving)" if lr in self.halved else "")
                         + ("   <- chosen" if lr == self.lr else ""))
        return "\n".join(lines)


def lr_search(method: Method, train_split, val_split, recipe: Recipe = RECIPE, seeds=(0,), *,
              cache: FrozenFeatureCache | None = None, progress: bool = False) -> LRSearch:
    """Fine-tune ``method`` at the lrs of :meth:`Method.lr_grid` for the first ``recipe.search_seeds`` of
    ``seeds``; choose the lr with the highest mean selected validation Recall@``ns[0]`` over them (ties: the
    smaller lr); then fine-tune the remaining seeds at the chosen lr only. Every run is seeded on its own, so
    a seed's run at the chosen lr is the same whether or not it took part in the choice. A one-point grid has
    nothing to choose: every seed runs at it and counts in ``val_recall``.

    **Successive halving** (``recipe.halving_epochs`` = r > 0, grids of 3 or more): every lr first trains r
    epochs; the better half by mean best validation recall so far (ties: the smaller lr) trains on to the end,
    continued from its checkpoint (the same weights as an uninterrupted run), and the others stop
    (``halved``). **Interior choice** (``recipe.lr_extend`` = e): while the chosen lr is the smallest or the
    largest tried, the next rate beyond it on the 1-3 ladder (:func:`ladder_step`) trains r epochs and on to
    the end only if its mean best validation recall then beats the chosen rate's after r epochs (else it is
    halved, and the choice is inside the grid); the choice is made again, at most e times (``extended``;
    :attr:`LRSearch.interior` says whether it ended inside).

    The choice is refused (``ValueError``) on a validation split with fewer than ``recipe.min_val_queries``
    queries unless it is made over at least ``recipe.search_seeds`` seeds: on 133 queries one query is
    0.0075 of Recall@1, the size of the differences between grid points. The frozen blocks are computed once
    for the whole search (``recipe.frozen_cache``; pass ``cache`` to share one between searches).
    """
    method, recipe = _check_method(method), _check_recipe(recipe)
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must list distinct training seeds, got {seeds}")
    queries = len(val_split.q_images)
    grid = method.lr_grid(recipe)
    chooses = seeds if len(grid) == 1 else seeds[:recipe.search_seeds]
    if len(grid) > 1 and queries < recipe.min_val_queries and len(chooses) < recipe.search_seeds:
        raise ValueError(f"the validation split has {queries} queries, fewer than recipe.min_val_queries = "
                         f"{recipe.min_val_queries}, too few to choose a learning rate on one seed; choose over "
                         f">= {recipe.search_seeds} seeds (seeds=(0, 1, 2, ...)), use a larger validation "
                         f"split, or fine-tune at a given lr (fine_tune(..., lr=recipe.lr))")
    if cache is None and recipe.frozen_cache:
        cache = FrozenFeatureCache(recipe.cache_dtype)
    runs, halved, extended = {}, {}, []
    rung = recipe.halving_epochs if 0 < recipe.halving_epochs < recipe.max_epochs else 0
    with tempfile.TemporaryDirectory(prefix="vpr_nb-lr-search-") as tmp:     # the runs stopped at the rung
        def run_all(lr, stop_after=None, resumable=False):
            return {s: _run(method, train_split, val_split, recipe, s, lr, cache, progress,
                            Path(tmp) / f"{lr:g}-{s}" if resumable else None, stop_after) for s in chooses}

        if len(grid) >= 3 and rung:
            first = {lr: run_all(lr, rung, True) for lr in grid}
            score = {lr: [r.history.best_recall for r in first[lr].values()] for lr in grid}
            keep = sorted(grid, key=lambda lr: (-float(np.mean(score[lr])), lr))[:math.ceil(len(grid) / 2)]
            for lr in grid:
                if lr in keep:
                    runs[lr] = run_all(lr, None, True)
                else:
                    runs[lr], halved[lr] = first[lr], rung
        else:
            runs = {lr: run_all(lr) for lr in grid}
        val_recall = {lr: [r.history.best_recall for r in rs.values()] for lr, rs in runs.items()}
        full = [lr for lr in runs if lr not in halved]
        chosen = _best(val_recall, full)
        for _ in range(recipe.lr_extend if len(grid) > 1 else 0):
            tried = sorted(runs)
            if tried[0] < chosen < tried[-1]:
                break
            new = ladder_step(chosen, up=chosen == tried[-1])
            extended.append(new)
            if rung:        # the rate beyond the edge trains on only if it leads the chosen one at the rung
                runs[new] = run_all(new, rung, True)
                if np.mean([r.history.best_recall for r in runs[new].values()]) > np.mean(
                        [_recall_after(r.history, rung, recipe.ns[0]) for r in runs[chosen].values()]):
                    runs[new] = run_all(new, None, True)
                else:
                    halved[new] = rung
            else:
                runs[new] = run_all(new)
            val_recall[new] = [r.history.best_recall for r in runs[new].values()]
            if new not in halved:
                full.append(new)
                chosen = _best(val_recall, full)
    histories = {lr: {s: r.history for s, r in runs[lr].items()} for lr in sorted(runs)}
    best_runs = dict(runs[chosen])
    for s in seeds[len(chooses):]:                         # the other seeds: at the chosen lr only
        best_runs[s] = _run(method, train_split, val_split, recipe, s, chosen, cache, progress)
        histories[chosen][s] = best_runs[s].history
    search = LRSearch(method.name, chosen, tuple(sorted(runs)), seeds, chooses, queries,
                      {lr: val_recall[lr] for lr in sorted(runs)}, {s: best_runs[s] for s in seeds}, histories,
                      None if cache is None else cache.stats(), halved, tuple(sorted(extended)))
    for r in best_runs.values():
        r.search = search
    return search


def fine_tune(method: Method, train_split, val_split, recipe: Recipe = RECIPE, seed: int = 0, *,
              lr: float | None = None, cache: FrozenFeatureCache | None = None,
              progress: bool = False) -> FineTuneResult:
    """Fine-tune ``method`` with ``recipe`` on ``train_split``, selecting on ``val_split``.

    ``lr=None`` chooses the learning rate on validation (:func:`lr_search` with this one seed, which needs a
    validation split of at least ``recipe.min_val_queries`` queries; to choose over seeds call
    :func:`lr_search` and use its ``runs``); a number trains at that rate. Returns a :class:`FineTuneResult`
    (``model``, ``history``, ``lr``, ``start``).
    """
    method, recipe = _check_method(method), _check_recipe(recipe)
    if lr is None:
        return lr_search(method, train_split, val_split, recipe, (seed,), cache=cache, progress=progress).runs[seed]
    lr = check_positive(lr, "lr")
    seed = check_int(seed, "seed", minimum=0)
    if cache is None and recipe.frozen_cache:
        cache = FrozenFeatureCache(recipe.cache_dtype)
    return _run(method, train_split, val_split, recipe, seed, lr, cache, progress)


def _search_one(args):
    method, train_split, val_split, recipe, seeds, lr = args
    if lr is not None:          # a given rate: the search over a one-point grid (nothing to choose)
        method = dataclasses.replace(method, paper_lr=None)
        recipe = dataclasses.replace(recipe, lr_grid=(lr,))
    return lr_search(method, train_split, val_split, recipe, seeds)


def search_methods(methods, train_split, val_split, recipe: Recipe = RECIPE, seeds=(0,), *,
                   lr: float | None = None, workers: int = 1) -> dict:
    """:func:`lr_search` for each of ``methods`` (each with its own frozen-block cache), as
    ``{method name: LRSearch}`` in the order given; ``lr`` given: every method trains at that rate (an
    ``LRSearch`` with a one-point grid).

    ``methods`` may also hold ``(method, recipe)`` pairs, for a row that deviates from the recipe (e.g. SGD).
    ``workers > 1`` runs the methods in that many processes (forked, so on Linux and macOS only); every run is
    seeded on its own, so the results do not depend on ``workers``."""
    items = []
    for entry in methods:
        method, rec = entry if isinstance(entry, tuple) else (entry, recipe)
        items.append((_check_method(method), _check_recipe(rec)))
    names = [m.name for m, _ in items]
    if not items or len(set(names)) != len(names):
        raise ValueError(f"methods must be a non-empty list of methods with distinct names, got {names}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    workers = check_int(workers, "workers", minimum=1)
    if lr is not None:
        lr = check_positive(lr, "lr")
    tasks = [(m, train_split, val_split, rec, seeds, lr) for m, rec in items]
    if workers == 1 or len(tasks) == 1:
        found = [_search_one(t) for t in tasks]
    else:
        if "fork" not in mp.get_all_start_methods():
            raise ValueError("workers > 1 needs the 'fork' start method (Linux, macOS); use workers=1 here")
        with ProcessPoolExecutor(min(workers, len(tasks)), mp_context=mp.get_context("fork")) as pool:
            found = list(pool.map(_search_one, tasks))
    return dict(zip(names, found))
