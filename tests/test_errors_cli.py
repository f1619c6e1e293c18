"""The commands on wrong inputs and faults: one ``error: ...`` line naming the file / field and the fix, exit
status 2, no traceback, nothing written before the checks that need no data, and a ``--out`` that a failed
start leaves reusable; warnings as one ``warning: ...`` line; Ctrl-C as one line and exit status 130 with the
run resumable. Also what a run writes besides its results: the CSV logs, ``train.log``, TensorBoard events when
installed, and the one-screen summary."""
import errno
import json
import logging
import os
import shlex
import shutil
import warnings
from pathlib import Path

import numpy
import pytest
import torch

from vpr_nb import cli
from vpr_nb import config as C
from vpr_nb import experiment as E
from vpr_nb.atomic import atomic_write_text
from vpr_nb.evaluate import main as evaluate_main
from vpr_nb.kernels import cpu_description
from vpr_nb.pretrain import main as pretrain_main
from vpr_nb.run_folder import FolderLock, OutputFolder
from vpr_nb.run_log import RunLog, tensorboard_writer_class
from vpr_nb.train import main as train_main
from vpr_nb.training import load_checkpoint, save_checkpoint

FIX = Path(__file__).resolve().parents[1] / "data_fixtures"
WORLD = 'data.overrides={"blocks": [5, 2], "image_size": [16, 24], "queries_per_place": 1.0%s}'
NET = 'model.backbone_kwargs={"width": 8, "out_channels": 16}'


def tiny(world_extra="", *sets, epochs=1):
    """``synthetic-city-triplet`` on a 5x2-block world of 16x24 images with an 8-channel CNN."""
    args = ["--preset", "synthetic-city-triplet", "--set", WORLD % world_extra, "--set", NET,
            "--set", f"train.epochs={epochs}", "--set", "train.step_size=1", "--set", "source.num_candidates=50",
            "--no-progress"]
    for s in sets:
        args += ["--set", s]
    return args


def fails(main, argv, capsys, *needles) -> str:
    """``main(argv)`` exits 2 with exactly one ``error:`` line (containing every needle) and no traceback."""
    rc = main(argv)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert rc == 2 and len(errors) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in errors[0], errors[0]
    return errors[0]


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


# ------------------------------------------------------------------------------------------ no optimiser step
def test_a_run_that_takes_no_step_fails_and_leaves_out_reusable(tmp_path, capsys):
    out = tmp_path / "run"
    fails(train_main, tiny(', "train_pos_radius": 0.001') + ["--out", str(out)], capsys,
          "took no optimiser step", "no positives within 0.001 m for 67 of 67 training queries")
    assert not out.exists()                       # nothing left: the corrected command may use the same --out
    out.mkdir()                                   # an empty folder given by the user stays, empty
    fails(train_main, tiny(', "train_pos_radius": 0.001') + ["--out", str(out)], capsys, "no positives")
    assert listing(out) == []


def test_a_place_source_without_batches_fails():
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import PlaceBatchSource, TrainConfig, train
    import numpy as np

    ds = make_dataset("route", 0, num_frames=60, image_size=(16, 24))
    src = PlaceBatchSource(ds.train.db_images, lambda m, e, r: np.zeros((0, 4, 2), np.int64))
    model = E.build(C.resolve("synthetic-route-ms", [NET]))
    with pytest.raises(ValueError, match="took no optimiser step, so nothing would be trained: make_batches gave no"):
        train(model, src, ds.val, TrainConfig(epochs=1, optimizer="adam", lr=1e-3), progress=False)


# ------------------------------------------------------------------------------------------ divergence, disk, device
def test_a_diverging_run_names_the_step_and_the_lr(tmp_path, capsys):
    out = tmp_path / "run"
    fails(train_main, tiny("", "train.lr=1e8") + ["--out", str(out)], capsys,
          "training diverged", "at optimiser step", "(lr 1e+08)", "lower train.lr")
    assert not out.exists()


