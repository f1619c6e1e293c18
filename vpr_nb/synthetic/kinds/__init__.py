"""The world kinds: one module per kind, each defining one :class:`WorldKind` record, registered below.

A new kind of world (a harbour, a campus, ...) is one module here, laying out its scene, placing its
cameras and texturing its ground with the blocks of :mod:`vpr_nb.synthetic.layout` and
:mod:`vpr_nb.synthetic.cameras`, plus one line in ``_KINDS``; its new scene knobs are
:class:`~vpr_nb.synthetic.config.WorldConfig` fields, listed in the record's ``fields``.
"""
from __future__ import annotations

from .base import WorldKind
from .city import CITY
from .route import ROUTE

_KINDS = (
    CITY,
    ROUTE,
)
WORLD_KINDS: dict[str, WorldKind] = {k.name: k for k in _KINDS}


def world_kind(name: str) -> WorldKind:
    """The record of world kind ``name`` (a ``preset`` of :func:`~vpr_nb.synthetic.make_dataset`)."""
    if name not in WORLD_KINDS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(WORLD_KINDS)}")
    return WORLD_KINDS[name]


__all__ = ["WorldKind", "WORLD_KINDS", "world_kind", "CITY", "ROUTE"]
