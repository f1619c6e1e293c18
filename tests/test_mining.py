"""Tests for vpr_nb.mining: CliqueMining batches, random-place batches, NetVLAD triplet mining."""
import numpy as np
import pytest
import torch

from vpr_nb.mining import (CliqueBatchMaker, TripletBatch, clique_batches, mine_triplets,
                           random_place_batches, sample_group_descriptors)


# ----------------------------------------------------------------------------- helpers
def street_world(n_streets=6, length=400.0, spacing=4.0, noise=1.0, group_len=25.0, seed=0, dim=8):
    """Images every ``spacing`` m along parallel streets 100 m apart, grouped in ``group_len`` m cells.

    Returns ``utm (N, 2)``, ``groups (N,)`` and ``group_descriptors (G, dim)`` (a smooth function of
    the group centre, so nearby groups look alike).
    """
    rng = np.random.default_rng(seed)
    s = np.arange(0.0, length, spacing)
    utm = np.concatenate([np.stack([s, np.full_like(s, 100.0 * k)], 1) for k in range(n_streets)])
    utm = utm + rng.normal(scale=noise, size=utm.shape)
    cell = np.floor(np.maximum(utm[:, 0], 0) / group_len).astype(np.int64)
    street = np.repeat(np.arange(n_streets), len(s))
    groups = street * int(np.ceil(length / group_len) + 1) + cell
    centres = np.zeros((groups.max() + 1, 2))
    np.add.at(centres, groups, utm)
    centres /= np.maximum(np.bincount(groups, minlength=len(centres)), 1)[:, None]
    freq = rng.normal(size=(2, dim)) / 60.0
    desc = np.cos(centres @ freq + rng.uniform(0, 6, dim)).astype(np.float32)
    return utm, groups, desc


def check_batch_invariants(batches, utm, threshold, shape):
    """The CliqueMining invariants of issue 5 sec. 3 for every batch."""
    assert batches.shape == shape and batches.dtype == np.int64
    for b in batches:
        flat = b.reshape(-1)
        assert len(np.unique(flat)) == len(flat), "an image appears twice in a batch"
        pts = utm[b]  # (P, K, 2)
        d = np.linalg.norm(pts[:, None, :, None, :] - pts[None, :, None, :, :], axis=-1)  # (P, P, K, K)
        p = len(b)
        same = d[np.arange(p), np.arange(p)]  # (P, K, K)
        assert (same < threshold).all(), "images of one place are not pairwise < threshold"
        other = ~np.eye(p, dtype=bool)
        assert (d[other] >= threshold).all(), "two places of a batch are closer than the threshold"


@pytest.fixture(scope="module")
def world():
    return street_world()


# ----------------------------------------------------------------------------- clique_batches
@pytest.mark.parametrize("threshold,places,m", [(25.0, 10, 4), (12.0, 8, 3), (25.0, 20, 4)])
def test_clique_invariants(world, threshold, places, m):
    utm, groups, desc = world
    out = clique_batches(utm, groups, desc, places, images_per_place=m, same_place_threshold=threshold,
                         similar_groups=5, num_batches=6, seed=1)
    check_batch_invariants(out, utm, threshold, (6, places, m))


