# ---
# jupyter:
#   jupytext:
#     cell_metadata_filter: tags,nbgrader,-all
#     formats: ipynb,py:percent
#     notebook_metadata_filter: kernelspec,jupytext,-all
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 04 · From bag of words to NetVLAD
#
# **Aim.** Build the NetVLAD aggregation layer (Arandjelović et al., CVPR 2016) step by step. Then fine-tune
# it on a pretrained backbone, as the paper does with VGG16. You will
#
# * go from a **bag of visual words** (counts) to **VLAD** (residual sums) to **NetVLAD** (soft, learnable
#   assignment) in torch;
# * normalise as the paper does: each descriptor, each cluster (*intra-normalisation*), the whole vector;
# * initialise with **k-means** clustering (faiss) and pick the softmax sharpness $\alpha$ from the data;
# * check your layer against the library's `NetVLAD`, which loads the public checkpoints;
# * measure whether NetVLAD should read the backbone **before or after its last ReLU** (the activation
#   $\max(0, x)$);
# * fine-tune the **course backbone** with **GeM pooling** (Eq. G) vs NetVLAD on the tiny `city` world, with
#   the same pipeline and budget.

# %% tags=["parameters", "grade-deps:ex-04-soft-share"]
PROFILE = "ci"  # "ci": 1 seed, 1 epoch per model (a smoke test, < 60 s); "reproduce": 5 paired seeds, the full budget

# %% tags=["grade-deps:ex-04-soft-share"]
import vpr_nb.notebook  # first, before numpy and torch start: it pins the CPU kernels (the stored numbers)
import copy
import time

import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F

from vpr_nb import plots, results
from vpr_nb.aggregation import GeM, NetVLAD, kmeans_centroids, sample_local_descriptors
from vpr_nb.losses import LOSSES
from vpr_nb.evaluation import (images_to_tensor,
                               model_recall_row, raw_pixel_descriptors, recall_row)
from vpr_nb.feature_cache import FrozenFeatureCache
from vpr_nb.models import build_model, init_netvlad
from vpr_nb.pretrain import card, course_backbone
from vpr_nb.report import record
from vpr_nb.synthetic import make_dataset
from vpr_nb.trained_weights import load_trained, save_trained
from vpr_nb.verdict import control_gate, family_note, paired_differences, verdicts
from vpr_nb.training import TrainConfig, TripletSource, mean_pairwise_cosine, train

SETUP = vpr_nb.notebook.setup(PROFILE)   # checks PROFILE; one torch thread, everything seeded with 0
EXPERIMENT = {                 # every setting of the reproduce-profile experiment (notebook 05 reuses it)
    "world": {"preset": "city", "seed": 0, "size": "tiny", "eval split": "test"},
    "backbone": {"checkpoint sha256": card()["sha256"], "features": "after the final ReLU"},
    "trainable_blocks": {"GeM": 1, "NetVLAD": 1, "NetVLAD, frozen backbone": 0},
    "netvlad": {"clusters": 16, "vladv2": False, "kmeans": {"per_image": 20, "niter": 50, "images": "train database"}},
    "triplets": {"loss": "triplet", "margin": 0.1, "batch_size": 16, "num_negatives": 5, "num_candidates": 300,
                 "max_heading_diff": 45},
    "optimizer": {"name": "adam", "lr": 1e-3, "weight_decay": 1e-3, "step_size": 5, "gamma": 0.5},
    "epochs": 8,
    "seeds": [0, 1, 2, 3, 4],                   # fine-tuning seeds (the world is the same)
    "ns": [1, 5, 10],
}
RUN = vpr_nb.notebook.budget(PROFILE, ci={**EXPERIMENT, "epochs": 1, "seeds": [0]}, reproduce=EXPERIMENT)
K = EXPERIMENT["netvlad"]["clusters"]       # NetVLAD clusters (64 in the paper, with VGG16's 512 channels)
NS = tuple(EXPERIMENT["ns"])
print(f"profile {PROFILE}: {RUN['epochs']} epoch(s) per model, seeds {RUN['seeds']}, K = {K}")


# %% [markdown]
# ## Theory
#
# A CNN turns an image into $N = h \cdot w$ local descriptors $x_i \in \mathbb{R}^D$. An aggregation layer
# turns this *set* into one global vector. It uses $K$ centroids $c_1, \dots, c_K$, a "visual vocabulary"
# (e.g. from k-means on training descriptors).
#
# **Bag of visual words** counts the descriptors nearest to each centroid:
#
# $$h_k = \sum_i a_k(x_i), \quad a_k(x_i) = \mathbb{1}[k = \arg\min_{k'} \|x_i - c_{k'}\|]. \tag{1}$$
#
# **VLAD** (Jégou et al., CVPR 2010) also keeps *where* the descriptors lie in each cell. It sums their
# residuals to the centroid, giving a $K \times D$ matrix:
#
# $$V_k = \sum_i a_k(x_i)(x_i - c_k). \tag{2}$$
#
# **NetVLAD** makes the assignment soft, so that everything is differentiable:
#
# $$\bar a_k(x_i) = \operatorname{softmax}_k(-\alpha \|x_i - c_k\|^2) = \operatorname{softmax}_k(w_k^\top x_i + b_k),
# \quad w_k = 2\alpha c_k,\ b_k = -\alpha \|c_k\|^2 \tag{3}$$
#
# (the $\|x_i\|^2$ term cancels). NetVLAD then *decouples*
# $\{w_k, b_k\}$ from $\{c_k\}$ and learns all three:
#
# $$V_k = \sum_i \bar a_k(x_i)(x_i - c_k) = \sum_i \bar a_k(x_i) x_i - \big(\sum_i \bar a_k(x_i)\big) c_k . \tag{4}$$
#
# So (3) is a $1\times1$ convolution plus a softmax, and the right side of (4) is one batched matrix
# product.
#
# **Normalisations.** Each $x_i$ is L2-normalised first. Then each row $V_k$ is L2-normalised
# (**intra-normalisation**), so a bursty cluster (a repeated window
# pattern) cannot dominate. Last, the flattened $K \cdot D$ vector is L2-normalised:
#
# $$v = \mathrm{vec}(V_1/\|V_1\|, \dots, V_K/\|V_K\|) / \|\cdot\|. \tag{5}$$
#
# **Initialisation.** The public code (vladv1) sets $b_k = 0$ and $w_k = \alpha\, \hat c_k$ with
# $\hat c_k = c_k/\|c_k\|$. For unit $x_i$ the logits are then $\alpha \cos(x_i, c_k)$. We choose
# $\alpha$ so that, on average, the best cluster gets **100 times** the weight of the second best:
#
# $$\alpha = \frac{\ln 100}{\bar\Delta}, \quad \bar\Delta = \operatorname{mean}_i (\cos_{(1)}(x_i) - \cos_{(2)}(x_i)), \tag{6}$$
#
# with the best and second-best cosines of $x_i$ to the centroids.
# (vladv2 uses Eq. 3 with squared distances instead.)
#
# **The baseline: GeM.** Generalised-mean pooling (Radenović et al., 2018) keeps
# one number per channel, not a residual per cluster. For the $N$ activations $x_{c,i} \ge 0$ of channel $c$:
#
# $$f_c = \big(\tfrac{1}{N} \sum_i x_{c,i}^p\big)^{1/p}, \quad \mathbf{f} = [f_1, \dots, f_D] / \|\cdot\|, \tag{G}$$
#
# The learnable $p$ starts at 3; $p = 1$ is mean pooling, $p \to \infty$ max pooling. It gives $D$ numbers,
# NetVLAD $K \cdot D$. The library's `GeM` clamps activations at $10^{-6}$, so it needs no ReLU.

