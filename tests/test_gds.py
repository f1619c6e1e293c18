"""Tests for vpr_nb.gds: GDS profile, mis-ordering probability, top-k order agreement."""
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.stats import kendalltau  # noqa: E402

from vpr_nb.gds import (GDSProfile, gds_profile, misordering_matrix,  # noqa: E402
                        misordering_probability, topk_order_agreement)


def far_pairs(specs):
    """Isolated image pairs: for each (geo, desc) one pair ``geo`` m apart, descriptor distance ``desc``.

    Pairs are 1 km from each other, so no other pair is within any max_distance used here.
    """
    utm, desc = [], []
    for k, (g, v) in enumerate(specs):
        utm += [(1000.0 * k, 0.0), (1000.0 * k + g, 0.0)]
        desc += [(0.0, 0.0), (v, 0.0)]
    return np.array(desc, dtype=np.float32), np.array(utm)


def brute_pairs(qd, dbd, qu, du, max_distance, all_pairs):
    """Reference pair list from dense matrices (fine for small N)."""
    geo = np.linalg.norm(qu[:, None] - du[None], axis=2)
    desc = np.linalg.norm(qd[:, None].astype(np.float64) - dbd[None], axis=2)
    mask = geo <= max_distance
    if all_pairs:
        mask &= np.triu(np.ones_like(mask), 1).astype(bool)
    return geo[mask], desc[mask]


def reference_stats(geo, desc, max_distance, bin_width, qs):
    nb = int(math.ceil(max_distance / bin_width))
    count, mean, std = np.zeros(nb, int), np.full(nb, np.nan), np.full(nb, np.nan)
    quant = {q: np.full(nb, np.nan) for q in qs}
    for b in range(nb):
        lo, hi = b * bin_width, (b + 1) * bin_width
        sel = (geo >= lo) & ((geo < hi) if b < nb - 1 else (geo <= hi))
        count[b] = sel.sum()
        if count[b]:
            mean[b], std[b] = desc[sel].mean(), desc[sel].std()
            for q in qs:
                quant[q][b] = np.quantile(desc[sel], q)
    return count, mean, std, quant


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(3)
    utm = rng.uniform(0, 60, (300, 2))
    desc = (rng.normal(size=(300, 8)) + utm[:, :1] / 20).astype(np.float32)
    return desc, utm


@pytest.mark.parametrize("mode", ["all", "query-db"])
def test_profile_matches_dense_reference(world, mode):
    desc, utm = world
    qs = (0.1, 0.5, 0.9)
    if mode == "all":
        prof = gds_profile(desc, utm, 20.0, 2.5, "all", quantiles=qs, fit_range=(0, 15))
        geo, dd = brute_pairs(desc, desc, utm, utm, 20.0, True)
    else:
        prof = gds_profile(desc[100:], utm[100:], 20.0, 2.5, query_descriptors=desc[:100],
                           query_utm=utm[:100], quantiles=qs, fit_range=(0, 15))
        geo, dd = brute_pairs(desc[:100], desc[100:], utm[:100], utm[100:], 20.0, False)
    count, mean, std, quant = reference_stats(geo, dd, 20.0, 2.5, qs)
    np.testing.assert_array_equal(prof.count, count)
    np.testing.assert_allclose(prof.mean, mean, rtol=1e-5)
    np.testing.assert_allclose(prof.std, std, rtol=1e-4)
    for q in qs:
        np.testing.assert_allclose(prof.quantiles[q], quant[q], rtol=1e-5)
    np.testing.assert_allclose(prof.bin_edges, np.arange(9) * 2.5)
    np.testing.assert_allclose(prof.bin_centers, np.arange(8) * 2.5 + 1.25)
    # weighted least squares over bins with centre in [0, 15]: polyfit weights multiply residuals
    fit = prof.bin_centers <= 15
    slope, intercept = np.polyfit(prof.bin_centers[fit], mean[fit], 1, w=np.sqrt(count[fit]))
    assert prof.slope == pytest.approx(slope, rel=1e-6)
    assert prof.intercept == pytest.approx(intercept, rel=1e-6)
    assert prof.pairs == mode


