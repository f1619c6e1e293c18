"""Cost of the input checks (shapes, dtypes, NaN/inf) in NetVLAD, SALAD and a course training step.

Every case runs with the checks on and off, alternating call by call in this one process (pairs in both
orders, so a change of load hits both alike); "off" replaces ``check_tensor`` and the feature-map / image checks of
``vpr_nb.aggregation``, ``vpr_nb.models`` and ``vpr_nb.losses`` by pass-throughs. Times are process
CPU seconds on one torch thread (less sensitive to other jobs than wall time). Printed per case: the
checks' share of the time with checks on, ``1 - median(off) / median(on)`` over the calls.
Target: <= 3 % of NetVLAD and SALAD layer inference (the run fails above it).

Cases: the NetVLAD and SALAD layers at the sizes of bench_aggregation.py (inference, and NetVLAD
forward + backward), and the course model (SmallCNN + NetVLAD, 32x48 images) for inference and one
triplet training step (forward, loss, backward, Adam).

    python bench/bench_checks.py            # full sizes, 15 s of CPU time per case
    python bench/bench_checks.py --quick    # smaller SALAD, 4 s per case
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time
from typing import Callable

import torch

from vpr_nb.aggregation import SALAD, NetVLAD
from vpr_nb.losses import triplet_loss
from vpr_nb.models import build_model

TARGET = 0.03   # checks' share of NetVLAD and SALAD inference
# the check functions, in every module of these packages that binds one (a package's modules import them by name)
_PACKAGES = ("vpr_nb.aggregation", "vpr_nb.models", "vpr_nb.losses")
_CHECK_NAMES = ("check_tensor", "_check_feature_map", "_check_images")


def _passthrough(x, *args, **kwargs):
    return x


@contextlib.contextmanager
def checks_off():
    """Replace the tensor checks of the layers, models and losses by pass-throughs."""
    modules = [m for key, m in sorted(sys.modules.items()) if key.startswith(_PACKAGES)]
    saved = [(mod, name, getattr(mod, name)) for mod in modules for name in _CHECK_NAMES if hasattr(mod, name)]
    for mod, name, _ in saved:
        setattr(mod, name, _passthrough)
    try:
        yield
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)


def share_of_checks(step: Callable[[], None], seconds: float) -> tuple[float, float, float]:
    """Checks' share ``1 - median(off) / median(on)`` of the per-call CPU time, calls alternating on/off
    (pairs in both orders) for about ``seconds`` of CPU time; also the quartiles of the per-pair shares."""
    for mode in ("on", "off", "on", "off"):   # warm-up
        with checks_off() if mode == "off" else contextlib.nullcontext():
            step()
    times: dict[str, list[float]] = {"on": [], "off": []}
    pairs: list[float] = []
    c_start = time.process_time()
    while time.process_time() - c_start < seconds or len(pairs) < 10:
        order = ("on", "off") if len(pairs) % 2 == 0 else ("off", "on")
        t = {}
        for mode in order:
            with checks_off() if mode == "off" else contextlib.nullcontext():
                c0 = time.process_time()
                step()
                t[mode] = time.process_time() - c0
            times[mode].append(t[mode])
        pairs.append(1 - t["off"] / t["on"])
    q = statistics.quantiles(pairs, n=4)
    return 1 - statistics.median(times["off"]) / statistics.median(times["on"]), q[0], q[2]


def cases(quick: bool) -> dict[str, tuple[Callable[[], None], bool]]:
    """name -> (step, held to the target)."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    netvlad = NetVLAD(num_clusters=64, dim=512).eval()
    x_nv = torch.randn(8, 512, 30, 40, generator=g)
    c, side, batch = (256, 16, 8) if quick else (768, 23, 32)
    salad = SALAD(num_channels=c).eval()
    feats, token = torch.randn(batch, c, side, side, generator=g), torch.randn(batch, c, generator=g)
    x_grad = x_nv.clone().requires_grad_(True)

    def netvlad_fwd_bwd() -> None:
        x_grad.grad = None
        netvlad.zero_grad(set_to_none=True)
        netvlad(x_grad).square().sum().backward()

    model = build_model("small_cnn", "netvlad", num_clusters=16)
    images = torch.randn(48, 3, 32, 48, generator=g)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def train_step() -> None:
        d = model(images)
        loss = triplet_loss(d[:16], d[16:32], d[32:].reshape(16, 1, -1), 0.1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def no_grad(fn):
        def run() -> None:
            with torch.no_grad():
                fn()
        return run

    return {
        "NetVLAD layer inference (B=8, D=512, K=64, 30x40)": (no_grad(lambda: netvlad(x_nv)), True),
        f"SALAD layer inference (B={batch}, C={c}, {side}x{side})": (no_grad(lambda: salad((feats, token))), True),
        "NetVLAD layer forward + backward": (netvlad_fwd_bwd, False),
        "course model inference (SmallCNN + NetVLAD-16, 48 images)": (no_grad(lambda: model(images)), False),
        "course training step (triplet loss, Adam)": (train_step, False),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a smaller SALAD input and fewer rounds")
    parser.add_argument("--seconds", type=float, default=None, help="CPU seconds per case (default 15, quick 4)")
    args = parser.parse_args()
    seconds = args.seconds or (4.0 if args.quick else 15.0)
    torch.set_num_threads(1)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; torch 1 thread; "
          f"checks on/off alternating call by call for {seconds:g} s of CPU time per case")
    failed = []
    for name, (step, held) in cases(args.quick).items():
        share, lo, hi = share_of_checks(step, seconds)
        verdict = ""
        if held:
            verdict = f" (target <= {TARGET:.0%}: {'met' if share <= TARGET else 'NOT met'})"
            if share > TARGET:
                failed.append(name)
        print(f"  {name}: checks {share:6.1%} of the time (quartiles of the per-pair shares {lo:.1%} .. {hi:.1%})"
              f"{verdict}")
    if failed:
        print("checks over target in: " + "; ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
