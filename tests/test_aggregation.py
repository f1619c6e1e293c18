"""Tests of vpr_nb.aggregation: pooling, NetVLAD (+ k-means init), Sinkhorn and SALAD."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vpr_nb.aggregation import (AGGREGATOR_NAMES, GeM, MaxPool, MeanPool, NetVLAD, SALAD, kmeans_centroids,
                                make_aggregator, salad_aggregate, sample_local_descriptors, sinkhorn)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reference_aggregation import (netvlad_loop_reference, salad_aggregate_reference, salad_reference,  # noqa: E402
                                   sinkhorn_reference)

LN100 = math.log(100.0)


def _map(values) -> torch.Tensor:
    """[C][positions] nested list → a [1, C, 1, positions] float map."""
    return torch.tensor(values, dtype=torch.float32)[None, :, None, :]


# ------------------------------------------------------------------------------------------ pooling


def test_max_and_mean_pool_hand_values():
    x = _map([[3.0, 1.0], [0.0, 4.0]])
    assert torch.allclose(MaxPool()(x), torch.tensor([[0.6, 0.8]]))
    assert torch.allclose(MeanPool()(x), torch.tensor([[1.0, 1.0]]) / math.sqrt(2))


def test_gem_hand_values_and_limits():
    x = _map([[1.0, 7.0], [4.0, 4.0]])
    # p=2: sqrt((1+49)/2) = 5 and sqrt((16+16)/2) = 4
    assert torch.allclose(GeM(p=2.0)(x), torch.tensor([[5.0, 4.0]]) / math.sqrt(41))
    y = torch.rand(3, 5, 4, 6) + 0.1
    assert torch.allclose(GeM(p=1.0)(y), MeanPool()(y), atol=1e-6)
    assert torch.allclose(GeM(p=200.0)(y), MaxPool()(y), atol=2e-2)


def test_gem_clamps_negative_activations_at_eps():
    x = _map([[-5.0, 0.0], [2.0, 2.0]])
    out = GeM(p=3.0, eps=1e-6)(x)
    assert torch.isfinite(out).all()
    assert torch.allclose(out, torch.tensor([[1e-6 / 2.0, 1.0]]), atol=1e-6)


def test_gem_p_parameter_learnable_flag_and_gradient():
    gem = GeM(p=3.0)
    assert isinstance(gem.p, torch.nn.Parameter) and gem.p.requires_grad
    assert list(gem.state_dict()) == ["p"] and gem.p.shape == (1,)
    gem(torch.rand(2, 3, 4, 4) + 0.1)[:, 0].sum().backward()
    assert gem.p.grad is not None and gem.p.grad.abs().item() > 0
    assert not GeM(p=3.0, learnable=False).p.requires_grad


def test_pool_out_dim_and_unit_norm():
    x = torch.rand(4, 16, 3, 5)
    for layer in (MaxPool(in_channels=16), MeanPool(in_channels=16), GeM(in_channels=16)):
        out = layer(x)
        assert layer.out_dim == 16 and out.shape == (4, 16)
        assert torch.allclose(out.norm(dim=1), torch.ones(4), atol=1e-6)
    assert MaxPool().out_dim is None


@pytest.mark.parametrize("bad, match", [
    (torch.rand(2, 3, 4), "4 dimensions"),
    (torch.full((1, 3, 2, 2), float("nan")), "NaN"),
    (torch.zeros(1, 3, 2, 2, dtype=torch.int64), "floating"),
    (torch.rand(0, 3, 2, 2), "empty"),
    (torch.rand(1, 5, 2, 2), "5 channels but this layer was built for 3"),
])
def test_pool_rejects_bad_maps(bad, match):
    with pytest.raises(ValueError, match=match):
        GeM(in_channels=3)(bad)


@pytest.mark.parametrize("kwargs, match", [({"p": 0.0}, "p must be positive"), ({"p": float("nan")}, "finite"),
                                           ({"eps": -1.0}, "eps"), ({"learnable": 1}, "learnable"),
                                           ({"in_channels": 0}, "in_channels")])
def test_gem_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GeM(**kwargs)


# ------------------------------------------------------------------------------------------ factory


def test_make_aggregator_builds_each_name():
    expected = {"max": (MaxPool, 32), "mean": (MeanPool, 32), "gem": (GeM, 32),
                "netvlad": (NetVLAD, 8 * 32), "salad": (SALAD, 6 + 8 * 4)}
    extra = {"netvlad": {"num_clusters": 8}, "salad": {"num_clusters": 8, "cluster_dim": 4, "token_dim": 6}}
    assert set(expected) == set(AGGREGATOR_NAMES)
    for name, (cls, out_dim) in expected.items():
        layer = make_aggregator(name, 32, **extra.get(name, {}))
        assert type(layer) is cls and layer.out_dim == out_dim
        assert layer.needs_token is (name == "salad")
    assert make_aggregator("GeM", 8, p=4.0).p.item() == 4.0


def test_make_aggregator_rejects_unknown_name_and_bad_channels():
    with pytest.raises(ValueError, match="max, mean, gem, netvlad, salad"):
        make_aggregator("vlad", 32)
    with pytest.raises(ValueError, match="in_channels"):
        make_aggregator("gem", -1)
    with pytest.raises(ValueError, match="NetVLAD does not take dim, k; its options are num_clusters"):
        make_aggregator("netvlad", 8, k=4, dim=8)


# ------------------------------------------------------------------------------------------ NetVLAD


def test_netvlad_hand_computed_descriptor():
    layer = NetVLAD(num_clusters=2, dim=2, normalize_input=False)
    with torch.no_grad():
        layer.conv.weight.zero_()                       # uniform assignment 1/2 to each cluster
        layer.centroids.copy_(torch.tensor([[0.0, 0.0], [1.0, 1.0]]))
    x = _map([[1.0, 0.0], [0.0, 1.0]])                   # positions (1, 0) and (0, 1)
    # V1 = (x1 + x2)/2 - 1·c1 = (.5, .5); V2 = (x1 + x2)/2 - c2 = (-.5, -.5); cluster-major flatten
    assert torch.allclose(layer(x), torch.tensor([[0.5, 0.5, -0.5, -0.5]]), atol=1e-6)


@pytest.mark.parametrize("vladv2, normalize_input", [(False, True), (True, True), (False, False)])
def test_netvlad_matches_per_cluster_loop(vladv2, normalize_input):
    torch.manual_seed(0)
    layer = NetVLAD(num_clusters=8, dim=16, normalize_input=normalize_input, vladv2=vladv2)
    x = torch.randn(3, 16, 5, 7)
    ref = netvlad_loop_reference(x, layer.conv.weight, layer.conv.bias, layer.centroids, normalize_input)
    out = layer(x)
    assert out.shape == (3, layer.out_dim) == (3, 128)
    assert torch.allclose(out, ref, atol=1e-5)
    assert torch.allclose(out.norm(dim=1), torch.ones(3), atol=1e-6)


def test_netvlad_parameter_names_match_the_public_layer():
    v1 = {k: tuple(v.shape) for k, v in NetVLAD(64, 512).state_dict().items()}
    assert v1 == {"conv.weight": (64, 512, 1, 1), "centroids": (64, 512)}
    v2 = {k: tuple(v.shape) for k, v in NetVLAD(64, 512, vladv2=True).state_dict().items()}
    assert v2 == {"conv.weight": (64, 512, 1, 1), "conv.bias": (64,), "centroids": (64, 512)}
    published = {"conv.weight": torch.randn(4, 8, 1, 1), "centroids": torch.randn(4, 8)}
    layer = NetVLAD(4, 8)
    layer.load_state_dict(published, strict=True)
    assert torch.equal(layer.centroids, published["centroids"])


def test_netvlad_init_v1_hand_alpha():
    layer = NetVLAD(num_clusters=2, dim=2)
    centroids = np.array([[2.0, 0.0], [0.0, 3.0]])
    # cosines to (1,0),(0,1): (1, 0) → gap 1; (0.6, 0.8) → gap 0.2; mean gap 0.6
    layer.init_from_clusters(centroids, np.array([[1.0, 0.0], [0.6, 0.8]]))
    alpha = LN100 / 0.6
    assert isinstance(layer.alpha, float) and layer.alpha == pytest.approx(alpha, rel=1e-6)
    assert torch.allclose(layer.conv.weight[:, :, 0, 0], alpha * torch.eye(2), atol=1e-5)
    assert torch.allclose(layer.centroids, torch.tensor(centroids, dtype=torch.float32))
    assert layer.conv.bias is None


def test_netvlad_init_v1_gives_100_to_1_assignment_at_the_mean_gap():
    layer = NetVLAD(num_clusters=2, dim=2)
    layer.init_from_clusters(torch.eye(2), torch.tensor([[0.6, 0.8], [0.8, 0.6]]))
    assign = torch.softmax(layer.conv(_map([[0.6], [0.8]]))[0, :, 0, 0], dim=0)
    assert (assign[1] / assign[0]).item() == pytest.approx(100.0, rel=1e-4)


def test_netvlad_init_v2_uses_real_squared_distances():
    layer = NetVLAD(num_clusters=2, dim=2, normalize_input=False, vladv2=True)
    centroids = torch.tensor([[0.0, 0.0], [2.0, 0.0]])
    # (0.5, 0): d² = 0.25, 2.25; (1.5, 0): d² = 2.25, 0.25 → mean(d2² - d1²) = 2
    layer.init_from_clusters(centroids, np.array([[0.5, 0.0], [1.5, 0.0]]))
    alpha = LN100 / 2.0
    assert layer.alpha == pytest.approx(alpha, rel=1e-6)
    assert torch.allclose(layer.conv.weight[:, :, 0, 0], 2 * alpha * centroids, atol=1e-5)
    assert torch.allclose(layer.conv.bias, torch.tensor([0.0, -4.0 * alpha]), atol=1e-5)
    # the logits give the soft assignment exp(-α‖x - c_k‖²) / Σ (Eq. 2 of NetVLAD)
    x = torch.randn(5, 2)
    expected = torch.softmax(-alpha * torch.cdist(x, centroids) ** 2, dim=1)
    logits = layer.conv(x.T[None, :, None, :])[0, :, 0, :].T
    assert torch.allclose(torch.softmax(logits, dim=1), expected, atol=1e-4)


@pytest.mark.parametrize("centroids, descriptors, match", [
    (np.ones((3, 2)), np.eye(2), "num_clusters=2"),
    (np.eye(2, 3), np.eye(2), "must have 2 columns"),
    (np.eye(2), np.eye(3), "must have 2 columns"),
    (np.eye(2), np.array([[np.nan, 1.0]]), "NaN"),
    (np.zeros((2, 2)), np.eye(2), "all-zero"),
    (np.eye(2), np.array([[1.0, 1.0]]), "equally close"),
])
def test_netvlad_init_rejects_bad_inputs(centroids, descriptors, match):
    with pytest.raises(ValueError, match=match):
        NetVLAD(num_clusters=2, dim=2).init_from_clusters(centroids, descriptors)


def test_netvlad_init_needs_two_clusters():
    with pytest.raises(ValueError, match="at least 2 clusters"):
        NetVLAD(num_clusters=1, dim=2).init_from_clusters(np.ones((1, 2)), np.eye(2))


@pytest.mark.parametrize("kwargs, match", [({"num_clusters": 0}, "num_clusters"), ({"dim": 2.5}, "dim"),
                                           ({"vladv2": "yes"}, "vladv2"), ({"normalize_input": None}, "normalize")])
def test_netvlad_rejects_bad_constructor_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NetVLAD(**kwargs)


def test_netvlad_forward_rejects_wrong_channels():
    with pytest.raises(ValueError, match="built for 16"):
        NetVLAD(4, 16)(torch.randn(1, 8, 3, 3))


def test_sample_local_descriptors_picks_distinct_normalised_columns():
    maps = torch.randn(3, 4, 5, 6)
    out = sample_local_descriptors(maps, per_image=7, seed=1)
    assert isinstance(out, np.ndarray) and out.shape == (21, 4) and out.dtype == np.float32
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    for i in range(3):
        columns = torch.nn.functional.normalize(maps[i].flatten(1).T, dim=1).numpy()   # [30, 4]
        chosen = [int(np.argmin(np.linalg.norm(columns - row, axis=1))) for row in out[7 * i: 7 * (i + 1)]]
        assert np.allclose(columns[chosen], out[7 * i: 7 * (i + 1)], atol=1e-6)
        assert len(set(chosen)) == 7
    assert np.array_equal(out, sample_local_descriptors(maps, per_image=7, seed=1))
    assert not np.array_equal(out, sample_local_descriptors(maps, per_image=7, seed=2))


@pytest.mark.parametrize("maps, per_image, seed, match", [
    (torch.randn(2, 3, 2, 2), 5, 0, "<= 4"),
    (torch.randn(2, 3, 2, 2), 0, 0, "per_image"),
    (torch.randn(2, 3, 4), 1, 0, "4 dimensions"),
    (np.zeros((2, 3, 2, 2)), 1, 0, "torch.Tensor"),
    (torch.randn(2, 3, 2, 2), 1, -1, "seed"),
])
def test_sample_local_descriptors_rejects_bad_inputs(maps, per_image, seed, match):
    with pytest.raises(ValueError, match=match):
        sample_local_descriptors(maps, per_image, seed)


def test_kmeans_centroids_finds_blobs_deterministically():
    rng = np.random.default_rng(0)
    centres = np.array([[10.0, 0.0], [0.0, 10.0], [-10.0, -10.0]])
    points = (centres[:, None, :] + 0.1 * rng.standard_normal((3, 50, 2))).reshape(-1, 2)
    found = kmeans_centroids(points, 3, niter=20, seed=0)
    assert found.shape == (3, 2) and found.dtype == np.float32
    order = [int(np.argmin(np.linalg.norm(found - c, axis=1))) for c in centres]
    assert sorted(order) == [0, 1, 2]
    assert np.allclose(found[order], centres, atol=0.1)
    assert np.array_equal(found, kmeans_centroids(torch.from_numpy(points), 3, niter=20, seed=0))
    assert not np.array_equal(found, kmeans_centroids(points, 3, niter=20, seed=1))  # the seed is used


@pytest.mark.parametrize("descs, k, niter, match", [
    (np.ones((3, 2)), 4, 10, "4 clusters from 3"),
    (np.full((5, 2), np.nan), 2, 10, "NaN"),
    (np.ones((5, 2)), 2, 0, "niter"),
    (np.ones(5), 2, 10, "2-D"),
])
def test_kmeans_centroids_rejects_bad_inputs(descs, k, niter, match):
    with pytest.raises(ValueError, match=match):
        kmeans_centroids(descs, k, niter=niter)


def test_netvlad_cluster_init_pipeline_end_to_end():
    torch.manual_seed(0)
    maps = torch.randn(6, 8, 4, 4)
    descs = sample_local_descriptors(maps, per_image=10, seed=0)
    layer = NetVLAD(num_clusters=4, dim=8)
    layer.init_from_clusters(kmeans_centroids(descs, 4, niter=10, seed=0), descs)
    assert layer.alpha > 0
    out = layer(maps)
    assert out.shape == (6, 32) and torch.isfinite(out).all()


# ------------------------------------------------------------------------------------------ Sinkhorn


def test_sinkhorn_hand_computed_uniform_plan():
    # m=1, n=2, all-zero scores and dustbin: kernel of ones, marginals a=[1, 1], b=[1, 1] → P = 1/2
    log_p = sinkhorn(torch.zeros(1, 1, 2), torch.tensor(0.0), num_iters=1)
    assert torch.allclose(log_p, torch.full((1, 2, 2), math.log(0.5)), atol=1e-6)


def test_sinkhorn_marginals_after_many_iterations():
    torch.manual_seed(0)
    m, n = 6, 20
    plan = sinkhorn(torch.randn(3, m, n, dtype=torch.float64), torch.tensor(0.7), num_iters=100).exp()
    assert plan.shape == (3, m + 1, n)
    assert torch.allclose(plan.sum(dim=1), torch.ones(3, n, dtype=torch.float64), atol=1e-4)
    assert torch.allclose(plan[:, :m].sum(dim=2), torch.ones(3, m, dtype=torch.float64), atol=1e-4)
    assert torch.allclose(plan[:, m].sum(dim=1), torch.full((3,), n - m, dtype=torch.float64), atol=1e-4)


@pytest.mark.parametrize("num_iters", [1, 3])
def test_sinkhorn_matches_multiplicative_reference(num_iters):
    torch.manual_seed(1)
    scores = torch.randn(2, 5, 13, dtype=torch.float64) * 2
    ours = sinkhorn(scores, 1.0, num_iters).exp()
    assert torch.allclose(ours, sinkhorn_reference(scores, 1.0, num_iters), atol=1e-5)


def test_sinkhorn_single_image_equals_its_batched_row():
    torch.manual_seed(2)
    scores = torch.randn(2, 4, 9)
    assert torch.allclose(sinkhorn(scores[:1], 0.5), sinkhorn(scores, 0.5)[:1], atol=1e-6)


def test_sinkhorn_gradient_reaches_dustbin():
    dustbin = torch.tensor(1.0, requires_grad=True)
    sinkhorn(torch.randn(2, 3, 8), dustbin)[:, :3].exp().pow(2).sum().backward()
    assert dustbin.grad is not None and dustbin.grad.abs().item() > 0


@pytest.mark.parametrize("scores, dustbin, num_iters, match", [
    (torch.randn(1, 64, 64), 1.0, 3, r"64 clusters need more than 64 feature positions .* 9×9 map"),
    (torch.randn(1, 4, 9), torch.ones(2), 3, "scalar"),
    (torch.randn(1, 4, 9), "1", 3, "scalar"),
    (torch.randn(1, 4, 9), float("inf"), 3, "NaN or inf"),
    (torch.randn(4, 9), 1.0, 3, "3 dimensions"),
    (torch.full((1, 4, 9), float("nan")), 1.0, 3, "NaN"),
    (torch.randn(1, 4, 9), 1.0, 0, "num_iters"),
    (torch.randn(0, 4, 9), 1.0, 3, "empty"),
])
def test_sinkhorn_rejects_bad_inputs(scores, dustbin, num_iters, match):
    with pytest.raises(ValueError, match=match):
        sinkhorn(scores, dustbin, num_iters)


# ------------------------------------------------------------------------------------------ SALAD

# Key names and shapes of the aggregator in the published DINOv2-SALAD checkpoint (ViT-B, 64×128 + 256).
PUBLISHED_SALAD_SHAPES = {
    "token_features.0.weight": (512, 768), "token_features.0.bias": (512,),
    "token_features.2.weight": (256, 512), "token_features.2.bias": (256,),
    "cluster_features.0.weight": (512, 768, 1, 1), "cluster_features.0.bias": (512,),
    "cluster_features.3.weight": (128, 512, 1, 1), "cluster_features.3.bias": (128,),
    "score.0.weight": (512, 768, 1, 1), "score.0.bias": (512,),
    "score.3.weight": (64, 512, 1, 1), "score.3.bias": (64,),
    "dust_bin": (),
}


def test_salad_aggregate_hand_computed_order():
    # m=2 clusters, n=3 positions, zero scores and dustbin: uniform kernel, all marginals 1 → P = 1/3
    f = torch.tensor([[[3.0, 0.0, 0.0], [0.0, 0.0, 6.0]]])          # l=2 channels
    out = salad_aggregate(f, torch.zeros(1, 2, 3), torch.tensor([[3.0, 4.0]]), 0.0)
    # V[l, k] = Σ_i f[l, i] / 3 = [[1, 1], [2, 2]]; each cluster column → (1, 2)/√5; index l·m + k
    expected = torch.tensor([[0.6, 0.8, 1 / 5 ** 0.5, 1 / 5 ** 0.5, 2 / 5 ** 0.5, 2 / 5 ** 0.5]]) / 3 ** 0.5
    assert torch.allclose(out, expected, atol=1e-6)


def test_salad_aggregate_matches_repeat_reference():
    gen = torch.Generator().manual_seed(5)
    f, s = torch.randn(2, 6, 30, generator=gen), torch.randn(2, 5, 30, generator=gen)
    t = torch.randn(2, 3, generator=gen)
    assert torch.allclose(salad_aggregate(f, s, t, 0.3), salad_aggregate_reference(f, s, t, 0.3), atol=1e-5)


@pytest.mark.parametrize("f, s, t, match", [
    (torch.randn(2, 6, 30), torch.randn(2, 5, 31), torch.randn(2, 3), "batch size"),
    (torch.randn(2, 6, 30), torch.randn(1, 5, 30), torch.randn(2, 3), "batch size"),
    (torch.randn(2, 6, 30), torch.randn(2, 5, 30), torch.randn(3, 3), "batch size"),
    (torch.randn(6, 30), torch.randn(2, 5, 30), torch.randn(2, 3), "local_features must have 3"),
    (torch.randn(2, 6, 30), torch.randn(2, 5, 30), torch.full((2, 3), float("inf")), "token contains NaN"),
])
def test_salad_aggregate_rejects_bad_inputs(f, s, t, match):
    with pytest.raises(ValueError, match=match):
        salad_aggregate(f, s, t, 1.0)


def test_salad_default_parameter_count_and_out_dim():
    salad = SALAD()
    assert sum(p.numel() for p in salad.parameters()) == 1_411_009
    assert salad.out_dim == 8448


def test_salad_loads_published_state_dict_and_matches_reference():
    gen = torch.Generator().manual_seed(0)
    published = {k: torch.randn(shape, generator=gen) * 0.05 for k, shape in PUBLISHED_SALAD_SHAPES.items()}
    published["dust_bin"] = torch.tensor(0.8)
    salad = SALAD().eval()
    salad.load_state_dict(published, strict=True)
    features, token = torch.randn(2, 768, 10, 11, generator=gen), torch.randn(2, 768, generator=gen)
    with torch.no_grad():
        ours = salad((features, token))
        ref = salad_reference(published, features, token)
    assert ours.shape == (2, 8448)
    assert torch.allclose(ours, ref, atol=1e-5)
    assert torch.allclose(ours.norm(dim=1), torch.ones(2), atol=1e-6)


def test_salad_small_configuration_matches_reference_and_backpropagates():
    torch.manual_seed(3)
    salad = SALAD(num_channels=32, num_clusters=8, cluster_dim=4, token_dim=6, dropout=0.0)
    features, token = torch.randn(3, 32, 3, 4), torch.randn(3, 32)
    out = salad((features, token))
    ref = salad_reference(dict(salad.named_parameters()), features, token)
    assert out.shape == (3, 6 + 8 * 4)
    assert torch.allclose(out, ref, atol=1e-5)
    out[:, ::3].sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in salad.parameters())


def test_salad_dropout_only_in_train_mode():
    torch.manual_seed(4)
    salad = SALAD(num_channels=16, num_clusters=4, cluster_dim=4, token_dim=4, dropout=0.5)
    x = (torch.randn(2, 16, 3, 3), torch.randn(2, 16))
    assert not torch.allclose(salad(x), salad(x))
    salad.eval()
    assert torch.equal(salad(x), salad(x))


@pytest.mark.parametrize("x, match", [
    (torch.randn(1, 16, 3, 3), "pair"),
    ((torch.randn(1, 8, 3, 3), torch.randn(1, 16)), "built for 16"),
    ((torch.randn(1, 16, 3, 3), torch.randn(2, 16)), r"token must have shape \(1, 16\)"),
    ((torch.randn(1, 16, 3, 3), torch.randn(16)), "2 dimensions"),
    ((torch.full((1, 16, 3, 3), float("nan")), torch.randn(1, 16)), "NaN"),
    ((torch.randn(1, 16, 2, 2), torch.randn(1, 16)), r"4 clusters need more than 4 feature positions .* 3×3"),
])
def test_salad_rejects_bad_inputs(x, match):
    salad = SALAD(num_channels=16, num_clusters=4, cluster_dim=4, token_dim=4)
    with pytest.raises(ValueError, match=match):
        salad(x)


@pytest.mark.parametrize("kwargs, match", [({"dropout": 1.0}, "dropout"), ({"dropout": -0.1}, "dropout"),
                                           ({"num_clusters": 0}, "num_clusters"),
                                           ({"cluster_dim": 1.5}, "cluster_dim"), ({"token_dim": None}, "token_dim"),
                                           ({"hidden_dim": 0}, "hidden_dim")])
def test_salad_rejects_bad_constructor_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SALAD(num_channels=16, **kwargs)


def test_salad_hidden_dim_sets_the_head_width_and_keeps_the_published_names():
    torch.manual_seed(6)
    salad = SALAD(num_channels=32, num_clusters=8, cluster_dim=4, token_dim=6, dropout=0.0, hidden_dim=16)
    shapes = {k: tuple(v.shape) for k, v in salad.state_dict().items()}
    assert set(shapes) == set(PUBLISHED_SALAD_SHAPES)
    assert shapes["score.0.weight"] == (16, 32, 1, 1) and shapes["score.3.weight"] == (8, 16, 1, 1)
    assert shapes["token_features.0.weight"] == (16, 32) and shapes["cluster_features.3.weight"] == (4, 16, 1, 1)
    features, token = torch.randn(2, 32, 3, 4), torch.randn(2, 32)
    ref = salad_reference(dict(salad.named_parameters()), features, token)
    assert torch.allclose(salad((features, token)), ref, atol=1e-5)
    assert SALAD().hidden_dim == 512


def test_sample_local_descriptors_skips_exactly_zero_features():
    # a backbone ending in a ReLU switches whole positions off: those have no direction to cluster
    torch.manual_seed(0)
    maps = torch.relu(torch.randn(4, 6, 3, 5))
    maps[:, :, 0, :] = 0.0                       # the first row of every map is exactly zero
    maps[2, :, 1:, :] = 0.0                      # image 2: nothing but zeros
    maps[3, :, 1:, 1:] = 0.0                     # image 3: two non-zero positions left, (1, 0) and (2, 0)
    out = sample_local_descriptors(maps, per_image=4, seed=0)
    assert out.shape == (4 + 4 + 0 + 2, 6)
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    image3 = torch.nn.functional.normalize(maps[3, :, 1:, 0].T, dim=1).numpy()
    assert sorted(np.argmin(np.linalg.norm(image3[None] - out[-2:, None], axis=2), axis=1)) == [0, 1]
    kept = sample_local_descriptors(maps, per_image=4, seed=0, skip_zero=False)
    assert kept.shape == (16, 6) and (np.linalg.norm(kept, axis=1) == 0).any()
    dense = torch.randn(3, 4, 5, 6)                # no zero features: the same draw as before
    assert np.array_equal(sample_local_descriptors(dense, 7, seed=1),
                          sample_local_descriptors(dense, 7, seed=1, skip_zero=False))
    with pytest.raises(ValueError, match="exactly zero"):
        sample_local_descriptors(torch.zeros(2, 3, 2, 2), 1)
    with pytest.raises(ValueError, match="skip_zero"):
        sample_local_descriptors(dense, 1, skip_zero=1)
