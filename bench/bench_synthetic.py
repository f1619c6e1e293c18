"""Time and memory of the synthetic world generator against its budget (issue 2 §2).

Budget for a ``tiny`` preset: generation <= 5 s and <= 200 MB on 2 cores.

For each preset (``make_dataset(preset)``, size ``tiny``, seed 0, all splits) we measure

- **time**: best wall time of ``--repeats`` calls (without tracing, which would slow it down);
- **peak memory**: the peak of Python + numpy heap allocations during one call, from
  ``tracemalloc`` (numpy reports its array buffers to it), above what was allocated before the call;
- as a cross-check that also sees allocations outside numpy (scipy's KD-tree, ...): the growth of
  the process peak RSS (``resource.getrusage(...).ru_maxrss``) from after the imports to the end of
  all calls (an upper bound on the worst single call, since RSS also keeps freed pages).

Prints each value and its ratio to the budget (ratio <= 1 is within budget); the time both as wall
time and as the process's CPU time (less sensitive to other jobs on the machine). Only the memory
budget can fail the run (exit 1): time depends on what else the machine runs, so a slow time is
reported as a ratio and never stops ``make bench`` (which runs every bench in any case).
Run: ``python bench/bench_synthetic.py`` (``--quick``: one repeat).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from vpr_nb.synthetic import make_dataset  # noqa: E402

BUDGET_S = 5.0
BUDGET_MB = 200.0


def measure(preset: str, repeats: int) -> tuple[float, float, float, tuple]:
    """(best wall seconds, best CPU seconds, traced peak MB, db/q image shapes) of ``make_dataset(preset)``."""
    best = cpu = float("inf")
    for _ in range(repeats):
        start, c0 = time.perf_counter(), time.process_time()
        ds = make_dataset(preset)
        best = min(best, time.perf_counter() - start)
        cpu = min(cpu, time.process_time() - c0)
    shapes = (ds.db_images.shape, ds.q_images.shape)
    del ds
    tracemalloc.start()
    base, _ = tracemalloc.get_traced_memory()
    make_dataset(preset)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return best, cpu, (peak - base) / 2 ** 20, shapes


def max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one timing repeat instead of three")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args(argv)
    repeats = args.repeats or (1 if args.quick else 3)
    if repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {repeats}")
    over = False
    rss0 = max_rss_mb()
    print(f"synthetic bench: make_dataset(preset, size='tiny'), best of {repeats}; "
          f"budget {BUDGET_S:.0f} s and {BUDGET_MB:.0f} MB")
    for preset in ("city", "route"):
        seconds, cpu, mb, (db_shape, q_shape) = measure(preset, repeats)
        over |= mb > BUDGET_MB          # memory only: a loaded machine must not fail the bench
        slow = seconds > BUDGET_S
        print(f"  {preset:5s}: {seconds:6.2f} s wall, {cpu:6.2f} s CPU  ({seconds / BUDGET_S:.2f} / "
              f"{cpu / BUDGET_S:.2f} of budget)   "
              f"peak {mb:6.1f} MB ({mb / BUDGET_MB:.2f} of budget)   db {db_shape}, queries {q_shape}"
              + ("   (time over budget: load %.1f, not a failure)" % os.getloadavg()[0] if slow else ""))
    rss1 = max_rss_mb()
    print(f"  process peak RSS: {rss0:.0f} MB after imports, {rss1:.0f} MB after all calls "
          f"(growth {rss1 - rss0:.0f} MB, {(rss1 - rss0) / BUDGET_MB:.2f} of budget)")
    print("  memory within budget" if not over else "  MEMORY OVER BUDGET")
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
