"""Format ``"pitts"``: Pittsburgh 30k/250k in the NetVLAD convention (Relja/netvlad ``dbStruct`` ``.mat``).

``root`` is a ``dbStruct`` ``.mat`` file (e.g. ``pitts30k_test.mat``), read *by position* exactly as
pytorch-NetVlad does (0 whichSet, 1 dbImageFns, 2 utmDb (2xN), 3 qImageFns, 4 utmQ, 5 numImages,
6 numQueries, 7 posDistThr, 8 posDistSqThr, 9 nonTrivPosDistSqThr). Database images live under
``images_root/<dbImageFn>`` (folders ``000`` ... ``010``) and queries under
``images_root/queries_real/<qImageFn>``; ``images_root`` defaults to the parent of the ``datasets/``
folder that holds the ``.mat``. Positives: ``posDistThr`` (25 m); training positives:
``sqrt(nonTrivPosDistSqThr)`` (10 m). Recall@N over all queries (pytorch-NetVlad).
"""
from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np

from ._parsing import duplicates
from .geotags import CITY_SPAN_M, check_utm, warn_far_from_median
from .split import GeoSplit, check_image_files

_PITTS_FIELDS = ("whichSet", "dbImageFns", "utmDb", "qImageFns", "utmQ", "numImages", "numQueries",
                 "posDistThr", "posDistSqThr", "nonTrivPosDistSqThr")


def _mat_strings(cell, path, fld: str) -> list[str]:
    arr = np.asarray(cell)
    if arr.dtype.kind in "US":  # a char matrix (one name per row) instead of a cell array
        return [str(s).strip() for s in arr.reshape(-1)]
    if arr.dtype != object:
        raise ValueError(f"{path}: dbStruct field {fld} must be a cell array of file names, got dtype {arr.dtype}")
    out = []
    for i, f in enumerate(arr.reshape(-1)):
        v = np.asarray(f).reshape(-1)
        if v.size != 1 or v.dtype.kind not in "US":
            raise ValueError(f"{path}: dbStruct field {fld}, entry {i} is not a file name string")
        out.append(str(v[0]))
    return out


def _mat_scalar(value, path, fld: str) -> float:
    arr = np.asarray(value)
    if arr.size != 1 or arr.dtype.kind not in "iuf":
        raise ValueError(f"{path}: dbStruct field {fld} must be one number, got {arr.dtype} of shape {arr.shape}")
    v = float(arr.reshape(-1)[0])
    if not np.isfinite(v):
        raise ValueError(f"{path}: dbStruct field {fld} is {v}")
    return v


