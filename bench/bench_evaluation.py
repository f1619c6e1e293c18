"""Cost of ``vpr_nb.evaluation`` over a bare faiss search (issue 2 §3: ratio must be <= 1.3).

Data: ``db`` x ``queries`` random L2-normalised float32 descriptors of ``dim`` dimensions
(default 100k x 10k x 256), random UTM positions in a square whose side gives about 8 positives
within 25 m per query, k = 20 (the largest N of Recall@{1,5,10,20}).

What is timed (best of ``--repeats`` runs, the two paths interleaved, faiss on ``--threads`` threads,
1 by default because on a shared 2-core machine multi-threaded OpenMP timings swing by 2x):

- **baseline**: ``faiss.IndexFlatIP(dim)``, ``add(db)``, ``search(q, k)``, on the same arrays;
- **vpr_nb**: ``retrieve(db, q, k)`` (input validation, unit-norm check, the same faiss search,
  conversion to squared L2 distances) + ``recall_at_n(indices, positives)``.
  The positives (``positives_within``, a KD-tree on the UTM) are computed once beforehand and
  *not* included: they depend only on the geotags, not on the descriptors, and the bare faiss
  search has no equivalent. Their time is printed separately, as is the full
  ``evaluate_descriptors`` call (positives included), for information.

Run: ``python bench/bench_evaluation.py`` (``--quick``: 20k x 2k, for ``make bench``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import faiss
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from vpr_nb.evaluation import evaluate_descriptors, positives_within, recall_at_n, retrieve  # noqa: E402

TARGET = 1.3
RADIUS = 25.0
NS = (1, 5, 10, 20)


def unit_rows(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    x = rng.standard_normal((n, dim), dtype=np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="20k x 2k instead of 100k x 10k")
    parser.add_argument("--db", type=int, default=None, help="database size (default 100000, quick 20000)")
    parser.add_argument("--queries", type=int, default=None, help="number of queries (default 10000, quick 2000)")
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1,
                        help="faiss OpenMP threads (default 1: a stable ratio on a shared machine; 0: faiss default)")
    args = parser.parse_args(argv)
    n_db = args.db or (20_000 if args.quick else 100_000)
    n_q = args.queries or (2_000 if args.quick else 10_000)
    for name, v in (("--db", n_db), ("--queries", n_q), ("--dim", args.dim), ("--repeats", args.repeats)):
        if v < 1:
            raise ValueError(f"{name} must be >= 1, got {v}")
    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    k = max(NS)

    warnings.simplefilter("ignore", UserWarning)  # queries without positives: counted and printed below
    rng = np.random.default_rng(0)
    db, q = unit_rows(rng, n_db, args.dim), unit_rows(rng, n_q, args.dim)
    side = float(np.sqrt(n_db * np.pi * RADIUS ** 2 / 8.0))  # ~8 positives per query
    db_utm, q_utm = rng.uniform(0, side, (n_db, 2)), rng.uniform(0, side, (n_q, 2))
    t_pos = timed(lambda: positives_within(db_utm, q_utm, RADIUS))
    positives = positives_within(db_utm, q_utm, RADIUS)
    no_pos = sum(len(p) == 0 for p in positives)

    def bare():
        index = faiss.IndexFlatIP(args.dim)
        index.add(db)
        return index.search(q, k)

    # same neighbours (ties aside): a check that both paths do the same work
    _, i_bare = bare()
    _, i_ours = retrieve(db, q, k)
    agree = float(np.mean(i_bare[:, 0] == i_ours[:, 0]))
    t_bare, t_ours = [], []
    for _ in range(args.repeats):  # interleaved, so that load from other processes hits both alike
        t_bare.append(timed(bare))
        start = time.perf_counter()
        _, idx = retrieve(db, q, k)
        mid = time.perf_counter()
        recall_at_n(idx, positives, NS)
        t_ours.append((time.perf_counter() - start, mid - start, time.perf_counter() - mid))
    t_full = timed(lambda: evaluate_descriptors(db, q, db_utm, q_utm, RADIUS, NS))

    best_bare = min(t_bare)
    best_ours, t_retrieve, t_recall = min(t_ours)
    ratio = best_ours / best_bare
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; evaluation bench: db {n_db} x "
          f"queries {n_q} x dim {args.dim}, k={k}, faiss threads {faiss.omp_get_max_threads()}, best of {args.repeats}")
    print(f"  top-1 agreement vpr_nb vs bare faiss          : {agree:.4f}")
    print(f"  vpr_nb retrieve + recall_at_n / bare faiss     : {ratio:8.3f}   (target <= {TARGET}: "
          f"{'PASS' if ratio <= TARGET else 'FAIL'}; retrieve {t_retrieve / best_bare:.3f}, recall_at_n "
          f"{t_recall / best_bare:.3f})")
    print(f"  positives_within / bare faiss (not in ratio)   : {t_pos / best_bare:8.3f}   "
          f"({no_pos} queries without positive, excluded from Recall@N)")
    print(f"  evaluate_descriptors (all) / bare faiss        : {t_full / best_bare:8.3f}")
    return 0 if ratio <= TARGET else 1


if __name__ == "__main__":
    sys.exit(main())
