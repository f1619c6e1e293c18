"""One typed configuration for the reproduction commands, the presets, and the run logic behind them.

A run is a :class:`RunConfig` of five sections, each a dataclass that holds every default in one place:

- ``data``   (:class:`DataConfig`): dataset format and folders, image size, which data validates and
  which tests, image checks;
- ``model``  (:class:`ModelConfig`): backbone and aggregator (``vpr_nb.models.build_model``);
- ``source`` (:class:`SourceConfig`): how batches and the loss are formed (NetVLAD triplets or places);
  :data:`LOSSES` maps the loss name to its :mod:`vpr_nb.losses` object (:func:`build_loss`);
- ``train``  (:class:`vpr_nb.training.TrainConfig`): optimiser, schedule, epochs, seed, AMP;
- ``eval``   (:class:`EvalConfig`): Recall@N values, evaluation image size, Recall@N convention.

A preset (:data:`PRESETS`) holds only its deviations from these defaults. :func:`resolve` applies a
preset and ``section.key=value`` overrides; each value is parsed by the field's type (bool, int, float,
str, tuple, dict, ``None``), unknown sections and keys are refused with the list of known ones, and
:func:`validate` checks the whole config (choices, the val/test data, the model on a dummy batch)
before any data is read. :func:`train_run` and :func:`evaluate_run` are what ``python -m vpr_nb.train``
and ``python -m vpr_nb.evaluate`` call.

Validation and test data (``data.val_*`` / ``data.test_*``; ``None`` = the format's default):

========== ============================== ============================== ==========
format     val (model selection)          test (reported)                Recall@N
========== ============================== ============================== ==========
synthetic  the world's val split          the world's test split         exclude
pitts      ``pitts30k_val.mat``            ``pitts30k_test.mat``           all
gmberton   ``images/val``                  ``images/test``                 all
msls       must be given (e.g. Pitts30k)  MSLS-val (cph+sf, 740 queries) exclude
gsv-cities must be given (e.g. Pitts30k)  must be given (e.g. MSLS-val)  all
nordland   (a test set only: evaluate)    ``ref``/``query``                all
========== ============================== ============================== ==========

A config whose val and test are the same data is refused: the best epoch would be chosen on the test set.
"""
from __future__ import annotations

import copy
import inspect
import json
import math
import os
import typing
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from . import losses as L
from .training import SCHEDULERS, OPTIMIZERS, TrainConfig  # noqa: F401 (re-exported choices)

REAL_FORMATS = ("pitts", "gmberton", "msls", "gsv-cities", "nordland")
DATA_FORMATS = ("synthetic",) + REAL_FORMATS
SAMPLERS = ("random", "clique", "clique+random")
CHECK_IMAGES = ("skip", "fail", "off")
RECALL_CHOICES = ("auto", "all", "exclude")

# The one map from a loss name to its loss object: build_loss(source config) builds the class with the
# SourceConfig fields named as its parameters (e.g. "weighted" reads source.margin, source.sigma, source.eps).
LOSSES = {
    "triplet": L.TripletLoss,                 # Eq. (3) of DW-T-Loss
    "weighted": L.WeightedTripletLoss,        # Eq. (4) x Eq. (3), W-T-Loss
    "ce": L.CETripletLoss,                    # Eqs. (5)-(8), CE-Loss
    "dw": L.DWTripletLoss,                    # Eq. (9), DW-T-Loss
    "multi-similarity": L.MultiSimilarityLoss,  # Wang et al. Eq. (6) + miner: the loss of source.kind="places"
}
TRIPLET_LOSSES = tuple(k for k, cls in LOSSES.items() if issubclass(cls, L.TripletFamilyLoss))


# ================================================================================================ sections
@dataclass
class DataConfig:
    """Where the images come from. Synthetic fields: ``preset``, ``size``, ``seed``, ``overrides``
    (see :func:`vpr_nb.synthetic.make_dataset`); real formats: ``root`` and the rest."""

    format: str = "synthetic"                 # synthetic | pitts | gmberton | msls | gsv-cities | nordland
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
    pitts_set: str = "pitts30k"               # pitts30k | pitts250k: datasets/<set>_{train,val,test}.mat
    nordland_protocol: str = "auto"           # auto | 1frame | 25m (vpr_nb.datasets.load_nordland)
    msls_val_subset: str = "official"         # official (740 queries) | all
    gsv_cities: tuple[str, ...] | None = None # GSV-Cities cities (None: every Dataframes/*.csv)
    min_img_per_place: int = 4                # GSV-Cities places with fewer images are dropped
    check_files: bool = True                  # stat every listed image before training
    check_images: str = "skip"                # decode every image up front: skip (drop + report) | fail | off
    image_check_workers: int = 4


@dataclass
class ModelConfig:
    """``build_model(backbone, aggregator, backbone_kwargs=..., **aggregator_kwargs)``; the backbone's
    channel count is passed to the aggregator by ``build_model`` (do not set it)."""

    backbone: str = "small_cnn"               # small_cnn | vgg16 | dinov2
    aggregator: str = "gem"                   # gem | max | mean | netvlad | salad
    backbone_kwargs: dict = field(default_factory=dict)
    aggregator_kwargs: dict = field(default_factory=dict)
    init_per_image: int = 20                  # NetVLAD cluster init: local descriptors per image
    init_max_images: int = 500                # NetVLAD cluster init: images used


@dataclass
class SourceConfig:
    """Batches and loss: ``kind="triplet"`` (:class:`vpr_nb.training.TripletSource`) or ``"places"``
    (:class:`vpr_nb.training.PlaceBatchSource`, Multi-Similarity loss)."""

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
        parts = {}
        for name, cls_ in SECTIONS.items():
            parts[name] = _build_section(name, cls_, d.get(name, {}) or {})
        return cls(preset=str(d["preset"]), **parts)


