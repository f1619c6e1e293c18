"""Conditions: the illumination, season and weather of an image, as a small table of rendering parameters.

A :class:`~vpr_nb.synthetic.config.WorldConfig` names its conditions (``db_condition``,
``query_conditions``) from :data:`CONDITIONS`; a query's parameters are interpolated from the database
condition towards its own by ``condition_strength`` (:func:`condition_params`). The table is part of
the world: :func:`vpr_nb.results.world_fingerprint` covers the rows a world uses.
"""
from __future__ import annotations

import numpy as np

# The database uses the first condition of a world (``db_condition``).
CONDITIONS = {
    #            brightness, tint (rgb),        sun azimuth/deg, ambient, sky rgb,            foliage,  snow, fog m, noise, lit windows
    "summer":   dict(bright=1.00, tint=(1.00, 1.00, 1.00), sun=135.0, ambient=0.55, sky=(0.55, 0.72, 0.95), foliage=(0.20, 0.50, 0.15), snow=0.0, fog=400.0, noise=0.015, lit=0.0),
    "overcast": dict(bright=0.80, tint=(0.95, 0.97, 1.02), sun=135.0, ambient=0.95, sky=(0.70, 0.72, 0.75), foliage=(0.22, 0.42, 0.18), snow=0.0, fog=120.0, noise=0.03, lit=0.0),
    "dusk":     dict(bright=0.50, tint=(1.25, 0.85, 0.65), sun=290.0, ambient=0.45, sky=(0.95, 0.55, 0.35), foliage=(0.20, 0.35, 0.15), snow=0.0, fog=250.0, noise=0.04, lit=1.0),
    "autumn":   dict(bright=0.92, tint=(1.08, 0.98, 0.88), sun=200.0, ambient=0.65, sky=(0.65, 0.72, 0.85), foliage=(0.75, 0.40, 0.10), snow=0.0, fog=200.0, noise=0.02, lit=0.0),
    "winter":   dict(bright=1.05, tint=(0.92, 0.97, 1.08), sun=170.0, ambient=0.80, sky=(0.78, 0.80, 0.84), foliage=(0.35, 0.30, 0.25), snow=1.0, fog=150.0, noise=0.03, lit=0.0),
    "rain":     dict(bright=0.65, tint=(0.90, 0.95, 1.00), sun=135.0, ambient=0.90, sky=(0.45, 0.47, 0.50), foliage=(0.15, 0.35, 0.15), snow=0.0, fog=60.0, noise=0.045, lit=0.3),
}


def condition_params(cfg, name: str) -> dict:
    """The parameters of condition ``name`` in world ``cfg``: interpolated from the database condition
    by ``cfg.condition_strength`` (sun azimuth the short way round, fog in 1 / distance)."""
    base, tgt = CONDITIONS[cfg.db_condition], CONDITIONS[name]
    s = cfg.condition_strength if name != cfg.db_condition else 0.0
    out = {}
    for k in base:
        b, t = np.asarray(base[k], dtype=float), np.asarray(tgt[k], dtype=float)
        if k == "sun":  # interpolate angles the short way
            d = (t - b + 180) % 360 - 180
            out[k] = float(b + s * d)
        elif k == "fog":  # interpolate in 1/distance
            out[k] = float(1.0 / ((1 - s) / b + s / t))
        else:
            out[k] = b + s * (t - b)
    return out


def stack_conditions(conds: list[dict]) -> dict[str, np.ndarray]:
    """The condition parameters of N cameras as arrays with one row per camera (sun azimuth in radians)."""
    out = {k: np.array([c[k] for c in conds]) for k in conds[0]}
    out["sun"] = np.array([np.radians(c["sun"]) for c in conds])
    return out