def test_hand_made_slope_and_bins():
    # descriptor distance = 0.02 * geographic distance, pairs exactly at the bin centres
    desc, utm = far_pairs([(0.5, 0.01), (1.5, 0.03), (2.5, 0.05), (2.5, 0.05)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", fit_range=(0, 3))
    np.testing.assert_array_equal(prof.count, [1, 1, 2])
    np.testing.assert_allclose(prof.mean, [0.01, 0.03, 0.05], rtol=1e-6)
    np.testing.assert_allclose(prof.std, [0, 0, 0], atol=1e-7)
    assert prof.slope == pytest.approx(0.02, rel=1e-5)
    assert prof.intercept == pytest.approx(0.0, abs=1e-6)


def test_bin_boundaries():
    # 1.0 m goes to [1, 2); exactly max_distance goes to the last (closed) bin; 3.01 m is dropped
    desc, utm = far_pairs([(1.0, 1.0), (3.0, 2.0), (3.01, 5.0), (0.0, 4.0)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", quantiles=(), fit_range=(0, 3))
    np.testing.assert_array_equal(prof.count, [1, 1, 1])
    np.testing.assert_allclose(prof.mean, [4.0, 1.0, 2.0])
    assert prof.quantiles == {}


def test_non_multiple_bin_width_and_empty_bins():
    desc, utm = far_pairs([(0.2, 1.0), (2.4, 3.0)])
    prof = gds_profile(desc, utm, 2.5, 1.0, "all", fit_range=(0, 3))
    np.testing.assert_allclose(prof.bin_edges, [0, 1, 2, 3])
    np.testing.assert_array_equal(prof.count, [1, 0, 1])
    assert np.isnan(prof.mean[1]) and np.isnan(prof.std[1]) and np.isnan(prof.quantiles[0.5][1])
    # line through (0.5, 1) and (2.5, 3): slope 1, intercept 0.5
    assert prof.slope == pytest.approx(1.0) and prof.intercept == pytest.approx(0.5)


def test_fewer_than_two_fit_bins_gives_nan_slope():
    desc, utm = far_pairs([(0.5, 1.0), (4.5, 3.0)])
    with pytest.warns(UserWarning, match="fit_range"):
        prof = gds_profile(desc, utm, 5.0, 1.0, "all", fit_range=(0, 2))
    assert math.isnan(prof.slope) and math.isnan(prof.intercept)


def test_keep_pairs_sorted_by_bin_then_distance(world):
    desc, utm = world
    prof = gds_profile(desc, utm, 10.0, 2.0, "all", keep_pairs=True)
    geo, dd = brute_pairs(desc, desc, utm, utm, 10.0, True)
    assert len(prof.pair_geo) == len(geo) == prof.count.sum()
    np.testing.assert_allclose(np.sort(prof.pair_desc), np.sort(dd), rtol=1e-5)
    b = np.minimum(np.floor(prof.pair_geo / 2.0), 4)
    assert np.all(np.diff(b) >= 0)
    same = np.diff(b) == 0
    assert np.all(np.diff(prof.pair_desc)[same] >= 0)
    assert gds_profile(desc, utm, 10.0, 2.0, "all").pair_desc is None


def test_misordering_gaussian_and_empirical_by_hand():
    # bin [0,1): distances {1, 3} (mean 2, std 1); bin [2,3): {2, 4} (mean 3, std 1)
    desc, utm = far_pairs([(0.5, 1.0), (0.5, 3.0), (2.5, 2.0), (2.5, 4.0)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", keep_pairs=True, fit_range=(0, 3))
    expected = 0.5 * (1 + math.erf((2 - 3) / math.sqrt(2) / math.sqrt(2)))
    assert misordering_probability(prof, 0.2, 2.7) == pytest.approx(expected, rel=1e-6)
    # only (x1=3, x2=2) has the farther pair closer in descriptor space: 1 of 4
    assert misordering_probability(prof, 0.2, 2.7, "empirical") == pytest.approx(0.25)


def test_misordering_ties_count_half_and_zero_std():
    desc, utm = far_pairs([(0.5, 2.0), (2.5, 2.0), (2.5, 1.0)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", keep_pairs=True, fit_range=(0, 3))
    # x1 = {2}; x2 = {1, 2}: 1 < 2 counts 1, the tie counts 1/2 -> 1.5 / 2
    assert misordering_probability(prof, 0.5, 2.5, "empirical") == pytest.approx(0.75)
    desc, utm = far_pairs([(0.5, 2.0), (2.5, 1.0)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", fit_range=(0, 3))
    assert misordering_probability(prof, 0.5, 2.5) == 1.0  # zero std: a certain mis-ordering


def test_empirical_matches_brute_force(world):
    desc, utm = world
    prof = gds_profile(desc, utm, 20.0, 4.0, "all", keep_pairs=True)
    start = np.concatenate([[0], np.cumsum(prof.count)])
    x1 = prof.pair_desc[start[0]:start[1]].astype(np.float64)
    x2 = prof.pair_desc[start[4]:start[5]].astype(np.float64)
    ref = ((x2[None, :] < x1[:, None]).sum() + 0.5 * (x2[None, :] == x1[:, None]).sum()) / (len(x1) * len(x2))
    assert misordering_probability(prof, 1.0, 17.0, "empirical") == pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("method", ["gaussian", "empirical"])
def test_misordering_matrix(world, method):
    desc, utm = world
    prof = gds_profile(desc, utm, 20.0, 4.0, "all", keep_pairs=True)
    ds = [1.0, 5.0, 9.0, 17.0]
    m = misordering_matrix(prof, ds, method=method)
    assert m.shape == (4, 4)
    np.testing.assert_allclose(np.diag(m), 0.5)
    np.testing.assert_allclose(m + m.T, 1.0, atol=1e-12)
    assert m[0, 3] == pytest.approx(misordering_probability(prof, 1.0, 17.0, method))


def test_plot_draws_mean_band_and_dashed_fit(world):
    desc, utm = world
    prof = gds_profile(desc, utm, 20.0, 2.0, "all")
    fig, ax = plt.subplots()
    assert prof.plot(ax=ax, label="model", color="C3") is ax
    lines = ax.get_lines()
    assert len(lines) == 2 and lines[1].get_linestyle() == "--"
    np.testing.assert_allclose(lines[0].get_ydata(), prof.mean)
    assert len(ax.collections) == 1  # the +-1 std band
    assert ax.get_xlabel() == "geographic distance (m)"
    plt.close(fig)
    ax2 = prof.plot()
    assert ax2.get_legend() is None
    plt.close(ax2.figure)


def test_topk_order_agreement_sorted_and_reversed():
    du = np.stack([np.arange(10.0), np.zeros(10)], 1)
    dbd = (np.arange(10.0)[:, None] * 0.1 * np.array([[1.0, 0.0]])).astype(np.float32)
    qu = np.zeros((2, 2))
    qd = np.array([[0.0, 0.0], [1.0, 0.0]], dtype=np.float32)  # 2nd query looks like the far end
    res = topk_order_agreement(qd, dbd, qu, du, k=5)
    np.testing.assert_array_equal(res.topk, [[0, 1, 2, 3, 4], [9, 8, 7, 6, 5]])
    np.testing.assert_allclose(res.topk_geo[1], [9, 8, 7, 6, 5])
    np.testing.assert_allclose(res.fraction_correct, [1.0, 0.0])
    np.testing.assert_allclose(res.kendall_tau, [1.0, -1.0])
    assert res.mean_fraction_correct == pytest.approx(0.5)
    assert res.mean_kendall_tau == pytest.approx(0.0)


def test_topk_order_agreement_matches_scipy_with_ties():
    rng = np.random.default_rng(1)
    du = rng.integers(0, 5, (60, 2)).astype(float)  # integer grid: many tied distances
    dbd = rng.normal(size=(60, 6)).astype(np.float32)
    qu = rng.integers(0, 5, (15, 2)).astype(float)
    qd = rng.normal(size=(15, 6)).astype(np.float32)
    res = topk_order_agreement(qd, dbd, qu, du, k=8)
    for q in range(15):
        geo = res.topk_geo[q]
        ref = kendalltau(np.arange(8), geo).statistic
        if np.isnan(ref):
            assert np.isnan(res.kendall_tau[q])
        else:
            assert res.kendall_tau[q] == pytest.approx(ref)
        ok = sum(geo[a] <= geo[b] for a in range(8) for b in range(a + 1, 8))
        assert res.fraction_correct[q] == pytest.approx(ok / 28)
    d = np.linalg.norm(qd[:, None].astype(np.float64) - dbd[None], axis=2)
    np.testing.assert_array_equal(np.sort(res.topk, 1), np.sort(np.argsort(d, 1)[:, :8], 1))


def test_topk_all_tied_gives_nan_tau():
    du = np.array([[1.0, 0], [0, 1.0], [-1.0, 0]])
    res = topk_order_agreement(np.zeros((1, 2)), np.eye(3, 2), np.zeros((1, 2)), du, k=3)
    assert np.isnan(res.kendall_tau[0]) and np.isnan(res.mean_kendall_tau)
    assert res.fraction_correct[0] == 1.0


# ----------------------------------------------------------------------------- bad inputs
def test_profile_bad_inputs(world):
    desc, utm = world
    with pytest.raises(ValueError, match="pairs must be one of"):
        gds_profile(desc, utm, 10, 1, "pairs")
    with pytest.raises(ValueError, match="needs query_descriptors"):
        gds_profile(desc, utm, 10, 1)
    with pytest.raises(ValueError, match="drop query_descriptors"):
        gds_profile(desc, utm, 10, 1, "all", query_descriptors=desc, query_utm=utm)
    with pytest.raises(ValueError, match="one position per image"):
        gds_profile(desc, utm[:-1], 10, 1, "all")
    with pytest.raises(ValueError, match="query_utm has"):
        gds_profile(desc, utm, 10, 1, query_descriptors=desc, query_utm=utm[:-1])
    with pytest.raises(ValueError, match="must have 8 columns"):
        gds_profile(desc, utm, 10, 1, query_descriptors=desc[:, :4], query_utm=utm)
    bad = desc.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        gds_profile(bad, utm, 10, 1, "all")
    with pytest.raises(ValueError, match="bin_width must be positive"):
        gds_profile(desc, utm, 10, 0, "all")
    with pytest.raises(ValueError, match="max_distance must be positive"):
        gds_profile(desc, utm, -1, 1, "all")
    with pytest.raises(ValueError, match="must not exceed"):
        gds_profile(desc, utm, 10, 20, "all")
    with pytest.raises(ValueError, match="fit_range"):
        gds_profile(desc, utm, 10, 1, "all", fit_range=(5, 1))
    with pytest.raises(ValueError, match="fit_range"):
        gds_profile(desc, utm, 10, 1, "all", fit_range=3)
    with pytest.raises(ValueError, match="quantiles"):
        gds_profile(desc, utm, 10, 1, "all", quantiles=(0.5, 1.5))
    with pytest.raises(ValueError, match="at least two"):
        gds_profile(desc[:1], utm[:1], 10, 1, "all")
    with pytest.raises(ValueError, match="no image pair"):
        gds_profile(desc[:2], np.array([[0.0, 0], [100, 0]]), 10, 1, "all")


def test_misordering_bad_inputs():
    desc, utm = far_pairs([(0.5, 1.0), (2.5, 2.0)])
    prof = gds_profile(desc, utm, 3.0, 1.0, "all", fit_range=(0, 3))
    with pytest.raises(ValueError, match="d1 must be smaller"):
        misordering_probability(prof, 2.5, 0.5)
    with pytest.raises(ValueError, match="empty bin"):
        misordering_probability(prof, 0.5, 1.5)
    with pytest.raises(ValueError, match="beyond"):
        misordering_probability(prof, 0.5, 4.0)
    with pytest.raises(ValueError, match="d1 must be non-negative"):
        misordering_probability(prof, -1.0, 2.5)
    with pytest.raises(ValueError, match="keep_pairs=True"):
        misordering_probability(prof, 0.5, 2.5, "empirical")
    with pytest.raises(ValueError, match="method must be"):
        misordering_probability(prof, 0.5, 2.5, "exact")
    with pytest.raises(ValueError, match="GDSProfile"):
        misordering_probability({"mean": 1}, 0.5, 2.5)
    with pytest.raises(ValueError, match="non-empty 1-D"):
        misordering_matrix(prof, [])
    with pytest.raises(ValueError, match="empty bin"):
        misordering_matrix(prof, [0.5, 1.5])
    assert isinstance(prof, GDSProfile)


def test_topk_bad_inputs():
    d = np.zeros((5, 3), np.float32)
    u = np.zeros((5, 2))
    with pytest.raises(ValueError, match="k must be <= 5"):
        topk_order_agreement(d, d, u, u, k=6)
    with pytest.raises(ValueError, match="k must be >= 2"):
        topk_order_agreement(d, d, u, u, k=1)
    with pytest.raises(ValueError, match="q_utm has 4 rows"):
        topk_order_agreement(d, d, u[:4], u, k=2)
    with pytest.raises(ValueError, match="db_utm has 4 rows"):
        topk_order_agreement(d, d, u, u[:4], k=2)
    with pytest.raises(ValueError, match="must have 3 columns"):
        topk_order_agreement(d, d[:, :2], u, u, k=2)


def test_query_topk_pure_function():
    from vpr_nb.gds import query_topk

    # 1-D world: db at x = 0..9, descriptor = x (so the ranking is by |x - xq|), query at x = 3.2
    du = np.stack([np.arange(10.0), np.zeros(10)], 1)
    dbd = du[:, :1].astype(np.float32)
    qu = np.array([[3.2, 0.0], [0.0, 0.0]])
    qd = np.array([[3.2], [9.0]], np.float32)
    res = query_topk(qd, dbd, qu, du, 0, k=4, pos_radius=1.0)
    np.testing.assert_array_equal(res.db_index, [3, 4, 2, 5])
    np.testing.assert_allclose(res.geo_distance, [0.2, 0.8, 1.2, 1.8], rtol=1e-6)
    np.testing.assert_allclose(res.desc_distance, [0.2, 0.8, 1.2, 1.8], rtol=1e-6)
    np.testing.assert_array_equal(res.is_positive, [True, True, False, False])
    assert res.fraction_correct == 1.0
    assert "rank" in res.table() and len(res.table().splitlines()) == 6
    # query 1 looks like x = 9 but stands at x = 0: the top-3 are sorted backwards
    res = query_topk(qd, dbd, qu, du, 1, k=3)
    np.testing.assert_array_equal(res.db_index, [9, 8, 7])
    assert res.fraction_correct == 0.0 and not res.is_positive.any()
    # it agrees with topk_order_agreement on a random world
    rng = np.random.default_rng(0)
    d2, u2 = rng.normal(size=(40, 5)).astype(np.float32), rng.uniform(0, 50, (40, 2))
    agg = topk_order_agreement(d2[:10], d2[10:], u2[:10], u2[10:], k=5)
    for q in range(10):
        r = query_topk(d2[:10], d2[10:], u2[:10], u2[10:], q, k=5)
        np.testing.assert_array_equal(r.db_index, agg.topk[q])
        assert r.fraction_correct == pytest.approx(agg.fraction_correct[q])
    for bad in (dict(query=10), dict(query=-1), dict(k=0), dict(k=31), dict(pos_radius=0.0)):
        with pytest.raises(ValueError):
            query_topk(d2[:10], d2[10:], u2[:10], u2[10:], **{**dict(query=0, k=3), **bad})
    with pytest.raises(ValueError):
        query_topk(d2[:10], d2[10:, :3], u2[:10], u2[10:], 0)


# ----------------------------------------------------------------------------- issue 12: same outputs, less memory
def _previous_gds_profile(db, db_utm, max_distance, bin_width, q=None, q_utm=None, fit_range=(0.0, 25.0),
                          qs=(0.1, 0.5, 0.9), keep_pairs=False):
    """The computation of gds_profile before issue 12 (argsort of values, whole-array geo), for comparison.

    It takes the descriptor distances from the current ``_pair_descriptor_distances`` (tested against the
    naive formula below), so the rest of the pipeline must give exactly the same outputs."""
    import math
    from scipy.spatial import cKDTree
    from vpr_nb.gds.binning import _bin_index, _bin_quantiles
    from vpr_nb.gds.pairs import _pair_descriptor_distances
    from vpr_nb.gds.profile import _weighted_line
    db_tree = cKDTree(db_utm)
    if q is None:
        ij = db_tree.query_pairs(max_distance, output_type="ndarray")
        i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
        src, qd = db_utm, db
    else:
        sp = cKDTree(q_utm).sparse_distance_matrix(db_tree, max_distance, output_type="ndarray")
        i, j = sp["i"].astype(np.int64), sp["j"].astype(np.int64)
        src, qd = q_utm, q
    geo = np.sqrt(((src[i] - db_utm[j]) ** 2).sum(axis=1))
    keep = geo <= max_distance
    i, j, geo = i[keep], j[keep], geo[keep]
    desc = _pair_descriptor_distances(qd, db, i, j)
    num_bins = int(math.ceil(max_distance / bin_width - 1e-9))
    centers = bin_width * (np.arange(num_bins) + 0.5)
    b = _bin_index(geo, bin_width, num_bins)
    count = np.bincount(b, minlength=num_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(b, weights=desc, minlength=num_bins) / count
        std = np.sqrt(np.bincount(b, weights=(desc - mean[b]) ** 2, minlength=num_bins) / count)
    order = np.argsort(desc)
    order = order[np.argsort(b.astype(np.int16)[order], kind="stable")]
    quant = _bin_quantiles(desc[order], count, qs) if qs else {}
    fit = (count > 0) & (centers >= fit_range[0]) & (centers <= fit_range[1])
    slope, intercept = _weighted_line(centers[fit], mean[fit], count[fit].astype(np.float64))
    return dict(count=count, mean=mean, std=std, quantiles=quant, slope=slope, intercept=intercept,
                pair_geo=geo[order] if keep_pairs else None, pair_desc=desc[order] if keep_pairs else None)


@pytest.mark.parametrize("mode,keep", [("all", False), ("all", True), ("query-db", False), ("query-db", True)])
def test_gds_profile_outputs_identical_to_the_previous_implementation(mode, keep):
    rng = np.random.default_rng(11)
    db_utm = np.cumsum(rng.normal(scale=1.5, size=(3000, 2)), axis=0)
    db = rng.normal(size=(3000, 16)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q_utm = db_utm[::3] + rng.normal(scale=2.0, size=(1000, 2))
    q = rng.normal(size=(1000, 16)).astype(np.float32)
    kw = dict(fit_range=(0.0, 20.0), keep_pairs=keep)
    if mode == "all":
        new = gds_profile(db, db_utm, 30.0, 2.5, pairs="all", **kw)
        old = _previous_gds_profile(db, db_utm, 30.0, 2.5, fit_range=(0.0, 20.0), keep_pairs=keep)
    else:
        new = gds_profile(db, db_utm, 30.0, 2.5, query_descriptors=q, query_utm=q_utm, **kw)
        old = _previous_gds_profile(db, db_utm, 30.0, 2.5, q, q_utm, fit_range=(0.0, 20.0), keep_pairs=keep)
    np.testing.assert_array_equal(new.count, old["count"])
    np.testing.assert_array_equal(new.mean, old["mean"])
    np.testing.assert_array_equal(new.std, old["std"])
    assert new.slope == old["slope"] and new.intercept == old["intercept"]
    assert new.quantiles.keys() == old["quantiles"].keys()
    for k in new.quantiles:
        np.testing.assert_array_equal(new.quantiles[k], old["quantiles"][k])
    if keep:
        np.testing.assert_array_equal(new.pair_desc, old["pair_desc"])
        # pairs with exactly equal (bin, descriptor distance) may come in another order: compare canonically
        canon = lambda g, d: np.lexsort((g, d))
        np.testing.assert_array_equal(new.pair_geo[canon(new.pair_geo, new.pair_desc)],
                                      old["pair_geo"][canon(old["pair_geo"], old["pair_desc"])])
        for d1, d2 in ((0.0, 10.0), (2.5, 20.0)):
            assert misordering_probability(new, d1, d2, "empirical") == _emp(old, d1, d2)
    else:
        assert new.pair_desc is None and new.pair_geo is None


def _emp(old, d1, d2, width=2.5):
    start = np.concatenate([[0], np.cumsum(old["count"])])
    b1, b2 = int(d1 // width), int(d2 // width)
    x1, x2 = old["pair_desc"][start[b1]:start[b1 + 1]], old["pair_desc"][start[b2]:start[b2 + 1]]
    right, left = np.searchsorted(x1, x2, "right"), np.searchsorted(x1, x2, "left")
    return float((np.sum(len(x1) - right, dtype=np.float64) + 0.5 * np.sum(right - left, dtype=np.float64))
                 / (len(x1) * len(x2)))


def _naive_desc(a, b, i, j):
    """The naive per-pair formula ``sqrt(einsum(a_i - b_j, a_i - b_j))`` in float32, row by row."""
    return np.array([np.sqrt(np.einsum("i,i->", a[p] - b[r], a[p] - b[r])) for p, r in zip(i, j)], dtype=np.float32)


def _exact_desc(a, b, i, j):
    """The descriptor distances in float64 (the true values of the float32 inputs)."""
    diff = a[i].astype(np.float64) - b[j].astype(np.float64)
    return np.sqrt(np.einsum("ij,ij->i", diff, diff))


@pytest.mark.parametrize("mode", ["all", "query-db"])
def test_pair_distances_equal_the_naive_per_pair_formulas(mode):
    # geo: the chunked column-wise distances give exactly the floats of sqrt(((u_i - u_j) ** 2).sum());
    # descriptors: the Gram-matrix (dot product) distances agree with the difference formula to float32 rounding
    from vpr_nb.gds.pairs import _geo_pairs, _pair_descriptor_distances
    rng = np.random.default_rng(5)
    db_utm = np.cumsum(rng.normal(scale=2.0, size=(1500, 2)), axis=0) + [4.5e5, 5.1e6]
    db = rng.normal(size=(1500, 32)).astype(np.float32)
    q_utm = db_utm[::2] + rng.normal(scale=3.0, size=(750, 2)) if mode == "query-db" else None
    q = rng.normal(size=(750, 32)).astype(np.float32) if mode == "query-db" else db
    src = db_utm if q_utm is None else q_utm
    i, j, geo = _geo_pairs(db_utm, q_utm, 20.0)
    assert len(i) > 10_000 and (geo <= 20.0).all()
    if mode == "all":
        assert (i < j).all()
    naive_geo = np.array([np.sqrt(((src[a] - db_utm[b]) ** 2).sum()) for a, b in zip(i[:3000], j[:3000])])
    np.testing.assert_array_equal(geo[:3000], naive_geo)
    desc = _pair_descriptor_distances(q, db, i, j)
    assert desc.dtype == np.float32 and desc.shape == i.shape
    np.testing.assert_allclose(desc[:3000], _naive_desc(q, db, i[:3000], j[:3000]), rtol=2e-6)
    rows = np.sqrt(np.einsum("ij,ij->i", q[i] - db[j], q[i] - db[j]))     # one block, whole-array
    np.testing.assert_allclose(desc, rows, rtol=2e-6)
    np.testing.assert_allclose(desc, _exact_desc(q, db, i, j), rtol=2e-6)


@pytest.mark.parametrize("mode", ["all", "query-db"])
@pytest.mark.parametrize("dim", [16, 256])
def test_pair_distances_of_unit_descriptors_within_1e5_including_near_duplicates(mode, dim):
    # unit-norm descriptors whose neighbours along the track are near-duplicates (noise 0 up to 1e-1):
    # the dot formula cancels there, so those pairs must come from the difference; all within abs 1e-5
    from vpr_nb.gds.pairs import _geo_pairs, _pair_descriptor_distances
    rng = np.random.default_rng(21)
    n = 2000
    db_utm = np.cumsum(rng.normal(scale=1.0, size=(n, 2)), axis=0)
    base = rng.normal(size=(n // 20, dim))
    noise = np.array([0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0])[rng.integers(8, size=n)]
    db = np.repeat(base, 20, axis=0) + noise[:, None] * rng.normal(size=(n, dim))
    db[5] = db[4]                                     # exact duplicates: distance exactly 0
    db = (db / np.linalg.norm(db, axis=1, keepdims=True)).astype(np.float32)
    if mode == "all":
        q, q_utm = db, None
    else:
        q_utm = db_utm[::2] + rng.normal(scale=0.5, size=(n // 2, 2))
        q = db[::2] + (1e-4 * rng.normal(size=(n // 2, dim))).astype(np.float32)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
    i, j, _ = _geo_pairs(db_utm, q_utm, 6.0)
    desc = _pair_descriptor_distances(q, db, i, j)
    assert len(desc) > 5000 and (desc < 1e-2).sum() > 100          # many near-duplicate pairs
    np.testing.assert_allclose(desc, np.sqrt(np.einsum("ij,ij->i", q[i] - db[j], q[i] - db[j])), rtol=0, atol=1e-5)
    np.testing.assert_allclose(desc, _exact_desc(q, db, i, j), rtol=0, atol=1e-5)
    if mode == "all":
        assert desc[(i == 4) & (j == 5)].tolist() == [0.0]


def test_pair_distances_scattered_pairs_and_scaled_descriptors():
    # pairs in random order touch many images per chunk (difference formula); descriptors far from unit norm
    from vpr_nb.gds.pairs import _pair_descriptor_distances
    rng = np.random.default_rng(8)
    a = (300.0 * rng.normal(size=(5000, 64))).astype(np.float32)
    b = (1e-3 * rng.normal(size=(4000, 64))).astype(np.float32)
    for x, y in ((a, a), (a, a[::-1].copy()), (b, b)):
        i = rng.integers(len(x), size=20_000).astype(np.int32)
        j = rng.integers(len(y), size=20_000).astype(np.int32)
        local = np.sort(i[:9000])                     # and a local block, as a k-d tree emits them
        i[:9000], j[:9000] = local, np.minimum(local + rng.integers(0, 30, size=9000), len(y) - 1)
        desc = _pair_descriptor_distances(x, y, i, j)
        np.testing.assert_allclose(desc, _exact_desc(x, y, i, j), rtol=2e-6)
    assert _pair_descriptor_distances(a, a, np.zeros(0, np.int32), np.zeros(0, np.int32)).shape == (0,)


@pytest.mark.parametrize("num_bins", [1, 8, 25, 1000, 1_000_000])
def test_bin_order_statistics_equal_the_quantiles_of_the_sorted_values(num_bins):
    # the radix selection (only the buckets holding the needed ranks are sorted) against a full sort:
    # ties, zeros, a bin of equal values (every pair in one bucket), a one-pair bin, empty bins
    from vpr_nb.gds.binning import _bin_order_statistics, _bin_quantiles
    rng = np.random.default_rng(5)
    n = 30_000
    b = rng.integers(0, num_bins, size=n)
    values = rng.uniform(0.0, 2.0, size=n).astype(np.float32)
    values[rng.integers(n, size=3000)] = 0.0
    values[::7] = values[::7].round(2)                   # many exact ties
    b[:4000], values[:4000] = 0, np.float32(1.25)      # bin 0: 4000 equal values
    if num_bins > 2:
        b[b == num_bins - 1] = num_bins - 2               # last bin empty
        b[4000] = num_bins - 1                            # ... but for one pair
        b[b == 1] = 0                                     # bin 1 empty
    b = b.astype(np.int8 if num_bins <= 127 else np.int64)
    count = np.bincount(b, minlength=num_bins)
    qs = (0.0, 0.1, 0.5, 0.9, 0.99, 1.0)
    order = np.lexsort((values, b))
    want = _bin_quantiles(values[order], count, qs)
    got = _bin_order_statistics(b, values, count, qs)
    assert got.keys() == want.keys()
    for q in qs:
        np.testing.assert_array_equal(got[q], want[q])
