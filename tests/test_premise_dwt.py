"""DW-T-Loss's premise (notebook 03): the positive-selection option of triplet mining (neutral when off), the
placebo DW-T-Loss, and :mod:`vpr_nb.premise.dwt`'s measurement of Eq. (4)'s weights over the mined positives."""
import copy
import hashlib

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from vpr_nb import losses as L
from vpr_nb import mining
from vpr_nb.models import build_model
from vpr_nb.premise import dwt
from vpr_nb.seeding import seed_everything
from vpr_nb.synthetic import make_dataset
import vpr_nb.training.triplet_source as TS
from vpr_nb.training import TripletSource

# Fingerprints of the code before the positive option existed (recorded on it, commit d55e43e): the default
# (positive="best") must keep every batch, every loss and every random draw bit-identical.
MINE_HASH = "6fd9fa6fe5bce29b"
STEPS_HASH = "2f66a2a7e250da49"
STEPS_LOSSES = [19.48430824279785, 19.210729598999023, 19.815414428710938]
STEPS_COLLAPSED = 19.29451560974121


@pytest.fixture(scope="module")
def tiny():
    return make_dataset("city", 0, size="tiny")


def _update(h, tb):
    for a in (tb.query, tb.positive, tb.negatives, tb.negative_mask, tb.geo_qp, tb.valid):
        h.update(np.ascontiguousarray(a).tobytes())


def _mine_fingerprint(tr, **kw):
    rng = np.random.default_rng(3)
    qd = rng.normal(size=(len(tr.q_utm), 8)).astype(np.float32)
    dd = rng.normal(size=(len(tr.db_utm), 8)).astype(np.float32)
    h, cache, g = hashlib.sha256(), {}, np.random.default_rng(7)
    for ids in (np.arange(0, 40), np.arange(40, 80), np.arange(0, 40)):
        _update(h, mining.mine_triplets(qd, dd, tr.q_utm, tr.db_utm, ids, train_pos_radius=10.0, neg_radius=25.0,
                                        num_negatives=5, num_candidates=100, neg_cache=cache, rng=g, margin=0.1,
                                        **kw))
    h.update(g.integers(2**62, size=4).tobytes())
    return h.hexdigest()[:16]


def _steps_fingerprint(tr, monkeypatch, loss=None, **kw):
    rec = []

    def spy(*a, **k):
        rec.append(mining.mine_triplets(*a, **k))
        return rec[-1]

    monkeypatch.setattr(TS, "mine_triplets", spy)
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    src = TripletSource(tr, loss or L.DWTripletLoss(sigma=800.0, eps=0.1), batch_size=8, num_negatives=3,
                        num_candidates=50, max_heading_diff=45.0, **kw)
    g, losses = np.random.default_rng([0, 0]), []
    for i, loss in enumerate(src.steps(model, g)):
        losses.append(float(loss.detach()))
        if i == 2:
            break
    h = hashlib.sha256()
    for tb in rec:
        _update(h, tb)
    h.update(g.integers(2**62, size=4).tobytes())
    return h.hexdigest()[:16], losses, src.last_collapsed_loss, rec


def test_default_mining_is_unchanged(tiny):
    assert _mine_fingerprint(tiny.train) == MINE_HASH
    assert _mine_fingerprint(tiny.train, positive="best") == MINE_HASH


def test_default_triplet_source_is_unchanged(tiny, monkeypatch, one_thread):
    digest, losses, collapsed, _ = _steps_fingerprint(tiny.train, monkeypatch)
    assert digest == STEPS_HASH
    assert losses == STEPS_LOSSES and collapsed == STEPS_COLLAPSED


# ----------------------------------------------------------------------------- positive="random": mining
def _heading_ok(tr, i, pos, max_diff=45.0):
    return pos[np.abs((tr.db_heading[pos] - tr.q_heading[i] + 180.0) % 360.0 - 180.0) <= max_diff]


