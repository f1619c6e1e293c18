"""The method pictures of notebooks 05-07 (vpr_nb.plots.salad, .gds, .clique): they draw what their docstrings say
from the method's own tensors, check their inputs, draw on given axes and leave every random stream alone."""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from vpr_nb import plots  # noqa: E402
from vpr_nb.aggregation import sinkhorn  # noqa: E402
from vpr_nb.gds import gds_profile, misordering_probability  # noqa: E402
from vpr_nb.samplers import clique_batches, random_place_batches, sample_group_descriptors  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _plan(m=4, h=3, w=4, seed=0):
    scores = torch.randn(1, m, h * w, generator=torch.Generator().manual_seed(seed))
    return sinkhorn(3.0 * scores, 1.0, 3)[0].exp()            # (m + 1, n), dustbin last


def _image(h=30, w=40):
    return np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _profile(keep_pairs=True):
    rng = np.random.default_rng(0)
    utm = np.stack([5.0 * np.arange(60), np.zeros(60)], 1)
    q_utm = utm + rng.normal(0, 0.3, utm.shape)
    db = np.cumsum(rng.normal(0, 0.1, (60, 8)), 0)              # descriptors drift along the route
    q = db + rng.normal(0, 0.1, db.shape)
    return gds_profile(db, utm, 40.0, 4.8, query_descriptors=q, query_utm=q_utm, keep_pairs=keep_pairs)


def _random_state():
    return torch.get_rng_state().clone(), np.random.get_state()[1].copy()


def test_salad_plan_colours_positions_marks_the_dustbin_and_shows_the_plan():
    plan = _plan()
    before = _random_state()
    fig = plots.plot_salad_plan(_image(), plan, (3, 4))
    after = _random_state()
    assert torch.equal(before[0], after[0]) and np.array_equal(before[1], after[1])
    image_ax, plan_ax = fig.axes[:2]
    overlay = image_ax.get_images()[1].get_array()
    assert overlay.shape == (3, 4, 4)                          # one RGBA cell per position of the 3 x 4 map
    shown = plan_ax.get_images()[0].get_array()
    assert shown.shape == (5, 12) and np.allclose(shown, np.maximum(plan.numpy(), 1e-6))
    assert plan_ax.get_yticklabels()[-1].get_text() == "dustbin"
    discarded = (plan[-1] > 8 / 12).numpy()                    # default threshold (n - m) / n
    crosses = image_ax.collections[0].get_offsets()
    assert len(crosses) == discarded.sum()


def test_salad_plan_draws_on_given_axes_with_a_chosen_threshold():
    fig, axes = plt.subplots(1, 2)
    out = plots.plot_salad_plan(_image(), _plan().numpy(), (3, 4), dustbin_threshold=0.99, axes=axes)
    assert out is fig
    assert len(axes[0].collections[0].get_offsets()) == 0     # no position gives the dustbin 99 %


@pytest.mark.parametrize("kwargs, message", [
    ({"image": np.zeros((30, 40, 3))}, "uint8"),
    ({"plan": _plan()[:, :6]}, "grid_shape"),
    ({"plan": _plan().log()}, "non-negative"),
    ({"plan": _plan()[:-1]}, "sum to 1"),
    ({"plan": _plan().T}, "sum to 1"),
    ({"plan": torch.ones(1, 12)}, "(m + 1, n)"),
    ({"dustbin_threshold": 1.5}, "dustbin_threshold"),
    ({"axes": [None]}, "two matplotlib axes"),
])
def test_salad_plan_rejects_bad_inputs(kwargs, message):
    args = {"image": _image(), "plan": _plan(), "grid_shape": (3, 4), **kwargs}
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)").replace("+", r"\+")):
        plots.plot_salad_plan(**args)


def test_gds_picture_shows_the_band_the_two_bins_and_their_misordering():
    prof = _profile()
    before = _random_state()
    fig = plots.plot_gds_misordering(prof, 0.0, 10.0, label="toy")
    after = _random_state()
    assert torch.equal(before[0], after[0]) and np.array_equal(before[1], after[1])
    left, right = fig.axes[:2]
    mean_line = [ln for ln in left.get_lines() if len(ln.get_xdata()) == len(prof.bin_centers)][0]
    assert np.allclose(mean_line.get_ydata(), prof.mean)
    p = misordering_probability(prof, 0.0, 10.0)
    assert f"{p:.3f}" in right.get_title() and "toy" in right.get_title()
    assert len(right.patches) > 0                              # the pairs' histograms (keep_pairs=True)
    plots.plot_gds_misordering(_profile(keep_pairs=False), 0.0, 10.0, axes=plt.subplots(1, 2)[1])


@pytest.mark.parametrize("profile, d1, d2, message", [
    ("not a profile", 0.0, 10.0, "GDSProfile"),
    (None, 10.0, 0.0, "d1 must be smaller"),
    (None, 0.0, 100.0, "beyond the profile"),
    (None, float("nan"), 10.0, "finite"),
    (None, True, 10.0, "finite"),
])
def test_gds_picture_rejects_bad_inputs(profile, d1, d2, message):
    with pytest.raises(ValueError, match=message):
        plots.plot_gds_misordering(_profile() if profile is None else profile, d1, d2)


def _line_world():
    utm = np.stack([np.repeat(np.arange(40) * 10.0, 4) + np.tile([0.0, 0.5, 1.0, 1.5], 40), np.zeros(160)], 1)
    groups = np.repeat(np.arange(40), 4)
    desc = np.random.default_rng(0).normal(size=(160, 8)).astype(np.float32)
    clusters = groups // 4
    clique = clique_batches(utm, clusters, sample_group_descriptors(desc, clusters, 0), 6, 4, 5.0, similar_groups=3)
    return utm, clique[0], random_place_batches(groups, 6, 4)[0]


def test_clique_picture_draws_both_batches_on_the_same_map():
    utm, clique, random = _line_world()
    before = _random_state()
    fig = plots.plot_clique_batches(utm, clique, torch.from_numpy(random), threshold=5.0)
    after = _random_state()
    assert torch.equal(before[0], after[0]) and np.array_equal(before[1], after[1])
    top, bottom = fig.axes[:2]
    assert top.get_xlim() == bottom.get_xlim() and top.get_ylim() == bottom.get_ylim()
    for ax, batch in ((top, clique), (bottom, random)):
        assert len(ax.collections) == 1 + len(batch)            # the faint map, then one colour per place
        assert np.allclose(ax.collections[0].get_offsets(), utm)
        for place, coll in zip(batch, ax.collections[1:]):
            assert np.allclose(coll.get_offsets(), utm[place])
    assert "clique batch" in top.get_title() and "tau = 5 m" in top.get_title()


@pytest.mark.parametrize("change, message", [
    ({"utm": np.zeros((160, 3))}, "utm must be"),
    ({"clique_batch": np.zeros((2, 4, 4), dtype=int)}, "one batch"),
    ({"clique_batch": np.full((2, 4), 0.5)}, "integer"),
    ({"random_batch": np.array([[0, 1], [2, 999]])}, "utm has 160 rows"),
    ({"threshold": -1.0}, "threshold"),
    ({"axes": [None, None, None]}, "two matplotlib axes"),
])
def test_clique_picture_rejects_bad_inputs(change, message):
    utm, clique, random = _line_world()
    args = {"utm": utm, "clique_batch": clique, "random_batch": random, **change}
    with pytest.raises(ValueError, match=message):
        plots.plot_clique_batches(**args)
