"""What the pinned CPU kernels (vpr_nb.kernels) cost: pinned / native CPU time, per layer and for a course fine-tune.

The same work runs in two child processes started one after the other, one with the pinned environment and
one with the processor's own kernels, alternating (pinned, native, native, pinned) so that drifting load hits
both alike. Each child measures process CPU time on one torch thread:

* **layers** (one training batch of the course recipe, 112 images of 32x48 pixels, median of 15 repeats):
  the course backbone's frozen blocks (forward), its trainable 1x1 projection (forward + backward), and the
  NetVLAD-16 and SALAD heads on its 8x12 feature map (forward + backward);
* **products**: one float32 matrix product of the shapes the course's 1x1 layers multiply (10,752 rows = 112
  images x 96 positions, times the layer's weights), the BLAS call under every pinned 1x1 layer
  (:class:`vpr_nb.pointwise.PointwiseConv2d`): MKL's ``COMPATIBLE`` mode against its native code;
* **fine-tune**: ``vpr_nb.recipe.fine_tune`` of NetVLAD, 4 epochs (early stopping off) on the tiny city world.

Printed: each part's CPU seconds both ways and the ratio pinned / native (the target for a course
fine-tune: <= 1.5). Also which convolution paths the pinned child has (oneDNN and NNPACK both off).

    python bench/bench_kernels.py            # layers + products + fine-tune
    python bench/bench_kernels.py --layers   # layers and products only (about a minute)
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from vpr_nb.kernels import PINNED, pinned_environ

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child(parts: list[str]) -> dict:
    """Runs inside a child process: CPU seconds of each part."""
    import dataclasses

    import torch

    from vpr_nb.aggregation import SALAD, NetVLAD
    from vpr_nb.kernels import apply_in_process, is_pinned
    from vpr_nb.pretrain import course_backbone
    from vpr_nb.recipe import RECIPE, Method, fine_tune
    from vpr_nb.synthetic import make_dataset

    apply_in_process()
    torch.set_num_threads(1)
    # NNPACK runs stride-1 convolutions of >= 16 images where it is available and enabled (torch's own flag)
    out = {"pinned": is_pinned(), "nnpack": torch.backends.nnpack.is_available() and torch._C._get_nnpack_enabled(),
           "onednn": torch.backends.mkldnn.enabled}

    def timed(fn, repeats=15):
        fn()
        cpu = []
        for _ in range(repeats):
            t = time.process_time()
            fn()
            cpu.append(time.process_time() - t)
        return statistics.median(cpu)

    if "layers" in parts:
        torch.manual_seed(0)
        backbone = course_backbone(trainable_blocks=1)
        frozen, trainable = backbone.features[:backbone.num_frozen], backbone.features[backbone.num_frozen:]
        x = torch.randn(112, 3, 32, 48)
        with torch.no_grad():
            mid = frozen(x)
        out["frozen blocks, forward"] = timed(lambda: frozen(x).sum())

        def projection():
            trainable.zero_grad()
            trainable(mid).sum().backward()
        out["1x1 projection, forward + backward"] = timed(projection)
        fmap = trainable(mid).detach().requires_grad_(True)
        channels = fmap.shape[1]
        token = fmap.mean((2, 3)).detach()
        heads = (("NetVLAD-16", NetVLAD(num_clusters=16, dim=channels), fmap),
                 ("SALAD", SALAD(num_channels=channels, num_clusters=16, cluster_dim=32, token_dim=64,
                                 hidden_dim=64), (fmap, token)))
        for name, head, inputs in heads:
            def step(head=head, inputs=inputs):
                head.zero_grad()
                head(inputs).sum().backward()
            out[f"{name} head, forward + backward"] = timed(step)
        for k, n, what in ((96, 128, "projection"), (128, 16, "NetVLAD-16 assignment"),
                           (128, 64, "SALAD MLP in"), (64, 32, "SALAD MLP out")):
            rows, weight = torch.randn(112 * 96, k), torch.randn(n, k)
            out[f"product {k}->{n} ({what})"] = timed(lambda rows=rows, weight=weight: rows @ weight.t())
    if "fine-tune" in parts:
        ds = make_dataset("city", seed=0, size="tiny")
        recipe = dataclasses.replace(RECIPE, max_epochs=4, patience=4)
        t = time.process_time()
        fine_tune(Method("netvlad", "netvlad"), ds.train, ds.val, recipe, seed=0, lr=RECIPE.lr)
        out["NetVLAD fine-tune, 4 epochs"] = time.process_time() - t
        # which convolution kernels a (1-epoch) fine-tune calls, by the profiler's operator names
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            fine_tune(Method("netvlad", "netvlad"), ds.train, ds.val, dataclasses.replace(recipe, max_epochs=1),
                      seed=0, lr=RECIPE.lr)
        names = {e.key for e in prof.key_averages()}
        out["nnpack calls"] = sorted(n for n in names if "nnpack" in n.lower())
        out["onednn calls"] = sorted(n for n in names if "mkldnn" in n.lower())
    return out


def run_child(env: dict, parts: list[str]) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", ",".join(parts)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"child failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layers", action="store_true", help="the layers and products only")
    ap.add_argument("--quick", action="store_true", help="the layers and products only (make bench)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child.split(","))))
        return 0
    parts = ["layers"] if args.layers or args.quick else ["layers", "fine-tune"]
    native_env = {k: v for k, v in os.environ.items() if k not in PINNED}
    runs = {True: [], False: []}
    for pinned in (True, False, False, True):
        runs[pinned].append(run_child(pinned_environ(native_env) if pinned else native_env, parts))
    print(f"pinned child: pinned={runs[True][0]['pinned']}, oneDNN convolutions={runs[True][0]['onednn']}, "
          f"NNPACK={runs[True][0]['nnpack']}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"pinned fine-tune, profiled: NNPACK operators {runs[True][0].get('nnpack calls', '-')}, oneDNN "
          f"operators {runs[True][0].get('onednn calls', '-')}; native: NNPACK {runs[False][0].get('nnpack calls', '-')}, "
          f"oneDNN {runs[False][0].get('onednn calls', '-')}")
    for key in runs[True][0]:
        if key in ("pinned", "nnpack", "onednn", "nnpack calls", "onednn calls"):
            continue
        p = statistics.mean(r[key] for r in runs[True])
        n = statistics.mean(r[key] for r in runs[False])
        unit, scale = ("ms", 1e3) if p < 1 else ("s", 1.0)
        print(f"{key:40s} pinned {p * scale:8.2f} {unit}  native {n * scale:8.2f} {unit}  pinned/native {p / n:5.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
