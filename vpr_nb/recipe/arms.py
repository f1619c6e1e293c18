"""On/off experiments (notebooks 03, 05, 07): the same methods trained in two worlds, each arm's lr searched by
the recipe, every model scored on large test sets pooled over worlds, and paired by training seed.

- :data:`CITY_TEST_WORLDS` and :func:`test_splits`: test sets large enough to see a 0.01 gap (two unseen
  cities, 80 % of each for testing: 1,700+ queries, so one query is < 0.001 of Recall@1);
- :func:`pooled_recall`: Recall@N over several test splits, as if their queries were one set (each split's
  own database and positives; queries without a positive left out as in :func:`evaluate_on_split`);
- :func:`run_arms`: :func:`search_methods` per world, then the pooled test recall of every run and of its
  start, per seed, plus each arm's chosen lr and whether it is interior to its grid (and, with ``extra``, any
  other per-run numbers, e.g. CliqueMining's near-miss share, :mod:`vpr_nb.onoff.clique`).
"""
from __future__ import annotations

import fnmatch
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .._checks import check_int
from ..evaluation import compute_descriptors, evaluate_on_split
from ..split import check_split
from ..synthetic import make_dataset
from .protocol import RECIPE, Recipe, _check_recipe
from .search import search_methods

# Two cities never pretrained on (the course backbone saw city seeds 100-105), trained or validated on (city
# seeds 0 and 1), 80 % of each a test split: 893 + about as many test queries.
CITY_TEST_WORLDS = ({"preset": "city", "seed": 2, "size": "tiny", "overrides": {"split_fractions": (0.1, 0.1, 0.8)}},
                    {"preset": "city", "seed": 3, "size": "tiny", "overrides": {"split_fractions": (0.1, 0.1, 0.8)}})


def test_splits(worlds: Sequence[Mapping] = CITY_TEST_WORLDS) -> list:
    """The test split of each world (dicts ``preset``, ``seed``, optional ``size`` and ``overrides``)."""
    out = []
    for w in worlds:
        if not isinstance(w, Mapping) or not isinstance(w.get("preset"), str) or "seed" not in w:
            raise ValueError(f"each world must be a dict with 'preset' and 'seed' (and optional 'size', 'overrides'), "
                             f"got {w!r}")
        out.append(make_dataset(w["preset"], seed=w["seed"], size=w.get("size", "tiny"), splits=("test",),
                                **dict(w.get("overrides") or {})).test)
    if not out:
        raise ValueError("worlds must list at least one test world")
    return out


def counted_queries(split) -> int:
    """The queries Recall@N counts on ``split``: all of them, or (convention ``"exclude"``) those with a positive."""
    split = check_split(split)
    if split.recall_convention == "exclude":
        return int(sum(len(p) > 0 for p in split.positives()))
    return len(split.q_images)


def pooled_recall(model, tests: Sequence, ns: Sequence[int] = (1, 5, 10), *, descriptors=None) -> dict:
    """Recall@N of ``model`` over the test splits ``tests`` pooled: ``sum_i R_i · n_i / sum_i n_i`` with ``n_i``
    the counted queries of split i (:func:`counted_queries`); each split retrieves from its own database.
    Returns ``{N: recall}`` and ``"queries"``: the pooled count. ``descriptors``: a function ``images ->
    descriptors`` in place of ``model`` (e.g. raw pixels)."""
    if not tests:
        raise ValueError("tests must list at least one test split")
    ns = tuple(check_int(n, "ns entry") for n in ns)
    describe = descriptors or (lambda images: compute_descriptors(model, images))
    total, sums = 0, dict.fromkeys(ns, 0.0)
    for split in tests:
        n_q = counted_queries(split)
        rec = evaluate_on_split(describe(split.db_images), describe(split.q_images), split, ns)
        for n in ns:
            sums[n] += rec[n] * n_q
        total += n_q
    if total == 0:
        raise ValueError("the test splits have no query with a positive: nothing to score")
    return {**{n: float(sums[n] / total) for n in ns}, "queries": total}