# ================================================================================================ parsing
_HINTS: dict[type, dict] = {}


def _hints(cls) -> dict:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _none_text(v) -> bool:
    return isinstance(v, str) and v.strip().lower() in ("none", "null", "")


def parse_value(value, tp, where: str):
    """``value`` (a Python value, or the text of ``--set``) as type ``tp``; ValueError naming ``where``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None or _none_text(value):
            if type(None) in args:
                return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return parse_value(value, a, where)
            except ValueError as e:
                errors.append(str(e))
        raise ValueError(errors[0] if errors else f"{where}: cannot parse {value!r}")
    if tp is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in ("true", "yes", "on", "1"):
            return True
        if isinstance(value, str) and value.strip().lower() in ("false", "no", "off", "0"):
            return False
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ValueError(f"{where} must be true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool):
            raise ValueError(f"{where} must be an integer, got {value!r}")
        if isinstance(value, (int, np.integer)):
            return int(value)
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                try:
                    f = float(value)
                    if f.is_integer():
                        return int(f)
                except ValueError:
                    pass
        raise ValueError(f"{where} must be an integer, got {value!r}")
    if tp is float:
        if isinstance(value, bool):
            raise ValueError(f"{where} must be a number, got {value!r}")
        if isinstance(value, (int, float, np.integer, np.floating)):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value.strip())
            except ValueError:
                pass
        raise ValueError(f"{where} must be a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ValueError(f"{where} must be a string, got {value!r}")
    if origin is tuple or tp is tuple:
        if isinstance(value, str):
            text = value.strip()
            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                value = [v for v in text.strip("()[]").split(",") if v.strip()]
            if isinstance(value, (int, float, str)):
                value = [value]
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where} must be a list, e.g. [1,5,10], got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(parse_value(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if args:
            if len(value) != len(args):
                raise ValueError(f"{where} must have {len(args)} entries, got {list(value)!r}")
            return tuple(parse_value(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        return tuple(value)
    if tp is dict or origin is dict:
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                raise ValueError(f"{where} must be a JSON object, e.g. '{{\"width\": 8}}', got {value!r}") from None
        if not isinstance(value, dict):
            raise ValueError(f"{where} must be a dict (a JSON object), got {value!r}")
        return copy.deepcopy(value)
    raise ValueError(f"{where}: unsupported field type {tp!r}")


def _build_section(name: str, cls, values: dict):
    known = [f.name for f in fields(cls)]
    if not isinstance(values, dict):
        raise ValueError(f"section {name!r} must be a dict, got {type(values).__name__}")
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in section {name!r}; known keys: {', '.join(known)}")
    hints = _hints(cls)
    kw = {k: parse_value(v, hints[k], f"{name}.{k}") for k, v in values.items()}
    try:
        return cls(**kw)
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
# Each preset lists only what differs from the section defaults above.
_SYNTH_SMALL_CNN = {"model": {}, "data": {}}

PRESETS: dict[str, dict] = {
    "synthetic-city-triplet": {
        "source": {"max_heading_diff": 45.0},
        "train": {"epochs": 14},
    },
    "synthetic-city-dw": {
        "source": {"loss": "dw", "max_heading_diff": 45.0},
        "train": {"epochs": 14},
    },
    "synthetic-city-netvlad": {
        "model": {"aggregator": "netvlad", "aggregator_kwargs": {"num_clusters": 16}},
        "source": {"max_heading_diff": 45.0},
        "train": {"epochs": 14},
    },
    "synthetic-route-ms": {
        "data": {"preset": "route"},
        "source": {"kind": "places", "batches_per_epoch": 20},
        "train": {"epochs": 6, "optimizer": "adam", "lr": 1e-3, "weight_decay": 0.0},
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
# the MSLS train cities per batch; the clique loader (2000 mined batches per epoch) is cycled beside GSV-Cities
PRESETS["salad-cliquemining-msls"] = copy.deepcopy(PRESETS["salad-gsv"])
PRESETS["salad-cliquemining-msls"]["data"] = {"format": "msls", "image_size": (224, 224), "val_format": "pitts"}
PRESETS["salad-cliquemining-msls"]["source"].update(sampler="clique+random", clique_places=30,
                                                    clique_batches_per_epoch=2000)


def preset_names() -> list[str]:
    return sorted(PRESETS)


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
@dataclass(frozen=True)
class SplitSpec:
    """Which data a split is: format, folder and part (``train`` / ``val`` / ``test``)."""

    format: str
    root: str | None
    part: str

    def describe(self) -> str:
        return f"{self.format}:{self.part} ({self.root})" if self.root else f"{self.format}:{self.part}"


_NEED = "set data.{key}=/path/to/{what}"


def split_spec(data: DataConfig, which: str) -> SplitSpec:
    """The :class:`SplitSpec` of ``which`` (train / val / test) for ``data`` (see the module table)."""
    if which not in ("train", "val", "test"):
        raise ValueError(f"which must be 'train', 'val' or 'test', got {which!r}")
    fmt = data.format
    if which == "train":
        if fmt == "nordland":
            raise ValueError("Nordland is a test set (no training part): train on another dataset and run "
                             "python -m vpr_nb.evaluate --set data.test_format=nordland --set data.test_root=...")
        return SplitSpec(fmt, data.root, "train")
    own_fmt = data.val_format if which == "val" else data.test_format
    own_root = data.val_root if which == "val" else data.test_root
    if own_fmt is None:
        defaults = {"synthetic": fmt, "pitts": fmt, "gmberton": fmt, "nordland": fmt if which == "test" else None,
                    "msls": fmt if which == "test" else None, "gsv-cities": None}
        own_fmt = defaults[fmt]
        if own_fmt is None:
            hint = {"val": ("a published validation set, e.g. --set data.val_format=pitts --set "
                            "data.val_root=/data/Pittsburgh (Pitts30k-val, as SALAD selects)"),
                    "test": "e.g. --set data.test_format=msls --set data.test_root=/data/msls (MSLS-val)"}[which]
            why = "it is a training set only" if fmt == "gsv-cities" else "its only labelled evaluation data is the test set"
            raise ValueError(f"data.format={fmt!r} has no default {which} data ({why}); give {hint}")
        if own_root is None and own_fmt == fmt:
            own_root = data.root
    if own_root is None and own_fmt != "synthetic":
        if own_fmt == fmt:
            own_root = data.root
        else:
            raise ValueError(f"data.{which}_format={own_fmt!r} needs its folder: set data.{which}_root=/path/to/{own_fmt}")
    part = which
    if own_fmt == "msls":
        part = "val"          # MSLS-val (cph, sf) is the labelled MSLS evaluation set
    elif own_fmt == "nordland":
        part = "test"
    elif own_fmt != fmt and own_fmt in ("pitts", "gmberton"):
        part = "val" if which == "val" else "test"
    return SplitSpec(own_fmt, None if own_root is None else str(own_root), part)


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


def _check_choice(value, choices, where):
    if value not in choices:
        raise ValueError(f"{where} must be one of {', '.join(map(str, choices))}, got {value!r}")


def _check_pos_int(v, where, minimum=1):
    if v is not None and v < minimum:
        raise ValueError(f"{where} must be >= {minimum}, got {v}")


def model_input_size(cfg: RunConfig) -> tuple[int, int]:
    """(H, W) of the training images."""
    if cfg.data.format == "synthetic":
        from .synthetic import make_config
        return tuple(make_config(cfg.data.preset, cfg.data.size, **cfg.data.overrides).image_size)
    return tuple(cfg.data.image_size)


def validate(cfg: RunConfig, *, for_training: bool = True) -> None:
    """Check the whole config without reading any data; ValueError says what and how to fix."""
    d, s, m, e = cfg.data, cfg.source, cfg.model, cfg.eval
    _check_choice(d.format, DATA_FORMATS, "data.format")
    for k in ("val_format", "test_format"):
        if getattr(d, k) is not None:
            _check_choice(getattr(d, k), DATA_FORMATS, f"data.{k}")
    _check_choice(d.check_images, CHECK_IMAGES, "data.check_images")
    _check_choice(d.pitts_set, ("pitts30k", "pitts250k"), "data.pitts_set")
    _check_choice(d.nordland_protocol, ("auto", "1frame", "25m"), "data.nordland_protocol")
    _check_choice(d.msls_val_subset, ("official", "all"), "data.msls_val_subset")
    _check_pos_int(d.min_img_per_place, "data.min_img_per_place")
    _check_pos_int(d.image_check_workers, "data.image_check_workers")
    for k in ("image_size",):
        if min(d.image_size) < 1:
            raise ValueError(f"data.image_size must be positive (H, W), got {d.image_size}")
    if d.format == "synthetic":
        from .synthetic import make_config
        try:
            make_config(d.preset, d.size, **d.overrides)
        except TypeError as exc:
            raise ValueError(f"data.overrides: {exc}") from None
    _check_choice(s.kind, ("triplet", "places"), "source.kind")
    _check_choice(s.loss, TRIPLET_LOSSES, "source.loss")
    _check_choice(s.sampler, SAMPLERS, "source.sampler")
    for k in ("batch_size", "num_negatives", "num_candidates", "cache_refresh", "places_per_batch",
              "batches_per_epoch", "clique_batches_per_epoch", "refresh_every", "clique_places"):
        _check_pos_int(getattr(s, k), f"source.{k}")
    _check_pos_int(s.images_per_place, "source.images_per_place", 2)
    if s.clique_places is not None and s.clique_places >= s.places_per_batch:
        raise ValueError(f"source.clique_places ({s.clique_places}) must be below source.places_per_batch "
                         f"({s.places_per_batch}): the rest of each batch are GSV-Cities places")
    for k in ("margin", "sigma", "eps", "same_place_threshold", "beta", "alpha"):
        if getattr(s, k) < 0 or (k in ("sigma", "eps", "same_place_threshold", "alpha", "beta") and getattr(s, k) == 0):
            raise ValueError(f"source.{k} must be positive, got {getattr(s, k)}")
    try:
        build_loss(s)                         # the loss object checks its own parameters (base, miner_epsilon, ...)
    except ValueError as exc:
        raise ValueError(f"source: {exc}") from None
    _check_choice(m.backbone, ("small_cnn", "vgg16", "dinov2"), "model.backbone")
    from .aggregation import AGGREGATOR_NAMES
    _check_choice(m.aggregator, AGGREGATOR_NAMES, "model.aggregator")
    ch = {"salad": "num_channels", "netvlad": "dim"}.get(m.aggregator, "in_channels")
    if ch in m.aggregator_kwargs:
        raise ValueError(f"model.aggregator_kwargs must not set {ch!r}: the backbone's channel count is passed "
                         f"to {m.aggregator} by build_model")
    _check_pos_int(e.k, "eval.k")
    _check_pos_int(e.batch_size, "eval.batch_size")
    _check_choice(e.recall, RECALL_CHOICES, "eval.recall")
    if e.ns is not None:
        if not e.ns or min(e.ns) < 1:
            raise ValueError(f"eval.ns must list positive N, got {e.ns}")
    if e.image_size is not None and min(e.image_size) < 1:
        raise ValueError(f"eval.image_size must be positive (H, W), got {e.image_size}")
    if for_training:
        if d.format != "synthetic" and not d.root:
            raise ValueError(f"preset needs the dataset location: --set data.root=/path/to/{d.format} "
                             "(see README, 'Real datasets')")
        split_spec(d, "train")
        check_val_test(d)
        if s.kind == "triplet" and d.format == "gsv-cities":
            raise ValueError("GSV-Cities has no queries, so it cannot give NetVLAD triplets: use source.kind=places")
        if s.kind == "places" and d.format in ("pitts", "gmberton"):
            raise ValueError(f"source.kind=places needs place ids, which format {d.format!r} does not have; "
                             "use gsv-cities, msls or synthetic data, or source.kind=triplet")
        if s.sampler == "clique+random" and s.kind == "places":
            if d.format != "msls":
                raise ValueError("source.sampler=clique+random mixes MSLS cliques with GSV-Cities places: "
                                 "data.format must be msls")
            if not d.gsv_root and d.root:
                raise ValueError("source.sampler=clique+random needs the GSV-Cities folder: set data.gsv_root")
        if d.format != "synthetic":
            for spec in (split_spec(d, "train"), *check_val_test(d)):
                if not spec.root:
                    raise ValueError(f"preset needs the dataset location: --set data.root=/path/to/{d.format} "
                                     "(see README, 'Real datasets')")


# ================================================================================================ models
def build(cfg: RunConfig):
    """The model of ``cfg.model`` (``vpr_nb.models.build_model``)."""
    from .models import build_model
    m = cfg.model
    return build_model(m.backbone, m.aggregator, backbone_kwargs=m.backbone_kwargs or None, **m.aggregator_kwargs)


@torch.no_grad()
def check_model(model, sizes) -> int:
    """Run ``model`` on a dummy image of each (H, W) in ``sizes`` (eval mode); returns the descriptor size."""
    was = model.training
    model.eval()
    try:
        dev = next(model.parameters()).device
        for h, w in sizes:
            try:
                out = model(torch.zeros(1, 3, int(h), int(w), device=dev))
            except (ValueError, RuntimeError) as exc:
                raise ValueError(f"the model does not run on {h}x{w} images ({str(exc)[:300]}); "
                                 "check data.image_size / eval.image_size and the model section") from None
            if out.ndim != 2 or out.shape[0] != 1 or not torch.isfinite(out).all():
                raise ValueError(f"the model gives {tuple(out.shape)} non-finite/odd descriptors on {h}x{w} images")
    finally:
        model.train(was)
    return int(out.shape[1])


def build_checked(cfg: RunConfig):
    """Build the model and run it on a dummy batch at the training and evaluation sizes."""
    model = build(cfg)
    sizes = [model_input_size(cfg)]
    if cfg.eval.image_size is not None and tuple(cfg.eval.image_size) != sizes[0]:
        sizes.append(tuple(cfg.eval.image_size))
    check_model(model, sizes)
    return model


# ================================================================================================ steps
def steps_per_epoch(cfg: RunConfig, *, num_queries: int | None = None, num_places: int | None = None,
                    num_extra_places: int | None = None) -> int:
    """Optimiser steps per epoch of ``cfg.source`` for data of this size.

    triplets: ceil(training queries / batch_size) (pytorch-NetVlad: every query once per epoch);
    places, ``batches_per_epoch`` unset: ceil(places / places_per_batch) (GSV-Cities: every place once);
    clique+random: the GSV-Cities loader of ``places_per_batch - clique_places`` places, cycled together
    with the clique loader (Lightning's max_size_cycle): max(ceil(GSV places / (P - C)), clique batches).
    """
    s = cfg.source
    if s.kind == "triplet":
        if num_queries is None:
            raise ValueError("triplet sources need num_queries (the training queries)")
        return math.ceil(num_queries / s.batch_size)
    if s.batches_per_epoch is not None:
        return int(s.batches_per_epoch)
    if s.sampler == "clique+random":
        if num_extra_places is None:
            raise ValueError("clique+random needs num_extra_places (GSV-Cities places)")
        gsv = math.ceil(num_extra_places / (s.places_per_batch - clique_places(s)))
        return max(gsv, s.clique_batches_per_epoch or 0)
    if num_places is None:
        raise ValueError("place sources need num_places")
    return math.ceil(num_places / s.places_per_batch)


def optimizer_steps(cfg: RunConfig, **sizes) -> int:
    """Total optimiser steps of the run: ``train.epochs × steps_per_epoch`` (see :func:`steps_per_epoch`)."""
    return cfg.train.epochs * steps_per_epoch(cfg, **sizes)


def clique_places(s: SourceConfig) -> int:
    return s.clique_places if s.clique_places is not None else s.places_per_batch // 2


# ================================================================================================ data
def _load_geo(spec: SplitSpec, data: DataConfig):
    from . import datasets as D
    root = Path(spec.root)
    chk = data.check_files
    if spec.format == "pitts":
        return D.load(root / "datasets" / f"{data.pitts_set}_{spec.part}.mat", "pitts", check_files=chk)
    if spec.format == "gmberton":
        return D.load(root, "gmberton", split=spec.part, check_files=chk)
    if spec.format == "msls":
        if spec.part == "train":      # the official training cities that are present (never cph / sf)
            tv = root if root.name == "train_val" else root / "train_val"
            cities = [c for c in D.MSLS_CITIES["train"] if (tv / c).is_dir()]
            if not cities:
                raise FileNotFoundError(f"{tv}: none of the MSLS training cities ({', '.join(D.MSLS_CITIES['train'])}) "
                                        "is there; data.root must be the MSLS folder holding train_val/<city>")
            missing = [c for c in D.MSLS_CITIES["train"] if c not in cities]
            if missing:
                import warnings
                warnings.warn(f"{tv}: {len(missing)} of the {len(D.MSLS_CITIES['train'])} MSLS training cities are "
                              f"absent ({', '.join(missing[:5])}...); training on {', '.join(cities)}", stacklevel=2)
            return D.load(root, "msls", cities=cities, check_files=chk)
        sub = "official" if data.msls_val_subset == "official" else None
        return D.load(root, "msls", cities="val", val_subset=sub, check_files=chk)
    if spec.format == "gsv-cities":
        return D.load(root, "gsv-cities", cities=list(data.gsv_cities) if data.gsv_cities else None,
                      min_img_per_place=data.min_img_per_place, check_files=chk)
    if spec.format == "nordland":
        return D.load(root, "nordland", protocol=data.nordland_protocol, check_files=chk)
    raise ValueError(f"unknown data format {spec.format!r}")


def _image_check(geo, data: DataConfig, report: list):
    if data.check_images == "off":
        return geo
    from .datasets import drop_images, find_unreadable_images
    bad = find_unreadable_images(geo.db_paths + geo.q_paths, data.image_check_workers)
    if not bad:
        return geo
    if data.check_images == "fail":
        raise ValueError(f"{geo.name}: {len(bad)} image(s) cannot be decoded, first: {bad[0][0]} ({bad[0][1]}); "
                         "replace them, or set data.check_images=skip to leave them out")
    print(f"{geo.name}: skipping {len(bad)} unreadable image(s), first: {bad[0][0]} ({bad[0][1]})")
    report.extend((geo.name, p, err) for p, err in bad)
    return drop_images(geo, [p for p, _ in bad])


def load_split(cfg: RunConfig, which: str, *, image_size=None, report: list | None = None, synthetic=None):
    """One split (``train``/``val``/``test``) of ``cfg.data``, as the training loop and evaluation use it.

    Only this split's data is read. Images that cannot be decoded are dropped and appended to ``report``
    (``data.check_images=skip``) or refused (``fail``)."""
    d = cfg.data
    spec = split_spec(d, which)
    if spec.format == "synthetic":
        if synthetic is None:
            from .synthetic import make_dataset
            synthetic = make_dataset(d.preset, d.seed, d.size, **d.overrides)
        return getattr(synthetic, which)
    if not spec.root:
        raise ValueError(f"preset needs the dataset location: --set data.root=/path/to/{spec.format} "
                         "(see README, 'Real datasets')")
    from .datasets import TrainingSplit
    geo = _image_check(_load_geo(spec, d), d, report if report is not None else [])
    size = tuple(image_size) if image_size is not None else tuple(d.image_size)
    return TrainingSplit(geo, size)


def _paths(split) -> tuple[frozenset, frozenset] | None:
    geo = getattr(split, "geo", None)
    if geo is None:
        return None
    res = lambda ps: frozenset(os.path.realpath(p) for p in ps)  # noqa: E731
    return res(geo.db_paths), res(geo.q_paths)


def convention(cfg: RunConfig, split) -> str:
    """The Recall@N convention for ``split``: ``eval.recall`` or, with ``auto``, the split's format's."""
    if cfg.eval.recall != "auto":
        return cfg.eval.recall
    return getattr(split, "recall_convention", "exclude")


# ================================================================================================ samplers
def _place_pool(split):
    """(images, groups, utm, regions) of the training images that carry a place id (database, then queries)."""
    geo = getattr(split, "geo", None)
    has_q = split.q_images is not None and getattr(split, "q_place", None) is not None and len(split.q_utm) > 0
    if getattr(split, "db_place", None) is None:
        raise ValueError("place batches need place ids (db_place/q_place) for every training image")
    groups = np.concatenate([split.db_place, split.q_place]) if has_q else np.asarray(split.db_place)
    utm = np.concatenate([split.db_utm, split.q_utm]) if has_q else np.asarray(split.db_utm)
    dreg, qreg = getattr(split, "db_region", None), getattr(split, "q_region", None)
    if dreg is not None and (not has_q or qreg is not None):
        regions = np.concatenate([dreg, qreg]) if has_q else np.asarray(dreg)
    else:
        regions = np.zeros(len(groups), dtype=np.int64)
    if geo is not None:
        from .datasets import ImageArray
        images = ImageArray(list(geo.db_paths) + (list(geo.q_paths) if has_q else []), split.db_images.size)
    else:
        images = np.concatenate([split.db_images, split.q_images]) if has_q else split.db_images
    if len(groups) != len(utm):
        raise ValueError("place batches need place ids (db_place/q_place) for every training image")
    return images, np.asarray(groups, dtype=np.int64), utm, np.asarray(regions)


def _subset(images, idx):
    from .datasets import ImageArray
    if isinstance(images, ImageArray):
        return ImageArray([images.paths[i] for i in idx], images.size)
    return images[idx]


class EpochPlaceBatches:
    """GSV-Cities batches: every place (with >= K images) once per epoch in a random order, K random images
    each; with ``one_city`` the places are shuffled within each city and every batch comes from one city
    (places of another city at a boundary are replaced by unused places of the batch's city)."""

    def __init__(self, groups, regions, places_per_batch: int, images_per_place: int, num_batches: int,
                 one_city: bool = False):
        self.groups, self.regions = np.asarray(groups), np.asarray(regions)
        self.p, self.k, self.n, self.one_city = places_per_batch, images_per_place, num_batches, one_city
        ids, counts = np.unique(self.groups[self.groups >= 0], return_counts=True)
        self.places = ids[counts >= self.k]
        if len(self.places) < self.p:
            raise ValueError(f"only {len(self.places)} places have >= {self.k} images but a batch needs "
                             f"{self.p}; lower source.places_per_batch or source.images_per_place")
        order = np.argsort(self.groups, kind="stable")
        sorted_groups = self.groups[order]
        starts = np.searchsorted(sorted_groups, self.places, side="left")
        ends = np.searchsorted(sorted_groups, self.places, side="right")
        self.members = {int(g): order[a:b] for g, a, b in zip(self.places, starts, ends)}
        self.city = {int(g): self.regions[order[a]] for g, a in zip(self.places, starts)}
        self.cities = list(dict.fromkeys(self.city[int(g)] for g in self.places))
        self.by_city = {c: np.array([g for g in self.places if self.city[int(g)] == c]) for c in self.cities}
        if one_city:
            small = [c for c in self.cities if len(self.by_city[c]) < self.p]
            if small:
                raise ValueError(f"source.one_city_per_batch: city(ies) {small} have fewer than "
                                 f"{self.p} places; lower source.places_per_batch or set one_city_per_batch=false")

    def __call__(self, model, epoch, rng):
        rng = np.random.default_rng(int(rng.integers(2**63)))
        if self.one_city:
            seq = np.concatenate([rng.permutation(self.by_city[c]) for c in self.cities])
        else:
            seq = rng.permutation(self.places)
        out = np.empty((self.n, self.p, self.k), dtype=np.int64)
        for b in range(self.n):
            chunk = [int(seq[(b * self.p + j) % len(seq)]) for j in range(self.p)]
            if len(set(chunk)) < self.p:          # wrapped onto itself (tiny data): fill with unused places
                chunk = list(dict.fromkeys(chunk))
                rest = [int(g) for g in rng.permutation(self.places) if int(g) not in chunk]
                chunk += rest[:self.p - len(chunk)]
            if self.one_city:
                c = self.city[chunk[0]]
                keep = [g for g in chunk if self.city[g] == c]
                if len(keep) < self.p:            # a batch at a city boundary: fill it from its first city
                    used = set(keep)
                    spare = [int(g) for g in rng.permutation(self.by_city[c]) if int(g) not in used]
                    chunk = keep + spare[:self.p - len(keep)]
            for j, g in enumerate(chunk):
                out[b, j] = rng.choice(self.members[g], self.k, replace=False)
        return out


class CliqueSampler:
    """CliqueMining batches (:class:`vpr_nb.samplers.CliqueBatchMaker`) over the images with a place id.
    Cities are kept apart (their UTM is offset by 10 000 km per city), so a clique never spans two cities,
    and the similar groups of a batch are drawn within the anchor's city (``regions``), as published.
    ``state_dict`` holds the group descriptors, so a resumed run mines the same batches."""

    def __init__(self, images, groups, utm, regions, s: SourceConfig, num_batches: int, places: int):
        from .samplers import CliqueBatchMaker
        sub = np.flatnonzero(groups >= 0)
        _, gid = np.unique(groups[sub], return_inverse=True)
        _, rid = np.unique(regions[sub].astype(str), return_inverse=True)
        u = np.asarray(utm, dtype=np.float64)[sub].copy()
        u[:, 0] += rid.reshape(-1) * 1e7
        self.sub = sub
        self.maker = CliqueBatchMaker(_subset(images, sub), u, gid.reshape(-1), places, num_batches,
                                      images_per_place=s.images_per_place, same_place_threshold=s.same_place_threshold,
                                      similar_groups=s.similar_groups, refresh_every=s.refresh_every,
                                      regions=rid.reshape(-1))   # similar groups within the anchor's city, as published

    def __call__(self, model, epoch, rng):
        return self.sub[self.maker(model, epoch, rng)]

    def state_dict(self):
        return self.maker.state_dict()

    def load_state_dict(self, state):
        self.maker.load_state_dict(state)


class MixedSampler:
    """CliqueMining's batch: GSV-Cities places (``random``) followed by clique places of MSLS."""

    def __init__(self, random_part, clique_part, offset):
        self.random_part, self.clique_part, self.offset = random_part, clique_part, offset

    def __call__(self, model, epoch, rng):
        return np.concatenate([self.random_part(model, epoch, rng) + self.offset,
                               self.clique_part(model, epoch, rng)], axis=1)

    def state_dict(self):
        return self.clique_part.state_dict()

    def load_state_dict(self, state):
        self.clique_part.load_state_dict(state)


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


def build_source(cfg: RunConfig, train_split, extra_split=None):
    """The batch source of ``cfg.source`` on ``train_split`` (``extra_split``: the GSV-Cities pool of
    ``sampler="clique+random"``). Returns ``(source, steps_per_epoch)``."""
    from .training import PlaceBatchSource, TripletSource
    s = cfg.source
    if s.kind == "triplet":
        src = TripletSource(train_split, build_loss(s), batch_size=s.batch_size, num_negatives=s.num_negatives,
                            num_candidates=s.num_candidates, cache_refresh=s.cache_refresh,
                            max_heading_diff=s.max_heading_diff, neg_radius=s.neg_radius)
        return src, steps_per_epoch(cfg, num_queries=len(train_split.q_images))
    images, groups, utm, regions = _place_pool(train_split)
    k = s.images_per_place
    if s.sampler == "random":
        ids, counts = np.unique(groups[groups >= 0], return_counts=True)
        per_epoch = steps_per_epoch(cfg, num_places=int((counts >= k).sum()))
        make = EpochPlaceBatches(groups, regions, s.places_per_batch, k, per_epoch, s.one_city_per_batch)
    elif s.sampler == "clique":
        per_epoch = steps_per_epoch(cfg, num_places=len(np.unique(groups[groups >= 0])))
        make = CliqueSampler(images, groups, utm, regions, s, per_epoch, s.places_per_batch)
    else:
        if extra_split is None:
            raise ValueError("sampler 'clique+random' needs the GSV-Cities pool: set data.gsv_root")
        g_images, g_groups, _, g_regions = _place_pool(extra_split)
        from .datasets import ImageArray
        if not (isinstance(images, ImageArray) and isinstance(g_images, ImageArray)):
            raise ValueError("sampler 'clique+random' mixes two on-disk datasets (MSLS + GSV-Cities)")
        n_c = clique_places(s)
        gid, gcounts = np.unique(g_groups[g_groups >= 0], return_counts=True)
        per_epoch = steps_per_epoch(cfg, num_extra_places=int((gcounts >= k).sum()))
        rand = EpochPlaceBatches(g_groups, g_regions, s.places_per_batch - n_c, k, per_epoch, s.one_city_per_batch)
        clique = CliqueSampler(images, groups, utm, regions, s, per_epoch, n_c)
        make = MixedSampler(rand, clique, len(images))
        images = ImageArray(images.paths + g_images.paths, images.size)
    src = PlaceBatchSource(images, make, loss=build_loss(s))
    return src, per_epoch


# ================================================================================================ runs
class OutputFolder:
    """The ``--out`` folder of a run: refused when it already holds files unless ``resume``; locked while
    the run writes (``.lock`` with the process id; a lock left by a dead process is taken over)."""

    def __init__(self, path, resume: bool = False):
        self.path = Path(path)
        self.resume = bool(resume)
        self.lock = self.path / ".lock"
        self.held = False

    def check(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise ValueError(f"--out {p} is a file, not a folder")
        content = [c.name for c in p.iterdir()] if p.is_dir() else []
        if self.lock.exists():
            try:
                pid = int(self.lock.read_text().split()[0])
                os.kill(pid, 0)
                alive = pid != os.getpid()
            except (ValueError, IndexError, ProcessLookupError, PermissionError, OSError):
                alive = False
            if alive:
                raise ValueError(f"--out {p} is in use by another run (process {pid}, {self.lock}); "
                                 "choose another folder")
        if content and not self.resume and [c for c in content if c != ".lock"]:
            raise ValueError(f"--out {p} is not empty ({', '.join(sorted(content)[:4])}...): pass --resume to "
                             f"continue the run saved there, or choose a new folder")
        if self.resume and not (p / "config.json").is_file():
            raise ValueError(f"--resume: {p / 'config.json'} not found; there is no run to resume in {p}")

    def acquire(self) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        self.check()
        self.lock.write_text(f"{os.getpid()}\n")
        self.held = True

    def release(self) -> None:
        if self.held and self.lock.exists():
            self.lock.unlink()
        self.held = False


def train_run(cfg: RunConfig, out=None, *, resume: bool = False, progress: bool = True,
              folder: "OutputFolder | None" = None) -> dict:
    """Validate ``cfg`` and build its model (before any data is read), then load the data, train, select
    on the validation split, and test. With ``out``: ``history.json``, ``results.json``, ``checkpoints/``
    and ``unreadable_images.txt`` (images left out) are written there; with ``folder`` (the CLI's
    :class:`OutputFolder`) the folder is locked and ``config.json`` written once the model is built."""
    from . import seed_everything
    from .evaluation import evaluate_model
    from .training import train

    if not isinstance(cfg, RunConfig):
        raise ValueError(f"cfg must be a RunConfig (vpr_nb.config.resolve), got {type(cfg).__name__}")
    validate(cfg)
    out = None if out is None else Path(out)
    rank = torch.distributed.get_rank() if torch.distributed.is_available() and torch.distributed.is_initialized() else 0
    seed_everything(cfg.train.seed)
    model = build_checked(cfg)             # the model is built and run before any data loads
    if folder is not None and rank == 0:
        folder.acquire()
        (folder.path / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    synthetic = None
    if cfg.data.format == "synthetic":
        from .synthetic import make_dataset
        d = cfg.data
        synthetic = make_dataset(d.preset, d.seed, d.size, **d.overrides)
    bad: list = []
    train_split = load_split(cfg, "train", report=bad, synthetic=synthetic)
    val_split = load_split(cfg, "val", report=bad, synthetic=synthetic)
    test_split = load_split(cfg, "test", image_size=cfg.eval.image_size, report=bad, synthetic=synthetic)
    pv, pt = _paths(val_split), _paths(test_split)
    if pv is not None and pv == pt:
        raise ValueError(f"validation and test are the same images ({val_split.geo.name} = {test_split.geo.name}, "
                         "e.g. gmberton's MSLS where test is a link to val): the best epoch would be chosen on "
                         "the test set. Set data.val_format / data.val_root to a published validation set")
    if out is not None and rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    if out is not None and rank == 0 and bad:
        (out / "unreadable_images.txt").write_text("".join(f"{n}\t{p}\t{e}\n" for n, p, e in bad))
    extra = None
    if cfg.source.kind == "places" and cfg.source.sampler == "clique+random":
        from .datasets import TrainingSplit
        gsv = _image_check(_load_geo(SplitSpec("gsv-cities", cfg.data.gsv_root, "train"), cfg.data), cfg.data, bad)
        extra = TrainingSplit(gsv, tuple(cfg.data.image_size))
    if cfg.model.aggregator == "netvlad":            # NetVLAD's cluster step: k-means centroids and alpha
        from .models import init_netvlad
        init_netvlad(model, train_split.db_images, per_image=cfg.model.init_per_image, seed=cfg.train.seed,
                     max_images=cfg.model.init_max_images)
    source, per_epoch = build_source(cfg, train_split, extra)
    total = cfg.train.epochs * per_epoch
    conv = convention(cfg, test_split)
    if rank == 0 and progress:
        print(f"{cfg.preset}: {cfg.train.epochs} epochs x {per_epoch} steps = {total} optimiser steps; "
              f"val {split_spec(cfg.data, 'val').describe()}, test {split_spec(cfg.data, 'test').describe()}; "
              f"test Recall@N convention: {conv}")
    history = train(model, source, val_split, cfg.train,
                    checkpoint_dir=None if out is None else out / "checkpoints", resume=resume, progress=progress)
    ns = cfg.eval.ns or cfg.train.ns
    test = evaluate_model(model, test_split, ns=ns, batch_size=cfg.eval.batch_size, no_positive=conv)
    results = {"preset": cfg.preset, "best_epoch": history.best_epoch, "val_best_recall": history.best_recall,
               "test": {str(k): v for k, v in test.items()}, "steps_per_epoch": per_epoch,
               "optimizer_steps": total, "val": split_spec(cfg.data, "val").describe(),
               "test_data": split_spec(cfg.data, "test").describe(), "recall_convention": conv,
               "unreadable_images": len(bad)}
    if out is not None and rank == 0:
        (out / "history.json").write_text(json.dumps(history.to_dict(), indent=1))
        (out / "results.json").write_text(json.dumps(results, indent=1))
    return results


def _names(split, side: str) -> list[str]:
    geo = getattr(split, "geo", None)
    if geo is not None:
        return [str(p) for p in getattr(geo, f"{side}_paths")]
    return [f"{side}_{i}" for i in range(len(getattr(split, f"{side}_utm")))]


def evaluate_run(cfg: RunConfig, checkpoint, out=None, *, predictions: bool = False, grid_queries: int = 8,
                 device: str = "auto") -> dict:
    """Recall@N of the weights in ``checkpoint`` (a ``{"model": state_dict}`` file) on the test data of
    ``cfg`` only (``data.test_format``/``data.test_root``, by default the format's test set). Writes
    ``recalls.json`` (``num_queries`` = the queries Recall@N divides by), optionally ``predictions.csv``
    and ``retrieval_grid.png`` under ``out``."""
    from .evaluation import (as_image_array, compute_descriptors, counted_queries, positives_within, recall_at_n,
                             retrieve)
    from .training import load_checkpoint, resolve_device

    if not isinstance(cfg, RunConfig):
        raise ValueError(f"cfg must be a RunConfig, got {type(cfg).__name__}")
    validate(cfg, for_training=False)
    split_spec(cfg.data, "test")              # where the test data is, before reading anything
    state = load_checkpoint(checkpoint)
    if "model" not in state:
        raise ValueError(f"{checkpoint} has no 'model' entry; pass a best.pt/last.pt written by vpr_nb.training")
    model = build_checked(cfg)
    model.load_state_dict(state["model"])
    model.to(resolve_device(device))
    bad: list = []
    test = load_split(cfg, "test", image_size=cfg.eval.image_size or None, report=bad)
    conv = convention(cfg, test)
    db = compute_descriptors(model, test.db_images, cfg.eval.batch_size)
    q = compute_descriptors(model, test.q_images, cfg.eval.batch_size)
    ns = cfg.eval.ns or (1, 5, 10, 20)
    k = min(max(cfg.eval.k, max(ns)), len(db))
    _, idx = retrieve(db, q, k)
    pos = test.geo.positives() if hasattr(test, "geo") else positives_within(test.db_utm, test.q_utm, test.pos_radius)
    recalls = recall_at_n(idx, pos, [n for n in ns if n <= k], no_positive=conv)
    n_no_pos = sum(1 for p in pos if len(p) == 0)
    print(f"Recall@N convention: {conv} ({'every query counts' if conv == 'all' else 'queries without a positive are left out'}; "
          f"{n_no_pos} of {len(pos)} queries have no positive)")
    result = {"checkpoint": str(checkpoint), "data": asdict(cfg.data), "test_data": split_spec(cfg.data, "test").describe(),
              "num_db": len(db), "num_queries": counted_queries(pos, conv), "num_queries_total": len(q),
              "queries_without_positive": n_no_pos, "recall_convention": conv, "pos_radius": test.pos_radius,
              "unreadable_images": len(bad), "recall": {str(n): v for n, v in recalls.items()}}
    result = json.loads(json.dumps(result))
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "recalls.json").write_text(json.dumps(result, indent=1))
        if bad:
            (out / "unreadable_images.txt").write_text("".join(f"{n}\t{p}\t{e}\n" for n, p, e in bad))
        if predictions:
            import csv
            qn, dn = _names(test, "q"), _names(test, "db")
            with open(out / "predictions.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["query"] + [f"top{i + 1}" for i in range(k)])
                for i, row in enumerate(idx):
                    w.writerow([qn[i]] + [dn[j] for j in row])
        if grid_queries:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            from .plots import retrieval_grid
            qi = list(range(min(grid_queries, len(q))))
            top = min(5, k)
            q_imgs = np.asarray(as_image_array(test.q_images)[qi])
            needed = sorted({int(j) for i in qi for j in idx[i, :top]})
            remap = {j: r for r, j in enumerate(needed)}
            db_imgs = np.asarray(as_image_array(test.db_images)[needed])
            sub_pred = np.array([[remap[int(j)] for j in idx[i, :top]] for i in qi])
            sub_pos = [np.array([remap[int(j)] for j in pos[i] if int(j) in remap], dtype=np.int64) for i in qi]
            retrieval_grid(q_imgs, db_imgs, sub_pred, sub_pos, list(range(len(qi))), k=top)
            plt.savefig(out / "retrieval_grid.png", dpi=100, bbox_inches="tight")
            plt.close("all")
    return result


__all__ = ["DataConfig", "ModelConfig", "SourceConfig", "EvalConfig", "RunConfig", "PRESETS", "SECTIONS",
           "resolve", "with_overrides", "validate", "split_spec", "check_val_test", "build", "build_checked",
           "steps_per_epoch", "optimizer_steps", "load_split", "build_source", "train_run", "evaluate_run",
           "OutputFolder", "parse_value", "LOSSES", "TRIPLET_LOSSES", "build_loss"]
