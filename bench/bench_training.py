"""Training cost on this machine as ratios measured in one run: the losses, and an epoch over its steps.

1. **Losses**: forward + backward time of ``vpr_nb.losses`` triplet_loss (Eq. 3), weighted_triplet_loss
   (Eq. 4 x 3), ce_triplet_loss (Eqs. 5-8) and dw_triplet_loss (Eq. 9) on one (B=64, M=10, D=256) batch,
   as ratios to ``torch.nn.TripletMarginLoss(margin=0.1, p=2, reduction="sum")`` (fed the M triplets of
   each query as B*M rows). The cases take turns, round after round, so load from other processes hits
   all alike.
2. (not with ``--quick``) one epoch of the notebook-02 recipe (``TripletSource`` on the tiny city:
   descriptor cache, mining, training steps, validation) against its bare training steps: the same
   number of forward + loss + backward + SGD steps of the same model on a fixed batch of the same
   shape. The ratio (CPU time, >= 1) is what the data pipeline costs on top of the arithmetic.
   (The model's arithmetic against the machine's matmul limit is bench_throughput.py.)

    python bench/bench_training.py            # both, 1 thread
    python bench/bench_training.py --quick    # the losses, fewer repeats
    python bench/bench_training.py --threads 2
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from vpr_nb.losses import TripletLoss, ce_triplet_loss, dw_triplet_loss, triplet_loss, weighted_triplet_loss
from vpr_nb.models import build_model


def _median_ms(cases: dict[str, Callable[[], None]], repeats: int, warmup: int = 2) -> dict[str, float]:
    """Median wall time (ms) of each case; the cases take turns so that outside load hits all alike."""
    times: dict[str, list[float]] = {name: [] for name in cases}
    for i in range(repeats + warmup):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            ms = (time.perf_counter() - t0) * 1e3
            if i >= warmup:
                times[name].append(ms)
    return {name: statistics.median(v) for name, v in times.items()}


def bench_losses(b: int, m: int, d: int, repeats: int) -> None:
    g = torch.Generator().manual_seed(0)
    q = F.normalize(torch.randn(b, d, generator=g), dim=-1).requires_grad_(True)
    p = F.normalize(torch.randn(b, d, generator=g), dim=-1).requires_grad_(True)
    n = F.normalize(torch.randn(b, m, d, generator=g), dim=-1).requires_grad_(True)
    geo = torch.rand(b, generator=g) * 10.0           # metres: positives within the 10 m training radius
    ref = torch.nn.TripletMarginLoss(margin=0.1, p=2, reduction="sum")

    def case(fn: Callable[[], torch.Tensor]) -> Callable[[], None]:
        def run() -> None:
            for t in (q, p, n):
                t.grad = None
            fn().backward()
        return run

    cases = {
        "torch.nn.TripletMarginLoss": case(lambda: ref(q.repeat_interleave(m, 0), p.repeat_interleave(m, 0),
                                                       n.reshape(b * m, d))),
        "triplet_loss (Eq. 3)": case(lambda: triplet_loss(q, p, n, 0.1)),
        "weighted_triplet_loss (W-T)": case(lambda: weighted_triplet_loss(q, p, n, geo)),
        "ce_triplet_loss (Eqs. 5-8)": case(lambda: ce_triplet_loss(q, p, n)),
        "dw_triplet_loss (Eq. 9)": case(lambda: dw_triplet_loss(q, p, n, geo)),
    }
    ms = _median_ms(cases, repeats)
    base = ms["torch.nn.TripletMarginLoss"]
    print(f"losses, forward + backward, B={b} M={m} D={d}, median of {repeats}; time / torch.nn.TripletMarginLoss:")
    for name, t in ms.items():
        if name != "torch.nn.TripletMarginLoss":
            print(f"  {name:<30}{t / base:8.2f}")


def bench_epoch(repeats: int) -> None:
    import math

    from vpr_nb import seed_everything
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import TrainConfig, TripletSource, train

    ds = make_dataset("city", seed=0)
    seed_everything(0)
    model = build_model("small_cnn", "gem")
    src = TripletSource(ds.train, TripletLoss(), max_heading_diff=45)
    c0 = time.process_time()
    train(model, src, ds.val, TrainConfig(epochs=1, lr=0.05), progress=False)
    epoch = time.process_time() - c0
    steps = math.ceil(len(ds.train.q_images) / src.batch_size)
    bare = build_model("small_cnn", "gem")
    opt = torch.optim.SGD(bare.parameters(), lr=0.05, momentum=0.9, weight_decay=1e-3)
    b, m = src.batch_size, src.num_negatives
    x = torch.randn(b * (2 + m), 3, 32, 48, generator=torch.Generator().manual_seed(0))

    def step() -> None:
        out = bare(x)
        loss = src.loss(out[:b], out[b:2 * b], out[2 * b:].view(b, m, -1), torch.zeros(b))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    step()
    times = []
    for _ in range(repeats):
        c0 = time.process_time()
        step()
        times.append(time.process_time() - c0)
    print(f"notebook-02 recipe on the tiny city: one epoch / its {steps} bare training steps of {b * (2 + m)} images "
          f"= {epoch / (steps * statistics.median(times)):.2f} (CPU time; descriptor cache, mining and validation "
          f"on top of the arithmetic)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer repeats, no training epoch")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: steadier on a shared machine)")
    args = parser.parse_args()
    if args.threads < 1:
        raise ValueError("--threads must be >= 1")
    torch.set_num_threads(args.threads)
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average) on {os.cpu_count()} cores; torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s)")
    repeats = 5 if args.quick else 30
    bench_losses(64, 10, 256, repeats * 4)
    if not args.quick:
        bench_epoch(repeats)


if __name__ == "__main__":
    main()
