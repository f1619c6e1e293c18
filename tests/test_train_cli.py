"""The reproduction command: typed config, presets (model, step count), validation before data, val/test
separation, per-format Recall@N, outputs, resume (and extending a run), --help, and DDP (2 CPU processes, gloo)
vs 1 process."""
import csv
import importlib
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from vpr_nb import config as C
from vpr_nb import experiment as E
from vpr_nb.cli import plain_text
from vpr_nb.run_folder import FolderLock
from vpr_nb.train import PRESETS, main, resolve_config

FIX = Path(__file__).resolve().parents[1] / "data_fixtures"
SMALL = ["--set", 'data.overrides={"blocks": [5, 2], "image_size": [16, 24], "queries_per_place": 1.0}',
         "--set", 'model.backbone_kwargs={"width": 8, "out_channels": 16}',
         "--set", "train.epochs=2", "--set", "train.step_size=1", "--set", "source.num_candidates=50",
         "--no-progress"]


# ------------------------------------------------------------------------------------------ a DINOv2 stand-in
class TinyViT(nn.Module):
    """The interface of DINOv2's DinoVisionTransformer (patch 14) at a toy size."""

    def __init__(self, dim=16, depth=5):
        super().__init__()
        self.patch_size, self.embed_dim = 14, dim
        self.patch_embed = nn.Conv2d(3, dim, 14, 14)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.blocks = nn.ModuleList(nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.GELU())
                                    for _ in range(depth))
        self.norm = nn.LayerNorm(dim)

    def prepare_tokens_with_masks(self, x, masks=None):
        t = self.patch_embed(x).flatten(2).transpose(1, 2)
        return torch.cat([self.cls_token.expand(len(t), -1, -1), t], 1)


@pytest.fixture
def dinov2(monkeypatch):
    """DINOv2 from the hub clone when VPR_NB_DINOV2_HUB is set, else the tiny stand-in."""
    if os.environ.get("VPR_NB_DINOV2_HUB"):
        return
    from vpr_nb import models

    def fake(hub_dir=None, model="dinov2_vitb14", num_trainable_blocks=4):
        return models.DINOv2Backbone(TinyViT(), num_trainable_blocks)
    monkeypatch.setattr(models, "load_dinov2", fake)
    monkeypatch.setitem(models.BACKBONES, "dinov2", fake)      # the name -> builder map build_model reads


# ------------------------------------------------------------------------------------------ config
def test_every_preset_resolves_and_prints(capsys):
    for name in PRESETS:
        assert main(["--preset", name, "--print-config"]) == 0
        cfg = json.loads(capsys.readouterr().out)
        assert cfg["preset"] == name and {"data", "model", "source", "train", "eval"} <= set(cfg)
    dwt = resolve_config("dwt-pitts30k")
    assert dwt["train"]["lr"] == 1e-4 and dwt["train"]["seed"] == 123 and dwt["source"]["num_negatives"] == 10
    assert dwt["model"]["aggregator_kwargs"]["num_clusters"] == 64 and dwt["source"]["batch_size"] == 4
    salad = resolve_config("salad-gsv")
    assert salad["train"]["optimizer"] == "adamw" and salad["train"]["lr"] == 6e-5
    assert salad["source"]["places_per_batch"] == 60 and salad["source"]["images_per_place"] == 4


def test_presets_hold_only_deviations_from_the_defaults():
    assert set(C.PRESETS) == set(PRESETS)
    for name in PRESETS:               # vpr_nb.train.PRESETS: the resolved view
        assert {"preset": name, **PRESETS[name]} == resolve_config(name)
    for name, preset in C.PRESETS.items():
        assert set(preset) <= set(C.SECTIONS), name
        for section, values in preset.items():
            default = asdict(C.SECTIONS[section]())
            for key, value in values.items():
                assert key in default, (name, section, key)
                norm = list(value) if isinstance(value, tuple) else value
                dflt = list(default[key]) if isinstance(default[key], tuple) else default[key]
                assert norm != dflt, f"{name}: {section}.{key} repeats the default {value!r}"


