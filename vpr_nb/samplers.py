"""Which places go into a training batch: geotag/place batch samplers (CliqueMining, random places).

* :func:`clique_batches` -- CliqueMining (Izquierdo & Civera, ECCV 2024): batches of places that
  are visually similar yet geographically separated, found as cliques of a geographic graph.
* :class:`CliqueBatchMaker` -- CliqueMining batches for the training loop, with group descriptors
  from the current model computed once (the original) or refreshed every E epochs.
* :func:`random_place_batches` -- the GSV-Cities baseline: random places, random images of each.
* :func:`batch_statistics` -- how close and how alike the places of a batch are.
* :func:`sample_group_descriptors` -- one descriptor per place group (CliqueMining's group descriptors).

A sampler decides *which images* form a batch from geotags and place ids (as pytorch-metric-learning's
samplers do); the descriptor miners that pick pairs or triplets inside a batch or a database live in
:mod:`vpr_nb.mining`.

Every function takes a ``seed`` or a ``np.random.Generator`` and returns the same output for the
same seed. Distances between geotags are Euclidean distances of UTM (easting, northing) in metres.
"""
from __future__ import annotations

import multiprocessing

import numpy as np
from scipy.spatial import cKDTree

from vpr_nb._checks import as_float_matrix, as_utm, check_int, check_positive

_MIN_ANCHORS = 100  # a batch gives up after max(_MIN_ANCHORS, _ANCHORS_PER_PLACE * places) anchors
_ANCHORS_PER_PLACE = 10
_DENSE_MAX = 2048      # pools of up to this many images use the dense bit-set path (else k-d tree + sets)
_CHUNK = 1 << 16       # elements per temporary in the dense distance loops (bounded memory)


# ----------------------------------------------------------------------------- input checks
def _as_groups(groups, n: int | None) -> np.ndarray:
    """Validate a 1-D array of non-negative integer group ids (one per image)."""
    arr = np.asarray(groups)
    if arr.ndim != 1:
        raise ValueError(f"groups must be a 1-D array with one place-group id per image, got shape {arr.shape}")
    if len(arr) == 0:
        raise ValueError("groups is empty: give one place-group id per image")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"groups must hold integers (place-group ids), got dtype {arr.dtype}")
    if arr.min() < 0:
        raise ValueError(f"groups must be non-negative ids, found {int(arr.min())}")
    if n is not None and len(arr) != n:
        raise ValueError(f"groups has {len(arr)} entries but utm has {n} rows: give one group id per image")
    return arr.astype(np.int64, copy=False)   # no copy of int64 ids (the index never writes to them)


def _seed_sequences(seed, n: int) -> list[np.random.SeedSequence]:
    """One independent SeedSequence per batch, derived from an int seed or a Generator."""
    if isinstance(seed, np.random.Generator):
        seed = int(seed.integers(2**63))
    elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int or a np.random.Generator, got {seed!r}")
    return np.random.SeedSequence(int(seed)).spawn(n)


