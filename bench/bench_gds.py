"""Benchmark: GDS profile, all pairs within 25 m: time and memory against two baselines, in one run.

The images follow a random walk on a street grid (one image every ~1.5 m, with GPS noise);
their 256-D descriptors are random Fourier features of the position plus noise, so that
descriptor distance grows with geographic distance.

In one run it times ``gds_profile`` (quantiles only, and with ``keep_pairs=True``) against the two
earlier implementations kept in bench/reference_gds.py -- before issue 12 ("previous": argsort of the
values, whole-array temporaries) and issue 12's first pass ("first pass", commit 43078cd) -- alternating
so that a change of load hits all alike, checks their outputs, and measures their tracemalloc peaks.
The baselines compute each pair's descriptor distance from the gathered difference ``a_i - b_j``; the
current code reads it from per-chunk Gram matrices (``|a|^2 + |b|^2 - 2 a.b``, BLAS), so the bin counts
must be identical and the statistics and sorted pair distances may differ in float32 rounding only
(checked: within ``OUTPUT_ATOL``). Prints the speed-up and memory ratios, bytes per pair, and the memory
projected for 1M images at the same pair density (targets: >= 2x faster than before issue 12, 1M images
under 8 GB).
``--images N`` runs one extra measured profile of N images (e.g. 1000000; about 3 GB of RAM).
Nothing fails on absolute time.

    python bench/bench_gds.py            # 100k images
    python bench/bench_gds.py --quick    # 10k images
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_gds import first_pass_gds_profile, previous_gds_profile  # noqa: E402

from vpr_nb.gds import gds_profile, misordering_probability  # noqa: E402

TARGET_SPEEDUP = 2.0
TARGET_GB_1M = 8.0
OUTPUT_ATOL = 1e-5   # descriptor distances from dot products vs the baselines' differences (unit-norm descriptors)


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


def max_difference(new, old: dict, keep: bool) -> float:
    """Largest absolute difference of the statistics (and, with ``keep``, of the sorted pair distances)
    from a baseline; the pair counts per bin must be identical (the same pairs and bins)."""
    assert np.array_equal(new.count, old["count"])
    diffs = [np.nanmax(np.abs(new.mean - old["mean"])), np.nanmax(np.abs(new.std - old["std"])),
             abs(new.slope - old["slope"])]
    diffs += [np.nanmax(np.abs(new.quantiles[q] - old["quantiles"][q])) for q in old["quantiles"]]
    if keep:
        diffs.append(np.max(np.abs(new.pair_desc - old["pair_desc"])))
    return float(max(diffs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10k images instead of 100k")
    parser.add_argument("--images", type=int, default=0, help="also profile this many images once (time, peak)")
    args = parser.parse_args()
    n = 10_000 if args.quick else 100_000
    rng = np.random.default_rng(0)
    utm = street_walk(n, rng)
    desc = position_descriptors(utm, 256, rng)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores")
    print(f"images: {n:,}, descriptor dim 256, pairs='all' within 25 m, 1 m bins")
    impls = {"now": lambda keep: gds_profile(desc, utm, 25.0, 1.0, "all", keep_pairs=keep),
             "first pass": lambda keep: first_pass_gds_profile(desc, utm, 25.0, 1.0, keep),
             "previous": lambda keep: previous_gds_profile(desc, utm, 25.0, 1.0, keep)}
    for keep in (False, True):
        outs, mem = {}, {}
        for name, fn in impls.items():
            outs[name], _, mem[name] = traced(fn, keep)
        diff = max(max_difference(outs["now"], outs[name], keep) for name in ("first pass", "previous"))
        assert diff <= OUTPUT_ATOL, f"outputs differ from the baselines by {diff:.2g} (> {OUTPUT_ATOL:g})"
        pairs = int(outs["now"].count.sum())
        times = {name: [] for name in impls}
        for _ in range(3):   # alternate, so that a change of load hits all alike
            for name, fn in impls.items():
                times[name].append(timed(fn, keep)[1])
        t = {name: np.array(v) for name, v in times.items()}
        up_prev = float(np.median(t["previous"] / t["now"]))
        up_first = float(np.median(t["first pass"] / t["now"]))
        bpp = {name: mem[name] * 2 ** 20 / pairs for name in impls}
        gb_1m = bpp["now"] * pairs / n * 1_000_000 / 1e9
        print(f"[keep_pairs={keep}] {pairs:,} pairs ({pairs / n:.0f} per image), same bin counts as both baselines, "
              f"statistics{' and pair distances' if keep else ''} within {diff:.1g} of theirs (tolerance {OUTPUT_ATOL:g})")
        print(f"  time (median of 3 alternating rounds): previous {np.median(t['previous']):.2f} s, first pass "
              f"{np.median(t['first pass']):.2f} s, now {np.median(t['now']):.2f} s; speed-up {up_prev:.2f}x over "
              f"previous (target >= {TARGET_SPEEDUP:.0f}x, ratio to target {up_prev / TARGET_SPEEDUP:.2f}), "
              f"{up_first:.2f}x over the first pass")
        print(f"  memory (tracemalloc peak): previous {mem['previous']:.0f} MiB ({bpp['previous']:.0f} B/pair), first pass "
              f"{mem['first pass']:.0f} MiB ({bpp['first pass']:.0f} B/pair), now {mem['now']:.0f} MiB "
              f"({bpp['now']:.0f} B/pair); now / previous {mem['now'] / mem['previous']:.2f}, now / first pass "
              f"{mem['now'] / mem['first pass']:.2f}; 1M images at this density: {gb_1m:.1f} GB "
              f"(target < {TARGET_GB_1M:.0f} GB, ratio {gb_1m / TARGET_GB_1M:.2f})")
    print(f"P(misorder 2 m vs 20 m) = {misordering_probability(outs['now'], 2.0, 20.0, 'empirical'):.3f}")
    if args.images:
        big_utm = street_walk(args.images, np.random.default_rng(1), blocks=int(30 * np.sqrt(args.images / n)))
        big = np.empty((args.images, 256), dtype=np.float32)   # as position_descriptors, in blocks (no 2 GB temporary)
        frng = np.random.default_rng(2)
        w, phase = frng.normal(scale=1.0 / 40.0, size=(2, 256)), frng.uniform(0, 2 * np.pi, size=256)
        for s in range(0, args.images, 65536):
            d = np.cos(big_utm[s:s + 65536] @ w + phase) + 0.6 * frng.normal(size=(len(big_utm[s:s + 65536]), 256))
            big[s:s + len(d)] = d / np.linalg.norm(d, axis=1, keepdims=True)
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20   # GiB (ru_maxrss is KiB on Linux)
        prof, secs, peak = traced(gds_profile, big, big_utm, 25.0, 1.0, "all", keep_pairs=True)
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
        pairs = int(prof.count.sum())
        print(f"[{args.images:,} images] {pairs:,} pairs, keep_pairs=True: {secs:.1f} s (traced), tracemalloc peak "
              f"{peak / 1024:.2f} GiB above the inputs ({peak * 2 ** 20 / pairs:.0f} B/pair); process peak RSS "
              f"{rss1:.2f} GiB with the inputs ({rss0:.2f} GiB before the call); target < {TARGET_GB_1M:.0f} GB")


if __name__ == "__main__":
    main()
