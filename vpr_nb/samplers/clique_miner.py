"""The CliqueMining index and batch search behind :func:`vpr_nb.samplers.clique_batches`.

:class:`_CliqueMiner` is built once per image set (the images of each group, the groups of each region,
the group descriptors) and then mines batches: steps 1-6 of :func:`vpr_nb.samplers.clique_batches`
(the paper's Eqs. (1)-(4)). The clique search itself works on Python-int bit sets for small pools and on
a k-d tree with Python sets for large ones; both give the same places.
"""
from __future__ import annotations

import multiprocessing

import numpy as np
from scipy.spatial import cKDTree

from .._checks import as_float_matrix, as_utm, check_int, check_positive
from ._common import _CHUNK, _as_groups, _dist, _group_index, _seed_sequences

_MIN_ANCHORS = 100  # a batch gives up after max(_MIN_ANCHORS, _ANCHORS_PER_PLACE * places) anchors
_ANCHORS_PER_PLACE = 10
_DENSE_MAX = 2048      # pools of up to this many images use the dense bit-set path (else k-d tree + sets)


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


# ----------------------------------------------------------------------------- clique search
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
        are removed first. Then, scanning the pool in its order (:meth:`batch`: the drawn groups in a
        seeded random order, each group's images by index), the first alive image
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
        place_region: list[int] = []   # the region of each place: only places of the anchor's region block
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
            # the search scans the drawn groups in a seeded random order, each group's images in index order:
            # scanning all of them by index would fill batches from the lowest-index groups (a route's start)
            groups = groups[rng.permutation(len(groups))]
            pool = np.concatenate([np.sort(self.order[self.starts[g]:self.starts[g + 1]]) for g in groups])
            near = [p for p, pr in zip(places, place_region) if pr == r]   # other regions: other UTM frames
            blocked = self.utm[np.concatenate(near)] if near else np.empty((0, 2))
            new = self.places_in_pool(pool, blocked, self.places - len(places), rng)
            if new:
                places += new
                place_region += [r] * len(new)
                if len(places) == self.places:
                    return np.stack(places)
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

