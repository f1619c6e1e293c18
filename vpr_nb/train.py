"""The reproduction command: ``python -m vpr_nb.train --preset NAME [--set key=value ...] --out DIR``.

A preset is a nested config (``data``, ``model``, ``source``, ``train``) that encodes one paper's
setup; every value can be overridden with ``--set section.key=value`` (values parsed as JSON, else
kept as strings). The resolved config is printed and saved as ``DIR/config.json`` beside
``history.json``, ``results.json`` (test Recall@N) and ``checkpoints/`` (``last.pt``, ``best.pt``).

Presets:

- ``synthetic-city-triplet`` / ``synthetic-city-dw``: the notebooks' small CNN + GeM on the tiny
  city world (T-Loss, DW-T-Loss); ``synthetic-city-netvlad``; ``synthetic-route-ms``: MS loss with
  random-place batches on the route. These run on a laptop CPU in about a minute.
- ``dwt-pitts30k``: DW-T-Loss's Pittsburgh30k setup (VGG16 conv5 + NetVLAD 64; SGD 1e-4, momentum
  0.9, wd 1e-3, StepLR 5/0.5, 30 epochs, 4 triplets per batch, 10 hard negatives, seed 123);
  ``source.loss`` selects T / W-T / CE / DW-T (``triplet``, ``weighted``, ``ce``, ``dw``).
- ``salad-gsv`` and ``salad-cliquemining-msls``: DINOv2 ViT-B/14 (last 4 blocks trained) + SALAD
  64/128/256, MS loss (alpha 1, beta 50, base 0, miner epsilon 0.1), AdamW 6e-5 wd 9.5e-9,
  LinearLR 1 -> 0.2 over 4000 steps, 4 epochs, batches of 60 places x 4 images (CliqueMining: 30
  GSV-Cities places + 30 clique places from MSLS).

Real-data presets need ``data.root`` (and for DINOv2 a local hub directory, see
:func:`vpr_nb.models.load_dinov2`). Under ``torchrun --nproc_per_node N`` training runs with
DistributedDataParallel (gloo on CPU, nccl on GPU).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
from dataclasses import fields
from pathlib import Path

import torch

from . import seed_everything
from .evaluation import evaluate_model
from .models import build_model
from .training import PlaceBatchSource, TrainConfig, TripletSource, train

SYNTHETIC_CITY = {"format": "synthetic", "preset": "city", "size": "tiny", "seed": 0, "root": None, "overrides": {}}

PRESETS: dict[str, dict] = {
    "synthetic-city-triplet": {
        "data": dict(SYNTHETIC_CITY),
        "model": {"backbone": "small_cnn", "aggregator": "gem", "backbone_kwargs": {}, "aggregator_kwargs": {}},
        "source": {"kind": "triplet", "loss": "triplet", "batch_size": 16, "num_negatives": 5,
                   "num_candidates": 300, "margin": 0.1, "max_heading_diff": 45.0},
        "train": {"epochs": 14, "optimizer": "sgd", "lr": 0.05, "seed": 0},
    },
    "dwt-pitts30k": {
        "data": {"format": "pitts", "root": None, "image_size": [480, 640]},
        "model": {"backbone": "vgg16", "aggregator": "netvlad",
                  "backbone_kwargs": {"pretrained_state_dict": None, "trainable_from": "conv5"},
                  "aggregator_kwargs": {"num_clusters": 64}},
        "source": {"kind": "triplet", "loss": "dw", "batch_size": 4, "num_negatives": 10,
                   "num_candidates": 1000, "cache_refresh": 1000, "margin": 0.1, "sigma": 800.0, "eps": 0.1},
        "train": {"epochs": 30, "optimizer": "sgd", "lr": 1e-4, "momentum": 0.9, "weight_decay": 1e-3,
                  "scheduler": "step", "step_size": 5, "gamma": 0.5, "seed": 123, "ns": [1, 5, 10, 20]},
    },
    "salad-gsv": {
        "data": {"format": "gsv-cities", "root": None, "image_size": [224, 224]},
        "model": {"backbone": "dinov2", "aggregator": "salad",
                  "backbone_kwargs": {"hub_dir": None, "model": "dinov2_vitb14", "num_trainable_blocks": 4},
                  "aggregator_kwargs": {"num_channels": 768, "num_clusters": 64, "cluster_dim": 128,
                                        "token_dim": 256}},
        "source": {"kind": "places", "sampler": "random", "places_per_batch": 60, "images_per_place": 4,
                   "alpha": 1.0, "beta": 50.0, "base": 0.0, "miner_epsilon": 0.1},
        "train": {"epochs": 4, "optimizer": "adamw", "lr": 6e-5, "weight_decay": 9.5e-9, "scheduler": "linear",
                  "linear_end_factor": 0.2, "linear_steps": 4000, "seed": 0, "amp": True, "ns": [1, 5, 10, 20]},
    },
}
PRESETS["synthetic-city-dw"] = copy.deepcopy(PRESETS["synthetic-city-triplet"])
PRESETS["synthetic-city-dw"]["source"]["loss"] = "dw"
PRESETS["synthetic-city-netvlad"] = copy.deepcopy(PRESETS["synthetic-city-triplet"])
PRESETS["synthetic-city-netvlad"]["model"].update(aggregator="netvlad", aggregator_kwargs={"num_clusters": 16})
PRESETS["synthetic-route-ms"] = {
    "data": {"format": "synthetic", "preset": "route", "size": "tiny", "seed": 0, "root": None, "overrides": {}},
    "model": {"backbone": "small_cnn", "aggregator": "gem", "backbone_kwargs": {}, "aggregator_kwargs": {}},
    "source": {"kind": "places", "sampler": "random", "places_per_batch": 16, "images_per_place": 4,
               "batches_per_epoch": 20, "alpha": 1.0, "beta": 50.0, "base": 0.0, "miner_epsilon": 0.1},
    "train": {"epochs": 6, "optimizer": "adam", "lr": 1e-3, "weight_decay": 0.0, "seed": 0},
}
PRESETS["salad-cliquemining-msls"] = copy.deepcopy(PRESETS["salad-gsv"])
PRESETS["salad-cliquemining-msls"]["data"] = {"format": "msls", "root": None, "gsv_root": None,
                                              "image_size": [224, 224]}
PRESETS["salad-cliquemining-msls"]["source"].update(sampler="clique+random", places_per_batch=60,
                                                    clique_places=30, same_place_threshold=25.0,
                                                    similar_groups=15)


def parse_value(text: str):
    """JSON if it parses (numbers, true/false/null, lists, dicts), else the string itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def resolve_config(preset: str, overrides=()) -> dict:
    """The preset's nested config with ``section.key=value`` overrides applied (unknown keys are errors)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(sorted(PRESETS))}")
    cfg = copy.deepcopy(PRESETS[preset])
    train_keys = {f.name for f in fields(TrainConfig)}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ValueError(f"override {item!r} must look like section.key=value, e.g. train.lr=0.01")
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        if section not in cfg:
            raise ValueError(f"unknown config section {section!r} in {item!r}; sections: {', '.join(cfg)}")
        known = set(cfg[section]) | (train_keys if section == "train" else set())
        if name not in known and section != "data":     # data options differ per format (see load_splits)
            raise ValueError(f"unknown key {name!r} in section {section!r}; known keys: {', '.join(sorted(known))}")
        cfg[section][name] = parse_value(value)
    return {"preset": preset, **cfg}


def load_data(data: dict, splits=("train", "val", "test")):
    """(train, val, test) splits for the ``data`` section (real formats: only ``splits`` are loaded)."""
    if data["format"] == "synthetic":
        from .synthetic import make_dataset
        ds = make_dataset(data["preset"], data["seed"], data.get("size", "tiny"), **(data.get("overrides") or {}))
        return ds.train, ds.val, ds.test
    if not data.get("root"):
        raise ValueError(f"preset needs the dataset location: --set data.root=/path/to/{data['format']} "
                         "(see README, 'Real datasets')")
    from .datasets import load_splits
    return load_splits(data, splits)


def _place_pool(split):
    """(images, groups, utm) of the training images that carry a place id (database, then queries)."""
    import numpy as np
    geo = getattr(split, "geo", None)
    has_q = split.q_images is not None and split.q_place is not None and len(split.q_utm) > 0
    groups = np.concatenate([split.db_place, split.q_place]) if has_q else np.asarray(split.db_place)
    utm = np.concatenate([split.db_utm, split.q_utm]) if has_q else np.asarray(split.db_utm)
    if geo is not None:
        from .datasets import ImageArray
        images = ImageArray(list(geo.db_paths) + (list(geo.q_paths) if has_q else []), split.db_images.size)
    else:
        images = np.concatenate([split.db_images, split.q_images]) if has_q else split.db_images
    if groups is None or len(groups) != len(utm):
        raise ValueError("place batches need place ids (db_place/q_place) for every training image")
    return images, np.asarray(groups, dtype=np.int64), utm


def _subset(images, idx):
    """The images at ``idx`` without reading an on-disk array (a new ImageArray over those paths)."""
    from .datasets import ImageArray
    if isinstance(images, ImageArray):
        return ImageArray([images.paths[i] for i in idx], images.size)
    return images[idx]


def _clique_sampler(images, groups, utm, opts, per_epoch):
    """CliqueMining batches (:class:`vpr_nb.mining.CliqueBatchMaker`) over the images with a place id;
    ``refresh_every`` epochs between descriptor refreshes (absent: once, as the published code)."""
    import numpy as np
    from .mining import CliqueBatchMaker
    sub = np.flatnonzero(groups >= 0)
    _, gid = np.unique(groups[sub], return_inverse=True)
    makers = {}

    def make(model, epoch, rng, places):
        if places not in makers:
            makers[places] = CliqueBatchMaker(_subset(images, sub), utm[sub], gid, places, per_epoch,
                                              images_per_place=opts["images_per_place"],
                                              same_place_threshold=opts.get("same_place_threshold", 25.0),
                                              similar_groups=opts.get("similar_groups", 15),
                                              refresh_every=opts.get("refresh_every"))
        return sub[makers[places](model, epoch, rng)]
    return make


def build_source(src: dict, train_split, extra_split=None):
    """The batch source of the ``source`` section (``extra_split``: the GSV-Cities pool of
    ``sampler="clique+random"``, which mixes random GSV places with clique places of the main split)."""
    import numpy as np
    from .mining import random_place_batches
    opts = {k: v for k, v in src.items() if k != "kind"}
    if src["kind"] == "triplet":
        return TripletSource(train_split, **opts)
    if src["kind"] != "places":
        raise ValueError(f"source.kind must be 'triplet' or 'places', got {src['kind']!r}")
    sampler = opts.get("sampler", "random")
    per_epoch = int(opts.get("batches_per_epoch", 20))
    k = opts["images_per_place"]
    images, groups, utm = _place_pool(train_split)
    if sampler == "random":
        valid = np.flatnonzero(groups >= 0)

        def make_batches(model, epoch, rng):
            return valid[random_place_batches(groups[valid], opts["places_per_batch"], k, num_batches=per_epoch,
                                              seed=int(rng.integers(2**31)))]
    elif sampler == "clique":
        clique = _clique_sampler(images, groups, utm, opts, per_epoch)

        def make_batches(model, epoch, rng):
            return clique(model, epoch, rng, opts["places_per_batch"])
    elif sampler == "clique+random":
        if extra_split is None:
            raise ValueError("sampler 'clique+random' needs the GSV-Cities pool: set data.gsv_root")
        g_images, g_groups, _ = _place_pool(extra_split)
        from .datasets import ImageArray
        if not (isinstance(images, ImageArray) and isinstance(g_images, ImageArray)):
            raise ValueError("sampler 'clique+random' mixes two on-disk datasets (MSLS + GSV-Cities)")
        n_c = int(opts.get("clique_places", opts["places_per_batch"] // 2))
        clique = _clique_sampler(images, groups, utm, opts, per_epoch)
        offset = len(images)
        images = ImageArray(images.paths + g_images.paths, images.size)

        def make_batches(model, epoch, rng):
            rand = random_place_batches(g_groups, opts["places_per_batch"] - n_c, k, num_batches=per_epoch,
                                        seed=int(rng.integers(2**31)))
            return np.concatenate([rand + offset, clique(model, epoch, rng, n_c)], axis=1)
    else:
        raise ValueError(f"source.sampler must be 'random', 'clique' or 'clique+random', got {sampler!r}")
    return PlaceBatchSource(images, make_batches, alpha=opts["alpha"], beta=opts["beta"], base=opts["base"],
                            miner_epsilon=opts["miner_epsilon"])


def run(cfg: dict, out: Path | None, progress: bool = True) -> dict:
    """Train and evaluate one resolved config; returns the results dict (also written under ``out``)."""
    tr_cfg = dict(cfg["train"])
    if "ns" in tr_cfg:
        tr_cfg["ns"] = tuple(tr_cfg["ns"])
    config = TrainConfig(**tr_cfg)
    seed_everything(config.seed)
    train_split, val_split, test_split = load_data(cfg["data"])
    m = cfg["model"]
    model = build_model(m["backbone"], m["aggregator"], backbone_kwargs=m["backbone_kwargs"] or None,
                        **m["aggregator_kwargs"])
    extra = None
    if cfg["source"].get("sampler") == "clique+random":
        from .datasets import TrainingSplit, load
        gsv = cfg["data"].get("gsv_root")
        if not gsv:
            raise ValueError("salad-cliquemining-msls needs data.gsv_root (the GSV-Cities folder) besides data.root (MSLS)")
        extra = TrainingSplit(load(gsv, "gsv-cities", check_files=cfg["data"].get("check_files", True)),
                              tuple(cfg["data"]["image_size"]))
    if m["aggregator"] == "netvlad":            # NetVLAD's cluster step: k-means centroids and alpha
        from .models import init_netvlad
        init_netvlad(model, train_split.db_images, per_image=m.get("init_per_image", 20), seed=config.seed,
                     max_images=m.get("init_max_images", 500))
    source = build_source(cfg["source"], train_split, extra)
    history = train(model, source, val_split, config, checkpoint_dir=None if out is None else out / "checkpoints",
                    progress=progress)
    test = evaluate_model(model, test_split, ns=config.ns)
    results = {"preset": cfg["preset"], "best_epoch": history.best_epoch, "val_best_recall": history.best_recall,
               "test": {str(k): v for k, v in test.items()}}
    rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
    if out is not None and rank == 0:
        (out / "history.json").write_text(json.dumps(history.to_dict(), indent=1))
        (out / "results.json").write_text(json.dumps(results, indent=1))
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.train", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", help="one of: " + ", ".join(sorted(PRESETS)))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a config value (repeatable), e.g. --set train.lr=0.01")
    ap.add_argument("--out", type=Path, help="output folder (config.json, history.json, results.json, checkpoints/)")
    ap.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    ap.add_argument("--list", action="store_true", help="list the presets and exit")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(sorted(PRESETS)))
        return 0
    if not args.preset:
        ap.error("--preset is required (use --list to see them)")
    try:
        cfg = resolve_config(args.preset, args.overrides)
    except ValueError as e:
        ap.error(str(e))
    print(json.dumps(cfg, indent=1))
    if args.print_config:
        return 0
    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if distributed:
        backend = "nccl" if torch.cuda.is_available() and cfg["train"].get("device", "auto") != "cpu" else "gloo"
        torch.distributed.init_process_group(backend)
    rank = torch.distributed.get_rank() if distributed else 0
    if args.out is not None and rank == 0:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "config.json").write_text(json.dumps(cfg, indent=1))
    try:
        results = run(cfg, args.out, progress=not args.no_progress)
    finally:
        if distributed:
            torch.distributed.destroy_process_group()
    if rank == 0:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
