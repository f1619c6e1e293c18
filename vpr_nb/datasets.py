"""Loaders for the real VPR datasets, all returning one geotagged split object, :class:`GeoSplit`.

One entry point, :func:`load` ``(root, format)``, with ``format`` one of

``"pitts"``
    Pittsburgh 30k/250k in the NetVLAD convention: ``root`` is a ``dbStruct`` ``.mat`` file
    (e.g. ``pitts30k_test.mat``), read *by position* exactly as pytorch-NetVlad does
    (0 whichSet, 1 dbImageFns, 2 utmDb (2xN), 3 qImageFns, 4 utmQ, 5 numImages, 6 numQueries,
    7 posDistThr, 8 posDistSqThr, 9 nonTrivPosDistSqThr). Database images live under
    ``images_root/<dbImageFn>`` (folders ``000`` ... ``010``) and queries under
    ``images_root/queries_real/<qImageFn>``; ``images_root`` defaults to the parent of the
    ``datasets/`` folder that holds the ``.mat``. Positives: ``posDistThr`` (25 m); training
    positives: ``sqrt(nonTrivPosDistSqThr)`` (10 m).
``"gmberton"``
    The VPR-datasets-downloader layout ``images/<split>/{database,queries}/@east@north@zone@...@.jpg``
    (Pitts30k, MSLS, Nordland, Tokyo 24/7, SF-XL, SPED...). UTM east/north are fields 1 and 2 of
    ``name.split("@")``, the heading field 9. Positives 25 m, training positives 10 m.
``"msls"``
    Mapillary SLS ``train_val/<city>/{database,query}/{raw.csv,postprocessed.csv}`` (CSV files with
    the leading pandas index column). Panoramas are excluded by default (as the official code);
    ``unique_cluster`` is kept in ``db_place``/``q_place`` for CliqueMining; ``val_subset="official"``
    reproduces the official 740-query MSLS-val selection (see :func:`load_msls`).
``"gsv-cities"``
    GSV-Cities ``Dataframes/<city>.csv`` + ``Images/<city_id>/<name>.jpg``; places with at least
    ``min_img_per_place`` (4) images. A training set: every image is a database image, grouped
    by place (no queries, no positives radius).
``"nordland"``
    Nordland with frame-index ground truth: by default the +-1 frame convention of the VPR-Bench /
    GSV-Cities "Nordland*" test set (``protocol="1frame"``), or the gmberton 25 m = +-10 frames one
    (``protocol="25m"``). Positions are dummy UTM coordinates along one line, spaced so that the
    radius search of every other dataset gives exactly the frame tolerance.

Every loader checks that each listed image exists (``check_files=True``, one stat per file) and
names the first missing file; malformed inputs raise ``ValueError`` naming the file and field.

:class:`ImageDataset` reads the images with Pillow, resizes and ImageNet-normalises them with torch
ops (no torchvision) for :func:`torch.utils.data.DataLoader`.
"""
from __future__ import annotations

import csv
import inspect
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ._checks import check_int, check_positive
from .evaluation import IMAGENET_MEAN, IMAGENET_STD, positives_within

FORMATS = ("pitts", "gmberton", "msls", "gsv-cities", "nordland")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")

# mapillary_sls msls.py ``default_cities`` (also copied in gmberton's format_mapillary.py)
MSLS_CITIES = {
    "train": ("trondheim", "london", "boston", "melbourne", "amsterdam", "helsinki", "tokyo", "toronto",
              "saopaulo", "moscow", "zurich", "paris", "bangkok", "budapest", "austin", "berlin", "ottawa",
              "phoenix", "goa", "amman", "nairobi", "manila"),
    "val": ("cph", "sf"),
}

# Nordland: gmberton's download_nordland.py places frames on a line, DISTANCE = 25 m / (frames + 0.5)
NORDLAND_PROTOCOLS = {"1frame": 1, "25m": 10}


# ----------------------------------------------------------------------------------------------
# The common split object
# ----------------------------------------------------------------------------------------------
@dataclass(eq=False)
class GeoSplit:
    """A geotagged database/query split of a real dataset (images stay on disk).

    ``db_paths``/``q_paths`` are absolute image paths (str); ``db_utm``/``q_utm`` float64 (N, 2)
    (easting, northing) in metres; ``pos_radius`` is the evaluation positives radius (a database
    image is a positive of a query when ``||utm_q - utm_db|| <= pos_radius``) and
    ``train_pos_radius`` the training-positives radius, ``None`` where the format does not define
    one. Optional per-image fields are ``None`` when the format does not have them:
    ``*_heading`` (degrees), ``*_place`` (place / cluster id: GSV-Cities place, MSLS
    ``unique_cluster``, -1 = none) and ``*_region`` (city names: positives are only searched inside
    one region, because UTM coordinates of different zones are not comparable). ``extras`` holds
    the format-specific rest (Nordland frame indices, MSLS night/view direction, UTM zones...).
    """

    name: str
    format: str
    db_paths: list
    q_paths: list
    db_utm: np.ndarray
    q_utm: np.ndarray
    pos_radius: float | None
    train_pos_radius: float | None = None
    db_heading: np.ndarray | None = None
    q_heading: np.ndarray | None = None
    db_place: np.ndarray | None = None
    q_place: np.ndarray | None = None
    db_region: np.ndarray | None = None
    q_region: np.ndarray | None = None
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for side in ("db", "q"):
            paths = getattr(self, f"{side}_paths")
            n = len(paths)
            utm = np.asarray(getattr(self, f"{side}_utm"), dtype=np.float64).reshape(-1, 2)
            if utm.shape[0] != n:
                raise ValueError(f"{self.name}: {side}_utm has {utm.shape[0]} rows but {n} {side} paths")
            if not np.isfinite(utm).all():
                bad = int(np.flatnonzero(~np.isfinite(utm).all(axis=1))[0])
                raise ValueError(f"{self.name}: {side}_utm is NaN/inf for {paths[bad]}; every image needs a geotag")
            setattr(self, f"{side}_utm", utm)
            for extra in ("heading", "place", "region"):
                v = getattr(self, f"{side}_{extra}")
                if v is not None and len(v) != n:
                    raise ValueError(f"{self.name}: {side}_{extra} has {len(v)} entries but {n} {side} paths")

    @property
    def num_db(self) -> int:
        return len(self.db_paths)

    @property
    def num_q(self) -> int:
        return len(self.q_paths)

    def __len__(self) -> int:
        return self.num_db + self.num_q

    def __repr__(self) -> str:
        r = "-" if self.pos_radius is None else f"{self.pos_radius:g} m"
        return f"GeoSplit({self.name!r}, format={self.format!r}, db={self.num_db}, queries={self.num_q}, pos_radius={r})"

    def positives(self, radius: float | None = None) -> list[np.ndarray]:
        """Database indices within ``radius`` (default ``pos_radius``) of each query, sorted.

        The radius search of NetVLAD / gmberton / SALAD evaluation (``||x_q - x_db||_2 <= r``), done
        per region when ``*_region`` is set.
        """
        if self.num_q == 0:
            raise ValueError(f"{self.name} has no queries (a training-only set); positives need queries")
        r = self.pos_radius if radius is None else radius
        if r is None:
            raise ValueError(f"{self.name} defines no positives radius; pass radius=... in metres")
        if self.db_region is None or self.q_region is None:
            return positives_within(self.db_utm, self.q_utm, r)
        out: list[np.ndarray] = [np.zeros(0, np.int64)] * self.num_q
        db_region, q_region = np.asarray(self.db_region), np.asarray(self.q_region)
        for reg in np.unique(q_region):
            qi = np.flatnonzero(q_region == reg)
            di = np.flatnonzero(db_region == reg)
            if len(di) == 0:
                continue
            for i, hit in zip(qi, positives_within(self.db_utm[di], self.q_utm[qi], r)):
                out[i] = di[hit]
        return out

    def check_files(self) -> None:
        """Stat every listed image; raise FileNotFoundError naming the first missing one."""
        _check_files(self.db_paths + self.q_paths, self.name)

    def image_dataset(self, which: str = "all", size=None) -> "ImageDataset":
        """An :class:`ImageDataset` over the database (``"db"``), queries (``"q"``) or both (``"all"``,
        database first, so index ``i >= num_db`` is query ``i - num_db`` as in pytorch-NetVlad)."""
        paths = {"db": self.db_paths, "q": self.q_paths, "all": self.db_paths + self.q_paths}
        if which not in paths:
            raise ValueError(f"which must be 'db', 'q' or 'all', got {which!r}")
        return ImageDataset(paths[which], size=size)


