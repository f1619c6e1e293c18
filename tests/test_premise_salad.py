"""Tests of SALAD's premise measurement (vpr_nb.premise.salad) and the SALAD parts it needs: the softmax
ablation of the assignment (vpr_nb.aggregation), the score head from k-means (vpr_nb.models.data_init)."""
import itertools

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vpr_nb.aggregation import SALAD, make_aggregator, salad_aggregate, sinkhorn
from vpr_nb.image_tensors import images_to_tensor
from vpr_nb.models import (SmallCNN, build_model, init_netvlad, init_salad_scores_from_kmeans,
                           salad_scores_from_centroids)
from vpr_nb.premise import salad as premise
from vpr_nb.synthetic import LABEL_NAMES

pytestmark = pytest.mark.usefixtures("one_thread")   # tests/conftest.py
OBJ, GROUND, SKYLINE, SKY, OCC, DIS = range(6)


def _small_salad(assignment="sinkhorn", seed=0):
    torch.manual_seed(seed)
    return build_model(SmallCNN(width=8, out_channels=16), "salad", num_clusters=4, cluster_dim=4, token_dim=4,
                       hidden_dim=8, assignment=assignment)


def _images(n=6, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, 16, 24, 3), dtype=np.uint8)


# ------------------------------------------------------------------------------------------ labels
def test_label_shares_sum_to_one_and_count_pixels():
    lab = np.zeros((2, 4, 4), np.uint8)
    lab[0, :2] = SKY
    lab[1, :, :1] = DIS
    shares = premise.label_shares(lab)
    assert list(shares) == list(LABEL_NAMES)
    assert shares["sky"] == 8 / 32 and shares["distractor"] == 4 / 32 and shares["object"] == 20 / 32
    assert sum(shares.values()) == pytest.approx(1.0)
    for bad, match in [(np.full((2, 4, 4), 6), "outside"), (np.zeros((2, 4, 4)) + 0.5, "integer"),
                       (np.zeros((0, 4, 4), int), "non-empty")]:
        with pytest.raises(ValueError, match=match):
            premise.label_shares(bad)


def test_cell_labels_take_the_majority_per_cell():
    lab = np.zeros((1, 4, 8), int)
    lab[0, :, 4:] = GROUND
    lab[0, 0, 4:] = SKY                                             # 4 sky, 12 ground in the right cell
    lab[0, :2, :2] = OCC                                            # 4 occluder, 12 object in the left cell
    np.testing.assert_array_equal(premise.cell_labels(lab, (1, 2)), [[[OBJ, GROUND]]])
    tie = np.zeros((1, 2, 2), int)
    tie[0, 0] = SKY
    assert premise.cell_labels(tie, (1, 1))[0, 0, 0] == OBJ          # ties: the lower label id
    with pytest.raises(ValueError, match="square cells"):
        premise.cell_labels(lab, (3, 2))


# ------------------------------------------------------------------------------------ dustbin share
def test_dustbin_share_of_a_hand_made_plan():
    plan = np.array([[0.2, 0.5, 0.0],
                     [0.3, 0.1, 0.0],
                     [0.5, 0.4, 2.0]])                             # 2 clusters + the dustbin row, 3 features
    np.testing.assert_allclose(premise.plan_dustbin_share(plan), [[0.5, 0.4, 1.0]])
    np.testing.assert_allclose(premise.plan_dustbin_share(torch.tensor(plan)[None]), [[0.5, 0.4, 1.0]])
    for bad, match in [(-plan, "non-negative"), (np.zeros((3, 3)), "without mass"), (np.ones((1, 3)), "dustbin")]:
        with pytest.raises(ValueError, match=match):
            premise.plan_dustbin_share(bad)