def _mat_utm(value, n: int, path, fld: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{path}: dbStruct field {fld} must be a numeric 2xN UTM array, got dtype {arr.dtype}")
    if arr.shape == (2, n):
        utm = arr.T.astype(np.float64)
    elif n == 0 and arr.size == 0:
        utm = np.zeros((0, 2))
    else:
        raise ValueError(f"{path}: dbStruct field {fld} must be 2x{n} (UTM easting/northing of each image), "
                         f"got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(utm).all(axis=1))
    if len(bad):
        raise ValueError(f"{path}: dbStruct field {fld} has NaN/inf UTM for {len(bad)} image(s), first column {bad[0]}")
    return np.ascontiguousarray(utm)


def _check_geotags(path: Path, db_names: list, db_utm: np.ndarray, q_names: list, q_utm: np.ndarray) -> None:
    """ValueError for an impossible UTM position (:func:`~vpr_nb.datasets.geotags.check_utm`), a warning for
    an image more than :data:`~vpr_nb.datasets.geotags.CITY_SPAN_M` from the dataset's median (one city)."""
    for fld, utm, names in (("2 (utmDb)", db_utm, db_names), ("4 (utmQ)", q_utm, q_names)):
        check_utm(utm, lambda i, _, fld=fld, names=names: f"{path}: dbStruct field {fld}, entry {i} ({names[i]})",
                  swap_hint=f"{fld[3:-1]} rows swapped? (the first row must hold the eastings, the second the "
                            f"northings)")
    names = db_names + [f"queries_real/{n}" for n in q_names]
    warn_far_from_median(np.concatenate([db_utm, q_utm]), np.full(len(names), "Pittsburgh"), CITY_SPAN_M,
                         f"{path}", lambda i: names[i], what="city", stacklevel=4)


def load_pitts(mat_path, *, images_root=None, check_files: bool = True) -> GeoSplit:
    """Load a NetVLAD ``dbStruct`` ``.mat`` (Pitts30k/250k train/val/test), read by position.

    Fields (Relja/netvlad ``dbBase.m``): 0 whichSet, 1 dbImageFns, 2 utmDb (2 x numDb), 3 qImageFns,
    4 utmQ, 5 numImages, 6 numQueries, 7 posDistThr (25 m), 8 posDistSqThr (= posDistThr^2),
    9 nonTrivPosDistSqThr (100 m^2, i.e. 10 m training positives). ``pos_radius = posDistThr``,
    ``train_pos_radius = sqrt(nonTrivPosDistSqThr)``. Note the original MATLAB training positives
    also exclude database images within 1 m (``1 < d^2 <= nonTrivPosDistSqThr``); pytorch-NetVlad does not.
    An impossible UTM position (e.g. utmDb's rows swapped) raises ValueError naming the entry; an image
    more than 100 km from the others' median is named in a warning (:mod:`vpr_nb.datasets.geotags`).
    """
    from scipy.io import loadmat

    path = Path(mat_path)
    if not path.is_file():
        raise FileNotFoundError(f"Pittsburgh dbStruct file not found: {path} (e.g. datasets/pitts30k_test.mat)")
    try:
        mat = loadmat(str(path))
    except NotImplementedError:
        raise ValueError(f"{path}: a MATLAB v7.3 (HDF5) file; save it as -v7 or earlier for scipy.io.loadmat") from None
    except Exception as exc:
        raise ValueError(f"{path}: not a readable MATLAB .mat file ({exc})") from None
    if "dbStruct" not in mat:
        keys = [k for k in mat if not k.startswith("__")]
        raise ValueError(f"{path}: no variable 'dbStruct' (found {keys}); expected the NetVLAD dataset struct")
    st = np.asarray(mat["dbStruct"])
    if st.dtype.names is None or st.size != 1:
        raise ValueError(f"{path}: 'dbStruct' must be a 1x1 MATLAB struct, got dtype {st.dtype} shape {st.shape}")
    fields = st.reshape(-1)[0]
    if len(fields) < len(_PITTS_FIELDS):
        raise ValueError(f"{path}: dbStruct has {len(fields)} fields {st.dtype.names}, expected at least "
                         f"{len(_PITTS_FIELDS)} in the order {_PITTS_FIELDS}")
    which = np.asarray(fields[0]).reshape(-1)
    if which.size != 1 or which.dtype.kind not in "US":
        raise ValueError(f"{path}: dbStruct field 0 (whichSet) must be a string like 'test'")
    which_set = str(which[0])
    db_names = _mat_strings(fields[1], path, "1 (dbImageFns)")
    q_names = _mat_strings(fields[3], path, "3 (qImageFns)")
    for fld, names in (("1 (dbImageFns)", db_names), ("3 (qImageFns)", q_names)):
        if not names:
            raise ValueError(f"{path}: dbStruct field {fld} lists no image; a split needs database images and "
                             f"queries (is this the right .mat?)")
        dup = duplicates(names)
        if dup:
            name, rows = next(iter(dup.items()))
            raise ValueError(f"{path}: dbStruct field {fld} lists {len(dup)} image(s) more than once, e.g. {name!r} "
                             f"at entries {[r - 1 for r in rows]}; each image must be listed once")
    db_utm = _mat_utm(fields[2], len(db_names), path, "2 (utmDb)")
    q_utm = _mat_utm(fields[4], len(q_names), path, "4 (utmQ)")
    _check_geotags(path, db_names, db_utm, q_names, q_utm)
    num_db = _mat_scalar(fields[5], path, "5 (numImages)")
    num_q = _mat_scalar(fields[6], path, "6 (numQueries)")
    pos_thr = _mat_scalar(fields[7], path, "7 (posDistThr)")
    pos_sq = _mat_scalar(fields[8], path, "8 (posDistSqThr)")
    nontriv_sq = _mat_scalar(fields[9], path, "9 (nonTrivPosDistSqThr)")
    if pos_thr <= 0 or nontriv_sq <= 0:
        raise ValueError(f"{path}: posDistThr ({pos_thr}) and nonTrivPosDistSqThr ({nontriv_sq}) must be positive")
    if not np.isclose(pos_sq, pos_thr ** 2):
        raise ValueError(f"{path}: posDistSqThr={pos_sq} is not posDistThr^2={pos_thr ** 2}; "
                         f"the struct is inconsistent")
    if (num_db, num_q) != (len(db_names), len(q_names)):
        # Relja's dbLoad() recomputes both counts from the name lists, so we do the same.
        warnings.warn(f"{path}: numImages/numQueries = {num_db:g}/{num_q:g} but the struct lists "
                      f"{len(db_names)}/{len(q_names)} images; using the lists", stacklevel=3)
    if images_root is None:
        if path.parent.name != "datasets":
            raise ValueError(f"{path} is not inside a 'datasets/' folder, so the Pittsburgh images folder "
                             f"cannot be guessed; pass images_root= (the folder holding 000..010 and queries_real/)")
        images_root = path.parent.parent
    images_root = Path(images_root).resolve()
    if not images_root.is_dir():
        raise FileNotFoundError(f"Pittsburgh images_root not found: {images_root}")
    db_paths = [str(images_root / n) for n in db_names]
    q_paths = [str(images_root / "queries_real" / n) for n in q_names]
    extras = {"whichSet": which_set, "dataset": "pitts250k" if "250k" in path.name else "pitts30k",
              "mat_file": str(path.resolve()), "images_root": str(images_root)}
    yaw = re.compile(r"_pitch(\d+)_yaw(\d+)\.")
    for side, names in (("db", db_names), ("q", q_names)):
        m = [yaw.search(n) for n in names]
        if names and all(m):
            extras[f"{side}_pitch"] = np.array([int(x.group(1)) for x in m], dtype=np.int64)
            extras[f"{side}_yaw"] = np.array([int(x.group(2)) for x in m], dtype=np.int64)
    split = GeoSplit(name=path.stem, format="pitts", db_paths=db_paths, q_paths=q_paths, db_utm=db_utm,
                     q_utm=q_utm, pos_radius=pos_thr, train_pos_radius=math.sqrt(nontriv_sq), extras=extras)
    if check_files:
        check_image_files(db_paths + q_paths, f"{path.name} (images under {images_root})")
    return split


PITTS_SETS = ("pitts30k", "pitts250k")


def load_part(root, part: str, *, pitts_set: str = "pitts30k", check_files: bool = True) -> GeoSplit:
    """Part ``train`` / ``val`` / ``test`` of Pittsburgh under ``root`` (the folder holding ``datasets/``):
    ``datasets/<pitts_set>_<part>.mat`` (``pitts_set`` one of :data:`PITTS_SETS`)."""
    return load_pitts(Path(root) / "datasets" / f"{pitts_set}_{part}.mat", check_files=check_files)

__all__ = ['load_pitts', 'load_part', 'PITTS_SETS']
