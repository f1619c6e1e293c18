"""The frozen-block cache (vpr_nb.feature_cache): CPU time of a notebook-sized fine-tune without / with it.

1. **One fine-tune** per aggregator (``vpr_nb.recipe.fine_tune``, the course recipe: course backbone, last block
   trainable, triplets of 16 queries, Adam, validation every epoch, the epoch-0 candidate) on the tiny city
   world, ``--epochs`` epochs (early stopping off), without and with the cache, in the order
   uncached, cached, cached, uncached so that drifting load hits both alike. Printed: process CPU seconds,
   the ratio uncached / cached (target >= 1.4), and whether the two paths agree: per-epoch losses and final
   test descriptors (max |difference|, must be <= 1e-5).
2. (not with ``--quick``) **An lr search** (``lr_search``: 3 learning rates x 2 seeds, GeM), where one cache
   serves all six runs, as a notebook's search does.
3. (not with ``--quick``) **A wider backbone** (``--wide``, default 96): the same GeM fine-tune with a
   randomly initialised ``SmallCNN`` of that width standing in for the course backbone (timing only: the
   frozen blocks' share of a step grows with the width, so this is what the cache saves for the wider course
   backbone the world/backbone issue plans).
4. **Memory**: the cache's bytes per image and in all after a run, and the descriptor error of ``float16``
   storage (why the default is ``float32``).
5. **Where a step's time goes** (also ``--parts`` alone): one training batch of 112 images (16 triplets of a
   query, a positive and 5 negatives) through the course backbone: the frozen blocks' forward (what the cache
   saves) against the trainable block's forward + backward, median of 20 repeats, and the Amdahl cap on the
   cache's ratio for that batch, 1 + frozen / trainable (the aggregator, loss and optimiser only lower it).
   Which convolution path runs depends on the kernels: run it as ``python -m vpr_nb.kernels --run python
   bench/bench_frozen_cache.py --parts`` (pinned, as the notebooks) and without the pins to compare.

Timings are process CPU time on one torch thread; the script prints the load average, since the ratio is
what it measures (both paths in one run), not absolute time. Nothing fails on time; a disagreement of the two
paths beyond 1e-5 makes the script exit 1.

    python bench/bench_frozen_cache.py            # gem, netvlad, salad, 4 epochs each, + the lr search
    python bench/bench_frozen_cache.py --quick    # gem, 1 epoch
    python bench/bench_frozen_cache.py --parts    # part 5 only
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")     # as the notebooks: single-threaded numpy BLAS

import argparse
import dataclasses
import sys
import time

import numpy as np
import torch

import vpr_nb.pretrain
from vpr_nb.evaluation import compute_descriptors
from vpr_nb.feature_cache import FrozenFeatureCache
from vpr_nb.models import SmallCNN
from vpr_nb.recipe import RECIPE, Method, build_start, fine_tune, lr_search
from vpr_nb.synthetic import make_dataset

TOLERANCE = 1e-5


def _load() -> str:
    try:
        return "load average " + " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "load average unknown"


def _timed(fn):
    c0 = time.process_time()
    out = fn()
    return out, time.process_time() - c0


def _stand_in(width: int):
    """A random-init SmallCNN of ``width`` with course_backbone's signature (for the timing of a wider backbone)."""
    def make(path=None, trainable_blocks: int = 0, final_relu: bool = True):
        torch.manual_seed(0)
        backbone = SmallCNN(width=width, out_channels=128)
        if not final_relu:
            backbone.features[-1] = torch.nn.Identity()
        return backbone.set_trainable_blocks(trainable_blocks)
    return make


def bench_fine_tune(ds, aggregator: str, epochs: int, order: str, label: str = "") -> bool:
    recipe = dataclasses.replace(RECIPE, max_epochs=epochs, patience=epochs)
    method = Method(aggregator, aggregator)
    cpu = {False: [], True: []}
    runs, caches = {}, []
    for cached in (c == "C" for c in order):
        cache = FrozenFeatureCache() if cached else None
        rec = dataclasses.replace(recipe, frozen_cache=cached)
        run, sec = _timed(lambda: fine_tune(method, ds.train, ds.val, rec, seed=0, lr=RECIPE.lr, cache=cache))
        cpu[cached].append(sec)
        runs.setdefault(cached, run)
        if cache is not None:
            caches.append(cache)
    d0 = compute_descriptors(runs[False].model, ds.test.q_images)
    d1 = compute_descriptors(runs[True].model, ds.test.q_images)
    loss_diff = float(np.max(np.abs(np.subtract(runs[False].history.losses, runs[True].history.losses))))
    desc_diff = float(np.abs(d0 - d1).max())
    ratio = sum(cpu[False]) / sum(cpu[True])
    stats = caches[0].stats()
    print(f"{aggregator + label:8s} {epochs} epoch(s): uncached {np.mean(cpu[False]):6.1f} s, cached {np.mean(cpu[True]):6.1f} s "
          f"CPU per fine-tune -> ratio {ratio:.2f} (target >= 1.4); max |loss diff| {loss_diff:.1e}, "
          f"max |test descriptor diff| {desc_diff:.1e}; cache {stats['images']} images, {stats['MiB']} MiB, "
          f"hits/misses {stats['hits']}/{stats['misses']}")
    return loss_diff <= TOLERANCE and desc_diff <= TOLERANCE


