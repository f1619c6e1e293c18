"""Tests for vpr_nb.results: committed reproduce-profile results and their staleness check."""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import pytest

from vpr_nb import results
from vpr_nb.reproduce_one import EXTRAS
from vpr_nb.synthetic import CONDITIONS, WORLD_KINDS, make_config

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def test_save_then_load_round_trip(tmp_path):
    cfg = {"epochs": 10, "seeds": (0, 1, 2), "lr": 0.01}
    path = results.save("99_demo", cfg, {"R@1": {"T": [0.5, 0.6]}}, results_dir=tmp_path)
    doc = json.loads(path.read_text())
    assert doc["stamp"]["git commit"] and doc["stamp"]["torch"]
    got = results.load("99_demo", dict(cfg, seeds=[0, 1, 2]), results_dir=tmp_path)   # tuple == list
    assert got["results"] == {"R@1": {"T": [0.5, 0.6]}}


def test_the_stamp_counts_the_fine_tunes_logged_since_the_last_save(tmp_path, monkeypatch):
    log = tmp_path / "03.tasks.jsonl"
    monkeypatch.setenv(results.TIMES_ENV, str(log))
    log.write_text(json.dumps({"t0": 0, "t1": 9, "seconds": [60.0, 90.0], "reused": [True, False]}) + "\n"
                   + json.dumps({"t0": 9, "t1": 12, "seconds": [30.0], "reused": [True]}) + "\n"
                   + '{"t0": 12, "sec')                                  # a torn last line: not counted yet
    first = json.loads(results.save("99_demo", {}, {"x": 1}, results_dir=tmp_path).read_text())
    assert first["stamp"]["fine-tunes"] == {"run": 3, "reused": 2, "task seconds": 180.0}
    with log.open("a") as fh:
        fh.write('onds": [1], "t1": 13, "reused": [false]}\n')       # the torn line, finished
        fh.write(json.dumps({"t0": 13, "t1": 14, "seconds": [5.0], "reused": [False]}) + "\n")
    second = json.loads(results.save("99_other", {}, {"x": 1}, results_dir=tmp_path).read_text())
    assert second["stamp"]["fine-tunes"] == {"run": 2, "reused": 0, "task seconds": 6.0}   # only what came after
    third = json.loads(results.save("99_third", {}, {"x": 1}, results_dir=tmp_path).read_text())
    assert "fine-tunes" not in third["stamp"]                            # nothing since


def test_a_run_started_again_counts_each_fine_tune_once(tmp_path, monkeypatch):
    from vpr_nb import engine
    log = tmp_path / "03.tasks.jsonl"
    monkeypatch.setenv(results.TIMES_ENV, str(log))
    # the first attempt (another process) ran two fine-tunes and was stopped; this one reuses them, runs a third
    log.write_text(json.dumps({"t0": 0, "t1": 9, "seconds": [60.0, 90.0], "reused": [False, False],
                               "process": "0123456789ab"}) + "\n")
    engine.log_round(10.0, 11.0, [60.0, 90.0, 30.0], [True, True, False])
    doc = json.loads(results.save("99_again", {}, {"x": 1}, results_dir=tmp_path).read_text())
    assert doc["stamp"]["fine-tunes"] == {"run": 3, "reused": 2, "task seconds": 180.0}   # not 330


def test_load_refuses_stale_or_missing_results(tmp_path):
    results.save("99_demo", {"epochs": 10, "lr": 0.01}, {"x": 1}, results_dir=tmp_path)
    with pytest.raises(ValueError, match=r"stale.*\['epochs'\]"):
        results.load("99_demo", {"epochs": 12, "lr": 0.01}, results_dir=tmp_path)
    with pytest.raises(ValueError, match=r"stale.*\['seeds'\]"):
        results.load("99_demo", {"epochs": 10, "lr": 0.01, "seeds": [0]}, results_dir=tmp_path)
    with pytest.raises(FileNotFoundError, match="PROFILE = 'reproduce'"):
        results.load("98_none", {}, results_dir=tmp_path)
    with pytest.raises(ValueError, match="notebook stem"):
        results.load("../x", {}, results_dir=tmp_path)


def test_every_committed_result_belongs_to_a_notebook_that_loads_it():
    """A committed file that no notebook reads would be shown nowhere (and never checked)."""
    for path in sorted((NOTEBOOKS / "results").glob("*.json")):
        # NN_name.json belongs to NN_name.ipynb; a package experiment's file (vpr_nb.onoff: NN_premise.json,
        # NN_probes.json, ..., vpr_nb.reproduce_one.EXTRAS) to notebook NN
        nb = NOTEBOOKS / f"{path.stem}.ipynb"
        if path.stem.endswith(tuple(f"_{kind}" for kind in EXTRAS)):
            nb = next(iter(sorted(NOTEBOOKS.glob(f"{path.stem[:2]}_*.ipynb"))), nb)
        assert nb.is_file(), f"{path.name} has no notebook {nb.name}"
        assert re.search(rf"results\.(?:load|made_or_loaded)\(\s*\\?[\"']{path.stem}", nb.read_text()), \
            f"{nb.name} never calls results.load('{path.stem}', ...)"