def _same_weights(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _settings(model) -> tuple:
    """What a model computes besides its weights: each module's type and its plain settings (e.g. SALAD's
    ``assignment``, "sinkhorn" or "softmax")."""
    return tuple((name, type(m).__name__, tuple(sorted((k, v) for k, v in vars(m).items() if not k.startswith("_")
                                                       and isinstance(v, (str, int, float, bool)))))
                 for name, m in model.named_modules())


def _start_recall(model, tests, ns, starts: list) -> dict:
    """:func:`pooled_recall` of a start, scored once: arms of one seed share their start (same weights and the
    same settings, :func:`_settings`)."""
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    settings = _settings(model)
    for weights, kind, rec in starts:
        if kind == settings and _same_weights(weights, state):
            return rec
    rec = pooled_recall(model, tests, ns)
    starts.append((state, settings, rec))
    return rec


def _extra_values(extra, models, tests, digits: int, taken) -> dict:
    """``extra(model, tests)`` of each model, as ``{key: [per model]}``; keys of ``taken`` are refused."""
    rows = [extra(m, tests) for m in models]
    if not all(isinstance(r, Mapping) for r in rows) or len({tuple(r) for r in rows}) != 1:
        raise ValueError("extra must return a dict {key: number} with the same keys for every model")
    clash = sorted(set(rows[0]) & set(taken))
    if clash:
        raise ValueError(f"extra's keys {clash} are run_arms' own; name them otherwise")
    return {k: [round(float(r[k]), digits) for r in rows] for k in rows[0]}


@dataclass(frozen=True)
class Selection:
    """Some arms and seeds of an on/off experiment, to re-make one committed number: ``arms`` a shell pattern over
    arm names (``"cliques*"``), ``seeds`` the seeds (None: all), ``lrs`` ``{world: {arm: lr}}`` the committed
    choices, at which a searched arm's seed trains alone (the same run as in the search)."""

    arms: str = "*"
    seeds: tuple[int, ...] | None = None
    lrs: Mapping | None = None

    def __post_init__(self):
        if not isinstance(self.arms, str) or not self.arms:
            raise ValueError(f"arms must be a pattern over arm names such as 'cliques*', got {self.arms!r}")
        if self.seeds is not None:
            object.__setattr__(self, "seeds", tuple(check_int(s, "seed", minimum=0) for s in self.seeds))

    def methods(self, methods) -> list:
        return [m for m in methods if fnmatch.fnmatchcase((m[0] if isinstance(m, tuple) else m).name, self.arms)]


def run_arms(worlds: Mapping[str, Mapping], val_split, tests: Sequence, seeds: Sequence[int],
             recipe: Recipe = RECIPE, *, workers: int = 1, lr: float | None = None,
             digits: int = 4, extra=None, select: Selection | None = None) -> dict:
    """Train every arm of every world and score it: ``worlds`` = ``{world: {"train": split, "methods": [Method
    or (Method, Recipe)]}}``. Each world's methods go through :func:`search_methods` (lr searched per arm unless
    ``lr`` is given) on its own training split, selected on ``val_split``; every selected model and its start
    are scored by :func:`pooled_recall` on ``tests``.

    Returns ``{world: {arm: {"R@1": [per seed], "R@5": [...], "start R@1": [...], "lr": chosen, "lr interior":
    bool, "grid": [lrs tried], "best epoch": [...]}}}``; seeds in the order given (pair arms by position).

    ``extra``: a function ``(model, tests) -> {key: number}`` called on every selected model; each key is added
    to its arm as a per-seed list (rounded to ``digits``), beside the keys above (which it may not reuse).

    ``select`` (:class:`Selection`): only the arms and seeds it names, each at its committed lr when ``select.lrs``
    has one; worlds without a selected arm are left out."""
    recipe = _check_recipe(recipe)
    if extra is not None and not callable(extra):
        raise ValueError(f"extra must be a function (model, tests) -> {{key: number}} or None, got {extra!r}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    if select is not None:
        if not isinstance(select, Selection):
            raise ValueError(f"select must be a vpr_nb.recipe.arms.Selection, got {type(select).__name__}")
        unknown = sorted(set(select.seeds or ()) - set(seeds))
        if unknown:
            raise ValueError(f"seeds {unknown} are not among this experiment's seeds {list(seeds)}")
        seeds = select.seeds or seeds
    if not isinstance(worlds, Mapping) or not worlds:
        raise ValueError("worlds must be a non-empty dict {world: {'train': split, 'methods': [...]}}")
    out, starts = {}, []          # starts: (weights, pooled recall) of the starts scored so far
    for world, spec in worlds.items():
        if not isinstance(spec, Mapping) or "train" not in spec or "methods" not in spec:
            raise ValueError(f"worlds[{world!r}] must be a dict with 'train' (a split) and 'methods' (a list)")
        methods, arm_lr = spec["methods"], lr
        if select is not None:
            methods = select.methods(methods)
            if not methods:
                continue
            arm_lr = {**{(m[0] if isinstance(m, tuple) else m).name: lr for m in methods if lr is not None},
                      **dict((select.lrs or {}).get(world, {}))}
        found = search_methods(methods, spec["train"], val_split, recipe, seeds, lr=arm_lr, workers=workers)
        arms = {}
        for name, s in found.items():
            model_r = [pooled_recall(s.runs[seed].model, tests, recipe.ns) for seed in seeds]
            start_r = [_start_recall(s.runs[seed].start, tests, recipe.ns, starts) for seed in seeds]
            arms[name] = {**{f"R@{n}": [round(r[n], digits) for r in model_r] for n in recipe.ns},
                          "start R@1": [round(r[recipe.ns[0]], digits) for r in start_r],
                          "lr": s.lr, "lr interior": bool(s.interior), "grid": [float(f"{v:g}") for v in s.grid],
                          "best epoch": [int(s.runs[seed].best_epoch) for seed in seeds],
                          "test queries": int(model_r[0]["queries"])}
            if extra is not None:
                arms[name].update(_extra_values(extra, [s.runs[seed].model for seed in seeds], tests, digits,
                                                arms[name]))
        out[world] = arms
    return out


def arm_values(arms: Mapping, arm: str, key: str = "R@1") -> np.ndarray:
    """One arm's per-seed values of ``key`` from :func:`run_arms`' output for one world, as an array."""
    if arm not in arms:
        raise ValueError(f"no arm {arm!r}; the arms are {sorted(arms)}")
    return np.asarray(arms[arm][key], dtype=np.float64)