def test_overrides_are_parsed_by_type_and_checked():
    cfg = C.resolve("dwt-pitts30k", ["source.loss=triplet", "train.lr=0.001", "train.ns=[1,5]", "train.amp=False",
                                     "train.restore_best=false", "source.cache_refresh=none", "data.image_size=64,48",
                                     "source.batches_per_epoch=7", "model.backbone_kwargs={\"trainable_from\": \"conv4\"}",
                                     "eval.recall=exclude", "data.check_files=0"])
    assert cfg.source.loss == "triplet" and cfg.train.lr == 0.001 and cfg.train.ns == (1, 5)
    assert cfg.train.amp is False and cfg.train.restore_best is False and cfg.source.cache_refresh is None
    assert cfg.data.image_size == (64, 48) and cfg.source.batches_per_epoch == 7 and cfg.data.check_files is False
    assert cfg.model.backbone_kwargs == {"trainable_from": "conv4"} and cfg.eval.recall == "exclude"
    assert resolve_config("dwt-pitts30k", ["train.ns=[1,5]"])["train"]["ns"] == [1, 5]
    for bad, match in [("train.lrr=1", "unknown key 'lrr' in section 'train'; known keys: epochs"),
                       ("data.imagesize=3", "unknown key 'imagesize' in section 'data'; known keys: format"),
                       ("eval.n=3", "unknown key 'n' in section 'eval'"),
                       ("source.refresh=3", "unknown key 'refresh' in section 'source'"),
                       ("optim.lr=1", "unknown config section"), ("lr=1", "section.key=value"),
                       ("train.amp=maybe", "train.amp must be true or false"),
                       ("data.image_size=32", "data.image_size must have 2 entries"),
                       ("train.epochs=2.5", "train.epochs must be an integer"),
                       ("model.backbone_kwargs=[1]", "must be a dict"),
                       ("train.optimizer=lbfgs", "optimizer must be one of")]:
        with pytest.raises(ValueError, match=match):
            C.resolve("dwt-pitts30k", [bad])
    with pytest.raises(ValueError, match="unknown preset"):
        C.resolve("netvlad-tokyo")
    cfg = C.resolve("salad-gsv")
    assert C.RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="unknown key"):
        C.RunConfig.from_dict(dict(cfg.to_dict(), source={"nope": 1}))


def test_the_loss_registry_maps_each_name_to_its_object():
    """One place maps source.loss to a loss object; its parameters are the SourceConfig fields of the same names."""
    import inspect

    from vpr_nb import losses as L
    source_fields = {f.name for f in fields(C.SourceConfig)}
    for name, cls in C.LOSSES.items():
        assert set(inspect.signature(cls).parameters) <= source_fields, name
    assert C.TRIPLET_LOSSES == ("triplet", "weighted", "ce", "dw")
    s = C.resolve("dwt-pitts30k", ["source.sigma=30", "source.eps=0.5"]).source
    assert C.build_loss(s) == L.DWTripletLoss(sigma=30.0, eps=0.5)
    assert C.build_loss(C.resolve("dwt-pitts30k", ["source.loss=weighted", "source.margin=0.2"]).source) == \
        L.WeightedTripletLoss(margin=0.2, sigma=800.0, eps=0.1)
    assert C.build_loss(C.resolve("salad-gsv", ["source.miner_epsilon=none"]).source) == \
        L.MultiSimilarityLoss(miner_epsilon=None)
    with pytest.raises(ValueError, match="source.loss must be one of"):
        C.build_loss(C.SourceConfig(loss="contrastive"))
    with pytest.raises(ValueError, match="source: miner_epsilon"):
        C.validate(C.resolve("synthetic-city-triplet", ["source.kind=places", "source.miner_epsilon=-1"]))