def bench_search(ds, epochs: int) -> None:
    recipe = dataclasses.replace(RECIPE, max_epochs=epochs, patience=epochs, search_seeds=2)
    method = Method("GeM", "gem")
    cpu = {}
    for cached in (False, True, True, False):
        rec = dataclasses.replace(recipe, frozen_cache=cached)
        _, sec = _timed(lambda: lr_search(method, ds.train, ds.val, rec, seeds=(0, 1)))
        cpu.setdefault(cached, []).append(sec)
    print(f"lr search (GeM, grid {list(recipe.lr_grid)} x seeds [0, 1], {epochs} epoch(s) each, one cache for the "
          f"6 runs): uncached {np.mean(cpu[False]):.1f} s, cached {np.mean(cpu[True]):.1f} s CPU -> ratio "
          f"{sum(cpu[False]) / sum(cpu[True]):.2f}")


def bench_memory(ds) -> None:
    model = build_start(Method("GeM", "gem"), ds.train, RECIPE, seed=0)
    exact = compute_descriptors(model, ds.val.q_images)
    out = {}
    for dtype in ("float32", "float16"):
        cache = FrozenFeatureCache(dtype=dtype)
        with cache.attached(model.backbone):
            for split in (ds.train, ds.val):
                compute_descriptors(model, split.db_images)
                compute_descriptors(model, split.q_images)
            out[dtype] = (cache, float(np.abs(compute_descriptors(model, ds.val.q_images) - exact).max()))
    images = len(out["float32"][0])
    fmap = model.backbone.features[:model.backbone.num_frozen](
        torch.zeros(1, 3, *ds.train.db_images.shape[1:3]))
    per_image = fmap.numel() * 4
    key = 3 * int(np.prod(ds.train.db_images.shape[1:3])) * 4      # the key: the image's input floats
    print(f"memory: a frozen map is {tuple(fmap.shape[1:])} = {per_image / 1024:.1f} KiB in float32, its key "
          f"{key / 1024:.1f} KiB; the train + val splits of the tiny city ({images} images) take "
          f"{images * (per_image + key) / 2 ** 20:.1f} MiB (float32; the cache holds "
          f"{out['float32'][0].nbytes / 2 ** 20:.1f} MiB), float16 {out['float16'][0].nbytes / 2 ** 20:.1f} MiB")
    print(f"float16 storage: max |val descriptor difference| {out['float16'][1]:.1e} (float32: "
          f"{out['float32'][1]:.1e}); tolerance {TOLERANCE:g} -> default float32")


def bench_step_parts(ds, repeats: int = 20) -> None:
    """Part 5: the frozen blocks' forward vs the trainable block's forward + backward on one training batch."""
    from vpr_nb.evaluation import images_to_tensor
    from vpr_nb.kernels import describe

    backbone = vpr_nb.pretrain.course_backbone(trainable_blocks=RECIPE.trainable_blocks)
    k = backbone.num_frozen
    frozen, trainable = backbone.features[:k], backbone.features[k:]
    images = ds.train.db_images[np.random.default_rng(0).choice(len(ds.train.db_images), 112, replace=False)]
    x = images_to_tensor(images)

    def median_cpu(fn) -> float:
        fn()                                                     # warm-up
        return float(np.median([_timed(fn)[1] for _ in range(repeats)]))

    @torch.no_grad()
    def frozen_forward():
        return frozen(x)

    maps = frozen_forward()
    t_frozen = median_cpu(frozen_forward)

    def step():
        trainable.zero_grad(set_to_none=True)
        trainable(maps).sum().backward()

    t_train = median_cpu(step)
    info = describe()
    print(f"one batch of 112 images (kernels pinned: {info['pinned']}, oneDNN convolutions: "
          f"{info['onednn_convolutions']}): frozen blocks forward {t_frozen * 1e3:.1f} ms, trainable block "
          f"forward + backward {t_train * 1e3:.1f} ms -> the cache saves at most {1 + t_frozen / t_train:.2f}x "
          f"on the backbone's part of a step")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="GeM only, 1 epoch")
    parser.add_argument("--epochs", type=int, default=None)
    parser.add_argument("--wide", type=int, default=96, help="width of the stand-in backbone of part 3 (0: skip)")
    parser.add_argument("--only-wide", action="store_true", help="run part 3 only")
    parser.add_argument("--parts", action="store_true", help="run part 5 only")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    epochs = args.epochs or (1 if args.quick else 4)
    print(_load(), f"(before); {os.cpu_count()} cores; torch {torch.__version__}, 1 thread")
    ds = make_dataset("city", seed=0, size="tiny")
    print(ds.train, ds.val, sep="\n")
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])     # the first Adam imports torch._dynamo (~3 s): not timed
    ok = True
    if args.parts:
        bench_step_parts(ds)
        return 0
    if not args.only_wide:
        for aggregator in ("gem",) if args.quick else ("gem", "netvlad", "salad"):
            ok &= bench_fine_tune(ds, aggregator, epochs, "UCCU")
        if not args.quick:
            bench_search(ds, 2)
    if args.wide and (args.only_wide or not args.quick):
        course = vpr_nb.pretrain.course_backbone
        vpr_nb.pretrain.course_backbone = _stand_in(args.wide)
        try:
            ok &= bench_fine_tune(ds, "gem", epochs, "UCCU", label=f", random SmallCNN width {args.wide}:")
        finally:
            vpr_nb.pretrain.course_backbone = course
    if not args.only_wide:
        bench_memory(ds)
        bench_step_parts(ds)
    print(_load(), "(after)")
    if not ok:
        print(f"error: the cached and uncached paths differ by more than {TOLERANCE:g}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
