"""The place batch source: P places x K images per batch with the Multi-Similarity loss (GSV-Cities, CliqueMining).

:class:`PlaceBatchSource` takes batches from a sampler (:func:`vpr_nb.samplers.random_place_batches` or
:func:`vpr_nb.samplers.clique_batches`) and a :class:`vpr_nb.losses.MultiSimilarityLoss` object (loss and
miner); with ``loss_groups`` one loss per slice of places, summed (CliqueMining's training step: GSV-Cities
half + clique half). The source builds batches; the loss object it is given holds the loss's parameters.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .. import losses as L
from .._checks import check_int
from ..image_tensors import as_image_array, images_to_tensor
from .divergence import NotFinite


class PlaceBatchSource:
    """Batches of P places x K images with the Multi-Similarity loss (Wang et al., CVPR 2019, Eq. 6).

    ``make_batches(model, epoch, rng)`` returns an int array ``(num_batches, P, K)`` of indices into
    ``images`` (for example :func:`vpr_nb.samplers.random_place_batches` or
    :func:`vpr_nb.samplers.clique_batches` on descriptors from ``model``); images in the same place slot
    share a label. ``loss`` is a :class:`vpr_nb.losses.MultiSimilarityLoss` object (its ``alpha``, ``beta``,
    ``base`` and ``miner_epsilon``; default: the SALAD / GSV-Cities recipe), called as
    ``loss(embeddings, labels)``.

    ``loss_groups=(P1, P2, ...)`` (summing to P) splits every batch into consecutive slices of places and
    computes one loss (with its own miner) per slice, then sums them: the places of two slices are never
    each other's negatives. This is CliqueMining's training step (``serizba/cliquemining``
    ``training_step``: one MS loss over the GSV-Cities places, one over the MSLS clique places, summed),
    ``PlaceBatchSource(images, make_batches, loss_groups=(30, 30))``. None: one loss over all P places.
    """

    def __init__(self, images, make_batches: Callable, *, loss: L.MultiSimilarityLoss = L.MultiSimilarityLoss(),
                 loss_groups: tuple[int, ...] | None = None):
        self.x = as_image_array(images)
        images_to_tensor(self.x[:1])           # validates shape and dtype
        if not callable(make_batches):
            raise ValueError("make_batches must be a callable (model, epoch, rng) -> (num_batches, P, K) indices")
        if isinstance(loss, L.TripletFamilyLoss) or not callable(loss):
            raise ValueError(f"loss must be a place-batch loss called as loss(embeddings, labels), e.g. "
                             f"vpr_nb.losses.MultiSimilarityLoss(alpha, beta, base, miner_epsilon), got {loss!r}; "
                             f"triplet-family losses go with TripletSource")
        if loss_groups is not None:
            loss_groups = tuple(check_int(g, "loss_groups entry") for g in loss_groups)
            if not loss_groups:
                raise ValueError("loss_groups must list the places of each loss, e.g. (30, 30), or be None")
        self.make_batches, self.loss, self.loss_groups = make_batches, loss, loss_groups
        self.epoch = 0

    def state_dict(self) -> dict:
        """The sampler's state when ``make_batches`` has one (e.g. CliqueMining's group descriptors), so
        that a resumed run draws the same batches as an uninterrupted one."""
        sd = getattr(self.make_batches, "state_dict", None)
        return {"sampler": sd()} if callable(sd) else {}

    def load_state_dict(self, state: dict) -> None:
        if "sampler" in state:
            load = getattr(self.make_batches, "load_state_dict", None)
            if not callable(load):
                raise ValueError("the checkpoint holds a sampler state but this make_batches has no "
                                 "load_state_dict; resume with the same source.sampler")
            load(state["sampler"])

    def no_step_reason(self) -> str:
        """Why an epoch took no step (for :func:`train_epoch`'s error)."""
        return ("make_batches gave no batch of places: check that enough places have images_per_place images "
                "(source.places_per_batch, source.images_per_place, source.batches_per_epoch)")

    def _groups(self, p: int, shard: tuple[int, int]) -> list[np.ndarray]:
        """The place slots of each loss group that this process (``shard=(rank, world)``) takes."""
        sizes = self.loss_groups or (p,)
        if sum(sizes) != p:
            raise ValueError(f"loss_groups {sizes} cover {sum(sizes)} places but make_batches gives {p} per batch")
        rank, world = shard
        if min(sizes) < world:
            raise ValueError(f"every loss group needs at least one place per process: loss_groups {sizes}, "
                             f"{world} processes")
        starts = np.concatenate([[0], np.cumsum(sizes)])
        return [np.arange(a, b)[rank::world] for a, b in zip(starts[:-1], starts[1:])]

    def steps(self, model, rng: np.random.Generator, shard: tuple[int, int] = (0, 1), device=None):
        """One loss per batch (the sum over ``loss_groups``); with ``shard=(rank, world)`` each process
        takes every world-th place of each group."""
        batches = np.asarray(self.make_batches(model, self.epoch, rng))
        if batches.ndim != 3 or not np.issubdtype(batches.dtype, np.integer):
            raise ValueError(f"make_batches must return an integer array (num_batches, P, K), got {batches.shape}")
        if batches.size and (batches.min() < 0 or batches.max() >= len(self.x)):
            raise ValueError(f"make_batches returned indices outside [0, {len(self.x) - 1}]")
        groups = self._groups(batches.shape[1], shard)
        batches = batches[:, np.concatenate(groups)]
        k = batches.shape[2]
        ends = np.cumsum([len(g) * k for g in groups])
        parts = [(slice(e - len(g) * k, e), torch.arange(len(g), device=device).repeat_interleave(k))
                 for g, e in zip(groups, ends)]
        for batch in batches:
            emb = model(images_to_tensor(self.x[batch.reshape(-1)]).to(device)).float()
            if not torch.isfinite(emb).all():
                raise NotFinite("descriptors")
            same = torch.nn.functional.normalize(torch.ones_like(emb.detach()), dim=1)   # every descriptor equal
            if len(parts) == 1:
                self.last_collapsed_loss = float(self.loss(same, parts[0][1]))
                yield self.loss(emb, parts[0][1])
            else:
                self.last_collapsed_loss = float(sum(self.loss(same[s], y) for s, y in parts))
                yield sum(self.loss(emb[s], y) for s, y in parts)
