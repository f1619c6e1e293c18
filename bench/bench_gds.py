"""Benchmark: GDS profile of 100k images, all pairs within 25 m: time and memory, new vs previous.

The images follow a random walk on a street grid (one image every ~1.5 m, with GPS noise);
their 256-D descriptors are random Fourier features of the position plus noise, so that
descriptor distance grows with geographic distance.

In one run, alternating, it times ``gds_profile`` (quantiles only, and with ``keep_pairs=True``)
and the previous implementation of the same computation (argsort of the values, whole-array
temporaries; kept below for the comparison), checks that their outputs are identical, and
measures their tracemalloc peaks. Prints the speed-up and memory ratios, bytes per pair, and the
memory projected for 1M images at the same pair density (target: under 8 GB, and >= 2x faster).
Nothing fails on absolute time.

    python bench/bench_gds.py            # 100k images
    python bench/bench_gds.py --quick    # 10k images
"""
from __future__ import annotations

import argparse
import math
import time
import tracemalloc

import numpy as np

from scipy.spatial import cKDTree

from vpr_nb.gds import (_bin_index, _bin_quantiles, _pair_descriptor_distances, _weighted_line,
                        gds_profile, misordering_probability)

TARGET_SPEEDUP = 2.0
TARGET_GB_1M = 8.0


def previous_gds_profile(db, utm, max_distance, bin_width, keep_pairs, qs=(0.1, 0.5, 0.9), fit=(0.0, 25.0)):
    """gds_profile(pairs="all") as it was before issue 12 (the reference of the ratios)."""
    ij = cKDTree(utm).query_pairs(max_distance, output_type="ndarray")
    i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
    geo = np.sqrt(((utm[i] - utm[j]) ** 2).sum(axis=1))
    keep = geo <= max_distance
    i, j, geo = i[keep], j[keep], geo[keep]
    desc = _pair_descriptor_distances(db, db, i, j)
    del i, j
    num_bins = int(math.ceil(max_distance / bin_width - 1e-9))
    centers = bin_width * (np.arange(num_bins) + 0.5)
    b = _bin_index(geo, bin_width, num_bins)
    count = np.bincount(b, minlength=num_bins)
    mean = np.bincount(b, weights=desc, minlength=num_bins) / count
    std = np.sqrt(np.bincount(b, weights=(desc - mean[b]) ** 2, minlength=num_bins) / count)
    order = np.argsort(desc)
    order = order[np.argsort(b.astype(np.int16)[order], kind="stable")]
    quant = _bin_quantiles(desc[order], count, qs)
    f = (count > 0) & (centers >= fit[0]) & (centers <= fit[1])
    slope, _ = _weighted_line(centers[f], mean[f], count[f].astype(np.float64))
    return dict(count=count, mean=mean, std=std, quantiles=quant, slope=slope,
                pair_desc=desc[order] if keep_pairs else None)


def traced(fn, *args, **kwargs):
    """(result, seconds, tracemalloc peak MiB above the start)."""
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    seconds = time.perf_counter() - t0
    peak = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    tracemalloc.stop()
    return out, seconds, peak


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def street_walk(n: int, rng: np.random.Generator, block: float = 80.0, blocks: int = 30,
                step: float = 1.5, gps_noise: float = 1.0) -> np.ndarray:
    """``n`` UTM positions of a car driving a random walk on a ``blocks x blocks`` street grid."""
    per_segment = int(block / step)
    node = np.array([blocks // 2, blocks // 2])
    moves = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
    parts, total = [], 0
    while total < n:
        nxt = node + moves[rng.integers(4)]
        if np.any(nxt < 0) or np.any(nxt > blocks):
            continue
        t = (np.arange(per_segment) / per_segment)[:, None]
        parts.append(block * (node + t * (nxt - node)))
        total += per_segment
        node = nxt
    utm = np.concatenate(parts)[:n]
    return utm + rng.normal(scale=gps_noise, size=utm.shape)


def position_descriptors(utm: np.ndarray, dim: int, rng: np.random.Generator, scale: float = 40.0,
                         noise: float = 0.6) -> np.ndarray:
    """L2-normalised random Fourier features of the position plus Gaussian noise."""
    w = rng.normal(scale=1.0 / scale, size=(2, dim))
    phase = rng.uniform(0, 2 * np.pi, size=dim)
    d = np.cos(utm @ w + phase) + noise * rng.normal(size=(len(utm), dim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10k images instead of 100k")
    args = parser.parse_args()
    n = 10_000 if args.quick else 100_000
    rng = np.random.default_rng(0)
    utm = street_walk(n, rng)
    desc = position_descriptors(utm, 256, rng)
    print(f"images: {n:,}, descriptor dim 256, pairs='all' within 25 m, 1 m bins")
    for keep in (False, True):
        new, _, mem_new = traced(gds_profile, desc, utm, 25.0, 1.0, "all", keep_pairs=keep)
        old, _, mem_old = traced(previous_gds_profile, desc, utm, 25.0, 1.0, keep)
        assert np.array_equal(new.count, old["count"]) and np.array_equal(new.mean, old["mean"])
        assert np.array_equal(new.std, old["std"]) and new.slope == old["slope"]
        assert all(np.array_equal(new.quantiles[q], old["quantiles"][q]) for q in old["quantiles"])
        if keep:
            assert np.array_equal(new.pair_desc, old["pair_desc"])
        pairs = int(new.count.sum())
        t_new, t_old = [], []
        for _ in range(3):   # alternate, so that a change of load hits both alike
            t_old.append(timed(previous_gds_profile, desc, utm, 25.0, 1.0, keep)[1])
            t_new.append(timed(gds_profile, desc, utm, 25.0, 1.0, "all", keep_pairs=keep)[1])
        ratio = float(np.median(np.array(t_old) / np.array(t_new)))
        bpp_new, bpp_old = mem_new * 2 ** 20 / pairs, mem_old * 2 ** 20 / pairs
        gb_1m = bpp_new * pairs / n * 1_000_000 / 1e9
        print(f"[keep_pairs={keep}] {pairs:,} pairs ({pairs / n:.0f} per image), outputs identical")
        print(f"  time: previous {np.median(t_old):.2f} s, now {np.median(t_new):.2f} s, speed-up {ratio:.2f}x "
              f"(median of 3 alternating rounds; target >= {TARGET_SPEEDUP:.0f}x, ratio to target {ratio / TARGET_SPEEDUP:.2f})")
        print(f"  memory (tracemalloc peak): previous {mem_old:.0f} MiB ({bpp_old:.0f} B/pair), now {mem_new:.0f} MiB "
              f"({bpp_new:.0f} B/pair), ratio {mem_new / mem_old:.2f}; 1M images at this density: "
              f"{gb_1m:.1f} GB (target < {TARGET_GB_1M:.0f} GB, ratio {gb_1m / TARGET_GB_1M:.2f})")
    print(f"P(misorder 2 m vs 20 m) = {misordering_probability(new, 2.0, 20.0, 'empirical'):.3f}")


if __name__ == "__main__":
    main()
