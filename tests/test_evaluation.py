import warnings

import numpy as np
import pytest
import torch

from vpr_nb.evaluation import (compute_descriptors, evaluate_descriptors, evaluate_on_split, images_to_tensor,
                               mean_pairwise_cosine, positives_within, raw_pixel_descriptors, recall_at_n, recall_row,
                               retrieve)
from vpr_nb.split import Split


def _unit(x):
    x = np.asarray(x, dtype=np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_positives_within_hand_values():
    db = np.array([[0, 0], [10, 0], [30, 0], [0, 25]], float)
    q = np.array([[0, 0], [20, 0], [100, 100]], float)
    pos = positives_within(db, q, 25.0)
    assert [p.tolist() for p in pos] == [[0, 1, 3], [0, 1, 2], []]
    assert all(p.dtype == np.int64 for p in pos)
    # inclusive boundary: (0, 25) is exactly 25 m from (0, 0)
    assert 3 in positives_within(db, q[:1], 25.0)[0]


def test_positives_within_matches_brute_force():
    rng = np.random.default_rng(0)
    db, q = rng.uniform(0, 200, (300, 2)), rng.uniform(0, 200, (50, 2))
    pos = positives_within(db, q, 17.5)
    d = np.linalg.norm(q[:, None] - db[None], axis=2)
    for i in range(len(q)):
        assert pos[i].tolist() == np.flatnonzero(d[i] <= 17.5).tolist()


def test_retrieve_returns_sorted_squared_l2():
    db = _unit([[1, 0], [0, 1], [-1, 0], [0.6, 0.8]])
    q = _unit([[0.8, 0.6]])
    dist, idx = retrieve(db, q, 3)
    assert idx.tolist() == [[0, 3, 1]] or idx.tolist() == [[3, 0, 1]]
    expected = np.sort(((db - q) ** 2).sum(1))[:3]
    np.testing.assert_allclose(dist[0], expected, atol=1e-6)
    assert dist.dtype == np.float32 and idx.dtype == np.int64


def test_retrieve_matches_brute_force_ranking():
    rng = np.random.default_rng(1)
    db, q = _unit(rng.normal(size=(200, 16))), _unit(rng.normal(size=(20, 16)))
    _, idx = retrieve(db, q, 10)
    brute = np.argsort(((q[:, None] - db[None]) ** 2).sum(2), axis=1)[:, :10]
    assert (idx == brute).all()


def test_recall_at_n_hand_values():
    pred = np.array([[5, 1, 2], [3, 4, 0], [7, 8, 9]])
    pos = [np.array([1]), np.array([3]), np.array([0])]
    assert recall_at_n(pred, pos, ns=(1, 2, 3)) == {1: 1 / 3, 2: 2 / 3, 3: 2 / 3}


def test_recall_excludes_queries_without_positives_with_warning():
    pred = np.array([[0, 1], [1, 0]])
    with pytest.warns(UserWarning, match="1 of 2 queries have no positive"):
        r = recall_at_n(pred, [np.array([0]), np.array([], dtype=int)], ns=(1,))
    assert r == {1: 1.0}


def test_evaluate_descriptors_end_to_end():
    db = _unit(np.eye(4)[:, :4])
    q = _unit(np.eye(4)[[2, 0]] + 0.01)
    utm_db = np.array([[0, 0], [100, 0], [200, 0], [300, 0]], float)
    utm_q = np.array([[200, 5], [0, 5]], float)
    assert evaluate_descriptors(db, q, utm_db, utm_q, 25.0, ns=(1, 2)) == {1: 1.0, 2: 1.0}


def test_images_to_tensor_and_raw_pixels():
    img = np.zeros((2, 4, 6, 3), np.uint8)
    img[1] = 255
    x = images_to_tensor(img)
    assert x.shape == (2, 3, 4, 6) and x.dtype == torch.float32
    np.testing.assert_allclose(x[0, 0, 0, 0].item(), -0.485 / 0.229, rtol=1e-5)
    d = raw_pixel_descriptors(img // 2 + 1)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, rtol=1e-5)


def test_compute_descriptors_restores_mode():
    model = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(3 * 4 * 4, 8))
    model.train()
    out = compute_descriptors(model, np.zeros((5, 4, 4, 3), np.uint8), batch_size=2)
    assert out.shape == (5, 8) and model.training


@pytest.mark.parametrize("call, match", [
    (lambda: positives_within(np.zeros((3, 3)), np.zeros((1, 2)), 5), r"\(N, 2\)"),
    (lambda: positives_within(np.zeros((3, 2)), np.zeros((1, 2)), -1), "non-negative"),
    (lambda: positives_within(np.zeros((0, 2)), np.zeros((1, 2)), 5), "empty"),
    (lambda: positives_within(np.full((2, 2), np.nan), np.zeros((1, 2)), 5), "NaN"),
    (lambda: retrieve(_unit(np.ones((3, 4))), _unit(np.ones((2, 4))), 4), "larger than the database"),
    (lambda: retrieve(_unit(np.ones((3, 4))), _unit(np.ones((2, 5))), 1), "4 columns"),
    (lambda: retrieve(np.zeros((0, 4)), _unit(np.ones((2, 4))), 1), "empty"),
    (lambda: retrieve(_unit(np.ones((3, 4))), np.zeros((0, 4)), 1), "empty"),
    (lambda: retrieve(np.full((3, 4), np.nan), _unit(np.ones((2, 4))), 1), "NaN"),
    (lambda: retrieve(np.ones((3, 4)), np.ones((2, 4)), 1), "L2-normalised"),
    (lambda: retrieve(_unit(np.ones((3, 4))), _unit(np.ones((2, 4))), 0), ">= 1"),
    (lambda: retrieve(_unit(np.ones((3, 4)))[0], _unit(np.ones((2, 4))), 1), "2-D"),
    (lambda: recall_at_n(np.zeros((2, 3), int), [np.array([0])], (1,)), "same queries"),
    (lambda: recall_at_n(np.zeros((1, 3), int), [np.array([0])], (5,)), "k >= 5"),
    (lambda: recall_at_n(np.zeros((1, 3)), [np.array([0])], (1,)), "integer"),
    (lambda: recall_at_n(np.zeros((1, 3), int), [np.array([], int)], (1,)), "no query has a positive"),
    (lambda: recall_at_n(np.zeros((1, 3), int), [np.array([0])], ()), "empty"),
    (lambda: images_to_tensor(np.zeros((2, 4, 4, 3))), "uint8"),
    (lambda: images_to_tensor(np.zeros((4, 4, 3), np.uint8)), r"\(N, H, W, 3\)"),
])
def test_bad_inputs_raise_clear_errors(call, match):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=match):
            call()


