"""Figures of the world and of retrieval: the world map, image grids, retrieval grids, recall curves.

Every function draws on matplotlib axes and returns the figure (or axes), so a notebook can add a
title or save it; nothing here calls ``plt.show()``.
"""
from __future__ import annotations

from typing import Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle

from ..synthetic import SPLITS

SPLIT_COLOURS = {0: "tab:blue", 1: "tab:orange", 2: "tab:green"}
CORRECT, WRONG = "#1a9850", "#d73027"


def _check_images(images, name: str) -> np.ndarray:
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3 or arr.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8 images of shape (N, H, W, 3), got {arr.dtype} {arr.shape}")
    return arr


def plot_map(dataset, ax=None, show_scene: bool = True, title: str | None = None):
    """Database (dots) and query (crosses) positions coloured by split, over the scene's walls."""
    if ax is None:
        _, ax = plt.subplots(figsize=(10, 4))
    scene = dataset.extra.get("scene") if show_scene else None
    if scene is not None:
        segs = np.stack([scene.a, scene.b], 1)
        walls = scene.kind == 0
        lines = ax.plot(segs[walls][:, :, 0].T, segs[walls][:, :, 1].T, color="0.75", lw=0.8, zorder=0)
        if lines:
            lines[0].set_label("walls")
        trees = scene.kind == 1
        mid = segs[trees].mean(1)
        # dark grey, never a split colour (SPLIT_COLOURS): trees must not read as test images
        ax.scatter(mid[:, 0], mid[:, 1], s=2, color="0.35", zorder=0, label="trees" if len(mid) else None)
    for k, name in enumerate(SPLITS):
        m = dataset.db_split == k
        if m.any():
            ax.scatter(*dataset.db_utm[m].T, s=4, color=SPLIT_COLOURS[k], label=f"{name} database")
        m = dataset.q_split == k
        if m.any():
            ax.scatter(*dataset.q_utm[m].T, s=14, marker="x", lw=0.8, color=SPLIT_COLOURS[k], alpha=0.7,
                       label=f"{name} queries")
    ax.set_aspect("equal")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.18), frameon=False)
    ax.set_title(title or f"{dataset.name}: {len(dataset.db_images)} database images, {len(dataset.q_images)} queries")
    return ax.figure


def image_grid(images, titles: Sequence[str] | None = None, ncols: int = 8, scale: float = 1.6,
               frame_colours: Sequence[str | None] | None = None):
    """Show images in a grid, optionally with titles and coloured frames."""
    arr = _check_images(images, "images")
    n = len(arr)
    if n == 0:
        raise ValueError("images is empty: nothing to show")
    if titles is not None and len(titles) != n:
        raise ValueError(f"got {len(titles)} titles for {n} images")
    ncols = max(1, min(ncols, n))
    nrows = int(np.ceil(n / ncols))
    h, w = arr.shape[1:3]
    fig, axes = plt.subplots(nrows, ncols, figsize=(ncols * scale * w / h, nrows * scale * 1.15), squeeze=False)
    for i, ax in enumerate(axes.flat):
        ax.axis("off")
        if i >= n:
            continue
        ax.imshow(arr[i], interpolation="nearest")
        if titles is not None:
            ax.set_title(titles[i], fontsize=7)
        if frame_colours is not None and frame_colours[i]:
            ax.add_patch(Rectangle((-0.5, -0.5), w, h, fill=False, lw=3, edgecolor=frame_colours[i]))
    fig.tight_layout()
    return fig


def condition_grid(dataset, per_condition: int = 6, seed: int = 0):
    """One row per condition: random query images of that condition (row 0: the database condition)."""
    rng = np.random.default_rng(seed)
    images, titles = [], []
    for c, name in enumerate(dataset.condition_names):
        pool = np.flatnonzero(dataset.db_condition == c) if c == 0 else np.flatnonzero(dataset.q_condition == c)
        src = dataset.db_images if c == 0 else dataset.q_images
        if len(pool) == 0:
            continue
        pick = rng.choice(pool, min(per_condition, len(pool)), replace=False)
        images += [src[i] for i in pick] + [np.zeros_like(src[0])] * (per_condition - len(pick))
        titles += [name + (" (db)" if c == 0 else "")] + [""] * (per_condition - 1)
    return image_grid(np.stack(images), titles=titles, ncols=per_condition)


def retrieval_grid(q_images, db_images, predictions, positives, query_ids: Sequence[int], k: int = 5,
                   distances_m=None):
    """Each row: a query, then its top-k retrievals framed green (a positive) or red (wrong).

    ``distances_m`` (optional, num_queries x k) labels each retrieval with its true distance in metres.
    """
    q_arr, db_arr = _check_images(q_images, "q_images"), _check_images(db_images, "db_images")
    pred = np.asarray(predictions)
    if pred.ndim != 2 or pred.shape[1] < k:
        raise ValueError(f"predictions must be (num_queries, >= {k}), got shape {pred.shape}")
    if len(positives) != len(pred):
        raise ValueError("positives and predictions must describe the same queries")
    images, titles, frames = [], [], []
    for qi in query_ids:
        if not 0 <= qi < len(pred):
            raise ValueError(f"query id {qi} is out of range [0, {len(pred)})")
        images.append(q_arr[qi])
        titles.append(f"query {qi}")
        frames.append("0.2")
        pos = set(np.asarray(positives[qi]).tolist())
        for r in range(k):
            j = int(pred[qi, r])
            images.append(db_arr[j])
            label = f"top-{r + 1}"
            if distances_m is not None:
                label += f" {float(distances_m[qi][r]):.0f} m"
            titles.append(label)
            frames.append(CORRECT if j in pos else WRONG)
    return image_grid(np.stack(images), titles=titles, ncols=k + 1, frame_colours=frames)


def plot_recalls(results: dict[str, dict[int, float]], ax=None, title: str = "Recall@N"):
    """Recall@N curves, one line per method: ``{"method": {1: r1, 5: r5, ...}}``."""
    if not results:
        raise ValueError("results is empty: give {method: {N: recall}}")
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 3.5))
    for name, rec in results.items():
        ns = sorted(rec)
        ax.plot(ns, [rec[n] for n in ns], marker="o", label=name)
    ax.set_xscale("log")
    ax.set_xticks(sorted({n for r in results.values() for n in r}))
    ax.set_xticklabels([str(n) for n in sorted({n for r in results.values() for n in r})])
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("N")
    ax.set_ylabel("Recall@N")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return ax.figure
