"""The typed configuration of the reproduction commands: sections, presets, ``--set`` parsing, validation.

A run is a :class:`RunConfig` of five sections, dataclasses that hold every default once: ``data``
(:class:`DataConfig`: format, folders, image size, val/test data, format settings, image checks), ``model``
(:class:`ModelConfig`), ``source`` (:class:`SourceConfig`: triplets or places and the loss, built from
:data:`LOSSES` by :func:`build_loss`), ``train`` (:class:`vpr_nb.training.TrainConfig` itself, so its
learning-rate default is :data:`vpr_nb.training.config.DEFAULT_LR`, as the recipe's) and ``eval``
(:class:`EvalConfig`). A preset (:data:`PRESETS`) holds only its deviations from the defaults;
:func:`resolve` applies it and ``section.key=value`` overrides, each parsed by its field's type
(:func:`vpr_nb.typed_parsing.parse_value`, a dispatch table by type); unknown keys are refused with the
known ones; :func:`validate` checks the whole config before any data is read. Which data validates and
which tests (:func:`split_spec`) follows each format's line in :mod:`vpr_nb.datasets.registry`; a config
whose val and test are the same data is refused. What a run does with a config is :mod:`vpr_nb.experiment`.
"""
from __future__ import annotations

import copy
import inspect
import json
import typing
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch

from . import losses as L
from .aggregation import AGGREGATOR_NAMES, CHANNEL_ARGUMENTS
from .datasets.registry import REGISTRY, SYNTHETIC, SplitSpec, dataset_format, role_spec
from .losses import LOSSES, TRIPLET_LOSSES
from .models import BACKBONE_NAMES, BACKBONES
from .synthetic import make_config
from .training import SCHEDULERS, OPTIMIZERS, TrainConfig  # noqa: F401 (re-exported choices)
from .typed_parsing import parse_value

SOURCE_KINDS = ("triplet", "places")
SAMPLERS = ("random", "clique", "clique+random")
CHECK_IMAGES = ("skip", "fail", "off")
RECALL_CHOICES = ("auto", "all", "exclude")

# ================================================================================================ sections
@dataclass
class DataConfig:
    """Where the images come from. Synthetic fields: ``preset``, ``size``, ``seed``, ``overrides``
    (see :func:`vpr_nb.synthetic.make_dataset`); real formats: ``root`` and the rest. The format settings
    (``pitts_set`` ... ``min_img_per_place``) are read by the format's ``load_part`` (its registry line)."""

    format: str = "synthetic"                 # synthetic | a format of vpr_nb.datasets.REGISTRY
    root: str | None = None                   # the dataset folder (real formats)
    image_size: tuple[int, int] = (480, 640)  # (H, W) for training and validation (real formats)
    preset: str = "city"                      # synthetic world: "city" or "route"
    size: str = "tiny"                        # synthetic world size
    seed: int = 0                             # synthetic world seed
    overrides: dict = field(default_factory=dict)   # synthetic WorldConfig overrides
    val_format: str | None = None             # None: the format's default validation data
    val_root: str | None = None               # None: data.root
    test_format: str | None = None            # None: the format's default test data
    test_root: str | None = None              # None: data.root
    gsv_root: str | None = None               # GSV-Cities folder of sampler "clique+random" (CliqueMining)
    pitts_set: str = "pitts30k"               # pitts: datasets/<set>_{train,val,test}.mat
    nordland_protocol: str = "auto"           # nordland: auto | 1frame | 25m (vpr_nb.datasets.load_nordland)
    msls_val_subset: str = "official"         # msls: official (740 queries) | all
    gsv_cities: tuple[str, ...] | None = None # gsv-cities: cities (None: every Dataframes/*.csv)
    min_img_per_place: int = 4                # gsv-cities: places with fewer images are dropped
    check_files: bool = True                  # stat every listed image before training
    check_images: str = "skip"                # decode every image up front: skip (drop + report) | fail | off
    image_check_workers: int = 4