def test_load_refuses_results_of_other_backbone_weights(tmp_path):
    path = results.save("99_demo", {"epochs": 1}, {"x": 1}, results_dir=tmp_path)
    assert results.load("99_demo", {"epochs": 1}, results_dir=tmp_path)["course_backbone"] == results.backbone_fingerprint()
    doc = json.loads(path.read_text())
    doc["course_backbone"] = "0" * 64
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="other course-backbone weights"):
        results.load("99_demo", {"epochs": 1}, results_dir=tmp_path)


def test_backbone_fingerprint_follows_tensors_not_file_bytes(tmp_path):
    import torch
    from vpr_nb.pretrain import CHECKPOINT
    state = torch.load(CHECKPOINT, weights_only=True)
    torch.save(state, tmp_path / "other_name.pt")                 # other archive name: other bytes, same tensors
    assert results.backbone_fingerprint(tmp_path / "other_name.pt") == results.backbone_fingerprint()
    state[next(iter(state))].view(-1)[0] += 1
    torch.save(state, tmp_path / "changed.pt")
    assert results.backbone_fingerprint(tmp_path / "changed.pt") != results.backbone_fingerprint()


def test_mean_std():
    m, sd = results.mean_std([1.0, 2.0, 3.0])
    assert m == 2.0 and math.isclose(sd, 1.0)
    assert results.mean_std([4.0]) == (4.0, 0.0)
    with pytest.raises(ValueError, match="at least one"):
        results.mean_std([])


def test_print_table(capsys):
    results.print_table({"A": {"R@1": "0.500"}, "B": {"R@1": "0.600"}}, "title", label_width=5, col_width=7)
    assert capsys.readouterr().out.splitlines() == ["title", "           A      B", "  R@1  0.500  0.600"]
    with pytest.raises(ValueError, match="missing"):
        results.print_table({"A": {"R@1": "1"}, "B": {}}, "t")
    with pytest.raises(ValueError, match="non-empty"):
        results.print_table({}, "t")


# ------------------------------------------------------------------- keys: world and backbone fingerprints
WORLD_CFG = {"world": {"preset": "city", "seed": 0, "size": "tiny"}, "epochs": 1}


def test_fresh_when_neither_world_nor_backbone_changed(tmp_path):
    path = results.save("99_demo", WORLD_CFG, {"x": 1}, results_dir=tmp_path)
    doc = results.load("99_demo", WORLD_CFG, results_dir=tmp_path)
    assert doc["worlds"]["world"]["world"] == "city-tiny"
    assert doc["worlds"]["world"]["fingerprint"] == make_config("city").fingerprint()
    assert json.loads(path.read_text())["worlds"] == results.world_fingerprints(WORLD_CFG)


def test_stale_when_a_world_default_changes(tmp_path, monkeypatch):
    results.save("99_demo", WORLD_CFG, {"x": 1}, results_dir=tmp_path)
    # a kind's default moves (its record's deviations): the file names the field, old and new value
    city = WORLD_KINDS["city"]
    monkeypatch.setitem(WORLD_KINDS, "city", dataclasses.replace(city, preset={"building_height": (6.0, 30.0)}))
    with pytest.raises(ValueError, match=r"another synthetic world.*\['building_height'\].*\[6\.0, 26\.0\].*\[6\.0, 30\.0\]"
                                         r".*PROFILE = 'reproduce'"):
        results.load("99_demo", WORLD_CFG, results_dir=tmp_path)


def test_stale_when_a_worldconfig_default_changed_since_saving(tmp_path):
    # a file saved while WorldConfig.fov defaulted to 80: today's default (90) makes it stale
    path = results.save("99_demo", WORLD_CFG, {"x": 1}, results_dir=tmp_path)
    doc = json.loads(path.read_text())
    old = dataclasses.replace(make_config("city"), fov=80.0)
    doc["worlds"]["world"] = {"fingerprint": old.fingerprint(), "world": "city-tiny",
                              "config": json.loads(json.dumps(dataclasses.asdict(old)))}
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"WorldConfig field\(s\) \['fov'\] \(committed \[80\.0\], now \[90\.0\]\)"):
        results.load("99_demo", WORLD_CFG, results_dir=tmp_path)
    del doc["worlds"]                                    # a file from before worlds were fingerprinted
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="no fingerprint of the synthetic world"):
        results.load("99_demo", WORLD_CFG, results_dir=tmp_path)


def test_stale_when_a_condition_row_changes(tmp_path, monkeypatch):
    results.save("99_demo", WORLD_CFG, {"x": 1}, results_dir=tmp_path)
    monkeypatch.setitem(CONDITIONS, "rain", dict(CONDITIONS["rain"], fog=70.0))
    with pytest.raises(ValueError, match="condition rows"):
        results.load("99_demo", WORLD_CFG, results_dir=tmp_path)