def test_the_whole_config_is_validated_before_any_data(tmp_path, capsys):
    for sets, match in [(["data.format=tokyo"], "data.format must be one of"),
                        (["source.sampler=nearest"], "source.sampler must be one of"),
                        (['model.aggregator_kwargs={"num_channels": 768}'], "must not set 'num_channels'"),
                        (["model.backbone=resnet"], "model.backbone must be one of"),
                        (["data.check_images=maybe"], "data.check_images"),
                        (["data.val_format=msls", "data.val_root=/data/msls"],
                         "validation and test are the same data"),
                        ([], "data.root")]:
        roots = ["data.root=/data/msls", "data.gsv_root=/data/gsv", "data.val_root=/data/pitts"] if sets else []
        with pytest.raises(ValueError, match=match):
            C.validate(C.resolve("salad-cliquemining-msls", roots + sets))
    # the CLI says it before writing anything
    out = tmp_path / "never"
    assert main(["--preset", "salad-gsv", "--out", str(out), "--no-progress"]) == 2
    assert "data.root" in capsys.readouterr().err and not out.exists()
    out2 = tmp_path / "never2"       # a model that cannot run on the images: refused before anything is written
    assert main(["--preset", "dwt-pitts30k", "--set", f"data.root={FIX / 'pitts'}", "--set", "data.image_size=[8,8]",
                 "--out", str(out2), "--no-progress"]) == 2
    assert "does not run on 8x8" in capsys.readouterr().err and not out2.exists()
    with pytest.raises(ValueError, match="'nordland' is a test set"):
        C.validate(C.resolve("synthetic-city-triplet", ["data.format=nordland", "data.root=/x"]))
    with pytest.raises(ValueError, match="no queries"):
        C.validate(C.resolve("salad-gsv", ["source.kind=triplet", "data.root=/g", "data.val_root=/p",
                                           "data.test_root=/m"]))


def test_real_data_preset_without_root_says_how_to_fix():
    with pytest.raises(ValueError, match="data.root"):
        E.load_split(C.resolve("dwt-pitts30k"), "train")