def _check_files(paths: Sequence[str], what: str) -> None:
    missing = 0
    first = None
    for p in paths:
        if not os.path.isfile(p):
            missing += 1
            if first is None:
                first = p
    if missing:
        raise FileNotFoundError(f"{what}: {missing} listed image(s) are missing, first: {first} "
                                f"(fix the images folder, or pass check_files=False to skip this check)")


# ----------------------------------------------------------------------------------------------
# Image reading
# ----------------------------------------------------------------------------------------------
def _as_size(size) -> tuple[int, int] | None:
    if size is None:
        return None
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (int(size), int(size))
    try:
        h, w = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be None, an int or (height, width), got {size!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive, got {(h, w)}")
    return h, w


def read_image(path, size=None, normalize: bool = True) -> torch.Tensor:
    """Read one image with Pillow as a float (3, H, W) tensor.

    Pixels are scaled to [0, 1], optionally resized to ``size`` = (H, W) with antialiased bilinear
    interpolation (``F.interpolate``), then normalised with the ImageNet statistics
    ``x' = (x - mean) / std`` (mean = (0.485, 0.456, 0.406), std = (0.229, 0.224, 0.225)).
    """
    from PIL import Image, UnidentifiedImageError

    size = _as_size(size)
    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"cannot read image {path}: {exc}") from None
    x = torch.from_numpy(arr.copy()).permute(2, 0, 1).float().div_(255.0)
    if size is not None and tuple(x.shape[1:]) != size:
        x = F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=True)[0]
    if normalize:
        x = (x - torch.tensor(IMAGENET_MEAN).view(3, 1, 1)) / torch.tensor(IMAGENET_STD).view(3, 1, 1)
    return x


class ImageDataset(torch.utils.data.Dataset):
    """A torch Dataset of image files: item ``i`` is ``(image (3, H, W) float tensor, i)``.

    Reading with Pillow, resizing and normalisation as :func:`read_image`. Without ``size`` images
    keep their native resolution (pytorch-NetVlad feeds Pittsburgh at 640x480), so batch them only if
    they share one size.
    """

    def __init__(self, paths: Sequence, size=None, normalize: bool = True):
        if isinstance(paths, (str, os.PathLike)):
            raise ValueError("paths must be a sequence of image paths, not a single path")
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ValueError("paths is empty: an ImageDataset needs at least one image")
        self.size = _as_size(size)
        self.normalize = bool(normalize)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int):
        if not -len(self.paths) <= index < len(self.paths):
            raise IndexError(f"index {index} out of range for {len(self.paths)} images")
        return read_image(self.paths[index], self.size, self.normalize), int(index) % len(self.paths)


# ----------------------------------------------------------------------------------------------
# lat/lon -> UTM (WGS84), for GSV-Cities
# ----------------------------------------------------------------------------------------------
_WGS84_A = 6378137.0
_WGS84_F = 1 / 298.257223563


def utm_zone(lat: float, lon: float) -> int:
    """UTM zone number of a WGS84 position, with the Norway (32V) and Svalbard (31X-37X) exceptions."""
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat < 84.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9 else 33 if lon < 21 else 35 if lon < 33 else 37
    return zone


