"""Format ``"gmberton"``: the layout of gmberton's VPR-datasets-downloader (Pitts30k, MSLS, Nordland,
Tokyo 24/7, SF-XL, SPED...): ``images/<split>/{database,queries}/@east@north@zone@...@.jpg``.

UTM east/north are fields 1 and 2 of ``name.split("@")``, the heading field 9 (:func:`parse_gmberton_name`).
Positives 25 m, training positives 10 m; Recall@N over all queries (gmberton's benchmark).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .._checks import check_positive
from ._parsing import gmberton_split_dir, list_images
from .geotags import LAT_POLE, check_latlon, check_utm, warn_isolated
from .split import GeoSplit


def parse_gmberton_name(path) -> dict:
    """Fields of a VPR-datasets-downloader name ``@east@north@zone@letter@lat@lon@pano@tile@heading@...@.jpg``.

    Returns ``{"east", "north", "zone", "letter", "lat", "lon", "pano_id", "heading", "note"}`` (heading,
    lat, lon None if empty); raises ValueError naming the file when east/north are missing or not finite,
    lat/lon not numbers or the zone not 01..60.
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
    zone = get(3)
    if zone and not (zone.isdigit() and 1 <= int(zone) <= 60):
        raise ValueError(f"{path}: field 3 (UTM zone) {zone!r} is not a UTM zone number (01 to 60)")
    return {"east": num(1, "UTM_east"), "north": num(2, "UTM_north"), "zone": zone, "letter": get(4),
            "lat": num(5, "latitude") if get(5) else None, "lon": num(6, "longitude") if get(6) else None,
            "pano_id": get(7), "heading": heading, "note": get(14) if len(parts) > 15 else ""}


def _check_geotags(sdir: Path, sides: dict) -> None:
    """ValueError for an impossible UTM position (in names that carry a UTM zone: gmberton's Nordland names
    hold dummy positions and no zone) or latitude/longitude; a warning for an image with no other within
    :data:`~vpr_nb.datasets.geotags.CITY_SPAN_M` (a split may hold several cities and UTM zones)."""
    for files, parsed in sides.values():
        utm = np.array([[p["east"], p["north"]] for p in parsed], dtype=np.float64)
        check_utm(utm, lambda i, _, files=files: str(files[i]), rows=[bool(p["zone"]) for p in parsed],
                  labels=("east", "north"), swap_hint="fields 1 and 2 (UTM east, north) swapped?")
        nan = float("nan")
        check_latlon([nan if p["lat"] is None else p["lat"] for p in parsed],
                     [nan if p["lon"] is None else p["lon"] for p in parsed],
                     lambda i, c, files=files: f"{files[i]}: {c}", lat_limit=LAT_POLE,
                     labels=("field 5 (latitude)", "field 6 (longitude)"))
    files = [f for fs, _ in sides.values() for f in fs]
    warn_isolated(np.array([[p["east"], p["north"]] for _, ps in sides.values() for p in ps], dtype=np.float64),
                  str(sdir), lambda i: files[i].name, stacklevel=4)


def load_gmberton(root, *, split: str = "test", pos_radius: float = 25.0, train_pos_radius: float = 10.0,
                  check_files: bool = True) -> GeoSplit:
    """Load a dataset formatted by gmberton's VPR-datasets-downloader.

    ``root`` is ``datasets/<name>`` (holding ``images/<split>/``) or the split folder itself. Images
    are found recursively and sorted (as the benchmark's ``sorted(glob('**/*.jpg'))``: only lower-case
    ``.jpg`` files count, stray ``.JPG``/``.png`` files are ignored with a warning); UTM east and
    north are fields 1 and 2 of the ``@``-split name. Positives within ``pos_radius`` (25 m,
    ``val_positive_dist_threshold``), training positives ``train_pos_radius`` (10 m). An impossible
    geotag raises ValueError naming the file, an image far from all others is named in a warning
    (:mod:`vpr_nb.datasets.geotags`).
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
    _check_geotags(sdir, sides)
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
