"""The pictures' one input check: an array or tensor of finite numbers with the expected number of dimensions."""
from __future__ import annotations

import numpy as np


def as_numbers(x, name: str, ndim: int, what: str = "") -> np.ndarray:
    """``x`` (a numpy array, a list or a torch tensor) as a float64 array of ``ndim`` dimensions, none empty, every
    value finite; else ValueError naming ``name`` (and ``what`` it holds, e.g. "one per query-positive pair")."""
    arr = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number) or arr.ndim != ndim or 0 in arr.shape:
        holds = f" ({what})" if what else ""
        raise ValueError(f"{name} must be a non-empty {ndim}-D array of numbers{holds}, got {arr.dtype} of shape "
                         f"{tuple(arr.shape)}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf")
    return arr