@dataclass
class ModelConfig:
    """``build_model(backbone, aggregator, backbone_kwargs=..., **aggregator_kwargs)``; the backbone's
    channel count is passed to the aggregator by ``build_model`` (do not set it)."""

    backbone: str = "small_cnn"               # vpr_nb.models.BACKBONE_NAMES
    aggregator: str = "gem"                   # vpr_nb.aggregation.AGGREGATOR_NAMES
    backbone_kwargs: dict = field(default_factory=dict)
    aggregator_kwargs: dict = field(default_factory=dict)
    init_per_image: int = 20                  # NetVLAD cluster init: local descriptors per image
    init_max_images: int = 500                # NetVLAD cluster init: images used


@dataclass
class SourceConfig:
    """Batches and loss: ``kind="triplet"`` (:class:`vpr_nb.training.TripletSource`) or ``"places"``
    (:class:`vpr_nb.training.PlaceBatchSource`, Multi-Similarity loss). ``sampler="clique+random"`` is
    CliqueMining's step: ``places_per_batch - clique_places`` GSV-Cities places and ``clique_places``
    clique places per batch, one MS loss over each, summed."""

    kind: str = "triplet"
    # --- triplets (NetVLAD / DW-T-Loss)
    loss: str = "triplet"                     # triplet | weighted | ce | dw (kind="places": multi-similarity)
    batch_size: int = 16                      # queries per optimiser step
    num_negatives: int = 5
    num_candidates: int = 300
    cache_refresh: int | None = None          # queries between descriptor-cache refreshes (None: per epoch)
    margin: float = L.DEFAULT_MARGIN          # Eq. (3) margin (losses triplet, weighted)
    sigma: float = L.DEFAULT_SIGMA            # Eq. (4) sigma, metres (losses weighted, dw)
    eps: float = L.DEFAULT_EPS                # Eq. (4) eps (losses weighted, dw)
    max_heading_diff: float | None = None
    neg_radius: float | None = None
    # --- places (GSV-Cities / SALAD / CliqueMining)
    sampler: str = "random"                   # random | clique | clique+random
    places_per_batch: int = 16
    images_per_place: int = 4
    batches_per_epoch: int | None = None      # None: one pass over the places, ceil(places / places_per_batch)
    one_city_per_batch: bool = False          # GSV-Cities: every batch from one city
    clique_places: int | None = None          # clique+random: clique places per batch (None: half)
    clique_batches_per_epoch: int | None = None   # clique+random: length of the clique loader (cycled)
    same_place_threshold: float = 25.0
    similar_groups: int = 15
    refresh_every: int | None = None          # epochs between clique descriptor refreshes (None: once)
    alpha: float = L.DEFAULT_MS_ALPHA         # Multi-Similarity loss (Wang et al. Eq. 6)
    beta: float = L.DEFAULT_MS_BETA
    base: float = L.DEFAULT_MS_BASE
    miner_epsilon: float | None = L.DEFAULT_MS_MINER_EPSILON   # None: every pair, no mining


@dataclass
class EvalConfig:
    """Test-time evaluation."""

    ns: tuple[int, ...] | None = None         # Recall@N values (None: train.ns)
    k: int = 20                               # retrievals per query written to predictions.csv
    image_size: tuple[int, int] | None = None # None: data.image_size (SALAD: 322 x 322)
    recall: str = "auto"                      # auto (the format's convention) | all | exclude
    batch_size: int = 256                     # images per descriptor batch


SECTIONS = {"data": DataConfig, "model": ModelConfig, "source": SourceConfig, "train": TrainConfig,
            "eval": EvalConfig}


@dataclass
class RunConfig:
    preset: str
    data: DataConfig
    model: ModelConfig
    source: SourceConfig
    train: TrainConfig
    eval: EvalConfig

    def to_dict(self) -> dict:
        """Plain JSON data (tuples as lists), as saved in ``config.json``."""
        return json.loads(json.dumps({"preset": self.preset, **{s: asdict(getattr(self, s)) for s in SECTIONS}}))

    @classmethod
    def from_dict(cls, d: dict) -> "RunConfig":
        """The inverse of :meth:`to_dict` (values re-parsed by type, unknown keys refused)."""
        if not isinstance(d, dict) or "preset" not in d:
            raise ValueError("a run config is a dict with 'preset' and the sections " + ", ".join(SECTIONS))
        unknown = sorted(set(d) - set(SECTIONS) - {"preset"})
        if unknown:
            raise ValueError(f"unknown config section(s) {unknown}; sections: {', '.join(SECTIONS)}")
        return cls(preset=str(d["preset"]), **{n: _build_section(n, c, d.get(n, {}) or {}) for n, c in SECTIONS.items()})