def _mine(tr, desc, ids, rng=0, **kw):
    return mining.mine_triplets(desc[0], desc[1], tr.q_utm, tr.db_utm, ids, train_pos_radius=10.0, neg_radius=25.0,
                                num_negatives=3, num_candidates=60, rng=rng, q_heading=tr.q_heading,
                                db_heading=tr.db_heading, max_heading_diff=45.0, **kw)


def _random_desc(tr, seed):
    g = np.random.default_rng(seed)
    return (g.normal(size=(len(tr.q_utm), 8)).astype(np.float32),
            g.normal(size=(len(tr.db_utm), 8)).astype(np.float32))


def test_positive_rule_is_validated(tiny):
    tr, desc = tiny.train, _random_desc(tiny.train, 0)
    for bad in ("nearest", "Best", None, 1):
        with pytest.raises(ValueError, match=r"positive must be one of \('best', 'random'\)"):
            _mine(tr, desc, np.arange(4), positive=bad)
        with pytest.raises(ValueError, match=r"positive must be one of \('best', 'random'\)"):
            TripletSource(tr, positive=bad)
    with pytest.raises(ValueError, match="positive_seed must be"):
        _mine(tr, desc, np.arange(4), positive="random", positive_seed=-1)
    legacy = np.random.MT19937()
    legacy._legacy_seeding(0)                                          # a generator without a SeedSequence
    with pytest.raises(ValueError, match="SeedSequence"):
        list(TripletSource(tr, positive="random").steps(None, np.random.Generator(legacy)))


def test_random_positive_is_a_seeded_uniform_draw_that_ignores_the_model(tiny):
    tr, ids = tiny.train, np.arange(0, 120)
    a = _mine(tr, _random_desc(tr, 0), ids, positive="random", positive_seed=(5, 2))
    b = _mine(tr, _random_desc(tr, 1), ids, positive="random", positive_seed=(5, 2))     # another model
    c = _mine(tr, _random_desc(tr, 0), ids, positive="random", positive_seed=(5, 3))     # another epoch
    part = _mine(tr, _random_desc(tr, 0), ids[60:], positive="random", positive_seed=(5, 2))  # another batch
    np.testing.assert_array_equal(a.positive, b.positive)
    np.testing.assert_array_equal(a.positive[60:], part.positive)
    assert (a.positive != c.positive).any()
    pots = tr.positives(10.0)
    for r, i in enumerate(ids):
        ok = _heading_ok(tr, i, pots[i])
        assert (a.positive[r] in ok) if len(ok) else a.positive[r] == -1
        if len(ok):
            assert a.geo_qp[r] == pytest.approx(np.linalg.norm(tr.db_utm[a.positive[r]] - tr.q_utm[i]))
    # uniform: over many seeds, every potential positive of a query with several is drawn, about equally often
    i = next(i for i in range(len(tr.q_utm)) if len(_heading_ok(tr, i, pots[i])) >= 3)
    ok = _heading_ok(tr, i, pots[i])
    draws = [mining.positive_rng(s, i).integers(len(ok)) for s in range(3000)]
    counts = np.bincount(draws, minlength=len(ok)) / 3000
    assert np.allclose(counts, 1 / len(ok), atol=0.04)


def test_random_positive_leaves_the_negatives_draws_alone(tiny):
    tr, ids, desc = tiny.train, np.arange(40), _random_desc(tiny.train, 0)
    g_best, g_rand = np.random.default_rng(9), np.random.default_rng(9)
    best = _mine(tr, desc, ids, rng=g_best)
    rand = _mine(tr, desc, ids, rng=g_rand, positive="random", positive_seed=4)
    np.testing.assert_array_equal(best.negatives, rand.negatives)      # no margin: the same hardest negatives
    assert g_best.integers(2**62) == g_rand.integers(2**62)            # and the same stream afterwards
    assert (best.positive != rand.positive).any()
    # without positive_seed the draw comes from rng: reproducible, but it shifts the negatives' stream
    x = _mine(tr, desc, ids, rng=np.random.default_rng(9), positive="random")
    y = _mine(tr, desc, ids, rng=np.random.default_rng(9), positive="random")
    np.testing.assert_array_equal(x.positive, y.positive)