# %% [markdown]
# ## Build it: BoW, VLAD and NetVLAD in plain torch

# %%
def bow_by_hand(x, c):                           # Eq. (1): x [N, D] descriptors, c [K, D] centroids
    nearest = torch.cdist(x, c).argmin(dim=1)
    return torch.bincount(nearest, minlength=len(c)).float()


def hard_assign(x, c):                           # one-hot a_k(x_i) of Eq. (1), [N, K]
    return F.one_hot(torch.cdist(x, c).argmin(dim=1), len(c)).float()


def soft_assign(x, w, b=None):                   # Eq. (3): softmax over clusters of w_k.x_i + b_k, [N, K]
    return torch.softmax(x @ w.T + (0.0 if b is None else b), dim=1)


def vlad_by_hand(x, c, assign):                  # Eqs. (2)/(4) + (5), for hard or soft assignments
    v = assign.T @ x - assign.sum(dim=0)[:, None] * c      # [K, D]: sum_i a_k(x_i) (x_i - c_k)
    v = F.normalize(v, dim=1)                               # intra-normalisation
    return F.normalize(v.flatten(), dim=0)                  # global L2


def netvlad_by_hand(fmap, w, b, c):              # one image's feature map [D, H, W] -> [K*D]
    x = F.normalize(fmap.flatten(1).T, dim=1)               # N = H*W local descriptors, each L2-normalised
    return vlad_by_hand(x, c, soft_assign(x, w, b))


# %% [markdown]
# ### A toy vocabulary in 2-D
#
# Three centroids and 300 descriptors in the plane. BoW keeps the counts; VLAD keeps the mean offset of each
# cell's descriptors from its centroid. With the vladv2 weights of Eq. (3), soft assignment tends to hard as
# $\alpha$ grows, and NetVLAD to VLAD.

# %%
gen = torch.Generator().manual_seed(0)
toy_c = torch.tensor([[0.0, 0.0], [3.0, 0.0], [1.5, 2.5]])
toy_x = torch.cat([toy_c[k] + torch.tensor(shift) + 0.6 * torch.randn(n, 2, generator=gen)
                   for k, (n, shift) in enumerate([(150, (0.3, 0.2)), (100, (0.0, -0.4)), (50, (-0.5, 0.0))])])
print("BoW histogram h_k        :", bow_by_hand(toy_x, toy_c).tolist())
print("VLAD (hard), rows V_k/|V|:", np.round(vlad_by_hand(toy_x, toy_c, hard_assign(toy_x, toy_c)).view(3, 2).double().numpy(), 3).tolist())
for alpha in (0.3, 3.0, 30.0):
    a = soft_assign(toy_x, 2 * alpha * toy_c, -alpha * (toy_c ** 2).sum(1))       # vladv2 weights, Eq. (3)
    gap = (vlad_by_hand(toy_x, toy_c, a) - vlad_by_hand(toy_x, toy_c, hard_assign(toy_x, toy_c))).norm()
    print(f"alpha = {alpha:5.1f}: mean max assignment {a.max(1).values.mean():.3f}, "
          f"|NetVLAD - VLAD| = {gap:.3f}")

grid = torch.stack(torch.meshgrid(torch.linspace(-2, 5, 120), torch.linspace(-2, 4.5, 110), indexing="xy"), -1)
fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), sharey=True)
for ax, alpha in zip(axes, (0.3, 3.0, 30.0)):
    a = soft_assign(grid.reshape(-1, 2), 2 * alpha * toy_c, -alpha * (toy_c ** 2).sum(1)).reshape(*grid.shape[:2], 3)
    ax.imshow(a.numpy(), origin="lower", extent=(-2, 5, -2, 4.5))       # RGB = soft assignment to the 3 clusters
    ax.scatter(toy_x[:, 0], toy_x[:, 1], s=3, c="k", alpha=0.4)
    ax.scatter(toy_c[:, 0], toy_c[:, 1], s=120, marker="*", c="w", edgecolors="k")
    ax.set_title(f"soft assignment, alpha = {alpha:g}")
fig.suptitle("colour = (a_1, a_2, a_3) as RGB; white stars = centroids", y=1.02)
fig.tight_layout()
plt.show()

