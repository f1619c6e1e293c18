"""Answers as data: written by the sandboxed student process, read and compared by the grader.

A value crosses the sandbox boundary as a JSON tree plus a ``.npz`` file of arrays, never as a pickle:
numbers, booleans, strings, ``None``, lists, tuples, dicts with string keys, numpy arrays of numbers or
booleans and torch tensors (stored as their numpy values, marked as tensors). Anything else is refused
with a message saying what came back. :func:`read` validates sizes, depth and dtypes before it builds a
value, and loads arrays with ``allow_pickle=False``; :func:`compare` checks a decoded answer against the
instructor's reference with a tolerance and says where and how they differ.
"""
from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_DEPTH = 20
MAX_NODES = 100_000
MAX_STRING = 20_000
MAX_ELEMENTS = 20_000_000          # array elements in one file, all arrays together
MAX_JSON_BYTES = 8 * 2 ** 20
MAX_NPZ_BYTES = 256 * 2 ** 20
NUMERIC_KINDS = "biufc"            # bool, int, uint, float, complex


class DataError(ValueError):
    """A value that cannot cross the sandbox boundary (or a file that does not hold one)."""


@dataclass(frozen=True, eq=False)
class TensorValue:
    """A torch tensor's values, as the grader sees them (the grader never needs torch to compare)."""
    array: np.ndarray

    def __repr__(self) -> str:
        return f"tensor({self.array.tolist() if self.array.size <= 8 else f'shape {self.array.shape}'})"


# --------------------------------------------------------------------------------------------------
# encoding (both sides) and decoding


def _tensor_type():
    import sys
    torch = sys.modules.get("torch")         # a tensor can only exist if torch was imported
    return torch.Tensor if torch is not None else None


def encode(value, arrays: dict | None = None, _depth: int = 0, _count: list | None = None):
    """``value`` as a JSON-able tree; arrays go into ``arrays`` (name -> ndarray). Raises DataError."""
    arrays = {} if arrays is None else arrays
    _count = [0] if _count is None else _count
    _count[0] += 1
    if _count[0] > MAX_NODES or _depth > MAX_DEPTH:
        raise DataError(f"the value is too large or too deeply nested (more than {MAX_NODES} items "
                        f"or {MAX_DEPTH} levels)")
    tensor = _tensor_type()
    if value is None or isinstance(value, (bool, str)):
        if isinstance(value, str) and len(value) > MAX_STRING:
            raise DataError(f"a string of {len(value)} characters (at most {MAX_STRING})")
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {"$int": str(value)} if isinstance(value, int) and abs(value) > 2 ** 53 else value
    if isinstance(value, np.generic):
        if value.dtype.kind not in NUMERIC_KINDS:
            raise DataError(f"a numpy scalar of dtype {value.dtype} (only numbers and booleans)")
        return encode(value.item(), arrays, _depth + 1, _count)
    if tensor is not None and isinstance(value, tensor):
        import torch
        t = value.detach().cpu().resolve_conj()
        if t.dtype in (torch.bfloat16, torch.float16):
            t = t.float()
        return {"$tensor": _add_array(t.numpy(), arrays)}
    if isinstance(value, np.ndarray):
        return {"$array": _add_array(value, arrays)}
    if isinstance(value, (list, tuple)):
        items = [encode(v, arrays, _depth + 1, _count) for v in value]
        return {"$tuple": items} if isinstance(value, tuple) else items
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise DataError("a dict whose keys are not all strings")
        return {"$dict": {k: encode(v, arrays, _depth + 1, _count) for k, v in value.items()}}
    raise DataError(f"a {type(value).__module__}.{type(value).__qualname__} (only numbers, booleans, strings, "
                    "None, lists, tuples, dicts, numpy arrays and torch tensors can be graded)")


def _add_array(a: np.ndarray, arrays: dict) -> str:
    if a.dtype.kind not in NUMERIC_KINDS:
        raise DataError(f"an array of dtype {a.dtype} (only numbers and booleans)")
    if sum(x.size for x in arrays.values()) + a.size > MAX_ELEMENTS:
        raise DataError(f"arrays of more than {MAX_ELEMENTS} elements in all")
    name = f"a{len(arrays)}"
    arrays[name] = np.array(a, order="C", copy=True)      # keeps 0-d arrays 0-d
    return name


