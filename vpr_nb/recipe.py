"""The course's fine-tuning recipe: one protocol for every fine-tuning experiment of notebooks 03–07.

Each paper fine-tunes a pretrained backbone with its own aggregator and loss; what the course compares is
the *method* (a loss, an aggregator, a batch sampler), so everything else is fixed here, once:

- **Backbone**: the course backbone (:func:`vpr_nb.pretrain.course_backbone`) with its last block trainable
  (VGG16's conv5 in DW-T-Loss, DINOv2's last blocks in SALAD). Every aggregator reads its **output, after its
  final ReLU** (``after_relu``): the backbone is pretrained with a local contrastive term on the features
  before that ReLU (:mod:`vpr_nb.pretrain`), and measured on it, NetVLAD's k-means start reads the output
  better (notebook 04's untrained table, before vs after the ReLU), as does mean pooling (its signed mean
  cancels); max pooling and GeM give the same descriptor either way. SALAD reads what NetVLAD reads (notebook
  05). The public NetVLAD code reads VGG16's conv5_3 before its ReLU: the right side is an empirical question
  for each backbone, which notebook 04 asks.
- **Heads initialised from data**: NetVLAD by k-means (:func:`vpr_nb.models.init_netvlad`, 20 features per
  training-database image, 50 iterations, the training seed); SALAD with standardised head inputs
  (:func:`vpr_nb.models.init_salad`; the published initialisation starts collapsed here, notebook 05).
- **Batches**: triplets (:class:`vpr_nb.training.TripletSource`, notebook 04: 16 queries per step, the 5 hardest
  of 300 negatives, margin 0.1, positives facing within 45°) or P × K place batches
  (:class:`vpr_nb.training.PlaceBatchSource`, notebook 05's MS recipe: 32 places × 4 images, 30 batches an
  epoch), or a method's own source.
- **Optimiser**: Adam, weight decay 1e-3, StepLR(5, 0.5) (notebook 04).
- **Selection**: the starting weights are the **epoch-0 candidate** (a fine-tune never reports worse than not
  training without saying so: ``History.initial_won``); training stops when validation Recall@1 has not
  improved for ``patience`` epochs (at most ``max_epochs``), and the best-on-validation weights are kept.
- **Learning rate per method** from a small grid (``lr_grid`` plus the method's ``paper_lr``, the paper's
  learning rate rescaled as the notebook explains), chosen on validation: the mean over the first
  ``search_seeds`` seeds of a multi-seed run, whose other seeds then train at the chosen rate only
  (:func:`lr_search`); on a split under ``min_val_queries`` queries the choice needs that many seeds.
- **Frozen blocks computed once** (:mod:`vpr_nb.feature_cache`): one cache per search, shared by every run.

A notebook states only what deviates: ``dataclasses.replace(RECIPE, batch_size=4)``.

    method = Method("T-Loss", "netvlad", loss=TripletLoss())
    search = lr_search(method, ds.train, ds.val, RECIPE, seeds=(0, 1, 2, 3, 4))
    for seed, run in search.runs.items():       # each: model, history, lr, start (the epoch-0 weights)
        ...
"""
from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
import dataclasses
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from . import losses as L
from ._checks import check_int, check_positive
from .feature_cache import CACHE_DTYPES, FrozenFeatureCache
from .training import OPTIMIZERS, History, PlaceBatchSource, TrainConfig, TripletSource, train

BATCHES = ("triplets", "places")


