"""Format ``"gsv-cities"``: GSV-Cities ``Dataframes/<city>.csv`` + ``Images/<city_id>/<name>.jpg``.

Places with at least ``min_img_per_place`` (4) images, as GSVCitiesDataset keeps. A training set:
every image is a database image, grouped by place (no queries, no positives radius); lat/lon are
projected to UTM per city (:mod:`vpr_nb.datasets.utm`) and the city is the region.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .._checks import check_int
from ._parsing import duplicates, float_column, read_csv_columns
from .geotags import CITY_SPAN_M, LAT_LIMIT, LON_LIMIT, PLACE_SPREAD_M, check_latlon, warn_far_from_median
from .split import GeoSplit
from .utm import latlon_to_utm

_GSV_COLS = ("place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid")


def gsv_image_name(city_id: str, place_id: int, year: int, month: int, northdeg: int, lat: float, lon: float,
                   panoid: str) -> str:
    """GSV-Cities file name: ``{city}_{place:07d}_{year}_{month:02d}_{northdeg:03d}_{lat}_{lon}_{panoid}.jpg``
    (lat/lon written as Python writes the floats, as ``GSVCitiesDataset.get_img_name`` does)."""
    return (f"{city_id}_{str(int(place_id)).zfill(7)}_{int(year)}_{str(int(month)).zfill(2)}_"
            f"{str(int(northdeg)).zfill(3)}_{float(lat)}_{float(lon)}_{panoid}.jpg")


def _drop_repeated_rows(df: dict[str, list[str]], path) -> dict[str, list[str]]:
    """``df`` without rows that repeat an earlier row's image (same values in every named column, so
    the same file name), with a warning naming the file and rows: the image would count twice."""
    n = len(df["place_id"])
    rep = list(duplicates(["\x1f".join(df[c][i] for c in _GSV_COLS) for i in range(n)]).values())
    if not rep:
        return df
    drop = sorted(i - 1 for rows in rep for i in rows[1:])
    first = rep[0]
    warnings.warn(f"{path}: {len(drop)} row(s) repeat an earlier row (the same image), e.g. data rows {first} "
                  f"(lines {[r + 1 for r in first]}); each image is counted once", stacklevel=4)
    keep = np.setdiff1d(np.arange(n), drop)
    return {c: [v[i] for i in keep] for c, v in df.items()}


def _check_spread(path, city: str, utm: np.ndarray, place: np.ndarray, lat: np.ndarray, lon: np.ndarray,
                  zone: int, image) -> None:
    """Warn about images far from their place (:data:`~vpr_nb.datasets.geotags.PLACE_SPREAD_M`) or, the
    others, from their city (:data:`~vpr_nb.datasets.geotags.CITY_SPAN_M`), asking "latitude and longitude
    swapped?" when exchanging them (projected in the city's ``zone``) puts the image back."""
    swapped = np.full_like(utm, np.nan)
    ok = (np.abs(lon) <= LAT_LIMIT) & (np.abs(lat) <= LON_LIMIT)
    if ok.any():
        with np.errstate(invalid="ignore", divide="ignore"):
            se, sn, _ = latlon_to_utm(lon[ok], lat[ok], zone=zone)
        swapped[ok] = np.stack([se, sn], axis=1)
    source = f"{path} (GSV-Cities city {city!r})"
    far = warn_far_from_median(utm, place, PLACE_SPREAD_M, source, image, what="place", swapped_utm=swapped,
                               stacklevel=4)
    warn_far_from_median(utm, np.full(len(utm), city), CITY_SPAN_M, source, image, what="city",
                         swapped_utm=swapped, skip=far, stacklevel=4)


