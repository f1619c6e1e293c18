"""Benchmark: GDS profile of 100k images, all pairs within 25 m, against a 30 s budget.

The images follow a random walk on a street grid (one image every ~1.5 m, with GPS noise);
their 256-D descriptors are random Fourier features of the position plus noise, so that
descriptor distance grows with geographic distance. Prints the run time, its ratio to the
30 s budget (< 1 is within budget) and the peak resident memory.

    python bench/bench_gds.py            # 100k images
    python bench/bench_gds.py --quick    # 10k images
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from vpr_nb.gds import gds_profile, misordering_probability

BUDGET_S = 30.0


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
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    t0 = time.perf_counter()
    prof = gds_profile(desc, utm, max_distance=25.0, bin_width=1.0, pairs="all", keep_pairs=True)
    seconds = time.perf_counter() - t0
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    print(f"images: {n}, pairs within 25 m: {int(prof.count.sum()):,}, descriptor dim: 256")
    print(f"slope: {prof.slope:.5f} per m, intercept {prof.intercept:.4f}; "
          f"P(misorder 2 m vs 20 m) = {misordering_probability(prof, 2.0, 20.0, 'empirical'):.3f}")
    print(f"gds_profile(pairs='all', keep_pairs=True): {seconds:.2f} s")
    print(f"ratio to the {BUDGET_S:.0f} s budget: {seconds / BUDGET_S:.3f} (< 1 is within budget)")
    print(f"peak RSS: {rss_after:.0f} MiB (was {rss_before:.0f} MiB before the call; "
          f"a dense N x N float32 matrix would need {n * n * 4 / 2**20:,.0f} MiB)")


if __name__ == "__main__":
    main()