def test_a_model_that_gives_nan_before_training_is_named():
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import TrainConfig, TripletSource, train

    ds = make_dataset("city", 0, "tiny", blocks=[5, 2], image_size=[16, 24], queries_per_place=1.0)
    model = E.build(C.resolve("synthetic-city-triplet", [NET]))
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))          # e.g. a broken backbone checkpoint
    with pytest.raises(ValueError, match="the model's weights hold NaN or inf at the start of epoch 0"):
        train(model, TripletSource(ds.train, num_candidates=50), ds.val, TrainConfig(epochs=1), progress=False)
    model = E.build(C.resolve("synthetic-city-triplet", [NET]))
    with torch.no_grad():
        next(model.parameters()).mul_(1e37)                    # finite weights whose activations overflow
    with pytest.raises(ValueError, match="before the first optimiser step: the untrained model gives NaN/inf"):
        train(model, TripletSource(ds.train, num_candidates=50), ds.val, TrainConfig(epochs=1), progress=False)


@pytest.mark.parametrize("how", ["oserror", "dev-full"])
def test_a_full_disk_while_writing_a_checkpoint(tmp_path, capsys, monkeypatch, how):
    """One line naming the checkpoint and the fix; no temporary file; the folder left reusable."""
    real_save = torch.save

    def full_disk(state, f):
        if how == "oserror":
            f.write(b"PK\x03\x04 half a checkpoint")
            raise OSError(errno.ENOSPC, "No space left on device")
        with open("/dev/full", "wb") as full:          # torch's own failure: three chained exceptions
            real_save(state, full)
    if how == "dev-full" and not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    monkeypatch.setattr(torch, "save", full_disk)
    out = tmp_path / "run"
    fails(train_main, tiny() + ["--out", str(out)], capsys, "could not write", "best.pt", "the disk is full")
    assert not out.exists()