def test_clique_deterministic_per_seed(world):
    utm, groups, desc = world
    a = clique_batches(utm, groups, desc, 10, num_batches=5, seed=7)
    b = clique_batches(utm, groups, desc, 10, num_batches=5, seed=7)
    c = clique_batches(utm, groups, desc, 10, num_batches=5, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # a Generator seed is reproducible too, and batch b does not depend on num_batches
    g1 = clique_batches(utm, groups, desc, 10, num_batches=3, seed=np.random.default_rng(2))
    g2 = clique_batches(utm, groups, desc, 10, num_batches=3, seed=np.random.default_rng(2))
    np.testing.assert_array_equal(g1, g2)


def test_clique_parallel_equals_serial(world):
    utm, groups, desc = world
    serial = clique_batches(utm, groups, desc, 10, num_batches=6, seed=3)
    parallel = clique_batches(utm, groups, desc, 10, num_batches=6, seed=3, num_workers=2)
    np.testing.assert_array_equal(serial, parallel)


def test_clique_places_come_from_similar_groups(world):
    # with one similar group the first places of a batch lie in the anchor group or its drawn partner:
    # the images of the first place belong to at most two groups
    utm, groups, desc = world
    out = clique_batches(utm, groups, desc, 1, similar_groups=1, num_batches=20, seed=0)
    for b in out:
        assert len(np.unique(groups[b[0]])) <= 2


def test_similar_groups_are_drawn_by_descriptor_similarity():
    # 1 anchor + 1 drawn group out of: a near-identical group (weight ~max) and far ones (weight ~0)
    utm = np.array([[0, 0], [1, 0], [2, 0], [3, 0]] * 3, float) + np.repeat([[0, 0], [500, 0], [1000, 0]], 4, 0)
    groups = np.repeat([0, 1, 2], 4)
    desc = np.array([[0.0, 0.0], [0.01, 0.0], [1.0, 0.0]], np.float32)
    from vpr_nb.mining import _CliqueMiner
    miner = _CliqueMiner(utm, groups, desc, 1, 4, 25.0, 1)
    rng = np.random.default_rng(0)
    drawn = [miner.similar_groups(0, rng)[1] for _ in range(200)]
    # weights: group 1 -> 1.0 - 0.01 = 0.99, group 2 (farthest) -> 0: never drawn while group 1 can be
    assert set(drawn) == {1}
    assert all(miner.similar_groups(0, rng)[0] == 0 for _ in range(5))  # the anchor comes first


def test_clique_too_few_places_raises(world):
    utm, groups, desc = world
    tiny = utm[:40]  # one street stretch of 160 m: at most ~7 separated places of 25 m
    with pytest.raises(ValueError, match="could not fill batch"):
        clique_batches(tiny, groups[:40], desc, 9, num_batches=1)


def test_clique_bad_inputs(world):
    utm, groups, desc = world
    bad = [
        dict(utm=utm[:, :1]),
        dict(groups=groups[:-1]),
        dict(groups=groups.astype(float)),
        dict(groups=-groups - 1),
        dict(group_descriptors=desc[:3]),
        dict(places_per_batch=0),
        dict(images_per_place=1),
        dict(same_place_threshold=0.0),
        dict(similar_groups=-1),
        dict(num_batches=0),
        dict(seed=-1),
        dict(seed=1.5),
        dict(num_workers=0),
        dict(places_per_batch=10_000),
    ]
    base = dict(utm=utm, groups=groups, group_descriptors=desc, places_per_batch=5)
    for kw in bad:
        with pytest.raises(ValueError):
            clique_batches(**{**base, **kw})
    nan = utm.copy()
    nan[0, 0] = np.nan
    with pytest.raises(ValueError):
        clique_batches(nan, groups, desc, 5)


# ----------------------------------------------------------------------------- random baseline
def test_random_place_batches(world):
    utm, groups, desc = world
    out = random_place_batches(groups, 12, 4, num_batches=7, seed=4)
    assert out.shape == (7, 12, 4) and out.dtype == np.int64
    for b in out:
        assert len(np.unique(b)) == b.size
        g = groups[b]
        assert (g == g[:, :1]).all()  # the images of a place share its group
        assert len(np.unique(g[:, 0])) == 12  # distinct places
    np.testing.assert_array_equal(out, random_place_batches(groups, 12, 4, num_batches=7, seed=4))
    assert not np.array_equal(out, random_place_batches(groups, 12, 4, num_batches=7, seed=5))


def test_random_place_batches_bad_inputs(world):
    _, groups, _ = world
    for kw in (dict(places_per_batch=0), dict(images_per_place=1), dict(num_batches=0), dict(seed=-2),
               dict(places_per_batch=10_000), dict(images_per_place=50)):
        with pytest.raises(ValueError):
            random_place_batches(groups, **{**dict(places_per_batch=4), **kw})
    with pytest.raises(ValueError):
        random_place_batches(groups.reshape(2, -1), 4)
    with pytest.raises(ValueError):
        random_place_batches(np.array([]), 4)


# ----------------------------------------------------------------------------- group descriptors / refresh
def test_sample_group_descriptors(world):
    utm, groups, _ = world
    desc = np.arange(len(groups) * 2, dtype=np.float32).reshape(-1, 2)
    g = groups.copy()
    g[g == 3] = 4  # id 3 has no image
    out = sample_group_descriptors(desc, g, seed=0)
    assert out.shape == (g.max() + 1, 2)
    np.testing.assert_array_equal(out[3], 0)
    for gid in np.unique(g):
        row = int(out[gid, 0]) // 2
        assert g[row] == gid  # the row is the descriptor of one image of that group
    np.testing.assert_array_equal(out, sample_group_descriptors(desc, g, seed=0))
    with pytest.raises(ValueError):
        sample_group_descriptors(desc[:-1], g)


class CountingModel(torch.nn.Module):
    """Mean colour as a 3-D descriptor; counts its forward calls."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(1))
        self.calls = 0

    def forward(self, x):
        self.calls += 1
        return torch.nn.functional.normalize(x.mean(dim=(2, 3)) * self.w, dim=1)


@pytest.mark.parametrize("refresh,expected", [(None, [0]), (2, [0, 2, 4])])
def test_clique_batch_maker_refresh(world, refresh, expected):
    utm, groups, _ = world
    images = np.random.default_rng(0).integers(0, 255, (len(utm), 4, 4, 3), dtype=np.uint8)
    maker = CliqueBatchMaker(images, utm, groups, 6, 2, similar_groups=4, refresh_every=refresh)
    model = CountingModel()
    model.train()
    for epoch in range(5):
        out = maker(model, epoch, np.random.default_rng(epoch))
        check_batch_invariants(out, utm, 25.0, (2, 6, 4))
    assert maker.refreshed_at == expected
    assert model.training  # the train/eval mode is restored


def test_clique_batch_maker_bad_inputs(world):
    utm, groups, _ = world
    images = np.zeros((len(utm), 4, 4, 3), np.uint8)
    with pytest.raises(ValueError):
        CliqueBatchMaker(images[:-1], utm, groups, 6, 2)
    with pytest.raises(ValueError):
        CliqueBatchMaker(images, utm, groups, 6, 2, refresh_every=0)
    with pytest.raises(ValueError):
        CliqueBatchMaker(images, utm, groups, 0, 2)


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


# ----------------------------------------------------------------------------- regions, headings, batch statistics
def city_worlds(n_cities=4, seed=0):
    """Several ``street_world`` cities 100 km apart: utm, groups, group descriptors, region labels."""
    parts, off = [], 0
    for c in range(n_cities):
        utm, groups, desc = street_world(seed=seed + c, n_streets=4)
        parts.append((utm + [c * 1e5, 0.0], groups + off, desc, np.full(len(utm), f"city{c}")))
        off += len(desc)
    utm = np.concatenate([p[0] for p in parts])
    groups = np.concatenate([p[1] for p in parts])
    desc = np.concatenate([p[2] for p in parts])
    regions = np.concatenate([p[3] for p in parts])
    return utm, groups, desc, regions


def test_similar_groups_stay_in_the_anchor_region():
    utm, groups, desc, regions = city_worlds()
    out = clique_batches(utm, groups, desc, 1, similar_groups=15, num_batches=30, seed=0, regions=regions)
    for b in out:   # a 1-place batch comes from one anchor: all of its images lie in one city
        assert len(np.unique(regions[b.reshape(-1)])) == 1
    full = clique_batches(utm, groups, desc, 20, similar_groups=15, num_batches=4, seed=1, regions=regions)
    check_batch_invariants(full, utm, 25.0, (4, 20, 4))
    with pytest.raises(ValueError, match="same region"):
        bad = regions.copy()
        bad[0] = "city3"
        clique_batches(utm, groups, desc, 5, regions=bad)
    with pytest.raises(ValueError):
        clique_batches(utm, groups, desc, 5, regions=regions[:-1])


def test_clique_batches_are_closer_and_more_alike_than_random():
    # the issue-12 check: within-city similar groups give places that are closer and look more alike
    from vpr_nb.mining import batch_statistics
    utm, groups, desc, regions = city_worlds()
    image_desc = desc[groups] / np.linalg.norm(desc[groups], axis=1, keepdims=True)
    cb = clique_batches(utm, groups, desc, 10, similar_groups=15, num_batches=20, seed=0, regions=regions)
    rb = random_place_batches(groups, 10, 4, num_batches=20, seed=0)
    sc, sr = batch_statistics(cb, utm, image_desc), batch_statistics(rb, utm, image_desc)
    assert sc["median place distance (m)"] < 0.5 * sr["median place distance (m)"]
    assert sc["median place similarity"] > sr["median place similarity"]


def test_heading_test_in_the_clique_graph():
    # images at one spot facing two opposite ways: without the heading test a place mixes them
    rng = np.random.default_rng(0)
    spots = np.repeat(np.arange(0.0, 600.0, 30.0), 8)
    utm = np.stack([spots, np.zeros_like(spots)], 1) + rng.normal(scale=0.5, size=(len(spots), 2))
    heading = np.tile([0.0, 0.0, 0.0, 0.0, 180.0, 180.0, 180.0, 180.0], len(spots) // 8) + rng.normal(0, 3, len(spots))
    groups = (np.arange(len(spots)) // 8) * 2 + (heading > 90)
    desc = rng.normal(size=(groups.max() + 1, 4)).astype(np.float32)
    kw = dict(images_per_place=4, similar_groups=3, num_batches=10, seed=0)
    mixed = clique_batches(utm, groups, desc, 5, **kw)
    same = clique_batches(utm, groups, desc, 5, headings=heading, max_heading_diff=30.0, **kw)
    spread = lambda b: np.abs((heading[b] - heading[b][..., :1] + 180) % 360 - 180).max(axis=-1)
    assert (spread(same) <= 30.0).all()
    assert (spread(mixed) > 30.0).any()
    check_batch_invariants(same, utm, 25.0, (10, 5, 4))
    with pytest.raises(ValueError, match="headings"):
        clique_batches(utm, groups, desc, 5, max_heading_diff=30.0)


def test_clique_batch_maker_given_descriptors_and_resume(world):
    utm, groups, desc = world
    images = np.zeros((len(utm), 4, 4, 3), np.uint8)
    maker = CliqueBatchMaker(images, utm, groups, 6, 2, similar_groups=4, group_descriptors=desc)
    model = CountingModel()
    a = maker(model, 0, np.random.default_rng(0))
    assert model.calls == 0 and maker.refreshed_at == []   # given descriptors: the model is not run
    expect = clique_batches(utm, groups, desc, 6, similar_groups=4, num_batches=2,
                            seed=int(np.random.default_rng(0).integers(2**63)))
    np.testing.assert_array_equal(a, expect)
    other = CliqueBatchMaker(images, utm, groups, 6, 2, similar_groups=4)
    other.load_state_dict(maker.state_dict())
    np.testing.assert_array_equal(other(model, 1, np.random.default_rng(5)), maker(model, 1, np.random.default_rng(5)))
    assert model.calls == 0


def test_one_region_gives_the_same_batches_as_no_regions(world):
    utm, groups, desc = world
    a = clique_batches(utm, groups, desc, 10, num_batches=4, seed=2)
    b = clique_batches(utm, groups, desc, 10, num_batches=4, seed=2, regions=np.zeros(len(utm), int))
    np.testing.assert_array_equal(a, b)