def decode(tree, arrays, make_tensor=None, _depth: int = 0):
    """The value of an encoded tree. ``make_tensor`` turns a tensor's array into the caller's type
    (default :class:`TensorValue`; the sandbox passes ``torch.from_numpy``)."""
    if _depth > MAX_DEPTH:
        raise DataError(f"nested more than {MAX_DEPTH} levels")
    if tree is None or isinstance(tree, (bool, int, float, str)):
        if isinstance(tree, str) and len(tree) > MAX_STRING:
            raise DataError(f"a string of {len(tree)} characters (at most {MAX_STRING})")
        return tree
    if isinstance(tree, list):
        return [decode(v, arrays, make_tensor, _depth + 1) for v in tree]
    if isinstance(tree, dict) and len(tree) == 1:
        (tag, body), = tree.items()
        if tag == "$int" and isinstance(body, str) and len(body) < 400:
            return int(body)
        if tag == "$tuple" and isinstance(body, list):
            return tuple(decode(v, arrays, make_tensor, _depth + 1) for v in body)
        if tag == "$dict" and isinstance(body, dict):
            return {str(k): decode(v, arrays, make_tensor, _depth + 1) for k, v in body.items()}
        if tag in ("$array", "$tensor") and isinstance(body, str):
            if body not in arrays:
                raise DataError(f"the array {body!r} is missing from the data file")
            a = arrays[body]
            if tag == "$array":
                return a
            return make_tensor(a) if make_tensor is not None else TensorValue(a)
    raise DataError(f"an unknown item in the data file: {str(tree)[:80]}")


def write(value, folder, stem: str) -> None:
    """Write ``value`` as ``stem.json`` + ``stem.npz`` in ``folder`` (atomically: the JSON last)."""
    folder = Path(folder)
    arrays: dict = {}
    tree = encode(value, arrays)
    tmp = folder / f".{stem}.npz.tmp"
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, folder / f"{stem}.npz")
    tmp = folder / f".{stem}.json.tmp"
    tmp.write_text(json.dumps(tree))
    os.replace(tmp, folder / f"{stem}.json")


def read(folder, stem: str, make_tensor=None):
    """Read a value written by :func:`write`, refusing anything that is not plain data. Raises DataError."""
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        raise DataError(f"{folder.name} is missing (or not a plain folder)")
    jpath, npath = folder / f"{stem}.json", folder / f"{stem}.npz"
    for p, limit in ((jpath, MAX_JSON_BYTES), (npath, MAX_NPZ_BYTES)):
        if p.is_symlink() or not p.is_file():
            raise DataError(f"{p.name} is missing (or not a plain file)")
        if p.stat().st_size > limit:
            raise DataError(f"{p.name} is {p.stat().st_size} bytes (at most {limit})")
    try:
        tree = json.loads(jpath.read_text())
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"{jpath.name} is not valid JSON ({err})") from err
    try:
        with zipfile.ZipFile(npath) as z:
            infos = z.infolist()
            if sum(i.file_size for i in infos) > MAX_NPZ_BYTES or len(infos) > MAX_NODES:
                raise DataError(f"{npath.name} unpacks to more than {MAX_NPZ_BYTES} bytes")
        arrays = {}
        with np.load(npath, allow_pickle=False) as npz:
            for name in npz.files:
                a = npz[name]
                if a.dtype.kind not in NUMERIC_KINDS:
                    raise DataError(f"the array {name!r} has dtype {a.dtype} (only numbers and booleans)")
                arrays[name] = a
    except DataError:
        raise
    except Exception as err:     # a corrupt zip, an object array (pickle refused), a truncated file
        raise DataError(f"{npath.name} is not a plain numpy archive ({type(err).__name__}: {err})") from err
    return decode(tree, arrays, make_tensor)


def roundtrip(value):
    """``value`` as the grader would receive it from a sandbox (raises DataError where it could not)."""
    arrays: dict = {}
    tree = encode(value, arrays)
    return decode(json.loads(json.dumps(tree)), {k: v.copy() for k, v in arrays.items()})


# --------------------------------------------------------------------------------------------------
# comparison in the grader


def fmt(value) -> str:
    """Short text of a decoded value, as it appears in feedback."""
    if isinstance(value, TensorValue):
        a = value.array
        return f"tensor({_fmt_array(a)})" if a.size <= 8 else f"a tensor of shape {tuple(a.shape)}"
    if isinstance(value, np.ndarray):
        return _fmt_array(value) if value.size <= 8 else f"an array of shape {value.shape}"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str):
        return repr(value if len(value) <= 80 else value[:77] + "...")
    if isinstance(value, (list, tuple)) and len(value) <= 8:
        inner = ", ".join(fmt(v) for v in value)
        return f"[{inner}]" if isinstance(value, list) else f"({inner}{',' if len(value) == 1 else ''})"
    if isinstance(value, (list, tuple)):
        return f"a {type(value).__name__} of {len(value)} items"
    if isinstance(value, dict):
        text = "{" + ", ".join(f"{k!r}: {fmt(v)}" for k, v in list(value.items())[:8]) + "}"
        return text if len(text) <= 200 else f"a dict with keys {sorted(value)[:8]}"
    return repr(value)


def _fmt_array(a: np.ndarray) -> str:
    if a.ndim == 0:
        return fmt(a.item())
    return np.array2string(a, precision=6, separator=", ")


