"""The course backbone: the course's stand-in for ImageNet-VGG16 (DW-T-Loss) and DINOv2 (SALAD).

Both papers fine-tune a *pretrained* backbone; training a random-init CNN from scratch for a few
epochs instead collapses (every image gets nearly the same descriptor) and says nothing about a
loss or an aggregator. This module trains, once, a :class:`vpr_nb.models.SmallCNN` on a synthetic
corpus that is **disjoint from every world a notebook evaluates on** (world seeds
``CORPUS_SEED_BASE`` and up, never the notebooks' seeds 0–4), both presets, every condition,
database and query images of every split, with a generic objective: the Multi-Similarity loss
(Wang et al., CVPR 2019) over P places × K images, places being 30 m of street × 4 view directions, on the
GeM descriptor, plus 0.07 × a local InfoNCE term (:func:`vpr_nb.losses.local_infonce`, Eq. L) on the features
before the last ReLU: 32 database images per step against their **condition twins** (the same camera rendered
under another of its world's conditions) shifted by 1–2 feature columns, every other sampled position a negative.

Why the local term: trained with the MS loss alone, the backbone's local features (before the last ReLU)
spanned about 12 effective dimensions of 128 with a mean within-image cosine of 0.90, which leaves SALAD's
optimal-transport assignment nothing to sort (notebook 05). Measured at the full budget, unpinned kernels:
frozen backbone + GeM test R@1 on the city and the route (seed 0); the local-feature probe on the city test
database before / after the last ReLU; NetVLAD-16 with k-means initialisation, frozen, reading the features
before / after the last ReLU:

=====================================================  =====  =====  ===========  ===========  ===========
configuration                                          city   route  eff. dim.    cosine       NetVLAD
=====================================================  =====  =====  ===========  ===========  ===========
MS loss alone (the previous backbone; older route)     0.714  0.520  ≈ 12 / –     0.90 / –     0.802/0.437
local term on shifted copies of the same image         0.799  0.603  35.3 / 70.9  0.10 / 0.31  0.52 /0.69
 (+ a GroupNorm on the last layer, 8 groups; pinned)
the same on the features after the ReLU                0.758  0.704  8.2 / 81.2   0.78 / 0.10  0.66 /0.54
**condition twins, shifted** (the default)             0.786  0.715  45.8 / 69.6  0.11 / 0.29  0.66 /0.76
(the same, pinned: the committed checkpoint)           0.748  0.693  47.6 / –     0.12 / –     0.65 /0.76
condition twins, weight 0.15                           0.648  0.637  59.7 / 72.2  0.07 / 0.32  0.67 /0.68
=====================================================  =====  =====  ===========  ===========  ===========

Shifted copies of one image teach the features to tell positions apart, not to survive a change of condition:
the route and NetVLAD suffer. Condition twins give both. Whichever side of the ReLU the local term acts on
becomes diverse and the *other* side reads better in NetVLAD; with the term before the ReLU, NetVLAD, SALAD,
max and mean pooling read after it (:mod:`vpr_nb.recipe`, notebook 04 measures it). A weight of 0.15 costs
GeM a tenth of its Recall. The committed checkpoint's card records its own numbers (``probes``,
``held_out``), computed with the pinned kernels.

    python -m vpr_nb.pretrain                                             # the committed checkpoint (vpr_nb/weights/)
    python -m vpr_nb.pretrain --profile quick --out /tmp/cb.pt            # a 20-second smoke run

writes a weights-only half-precision state dict and a JSON beside it (command, config, sha256, torch
version, training time, Recall@N of the frozen backbone + GeM on held-out worlds).
:func:`course_backbone` loads it with ``torch.load(..., weights_only=True)`` after checking the hash,
optionally with only the last blocks trainable, the way VGG16 conv5 / DINOv2's last 4 blocks are.
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
import platform
import sys
import time
import typing
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from . import cli
from ._checks import check_int
from .aggregation import GeM
from .evaluation import evaluate_descriptors, evaluate_model, images_to_tensor, raw_pixel_descriptors
from .kernels import apply_in_process, cpu_description
from .losses import LOCAL_NEGATIVES, MultiSimilarityLoss, local_infonce
from .models import SmallCNN, VPRModel, load_state_checked, read_weights
from .package_data import checkout_root, course_backbone_path
from .probes import local_feature_probe, near_duplicate_probe
from .samplers import random_place_batches
from .seeding import seed_everything
from .synthetic import make_dataset
from .training import PlaceBatchSource, TrainConfig, save_checkpoint, train
from .typed_parsing import parse_value

CHECKPOINT = course_backbone_path()    # vpr_nb/weights/course_backbone.pt, package data (installed with vpr_nb)
CORPUS_SEED_BASE = 100        # corpus worlds use seeds >= 100; notebooks use seeds 0-4
HELD_OUT = (("city", 0, "test"), ("route", 0, "test"), ("city", 97, "test"))  # never trained on
SELECTION_WORLD = ("city", 98, "val")    # best epoch chosen here, never on a reported world


@dataclass(frozen=True)
class PretrainConfig:
    """Every knob of the pretraining, in one place (``PROFILES`` holds the named deviations)."""

    city_seeds: tuple[int, ...] = (100, 101, 102, 103, 104, 105)
    route_seeds: tuple[int, ...] = (100, 101, 102)
    world_size: str = "tiny"
    spots_per_place: int = 3          # city: a place = 3 street spots (30 m) x one of 4 view directions
    width: int = 48                   # SmallCNN width (channels of the first blocks)
    out_channels: int = 128
    places_per_batch: int = 32
    images_per_place: int = 4
    batches_per_epoch: int = 120
    epochs: int = 12
    lr: float = 2e-3                  # Adam; StepLR halves it every step_size epochs
    step_size: int = 4
    seed: int = 0
    # richer local features (what NetVLAD and SALAD assign to clusters): a local InfoNCE term between each image
    # and a shifted crop of its condition twin (vpr_nb.losses.local_infonce); optionally a GroupNorm on the projection
    final_norm: int = 0               # GroupNorm groups on the 1x1 projection (0: none; tried, not kept: above)
    local_weight: float = 0.07        # weight of the local term beside the MS loss (0: off); the choice: above
    local_shift: int = 2              # the crop drops 1..local_shift feature columns (4 px each) on the left
    local_temperature: float = 0.1
    local_negatives: str = "batch"    # "image": the other positions of the same image; "batch": of every image
    local_views: int = 32             # image pairs per step for the local term
    local_twins: bool = True          # the second view: the same camera under another condition (then shifted)

    def __post_init__(self):
        for name in ("city_seeds", "route_seeds"):
            seeds = tuple(getattr(self, name))
            if any(check_int(s, f"{name} entry", minimum=0) < CORPUS_SEED_BASE for s in seeds):
                raise ValueError(f"{name} {seeds}: corpus world seeds must be >= {CORPUS_SEED_BASE} so that the "
                                 f"corpus never overlaps a world the notebooks evaluate on (seeds 0-4)")
            object.__setattr__(self, name, seeds)
        if not self.city_seeds and not self.route_seeds:
            raise ValueError("the corpus needs at least one world: give city_seeds or route_seeds")
        for name in ("spots_per_place", "width", "out_channels", "places_per_batch", "batches_per_epoch", "epochs",
                     "step_size", "local_shift", "local_views"):
            check_int(getattr(self, name), name)
        check_int(self.images_per_place, "images_per_place", minimum=2)
        check_int(self.final_norm, "final_norm", minimum=0)
        if self.final_norm and self.out_channels % self.final_norm:
            raise ValueError(f"final_norm={self.final_norm} groups must divide out_channels={self.out_channels}")
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")
        if not (self.local_weight >= 0 and self.local_temperature > 0):
            raise ValueError(f"local_weight must be >= 0 and local_temperature > 0, got {self.local_weight} and "
                             f"{self.local_temperature}")
        if self.local_negatives not in LOCAL_NEGATIVES:
            raise ValueError(f"local_negatives must be one of {LOCAL_NEGATIVES}, got {self.local_negatives!r}")


PROFILES = {
    "full": {},
    "quick": dict(city_seeds=(100,), route_seeds=(100,), width=16, batches_per_epoch=6, epochs=2,
                  places_per_batch=16),
}


def place_labels(ds, spots_per_place: int) -> np.ndarray:
    """Place label of every image of ``ds`` (database first, then queries).

    City: ``spots_per_place`` consecutive database spots along a street (10 m apart; queries belong to
    their nearest spot) × which of 4 directions (0–90°, 90–180°, …) the camera faces; route: the
    world's 5-frame place groups. Images of one label see the same facades from a few metres apart,
    under any condition."""
    place = np.concatenate([ds.db_place, ds.q_place]).astype(np.int64)
    if ds.config.preset == "city":
        place = place // spots_per_place
    heading = np.concatenate([ds.db_heading, ds.q_heading]) % 360
    keys = np.stack([place, (heading // 90).astype(np.int64)], 1)
    return np.unique(keys, axis=0, return_inverse=True)[1].ravel()


def build_corpus(cfg: PretrainConfig, progress: bool = True, twins: bool = False):
    """uint8 images (N, H, W, 3) and int64 place labels (N,) of every corpus world, all splits, and with
    ``twins`` their **condition twins** for the local term: every database image rendered again from the same
    camera under each of its world's query conditions. Returns (images, labels, (twin_of, twin_images)):
    ``twin_images[i]`` shows what ``images[twin_of[i]]`` shows, from the same camera, under another condition
    (None without twins)."""


    worlds = [("city", s) for s in cfg.city_seeds] + [("route", s) for s in cfg.route_seeds]
    images, labels, offset, start, twin_of, twin_images = [], [], 0, 0, [], []
    for preset, seed in tqdm(worlds, desc="rendering corpus", disable=not progress, leave=False):
        ds = make_dataset(preset, seed=seed, size=cfg.world_size)
        lab = place_labels(ds, cfg.spots_per_place)
        images += [ds.db_images, ds.q_images]
        labels.append(lab + offset)
        offset += int(lab.max()) + 1
        for cond in (c for c in ds.config.query_conditions if twins and c != ds.config.db_condition):
            twin_images.append(make_dataset(preset, seed=seed, size=cfg.world_size, db_condition=cond).db_images)
            twin_of.append(start + np.arange(len(ds.db_images)))        # the same cameras, in the same order
        start += len(ds.db_images) + len(ds.q_images)
    pairs = (np.concatenate(twin_of), np.concatenate(twin_images)) if twin_images else None
    return np.concatenate(images), np.concatenate(labels), pairs


def _split(preset: str, seed: int, split: str):
    return make_dataset(preset, seed=seed, splits=(split,)).split(split)


def held_out_recalls(backbone, ns=(1, 5, 10)) -> dict[str, dict]:
    """Recall@N of ``backbone`` frozen + GeM (and of raw pixels) on the :data:`HELD_OUT` worlds."""

    model = VPRModel(backbone, GeM(in_channels=backbone.out_channels))
    out = {}
    for preset, seed, split in HELD_OUT:
        s = _split(preset, seed, split)
        raw = evaluate_descriptors(raw_pixel_descriptors(s.db_images), raw_pixel_descriptors(s.q_images),
                                   s.db_utm, s.q_utm, s.pos_radius, ns)
        out[f"{preset} seed {seed} {split}"] = {
            "course backbone + GeM": {f"R@{n}": round(float(v), 4) for n, v in evaluate_model(model, s, ns).items()},
            "raw pixels": {f"R@{n}": round(float(v), 4) for n, v in raw.items()}}
    return out


def _local_term_source(images, batches, cfg: PretrainConfig, twins=None):
    """The pretraining's batch source: the MS loss over P x K place batches (:class:`vpr_nb.training.PlaceBatchSource`),
    plus (``cfg.local_weight`` > 0) the local InfoNCE term of :func:`vpr_nb.losses.local_infonce` on
    ``cfg.local_views`` image pairs per step, read before the backbone's final ReLU: each pair is a corpus image
    and its condition twin (``twins`` = (twin_of, twin_images), :func:`build_corpus`; without twins the image
    itself), the second one cropped by 1..``cfg.local_shift`` feature columns (drawn per step from the epoch's
    generator)."""

    class LocalContrastSource(PlaceBatchSource):
        def steps(self, model, rng, shard=(0, 1), device=None):
            if cfg.local_weight and shard != (0, 1):
                raise ValueError("the local term of the course backbone's pretraining runs in one process")
            for loss in super().steps(model, rng, shard, device):
                yield loss + cfg.local_weight * self.local_term(model, rng, device) if cfg.local_weight else loss

        def local_term(self, model, rng, device):
            before_relu = model.backbone.features[:-1]
            offset = int(rng.integers(1, cfg.local_shift + 1))
            pick = rng.integers(0, len(twins[0]) if twins is not None else len(self.x), cfg.local_views)
            anchors, views = (twins[0][pick], twins[1][pick]) if twins is not None else (pick, self.x[pick])
            first = before_relu(images_to_tensor(self.x[anchors]).to(device))
            shifted = before_relu(images_to_tensor(views).to(device)[:, :, :, SmallCNN.stride * offset:])
            gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
            return local_infonce(first, shifted, offset, cfg.local_temperature, cfg.local_negatives, generator=gen)

    return LocalContrastSource(images, batches, loss=MultiSimilarityLoss())   # alpha 1, beta 50, base 0, miner 0.1


PROBE_WORLDS = {"local features": ("city", 0, "test"), "near duplicates": ("route", 0, "test")}


def backbone_probes(backbone: SmallCNN) -> dict:
    """The probes of :mod:`vpr_nb.probes` for the card, on the notebooks' test splits (:data:`PROBE_WORLDS`):
    the local features before the final ReLU on the city's database images (effective dimension, Eq. 1, and
    within-image cosine; the course's targets >= 32 and <= 0.5) and the near-duplicate rate on the route at 5
    and 10 m, raw pixels and frozen backbone + GeM (targets <= 0.5 and <= 0.25 at 5 m)."""


    pre = copy.deepcopy(backbone)
    pre.features[-1] = torch.nn.Identity()
    city, route = (_split(*PROBE_WORLDS[k]) for k in ("local features", "near duplicates"))
    local = local_feature_probe(pre, city.db_images)
    model = VPRModel(backbone, GeM(in_channels=backbone.out_channels))
    steps = (5.0, 10.0)
    return {"local features": {"world": " ".join(map(str, PROBE_WORLDS["local features"])) + " database",
                               **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in local.items()}},
            "near duplicates": {"world": " ".join(map(str, PROBE_WORLDS["near duplicates"])),
                                "raw pixels": {f"{k:g} m": round(v, 4) for k, v in
                                               near_duplicate_probe(route, None, steps).items()},
                                "course backbone + GeM": {f"{k:g} m": round(v, 4) for k, v in
                                                          near_duplicate_probe(route, model, steps).items()}}}


def pretrain(cfg: PretrainConfig, progress: bool = True) -> tuple[SmallCNN, dict]:
    """Train the course backbone on the corpus; returns (backbone, info) deterministically."""

    t0 = time.perf_counter()
    images, labels, twins = build_corpus(cfg, progress, twins=cfg.local_weight > 0 and cfg.local_twins)
    render_s = time.perf_counter() - t0
    seed_everything(cfg.seed)
    backbone = SmallCNN(width=cfg.width, out_channels=cfg.out_channels, final_norm=cfg.final_norm)
    model = VPRModel(backbone, GeM(in_channels=backbone.out_channels))

    def batches(_model, _epoch, rng):
        return random_place_batches(labels, cfg.places_per_batch, cfg.images_per_place,
                                    num_batches=cfg.batches_per_epoch, seed=rng)

    source = _local_term_source(images, batches, cfg, twins)
    tcfg = TrainConfig(epochs=cfg.epochs, optimizer="adam", lr=cfg.lr, weight_decay=0.0,
                       step_size=cfg.step_size, gamma=0.5, seed=cfg.seed, ns=(1, 5), device="cpu")
    sel = _split(*SELECTION_WORLD)
    t1 = time.perf_counter()
    hist = train(model, source, sel, tcfg, progress=progress)
    info = {"corpus": {"images": int(len(images)), "places": int(labels.max() + 1),
                       "condition twins": 0 if twins is None else int(len(twins[0])),
                       "render_seconds": round(render_s, 1)},
            "train_seconds": round(time.perf_counter() - t1, 1),
            "selection": {"world": " ".join(map(str, SELECTION_WORLD)), "best_epoch": hist.best_epoch,
                          "best_R@1": round(hist.best_recall, 4)},
            "history": [{"epoch": e["epoch"], "loss": round(e["loss"], 4), "val R@1": round(e["val"][1], 4)}
                        for e in hist.epochs]}
    return backbone, info


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_backbone(backbone: SmallCNN, cfg: PretrainConfig, info: dict, out, command: str) -> dict:
    """Write the half-precision state dict atomically to ``out`` and its JSON card beside it."""

    out = Path(out)
    state = {k: v.detach().to(torch.float16) if v.is_floating_point() else v
             for k, v in backbone.state_dict().items()}
    save_checkpoint(out, state)
    loaded = _read_backbone(out, cfg.width, cfg.out_channels, cfg.final_norm)   # what was written (fp16 weights)
    card = {"file": out.name, "sha256": _sha256(out), "bytes": out.stat().st_size,
            "command": command, "config": asdict(cfg), "architecture": "SmallCNN",
            "torch": torch.__version__, "python": platform.python_version(),
            "threads": torch.get_num_threads(), "cpu": cpu_description(), **info,
            "held_out": held_out_recalls(loaded), "probes": backbone_probes(loaded)}
    card_path = out.with_suffix(".json")
    tmp = card_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(card, indent=1) + "\n")
    tmp.replace(card_path)
    return card


def card(path=CHECKPOINT) -> dict:
    """The JSON card written beside a course-backbone checkpoint.

    FileNotFoundError when it is missing; ValueError naming the card when it is not a JSON object
    holding ``sha256`` (64 hex digits) and ``config`` with the integer ``width`` and ``out_channels``
    (what :func:`course_backbone` reads)."""
    p = Path(path).with_suffix(".json")
    remake = f"restore it with git or re-make the pair with `python -m vpr_nb.pretrain --out {Path(path).name}`"
    if not p.is_file():
        raise FileNotFoundError(f"{p} is missing: the checkpoint's card is written by "
                                f"`python -m vpr_nb.pretrain --out {Path(path).name}`")
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p} is not a readable JSON card ({exc}); {remake}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{p} holds a JSON {type(meta).__name__}, not the card object; {remake}")
    sha = meta.get("sha256")
    if not isinstance(sha, str) or len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha):
        raise ValueError(f"{p} has no valid 'sha256' (got {sha!r}), so {Path(path).name} cannot be checked "
                         f"against it; {remake}")
    config = meta.get("config")
    bad = [k for k in ("width", "out_channels") if not isinstance(config, dict) or isinstance(config.get(k), bool)
           or not isinstance(config.get(k), int) or config.get(k) < 1]
    if bad:
        raise ValueError(f"{p}: 'config' must hold the positive integers {bad} of the SmallCNN; {remake}")
    norm = config.get("final_norm", 0)
    if isinstance(norm, bool) or not isinstance(norm, int) or norm < 0:
        raise ValueError(f"{p}: 'config' final_norm must be a whole number >= 0 (GroupNorm groups), got {norm!r}; "
                         f"{remake}")
    return meta


def course_backbone(path=CHECKPOINT, trainable_blocks: int = 0, final_relu: bool = True) -> SmallCNN:
    """Load the pretrained course backbone (float32), the last ``trainable_blocks`` of its 4 blocks trainable.

    ``trainable_blocks=0`` freezes it entirely (features only; the global token layer that SALAD
    reads always trains); 1 trains the last block (the 1×1 projection), as DW-T-Loss trains VGG16's
    conv5 and SALAD DINOv2's last blocks. The file's sha256 must equal the one in its JSON card.

    ``final_relu=False`` reads the features before the last ReLU (the ReLU becomes an identity), as
    pytorch-NetVlad reads VGG16's conv5_3 and SALAD reads DINOv2's tokens: after the ReLU many
    positions are exactly zero in every channel, which NetVLAD's per-feature L2 normalisation and
    SALAD's score head cannot use (notebook 04 measures it). GeM clamps at ε, so it gives the same
    descriptor either way.
    """
    if not isinstance(final_relu, bool):
        raise ValueError(f"final_relu must be True or False, got {final_relu!r}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no course backbone at {path}; it ships with vpr_nb (vpr_nb/weights/) or is "
                                f"re-made with `python -m vpr_nb.pretrain --out {path}`")
    meta = card(path)
    if _sha256(path) != meta["sha256"]:
        raise ValueError(f"{path} does not match the sha256 in its card {path.with_suffix('.json').name}: "
                         f"the file was changed or truncated; restore it with git or re-run its command "
                         f"({meta.get('command', 'python -m vpr_nb.pretrain --out ' + str(path))})")
    backbone = _read_backbone(path, meta["config"]["width"], meta["config"]["out_channels"],
                              meta["config"].get("final_norm", 0))
    if not final_relu:
        backbone.features[-1] = torch.nn.Identity()
    return backbone.set_trainable_blocks(trainable_blocks)


def _read_backbone(path: Path, width: int, out_channels: int, final_norm: int = 0) -> SmallCNN:
    """The SmallCNN(width, out_channels, final_norm) in ``path`` (weights-only, float32); one-line errors
    (:func:`vpr_nb.models.read_weights`, :func:`vpr_nb.models.load_state_checked`)."""
    state = read_weights(path, "course backbone")
    state = {k: v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v for k, v in state.items()}
    arch = f"SmallCNN(width={width}, out_channels={out_channels}, final_norm={final_norm})"
    return load_state_checked(SmallCNN(width=width, out_channels=out_channels, final_norm=final_norm), state, path,
                              hint=f"its card says {arch}; restore the pair with git or re-make it with "
                                   f"`python -m vpr_nb.pretrain --out {path}`")


def _config_from(profile: str, items) -> PretrainConfig:
    """The :class:`PretrainConfig` of ``profile`` with ``KEY=VALUE`` items, each parsed by its field's type."""


    kw = dict(PROFILES[profile])
    hints = typing.get_type_hints(PretrainConfig)
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in hints:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY one of {', '.join(hints)}")
        kw[key] = parse_value(value, hints[key], f"--set {key}")
    try:
        return PretrainConfig(**kw)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"--set: {exc}") from None


