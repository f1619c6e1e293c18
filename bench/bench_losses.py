"""Forward+backward time of the DW-T-Loss triplet family against ``torch.nn.TripletMarginLoss``.

One batch of B queries, B positives and B x M negatives of dimension D; every loss runs on the
same tensors with ``reduction="sum"``. Prints the median time of each loss and its ratio to
TripletMarginLoss (the cases take turns, round after round; torch is fed the M triplets per query as (B, 1, D), (B, 1, D), (B, M, D) tensors).

    python bench/bench_losses.py            # B=32, M=10, D=4096
    python bench/bench_losses.py --quick    # B=8, M=4, D=256
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Callable

import torch

from vpr_nb.losses import ce_triplet_loss, dw_triplet_loss, triplet_loss, weighted_triplet_loss


def _time_ms(step: Callable[[], torch.Tensor], tensors: list[torch.Tensor], device: torch.device) -> float:
    """Wall time (ms) of one ``step().backward()``."""
    for t in tensors:
        t.grad = None
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    step().backward()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) * 1e3


def _median_ms(cases: dict[str, Callable[[], torch.Tensor]], tensors: list[torch.Tensor], repeats: int,
               device: torch.device) -> dict[str, float]:
    """Median time of each case; the cases take turns so that load from other processes hits all alike."""
    times: dict[str, list[float]] = {name: [] for name in cases}
    for i in range(repeats + 2):  # two warm-up rounds
        for name, step in cases.items():
            ms = _time_ms(step, tensors, device)
            if i >= 2:
                times[name].append(ms)
    return {name: statistics.median(values) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small batch (B=8, M=4, D=256), few repeats")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--negatives", type=int, default=10)
    parser.add_argument("--dim", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 gives steadier timings on a shared machine)")
    args = parser.parse_args()
    b, m, d, repeats = (8, 4, 256, 10) if args.quick else (args.batch, args.negatives, args.dim, args.repeats)
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)

    g = torch.Generator().manual_seed(args.seed)
    q, p = (torch.nn.functional.normalize(torch.randn(b, d, generator=g), dim=-1) for _ in range(2))
    n = torch.nn.functional.normalize(torch.randn(b, m, d, generator=g), dim=-1)
    geo = torch.rand(b, generator=g) * 25.0  # metres, inside a 25 m positive radius
    q, p, n, geo = (t.to(device) for t in (q, p, n, geo))
    leaves = [t.requires_grad_(True) for t in (q, p, n)]

    torch_loss = torch.nn.TripletMarginLoss(margin=0.1, p=2, reduction="sum")
    cases: dict[str, Callable[[], torch.Tensor]] = {
        "torch.nn.TripletMarginLoss": lambda: torch_loss(q.unsqueeze(1), p.unsqueeze(1), n),
        "triplet_loss (Eq. 3)": lambda: triplet_loss(q, p, n),
        "weighted_triplet_loss (W-T)": lambda: weighted_triplet_loss(q, p, n, geo),
        "ce_triplet_loss (Eqs. 5-8)": lambda: ce_triplet_loss(q, p, n),
        "dw_triplet_loss (Eq. 9)": lambda: dw_triplet_loss(q, p, n, geo),
    }
    times = _median_ms(cases, leaves, repeats, device)
    baseline = times["torch.nn.TripletMarginLoss"]

    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; forward+backward, B={b} "
          f"M={m} D={d}, device={device}, median of {repeats}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads; time / torch.nn.TripletMarginLoss:")
    for name, ms in times.items():
        if name != "torch.nn.TripletMarginLoss":
            print(f"  {name:<30}{ms / baseline:>8.2f}")


if __name__ == "__main__":
    main()
