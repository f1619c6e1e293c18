"""Benchmark: CliqueMining batches (vpr_nb.samplers) -- speed-up, cost per batch against N, memory.

1. Speed-up over the straightforward formulation of bench/reference_clique.py (a dense adjacency
   and a new networkx graph per place) on the same inputs: target >= 10x. Both outputs are checked
   against the invariants (every place pairwise < threshold, places >= threshold apart, no image
   twice in a batch).
2. Cost of one 30 x 4 batch against the number of geotags N (10k, 100k, 1M): the per-region index is
   built once (as CliqueBatchMaker does), then batches are mined with the bit-set clique search
   (pools up to ``dense_max`` images) and, alternating in the same run, with the previous k-d tree +
   Python-set search (``dense_max = 0``); both must give identical batches. Target <= 5 ms per batch at
   1M and flat in N: the fitted exponent of ms-per-batch ~ N^e from 10k to 1M is printed (~0 is flat).
   Wall and CPU (process) time are both printed: on a loaded machine the wall time is inflated.
3. Memory (tracemalloc peaks): the index (once) and one batch at 1M geotags, against one call of the
   published-style reference on one 10k-image city (the published code works city by city). Target:
   both ratios to the reference <= 1 (the index keeps int32 image indices, builds the group order
   block by block and keeps the group descriptors as given when each city's ids are consecutive).

Only ratios and times measured in this one run are printed; nothing fails on absolute time (the
machine may be loaded), only on broken invariants or different batches.

The geotags are MSLS-like: cities of 10k images, each several drives (random walks on a street grid,
one image every ~3 m, GPS noise) over the same streets, grouped into 25 m cells (the
``unique_cluster`` analogue); each group descriptor is a 64-D random Fourier feature of the cell
centre plus noise, L2-normalised. Cities are 100 km apart and labelled as regions.

    python bench/bench_mining.py            # 20k geotags for the speed-up, 200 batches per N
    python bench/bench_mining.py --quick    # 5k geotags for the speed-up, 40 batches per N
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_clique import reference_clique_batches  # noqa: E402

from vpr_nb.samplers import _DENSE_MAX, _checked_miner, clique_batches  # noqa: E402

TARGET_MS = 5.0
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

    # 2. cost per batch against N, index built once; bit-set search vs the previous set search, alternating
    sizes = (10_000, 100_000, 1_000_000)
    n_batches, rounds = (40, 3) if args.quick else (200, 3)
    wall, cpu = [], []
    for n in sizes:
        (utm, groups, desc, regions), t_gen = timed(cities, n, 1)
        miner, t_index = timed(_checked_miner, utm, groups, desc, 30, 4, 25.0, 15, regions, None, None)
        miner.mine(5, 99)                                  # warm-up
        times = {"bit sets": ([], []), "previous": ([], [])}
        for r in range(rounds):
            outs = {}
            for name, dense_max in (("bit sets", _DENSE_MAX), ("previous", 0)):
                miner.dense_max = dense_max
                w0, c0 = time.perf_counter(), time.process_time()
                outs[name] = miner.mine(n_batches, r)
                times[name][0].append(1e3 * (time.perf_counter() - w0) / n_batches)
                times[name][1].append(1e3 * (time.process_time() - c0) / n_batches)
            assert np.array_equal(outs["bit sets"], outs["previous"]), "the bit-set search changed the batches"
        del miner.dense_max                                # back to the class default
        check_invariants(outs["bit sets"][:20], utm, 25.0)
        (w_new, c_new), (w_old, c_old) = [[float(np.median(t)) for t in times[k]] for k in ("bit sets", "previous")]
        ratio = float(np.median(np.array(times["previous"][1]) / np.array(times["bit sets"][1])))
        wall.append(w_new)
        cpu.append(c_new)
        print(f"[per batch] N={n:>9,}: {groups.max() + 1:,} groups in {regions.max() + 1} cities "
              f"(generated in {t_gen:.1f} s), index {t_index:.2f} s once; identical batches")
        print(f"    {w_new:.2f} ms wall / {c_new:.2f} ms CPU per 30x4 batch (ratio to the {TARGET_MS:.0f} ms target: "
              f"{w_new / TARGET_MS:.2f} wall, {c_new / TARGET_MS:.2f} CPU); previous set search {w_old:.2f} ms wall / "
              f"{c_old:.2f} ms CPU; speed-up {ratio:.2f}x (CPU, median of {rounds} alternating rounds)")
    e_wall = np.polyfit(np.log(sizes), np.log(wall), 1)[0]
    e_cpu = np.polyfit(np.log(sizes), np.log(cpu), 1)[0]
    print(f"  fitted exponent of ms per batch ~ N^e from {sizes[0]:,} to {sizes[-1]:,}: e = {e_cpu:.3f} (CPU), "
          f"{e_wall:.3f} (wall) (flat: ~0)")

    # 3. memory: the index once and one batch at the largest N, the reference on one city
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    miner = _checked_miner(utm, groups, desc, 30, 4, 25.0, 15, regions, None, None)
    index_mb = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    batch_mb = {}
    for name, dense_max in (("bit sets", _DENSE_MAX), ("previous", 0)):
        miner.dense_max = dense_max
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        miner.mine(3, 7)
        batch_mb[name] = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    cu, cg, cd, _ = cities(CITY, 2)
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    reference_clique_batches(cu, cg, cd, 30, num_batches=1, seed=0)
    ref_mb = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    tracemalloc.stop()
    print(f"[memory] N={sizes[-1]:,}: index {index_mb:.1f} MiB (once per run); mining 3 batches: bit sets "
          f"{batch_mb['bit sets']:.2f} MiB, previous {batch_mb['previous']:.2f} MiB; reference, one call on a "
          f"{CITY:,}-image city: {ref_mb:.2f} MiB; batch / reference = {batch_mb['bit sets'] / ref_mb:.2f} "
          f"(target <= 1), index / reference = {index_mb / ref_mb:.2f} (target <= 1)")

if __name__ == "__main__":
    main()