# ================================================================================================ parsing
_HINTS: dict[type, dict] = {}


def _hints(cls) -> dict:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _build_section(name: str, cls, values: dict):
    known = [f.name for f in fields(cls)]
    if not isinstance(values, dict):
        raise ValueError(f"section {name!r} must be a dict, got {type(values).__name__}")
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in section {name!r}; known keys: {', '.join(known)}")
    hints = _hints(cls)
    try:
        return cls(**{k: parse_value(v, hints[k], f"{name}.{k}") for k, v in values.items()})
    except TypeError as e:
        raise ValueError(f"section {name!r}: {e}") from None


def split_override(item: str) -> tuple[str, str, str]:
    """``"section.key=value"`` -> (section, key, value text), checking section and key."""
    if not isinstance(item, str) or "=" not in item or "." not in item.split("=", 1)[0]:
        raise ValueError(f"override {item!r} must look like section.key=value, e.g. train.lr=0.01")
    key, value = item.split("=", 1)
    section, name = key.strip().split(".", 1)
    if section not in SECTIONS:
        raise ValueError(f"unknown config section {section!r} in {item!r}; sections: {', '.join(SECTIONS)}")
    known = [f.name for f in fields(SECTIONS[section])]
    if name not in known:
        raise ValueError(f"unknown key {name!r} in section {section!r}; known keys: {', '.join(known)}")
    return section, name, value


# ================================================================================================ presets
# Each preset lists only what differs from the section defaults above. The learning rate's default is
# vpr_nb.training.config.DEFAULT_LR (1e-3, the train section is a TrainConfig); the synthetic-city presets train
# notebook 02's small CNN from scratch with SGD at notebook 02's 0.05, the paper presets at their papers' rates.
PRESETS: dict[str, dict] = {
    "synthetic-city-triplet": {
        "source": {"max_heading_diff": 45.0},
        "train": {"epochs": 14, "lr": 0.05},
    },
    "synthetic-city-dw": {
        "source": {"loss": "dw", "max_heading_diff": 45.0},
        "train": {"epochs": 14, "lr": 0.05},
    },
    "synthetic-city-netvlad": {
        "model": {"aggregator": "netvlad", "aggregator_kwargs": {"num_clusters": 16}},
        "source": {"max_heading_diff": 45.0},
        "train": {"epochs": 14, "lr": 0.05},
    },
    "synthetic-route-ms": {
        "data": {"preset": "route"},
        "source": {"kind": "places", "batches_per_epoch": 20},
        "train": {"epochs": 6, "optimizer": "adam", "weight_decay": 0.0},     # lr: the default, 1e-3
    },
    # DW-T-Loss on Pittsburgh30k = pytorch-NetVlad's recipe (main.py defaults) with the DW-T loss
    "dwt-pitts30k": {
        "data": {"format": "pitts"},
        "model": {"backbone": "vgg16", "aggregator": "netvlad",
                  "backbone_kwargs": {"pretrained_state_dict": None, "trainable_from": "conv5"},
                  "aggregator_kwargs": {"num_clusters": 64}},
        "source": {"loss": "dw", "batch_size": 4, "num_negatives": 10, "num_candidates": 1000,
                   "cache_refresh": 1000},
        "train": {"epochs": 30, "lr": 1e-4, "seed": 123, "ns": (1, 5, 10, 20)},
    },
    # DINOv2-SALAD (serizba/salad main.py): GSV-Cities, selection on Pitts30k-val, reported on MSLS-val
    "salad-gsv": {
        "data": {"format": "gsv-cities", "image_size": (224, 224), "val_format": "pitts", "test_format": "msls"},
        "model": {"backbone": "dinov2", "aggregator": "salad",
                  "backbone_kwargs": {"hub_dir": None, "model": "dinov2_vitb14", "num_trainable_blocks": 4},
                  "aggregator_kwargs": {"num_clusters": 64, "cluster_dim": 128, "token_dim": 256}},
        "source": {"kind": "places", "places_per_batch": 60, "one_city_per_batch": True},
        "train": {"epochs": 4, "optimizer": "adamw", "lr": 6e-5, "weight_decay": 9.5e-9, "scheduler": "linear",
                  "amp": True, "ns": (1, 5, 10, 20)},     # LinearLR 1 -> 0.2 over 4000 steps: the defaults
        "eval": {"image_size": (322, 322)},
    },
}
# DINOv2-SALAD + CliqueMining (serizba/cliquemining main.py): 30 GSV-Cities places + 30 clique places from
# the MSLS train cities per batch, one MS loss over each half, summed; the clique loader (2000 mined batches
# per epoch) is cycled beside GSV-Cities
PRESETS["salad-cliquemining-msls"] = copy.deepcopy(PRESETS["salad-gsv"])
PRESETS["salad-cliquemining-msls"]["data"] = {"format": "msls", "image_size": (224, 224), "val_format": "pitts"}
PRESETS["salad-cliquemining-msls"]["source"].update(sampler="clique+random", clique_places=30,
                                                    clique_batches_per_epoch=2000)