@dataclass(frozen=True)
class Recipe:
    """Every default of the course's fine-tuning protocol (the module docstring gives each one's source)."""

    # backbone and how the aggregators read it
    trainable_blocks: int = 1                    # the last block trains (VGG16 conv5 / DINOv2's last blocks)
    after_relu: tuple[str, ...] = ("max", "mean", "gem", "netvlad", "salad")   # read the final ReLU's output
                                                 # (the others read before it; notebook 04 measures NetVLAD)
    # triplet batches (notebook 04)
    batch_size: int = 16
    margin: float = L.DEFAULT_MARGIN
    num_negatives: int = 5
    num_candidates: int = 300
    max_heading_diff: float | None = 45.0
    # place batches (notebook 05's MS recipe)
    places_per_batch: int = 32
    images_per_place: int = 4
    place_batches_per_epoch: int = 30
    spots_per_place: int = 3
    # aggregator sizes and their data-dependent initialisation (notebooks 04, 05)
    netvlad_clusters: int = 16
    netvlad_per_image: int = 20
    netvlad_niter: int = 50
    salad_clusters: int = 16
    salad_cluster_dim: int = 32
    salad_token_dim: int = 64
    salad_hidden_dim: int = 64
    salad_dropout: float = 0.3
    salad_standardise: bool = True
    # optimiser (notebook 04)
    optimizer: str = "adam"
    lr: float = 1e-3                             # a run without search (e.g. a CI smoke test); also in lr_grid
    weight_decay: float = 1e-3
    step_size: int = 5
    gamma: float = 0.5
    # selection
    lr_grid: tuple[float, ...] = (3e-4, 1e-3, 3e-3)   # x3 around notebook 04's 1e-3 (+ each method's paper_lr)
    max_epochs: int = 24             # measured: SALAD stops at epochs 12-13 (best 8-9), GeM at 7-10
    patience: int = 4                # on 04's and 05's 35 committed 8-epoch curves it keeps the best in 34 (3: 31)
    initial_candidate: bool = True
    min_val_queries: int = 500       # below it, choose the lr over >= search_seeds seeds
    search_seeds: int = 3            # the lr is chosen on a run's first 3 seeds (on notebook 03's 8 searched
                                     # rows and 06's 2 arms the same rate as the mean over all 5 seeds)
    ns: tuple[int, ...] = (1, 5, 10)
    # frozen-block cache
    frozen_cache: bool = True
    cache_dtype: str = "float32"

    def __post_init__(self):
        from .aggregation import AGGREGATOR_NAMES

        ints = ("batch_size", "num_negatives", "num_candidates", "places_per_batch", "place_batches_per_epoch",
                "spots_per_place", "netvlad_clusters", "netvlad_per_image", "netvlad_niter", "salad_clusters",
                "salad_cluster_dim", "salad_token_dim", "salad_hidden_dim", "step_size", "max_epochs", "patience",
                "search_seeds")
        for name in ints:
            check_int(getattr(self, name), name)
        check_int(self.trainable_blocks, "trainable_blocks", minimum=0, maximum=4)
        check_int(self.images_per_place, "images_per_place", minimum=2)
        check_int(self.min_val_queries, "min_val_queries", minimum=0)
        for name in ("margin", "weight_decay", "salad_dropout"):
            check_positive(getattr(self, name), name, allow_zero=True)
        for name in ("lr", "gamma"):
            check_positive(getattr(self, name), name)
        if self.max_heading_diff is not None:
            check_positive(self.max_heading_diff, "max_heading_diff")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.cache_dtype not in CACHE_DTYPES:
            raise ValueError(f"cache_dtype must be one of {sorted(CACHE_DTYPES)}, got {self.cache_dtype!r}")
        for name in ("salad_standardise", "initial_candidate", "frozen_cache"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        grid = tuple(float(check_positive(v, "lr_grid entry")) for v in self.lr_grid)
        if not grid:
            raise ValueError("lr_grid must list at least one learning rate")
        object.__setattr__(self, "lr_grid", grid)
        after = tuple(self.after_relu)
        unknown = sorted(set(after) - set(AGGREGATOR_NAMES))
        if unknown:
            raise ValueError(f"after_relu names unknown aggregators {unknown}; known: {', '.join(AGGREGATOR_NAMES)}")
        object.__setattr__(self, "after_relu", after)
        ns = tuple(check_int(n, "ns entry") for n in self.ns)
        if not ns:
            raise ValueError("ns must list at least one N for Recall@N, e.g. (1, 5, 10)")
        object.__setattr__(self, "ns", ns)

    def to_dict(self) -> dict:
        """The recipe as plain data (for a notebook's ``EXPERIMENT`` config)."""
        return asdict(self)

    def aggregator_kwargs(self, aggregator: str) -> dict:
        """The recipe's size settings for ``aggregator`` (``build_model`` keyword arguments)."""
        if aggregator == "netvlad":
            return {"num_clusters": self.netvlad_clusters}
        if aggregator == "salad":
            return {"num_clusters": self.salad_clusters, "cluster_dim": self.salad_cluster_dim,
                    "token_dim": self.salad_token_dim, "hidden_dim": self.salad_hidden_dim,
                    "dropout": self.salad_dropout}
        return {}

    def train_config(self, lr: float, seed: int) -> TrainConfig:
        """The :class:`vpr_nb.training.TrainConfig` of one run of this recipe."""
        return TrainConfig(epochs=self.max_epochs, optimizer=self.optimizer, lr=lr, weight_decay=self.weight_decay,
                           step_size=self.step_size, gamma=self.gamma, seed=seed, ns=self.ns, restore_best=True,
                           initial_candidate=self.initial_candidate, patience=self.patience, device="cpu")


RECIPE = Recipe()

# The validation world of the city notebooks (03, 05). The fine-tuning world (city seed 0) has a validation
# split of 133 queries, where one query is 0.0075 of Recall@1, the size of the differences between epochs and
# grid points, so best-on-validation selection there keeps noise (measured on notebook 03's T-Loss, 5 seeds:
# test R@1 minus the start +0.016 ± 0.025 with lr and epochs selected on those 133 queries, +0.030 ± 0.009
# selected on this world's 803). A second city, seed 1 (never pretrained on, trained or tested
# on), almost all of it validation, has 803 queries, above ``Recipe.min_val_queries``.
VALIDATION_WORLD = {"preset": "city", "seed": 1, "size": "tiny", "overrides": {"split_fractions": (0.1, 0.8, 0.1)}}


def validation_split(world: Mapping = VALIDATION_WORLD):
    """The validation split of ``world`` (a dict ``preset``, ``seed``, optional ``size`` and ``overrides``, as a
    notebook's experiment config names a world; default :data:`VALIDATION_WORLD`)."""
    from .synthetic import make_dataset

    if not isinstance(world, Mapping) or not isinstance(world.get("preset"), str) or "seed" not in world:
        raise ValueError(f"world must be a dict with 'preset' and 'seed' (and optional 'size', 'overrides'), "
                         f"got {world!r}")
    return make_dataset(world["preset"], seed=world["seed"], size=world.get("size", "tiny"), splits=("val",),
                        **dict(world.get("overrides") or {})).val


@dataclass(frozen=True)
class Method:
    """What a fine-tuning experiment varies; the rest is the :class:`Recipe`.

    Args:
        name: the row's label.
        aggregator: one of :data:`vpr_nb.aggregation.AGGREGATOR_NAMES` (sizes from the recipe, overridden
            by ``aggregator_kwargs``).
        loss: a loss object: triplet-family (:class:`vpr_nb.losses.TripletLoss`, ``WeightedTripletLoss``,
            ``CETripletLoss``, ``DWTripletLoss``) for ``batches="triplets"``, ``MultiSimilarityLoss`` for
            ``"places"``; ``None``: ``TripletLoss(recipe.margin)`` / ``MultiSimilarityLoss()``.
        batches: ``"triplets"``, ``"places"`` or a callable ``(train_split, recipe, loss) -> source`` (an object
            with ``steps(model, rng)``, e.g. a :class:`PlaceBatchSource` subclass).
        trainable_blocks: ``None``: the recipe's; 0 trains the head alone on a frozen backbone.
        paper_lr: the paper's learning rate rescaled to this recipe (the notebook says how); added to the grid.
    """

    name: str
    aggregator: str = "gem"
    loss: object = None
    batches: str | Callable = "triplets"
    aggregator_kwargs: Mapping = field(default_factory=dict)
    trainable_blocks: int | None = None
    paper_lr: float | None = None

    def __post_init__(self):
        from .aggregation import AGGREGATOR_NAMES

        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        if self.aggregator not in AGGREGATOR_NAMES:
            raise ValueError(f"unknown aggregator {self.aggregator!r}; valid names are {', '.join(AGGREGATOR_NAMES)}")
        if not callable(self.batches) and self.batches not in BATCHES:
            raise ValueError(f"batches must be one of {BATCHES} or a callable (train_split, recipe, loss) -> source, "
                             f"got {self.batches!r}")
        if self.batches == "triplets" and self.loss is not None and not isinstance(self.loss, L.TripletFamilyLoss):
            raise ValueError(f"triplet batches need a triplet-family loss (TripletLoss, WeightedTripletLoss, "
                             f"CETripletLoss, DWTripletLoss), got {self.loss!r}")
        if self.batches == "places" and self.loss is not None and (isinstance(self.loss, L.TripletFamilyLoss)
                                                                   or not callable(self.loss)):
            raise ValueError(f"place batches need a loss called as loss(embeddings, labels), e.g. "
                             f"MultiSimilarityLoss(), got {self.loss!r}")
        if not isinstance(self.aggregator_kwargs, Mapping):
            raise ValueError(f"aggregator_kwargs must be a dict, got {type(self.aggregator_kwargs).__name__}")
        if self.trainable_blocks is not None:
            check_int(self.trainable_blocks, "trainable_blocks", minimum=0, maximum=4)
        if self.paper_lr is not None:
            check_positive(self.paper_lr, "paper_lr")

    def to_dict(self) -> dict:
        """The method as plain data (for a notebook's ``EXPERIMENT`` config)."""
        loss = None if self.loss is None else {"class": type(self.loss).__name__, **(
            asdict(self.loss) if hasattr(self.loss, "__dataclass_fields__") else {})}
        batches = self.batches if isinstance(self.batches, str) else (
            getattr(self.batches, "name", None) or getattr(self.batches, "__name__", "custom"))
        return {"name": self.name, "aggregator": self.aggregator, "loss": loss, "batches": batches,
                "aggregator_kwargs": dict(self.aggregator_kwargs), "trainable_blocks": self.trainable_blocks,
                "paper_lr": self.paper_lr}

    def lr_grid(self, recipe: Recipe) -> tuple[float, ...]:
        """The learning rates :func:`lr_search` tries: the recipe's grid and ``paper_lr``, ascending."""
        grid = set(recipe.lr_grid) | ({float(self.paper_lr)} if self.paper_lr is not None else set())
        return tuple(sorted(grid))


def _check_recipe(recipe) -> Recipe:
    if not isinstance(recipe, Recipe):
        raise ValueError(f"recipe must be a vpr_nb.recipe.Recipe, got {type(recipe).__name__}")
    return recipe


def _check_method(method) -> Method:
    if not isinstance(method, Method):
        raise ValueError(f"method must be a vpr_nb.recipe.Method, got {type(method).__name__}")
    return method


def build_start(method: Method, train_split, recipe: Recipe = RECIPE, seed: int = 0,
                cache: FrozenFeatureCache | None = None):
    """The starting model of ``method`` (the epoch-0 candidate): the course backbone read before or after its
    final ReLU (``recipe.after_relu``), the recipe's trainable blocks and the aggregator, initialised from the
    training database (NetVLAD: k-means; SALAD: standardised head inputs). Seeded by ``seed``; with
    ``cache`` attached to the backbone (the caller detaches it)."""
    import vpr_nb

    from .feature_cache import attach
    from .models import build_model, init_netvlad, init_salad
    from .pretrain import course_backbone

    method, recipe = _check_method(method), _check_recipe(recipe)
    seed = check_int(seed, "seed", minimum=0)
    vpr_nb.seed_everything(seed)
    blocks = recipe.trainable_blocks if method.trainable_blocks is None else method.trainable_blocks
    backbone = course_backbone(trainable_blocks=blocks, final_relu=method.aggregator in recipe.after_relu)
    if cache is not None:
        attach(backbone, cache)
    model = build_model(backbone, method.aggregator,
                        **{**recipe.aggregator_kwargs(method.aggregator), **method.aggregator_kwargs})
    if method.aggregator == "netvlad":
        init_netvlad(model, train_split.db_images, per_image=recipe.netvlad_per_image, niter=recipe.netvlad_niter,
                     seed=seed)
    elif method.aggregator == "salad" and recipe.salad_standardise:
        init_salad(model, train_split.db_images)
    return model


def place_batch_labels(split, recipe: Recipe = RECIPE) -> np.ndarray:
    """Place label of every image of ``split`` (database first, then queries) for P × K place batches.

    City: :func:`vpr_nb.pretrain.place_labels` (``recipe.spots_per_place`` street spots × view-direction
    quadrant, notebook 05). Other worlds: the world's own place groups (``db_place`` / ``q_place``; the route's
    5-frame groups, notebook 06): the route's cameras face about 0°, so their headings straddle the
    quadrant boundary at 360° and a quadrant split would cut a place in two."""
    from .pretrain import place_labels

    if getattr(getattr(split, "config", None), "preset", None) == "city":
        return place_labels(split, recipe.spots_per_place)
    return np.concatenate([split.db_place, split.q_place]).astype(np.int64)


def make_source(method: Method, train_split, recipe: Recipe = RECIPE):
    """The batch source of ``method`` on ``train_split`` with the recipe's batch settings."""
    from .samplers import random_place_batches

    method, recipe = _check_method(method), _check_recipe(recipe)
    if callable(method.batches):
        return method.batches(train_split, recipe, method.loss)
    if method.batches == "triplets":
        return TripletSource(train_split, method.loss or L.TripletLoss(margin=recipe.margin),
                             batch_size=recipe.batch_size, num_negatives=recipe.num_negatives,
                             num_candidates=recipe.num_candidates, max_heading_diff=recipe.max_heading_diff)
    labels = place_batch_labels(train_split, recipe)                    # database first, then queries
    images = np.concatenate([train_split.db_images, train_split.q_images])

    def batches(_model, _epoch, rng):
        return random_place_batches(labels, recipe.places_per_batch, recipe.images_per_place,
                                    num_batches=recipe.place_batches_per_epoch, seed=rng)

    return PlaceBatchSource(images, batches, loss=method.loss or L.MultiSimilarityLoss())


@dataclass(eq=False)
class PlaceBatches:
    """A :class:`Method`'s ``batches`` for place batches the recipe does not build itself: ``make_batches(model,
    epoch, rng)`` (e.g. :class:`vpr_nb.samplers.MixedPlaceBatches` of random and clique halves) over ``images``,
    with one loss per part of ``loss_groups`` (CliqueMining's two-loss step). Picklable when ``make_batches``
    is (the package's samplers are), so :func:`search_methods` can run it in worker processes."""

    name: str
    images: np.ndarray
    make_batches: Callable
    loss_groups: tuple[int, ...] | None = None

    def __call__(self, train_split, recipe, loss):
        return PlaceBatchSource(self.images, self.make_batches, loss=loss or L.MultiSimilarityLoss(),
                                loss_groups=self.loss_groups)


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


def _run(method, train_split, val_split, recipe, seed, lr, cache, progress) -> FineTuneResult:
    from .feature_cache import detach

    model = build_start(method, train_split, recipe, seed, cache)
    start = copy.deepcopy(model)
    detach(start.backbone)
    try:
        history = train(model, make_source(method, train_split, recipe), val_split, recipe.train_config(lr, seed),
                        progress=progress)
    finally:
        detach(model.backbone)
    return FineTuneResult(method.name, seed, float(lr), model, history, start)


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

    def table(self) -> str:
        """One line per lr: mean ± std of the selected val Recall over the search seeds, best epochs, the
        choice."""
        lines = [f"{self.method}: lr chosen on validation ({self.val_queries} queries, "
                 f"mean over seeds {list(self.search_seeds)})"]
        for lr in self.grid:
            vals = self.val_recall[lr]
            sd = float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0
            epochs = [self.histories[lr][s].best_epoch + 1 for s in self.search_seeds]
            lines.append(f"  lr {lr:.2g}: val R@1 {np.mean(vals):.3f} ± {sd:.3f}, best epoch {epochs}"
                         + ("   <- chosen" if lr == self.lr else ""))
        return "\n".join(lines)


def lr_search(method: Method, train_split, val_split, recipe: Recipe = RECIPE, seeds=(0,), *,
              cache: FrozenFeatureCache | None = None, progress: bool = False) -> LRSearch:
    """Fine-tune ``method`` at every lr of :meth:`Method.lr_grid` for the first ``recipe.search_seeds`` of
    ``seeds``; choose the lr with the highest mean selected validation Recall@``ns[0]`` over them (ties: the
    smaller lr); then fine-tune the remaining seeds at the chosen lr only. Every run is seeded on its own, so
    a seed's run at the chosen lr is the same whether or not it took part in the choice. A one-point grid has
    nothing to choose: every seed runs at it and counts in ``val_recall``.

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
    val_recall, histories, best, best_runs = {}, {}, -math.inf, {}
    for lr in grid:
        runs = {s: _run(method, train_split, val_split, recipe, s, lr, cache, progress) for s in chooses}
        val_recall[lr] = [r.history.best_recall for r in runs.values()]
        histories[lr] = {s: r.history for s, r in runs.items()}
        if float(np.mean(val_recall[lr])) > best:          # ascending grid: a tie keeps the smaller lr
            best, best_runs = float(np.mean(val_recall[lr])), runs
    chosen = next(iter(best_runs.values())).lr
    for s in seeds[len(chooses):]:                         # the other seeds: at the chosen lr only
        best_runs[s] = _run(method, train_split, val_split, recipe, s, chosen, cache, progress)
        histories[chosen][s] = best_runs[s].history
    search = LRSearch(method.name, chosen, grid, seeds, chooses, queries, val_recall,
                      {s: best_runs[s] for s in seeds}, histories, None if cache is None else cache.stats())
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
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        if "fork" not in mp.get_all_start_methods():
            raise ValueError("workers > 1 needs the 'fork' start method (Linux, macOS); use workers=1 here")
        with ProcessPoolExecutor(min(workers, len(tasks)), mp_context=mp.get_context("fork")) as pool:
            found = list(pool.map(_search_one, tasks))
    return dict(zip(names, found))
