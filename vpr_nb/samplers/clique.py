"""CliqueMining batches (Izquierdo & Civera, ECCV 2024): places that look alike yet lie apart.

* :func:`clique_batches` -- batches of places that are visually similar yet geographically separated,
  found as cliques of a geographic graph (the index and search: :mod:`vpr_nb.samplers.clique_miner`).
* :class:`CliqueBatchMaker` -- the same for the training loop (``make_batches`` of
  :class:`vpr_nb.training.PlaceBatchSource`), with group descriptors from the current model computed once
  (the original) or refreshed every E epochs; :meth:`CliqueBatchMaker.from_pool` over a split's place pool.
* :func:`sample_group_descriptors` -- one descriptor per place group (CliqueMining's group descriptors).
"""
from __future__ import annotations

import numpy as np
import torch

from .._checks import as_float_matrix, as_utm, check_int
from ..evaluation import as_image_array, compute_descriptors
from ..split import PlacePool
from ._common import _as_groups, _as_rng, _group_index
from .clique_miner import _checked_miner


def clique_batches(utm, groups, group_descriptors, places_per_batch: int, images_per_place: int = 4,
                   same_place_threshold: float = 25.0, similar_groups: int = 15, num_batches: int = 1,
                   seed: int | np.random.Generator = 0, num_workers: int = 1, *, regions=None,
                   headings=None, max_heading_diff: float | None = None) -> np.ndarray:
    """CliqueMining batches (Izquierdo & Civera, ECCV 2024, Sec. 4 and ``create_dataset_part``).

    Each batch is built as in the authors' code:

    1. pick a *region* (MSLS city) with probability proportional to its number of place groups,
       never one already used in this batch, and an *anchor* place-group uniformly in it;
    2. draw ``similar_groups`` other groups **of the same region** without replacement with
       probability proportional to ``max_j d_j - d_i``, where ``d_i`` is the Euclidean distance
       between the descriptors of group ``i`` and of the anchor over the region's groups (linear
       weights, anchor weight 0; if all weights are 0 the draw is uniform), so visually similar
       groups of the same city, usually close by, are likely;
    3. build the geographic graph on all images of these groups: an edge joins two images whose
       UTM distance is ``< same_place_threshold`` (and, with ``max_heading_diff``, whose headings
       differ by at most that many degrees);
    4. take a clique of ``>= images_per_place`` images as one place and keep ``images_per_place``
       random members of it: they are pairwise closer than the threshold;
    5. remove the chosen images *and every image within the threshold of them*, so that all
       later places are ``>= same_place_threshold`` from every chosen image (hard negatives);
    6. repeat 4-5 until the batch is full or no clique is left, then go back to 1 with a new
       region and keep filling the same batch.

    Remaining differences from the original code:

    * which clique: the original takes the first maximal clique of ``networkx.find_cliques``
      (DFS order, over the pool in MSLS row order); here the drawn groups are scanned in a seeded
      random order, each group's images by index, and a place is the maximal clique grown greedily
      (earliest in that order first) from the first alive image that lies in a clique of
      ``>= images_per_place`` images. Scanning the whole pool by index instead filled a batch from the
      lowest-index groups drawn: on a route numbered along its track, 0.94 of the places sat in its
      first quarter (notebook 07 before this order);
    * ``regions=None`` means one region (the whole data set, as one MSLS city); once every region
      was used in a batch, regions may repeat (the original would stop); images within the
      threshold of places of the anchor's region already in the batch are removed before each new
      anchor, so every pair of places of one region in a batch is ``>= threshold`` apart, across
      anchors too (the original never meets its earlier places again because it moves to another
      city). Places of different regions never block each other: the regions' UTM coordinates may
      overlap (different zones), so region labels alone keep cities apart;
    * the similar groups are drawn among the group ids that have images (the original also
      draws ids with no image, whose zero descriptor rows give them a positive weight);
    * the heading test (``max_heading_diff``) is an option the original does not have (MSLS
      clusters are taken as they are); removal around a chosen place ignores headings;
    * the graph is built once per anchor instead of a new ``networkx.Graph`` from a dense adjacency
      matrix for every place: for pools of up to 2048 images (16 MSLS-like groups hold a few hundred)
      each image's neighbours are one Python-int bit set and the clique search and removals are bit
      operations on them, with an alive bit set; larger pools use a k-d tree and Python sets (same
      places, same random numbers). The per-region index is built once per call (once per run in
      :class:`CliqueBatchMaker`), so a batch costs the same at 10k and 1M images
      (``bench/bench_mining.py``);
    * batches are reproducible: batch ``b`` uses ``SeedSequence(seed).spawn(num_batches)[b]``,
      so the output does not depend on ``num_workers`` (the original seeds from pid and time).

    The group descriptors are used as given: the original computes them once, offline, with the
    pre-trained model (one random image per group). :class:`CliqueBatchMaker` wraps this function
    for the training loop and takes them given, computes them once, or refreshes them every E epochs.

    Args:
        utm: ``(N, 2)`` UTM positions in metres, one per image.
        groups: ``(N,)`` non-negative place-group id of each image (MSLS ``unique_cluster``).
        group_descriptors: ``(G, D)`` one descriptor per group id ``0..G-1``, ``G > max(groups)``
            (rows of ids without images are ignored and may be zero).
        places_per_batch: places per batch (30 in the paper).
        images_per_place: images per place, >= 2 (4 in the paper).
        same_place_threshold: metres; images closer than this are the same place (25 in the paper).
        similar_groups: number of visually similar groups drawn besides the anchor (15).
        num_batches: number of batches.
        seed: int seed (or a Generator that provides one).
        num_workers: processes (``multiprocessing`` "spawn" context) when > 1; same output.
        regions: ``(N,)`` city / region label of each image (any sortable dtype); a group must not
            span two regions. None: one region.
        headings: ``(N,)`` camera headings in degrees (only with ``max_heading_diff``).
        max_heading_diff: degrees; two images are joined in the clique graph only if their headings
            differ by at most this (None: no heading test, as published).

    Returns:
        int64 array ``(num_batches, places_per_batch, images_per_place)`` of image indices.

    Raises:
        ValueError: on bad inputs, or when a batch cannot be filled after
            ``max(100, 10 * places_per_batch)`` anchors (too few separated places in the data).
    """
    if group_descriptors is None:
        raise ValueError("group_descriptors is required: one descriptor row per group id")
    miner = _checked_miner(utm, groups, group_descriptors, places_per_batch, images_per_place,
                           same_place_threshold, similar_groups, regions, headings, max_heading_diff)
    return miner.mine(check_int(num_batches, "num_batches"), seed, check_int(num_workers, "num_workers"))


