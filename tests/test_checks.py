"""Input checks (vpr_nb._checks) and the single-thread hot loops (vpr_nb._threads)."""
import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_info

from vpr_nb import _checks
from vpr_nb._checks import array_is_finite, as_float_matrix, check_tensor, tensor_is_finite, validated_inputs
from vpr_nb._threads import single_threaded, single_threaded_call
from vpr_nb.aggregation import SALAD, NetVLAD, salad_aggregate, sinkhorn
from vpr_nb.models import build_model


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_tensor_is_finite_finds_one_bad_value(dtype, bad):
    x = torch.rand(3, 50, dtype=dtype)
    assert tensor_is_finite(x)
    x[2, 17] = bad
    assert not tensor_is_finite(x)


def test_finite_values_whose_sum_overflows_pass():
    x = torch.full((4, 8), 3e38)                         # every value finite, the float32 sum is inf
    assert not torch.isfinite(x.sum())
    assert tensor_is_finite(x)
    assert check_tensor(x, "x") is x
    h = torch.full((100_000,), 60000.0, dtype=torch.float16)   # sum far beyond float16's range
    assert tensor_is_finite(h)
    a = np.full((4, 8), 3e38, dtype=np.float32)
    assert array_is_finite(a)
    assert as_float_matrix(a, "a") is not None
    a[1, 3] = np.nan
    with pytest.raises(ValueError, match="a contains NaN or inf in 1 row"):
        as_float_matrix(a, "a")


def test_inf_plus_minus_inf_is_caught():
    x = torch.tensor([float("inf"), -float("inf"), 1.0])   # the sum is NaN, not inf
    with pytest.raises(ValueError, match="x contains NaN or inf"):
        check_tensor(x, "x")


def test_validated_inputs_skips_only_the_finiteness_scan():
    bad = torch.tensor([[1.0, float("nan")]])
    with validated_inputs():
        assert check_tensor(bad, "x") is bad                     # the caller checked the values
        with pytest.raises(ValueError, match="2 dimensions"):
            check_tensor(bad[0], "x", ndim=2)                    # shapes are still checked
    with pytest.raises(ValueError, match="NaN or inf"):          # and the scan is back outside
        check_tensor(bad, "x")


def test_validated_inputs_is_restored_after_an_error():
    with pytest.raises(RuntimeError):
        with validated_inputs():
            raise RuntimeError("boom")
    assert not _checks._inputs_validated()


def test_model_scans_the_images_once(monkeypatch):
    """A VPRModel checks its images; its backbone and aggregator do not scan them (or their features) again."""
    calls = []
    real = _checks.tensor_is_finite
    monkeypatch.setattr(_checks, "tensor_is_finite", lambda x: calls.append(tuple(x.shape)) or real(x))
    model = build_model("small_cnn", "netvlad", num_clusters=4)
    model(torch.rand(2, 3, 32, 48))
    assert calls == [(2, 3, 32, 48)]
    calls.clear()
    salad = SALAD(num_channels=16, num_clusters=4, cluster_dim=8, token_dim=8, hidden_dim=16).eval()
    salad((torch.randn(2, 16, 5, 5), torch.randn(2, 16)))
    assert sorted(calls) == [(2, 16), (2, 16, 5, 5)]             # features and token, not f, s, scores, dustbin


def test_public_functions_still_check_when_called_directly():
    with pytest.raises(ValueError, match="scores contains NaN"):
        sinkhorn(torch.full((1, 4, 9), float("nan")), 1.0)
    f, s, t = torch.randn(1, 3, 9), torch.randn(1, 4, 9), torch.randn(1, 2)
    s[0, 1, 2] = float("inf")
    with pytest.raises(ValueError, match="scores contains NaN or inf"):
        salad_aggregate(f, s, t, 1.0)


@pytest.mark.parametrize("normalize_input", [True, False])
def test_netvlad_rejects_non_finite_input(normalize_input):
    layer = NetVLAD(num_clusters=4, dim=8, normalize_input=normalize_input)
    x = torch.randn(1, 8, 3, 3)
    x[0, 5, 2, 0] = -float("inf")
    with pytest.raises(ValueError, match="x contains NaN or inf"):
        layer(x)
    layer(torch.full((1, 8, 3, 3), 1e30))     # finite values whose squares overflow the norm: no error


def _blas_threads():
    return sorted({d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"})


def test_single_threaded_limits_blas_and_faiss_then_restores():
    import faiss

    before_blas, before_omp = _blas_threads(), faiss.omp_get_max_threads()
    with single_threaded():
        assert _blas_threads() == [1]
        assert faiss.omp_get_max_threads() == 1
    assert _blas_threads() == before_blas
    assert faiss.omp_get_max_threads() == before_omp

    @single_threaded_call
    def inside():
        """docstring kept"""
        return _blas_threads(), faiss.omp_get_max_threads()

    assert inside() == ([1], 1)
    assert inside.__doc__ == "docstring kept"
    assert faiss.omp_get_max_threads() == before_omp


def test_salad_aggregate_checks_its_dustbin():
    with pytest.raises(ValueError, match="dustbin contains NaN"):
        salad_aggregate(torch.randn(1, 3, 9), torch.randn(1, 4, 9), torch.randn(1, 2), float("nan"))
