"""Tests for :mod:`vpr_nb.losses`: hand-computed values, torch / pytorch-metric-learning references, errors."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pytorch_metric_learning.distances import CosineSimilarity, DotProductSimilarity
from pytorch_metric_learning.losses import MultiSimilarityLoss
from pytorch_metric_learning.miners import MultiSimilarityMiner

import torch.nn.functional as F

from vpr_nb import losses as L
from vpr_nb.losses import (
    ce_triplet_loss,
    distance_weight,
    dw_triplet_loss,
    multi_similarity_loss,
    multi_similarity_miner,
    triplet_loss,
    weighted_triplet_loss,
)


# ----------------------------------------------------------------------------------------------
# fixtures
# ----------------------------------------------------------------------------------------------
@pytest.fixture
def hand_triplets():
    """Two queries, three negatives each, with integer distances (3-4-5 triangles).

    Query 0 at the origin: d(q,p)=5, d(q,n)=10, 5, 1.  Query 1 at (1,1): d(q,p)=2, d(q,n)=2, 4, 1.
    """
    q = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    p = torch.tensor([[3.0, 4.0], [1.0, 3.0]])
    n = torch.tensor([[[6.0, 8.0], [0.0, 5.0], [0.0, 1.0]],
                      [[3.0, 1.0], [1.0, 5.0], [1.0, 0.0]]])
    d_p = [[5.0] * 3, [2.0] * 3]
    d_n = [[10.0, 5.0, 1.0], [2.0, 4.0, 1.0]]
    return q, p, n, d_p, d_n


@pytest.fixture
def random_triplets():
    g = torch.Generator().manual_seed(0)
    q, p = torch.randn(4, 16, generator=g), torch.randn(4, 16, generator=g)
    n = torch.randn(4, 5, 16, generator=g)
    return q, p, n


def _ce(dp: float, dn: float) -> float:
    """Eqs. (5)-(8) literally: -log(e^{dn} / (e^{dp} + e^{dn}))."""
    return -math.log(math.exp(dn) / (math.exp(dp) + math.exp(dn)))


def _w(geo: float, sigma: float = 800.0, eps: float = 0.1) -> float:
    return (1 + eps) / (geo / sigma + eps) - 1


# ----------------------------------------------------------------------------------------------
# Eq. (3) triplet loss
# ----------------------------------------------------------------------------------------------
def test_triplet_loss_hand_values(hand_triplets):
    q, p, n, d_p, d_n = hand_triplets
    expected = torch.tensor([[max(0.0, a - b + 0.1) for a, b in zip(ra, rb)] for ra, rb in zip(d_p, d_n)])
    # query 0: 0, 0.1, 4.1 ; query 1: 0.1, 0, 1.1
    assert torch.allclose(triplet_loss(q, p, n, reduction="none"), expected, atol=1e-6)
    assert triplet_loss(q, p, n).item() == pytest.approx(5.4, abs=1e-5)
    assert triplet_loss(q, p, n, reduction="mean").item() == pytest.approx(5.4 / 6, abs=1e-6)
    assert triplet_loss(q, p, n, margin=0.0).item() == pytest.approx(4.0 + 1.0, abs=1e-5)


@pytest.mark.parametrize("reduction", ["sum", "mean", "none"])
def test_triplet_loss_matches_torch_single_negative(random_triplets, reduction):
    q, p, n = random_triplets
    ref = torch.nn.TripletMarginLoss(margin=0.5, p=2, reduction=reduction)(q, p, n[:, 0])
    ours = triplet_loss(q, p, n[:, 0], margin=0.5, reduction=reduction)
    assert ours.shape == ref.shape == ((4,) if reduction == "none" else ())
    assert torch.allclose(ours, ref, rtol=1e-5, atol=1e-4)  # torch adds eps=1e-6 inside its distance


@pytest.mark.parametrize("reduction", ["sum", "mean", "none"])
def test_triplet_loss_matches_torch_many_negatives(random_triplets, reduction):
    q, p, n = random_triplets
    b, m, d = n.shape
    ref = torch.nn.TripletMarginLoss(margin=1.0, p=2, reduction=reduction)(
        q.repeat_interleave(m, 0), p.repeat_interleave(m, 0), n.reshape(b * m, d))
    ours = triplet_loss(q, p, n, margin=1.0, reduction=reduction)
    if reduction == "none":
        ref = ref.reshape(b, m)
    assert ours.shape == ref.shape
    assert ref.abs().sum() > 0  # some triplets are active, so the comparison is meaningful
    assert torch.allclose(ours, ref, rtol=1e-5, atol=1e-4)


# ----------------------------------------------------------------------------------------------
# Eq. (4) distance weight
# ----------------------------------------------------------------------------------------------
def test_distance_weight_values_and_negative_beyond_sigma():
    geo = np.array([0.0, 400.0, 800.0, 1600.0])
    w = distance_weight(geo, sigma=800.0, eps=0.1)
    assert isinstance(w, np.ndarray)
    # 1/eps at 0 m, 0 at sigma, negative (not clipped) beyond sigma
    np.testing.assert_allclose(w, [10.0, 1.1 / 0.6 - 1, 0.0, 1.1 / 2.1 - 1], atol=1e-12)
    assert w[-1] < 0


def test_distance_weight_keeps_kind():
    t = torch.tensor([0.0, 25.0], dtype=torch.float64)
    wt = distance_weight(t, sigma=25.0, eps=0.5)
    assert isinstance(wt, torch.Tensor) and wt.dtype == torch.float64
    assert torch.allclose(wt, torch.tensor([2.0, 0.0], dtype=torch.float64))
    wi = distance_weight(torch.tensor([0, 10]), sigma=20.0)
    assert wi.is_floating_point() and wi[1].item() == pytest.approx(_w(10, 20.0), rel=1e-6)
    wl = distance_weight([10.0], sigma=20.0)
    assert isinstance(wl, np.ndarray) and wl[0] == pytest.approx(_w(10, 20.0))


# ----------------------------------------------------------------------------------------------
# W-T-Loss, CE triplet (Eqs. 5-8), DW-T-Loss (Eq. 9)
# ----------------------------------------------------------------------------------------------
def test_weighted_triplet_loss_hand_values(hand_triplets):
    q, p, n, d_p, d_n = hand_triplets
    geo = [0.0, 1600.0]  # weights 1 and 1.1/2.1 - 1 (negative, beyond sigma)
    hinge = [[max(0.0, a - b + 0.1) for a, b in zip(ra, rb)] for ra, rb in zip(d_p, d_n)]
    expected = torch.tensor([[_w(g) * h for h in row] for g, row in zip(geo, hinge)])
    for geo_kind in (geo, np.array(geo), torch.tensor(geo)):
        out = weighted_triplet_loss(q, p, n, geo_kind, reduction="none")
        assert torch.allclose(out, expected, atol=1e-6)
    assert weighted_triplet_loss(q, p, n, geo).item() == pytest.approx(float(expected.sum()), abs=1e-5)


def test_ce_triplet_loss_hand_values(hand_triplets):
    q, p, n, d_p, d_n = hand_triplets
    expected = torch.tensor([[_ce(a, b) for a, b in zip(ra, rb)] for ra, rb in zip(d_p, d_n)])
    assert torch.allclose(ce_triplet_loss(q, p, n, reduction="none"), expected, atol=1e-6)
    assert ce_triplet_loss(q, p, n).item() == pytest.approx(float(expected.sum()), rel=1e-6)
    assert ce_triplet_loss(q, p, n, reduction="mean").item() == pytest.approx(float(expected.mean()), rel=1e-6)


def test_ce_and_dw_stable_for_huge_distances():
    q = torch.zeros(2, 3, requires_grad=True)
    p = torch.tensor([[1e4, 0.0, 0.0], [3e4, 0.0, 0.0]])
    n = torch.tensor([[3e4, 0.0, 0.0], [1e4, 0.0, 0.0]])
    per = ce_triplet_loss(q, p, n, reduction="none")
    assert torch.isfinite(per).all()
    assert per[0].item() == pytest.approx(0.0, abs=1e-6)  # -log(1 / (1 + e^{-2e4}))
    assert per[1].item() == pytest.approx(2e4, rel=1e-6)  # -log(e^{-2e4} / (1 + e^{-2e4}))
    dw = dw_triplet_loss(q, p, n, torch.tensor([0.0, 0.0]))
    dw.backward()
    assert torch.isfinite(dw) and torch.isfinite(q.grad).all()
    assert dw.item() == pytest.approx(10 * 2e4, rel=1e-6)  # w = 1/eps = 10 at 0 m


def test_dw_triplet_loss_hand_values(hand_triplets):
    q, p, n, d_p, d_n = hand_triplets
    geo = [200.0, 1000.0]
    expected = torch.tensor([[_w(g, 900.0, 0.2) * _ce(a, b) for a, b in zip(ra, rb)]
                             for g, ra, rb in zip(geo, d_p, d_n)])
    out = dw_triplet_loss(q, p, n, geo, sigma=900.0, eps=0.2, reduction="none")
    assert torch.allclose(out, expected, atol=1e-6)
    assert dw_triplet_loss(q, p, n, geo, sigma=900.0, eps=0.2).item() == pytest.approx(float(expected.sum()), rel=1e-5)


def test_single_negative_none_shape_is_batch(hand_triplets):
    q, p, n, d_p, d_n = hand_triplets
    out = ce_triplet_loss(q, p, n[:, 2], reduction="none")
    assert out.shape == (2,)
    assert torch.allclose(out, torch.tensor([_ce(5.0, 1.0), _ce(2.0, 1.0)]), atol=1e-6)


@pytest.mark.parametrize("loss", ["triplet", "weighted", "ce", "dw"])
def test_triplet_family_gradients_flow(random_triplets, loss):
    q, p, n = (t.clone().requires_grad_(True) for t in random_triplets)
    geo = torch.tensor([0.0, 100.0, 300.0, 700.0])
    value = {"triplet": lambda: triplet_loss(q, p, n, margin=5.0),
             "weighted": lambda: weighted_triplet_loss(q, p, n, geo, margin=5.0),
             "ce": lambda: ce_triplet_loss(q, p, n),
             "dw": lambda: dw_triplet_loss(q, p, n, geo)}[loss]()
    value.backward()
    for t in (q, p, n):
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


# ----------------------------------------------------------------------------------------------
# triplet family: bad inputs
# ----------------------------------------------------------------------------------------------
def _ok():
    return torch.zeros(2, 3), torch.ones(2, 3), torch.full((2, 4, 3), 2.0), [10.0, 20.0]


def _nan(shape):
    t = torch.zeros(shape)
    t.view(-1)[0] = float("nan")
    return t


BAD_TRIPLETS = {
    "p shape": dict(p=torch.ones(2, 4)),
    "n batch": dict(n=torch.ones(3, 4, 3)),
    "n dim": dict(n=torch.ones(2, 4, 5)),
    "n 4-D": dict(n=torch.ones(2, 4, 3, 1)),
    "no negatives": dict(n=torch.ones(2, 0, 3)),
    "q 1-D": dict(q=torch.zeros(3)),
    "q empty": dict(q=torch.zeros(0, 3), p=torch.zeros(0, 3), n=torch.zeros(0, 3)),
    "q numpy": dict(q=np.zeros((2, 3))),
    "q integer": dict(q=torch.zeros(2, 3, dtype=torch.long)),
    "p dtype": dict(p=torch.ones(2, 3, dtype=torch.float64)),
    "q NaN": dict(q=_nan((2, 3))),
    "n inf": dict(n=torch.full((2, 4, 3), float("inf"))),
    "p NaN": dict(p=_nan((2, 3))),
    "p and n -inf": dict(p=torch.full((2, 3), -float("inf")), n=torch.full((2, 4, 3), -float("inf"))),
    "overflow": dict(q=torch.full((2, 3), 1e30)),
    "reduction": dict(reduction="avg"),
}
BAD_GEO = {
    "geo shape": dict(geo_qp=[1.0, 2.0, 3.0]),
    "geo 2-D": dict(geo_qp=[[1.0], [2.0]]),
    "geo negative": dict(geo_qp=[1.0, -2.0]),
    "geo NaN": dict(geo_qp=[1.0, float("nan")]),
    "geo text": dict(geo_qp=["a", "b"]),
    "sigma zero": dict(sigma=0.0),
    "sigma negative": dict(sigma=-800.0),
    "eps zero": dict(eps=0.0),
    "eps negative": dict(eps=-0.1),
}
BAD_MARGIN = {"margin negative": dict(margin=-0.1), "margin NaN": dict(margin=float("nan"))}


def _call(name: str, **override):
    q, p, n, geo = _ok()
    args = dict(q=q, p=p, n=n, geo_qp=geo)
    args.update(override)
    fn = {"triplet": triplet_loss, "weighted": weighted_triplet_loss, "ce": ce_triplet_loss,
          "dw": dw_triplet_loss}[name]
    if name in ("triplet", "ce"):
        args.pop("geo_qp")
    return fn(**args)


@pytest.mark.parametrize("name", ["triplet", "weighted", "ce", "dw"])
@pytest.mark.parametrize("case", list(BAD_TRIPLETS))
def test_triplet_family_rejects_bad_descriptors(name, case):
    with pytest.raises(ValueError):
        _call(name, **BAD_TRIPLETS[case])


@pytest.mark.parametrize("culprit", ["q", "p", "n"])
def test_non_finite_input_is_named(culprit):
    q, p, n, _ = _ok()
    bad = {"q": q, "p": p, "n": n}[culprit]
    bad.view(-1)[-1] = float("nan")
    with pytest.raises(ValueError, match=f"^{culprit} contains NaN or inf"):
        triplet_loss(q, p, n)


def test_overflowing_distances_are_reported():
    q, p, n, _ = _ok()
    with pytest.raises(ValueError, match="overflow.*L2-normalise"):
        ce_triplet_loss(q + 1e30, p, n)


@pytest.mark.parametrize("name", ["weighted", "dw"])
@pytest.mark.parametrize("case", list(BAD_GEO))
def test_weighted_losses_reject_bad_geo(name, case):
    with pytest.raises(ValueError):
        _call(name, **BAD_GEO[case])


@pytest.mark.parametrize("name", ["triplet", "weighted"])
@pytest.mark.parametrize("case", list(BAD_MARGIN))
def test_margin_losses_reject_bad_margin(name, case):
    with pytest.raises(ValueError, match="margin"):
        _call(name, **BAD_MARGIN[case])


def test_valid_defaults_do_not_raise():
    # guards the error tests above: the unmodified inputs are accepted by every loss
    for name in ("triplet", "weighted", "ce", "dw"):
        assert torch.isfinite(_call(name))


@pytest.mark.parametrize("kwargs", [dict(geo_qp=[-1.0]), dict(geo_qp=[float("inf")]), dict(geo_qp=[1.0], sigma=0),
                                    dict(geo_qp=[1.0], eps=-1), dict(geo_qp=torch.tensor([float("nan")])),
                                    dict(geo_qp=object())])
def test_distance_weight_rejects(kwargs):
    with pytest.raises(ValueError):
        distance_weight(**kwargs)


# ----------------------------------------------------------------------------------------------
# Multi-Similarity
# ----------------------------------------------------------------------------------------------
@pytest.fixture
def ms_batch():
    """8 places x 4 images, L2-normalised, clustered per place so that mining is selective."""
    g = torch.Generator().manual_seed(3)
    centres = torch.randn(8, 32, generator=g)
    labels = torch.arange(8).repeat_interleave(4)
    perm = torch.randperm(32, generator=g)
    labels = labels[perm]
    emb = centres[labels] + 1.2 * torch.randn(32, 32, generator=g)
    return torch.nn.functional.normalize(emb, dim=1), labels


def _pml_loss():
    return MultiSimilarityLoss(alpha=1, beta=50, base=0, distance=DotProductSimilarity())


def _pairs(a, b):
    return set(zip(a.tolist(), b.tolist()))


def test_ms_loss_matches_pml_all_pairs(ms_batch):
    emb, labels = ms_batch
    ours = multi_similarity_loss(emb, labels, alpha=1.0, beta=50.0, base=0.0)
    ref = _pml_loss()(emb, labels)
    assert ours.item() == pytest.approx(ref.item(), abs=1e-5, rel=1e-5)


def test_ms_loss_matches_pml_other_hyperparameters(ms_batch):
    emb, labels = ms_batch
    ours = multi_similarity_loss(emb, labels, alpha=2.0, beta=40.0, base=0.5)
    ref = MultiSimilarityLoss(alpha=2, beta=40, base=0.5, distance=DotProductSimilarity())(emb, labels)
    assert ours.item() == pytest.approx(ref.item(), abs=1e-5, rel=1e-5)


def test_ms_loss_uses_raw_dot_product(ms_batch):
    emb, labels = ms_batch
    emb = emb * torch.linspace(0.5, 1.5, 32).unsqueeze(1)  # no longer unit norm
    ours = multi_similarity_loss(emb, labels)
    ref = MultiSimilarityLoss(alpha=1, beta=50, base=0,
                              distance=DotProductSimilarity(normalize_embeddings=False))(emb, labels)
    assert ours.item() == pytest.approx(ref.item(), abs=1e-5, rel=1e-5)


def test_miner_matches_pml(ms_batch):
    emb, labels = ms_batch
    a1, p, a2, n = multi_similarity_miner(emb, labels, epsilon=0.1)
    r1, rp, r2, rn = MultiSimilarityMiner(0.1, distance=CosineSimilarity())(emb, labels)
    assert all(t.dtype == torch.long for t in (a1, p, a2, n))
    assert _pairs(a1, p) == _pairs(r1, rp) and len(a1) == len(r1)
    assert _pairs(a2, n) == _pairs(r2, rn) and len(a2) == len(r2)
    assert 0 < len(a2) < 32 * 28  # mining actually dropped some negatives
    assert 0 < len(a1)


def test_ms_loss_with_miner_matches_pml(ms_batch):
    emb, labels = ms_batch
    pairs = multi_similarity_miner(emb, labels, epsilon=0.1)
    ours = multi_similarity_loss(emb, labels, miner_pairs=pairs)
    ref = _pml_loss()(emb, labels, MultiSimilarityMiner(0.1, distance=CosineSimilarity())(emb, labels))
    assert ours.item() == pytest.approx(ref.item(), abs=1e-5, rel=1e-5)
    assert ours.item() != pytest.approx(multi_similarity_loss(emb, labels).item(), abs=1e-4)


def test_ms_loss_hand_values():
    emb = torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.0, 1.0]])  # S01=0.6, S02=0, S12=0.8
    labels = [0, 0, 1]
    l0 = math.log(1 + math.exp(-0.6)) + math.log(1 + math.exp(0.0)) / 50
    l1 = math.log(1 + math.exp(-0.6)) + math.log(1 + math.exp(40.0)) / 50
    l2 = math.log(1 + math.exp(0.0) + math.exp(40.0)) / 50  # no positive: only the negative term
    assert multi_similarity_loss(emb, labels).item() == pytest.approx((l0 + l1 + l2) / 3, rel=1e-6)
    # one mined positive and one mined negative, both for anchor 0; anchors 1 and 2 count as 0 in the mean
    # (pytorch-metric-learning returns 0 here: it skips batches whose index tensors all have <= 1 pair)
    pairs = (torch.tensor([0]), torch.tensor([1]), torch.tensor([0]), torch.tensor([2]))
    assert multi_similarity_loss(emb, labels, miner_pairs=pairs).item() == pytest.approx(l0 / 3, rel=1e-6)


def test_ms_mean_counts_anchors_without_pairs_like_pml():
    g = torch.Generator().manual_seed(1)
    emb = torch.nn.functional.normalize(torch.randn(5, 8, generator=g), dim=1)
    labels = torch.tensor([0, 0, 1, 1, 2])
    # anchor 1 has only a positive, anchors 3 and 4 have no pair at all
    pairs = (torch.tensor([0, 1]), torch.tensor([1, 0]), torch.tensor([0, 2]), torch.tensor([2, 4]))
    ours = multi_similarity_loss(emb, labels, miner_pairs=pairs)
    ref = _pml_loss()(emb, labels, pairs)
    assert ours.item() == pytest.approx(ref.item(), abs=1e-6, rel=1e-6)
    s = emb @ emb.T
    l0 = math.log(1 + math.exp(-s[0, 1])) + math.log(1 + math.exp(50 * s[0, 2])) / 50
    l1 = math.log(1 + math.exp(-s[1, 0]))
    l2 = math.log(1 + math.exp(50 * s[2, 4])) / 50
    assert ours.item() == pytest.approx((l0 + l1 + l2) / 5, rel=1e-5)


def test_miner_hand_values():
    c30, s30 = math.cos(math.pi / 6), 0.5
    emb = torch.tensor([[1.0, 0.0], [0.5, c30], [c30, s30], [-1.0, 0.0]]) * 3.0  # cosine ignores the scale
    a1, p, a2, n = multi_similarity_miner(emb, torch.tensor([0, 0, 1, 1]), epsilon=0.1)
    assert _pairs(a1, p) == {(0, 1), (1, 0), (2, 3), (3, 2)}
    assert _pairs(a2, n) == {(0, 2), (1, 2), (2, 0), (2, 1), (3, 1)}


def test_ms_loss_stable_for_large_similarities():
    emb = torch.tensor([[10.0, 0.0], [9.0, 1.0], [10.0, 1.0], [0.0, 10.0]], requires_grad=True)
    loss = multi_similarity_loss(emb, [0, 0, 1, 1])  # beta * S ~ 5000: naive exp overflows
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(emb.grad).all()
    # anchor 0: negatives 2 (S=100) and 3 (S=0); its negative term is ~ max_n S = 100
    assert loss.item() > 100 / 4


@pytest.mark.parametrize("with_miner", [False, True])
def test_ms_loss_gradients_flow(ms_batch, with_miner):
    emb, labels = ms_batch
    emb = emb.clone().requires_grad_(True)
    pairs = multi_similarity_miner(emb, labels) if with_miner else None
    multi_similarity_loss(emb, labels, miner_pairs=pairs).backward()
    assert torch.isfinite(emb.grad).all() and emb.grad.abs().sum() > 0


def test_miner_accepts_numpy_labels_and_returns_no_grad(ms_batch):
    emb, labels = ms_batch
    out = multi_similarity_miner(emb.clone().requires_grad_(True), labels.numpy())
    ref = multi_similarity_miner(emb, labels)
    assert all(torch.equal(a, b) and not a.requires_grad for a, b in zip(out, ref))


BAD_MS = {
    "labels length": dict(labels=[0, 1, 1]),
    "labels 2-D": dict(labels=[[0, 0, 1, 1]]),
    "labels NaN": dict(labels=[0.0, 0.0, float("nan"), 1.0]),
    "labels bool": dict(labels=[True, True, False, False]),
    "labels text": dict(labels=["a", "a", "b", "b"]),
    "embeddings 1-D": dict(embeddings=torch.ones(4)),
    "embeddings NaN": dict(embeddings=_nan((4, 2))),
    "embeddings empty": dict(embeddings=torch.ones(0, 2), labels=[]),
    "embeddings numpy": dict(embeddings=np.ones((4, 2))),
    "alpha zero": dict(alpha=0.0),
    "beta negative": dict(beta=-50.0),
    "base inf": dict(base=float("inf")),
    "base None": dict(base=None),
    "pairs length": dict(miner_pairs=(torch.tensor([0]), torch.tensor([1]))),
    "pairs unequal": dict(miner_pairs=(torch.tensor([0, 1]), torch.tensor([1]), torch.tensor([0]), torch.tensor([2]))),
    "pairs range": dict(miner_pairs=(torch.tensor([0]), torch.tensor([1]), torch.tensor([0]), torch.tensor([7]))),
    "pairs float": dict(miner_pairs=(torch.tensor([0.0]), torch.tensor([1.0]), torch.tensor([0]), torch.tensor([2]))),
    "positive is other place": dict(miner_pairs=(torch.tensor([0]), torch.tensor([2]), torch.tensor([0]), torch.tensor([3]))),
    "positive is self": dict(miner_pairs=(torch.tensor([0]), torch.tensor([0]), torch.tensor([0]), torch.tensor([3]))),
    "negative is same place": dict(miner_pairs=(torch.tensor([0]), torch.tensor([1]), torch.tensor([0]), torch.tensor([1]))),
}


def _ms_args(**override):
    args = dict(embeddings=torch.eye(4, 2), labels=[0, 0, 1, 1])
    args.update(override)
    return args


@pytest.mark.parametrize("case", list(BAD_MS))
def test_ms_loss_rejects(case):
    with pytest.raises(ValueError):
        multi_similarity_loss(**_ms_args(**BAD_MS[case]))


def test_ms_valid_defaults_do_not_raise():
    pairs = (torch.tensor([0]), torch.tensor([1]), torch.tensor([0]), torch.tensor([3]))
    assert torch.isfinite(multi_similarity_loss(**_ms_args(miner_pairs=pairs)))
    assert len(multi_similarity_miner(**_ms_args())) == 4


@pytest.mark.parametrize("case", ["labels length", "labels NaN", "embeddings 1-D", "embeddings NaN"])
def test_miner_rejects(case):
    with pytest.raises(ValueError):
        multi_similarity_miner(**_ms_args(**BAD_MS[case]))


def test_miner_rejects_negative_epsilon():
    with pytest.raises(ValueError, match="epsilon"):
        multi_similarity_miner(**_ms_args(epsilon=-0.1))


# ----------------------------------------------------------------------------------------------
# loss objects: their parameters held and validated; the same numbers as the functions
# ----------------------------------------------------------------------------------------------
def test_loss_objects_compute_exactly_the_functions(random_triplets):
    from vpr_nb import losses as L
    q, p, n = random_triplets
    geo = torch.tensor([0.0, 3.0, 12.5, 24.0])
    cases = [(L.TripletLoss(margin=0.3), triplet_loss(q, p, n, 0.3)),
             (L.WeightedTripletLoss(margin=0.3, sigma=30.0, eps=0.5), weighted_triplet_loss(q, p, n, geo, 0.3, 30.0, 0.5)),
             (L.CETripletLoss(), ce_triplet_loss(q, p, n)),
             (L.DWTripletLoss(sigma=30.0, eps=0.5), dw_triplet_loss(q, p, n, geo, 30.0, 0.5))]
    for loss, want in cases:
        assert isinstance(loss, L.TripletFamilyLoss)
        assert torch.equal(loss(q, p, n, geo), want), loss


def test_ms_loss_object_computes_exactly_the_functions(ms_batch):
    from vpr_nb import losses as L
    emb, labels = ms_batch
    pairs = multi_similarity_miner(emb, labels, 0.2)
    assert torch.equal(L.MultiSimilarityLoss(2.0, 40.0, 0.5, 0.2)(emb, labels),
                       multi_similarity_loss(emb, labels, 2.0, 40.0, 0.5, miner_pairs=pairs))
    assert torch.equal(L.MultiSimilarityLoss(miner_epsilon=None)(emb, labels), multi_similarity_loss(emb, labels))


def test_loss_objects_share_the_functions_defaults():
    import inspect

    from vpr_nb import losses as L

    def defaults(f):
        return {k: v.default for k, v in inspect.signature(f).parameters.items() if v.default is not inspect._empty}
    assert L.TripletLoss().margin == defaults(triplet_loss)["margin"]
    w = L.WeightedTripletLoss()
    assert (w.margin, w.sigma, w.eps) == tuple(defaults(weighted_triplet_loss)[k] for k in ("margin", "sigma", "eps"))
    assert (L.DWTripletLoss().sigma, L.DWTripletLoss().eps) == tuple(defaults(distance_weight).values())
    ms, f = L.MultiSimilarityLoss(), defaults(multi_similarity_loss)
    assert (ms.alpha, ms.beta, ms.base) == (f["alpha"], f["beta"], f["base"])
    assert ms.miner_epsilon == defaults(multi_similarity_miner)["epsilon"]


@pytest.mark.parametrize("make, match", [
    (lambda L: L.TripletLoss(margin=-0.1), "margin must be non-negative"),
    (lambda L: L.TripletLoss(margin="big"), "margin must be a number"),
    (lambda L: L.WeightedTripletLoss(sigma=0.0), "sigma must be positive"),
    (lambda L: L.WeightedTripletLoss(eps=float("nan")), "eps must be finite"),
    (lambda L: L.DWTripletLoss(eps=-1.0), "eps must be positive"),
    (lambda L: L.MultiSimilarityLoss(alpha=0.0), "alpha must be positive"),
    (lambda L: L.MultiSimilarityLoss(beta=-1.0), "beta must be positive"),
    (lambda L: L.MultiSimilarityLoss(base=float("inf")), "base"),
    (lambda L: L.MultiSimilarityLoss(miner_epsilon=-0.1), "miner_epsilon"),
])
def test_loss_objects_validate_their_parameters(make, match):
    from vpr_nb import losses as L
    with pytest.raises(ValueError, match=match):
        make(L)


def test_weighted_loss_objects_need_the_geographic_distances(random_triplets):
    from vpr_nb import losses as L
    q, p, n = random_triplets
    for loss in (L.WeightedTripletLoss(), L.DWTripletLoss()):
        with pytest.raises(ValueError, match="needs geo_qp"):
            loss(q, p, n)
    assert torch.equal(L.TripletLoss()(q, p, n), triplet_loss(q, p, n))      # geo_qp unused, may be left out


def test_loss_objects_are_immutable_values():
    import dataclasses

    from vpr_nb import losses as L
    loss = L.DWTripletLoss(sigma=25)
    assert loss == L.DWTripletLoss(sigma=25.0) and repr(loss) == "DWTripletLoss(sigma=25.0, eps=0.1)"
    with pytest.raises(dataclasses.FrozenInstanceError):
        loss.sigma = 30.0


# ------------------------------------------------------------------------------ local InfoNCE (pretraining)
def _local_by_hand(full, shifted, offset, tau):
    """Eq. (L) with a loop over images and anchors, the 'image' negatives."""
    b, c, h, w = full.shape
    ws = shifted.shape[3]
    total, count = 0.0, 0
    for i in range(b):
        v = F.normalize(shifted[i].reshape(c, -1), dim=0)             # [C, h*ws]
        for r in range(h):
            for j in range(min(w - offset, ws)):
                u = F.normalize(full[i, :, r, j + offset], dim=0)
                logits = (u @ v) / tau
                total += float(torch.logsumexp(logits, 0) - logits[r * ws + j])
                count += 1
    return total / count


def test_local_infonce_is_eq_L_by_hand():
    g = torch.Generator().manual_seed(0)
    full = torch.randn(3, 8, 4, 6, generator=g)
    shifted = full[:, :, :, 2:] + 0.3 * torch.randn(3, 8, 4, 4, generator=g)
    got = L.local_infonce(full, shifted, 2, temperature=0.2)
    assert float(got) == pytest.approx(_local_by_hand(full, shifted, 2, 0.2), rel=1e-5)


def test_local_infonce_rewards_matching_positions_and_tells_them_apart():
    g = torch.Generator().manual_seed(1)
    full = torch.randn(4, 16, 8, 12, generator=g)
    aligned = L.local_infonce(full, full[:, :, :, 3:].clone(), 3)
    scrambled = L.local_infonce(full, torch.randn(4, 16, 8, 9, generator=g), 3)
    assert float(aligned) < 0.1 < 3.0 < float(scrambled)
    for negatives in L.LOCAL_NEGATIVES:                                # both forms give a gradient to both maps
        a, b = full.clone().requires_grad_(), full[:, :, :, 3:].clone().requires_grad_()
        L.local_infonce(a, b + 0.1, 3, negatives=negatives, max_anchors=50,
                        generator=torch.Generator().manual_seed(0)).backward()
        assert a.grad.abs().sum() > 0 and b.grad.abs().sum() > 0


@pytest.mark.parametrize("kwargs, match", [
    (dict(offset=0), "offset"), (dict(offset=12), "offset"), (dict(temperature=0.0), "temperature"),
    (dict(negatives="all"), "negatives must be one of"), (dict(shifted=torch.zeros(2, 8, 4, 5)), "shifted must be"),
])
def test_local_infonce_rejects(kwargs, match):
    args = dict(full=torch.zeros(2, 16, 4, 12), shifted=torch.zeros(2, 16, 4, 10), offset=2)
    with pytest.raises(ValueError, match=match):
        L.local_infonce(**{**args, **kwargs})
