"""Tests for vpr_nb.probes: effective dimension, within-image cosine, near-duplicate rate."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from vpr_nb.evaluation import compute_descriptors, raw_pixel_descriptors
from vpr_nb.models import SmallCNN, build_model
from vpr_nb.probes import (effective_dimension, local_feature_maps, local_feature_probe, near_duplicate_probe,
                           near_duplicate_rate, within_image_cosine)

pytestmark = pytest.mark.usefixtures("one_thread")   # tests/conftest.py


# ------------------------------------------------------------------------------ effective dimension
@pytest.mark.parametrize("normalize", [False, True])
def test_isotropic_gaussian_has_effective_dimension_d(normalize):
    x = np.random.default_rng(0).normal(size=(40_000, 16))
    ed = effective_dimension(x, normalize=normalize)
    assert ed.participation_ratio == pytest.approx(16, rel=0.02)
    assert ed.dims in (14, 15)                    # 0.9 * 16 = 14.4 of a near-flat spectrum


def test_known_spectrum_exactly():
    """Rows +-a_k e_k: mean 0, covariance diag(a_k^2) / C, so PR = (sum a^2)^2 / sum a^4 exactly."""
    a = np.array([3.0, 2.0, 1.0, 1.0, 0.5])
    x = np.concatenate([np.diag(a), -np.diag(a)])
    ed = effective_dimension(x, normalize=False)
    lam = a ** 2
    assert ed.participation_ratio == pytest.approx(lam.sum() ** 2 / (lam ** 2).sum(), rel=1e-9)
    np.testing.assert_allclose(ed.eigenvalues, np.sort(lam)[::-1] / len(a), rtol=1e-9)
    share = np.cumsum(np.sort(lam)[::-1]) / lam.sum()       # 0.59, 0.85, 0.91, ...
    assert ed.dims == 3 == int(np.argmax(share >= 0.9)) + 1
    assert effective_dimension(x, normalize=False, variance=0.5).dims == 1
    assert effective_dimension(x, normalize=False, variance=1.0).dims == 5


def test_effective_dimension_is_centred_and_normalised():
    rng = np.random.default_rng(1)
    line = rng.normal(size=(500, 1)) * np.array([[1.0, 2.0, -1.0]])
    assert effective_dimension(line + 10.0, normalize=False).participation_ratio == pytest.approx(1.0)   # offset ignored
    # rows of different norms along 3 directions: normalised, the norms no longer matter
    dirs = np.eye(3)[np.arange(600) % 3] * np.array([1.0, 10.0, 100.0])[np.arange(600) % 3, None]
    assert effective_dimension(dirs).participation_ratio == pytest.approx(2.0)     # 3 corners of a simplex
    assert effective_dimension(dirs, normalize=False).participation_ratio < 1.1
    zeros = np.concatenate([dirs, np.zeros((50, 3))])           # all-zero features have no direction
    assert effective_dimension(zeros).participation_ratio == pytest.approx(2.0)


def test_feature_map_pools_images_and_positions():
    m = torch.randn(3, 8, 4, 5, generator=torch.Generator().manual_seed(0))
    rows = m.permute(0, 2, 3, 1).reshape(-1, 8)
    assert effective_dimension(m).participation_ratio == pytest.approx(effective_dimension(rows).participation_ratio)


def test_effective_dimension_refuses_bad_input():
    with pytest.raises(ValueError, match=r"\[N, C\]"):
        effective_dimension(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        effective_dimension(np.array([[0.0, 1.0], [np.nan, 1.0]]))
    with pytest.raises(ValueError, match="at least 2"):
        effective_dimension(np.array([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="do not vary"):
        effective_dimension(np.ones((4, 3)))
    with pytest.raises(ValueError, match="variance"):
        effective_dimension(np.eye(3), variance=1.5)
    with pytest.raises(ValueError, match="normalize"):
        effective_dimension(np.eye(3), normalize="yes")


# ------------------------------------------------------------------------------ within-image cosine
def _map(vectors):
    """A [1, C, 1, n] map whose n local features are the given C-vectors."""
    return np.asarray(vectors, dtype=np.float64).T[None, :, None, :]


def test_within_image_cosine_known_values():
    v = np.array([1.0, 2.0, 3.0])
    assert within_image_cosine(_map([v, 2 * v, 5 * v])) == pytest.approx(1.0)       # identical directions
    assert within_image_cosine(_map(np.eye(4))) == pytest.approx(0.0)               # orthogonal
    assert within_image_cosine(_map([v, -v])) == pytest.approx(-1.0)
    # uncentred: a shared offset raises the cosine; zero features are left out
    assert within_image_cosine(_map([[1.0, 0.0], [1.0, 1.0], [0.0, 0.0]])) == pytest.approx(np.sqrt(0.5))
    two = np.concatenate([_map([v, v]), _map([[1.0, 0, 0], [0, 1.0, 0]])])          # mean over images
    assert within_image_cosine(two) == pytest.approx(0.5)
    m = torch.randn(5, 6, 3, 4, generator=torch.Generator().manual_seed(0))
    f = torch.nn.functional.normalize(m.flatten(2), dim=1)
    ref = np.mean([(g.T @ g).sum().item() - 12 for g in f]) / (12 * 11)
    assert within_image_cosine(m) == pytest.approx(ref, abs=1e-6)


def test_within_image_cosine_refuses_bad_input():
    with pytest.raises(ValueError, match=r"\[B, C, h, w\]"):
        within_image_cosine(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="two non-zero"):
        within_image_cosine(_map([[0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="finite"):
        within_image_cosine(np.full((1, 2, 1, 2), np.inf))


def test_local_feature_probe_of_a_backbone():
    net = SmallCNN(width=8, out_channels=16)
    net.features[-1] = torch.nn.Identity()          # before the final ReLU
    images = np.random.default_rng(0).integers(0, 256, (6, 32, 48, 3), dtype=np.uint8)
    maps = local_feature_maps(net, images, batch_size=4)
    assert maps.shape == (6, 16, 8, 12) and net.training                  # mode restored
    probe = local_feature_probe(net, images)
    assert probe["effective dimension"] == pytest.approx(effective_dimension(maps).participation_ratio)
    assert probe["within-image cosine"] == pytest.approx(within_image_cosine(maps))
    assert probe["features"] == 6 * 96 and 1 <= probe["dims for 90% variance"] <= 16
    with pytest.raises(ValueError, match="Module"):
        local_feature_maps("net", images)
    with pytest.raises(ValueError, match="uint8"):
        local_feature_maps(net, images[0])


# ------------------------------------------------------------------------------ near duplicates
def _route(n=40, spacing=2.5, gap_after=None):
    x = np.arange(n) * spacing
    if gap_after is not None:
        x[gap_after:] += 50.0
    return np.stack([x, np.zeros(n)], 1)


def _circle(angles):
    return np.stack([np.cos(angles), np.sin(angles)], 1)


def test_near_duplicate_rate_constructed_route():
    """Database frame i at angle i*alpha on the unit circle, query i at i*alpha + delta_i: frame i+k is
    closer than the positive exactly when k*alpha < delta_i."""
    n, alpha = 40, 0.01
    delta = np.where(np.arange(n) % 4 == 0, 0.015, 0.035)       # a quarter of the frames: small delta
    db = _circle(np.arange(n) * alpha)
    q = _circle(np.arange(n) * alpha + delta)
    utm = _route(n)
    assert near_duplicate_rate(db, q, utm, 2.5) == 1.0            # k = 1: alpha < every delta
    # k = 2: frames 0..37 count, the 10 with i % 4 == 0 (delta 0.015 < 0.02) are not closer
    assert near_duplicate_rate(db, q, utm, 5.0) == pytest.approx(28 / 38)
    assert near_duplicate_rate(db, q, utm, 10.0) == 0.0           # k = 4: 0.04 > every delta


def test_near_duplicate_rate_anchor_and_gaps():
    n = 20
    db = np.zeros((n, 2))                            # every database frame the same descriptor
    q = np.stack([np.ones(n), 3.0 * np.arange(n)], 1)  # query i at distance sqrt(1 + 9 i^2) from its positive
    utm = _route(n)
    assert near_duplicate_rate(db, q, utm, 2.5) == 1.0
    # query anchor: |q_i - q_{i+1}| = 3 is below sqrt(1 + 9 i^2) for every frame but frame 0
    assert near_duplicate_rate(db, q, utm, 2.5, anchor="query") == pytest.approx(18 / 19)
    # a split gap: frames 9 -> 10 jump 50 m; pairs across it are left out (not counted as frames)
    x = np.where(np.arange(n) < 10, 0.0, 1.0)
    db_g, q_g = _circle(x), _circle(x + 0.3)         # frame 9 and 10 differ: would count as "not closer"
    assert near_duplicate_rate(db_g, q_g, _route(n, gap_after=10), 2.5) == 1.0


def test_near_duplicate_rate_refuses_bad_input():
    db, utm = _circle(np.zeros(10)), _route(10)
    with pytest.raises(ValueError, match="multiple of the frame spacing"):
        near_duplicate_rate(db, db, utm, 3.7)
    with pytest.raises(ValueError, match="one row per frame"):
        near_duplicate_rate(db, db[:5], utm, 2.5)
    with pytest.raises(ValueError, match="anchor"):
        near_duplicate_rate(db, db, utm, 2.5, anchor="summer")
    with pytest.raises(ValueError, match="columns"):
        near_duplicate_rate(db, np.ones((10, 3)), utm, 2.5)
    with pytest.raises(ValueError, match="no two frames"):
        near_duplicate_rate(db[:3], db[:3], np.array([[0, 0], [2.5, 0], [5.0, 0]]), 10.0)
    with pytest.raises(ValueError, match="positive"):
        near_duplicate_rate(db, db, utm, -5.0)


def _fake_route_split(n=12, seed=0):
    rng = np.random.default_rng(seed)
    utm = _route(n)
    return SimpleNamespace(db_images=rng.integers(0, 256, (n, 32, 48, 3), dtype=np.uint8),
                           q_images=rng.integers(0, 256, (n, 32, 48, 3), dtype=np.uint8),
                           db_utm=utm, q_utm=utm.copy())


def test_near_duplicate_probe_raw_pixels_and_model():
    split = _fake_route_split()
    got = near_duplicate_probe(split, steps=(2.5, 5.0))
    db, q = raw_pixel_descriptors(split.db_images), raw_pixel_descriptors(split.q_images)
    assert got == {2.5: near_duplicate_rate(db, q, split.db_utm, 2.5), 5.0: near_duplicate_rate(db, q, split.db_utm, 5.0)}
    torch.manual_seed(0)
    model = build_model(SmallCNN(width=8, out_channels=16), "gem")
    got = near_duplicate_probe(split, model, steps=(5.0,), anchor="query")
    db, q = compute_descriptors(model, split.db_images), compute_descriptors(model, split.q_images)
    assert got == {5.0: near_duplicate_rate(db, q, split.db_utm, 5.0, anchor="query")}
    city = SimpleNamespace(**{**vars(split), "q_utm": split.q_utm + 3.0})
    with pytest.raises(ValueError, match="route split"):
        near_duplicate_probe(city)
    with pytest.raises(ValueError, match="Module or None"):
        near_duplicate_probe(split, "gem")
    with pytest.raises(ValueError, match="steps is empty"):
        near_duplicate_probe(split, steps=())
