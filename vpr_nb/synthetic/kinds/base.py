"""The record of a world kind: everything that differs between the city, the route and any new kind."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np


@dataclass(frozen=True)
class WorldKind:
    """One kind of synthetic world, as data and the three functions that make it differ.

    ``preset`` holds the kind's deviations from the :class:`~vpr_nb.synthetic.config.WorldConfig`
    defaults (the defaults are the city's), ``sizes`` the deviations of each world size; ``fields``
    names the config fields only this kind reads (the other kinds ignore them). ``layout(cfg, rng)``
    lays out the :class:`~vpr_nb.synthetic.layout.Scene`, ``cameras(cfg, rng, scene)`` places the
    :class:`~vpr_nb.synthetic.cameras.Cameras`, ``ground(points, scene.layout, snow)`` gives the
    ground's colour (P, 3) and snow cover (P,) at ground points (P, 2); ``skyline_colour`` is the far
    skyline's rgb. ``pos_radius_frames``: when set, the positive radius defaults to that many frame
    spacings (a frame-aligned benchmark such as Nordland). ``check(cfg)`` raises ValueError for
    kind-specific limits.
    """

    name: str
    description: str
    layout: Callable
    cameras: Callable
    ground: Callable
    skyline_colour: np.ndarray
    fields: frozenset = frozenset()
    preset: Mapping = field(default_factory=dict)
    sizes: Mapping = field(default_factory=lambda: {"tiny": {}})
    pos_radius_frames: float | None = None
    check: Callable | None = None