def load_gsv_cities(root, *, cities=None, min_img_per_place: int = 4, images_root=None,
                    check_files: bool = True) -> GeoSplit:
    """Load GSV-Cities: ``Dataframes/<city>.csv`` (columns place_id, year, month, northdeg, city_id,
    lat, lon, panoid) and ``Images/<city_id>/<gsv_image_name>``.

    Places with fewer than ``min_img_per_place`` images are dropped (``groupby('place_id')
    .transform('size') >= min_img_per_place`` in GSVCitiesDataset). The i-th city's place ids are offset
    by ``i * 10**5`` as in that code, giving global ``db_place`` labels. A training set: every image is a
    database image, there are no queries and no positives radius. lat/lon are projected to UTM per city
    (one zone per city, :func:`latlon_to_utm`); ``db_region`` is the city.

    Rows that repeat an earlier row (the same image) are counted once, with a warning naming the file
    and rows; a city left without images is named in a warning; a lat/lon outside UTM's range raises
    ValueError naming the file and row; an image more than 1 km from its place's median position, or
    100 km from its city's, is named in a warning (with "latitude and longitude swapped?" when exchanging
    them puts it back; :mod:`vpr_nb.datasets.geotags`).
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
    utm, heading, place, region, zones, years, notes = [], [], [], [], {}, [], []
    for ci, city in enumerate(cities):
        path = dfdir / f"{city}.csv"
        _, df = read_csv_columns(path, _GSV_COLS)
        n = len(df["place_id"])
        if n == 0:
            notes.append((path, f"lists no image (header only); GSV-Cities city {city!r} is left out"))
            continue
        df = _drop_repeated_rows(df, path)
        ints = {}
        for c in ("place_id", "year", "month", "northdeg"):
            v = float_column(df[c], path, c)
            if (v != np.round(v)).any():
                raise ValueError(f"{path}: column {c!r} must hold integers")
            ints[c] = v.astype(np.int64)
        lat, lon = float_column(df["lat"], path, "lat"), float_column(df["lon"], path, "lon")
        check_latlon(lat, lon, lambda i, c: f"{path}: column {c!r}, data row {i + 1} (line {i + 2})")
        ids, counts = np.unique(ints["place_id"], return_counts=True)
        big = set(ids[counts >= min_img_per_place].tolist())
        keep = np.array([p in big for p in ints["place_id"]], dtype=bool)
        if not keep.any():
            notes.append((path, f"none of its {len(ids)} place(s) has >= {min_img_per_place} images "
                                f"(min_img_per_place); GSV-Cities city {city!r} is left out"))
            continue
        e, nth, zone = latlon_to_utm(lat[keep], lon[keep])
        zones[city] = zone
        rows = np.flatnonzero(keep)
        names = [gsv_image_name(df["city_id"][i], ints["place_id"][i], ints["year"][i], ints["month"][i],
                                ints["northdeg"][i], df["lat"][i], df["lon"][i], df["panoid"][i]) for i in rows]
        paths.extend(str(img_root / "Images" / df["city_id"][i] / name) for i, name in zip(rows, names))
        _check_spread(path, city, np.stack([e, nth], axis=1), ints["place_id"][keep], lat[keep], lon[keep], zone,
                      lambda j: f"{names[j]} (data row {rows[j] + 1})")
        utm.append(np.stack([e, nth], axis=1))
        heading.append(ints["northdeg"][keep].astype(np.float64))
        place.append(ints["place_id"][keep] + ci * 10 ** 5)
        region.append(np.array([city] * int(keep.sum())))
        years.append(ints["year"][keep] * 100 + ints["month"][keep])
    if not paths:
        raise ValueError(f"{dfdir}: no place of cities {cities} has >= {min_img_per_place} images "
                         f"({'; '.join(f'{p.name}: {why}' for p, why in notes)})")
    for p, why in notes:
        warnings.warn(f"{p}: {why}", stacklevel=3)
    out = GeoSplit(name="gsv-cities", format="gsv-cities", db_paths=paths, q_paths=[],
                   db_utm=np.concatenate(utm), q_utm=np.zeros((0, 2)), pos_radius=None, train_pos_radius=None,
                   db_heading=np.concatenate(heading), db_place=np.concatenate(place),
                   db_region=np.concatenate(region),
                   extras={"cities": cities, "utm_zone": zones, "db_yearmonth": np.concatenate(years),
                           "min_img_per_place": min_img_per_place})
    if check_files:
        out.check_files()
    return out



def load_part(root, part: str = "train", *, gsv_cities=None, min_img_per_place: int = 4,
              check_files: bool = True) -> GeoSplit:
    """GSV-Cities (a training set: ``part`` is ``train``), the cities ``gsv_cities`` (None: every
    ``Dataframes/*.csv``), places of at least ``min_img_per_place`` images."""
    return load_gsv_cities(root, cities=list(gsv_cities) if gsv_cities else None,
                           min_img_per_place=min_img_per_place, check_files=check_files)

__all__ = ['load_gsv_cities', 'gsv_image_name', 'load_part']
