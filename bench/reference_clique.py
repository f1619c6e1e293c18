"""Straightforward CliqueMining batch construction, used as the reference in bench/bench_mining.py.

It follows the published algorithm step by step (Izquierdo & Civera, ECCV 2024; the authors'
``create_dataset_part``) with plain tools and no optimisation:

1. anchor group uniformly among the groups that have images;
2. ``similar_groups`` other groups drawn without replacement with ``rng.choice(p=...)``,
   ``p ∝ max(d) - d`` (d = Euclidean descriptor distance to the anchor, anchor weight 0);
3. a dense boolean adjacency ``squareform(pdist(utm)) < threshold`` over all images of those groups,
   with the images already in the batch (and everything within the threshold of them) removed;
4. for every place: a new ``networkx.Graph`` from the adjacency, the first maximal clique of
   ``networkx.find_cliques`` with >= m nodes, m random members, then the chosen images and all
   their neighbours are cut out of the adjacency;
5. a new anchor when no clique is left, until the batch is full.

Same inputs and output shape as :func:`vpr_nb.samplers.clique_batches`; the batches differ (another
clique order and random stream) but satisfy the same invariants.
"""
from __future__ import annotations

import networkx
import numpy as np
from scipy.spatial.distance import cdist, pdist, squareform


def reference_clique_batches(utm, groups, group_descriptors, places_per_batch: int, images_per_place: int = 4,
                             same_place_threshold: float = 25.0, similar_groups: int = 15,
                             num_batches: int = 1, seed: int = 0, max_anchors: int = 300) -> np.ndarray:
    """CliqueMining batches rebuilt the straightforward way (a new networkx graph per place)."""
    utm = np.asarray(utm, dtype=np.float64)
    groups = np.asarray(groups, dtype=np.int64)
    desc = np.asarray(group_descriptors, dtype=np.float64)
    if utm.ndim != 2 or utm.shape[1] != 2 or len(groups) != len(utm):
        raise ValueError("utm must be (N, 2) and groups (N,)")
    rng = np.random.default_rng(seed)
    present = np.unique(groups)
    members = {int(g): np.flatnonzero(groups == g) for g in present}  # O(N * G): straightforward
    k = min(similar_groups, len(present) - 1)
    out = np.empty((num_batches, places_per_batch, images_per_place), dtype=np.int64)
    for b in range(num_batches):
        places: list[np.ndarray] = []
        for _ in range(max_anchors):
            anchor = int(rng.choice(present))
            d = cdist(desc[anchor][None], desc[present])[0]
            w = d.max() - d
            w[present == anchor] = 0.0
            if w.sum() == 0 or np.count_nonzero(w) < k:
                w = (present != anchor).astype(np.float64)
            chosen_groups = np.concatenate([[anchor], rng.choice(present, size=k, replace=False, p=w / w.sum())])
            pool = np.sort(np.concatenate([members[int(g)] for g in chosen_groups]))
            adj = squareform(pdist(utm[pool])) < same_place_threshold
            if places:
                near_batch = (cdist(utm[pool], utm[np.concatenate(places)]) < same_place_threshold).any(axis=1)
                adj[near_batch, :] = False
                adj[:, near_batch] = False
            np.fill_diagonal(adj, False)
            while len(places) < places_per_batch:
                graph = networkx.from_numpy_array(adj.astype(np.int8))
                clique = None
                for c in networkx.find_cliques(graph):
                    if len(c) >= images_per_place:
                        clique = rng.choice(np.array(c), images_per_place, replace=False)
                        break
                if clique is None:
                    break
                places.append(pool[clique])
                neighbours = np.flatnonzero(adj[clique].any(axis=0))
                cut = np.concatenate([clique, neighbours])
                adj[cut, :] = False
                adj[:, cut] = False
            if len(places) == places_per_batch:
                break
        if len(places) < places_per_batch:
            raise ValueError(f"could not fill batch {b}: {len(places)} of {places_per_batch} places")
        out[b] = np.stack(places)
    return out