def _check_out(out: Path) -> Path:
    """``out`` can be written (before the minutes of training): not a folder, in a folder this user may write."""
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder: give the checkpoint's file name, e.g. {out / 'course_backbone.pt'}")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise ValueError(f"--out {out}: cannot write in {parent}; choose a folder you can write to")
    return out


EXAMPLES = (("re-make the committed course backbone (about 6 min on 2 cores)", ""),
            ("a quick backbone into another file, with a setting changed",
             "--profile quick --set lr=0.002 --out /tmp/backbone.pt"))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = cli.parser("vpr-pretrain", "vpr_nb.pretrain", __doc__, EXAMPLES)
    parser.add_argument("--profile", choices=sorted(PROFILES), default="full")
    parser.add_argument("--out", default=None, help="checkpoint path (a .json card is written beside it); default: the "
                        "committed vpr_nb/weights/course_backbone.pt of the clone vpr_nb runs from")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help=f"override a PretrainConfig field ({', '.join(f.name for f in fields(PretrainConfig))})")
    args = parser.parse_args(argv)
    if args.out is None:
        if checkout_root() is None:
            parser.error("--out is required: this vpr_nb is installed, not run from a clone of the course, and the "
                         "installed course backbone is not overwritten")
        args.out = str(CHECKPOINT)
    at = {"saving": False}

    def interrupted(exc):
        kept = ("it was being written: check its .json card" if at["saving"] else "it was not written")
        return f"interrupted; {args.out}: {kept}; run the command again: {cli.command_line(parser.prog, argv)}"

    def work() -> int:
        cfg = _config_from(args.profile, args.set)       # checked before the minutes of training
        out = _check_out(Path(args.out))
        apply_in_process()                   # the pinned kernels' convolutions (vpr_nb.kernels), as every front door
        torch.set_num_threads(1)             # one thread: the same weights on any machine
        backbone, info = pretrain(cfg)
        at["saving"] = True
        command = "python -m vpr_nb.pretrain " + " ".join(a if " " not in a else repr(a) for a in argv)
        meta = save_backbone(backbone, cfg, info, out, command.strip())
        print(json.dumps({k: meta[k] for k in ("file", "sha256", "bytes", "train_seconds", "held_out")}, indent=1))
        return 0
    return cli.run(work, interrupted)


if __name__ == "__main__":
    sys.exit(main())