def _as_rng(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool) and rng >= 0:
        return np.random.default_rng(int(rng))
    raise ValueError(f"rng must be a np.random.Generator (or a non-negative int seed), got {rng!r}")


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance of broadcastable (..., 2) UTM arrays, in metres."""
    return np.sqrt(((a - b) ** 2).sum(axis=-1))


def _planar_sq(ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
    """``(ax - bx)^2 + (ay - by)^2`` of broadcastable easting/northing arrays: the float operations of
    :func:`_dist` before its square root, without the slow reduction over a length-2 axis."""
    dx = ax - bx
    dy = ay - by
    np.multiply(dx, dx, out=dx)
    np.multiply(dy, dy, out=dy)
    dx += dy
    return dx


def _sqrt_limit(threshold: float) -> float:
    """The float64 ``t`` with ``sqrt(s) < threshold  <=>  s < t`` for every float64 ``s >= 0``.

    ``np.sqrt`` is correctly rounded, hence monotonic, so ``{s : sqrt(s) < threshold}`` is an interval
    ``[0, t)``; ``t`` is the smallest float whose root reaches the threshold, found by stepping from
    ``threshold ** 2`` one ulp at a time (at most a few steps).
    """
    thr = np.float64(threshold)
    t = thr * thr
    while np.sqrt(t) >= thr:
        t = np.nextafter(t, -np.inf)
    while np.sqrt(t) < thr:
        t = np.nextafter(t, np.inf)
    return float(t)


def _check_regions(regions: np.ndarray, groups: np.ndarray, present: np.ndarray, first: np.ndarray) -> None:
    """Raise ValueError unless every image carries the region label of its group's first image.

    Compared in blocks of images (bounded memory); NaN labels count as one label, as in ``np.unique``.
    """
    label = np.empty(int(groups.max()) + 1, dtype=regions.dtype)
    label[present] = regions[first]
    nan = regions.dtype.kind in "fc"
    for s in range(0, len(groups), _CHUNK):
        a, b = regions[s:s + _CHUNK], label[groups[s:s + _CHUNK]]
        same = np.asarray(a == b, dtype=bool)
        if nan:
            same |= (a != a) & (b != b)
        if not same.all():
            raise ValueError("every image of a place group must be in the same region (city): "
                             "give groups that do not span regions")


def _group_index(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order, starts)``: the images of group ``g`` are ``order[starts[g]:starts[g + 1]]``.

    ``order`` is ``np.argsort(groups, kind="stable")`` (images of a group in ascending index), built
    as a counting sort over blocks of ``_CHUNK`` images, so no temporary has the size of the data set;
    it is int32 when the indices fit (half the memory of int64).
    """
    counts = np.bincount(groups)
    starts = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    order = np.empty(len(groups), dtype=np.int32 if len(groups) < 2**31 else np.int64)
    cursor = starts[:-1].copy()   # next free slot of each group in ``order``
    for s in range(0, len(groups), _CHUNK):
        g = groups[s:s + _CHUNK]
        o = np.argsort(g, kind="stable")          # the block's images, by group, ascending within a group
        gs = g[o]
        run = np.flatnonzero(np.concatenate([[True], gs[1:] != gs[:-1]]))   # first position of each group
        lens = np.diff(np.append(run, len(gs)))
        ids = gs[run]
        order[np.repeat(cursor[ids] - run, lens) + np.arange(len(gs))] = o + s
        cursor[ids] += lens
    return order, starts


# ----------------------------------------------------------------------------- CliqueMining
def _grow_clique(clique: list[int], cand: list[int], adj, m: int) -> list[int] | None:
    """Depth-first search for a clique of ``m`` nodes extending ``clique`` with nodes of ``cand``.

    Every node of ``cand`` is adjacent to every node of ``clique``; ``adj(u)`` is u's neighbour set.
    """
    if len(clique) >= m:
        return clique
    for pos, u in enumerate(cand):
        if len(clique) + len(cand) - pos < m:
            return None
        nu = adj(u)
        found = _grow_clique(clique + [u], [w for w in cand[pos + 1:] if w in nu], adj, m)
        if found is not None:
            return found
    return None


def _grow_clique_bits(clique: list[int], cand: int, adj: list[int], m: int) -> list[int] | None:
    """:func:`_grow_clique` on bit sets: ``cand`` and ``adj[u]`` are Python ints, bit ``w`` set for node ``w``.

    The candidates are visited in ascending order with the same pruning, so the result is the clique
    :func:`_grow_clique` returns for the sorted candidate list.
    """
    if len(clique) >= m:
        return clique
    left = cand.bit_count()
    while cand:
        if len(clique) + left < m:
            return None
        low = cand & -cand
        u = low.bit_length() - 1
        cand ^= low
        left -= 1
        found = _grow_clique_bits(clique + [u], cand & adj[u], adj, m)
        if found is not None:
            return found
    return None