def resolve(preset: str, overrides=()) -> RunConfig:
    """The :class:`RunConfig` of ``preset`` with ``section.key=value`` overrides applied (parsed by type)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(sorted(PRESETS))}")
    if isinstance(overrides, str):
        raise ValueError("overrides must be a list of 'section.key=value' strings, not one string")
    values = {s: dict(copy.deepcopy(PRESETS[preset].get(s, {}))) for s in SECTIONS}
    for item in overrides:
        section, name, value = split_override(item)
        values[section][name] = value
    return RunConfig(preset=preset, **{s: _build_section(s, c, values[s]) for s, c in SECTIONS.items()})


def with_overrides(cfg: RunConfig, overrides=()) -> RunConfig:
    """A copy of ``cfg`` with ``section.key=value`` overrides applied."""
    d = cfg.to_dict()
    for item in overrides:
        section, name, value = split_override(item)
        d[section][name] = parse_value(value, _hints(SECTIONS[section])[name], f"{section}.{name}")
    return RunConfig.from_dict(d)


# ================================================================================================ validation
def split_spec(data: DataConfig, which: str) -> SplitSpec:
    """The :class:`~vpr_nb.datasets.registry.SplitSpec` of ``which`` (train / val / test) for ``data``: the
    ``data.<which>_format`` / ``_root`` given, else the format's default (:func:`~vpr_nb.datasets.registry.role_spec`)."""
    own = {"train": (None, None), "val": (data.val_format, data.val_root), "test": (data.test_format, data.test_root)}
    if which not in own:
        raise ValueError(f"which must be 'train', 'val' or 'test', got {which!r}")
    return role_spec(data.format, data.root, which, *own[which])


def _same_folder(a: str | None, b: str | None) -> bool:
    if a is None or b is None:
        return a == b
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return a == b


def check_val_test(data: DataConfig) -> tuple[SplitSpec, SplitSpec]:
    """(val, test) specs; ValueError when they name the same data (model selection on the test set)."""
    val, test = split_spec(data, "val"), split_spec(data, "test")
    if val.format == test.format and val.part == test.part and _same_folder(val.root, test.root):
        raise ValueError(
            f"validation and test are the same data ({test.describe()}): the best epoch would be chosen on the "
            f"test set. Validate on a published validation set instead, e.g. --set data.val_format=pitts "
            f"--set data.val_root=/data/Pittsburgh (Pitts30k-val, as SALAD does), or test elsewhere with "
            f"data.test_format / data.test_root")
    return val, test


