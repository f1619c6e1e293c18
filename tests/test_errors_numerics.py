"""Numerical inputs: half-precision descriptors, Recall@N beyond the database, out-of-range predictions,
a GDS bin width asking for too many bins."""
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vpr_nb import gds
from vpr_nb.evaluation import evaluate_descriptors, recall_at_n, retrieve


def _unit(n, d, seed):
    return F.normalize(torch.randn(n, d, generator=torch.Generator().manual_seed(seed)), dim=1)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_descriptors_are_searched_in_float32(dtype):
    db, q = _unit(40, 8, 0), _unit(5, 8, 1)
    with pytest.warns(UserWarning, match="upcast to float32"):
        dist, idx = retrieve(db.to(dtype), q.to(dtype), 3)
    _, ref = retrieve(db, q, 3)
    assert dist.dtype == np.float32 and idx.dtype == np.int64
    assert (idx[:, 0] == ref[:, 0]).mean() >= 0.8            # rounding may swap near ties, nothing else
    with pytest.warns(UserWarning, match="upcast to float32"):
        rec = evaluate_descriptors(db.to(dtype), q.to(dtype), torch.zeros(40, 2), torch.zeros(5, 2), 1.0, ns=(1,))
    assert rec == {1: 1.0}
    with pytest.raises(ValueError, match="L2-normalised"):
        retrieve((2 * db).to(dtype), q.to(dtype), 3)


def _separated(seed=0):
    """8 database descriptors far apart (rows of a rotation) and 8 queries near them in another order."""
    rot, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((8, 8)))
    db = rot.astype(np.float32)
    q = db[[3, 0, 7, 1, 6, 2, 5, 4]] + 0.05 * np.random.default_rng(seed + 1).standard_normal((8, 8)).astype(np.float32)
    return db, q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.mark.parametrize("to, name", [(lambda x: torch.from_numpy(x).to(torch.bfloat16), "bfloat16"),
                                      (lambda x: torch.from_numpy(x).to(torch.float16), "float16"),
                                      (lambda x: x.astype(np.float16), "float16")])
def test_low_precision_descriptors_warn_naming_the_precision(to, name):
    db, q = _separated()
    _, ref = retrieve(db, q, 3)
    with pytest.warns(UserWarning, match=rf"retrieve got {name} descriptors \(db_desc, q_desc\); upcast to float32 "
                                         r"for the exact search"):
        dist, idx = retrieve(to(db), to(q), 3)
    assert idx[:, 0].tolist() == ref[:, 0].tolist() == [3, 0, 7, 1, 6, 2, 5, 4]   # the same neighbours
    assert dist.dtype == np.float32 and idx.dtype == np.int64
    with pytest.warns(UserWarning, match=rf"retrieve got {name} descriptors \(q_desc\); upcast"):
        assert retrieve(db, to(q), 1)[1][:, 0].tolist() == ref[:, 0].tolist()


def test_float32_descriptors_are_searched_as_they_are_without_a_warning():
    db, q = _separated()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dist, idx = retrieve(db, q, 8)
        retrieve(torch.from_numpy(db), torch.from_numpy(q), 8)
    sims = q @ db.T                                              # the brute-force inner products
    assert idx.tolist() == np.argsort(-sims, axis=1, kind="stable").tolist()
    np.testing.assert_allclose(dist, np.take_along_axis(2 - 2 * sims, idx, axis=1), atol=1e-5)


def test_recall_at_n_beyond_the_database_is_recall_at_the_database_size():
    pred = np.array([[2, 1, 0], [2, 1, 0]])
    pos = [np.array([1]), np.array([0])]
    with pytest.warns(UserWarning, match=r"Recall@N for N = \[5, 10\] is larger than the database \(3 images\): "
                                         r"it equals Recall@3"):
        rec = recall_at_n(pred, pos, ns=(1, 2, 5, 10), num_db=3)
    assert rec == {1: 0.0, 2: 0.5, 5: 1.0, 10: 1.0}
    with pytest.raises(ValueError, match="N=5 needs at least 5 predictions"):
        recall_at_n(pred, pos, ns=(5,))                     # without num_db nothing is assumed
    db, q = _unit(4, 8, 2), _unit(3, 8, 3)
    with pytest.warns(UserWarning, match=r"N = \[20\] is larger than the database \(4 images\)"):
        rec = evaluate_descriptors(db, q, np.zeros((4, 2)), np.zeros((3, 2)), 1.0, ns=(1, 20))
    assert rec[20] == 1.0 and set(rec) == {1, 20}


def test_prediction_indices_outside_the_database_are_refused():
    pos = [np.array([1]), np.array([0])]
    with pytest.raises(ValueError, match=r"predictions hold the index 7 \(first in query row 1\) but the database "
                                         r"has 3 images"):
        recall_at_n(np.array([[0, 1], [7, 0]]), pos, ns=(1,), num_db=3)
    with pytest.raises(ValueError, match=r"predictions hold the index -2"):
        recall_at_n(np.array([[0, 1], [-2, 0]]), pos, ns=(1,))
    assert recall_at_n(np.array([[1, -1], [-1, -1]]), pos, ns=(1,), num_db=3) == {1: 0.5}   # -1: faiss's "none"
    with pytest.raises(ValueError, match=r"positives hold the database index 9, outside 0 \.\. 2"):
        recall_at_n(np.array([[0, 1], [1, 0]]), [np.array([9]), np.array([0])], ns=(1,), num_db=3)


def test_a_gds_bin_width_asking_for_too_many_bins_is_refused_up_front():
    d = _unit(20, 4, 4).numpy()
    utm = np.stack([np.arange(20.0), np.zeros(20)], axis=1)
    with pytest.raises(ValueError, match=r"bin_width=1e-06 m over the range \[0, 500\] m asks for 5e\+08 bins, more "
                                         r"than MAX_BINS=1000000; use bin_width >= 0\.0005 m"):
        gds.gds_profile(d, utm, 500.0, 1e-6, pairs="all")
    assert len(gds.gds_profile(d, utm, 20.0, 1.0, pairs="all").count) == 20
