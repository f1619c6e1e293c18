"""Input validation shared by every public function of :mod:`vpr_nb`.

Each helper raises a :class:`ValueError` whose message names the argument, says what was
wrong and what is expected, so that a student who passes the wrong thing learns how to fix it.

Finiteness is checked once per public call and cheaply: one sum over the values (NaN and inf
propagate into it), and the element-wise scan only when that sum is not finite -- to name the
culprit, or to find that the values were finite after all and only their sum overflowed. A public
function that hands already validated tensors (or values computed from them) to other public
functions runs them inside :func:`validated_inputs`, where :func:`check_tensor` and :func:`as_float_matrix`
keep their shape and dtype checks but skip the finiteness scan (a model checks its images once, not again in
its backbone and its aggregator; SALAD checks its inputs once, not again in ``salad_aggregate`` and
``sinkhorn``; a triplet source checks its mining descriptors once per refresh, not at every batch).
"""
from __future__ import annotations

import contextlib
import threading
from typing import Iterator, Sequence

import numpy as np
import torch

_STATE = threading.local()   # ``depth``: how many validated public calls enclose the current code


@contextlib.contextmanager
def validated_inputs() -> Iterator[None]:
    """Run the body of a public call whose tensor inputs were checked: nested :func:`check_tensor` calls
    skip the finiteness scan (shapes and dtypes are still checked)."""
    depth = getattr(_STATE, "depth", 0)
    _STATE.depth = depth + 1
    try:
        yield
    finally:
        _STATE.depth = depth


def _inputs_validated() -> bool:
    return getattr(_STATE, "depth", 0) > 0


def tensor_is_finite(x: torch.Tensor) -> bool:
    """True iff every value of the floating tensor ``x`` is finite: one reduction, and the element-wise
    scan only when the sum is not finite (NaN/inf inside, or finite values whose sum overflows)."""
    with torch.no_grad():
        x = x.detach()
        # low-precision values are summed in float32, whose range their sum cannot overflow as easily
        total = x.sum(dtype=torch.float32) if x.element_size() < 4 else x.sum()
        if bool(torch.isfinite(total)):
            return True
        return bool(torch.isfinite(x).all())


def array_is_finite(arr: np.ndarray) -> bool:
    """:func:`tensor_is_finite` for a numpy float array."""
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(arr.sum()):
            return True
    return bool(np.isfinite(arr).all())


def as_float_matrix(x, name: str, *, dim: int | None = None, allow_empty: bool = False) -> np.ndarray:
    """Return ``x`` as a C-contiguous float32 ``(N, D)`` numpy array, validating it (its values' finiteness
    only outside :func:`validated_inputs`).

    Accepts numpy arrays, torch tensors (detached, moved to CPU) and nested lists.
    """
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu()
        x = (x.float() if x.dtype in (torch.bfloat16, torch.float16) else x).numpy()   # bfloat16 (AMP's) has no numpy dtype
    try:
        arr = np.asarray(x)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise ValueError(f"{name} must be an array of shape (N, D); could not convert {type(x).__name__}: {exc}") from exc
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise ValueError(f"{name} must be 2-D (N, D), got shape {tuple(arr.shape)}; "
                         f"reshape a single vector with x[None, :]")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name} is empty (shape {tuple(arr.shape)}): it needs at least one row")
    if arr.shape[1] == 0:
        raise ValueError(f"{name} has zero columns (shape {tuple(arr.shape)})")
    if dim is not None and arr.shape[1] != dim:
        raise ValueError(f"{name} must have {dim} columns, got shape {tuple(arr.shape)}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not _inputs_validated() and not array_is_finite(arr):
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise ValueError(f"{name} contains NaN or inf in {bad} row(s); clean or drop them first")
    return arr


def as_utm(x, name: str, *, allow_empty: bool = False) -> np.ndarray:
    """Return ``x`` as a float64 ``(N, 2)`` array of easting/northing in metres."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must be an (N, 2) array of (easting, northing) in metres, got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name} is empty: it needs at least one position")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must hold numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not array_is_finite(arr):
        raise ValueError(f"{name} contains NaN or inf coordinates; every image needs a valid geotag")
    return arr


def check_positive(value, name: str, *, allow_zero: bool = False) -> float:
    """Validate a finite positive (or non-negative) scalar and return it as float."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    if v < 0 or (v == 0 and not allow_zero):
        need = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be {need}, got {v}")
    return v


def check_int(value, name: str, *, minimum: int = 1, maximum: int | None = None) -> int:
    """Validate an integer in ``[minimum, maximum]`` and return it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise ValueError(f"{name} must be <= {maximum}, got {v}")
    return v


def check_tensor(x, name: str, *, ndim: int | Sequence[int] | None = None, finite: bool = True) -> torch.Tensor:
    """Validate a floating torch tensor (dimensions and finiteness) and return it.

    The finiteness check is one reduction (:func:`tensor_is_finite`) and is skipped inside
    :func:`validated_inputs`, where the caller has checked the values this tensor comes from.
    """
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not torch.is_floating_point(x):
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if x.ndim not in allowed:
            raise ValueError(f"{name} must have {' or '.join(map(str, allowed))} dimensions, got shape {tuple(x.shape)}")
    if finite and x.numel() and not _inputs_validated() and not tensor_is_finite(x):
        raise ValueError(f"{name} contains NaN or inf")
    return x


def check_geo_descriptors(q_desc, db_desc, q_utm, db_utm):
    """Validate query/database descriptors with their positions: ``(qd, dbd, qu, du)`` as float arrays,
    same descriptor dimension, one UTM row per descriptor."""
    qd = as_float_matrix(q_desc, "q_desc")
    dbd = as_float_matrix(db_desc, "db_desc", dim=qd.shape[1])
    qu = as_utm(q_utm, "q_utm")
    du = as_utm(db_utm, "db_utm")
    if len(qu) != len(qd):
        raise ValueError(f"q_utm has {len(qu)} rows but q_desc has {len(qd)}: one position per query")
    if len(du) != len(dbd):
        raise ValueError(f"db_utm has {len(du)} rows but db_desc has {len(dbd)}: one position per database image")
    return qd, dbd, qu, du
