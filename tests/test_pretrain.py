"""Tests for vpr_nb.pretrain (the course backbone) and SmallCNN's partial freezing."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vpr_nb import pretrain
from vpr_nb.models import SmallCNN
from vpr_nb.synthetic import make_dataset


pytestmark = pytest.mark.usefixtures("one_thread")   # tests/conftest.py


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """The pretrain command end to end in its reduced profile (about 20 s)."""
    out = tmp_path_factory.mktemp("cb") / "cb.pt"
    assert pretrain.main(["--profile", "quick", "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_pretrain_command_writes_checkpoint_and_card(quick_run):
    card = json.loads(quick_run.with_suffix(".json").read_text())
    assert card["sha256"] == pretrain._sha256(quick_run)
    assert card["config"]["epochs"] == pretrain.PROFILES["quick"]["epochs"]
    assert card["torch"] == torch.__version__ and card["train_seconds"] > 0
    assert set(card["held_out"]) == {f"{p} seed {s} {sp}" for p, s, sp in pretrain.HELD_OUT}
    state = torch.load(quick_run, weights_only=True)
    assert all(v.dtype == torch.float16 for v in state.values() if v.is_floating_point())
    backbone = pretrain.course_backbone(quick_run)
    assert backbone.out_channels == card["config"]["out_channels"]


@pytest.mark.slow
def test_pretrain_is_deterministic(quick_run, tmp_path):
    out = tmp_path / "cb.pt"             # same file name: torch.save stores it in the archive
    pretrain.main(["--profile", "quick", "--out", str(out)])
    assert pretrain._sha256(out) == pretrain._sha256(quick_run)


@pytest.mark.slow
def test_course_backbone_refuses_a_changed_file(quick_run, tmp_path):
    bad = tmp_path / "cb.pt"
    bad.write_bytes(quick_run.read_bytes()[:-10] + b"0123456789")
    (tmp_path / "cb.json").write_text(quick_run.with_suffix(".json").read_text())
    with pytest.raises(ValueError, match="sha256"):
        pretrain.course_backbone(bad)
    with pytest.raises(FileNotFoundError, match="python -m vpr_nb.pretrain"):
        pretrain.course_backbone(tmp_path / "missing.pt")
    (tmp_path / "lonely.pt").write_bytes(b"x")
    with pytest.raises(FileNotFoundError, match="card"):
        pretrain.course_backbone(tmp_path / "lonely.pt")


@pytest.mark.slow
def test_committed_checkpoint_is_small_and_keeps_its_recall():
    """Frozen + GeM on a world seed it never saw: at least what its card records (minus 0.01)."""
    card = pretrain.card()
    assert pretrain.CHECKPOINT.stat().st_size <= 3 * 2**20
    backbone = pretrain.course_backbone()
    assert not any(p.requires_grad for p in backbone.features.parameters())
    got = pretrain.held_out_recalls(backbone, ns=(1, 5, 10))
    for world, rows in card["held_out"].items():
        for n, want in rows["course backbone + GeM"].items():
            assert got[world]["course backbone + GeM"][n] >= want - 0.01, (world, n, got[world], want)


def test_corpus_is_disjoint_from_notebook_worlds():
    with pytest.raises(ValueError, match=">= 100"):
        pretrain.PretrainConfig(city_seeds=(0, 100))
    with pytest.raises(ValueError, match="at least one world"):
        pretrain.PretrainConfig(city_seeds=(), route_seeds=())
    cfg = pretrain.PretrainConfig()
    used = {s for p, s, _ in pretrain.HELD_OUT} | {pretrain.SELECTION_WORLD[1]}
    assert not used & (set(cfg.city_seeds) | set(cfg.route_seeds))


def test_place_labels_group_nearby_views_facing_the_same_way():
    ds = make_dataset("city", seed=100, splits=("val",)).val
    lab = pretrain.place_labels(ds, 3)
    utm = np.concatenate([ds.db_utm, ds.q_utm])
    head = np.concatenate([ds.db_heading, ds.q_heading]) % 360
    for g in np.unique(lab)[:50]:
        m = lab == g
        assert np.ptp(utm[m], axis=0).max() < 45          # 3 spots of 10 m + query offsets
        assert len(np.unique(head[m] // 90)) == 1


@pytest.mark.parametrize("k, trainable", [(0, []), (1, [9]), (2, [6, 7, 9]), (4, [0, 1, 3, 4, 6, 7, 9])])
def test_small_cnn_trainable_blocks(k, trainable):
    net = SmallCNN(width=8, out_channels=16).set_trainable_blocks(k)
    layers = [i for i, layer in enumerate(net.features) if any(p.requires_grad for p in layer.parameters())]
    assert layers == trainable
    out = net(torch.randn(2, 3, 32, 48))
    assert out.requires_grad == (k > 0)
    with pytest.raises(ValueError, match="trainable_blocks"):
        net.set_trainable_blocks(5)


def test_course_backbone_before_the_final_relu():
    """final_relu=False only removes the last ReLU: the map equals the pre-ReLU map, GeM is unchanged."""
    from vpr_nb.aggregation import GeM
    x = torch.randn(2, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    after, before = pretrain.course_backbone(), pretrain.course_backbone(final_relu=False)
    with torch.no_grad():
        a, b = after(x), before(x)
    assert torch.equal(a, torch.relu(b)) and (b < 0).any()
    assert torch.allclose(GeM(in_channels=128)(a), GeM(in_channels=128)(b))
    with pytest.raises(ValueError, match="final_relu"):
        pretrain.course_backbone(final_relu="no")


def test_small_cnn_final_norm_adds_a_groupnorm_to_the_last_block():
    plain, normed = SmallCNN(width=8, out_channels=16), SmallCNN(width=8, out_channels=16, final_norm=4)
    assert len(normed.features) == len(plain.features) + 1
    assert isinstance(normed.features[-2], torch.nn.GroupNorm) and normed.features[-2].num_groups == 4
    normed.set_trainable_blocks(1)                        # the last block: the projection and its GroupNorm
    assert [i for i, m in enumerate(normed.features) if any(p.requires_grad for p in m.parameters())] == [9, 10]
    out = normed(torch.randn(2, 3, 32, 48))
    assert out.shape == (2, 16, 8, 12) and (out >= 0).all()
    with pytest.raises(ValueError, match="final_norm=3 groups must divide out_channels=16"):
        SmallCNN(width=8, out_channels=16, final_norm=3)


@pytest.mark.parametrize("kw, match", [
    (dict(final_norm=5), "must divide out_channels"), (dict(local_negatives="all"), "local_negatives"),
    (dict(local_weight=-1.0), "local_weight"), (dict(local_temperature=0.0), "local_temperature"),
    (dict(local_shift=0), "local_shift"),
])
def test_pretrain_config_checks_the_local_feature_knobs(kw, match):
    with pytest.raises(ValueError, match=match):
        pretrain.PretrainConfig(**kw)


def test_the_local_term_trains_and_is_seeded(tmp_path):
    """A tiny corpus: one MS + local InfoNCE epoch twice gives the same weights; the term moves them."""
    cfg = dict(city_seeds=(100,), route_seeds=(), width=8, out_channels=16, batches_per_epoch=2, epochs=1,
               places_per_batch=4, final_norm=4, local_views=4)
    a, _ = pretrain.pretrain(pretrain.PretrainConfig(**cfg, local_weight=0.5), progress=False)
    b, _ = pretrain.pretrain(pretrain.PretrainConfig(**cfg, local_weight=0.5), progress=False)
    c, _ = pretrain.pretrain(pretrain.PretrainConfig(**cfg, local_weight=0.0), progress=False)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