def test_triplet_source_random_positives_are_paired_across_models(tiny, monkeypatch, one_thread):
    tr = tiny.train
    d1, _, _, rec1 = _steps_fingerprint(tr, monkeypatch, positive="random")
    d2, _, _, rec2 = _steps_fingerprint(tr, monkeypatch, positive="random")
    assert d1 == d2                                                    # same seed: the same run
    seed_everything(1)                                                 # another model, the same rng seed
    other = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    rec3 = []
    monkeypatch.setattr(TS, "mine_triplets", lambda *a, **k: rec3.append(mining.mine_triplets(*a, **k)) or rec3[-1])
    src = TripletSource(tr, L.DWTripletLoss(), batch_size=8, num_negatives=3, num_candidates=50, max_heading_diff=45.0,
                        positive="random")
    for i, _ in enumerate(src.steps(other, np.random.default_rng([0, 0]))):
        if i == 2:
            break
    for x, y, z in zip(rec1, rec2, rec3):
        np.testing.assert_array_equal(x.query, z.query)                # the rng's stream is the best rule's
        np.testing.assert_array_equal(x.positive, z.positive)          # the positives do not depend on the model
    assert d1 != STEPS_HASH


# ----------------------------------------------------------------------------- the placebo DW-T-Loss
def _triplets(b=12, m=3, d=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    q, p, n = (torch.nn.functional.normalize(torch.randn(*s, generator=g), dim=-1) for s in ((b, d), (b, d), (b, m, d)))
    geo = torch.rand(b, generator=g, dtype=torch.float32) * 15.0
    return q, p, n, geo


def test_placebo_with_the_identity_is_dw_t_loss():
    q, p, n, geo = _triplets()
    ident = np.arange(len(geo))
    assert torch.equal(L.placebo_dw_triplet_loss(q, p, n, geo, ident, 18.0, 0.1), L.DWTripletLoss(18.0, 0.1)(q, p, n, geo))
    assert torch.equal(L.placebo_dw_triplet_loss(q, p, n, geo, ident, 18.0, 0.1, reduction="none"),
                       L.dw_triplet_loss(q, p, n, geo, 18.0, 0.1, reduction="none"))


def test_placebo_permutes_the_weights_reproducibly():
    q, p, n, geo = _triplets()
    loss = L.PlaceboDWTripletLoss(sigma=18.0, eps=0.1, seed=3)
    perm = loss.permutation(geo)
    assert sorted(perm.tolist()) == list(range(len(geo)))                          # a permutation
    assert (perm != np.arange(len(geo))).any()
    np.testing.assert_array_equal(perm, L.PlaceboDWTripletLoss(18.0, 0.1, 3).permutation(geo.clone()))  # seeded
    np.testing.assert_array_equal(perm, L.placebo_permutation(geo.double(), 3))   # the values, not the dtype's bits
    assert (perm != L.PlaceboDWTripletLoss(18.0, 0.1, 4).permutation(geo)).any()  # another seed, another draw
    out = loss(q, p, n, geo)
    assert torch.equal(out, L.dw_triplet_loss(q, p, n, geo[torch.as_tensor(perm)], 18.0, 0.1))
    assert not torch.allclose(out, L.DWTripletLoss(18.0, 0.1)(q, p, n, geo))       # the link to each triplet is gone
    w = L.distance_weight(geo, 18.0, 0.1)                                            # the same weights, reassigned
    assert torch.equal(torch.sort(w[torch.as_tensor(perm)]).values, torch.sort(w).values)
    # the ranking is gone: the weight a triplet gets no longer decreases with its own distance
    many = torch.linspace(0.0, 15.0, 400)
    rho = spearmanr(many.numpy(), L.distance_weight(many[torch.as_tensor(loss.permutation(many))], 18.0, 0.1)).statistic
    assert abs(rho) < 0.2


def test_placebo_validates_its_inputs():
    q, p, n, geo = _triplets()
    with pytest.raises(ValueError, match="seed"):
        L.PlaceboDWTripletLoss(seed=-1)
    with pytest.raises(ValueError, match="sigma"):
        L.PlaceboDWTripletLoss(sigma=0.0)
    with pytest.raises(ValueError, match="needs geo_qp"):
        L.PlaceboDWTripletLoss()(q, p, n)
    with pytest.raises(ValueError, match="permutation of range"):
        L.placebo_dw_triplet_loss(q, p, n, geo, np.zeros(len(geo), int))
    with pytest.raises(ValueError, match="geo_qp must"):
        L.PlaceboDWTripletLoss()(q, p, n, geo[:3])


def test_placebo_trains_where_dw_t_loss_does(tiny, monkeypatch, one_thread):
    _, losses, collapsed, _ = _steps_fingerprint(tiny.train, monkeypatch, loss=L.PlaceboDWTripletLoss(800.0, 0.1, 0))
    assert all(np.isfinite(losses)) and np.isfinite(collapsed)
    assert losses != STEPS_LOSSES and sum(losses) == pytest.approx(sum(STEPS_LOSSES), rel=0.1)


# ----------------------------------------------------------------------------- the premise: vpr_nb.premise.dwt
def _positions(tr):
    """Descriptors that are the positions: the best positive is then the geographically nearest one."""
    return tr.q_utm.astype(np.float32), tr.db_utm.astype(np.float32)


def test_mined_distances_follow_the_rule(tiny):
    tr = tiny.train
    best = dwt.mined_positive_distances(tr, _positions(tr), 10.0, "best")
    rand = dwt.mined_positive_distances(tr, None, 10.0, "random", seed=0)
    u = TripletSource(tr, max_heading_diff=45.0).untrainable()
    assert len(best) == len(rand) == u["queries"] - u["no_positive"] - u["heading"]      # one per trainable query
    pots = tr.positives(10.0)
    nearest = [np.linalg.norm(tr.db_utm[ok] - tr.q_utm[i], axis=1).min()
               for i in range(len(pots)) if len(ok := _heading_ok(tr, i, pots[i]))]
    np.testing.assert_allclose(best, nearest, rtol=1e-6)          # best = nearest in descriptor = in space here
    assert (rand <= 10.0).all() and (rand >= best - 1e-9).all()
    assert np.median(rand) > np.median(best) + 0.5 and rand.std() > best.std()   # random spreads wider
    np.testing.assert_array_equal(rand, dwt.mined_positive_distances(tr, None, 10.0, "random", seed=0))
    assert not np.array_equal(rand, dwt.mined_positive_distances(tr, None, 10.0, "random", seed=1))
    wide = dwt.mined_positive_distances(tr, None, 25.0, "random", max_heading_diff=None)
    assert len(wide) >= len(rand) and wide.max() <= 25.0


def test_weight_spread_is_flat_at_800_m_and_ranks_at_sigma_near_the_radius(tiny):
    tr = tiny.train
    rand = dwt.mined_positive_distances(tr, None, 10.0, "random")      # the training radius, 10 m
    flat, ranks = dwt.weight_spread(rand, 800.0, 0.1), dwt.weight_spread(rand, 12.0, 0.1)
    assert flat["cv"] < 0.05 < 0.5 < ranks["cv"]
    assert flat["max_over_min"] < 1.3 < 10.0 < ranks["max_over_min"]
    w = L.distance_weight(rand, 12.0, 0.1)
    assert ranks["n"] == len(rand) and ranks["min"] == w.min() and ranks["max"] == w.max()
    assert ranks["mean"] == pytest.approx(w.mean()) and ranks["cv"] == pytest.approx(w.std() / w.mean())
    assert dwt.weight_spread([0.0, 10.0, 20.0], 20.0, 0.1)["max_over_min"] == float("inf")   # w(sigma) = 0
    with pytest.raises(ValueError, match="non-empty"):
        dwt.weight_spread([], 800.0)
    with pytest.raises(ValueError, match="sigma"):
        dwt.weight_spread([1.0], 0.0)


def test_premise_table_rows(tiny):
    tr = tiny.train
    rows = dwt.premise_table(tr, _positions(tr), radii=(10, 25), sigmas=(800.0,), sigma_factors=(1.2,))
    assert len(rows) == 2 * 2 * 2
    assert [(r["rule"], r["radius"], r["sigma"]) for r in rows[:4]] == [("best", 10.0, 800.0), ("best", 10.0, 12.0),
                                                                        ("best", 25.0, 800.0), ("best", 25.0, 30.0)]
    for r in rows:
        assert set(r) == {"rule", "radius", "sigma", "n", "dist_median", "dist_p90", "weight_min", "weight_max",
                          "weight_cv", "weight_max_over_min"}
        assert 0 < r["dist_median"] <= r["dist_p90"] <= r["radius"]
        assert (r["weight_cv"] < 0.1) == (r["sigma"] == 800.0)
    assert rows[0]["dist_median"] < rows[4]["dist_median"]              # best < random, radius 10
    only_random = dwt.premise_table(tr, radii=(15,), rules=("random",), sigmas=(), sigma_factors=(1.2,))
    assert len(only_random) == 1 and only_random[0]["sigma"] == pytest.approx(18.0)
    twice = dwt.premise_table(tr, radii=(10,), rules=("random",), sigmas=(12.0, 800.0), sigma_factors=(1.2, 1.0))
    assert [r["sigma"] for r in twice] == [12.0, 800.0, 10.0]          # 1.2 x 10 m = 12 m is listed once


def test_usefulness_correlation(tiny):
    tr = tiny.train
    same = dwt.usefulness_correlation(tr, _positions(tr), 25.0)       # descriptor distance = geographic distance
    assert same["rho"] == pytest.approx(1.0) and same["rho_within"] == pytest.approx(1.0) and same["n"] > 100
    noise = dwt.usefulness_correlation(tr, _random_desc(tr, 0), 25.0)
    assert abs(noise["rho"]) < 0.2 and noise["pvalue"] > 1e-3
    picked = dwt.usefulness_correlation(tr, _positions(tr), 25.0, rule="random")
    assert picked["rho"] == pytest.approx(1.0) and "rho_within" not in picked


def test_premise_inputs_are_validated(tiny):
    tr, desc = tiny.train, _positions(tiny.train)
    empty = copy.copy(tr)
    empty.q_utm, empty.q_images = tr.q_utm[:0], tr.q_images[:0]
    for call in (lambda s: dwt.mined_positive_distances(s, None, 10.0, "random"),
                 lambda s: dwt.premise_table(s, rules=("random",)),
                 lambda s: dwt.usefulness_correlation(s, desc)):
        with pytest.raises(ValueError, match="is empty"):
            call(empty)
        with pytest.raises(ValueError, match="must be a vpr_nb.split.Split"):
            call("not a split")
    for radius in (0.0, -5.0, float("nan")):
        with pytest.raises(ValueError, match="radius"):
            dwt.mined_positive_distances(tr, desc, radius)
        with pytest.raises(ValueError, match="radius"):
            dwt.premise_table(tr, desc, radii=(radius,))
    with pytest.raises(ValueError, match=r"one of \('best', 'random'\)"):
        dwt.mined_positive_distances(tr, desc, 10.0, "hardest")
    with pytest.raises(ValueError, match=r"one of \('best', 'random'\)"):
        dwt.premise_table(tr, desc, rules=("best", "hardest"))
    with pytest.raises(ValueError, match="pass model_or_descriptors"):
        dwt.mined_positive_distances(tr, None, 10.0, "best")
    with pytest.raises(ValueError, match="pass descriptors"):
        dwt.premise_table(tr)
    with pytest.raises(ValueError, match=r"descriptors must be \(Q, D\)"):
        dwt.mined_positive_distances(tr, (desc[0][:5], desc[1]), 10.0)
    with pytest.raises(ValueError, match="no query"):
        dwt.premise_table(tr, rules=("random",), radii=(1e-6,))