def sample_group_descriptors(descriptors, groups, seed: int | np.random.Generator = 0) -> np.ndarray:
    """One descriptor per place group: that of one random image of the group (CliqueMining's
    ``compute_cluster_descriptors``, which samples one image per ``unique_cluster``).

    Args:
        descriptors: ``(N, D)`` image descriptors.
        groups: ``(N,)`` non-negative group id of each image.
        seed: int seed or Generator choosing the image of each group.

    Returns:
        float32 ``(max(groups) + 1, D)``; rows of ids without images are zero.
    """
    desc = as_float_matrix(descriptors, "descriptors")
    present, pick, num = _one_image_per_group(_as_groups(groups, len(desc)), seed)
    out = np.zeros((num, desc.shape[1]), dtype=np.float32)
    out[present] = desc[pick]
    return out


def _one_image_per_group(groups: np.ndarray, seed) -> tuple[np.ndarray, np.ndarray, int]:
    """(ids of the non-empty groups, one random image index of each, number of group ids)."""
    rng = _as_rng(seed)
    order, starts = _group_index(groups)
    sizes = np.diff(starts)
    present = np.flatnonzero(sizes > 0)
    pick = order[starts[present] + (rng.random(len(present)) * sizes[present]).astype(np.int64)].astype(np.int64)
    return present, pick, len(sizes)


