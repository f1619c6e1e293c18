"""Builder of notebooks/04_netvlad.ipynb.

Run ``python notebooks/build/04_netvlad.py`` to (re)write the notebook from the cell sources below,
then execute it in place with nbconvert (see the Makefile).
"""
from _nb import write

NAME = "04_netvlad"

CELLS = [
    ("md", r"""
# 04 · From bag of words to NetVLAD

**Aim.** Build the NetVLAD aggregation layer (Arandjelović et al., CVPR 2016) one step at a time and
train it. You will

* go from a **bag of visual words** (a histogram of nearest centroids) to **VLAD** (sums of residuals
  to the centroids) to **NetVLAD** (soft assignment, learnable), in a few lines of torch;
* normalise the way the paper does: each local descriptor, each cluster's residual sum
  (*intra-normalisation*), then the whole vector;
* initialise the layer with **k-means** (faiss) and choose the softmax sharpness $\alpha$ from the data;
* check that the layer derived here equals `vpr_nb.aggregation.NetVLAD` (whose parameter names load
  the public `pytorch-NetVlad` checkpoints);
* look at the soft assignments over an image, and train **GeM pooling vs NetVLAD** with the same
  triplet pipeline and budget on the tiny `city` world.
"""),
    ("code", r"""
PROFILE = "ci"  # "ci": 4 epochs per model, one seed (a small budget: the notebook runs in < 60 s); "reproduce": 14 epochs, 3 seeds
""", ["parameters"]),
    ("code", r"""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # single-threaded numpy BLAS: much faster for the many
                                                     # small products of the triplet mining on a busy 2-core CPU
import copy
import time

import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F

import vpr_nb
from vpr_nb import plots
from vpr_nb.aggregation import NetVLAD, kmeans_centroids, sample_local_descriptors
from vpr_nb.evaluation import evaluate_model, images_to_tensor
from vpr_nb.models import build_model, init_netvlad
from vpr_nb.report import record
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import TrainConfig, TripletSource, train

if PROFILE not in ("ci", "reproduce"):
    raise ValueError(f"PROFILE must be 'ci' or 'reproduce', got {PROFILE!r}")
EPOCHS = {"ci": 4, "reproduce": 14}[PROFILE]           # training epochs, the same for every aggregator
SEEDS = {"ci": (0,), "reproduce": (0, 1, 2)}[PROFILE]   # training seeds (the world is always seed 0)
K = 16                                                  # NetVLAD clusters (64 in the paper, with VGG16)
NS = (1, 5, 10)
torch.set_num_threads(1)   # one thread: fastest on a shared 2-core CPU, and results independent of the core count
vpr_nb.seed_everything(0)
print(f"profile {PROFILE}: {EPOCHS} epochs per model, seeds {SEEDS}, K = {K}")
"""),
    ("md", r"""
## Theory

A CNN turns an image into $N = h \cdot w$ local descriptors $x_i \in \mathbb{R}^D$. An aggregation layer
turns this *set* into one global vector. Given $K$ centroids $c_1, \dots, c_K$ (a "visual vocabulary",
e.g. from k-means on local descriptors of training images):

**Bag of visual words** counts how many descriptors fall nearest to each centroid:

$$h_k = \sum_{i=1}^{N} a_k(x_i), \qquad a_k(x_i) = \mathbb{1}\big[k = \arg\min_{k'} \lVert x_i - c_{k'} \rVert\big]. \tag{1}$$

**VLAD** (Jégou et al., CVPR 2010) keeps *where* in each cell the descriptors lie, by summing their
residuals to the centroid: a $K \times D$ matrix

$$V_k = \sum_{i=1}^{N} a_k(x_i)\,(x_i - c_k) \in \mathbb{R}^D. \tag{2}$$

**NetVLAD** replaces the hard assignment by a soft one, differentiable in everything:

$$\bar a_k(x_i) = \frac{e^{-\alpha \lVert x_i - c_k \rVert^2}}{\sum_{k'} e^{-\alpha \lVert x_i - c_{k'} \rVert^2}}
= \frac{e^{w_k^\top x_i + b_k}}{\sum_{k'} e^{w_{k'}^\top x_i + b_{k'}}},
\qquad w_k = 2\alpha c_k,\; b_k = -\alpha \lVert c_k \rVert^2 \tag{3}$$

(the $-\alpha\lVert x_i\rVert^2$ term is the same for every $k$ and cancels). NetVLAD then *decouples*
$\{w_k, b_k\}$ from $\{c_k\}$ and learns all three:

$$V_k = \sum_{i=1}^{N} \bar a_k(x_i)\,(x_i - c_k) = \Big(\sum_i \bar a_k(x_i)\, x_i\Big) - \Big(\sum_i \bar a_k(x_i)\Big) c_k . \tag{4}$$

The soft assignment (3) is a $1\times1$ convolution followed by a softmax over clusters; the right-hand
form of (4) is one batched matrix product, no loop over clusters.

**Normalisations.** Each $x_i$ is L2-normalised first; each row $V_k$ is L2-normalised
(**intra-normalisation**, Arandjelović & Zisserman, CVPR 2013: one bursty cluster, say a repeated
window pattern, cannot dominate); the flattened $K \cdot D$ vector is L2-normalised again:

$$v = \frac{\mathrm{vec}\big(V_1/\lVert V_1\rVert, \dots, V_K/\lVert V_K\rVert\big)}{\lVert \cdot \rVert}. \tag{5}$$

**Initialisation.** The widely used code (vladv1) sets $b_k = 0$ and $w_k = \alpha\, \hat c_k$ with
$\hat c_k = c_k/\lVert c_k\rVert$: for unit $x_i$, the logits are $\alpha \cos(x_i, c_k)$. $\alpha$ is
chosen so that, on average over sampled descriptors, the best cluster gets **100 times** the weight of
the second best, $e^{\alpha \bar\Delta} = 100$:

$$\alpha = \frac{-\ln 0.01}{\bar\Delta}, \qquad \bar\Delta = \operatorname{mean}_i \big(\cos_{(1)}(x_i) - \cos_{(2)}(x_i)\big), \tag{6}$$

with $\cos_{(1)}, \cos_{(2)}$ the best and second-best cosine similarity of $x_i$ to the centroids
(vladv2 uses Eq. 3 with squared distances instead).
"""),
    ("md", r"""
## Build it: BoW, VLAD and NetVLAD in plain torch
"""),
    ("code", r"""
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
"""),
    ("md", r"""
### A toy vocabulary in 2-D

Three centroids and 300 descriptors in the plane. BoW keeps only the counts; VLAD keeps the mean
offset of each cell's descriptors from its centroid. With the vladv2 weights of Eq. (3), the soft
assignment tends to the hard one as $\alpha$ grows, and so does NetVLAD to VLAD.
"""),
    ("code", r"""
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
"""),
    ("md", r"""
## Use `vpr_nb`: the same layer from the library

`vpr_nb.aggregation.NetVLAD` computes Eq. (4) for a whole batch with one `bmm` (no loop over
clusters). Its parameters are named as in the public `pytorch-NetVlad` layer (`conv.weight`,
`conv.bias` for vladv2, `centroids`), so those checkpoints load with `load_state_dict`. Same weights,
same output as the derivation above:
"""),
    ("code", r"""
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
"""),
    ("md", r"""
## k-means initialisation and $\alpha$ on the synthetic city

The backbone is the course's `SmallCNN` (32×48 images → an 8×12 map of $N = 96$ descriptors with
$D = 128$ channels). As in the NetVLAD code, we sample local descriptors of training images (here from
the randomly initialised CNN: nothing is pretrained in this course), L2-normalise them, run faiss
k-means and compute $\alpha$ with Eq. (6). `init_from_clusters` does the same; we check it.
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (generation time varies)
t0 = time.perf_counter()
ds = make_dataset("city", seed=0)
train_split, val_split, test_split = ds.train, ds.val, ds.test
print(f"generated in {time.perf_counter() - t0:.1f} s")
"""),
    ("code", r"""
for s in (train_split, val_split, test_split):
    print(s)


def kmeans_init(model, seed):
    # NetVLAD's cluster step: sample 20 L2-normalised descriptors per training database image, k-means, alpha
    with torch.no_grad():
        fmaps = model.backbone(images_to_tensor(train_split.db_images))
    descs = sample_local_descriptors(fmaps, per_image=20, seed=seed)
    cents = kmeans_centroids(descs, K, niter=50, seed=seed)
    model.aggregator.init_from_clusters(cents, descs)
    return descs, cents


vpr_nb.seed_everything(0)
netvlad_model = build_model("small_cnn", "netvlad", num_clusters=K)
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

# the package keeps this cluster step as vpr_nb.models.init_netvlad (notebook 05 and `python -m vpr_nb.train` use it)
vpr_nb.seed_everything(0)
pkg_model = build_model("small_cnn", "netvlad", num_clusters=K)
init_netvlad(pkg_model, train_split.db_images, per_image=20, niter=50, seed=0)
assert torch.allclose(pkg_model.aggregator.conv.weight, netvlad_model.aggregator.conv.weight, atol=1e-5)
assert torch.allclose(pkg_model.aggregator.centroids, netvlad_model.aggregator.centroids, atol=1e-5)
print("kmeans_init by hand == vpr_nb.models.init_netvlad: True")
"""),
    ("md", r"""
## Experiment: GeM pooling vs NetVLAD

Both models use the same backbone, the same weakly supervised triplet pipeline (notebook 03: each
training query, its best potential positive facing the same way, hard negatives beyond 25 m, margin
0.1), the same optimiser (Adam, lr $10^{-3}$, StepLR) and the **same number of epochs**. The model with
the best validation Recall@1 is kept and evaluated once on the test split. (In a short tuning run on the
validation split, SGD with lr 0.05, the GeM recipe of notebook 03, trained NetVLAD much worse than Adam
with lr $10^{-3}$, while GeM trained about equally well with both; so both use Adam here.) GeM gives a
128-D descriptor, NetVLAD with $K = 16$ a $16 \cdot 128 = 2048$-D one.

The CI profile trains only a few epochs (the notebook must run in under a minute on two cores), so
its numbers are far from converged: run `PROFILE = "reproduce"` for 14 epochs and 3 seeds.
"""),
    ("code", r"""
OPTIM = dict(optimizer="adam", lr=1e-3)     # the same optimiser and budget for both aggregators


def make_model(name, seed):
    vpr_nb.seed_everything(seed)
    if name == "GeM":
        return build_model("small_cnn", "gem")
    model = build_model("small_cnn", "netvlad", num_clusters=K)
    kmeans_init(model, seed)
    return model


def run(name, seed):
    model = make_model(name, seed)
    init = copy.deepcopy(model)
    source = TripletSource(train_split, "triplet", max_heading_diff=45)
    t0 = time.perf_counter()
    hist = train(model, source, val_split, TrainConfig(epochs=EPOCHS, seed=seed, **OPTIM), progress=False)
    seconds = time.perf_counter() - t0
    return dict(model=model, init=init, hist=hist, seconds=seconds, test=evaluate_model(model, test_split, ns=NS))


METHODS = ("GeM", "NetVLAD")
runs = {(m, s): run(m, s) for m in METHODS for s in SEEDS}
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (timings vary from machine to machine)
for (m, s), r in runs.items():
    print(f"{m:8s} seed {s}: {r['seconds']:.1f} s for {EPOCHS} epochs ({r['seconds'] / EPOCHS:.1f} s/epoch)")
"""),
    ("code", r"""
test = {m: {n: [runs[m, s]["test"][n] for s in SEEDS] for n in NS} for m in METHODS}
dims = {m: runs[m, SEEDS[0]]["model"].out_dim for m in METHODS}
print(f"test Recall@N on city tiny, {EPOCHS} epochs, " +
      (f"mean +- std over seeds {SEEDS}" if len(SEEDS) > 1 else f"seed {SEEDS[0]}"))
print(f"{'method':9s}{'dim':>6s}" + "".join(f"{'R@' + str(n):>15s}" for n in NS) + "   best epoch")
for m in METHODS:
    cells = "".join(f"{np.mean(test[m][n]):9.3f} +- {np.std(test[m][n]):.3f}" if len(SEEDS) > 1
                    else f"{test[m][n][0]:15.3f}" for n in NS)
    print(f"{m:9s}{dims[m]:6d}{cells}   {[runs[m, s]['hist'].best_epoch + 1 for s in SEEDS]}")

fig, axes = plt.subplots(1, 3, figsize=(14, 3.5))
plots.plot_recalls({m: {n: float(np.mean(test[m][n])) for n in NS} for m in METHODS}, ax=axes[0],
                   title="test Recall@N (city tiny)")
for m in METHODS:
    runs[m, SEEDS[0]]["hist"].plot(axes=axes[1:], label=m)
fig.tight_layout()
plt.show()
"""),
    ("md", r"""
## What NetVLAD assigns where

For three test queries: the image, the hard cluster of each of the 8×12 positions ($\arg\max_k \bar a_k$,
one colour per cluster) with the k-means initialisation and after training, and the confidence
$\max_k \bar a_k$ after training. Positions that look alike (sky, road, a facade type) share a
cluster; training reshapes the clusters for the retrieval task.
"""),
    ("code", r"""
def assignments(model, images):
    with torch.no_grad():
        x = F.normalize(model.backbone(images_to_tensor(images)), dim=1)
        return torch.softmax(model.aggregator.conv(x), dim=1)          # [B, K, h, w], Eq. (3)


best = runs["NetVLAD", SEEDS[0]]
show = test_split.q_images[[0, 40, 80]]
a_init, a_trained = assignments(best["init"], show), assignments(best["model"], show)
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
"""),
    ("code", r"""
record("04_netvlad", {
    "profile": PROFILE, "epochs": EPOCHS, "seeds": list(SEEDS), "NetVLAD clusters": K,
    "alpha (k-means init, seed 0)": round(float(alpha), 2),
    **{f"{m} test R@{n}": round(float(np.mean(test[m][n])), 3) for m in METHODS for n in NS},
    **({f"{m} test R@1 std": round(float(np.std(test[m][1])), 3) for m in METHODS} if len(SEEDS) > 1 else {}),
    **{f"{m} descriptor dim": dims[m] for m in METHODS},
})
"""),
    ("md", r"""
## Graded exercise: $\alpha$ by hand

Write `alpha_from_clusters(descs, cents)`: Eq. (6) for L2-normalised descriptors `descs` $[N, D]$ and
centroids `cents` $[K, D]$ (numpy arrays; the centroids are *not* normalised), returning a Python float.
"""),
    ("solution", r"""
def alpha_from_clusters(descs, cents):
    ### BEGIN SOLUTION
    cos = descs @ (cents / np.linalg.norm(cents, axis=1, keepdims=True)).T
    top2 = np.sort(cos, axis=1)[:, -2:]
    return float(-np.log(0.01) / (top2[:, 1] - top2[:, 0]).mean())
    ### END SOLUTION
""", "ex-04-alpha"),
    ("tests", r"""
assert isinstance(alpha_from_clusters(descs, cents), float)
assert np.isclose(alpha_from_clusters(descs, cents), netvlad_model.aggregator.alpha, rtol=1e-4)
### BEGIN HIDDEN TESTS
_layer = NetVLAD(num_clusters=3, dim=4)
_rng = np.random.default_rng(1)
_d = _rng.standard_normal((50, 4))
_d /= np.linalg.norm(_d, axis=1, keepdims=True)
_c = 3.0 * _rng.standard_normal((3, 4))
_layer.init_from_clusters(_c, _d)
assert np.isclose(alpha_from_clusters(_d, _c), _layer.alpha, rtol=1e-6)
### END HIDDEN TESTS
""", "ex-04-alpha", 1),
    ("md", r"""
## Exercises

1. **Hard vs soft.** Replace `soft_assign` by `hard_assign` inside `netvlad_by_hand`: is the result
   still differentiable with respect to the centroids? With respect to the $1\times1$ conv weights?
2. **No intra-normalisation.** Remove the row-wise `F.normalize` in `vlad_by_hand`, rebuild a layer
   without it (subclass `NetVLAD`) and retrain. Which clusters dominate the descriptor now?
3. **The 100:1 rule.** Initialise with $\alpha$ ten times smaller and ten times larger than Eq. (6).
   How do the first-epoch validation recall and the mean max assignment change?
4. **vladv2.** Train `build_model("small_cnn", "netvlad", num_clusters=K, vladv2=True)` with
   `normalize_input=False`; Eq. (3) now holds exactly. Does it train better here?
5. **Budget.** NetVLAD's descriptor is 16× larger than GeM's. Reduce it with PCA (faiss `PCAMatrix`) to
   128-D after training and compare the Recall table at equal descriptor size.

## Takeaways

* BoW counts, VLAD sums residuals, NetVLAD soft-assigns (a $1\times1$ conv + softmax, Eq. 3) and learns
  centroids and assignment weights separately (Eq. 4).
* Three normalisations: each local descriptor, each cluster (intra-normalisation), the whole vector.
* k-means gives the centroids, and Eq. (6) a softmax sharp enough that each descriptor mostly votes for
  one cluster (best/second-best weight 100:1 on average).
* The residual sum is a batched matrix product, so the layer has no loop over clusters, and
  `vpr_nb.aggregation.NetVLAD` loads the public checkpoints by name.
* On this tiny world, compare GeM and NetVLAD with the table above, not with the paper: the ranking can
  change with the training budget (see the reproduce profile) and with the backbone.
"""),
]



if __name__ == "__main__":
    write(NAME, CELLS)