# %% [markdown]
# **Figure 1.** Soft assignment (3) of the toy vocabulary at α = 0.3, 3 and 30, as RGB; black dots are
# descriptors, white stars centroids. A large
# α approaches VLAD's hard assignment.

# %% [markdown]
# ## Use `vpr_nb`: the same layer from the library
#
# The library's `NetVLAD` computes Eq. (4) for a whole batch with one batched matrix product (`bmm`). Its
# parameters are named as in the public `pytorch-NetVlad` layer, so its checkpoints load. Same weights, same
# output as above:

# %%
vpr_nb.seed_everything(0)
for vladv2 in (False, True):
    layer = NetVLAD(num_clusters=4, dim=8, vladv2=vladv2)
    fmaps = torch.randn(3, 8, 5, 6)
    bias = layer.conv.bias if vladv2 else None
    ours = torch.stack([netvlad_by_hand(f, layer.conv.weight[:, :, 0, 0], bias, layer.centroids) for f in fmaps])
    with torch.no_grad():
        lib = layer(fmaps)
    assert torch.allclose(ours, lib, atol=1e-6)
    print(f"vladv2={vladv2}: state dict {[(k, tuple(v.shape)) for k, v in layer.state_dict().items()]}; "
          f"by hand = vpr_nb to 1e-6: {bool((ours - lib).abs().max() < 1e-6)}")

# %% [markdown]
# ## The course backbone and its local features
#
# Like NetVLAD (VGG16 pretrained on ImageNet, only its last block conv5 trains), we fine-tune a *pretrained*
# backbone: the **course backbone**. It maps a 32×48 image to an 8×12 map: $N = 96$ local features with
# $D = 128$ channels, pretrained (with GeM and notebook 07's Multi-Similarity loss) on synthetic worlds of
# seeds $\ge 100$, never on the seed-0 world used below. `course_backbone(k)` trains its last $k$ of 4 blocks
# (1 = the final 1×1 projection, like conv5).
#
# That last block ends in a **ReLU**. The public NetVLAD code reads VGG16's conv5_3 **before** its ReLU, so we
# measure both sides. The recipe reads the output, after the ReLU; `before_relu` swaps the ReLU for an
# identity.

# %%
# NBVAL_IGNORE_OUTPUT
# (generation time varies)
t0 = time.perf_counter()
w = EXPERIMENT["world"]
ds = make_dataset(w["preset"], seed=w["seed"], size=w["size"])
train_split, val_split, test_split = ds.train, ds.val, ds.test
print(f"generated in {time.perf_counter() - t0:.1f} s")

# %%
for s in (train_split, val_split, test_split):
    print(s)
cfg = card()["config"]
print(f"course backbone: SmallCNN width {cfg['width']}, {cfg['out_channels']} channels, pretrained on city worlds "
      f"{cfg['city_seeds']} and route worlds {cfg['route_seeds']}")


def before_relu(trainable_blocks):
    # the course backbone read before its final ReLU (as pytorch-NetVlad reads VGG16's conv5_3)
    backbone = course_backbone(trainable_blocks=trainable_blocks)
    assert isinstance(backbone.features[-1], torch.nn.ReLU)
    backbone.features[-1] = torch.nn.Identity()
    return backbone


def course(trainable_blocks):
    # the recipe's reading: the course backbone's output, after its final ReLU (measured below)
    return course_backbone(trainable_blocks=trainable_blocks)


with torch.no_grad():
    x = images_to_tensor(train_split.db_images)
    after, before = course(0)(x), before_relu(0)(x)                # [N, 128, 8, 12] each
zero = (after == 0).all(dim=1)                                      # positions whose every channel is 0
print(f"after the final ReLU : {zero.float().mean():.1%} of the {zero.numel()} local features are exactly zero, "
      f"{(after > 0).float().mean():.2%} of all activations are positive")
print(f"before the final ReLU: {(before == 0).all(dim=1).float().mean():.1%} exactly zero")
for name, fmap in (("after", after), ("before", before)):
    feats = F.normalize(fmap.flatten(2).transpose(1, 2).reshape(-1, fmap.shape[1]), dim=1)
    feats = feats[feats.norm(dim=1) > 0]                            # zero features have no direction
    sample = feats[torch.randperm(len(feats), generator=torch.Generator().manual_seed(0))[:2000]]
    print(f"mean cosine between two local features ({name} the ReLU): {mean_pairwise_cosine(sample.numpy()):.3f}")

# GeM clamps at eps, so the ReLU changes nothing for it (Eq. G): both ways give the same descriptor
gem = GeM(in_channels=128)
assert torch.equal(gem(after), gem(before))
print("GeM(after the ReLU) == GeM(before the ReLU): True")
# the package keeps this swap: course_backbone(final_relu=False)
assert torch.equal(course_backbone(final_relu=False)(x), before)

# %% [markdown]
# ## k-means initialisation and $\alpha$ on the course backbone
#
# As in the NetVLAD code, we sample local features of training images, L2-normalise them, run faiss k-means
# and compute $\alpha$ with Eq. (6). `init_netvlad` packages the same step.

# %%
KM = EXPERIMENT["netvlad"]["kmeans"]


def kmeans_init(model, seed):
    # NetVLAD's cluster step: sample 20 L2-normalised local features per training database image, k-means, alpha
    with torch.no_grad():
        fmaps = model.backbone(images_to_tensor(train_split.db_images))
    descs = sample_local_descriptors(fmaps, per_image=KM["per_image"], seed=seed)
    cents = kmeans_centroids(descs, K, niter=KM["niter"], seed=seed)
    model.aggregator.init_from_clusters(cents, descs)
    return descs, cents