class CliqueBatchMaker:
    """``make_batches(model, epoch, rng)`` for :class:`vpr_nb.training.PlaceBatchSource` with CliqueMining.

    The per-region index of :func:`clique_batches` is built once, here. The group descriptors are
    ``group_descriptors`` when given (the original: descriptors of a pre-trained model, computed
    once, offline), else they come from ``model`` (one random image per group, as in the original
    code; only those images are encoded, so ``images`` may be a lazy on-disk array).
    ``refresh_every=None`` keeps the first descriptors for the whole run (computed at the first call
    if not given); ``refresh_every=E`` recomputes them with the current model at every epoch that is a
    multiple of E. Each call mines ``num_batches`` fresh batches, seeded from ``rng``.

    Attributes:
        refreshed_at: epochs at which the descriptors were computed from the model.
    """

    def __init__(self, images, utm, groups, places_per_batch: int, num_batches: int, *,
                 images_per_place: int = 4, same_place_threshold: float = 25.0, similar_groups: int = 15,
                 refresh_every: int | None = None, num_workers: int = 1, group_descriptors=None,
                 regions=None, headings=None, max_heading_diff: float | None = None):
        self.images = as_image_array(images)   # numpy, or a lazy on-disk ImageArray (only indexed images are read)
        self.utm = as_utm(utm, "utm")
        self.groups = _as_groups(groups, len(self.utm))
        if len(self.images) != len(self.utm):
            raise ValueError(f"images has {len(self.images)} entries but utm has {len(self.utm)}: one geotag per image")
        self.num_batches = check_int(num_batches, "num_batches")
        self.num_workers = check_int(num_workers, "num_workers")
        self.refresh_every = None if refresh_every is None else check_int(refresh_every, "refresh_every")
        self.miner = _checked_miner(self.utm, self.groups, group_descriptors, places_per_batch, images_per_place,
                                    same_place_threshold, similar_groups, regions, headings, max_heading_diff)
        self.group_descriptors: np.ndarray | None = None
        if group_descriptors is not None:
            self.group_descriptors = as_float_matrix(group_descriptors, "group_descriptors").copy()
        self.refreshed_at: list[int] = []

    @classmethod
    def from_pool(cls, pool: PlacePool, places_per_batch: int, num_batches: int, **kwargs) -> "CliqueBatchMaker":
        """CliqueMining over a split's :meth:`~vpr_nb.split.Split.place_pool`: its place ids numbered
        compactly (one group descriptor row per place) and its cities as regions (similar groups and
        cliques within the anchor's city, as published). The batches index ``pool.images``."""
        if not isinstance(pool, PlacePool):
            raise ValueError(f"pool must be a split's place_pool(), got {type(pool).__name__}")
        groups = np.unique(pool.places, return_inverse=True)[1].reshape(-1)
        regions = None if pool.regions is None else \
            np.unique(np.asarray(pool.regions).astype(str), return_inverse=True)[1].reshape(-1)
        return cls(pool.images, pool.utm, groups, places_per_batch, num_batches, regions=regions, **kwargs)

    def state_dict(self) -> dict:
        """The group descriptors in use and the refresh epochs (for exact resume from a checkpoint)."""
        d = self.group_descriptors
        return {"group_descriptors": None if d is None else torch.from_numpy(d.copy()),
                "refreshed_at": [int(e) for e in self.refreshed_at]}

    def load_state_dict(self, state: dict) -> None:
        d = state.get("group_descriptors")
        self.group_descriptors = None if d is None else np.asarray(d, dtype=np.float32).copy()
        if self.group_descriptors is not None:
            self.miner.set_descriptors(self.group_descriptors)
        self.refreshed_at = [int(e) for e in state.get("refreshed_at", [])]

    def __call__(self, model, epoch: int, rng: np.random.Generator) -> np.ndarray:
        rng = _as_rng(rng)
        due = self.refresh_every is not None and epoch % self.refresh_every == 0
        if self.group_descriptors is None or (due and epoch not in self.refreshed_at):
            # one random image per group (sample_group_descriptors); only those images are encoded
            present, pick, num = _one_image_per_group(self.groups, rng)
            desc = compute_descriptors(getattr(model, "module", model), self.images[pick])  # restores train/eval mode
            self.group_descriptors = np.zeros((num, desc.shape[1]), dtype=np.float32)
            self.group_descriptors[present] = desc
            self.refreshed_at.append(int(epoch))
        if self.miner.sqnorm is None or self._set_from is not self.group_descriptors:
            self.miner.set_descriptors(self.group_descriptors)
            self._set_from = self.group_descriptors
        return self.miner.mine(self.num_batches, int(rng.integers(2**63)), self.num_workers)

    _set_from = None

