"""WGS84 latitude/longitude -> UTM easting/northing (metres), for the formats that ship lat/lon
(GSV-Cities); every other format already stores UTM. No pyproj: Krüger's series, see :func:`latlon_to_utm`.
"""
from __future__ import annotations

import math

import numpy as np

from .._checks import check_int
from .geotags import LAT_LIMIT, LON_LIMIT

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
        first = int(np.flatnonzero(~(np.isfinite(lat) & np.isfinite(lon)).ravel())[0])
        raise ValueError(f"lat/lon contain NaN or inf (first at flat index {first})")
    bad = np.flatnonzero(((np.abs(lat) > LAT_LIMIT) | (np.abs(lon) > LON_LIMIT)).ravel())
    if len(bad):
        i = int(bad[0])
        raise ValueError(f"lat must be within [-{LAT_LIMIT:g}, {LAT_LIMIT:g}] and lon within [-{LON_LIMIT:g}, "
                         f"{LON_LIMIT:g}] degrees for UTM; {len(bad)} "
                         f"position(s) are not, first at flat index {i}: lat={lat.ravel()[i]:g}, lon={lon.ravel()[i]:g}")
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


__all__ = ["utm_zone", "latlon_to_utm"]