vpr_nb.seed_everything(0)
netvlad_model = build_model(course(1), "netvlad", num_clusters=K)
descs, cents = kmeans_init(netvlad_model, seed=0)
cos = descs @ (cents / np.linalg.norm(cents, axis=1, keepdims=True)).T       # [N, K] cosine similarities
top2 = np.sort(cos, axis=1)[:, -2:]
delta = top2[:, 1] - top2[:, 0]
alpha = -np.log(0.01) / delta.mean()                                           # Eq. (6)
assert np.isclose(alpha, netvlad_model.aggregator.alpha, rtol=1e-4)
ratio = np.exp(alpha * delta)                                                  # best / second-best soft weight
print(f"{len(descs)} descriptors of dimension {descs.shape[1]}, K = {K} centroids")
print(f"mean best - second-best cosine = {delta.mean():.4f} -> alpha = {alpha:.1f} (vpr_nb: {netvlad_model.aggregator.alpha:.1f})")
print(f"best/second-best weight ratio: median {np.median(ratio):.1f}, mean of log = {np.log(ratio).mean():.3f} (= ln 100 = {np.log(100):.3f})")

vpr_nb.seed_everything(0)
pkg_model = build_model(course(1), "netvlad", num_clusters=K)
init_netvlad(pkg_model, train_split.db_images, per_image=KM["per_image"], niter=KM["niter"], seed=0)
assert torch.allclose(pkg_model.aggregator.conv.weight, netvlad_model.aggregator.conv.weight, atol=1e-5)
assert torch.allclose(pkg_model.aggregator.centroids, netvlad_model.aggregator.centroids, atol=1e-5)
print("kmeans_init by hand == vpr_nb.models.init_netvlad: True")

# %%
# the layer just initialised, on one training image: Eq. (3) with soft_assign and Eq. (4) by hand
image = train_split.db_images[0]
nv = netvlad_model.aggregator
with torch.no_grad():
    fmap0 = netvlad_model.backbone(images_to_tensor(image[None]))[0]          # [D, 8, 12]
    x0 = F.normalize(fmap0.flatten(1).T, dim=1)                               # N = 96 local descriptors
    a0 = soft_assign(x0, nv.conv.weight[:, :, 0, 0], nv.conv.bias)           # Eq. (3), [N, K]
    V0 = a0.T @ x0 - a0.sum(dim=0)[:, None] * nv.centroids                   # Eq. (4), [K, D]
    assert torch.allclose(F.normalize(F.normalize(V0, dim=1).flatten(), dim=0), nv(fmap0[None])[0], atol=1e-5)
plots.plot_netvlad(image, a0.T.reshape(K, *fmap0.shape[1:]), V0)
plt.show()

# %% [markdown]
# **Figure 2.** The k-means-initialised NetVLAD on one training image: the image, each position's nearest
# cluster (one colour per cluster), how decided the soft assignment (3) is, and the norm of each residual sum
# $V_k$ (4) before intra-normalisation.

# %% [markdown]
# **Before or after the ReLU, measured.** The same k-means-initialised NetVLAD, nothing trained, reads the
# frozen backbone after and before its last ReLU. The table gives test Recall@N and the mean pairwise cosine of
# test database descriptors (near 1: all images look alike). References: raw
# pixels and the frozen backbone with GeM ($p = 3$), also untrained.

# %%
def untrained_netvlad(relu, seed=0):
    vpr_nb.seed_everything(seed)
    backbone = course(0) if relu else before_relu(0)
    model = build_model(backbone, "netvlad", num_clusters=K)
    init_netvlad(model, train_split.db_images, per_image=KM["per_image"], niter=KM["niter"], seed=seed)
    return model


def test_row(db, q):          # Recall@N, dim and mean cosine on the test split
    return recall_row(db, q, test_split, NS)


def model_row(model):
    return model_recall_row(model, test_split, NS)


vpr_nb.seed_everything(0)
fixed = {"raw pixels": test_row(raw_pixel_descriptors(test_split.db_images), raw_pixel_descriptors(test_split.q_images)),
         "frozen backbone + GeM": model_row(build_model(course(0), "gem")),
         "NetVLAD k-means init, after the ReLU": model_row(untrained_netvlad(relu=True)),
         "NetVLAD k-means init, before the ReLU": model_row(untrained_netvlad(relu=False))}
print(f"untrained, test split ({len(test_split.q_images)} queries)")
print(f"{'':40s}{'dim':>6s}" + "".join(f"{'R@' + str(n):>8s}" for n in NS) + f"{'mean cosine':>13s}")
for name, r in fixed.items():
    print(f"{name:40s}{r['dim']:6d}" + "".join(f"{r[f'R@{n}']:8.3f}" for n in NS) + f"{r['mean cosine']:13.3f}")

# %% [markdown]
# ## Experiment: GeM vs NetVLAD, fine-tuned
#
# Both models read the course backbone after its last ReLU, with its **last block trainable** (like NetVLAD's
# conv5). A third row keeps the backbone **frozen** and trains only the NetVLAD layer. All rows share the
# triplet pipeline of notebook 03 (best positive facing the same way, the 5 hardest of 300 random negatives
# beyond 25 m, margin 0.1). They also share the optimiser (Adam, lr $10^{-3}$, halved every 5 epochs), the
# **number of epochs** and, per seed, the mining randomness. The best model on validation Recall@1 is tested
# once. Descriptors: GeM 128-D, NetVLAD ($K = 16$) 2048-D.
#
# The stored `ci` run: one seed, one epoch. Committed (`reproduce`): 5 seeds, 8 epochs each. Notebooks 03
# and 05 train the NetVLAD row until validation stops improving; 03 also searches the lr.

# %%
TB = EXPERIMENT["trainable_blocks"]
METHODS = tuple(TB)                        # "GeM", "NetVLAD", "NetVLAD, frozen backbone"
CACHES = {}                                # the frozen blocks' maps, per number of trainable blocks


def make_model(name, seed):
    vpr_nb.seed_everything(seed)
    backbone = course(TB[name])
    if name == "GeM":
        return build_model(backbone, "gem")
    model = build_model(backbone, "netvlad", num_clusters=K, vladv2=EXPERIMENT["netvlad"]["vladv2"])
    init_netvlad(model, train_split.db_images, per_image=KM["per_image"], niter=KM["niter"], seed=seed)
    return model


