"""The reproduction command: presets, overrides, outputs, and DDP (2 CPU processes, gloo) vs 1 process."""
import json
import os
import subprocess
import sys

import pytest

from vpr_nb.train import PRESETS, main, resolve_config

SMALL = ["--set", 'data.overrides={"blocks": [5, 2], "image_size": [16, 24], "queries_per_place": 1.0}',
         "--set", 'model.backbone_kwargs={"width": 8, "out_channels": 16}',
         "--set", "train.epochs=2", "--set", "train.step_size=1", "--set", "source.num_candidates=50",
         "--no-progress"]


def test_every_preset_resolves_and_prints(capsys):
    for name in PRESETS:
        assert main(["--preset", name, "--print-config"]) == 0
        cfg = json.loads(capsys.readouterr().out)
        assert cfg["preset"] == name and {"data", "model", "source", "train"} <= set(cfg)
    dwt = resolve_config("dwt-pitts30k")
    assert dwt["train"]["lr"] == 1e-4 and dwt["train"]["seed"] == 123 and dwt["source"]["num_negatives"] == 10
    assert dwt["model"]["aggregator_kwargs"]["num_clusters"] == 64 and dwt["source"]["batch_size"] == 4
    salad = resolve_config("salad-gsv")
    assert salad["train"]["optimizer"] == "adamw" and salad["train"]["lr"] == 6e-5
    assert salad["source"]["places_per_batch"] == 60 and salad["source"]["images_per_place"] == 4


def test_overrides_are_parsed_and_checked():
    cfg = resolve_config("dwt-pitts30k", ["source.loss=triplet", "train.lr=0.001", "train.ns=[1,5]"])
    assert cfg["source"]["loss"] == "triplet" and cfg["train"]["lr"] == 0.001 and cfg["train"]["ns"] == [1, 5]
    for bad, match in [("train.lrr=1", "unknown key"), ("optim.lr=1", "unknown config section"),
                       ("lr=1", "section.key=value")]:
        with pytest.raises(ValueError, match=match):
            resolve_config("dwt-pitts30k", [bad])
    with pytest.raises(ValueError, match="unknown preset"):
        resolve_config("netvlad-tokyo")


def test_real_data_preset_without_root_says_how_to_fix(tmp_path):
    from vpr_nb.train import load_data
    with pytest.raises(ValueError, match="data.root"):
        load_data(resolve_config("dwt-pitts30k")["data"])


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
    from pathlib import Path

    import numpy as np

    from vpr_nb import seed_everything
    from vpr_nb.datasets import ImageArray, TrainingSplit, load
    from vpr_nb.evaluation import compute_descriptors, evaluate_model
    from vpr_nb.models import build_model
    from vpr_nb.training import TrainConfig, TripletSource, train

    root = Path(__file__).resolve().parents[1] / "data_fixtures" / "gmberton" / "pitts30k"
    split = TrainingSplit(load(root, "gmberton", split="test"), (16, 16))
    assert isinstance(split.db_images, ImageArray) and split.db_images.shape[1:] == (16, 16, 3)
    assert split.db_images[[0, 1]].dtype == np.uint8 and split.db_images[0].shape == (16, 16, 3)
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    assert compute_descriptors(model, split.db_images).shape == (len(split.db_images), 16)
    source = TripletSource(split, batch_size=2, num_negatives=1, num_candidates=10)
    with pytest.warns(UserWarning, match="no positive"):        # the fixture has a query without positives
        hist = train(model, source, split, TrainConfig(epochs=1, ns=(1, 2)), progress=False)
        assert len(hist.epochs) == 1 and set(evaluate_model(model, split, ns=(1, 2))) == {1, 2}
    with pytest.raises(ValueError, match="fixed size"):
        ImageArray(split.geo.db_paths, None)


def test_evaluate_a_run_and_another_dataset(tmp_path):
    from vpr_nb.evaluate import main as evaluate_main
    _run(SMALL[:-5] + ["--set", "train.epochs=1", "--no-progress"], tmp_path / "run")
    assert evaluate_main(["--run", str(tmp_path / "run"), "--out", str(tmp_path / "ev"), "--predictions"]) == 0
    rec = json.loads((tmp_path / "ev" / "recalls.json").read_text())
    assert set(rec["recall"]) == {"1", "5", "10", "20"} and all(0 <= v <= 1 for v in rec["recall"].values())
    rows = (tmp_path / "ev" / "predictions.csv").read_text().splitlines()
    assert len(rows) == rec["num_queries"] + 1 and (tmp_path / "ev" / "retrieval_grid.png").stat().st_size > 0
    # the same weights on a real-format fixture (gmberton layout), test split only
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "data_fixtures" / "gmberton" / "pitts30k"
    with pytest.warns(UserWarning, match="no positive"):
        assert evaluate_main(["--run", str(tmp_path / "run"), "--out", str(tmp_path / "ev2"), "--set",
                              "data.format=gmberton", "--set", f"data.root={root}", "--set", "data.image_size=[16,24]"]) == 0
    rec2 = json.loads((tmp_path / "ev2" / "recalls.json").read_text())
    assert rec2["num_queries"] == 3
    assert evaluate_main(["--run", str(tmp_path / "nowhere"), "--out", str(tmp_path / "ev3")]) == 2


@pytest.mark.parametrize("sampler", ["random", "clique"])
def test_place_samplers_train(sampler):
    import numpy as np

    from vpr_nb import seed_everything
    from vpr_nb.models import build_model
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.train import build_source
    from vpr_nb.training import TrainConfig, train

    ds = make_dataset("route", 0, num_frames=200, image_size=(16, 24))
    src = dict(resolve_config("synthetic-route-ms")["source"], sampler=sampler, places_per_batch=4,
               images_per_place=4, batches_per_epoch=2)
    source = build_source(src, ds.train)
    batches = source.make_batches(None if sampler == "random" else build_model("small_cnn", "gem"), 0,
                                  np.random.default_rng(0))
    assert batches.shape == (2, 4, 4) and len(np.unique(batches[0])) == 16
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    hist = train(model, source, ds.val, TrainConfig(epochs=1, optimizer="adam", lr=1e-3), progress=False)
    assert np.isfinite(hist.losses).all()
    with pytest.raises(ValueError, match="sampler"):
        build_source(dict(src, sampler="nearest"), ds.train)
    with pytest.raises(ValueError, match="gsv_root|GSV"):
        build_source(dict(src, sampler="clique+random"), ds.train)