def test_share_by_label_and_auc_on_hand_made_shares():
    lab = np.zeros((1, 4, 8), int)                                  # 1 x 2 cells of 4 x 4 pixels
    lab[0, :, 4:] = SKY
    shares = np.array([[[0.6, 0.9]]])                               # the object cell keeps more
    by_label = premise.share_by_label(shares, lab)
    assert by_label["object"] == 0.6 and by_label["sky"] == 0.9 and np.isnan(by_label["ground"])
    assert premise.kept_mass_auc(shares, lab) == 1.0
    assert premise.kept_mass_auc(shares[:, :, ::-1], lab) == 0.0
    with pytest.raises(ValueError, match="at least one positive"):
        premise.kept_mass_auc(shares, lab, uninformative=("ground",))
    with pytest.raises(ValueError, match="must not share"):
        premise.kept_mass_auc(shares, lab, informative=("object", "sky"))
    with pytest.raises(ValueError, match="label names"):
        premise.kept_mass_auc(shares, lab, informative=("facade",))


def test_rank_auc_is_the_pairwise_probability():
    assert premise.rank_auc([3, 4, 5], [0, 1, 2]) == 1.0               # a perfect separator
    assert premise.rank_auc([0, 1], [2, 3]) == 0.0
    assert premise.rank_auc([1, 1], [1, 1]) == 0.5
    rng = np.random.default_rng(0)
    pos, neg = rng.integers(0, 5, 30).astype(float), rng.integers(0, 5, 20).astype(float)
    pairs = [(p > q) + 0.5 * (p == q) for p, q in itertools.product(pos, neg)]
    assert premise.rank_auc(pos, neg) == pytest.approx(np.mean(pairs))
    with pytest.raises(ValueError, match="finite"):
        premise.rank_auc([np.nan], [0.0])


def test_dustbin_shares_of_a_model():
    model = _small_salad()
    model.train()
    imgs = _images()
    shares = premise.dustbin_shares(model, imgs, batch_size=4)
    assert shares.shape == (6, 4, 6) and model.training             # 16 x 24 images, stride 4; mode restored
    n, m = 24, 4
    assert shares.mean() == pytest.approx((n - m) / n, abs=0.02)    # Eq. (3): the dustbin receives n - m of n
    with torch.no_grad():                                          # the same as the plan computed by hand
        model.eval()
        fmap, _ = model.backbone.forward_with_token(images_to_tensor(imgs[:1]))
        plan = sinkhorn(model.aggregator.score(fmap).flatten(2), model.aggregator.dust_bin, 3).exp()[0]
    np.testing.assert_allclose(shares[0].ravel(), (plan[-1] / plan.sum(0)).numpy(), rtol=1e-6)
    lab = np.zeros((6, 16, 24), np.uint8)
    lab[:, 8:] = GROUND
    by_label = premise.dustbin_share_by_label(model, imgs, lab)
    assert np.isfinite([by_label["object"], by_label["ground"]]).all()
    assert 0 <= premise.dustbin_auc(model, imgs, lab, uninformative=("ground",)) <= 1
    with pytest.raises(ValueError, match="one .H, W. map per image"):
        premise.dustbin_share_by_label(model, imgs, lab[:3])
    with pytest.raises(ValueError, match="no dustbin"):
        premise.dustbin_shares(_small_salad("softmax"), imgs)
    with pytest.raises(ValueError, match="SALAD aggregator"):
        premise.dustbin_shares(build_model(SmallCNN(width=8, out_channels=16), "gem"), imgs)


# --------------------------------------------------------------------------- SALAD's assignment ablation
def test_sinkhorn_default_is_todays_salad_bit_for_bit():
    gen = torch.Generator().manual_seed(0)
    f, s, t = torch.randn(2, 4, 30, generator=gen), torch.randn(2, 5, 30, generator=gen), torch.randn(2, 6, generator=gen)
    p = torch.exp(sinkhorn(s, 0.7, 3))[:, :-1, :]                   # the code before the option existed
    v = F.normalize(torch.bmm(f, p.transpose(1, 2)), p=2, dim=1).flatten(1)
    before = F.normalize(torch.cat([F.normalize(t, p=2, dim=-1), v], dim=-1), p=2, dim=-1)
    assert torch.equal(salad_aggregate(f, s, t, 0.7), before)
    assert torch.equal(salad_aggregate(f, s, t, 0.7, 3, "sinkhorn"), before)
    x = (torch.randn(2, 16, 5, 6, generator=gen), torch.randn(2, 16, generator=gen))
    outs = []
    for kwargs in ({}, {"assignment": "sinkhorn"}):
        torch.manual_seed(1)
        outs.append(SALAD(num_channels=16, num_clusters=4, cluster_dim=4, token_dim=4, **kwargs).eval()(x))
    assert torch.equal(outs[0], outs[1])


