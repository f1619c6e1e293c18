"""What a fine-tuning experiment varies, a :class:`Method`: a loss, an aggregator and a batch sampler."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field

from .. import losses as L
from .._checks import check_int, check_positive
from ..aggregation import AGGREGATOR_NAMES
from .protocol import Recipe

BATCHES = ("triplets", "places")


@dataclass(frozen=True)
class Method:
    """What a fine-tuning experiment varies; the rest is the :class:`Recipe`.

    Args:
        name: the row's label.
        aggregator: one of :data:`vpr_nb.aggregation.AGGREGATOR_NAMES` (sizes from the recipe, overridden
            by ``aggregator_kwargs``).
        loss: a loss object: triplet-family (:class:`vpr_nb.losses.TripletLoss`, ``WeightedTripletLoss``,
            ``CETripletLoss``, ``DWTripletLoss``) for ``batches="triplets"``, ``MultiSimilarityLoss`` for
            ``"places"``; ``None``: ``TripletLoss(recipe.margin)`` / ``MultiSimilarityLoss()``.
        batches: ``"triplets"``, ``"places"`` or a callable ``(train_split, recipe, loss) -> source`` (an object
            with ``steps(model, rng)``, e.g. a :class:`PlaceBatchSource` subclass).
        trainable_blocks: ``None``: the recipe's; 0 trains the head alone on a frozen backbone.
        paper_lr: the paper's learning rate rescaled to this recipe (the notebook says how); added to the grid.
    """

    name: str
    aggregator: str = "gem"
    loss: object = None
    batches: str | Callable = "triplets"
    aggregator_kwargs: Mapping = field(default_factory=dict)
    trainable_blocks: int | None = None
    paper_lr: float | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        if self.aggregator not in AGGREGATOR_NAMES:
            raise ValueError(f"unknown aggregator {self.aggregator!r}; valid names are {', '.join(AGGREGATOR_NAMES)}")
        if not callable(self.batches) and self.batches not in BATCHES:
            raise ValueError(f"batches must be one of {BATCHES} or a callable (train_split, recipe, loss) -> source, "
                             f"got {self.batches!r}")
        if self.batches == "triplets" and self.loss is not None and not isinstance(self.loss, L.TripletFamilyLoss):
            raise ValueError(f"triplet batches need a triplet-family loss (TripletLoss, WeightedTripletLoss, "
                             f"CETripletLoss, DWTripletLoss), got {self.loss!r}")
        if self.batches == "places" and self.loss is not None and (isinstance(self.loss, L.TripletFamilyLoss)
                                                                   or not callable(self.loss)):
            raise ValueError(f"place batches need a loss called as loss(embeddings, labels), e.g. "
                             f"MultiSimilarityLoss(), got {self.loss!r}")
        if not isinstance(self.aggregator_kwargs, Mapping):
            raise ValueError(f"aggregator_kwargs must be a dict, got {type(self.aggregator_kwargs).__name__}")
        if self.trainable_blocks is not None:
            check_int(self.trainable_blocks, "trainable_blocks", minimum=0, maximum=4)
        if self.paper_lr is not None:
            check_positive(self.paper_lr, "paper_lr")

    def to_dict(self) -> dict:
        """The method as plain data (for a notebook's ``EXPERIMENT`` config)."""
        loss = None if self.loss is None else {"class": type(self.loss).__name__, **(
            asdict(self.loss) if hasattr(self.loss, "__dataclass_fields__") else {})}
        batches = self.batches if isinstance(self.batches, str) else (
            getattr(self.batches, "name", None) or getattr(self.batches, "__name__", "custom"))
        return {"name": self.name, "aggregator": self.aggregator, "loss": loss, "batches": batches,
                "aggregator_kwargs": dict(self.aggregator_kwargs), "trainable_blocks": self.trainable_blocks,
                "paper_lr": self.paper_lr}

    def lr_grid(self, recipe: Recipe) -> tuple[float, ...]:
        """The learning rates :func:`lr_search` tries: the recipe's grid and ``paper_lr``, ascending."""
        grid = set(recipe.lr_grid) | ({float(self.paper_lr)} if self.paper_lr is not None else set())
        return tuple(sorted(grid))


def _check_method(method) -> Method:
    if not isinstance(method, Method):
        raise ValueError(f"method must be a vpr_nb.recipe.Method, got {type(method).__name__}")
    return method