def latlon_to_utm(lat, lon, zone: int | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Project WGS84 latitude/longitude (degrees) to UTM easting/northing (metres).

    Transverse Mercator with Krüger's series to third order in the third flattening n
    (Karney 2011, eqs. 7-9, 11): t = sinh(atanh(sin phi) - e atanh(e sin phi)),
    xi' = atan(t / cos dlambda), eta' = atanh(sin dlambda / sqrt(1 + t^2)),
    E = E0 + k0 A (eta' + sum_j alpha_j cos(2j xi') sinh(2j eta')),
    N = N0 + k0 A (xi' + sum_j alpha_j sin(2j xi') cosh(2j eta')), k0 = 0.9996, E0 = 500 km,
    N0 = 10 000 km south of the equator. Millimetre-accurate inside a zone.
    All points are projected in one ``zone`` (default: the zone of their mean position), so that
    distances between them stay metric even if they straddle a zone edge.
    Returns ``(easting, northing, zone)``.
    """
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if lat.shape != lon.shape:
        raise ValueError(f"lat and lon must have the same shape, got {lat.shape} and {lon.shape}")
    if not (np.isfinite(lat).all() and np.isfinite(lon).all()):
        raise ValueError("lat/lon contain NaN or inf")
    if (np.abs(lat) > 84.0).any() or (np.abs(lon) > 180.0).any():
        raise ValueError("lat must be within [-84, 84] and lon within [-180, 180] degrees for UTM")
    if zone is None:
        zone = utm_zone(float(lat.mean()), float(lon.mean()))
    zone = check_int(zone, "zone", minimum=1, maximum=60)
    f = _WGS84_F
    n = f / (2 - f)
    e = 2 * math.sqrt(n) / (1 + n)
    big_a = _WGS84_A / (1 + n) * (1 + n ** 2 / 4 + n ** 4 / 64)
    alpha = (n / 2 - 2 * n ** 2 / 3 + 5 * n ** 3 / 16, 13 * n ** 2 / 48 - 3 * n ** 3 / 5, 61 * n ** 3 / 240)
    phi = np.radians(lat)
    dlam = np.radians(lon - (6 * zone - 183))
    t = np.sinh(np.arctanh(np.sin(phi)) - e * np.arctanh(e * np.sin(phi)))
    xi = np.arctan2(t, np.cos(dlam))
    eta = np.arctanh(np.sin(dlam) / np.sqrt(1 + t ** 2))
    sx, sy = xi.copy(), eta.copy()
    for j, a in enumerate(alpha, start=1):
        sx += a * np.sin(2 * j * xi) * np.cosh(2 * j * eta)
        sy += a * np.cos(2 * j * xi) * np.sinh(2 * j * eta)
    k0 = 0.9996
    easting = 500000.0 + k0 * big_a * sy
    northing = k0 * big_a * sx + np.where(lat < 0, 10000000.0, 0.0)
    return easting, northing, zone


# ----------------------------------------------------------------------------------------------
# small parsing helpers
# ----------------------------------------------------------------------------------------------
def _read_csv(path: Path, required: Sequence[str]) -> tuple[list[str], dict[str, list[str]]]:
    """Read a CSV (leading unnamed pandas index column allowed) into columns of strings."""
    if not path.is_file():
        raise FileNotFoundError(f"CSV file not found: {path}")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows or not any(h.strip() for h in rows[0]):
        raise ValueError(f"{path}: empty CSV file (no header)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; header is {header}")
    cols: dict[str, list[str]] = {h: [] for h in header if h}
    for line_no, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(header):
            raise ValueError(f"{path}, line {line_no}: {len(row)} fields but the header has {len(header)}")
        for h, v in zip(header, row):
            if h:
                cols[h].append(v.strip())
    return header, cols


def _floats(values: Sequence[str], path, column: str) -> np.ndarray:
    out = np.empty(len(values), dtype=np.float64)
    for i, v in enumerate(values):
        try:
            out[i] = float(v)
        except ValueError:
            raise ValueError(f"{path}: column {column!r}, data row {i + 1}: {v!r} is not a number") from None
    bad = np.flatnonzero(~np.isfinite(out))
    if len(bad):
        raise ValueError(f"{path}: column {column!r} is NaN/inf in {len(bad)} row(s), first data row "
                         f"{bad[0] + 1}; every image needs a valid geotag (drop those rows)")
    return out


def _bools(values: Sequence[str], path, column: str) -> np.ndarray:
    table = {"true": True, "false": False, "1": True, "0": False, "1.0": True, "0.0": False}
    try:
        return np.array([table[v.lower()] for v in values], dtype=bool)
    except KeyError as exc:
        raise ValueError(f"{path}: column {column!r} must be True/False, got {exc.args[0]!r}") from None


def _list_images(folder: Path, suffixes: Sequence[str] | None = None) -> list[Path]:
    """Image files under ``folder`` (recursive, sorted). ``suffixes=None``: any of IMAGE_SUFFIXES in any
    case; otherwise exactly these (case-sensitive, as ``glob('**/*.jpg')``), other images are skipped
    with a warning that counts them."""
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder not found: {folder}")
    every = [p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and not p.is_dir()]
    if suffixes is None:
        files = sorted(every)
    else:
        files = sorted(p for p in every if p.suffix in suffixes)
        stray = len(every) - len(files)
        if stray:
            warnings.warn(f"{folder}: {stray} image file(s) not named *{'/*'.join(suffixes)} are ignored, "
                          f"as the reference code does (e.g. {next(p.name for p in every if p.suffix not in suffixes)})",
                          stacklevel=3)
    if not files:
        raise ValueError(f"no images ({', '.join(suffixes or IMAGE_SUFFIXES)}) found under {folder}")
    return files


# ----------------------------------------------------------------------------------------------
# Pittsburgh (NetVLAD dbStruct .mat)
# ----------------------------------------------------------------------------------------------
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


def load_pitts(mat_path, *, images_root=None, check_files: bool = True) -> GeoSplit:
    """Load a NetVLAD ``dbStruct`` ``.mat`` (Pitts30k/250k train/val/test), read by position.

    Fields (Relja/netvlad ``dbBase.m``): 0 whichSet, 1 dbImageFns, 2 utmDb (2 x numDb), 3 qImageFns,
    4 utmQ, 5 numImages, 6 numQueries, 7 posDistThr (25 m), 8 posDistSqThr (= posDistThr^2),
    9 nonTrivPosDistSqThr (100 m^2, i.e. 10 m training positives). ``pos_radius = posDistThr``,
    ``train_pos_radius = sqrt(nonTrivPosDistSqThr)``. Note the original MATLAB training positives
    also exclude database images within 1 m (``1 < d^2 <= nonTrivPosDistSqThr``); pytorch-NetVlad does not.
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
    db_utm = _mat_utm(fields[2], len(db_names), path, "2 (utmDb)")
    q_utm = _mat_utm(fields[4], len(q_names), path, "4 (utmQ)")
    num_db = _mat_scalar(fields[5], path, "5 (numImages)")
    num_q = _mat_scalar(fields[6], path, "6 (numQueries)")
    pos_thr = _mat_scalar(fields[7], path, "7 (posDistThr)")
    pos_sq = _mat_scalar(fields[8], path, "8 (posDistSqThr)")
    nontriv_sq = _mat_scalar(fields[9], path, "9 (nonTrivPosDistSqThr)")
    if pos_thr <= 0 or nontriv_sq <= 0:
        raise ValueError(f"{path}: posDistThr ({pos_thr}) and nonTrivPosDistSqThr ({nontriv_sq}) must be positive")
    if not np.isclose(pos_sq, pos_thr ** 2):
        raise ValueError(f"{path}: posDistSqThr={pos_sq} is not posDistThr^2={pos_thr ** 2}; the struct is inconsistent")
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
        _check_files(db_paths + q_paths, f"{path.name} (images under {images_root})")
    return split


# ----------------------------------------------------------------------------------------------
# gmberton @-filename layout
# ----------------------------------------------------------------------------------------------
def parse_gmberton_name(path) -> dict:
    """Fields of a VPR-datasets-downloader name ``@east@north@zone@letter@lat@lon@pano@tile@heading@...@.jpg``.

    Returns ``{"east", "north", "zone", "letter", "pano_id", "heading", "note"}`` (heading None if
    empty); raises ValueError naming the file when east/north are missing or not finite.
    """
    name = Path(path).name
    parts = name.split("@")
    if len(parts) < 3:
        raise ValueError(f"{path}: not a gmberton '@' file name (expected @UTM_east@UTM_north@...@.jpg)")

    def num(i: int, label: str) -> float:
        try:
            v = float(parts[i])
        except ValueError:
            raise ValueError(f"{path}: field {i} ({label}) {parts[i]!r} is not a number") from None
        if not np.isfinite(v):
            raise ValueError(f"{path}: field {i} ({label}) is {parts[i]!r}; every image needs a valid UTM geotag")
        return v

    get = lambda i: parts[i] if len(parts) > i else ""  # noqa: E731
    heading = num(9, "heading") if get(9) else None
    return {"east": num(1, "UTM_east"), "north": num(2, "UTM_north"), "zone": get(3), "letter": get(4),
            "pano_id": get(7), "heading": heading, "note": get(14) if len(parts) > 15 else ""}


def _gmberton_split_dir(root: Path, split: str) -> Path:
    if (root / "database").is_dir() and (root / "queries").is_dir():
        return root
    for cand in (root / "images" / split, root / split):
        if (cand / "database").is_dir() and (cand / "queries").is_dir():
            return cand
    raise FileNotFoundError(f"{root}: expected images/{split}/{{database,queries}}/ (or database/ and queries/) "
                            f"in the gmberton VPR-datasets-downloader layout")


def load_gmberton(root, *, split: str = "test", pos_radius: float = 25.0, train_pos_radius: float = 10.0,
                  check_files: bool = True) -> GeoSplit:
    """Load a dataset formatted by gmberton's VPR-datasets-downloader.

    ``root`` is ``datasets/<name>`` (holding ``images/<split>/``) or the split folder itself. Images
    are found recursively and sorted (as the benchmark's ``sorted(glob('**/*.jpg'))``: only lower-case
    ``.jpg`` files count, stray ``.JPG``/``.png`` files are ignored with a warning); UTM east and
    north are fields 1 and 2 of the ``@``-split name. Positives within ``pos_radius`` (25 m,
    ``val_positive_dist_threshold``), training positives ``train_pos_radius`` (10 m).
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"gmberton dataset folder not found: {root}")
    pos_radius = check_positive(pos_radius, "pos_radius")
    train_pos_radius = check_positive(train_pos_radius, "train_pos_radius")
    sdir = _gmberton_split_dir(root, split).resolve()
    sides = {}
    for side, folder in (("db", "database"), ("q", "queries")):
        files = _list_images(sdir / folder, suffixes=(".jpg",))   # datasets_ws.py: sorted(glob("**/*.jpg"))
        parsed = [parse_gmberton_name(f) for f in files]
        sides[side] = (files, parsed)
    extras: dict = {"split_dir": str(sdir)}
    kw: dict = {}
    for side, (files, parsed) in sides.items():
        kw[f"{side}_utm"] = np.array([[p["east"], p["north"]] for p in parsed], dtype=np.float64)
        if all(p["heading"] is not None for p in parsed):
            kw[f"{side}_heading"] = np.array([p["heading"] for p in parsed], dtype=np.float64)
        extras[f"{side}_zone"] = np.array([p["zone"] + p["letter"] for p in parsed])
        extras[f"{side}_note"] = np.array([p["note"] for p in parsed])
        extras[f"{side}_pano_id"] = np.array([p["pano_id"] for p in parsed])
    name = f"{root.resolve().name}_{split}" if sdir != root.resolve() else sdir.name
    out = GeoSplit(name=name, format="gmberton", db_paths=[str(f) for f in sides["db"][0]],
                   q_paths=[str(f) for f in sides["q"][0]], pos_radius=pos_radius,
                   train_pos_radius=train_pos_radius, extras=extras, **kw)
    if check_files:  # catches broken symlinks (e.g. MSLS test -> val)
        out.check_files()
    return out


# ----------------------------------------------------------------------------------------------
# MSLS
# ----------------------------------------------------------------------------------------------
_MSLS_RAW = ("key", "lon", "lat", "ca", "captured_at", "pano")
_MSLS_POST = ("key", "easting", "northing", "unique_cluster", "night", "view_direction")


def _read_key_list(path) -> set[str]:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"query key list not found: {p}")
    if p.suffix == ".npy":
        arr = np.load(p, allow_pickle=False)
        items = [str(x) for x in arr.reshape(-1)]
    else:
        items = [ln.strip() for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
    if not items:
        raise ValueError(f"{p}: the query key list is empty")
    return {Path(s).stem for s in items}


def _msls_side(cdir: Path, side: str, exclude_panos: bool, subtask: str | None):
    folder = cdir / side
    _, post = _read_csv(folder / "postprocessed.csv", _MSLS_POST)
    _, raw = _read_csv(folder / "raw.csv", _MSLS_RAW)
    keys = post["key"]
    if sorted(keys) != sorted(raw["key"]):
        raise ValueError(f"{folder / 'raw.csv'}: its 'key' column does not list the same images as "
                         f"{folder / 'postprocessed.csv'}")
    raw_row = {k: i for i, k in enumerate(raw["key"])}
    ridx = np.array([raw_row[k] for k in keys], dtype=np.int64)
    pano = _bools(raw["pano"], folder / "raw.csv", "pano")[ridx] if keys else np.zeros(0, bool)
    utm = np.stack([_floats(post["easting"], folder / "postprocessed.csv", "easting"),
                    _floats(post["northing"], folder / "postprocessed.csv", "northing")], axis=1).reshape(-1, 2)
    cl = []
    for i, v in enumerate(post["unique_cluster"]):
        try:
            x = float(v) if v else float("nan")
        except ValueError:
            raise ValueError(f"{folder / 'postprocessed.csv'}: column 'unique_cluster', data row {i + 1}: "
                             f"{v!r} is not a number") from None
        cl.append(int(x) if np.isfinite(x) else -1)
    keep = ~pano if exclude_panos else np.ones(len(keys), bool)
    if subtask is not None:
        sub_path = folder / "subtask_index.csv"
        _, sub = _read_csv(sub_path, (subtask,))
        if len(sub[subtask]) != len(keys):
            raise ValueError(f"{sub_path}: {len(sub[subtask])} rows but postprocessed.csv has {len(keys)}")
        keep &= _bools(sub[subtask], sub_path, subtask)
    heading = _floats(raw["ca"], folder / "raw.csv", "ca")[ridx] if keys else np.zeros(0)
    night = _bools(post["night"], folder / "postprocessed.csv", "night") if keys else np.zeros(0, bool)
    paths = [str((folder / "images" / f"{k}.jpg").resolve()) for k in keys]
    sel = np.flatnonzero(keep)
    return {"paths": [paths[i] for i in sel], "keys": [keys[i] for i in sel], "utm": utm[sel],
            "heading": heading[sel], "place": np.asarray(cl, dtype=np.int64)[sel], "night": night[sel],
            "view": np.array(post["view_direction"], dtype=object)[sel].astype(str)}


def load_msls(root, *, cities=None, exclude_panos: bool = True, val_subset: str | None = None,
              query_keys=None, pos_radius: float = 25.0, train_pos_radius: float = 10.0,
              check_files: bool = True) -> GeoSplit:
    """Load Mapillary SLS ``train_val/<city>/{database,query}`` (CSV headers as shipped, with the
    leading pandas index column: ``,key,lon,lat,ca,captured_at,pano`` and
    ``,key,easting,northing,unique_cluster,control_panel,night,view_direction``).

    ``cities``: None (every city folder), ``"train"``/``"val"`` (the official lists of
    mapillary_sls ``msls.py``; val = cph, sf) or a list of names. Cities are concatenated in that order;
    positives are searched inside each city (``db_region``/``q_region``). ``unique_cluster`` restarts
    in every city, so a place is the pair (city, ``unique_cluster``): ``db_place``/``q_place`` number
    these pairs globally (-1 where the cluster is empty) and the raw ids are kept in
    ``extras["db_cluster"|"q_cluster"]``. Headings are the compass angle
    ``ca``. Defaults follow the official code: panoramas excluded, positives 25 m (``evaluate.py``
    threshold), training positives 10 m (``posDistThr``).

    ``val_subset="official"`` reproduces the official MSLS-val query set (740 queries on cph+sf):
    only frames flagged in ``subtask_index.csv`` column ``all`` (database and queries), panoramas
    excluded, and queries with at least one database image within ``pos_radius`` (25 m, the radius
    of GSV-Cities' ``msls_val_pIdx.npy``); 747 -> 740 queries on the real data. Alternatively
    ``query_keys`` = a path to the list used by others (a ``.txt`` with one key or image path per
    line, or a ``.npy`` of strings such as GSV-Cities ``msls_val_qImages.npy[msls_val_qIdx]``); the
    list is not shipped here, since it is not available offline, so pass its path.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"MSLS folder not found: {root}")
    tv = root if root.name == "train_val" else root / "train_val"
    if not tv.is_dir():
        raise FileNotFoundError(f"{root}: no train_val/ folder (expected <msls>/train_val/<city>/{{database,query}})")
    found = sorted(p.name for p in tv.iterdir() if p.is_dir())
    if cities is None:
        cities = found
    elif isinstance(cities, str):
        if cities not in MSLS_CITIES:
            raise ValueError(f"cities must be None, 'train', 'val' or a list of city names, got {cities!r}")
        cities = list(MSLS_CITIES[cities])
    cities = list(cities)
    if not cities:
        raise ValueError(f"{tv}: no city folders to load")
    missing = [c for c in cities if c not in found]
    if missing:
        raise FileNotFoundError(f"{tv}: city folder(s) {missing} not found (present: {found})")
    if val_subset not in (None, "official"):
        raise ValueError(f"val_subset must be None or 'official', got {val_subset!r}")
    if val_subset is not None and query_keys is not None:
        raise ValueError("pass either val_subset='official' or query_keys=<file>, not both")
    pos_radius = check_positive(pos_radius, "pos_radius")
    train_pos_radius = check_positive(train_pos_radius, "train_pos_radius")
    subtask = "all" if val_subset == "official" else None
    wanted = _read_key_list(query_keys) if query_keys is not None else None
    db_parts, q_parts = [], []
    for city in cities:
        db = _msls_side(tv / city, "database", exclude_panos, subtask)
        q = _msls_side(tv / city, "query", exclude_panos, subtask)
        if wanted is not None:
            sel = np.array([k in wanted for k in q["keys"]], dtype=bool)
            q = {k: ([v[i] for i in np.flatnonzero(sel)] if isinstance(v, list) else v[sel]) for k, v in q.items()}
        if val_subset == "official" and len(q["keys"]) and len(db["keys"]):
            has = np.array([len(p) > 0 for p in positives_within(db["utm"], q["utm"], pos_radius)], dtype=bool)
            q = {k: ([v[i] for i in np.flatnonzero(has)] if isinstance(v, list) else v[has]) for k, v in q.items()}
        elif val_subset == "official":
            q = {k: (v[:0] if not isinstance(v, list) else []) for k, v in q.items()}
        for part, lst in ((db, db_parts), (q, q_parts)):
            part["region"] = np.array([city] * len(part["keys"]), dtype=object).astype(str)
            lst.append(part)

    def cat(parts, k):
        vals = [p[k] for p in parts]
        return sum(vals, []) if isinstance(vals[0], list) else np.concatenate(vals)

    if wanted is not None:
        got = set(cat(q_parts, "keys"))
        if not got:
            raise ValueError(f"{query_keys}: none of its keys is a query of cities {cities}")
        if len(got) < len(wanted):
            warnings.warn(f"{query_keys}: {len(wanted) - len(got)} listed key(s) are not queries of {cities}",
                          stacklevel=3)
    # unique_cluster restarts in every city: a place is the pair (city, cluster), numbered globally
    db_cl, q_cl = cat(db_parts, "place"), cat(q_parts, "place")
    db_reg, q_reg = cat(db_parts, "region"), cat(q_parts, "region")
    cl_all, reg_all = np.concatenate([db_cl, q_cl]), np.concatenate([db_reg, q_reg])
    place_all = np.full(len(cl_all), -1, dtype=np.int64)
    has = cl_all >= 0
    if has.any():
        pair = np.char.add(np.char.add(reg_all[has].astype(str), ":"), cl_all[has].astype(str))
        place_all[has] = np.unique(pair, return_inverse=True)[1].reshape(-1)
    db_place, q_place = place_all[:len(db_cl)], place_all[len(db_cl):]
    extras = {"cities": cities, "db_key": cat(db_parts, "keys"), "q_key": cat(q_parts, "keys"),
              "db_cluster": db_cl, "q_cluster": q_cl,
              "db_night": cat(db_parts, "night"), "q_night": cat(q_parts, "night"),
              "db_view_direction": cat(db_parts, "view"), "q_view_direction": cat(q_parts, "view"),
              "val_subset": val_subset, "exclude_panos": exclude_panos}
    name = "msls_" + ("val" if sorted(cities) == sorted(MSLS_CITIES["val"]) else "+".join(cities))
    out = GeoSplit(name=name, format="msls", db_paths=cat(db_parts, "paths"), q_paths=cat(q_parts, "paths"),
                   db_utm=cat(db_parts, "utm"), q_utm=cat(q_parts, "utm"), pos_radius=pos_radius,
                   train_pos_radius=train_pos_radius, db_heading=cat(db_parts, "heading"),
                   q_heading=cat(q_parts, "heading"), db_place=db_place, q_place=q_place,
                   db_region=db_reg, q_region=q_reg, extras=extras)
    if check_files:
        out.check_files()
    return out


# ----------------------------------------------------------------------------------------------
# GSV-Cities
# ----------------------------------------------------------------------------------------------
_GSV_COLS = ("place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid")


def gsv_image_name(city_id: str, place_id: int, year: int, month: int, northdeg: int, lat: float, lon: float,
                   panoid: str) -> str:
    """GSV-Cities file name: ``{city}_{place:07d}_{year}_{month:02d}_{northdeg:03d}_{lat}_{lon}_{panoid}.jpg``
    (lat/lon written as Python writes the floats, as ``GSVCitiesDataset.get_img_name`` does)."""
    return (f"{city_id}_{str(int(place_id)).zfill(7)}_{int(year)}_{str(int(month)).zfill(2)}_"
            f"{str(int(northdeg)).zfill(3)}_{float(lat)}_{float(lon)}_{panoid}.jpg")


def load_gsv_cities(root, *, cities=None, min_img_per_place: int = 4, images_root=None,
                    check_files: bool = True) -> GeoSplit:
    """Load GSV-Cities: ``Dataframes/<city>.csv`` (columns place_id, year, month, northdeg, city_id,
    lat, lon, panoid) and ``Images/<city_id>/<gsv_image_name>``.

    Places with fewer than ``min_img_per_place`` images are dropped (``groupby('place_id')
    .transform('size') >= min_img_per_place`` in GSVCitiesDataset). The i-th city's place ids are offset
    by ``i * 10**5`` as in that code, giving global ``db_place`` labels. A training set: every image is a
    database image, there are no queries and no positives radius. lat/lon are projected to UTM per city
    (one zone per city, :func:`latlon_to_utm`); ``db_region`` is the city.
    """
    root = Path(root)
    dfdir = root / "Dataframes"
    if not dfdir.is_dir():
        raise FileNotFoundError(f"{root}: no Dataframes/ folder (expected GSV-Cities Dataframes/<city>.csv)")
    found = sorted(p.stem for p in dfdir.glob("*.csv"))
    if cities is None:
        cities = found
    cities = [cities] if isinstance(cities, str) else list(cities)
    if not cities:
        raise ValueError(f"{dfdir}: no city CSV files")
    missing = [c for c in cities if c not in found]
    if missing:
        raise FileNotFoundError(f"{dfdir}: no CSV for city(ies) {missing} (present: {found})")
    min_img_per_place = check_int(min_img_per_place, "min_img_per_place", minimum=1)
    img_root = Path(images_root) if images_root is not None else root
    img_root = img_root.resolve()
    paths: list[str] = []
    utm, heading, place, region, zones, years = [], [], [], [], {}, []
    for ci, city in enumerate(cities):
        path = dfdir / f"{city}.csv"
        _, df = _read_csv(path, _GSV_COLS)
        n = len(df["place_id"])
        if n == 0:
            continue
        ints = {}
        for c in ("place_id", "year", "month", "northdeg"):
            v = _floats(df[c], path, c)
            if (v != np.round(v)).any():
                raise ValueError(f"{path}: column {c!r} must hold integers")
            ints[c] = v.astype(np.int64)
        lat, lon = _floats(df["lat"], path, "lat"), _floats(df["lon"], path, "lon")
        ids, counts = np.unique(ints["place_id"], return_counts=True)
        big = set(ids[counts >= min_img_per_place].tolist())
        keep = np.array([p in big for p in ints["place_id"]], dtype=bool)
        if not keep.any():
            continue
        e, nth, zone = latlon_to_utm(lat[keep], lon[keep])
        zones[city] = zone
        for i in np.flatnonzero(keep):
            name = gsv_image_name(df["city_id"][i], ints["place_id"][i], ints["year"][i], ints["month"][i],
                                  ints["northdeg"][i], df["lat"][i], df["lon"][i], df["panoid"][i])
            paths.append(str(img_root / "Images" / df["city_id"][i] / name))
        utm.append(np.stack([e, nth], axis=1))
        heading.append(ints["northdeg"][keep].astype(np.float64))
        place.append(ints["place_id"][keep] + ci * 10 ** 5)
        region.append(np.array([city] * int(keep.sum())))
        years.append(ints["year"][keep] * 100 + ints["month"][keep])
    if not paths:
        raise ValueError(f"{dfdir}: no place of cities {cities} has >= {min_img_per_place} images")
    out = GeoSplit(name="gsv-cities", format="gsv-cities", db_paths=paths, q_paths=[],
                   db_utm=np.concatenate(utm), q_utm=np.zeros((0, 2)), pos_radius=None, train_pos_radius=None,
                   db_heading=np.concatenate(heading), db_place=np.concatenate(place),
                   db_region=np.concatenate(region),
                   extras={"cities": cities, "utm_zone": zones, "db_yearmonth": np.concatenate(years),
                           "min_img_per_place": min_img_per_place})
    if check_files:
        out.check_files()
    return out


# ----------------------------------------------------------------------------------------------
# Nordland
# ----------------------------------------------------------------------------------------------
def _frame_of(path: Path) -> int:
    name = path.name
    if "@" in name:
        parts = name.split("@")
        v = parts[7] if len(parts) > 7 else ""  # gmberton: pano_id slot holds the frame number
        if not v.isdigit():
            raise ValueError(f"{path}: field 7 (frame number) {v!r} of the gmberton Nordland name is not an integer")
        return int(v)
    nums = re.findall(r"\d+", path.stem)
    if not nums:
        raise ValueError(f"{path}: no frame number in the file name (expected e.g. 0000123.jpg or image-00123.png)")
    return int(nums[-1])


def load_nordland(root, *, protocol: str = "auto", db_folder: str | None = None, q_folder: str | None = None,
                  query_frame_step: int | None = None, check_files: bool = True) -> GeoSplit:
    """Load Nordland with frame-index ground truth.

    Layouts: VPR-Bench / GSV-Cities "Nordland*" (``ref/`` 27 592 summer frames, ``query/`` 2 760 winter
    frames, query i = frame 10 i, so ``query_frame_step`` defaults to 10), or gmberton's
    (``images/test/{database,queries}`` with the frame number in name field 7, step 1); other folders
    with ``db_folder=``/``q_folder=`` (frame = last integer of the file stem).

    Protocols (a query's positives are the database frames f with ``|f - f_q| <= T``); ``"auto"``
    (default) is the protocol of the layout: ``"1frame"`` for ``ref/``+``query/`` and custom folders,
    ``"25m"`` for gmberton's folder (whose dummy UTM spacing encodes +-10 frames):

    - ``"1frame"``, T = 1: the GSV-Cities ``Nordland_gt.npy`` / SALAD / CliqueMining
      convention (refs 10i-1, 10i, 10i+1 for query i);
    - ``"25m"``, T = 10: gmberton's download_nordland.py (25 m = +-10 frames), as in the papers that
      report Nordland "within 25 m".

    As in gmberton's script, frames get dummy UTM (0, f * 25 / (T + 0.5)) so that ``pos_radius = 25 m``
    gives exactly the T-frame tolerance; frame indices are in ``extras["db_frame"|"q_frame"]``.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"Nordland folder not found: {root}")
    if protocol != "auto" and protocol not in NORDLAND_PROTOCOLS:
        raise ValueError(f"protocol must be 'auto' or one of {sorted(NORDLAND_PROTOCOLS)}, got {protocol!r}")
    if (db_folder is None) != (q_folder is None):
        raise ValueError("pass both db_folder and q_folder, or neither")
    if db_folder is None:
        if (root / "ref").is_dir() and (root / "query").is_dir():
            db_folder, q_folder, step, auto = "ref", "query", 10, "1frame"
        else:
            sdir = _gmberton_split_dir(root, "test")
            db_folder, q_folder, step, auto = str(sdir / "database"), str(sdir / "queries"), 1, "25m"
    else:
        step, auto = 1, "1frame"
    if protocol == "auto":
        protocol = auto
    if query_frame_step is not None:
        step = check_int(query_frame_step, "query_frame_step", minimum=1)
    frames_tol = NORDLAND_PROTOCOLS[protocol]
    spacing = 25.0 / (frames_tol + 0.5)
    db_files = _list_images((root / db_folder).resolve())
    q_files = _list_images((root / q_folder).resolve())
    db_frame = np.array([_frame_of(p) for p in db_files], dtype=np.int64)
    q_frame = np.array([_frame_of(p) for p in q_files], dtype=np.int64) * step
    if len(np.unique(db_frame)) != len(db_frame):
        raise ValueError(f"{root / db_folder}: several database images have the same frame number")
    as_utm = lambda fr: np.stack([np.zeros(len(fr)), fr * spacing], axis=1)  # noqa: E731
    out = GeoSplit(name=f"nordland_{protocol}", format="nordland", db_paths=[str(p) for p in db_files],
                   q_paths=[str(p) for p in q_files], db_utm=as_utm(db_frame), q_utm=as_utm(q_frame),
                   pos_radius=25.0, train_pos_radius=None,
                   extras={"db_frame": db_frame, "q_frame": q_frame, "frame_tolerance": frames_tol,
                           "frame_spacing_m": spacing, "query_frame_step": step, "protocol": protocol})
    if check_files:
        out.check_files()
    return out


# ----------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------
_LOADERS = {"pitts": load_pitts, "gmberton": load_gmberton, "msls": load_msls, "gsv-cities": load_gsv_cities,
            "nordland": load_nordland}


def load(root, format: str, *, check_files: bool = True, images_root=None, **options) -> GeoSplit:
    """Load a real VPR dataset split as a :class:`GeoSplit`.

    ``format``: ``"pitts"`` (``root`` = the dbStruct ``.mat``; ``images_root`` defaults to the parent of
    its ``datasets/`` folder), ``"gmberton"``, ``"msls"``, ``"gsv-cities"`` (``images_root`` replaces
    ``root`` for ``Images/``), ``"nordland"``. ``options`` go to the format's loader
    (:func:`load_pitts`, :func:`load_gmberton`, :func:`load_msls`, :func:`load_gsv_cities`,
    :func:`load_nordland`). ``check_files=True`` stats every listed image and names the first missing one.
    """
    if format not in _LOADERS:
        raise ValueError(f"unknown dataset format {format!r}; choose one of {FORMATS}")
    fn = _LOADERS[format]
    accepted = [p for p in inspect.signature(fn).parameters if p not in ("root", "mat_path", "check_files")]
    unknown = [k for k in options if k not in accepted]
    if unknown:
        raise ValueError(f"format {format!r} does not take option(s) {unknown}; it accepts {accepted}")
    if images_root is not None:
        if "images_root" not in accepted:
            raise ValueError(f"images_root is only used by the 'pitts' and 'gsv-cities' formats, not {format!r}")
        options["images_root"] = images_root
    return fn(root, check_files=bool(check_files), **options)


__all__ = ["FORMATS", "GeoSplit", "ImageDataset", "read_image", "load", "load_pitts", "load_gmberton", "load_msls",
           "load_gsv_cities", "load_nordland", "latlon_to_utm", "utm_zone", "parse_gmberton_name", "gsv_image_name"]



# ----------------------------------------------------------------------------------------------
# Real splits in the shape the training loop and evaluation use (images loaded lazily)
# ----------------------------------------------------------------------------------------------
class ImageArray:
    """A lazy ``(N, H, W, 3)`` uint8 "array" of image files: indexing reads and resizes only the
    requested images (Pillow + antialiased ``F.interpolate``), so the training loop and
    :func:`vpr_nb.evaluation.compute_descriptors` can treat on-disk datasets like in-memory ones."""

    dtype = np.dtype(np.uint8)
    ndim = 4

    def __init__(self, paths: Sequence, size):
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ValueError("ImageArray needs at least one image path")
        size = _as_size(size)
        if size is None:
            raise ValueError("ImageArray needs a fixed size (H, W) so that batches stack")
        self.size = size

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (len(self.paths), *self.size, 3)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index) -> np.ndarray:
        idx = np.arange(len(self.paths))[index]
        if np.ndim(idx) == 0:
            return self[[int(idx)]][0]
        out = np.empty((len(idx), *self.size, 3), np.uint8)
        for k, i in enumerate(idx):
            x = read_image(self.paths[i], self.size, normalize=False)
            out[k] = (x.permute(1, 2, 0).clamp_(0, 1) * 255).round_().to(torch.uint8).numpy()
        return out


# Recall@N convention per format for queries without any positive within the radius:
# "all" divides by every query (pytorch-NetVlad, gmberton's benchmark / VPR-methods-evaluation, GSV-Cities'
# validation, VPR-Bench Nordland), "exclude" leaves them out (mapillary_sls evaluate.py; the notebooks).
RECALL_CONVENTIONS = ("all", "exclude")
FORMAT_RECALL = {"pitts": "all", "gmberton": "all", "gsv-cities": "all", "nordland": "all", "msls": "exclude",
                 "synthetic": "exclude"}


def recall_convention(format: str) -> str:
    """The Recall@N convention of a dataset format (see :data:`FORMAT_RECALL`)."""
    if format not in FORMAT_RECALL:
        raise ValueError(f"unknown dataset format {format!r}; choose one of {sorted(FORMAT_RECALL)}")
    return FORMAT_RECALL[format]


def _decode_error(path: str) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as im:
            if im.format == "JPEG":      # decode at 1/8 scale: every byte is still read, so truncation shows
                im.draft("RGB", (max(1, im.width // 8), max(1, im.height // 8)))
            im.load()
    except Exception as exc:  # noqa: BLE001 - any decoder error makes the file unusable
        return f"{type(exc).__name__}: {exc}"
    return None


def find_unreadable_images(paths: Sequence, num_workers: int = 4) -> list[tuple[str, str]]:
    """``(path, error)`` of every image in ``paths`` that Pillow cannot fully decode (truncated or corrupt
    files, missing files), in the order given. JPEGs are decoded in draft mode (1/8 scale), which still
    reads the whole stream, so this costs a fraction of a full read."""
    if isinstance(paths, (str, os.PathLike)):
        raise ValueError("paths must be a sequence of image paths, not a single path")
    num_workers = check_int(num_workers, "num_workers")
    paths = [str(p) for p in paths]
    if num_workers == 1 or len(paths) < 64:
        errors = [_decode_error(p) for p in paths]
    else:
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(num_workers) as pool:
            errors = list(pool.map(_decode_error, paths, chunksize=256))
    return [(p, e) for p, e in zip(paths, errors) if e is not None]


def drop_images(split: GeoSplit, bad) -> GeoSplit:
    """A copy of ``split`` without the images whose path is in ``bad`` (per-image arrays and the
    ``extras`` arrays of matching length are filtered alike)."""
    if not isinstance(split, GeoSplit):
        raise ValueError(f"split must be a GeoSplit, got {type(split).__name__}")
    bad = {str(p) for p in bad}
    keep = {side: np.array([p not in bad for p in getattr(split, f"{side}_paths")], dtype=bool)
            for side in ("db", "q")}
    if keep["db"].all() and keep["q"].all():
        return split
    kw = {}
    for side in ("db", "q"):
        k = keep[side]
        kw[f"{side}_paths"] = [p for p, ok in zip(getattr(split, f"{side}_paths"), k) if ok]
        kw[f"{side}_utm"] = split.__dict__[f"{side}_utm"][k]
        for extra in ("heading", "place", "region"):
            v = getattr(split, f"{side}_{extra}")
            kw[f"{side}_{extra}"] = None if v is None else np.asarray(v)[k]
    extras = {}
    for key, v in split.extras.items():
        side = key.split("_", 1)[0]
        if side in keep and isinstance(v, np.ndarray) and len(v) == len(keep[side]):
            v = v[keep[side]]
        elif side in keep and isinstance(v, list) and len(v) == len(keep[side]):
            v = [x for x, ok in zip(v, keep[side]) if ok]
        extras[key] = v
    if not kw["db_paths"]:
        raise ValueError(f"{split.name}: every database image is unreadable")
    return GeoSplit(name=split.name, format=split.format, pos_radius=split.pos_radius,
                    train_pos_radius=split.train_pos_radius, extras=extras, **kw)


@dataclass
class TrainingSplit:
    """A :class:`GeoSplit` seen through the attributes of the synthetic ``VPRDataset`` splits
    (``db_images``/``q_images`` as lazy :class:`ImageArray`, ``db_utm``, ``pos_radius``, ...), so
    :class:`vpr_nb.training.TripletSource` and :func:`vpr_nb.evaluation.evaluate_model` accept it.
    ``recall_convention`` is the format's (:func:`recall_convention`)."""

    geo: GeoSplit
    image_size: tuple[int, int]

    def __post_init__(self):
        g = self.geo
        self.db_images = ImageArray(g.db_paths, self.image_size)
        self.q_images = ImageArray(g.q_paths, self.image_size) if g.q_paths else None
        self.db_utm, self.q_utm = g.db_utm, g.q_utm
        self.db_heading, self.q_heading = g.db_heading, g.q_heading
        self.db_place, self.q_place = g.db_place, g.q_place
        self.db_region, self.q_region = g.db_region, g.q_region
        self.pos_radius = g.pos_radius if g.pos_radius is not None else 25.0
        self.train_pos_radius = g.train_pos_radius if g.train_pos_radius is not None else 10.0
        self.recall_convention = recall_convention(g.format)
        self.name = g.name


__all__ += ["ImageArray", "TrainingSplit", "RECALL_CONVENTIONS", "FORMAT_RECALL", "recall_convention",
            "find_unreadable_images", "drop_images"]