def test_softmax_assignment_gives_each_feature_one_unit_over_the_clusters():
    gen = torch.Generator().manual_seed(0)
    f, s, t = torch.randn(2, 4, 30, generator=gen), torch.randn(2, 5, 30, generator=gen), torch.randn(2, 6, generator=gen)
    p = torch.softmax(s, dim=1)
    torch.testing.assert_close(p.sum(1), torch.ones(2, 30))         # one unit per feature, no dustbin
    v = F.normalize(torch.bmm(f, p.transpose(1, 2)), p=2, dim=1).flatten(1)
    expected = F.normalize(torch.cat([F.normalize(t, p=2, dim=-1), v], dim=-1), p=2, dim=-1)
    torch.testing.assert_close(salad_aggregate(f, s, t, 0.7, assignment="softmax"), expected)
    layer = make_aggregator("salad", 16, num_clusters=4, cluster_dim=4, token_dim=4, assignment="softmax")
    out = layer((torch.randn(2, 16, 5, 6), torch.randn(2, 16)))
    out.sum().backward()
    assert out.shape == (2, 4 + 16) and layer.dust_bin.grad is None
    with pytest.raises(ValueError, match="assignment"):
        SALAD(num_channels=16, assignment="hungarian")
    with pytest.raises(ValueError, match="assignment"):
        salad_aggregate(f, s, t, 0.7, assignment="hard")


# -------------------------------------------------------------------------------- score head from k-means
def test_score_head_from_centroids_gives_netvlad_logits():
    model = _small_salad()
    agg = model.aggregator.eval()
    cents = np.random.default_rng(0).normal(size=(4, 16))
    salad_scores_from_centroids(agg, cents, alpha=3.0)
    x = torch.randn(2, 16, 3, 5)
    unit = torch.from_numpy(cents / np.linalg.norm(cents, axis=1, keepdims=True)).float()
    torch.testing.assert_close(agg.score(x), 3.0 * torch.einsum("kc,bchw->bkhw", unit, x), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="hidden_dim"):
        salad_scores_from_centroids(SALAD(num_channels=16, num_clusters=4, hidden_dim=6), cents, 1.0)
    with pytest.raises(ValueError, match="num_clusters"):
        salad_scores_from_centroids(agg, cents[:3], 1.0)


def test_salad_starts_from_netvlads_centroids():
    imgs = _images(8)
    salad = _small_salad()
    torch.manual_seed(0)
    netvlad = build_model(SmallCNN(width=8, out_channels=16), "netvlad", num_clusters=4)
    netvlad.backbone.load_state_dict(salad.backbone.state_dict())
    _, nv_cents = init_netvlad(netvlad, imgs, per_image=10, niter=10, seed=3)
    cents, alpha = init_salad_scores_from_kmeans(salad, imgs, per_image=10, niter=10, seed=3)
    np.testing.assert_array_equal(cents, nv_cents)                   # the same k-means as NetVLAD's start
    with torch.no_grad():
        norms = netvlad.backbone(images_to_tensor(imgs)).norm(dim=1)
    assert alpha == pytest.approx(netvlad.aggregator.alpha / float(norms[norms > 0].mean()), rel=1e-5)
    salad.eval()
    x = torch.randn(2, 16, 3, 5)
    unit = F.normalize(torch.from_numpy(cents).float(), dim=1)
    torch.testing.assert_close(salad.aggregator.score(x), alpha * torch.einsum("kc,bchw->bkhw", unit, x),
                               rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="SALAD"):
        init_salad_scores_from_kmeans(netvlad, imgs)
