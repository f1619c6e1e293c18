"""The registry of losses: :data:`LOSSES` maps a loss name of the run config to its loss object class."""
from __future__ import annotations

from .multi_similarity import MultiSimilarityLoss
from .triplet import CETripletLoss, DWTripletLoss, TripletFamilyLoss, TripletLoss, WeightedTripletLoss

# The one map from a loss name (the run config's ``source.loss``) to its loss object; each class's parameters
# are named as the run config's source fields (vpr_nb.config.build_loss). A new loss: a class in its module
# and a line here.
LOSSES = {
    "triplet": TripletLoss,                 # Eq. (3) of DW-T-Loss
    "weighted": WeightedTripletLoss,        # Eq. (4) x Eq. (3), W-T-Loss
    "ce": CETripletLoss,                    # Eqs. (5)-(8), CE-Loss
    "dw": DWTripletLoss,                    # Eq. (9), DW-T-Loss
    "multi-similarity": MultiSimilarityLoss,  # Wang et al. Eq. (6) + miner: the loss of place batches
}
TRIPLET_LOSSES = tuple(k for k, cls in LOSSES.items() if issubclass(cls, TripletFamilyLoss))
