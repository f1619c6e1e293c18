"""A machine's fingerprint: short hashes of what the course computes there, stage by stage, to compare two machines.

Equal hashes on two machines mean that the pinned CPU kernels (:mod:`vpr_nb.kernels`) give the same bits there
for rendering, the course backbone's features, faiss k-means and search, and a few steps of the course recipe's
fine-tuning (:mod:`vpr_nb.recipe`). ``python -m vpr_nb.fingerprint`` prints them with the machine's description;
``tests/test_kernels.py`` compares them with the recorded ones.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys

import numpy as np
import torch

from ._checks import check_int
from .aggregation import kmeans_centroids
from .evaluation import images_to_tensor, retrieve
from .kernels import apply_in_process, describe
from .pretrain import course_backbone
from .recipe import RECIPE, Method, build_start, make_source
from .synthetic import make_dataset
from .training import make_optimizer


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def fingerprint(steps: int = 6) -> dict[str, str]:
    """Short hashes of what the course computes, each stage on its own, so two machines can be compared:
    ``render`` (a tiny city split's pixels, numpy), ``features`` (the course backbone's local features),
    ``kmeans`` (faiss k-means, NetVLAD's initialisation), ``search`` (faiss exact search), and ``netvlad`` /
    ``salad`` (the weights after ``steps`` Adam steps of the course recipe's triplet fine-tuning).

    Equal hashes on two machines mean those numbers are bit for bit the same there (same library versions).
    Uses one torch thread, as the notebooks do; takes a few seconds."""
    steps = check_int(steps, "steps", minimum=1)
    apply_in_process()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        split = make_dataset("city", seed=0, size="tiny", splits=("train",)).train
        out = {"render": _digest(split.db_images, split.q_images)}
        backbone = course_backbone(final_relu=False).eval()
        with torch.no_grad():
            fmap = backbone(images_to_tensor(split.db_images[:64]))
        out["features"] = _digest(fmap.numpy())
        local = fmap.permute(0, 2, 3, 1).reshape(-1, fmap.shape[1]).numpy()
        centroids = kmeans_centroids(local, 8, niter=10, seed=0)
        out["kmeans"] = _digest(np.ascontiguousarray(centroids, dtype=np.float32))
        desc = torch.nn.functional.normalize(fmap.mean((2, 3)), dim=1).numpy()
        dist, idx = retrieve(desc[:48], desc[48:], k=5)
        out["search"] = _digest(np.ascontiguousarray(dist), np.ascontiguousarray(idx))
        recipe = dataclasses.replace(RECIPE, batch_size=4, num_candidates=50, frozen_cache=False)
        for agg in ("netvlad", "salad"):
            method = Method(agg, agg)
            model = build_start(method, split, recipe, seed=0)
            opt = make_optimizer(model, recipe.train_config(1e-3, 0))
            model.train()
            losses = []
            for step, loss in enumerate(make_source(method, split, recipe).steps(model, np.random.default_rng(0))):
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
                if step + 1 == steps:
                    break
            out[agg] = _digest(np.array(losses), *[p.detach().numpy().copy() for p in model.parameters()])
    finally:
        torch.set_num_threads(threads)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.fingerprint", description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=6, help="training steps of the fingerprint (default 6)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.steps < 1:
        print(f"error: --steps must be at least 1, got {args.steps}", file=sys.stderr)
        return 2
    apply_in_process()
    for k, v in describe().items():
        print(f"{k}: {v}")
    for k, v in fingerprint(args.steps).items():
        print(f"fingerprint {k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