def run(name, seed, epochs):
    model = make_model(name, seed)
    init = copy.deepcopy(model)
    t, o = EXPERIMENT["triplets"], EXPERIMENT["optimizer"]
    source = TripletSource(train_split, LOSSES[t["loss"]](margin=t["margin"]), batch_size=t["batch_size"],
                           num_negatives=t["num_negatives"], num_candidates=t["num_candidates"],
                           max_heading_diff=t["max_heading_diff"])
    cfg = TrainConfig(epochs=epochs, optimizer=o["name"], lr=o["lr"], weight_decay=o["weight_decay"],
                      step_size=o["step_size"], gamma=o["gamma"], seed=seed, ns=NS)
    t0 = time.perf_counter()
    with CACHES.setdefault(TB[name], FrozenFeatureCache()).attached(model.backbone):   # frozen blocks: once
        hist = train(model, source, val_split, cfg, progress=False)
    seconds = time.perf_counter() - t0
    return dict(model=model, init=init, hist=hist, seconds=seconds, row=model_row(model))


t_all = time.perf_counter()
runs = {(m, s): run(m, s, RUN["epochs"]) for s in RUN["seeds"] for m in METHODS}

# %%
# NBVAL_IGNORE_OUTPUT
# (timings vary from machine to machine)
for (m, s), r in runs.items():
    print(f"{m:26s} seed {s}: {r['seconds']:.1f} s for {RUN['epochs']} epoch(s) ({r['seconds'] / RUN['epochs']:.1f} s/epoch)")
print(f"all runs: {time.perf_counter() - t_all:.0f} s")


# %%
def fmt(vals):
    # mean ± std over seeds, or the single value of a one-seed run
    return "{:9.3f} ± {:.3f}".format(*results.mean_std(vals)) if len(vals) > 1 else f"{vals[0]:16.3f}"


def per_seed(rows_of):
    # {method: {metric: [value per seed]}} from {method: [row per seed]}
    return {m: {k: [r[k] for r in rows] for k in rows[0]} for m, rows in rows_of.items()}


live = per_seed({m: [dict(runs[m, s]["row"], **{"best epoch": runs[m, s]["hist"].best_epoch + 1})
                     for s in RUN["seeds"]] for m in METHODS})
print(f"live ({PROFILE} profile): test Recall@N on the city seed-0 world, {RUN['epochs']} epoch(s), "
      f"seed(s) {RUN['seeds']}" + (" (one seed: no spread)" if len(RUN["seeds"]) == 1 else ", mean ± std"))
print(f"{'':40s}{'dim':>6s}" + "".join(f"{'R@' + str(n):>16s}" for n in NS) + f"{'mean cosine':>13s}")
for name, r in fixed.items():
    print(f"{name:40s}{r['dim']:6d}" + "".join(f"{r[f'R@{n}']:16.3f}" for n in NS) + f"{r['mean cosine']:13.3f}")
for m, cols in live.items():
    cells = "".join(fmt(cols[f"R@{n}"]) for n in NS)
    print(f"{m + ', fine-tuned':40s}{cols['dim'][0]:6d}{cells}{np.mean(cols['mean cosine']):13.3f}")

# %%
if PROFILE == "reproduce":
    results.save("04_netvlad", EXPERIMENT, {
        "fixed": fixed,
        "per seed": {m: {**cols, "val R@1 per epoch": [runs[m, s]["hist"].recalls(1) for s in RUN["seeds"]]}
                     for m, cols in live.items()},
        "seconds": round(time.perf_counter() - t_all, 1),
        # the trained NetVLAD of seed 0, for the figure of what it assigns where (vpr_nb.trained_weights)
        "trained weights": {"netvlad-seed0": save_trained("04_netvlad", "netvlad-seed0", runs["NetVLAD", 0]["model"],
                                                           runs["NetVLAD", 0]["init"])}})

committed = results.load("04_netvlad", EXPERIMENT)
st, res = committed["stamp"], committed["results"]
SEEDS = EXPERIMENT["seeds"]
PAPER = "VGG16 + NetVLAD-64, Pittsburgh30k val (as quoted in pytorch-NetVlad's README): R@1 / R@5 / R@10 = 0.841 / 0.946 / 0.955"
print(f"reproduce profile, {len(SEEDS)} seeds (notebooks/results/04_netvlad.json, "
      f"date {st['date']}): test Recall@N, {EXPERIMENT['epochs']} epochs, mean ± std over seeds {SEEDS}")
print(f"{'':40s}{'dim':>6s}" + "".join(f"{'R@' + str(n):>16s}" for n in NS) + f"{'mean cosine':>13s}   best epoch per seed")
for name, r in res["fixed"].items():
    print(f"{name:40s}{r['dim']:6d}" + "".join(f"{r[f'R@{n}']:16.3f}" for n in NS) + f"{r['mean cosine']:13.3f}")
for m, cols in res["per seed"].items():
    cells = "".join(fmt(cols[f"R@{n}"]) for n in NS)
    print(f"{m + ', fine-tuned':40s}{cols['dim'][0]:6d}{cells}{np.mean(cols['mean cosine']):13.3f}"
          f"   {cols['best epoch']}")
print(f"paper: {PAPER}")
print(f"(the committed run took {results.run_minutes(committed):.1f} min, torch on one thread)")


# %% [markdown]
# **Verdicts.** Rows are paired by seed; an untrained reference is repeated for every seed. A difference
# counts only if a paired t test finds it, corrected for the table's five comparisons (Holm). A fine-tuned
# baseline is compared against only if it beats its own start. An untrained reference is itself such a
# control. Two caveats: the paper's line above is VGG16 with 64 clusters on Pittsburgh, another network and
# dataset; and our backbone was pretrained with GeM, a confound of NetVLAD − GeM:

# %%
def r1(name):
    if name in res["per seed"]:
        return res["per seed"][name]["R@1"]
    return [res["fixed"][name]["R@1"]] * len(SEEDS)


