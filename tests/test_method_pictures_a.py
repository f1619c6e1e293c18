"""The method pictures of notebooks 02-04 (vpr_nb.plots.triplet, .distance_weight, .netvlad): each draws from small
tensors, leaves the random streams alone, and refuses a wrong input with a ValueError that says what is expected."""
import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from vpr_nb import plots  # noqa: E402
from vpr_nb.losses import distance_weight  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _triplets(b=4, m=3, d=8):
    g = torch.Generator().manual_seed(0)
    q = F.normalize(torch.randn(b, d, generator=g), dim=-1)
    return q, F.normalize(q + 0.8 * torch.randn(b, d, generator=g), dim=-1), \
        F.normalize(q[:, None] + torch.randn(b, m, d, generator=g), dim=-1)


def _netvlad(k=5, h=2, w=3, d=4):
    g = torch.Generator().manual_seed(0)
    image = (255 * torch.rand(8, 12, 3, generator=g)).to(torch.uint8).numpy()
    assign = torch.softmax(torch.randn(k, h, w, generator=g), dim=0)
    return image, assign, torch.randn(k, d, generator=g)


def test_triplet_picture_draws_both_panels_and_counts_the_active_triplets():
    q, p, n = _triplets()
    torch.manual_seed(123)
    state = torch.get_rng_state()
    fig = plots.plot_triplets(q, p, n, margin=0.1)
    assert torch.equal(torch.get_rng_state(), state)            # no random draw: a notebook's streams stay put
    assert len(fig.axes) == 2
    active = int(((q - p).norm(dim=-1)[:, None] - (q[:, None] - n).norm(dim=-1) + 0.1 > 0).sum())
    labels = fig.axes[1].get_legend_handles_labels()[1]
    assert f"active (loss > 0): {active} of 12" in labels
    _, axes = plt.subplots(1, 2)
    assert plots.plot_triplets(q.numpy(), p.numpy(), n.numpy(), 0.0, query=1, axes=axes) is axes[0].figure


@pytest.mark.parametrize("change, message", [
    (lambda q, p, n: (q, p[:-1], n), "shape of q"),
    (lambda q, p, n: (q, p, n[:, :, :-1]), r"\(B, M, D\)"),
    (lambda q, p, n: (q, p, n[0]), r"\(B, M, D\)"),
    (lambda q, p, n: (q.clone().fill_(float("nan")), p, n), "NaN"),
])
def test_triplet_picture_refuses_mismatched_descriptors(change, message):
    with pytest.raises(ValueError, match=message):
        plots.plot_triplets(*change(*_triplets()), margin=0.1)


def test_triplet_picture_refuses_a_bad_margin_or_query():
    with pytest.raises(ValueError, match="margin"):
        plots.plot_triplets(*_triplets(), margin=-0.1)
    with pytest.raises(ValueError, match="query"):
        plots.plot_triplets(*_triplets(b=4), margin=0.1, query=4)


def test_distance_weight_picture_draws_the_curve_sigma_and_the_flat_triplet_weight():
    geo = torch.tensor([0.0, 2.5, 7.0, 9.5])
    fig = plots.plot_distance_weight(geo, distance_weight(geo, 800.0, 0.1), sigma=800.0, eps=0.1)
    curve, ranks = fig.axes
    labels = curve.get_legend_handles_labels()[1]
    assert "σ = 800 m: w = 0" in labels and any("T-Loss" in s for s in labels)
    assert [round(b.get_height(), 4) for b in ranks.patches] == \
        [round(float(w), 4) for w in distance_weight(np.sort(geo.numpy()), 800.0, 0.1)]   # by rank: nearest first


@pytest.mark.parametrize("geo, weights, sigma, message", [
    ([1.0, 2.0], [9.0], 800.0, "one weight per pair"),
    ([1.0, -2.0], [9.0, 9.0], 800.0, ">= 0"),
    ([[1.0, 2.0]], [[9.0, 9.0]], 800.0, "1-D"),
    ([1.0, 2.0], list(distance_weight(np.array([1.0, 2.0]), 800.0, 0.1)), 25.0, "not Eq. \\(4\\)"),
    ([1.0, 2.0], [9.0, 9.0], 0.0, "sigma"),
])
def test_distance_weight_picture_refuses_inconsistent_inputs(geo, weights, sigma, message):
    with pytest.raises(ValueError, match=message):
        plots.plot_distance_weight(geo, weights, sigma=sigma, eps=0.1)


def test_netvlad_picture_draws_the_image_the_clusters_and_one_residual_bar_per_cluster():
    image, assign, residuals = _netvlad(k=5)
    fig = plots.plot_netvlad(image, assign, residuals)
    bars = fig.axes[3].patches
    assert len(bars) == 5
    assert np.allclose([b.get_height() for b in bars], residuals.norm(dim=1).numpy(), atol=1e-6)
    hatched = [bool(b.get_hatch()) for b in bars]
    assert hatched == [k not in set(assign.argmax(0).flatten().tolist()) for k in range(5)]


@pytest.mark.parametrize("change, message", [
    (lambda i, a, r: (i.astype(np.float32), a, r), "uint8"),
    (lambda i, a, r: (i, a.permute(1, 2, 0), r), "soft assignment"),
    (lambda i, a, r: (i, torch.log(a), r), "soft assignment"),
    (lambda i, a, r: (i, a, r[:-1]), "one V_k per cluster"),
    (lambda i, a, r: (i, a[0], r), "3-D"),
])
def test_netvlad_picture_refuses_a_wrong_input(change, message):
    with pytest.raises(ValueError, match=message):
        plots.plot_netvlad(*change(*_netvlad()))
