"""Training throughput of SmallCNN + GeM as a fraction of this machine's matmul speed, measured in one run.

One training step = forward + backward + SGD update of ``build_model("small_cnn", "gem")`` on a batch
of 64 images of 32×48 (the course's synthetic size), with a loss on the descriptors. The baseline is
the machine's sgemm limit measured in the same run: GFLOP/s of a large square ``torch.matmul``
(2·n³ FLOPs) on the same thread count. Printed: the fraction of that limit the training step reaches
(FLOPs of one step counted by ``torch.utils.flop_counter.FlopCounterMode``, divided by its time) and
the same for the forward pass alone. One torch thread by default, as the notebooks run (on a shared
2-core machine a second thread mostly measures the other jobs).

Run: ``python bench/bench_throughput.py`` (``--quick`` for a short run, ``--threads N`` for N threads).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from vpr_nb.models import build_model  # noqa: E402


def best_seconds(fn, repeats: int, number: int) -> float:
    """Best over ``repeats`` of the mean time of ``number`` calls of ``fn`` (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - start) / number)
    return best


def matmul_gflops(n: int, repeats: int, number: int) -> float:
    """GFLOP/s of an ``n×n @ n×n`` float32 matmul (2·n³ FLOPs)."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(n, n, generator=g), torch.randn(n, n, generator=g)
    return 2 * n ** 3 / best_seconds(lambda: a @ b, repeats, number) / 1e9


def make_train_step(batch: int, height: int, width: int):
    """Closures running one SGD step, and one forward pass, of SmallCNN + GeM on a fixed random batch."""
    torch.manual_seed(0)
    model = build_model("small_cnn", "gem").train()
    optimizer = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9)
    x = torch.randn(batch, 3, height, width, generator=torch.Generator().manual_seed(1))

    def step() -> None:
        desc = model(x)
        loss = (desc @ desc.T).triu(1).square().mean()  # push descriptors apart; any scalar works
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    def forward() -> None:
        with torch.no_grad():
            model(x)

    return step, forward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and a smaller matmul")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as the notebooks)")
    parser.add_argument("--batch", type=int, default=64)
    args = parser.parse_args()
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    torch.set_num_threads(args.threads)
    repeats, number, n = (2, 3, 1024) if args.quick else (5, 10, 2048)

    step, forward = make_train_step(args.batch, 32, 48)
    flops = {}
    for name, fn in (("step", step), ("forward", forward)):
        with FlopCounterMode(display=False) as counter:
            fn()
        flops[name] = counter.get_total_flops()
    peak = matmul_gflops(n, repeats, number)            # measured before and after the model: the limit is
    step_s = best_seconds(step, repeats, number)        # the better of the two (load can only lower it)
    forward_s = best_seconds(forward, repeats, number)
    peak = max(peak, matmul_gflops(n, repeats, number))

    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s); SmallCNN+GeM, batch {args.batch} of 32x48 images; baseline: "
          f"{n}x{n} float32 matmul in this run")
    print(f"training step (forward + backward + SGD): {flops['step'] / step_s / 1e9 / peak:.3f} of the matmul limit")
    print(f"forward pass (no grad):                   {flops['forward'] / forward_s / 1e9 / peak:.3f} of the matmul limit")


if __name__ == "__main__":
    main()
