"""Training losses for VPR: the triplet family of DW-T-Loss and Multi-Similarity.

One idea per module, in the spirit of pytorch-metric-learning's ``losses/``; every name is re-exported here:

======================================  ==================================================================
:mod:`~vpr_nb.losses.triplet`           the triplet family of DW-T-Loss (Xiong, Xu, Meng), Eqs. (3)-(9):
                                        :func:`triplet_loss` (Eq. (3)), :func:`distance_weight` (Eq. (4)),
                                        :func:`weighted_triplet_loss` (Eq. (4) x (3)), :func:`ce_triplet_loss`
                                        (Eqs. (5)-(8)), :func:`dw_triplet_loss` (Eq. (9)) and their loss
                                        objects (:class:`TripletFamilyLoss` and its subclasses)
:mod:`~vpr_nb.losses.placebo`           the placebo of DW-T-Loss: Eq. (9) with the batch's query-positive distances
                                        permuted across its queries (:class:`PlaceboDWTripletLoss`), which keeps
                                        the weights' values and removes their ranking
:mod:`~vpr_nb.losses.normalised`        DW-T-Loss with its weight divided by its batch mean
                                        (:class:`BatchMeanDWTripletLoss`): the ranking without the scale
:mod:`~vpr_nb.losses.multi_similarity`  Multi-Similarity (Wang et al., CVPR 2019), as used to train SALAD and
                                        CliqueMining through pytorch-metric-learning: :func:`multi_similarity_loss`
                                        (Eq. (6)), :func:`multi_similarity_miner` (Sec. 3.3) and
                                        :class:`MultiSimilarityLoss`
:mod:`~vpr_nb.losses.infonce`           :func:`local_infonce`, the local InfoNCE term (Eq. L) of the course
                                        backbone's pretraining (:mod:`vpr_nb.pretrain`)
:mod:`~vpr_nb.losses.registry`          :data:`LOSSES`, the map from a loss name of the run config to its loss
                                        object, and :data:`TRIPLET_LOSSES`
:mod:`~vpr_nb.losses._common`           the input checks and the reduction that the loss functions share
======================================  ==================================================================

Loss objects, for the batch sources of :mod:`vpr_nb.training`: each holds its parameters, validated when
it is built, and calls its loss function with them (the same floating-point operations):

==============================  ==============  ================================================  ================
object                          paper equation  parameters                                        source
==============================  ==============  ================================================  ================
:class:`TripletLoss`            Eq. (3)         ``margin``                                        TripletSource
:class:`WeightedTripletLoss`    Eq. (4) x (3)   ``margin``, ``sigma``, ``eps``                    TripletSource
:class:`CETripletLoss`          Eqs. (5)-(8)    (none)                                            TripletSource
:class:`DWTripletLoss`          Eq. (9)         ``sigma``, ``eps``                                TripletSource
:class:`PlaceboDWTripletLoss`   Eq. (9)         ``sigma``, ``eps``, ``seed``                      TripletSource
:class:`MultiSimilarityLoss`    Wang Eq. (6)    ``alpha``, ``beta``, ``base``, ``miner_epsilon``  PlaceBatchSource
==============================  ==============  ================================================  ================

:class:`BatchMeanDWTripletLoss` (Eq. (9) with the weight over its batch mean; ``sigma``, ``eps``) is a triplet-family
object too.

Every default value lives once, in the ``DEFAULT_*`` constants of its loss's module (``DEFAULT_MARGIN``,
``DEFAULT_SIGMA``, ``DEFAULT_EPS`` in :mod:`~vpr_nb.losses.triplet`, ``DEFAULT_MS_*`` in
:mod:`~vpr_nb.losses.multi_similarity`), which both the functions and the classes use.
"""
from __future__ import annotations

from .infonce import LOCAL_NEGATIVES, local_infonce
from .multi_similarity import MultiSimilarityLoss, multi_similarity_loss, multi_similarity_miner
from .normalised import BatchMeanDWTripletLoss, batch_mean_dw_triplet_loss
from .placebo import PlaceboDWTripletLoss, placebo_dw_triplet_loss, placebo_permutation
from .registry import LOSSES, TRIPLET_LOSSES
from .triplet import (
    CETripletLoss,
    DWTripletLoss,
    TripletFamilyLoss,
    TripletLoss,
    WeightedTripletLoss,
    ce_triplet_loss,
    distance_weight,
    dw_triplet_loss,
    triplet_loss,
    weighted_triplet_loss,
)

# the defaults and the miner's output type, importable from here as before (not part of ``import *``)
from .multi_similarity import (DEFAULT_MS_ALPHA, DEFAULT_MS_BASE, DEFAULT_MS_BETA,  # noqa: F401
                               DEFAULT_MS_MINER_EPSILON, MinerPairs)
from .triplet import DEFAULT_EPS, DEFAULT_MARGIN, DEFAULT_SIGMA  # noqa: F401

__all__ = [
    "triplet_loss",
    "distance_weight",
    "weighted_triplet_loss",
    "ce_triplet_loss",
    "dw_triplet_loss",
    "placebo_dw_triplet_loss",
    "placebo_permutation",
    "batch_mean_dw_triplet_loss",
    "multi_similarity_loss",
    "multi_similarity_miner",
    "local_infonce",
    "LOCAL_NEGATIVES",
    "TripletFamilyLoss",
    "TripletLoss",
    "WeightedTripletLoss",
    "CETripletLoss",
    "DWTripletLoss",
    "PlaceboDWTripletLoss",
    "BatchMeanDWTripletLoss",
    "MultiSimilarityLoss",
    "LOSSES",
    "TRIPLET_LOSSES",
]
