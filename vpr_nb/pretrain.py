"""The course backbone: the course's stand-in for ImageNet-VGG16 (DW-T-Loss) and DINOv2 (SALAD).

Both papers fine-tune a *pretrained* backbone; training a random-init CNN from scratch for a few
epochs instead collapses (every image gets nearly the same descriptor) and says nothing about a
loss or an aggregator. This module trains, once, a :class:`vpr_nb.models.SmallCNN` on a synthetic
corpus that is **disjoint from every world a notebook evaluates on** (world seeds
``CORPUS_SEED_BASE`` and up, never the notebooks' seeds 0–4), both presets, every condition,
database and query images of every split, with a generic objective: the Multi-Similarity loss
(Wang et al., CVPR 2019) over P places × K images, places being 30 m of street × 4 view directions.

    python -m vpr_nb.pretrain                                             # the committed checkpoint (vpr_nb/weights/)
    python -m vpr_nb.pretrain --profile quick --out /tmp/cb.pt            # a 20-second smoke run

writes a weights-only half-precision state dict and a JSON beside it (command, config, sha256, torch
version, training time, Recall@N of the frozen backbone + GeM on held-out worlds).
:func:`course_backbone` loads it with ``torch.load(..., weights_only=True)`` after checking the hash,
optionally with only the last blocks trainable, the way VGG16 conv5 / DINOv2's last 4 blocks are.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from ._checks import check_int
from .models import SmallCNN, load_state_checked, read_weights
from .package_data import checkout_root, course_backbone_path

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

    def __post_init__(self):
        for name in ("city_seeds", "route_seeds"):
            seeds = tuple(getattr(self, name))
            if any(check_int(s, f"{name} entry", minimum=0) < CORPUS_SEED_BASE for s in seeds):
                raise ValueError(f"{name} {seeds}: corpus world seeds must be >= {CORPUS_SEED_BASE} so that the "
                                 f"corpus never overlaps a world the notebooks evaluate on (seeds 0-4)")
            object.__setattr__(self, name, seeds)
        if not self.city_seeds and not self.route_seeds:
            raise ValueError("the corpus needs at least one world: give city_seeds or route_seeds")
        for name in ("spots_per_place", "width", "out_channels", "places_per_batch", "batches_per_epoch", "epochs", "step_size"):
            check_int(getattr(self, name), name)
        check_int(self.images_per_place, "images_per_place", minimum=2)
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")


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


def build_corpus(cfg: PretrainConfig, progress: bool = True):
    """(uint8 images (N, H, W, 3), int64 place labels (N,)) of every corpus world, all splits."""
    from tqdm.auto import tqdm

    from .synthetic import make_dataset

    worlds = [("city", s) for s in cfg.city_seeds] + [("route", s) for s in cfg.route_seeds]
    images, labels, offset = [], [], 0
    for preset, seed in tqdm(worlds, desc="rendering corpus", disable=not progress, leave=False):
        ds = make_dataset(preset, seed=seed, size=cfg.world_size)
        lab = place_labels(ds, cfg.spots_per_place)
        images += [ds.db_images, ds.q_images]
        labels.append(lab + offset)
        offset += int(lab.max()) + 1
    return np.concatenate(images), np.concatenate(labels)


def _split(preset: str, seed: int, split: str):
    from .synthetic import make_dataset
    return make_dataset(preset, seed=seed, splits=(split,)).split(split)


def held_out_recalls(backbone, ns=(1, 5, 10)) -> dict[str, dict]:
    """Recall@N of ``backbone`` frozen + GeM (and of raw pixels) on the :data:`HELD_OUT` worlds."""
    from .aggregation import GeM
    from .evaluation import evaluate_descriptors, evaluate_model, raw_pixel_descriptors
    from .models import VPRModel

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


def pretrain(cfg: PretrainConfig, progress: bool = True) -> tuple[SmallCNN, dict]:
    """Train the course backbone on the corpus; returns (backbone, info) deterministically."""
    import vpr_nb
    from .aggregation import GeM
    from .samplers import random_place_batches
    from .models import VPRModel
    from .losses import MultiSimilarityLoss
    from .training import PlaceBatchSource, TrainConfig, train

    t0 = time.perf_counter()
    images, labels = build_corpus(cfg, progress)
    render_s = time.perf_counter() - t0
    vpr_nb.seed_everything(cfg.seed)
    backbone = SmallCNN(width=cfg.width, out_channels=cfg.out_channels)
    model = VPRModel(backbone, GeM(in_channels=backbone.out_channels))

    def batches(_model, _epoch, rng):
        return random_place_batches(labels, cfg.places_per_batch, cfg.images_per_place,
                                    num_batches=cfg.batches_per_epoch, seed=rng)

    source = PlaceBatchSource(images, batches, loss=MultiSimilarityLoss())   # alpha 1, beta 50, base 0, miner 0.1
    tcfg = TrainConfig(epochs=cfg.epochs, optimizer="adam", lr=cfg.lr, weight_decay=0.0,
                       step_size=cfg.step_size, gamma=0.5, seed=cfg.seed, ns=(1, 5), device="cpu")
    sel = _split(*SELECTION_WORLD)
    t1 = time.perf_counter()
    hist = train(model, source, sel, tcfg, progress=progress)
    info = {"corpus": {"images": int(len(images)), "places": int(labels.max() + 1),
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
    from .training import save_checkpoint

    out = Path(out)
    state = {k: v.detach().to(torch.float16) if v.is_floating_point() else v
             for k, v in backbone.state_dict().items()}
    save_checkpoint(out, state)
    loaded = _read_backbone(out, cfg.width, cfg.out_channels)   # evaluate what was written (fp16 weights)
    card = {"file": out.name, "sha256": _sha256(out), "bytes": out.stat().st_size,
            "command": command, "config": asdict(cfg), "architecture": "SmallCNN",
            "torch": torch.__version__, "python": platform.python_version(),
            "threads": torch.get_num_threads(), **info,
            "held_out": held_out_recalls(loaded)}
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
    backbone = _read_backbone(path, meta["config"]["width"], meta["config"]["out_channels"])
    if not final_relu:
        backbone.features[-1] = torch.nn.Identity()
    return backbone.set_trainable_blocks(trainable_blocks)


def _read_backbone(path: Path, width: int, out_channels: int) -> SmallCNN:
    """The SmallCNN(width, out_channels) in ``path`` (weights-only, float32); one-line errors
    (:func:`vpr_nb.models.read_weights`, :func:`vpr_nb.models.load_state_checked`)."""
    state = read_weights(path, "course backbone")
    state = {k: v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v for k, v in state.items()}
    return load_state_checked(SmallCNN(width=width, out_channels=out_channels), state, path,
                              hint=f"its card says SmallCNN(width={width}, out_channels={out_channels}); restore "
                                   f"the pair with git or re-make it with `python -m vpr_nb.pretrain --out {path}`")


def _config_from(profile: str, items) -> PretrainConfig:
    """The :class:`PretrainConfig` of ``profile`` with ``KEY=VALUE`` items, each parsed by its field's type."""
    import typing

    from .typed_parsing import parse_value

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


def main(argv=None) -> int:
    from .experiment import CLI_ERRORS

    parser = argparse.ArgumentParser(prog="python -m vpr_nb.pretrain", description=__doc__.split("\n\n")[0])
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
    try:
        cfg = _config_from(args.profile, args.set)       # checked before the minutes of training
        out = _check_out(Path(args.out))
        torch.set_num_threads(1)             # one thread: the same weights on any machine
        backbone, info = pretrain(cfg)
        command = "python -m vpr_nb.pretrain " + " ".join(a if " " not in a else repr(a) for a in (argv or sys.argv[1:]))
        meta = save_backbone(backbone, cfg, info, out, command.strip())
    except CLI_ERRORS as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({k: meta[k] for k in ("file", "sha256", "bytes", "train_seconds", "held_out")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