def describe(value) -> str:
    """What kind of value came back, for a type mismatch."""
    if isinstance(value, TensorValue):
        return f"a torch tensor of shape {tuple(value.array.shape)}"
    if isinstance(value, np.ndarray):
        return f"a numpy array of shape {value.shape}"
    if value is None:
        return "None"
    return f"a {type(value).__name__} {fmt(value)}"


def _number(value):
    """A real number from a Python number or a one-element array/tensor; None otherwise."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return value
    arr = value.array if isinstance(value, TensorValue) else value if isinstance(value, np.ndarray) else None
    if arr is not None and arr.size == 1 and arr.dtype.kind in "iuf":
        return arr.reshape(()).item()
    return None


def _close(got: float, expect: float, atol: float, rtol: float) -> bool:
    if isinstance(expect, float) and math.isnan(expect):
        return isinstance(got, float) and math.isnan(got)
    if isinstance(got, float) and math.isnan(got):
        return False
    if isinstance(expect, float) and math.isinf(expect):
        return got == expect
    return abs(got - expect) <= atol + rtol * abs(expect)


def compare(got, expect, atol: float = 1e-6, rtol: float = 1e-6, where: str = "") -> str | None:
    """None when the decoded answer ``got`` matches ``expect``; otherwise what differs.

    Tensors must come back as tensors of the same shape, arrays as arrays (or tensors, or lists) of the
    same shape, numbers as numbers (or one-element arrays), booleans, strings and None exactly, lists and
    tuples item by item, dicts key by key; numbers within ``atol + rtol * |expect|``.
    """
    at = f" at {where}" if where else ""
    if isinstance(expect, (TensorValue, np.ndarray)):
        want = expect.array if isinstance(expect, TensorValue) else expect
        if isinstance(expect, TensorValue) and not isinstance(got, TensorValue):
            return f"expected a torch tensor of shape {tuple(want.shape)}{at}, got {describe(got)}"
        if isinstance(got, TensorValue):
            have = got.array
        elif isinstance(got, np.ndarray):
            have = got
        else:
            try:
                have = np.asarray(got, dtype=float)
            except (TypeError, ValueError):
                return f"expected an array of shape {want.shape}{at}, got {describe(got)}"
        if have.shape != want.shape:
            return f"expected shape {tuple(want.shape)}{at}, got shape {tuple(have.shape)}"
        if have.dtype.kind not in "biuf" or want.dtype.kind not in "biuf":
            return None if np.array_equal(have, want) else f"expected {fmt(expect)}{at}, got {fmt(got)}"
        h, w = have.astype(float), want.astype(float)
        bad = ~(np.isclose(h, w, atol=atol, rtol=rtol) | (np.isnan(h) & np.isnan(w)))
        if not bad.any():
            return None
        if want.size <= 8:
            return f"expected {fmt(expect)}{at}, got {fmt(got)}"
        i = tuple(int(j) for j in np.argwhere(bad)[0])
        return (f"{int(bad.sum())} of {want.size} values differ{at}; first at index {i}: expected "
                f"{w[i]:.6g}, got {h[i]:.6g}")
    if isinstance(expect, bool) or expect is None or isinstance(expect, str):
        ok = (isinstance(got, bool) and got == expect) if isinstance(expect, bool) else \
             (got is None) if expect is None else (isinstance(got, str) and got == expect)
        return None if ok else f"expected {fmt(expect)}{at}, got {describe(got) if type(got) is not type(expect) else fmt(got)}"
    if isinstance(expect, (int, float)):
        num = _number(got)
        if num is None:
            return f"expected a number{at} ({fmt(expect)}), got {describe(got)}"
        return None if _close(num, expect, atol, rtol) else f"expected {fmt(expect)}{at}, got {fmt(num)}"
    if isinstance(expect, (list, tuple)):
        if not isinstance(got, (list, tuple)):
            return f"expected a {type(expect).__name__} of {len(expect)} items{at}, got {describe(got)}"
        if len(got) != len(expect):
            return f"expected {len(expect)} items{at}, got {len(got)}: {fmt(got)}"
        for i, (g, e) in enumerate(zip(got, expect)):
            msg = compare(g, e, atol, rtol, f"{where}[{i}]")
            if msg:
                return msg
        return None
    if isinstance(expect, dict):
        if not isinstance(got, dict):
            return f"expected a dict with keys {sorted(expect)}{at}, got {describe(got)}"
        if set(got) != set(expect):
            missing, extra = sorted(set(expect) - set(got)), sorted(set(got) - set(expect))
            return (f"expected the keys {sorted(expect)}{at}"
                    + (f"; missing {missing}" if missing else "") + (f"; unexpected {extra}" if extra else ""))
        for k in expect:
            msg = compare(got[k], expect[k], atol, rtol, f"{where}[{k!r}]")
            if msg:
                return msg
        return None
    raise DataError(f"cannot compare with a reference of type {type(expect).__name__}")