def _split(db_utm, q_utm, radius, **regions):
    """A bare :class:`Split` with geotags only (what Recall@N reads)."""
    split = Split()
    split.name, split.db_utm, split.q_utm, split.pos_radius = "grid", np.asarray(db_utm), np.asarray(q_utm), radius
    for k, v in regions.items():
        setattr(split, k, np.asarray(v))
    return split


def test_recall_row_and_mean_cosine():
    rng = np.random.default_rng(0)
    db = rng.normal(size=(6, 4)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    split = _split(np.arange(12.0).reshape(6, 2) * 10, np.arange(12.0).reshape(6, 2) * 10, 1.0)
    row = recall_row(db, db, split, (1, 5))
    assert row == {"R@1": 1.0, "R@5": 1.0, "dim": 4, "mean cosine": round(mean_pairwise_cosine(db), 4)}
    sims = db @ db.T
    assert mean_pairwise_cosine(db) == pytest.approx(sims[~np.eye(6, dtype=bool)].mean(), abs=1e-6)


def test_recall_on_a_split_takes_its_positives_and_convention():
    # two cities with the same coordinates: a database image of the other city is no positive
    utm = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 0.0], [100.0, 0.0]])
    city = np.array(["a", "a", "b", "b"])
    db = _unit(np.eye(4, dtype=np.float32)[[0, 1, 2, 3]] + 0.01)
    q = _unit(np.eye(4, dtype=np.float32)[[2, 3, 0, 1]] + 0.01)     # each query looks like the other city's twin
    flat = evaluate_descriptors(db, q, utm, utm, 1.0, (1,))
    assert flat[1] == 1.0                                           # raw geotags: the twin is "within 1 m"
    split = _split(utm, utm, 1.0, db_region=city, q_region=city)
    assert evaluate_on_split(db, q, split, (1,))[1] == 0.0          # per city: it is not
    assert [p.tolist() for p in split.positives()] == [[0], [1], [2], [3]]
    with pytest.raises(ValueError, match="must be a vpr_nb.split.Split"):
        recall_row(db, q, object(), (1,))
    lonely = _split(utm, utm + [[0.0, 50.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]], 1.0)
    with pytest.warns(UserWarning, match="1 of 4 queries"):          # the split's convention, "exclude"
        assert evaluate_on_split(_unit(np.eye(4, dtype=np.float32)), _unit(np.eye(4, dtype=np.float32)), lonely,
                                 (1,))[1] == 1.0
    lonely.recall_convention = "all"
    assert evaluate_on_split(_unit(np.eye(4, dtype=np.float32)), _unit(np.eye(4, dtype=np.float32)), lonely,
                             (1,))[1] == 0.75