# ------------------------------------------------------------------------------------------ presets
PAPER_STEPS = {   # (sizes of the real data, expected optimiser steps of the paper's code)
    "dwt-pitts30k": ({"num_queries": 7416}, 30 * math.ceil(7416 / 4)),                  # pytorch-NetVlad, bs 4
    "salad-gsv": ({"num_places": 62_000}, 4 * math.ceil(62_000 / 60)),                   # SALAD: 4 x ceil(P/60)
    "salad-cliquemining-msls": ({"num_extra_places": 62_000}, 4 * max(math.ceil(62_000 / 30), 2000)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_each_preset_builds_its_model_and_counts_its_steps(name, dinov2):
    cfg = C.resolve(name)
    C.validate(cfg, for_training=False)
    torch.manual_seed(0)
    model = E.build_checked(cfg)              # dummy batch at the training (and evaluation) size
    assert model.out_dim >= 1
    if name.startswith("salad"):
        assert model.aggregator.num_channels == model.backbone.out_channels
        assert cfg.train.scheduler == "linear" and cfg.train.linear_steps == 4000 and cfg.train.epochs == 4
        assert cfg.eval.image_size == (322, 322) and cfg.data.image_size == (224, 224)
        assert C.split_spec(C.resolve(name, ["data.root=/r", "data.val_root=/p", "data.test_root=/m"]).data,
                            "val").format == "pitts"
    if name in PAPER_STEPS:
        sizes, steps = PAPER_STEPS[name]
        assert E.optimizer_steps(cfg, **sizes) == steps
        if name == "salad-gsv":
            assert 3900 <= steps <= 4200       # why SALAD's LinearLR spans 4000 steps
    else:
        from vpr_nb.synthetic import make_dataset
        ds = make_dataset(cfg.data.preset, cfg.data.seed, cfg.data.size, **cfg.data.overrides)
        sizes = ({"num_queries": len(ds.train.q_images)} if cfg.source.kind == "triplet"
                 else {"num_places": len(np.unique(ds.train.db_place))})
        assert E.optimizer_steps(cfg, **sizes) >= cfg.train.epochs


# ------------------------------------------------------------------------------------------ end to end on fixtures
def _pitts_sets():
    return ["--set", f"data.root={FIX / 'pitts'}", "--set", "data.image_size=[32,32]",
            "--set", 'model.aggregator_kwargs={"num_clusters": 4}', "--set", "model.init_per_image=4",
            "--set", "train.epochs=1", "--set", "source.num_candidates=5", "--set", "source.num_negatives=2",
            "--set", "data.image_check_workers=1", "--no-progress"]


@pytest.mark.slow
def test_dwt_pitts30k_end_to_end_on_fixtures(tmp_path):
    out = tmp_path / "dwt"
    assert main(["--preset", "dwt-pitts30k", "--out", str(out)] + _pitts_sets()) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["optimizer_steps"] == 1 * math.ceil(3 / 4) and res["steps_per_epoch"] == 1
    assert res["val"].startswith("pitts:val") and res["test_data"].startswith("pitts:test")
    assert res["recall_convention"] == "all" and (out / "checkpoints" / "best.pt").is_file()
    assert not (out / ".lock").exists()
    # a second run into the same folder is refused; --resume continues it
    assert main(["--preset", "dwt-pitts30k", "--out", str(out)] + _pitts_sets()) == 2
    assert main(["--resume", "--out", str(out), "--no-progress"]) == 0
    assert main(["--resume", "--preset", "dwt-pitts30k", "--set", "train.lr=1", "--out", str(out)]) == 2
    with FolderLock(out):                                          # another run holds the folder
        assert main(["--resume", "--out", str(out), "--no-progress"]) == 2
    (out / ".lock").write_text("999999999 host 2020-01-01T00:00:00\n")   # left by a dead one: taken over
    assert main(["--resume", "--out", str(out), "--no-progress"]) == 0
    # pitts250k names
    root = tmp_path / "p250"
    shutil.copytree(FIX / "pitts", root)
    for part in ("train", "val", "test"):
        (root / "datasets" / f"pitts30k_{part}.mat").rename(root / "datasets" / f"pitts250k_{part}.mat")
    cfg = C.resolve("dwt-pitts30k", [f"data.root={root}", "data.pitts_set=pitts250k", "data.image_size=[32,32]"])
    assert E.load_split(cfg, "test").geo.extras["dataset"] == "pitts250k"


def _salad_sets(tmp):
    return ["--set", f"data.root={FIX / 'gsv_cities'}", "--set", f"data.val_root={FIX / 'pitts'}",
            "--set", f"data.test_root={FIX / 'msls'}", "--set", "data.image_size=[28,28]",
            "--set", "eval.image_size=[42,42]", "--set", "source.places_per_batch=2",
            "--set", 'model.aggregator_kwargs={"num_clusters": 2, "cluster_dim": 4, "token_dim": 4, "hidden_dim": 8}',
            "--set", "train.epochs=1", "--set", "data.image_check_workers=1", "--no-progress"]


def test_salad_gsv_end_to_end_on_fixtures(tmp_path, dinov2):
    if os.environ.get("VPR_NB_DINOV2_HUB"):
        pytest.skip("the toy sizes below are for the stand-in")
    out = tmp_path / "salad"
    assert main(["--preset", "salad-gsv", "--out", str(out)] + _salad_sets(tmp_path)) == 0   # AMP on: bf16 on CPU
    res = json.loads((out / "results.json").read_text())
    assert res["steps_per_epoch"] == math.ceil(4 / 2) and res["optimizer_steps"] == 2
    assert res["val"].startswith("pitts:val") and res["test_data"].startswith("msls:val")
    assert res["recall_convention"] == "exclude"
    hist = json.loads((out / "history.json").read_text())
    assert len(hist["epochs"]) == 1 and np.isfinite(hist["epochs"][0]["loss"])


def test_salad_cliquemining_end_to_end_and_unreadable_images(tmp_path, dinov2, capsys):
    if os.environ.get("VPR_NB_DINOV2_HUB"):
        pytest.skip("the toy sizes below are for the stand-in")
    out = tmp_path / "cm"
    sets = ["--set", f"data.root={FIX / 'msls'}", "--set", f"data.val_root={FIX / 'pitts'}",
            "--set", f"data.gsv_root={FIX / 'gsv_cities'}", "--set", "data.image_size=[28,28]",
            "--set", "eval.image_size=[42,42]", "--set", "source.places_per_batch=3",
            "--set", 'model.aggregator_kwargs={"num_clusters": 2, "cluster_dim": 4, "token_dim": 4, "hidden_dim": 8}',
            "--set", "train.epochs=1", "--set", "source.clique_places=1", "--set", "source.clique_batches_per_epoch=1",
            "--set", "data.image_check_workers=1", "--no-progress"]
    assert main(["--preset", "salad-cliquemining-msls", "--out", str(out)] + sets) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "MSLS training cities are absent" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: ") and ".py" not in warned[0]   # the CLI's one line
    assert "MSLS training cities are absent" in (out / "train.log").read_text()
    res = json.loads((out / "results.json").read_text())
    assert res["steps_per_epoch"] == max(math.ceil(4 / 2), 1) and res["unreadable_images"] == 1
    assert res["test_data"].startswith("msls:val") and res["val"].startswith("pitts:val")
    listed = (out / "unreadable_images.txt").read_text()
    assert "london" in listed and "runcated" in listed
    cfg = C.resolve("salad-cliquemining-msls", [s for s in sets if "=" in s] + ["data.check_images=fail"])
    with pytest.raises(ValueError, match="cannot be decoded"):
        E.load_split(cfg, "train")


def test_cliquemining_preset_sums_one_loss_per_half():
    """serizba/cliquemining's training_step: one MS loss over the GSV-Cities places, one over the clique places."""
    from vpr_nb.datasets import TrainingSplit, load
    from vpr_nb.models import build_model

    full = C.resolve("salad-cliquemining-msls").source
    assert (full.places_per_batch - E.clique_places(full), E.clique_places(full)) == (30, 30)
    cfg = C.resolve("salad-cliquemining-msls", [f"data.root={FIX / 'msls'}", f"data.gsv_root={FIX / 'gsv_cities'}",
                                                f"data.val_root={FIX / 'pitts'}", "data.image_size=[28,28]",
                                                "source.places_per_batch=3", "source.clique_places=1",
                                                "source.clique_batches_per_epoch=1", "data.check_images=off"])
    with pytest.warns(UserWarning, match="MSLS training cities are absent"):
        msls = E.load_split(cfg, "train")
    gsv = TrainingSplit(load(FIX / "gsv_cities", "gsv-cities"), (28, 28))
    source, per_epoch = E.build_source(cfg, msls, gsv)
    assert source.loss_groups == (2, 1) and per_epoch == 2
    torch.manual_seed(0)
    batches = source.make_batches(build_model("small_cnn", "gem", backbone_kwargs={"width": 8, "out_channels": 16}),
                                  0, np.random.default_rng(0))
    paths = np.array(source.x.paths)[batches]                     # (batches, places, images)
    assert all("gsv_cities" in p for p in paths[:, :2].reshape(-1)) and all("msls" in p for p in paths[:, 2:].reshape(-1))


def test_val_equal_to_test_images_is_refused(tmp_path):
    """gmberton's MSLS: images/test is a link to images/val."""
    root = tmp_path / "msls_gm"
    (root / "images").mkdir(parents=True)
    shutil.copytree(FIX / "gmberton" / "pitts30k" / "images" / "test", root / "images" / "val")
    shutil.copytree(FIX / "gmberton" / "pitts30k" / "images" / "test", root / "images" / "train")
    (root / "images" / "test").symlink_to(root / "images" / "val")
    cfg = C.resolve("synthetic-city-triplet", ["data.format=gmberton", f"data.root={root}", "data.image_size=[16,16]",
                                               'model.backbone_kwargs={"width": 8, "out_channels": 16}'])
    with pytest.raises(ValueError, match="validation and test are the same images"):
        E.train_run(cfg, None, progress=False)


# ------------------------------------------------------------------------------------------ evaluation
def _checkpoint(tmp_path):
    from vpr_nb.training import save_checkpoint
    torch.manual_seed(0)
    cfg = C.resolve("synthetic-city-triplet", ['model.backbone_kwargs={"width": 8, "out_channels": 16}'])
    return cfg, save_checkpoint(tmp_path / "best.pt", {"model": E.build(cfg).state_dict()})


def test_evaluate_needs_only_the_test_data(tmp_path, capsys):
    cfg, ck = _checkpoint(tmp_path)
    msls = C.with_overrides(cfg, ["data.format=msls", f"data.root={FIX / 'msls_val_only'}", "data.image_size=[16,16]"])
    res = E.evaluate_run(msls, ck, tmp_path / "ev", grid_queries=0)
    assert res["recall_convention"] == "exclude" and res["num_queries"] == 4 and res["test_data"].startswith("msls:val")
    assert "Recall@N convention: exclude" in capsys.readouterr().out
    gm = C.with_overrides(cfg, ["data.format=gmberton", f"data.root={FIX / 'gmberton' / 'pitts30k'}",
                                "data.image_size=[16,16]"])
    res = E.evaluate_run(gm, ck, None)
    assert res["recall_convention"] == "all" and res["num_queries"] == 3 == res["num_queries_total"]
    assert res["queries_without_positive"] == 1
    ex = E.evaluate_run(C.with_overrides(gm, ["eval.recall=exclude"]), ck, None)
    assert ex["num_queries"] == 2 and ex["recall"]["1"] == pytest.approx(res["recall"]["1"] * 3 / 2)
    nord = C.with_overrides(cfg, ["data.format=nordland", f"data.root={FIX / 'nordland'}", "data.image_size=[16,16]",
                                  "data.nordland_protocol=25m"])
    res = E.evaluate_run(nord, ck, None)
    assert res["data"]["nordland_protocol"] == "25m" and res["num_queries"] == 4


@pytest.mark.slow
def test_evaluate_a_run_and_another_dataset(tmp_path):
    from vpr_nb.evaluate import main as evaluate_main
    _run(SMALL[:-5] + ["--set", "train.epochs=1", "--no-progress"], tmp_path / "run")
    assert evaluate_main(["--run", str(tmp_path / "run"), "--out", str(tmp_path / "ev"), "--predictions"]) == 0
    rec = json.loads((tmp_path / "ev" / "recalls.json").read_text())
    assert set(rec["recall"]) == {"1", "5", "10", "20"} and all(0 <= v <= 1 for v in rec["recall"].values())
    rows = (tmp_path / "ev" / "predictions.csv").read_text().splitlines()
    assert len(rows) == rec["num_queries_total"] + 1 and (tmp_path / "ev" / "retrieval_grid.png").stat().st_size > 0
    root = FIX / "gmberton" / "pitts30k"
    assert evaluate_main(["--run", str(tmp_path / "run"), "--out", str(tmp_path / "ev2"), "--set",
                          "data.format=gmberton", "--set", f"data.root={root}", "--set", "data.image_size=[16,24]"]) == 0
    rec2 = json.loads((tmp_path / "ev2" / "recalls.json").read_text())
    assert rec2["num_queries"] == 3 and rec2["recall_convention"] == "all"
    assert evaluate_main(["--run", str(tmp_path / "nowhere"), "--out", str(tmp_path / "ev3")]) == 2
    # a pickled (not weights-only) checkpoint: a clear refusal
    torch.save({"model": TinyViT()}, tmp_path / "pickled.pt")
    assert evaluate_main(["--run", str(tmp_path / "run"), "--checkpoint", str(tmp_path / "pickled.pt"),
                          "--out", str(tmp_path / "ev4")]) == 2


# ------------------------------------------------------------------------------------------ samplers and resume
@pytest.mark.parametrize("sampler", ["random", "clique"])
def test_place_samplers_train(sampler):
    from vpr_nb.seeding import seed_everything
    from vpr_nb.models import build_model
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import TrainConfig, train

    ds = make_dataset("route", 0, num_frames=200, image_size=(16, 24))
    cfg = C.resolve("synthetic-route-ms", [f"source.sampler={sampler}", "source.places_per_batch=4",
                                           "source.batches_per_epoch=2"])
    source, per_epoch = E.build_source(cfg, ds.train)
    assert per_epoch == 2
    batches = source.make_batches(None if sampler == "random" else build_model("small_cnn", "gem"), 0,
                                  np.random.default_rng(0))
    assert batches.shape == (2, 4, 4) and len(np.unique(batches[0])) == 16
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    hist = train(model, source, ds.val, TrainConfig(epochs=1, optimizer="adam", lr=1e-3), progress=False)
    assert np.isfinite(hist.losses).all()
    with pytest.raises(ValueError, match="gsv_root|GSV"):
        E.build_source(C.with_overrides(cfg, ["source.sampler=clique+random"]), ds.train)


@pytest.mark.slow
def test_cliquemining_run_resumes_exactly(tmp_path):
    from vpr_nb.seeding import seed_everything
    from vpr_nb.models import build_model
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import TrainConfig, train

    ds = make_dataset("route", 0, num_frames=160, image_size=(16, 24))
    cfg = C.resolve("synthetic-route-ms", ["source.sampler=clique", "source.places_per_batch=4",
                                           "source.batches_per_epoch=2"])
    tc = TrainConfig(epochs=2, optimizer="adam", lr=1e-3)

    def fresh():
        seed_everything(0)
        return build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))

    full = fresh()
    train(full, E.build_source(cfg, ds.train)[0], ds.val, tc, progress=False)
    part = fresh()
    train(part, E.build_source(cfg, ds.train)[0], ds.val, tc, checkpoint_dir=tmp_path, progress=False, stop_after=1)
    resumed = fresh()                                     # a new process: fresh model and sampler
    train(resumed, E.build_source(cfg, ds.train)[0], ds.val, tc, checkpoint_dir=tmp_path, progress=False)
    assert all(torch.equal(a, b) for a, b in zip(full.state_dict().values(), resumed.state_dict().values()))


