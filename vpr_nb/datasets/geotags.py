"""Checking the geotags a real-format loader reads: one job, saying when a position cannot be right.

Every format module (:mod:`~vpr_nb.datasets.pitts`, :mod:`~vpr_nb.datasets.gmberton`,
:mod:`~vpr_nb.datasets.msls`, :mod:`~vpr_nb.datasets.gsv_cities`) runs its positions through these checks
right after parsing them:

- :func:`check_utm` raises ValueError for an *impossible* UTM position (outside :data:`UTM_EASTING_RANGE` /
  :data:`UTM_NORTHING_RANGE`), naming the file, the row and the likely cause (easting and northing
  exchanged, degrees instead of metres);
- :func:`check_latlon` raises ValueError for an impossible latitude / longitude, and says when the two
  look exchanged;
- :func:`warn_far_from_median` warns about *implausible* positions: images far from the median position of
  their group (a GSV-Cities place, a city), with "latitude and longitude swapped?" when exchanging them
  puts the image back in its group;
- :func:`warn_isolated` warns about an image with no other image of its set within :data:`CITY_SPAN_M`
  (for splits that may hold several cities or UTM zones, where a median means nothing).

Nordland is not checked: it carries no geotag at all (frame numbers only; :mod:`~vpr_nb.datasets.nordland`
builds dummy positions on a line itself, and gmberton's Nordland names hold such dummy positions without a
UTM zone, which :mod:`~vpr_nb.datasets.gmberton` leaves out of the UTM range check).
"""
from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

# UTM (WGS84, false easting 500 km): inside its own 6-degree zone an easting lies within 166,021-833,979 m at
# the equator and nearer to 500 km elsewhere (wider zones 32V / 31X-37X stay inside too); 100-900 km leaves
# ~0.6 degree of margin at the equator (more elsewhere) for points projected in a neighbouring zone (one zone
# per GSV-Cities city). The `utm` package's to_latlon accepts 100-1000 km.
UTM_EASTING_RANGE = (100_000.0, 900_000.0)
# northing: metres from the equator, plus a 10,000 km false northing south of it (80 S = 1,116 km,
# 84 N = 9,329 km), so always within 0-10,000 km (the `utm` package's to_latlon range too)
UTM_NORTHING_RANGE = (0.0, 10_000_000.0)
# WGS84 degrees: a latitude lies within [-90, 90], a longitude within [-180, 180]; UTM covers 80 S to 84 N
# (polar regions use UPS), so a latitude that is projected to UTM (latlon_to_utm) must lie within [-84, 84]
LAT_POLE = 90.0
LAT_LIMIT = 84.0
LON_LIMIT = 180.0
# GSV-Cities: the images of one place_id show one spot over the years, metres to tens of metres apart (the
# fixtures: < 10 m); 1 km from the place's median is far beyond that and flags only gross errors (swapped or
# mistyped coordinates). A warning: the image is still loaded
PLACE_SPREAD_M = 1_000.0
# a city's images lie within 100 km of its median: the cities of the VPR datasets (Pittsburgh, the MSLS and
# GSV-Cities cities, SF-XL) are street networks of metropolitan areas, tens of km across; an image beyond
# belongs to another city or has a wrong geotag. A warning: a larger city still loads
CITY_SPAN_M = 100_000.0

Where = Callable[[int, str], str]   # (row, column) -> "file: column 'x', data row 3 (line 4)" etc.
Image = Callable[[int], str]        # row -> the image's name, as the dataset's user knows it


def _fmt_range(lo: float, hi: float) -> str:
    return f"[{lo:,.0f}, {hi:,.0f}]"


