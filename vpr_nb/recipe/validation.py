"""The validation world of the city notebooks and :func:`validation_split`, which renders its validation split."""
from __future__ import annotations

from collections.abc import Mapping

from ..synthetic import make_dataset

# The validation world of the city notebooks (03, 05). The fine-tuning world (city seed 0) has a validation
# split of 133 queries, where one query is 0.0075 of Recall@1, the size of the differences between epochs and
# grid points, so best-on-validation selection there keeps noise (measured on notebook 03's T-Loss, 5 seeds:
# test R@1 minus the start +0.016 ± 0.025 with lr and epochs selected on those 133 queries, +0.030 ± 0.009
# selected on this world's 803). A second city, seed 1 (never pretrained on, trained or tested
# on), almost all of it validation, has 803 queries, above ``Recipe.min_val_queries``.
VALIDATION_WORLD = {"preset": "city", "seed": 1, "size": "tiny", "overrides": {"split_fractions": (0.1, 0.8, 0.1)}}


def validation_split(world: Mapping = VALIDATION_WORLD):
    """The validation split of ``world`` (a dict ``preset``, ``seed``, optional ``size`` and ``overrides``, as a
    notebook's experiment config names a world; default :data:`VALIDATION_WORLD`)."""
    if not isinstance(world, Mapping) or not isinstance(world.get("preset"), str) or "seed" not in world:
        raise ValueError(f"world must be a dict with 'preset' and 'seed' (and optional 'size', 'overrides'), "
                         f"got {world!r}")
    return make_dataset(world["preset"], seed=world["seed"], size=world.get("size", "tiny"), splits=("val",),
                        **dict(world.get("overrides") or {})).val