def test_a_failed_write_keeps_the_previous_file_and_no_temporary(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "best.pt", {"w": torch.ones(3)})
    before = path.read_bytes()
    monkeypatch.setattr(torch, "save", lambda state, f: (f.write(b"xx"), (_ for _ in ()).throw(
        OSError(errno.ENOSPC, "No space left on device"))))
    with pytest.raises(OSError, match="best.pt .*the disk is full.*previous best.pt .*unchanged"):
        save_checkpoint(path, {"w": torch.zeros(3)})
    assert path.read_bytes() == before and listing(tmp_path) == ["best.pt"]
    assert (path.stat().st_mode & 0o777) == (0o666 & ~_umask())        # as open() makes files, not 0o600
    with pytest.raises(UnicodeEncodeError):
        atomic_write_text(tmp_path / "names.txt", "a\udcff")           # a name that is not UTF-8, strict
    assert listing(tmp_path) == ["best.pt"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_without_cuda_is_refused_before_out_is_written(tmp_path, capsys):
    out = tmp_path / "run"
    fails(train_main, tiny("", "train.device=cuda") + ["--out", str(out)], capsys,
          "train.device=cuda: CUDA is not available", "train.device=auto")
    assert not out.exists()
    cfg, ck = _checkpoint(tmp_path)
    fails(evaluate_main, ["--preset", "synthetic-city-triplet", "--checkpoint", str(ck), "--set", NET,
                          "--out", str(tmp_path / "ev"), "--device", "cuda"], capsys, "--device=cuda")
    assert not (tmp_path / "ev").exists()


def test_unknown_backbone_kwargs_are_refused_before_anything(tmp_path, capsys):
    out = tmp_path / "run"
    fails(train_main, tiny() + ["--set", 'model.backbone_kwargs={"widht": 8}', "--out", str(out)], capsys,
          "model.backbone_kwargs: small_cnn does not take 'widht'", "its options are in_channels, width")
    assert not out.exists()
    with pytest.raises(ValueError, match="vgg16 does not take 'pretrained'"):
        C.validate(C.resolve("dwt-pitts30k", ['model.backbone_kwargs={"pretrained": true}', "data.root=/x"]))


def test_a_start_that_fails_on_missing_data_leaves_out_reusable(tmp_path, capsys):
    out = tmp_path / "run"
    missing = ["--set", "data.format=gmberton", "--set", f"data.root={tmp_path / 'nowhere'}",
               "--set", "data.image_size=[16,16]"]
    fails(train_main, tiny() + missing + ["--out", str(out)], capsys, "nowhere")
    assert not out.exists()
    out.mkdir()
    fails(train_main, tiny() + missing + ["--out", str(out)], capsys, "nowhere")
    assert listing(out) == []
    with OutputFolder(out):                       # the corrected command is not refused
        pass


# ------------------------------------------------------------------------------------------ resume, evaluate
@pytest.mark.parametrize("content, needle", [(b'{"preset": ', "is not valid JSON (Expecting value, line 1"),
                                             (b"\xff\xfe{}", "is not UTF-8 text"),
                                             (b"[1, 2]", "is not a run config")])
def test_resume_and_evaluate_on_a_broken_config_json_name_the_file(tmp_path, capsys, content, needle):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_bytes(content)
    fails(train_main, ["--resume", "--out", str(run)], capsys, str(run / "config.json"), needle)
    fails(evaluate_main, ["--run", str(run), "--out", str(tmp_path / "ev")], capsys, str(run / "config.json"), needle)
    assert not (tmp_path / "ev").exists()
    fails(train_main, ["--resume", "--out", str(tmp_path / "none")], capsys, "config.json not found")


def _checkpoint(tmp_path, backbone_kwargs=NET):
    torch.manual_seed(0)
    cfg = C.resolve("synthetic-city-triplet", [backbone_kwargs])
    return cfg, save_checkpoint(tmp_path / "best.pt", {"model": E.build(cfg).state_dict()})


def _gmberton(root=FIX / "gmberton" / "pitts30k"):
    return ["--set", "data.format=gmberton", "--set", f"data.root={root}", "--set", "data.image_size=[16,16]",
            "--set", NET]


@pytest.mark.parametrize("sets, needles", [
    (['model.backbone_kwargs={"width": 16, "out_channels": 16}'],
     ("does not fit this VPRModel", "tensor(s) differ: backbone.features.0.weight is (8, 3, 4, 4) in the file but "
      "(16, 3, 4, 4) in the model", "--run its run folder")),
    ([NET, "model.aggregator=netvlad"],
     ("key(s) of the model are missing: aggregator.centroids", "are not in the model: aggregator.p"))])
def test_evaluate_a_checkpoint_of_another_model(tmp_path, capsys, sets, needles):
    _, ck = _checkpoint(tmp_path)
    args = ["--preset", "synthetic-city-triplet", "--checkpoint", str(ck), "--out", str(tmp_path / "ev")]
    for s in sets:
        args += ["--set", s]
    fails(evaluate_main, args, capsys, str(ck), *needles)
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("keep", [0, 1, 100, 0.5, -100, -1])
def test_evaluate_a_truncated_checkpoint(tmp_path, capsys, keep):
    _, ck = _checkpoint(tmp_path)
    data = ck.read_bytes()
    n = int(len(data) * keep) if isinstance(keep, float) else keep % len(data) if keep < 0 else keep
    (tmp_path / "cut.pt").write_bytes(data[:n])
    fails(evaluate_main, ["--preset", "synthetic-city-triplet", "--checkpoint", str(tmp_path / "cut.pt"),
                          "--set", NET, "--out", str(tmp_path / "ev")], capsys, str(tmp_path / "cut.pt"),
          "torch checkpoint", "restore it or write it again")
    with pytest.raises(ValueError):
        load_checkpoint(tmp_path / "cut.pt")


def test_evaluate_writes_predictions_of_non_utf8_file_names_whole(tmp_path, capsys):
    root = tmp_path / "gm"
    shutil.copytree(FIX / "gmberton" / "pitts30k", root)
    db = root / "images" / "test" / "database"
    first = sorted(os.listdir(db))[0]
    os.rename(os.fsencode(db / first), os.fsencode(db) + b"/" + first.replace("pano0", "pano\xe9").encode("latin-1"))
    _, ck = _checkpoint(tmp_path)
    ev = tmp_path / "ev"
    assert evaluate_main(["--preset", "synthetic-city-triplet", "--checkpoint", str(ck), "--out", str(ev),
                          "--predictions"] + _gmberton(root)) == 0
    rows = (ev / "predictions.csv").read_bytes().splitlines()
    rec = json.loads((ev / "recalls.json").read_text())
    assert len(rows) == rec["num_queries_total"] + 1 and b"pano\xe9" in b"".join(rows)   # the name's own bytes
    assert sorted(p.name for p in ev.iterdir()) == ["predictions.csv", "recalls.json", "retrieval_grid.png"]


# ------------------------------------------------------------------------------------------ the lock in the commands
def test_train_and_evaluate_refuse_a_folder_another_run_holds(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    with FolderLock(out):
        err = fails(train_main, tiny() + ["--out", str(out)], capsys, "is in use by another run", f"process {os.getpid()}")
        assert "wait for it to finish or choose another folder" in err
        _, ck = _checkpoint(tmp_path)
        fails(evaluate_main, ["--preset", "synthetic-city-triplet", "--checkpoint", str(ck), "--out", str(out)]
              + _gmberton(), capsys, "is in use by another run")
        assert listing(out) == [".lock"]
    assert listing(out) == []


def test_stale_temporaries_of_a_killed_writer_are_removed(tmp_path):
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    for name in (".last.pt.ab12.tmp", "best.pt3f9x.tmp"):
        (out / "checkpoints" / name).write_bytes(b"half")
    (out / "config.json").write_text("{}")
    with OutputFolder(out, resume=True):
        assert listing(out / "checkpoints") == []


# ------------------------------------------------------------------------------------------ logs and summary
def test_a_run_writes_step_and_epoch_csvs_and_a_short_summary(tmp_path, capsys):
    import csv
    out = tmp_path / "run"
    assert train_main(tiny(epochs=2) + ["--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    summary = stdout[:stdout.index("\n{")].splitlines()
    assert len(summary) <= 15 and summary[0].startswith("synthetic-city-triplet -> ")
    assert any("train: epochs=2, lr=0.05, step_size=1" in line for line in summary)   # the preset's lr, notebook 02's
    assert any("2 epochs x 5 = 10 optimiser steps" in line for line in summary)
    assert C.RunConfig.from_dict(json.loads((out / "config.json").read_text())) == C.resolve(
        "synthetic-city-triplet", [a for a in tiny(epochs=2) if "=" in a])          # the full config
    steps = list(csv.DictReader(open(out / "steps.csv")))
    epochs = list(csv.DictReader(open(out / "epochs.csv")))
    history = json.loads((out / "history.json").read_text())["epochs"]
    assert [int(r["global_step"]) for r in steps] == list(range(10)) and {r["epoch"] for r in steps} == {"0", "1"}
    assert [int(r["steps"]) for r in epochs] == [5, 5]
    for row, h in zip(epochs, history):
        assert float(row["loss"]) == pytest.approx(h["loss"]) and float(row["val_R@1"]) == pytest.approx(h["val"]["1"])
    assert float(steps[0]["lr"]) == 0.05 and float(steps[-1]["lr"]) == 0.025          # StepLR(1, 0.5)
    mean0 = sum(float(r["loss"]) for r in steps if r["epoch"] == "0") / 5
    assert mean0 == pytest.approx(history[0]["loss"])
    tb = tensorboard_writer_class() is not None
    assert any(("TensorBoard: tensorboard/" if tb else "TensorBoard: not installed") in line for line in summary)
    assert (out / "tensorboard").is_dir() == tb
    assert train_main(tiny(epochs=2) + ["--out", str(out), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == C.resolve("synthetic-city-triplet", [
        a for a in tiny(epochs=2) if "=" in a]).to_dict()


def test_a_resumed_log_drops_the_rows_of_epochs_it_runs_again(tmp_path):
    def epoch(log, e, steps):
        for i in range(steps):
            log.step({"epoch": e, "step": i, "loss": float(e + i), "collapsed_loss": 0.5, "lr": 0.1, "seconds": 0.0})
        log.epoch({"epoch": e, "loss": float(e), "collapsed_loss": 0.5, "mean_cosine": 0.9, "lr": 0.1,
                   "seconds": 1.0, "val": {1: 0.5, 5: 0.75}})
    with RunLog(tmp_path, tensorboard=False) as log:
        epoch(log, 0, 3)
        epoch(log, 1, 2)
        log.step({"epoch": 2, "step": 0, "loss": 9.0, "collapsed_loss": 0.5, "lr": 0.1, "seconds": 0.0})  # interrupted
    with RunLog(tmp_path, tensorboard=False) as log:      # resumed from the checkpoint of epoch 1
        epoch(log, 2, 4)
    import csv
    steps = list(csv.DictReader(open(tmp_path / "steps.csv")))
    epochs = list(csv.DictReader(open(tmp_path / "epochs.csv")))
    assert [(r["epoch"], r["global_step"]) for r in steps] == [("0", "0"), ("0", "1"), ("0", "2"), ("1", "3"),
                                                                ("1", "4"), ("2", "5"), ("2", "6"), ("2", "7"), ("2", "8")]
    assert [r["steps"] for r in epochs] == ["3", "2", "4"] and epochs[0]["val_R@5"] == "0.75"
    with RunLog(tmp_path, tensorboard=False) as log:      # resumed from epoch 0's checkpoint
        epoch(log, 1, 1)
    assert [r["epoch"] for r in csv.DictReader(open(tmp_path / "epochs.csv"))] == ["0", "1"]
    assert len(list(csv.DictReader(open(tmp_path / "steps.csv")))) == 4


def test_tensorboard_events_when_installed(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    def epoch(log, e, steps):
        for i in range(steps):
            log.step({"epoch": e, "step": i, "loss": float(10 * e + i), "collapsed_loss": 0.5, "lr": 0.1,
                      "seconds": 0.0})
        log.epoch({"epoch": e, "loss": float(e), "collapsed_loss": 0.5, "mean_cosine": 0.9, "lr": 0.1,
                   "seconds": 1.0, "val": {1: 0.5}})
    with RunLog(tmp_path) as log:
        epoch(log, 0, 2)
        epoch(log, 1, 2)
    with RunLog(tmp_path) as log:                         # resumed after epoch 0: epoch 1's events purged
        epoch(log, 1, 3)
    assert log.tensorboard == tmp_path / "tensorboard" and any((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    ea = EventAccumulator(str(tmp_path / "tensorboard"))
    ea.Reload()
    assert [(e.step, e.value) for e in ea.Scalars("train/loss")] == [(0, 0.0), (1, 1.0), (2, 10.0), (3, 11.0), (4, 12.0)]
    assert [e.step for e in ea.Scalars("val/R@1")] == [1, 4]


# ------------------------------------------------------------------------------------------ Ctrl-C and warnings
def _ctrl_c_at_call(monkeypatch, n: int):
    """Ctrl-C (KeyboardInterrupt) in the ``n``-th optimiser step of the process (counted from 1)."""
    import vpr_nb.training.loop as loop
    real, calls = loop.optimizer_step, []

    def step(*args, **kwargs):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)
    monkeypatch.setattr(loop, "optimizer_step", step)


def test_ctrl_c_is_one_line_status_130_and_the_run_resumes(tmp_path, capsys, monkeypatch):
    out, straight = tmp_path / "run", tmp_path / "straight"
    _ctrl_c_at_call(monkeypatch, 5 + 3)              # 5 steps per epoch: epoch 2, after its 2nd step
    assert train_main(tiny(epochs=2) + ["--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert err.splitlines() == [f"interrupted at epoch 2, step 2; resume with: python -m vpr_nb.train --resume "
                                f"--out {out}"], err
    assert load_checkpoint(out / "checkpoints" / "last.pt")["epoch"] == 0     # epoch 1 is saved, whole
    assert not (out / ".lock").exists()
    last = (out / "train.log").read_text().splitlines()[-1]
    assert "interrupted at epoch 2, step 2; resume with:" in last and last.endswith("(last saved: epoch 1)")
    monkeypatch.undo()
    assert train_main(["--resume", "--out", str(out), "--no-progress"]) == 0   # epoch 2 again, from its start
    assert train_main(tiny(epochs=2) + ["--out", str(straight)]) == 0
    a, b = (load_checkpoint(d / "checkpoints" / "last.pt")["model"] for d in (out, straight))
    assert all(torch.equal(a[k], b[k]) for k in a)                 # nothing lost
    assert [e["loss"] for e in json.loads((out / "history.json").read_text())["epochs"]] == \
        [e["loss"] for e in json.loads((straight / "history.json").read_text())["epochs"]]


def test_ctrl_c_before_the_first_checkpoint_leaves_nothing_and_says_so(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    _ctrl_c_at_call(monkeypatch, 1)
    argv = tiny() + ["--out", str(out)]
    assert train_main(argv) == 130
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"interrupted at epoch 1, step 0; nothing to resume in {out} "), err
    assert err[0].endswith("start again with: python -m vpr_nb.train " + " ".join(map(shlex.quote, argv)))
    assert not out.exists()                         # the folder is left as it was found: the command can be rerun


def test_a_warning_is_one_line_without_a_path_and_goes_into_train_log(tmp_path, capsys):
    out = tmp_path / "run"
    shown = warnings.showwarning
    assert train_main(tiny("", "eval.ns=[1,5,1000]") + ["--out", str(out)]) == 0     # more than the 172 images
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: Recall@N for N = [1000] is larger than the database (172 images): it equals "
                   "Recall@172, which is reported for those N"], err
    assert "warning: Recall@N for N = [1000] is larger" in (out / "train.log").read_text()
    assert warnings.showwarning is shown            # the CLI's channel is gone once main returns (notebooks)
    with cli.diagnostics():
        warnings.warn("a\nb", RuntimeWarning)
        logging.getLogger("vpr_nb.test").warning("from logging")
        logging.getLogger("vpr_nb.test").error("an error")
    assert capsys.readouterr().err.splitlines() == ["warning: a b (RuntimeWarning)", "warning: from logging",
                                                    "error: an error"]


def test_every_run_writes_train_log_and_a_resume_appends(tmp_path):
    out = tmp_path / "run"
    assert train_main(tiny(epochs=2) + ["--out", str(out)]) == 0
    first = (out / "train.log").read_text()
    lines = [line[20:] for line in first.splitlines()]             # after the "YYYY-mm-dd HH:MM:SS " stamp
    assert lines[0] == f"start: a new run in {out}"
    train_cfg = next(json.loads(line[len("config train: "):]) for line in lines if line.startswith("config train: "))
    assert train_cfg["epochs"] == 2 and train_cfg["step_size"] == 1
    env = next(line for line in lines if line.startswith("environment: "))
    assert f"torch {torch.__version__}" in env and f"numpy {numpy.__version__}" in env and "device cpu" in env
    assert cpu_description() in env
    epochs = [line for line in lines if line.startswith("epoch ")]
    assert [e.split(":")[0] for e in epochs] == ["epoch 1/2", "epoch 2/2"] and all("val R@1 " in e for e in epochs)
    history = json.loads((out / "history.json").read_text())["epochs"]
    assert f"loss {history[1]['loss']:.4f}" in epochs[1] and f"R@5 {history[1]['val']['5']:.4f}" in epochs[1]
    assert lines[-1].startswith("end: 2 epochs, selected epoch ") and "test R@1 " in lines[-1]
    assert train_main(["--resume", "--out", str(out), "--no-progress"]) == 0
    again = (out / "train.log").read_text()
    assert again.startswith(first) and f"start: resuming the run in {out}" in again[len(first):]
    assert "2 of 2 epochs trained" in again[len(first):] and again.rstrip().splitlines()[-1][20:].startswith("end: ")


# ------------------------------------------------------------------------------------------ pretrain
def test_pretrain_refuses_bad_settings_before_training(tmp_path, capsys):
    fails(pretrain_main, ["--profile", "quick", "--out", str(tmp_path / "cb.pt"), "--set", "lr=abc"], capsys,
          "--set lr must be a number")
    fails(pretrain_main, ["--profile", "quick", "--out", str(tmp_path / "cb.pt"), "--set", "city_seeds=[3]"], capsys,
          "corpus world seeds must be >= 100")
    fails(pretrain_main, ["--profile", "quick", "--out", str(tmp_path / "cb.pt"), "--set", "depth=3"], capsys,
          "--set 'depth=3': expected KEY=VALUE with KEY one of city_seeds")
    fails(pretrain_main, ["--profile", "quick", "--out", str(tmp_path)], capsys, "is a folder")
    assert listing(tmp_path) == []