def _bit_rows(mask: np.ndarray) -> list[int]:
    """Row ``i`` of a boolean ``(n, n)`` matrix as a Python int whose bit ``j`` is ``mask[i, j]``."""
    packed = np.packbits(mask, axis=1, bitorder="little")
    raw, w = packed.tobytes(), packed.shape[1]
    return [int.from_bytes(raw[i * w:(i + 1) * w], "little") for i in range(len(mask))]


def _bits(flags: np.ndarray) -> int:
    """A boolean vector as a Python int (bit ``i`` is ``flags[i]``)."""
    return int.from_bytes(np.packbits(flags, bitorder="little").tobytes(), "little")


class _CliqueMiner:
    """The index shared by every batch (built once; picklable for worker processes).

    Built once per image set: the images of each group (``order``/``starts``), the present groups
    sorted by region (``present``, with region ``r`` owning ``present[rstarts[r]:rstarts[r + 1]]``),
    and, after :meth:`set_descriptors`, their descriptors in the same order (a view of the given
    descriptors when every region's groups are consecutive ids, as with compact ids city after city;
    else a reordered copy). A batch then touches only the anchor region's groups and the images of
    the drawn groups: its cost does not grow with the number of images or regions.
    """

    def __init__(self, utm: np.ndarray, groups: np.ndarray, group_descriptors: np.ndarray | None,
                 places_per_batch: int, images_per_place: int, threshold: float, similar_groups: int,
                 regions: np.ndarray | None = None, headings: np.ndarray | None = None,
                 max_heading_diff: float | None = None):
        self.utm = utm
        self.order, self.starts = _group_index(groups)
        present = np.flatnonzero(np.diff(self.starts) > 0)  # group ids that have images
        if regions is None:
            greg = np.zeros(len(present), dtype=np.int64)
        else:
            regions = np.asarray(regions)
            first = self.order[self.starts[present]]       # each group's first image
            _check_regions(regions, groups, present, first)
            # every region has a group, so the labels of the groups' first images are all the labels:
            # the same sorted region ids as over all images, without sorting every image's label
            greg = np.unique(regions[first], return_inverse=True)[1].reshape(-1)
        ro = np.argsort(greg, kind="stable")
        self.present = present[ro]
        counts = np.bincount(greg)
        self.rstarts = np.concatenate([[0], np.cumsum(counts)])
        self.rlist = np.flatnonzero(counts > 0)              # regions that have groups
        self.rweight = counts[self.rlist].astype(np.float64)  # P(region) ∝ its number of groups (as published)
        self.headings = None if headings is None else np.asarray(headings, dtype=np.float64)
        self.max_heading_diff = max_heading_diff
        self.similar = similar_groups
        self.places = places_per_batch
        self.m = images_per_place
        self.threshold = threshold
        self.sq_limit = _sqrt_limit(threshold)
        self.max_anchors = max(_MIN_ANCHORS, _ANCHORS_PER_PLACE * places_per_batch)
        # every region's groups are consecutive ids: its descriptors are a slice of the given ones
        last = self.rstarts[self.rlist + 1] - 1
        self.consecutive = bool(np.all(self.present[last] - self.present[self.rstarts[self.rlist]] ==
                                       last - self.rstarts[self.rlist]))
        self.desc = self.sqnorm = self.gdesc = None
        if group_descriptors is not None:
            self.set_descriptors(group_descriptors)

    def set_descriptors(self, group_descriptors: np.ndarray) -> None:
        """Use these ``(G, D)`` group descriptors (rows indexed by group id).

        Kept without a copy when every region's groups are consecutive ids (then the rows of region
        ``r`` are one slice); else the rows of the present groups are copied in region order.
        """
        if self.consecutive:
            self.gdesc, self.desc = np.ascontiguousarray(group_descriptors), None
            sq = np.einsum("ij,ij->i", self.gdesc, self.gdesc)   # row by row: the same values as on a copy
            self.sqnorm = sq[self.present]
        else:
            self.gdesc, self.desc = None, np.ascontiguousarray(group_descriptors[self.present])
            self.sqnorm = np.einsum("ij,ij->i", self.desc, self.desc)

    def _descriptors(self, lo: int, hi: int) -> np.ndarray:
        """The descriptors of the groups ``present[lo:hi]``, in that order."""
        if self.gdesc is None:
            return self.desc[lo:hi]
        first = int(self.present[lo])
        if int(self.present[hi - 1]) - first == hi - 1 - lo:   # consecutive ids (always within a region)
            return self.gdesc[first:first + hi - lo]
        return self.gdesc[self.present[lo:hi]]

    @property
    def k_similar(self) -> int:  # over the whole data set (one region); per region see similar_groups
        return min(self.similar, len(self.present) - 1)

    def similar_groups(self, anchor: int, rng: np.random.Generator, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """Anchor + ``similar_groups`` groups of its region drawn without replacement, P ∝ (max d - d).

        ``anchor`` indexes ``present``; the region is ``present[lo:hi]`` (all groups by default).
        ``d`` is the descriptor distance to the anchor over the region's groups. Sampling uses the
        exponential race (the k smallest ``E_j / w_j``), which has the law of successive draws
        without replacement. Zero-weight groups (the farthest one; all of them when every distance
        is equal) are drawn uniformly, only after every positive-weight group.
        """
        if self.sqnorm is None:
            raise ValueError("no group descriptors: call set_descriptors first")
        hi = len(self.present) if hi is None else hi
        desc, sq, a = self._descriptors(lo, hi), self.sqnorm[lo:hi], anchor - lo
        k = min(self.similar, hi - lo - 1)
        # einsum, not ``@``: a multi-threaded BLAS gemv is ~50x slower on an oversubscribed machine
        d2 = sq + sq[a] - 2.0 * np.einsum("ij,j->i", desc, desc[a])
        d = np.sqrt(np.maximum(d2, 0.0))
        w = d.max() - d
        e = rng.standard_exponential(len(w))
        w[a], e[a] = 0.0, np.inf  # the anchor is never drawn
        pos = np.flatnonzero(w > 0)
        if len(pos) >= k:
            pick = pos[np.argpartition(e[pos] / w[pos], k - 1)[:k]] if k else pos[:0]
        else:
            zero = np.flatnonzero(w <= 0)
            rest = k - len(pos)
            pick = np.concatenate([pos, zero[np.argpartition(e[zero], rest - 1)[:rest]]])
        return self.present[lo + np.concatenate([[a], pick]).astype(np.int64)]

    def neighbours(self, pool: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], cKDTree]:
        """For each image of ``pool``: (the sorted pool positions of the other images closer than the
        threshold, the same restricted to images facing the same way, the pool's k-d tree) -- the
        second list is the clique graph, the first one what is removed around a chosen place."""
        pts = self.utm[pool]
        n = len(pts)
        tree = cKDTree(pts)
        ij = tree.query_pairs(self.threshold * (1 + 1e-9), output_type="ndarray")
        ij = ij[_dist(pts[ij[:, 0]], pts[ij[:, 1]]) < self.threshold]
        geo = self._lists(ij, n)
        if self.headings is None or self.max_heading_diff is None:
            return geo, geo, tree
        h = self.headings[pool]
        ok = np.abs((h[ij[:, 0]] - h[ij[:, 1]] + 180.0) % 360.0 - 180.0) <= self.max_heading_diff
        return geo, self._lists(ij[ok], n), tree

    @staticmethod
    def _lists(ij: np.ndarray, n: int) -> list[np.ndarray]:
        rows = np.concatenate([ij[:, 0], ij[:, 1]]).astype(np.int64)
        cols = np.concatenate([ij[:, 1], ij[:, 0]]).astype(np.int64)
        key = rows * n + cols                      # sort the (row, col) keys themselves, not a permutation
        key.sort()
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])
        cols = key % n
        return [cols[indptr[v]:indptr[v + 1]] for v in range(n)]

    dense_max = _DENSE_MAX   # class attribute: tests set it to 0 to check that both paths agree

    def places_in_pool(self, pool: np.ndarray, blocked: np.ndarray, need: int,
                       rng: np.random.Generator) -> list[np.ndarray]:
        """Up to ``need`` places (arrays of ``m`` image indices) from the images in ``pool``.

        Steps 3-6 of :func:`clique_batches` (Eqs. (2) and (4) of the paper). Pools of up to
        ``dense_max`` images (every pool of 16 MSLS-like groups) use :meth:`_places_dense`, larger
        ones :meth:`_places_sets`; both return the same places and draw the same random numbers.
        """
        if len(pool) <= self.dense_max:
            return self._places_dense(pool, blocked, need, rng)
        return self._places_sets(pool, blocked, need, rng)

    def _dense_graph(self, pool: np.ndarray, blocked: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(geo, nbrs, alive)`` over the pool: ``geo[i, j]``, images closer than the threshold;
        ``nbrs``, the same pairs that also pass the heading test (the clique graph of Eq. (2));
        ``alive``, images not within the threshold of a ``blocked`` position.

        The test ``sqrt(dx^2 + dy^2) < threshold`` of :meth:`neighbours` (same float operations; the
        pair distance is symmetric) is evaluated as ``dx^2 + dy^2 < self.sq_limit``, which holds for
        exactly the same float values (see :func:`_sqrt_limit`), row block by row block.
        """
        pts = self.utm[pool]
        n = len(pts)
        x, y = pts[:, 0].copy(), pts[:, 1].copy()
        geo = np.zeros((n, n), dtype=bool)
        step = min(64, max(1, _CHUNK // n))
        for s in range(0, n, step):    # the blocks on and above the diagonal, then mirrored (the distance
            geo[s:s + step, s:] = _planar_sq(x[s:s + step, None], y[s:s + step, None], x[s:], y[s:]) < self.sq_limit
        np.fill_diagonal(geo, False)   # is symmetric, so the lower half of a diagonal block is already right)
        geo |= geo.T
        alive = np.ones(n, dtype=bool)
        if len(blocked):
            bx, by = blocked[:, 0].copy(), blocked[:, 1].copy()
            step = max(1, _CHUNK // len(blocked))
            for s in range(0, n, step):
                near = _planar_sq(x[s:s + step, None], y[s:s + step, None], bx, by) < self.sq_limit
                alive[s:s + step] = ~near.any(axis=1)
        if self.headings is None or self.max_heading_diff is None:
            return geo, geo, alive
        i, j = np.nonzero(np.triu(geo, 1))            # pairs i < j, oriented as neighbours() orients them
        h = self.headings[pool]
        ok = np.abs((h[i] - h[j] + 180.0) % 360.0 - 180.0) <= self.max_heading_diff
        nbrs = np.zeros((n, n), dtype=bool)
        nbrs[i[ok], j[ok]] = True
        nbrs[j[ok], i[ok]] = True
        return geo, nbrs, alive

    def _places_dense(self, pool: np.ndarray, blocked: np.ndarray, need: int,
                      rng: np.random.Generator) -> list[np.ndarray]:
        """:meth:`_places_sets` with the graph as Python-int bit sets (one per image) built from dense
        boolean matrices: intersections are one machine operation per 64 images, so a pool of a few
        hundred images costs a few hundred big-int operations instead of Python sets."""
        geo_m, nbr_m, alive_v = self._dense_graph(pool, blocked)
        nbrs = _bit_rows(nbr_m)
        geo = nbrs if nbr_m is geo_m else _bit_rows(geo_m)
        alive = _bits(alive_v)
        m = self.m
        found: list[np.ndarray] = []
        todo = alive          # the alive images not visited yet; visited in ascending index
        while todo:
            low = todo & -todo
            v = low.bit_length() - 1
            todo ^= low
            cand = nbrs[v] & alive
            if cand.bit_count() < m - 1:
                continue
            clique = _grow_clique_bits([v], cand, nbrs, m)
            if clique is None:
                continue
            common = cand        # alive neighbours of v that are adjacent to the whole clique
            for c in clique[1:]:
                common &= nbrs[c]
            while common:        # grow to a maximal clique, smallest index first
                bit = common & -common
                u = bit.bit_length() - 1
                clique.append(u)
                common &= nbrs[u]
            chosen = rng.choice(np.sort(clique), m, replace=False)
            found.append(pool[chosen])
            if len(found) == need:
                break
            for c in chosen.tolist():
                alive &= ~((1 << c) | geo[c])
            todo &= alive
        return found

    def _places_sets(self, pool: np.ndarray, blocked: np.ndarray, need: int,
                     rng: np.random.Generator) -> list[np.ndarray]:
        """Up to ``need`` places (arrays of ``m`` image indices) from the images in ``pool``.

        Images closer than the threshold to a ``blocked`` position (images already in the batch)
        are removed first. Then, scanning the pool in ascending image index, the first alive image
        that belongs to a clique of >= m alive images gives a place: that clique is grown greedily
        to a maximal clique, m random members are taken, and they and all their geographic
        neighbours (any heading) are removed. An image that is in no such clique now never will be
        (the graph only shrinks), so each image is visited once.
        """
        alive = np.ones(len(pool), dtype=bool)
        geo, nbrs, tree = self.neighbours(pool)
        if len(blocked):   # pool images within the threshold of an image already in the batch
            near = tree.query_ball_point(blocked, self.threshold * (1 + 1e-9), return_sorted=False)
            cand = np.unique(np.fromiter((i for lst in near for i in lst), dtype=np.int64))
            if len(cand):
                pts = self.utm[pool[cand]]
                hit = (_dist(pts[:, None, :], blocked[None, :, :]) < self.threshold).any(axis=1)
                alive[cand[hit]] = False
        sets: dict[int, set[int]] = {}

        def adj(u: int) -> set[int]:
            if u not in sets:
                sets[u] = set(nbrs[u].tolist())
            return sets[u]

        found: list[np.ndarray] = []
        for v in range(len(pool)):
            if len(found) == need:
                break
            if not alive[v] or len(nbrs[v]) < self.m - 1:
                continue
            cand = nbrs[v][alive[nbrs[v]]].tolist()
            clique = _grow_clique([v], cand, adj, self.m)
            if clique is None:
                continue
            common = set(cand)  # alive neighbours of v that are adjacent to the whole clique
            for c in clique[1:]:
                common &= adj(c)
            while common:  # grow to a maximal clique, smallest index first
                u = min(common)
                clique.append(u)
                common &= adj(u)  # u has no self-loop, so it leaves ``common``
            chosen = rng.choice(np.sort(clique), self.m, replace=False)
            found.append(pool[chosen])
            alive[chosen] = False
            for c in chosen:
                alive[geo[c]] = False
        return found

    def batch(self, index: int, seed: np.random.SeedSequence) -> np.ndarray:
        """One ``(places, m)`` batch; raises ValueError when the data cannot fill it."""
        if self.sqnorm is None:
            raise ValueError("no group descriptors: call set_descriptors first")
        rng = np.random.default_rng(seed)
        places: list[np.ndarray] = []
        blocked = np.empty((0, 2))
        used = np.zeros(len(self.rlist), dtype=bool)
        for _ in range(self.max_anchors):
            if len(self.rlist) == 1:   # one region: no draw, so regions=None mines what it always did
                r = 0
            else:   # a region not used yet in this batch (all again once every one was used), P ∝ groups
                if used.all():
                    used[:] = False
                w = np.where(used, 0.0, self.rweight)
                r = int(rng.choice(len(w), p=w / w.sum()))
                used[r] = True
            lo, hi = int(self.rstarts[self.rlist[r]]), int(self.rstarts[self.rlist[r] + 1])
            anchor = lo + int(rng.integers(hi - lo))
            groups = self.similar_groups(anchor, rng, lo, hi)
            pool = np.sort(np.concatenate([self.order[self.starts[g]:self.starts[g + 1]] for g in groups]))
            new = self.places_in_pool(pool, blocked, self.places - len(places), rng)
            if new:
                places += new
                if len(places) == self.places:
                    return np.stack(places)
                blocked = self.utm[np.concatenate(places)]
        raise ValueError(
            f"could not fill batch {index}: found only {len(places)} of {self.places} places after "
            f"{self.max_anchors} anchor groups. The data has too few places of >= {self.m} images "
            f"pairwise < {self.threshold} m apart that are also >= {self.threshold} m from each other; "
            "lower places_per_batch, images_per_place or same_place_threshold, or add more groups")

    def mine(self, num_batches: int, seed, num_workers: int = 1) -> np.ndarray:
        """``num_batches`` batches; batch ``b`` uses ``SeedSequence(seed).spawn(num_batches)[b]``."""
        seeds = _seed_sequences(seed, num_batches)
        if num_workers == 1:
            return np.stack([self.batch(i, s) for i, s in enumerate(seeds)]).astype(np.int64)
        chunks = [c for c in np.array_split(np.arange(num_batches), 4 * num_workers) if len(c)]
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(num_workers, initializer=_init_worker, initargs=(self,)) as pool:
            parts = pool.map(_mine_in_worker, [[(int(i), seeds[i]) for i in c] for c in chunks])
        return np.concatenate(parts).astype(np.int64)


_WORKER_MINER: _CliqueMiner | None = None


def _init_worker(miner: _CliqueMiner) -> None:
    global _WORKER_MINER
    _WORKER_MINER = miner


def _mine_in_worker(items: list[tuple[int, np.random.SeedSequence]]) -> np.ndarray:
    return np.stack([_WORKER_MINER.batch(i, s) for i, s in items])


def _checked_miner(utm, groups, group_descriptors, places_per_batch, images_per_place, same_place_threshold,
                   similar_groups, regions, headings, max_heading_diff) -> _CliqueMiner:
    """Validate the inputs of :func:`clique_batches` / :class:`CliqueBatchMaker` and build the index once."""
    utm = as_utm(utm, "utm")
    groups = _as_groups(groups, len(utm))
    desc = None
    if group_descriptors is not None:
        desc = as_float_matrix(group_descriptors, "group_descriptors")
        if len(desc) <= groups.max():
            raise ValueError(f"group_descriptors has {len(desc)} rows but groups uses ids up to {int(groups.max())}: "
                             f"give one row per group id 0..{int(groups.max())} (zero rows for unused ids)")
    places_per_batch = check_int(places_per_batch, "places_per_batch")
    images_per_place = check_int(images_per_place, "images_per_place", minimum=2)
    threshold = check_positive(same_place_threshold, "same_place_threshold")
    similar_groups = check_int(similar_groups, "similar_groups", minimum=0)
    if len(utm) < places_per_batch * images_per_place:
        raise ValueError(f"a batch needs {places_per_batch * images_per_place} distinct images but there are "
                         f"only {len(utm)}; lower places_per_batch or images_per_place")
    if regions is not None:
        regions = np.asarray(regions)
        if regions.shape != (len(utm),):
            raise ValueError(f"regions must have one entry (city / region label) per image, shape ({len(utm)},); "
                             f"got {regions.shape}")
    if max_heading_diff is not None:
        max_heading_diff = check_positive(max_heading_diff, "max_heading_diff")
        if headings is None:
            raise ValueError("max_heading_diff needs headings (degrees, one per image)")
    if headings is not None:
        headings = np.asarray(headings, dtype=np.float64)
        if headings.shape != (len(utm),) or not np.isfinite(headings).all():
            raise ValueError(f"headings must be ({len(utm)},) finite degrees, one per image; got shape {headings.shape}")
    return _CliqueMiner(utm, groups, desc, places_per_batch, images_per_place, threshold, similar_groups,
                        regions, headings, max_heading_diff)


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
      (DFS order); here it is the maximal clique grown greedily (smallest index first) from the
      smallest-index alive image that lies in a clique of ``>= images_per_place`` images;
    * ``regions=None`` means one region (the whole data set, as one MSLS city); once every region
      was used in a batch, regions may repeat (the original would stop); images within the
      threshold of places already in the batch are removed before each new anchor, so every pair of
      places of a batch is ``>= threshold`` apart, across anchors too (the original never meets its
      earlier places again because it moves to another city);
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
        from vpr_nb.evaluation import as_image_array
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

    def state_dict(self) -> dict:
        """The group descriptors in use and the refresh epochs (for exact resume from a checkpoint)."""
        import torch
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
        from vpr_nb.evaluation import compute_descriptors

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


def batch_statistics(batches, utm, descriptors=None) -> dict:
    """How close and how alike the places of batches are (the point of CliqueMining).

    For every batch ``(P, K)`` and every pair of its places: the distance between the place centres
    (mean UTM of the K images) and, with ``descriptors`` (one row per image, L2-normalised), the
    cosine similarity of the place descriptors (mean of the K image descriptors, L2-normalised).

    Returns:
        ``{"median place distance (m)": ..., "median place similarity": ... (NaN without descriptors),
        "cities per batch": ...}`` medians over all pairs of all batches (the last key is absent).
    """
    b = np.asarray(batches)
    if b.ndim == 2:
        b = b[None]
    if b.ndim != 3 or b.shape[1] < 2:
        raise ValueError(f"batches must have shape (B, P, K) with P >= 2, got {b.shape}")
    u = as_utm(utm, "utm")
    iu = np.triu_indices(b.shape[1], 1)
    centre = u[b].mean(axis=2)                                             # (B, P, 2)
    dist = _dist(centre[:, :, None, :], centre[:, None, :, :])[:, iu[0], iu[1]]
    out = {"median place distance (m)": float(np.median(dist)), "median place similarity": float("nan")}
    if descriptors is not None:
        x = as_float_matrix(descriptors, "descriptors")[b].mean(axis=2)    # (B, P, D)
        x /= np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
        sim = np.einsum("bpd,bqd->bpq", x, x)[:, iu[0], iu[1]]
        out["median place similarity"] = float(np.median(sim))
    return out


# ----------------------------------------------------------------------------- random baseline
def random_place_batches(groups, places_per_batch: int, images_per_place: int = 4, *,
                         num_batches: int = 1, seed: int | np.random.Generator = 0) -> np.ndarray:
    """GSV-Cities-style batches: random places, random images of each place.

    Each batch draws ``places_per_batch`` distinct groups uniformly among the groups with at
    least ``images_per_place`` images, then ``images_per_place`` distinct random images of each.
    Unlike :func:`clique_batches` nothing keeps two places of a batch geographically apart.

    Returns:
        int64 array ``(num_batches, places_per_batch, images_per_place)`` of image indices.
    """
    groups = _as_groups(groups, None)
    places_per_batch = check_int(places_per_batch, "places_per_batch")
    images_per_place = check_int(images_per_place, "images_per_place", minimum=2)
    num_batches = check_int(num_batches, "num_batches")
    rng = _as_rng(seed)
    order, starts = _group_index(groups)
    eligible = np.flatnonzero(np.diff(starts) >= images_per_place)
    if len(eligible) < places_per_batch:
        raise ValueError(f"only {len(eligible)} groups have >= {images_per_place} images but a batch needs "
                         f"{places_per_batch} distinct places; lower places_per_batch or images_per_place")
    out = np.empty((num_batches, places_per_batch, images_per_place), dtype=np.int64)
    for b in range(num_batches):
        for p, g in enumerate(rng.choice(eligible, places_per_batch, replace=False)):
            out[b, p] = rng.choice(order[starts[g]:starts[g + 1]], images_per_place, replace=False)
    return out
