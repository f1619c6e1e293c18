"""A method's starting model (the epoch-0 candidate) and its batch source, built the recipe's way."""
from __future__ import annotations

import dataclasses
import pickle
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .. import losses as L
from .._checks import check_int, check_positive
from ..feature_cache import FrozenFeatureCache, attach
from ..mining import check_positive_rule
from ..models import build_model, init_netvlad, init_salad, init_salad_scores_from_kmeans
from ..pretrain import course_backbone, place_labels
from ..samplers import random_place_batches
from ..seeding import seed_everything
from ..training import PlaceBatchSource, TripletSource
from .method import Method, _check_method
from .protocol import RECIPE, Recipe, _check_recipe


def build_start(method: Method, train_split, recipe: Recipe = RECIPE, seed: int = 0,
                cache: FrozenFeatureCache | None = None):
    """The starting model of ``method`` (the epoch-0 candidate): the course backbone read before or after its
    final ReLU (``recipe.after_relu``), the recipe's trainable blocks and the aggregator, initialised from the
    training database (NetVLAD: k-means; SALAD: standardised head inputs, and with
    ``recipe.salad_kmeans_scores`` its score head set to NetVLAD's k-means logits, the same k-means as NetVLAD's
    start of this seed: :func:`vpr_nb.models.init_salad_scores_from_kmeans`). Seeded by ``seed``; with
    ``cache`` attached to the backbone (the caller detaches it)."""
    method, recipe = _check_method(method), _check_recipe(recipe)
    seed = check_int(seed, "seed", minimum=0)
    seed_everything(seed)
    blocks = recipe.trainable_blocks if method.trainable_blocks is None else method.trainable_blocks
    backbone = course_backbone(trainable_blocks=blocks, final_relu=method.aggregator in recipe.after_relu)
    if cache is not None:
        attach(backbone, cache)
    model = build_model(backbone, method.aggregator,
                        **{**recipe.aggregator_kwargs(method.aggregator), **method.aggregator_kwargs})
    if method.aggregator == "netvlad":
        init_netvlad(model, train_split.db_images, per_image=recipe.netvlad_per_image, niter=recipe.netvlad_niter,
                     seed=seed)
    elif method.aggregator == "salad":
        if recipe.salad_standardise:
            init_salad(model, train_split.db_images)
        if recipe.salad_kmeans_scores:
            init_salad_scores_from_kmeans(model, train_split.db_images, per_image=recipe.netvlad_per_image,
                                          niter=recipe.netvlad_niter, seed=seed,
                                          temperature=recipe.salad_kmeans_temperature)
    return model


def place_batch_labels(split, recipe: Recipe = RECIPE) -> np.ndarray:
    """Place label of every image of ``split`` (database first, then queries) for P × K place batches.

    City: :func:`vpr_nb.pretrain.place_labels` (``recipe.spots_per_place`` street spots × view-direction
    quadrant, notebook 05). Other worlds: the world's own place groups (``db_place`` / ``q_place``; the route's
    5-frame groups, notebook 06): the route's cameras face about 0°, so their headings straddle the
    quadrant boundary at 360° and a quadrant split would cut a place in two."""
    if getattr(getattr(split, "config", None), "preset", None) == "city":
        return place_labels(split, recipe.spots_per_place)
    return np.concatenate([split.db_place, split.q_place]).astype(np.int64)


def make_source(method: Method, train_split, recipe: Recipe = RECIPE):
    """The batch source of ``method`` on ``train_split`` with the recipe's batch settings."""
    method, recipe = _check_method(method), _check_recipe(recipe)
    if callable(method.batches):
        return method.batches(train_split, recipe, method.loss)
    if method.batches == "triplets":
        return TripletBatches("triplets")(train_split, recipe, method.loss)
    labels = place_batch_labels(train_split, recipe)                    # database first, then queries
    images = np.concatenate([train_split.db_images, train_split.q_images])

    def batches(_model, _epoch, rng):
        return random_place_batches(labels, recipe.places_per_batch, recipe.images_per_place,
                                    num_batches=recipe.place_batches_per_epoch, seed=rng)

    return PlaceBatchSource(images, batches, loss=method.loss or L.MultiSimilarityLoss())


@dataclass(frozen=True)
class TripletBatches:
    """A :class:`Method`'s ``batches`` for the recipe's triplet batches with another positive rule or training
    radius (notebook 03's premise worlds): ``positive`` is ``"best"`` (NetVLAD's rule, the recipe's) or
    ``"random"`` (one potential positive drawn at random, from the step's seeded stream, so arms stay
    paired); ``train_pos_radius`` in metres replaces the split's (``None``: the split's, 10 m on the city)."""

    name: str
    positive: str = "best"
    train_pos_radius: float | None = None

    def __post_init__(self):
        check_positive_rule(self.positive)
        if self.train_pos_radius is not None:
            check_positive(self.train_pos_radius, "train_pos_radius")

    def __call__(self, train_split, recipe, loss):
        if self.train_pos_radius is not None:
            train_split = dataclasses.replace(train_split, train_pos_radius=float(self.train_pos_radius))
        return TripletSource(train_split, loss or L.TripletLoss(margin=recipe.margin),
                             batch_size=recipe.batch_size, num_negatives=recipe.num_negatives,
                             num_candidates=recipe.num_candidates, max_heading_diff=recipe.max_heading_diff,
                             positive=self.positive)


@dataclass(eq=False)
class PlaceBatches:
    """A :class:`Method`'s ``batches`` for place batches the recipe does not build itself: ``make_batches(model,
    epoch, rng)`` (e.g. :class:`vpr_nb.samplers.MixedPlaceBatches` of random and clique halves) over ``images``,
    with one loss per part of ``loss_groups`` (CliqueMining's two-loss step). Picklable when ``make_batches``
    is (the package's samplers are), so :func:`search_methods` can run it in worker processes. Each source it
    makes gets its own copy of ``make_batches`` (a pickle round trip, as a worker process gets it): a sampler
    with state (CliqueMining's group descriptors) never carries one fine-tune's state into the next fine-tune
    run in the same process, so a task gives the same bits whatever ran before it."""

    name: str
    images: np.ndarray
    make_batches: Callable
    loss_groups: tuple[int, ...] | None = None

    def __call__(self, train_split, recipe, loss):
        try:
            make = pickle.loads(pickle.dumps(self.make_batches))
        except (pickle.PicklingError, AttributeError, TypeError):    # e.g. a lambda: nothing to copy, no state
            make = self.make_batches
        return PlaceBatchSource(self.images, make, loss=loss or L.MultiSimilarityLoss(), loss_groups=self.loss_groups)