PAIRS = [("NetVLAD", "GeM"), ("NetVLAD", "NetVLAD, frozen backbone"), ("GeM", "frozen backbone + GeM"),
         ("NetVLAD", "NetVLAD k-means init, after the ReLU"),
         ("NetVLAD, frozen backbone", "NetVLAD k-means init, after the ReLU")]
START = {"GeM": "frozen backbone + GeM", "NetVLAD": "NetVLAD k-means init, after the ReLU",
         "NetVLAD, frozen backbone": "NetVLAD k-means init, after the ReLU"}   # each fine-tune's starting point


family = verdicts({f"{a} − {b}": paired_differences(r1(a), r1(b)) for a, b in PAIRS},
                  gates={f"{a} − {b}": control_gate(r1(b), r1(START[b]), b, START[b])
                         for a, b in PAIRS if b in START})   # a fine-tuned baseline must beat its own start
verdict_text = {f"{a} vs {b}": f"{a} − {b}: {family[f'{a} − {b}'].text()}" for a, b in PAIRS}
for v in verdict_text.values():
    print("R@1:", v)
print(family_note(family))

fig, axes = plt.subplots(1, 2, figsize=(13, 3.6))
curves = {name: {n: r[f"R@{n}"] for n in NS} for name, r in res["fixed"].items() if "after" not in name}
curves.update({m + ", fine-tuned": {n: float(np.mean(c[f"R@{n}"])) for n in NS} for m, c in res["per seed"].items()})
plots.plot_recalls(curves, ax=axes[0], title=f"test Recall@N, reproduce profile (mean of {len(SEEDS)} seeds)")
colour = {line.get_label(): line.get_color() for line in axes[0].get_lines()}     # the same colour in both panels
for m, c in res["per seed"].items():
    v = np.array(c["val R@1 per epoch"])
    axes[1].errorbar(np.arange(1, v.shape[1] + 1), v.mean(0), yerr=v.std(0, ddof=1), marker="o", capsize=3, label=m,
                     color=colour[m + ", fine-tuned"])
axes[1].set(xlabel="epoch", ylabel="val Recall@1", title=f"validation Recall@1 per epoch (mean ± std, {len(SEEDS)} seeds)")
axes[1].legend()
fig.tight_layout()
plt.show()


# %% [markdown]
# **Figure 3.** Reproduce profile. Left: test Recall@N of every row (fine-tuned rows: mean over seeds).
# Right: validation Recall@1 per epoch of the fine-tuned rows (mean ± std over seeds).

# %% [markdown]
# ## What NetVLAD assigns where
#
# For three test queries we show each position's hard cluster before and after training, and its largest
# assignment weight. Positions that look alike (sky, road, a facade type) share a cluster; training reshapes
# the clusters for retrieval. The trained model is the committed reproduce-profile NetVLAD of seed 0, not the
# `ci` run.

# %%
def assignments(model, images):
    with torch.no_grad():
        x = F.normalize(model.backbone(images_to_tensor(images)), dim=1)
        return torch.softmax(model.aggregator.conv(x), dim=1)          # [B, K, h, w], Eq. (3)


start = runs["NetVLAD", 0]["init"]                                 # seed 0 at its k-means initialisation (both profiles)
trained = load_trained(committed, "netvlad-seed0", copy.deepcopy(start))   # the committed reproduce run, seed 0
show = test_split.q_images[[0, 40, 80]]
a_init, a_trained = assignments(start.eval(), show), assignments(trained.eval(), show)
fig, axes = plt.subplots(3, 4, figsize=(11, 5.4))
for row in range(3):
    panels = [(show[row], "query", {}),
              (a_init[row].argmax(0), "clusters at k-means init", dict(cmap="tab20", vmin=0, vmax=19)),
              (a_trained[row].argmax(0), "clusters after training", dict(cmap="tab20", vmin=0, vmax=19)),
              (a_trained[row].amax(0), "max assignment after training", dict(cmap="viridis", vmin=0, vmax=1))]
    for ax, (img, title, kw) in zip(axes[row], panels):
        ax.imshow(img, interpolation="nearest", **kw)
        ax.set(xticks=[], yticks=[], title=title if row == 0 else "")
fig.tight_layout()
plt.show()
print(f"mean max assignment on these images: k-means init {a_init.amax(1).mean():.3f}, "
      f"trained {a_trained.amax(1).mean():.3f}; clusters used: init {a_init.argmax(1).unique().numel()}, "
      f"trained {a_trained.argmax(1).unique().numel()} of {K}")

# %% [markdown]
# **Figure 4.** Three test queries (left); each position's cluster at the k-means initialisation and after
# training (middle, one colour per cluster); the largest assignment weight after training (right).

# %%
record("04_netvlad", {
    "profile": PROFILE, "epochs": RUN["epochs"], "seeds": list(RUN["seeds"]), "NetVLAD clusters": K,
    "alpha (k-means init, seed 0)": round(float(alpha), 2),
    **{f"{name} test R@1": r["R@1"] for name, r in fixed.items()},
    **{f"{m} test R@{n} (live)": round(float(np.mean(c[f"R@{n}"])), 3) for m, c in live.items() for n in NS},
    **{f"{m} test R@1 (committed, {len(SEEDS)} seeds)": "{:.3f} ± {:.3f}".format(*results.mean_std(c["R@1"]))
       for m, c in res["per seed"].items()},
    **verdict_text,
})


# %% [markdown]
# ## Graded exercise: which descriptors does $\alpha$ leave soft?
#
# With `vladv2=False` the layer gives a local descriptor $x_i$ the soft weight $\propto e^{\alpha \cos(x_i, c_k)}$
# for cluster $k$ (Eq. 3 with the init above). Eq. (6) makes the best/second-best weight ratio 100 only *on
# average* (of its log). Write `weak_assignment_share(descs, cents, alpha, ratio=100.0)` in numpy (no
# `vpr_nb`). It returns (a Python float) the fraction of the L2-normalised descriptors `descs` $[N, D]$
# whose best weight is *less* than `ratio` times their second-best weight. The centroids `cents` $[K, D]$ are
# *not* normalised. Grading runs only the notebook's import cells and your solution cell.

