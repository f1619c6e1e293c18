"""The published CliqueMining sampler's algorithm, the baseline of bench/bench_mining.py (never imported by
the package).

It follows ``create_dataset_part`` of serizba/cliquemining (Izquierdo & Civera, ECCV 2024) step by
step, written anew with numpy, scipy and networkx on the bench's arrays instead of MSLS dataframes:

1. a city with probability proportional to its number of clusters (rows of its descriptor table),
   redrawn while it was already used in this batch;
2. an anchor cluster uniformly among the city's clusters; weights ``max(d) - d`` over all the city's
   cluster descriptors (``d`` = Euclidean distance to the anchor's, computed with ``cdist``; the
   anchor's weight stays 0), normalised, and ``similar_groups`` clusters drawn without replacement;
3. the city's images whose cluster is one of the 16 (a scan over the whole city, as the dataframe
   filter ``isin`` does) and a dense adjacency ``squareform(pdist(utm)) < threshold``;
4. for every place: a new ``networkx.Graph`` from the adjacency and the first maximal clique of
   ``networkx.find_cliques`` with ``>= images_per_place`` nodes, ``images_per_place`` random members
   of it; then the rows and columns of the chosen images and of all their neighbours are cleared;
5. when no such clique is left, back to 1 with a new city, until the batch is full.

Differences from the published code, none of which changes its cost: a seeded ``np.random.Generator``
(the original seeds numpy's global state from pid and time), integer image indices instead of file
names, and a ``ValueError`` where the original would loop for ever (every city of the data set used
in one batch before it is full).
"""
from __future__ import annotations

import networkx
import numpy as np
from scipy.spatial.distance import cdist, pdist, squareform


def city_tables(groups: np.ndarray, group_descriptors: np.ndarray, regions: np.ndarray) -> dict:
    """Per city, what the published code loads once: the city's image indices, each image's cluster id
    within the city (0..C-1, as MSLS's ``unique_cluster``) and the city's ``(C, D)`` descriptor table."""
    tables = {}
    for city in np.unique(regions):
        images = np.flatnonzero(regions == city)
        ids, local = np.unique(groups[images], return_inverse=True)
        tables[city] = (images, local.reshape(-1), np.asarray(group_descriptors[ids], dtype=np.float64))
    return tables


def published_clique_batches(utm, tables: dict, places_per_batch: int = 30, images_per_place: int = 4,
                             same_place_threshold: float = 25.0, similar_groups: int = 15,
                             num_batches: int = 1, seed: int = 0) -> np.ndarray:
    """``(num_batches, places_per_batch, images_per_place)`` image indices, by the published algorithm."""
    rng = np.random.default_rng(seed)
    cities = list(tables)
    num_clusters = np.array([len(tables[c][2]) for c in cities], dtype=np.float64)
    out = np.empty((num_batches, places_per_batch, images_per_place), dtype=np.int64)
    for b in range(num_batches):
        used: list = []
        filled = 0
        while filled < places_per_batch:
            if len(used) == len(cities):
                raise ValueError(f"batch {b}: every city used with {filled} of {places_per_batch} places "
                                 f"(the published sampler would loop for ever)")
            city = cities[rng.choice(len(cities), p=num_clusters / num_clusters.sum())]
            while city in used:
                city = cities[rng.choice(len(cities), p=num_clusters / num_clusters.sum())]
            used.append(city)
            images, local, desc = tables[city]
            anchor = rng.choice(np.unique(local))
            weight = cdist(desc[anchor, None, :], desc)[0]
            nonzero = weight != 0
            weight[nonzero] = weight.max() - weight[nonzero]
            others = rng.choice(len(desc), size=similar_groups, p=weight / weight.sum(), replace=False)
            pool = images[np.isin(local, np.concatenate([[anchor], others]))]
            adj = squareform(pdist(utm[pool])) < same_place_threshold
            while filled < places_per_batch:
                clique = None
                for c in networkx.find_cliques(networkx.Graph(adj)):
                    if len(c) >= images_per_place:
                        clique = rng.choice(c, images_per_place, replace=False)
                        break
                if clique is None:
                    break
                neighbours = np.unique(np.where(adj[clique, :])[1])
                out[b, filled] = pool[clique]
                filled += 1
                adj[:, clique] = False
                adj[clique, :] = False
                adj[neighbours, :] = False
                adj[:, neighbours] = False
    return out
