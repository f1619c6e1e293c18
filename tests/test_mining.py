"""Tests for vpr_nb.mining: NetVLAD triplet mining (the geotag batch samplers are in tests/test_samplers.py)."""
import numpy as np
import pytest

from vpr_nb.mining import TripletBatch, mine_triplets
from vpr_nb.split import Split


# ----------------------------------------------------------------------------- mine_triplets
@pytest.fixture(scope="module")
def triplet_world():
    rng = np.random.default_rng(5)
    db_utm = np.stack([np.arange(0.0, 300.0, 2.0), np.zeros(150)], 1)
    q_utm = np.stack([np.arange(1.0, 300.0, 10.0), np.full(30, 1.0)], 1)
    db_desc = rng.normal(size=(150, 6)).astype(np.float32)
    q_desc = rng.normal(size=(30, 6)).astype(np.float32)
    db_head = rng.uniform(0, 360, 150)
    q_head = rng.uniform(0, 360, 30)
    return q_desc, db_desc, q_utm, db_utm, q_head, db_head


def test_mine_triplets_positives_and_negatives(triplet_world):
    qd, dbd, qu, du, _, _ = triplet_world
    ids = np.arange(30)
    tb = mine_triplets(qd, dbd, qu, du, ids, train_pos_radius=10.0, neg_radius=25.0, num_negatives=5,
                       num_candidates=150, rng=0)
    assert isinstance(tb, TripletBatch)
    assert tb.valid.all()
    for r, qi in enumerate(ids):
        geo = np.linalg.norm(du - qu[qi], axis=1)
        dd = np.linalg.norm(dbd - qd[qi], axis=1)
        pos = np.flatnonzero(geo <= 10.0)
        assert tb.positive[r] == pos[np.argmin(dd[pos])]  # best potential positive in descriptor space
        assert tb.geo_qp[r] == pytest.approx(geo[tb.positive[r]])
        # all candidates were sampled (num_candidates >= #far): negatives = the 5 hardest beyond 25 m
        far = np.flatnonzero(geo > 25.0)
        np.testing.assert_array_equal(tb.negatives[r], far[np.argsort(dd[far], kind="stable")[:5]])
        assert (np.diff(dd[tb.negatives[r]]) >= 0).all()  # hardest first
        assert (geo[tb.negatives[r]] > 25.0).all()
        np.testing.assert_array_equal(tb.neg_cache[int(qi)], tb.negatives[r])
    assert tb.negative_mask.all()


def test_mine_triplets_sampled_candidates_and_cache(triplet_world):
    qd, dbd, qu, du, _, _ = triplet_world
    ids = np.array([3, 7])
    a = mine_triplets(qd, dbd, qu, du, ids, num_negatives=4, num_candidates=10, rng=1)
    b = mine_triplets(qd, dbd, qu, du, ids, num_negatives=4, num_candidates=10, rng=1)
    np.testing.assert_array_equal(a.negatives, b.negatives)  # deterministic per seed
    for r, qi in enumerate(ids):
        assert (np.linalg.norm(du[a.negatives[r]] - qu[qi], axis=1) > 25.0).all()
    # the cache: with a cached set of the 4 globally hardest negatives, they are always kept
    cache = {}
    for qi in ids:
        geo = np.linalg.norm(du - qu[qi], axis=1)
        dd = np.linalg.norm(dbd - qd[qi], axis=1)
        far = np.flatnonzero(geo > 25.0)
        cache[int(qi)] = far[np.argsort(dd[far])[:4]]
    hardest = {k: v.copy() for k, v in cache.items()}
    c = mine_triplets(qd, dbd, qu, du, ids, num_negatives=4, num_candidates=10, rng=2, neg_cache=cache)
    for r, qi in enumerate(ids):
        np.testing.assert_array_equal(c.negatives[r], hardest[int(qi)])
    assert c.neg_cache is cache


def test_mine_triplets_margin_mask(triplet_world):
    qd, dbd, qu, du, _, _ = triplet_world
    tb = mine_triplets(qd, dbd, qu, du, np.arange(30), num_negatives=5, num_candidates=150, rng=0, margin=0.1)
    for r in range(30):
        dp = np.linalg.norm(dbd[tb.positive[r]] - qd[r])
        dn = np.linalg.norm(dbd[tb.negatives[r]] - qd[r], axis=1)
        np.testing.assert_array_equal(tb.negative_mask[r], dn < dp + 0.1)
        assert tb.valid[r] == tb.negative_mask[r].any()


