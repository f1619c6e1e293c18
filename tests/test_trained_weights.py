"""Tests for vpr_nb.trained_weights: trained heads committed beside a notebook's results."""
from __future__ import annotations

import copy
import pickle

import pytest
import torch

from vpr_nb import results
from vpr_nb.models import build_model
from vpr_nb.pretrain import course_backbone
from vpr_nb.trained_weights import load_trained, save_trained, state_sha256, trained_part


def _start(seed=0):
    torch.manual_seed(seed)
    return build_model(course_backbone(trainable_blocks=1, final_relu=False), "netvlad", num_clusters=4)


def _train_a_little(model):
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1)
    x = torch.rand(2, 3, 48, 64)
    model(x).sum().backward()
    opt.step()
    return model


def _committed(tmp_path, entry):
    results.save("99_demo", {"seed": 0}, {"trained weights": {"seed0": entry}}, results_dir=tmp_path)
    return results.load("99_demo", {"seed": 0}, results_dir=tmp_path)


def test_round_trip_restores_exactly_the_trained_model(tmp_path):
    start = _start()
    model = _train_a_little(copy.deepcopy(start))
    part = trained_part(model, start)
    assert all(k.startswith("aggregator.") or "blocks" in k or "layer" in k or k.startswith("backbone.") for k in part)
    assert len(part) < len(model.state_dict())          # the frozen blocks are not stored
    entry = save_trained("99_demo", "seed0", model, start, results_dir=tmp_path)
    assert (tmp_path / entry["file"]).stat().st_size == entry["bytes"]
    loaded = load_trained(_committed(tmp_path, entry), "seed0", _start(), results_dir=tmp_path)
    assert state_sha256(loaded.state_dict()) == state_sha256(model.state_dict())
    x = torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(loaded.eval()(x), model.eval()(x))


def test_load_refuses_missing_changed_or_hostile_files(tmp_path):
    start = _start()
    model = _train_a_little(copy.deepcopy(start))
    entry = save_trained("99_demo", "seed0", model, start, results_dir=tmp_path)
    committed = _committed(tmp_path, entry)
    with pytest.raises(ValueError, match="no trained weights 'other'"):
        load_trained(committed, "other", _start(), results_dir=tmp_path)
    path = tmp_path / entry["file"]
    good = path.read_bytes()
    path.write_bytes(good[:-10])
    with pytest.raises(ValueError, match="size or sha256 differs"):
        load_trained(committed, "seed0", _start(), results_dir=tmp_path)

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    evil = pickle.dumps(Evil(), protocol=2)                       # a pickle that would run code: refused by weights_only
    path.write_bytes(evil)
    import hashlib
    forged = dict(entry, bytes=len(evil), sha256=hashlib.sha256(evil).hexdigest())
    with pytest.raises(ValueError, match="not a weights-only state_dict"):
        load_trained(_committed(tmp_path, forged), "seed0", _start(), results_dir=tmp_path)
    path.unlink()
    with pytest.raises(FileNotFoundError, match="missing"):
        load_trained(committed, "seed0", _start(), results_dir=tmp_path)
    bad_name = dict(entry, file="../../etc/passwd")
    with pytest.raises(ValueError, match="plain '.pt' file name"):
        load_trained(_committed(tmp_path, bad_name), "seed0", _start(), results_dir=tmp_path)


def test_load_refuses_a_model_built_differently(tmp_path):
    start = _start()
    model = _train_a_little(copy.deepcopy(start))
    entry = save_trained("99_demo", "seed0", model, start, results_dir=tmp_path)
    committed = _committed(tmp_path, entry)
    torch.manual_seed(0)
    other_size = build_model(course_backbone(trainable_blocks=1, final_relu=False), "netvlad", num_clusters=8)
    with pytest.raises(ValueError, match="other shapes"):
        load_trained(committed, "seed0", other_size, results_dir=tmp_path)
    other_block = build_model(course_backbone(trainable_blocks=2, final_relu=False), "netvlad", num_clusters=4)
    _train_a_little(other_block)                        # its second-to-last block differs from the committed one
    with pytest.raises(ValueError, match="not the model the run trained"):
        load_trained(committed, "seed0", other_block, results_dir=tmp_path)
    torch.manual_seed(0)
    gem = build_model(course_backbone(trainable_blocks=1, final_relu=False), "gem")
    with pytest.raises(ValueError, match="entries the model has not"):
        load_trained(committed, "seed0", gem, results_dir=tmp_path)


def test_labels_are_file_name_parts(tmp_path):
    start = _start()
    for bad in ("", "../x", "a b", "x" * 65, 3):
        with pytest.raises(ValueError, match="label must be"):
            save_trained("99_demo", bad, start, start, results_dir=tmp_path)


def test_every_committed_weights_file_is_the_one_its_results_record():
    import hashlib
    import json
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "notebooks" / "results"
    recorded = {}
    for doc_path in folder.glob("*.json"):
        for label, entry in json.loads(doc_path.read_text())["results"].get("trained weights", {}).items():
            assert entry["file"] == f"{doc_path.stem}.{label}.pt", entry
            recorded[entry["file"]] = entry
    for path in folder.glob("*.pt"):
        assert path.name in recorded, f"{path.name} is recorded by no results file (shown nowhere): delete it"
    for file, entry in recorded.items():
        data = (folder / file).read_bytes()
        assert len(data) == entry["bytes"] and hashlib.sha256(data).hexdigest() == entry["sha256"], file
        assert len(data) < 1_000_000, f"{file}: {len(data)} bytes; trained parts stay small"
