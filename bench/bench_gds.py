"""Benchmark: GDS profile, all pairs within 25 m: speed and memory ratios against baselines, in one run.

The images follow a random walk on a street grid (one image every ~1.5 m, with GPS noise);
their 256-D descriptors are random Fourier features of the position plus noise, so that
descriptor distance grows with geographic distance.

In one run it times ``gds_profile`` (quantiles only, and with ``keep_pairs=True``) as the package runs it
("pinned": its Gram-matrix products on one BLAS thread, vpr_nb._threads), the same code with numpy's
default BLAS threads ("default threads"), and the two earlier implementations kept in
bench/reference_gds.py at default threads -- before issue 12 ("previous": argsort of the values,
whole-array temporaries) and issue 12's first pass ("first pass", commit 43078cd) -- alternating round
by round so that a change of load hits all alike; it checks their outputs and compares tracemalloc peaks
at the same N. The baselines compute each pair's descriptor distance from the gathered difference
``a_i - b_j``; the current code reads it from per-chunk Gram matrices (``|a|^2 + |b|^2 - 2 a.b``, BLAS),
so the bin counts must be identical and the statistics and sorted pair distances may differ in float32
rounding only (checked: within ``OUTPUT_ATOL``). Every printed number is a ratio measured in this run.
Target: pinned >= 2.5x faster than the previous implementation (quantiles, 100k images; the run fails
below it; ``--quick`` fails below 1.5x).
``--images N`` also profiles N images once with the pinned code and once with the previous one
(time and memory ratios at that N; at 1M the pinned code's tracemalloc peak is about 3 GB and the
previous one's is that divided by the memory ratio printed for 100k).

    python bench/bench_gds.py            # 100k images
    python bench/bench_gds.py --quick    # 10k images
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import tracemalloc

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference_gds import first_pass_gds_profile, previous_gds_profile  # noqa: E402

from vpr_nb.gds import pairs as gds_pairs  # noqa: E402 (its Gram products pin one BLAS thread)
from vpr_nb.gds import gds_profile  # noqa: E402

TARGET_SPEEDUP = 2.5   # pinned vs the previous implementation (quantiles), 100k images
QUICK_FLOOR = 1.5      # the same for --quick (10k images, half the pairs per image: less for the Gram products to save)
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


@contextlib.contextmanager
def default_threads():
    """Run the package's GDS code without its one-thread limit (numpy's default BLAS threads)."""
    pinned = gds_pairs.single_threaded
    gds_pairs.single_threaded = contextlib.nullcontext
    try:
        yield
    finally:
        gds_pairs.single_threaded = pinned


def unpinned_gds_profile(*args, **kwargs):
    with default_threads():
        return gds_profile(*args, **kwargs)


def big_inputs(n: int, n_ref: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` images at the pair density of the ``n_ref``-image run (a street grid grown with sqrt(n)),
    descriptors as :func:`position_descriptors` but in blocks (no 2 GB temporary at 1M)."""
    utm = street_walk(n, np.random.default_rng(1), blocks=int(30 * np.sqrt(n / n_ref)))
    desc = np.empty((n, 256), dtype=np.float32)
    rng = np.random.default_rng(2)
    w, phase = rng.normal(scale=1.0 / 40.0, size=(2, 256)), rng.uniform(0, 2 * np.pi, size=256)
    for s in range(0, n, 65536):
        d = np.cos(utm[s:s + 65536] @ w + phase) + 0.6 * rng.normal(size=(len(utm[s:s + 65536]), 256))
        desc[s:s + len(d)] = d / np.linalg.norm(d, axis=1, keepdims=True)
    return utm, desc


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10k images instead of 100k")
    parser.add_argument("--images", type=int, default=0, help="also profile this many images, pinned vs previous")
    args = parser.parse_args()
    n = 10_000 if args.quick else 100_000
    rounds = 3 if args.quick else 5
    rng = np.random.default_rng(0)
    utm = street_walk(n, rng)
    desc = position_descriptors(utm, 256, rng)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores")
    print(f"images: {n:,}, descriptor dim 256, pairs='all' within 25 m, 1 m bins; time: medians of the per-round "
          f"ratios of {rounds} alternating rounds (wall); memory: ratios of tracemalloc peaks; same inputs")
    # per round: the previous implementation, then pinned right after it (both single-threaded), then the
    # others; the multi-threaded variant last, so that its spinning threads do not slow the next one
    impls = {"previous": lambda keep: previous_gds_profile(desc, utm, 25.0, 1.0, keep),
             "pinned": lambda keep: gds_profile(desc, utm, 25.0, 1.0, "all", keep_pairs=keep),
             "first pass": lambda keep: first_pass_gds_profile(desc, utm, 25.0, 1.0, keep),
             "default threads": lambda keep: unpinned_gds_profile(desc, utm, 25.0, 1.0, "all", keep_pairs=keep)}
    failed = False
    for keep in (False, True):
        outs, mem = {}, {}
        for name, fn in impls.items():
            outs[name], _, mem[name] = traced(fn, keep)
        assert np.array_equal(outs["pinned"].count, outs["default threads"].count)
        diff = max(max_difference(outs["pinned"], outs[name], keep) for name in ("first pass", "previous"))
        assert diff <= OUTPUT_ATOL, f"outputs differ from the baselines by {diff:.2g} (> {OUTPUT_ATOL:g})"
        pairs = int(outs["pinned"].count.sum())
        times = {name: [] for name in impls}
        for _ in range(rounds):   # alternate, so that a change of load hits all alike
            for name, fn in impls.items():
                times[name].append(timed(fn, keep)[1])
        t = {name: np.array(v) for name, v in times.items()}
        up = {name: float(np.median(t[name] / t["pinned"])) for name in impls}   # medians of per-round ratios
        print(f"[keep_pairs={keep}] {pairs / n:.0f} pairs per image; same bin counts as both baselines, "
              f"statistics{' and pair distances' if keep else ''} within {diff:.1g} of theirs (tolerance {OUTPUT_ATOL:g})")
        print(f"  speed-up of pinned over: previous {up['previous']:.2f}x, first pass {up['first pass']:.2f}x, "
              f"the same code at default threads {up['default threads']:.2f}x")
        print(f"  speed-up of the same code at default threads over previous: "
              f"{float(np.median(t['previous'] / t['default threads'])):.2f}x")
        if not keep:
            target = QUICK_FLOOR if args.quick else TARGET_SPEEDUP
            met = up["previous"] >= target
            failed |= not met
            print(f"  target: pinned >= {target}x faster than previous{' (--quick floor)' if args.quick else ''}: "
                  f"{'met' if met else 'NOT met'} (ratio to target {up['previous'] / target:.2f})")
        print(f"  memory (tracemalloc peak, same {n:,} images): pinned / previous {mem['pinned'] / mem['previous']:.2f}, "
              f"pinned / first pass {mem['pinned'] / mem['first pass']:.2f}")
    if args.images:
        big_utm, big = big_inputs(args.images, n)
        now, t_now, m_now = traced(gds_profile, big, big_utm, 25.0, 1.0, "all", keep_pairs=True)
        old, t_old, m_old = traced(previous_gds_profile, big, big_utm, 25.0, 1.0, True)
        diff = max_difference(now, old, True)
        assert diff <= OUTPUT_ATOL, f"outputs differ from the previous implementation by {diff:.2g}"
        print(f"[{args.images:,} images, keep_pairs=True, traced] {int(now.count.sum()) / args.images:.0f} pairs per "
              f"image, same bin counts, within {diff:.1g}; speed-up of pinned over previous {t_old / t_now:.2f}x; "
              f"memory pinned / previous {m_now / m_old:.2f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