def test_mine_triplets_heading_filter(triplet_world):
    qd, dbd, qu, du, qh, dh = triplet_world
    tb = mine_triplets(qd, dbd, qu, du, np.arange(30), num_negatives=3, num_candidates=150, rng=0,
                       q_heading=qh, db_heading=dh, max_heading_diff=20.0)
    for r in range(30):
        geo = np.linalg.norm(du - qu[r], axis=1)
        diff = np.abs((dh - qh[r] + 180.0) % 360.0 - 180.0)
        pos = np.flatnonzero((geo <= 10.0) & (diff <= 20.0))
        if len(pos) == 0:
            assert tb.positive[r] == -1 and not tb.valid[r] and np.isnan(tb.geo_qp[r])
        else:
            dd = np.linalg.norm(dbd[pos] - qd[r], axis=1)
            assert tb.positive[r] == pos[np.argmin(dd)]
    assert (tb.positive == -1).any() and (tb.positive >= 0).any()  # the filter matters on this data


def test_mine_triplets_no_positive_is_invalid():
    du = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]])
    qu = np.array([[50.0, 0.0]])
    tb = mine_triplets(np.ones((1, 2), np.float32), np.eye(3, 2, dtype=np.float32), qu, du, np.array([0]),
                       num_negatives=1, num_candidates=2, rng=0)
    assert not tb.valid[0] and tb.positive[0] == -1 and (tb.negatives[0] == -1).all()


def test_mine_triplets_bad_inputs(triplet_world):
    qd, dbd, qu, du, qh, dh = triplet_world
    ids = np.arange(3)
    base = dict(q_desc=qd, db_desc=dbd, q_utm=qu, db_utm=du, query_ids=ids, rng=0)
    bad = [
        dict(db_desc=dbd[:, :3]),
        dict(q_utm=qu[:-1]),
        dict(db_utm=du[:-1]),
        dict(query_ids=np.array([], np.int64)),
        dict(query_ids=np.array([0.5])),
        dict(query_ids=np.array([30])),
        dict(query_ids=np.array([-1])),
        dict(train_pos_radius=0.0),
        dict(train_pos_radius=30.0, neg_radius=25.0),
        dict(num_negatives=0),
        dict(num_negatives=10, num_candidates=5),
        dict(margin=-1.0),
        dict(neg_cache=[1, 2]),
        dict(rng="seed"),
        dict(max_heading_diff=30.0),
        dict(max_heading_diff=30.0, q_heading=qh[:-1], db_heading=dh),
        dict(max_heading_diff=-5.0, q_heading=qh, db_heading=dh),
    ]
    for kw in bad:
        with pytest.raises(ValueError):
            mine_triplets(**{**base, **kw})


def test_mine_triplets_takes_positives_and_near_images_from_the_split(triplet_world):
    # the database twice, as two cities with the same coordinates: the split's per-city positives decide
    qd, dbd, qu, du, _, _ = triplet_world
    db_utm, db_desc = np.concatenate([du, du]), np.concatenate([dbd, dbd[::-1]])
    city = np.repeat(["a", "b"], len(du))
    split = Split()
    split.name, split.db_utm, split.q_utm, split.db_region, split.q_region = "twins", db_utm, qu, city, np.full(30, "a")
    ids = np.arange(30)
    kw = dict(train_pos_radius=10.0, neg_radius=25.0, num_negatives=5, num_candidates=300, rng=0)
    tb = mine_triplets(qd, db_desc, qu, db_utm, ids, positives=split.positives(10.0), near=split.positives(25.0), **kw)
    assert tb.valid.all() and (tb.positive < len(du)).all()           # every positive in the query's city
    geo = np.linalg.norm(db_utm[tb.negatives] - qu[:, None], axis=-1)
    assert ((geo > 25.0) | (city[tb.negatives] == "b")).all()          # the other city's images are negatives
    assert (city[tb.negatives] == "b").any() and (geo[city[tb.negatives] == "b"] <= 25.0).any()
    flat = mine_triplets(qd, db_desc, qu, db_utm, ids, **kw)          # raw geotags: both cities are one
    assert (flat.positive >= len(du)).any() and (np.linalg.norm(db_utm[flat.negatives] - qu[:, None], axis=-1) > 25.0).all()
    with pytest.raises(ValueError, match="one index array per query"):
        mine_triplets(qd, db_desc, qu, db_utm, ids, positives=split.positives(10.0)[:3], **kw)
    near = split.positives(25.0)
    near[4] = np.append(near[4], len(db_utm))                          # one index past the database
    with pytest.raises(ValueError, match=r"near must hold database indices in \[0, "):
        mine_triplets(qd, db_desc, qu, db_utm, ids, positives=split.positives(10.0), near=near, **kw)
