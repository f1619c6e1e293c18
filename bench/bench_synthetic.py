"""The synthetic world generator: batched rendering against one camera at a time, in one run.

For each preset (``make_dataset(preset)``, size ``tiny``, seed 0, all splits) it compares the package's
renderer, which ray-casts spatially coherent chunks of 32 cameras at once, with the naive version of
the same renderer: one camera per call (``render_all(..., chunk=1)``). Both must give identical
pixels (checked: the run fails otherwise). Every printed number is a ratio measured in this run:

- **time**: CPU seconds of ``make_dataset`` with one camera per call / batched (best of ``--repeats``
  calls each, alternating), and the same for wall seconds;
- **memory**: tracemalloc peak of one batched call / bytes of the images it returns (what any generator
  has to hold), and batched peak / one-camera peak.

    python bench/bench_synthetic.py            # 2 alternating repeats
    python bench/bench_synthetic.py --quick    # 1 repeat
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from vpr_nb.synthetic import make_dataset, world  # noqa: E402


@contextlib.contextmanager
def one_camera_per_call():
    """``make_dataset`` with its renderer called for one camera at a time (the naive loop)."""
    batched = world.render_all

    def one_camera(*args, **kwargs):
        return batched(*args[:8], 1, **kwargs)           # chunk (the 9th argument): one camera per call
    world.render_all = one_camera
    try:
        yield
    finally:
        world.render_all = batched


def run(preset: str, naive: bool):
    """(dataset, wall seconds, CPU seconds) of one ``make_dataset(preset)``."""
    with one_camera_per_call() if naive else contextlib.nullcontext():
        w0, c0 = time.perf_counter(), time.process_time()
        ds = make_dataset(preset)
        return ds, time.perf_counter() - w0, time.process_time() - c0


def peak_mb(preset: str, naive: bool) -> float:
    with one_camera_per_call() if naive else contextlib.nullcontext():
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        make_dataset(preset)
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
    return peak / 2 ** 20


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one timing repeat instead of two")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args(argv)
    repeats = args.repeats or (1 if args.quick else 2)
    if repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {repeats}")
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; make_dataset(preset, "
          f"size='tiny'), batched renderer vs one camera per call, best of {repeats} alternating")
    failed = False
    for preset in ("city", "route"):
        best = {False: (np.inf, np.inf), True: (np.inf, np.inf)}
        images = {}
        for _ in range(repeats):
            for naive in (False, True):
                ds, wall, cpu = run(preset, naive)
                images[naive] = (ds.db_images, ds.q_images)
                best[naive] = (min(best[naive][0], wall), min(best[naive][1], cpu))
        same = all(np.array_equal(a, b) for a, b in zip(images[False], images[True]))
        failed |= not same
        out_mb = sum(a.nbytes for a in images[False]) / 2 ** 20
        mb = {naive: peak_mb(preset, naive) for naive in (False, True)}
        print(f"  {preset:5s}: {'identical pixels' if same else 'PIXELS DIFFER'}; batched speed-up over one camera "
              f"per call {best[True][1] / best[False][1]:.2f}x CPU, {best[True][0] / best[False][0]:.2f}x wall; "
              f"peak memory / output images {mb[False] / out_mb:.2f}, batched peak / one-camera peak "
              f"{mb[False] / mb[True]:.2f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
