"""Training speed on this machine: the small CNN's throughput and the triplet losses' cost.

1. **Throughput** of one training step (forward + backward + SGD update) of
   ``build_model("small_cnn", "gem")`` on a batch of 64 images of 32x48 (the synthetic world's size),
   with the triplet loss of notebook 02 on the descriptors: images/s (median over repeats).
2. **Losses**: forward + backward time of ``vpr_nb.losses`` triplet_loss (Eq. 3), weighted_triplet_loss
   (Eq. 4 x 3), ce_triplet_loss (Eqs. 5-8) and dw_triplet_loss (Eq. 9) on the same (B=64, M=10, D=256)
   batch, as ratios to ``torch.nn.TripletMarginLoss(margin=0.1, p=2, reduction="sum")`` (fed the M
   triplets of each query as B*M rows). The cases take turns, round after round, so load from other
   processes hits all alike.
3. (not with ``--quick``) one epoch of the notebook-02 recipe (``TripletSource`` on the tiny city,
   mining + training + validation): seconds per epoch, the number that sets the notebooks' budgets.

    python bench/bench_training.py            # all three, 1 thread
    python bench/bench_training.py --quick    # 1 and 2 with fewer repeats
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


def bench_throughput(batch: int, repeats: int) -> None:
    torch.manual_seed(0)
    model = build_model("small_cnn", "gem")
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=1e-3)
    x = torch.randn(batch, 3, 32, 48)
    third = batch // 3

    def step() -> None:
        out = model(x)
        loss = triplet_loss(out[:third], out[third:2 * third], out[2 * third:3 * third])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def forward_only() -> None:
        with torch.no_grad():
            model(x)

    ms = _median_ms({"train step": step, "forward (no grad)": forward_only}, repeats)
    print(f"small CNN + GeM, batch {batch} of 3x32x48, median of {repeats}:")
    print(f"  training step (forward + backward + SGD): {ms['train step']:8.2f} ms  "
          f"= {batch / ms['train step'] * 1e3:8.0f} images/s")
    print(f"  forward only (descriptor cache, eval):    {ms['forward (no grad)']:8.2f} ms  "
          f"= {batch / ms['forward (no grad)'] * 1e3:8.0f} images/s")


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
    print(f"losses, forward + backward, B={b} M={m} D={d}, median of {repeats}:")
    print(f"  {'loss':<30}{'ms':>9}{'ratio to torch':>16}")
    for name, t in ms.items():
        print(f"  {name:<30}{t:9.3f}{t / base:16.2f}")


def bench_epoch() -> None:
    from vpr_nb import seed_everything
    from vpr_nb.synthetic import make_dataset
    from vpr_nb.training import TrainConfig, TripletSource, train

    t0 = time.perf_counter()
    ds = make_dataset("city", seed=0)
    gen = time.perf_counter() - t0
    seed_everything(0)
    model = build_model("small_cnn", "gem")
    src = TripletSource(ds.train, TripletLoss(), max_heading_diff=45)
    hist = train(model, src, ds.val, TrainConfig(epochs=2, lr=0.05), progress=False)
    secs = [e["seconds"] for e in hist.epochs]
    n_img = len(ds.train.q_images) * (2 + src.num_negatives)
    print(f"notebook-02 recipe on the tiny city: world generated in {gen:.1f} s; epochs took "
          + ", ".join(f"{s:.1f}" for s in secs) + f" s (~{n_img} training images + cache + validation each)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer repeats, no training epoch")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: steadier on a shared machine)")
    args = parser.parse_args()
    if args.threads < 1:
        raise ValueError("--threads must be >= 1")
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {os.cpu_count()} cores, "
          f"1-min load average {load:.2f} (timings are inflated when it exceeds the core count)")
    repeats = 5 if args.quick else 30
    bench_throughput(64, repeats)
    bench_losses(64, 10, 256, repeats * 4)
    if not args.quick:
        bench_epoch()


if __name__ == "__main__":
    main()
