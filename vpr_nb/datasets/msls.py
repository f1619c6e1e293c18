"""Format ``"msls"``: Mapillary SLS ``train_val/<city>/{database,query}/{raw.csv,postprocessed.csv}``.

CSV files with the leading pandas index column, as shipped. Panoramas are excluded by default (as the
official code); ``unique_cluster`` is kept in ``db_place``/``q_place`` for CliqueMining; positives are
searched inside each city (``*_region``); ``val_subset="official"`` reproduces the official 740-query
MSLS-val selection (see :func:`load_msls`). Recall@N excludes queries without positives
(mapillary_sls ``evaluate.py``).
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .._checks import check_positive
from ..split import positives_within
from ._parsing import bool_column, duplicates, float_column, read_csv_columns, read_text
from .geotags import LAT_POLE, check_latlon, check_utm, warn_isolated
from .split import GeoSplit

# mapillary_sls msls.py ``default_cities`` (also copied in gmberton's format_mapillary.py)
MSLS_CITIES = {
    "train": ("trondheim", "london", "boston", "melbourne", "amsterdam", "helsinki", "tokyo", "toronto",
              "saopaulo", "moscow", "zurich", "paris", "bangkok", "budapest", "austin", "berlin", "ottawa",
              "phoenix", "goa", "amman", "nairobi", "manila"),
    "val": ("cph", "sf"),
}


_MSLS_RAW = ("key", "lon", "lat", "ca", "captured_at", "pano")
_MSLS_POST = ("key", "easting", "northing", "unique_cluster", "night", "view_direction")


def _read_key_list(path) -> set[str]:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"query key list not found: {p}")
    if p.suffix == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ValueError(f"{p}: not a .npy array of strings ({exc})") from None
        items = [str(x) for x in arr.reshape(-1)]
    else:
        items = [ln.strip() for ln in read_text(p).splitlines() if ln.strip()]
    if not items:
        raise ValueError(f"{p}: the query key list is empty")
    return {Path(s).stem for s in items}


def _check_geotags(folder: Path, keys: list[str], utm: np.ndarray, raw: dict) -> None:
    """ValueError for an impossible UTM position of postprocessed.csv or lat/lon of raw.csv, a warning
    for an image with no other of this side within 100 km (:mod:`vpr_nb.datasets.geotags`; one median
    would mean nothing where a city straddles a UTM zone edge, as London the prime meridian)."""
    post, raw_csv = folder / "postprocessed.csv", folder / "raw.csv"
    check_utm(utm, lambda i, c: f"{post}: column {c!r}, data row {i + 1} (line {i + 2}, key {keys[i]})",
              swap_hint="columns 'easting' and 'northing' swapped?")
    check_latlon(float_column(raw["lat"], raw_csv, "lat"), float_column(raw["lon"], raw_csv, "lon"),
                 lambda i, c: f"{raw_csv}: column {c!r}, data row {i + 1} (line {i + 2}, key {raw['key'][i]})",
                 lat_limit=LAT_POLE)
    warn_isolated(utm, str(post), lambda i: f"key {keys[i]} (data row {i + 1})", stacklevel=4)


def _msls_side(cdir: Path, side: str, exclude_panos: bool, subtask: str | None):
    folder = cdir / side
    _, post = read_csv_columns(folder / "postprocessed.csv", _MSLS_POST)
    _, raw = read_csv_columns(folder / "raw.csv", _MSLS_RAW)
    keys = post["key"]
    for name, col in (("postprocessed.csv", keys), ("raw.csv", raw["key"])):
        dup = duplicates(col)
        if dup:
            key, rows = next(iter(dup.items()))
            raise ValueError(f"{folder / name}: {len(dup)} key(s) are listed more than once, e.g. {key!r} in data rows "
                             f"{rows} (lines {[r + 1 for r in rows]}); every image must be listed once: drop the "
                             f"repeated rows")
    if sorted(keys) != sorted(raw["key"]):
        raise ValueError(f"{folder / 'raw.csv'}: its 'key' column does not list the same images as "
                         f"{folder / 'postprocessed.csv'}")
    raw_row = {k: i for i, k in enumerate(raw["key"])}
    ridx = np.array([raw_row[k] for k in keys], dtype=np.int64)
    pano = bool_column(raw["pano"], folder / "raw.csv", "pano")[ridx] if keys else np.zeros(0, bool)
    utm = np.stack([float_column(post["easting"], folder / "postprocessed.csv", "easting"),
                    float_column(post["northing"], folder / "postprocessed.csv", "northing")], axis=1).reshape(-1, 2)
    _check_geotags(folder, keys, utm, raw)
    cl = []
    for i, v in enumerate(post["unique_cluster"]):
        try:
            x = float(v) if v else float("nan")
        except ValueError:
            raise ValueError(f"{folder / 'postprocessed.csv'}: column 'unique_cluster', data row {i + 1}: "
                             f"{v!r} is not a number") from None
        cl.append(int(x) if np.isfinite(x) else -1)
    keep = ~pano if exclude_panos else np.ones(len(keys), bool)
    n_panos = int((~keep).sum())
    if subtask is not None:
        sub_path = folder / "subtask_index.csv"
        _, sub = read_csv_columns(sub_path, (subtask,))
        if len(sub[subtask]) != len(keys):
            raise ValueError(f"{sub_path}: {len(sub[subtask])} rows but postprocessed.csv has {len(keys)}")
        keep &= bool_column(sub[subtask], sub_path, subtask)
    # why nothing is left of this side, if nothing is (load_msls names it when a city drops out)
    if keep.any():
        why = ""
    elif not keys:
        why = f"{side}/postprocessed.csv lists no image"
    elif n_panos == len(keys):
        why = f"all {len(keys)} {side} images are panoramas, which exclude_panos=True leaves out"
    else:
        why = f"none of its {len(keys) - n_panos} non-panorama {side} images is flagged in subtask_index.csv {subtask!r}"
    heading = float_column(raw["ca"], folder / "raw.csv", "ca")[ridx] if keys else np.zeros(0)
    night = bool_column(post["night"], folder / "postprocessed.csv", "night") if keys else np.zeros(0, bool)
    paths = [str((folder / "images" / f"{k}.jpg").resolve()) for k in keys]
    sel = np.flatnonzero(keep)
    return {"paths": [paths[i] for i in sel], "keys": [keys[i] for i in sel], "utm": utm[sel],
            "heading": heading[sel], "place": np.asarray(cl, dtype=np.int64)[sel], "night": night[sel],
            "view": np.array(post["view_direction"], dtype=object)[sel].astype(str), "why": why}


def _select(part: dict, sel: np.ndarray, why: str) -> dict:
    """The images of one city side where ``sel``; ``why`` says why none is left, if none is."""
    out = {k: ([v[i] for i in np.flatnonzero(sel)] if isinstance(v, list) else v[sel])
           for k, v in part.items() if k != "why"}
    out["why"] = part["why"] if not len(part["keys"]) else why
    return out


def _empty_city_notes(city: str, db: dict, q: dict, notes: list) -> None:
    """A note naming ``city`` and why, when its database or its queries came out empty."""
    n_db, n_q = len(db["keys"]), len(q["keys"])
    if not n_db and not n_q:
        notes.append(f"MSLS city {city!r} has no usable images ({db['why']}; {q['why']}) and is left out")
    elif not n_q:
        notes.append(f"MSLS city {city!r} has no usable queries ({q['why']}); its {n_db} database images stay "
                     f"in the database, but none of its places is queried")
    elif not n_db:
        notes.append(f"MSLS city {city!r} has no usable database images ({db['why']}); its {n_q} queries have "
                     f"no positive")


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

    A city left without queries or database images (header-only CSVs, only panoramas, nothing in the
    subset) is named in a warning; no usable database image or query in any city, a key listed twice
    in a CSV, a CSV that is not UTF-8 or an impossible geotag (:mod:`vpr_nb.datasets.geotags`) raise
    ValueError naming the file; an image far from all others of its city side is named in a warning.
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
    db_parts, q_parts, notes = [], [], []
    for city in cities:
        db = _msls_side(tv / city, "database", exclude_panos, subtask)
        q = _msls_side(tv / city, "query", exclude_panos, subtask)
        if wanted is not None and len(q["keys"]):
            q = _select(q, np.array([k in wanted for k in q["keys"]], dtype=bool),
                        f"none of its {len(q['keys'])} queries is in {Path(query_keys).name}")
        if val_subset == "official" and len(q["keys"]) and len(db["keys"]):
            has = np.array([len(p) > 0 for p in positives_within(db["utm"], q["utm"], pos_radius)], dtype=bool)
            q = _select(q, has, f"none of its {len(q['keys'])} queries has a database image within {pos_radius:g} m")
        elif val_subset == "official":
            q = _select(q, np.zeros(len(q["keys"]), bool), "none can have a positive: the city has no database images")
        for part, lst in ((db, db_parts), (q, q_parts)):
            part["region"] = np.array([city] * len(part["keys"]), dtype=object).astype(str)
            lst.append(part)
        _empty_city_notes(city, db, q, notes)

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
    for side, parts in (("database", db_parts), ("query", q_parts)):
        if not any(len(p["keys"]) for p in parts):
            why = "; ".join(f"{c}: {p['why']}" for c, p in zip(cities, parts))
            raise ValueError(f"{tv}: no usable {side} image in any of the cities ({why}); check their "
                             f"{side}/postprocessed.csv and raw.csv")
    for note in notes:
        warnings.warn(note, stacklevel=3)
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


MSLS_VAL_SUBSETS = ("official", "all")   # the official 740 MSLS-val queries, or every query of cph and sf


def load_part(root, part: str, *, msls_val_subset: str = "official", check_files: bool = True) -> GeoSplit:
    """Part ``train`` (the official training cities present under ``root``, never cph / sf; a warning
    names the absent ones) or ``val`` (MSLS-val: cph + sf, the labelled MSLS evaluation set, with the
    ``msls_val_subset`` queries of :data:`MSLS_VAL_SUBSETS`)."""
    root = Path(root)
    if part == "val":
        sub = "official" if msls_val_subset == "official" else None
        return load_msls(root, cities="val", val_subset=sub, check_files=check_files)
    tv = root if root.name == "train_val" else root / "train_val"
    cities = [c for c in MSLS_CITIES["train"] if (tv / c).is_dir()]
    if not cities:
        raise FileNotFoundError(f"{tv}: none of the MSLS training cities ({', '.join(MSLS_CITIES['train'])}) "
                                "is there; the root must be the MSLS folder holding train_val/<city>")
    missing = [c for c in MSLS_CITIES["train"] if c not in cities]
    if missing:
        warnings.warn(f"{tv}: {len(missing)} of the {len(MSLS_CITIES['train'])} MSLS training cities are "
                      f"absent ({', '.join(missing[:5])}...); training on {', '.join(cities)}", stacklevel=2)
    return load_msls(root, cities=cities, check_files=check_files)

__all__ = ['load_msls', 'MSLS_CITIES', 'MSLS_VAL_SUBSETS', 'load_part']