# ------------------------------------------------------------------------------------------ resume with changes
def _small(epochs, *sets):
    args = [a if a != "train.epochs=2" else f"train.epochs={epochs}" for a in SMALL]
    return ["--preset", "synthetic-city-triplet"] + args + [x for s in sets for x in ("--set", s)]


def _without_seconds(rows):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def test_resume_with_more_epochs_ends_as_a_run_started_with_them(tmp_path):
    """--resume --set train.epochs=6 on a finished 4-epoch run: the weights, history, logs and results of a
    straight 6-epoch run (StepLR counts epochs from the start, so nothing depends on the budget)."""
    ext, straight = tmp_path / "extended", tmp_path / "straight"
    assert main(_small(4) + ["--out", str(ext)]) == 0
    assert main(["--resume", "--out", str(ext), "--set", "train.epochs=6", "--no-progress"]) == 0
    assert main(_small(6) + ["--out", str(straight)]) == 0
    for name in ("last.pt", "best.pt"):                                # bit-identical state dicts
        a, b = (torch.load(d / "checkpoints" / name, weights_only=True) for d in (ext, straight))
        assert a["epoch"] == b["epoch"] and a["model"].keys() == b["model"].keys(), name
        assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"]), name
    h_ext, h_straight = (json.loads((d / "history.json").read_text()) for d in (ext, straight))
    assert len(h_ext["epochs"]) == 6 and _without_seconds(h_ext["epochs"]) == _without_seconds(h_straight["epochs"])
    assert {k: v for k, v in h_ext.items() if k != "epochs"} == {k: v for k, v in h_straight.items() if k != "epochs"}
    assert json.loads((ext / "results.json").read_text()) == json.loads((straight / "results.json").read_text())
    assert json.loads((ext / "config.json").read_text()) == json.loads((straight / "config.json").read_text())
    steps = [_without_seconds(csv.DictReader(open(d / "steps.csv"))) for d in (ext, straight)]
    assert len(steps[0]) == 30 and steps[0] == steps[1]
    log = (ext / "train.log").read_text()
    assert "changed: train.epochs: 4 → 6" in log and "4 of 6 epochs trained" in log and "epoch 6/6:" in log