# The field rules validate checks, declared once: allowed values and lower bounds (None values pass).
CHOICES = {"data.check_images": CHECK_IMAGES, "source.kind": SOURCE_KINDS, "source.loss": TRIPLET_LOSSES,
           "source.sampler": SAMPLERS, "model.backbone": BACKBONE_NAMES, "model.aggregator": AGGREGATOR_NAMES,
           "eval.recall": RECALL_CHOICES}
AT_LEAST = {"data.min_img_per_place": 1, "data.image_check_workers": 1, "source.batch_size": 1,
            "source.num_negatives": 1, "source.num_candidates": 1, "source.cache_refresh": 1,
            "source.places_per_batch": 1, "source.images_per_place": 2, "source.batches_per_epoch": 1,
            "source.clique_batches_per_epoch": 1, "source.refresh_every": 1, "source.clique_places": 1,
            "eval.k": 1, "eval.batch_size": 1}
POSITIVE = ("source.sigma", "source.eps", "source.same_place_threshold", "source.alpha", "source.beta")
SIZES = ("data.image_size", "eval.image_size", "eval.ns")          # tuples of positive entries


def _check_choice(value, choices, where):
    if value not in choices:
        raise ValueError(f"{where} must be one of {', '.join(map(str, choices))}, got {value!r}")


def _value(cfg: RunConfig, key: str):
    section, name = key.split(".")
    return getattr(getattr(cfg, section), name)


def build_loss(s: SourceConfig):
    """The loss object of a source config, from :data:`LOSSES`: ``source.loss`` for ``kind="triplet"``,
    Multi-Similarity for ``kind="places"``; its parameters are the SourceConfig fields of the same names."""
    if not isinstance(s, SourceConfig):
        raise ValueError(f"build_loss needs a SourceConfig, got {type(s).__name__}")
    name = s.loss if s.kind == "triplet" else "multi-similarity"
    if name not in TRIPLET_LOSSES + ("multi-similarity",):
        raise ValueError(f"source.loss must be one of {TRIPLET_LOSSES}, got {name!r}")
    cls = LOSSES[name]
    return cls(**{k: getattr(s, k) for k in inspect.signature(cls).parameters})


def _validate_fields(cfg: RunConfig) -> None:
    """The per-field rules above, the formats (from the registry, with their settings' choices) and the loss."""
    for key, choices in CHOICES.items():
        _check_choice(_value(cfg, key), choices, key)
    for key, low in AT_LEAST.items():
        if _value(cfg, key) is not None and _value(cfg, key) < low:
            raise ValueError(f"{key} must be >= {low}, got {_value(cfg, key)}")
    for key in POSITIVE + ("source.margin",):
        if _value(cfg, key) < 0 or (key in POSITIVE and _value(cfg, key) == 0):
            raise ValueError(f"{key} must be positive, got {_value(cfg, key)}")
    for key in SIZES:
        if _value(cfg, key) is not None and (not _value(cfg, key) or min(_value(cfg, key)) < 1):
            raise ValueError(f"{key} must list positive numbers, got {_value(cfg, key)}")
    d = cfg.data
    for key in ("format", "val_format", "test_format"):
        if key == "format" or getattr(d, key) is not None:
            _check_choice(getattr(d, key), (SYNTHETIC, *REGISTRY), f"data.{key}")
    for fmt in REGISTRY.values():
        for name, choices in fmt.settings.items():
            if name not in DataConfig.__dataclass_fields__:
                raise ValueError(f"format {fmt.name!r} reads data.{name}, which DataConfig does not have")
            if choices is not None:
                _check_choice(getattr(d, name), choices, f"data.{name}")
    if cfg.source.clique_places is not None and cfg.source.clique_places >= cfg.source.places_per_batch:
        raise ValueError(f"source.clique_places ({cfg.source.clique_places}) must be below source.places_per_batch "
                         f"({cfg.source.places_per_batch}): the rest of each batch are GSV-Cities places")
    try:
        build_loss(cfg.source)                # the loss object checks its own parameters (base, miner_epsilon, ...)
    except ValueError as exc:
        raise ValueError(f"source: {exc}") from None


