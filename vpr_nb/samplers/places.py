"""Random-place batches (the GSV-Cities sampler) and batches that put several samplers side by side.

* :func:`random_place_batches` -- P random places x K random images of each: independent draws, or
  (``each_place_once``) every place in turn once per epoch, optionally every batch from one city
  (``one_city``, GSV-Cities' ``shuffle_all=False`` as SALAD trains);
* :class:`RandomPlaceBatches` -- the same as ``make_batches`` of :class:`vpr_nb.training.PlaceBatchSource`;
* :class:`MixedPlaceBatches` -- the places of several samplers in one batch, each over its own images
  (CliqueMining's step: GSV-Cities places, then MSLS clique places).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .._checks import check_int
from ._common import _as_groups, _as_rng, _group_index


class _Places:
    """The places with at least ``k`` images (sorted ids), their images and, with ``regions``, their cities."""

    def __init__(self, groups, places_per_batch: int, images_per_place: int, regions=None, one_city: bool = False):
        groups = _as_groups(groups, None)
        self.p = check_int(places_per_batch, "places_per_batch")
        self.k = check_int(images_per_place, "images_per_place", minimum=2)
        self.order, self.starts = _group_index(groups)
        self.places = np.flatnonzero(np.diff(self.starts) >= self.k)
        if len(self.places) < self.p:
            raise ValueError(f"only {len(self.places)} places have >= {self.k} images but a batch needs {self.p} "
                             f"distinct places; lower places_per_batch or images_per_place")
        self.one_city = bool(one_city)
        if regions is not None:
            regions = np.asarray(regions)
            if regions.shape != groups.shape:
                raise ValueError(f"regions must have one label per image, shape {groups.shape}; got {regions.shape}")
            self.city = {int(g): regions[self.order[self.starts[g]]] for g in self.places}
        else:
            self.city = {int(g): 0 for g in self.places}
        self.cities = list(dict.fromkeys(self.city[int(g)] for g in self.places))
        self.by_city = {c: np.array([g for g in self.places if self.city[int(g)] == c]) for c in self.cities}
        small = [c for c in self.cities if len(self.by_city[c]) < self.p]
        if one_city and small:
            raise ValueError(f"one city per batch: city(ies) {small} have fewer than {self.p} places; lower "
                             f"places_per_batch or draw batches across cities")

    def members(self, g: int) -> np.ndarray:
        return self.order[self.starts[g]:self.starts[g + 1]]

    def independent(self, num_batches: int, rng: np.random.Generator) -> np.ndarray:
        """Each batch: P distinct places drawn uniformly, K distinct images of each."""
        out = np.empty((num_batches, self.p, self.k), dtype=np.int64)
        for b in range(num_batches):
            for j, g in enumerate(rng.choice(self.places, self.p, replace=False)):
                out[b, j] = rng.choice(self.members(g), self.k, replace=False)
        return out

    def in_turn(self, num_batches: int, rng: np.random.Generator) -> np.ndarray:
        """The places shuffled (within each city, city after city, with ``one_city``) and taken P at a time,
        wrapping around; a batch that would repeat a place or (``one_city``) cross a city boundary is filled
        with unused places of its first city."""
        if self.one_city:
            seq = np.concatenate([rng.permutation(self.by_city[c]) for c in self.cities])
        else:
            seq = rng.permutation(self.places)
        out = np.empty((num_batches, self.p, self.k), dtype=np.int64)
        for b in range(num_batches):
            chunk = [int(seq[(b * self.p + j) % len(seq)]) for j in range(self.p)]
            if len(set(chunk)) < self.p:          # wrapped onto itself (tiny data): fill with unused places
                chunk = list(dict.fromkeys(chunk))
                rest = [int(g) for g in rng.permutation(self.places) if int(g) not in chunk]
                chunk += rest[:self.p - len(chunk)]
            if self.one_city:
                c = self.city[chunk[0]]
                keep = [g for g in chunk if self.city[g] == c]
                if len(keep) < self.p:            # a batch at a city boundary: fill it from its first city
                    used = set(keep)
                    spare = [int(g) for g in rng.permutation(self.by_city[c]) if int(g) not in used]
                    chunk = keep + spare[:self.p - len(keep)]
            for j, g in enumerate(chunk):
                out[b, j] = rng.choice(self.members(g), self.k, replace=False)
        return out


def random_place_batches(groups, places_per_batch: int, images_per_place: int = 4, *,
                         num_batches: int = 1, seed: int | np.random.Generator = 0, each_place_once: bool = False,
                         regions=None, one_city: bool = False) -> np.ndarray:
    """GSV-Cities batches: random places, random images of each place.

    The places are the groups with at least ``images_per_place`` images; each gets ``images_per_place``
    distinct random images. By default every batch draws ``places_per_batch`` distinct places uniformly.
    With ``each_place_once`` the places are shuffled once and taken in turn (GSV-Cities' epoch: every
    place once in ``ceil(places / places_per_batch)`` batches); with ``one_city`` as well, they are
    shuffled within each city (``regions``: one label per image) and every batch comes from one city.
    Unlike :func:`vpr_nb.samplers.clique_batches` nothing keeps two places of a batch apart.

    Returns:
        int64 array ``(num_batches, places_per_batch, images_per_place)`` of image indices.
    """
    if one_city and not each_place_once:
        raise ValueError("one_city takes the places city by city in turn: pass each_place_once=True too")
    places = _Places(groups, places_per_batch, images_per_place, regions, one_city)
    num_batches, rng = check_int(num_batches, "num_batches"), _as_rng(seed)
    return places.in_turn(num_batches, rng) if each_place_once else places.independent(num_batches, rng)


class RandomPlaceBatches:
    """``make_batches(model, epoch, rng)`` of :func:`random_place_batches` for
    :class:`vpr_nb.training.PlaceBatchSource`: ``num_batches`` batches per call (one epoch), seeded from
    ``rng``; by default every place once per epoch (``each_place_once``), as GSV-Cities trains."""

    def __init__(self, groups, places_per_batch: int, images_per_place: int, num_batches: int, *,
                 each_place_once: bool = True, regions=None, one_city: bool = False):
        if one_city and not each_place_once:
            raise ValueError("one_city takes the places city by city in turn: pass each_place_once=True too")
        self.places = _Places(groups, places_per_batch, images_per_place, regions, one_city)
        self.num_batches, self.each_place_once = check_int(num_batches, "num_batches"), bool(each_place_once)

    def __call__(self, model, epoch: int, rng: np.random.Generator) -> np.ndarray:
        rng = _as_rng(int(_as_rng(rng).integers(2**63)))
        draw = self.places.in_turn if self.each_place_once else self.places.independent
        return draw(self.num_batches, rng)


class MixedPlaceBatches:
    """Batches whose places come from several samplers side by side (CliqueMining: GSV-Cities places, then
    MSLS clique places). Part ``i`` indexes its own images, which start at ``offsets[i]`` in the images of
    the :class:`vpr_nb.training.PlaceBatchSource`; its places follow those of part ``i - 1`` in every batch.
    ``state_dict`` holds the states of the parts that have one (CliqueMining's group descriptors)."""

    def __init__(self, parts: Sequence, offsets: Sequence[int]):
        if len(parts) != len(offsets) or not parts or not all(callable(p) for p in parts):
            raise ValueError("give one make_batches callable per offset")
        self.parts, self.offsets = list(parts), [check_int(o, "offset", minimum=0) for o in offsets]

    def __call__(self, model, epoch: int, rng: np.random.Generator) -> np.ndarray:
        return np.concatenate([np.asarray(p(model, epoch, rng)) + o for p, o in zip(self.parts, self.offsets)], axis=1)

    def _stateful(self):
        return {str(i): p for i, p in enumerate(self.parts) if callable(getattr(p, "state_dict", None))}

    def state_dict(self) -> dict:
        return {i: p.state_dict() for i, p in self._stateful().items()}

    def load_state_dict(self, state: dict) -> None:
        for i, p in self._stateful().items():
            if i in state:
                p.load_state_dict(state[i])
