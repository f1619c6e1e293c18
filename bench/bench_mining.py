"""Benchmark: CliqueMining batches (vpr_nb.samplers) against the published sampler's algorithm, in one run.

Every printed number is a ratio measured in this run, at the same N for both sides:

1. Speed-up over the published algorithm (bench/reference_clique.py: a new ``networkx.Graph`` from a
   dense adjacency for every place and ``networkx.find_cliques``, city by city, as serizba/cliquemining's
   ``create_dataset_part``) for N geotags in cities of 10k: CPU time per 30 x 4 batch, both sides built
   once (our per-region index, the published per-city tables) and then timed alternating round by round.
   Target >= 10x (the run fails below it). Both outputs are checked against the invariants (every place
   pairwise < threshold, places >= threshold apart, no image twice in a batch).
2. Our bit-set clique search against the previous k-d tree + Python-set search (``dense_max = 0``) in the
   same run: identical batches (checked) and the speed-up.
3. Flat in N: per-batch time at the largest N over the smallest, and the fitted exponent ``e`` of
   time ~ N^e, for ours and for the published algorithm.
4. Memory at the largest N (tracemalloc peaks above the inputs): ours (index + 3 batches) / published
   (per-city tables + 3 batches), and the 3 batches alone / the published's.

The published algorithm needs several cities per batch (a city gives up to ~16 places and is used once
per batch), so the smallest N holds 5 cities. The geotags are MSLS-like: cities of 10k images, each
several drives (random walks on a street grid, one image every ~3 m, GPS noise) over the same streets,
grouped into 25 m cells (the ``unique_cluster`` analogue); each group descriptor is a 64-D random Fourier
feature of the cell centre plus noise, L2-normalised. Cities are 100 km apart and labelled as regions.

    python bench/bench_mining.py            # N = 50k, 200k, 1M; 10 published batches per round
    python bench/bench_mining.py --quick    # N = 50k, 100k; 2 published batches per round
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_clique import city_tables, published_clique_batches  # noqa: E402

from vpr_nb.samplers import _DENSE_MAX, _checked_miner  # noqa: E402

CITY = 10_000
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


def cities(n: int, seed: int = 0):
    """``n`` geotags in cities of ``CITY`` images 100 km apart: utm, compact group ids, descriptors, regions."""
    parts, off = [], 0
    for c in range(int(np.ceil(n / CITY))):
        utm, groups, desc = geotagged_groups(min(CITY, n - c * CITY), seed=seed * 1000 + c)
        parts.append((utm + [c * 1e5, 0.0], groups + off, desc, np.full(len(utm), c)))
        off += len(desc)
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))


def check_invariants(batches: np.ndarray, utm: np.ndarray, threshold: float) -> None:
    for b in batches:
        assert len(np.unique(b)) == b.size, "an image twice in a batch"
        pts = utm[b]
        d = np.linalg.norm(pts[:, None, :, None, :] - pts[None, :, None, :, :], axis=-1)
        p = len(b)
        assert (d[np.arange(p), np.arange(p)] < threshold).all(), "a place is not pairwise < threshold"
        assert (d[~np.eye(p, dtype=bool)] >= threshold).all(), "two places closer than the threshold"


def cpu_per_batch(fn, *args) -> tuple[np.ndarray, float]:
    """(batches, CPU ms per batch) of ``fn(*args)``, whose first array dimension is the batch."""
    c0 = time.process_time()
    out = fn(*args)
    return out, 1e3 * (time.process_time() - c0) / len(out)


def traced_peak(fn, *args) -> tuple[object, float]:
    """(result, tracemalloc peak MiB above the start) of ``fn(*args)``."""
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    out = fn(*args)
    peak = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    tracemalloc.stop()
    return out, peak


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller inputs (a smoke run)")
    args = parser.parse_args()
    sizes = (50_000, 100_000) if args.quick else (50_000, 200_000, 1_000_000)
    n_pub, n_ours, rounds = (2, 20, 2) if args.quick else (10, 200, 3)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; 30 x 4 batches, threshold "
          f"25 m, 15 similar groups; CPU time, {rounds} alternating rounds, medians of the per-round ratios")
    failed = []
    ours_ms, pub_ms = [], []
    for n in sizes:
        utm, groups, desc, regions = cities(n, 1)
        miner = _checked_miner(utm, groups, desc, 30, 4, 25.0, 15, regions, None, None)
        tables = city_tables(groups, desc, regions)
        miner.mine(2, 99)                                  # warm-up
        t = {"bit sets": [], "previous": [], "published": []}
        for r in range(rounds):
            outs = {}
            for name, dense_max in (("bit sets", _DENSE_MAX), ("previous", 0)):
                miner.dense_max = dense_max
                outs[name], ms = cpu_per_batch(miner.mine, n_ours, r)
                t[name].append(ms)
            assert np.array_equal(outs["bit sets"], outs["previous"]), "the bit-set search changed the batches"
            pub, ms = cpu_per_batch(published_clique_batches, utm, tables, 30, 4, 25.0, 15, n_pub, r)
            t["published"].append(ms)
            check_invariants(outs["bit sets"][:20], utm, 25.0)
            check_invariants(pub, utm, 25.0)
        del miner.dense_max                                # back to the class default
        up = float(np.median(np.array(t["published"]) / np.array(t["bit sets"])))
        up_prev = float(np.median(np.array(t["previous"]) / np.array(t["bit sets"])))
        ours_ms.append(float(np.median(t["bit sets"])))
        pub_ms.append(float(np.median(t["published"])))
        met = up >= TARGET_SPEEDUP
        if not met:
            failed.append(f"speed-up at N={n:,}")
        print(f"[N={n:>9,}: {regions.max() + 1} cities, {groups.max() + 1:,} groups] invariants hold for both; "
              f"speed-up over the published algorithm {up:.0f}x (target >= {TARGET_SPEEDUP:.0f}x: "
              f"{'met' if met else 'NOT met'}); over the previous set search {up_prev:.2f}x (identical batches)")
    e_ours = np.polyfit(np.log(sizes), np.log(ours_ms), 1)[0]
    e_pub = np.polyfit(np.log(sizes), np.log(pub_ms), 1)[0]
    print(f"[flat in N] per-batch time at N={sizes[-1]:,} / at N={sizes[0]:,}: ours {ours_ms[-1] / ours_ms[0]:.2f}, "
          f"published {pub_ms[-1] / pub_ms[0]:.2f}; fitted exponent of time ~ N^e: ours {e_ours:.3f}, "
          f"published {e_pub:.3f} (flat: ~0)")

    # memory at the largest N, same inputs: our index + 3 batches vs the published tables + 3 batches
    def ours_all():
        return _checked_miner(utm, groups, desc, 30, 4, 25.0, 15, regions, None, None).mine(3, 7)

    def published_all():
        return published_clique_batches(utm, city_tables(groups, desc, regions), 30, 4, 25.0, 15, 3, 7)

    _, m_ours = traced_peak(ours_all)
    _, m_pub = traced_peak(published_all)
    miner = _checked_miner(utm, groups, desc, 30, 4, 25.0, 15, regions, None, None)
    _, m_batch = traced_peak(miner.mine, 3, 7)
    _, m_pub_batch = traced_peak(published_clique_batches, utm, tables, 30, 4, 25.0, 15, 3, 7)
    print(f"[memory, N={sizes[-1]:,}] tracemalloc peak, ours / published: index + 3 batches vs per-city tables + "
          f"3 batches {m_ours / m_pub:.2f}; the 3 batches alone {m_batch / m_pub_batch:.2f}")
    if failed:
        print("failed: " + "; ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
