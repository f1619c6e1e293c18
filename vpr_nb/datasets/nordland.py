"""Format ``"nordland"``: Nordland with frame-index ground truth.

By default the +-1 frame convention of the VPR-Bench / GSV-Cities "Nordland*" test set
(``protocol="1frame"``), or the gmberton 25 m = +-10 frames one (``protocol="25m"``). Positions are
dummy UTM coordinates along one line, spaced so that the radius search of every other dataset gives
exactly the frame tolerance. Recall@N over all queries (VPR-Bench). Nordland carries no geotag (frame
numbers only), so :mod:`vpr_nb.datasets.geotags` has nothing to check here.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .._checks import check_int
from ._parsing import gmberton_split_dir, list_images
from .split import GeoSplit

# Nordland: gmberton's download_nordland.py places frames on a line, DISTANCE = 25 m / (frames + 0.5)
NORDLAND_PROTOCOLS = {"1frame": 1, "25m": 10}


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


def _queries_without_positive(db_frame: np.ndarray, q_frame: np.ndarray, tol: int) -> np.ndarray:
    """Indices of the queries with no database frame within ``tol`` frames (sorted search, O(Q log N))."""
    ref = np.sort(db_frame)
    at = np.searchsorted(ref, q_frame - tol)          # first reference frame >= f_q - tol
    ok = (at < len(ref)) & (ref[np.minimum(at, len(ref) - 1)] <= q_frame + tol)
    return np.flatnonzero(~ok)


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

    Every query must have a reference frame within T frames (the protocol defines its positives so):
    folders that do not match (other counts, another stretch, a wrong ``query_frame_step``) raise
    ValueError naming both folders and the counts, as do two images of one frame.
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
            sdir = gmberton_split_dir(root, "test")
            db_folder, q_folder, step, auto = str(sdir / "database"), str(sdir / "queries"), 1, "25m"
    else:
        step, auto = 1, "1frame"
    if protocol == "auto":
        protocol = auto
    if query_frame_step is not None:
        step = check_int(query_frame_step, "query_frame_step", minimum=1)
    frames_tol = NORDLAND_PROTOCOLS[protocol]
    spacing = 25.0 / (frames_tol + 0.5)
    db_files = list_images((root / db_folder).resolve())
    q_files = list_images((root / q_folder).resolve())
    db_frame = np.array([_frame_of(p) for p in db_files], dtype=np.int64)
    q_frame = np.array([_frame_of(p) for p in q_files], dtype=np.int64) * step
    for folder, files, frames in ((db_folder, db_files, db_frame), (q_folder, q_files, q_frame)):
        uniq, counts = np.unique(frames, return_counts=True)
        if len(uniq) != len(frames):
            same = [files[i].name for i in np.flatnonzero(frames == uniq[np.argmax(counts > 1)])]
            raise ValueError(f"{root / folder}: {len(frames) - len(uniq)} image(s) repeat the frame number of "
                             f"another, e.g. {same[:3]}; keep one image per frame")
    lonely = _queries_without_positive(db_frame, q_frame, frames_tol)
    if len(lonely):
        raise ValueError(f"{root / q_folder} and {root / db_folder} do not match: {len(lonely)} of {len(q_files)} "
                         f"queries (e.g. {q_files[lonely[0]].name}, frame {q_frame[lonely[0]]}) have no reference "
                         f"frame within +-{frames_tol} frames among the {len(db_files)} references (frames "
                         f"{db_frame.min()}..{db_frame.max()}); with query_frame_step={step} the {len(q_files)} "
                         f"queries need reference frames up to {q_frame.max()}: check that both folders hold "
                         f"the same stretch of the route, or pass the right query_frame_step")
    as_utm = lambda fr: np.stack([np.zeros(len(fr)), fr * spacing], axis=1)  # noqa: E731
    out = GeoSplit(name=f"nordland_{protocol}", format="nordland", db_paths=[str(p) for p in db_files],
                   q_paths=[str(p) for p in q_files], db_utm=as_utm(db_frame), q_utm=as_utm(q_frame),
                   pos_radius=25.0, train_pos_radius=None,
                   extras={"db_frame": db_frame, "q_frame": q_frame, "frame_tolerance": frames_tol,
                           "frame_spacing_m": spacing, "query_frame_step": step, "protocol": protocol})
    if check_files:
        out.check_files()
    return out



def load_part(root, part: str = "test", *, nordland_protocol: str = "auto", check_files: bool = True) -> GeoSplit:
    """Nordland (a test set: ``part`` is ``test``) with the ground truth ``nordland_protocol``
    (``auto`` or a key of :data:`NORDLAND_PROTOCOLS`)."""
    return load_nordland(root, protocol=nordland_protocol, check_files=check_files)

__all__ = ['load_nordland', 'NORDLAND_PROTOCOLS', 'load_part']
