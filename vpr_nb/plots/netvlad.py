"""NetVLAD on one image as a picture: its soft assignment over the image and the residual norm of every cluster.

:func:`plot_netvlad` draws Eqs. (3) and (4) of NetVLAD (notebook 04) from the layer's own tensors for one image; it
calls no random generator, so a notebook's random streams are left as they were.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from ._inputs import as_numbers

CLUSTER_CMAP = "tab20"   # cluster k gets colour k (mod 20), as in the notebook's cluster maps


def plot_netvlad(image, assignment, residuals, axes=None):
    """NetVLAD's soft assignment, Eq. (3), over one image and the norms of its residual sums, Eq. (4).

    ``image``: the image, uint8 (H, W, 3); ``assignment``: the soft assignment a_k(x_i) of its h x w local
    features to the K clusters, (K, h, w), non-negative and summing to 1 over k at every position;
    ``residuals``: the residual sums V_k = sum_i a_k(x_i) (x_i - c_k) of Eq. (4) before any normalisation,
    (K, D); numpy arrays or torch tensors. Panels: the image; its nearest cluster argmax_k a_k at each position,
    upsampled over it (one colour per cluster); the assignment strength max_k a_k (1/K: undecided, 1: hard);
    ``||V_k||`` per cluster, the size of each cluster's part of the descriptor before intra-normalisation.
    Four axes may be given in ``axes``; returns the figure.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be one uint8 image of shape (H, W, 3), got {img.dtype} {img.shape}")
    a = as_numbers(assignment, "assignment", 3)
    if (a < 0).any() or not np.allclose(a.sum(0), 1.0, atol=1e-3):
        raise ValueError("assignment must be a soft assignment, (K, h, w) non-negative and summing to 1 over the K "
                         "clusters at every position (the softmax of Eq. 3); did you pass (h, w, K) or logits?")
    v = as_numbers(residuals, "residuals", 2)
    k = a.shape[0]
    if v.shape[0] != k:
        raise ValueError(f"residuals has {v.shape[0]} rows for the {k} clusters of assignment: "
                         "give one V_k per cluster")
    if axes is None:
        _, axes = plt.subplots(1, 4, figsize=(13, 3.3), gridspec_kw={"width_ratios": [1, 1, 1, 1.15]})
    if len(axes) != 4:
        raise ValueError(f"axes must be four matplotlib axes (image, clusters, strength, residuals), got {len(axes)}")
    h, w = img.shape[:2]
    over = dict(extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest")   # the h x w map over the image
    nearest, strength = a.argmax(0), a.max(0)
    cmap = plt.get_cmap(CLUSTER_CMAP)
    axes[0].imshow(img, interpolation="nearest")
    axes[0].set_title("image")
    axes[1].imshow(img, interpolation="nearest")
    axes[1].imshow(nearest % cmap.N, cmap=cmap, vmin=0, vmax=cmap.N - 1, alpha=0.65, **over)
    axes[1].set_title(f"nearest cluster, {len(np.unique(nearest))} of {k} used")
    axes[2].imshow(img, interpolation="nearest")
    shown = axes[2].imshow(strength, cmap="viridis", vmin=1.0 / k, vmax=1.0, alpha=0.75, **over)
    axes[2].figure.colorbar(shown, ax=axes[2], fraction=0.035, pad=0.02).set_label("max_k a_k", fontsize=8)
    axes[2].set_title(f"strength, mean {strength.mean():.2f}")
    for ax in axes[:3]:
        ax.set(xticks=[], yticks=[], xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5))
    norms = np.linalg.norm(v, axis=1)
    used = np.isin(np.arange(k), nearest)
    colours = [cmap(c % cmap.N) if u else "white" for c, u in enumerate(used)]
    bars = axes[3].bar(np.arange(k), norms, color=colours, edgecolor="k", lw=0.4)
    for bar in np.asarray(bars.patches, dtype=object)[~used]:
        bar.set_hatch("////")
    axes[3].set(xlabel="cluster k (hatched: nearest to no position)", ylabel="‖V_k‖, Eq. (4)",
                title="residual sum per cluster", xticks=np.arange(0, k, max(1, k // 8)))
    fig = axes[0].figure
    fig.tight_layout()
    return fig
