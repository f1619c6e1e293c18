"""Which places go into a training batch: geotag/place batch samplers (CliqueMining, random places).

=========================================  ===================================================================
:mod:`~vpr_nb.samplers.clique`             :func:`clique_batches` (CliqueMining, Izquierdo & Civera, ECCV 2024:
                                           places that look alike yet lie apart, cliques of a geographic
                                           graph), :class:`CliqueBatchMaker` (the same for the training loop,
                                           group descriptors from the model, once or every E epochs),
                                           :func:`sample_group_descriptors`
:mod:`~vpr_nb.samplers.clique_miner`       the index and clique search behind them (built once per data set)
:mod:`~vpr_nb.samplers.places`             :func:`random_place_batches` (GSV-Cities: random places, random
                                           images of each; every place once per epoch, one city per batch),
                                           :class:`RandomPlaceBatches`, :class:`MixedPlaceBatches` (several
                                           samplers side by side, e.g. GSV-Cities + clique places)
:mod:`~vpr_nb.samplers.statistics`         :func:`batch_statistics`: how close and how alike a batch's places are
=========================================  ===================================================================

A sampler decides *which images* form a batch from geotags and place ids (as pytorch-metric-learning's
samplers do); the descriptor miners that pick pairs or triplets inside a batch or a database live in
:mod:`vpr_nb.mining`. Every sampler takes a ``seed`` or a ``np.random.Generator`` and returns the same
output for the same seed. Distances between geotags are Euclidean distances of UTM (easting, northing)
in metres; region (city) labels keep cities apart.
"""
from __future__ import annotations

from .clique import CliqueBatchMaker, clique_batches, sample_group_descriptors
from .clique_miner import _DENSE_MAX, _checked_miner  # noqa: F401 (bench/bench_mining.py measures the index)
from .places import MixedPlaceBatches, RandomPlaceBatches, random_place_batches
from .statistics import batch_statistics

__all__ = ["clique_batches", "CliqueBatchMaker", "sample_group_descriptors", "random_place_batches",
           "RandomPlaceBatches", "MixedPlaceBatches", "batch_statistics"]
