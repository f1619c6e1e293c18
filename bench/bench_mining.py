"""Benchmark: CliqueMining batches (vpr_nb.mining.clique_batches) against two budgets.

1. Speed-up over the straightforward formulation of bench/reference_clique.py (a dense adjacency
   and a new networkx graph per place) on the same inputs: target >= 10x. Both outputs are checked
   against the invariants (every place pairwise < threshold, places >= threshold apart, no image
   twice in a batch).
2. 1M geotags -> 1000 batches of 30 places x 4 images in <= 60 s (2 cores; 1 worker and 2 workers).

The geotags are MSLS-like: several drives (random walks on a street grid, one image every ~3 m,
GPS noise) over the same streets, grouped into 25 m cells (the ``unique_cluster`` analogue); each
group descriptor is a 64-D random Fourier feature of the cell centre plus noise, L2-normalised.

    python bench/bench_mining.py            # 20k geotags for the speed-up, 1M for the budget
    python bench/bench_mining.py --quick    # 5k geotags for the speed-up, 100k / 100 batches
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_clique import reference_clique_batches  # noqa: E402

from vpr_nb.mining import clique_batches  # noqa: E402

BUDGET_S = 60.0
TARGET_SPEEDUP = 10.0


def drives(n: int, rng: np.random.Generator, block: float = 80.0, blocks: int | None = None,
           step: float = 3.0, gps_noise: float = 1.5) -> np.ndarray:
    """``n`` UTM positions of random-walk drives on a street grid sized so that streets are revisited."""
    if blocks is None:
        blocks = max(4, int(np.sqrt(n / 40)))  # ~40 images per block edge on average over all drives
    per_segment = int(block / step)
    moves = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
    parts, total = [], 0
    node = rng.integers(0, blocks + 1, 2)
    t = (np.arange(per_segment) / per_segment)[:, None]
    while total < n:
        nxt = node + moves[rng.integers(4)]
        if np.any(nxt < 0) or np.any(nxt > blocks):
            continue
        parts.append(block * (node + t * (nxt - node)))
        total += per_segment
        node = nxt
    utm = np.concatenate(parts)[:n]
    return utm + rng.normal(scale=gps_noise, size=utm.shape)


def geotagged_groups(n: int, seed: int = 0, cell: float = 25.0, dim: int = 64):
    """Positions, 25 m cell groups (compact ids) and one descriptor per group."""
    rng = np.random.default_rng(seed)
    utm = drives(n, rng)
    ij = np.floor(utm / cell).astype(np.int64)
    _, groups = np.unique(ij[:, 0] * 1_000_003 + ij[:, 1], return_inverse=True)
    groups = groups.reshape(-1)
    centres = np.zeros((groups.max() + 1, 2))
    np.add.at(centres, groups, utm)
    centres /= np.bincount(groups)[:, None]
    w = rng.normal(scale=1.0 / 150.0, size=(2, dim))
    desc = np.cos(centres @ w + rng.uniform(0, 2 * np.pi, dim)) + 0.3 * rng.normal(size=(len(centres), dim))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    return utm, groups, desc.astype(np.float32)


def check_invariants(batches: np.ndarray, utm: np.ndarray, threshold: float) -> None:
    for b in batches:
        assert len(np.unique(b)) == b.size, "an image twice in a batch"
        pts = utm[b]
        d = np.linalg.norm(pts[:, None, :, None, :] - pts[None, :, None, :, :], axis=-1)
        p = len(b)
        assert (d[np.arange(p), np.arange(p)] < threshold).all(), "a place is not pairwise < threshold"
        assert (d[~np.eye(p, dtype=bool)] >= threshold).all(), "two places closer than the threshold"


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller inputs (a smoke run)")
    args = parser.parse_args()
    n_ref, ref_batches = (5_000, 5) if args.quick else (20_000, 20)
    n_big, big_batches = (100_000, 100) if args.quick else (1_000_000, 1000)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores")

    # 1. speed-up over the networkx reference, same inputs
    utm, groups, desc = geotagged_groups(n_ref, seed=0)
    kw = dict(places_per_batch=30, images_per_place=4, same_place_threshold=25.0, similar_groups=15,
              num_batches=ref_batches, seed=0)
    ours, t_ours = timed(clique_batches, utm, groups, desc, **kw)
    ref, t_ref = timed(reference_clique_batches, utm, groups, desc, **kw)
    check_invariants(ours, utm, 25.0)
    check_invariants(ref, utm, 25.0)
    print(f"[speed-up] {n_ref:,} geotags, {groups.max() + 1:,} groups, {ref_batches} batches of 30x4 "
          f"(invariants hold for both)")
    print(f"  networkx reference: {t_ref:.2f} s   clique_batches: {t_ours:.3f} s   "
          f"speed-up: {t_ref / t_ours:.1f}x (target >= {TARGET_SPEEDUP:.0f}x, ratio to target "
          f"{t_ref / t_ours / TARGET_SPEEDUP:.2f})")

    # 2. the 1M-geotag budget
    (utm, groups, desc), t_gen = timed(geotagged_groups, n_big, 1)
    print(f"[budget] {n_big:,} geotags, {groups.max() + 1:,} groups (generated in {t_gen:.1f} s), "
          f"{big_batches} batches of 30x4")
    for workers in (1, 2):
        out, secs = timed(clique_batches, utm, groups, desc, 30, num_batches=big_batches, seed=0,
                          num_workers=workers)
        check_invariants(out[:50], utm, 25.0)
        print(f"  num_workers={workers}: {secs:.2f} s   ratio to the {BUDGET_S:.0f} s budget: "
              f"{secs / BUDGET_S:.3f} (< 1 is within budget)")


if __name__ == "__main__":
    main()