# %% nbgrader={"grade": false, "grade_id": "ex-04-soft-share", "locked": false, "schema_version": 3, "solution": true}
def weak_assignment_share(descs, cents, alpha, ratio=100.0):
    ### BEGIN SOLUTION
    unit = cents / np.linalg.norm(cents, axis=1)[:, None]
    logits = alpha * np.einsum("nd,kd->nk", descs, unit)                  # log of the unnormalised weights
    best_two = -np.partition(-logits, 1, axis=1)[:, :2]
    return float(np.mean(best_two[:, 0] - best_two[:, 1] < np.log(ratio)))
    ### END SOLUTION


# %% nbgrader={"grade": true, "grade_id": "ex-04-soft-share-tests", "locked": true, "points": 1, "schema_version": 3, "solution": false}
import numpy as np

from vpr_nb.assignments import Case, check

toy_d, toy_k = np.array([[1.0, 0.0], [0.6, 0.8]]), np.array([[2.0, 0.0], [0.0, 3.0]])   # cosine gaps 1.0 and 0.2
check("weak_assignment_share", [Case("alpha = 10: weight ratios e^10 (>= 100) and e^2 (< 100), so a share of 0.5",
                                     (toy_d, toy_k, 10.0), expect=0.5, atol=1e-12)])
### BEGIN HIDDEN TESTS
import torch

rng = np.random.default_rng(1)
d_h = rng.standard_normal((400, 4))
d_h /= np.linalg.norm(d_h, axis=1, keepdims=True)
c_h = 3.0 * rng.standard_normal((5, 4))
w_h = torch.softmax(torch.as_tensor(d_h @ (c_h / np.linalg.norm(c_h, axis=1, keepdims=True)).T) * 25.0, dim=1).numpy()
top_h = np.sort(w_h, axis=1)[:, -2:]
check("weak_assignment_share", [
    Case(f"400 random descriptors, 5 centroids, alpha 25, ratio {r:g}", (d_h, c_h, 25.0, r),
         expect=float(np.mean(top_h[:, 1] < r * top_h[:, 0])), atol=1e-9) for r in (100.0, 10.0)] + [
    Case("alpha = 0 makes every assignment uniform, so a share of 1.0", (d_h, c_h, 0.0), expect=1.0, atol=1e-12)])
### END HIDDEN TESTS

# %% [markdown]
# ## Graded exercise: predict, then compute the descriptor of a switched-off image
#
# A ReLU can switch a local feature off: zero in every channel. The course backbone has none, other backbones
# can have many. Take an image whose $N$ local features are **all**
# zero, and this notebook's layer (`vladv2=False`). Recall its steps: each feature is L2-normalised (zero stays
# zero) and soft-assigned by a softmax of $\alpha \cos(x_i, c_k)$; then each residual sum and the whole vector
# are L2-normalised.
#
# **Predict first:** its NetVLAD descriptor is (a) `"zero"`, (b) `"depends on N"` (the number of local
# features), or (c) `"fixed by the centroids"` (the same for every such image). Replace the `raise` below by
# `ZERO_IMAGE = "..."` with one of those three strings.

# %% tags=["grade-deps:ex-04-zero-predict", "grade-deps:ex-04-zero-descriptor"]
import numpy as np  # what the two exercises below need: grading runs this cell, then your solution cell

# %% nbgrader={"grade": false, "grade_id": "ex-04-zero-predict", "locked": false, "schema_version": 3, "solution": true}
### BEGIN SOLUTION
ZERO_IMAGE = "fixed by the centroids"
### END SOLUTION

# %% nbgrader={"grade": true, "grade_id": "ex-04-zero-predict-tests", "locked": true, "points": 1, "schema_version": 3, "solution": false}
from vpr_nb.assignments import Case, check, one_of

check("ZERO_IMAGE", [Case("your prediction", rubric=one_of("zero", "depends on N", "fixed by the centroids"))], call=False)
### BEGIN HIDDEN TESTS
check("ZERO_IMAGE", [Case("the NetVLAD descriptor of an image whose local features are all zero",
                          expect="fixed by the centroids")], call=False)
### END HIDDEN TESTS

# %% [markdown]
# **Then compute it.** Write `zero_image_descriptor(cents)` in numpy (no `vpr_nb`) for centroids `cents`
# $[K, D]$ (not normalised). Return the final NetVLAD descriptor of such an image, a numpy array $[K \cdot D]$
# ordered cluster by cluster (entries $kD, \dots, kD + D - 1$ for cluster $k$). What does it say about the mean
# pairwise cosine of untrained descriptors when many features are switched off?

# %% nbgrader={"grade": false, "grade_id": "ex-04-zero-descriptor", "locked": false, "schema_version": 3, "solution": true}
def zero_image_descriptor(cents):
    ### BEGIN SOLUTION
    k = cents.shape[0]
    blocks = -cents / np.linalg.norm(cents, axis=1)[:, None]     # each residual sum is -N c_k / K
    return blocks.reshape(-1) / np.sqrt(k)
    ### END SOLUTION


# %% nbgrader={"grade": true, "grade_id": "ex-04-zero-descriptor-tests", "locked": true, "points": 1, "schema_version": 3, "solution": false}
import numpy as np

from vpr_nb.assignments import Case, check

check("zero_image_descriptor", [Case("two centroids (3, 4) and (0, -2)", (np.array([[3.0, 4.0], [0.0, -2.0]]),),
                                     expect=np.array([-0.6, -0.8, 0.0, 1.0]) / np.sqrt(2), atol=1e-6)])
### BEGIN HIDDEN TESTS
import torch
import torch.nn.functional as F