def test_stale_when_the_backbone_file_changes(tmp_path, monkeypatch):
    import torch
    from vpr_nb import pretrain
    results.save("99_demo", WORLD_CFG, {"x": 1}, results_dir=tmp_path)
    state = torch.load(pretrain.CHECKPOINT, weights_only=True)
    state[next(iter(state))].view(-1)[0] += 1
    torch.save(state, tmp_path / "retrained.pt")
    monkeypatch.setattr(results, "CHECKPOINT", tmp_path / "retrained.pt")
    with pytest.raises(ValueError, match="other course-backbone weights"):
        results.load("99_demo", WORLD_CFG, results_dir=tmp_path)


def test_world_specs_are_validated_and_several_worlds_are_keyed():
    cfg = {"worlds": {"a": {"preset": "route", "overrides": {"frame_spacing": 2.5}}, "b": {"preset": "city"}}}
    got = results.world_fingerprints(cfg)
    assert sorted(got) == ["worlds.a", "worlds.b"] and got["worlds.a"]["config"]["frame_spacing"] == 2.5
    assert got["worlds.a"]["fingerprint"] != results.world_fingerprints({"worlds": {"a": {"preset": "route"}}})["worlds.a"]["fingerprint"]
    assert results.world_fingerprints({"epochs": 1}) == {}
    with pytest.raises(ValueError, match="unknown preset"):
        results.world_fingerprints({"world": {"preset": "desert"}})
    with pytest.raises(ValueError, match="'preset'"):
        results.world_fingerprints({"worlds": {"a": "city"}})


def test_committed_results_match_todays_worlds():
    """The committed files' world fingerprints are today's: the notebooks' results.load accepts them."""
    for path in sorted((NOTEBOOKS / "results").glob("*.json")):
        doc = json.loads(path.read_text())
        assert doc.get("worlds") == results.world_fingerprints(doc["config"]), f"{path.name}: stale world fingerprint"


def test_committed_results_are_refused_from_a_dirty_tree_unless_allowed(tmp_path, monkeypatch):
    """A reproduce run writes notebooks/results/ only from a clean commit; a trial run may opt out."""
    from vpr_nb import report
    for module in (report, results):      # the stamp (report) and the refusal (results) both ask git
        monkeypatch.setattr(module, "uncommitted_changes", lambda: ["vpr_nb/losses.py"])
    monkeypatch.setenv("VPR_NB_RESULTS_DIR", str(tmp_path))
    monkeypatch.delenv(results.ALLOW_DIRTY_ENV, raising=False)
    with pytest.raises(ValueError, match=r"uncommitted changes \(vpr_nb/losses.py\).*VPR_NB_ALLOW_DIRTY=1"):
        results.save("99_demo", {"epochs": 1}, {"x": 1})
    monkeypatch.setenv(results.ALLOW_DIRTY_ENV, "1")
    path = results.save("99_demo", {"epochs": 1}, {"x": 1})
    assert "with uncommitted changes" in json.loads(path.read_text())["stamp"]["git commit"]
    for module in (report, results):
        monkeypatch.setattr(module, "uncommitted_changes", lambda: [])
    monkeypatch.delenv(results.ALLOW_DIRTY_ENV)
    assert "uncommitted" not in json.loads(results.save("99_demo", {"epochs": 1}, {"x": 1}).read_text())["stamp"]["git commit"]


def test_results_files_are_not_changes_of_the_code(monkeypatch):
    import subprocess
    from vpr_nb import report
    out = " M notebooks/results/03_x.json\n M vpr_nb/gds.py\n"
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, 0, stdout=out))
    assert report.uncommitted_changes() == ["vpr_nb/gds.py"]


def test_made_or_loaded_runs_and_saves_only_in_the_reproduce_profile(tmp_path, monkeypatch):
    monkeypatch.setenv("VPR_NB_ALLOW_DIRTY", "1")
    calls = []

    def run():
        calls.append(1)
        return {"R@1": 0.5}

    with pytest.raises(FileNotFoundError):
        results.made_or_loaded("99_demo", {"epochs": 1}, run, "ci", results_dir=tmp_path)
    assert calls == []                                        # ci: never runs
    doc = results.made_or_loaded("99_demo", {"epochs": 1}, run, "reproduce", results_dir=tmp_path)
    assert calls == [1] and doc["results"]["R@1"] == 0.5 and doc["results"]["seconds"] >= 0
    assert results.made_or_loaded("99_demo", {"epochs": 1}, run, "ci", results_dir=tmp_path)["results"] == \
        doc["results"] and calls == [1]
    with pytest.raises(ValueError, match="function"):
        results.made_or_loaded("99_demo", {"epochs": 1}, {"R@1": 0.5}, "ci", results_dir=tmp_path)


def test_run_minutes_counts_reused_fine_tunes_at_their_own_times():
    doc = {"results": {"seconds": 120.0}, "stamp": {}}
    assert results.run_minutes(doc) == 2.0
    doc["stamp"]["fine-tunes"] = {"run": 40, "reused": 30, "task seconds": 6000.0}   # a run started again
    assert results.run_minutes(doc) == 50.0                                         # 6000 s two at a time
    doc["stamp"]["fine-tunes"] = {"run": 40, "reused": 0, "task seconds": 6000.0}
    assert results.run_minutes(doc) == 2.0
    with pytest.raises(ValueError, match="no run time"):
        results.run_minutes({"results": {}, "stamp": {}})