def check_utm(utm, where: Where, *, swap_hint: str, labels: tuple[str, str] = ("easting", "northing"),
              rows=None) -> None:
    """ValueError when a UTM position (``utm``: (N, 2) easting, northing in metres) is impossible.

    ``where(i, label)`` names row ``i`` (file and row); ``swap_hint`` is the format's words for an exchange
    of the two coordinates (e.g. "utmDb rows swapped?"), said when the exchanged pair would be valid;
    ``rows``: a boolean mask of the rows that hold UTM (None: all)."""
    utm = np.asarray(utm, dtype=np.float64).reshape(-1, 2)
    e, n = utm[:, 0], utm[:, 1]
    ok_e = (e >= UTM_EASTING_RANGE[0]) & (e <= UTM_EASTING_RANGE[1])
    ok_n = (n >= UTM_NORTHING_RANGE[0]) & (n <= UTM_NORTHING_RANGE[1])
    bad = ~(ok_e & ok_n)
    if rows is not None:
        bad &= np.asarray(rows, dtype=bool)
    if not bad.any():
        return
    idx = np.flatnonzero(bad)
    i = int(idx[0])
    swapped = (UTM_EASTING_RANGE[0] <= n[i] <= UTM_EASTING_RANGE[1]) and \
        (UTM_NORTHING_RANGE[0] <= e[i] <= UTM_NORTHING_RANGE[1])
    if swapped:
        cause = (f"{labels[0]} and {labels[1]} look exchanged (({n[i]:.2f}, {e[i]:.2f}) would be valid): "
                 f"{swap_hint}; fix the file")
    elif abs(e[i]) <= LON_LIMIT and abs(n[i]) <= LAT_POLE or abs(n[i]) <= LON_LIMIT and abs(e[i]) <= LAT_POLE:
        cause = "latitude/longitude degrees instead of UTM metres? Fix the geotag or drop the image"
    else:
        cause = "a mistyped or corrupted geotag? Fix it or drop the image"
    label = labels[0] if not ok_e[i] else labels[1]
    raise ValueError(f"{where(i, label)}: UTM {labels[0]}={e[i]:.2f} m, {labels[1]}={n[i]:.2f} m is impossible: a "
                     f"UTM easting lies within {_fmt_range(*UTM_EASTING_RANGE)} m and a northing within "
                     f"{_fmt_range(*UTM_NORTHING_RANGE)} m ({len(idx)} position(s) in all); {cause}")


def check_latlon(lat, lon, where: Where, *, lat_limit: float = LAT_LIMIT,
                 labels: tuple[str, str] = ("lat", "lon")) -> None:
    """ValueError when a latitude is outside ``[-lat_limit, lat_limit]`` (84: where UTM applies; 90 for
    positions that are not projected) or a longitude outside [-180, 180] degrees; ``where(i, label)`` names
    the row and the column, and "latitude and longitude swapped?" is said when exchanging them is valid."""
    lat = np.asarray(lat, dtype=np.float64).reshape(-1)
    lon = np.asarray(lon, dtype=np.float64).reshape(-1)
    for label, v, lim in ((labels[0], lat, lat_limit), (labels[1], lon, LON_LIMIT)):
        bad = np.flatnonzero(np.abs(v) > lim)
        if not len(bad):
            continue
        i = int(bad[0])
        if abs(lon[i]) <= lat_limit and abs(lat[i]) <= LON_LIMIT:
            cause = (f"latitude and longitude swapped? ({labels[0]}={lon[i]:g}, {labels[1]}={lat[i]:g} would be "
                     f"valid): fix the geotag or drop the row")
        else:
            cause = "fix the geotag or drop the row"
        where_utm = f"; UTM covers {lat_limit:g} S to {lat_limit:g} N" if lim == lat_limit == LAT_LIMIT else ""
        raise ValueError(f"{where(i, label)}: {v[i]:g} is outside [-{lim:g}, {lim:g}] degrees ({len(bad)} row(s) "
                         f"in all){where_utm}: {cause}")


