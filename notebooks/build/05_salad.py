"""Builder of notebooks/05_salad.ipynb.

Run ``python notebooks/build/05_salad.py`` to (re)write the notebook from the cell sources below,
then execute it in place with nbconvert (see the Makefile).
"""
from _nb import write

NAME = "05_salad"

CELLS = [
    ("md", r"""
# 05 · SALAD: aggregation as optimal transport

**Aim.** NetVLAD (notebook 04) lets every local feature spread its weight over the clusters with a
softmax, independently of the other features. SALAD (Izquierdo & Civera, CVPR 2024) assigns *all*
features to the clusters **jointly**, as an optimal-transport problem solved by a few Sinkhorn
iterations, with a **dustbin** that absorbs uninformative features. You will

* write log-space Sinkhorn from scratch on a toy matrix, check its marginals and see the transport
  plan as an image;
* derive SALAD's aggregation and check it against `vpr_nb.aggregation.SALAD` (state-dict compatible
  with the published DINOv2-SALAD aggregator);
* train SALAD, NetVLAD and GeM on the tiny `city` world with the same triplet pipeline and the same
  budget, and compare them (one seed in CI, several seeds in the reproduce profile).
"""),
    ("code", r"""
PROFILE = "ci"  # "ci": 3 epochs per model, one seed (a small budget: the notebook runs in < 60 s); "reproduce": 14 epochs, 5 seeds
""", ["parameters"]),
    ("code", r"""
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # single-threaded numpy BLAS: much faster for the many
                                                     # small products of the triplet mining on a busy 2-core CPU
import time

import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F

import vpr_nb
from vpr_nb import plots
from vpr_nb.aggregation import SALAD, salad_aggregate, sinkhorn
from vpr_nb.evaluation import evaluate_model, images_to_tensor
from vpr_nb.models import SmallCNN, VPRModel, build_model, init_netvlad
from vpr_nb.report import record
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import TrainConfig, TripletSource, train

if PROFILE not in ("ci", "reproduce"):
    raise ValueError(f"PROFILE must be 'ci' or 'reproduce', got {PROFILE!r}")
EPOCHS = {"ci": 3, "reproduce": 14}[PROFILE]              # training epochs, the same for every aggregator
SEEDS = {"ci": (0,), "reproduce": (0, 1, 2, 3, 4)}[PROFILE]  # training seeds (the world is always seed 0)
SALAD_SIZE = dict(num_clusters=16, cluster_dim=32, token_dim=64, hidden_dim=64)  # paper: 64, 128, 256, 512
NETVLAD_K = 16
NS = (1, 5, 10)
torch.set_num_threads(1)   # one thread: fastest on a shared 2-core CPU, and results independent of the core count
vpr_nb.seed_everything(0)
print(f"profile {PROFILE}: {EPOCHS} epochs per model, seeds {SEEDS}")
"""),
    ("md", r"""
## Theory

**Optimal transport.** $n$ local features must send their mass to $m$ clusters. With a score matrix
$S \in \mathbb{R}^{m \times n}$ (how well feature $i$ fits cluster $k$), find a transport plan
$P \ge 0$ with prescribed row sums $a \in \mathbb{R}^m$ (what each cluster receives) and column sums
$b \in \mathbb{R}^n$ (what each feature gives), maximising the score plus an entropy term:

$$P^\star = \arg\max_{P\,\mathbf{1} = a,\; P^\top \mathbf{1} = b} \;\langle P, S\rangle - \sum_{k,i} P_{ki}\,(\log P_{ki} - 1). \tag{1}$$

**Sinkhorn** (Cuturi, NeurIPS 2013). The solution has the form $P = \mathrm{diag}(e^{u})\, e^{S}\, \mathrm{diag}(e^{v})$;
alternately fitting the rows and the columns gives, in log space (stable for large scores),

$$u_k \leftarrow \log a_k - \log \sum_i e^{S_{ki} + v_i}, \qquad v_i \leftarrow \log b_i - \log \sum_k e^{S_{ki} + u_k}, \qquad \log P_{ki} = S_{ki} + u_k + v_i . \tag{2}$$

After a $v$ update the column sums are exact; the row sums converge geometrically.

**The dustbin.** With $n > m$ features, forcing every feature into a cluster would also aggregate sky
and road. SALAD appends a row with one learned score $z$ for every feature, $\bar S = [S; z\,\mathbf{1}^\top]$
of size $(m+1) \times n$, and asks

$$a = [\underbrace{1, \dots, 1}_{m}, \; n - m], \qquad b = [\underbrace{1, \dots, 1}_{n}] \tag{3}$$

so that each feature distributes mass 1, each cluster receives mass 1 and the dustbin takes the
rest: this needs $n > m$. (The published code divides $a, b$ by $n+m$ during the iterations and
multiplies back at the end, and runs only **3 iterations**.)

**SALAD** (Izquierdo & Civera, CVPR 2024). From the local features $x_i$ and the global token $t$ of the
backbone: projected features $f_i = \mathrm{MLP}_f(x_i) \in \mathbb{R}^{l}$, scores
$s_i = \mathrm{MLP}_s(x_i) \in \mathbb{R}^m$, the plan $P$ of Eq. (2)-(3) without its dustbin row, and

$$V_{\cdot k} = \sum_{i=1}^{n} P_{ki}\, f_i \in \mathbb{R}^{l} \quad\text{(no centroid residual, unlike NetVLAD's Eq. 4)}, \tag{4}$$

$$\mathrm{SALAD}(x, t) = \mathrm{L2}\Big(\big[\, \mathrm{L2}(\mathrm{MLP}_g(t)),\; \mathrm{vec}\big(V_{\cdot 1}/\lVert V_{\cdot 1}\rVert, \dots, V_{\cdot m}/\lVert V_{\cdot m}\rVert\big)\big]\Big), \tag{5}$$

of size $d_g + m \cdot l$ (256 + 64·128 = 8448 in the paper). Eq. (4) for all clusters at once is the
matrix product $F P^\top$ ($[l \times n] \cdot [n \times m]$).
"""),
    ("md", r"""
## Build it: Sinkhorn with a dustbin, on a toy matrix
"""),
    ("code", r"""
def sinkhorn_by_hand(scores, z, iters):
    # scores [m, n], z the dustbin score -> log P [m+1, n], Eqs. (2)-(3)
    m, n = scores.shape
    if n <= m:
        raise ValueError(f"the dustbin needs more features than clusters, got n={n}, m={m}")
    kw = dict(dtype=scores.dtype)
    s_bar = torch.cat([scores, torch.full((1, n), float(z), **kw)])                # [m+1, n] with the dustbin row
    log_a = torch.tensor([0.0] * m + [np.log(n - m)], **kw) - np.log(n + m)        # Eq. (3), divided by n+m
    log_b = torch.full((n,), -np.log(n + m), **kw)
    u, v = torch.zeros(m + 1, **kw), torch.zeros(n, **kw)
    for _ in range(iters):
        u = log_a - torch.logsumexp(s_bar + v[None, :], dim=1)
        v = log_b - torch.logsumexp(s_bar + u[:, None], dim=0)
    return s_bar + u[:, None] + v[None, :] + np.log(n + m)


gen = torch.Generator().manual_seed(0)
toy_scores = 2.0 * torch.randn(4, 12, generator=gen, dtype=torch.float64)     # m = 4 clusters, n = 12 features
z = 0.5
for iters in (1, 3, 100):
    plan = sinkhorn_by_hand(toy_scores, z, iters).exp()
    print(f"{iters:3d} iterations: column sums in [{plan.sum(0).min():.3f}, {plan.sum(0).max():.3f}], "
          f"cluster row sums {np.round(plan[:4].sum(1).numpy(), 3).tolist()}, dustbin row {plan[4].sum():.3f} (n - m = 8)")
"""),
    ("md", r"""
After 100 iterations every marginal of Eq. (3) holds; after SALAD's 3 iterations the columns are
exact and the rows close. The library's batched `vpr_nb.aggregation.sinkhorn` is the same function:
"""),
    ("code", r"""
for iters in (1, 3, 100):
    ours = sinkhorn_by_hand(toy_scores, z, iters)
    lib = sinkhorn(toy_scores[None], z, num_iters=iters)[0]
    assert torch.allclose(ours, lib, atol=1e-10)
plan = sinkhorn(toy_scores[None], z, num_iters=100)[0].exp()
assert torch.allclose(plan.sum(0), torch.ones(12, dtype=torch.float64), atol=1e-4)
assert torch.allclose(plan.sum(1), torch.tensor([1.0, 1, 1, 1, 8], dtype=torch.float64), atol=1e-4)
print("vpr_nb.sinkhorn equals the derivation; marginals (1, ..., 1 | n - m) and (1, ..., 1) hold to 1e-4")

iters_axis = np.arange(1, 31)
row_err = [(sinkhorn(toy_scores[None], z, num_iters=int(k))[0].exp().sum(1)
            - torch.tensor([1.0, 1, 1, 1, 8], dtype=torch.float64)).abs().max().item() for k in iters_axis]
softmax_plan = torch.softmax(toy_scores, dim=0)          # NetVLAD-style: each feature on its own
panels = [(softmax_plan, "softmax over clusters (NetVLAD)")] + \
         [(sinkhorn(toy_scores[None], z, num_iters=k)[0].exp(), f"Sinkhorn, {k} iteration{'s' * (k > 1)}") for k in (1, 3)]
fig, axes = plt.subplots(1, 4, figsize=(15, 2.8), gridspec_kw=dict(width_ratios=[1, 1, 1, 0.8]))
for ax, (p, title) in zip(axes, panels):
    im = ax.imshow(p.numpy(), cmap="magma", vmin=0, vmax=1)
    ax.set(title=title, xlabel="feature i", ylabel="cluster k" + (" (+ dustbin)" if p.shape[0] > 4 else ""))
fig.colorbar(im, ax=axes[:3], fraction=0.02)
axes[3].semilogy(iters_axis, row_err, marker=".")
axes[3].set(xlabel="Sinkhorn iterations", ylabel="max |row sum - a_k|", title="row marginal error")
axes[3].grid(alpha=0.3)
plt.show()
"""),
    ("md", r"""
The softmax plan (left) lets one cluster take most features and others none; the transport plan
spreads one unit of mass to each cluster and sends the leftover to the dustbin (last row).

## Build it: SALAD from the plan

Given the projected features, scores and token (the MLP heads are plain 1×1 convolutions and linear
layers), Eqs. (4)-(5) take three lines. We reuse the heads of a `vpr_nb` SALAD layer built with
SALAD's **default (paper) sizes**, and the derivation must give the same 8448-D descriptor:
"""),
    ("code", r"""
def salad_by_hand(f, s, g, z):
    # f [l, n] projected features, s [m, n] scores, g [d] projected token -> Eq. (5)
    p = sinkhorn_by_hand(s, z, 3).exp()[:-1]                # drop the dustbin row, [m, n]
    v = F.normalize(f @ p.T, dim=0)                         # Eq. (4), each cluster column L2-normalised, [l, m]
    return F.normalize(torch.cat([F.normalize(g, dim=0), v.flatten()]), dim=0)   # flattened as l*m + k


vpr_nb.seed_everything(0)
salad = SALAD().eval()                                       # 768 channels, 64 clusters x 128 + 256
features, token = torch.randn(2, 768, 16, 16), torch.randn(2, 768)   # a 224x224 image through DINOv2 ViT-B/14
with torch.no_grad():
    lib = salad((features, token))
    ours = torch.stack([salad_by_hand(salad.cluster_features(features[b:b + 1])[0].flatten(1),
                                      salad.score(features[b:b + 1])[0].flatten(1),
                                      salad.token_features(token[b]), salad.dust_bin.item()) for b in range(2)])
assert torch.allclose(ours, lib, atol=1e-5)
print(f"descriptor {tuple(lib.shape)}; by hand = vpr_nb to 1e-5: {bool((ours - lib).abs().max() < 1e-5)}")
print("state-dict keys:", sorted({k.split('.')[0] for k in salad.state_dict()}),
      f"{sum(p.numel() for p in salad.parameters()):,} parameters")
try:
    salad((torch.randn(1, 768, 8, 8), torch.randn(1, 768)))     # 64 features for 64 clusters
except ValueError as err:
    print("8x8 map with 64 clusters ->", err)
"""),
    ("md", r"""
## Experiment: SALAD vs NetVLAD vs GeM at equal budget

The course's `SmallCNN` gives $n = 8 \cdot 12 = 96$ local features of 128 channels and a global token
(a linear layer on the mean feature, the analogue of DINOv2's CLS token). SALAD is scaled down to
$m = 16$ clusters of $l = 32$ dimensions plus a 64-D token ($n = 96 > m$): a 576-D descriptor; its
MLP heads are 64 wide instead of 512 (`hidden_dim`), so that they do not cost more than the backbone.
NetVLAD has $K = 16$ k-means-initialised clusters (2048-D), GeM 128-D.

All three use the same triplet pipeline (notebook 03), the same optimiser (Adam, lr $10^{-3}$) and the
**same number of epochs**; the best-on-validation weights are tested once. In a short tuning run on the
validation split, SGD with lr 0.05 (the GeM recipe) trained NetVLAD much worse than Adam, GeM trained
equally well with both, and SALAD improved little over its first epoch with any of SGD 0.05,
Adam $10^{-3}$ or Adam $10^{-4}$ (with or without dropout): see the discussion after the table.

The CI budget is tiny (3 epochs, one seed: the notebook must run in under a minute on two cores), so
the CI numbers are a smoke test rather than a ranking; the reproduce profile trains 14 epochs with
5 seeds and reports mean ± std.
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
OPTIM = dict(optimizer="adam", lr=1e-3)      # the same optimiser and budget for all aggregators
METHODS = ("GeM", "NetVLAD", "SALAD")


def make_model(name, seed):
    vpr_nb.seed_everything(seed)
    if name == "GeM":
        return build_model("small_cnn", "gem")
    if name == "SALAD":
        return build_model("small_cnn", "salad", **SALAD_SIZE)
    model = build_model("small_cnn", "netvlad", num_clusters=NETVLAD_K)
    init_netvlad(model, train_split.db_images, per_image=20, niter=50, seed=seed)   # k-means init, notebook 04
    return model


def run(name, seed, make=make_model):
    model = make(name, seed)
    source = TripletSource(train_split, "triplet", max_heading_diff=45)
    t0 = time.perf_counter()
    hist = train(model, source, val_split, TrainConfig(epochs=EPOCHS, seed=seed, **OPTIM), progress=False)
    seconds = time.perf_counter() - t0
    return dict(model=model, hist=hist, seconds=seconds, test=evaluate_model(model, test_split, ns=NS))


runs = {(m, s): run(m, s) for s in SEEDS for m in METHODS}
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (timings vary from machine to machine)
for m in METHODS:
    sec = np.mean([runs[m, s]["seconds"] for s in SEEDS])
    print(f"{m:8s}: {sec / EPOCHS:.1f} s/epoch (mean over {len(SEEDS)} run(s))")
"""),
    ("code", r"""
test = {m: {n: np.array([runs[m, s]["test"][n] for s in SEEDS]) for n in NS} for m in METHODS}
dims = {m: runs[m, SEEDS[0]]["model"].out_dim for m in METHODS}
agg_params = {m: sum(p.numel() for p in runs[m, SEEDS[0]]["model"].aggregator.parameters()) for m in METHODS}
print(f"test Recall@N on city tiny, {EPOCHS} epochs, " +
      (f"mean +- std over seeds {SEEDS}" if len(SEEDS) > 1 else f"seed {SEEDS[0]} (CI profile: one seed, no spread)"))
print(f"{'method':9s}{'dim':>6s}{'agg. params':>13s}" + "".join(f"{'R@' + str(n):>15s}" for n in NS))
for m in METHODS:
    cells = "".join(f"{test[m][n].mean():9.3f} +- {test[m][n].std():.3f}" if len(SEEDS) > 1
                    else f"{test[m][n][0]:15.3f}" for n in NS)
    print(f"{m:9s}{dims[m]:6d}{agg_params[m]:13,d}{cells}")

fig, axes = plt.subplots(1, 3, figsize=(14, 3.5))
plots.plot_recalls({m: {n: float(test[m][n].mean()) for n in NS} for m in METHODS}, ax=axes[0],
                   title="test Recall@N (city tiny)")
for m in METHODS:
    runs[m, SEEDS[0]]["hist"].plot(axes=axes[1:], label=m)
fig.tight_layout()
plt.show()
"""),
    ("md", r"""
### Reading the table

SALAD starts close to **mean pooling of its projected features**: with a randomly initialised score
head the scores barely differ, so the plan is nearly uniform and every cluster vector $V_{\cdot k}$ of
Eq. (4) is about the same average of the projected features $f_i$. When all $V_{\cdot k}$ are equal,
moving mass between clusters changes nothing, so the score head receives almost no gradient: a
symmetric starting point that training must break. NetVLAD avoids it with k-means centroids and a sharp
softmax ($\alpha$, notebook 04), GeM does not need clusters at all. With DINOv2 features (diverse,
pretrained) the scores differ from the start.

The next cell measures that symmetry at initialisation: the gradient that one triplet-loss step sends
to each head, per unit of the head's weight norm.
"""),
    ("code", r"""
from vpr_nb.losses import triplet_loss

fresh = make_model("SALAD", 0).eval()                           # freshly initialised (eval: no dropout)
rng = np.random.default_rng(0)
positives = train_split.positives()
q_idx = rng.choice([i for i, p in enumerate(positives) if len(p)], 16, replace=False)
pos_idx = [positives[i][0] for i in q_idx]                      # a true positive of each query
neg_idx = rng.choice(len(train_split.db_images), 16)            # random database images
desc = [fresh(images_to_tensor(im)) for im in (train_split.q_images[q_idx], train_split.db_images[pos_idx],
                                                train_split.db_images[neg_idx])]
triplet_loss(desc[0], desc[1], desc[2][:, None], margin=0.1).backward()


def relative_grad(head):
    weights = [p for name, p in head.named_parameters() if name.endswith("weight")]
    return (sum(p.grad.norm() ** 2 for p in weights) ** 0.5 / sum(p.norm() ** 2 for p in weights) ** 0.5).item()


heads = {"score": fresh.aggregator.score, "cluster_features": fresh.aggregator.cluster_features,
         "token_features": fresh.aggregator.token_features}
rel = {name: relative_grad(head) for name, head in heads.items()}
for name, value in rel.items():
    print(f"{name:17s} |grad W| / |W| = {value:.1e}")
print(f"the score head gets {rel['cluster_features'] / rel['score']:.0f}x less gradient per unit weight "
      "than the feature head")
"""),
    ("md", r"""
The symmetry is not the whole story, though: a uniform plan makes SALAD the *mean of its projected
features* $f_i$ (a learned 1×1-conv MLP on the backbone features), and that projection by itself may be
what trains badly here. The reproduce profile tests this with three aggregators that have **no clusters
at all**, trained with the same recipe and seeds: `mean(f)` (SALAD's feature head, averaged),
`mean(ReLU(f))` (the same with non-negative outputs) and plain mean pooling of the backbone features.
Reading the outcome: if `mean(f)` stays near SALAD while mean pooling trains, the weak link on this tiny
CNN is the learned projection before pooling, not the optimal transport; `mean(ReLU(f))` tells whether
the sign of the projection matters. In our `make reproduce` run (5 seeds x 14 epochs) both projected
means stayed at SALAD's level and mean pooling came close to GeM: the projection head, signed or not,
is what stops the training here, and we do not yet know why (Exercise 6). The CI profile skips the
ablation, since 3 more models x 5 seeds do not fit in a minute.
"""),
    ("code", r"""
class ProjectedMean(torch.nn.Module):
    # the mean over positions of SALAD's feature head f_i (optionally ReLU(f_i)), L2-normalised
    def __init__(self, in_channels, relu):
        super().__init__()
        self.cluster_features = SALAD(in_channels, **SALAD_SIZE).cluster_features
        self.relu, self.out_dim = relu, SALAD_SIZE["cluster_dim"]

    def forward(self, x):
        f = self.cluster_features(x).flatten(2)
        return F.normalize((F.relu(f) if self.relu else f).mean(dim=2), dim=1)


def ablation_model(name, seed):
    vpr_nb.seed_everything(seed)
    if name == "mean pooling":
        return build_model("small_cnn", "mean")
    backbone = SmallCNN()
    return VPRModel(backbone, ProjectedMean(backbone.out_channels, relu=name == "mean(ReLU(f))"))


ABLATION = ("mean(f)", "mean(ReLU(f))", "mean pooling")
if PROFILE == "reproduce":
    ablation = {name: np.array([run(name, seed, ablation_model)["test"][1] for seed in SEEDS]) for name in ABLATION}
    print(f"no-cluster ablation, test R@1, {EPOCHS} epochs, mean +- std over seeds {SEEDS}")
    for name in ("SALAD", "GeM"):
        print(f"{name:15s}{test[name][1].mean():.3f} +- {test[name][1].std():.3f}  (table above)")
    for name in ABLATION:
        print(f"{name:15s}{ablation[name].mean():.3f} +- {ablation[name].std():.3f}")
    # paired by seed (same seeds, same world): differences with their standard error
    for a, b in (("mean(f)", "SALAD"), ("mean(ReLU(f))", "mean(f)"), ("mean pooling", "mean(f)")):
        da = ablation[a] - (test[b][1] if b in test else ablation[b])
        print(f"{a} - {b}: {da.mean():+.3f} (standard error {da.std(ddof=1) / np.sqrt(len(da)):.3f})")
else:
    ablation = None
    print("no-cluster ablation: reproduce profile only (make reproduce, or papermill -p PROFILE reproduce)")
"""),
    ("md", r"""
## What the trained SALAD keeps and discards

For three test queries: the image, the dustbin's share of each of the 96 positions
($P_{m+1,i}$: 1 = discarded) and the cluster that receives most of each position's mass.
"""),
    ("code", r"""
salad_model = runs["SALAD", SEEDS[0]]["model"].eval()
show = test_split.q_images[[0, 40, 80]]
with torch.no_grad():
    fmap, tok = salad_model.backbone.forward_with_token(images_to_tensor(show))
    scores = salad_model.aggregator.score(fmap).flatten(2)
    plans = sinkhorn(scores, salad_model.aggregator.dust_bin, 3).exp()          # [3, m+1, n]
h, w = fmap.shape[2:]
fig, axes = plt.subplots(3, 3, figsize=(8.5, 5.4))
for row in range(3):
    panels = [(show[row], "query", {}),
              (plans[row, -1].reshape(h, w), "dustbin share", dict(cmap="viridis", vmin=0, vmax=1)),
              (plans[row, :-1].argmax(0).reshape(h, w), "main cluster", dict(cmap="tab20", vmin=0, vmax=19))]
    for ax, (img, title, kw) in zip(axes[row], panels):
        ax.imshow(img, interpolation="nearest", **kw)
        ax.set(xticks=[], yticks=[], title=title if row == 0 else "")
fig.tight_layout()
plt.show()
print(f"dustbin score z = {salad_model.aggregator.dust_bin.item():.3f}; mean dustbin share on these images "
      f"{plans[:, -1].mean():.3f} (the marginals force (n - m) / n = {(h * w - 16) / (h * w):.3f} after full convergence)")
print(f"largest entry of each cluster row of the plan, mean: {plans[:, :-1].amax(2).mean():.3f} "
      f"(uniform plan 1/n = {1 / (h * w):.3f}; hard assignment of one feature per cluster = 1)")
spread = F.normalize(salad_model.aggregator.cluster_features(fmap).flatten(2) @ plans[:, :-1].transpose(1, 2), dim=1)
cos_between_clusters = (spread.transpose(1, 2) @ spread).mean().item()
print(f"mean cosine between the 16 cluster vectors V_k of an image: {cos_between_clusters:.3f} (1 = all clusters identical)")
"""),
    ("code", r"""
record("05_salad", {
    "profile": PROFILE, "epochs": EPOCHS, "seeds": list(SEEDS), "optimizer": f"{OPTIM['optimizer']} lr {OPTIM['lr']}",
    **{f"{m} test R@{n}": round(float(test[m][n].mean()), 3) for m in METHODS for n in NS},
    **({f"{m} test R@1 std": round(float(test[m][1].std()), 3) for m in METHODS} if len(SEEDS) > 1 else {}),
    **{f"{m} descriptor dim": dims[m] for m in METHODS},
    "score-head gradient deficit at init (x)": round(rel["cluster_features"] / rel["score"]),
    **({f"ablation {name} test R@1": round(float(ablation[name].mean()), 3) for name in ABLATION}
       if ablation is not None else {}),
})
"""),
    ("md", r"""
## Graded exercise: Eq. (4) with intra-normalisation

Write `cluster_vectors(f, p)`: for projected features `f` $[l, n]$ and a plan `p` $[m, n]$ (torch tensors,
dustbin row already removed), return the $[l, m]$ matrix whose column $k$ is $V_{\cdot k} / \lVert V_{\cdot k} \rVert$.
"""),
    ("solution", r"""
def cluster_vectors(f, p):
    ### BEGIN SOLUTION
    return F.normalize(f @ p.T, dim=0)
    ### END SOLUTION
""", "ex-05-clusters"),
    ("tests", r"""
_gen = torch.Generator().manual_seed(3)
_f, _s, _t = torch.randn(6, 20, generator=_gen), torch.randn(4, 20, generator=_gen), torch.randn(5, generator=_gen)
_p = sinkhorn(_s[None], 0.5, 3)[0].exp()[:-1]
_v = cluster_vectors(_f, _p)
assert _v.shape == (6, 4)
_desc = F.normalize(torch.cat([F.normalize(_t, dim=0), _v.flatten()]), dim=0)
assert torch.allclose(_desc, salad_aggregate(_f[None], _s[None], _t[None], 0.5)[0], atol=1e-5)
### BEGIN HIDDEN TESTS
assert torch.allclose(cluster_vectors(_f, _p).norm(dim=0), torch.ones(4), atol=1e-5)
assert torch.allclose(cluster_vectors(2 * _f, _p), _v, atol=1e-5)
### END HIDDEN TESTS
""", "ex-05-clusters", 1),
    ("md", r"""
## Exercises

1. **Iterations.** Train SALAD with 1 and with 10 Sinkhorn iterations (subclass `SALAD` and call
   `vpr_nb.aggregation.salad_aggregate(..., num_iters=k)`). Does the exact marginal matter for Recall?
2. **No dustbin.** Set the dustbin score to $-\infty$ in `sinkhorn_by_hand` (and $a = [n/m, \dots]$ so the
   marginals stay feasible). What happens to the features of the sky and the road?
3. **Temperature.** Sinkhorn here has regularisation 1 (Eq. 1). Multiply the toy scores by 10 and by 0.1:
   how does the plan change, and how many iterations does the row error need to reach $10^{-4}$?
4. **Token or clusters?** Retrain SALAD with `token_dim` tiny (e.g. 4) and with `cluster_dim` tiny: which
   part of the descriptor carries the retrieval performance here?
5. **Equal size.** Compare SALAD and NetVLAD at equal descriptor size (e.g. NetVLAD with $K = 4$, 512-D).
6. **Why does the projection head stall?** Mean pooling trains and `mean(f)` (the same pooling after
   SALAD's feature head) does not. Try a single linear 1×1 layer instead of the MLP, no dropout, a ten
   times smaller learning rate for the head only (two parameter groups), or the Multi-Similarity loss
   of notebook 07 instead of hardest-negative triplets. Which of them lets `mean(f)` and then SALAD train?

## Takeaways

* Sinkhorn alternates row and column normalisations of $e^{S}$, in log space for stability (Eq. 2); the
  columns are exact after each iteration, the rows converge geometrically.
* The dustbin row with a learned score lets the transport discard features; it needs more features than
  clusters ($n > m$), which is why tiny feature maps with 64 clusters are rejected.
* SALAD = MLP scores + optimal-transport assignment + MLP features, summed without centroid residuals,
  intra-normalised, concatenated with a global token (Eqs. 4-5); `vpr_nb.aggregation.SALAD` computes
  Eq. (4) as one batched product and loads the published DINOv2-SALAD aggregator weights by name.
* On the tiny CNN trained from scratch SALAD stays far below GeM and NetVLAD. Its score head starts
  symmetric (about a hundred times less gradient than the feature head), and the reproduce ablation
  shows that averaging SALAD's projected features without any clusters stalls just the same, while
  plain mean pooling trains: here the learned projection head, not the optimal transport, is the weak
  link. The paper's gains come with a pretrained DINOv2 backbone; read the table as what it measured.
"""),
]



if __name__ == "__main__":
    write(NAME, CELLS)
