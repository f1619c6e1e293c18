"""Training throughput of SmallCNN + GeM, and its ratio to this machine's matmul speed.

One training step = forward + backward + SGD update of ``build_model("small_cnn", "gem")`` on a batch
of 64 images of 32×48 (the course's synthetic size), with a loss on the descriptors. We report

- images/s of the training step;
- achieved GFLOP/s = (FLOPs of one step, counted by ``torch.utils.flop_counter.FlopCounterMode``)
  / (seconds per step);
- the baseline: GFLOP/s of a large square ``torch.matmul`` (2·n³ FLOPs) on the same threads;
- ratio = achieved / matmul, the fraction of the machine's dense-compute limit the model reaches.

Run: ``python bench/bench_throughput.py`` (``--quick`` for a short run, ``--threads`` to pin threads).
"""
from __future__ import annotations

import argparse
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
    """A closure running one SGD step of SmallCNN + GeM on a fixed random batch."""
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

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and a smaller matmul")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--batch", type=int, default=64)
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    repeats, number, n = (2, 3, 1024) if args.quick else (5, 10, 2048)

    step = make_train_step(args.batch, 32, 48)
    with FlopCounterMode(display=False) as counter:
        step()
    flops = counter.get_total_flops()
    seconds = best_seconds(step, repeats, number)
    achieved = flops / seconds / 1e9
    peak = matmul_gflops(n, repeats, number)

    print(f"threads={torch.get_num_threads()}  batch={args.batch}  images 32x48  torch {torch.__version__}")
    print(f"SmallCNN+GeM train step: {seconds * 1e3:.1f} ms, {args.batch / seconds:.0f} images/s, "
          f"{flops / args.batch / 1e6:.1f} MFLOP/image (forward+backward)")
    print(f"achieved {achieved:.1f} GFLOP/s  vs  matmul {n}x{n}: {peak:.1f} GFLOP/s")
    print(f"ratio (model / matmul) = {achieved / peak:.3f}")


if __name__ == "__main__":
    main()
