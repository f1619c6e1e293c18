"""The course's fine-tuning protocol as data: :class:`Recipe`, every setting a fine-tuning run does not vary."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from .. import losses as L
from .._checks import check_int, check_positive
from ..aggregation import AGGREGATOR_NAMES
from ..feature_cache import CACHE_DTYPES
from ..training import OPTIMIZERS, TrainConfig
from ..training.config import DEFAULT_LR, train_config_from


@dataclass(frozen=True)
class Recipe:
    """Every default of the course's fine-tuning protocol (:mod:`vpr_nb.recipe`'s docstring gives each one's
    source)."""

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
    salad_kmeans_scores: bool = False            # on: SALAD's score head from NetVLAD's k-means logits, so that
                                                 # assignments compare from one start (vpr_nb.onoff.salad)
    salad_kmeans_temperature: float = 1.0        # those logits / this (> 1: a softer start; vpr_nb.onoff.salad_fair
                                                 # levels Sinkhorn's start with softmax's by it)
    # optimiser (notebook 04)
    optimizer: str = "adam"
    lr: float = DEFAULT_LR                       # 1e-3 (vpr_nb.training.config): a run without search (e.g. a
                                                 # CI smoke test); also in lr_grid
    weight_decay: float = 1e-3
    step_size: int = 5
    gamma: float = 0.5
    # selection
    lr_grid: tuple[float, ...] = (3e-4, 1e-3, 3e-3)   # x3 around notebook 04's 1e-3 (+ each method's paper_lr)
    max_epochs: int = 24             # measured: SALAD stops at epochs 12-13 (best 8-9), GeM at 7-10
    patience: int = 6                # no arm cut short: at 6, not 4, 16 of notebook 03's 80 runs find a later best
    initial_candidate: bool = True
    min_val_queries: int = 500       # below it, choose the lr over >= search_seeds seeds
    search_seeds: int = 3            # the lr is chosen on a run's first 3 seeds (on notebook 03's 8 searched
                                     # rows and 06's 2 arms the same rate as the mean over all 5 seeds)
    halving_epochs: int = 3          # successive halving: after 3 epochs the better half of the lrs (mean val
                                     # R@1 so far over the search seeds) trains on, the rest stop (0: off)
    lr_extend: int = 3               # the grid grows by up to 3 steps of the 1-3 ladder beyond an edge the
                                     # chosen lr sits on, so that the choice is interior (0: never)
    ns: tuple[int, ...] = (1, 5, 10)
    # frozen-block cache
    frozen_cache: bool = True
    cache_dtype: str = "float32"

    def __post_init__(self):
        ints = ("batch_size", "num_negatives", "num_candidates", "places_per_batch", "place_batches_per_epoch",
                "spots_per_place", "netvlad_clusters", "netvlad_per_image", "netvlad_niter", "salad_clusters",
                "salad_cluster_dim", "salad_token_dim", "salad_hidden_dim", "step_size", "max_epochs", "patience",
                "search_seeds")
        for name in ints:
            check_int(getattr(self, name), name)
        check_int(self.trainable_blocks, "trainable_blocks", minimum=0, maximum=4)
        check_int(self.images_per_place, "images_per_place", minimum=2)
        check_int(self.min_val_queries, "min_val_queries", minimum=0)
        check_int(self.halving_epochs, "halving_epochs", minimum=0)
        check_int(self.lr_extend, "lr_extend", minimum=0)
        for name in ("margin", "weight_decay", "salad_dropout"):
            check_positive(getattr(self, name), name, allow_zero=True)
        for name in ("lr", "gamma", "salad_kmeans_temperature"):
            check_positive(getattr(self, name), name)
        if self.max_heading_diff is not None:
            check_positive(self.max_heading_diff, "max_heading_diff")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.cache_dtype not in CACHE_DTYPES:
            raise ValueError(f"cache_dtype must be one of {sorted(CACHE_DTYPES)}, got {self.cache_dtype!r}")
        for name in ("salad_standardise", "salad_kmeans_scores", "initial_candidate", "frozen_cache"):
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
        """The recipe as plain data (for a notebook's ``EXPERIMENT`` config). Settings added after results were
        committed (:data:`OPTIONAL_SETTINGS`) appear only when set away from their default, so a recipe without
        them gives the dict it gave before and committed results stay keyed on the same config."""
        return {k: v for k, v in asdict(self).items()
                if not (k in OPTIONAL_SETTINGS and v == _DEFAULTS[k])}

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
        """The :class:`vpr_nb.training.TrainConfig` of one run of this recipe at ``lr`` from ``seed``: every
        TrainConfig field the recipe has by name (``optimizer``, ``weight_decay``, ``step_size``, ``gamma``,
        ``ns``, ``initial_candidate``, ``patience``), ``epochs`` = ``max_epochs``, and :data:`RUN_TRAINING`;
        the fields of :data:`TRAINCONFIG_DEFAULTS` keep TrainConfig's defaults."""
        return train_config_from(self, epochs=self.max_epochs, lr=lr, seed=seed, **RUN_TRAINING)


# How Recipe.train_config fills the TrainConfig fields that are not the recipe's by name, each on purpose
# (tests/test_train_config.py checks that every TrainConfig field is the recipe's by name or listed here):
# epochs is max_epochs, lr and seed are the run's, these are fixed, and these keep TrainConfig's defaults
# (the recipe has no such setting: momentum 0.9 where a recipe picks SGD, StepLR, no AMP on the CPU).
RUN_TRAINING = {"restore_best": True, "device": "cpu"}
TRAINCONFIG_DEFAULTS = ("momentum", "scheduler", "linear_end_factor", "linear_steps", "amp")


# Settings that are off by default and leave :meth:`Recipe.to_dict` alone while they are off (as
# vpr_nb.synthetic's OPTIONAL_CONTENT leaves a world's fingerprint alone).
OPTIONAL_SETTINGS = ("salad_kmeans_scores", "salad_kmeans_temperature")
_DEFAULTS = {f.name: f.default for f in fields(Recipe)}
RECIPE = Recipe()


def _check_recipe(recipe) -> Recipe:
    if not isinstance(recipe, Recipe):
        raise ValueError(f"recipe must be a vpr_nb.recipe.Recipe, got {type(recipe).__name__}")
    return recipe