def reference(cents, n=7):          # the layer itself, on an all-zero feature map of n positions
    c = torch.as_tensor(cents, dtype=torch.float64)
    x = F.normalize(torch.zeros(n, c.shape[1], dtype=torch.float64), dim=1)
    a = torch.softmax(30.0 * x @ F.normalize(c, dim=1).T, dim=1)            # [n, K]
    v = a.T @ x - a.sum(0)[:, None] * c                                       # residual sums [K, D]
    return F.normalize(F.normalize(v, dim=1).reshape(-1), dim=0).numpy()


rng = np.random.default_rng(4)
check("zero_image_descriptor", [Case(f"{k} random centroids of dimension {d}", (c,), expect=reference(c), atol=1e-6)
                                for k, d, c in ((k, d, rng.normal(0.0, 2.0, (k, d))) for k, d in ((4, 3), (16, 8)))])
### END HIDDEN TESTS

# %% [markdown]
# ## Exercises
#
# 1. **Hard vs soft** (no training). Use `hard_assign` instead of `soft_assign` in `netvlad_by_hand`. Is the
#    result still differentiable with respect to the centroids? And to the $1\times1$ conv weights?
#    <details><summary>Hint</summary>Call <code>.backward()</code> on the output's sum. An argmax has no
#    gradient; a residual does.</details>
# 2. **No intra-normalisation** (about 2 min: one 8-epoch run). Drop the intra-normalisation of `vlad_by_hand`
#    in a `NetVLAD` subclass and retrain. Which clusters dominate now?
#    <details><summary>Hint</summary>Print each block's norm for a few test images.</details>
# 3. **The 100:1 rule** (no training). Initialise with $\alpha$ ten times smaller and ten times larger than
#    Eq. (6). How do the untrained test recall and the mean max assignment change?
#    <details><summary>Hint</summary>Scale the conv weights after <code>init_netvlad</code>.</details>
# 4. **Before the ReLU** (about 2 min: one 8-epoch run). Train NetVLAD on `before_relu(1)` with `run`'s
#    recipe. Does training close the gap of the untrained table?
#    <details><summary>Hint</summary>Compare its test R@1 with the two k-means-init rows.</details>
# 5. **vladv2** (about 2 min: one 8-epoch run). Train with `vladv2=True` and `normalize_input=False`; Eq. (3)
#    now holds exactly. Does it train better here?
#    <details><summary>Hint</summary>The conv now has a bias, $-\alpha \|c_k\|^2$.</details>
# 6. **Budget** (no training). NetVLAD's descriptor is 16× larger than GeM's. Reduce it to 128-D with PCA and
#    compare recall at equal size.
#    <details><summary>Hint</summary>Fit the PCA on <em>training</em> database descriptors only, then
#    L2-normalise.</details>
#
# ## Takeaways
#
# * BoW counts, VLAD sums residuals, NetVLAD soft-assigns with learnable weights (Eqs. 3–4) and normalises
#   three times.
# * Initialised by k-means and Eq. (6), the untrained layer retrieves about as well as the frozen backbone
#   with GeM (R@1 0.758 vs 0.748).
# * The public code reads VGG16 before its ReLU. The course backbone, pretrained with a local contrastive term
#   *before* the ReLU, gives NetVLAD a better start *after* it (0.758 vs 0.648), so the recipe reads its output.
# * Fine-tuned with the same recipe and seeds, NetVLAD leads GeM by +0.031 ± 0.015 R@1 over 5 paired seeds:
#   **no measurable effect** after Holm's correction, with our GeM-pretrained backbone as a confound. The
#   control passes: GeM gains +0.043 ± 0.009 over its frozen start. Training the backbone's last block adds
#   +0.048 ± 0.009 over the layer alone, which still beats its k-means start (+0.017 ± 0.003).
# * Compare methods with the committed table, not the live `ci` run.

# %% [markdown]
# ## Self-check
#
# 1. What do BoW, VLAD and NetVLAD each keep of the descriptors assigned to a cluster?
#    <details><summary>Answer</summary>Their count; the sum of their residuals; that sum with soft, learnable
#    weights (Eqs. 3–4).</details>
# 2. What does Eq. (6) choose α for? Does it make every descriptor's assignment sharp?
#    <details><summary>Answer</summary>A best/second-best weight ratio of 100 on average. No: descriptors
#    almost equidistant from two centroids stay soft.</details>
# 3. The public NetVLAD code reads VGG16 before its last ReLU. Why does the course read its backbone after it?
#    <details><summary>Answer</summary>It measured better here (untrained R@1 0.758 vs 0.648). Which side
#    wins depends on the backbone.</details>

# %% [markdown]
# ## References
#
# * R. Arandjelović, P. Gronát, A. Torii, T. Pajdla, J. Sivic. *NetVLAD: CNN architecture for weakly supervised
#   place recognition.* CVPR 2016. <https://arxiv.org/abs/1511.07247>
# * H. Jégou, M. Douze, C. Schmid, P. Pérez. *Aggregating local descriptors into a compact image
#   representation.* CVPR 2010. <https://doi.org/10.1109/CVPR.2010.5540039>
# * R. Arandjelović, A. Zisserman. *All about VLAD.* CVPR 2013. <https://doi.org/10.1109/CVPR.2013.207>
# * J. Sivic, A. Zisserman. *Video Google: a text retrieval approach to object matching in videos.* ICCV 2003.
#   <https://doi.org/10.1109/ICCV.2003.1238663>
# * F. Radenović, G. Tolias, O. Chum. *Fine-tuning CNN image retrieval with no human annotation.* TPAMI 2018.
#   <https://arxiv.org/abs/1711.02512>
# * K. Simonyan, A. Zisserman. *Very deep convolutional networks for large-scale image recognition.*
#   ICLR 2015. <https://arxiv.org/abs/1409.1556>
# * J. Johnson, M. Douze, H. Jégou. *Billion-scale similarity search with GPUs.* arXiv 2017.
#   <https://arxiv.org/abs/1702.08734>