def _medians(utm: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """The per-coordinate median position of each row's group, (N, 2) (sorted once per coordinate, so
    O(N log N) whatever the number of groups)."""
    _, inv, counts = np.unique(groups, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    out = np.empty_like(utm)
    for c in range(2):
        v = utm[np.lexsort((utm[:, c], inv)), c]              # by group, then by value
        out[:, c] = ((v[lo] + v[hi]) / 2)[inv]
    return out


def warn_far_from_median(utm, groups, limit: float, source: str, image: Image, *, what: str,
                         swapped_utm=None, skip=None, stacklevel: int = 2) -> np.ndarray:
    """Warn (once, naming ``source``, a count and an example image) about the rows farther than ``limit``
    metres from the median position of their group (``groups``: one label per row; ``what`` names a group,
    e.g. "place" or "city"). ``swapped_utm``: the rows' positions with latitude and longitude exchanged
    (NaN where impossible): when that puts a far image back within ``limit``, the warning asks
    "latitude and longitude swapped?". ``skip``: rows already reported. Returns the mask of far rows."""
    utm = np.asarray(utm, dtype=np.float64).reshape(-1, 2)
    groups = np.asarray(groups)
    far = np.zeros(len(utm), dtype=bool)
    keep = np.ones(len(utm), dtype=bool) if skip is None else ~np.asarray(skip, dtype=bool)
    if not keep.any():
        return far
    med = np.full_like(utm, np.nan)
    med[keep] = _medians(utm[keep], groups[keep])
    dist = np.linalg.norm(utm - med, axis=1)
    far = keep & (dist > limit)
    if not far.any():
        return far
    idx = np.flatnonzero(far)
    i = int(idx[np.argmax(dist[idx])])
    hint = f"a wrong geotag, or an image listed under the wrong {what}? Fix or drop it"
    if swapped_utm is not None:
        with np.errstate(invalid="ignore"):
            back = np.linalg.norm(np.asarray(swapped_utm, dtype=np.float64).reshape(-1, 2) - med, axis=1)
        fits = idx[back[idx] <= limit]
        if len(fits):
            i = int(fits[0])
            hint = (f"latitude and longitude swapped? (exchanged, they put that image {back[i]:,.0f} m from the "
                    f"median of its {what}): fix the geotag")
    warnings.warn(f"{source}: {len(idx)} image(s) lie more than {limit:,.0f} m from the median position of their "
                  f"{what} (e.g. {image(i)}, {dist[i] / 1000:,.1f} km from that of {what} {groups[i]}); the images "
                  f"of one {what} lie within {limit:,.0f} m of it: {hint}", stacklevel=stacklevel + 1)
    return far


def warn_isolated(utm, source: str, image: Image, *, limit: float = CITY_SPAN_M, stacklevel: int = 2) -> None:
    """Warn (once, naming ``source``, a count and an example) about the images of ``utm`` with no other
    image within ``limit`` metres (cells of ``limit`` metres: a flagged image has none in its cell and the 8
    around it). For sets that may span several cities or UTM zones (a gmberton split, an MSLS city across a
    zone edge), where one median position means nothing, but a lone image far from all others is a typo."""
    utm = np.asarray(utm, dtype=np.float64).reshape(-1, 2)
    if len(utm) < 2:
        return
    cells = np.floor(np.clip(utm, -1e12, 1e12) / limit).astype(np.int64)
    cells -= cells.min(axis=0) - 1
    width = int(cells[:, 1].max()) + 2
    keys = cells[:, 0] * width + cells[:, 1]
    uniq, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    lone = np.flatnonzero(counts == 1)
    if not len(lone):
        return
    around = np.array([dx * width + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy], dtype=np.int64)
    alone = ~np.isin(uniq[lone][:, None] + around[None, :], uniq).any(axis=1)
    if not alone.any():
        return
    idx = np.flatnonzero(np.isin(inv.reshape(-1), lone[alone]))
    i = int(idx[0])
    others = np.delete(utm, i, axis=0)
    nearest = float(np.linalg.norm(others - utm[i], axis=1).min())
    warnings.warn(f"{source}: {len(idx)} image(s) have no other image within {limit:,.0f} m (e.g. {image(i)} at "
                  f"easting {utm[i, 0]:.2f}, northing {utm[i, 1]:.2f} m, {nearest / 1000:,.1f} km from the nearest "
                  f"other); the images of a dataset come in streets and routes, so its geotag is likely wrong "
                  f"(a mistyped digit?): fix or drop it", stacklevel=stacklevel + 1)


__all__ = ["check_utm", "check_latlon", "warn_far_from_median", "warn_isolated", "UTM_EASTING_RANGE",
           "UTM_NORTHING_RANGE", "LAT_POLE", "LAT_LIMIT", "LON_LIMIT", "PLACE_SPREAD_M", "CITY_SPAN_M"]