def _validate_training_data(d: DataConfig, s: SourceConfig) -> None:
    """What training on ``d`` with ``s`` needs: the folders, val != test, queries or places."""
    need_root = ValueError(f"preset needs the dataset location: --set data.root=/path/to/{d.format} "
                           "(see docs/reproduction.md, 'Real datasets')")
    if d.format != SYNTHETIC and not d.root:
        raise need_root
    specs = (split_spec(d, "train"), *check_val_test(d))
    fmt = None if d.format == SYNTHETIC else dataset_format(d.format)
    if s.kind == "triplet" and fmt is not None and not fmt.queries:
        raise ValueError(f"format {d.format!r} has no queries, so it cannot give NetVLAD triplets: use source.kind=places")
    if s.kind == "places" and fmt is not None and not fmt.places:
        raise ValueError(f"source.kind=places needs place ids, which format {d.format!r} does not have; "
                         "use a format with places (e.g. gsv-cities, msls) or synthetic data, or source.kind=triplet")
    if s.kind == "places" and s.sampler == "clique+random":
        if fmt is None:
            raise ValueError("source.sampler=clique+random mixes clique places of an on-disk dataset (MSLS) with "
                             "GSV-Cities places: data.format must be a real format with places, e.g. msls")
        if not d.gsv_root:
            raise ValueError("source.sampler=clique+random needs the GSV-Cities folder: set data.gsv_root")
    if any(spec.format != SYNTHETIC and not spec.root for spec in specs):
        raise need_root


def check_backbone_kwargs(m: ModelConfig) -> None:
    """``model.backbone_kwargs`` holds only arguments of the backbone's constructor (before anything is built)."""
    build = BACKBONES.get(m.backbone)
    if build is None:
        return                                # an unknown backbone name is refused by the choices check
    params = inspect.signature(build).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return
    unknown = sorted(set(m.backbone_kwargs) - set(params))
    if unknown:
        raise ValueError(f"model.backbone_kwargs: {m.backbone} does not take {', '.join(map(repr, unknown))}; "
                         f"its options are {', '.join(params)} (e.g. --set model.backbone_kwargs='{{\"width\": 8}}')")


def check_device(name: str, where: str = "train.device") -> None:
    """A CUDA device only where CUDA is available (and that many GPUs exist)."""
    if not isinstance(name, str) or not name.startswith("cuda"):
        return
    if not torch.cuda.is_available():
        raise ValueError(f"{where}={name}: CUDA is not available on this machine; use {where}=auto (CUDA when "
                         f"present, else CPU) or {where}=cpu")
    index = name.partition(":")[2]
    if index and (not index.isdigit() or int(index) >= torch.cuda.device_count()):
        raise ValueError(f"{where}={name}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                         f"cuda:0 to cuda:{torch.cuda.device_count() - 1}")


def validate(cfg: RunConfig, *, for_training: bool = True) -> None:
    """Check the whole config without reading any data; ValueError says what and how to fix."""
    if not isinstance(cfg, RunConfig):
        raise ValueError(f"cfg must be a RunConfig (vpr_nb.config.resolve), got {type(cfg).__name__}")
    _validate_fields(cfg)
    m, d = cfg.model, cfg.data
    check_backbone_kwargs(m)
    if CHANNEL_ARGUMENTS[m.aggregator] in m.aggregator_kwargs:
        raise ValueError(f"model.aggregator_kwargs must not set {CHANNEL_ARGUMENTS[m.aggregator]!r}: the backbone's "
                         f"channel count is passed to {m.aggregator} by build_model")
    if d.format == SYNTHETIC:
        try:
            make_config(d.preset, d.size, **d.overrides)
        except TypeError as exc:
            raise ValueError(f"data.overrides: {exc}") from None
    if for_training:
        check_device(cfg.train.device)
        _validate_training_data(d, cfg.source)


__all__ = ["DataConfig", "ModelConfig", "SourceConfig", "EvalConfig", "RunConfig", "PRESETS", "SECTIONS",
           "resolve", "with_overrides", "validate", "split_spec", "check_val_test", "SplitSpec", "split_override",
           "parse_value", "LOSSES", "TRIPLET_LOSSES", "build_loss", "check_device", "check_backbone_kwargs"]