def test_resume_with_another_config_names_each_field_and_the_new_run_command(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(_small(1, "train.lr=0.001") + ["--out", str(out)]) == 0
    saved = (out / "config.json").read_text()
    capsys.readouterr()
    assert main(["--resume", "--out", str(out), "--set", "train.lr=0.01", "--set", "data.seed=3",
                 "--set", "train.epochs=2"]) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --resume: ") and "Traceback" not in err, err
    assert "(data.seed: 0 → 3, train.lr: 0.001 → 0.01)" in lines[0]      # every changed field, not the epochs
    assert "may change only train.epochs and train.patience" in lines[0]
    command = shlex.split(lines[0].split("start a new run: ", 1)[1])
    assert command[:3] == ["python", "-m", "vpr_nb.train"] and command[-2:] == ["--out", "NEW_DIR"]
    assert main(command[3:-1] + [str(tmp_path / "new"), "--print-config"]) == 0     # the command as printed
    want = C.with_overrides(C.RunConfig.from_dict(json.loads(saved)),
                            ["train.lr=0.01", "data.seed=3", "train.epochs=2"])
    assert json.loads(capsys.readouterr().out) == want.to_dict()
    assert (out / "config.json").read_text() == saved and not (tmp_path / "new").exists()   # nothing touched


# ------------------------------------------------------------------------------------------ --help
@pytest.mark.parametrize("script, module", [("vpr-train", "vpr_nb.train"), ("vpr-evaluate", "vpr_nb.evaluate"),
                                            ("vpr-pretrain", "vpr_nb.pretrain")])
def test_help_names_the_script_reads_as_plain_text_and_gives_examples(script, module, monkeypatch, capsys):
    script_main = importlib.import_module(module).main
    for argv0, prog in ((f"/venv/bin/{script}", script), ("/usr/lib/python3/bin/pytest", f"python -m {module}")):
        monkeypatch.setattr(sys, "argv", [argv0, "--help"])
        with pytest.raises(SystemExit) as done:
            script_main(["--help"])
        text = capsys.readouterr().out
        assert done.value.code == 0 and text.startswith(f"usage: {prog} "), text[:200]
        assert "``" not in text and not any(role in text for role in (":func:", ":class:", ":mod:", ":meth:")), text
        examples = text.split("examples:\n", 1)[1].splitlines()
        assert sum(line.startswith(f"  {prog}") for line in examples) >= 2, text
    assert plain_text("``a --b`` :func:`vpr_nb.x.f`, :class:`~vpr_nb.run_folder.OutputFolder`, :mod:`t <vpr_nb.t>`, "
                      "**bold** `x`::") == "a --b vpr_nb.x.f, OutputFolder, t, bold x:"


# ------------------------------------------------------------------------------------------ synthetic runs, DDP
def _run(args, tmp, nproc=1):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if nproc == 1:
        cmd = [sys.executable, "-m", "vpr_nb.train"]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
               "-m", "vpr_nb.train"]
    subprocess.run(cmd + ["--preset", "synthetic-city-triplet", "--out", str(tmp)] + args, check=True, env=env,
                   capture_output=True, timeout=600)
    return json.loads((tmp / "results.json").read_text()), json.loads((tmp / "history.json").read_text())


