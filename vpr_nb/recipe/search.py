"""Fine-tuning runs of a method and the choice of its learning rate on validation, one method or many, as
synchronous rounds of tasks (:class:`~vpr_nb.recipe.task.FineTuneTask`) on an engine (:mod:`vpr_nb.engine`)."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .._checks import check_int, check_positive
from ..engine import LocalEngine, engine_from_env
from .method import Method, _check_method
from .protocol import RECIPE, Recipe, _check_recipe
from .segments import SEGMENT_EPOCHS, run_round
from .task import FineTuneResult, FineTuneTask, run_task


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
              engine=None) -> LRSearch:
    """Fine-tune ``method`` at the lrs of :meth:`Method.lr_grid` for the first ``recipe.search_seeds`` of
    ``seeds``; choose the lr with the highest mean selected validation Recall@``ns[0]`` over them (ties: the
    smaller lr); then fine-tune the remaining seeds at the chosen lr only. Every run is seeded on its own, so
    a seed's run at the chosen lr is the same whether or not it took part in the choice. A one-point grid has
    nothing to choose: every seed runs at it and counts in ``val_recall``.

    **Successive halving** (``recipe.halving_epochs`` = r > 0, grids of 3 or more): every lr first trains r
    epochs; the better half by mean best validation recall so far (ties: the smaller lr) trains to the end
    (the same weights as if it had gone on from the rung), and the others stop (``halved``). **Interior choice** (``recipe.lr_extend`` = e): while the chosen lr is the smallest or the
    largest tried, the next rate beyond it on the 1-3 ladder (:func:`ladder_step`) trains r epochs and on to
    the end only if its mean best validation recall then beats the chosen rate's after r epochs (else it is
    halved, and the choice is inside the grid); the choice is made again, at most e times (``extended``;
    :attr:`LRSearch.interior` says whether it ended inside).

    The choice is refused (``ValueError``) on a validation split with fewer than ``recipe.min_val_queries``
    queries unless it is made over at least ``recipe.search_seeds`` seeds: on 133 queries one query is
    0.0075 of Recall@1, the size of the differences between grid points. Each training run is a task
    (:class:`~vpr_nb.recipe.task.FineTuneTask`) on ``engine`` (default :func:`vpr_nb.engine.engine_from_env`),
    in rounds: every task of a round runs before the next round is decided, so the choice never depends on how
    many workers ran them. A run that halving kept trains again from its start, so a task never needs another
    task's checkpoint (3 more epochs per kept rate). Each worker process keeps the frozen blocks it computed.
    """
    return drive([search_rounds(method, train_split, val_split, recipe, seeds)], engine or engine_from_env())[0]


def search_rounds(method: Method, train_split, val_split, recipe: Recipe = RECIPE, seeds=(0,)):
    """:func:`lr_search` as a generator of rounds: it yields a list of tasks, is sent their results in the same
    order, and returns the :class:`LRSearch` (``StopIteration.value``); :func:`drive` runs it."""
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
    rung = recipe.halving_epochs if 0 < recipe.halving_epochs < recipe.max_epochs else 0

    def tasks(lrs, stop_after=None, which=chooses):
        return [FineTuneTask(method, train_split, val_split, recipe, s, lr, stop_after) for lr in lrs for s in which]

    def by_lr(lrs, results, which=chooses):
        it = iter(results)
        return {lr: {s: next(it) for s in which} for lr in lrs}

    runs, halved, extended = {}, {}, []
    if len(grid) >= 3 and rung:
        first = by_lr(grid, (yield tasks(grid, rung)))
        score = {lr: [r.history.best_recall for r in first[lr].values()] for lr in grid}
        keep = sorted(sorted(grid, key=lambda lr: (-float(np.mean(score[lr])), lr))[:math.ceil(len(grid) / 2)])
        runs = {**{lr: first[lr] for lr in grid if lr not in keep}, **by_lr(keep, (yield tasks(keep)))}
        halved = {lr: rung for lr in grid if lr not in keep}
    else:
        runs = by_lr(grid, (yield tasks(grid)))
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
            runs[new] = by_lr([new], (yield tasks([new], rung)))[new]
            if np.mean([r.history.best_recall for r in runs[new].values()]) > np.mean(
                    [_recall_after(r.history, rung, recipe.ns[0]) for r in runs[chosen].values()]):
                runs[new] = by_lr([new], (yield tasks([new])))[new]
            else:
                halved[new] = rung
        else:
            runs[new] = by_lr([new], (yield tasks([new])))[new]
        val_recall[new] = [r.history.best_recall for r in runs[new].values()]
        if new not in halved:
            full.append(new)
            chosen = _best(val_recall, full)
    histories = {lr: {s: r.history for s, r in runs[lr].items()} for lr in sorted(runs)}
    best_runs = dict(runs[chosen])
    rest = seeds[len(chooses):]                            # the other seeds: at the chosen lr only
    if rest:
        best_runs.update(by_lr([chosen], (yield tasks([chosen], None, rest)), rest)[chosen])
        for s in rest:
            histories[chosen][s] = best_runs[s].history
    search = LRSearch(method.name, chosen, tuple(sorted(runs)), seeds, chooses, queries,
                      {lr: val_recall[lr] for lr in sorted(runs)}, {s: best_runs[s] for s in seeds}, histories,
                      halved, tuple(sorted(extended)))
    for r in best_runs.values():
        r.search = search
    return search


def drive(rounds, engine=None, segment_epochs: int | None = SEGMENT_EPOCHS) -> list:
    """Run generators of task rounds (:func:`search_rounds`) together: each step gathers the next round of every
    generator still running into one list for ``engine.map`` (default :class:`~vpr_nb.engine.LocalEngine`, one
    worker), sends each its results, and returns what each generator returned, in order. Rounds are
    synchronous: a generator decides its next round from its whole previous one, whatever ran where. Each
    fine-tune runs in segments of ``segment_epochs`` epochs (:func:`~vpr_nb.recipe.segments.run_round`; None:
    whole), which gives the same bits."""
    engine = engine or LocalEngine()
    rounds = list(rounds)
    out: list = [None] * len(rounds)
    pending = {}
    for i, gen in enumerate(rounds):
        try:
            pending[i] = next(gen)
        except StopIteration as stop:
            out[i] = stop.value
    while pending:
        order = list(pending)
        batch = [t for i in order for t in pending[i]]
        results = run_round(engine, batch, segment_epochs)
        pos, nxt = 0, {}
        for i in order:
            part, pos = results[pos:pos + len(pending[i])], pos + len(pending[i])
            try:
                nxt[i] = rounds[i].send(part)
            except StopIteration as stop:
                out[i] = stop.value
        pending = nxt
    return out


def fine_tune(method: Method, train_split, val_split, recipe: Recipe = RECIPE, seed: int = 0, *,
              lr: float | None = None, engine=None) -> FineTuneResult:
    """Fine-tune ``method`` with ``recipe`` on ``train_split``, selecting on ``val_split``.

    ``lr=None`` chooses the learning rate on validation (:func:`lr_search` with this one seed, which needs a
    validation split of at least ``recipe.min_val_queries`` queries; to choose over seeds call
    :func:`lr_search` and use its ``runs``); a number trains at that rate (one task, run in this process).
    Returns a :class:`FineTuneResult` (``model``, ``history``, ``lr``, ``start``).
    """
    method, recipe = _check_method(method), _check_recipe(recipe)
    if lr is None:
        return lr_search(method, train_split, val_split, recipe, (seed,), engine=engine).runs[seed]
    return run_task(FineTuneTask(method, train_split, val_split, recipe, seed, lr))


def _fixed_lr(method: Method, recipe: Recipe, lr) -> tuple[Method, Recipe]:
    """A given rate (a number, or ``{method name: rate}``): the search over a one-point grid (nothing to
    choose)."""
    if isinstance(lr, Mapping):
        lr = lr.get(method.name)
    if lr is None:
        return method, recipe
    return dataclasses.replace(method, paper_lr=None), dataclasses.replace(recipe, lr_grid=(lr,))


def search_methods(methods, train_split, val_split, recipe: Recipe = RECIPE, seeds=(0,), *,
                   lr=None, workers: int = 1, engine=None, segment_epochs: int | None = SEGMENT_EPOCHS) -> dict:
    """:func:`lr_search` for each of ``methods``, as ``{method name: LRSearch}`` in the order given; ``lr``
    given: every method trains at that rate (an ``LRSearch`` with a one-point grid); a dict ``{method name:
    rate}`` fixes the rate of the methods it names (e.g. a committed choice, to re-make one seed).

    ``methods`` may also hold ``(method, recipe)`` pairs, for a row that deviates from the recipe (e.g. SGD).
    The searches advance together, round by round (:func:`drive`), on ``engine`` (default:
    :func:`vpr_nb.engine.engine_from_env` with ``workers`` local processes), each fine-tune in segments of
    ``segment_epochs`` epochs (None: whole); every run is seeded on its own, so the results do not depend on the
    engine, its workers or the segment length."""
    items = []
    for entry in methods:
        method, rec = entry if isinstance(entry, tuple) else (entry, recipe)
        items.append((_check_method(method), _check_recipe(rec)))
    names = [m.name for m, _ in items]
    if not items or len(set(names)) != len(names):
        raise ValueError(f"methods must be a non-empty list of methods with distinct names, got {names}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    workers = check_int(workers, "workers", minimum=1)
    if isinstance(lr, Mapping):
        lr = {k: check_positive(v, f"lr of {k!r}") for k, v in lr.items()}
    elif lr is not None:
        lr = check_positive(lr, "lr")
    fixed = [_fixed_lr(m, rec, lr) for m, rec in items]
    gens = [search_rounds(m, train_split, val_split, rec, seeds) for m, rec in fixed]
    return dict(zip(names, drive(gens, engine or engine_from_env(workers), segment_epochs)))
