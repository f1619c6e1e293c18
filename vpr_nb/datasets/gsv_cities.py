"""Format ``"gsv-cities"``: GSV-Cities ``Dataframes/<city>.csv`` + ``Images/<city_id>/<name>.jpg``.

Places with at least ``min_img_per_place`` (4) images, as GSVCitiesDataset keeps. A training set:
every image is a database image, grouped by place (no queries, no positives radius); lat/lon are
projected to UTM per city (:mod:`vpr_nb.datasets.utm`) and the city is the region.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .._checks import check_int
from ._parsing import float_column, read_csv_columns
from .split import GeoSplit
from .utm import latlon_to_utm

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
        _, df = read_csv_columns(path, _GSV_COLS)
        n = len(df["place_id"])
        if n == 0:
            continue
        ints = {}
        for c in ("place_id", "year", "month", "northdeg"):
            v = float_column(df[c], path, c)
            if (v != np.round(v)).any():
                raise ValueError(f"{path}: column {c!r} must hold integers")
            ints[c] = v.astype(np.int64)
        lat, lon = float_column(df["lat"], path, "lat"), float_column(df["lon"], path, "lon")
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



def load_part(root, part: str = "train", *, gsv_cities=None, min_img_per_place: int = 4,
              check_files: bool = True) -> GeoSplit:
    """GSV-Cities (a training set: ``part`` is ``train``), the cities ``gsv_cities`` (None: every
    ``Dataframes/*.csv``), places of at least ``min_img_per_place`` images."""
    return load_gsv_cities(root, cities=list(gsv_cities) if gsv_cities else None,
                           min_img_per_place=min_img_per_place, check_files=check_files)

__all__ = ['load_gsv_cities', 'gsv_image_name', 'load_part']