@pytest.mark.slow
def test_ddp_two_processes_match_one(tmp_path):
    one, h1 = _run(SMALL, tmp_path / "one")
    two, h2 = _run(SMALL, tmp_path / "two", nproc=2)
    assert json.loads((tmp_path / "one" / "config.json").read_text())["preset"] == "synthetic-city-triplet"
    assert (tmp_path / "two" / "checkpoints" / "last.pt").is_file()
    for a, b in zip(h1["epochs"], h2["epochs"]):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-3)
    for n in one["test"]:
        assert abs(one["test"][n] - two["test"][n]) <= 0.05


def test_real_format_split_trains_and_evaluates():
    """A gmberton-format fixture goes through the same loop as the synthetic world (images read lazily)."""
    from vpr_nb.seeding import seed_everything
    from vpr_nb.datasets import ImageArray, TrainingSplit, load
    from vpr_nb.evaluation import compute_descriptors, evaluate_model
    from vpr_nb.models import build_model
    from vpr_nb.training import TrainConfig, TripletSource, train

    split = TrainingSplit(load(FIX / "gmberton" / "pitts30k", "gmberton", split="test"), (16, 16))
    assert isinstance(split.db_images, ImageArray) and split.db_images.shape[1:] == (16, 16, 3)
    assert split.db_images[[0, 1]].dtype == np.uint8 and split.db_images[0].shape == (16, 16, 3)
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    assert compute_descriptors(model, split.db_images).shape == (len(split.db_images), 16)
    source = TripletSource(split, batch_size=2, num_negatives=1, num_candidates=10)
    hist = train(model, source, split, TrainConfig(epochs=1, ns=(1, 2)), progress=False)
    assert len(hist.epochs) == 1 and set(evaluate_model(model, split, ns=(1, 2))) == {1, 2}
    assert split.recall_convention == "all"      # validation and evaluation count the query without a positive...
    with pytest.warns(UserWarning, match="no positive"):        # ...which the MSLS convention leaves out
        evaluate_model(model, split, ns=(1,), no_positive="exclude")
    with pytest.raises(ValueError, match="fixed size"):
        ImageArray(split.geo.db_paths, None)
