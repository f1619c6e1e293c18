"""Format ``"gmberton"``: the layout of gmberton's VPR-datasets-downloader (Pitts30k, MSLS, Nordland,
Tokyo 24/7, SF-XL, SPED...): ``images/<split>/{database,queries}/@east@north@zone@...@.jpg``.

UTM east/north are fields 1 and 2 of ``name.split("@")``, the heading field 9 (:func:`parse_gmberton_name`).
Positives 25 m, training positives 10 m; Recall@N over all queries (gmberton's benchmark).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .._checks import check_positive
from ._parsing import list_images
from .split import GeoSplit


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


def gmberton_split_dir(root: Path, split: str) -> Path:
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
    sdir = gmberton_split_dir(root, split).resolve()
    sides = {}
    for side, folder in (("db", "database"), ("q", "queries")):
        files = list_images(sdir / folder, suffixes=(".jpg",))   # datasets_ws.py: sorted(glob("**/*.jpg"))
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



def load_part(root, part: str, *, check_files: bool = True) -> GeoSplit:
    """Part ``train`` / ``val`` / ``test`` of a VPR-datasets-downloader folder: ``images/<part>``."""
    return load_gmberton(root, split=part, check_files=check_files)

__all__ = ['load_gmberton', 'parse_gmberton_name', 'load_part']
