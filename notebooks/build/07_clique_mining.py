"""Builder of notebooks/07_clique_mining.ipynb.

Run ``python notebooks/build/07_clique_mining.py`` to (re)write the notebook from the cell sources below,
then execute it in place with nbconvert (see the Makefile); cells are assembled by ``_nb.py``.
"""
from _nb import write

NAME = "07_clique_mining"

CELLS = [
    ("md", r"""
# 07 · CliqueMining: batches of places that are close, alike, and apart

**Aim.** Notebook 06 showed that a trained model confuses the right frame with one 10 m away. CliqueMining
(Izquierdo & Civera, ECCV 2024) changes only *which images go into a training batch*: places that look
alike and lie just beyond the same-place threshold, so that the Multi-Similarity loss has to separate
them. You will

* write the two ingredients (similarity-weighted group sampling and the geographic clique graph) and check
  the invariants of `vpr_nb.mining.clique_batches`;
* draw the graph, its cliques and one batch on the map, and compare the negatives of clique batches with
  those of random-place batches (the GSV-Cities baseline);
* train the same model (small CNN + GeM, MS loss) with random-place vs clique batches on the dense `route`
  world and on `city`, and report Recall@1/5 and the GDS slope before and after.
"""),
    ("code", r"""
PROFILE = "ci"  # "ci": 1 seed, 4 epochs (fast, what CI checks); "reproduce": 5 seeds, 10 epochs
""", ["parameters"]),
    ("code", r"""
import time

import matplotlib.pyplot as plt
import numpy as np
import torch
from scipy.spatial import cKDTree

import vpr_nb
from vpr_nb.evaluation import compute_descriptors, evaluate_model
from vpr_nb.gds import gds_profile
from vpr_nb.mining import CliqueBatchMaker, clique_batches, random_place_batches, sample_group_descriptors
from vpr_nb.models import build_model
from vpr_nb.report import record
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import PlaceBatchSource, TrainConfig, train

if PROFILE not in ("ci", "reproduce"):
    raise ValueError(f"PROFILE must be 'ci' or 'reproduce', got {PROFILE!r}")
SEEDS = {"ci": (0,), "reproduce": (0, 1, 2, 3, 4)}[PROFILE]   # training seeds (the world is seed 0)
EPOCHS = {"ci": 4, "reproduce": 10}[PROFILE]
P, K, BATCHES = 16, 4, 10          # places x images per batch, batches per epoch
THRESHOLD = {"route": 10.0, "city": 25.0}   # same-place threshold (m): route = 2 frames, city = pos_radius
REFRESH_EVERY = 1                  # recompute the group descriptors with the current model every epoch
torch.set_num_threads(1)           # same floats on every machine (and faster on a shared 2-core box)
vpr_nb.seed_everything(0)
print(f"profile {PROFILE}: seeds {SEEDS}, {EPOCHS} epochs of {BATCHES} batches of {P} x {K}")
"""),
    ("md", r"""
## Theory

The images carry geotags $g_i$ and a place-group id (MSLS's `unique_cluster`; here the world's place ids:
5 consecutive frames on the route, a street spot on the city). One batch of $P$ places $\times$ $K$ images:

1. **Anchor.** Draw a group $a$ uniformly. Describe every group $j$ by the descriptor $x_j$ of one random
   image of it (computed by a model).
2. **Similar groups.** With $d_j = \lVert x_a - x_j \rVert_2$, draw $S = 15$ groups without replacement with

$$P(j) \propto w_j = \max_k d_k - d_j \quad (j \ne a), \tag{1}$$

   so groups that look like the anchor are likely (linear weights: the farthest group never comes).
3. **Graph.** Over all images of the $S + 1$ groups, join two images when they are closer than the
   same-place threshold $\tau$ (25 m in the paper):

$$E = \{(i, j) : \lVert g_i - g_j \rVert_2 < \tau\}. \tag{2}$$

4. **Places = cliques.** A clique $C$ with $|C| \ge K$ is a set of images pairwise closer than $\tau$; keep
   $K$ random members as one place, then delete them **and all their neighbours**,
   $V \leftarrow V \setminus (C_K \cup N(C_K))$, so every later place is $\ge \tau$ from every chosen image.
   Repeat until $P$ places or no clique is left; then a new anchor.

The batch is trained with the **Multi-Similarity loss** (Wang et al., CVPR 2019, Eq. 6), with $S_{ij}$ the
cosine similarity, $\mathcal P_i$/$\mathcal N_i$ the mined positives/negatives of anchor $i$, $\alpha=1$,
$\beta=50$, $\lambda=0$:

$$\mathcal L = \frac1{PK}\sum_i \Big[\frac1\alpha \log\big(1 + \sum_{p \in \mathcal P_i} e^{-\alpha (S_{ip} - \lambda)}\big) + \frac1\beta \log\big(1 + \sum_{n \in \mathcal N_i} e^{\beta (S_{in} - \lambda)}\big)\Big]. \tag{3}$$

Random-place batches (GSV-Cities) draw $P$ groups uniformly and $K$ random images of each: two places of a
batch are usually far apart, so the negatives of Eq. (3) are easy.

**Descriptor refresh.** The original computes the group descriptors **once**, offline, with a
*pre-trained* SALAD. We have no pre-trained model, so this notebook recomputes them with the *current*
model at the start of every epoch (`CliqueBatchMaker(refresh_every=1)`); `refresh_every=None` gives the
original compute-once behaviour (here: with the untrained model).
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (generation time varies)
t0 = time.perf_counter()
worlds = {p: make_dataset(p, seed=0) for p in ("route", "city")}
print(f"generated in {time.perf_counter() - t0:.1f} s")
"""),
    ("code", r"""
def training_set(ds):
    tr = ds.train                   # images = train database + train queries, groups = place ids
    return dict(images=np.concatenate([tr.db_images, tr.q_images]), utm=np.concatenate([tr.db_utm, tr.q_utm]),
                groups=np.concatenate([tr.db_place, tr.q_place]))

data = {p: training_set(ds) for p, ds in worlds.items()}
for p, d in data.items():
    sizes = np.bincount(d["groups"])
    print(f"{p}: {len(d['utm'])} training images in {np.count_nonzero(sizes)} groups "
          f"(median {np.median(sizes[sizes > 0]):.0f} images), threshold {THRESHOLD[p]:.0f} m")
"""),
    ("md", r"""
## Build it: Eq. (1) and the batch invariants

The weights of Eq. (1) in three lines, and a checker for what Eqs. (2) and (4) guarantee: every place
pairwise $< \tau$, different places $\ge \tau$ apart, no image twice. `vpr_nb.mining.clique_batches` satisfies
them; random-place batches do not keep places apart.
"""),
    ("code", r"""
def similar_group_probs(x, anchor):                                  # Eq. (1)
    d = np.linalg.norm(x - x[anchor], axis=1)
    w = d.max() - d
    w[anchor] = 0.0
    return w / w.sum()

def check_batch(batch, utm, tau):                                   # Eqs. (2) and (4)
    pts = utm[batch]                                                 # (P, K, 2)
    d = np.linalg.norm(pts[:, None, :, None] - pts[None, :, None, :], axis=-1)   # (P, P, K, K)
    same = d[np.arange(len(batch)), np.arange(len(batch))]
    other = d[~np.eye(len(batch), dtype=bool)]
    return bool((same < tau).all()), bool((other >= tau).all()), len(np.unique(batch)) == batch.size

d = data["city"]
x = sample_group_descriptors(compute_descriptors(build_model("small_cnn", "gem"), d["images"]), d["groups"], 0)
prob = similar_group_probs(x, 0)
assert np.isclose(prob.sum(), 1.0) and prob[0] == 0 and prob.min() == 0
cb = clique_batches(d["utm"], d["groups"], x, P, K, THRESHOLD["city"], num_batches=20, seed=0)
rb = random_place_batches(d["groups"], P, K, num_batches=20, seed=0)
assert all(all(check_batch(b, d["utm"], THRESHOLD["city"])) for b in cb)
print("clique batches (pairwise < tau, places >= tau apart, distinct):", check_batch(cb[0], d["utm"], 25.0))
print("random batches:                                               ", check_batch(rb[0], d["utm"], 25.0))
"""),
    ("md", r"""
## The graph, its cliques and a batch on the map

The images of the groups used by one city batch, the edges of Eq. (2), and the places the batch took (one
colour each). Below: for every image of a batch, the distance to the nearest image of *another* place of
the batch — its hardest geographic negative. Clique batches put it just beyond $\tau$; random batches
hundreds of metres away.
"""),
    ("code", r"""
batch = cb[0]
pool = np.flatnonzero(np.isin(d["groups"], np.unique(d["groups"][batch])))
ij = cKDTree(d["utm"][pool]).query_pairs(THRESHOLD["city"] - 1e-9, output_type="ndarray")
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
ax = axes[0]
ax.scatter(*d["utm"].T, s=2, color="0.85")
seg = d["utm"][pool][ij]
ax.plot(seg[:, :, 0].T, seg[:, :, 1].T, color="0.6", lw=0.4)
ax.scatter(*d["utm"][pool].T, s=6, color="0.4")
colours = plt.cm.tab20(np.arange(len(batch)) % 20)
for place, c in zip(batch, colours):
    ax.scatter(*d["utm"][place].T, s=30, color=c, edgecolor="k", lw=0.4, zorder=3)
ax.set(aspect="equal", xlabel="easting (m)", ylabel="northing (m)",
       title=f"one clique batch: {len(batch)} places, graph edges < {THRESHOLD['city']:.0f} m")

def nearest_other_place(batches, utm):
    out = []
    for b in batches:
        pts = utm[b]
        dist = np.linalg.norm(pts[:, :, None, None] - pts[None, None], axis=-1)   # (P, K, P, K)
        for p in range(len(b)):
            dist[p, :, p, :] = np.inf
        out.append(dist.reshape(b.size, -1).min(axis=1))
    return np.concatenate(out)

bins = np.arange(0, 200, 5)
for name, bb in (("clique batches", cb), ("random batches", rb)):
    nn = nearest_other_place(bb, d["utm"])
    axes[1].hist(np.minimum(nn, 199), bins=bins, alpha=0.6, label=f"{name} (median {np.median(nn):.0f} m)")
axes[1].axvline(THRESHOLD["city"], color="k", ls="--", lw=1)
axes[1].set(xlabel="distance to the nearest image of another place (m, clipped at 200)", ylabel="images",
            title="geographic hardness of the negatives")
axes[1].legend()
plt.tight_layout()
plt.show()
"""),
    ("md", r"""
## Experiment: random-place vs clique batches

Same model (small CNN + GeM), same loss (MS loss + MS miner, Eq. 3), same optimiser (Adam, lr $10^{-3}$,
last-epoch weights), same number of steps; only the batches differ. The route uses $\tau = 10$ m (two frames:
a place is two consecutive frames, database + query, and the nearest negatives are two frames away,
matching its ±1-frame positives); the city uses $\tau = 25$ m. GDS slope: `gds_profile` on the test split,
query-database pairs, fitted over 0–30 m (route bins of 4.8 m, one frame each; city bins of 5 m).
"""),
    ("code", r"""
def gds_slope(model, split, preset):
    db, q = compute_descriptors(model, split.db_images), compute_descriptors(model, split.q_images)
    width = 4.8 if preset == "route" else 5.0
    return gds_profile(db, split.db_utm, 12 * width, width, query_descriptors=q, query_utm=split.q_utm,
                       fit_range=(0.0, 30.0)).slope

def run(preset, sampler, seed):
    ds, d = worlds[preset], data[preset]
    vpr_nb.seed_everything(seed)
    model = build_model("small_cnn", "gem")
    if sampler == "random":
        make = lambda model, epoch, rng: random_place_batches(d["groups"], P, K, num_batches=BATCHES, seed=rng)
    else:
        make = CliqueBatchMaker(d["images"], d["utm"], d["groups"], P, BATCHES, images_per_place=K,
                                same_place_threshold=THRESHOLD[preset], refresh_every=REFRESH_EVERY)
    train(model, PlaceBatchSource(d["images"], make), ds.val,
          TrainConfig(epochs=EPOCHS, optimizer="adam", lr=1e-3, seed=seed, restore_best=False), progress=False)
    rec = evaluate_model(model, ds.test, ns=(1, 5))
    return {"R@1": rec[1], "R@5": rec[5], "slope": gds_slope(model, ds.test, preset)}

t0 = time.perf_counter()
results = {}
for preset in ("route", "city"):
    vpr_nb.seed_everything(0)
    untrained = build_model("small_cnn", "gem")
    rec = evaluate_model(untrained, worlds[preset].test, ns=(1, 5))
    results[(preset, "untrained")] = [{"R@1": rec[1], "R@5": rec[5],
                                       "slope": gds_slope(untrained, worlds[preset].test, preset)}]
    for sampler in ("random", "clique"):
        results[(preset, sampler)] = [run(preset, sampler, s) for s in SEEDS]
train_seconds = time.perf_counter() - t0
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
print(f"{4 * len(SEEDS)} training runs in {train_seconds:.1f} s")
"""),
    ("code", r"""
def mean_std(rows, key):
    v = np.array([r[key] for r in rows])
    return v.mean(), v.std(ddof=1) if len(v) > 1 else 0.0

table = {}
print(f"{'world':>6} {'batches':>10} {'R@1':>15} {'R@5':>15} {'GDS slope (1/m)':>19}   (mean ± std over {len(SEEDS)} seed(s))")
for (preset, sampler), rows in results.items():
    stats = {k: mean_std(rows, k) for k in ("R@1", "R@5", "slope")}
    table[f"{preset}/{sampler}"] = {k: [round(float(m), 4), round(float(s), 4)] for k, (m, s) in stats.items()}
    print(f"{preset:>6} {sampler:>10} " + " ".join(
        f"{m:>8.3f} ± {s:.3f}" if k != "slope" else f"{m:>10.5f} ± {s:.5f}" for k, (m, s) in stats.items()))
"""),
    ("code", r"""
fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
for ax, key in zip(axes, ("R@1", "slope")):
    for k, sampler in enumerate(("untrained", "random", "clique")):
        m = [mean_std(results[(p, sampler)], key)[0] for p in ("route", "city")]
        s = [mean_std(results[(p, sampler)], key)[1] for p in ("route", "city")]
        err = dict(yerr=s, capsize=3) if len(SEEDS) > 1 else {}   # a spread needs more than one seed
        ax.bar(np.arange(2) + 0.27 * (k - 1), m, 0.27, label=sampler, **err)
    ax.set_xticks([0, 1], ["route", "city"])
    spread = f"mean ± std, {len(SEEDS)} seeds" if len(SEEDS) > 1 else "1 seed, no spread"
    ax.set_title((f"test {key}" if key == "R@1" else "GDS slope (0-30 m)") + f" ({spread})")
axes[0].legend()
plt.tight_layout()
plt.show()
"""),
    ("md", r"""
## Verdict

The paper reports that CliqueMining lifts DINOv2-SALAD from 76 to 90 R@1 on Nordland (+14 points) and
raises the GDS. The cell below states what *these* runs show, computed from the numbers above: the mean
paired difference (clique − random, same seed) and whether it exceeds twice its standard error.
"""),
    ("code", r"""
verdict = {}
for preset in ("route", "city"):
    for key in ("R@1", "slope"):
        diff = np.array([c[key] - r[key] for c, r in zip(results[(preset, "clique")], results[(preset, "random")])])
        se = diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else float("nan")
        if len(diff) < 3:
            word = "undecided (too few seeds; run PROFILE='reproduce')"
        elif diff.mean() > 2 * se:
            word = "clique mining is better"
        elif diff.mean() < -2 * se:
            word = "clique mining is worse"
        else:
            word = "no significant difference"
        verdict[f"{preset} {key}"] = word
        unit = "points" if key == "R@1" else "per m"
        scale = 100 if key == "R@1" else 1
        fmt = ".1f" if key == "R@1" else ".5f"
        print(f"{preset:>5} {key:>5}: clique - random = {scale * diff.mean():{fmt}} {unit} "
              f"(std err {scale * se:{fmt}}, {len(diff)} seed(s)) -> {word}")
print("paper (Nordland, SALAD): 76 -> 90 R@1, +14 points")
"""),
    ("code", r"""
record("07_clique_mining", {"profile": PROFILE, "seeds": len(SEEDS), "epochs": EPOCHS,
                            "descriptor refresh": f"every {REFRESH_EVERY} epoch(s), current model",
                            "results (mean, std)": table, "verdict": verdict})
"""),
    ("md", r"""
## Graded exercise: the hardest geographic negative of a batch

Write `min_other_place_distance(batch, utm)`: the smallest geographic distance between two images that
belong to *different* places of one batch `(P, K)`. For a clique batch it must be $\ge \tau$.
"""),
    ("solution", r"""
def min_other_place_distance(batch, utm):
    ### BEGIN SOLUTION
    pts = utm[batch]                                                   # (P, K, 2)
    dist = np.linalg.norm(pts[:, None, :, None] - pts[None, :, None, :], axis=-1)   # (P, P, K, K)
    return float(dist[~np.eye(len(batch), dtype=bool)].min())
    ### END SOLUTION
""", "ex-07-hardest"),
    ("tests", r"""
assert min_other_place_distance(cb[0], d["utm"]) >= THRESHOLD["city"]
assert abs(min_other_place_distance(rb[0], d["utm"]) - nearest_other_place(rb[:1], d["utm"]).min()) < 1e-9
### BEGIN HIDDEN TESTS
toy = np.array([[0.0, 0.0], [1.0, 0.0], [30.0, 0.0], [31.0, 0.0]])
assert abs(min_other_place_distance(np.array([[0, 1], [2, 3]]), toy) - 29.0) < 1e-9
### END HIDDEN TESTS
""", "ex-07-hardest", 1),
    ("md", r"""
**Reading the result.** Whatever the verdict cell says for your profile, keep the scale in mind: the paper
fine-tunes a strong pre-trained model (DINOv2-SALAD) on MSLS + GSV-Cities for thousands of steps with
descriptors from a pre-trained SALAD; here a 0.1 M-parameter CNN trains from scratch for a few dozen steps
on a few hundred synthetic places. Clique batches are harder (their hardest negatives sit just beyond $\tau$),
and hard batches help most once the model already recognises the area — which our small model barely does.
On the city, a place holds database images in 4 headings, so the positives of Eq. (3) include views
that share no content (neither sampler, nor the original clique graph, tests headings): both samplers
struggle there. A null or noisy result here is not evidence against the paper; a consistent gain would be a reproduction of
its direction, not of its size.

## Exercises

1. **Compute once.** Set `REFRESH_EVERY = None` (the original: descriptors computed once). With an untrained
   model the similar groups are nearly random; does that change the result? Then compute them once with the
   random-batch model of the same seed (pass its descriptors via `clique_batches` in your own `make_batches`).
2. **Threshold.** On the route, try $\tau = 25$ m (the paper's value). A place then spans 5 frames, so the
   MS loss pulls together images 20 m apart: what happens to R@1 at ±1 frame and to the GDS slope?
3. **Mix the batches.** The original trains on a GSV-Cities batch *and* a clique batch per step, with two
   losses. Write a `make_batches` that alternates random and clique batches.
4. **Similar groups.** Set `similar_groups=0` in `CliqueBatchMaker`: cliques from the anchor group only.
   How many anchors does a batch need, and how do the negatives change?
5. **Speed.** Run `python bench/bench_mining.py --quick` and read `bench/reference_clique.py`: why is a new
   networkx graph per place so much slower than one k-d tree per anchor and an alive mask?

## Takeaways

* CliqueMining only changes the batches: visually similar groups (Eq. 1), places as cliques of the
  geographic graph (Eq. 2), and negatives just beyond the same-place threshold.
* `clique_batches` guarantees the invariants (places pairwise $< \tau$, places $\ge \tau$ apart, no repeats),
  is deterministic per seed and mines 1000 batches of 30 × 4 from 1M geotags in well under a minute.
* Whether it pays off depends on the model and the data: measure it with several seeds and a paired
  comparison, as in the verdict cell, before claiming a gain.

## References

* S. Izquierdo, J. Civera. *Close, But Not There: Boosting Geographic Distance Sensitivity in Visual Place
  Recognition.* ECCV 2024. [arXiv:2407.02422](https://arxiv.org/abs/2407.02422); code:
  [github.com/serizba/cliquemining](https://github.com/serizba/cliquemining).
* S. Izquierdo, J. Civera. *Optimal Transport Aggregation for Visual Place Recognition* (DINOv2-SALAD).
  CVPR 2024. [arXiv:2311.15937](https://arxiv.org/abs/2311.15937); code:
  [github.com/serizba/salad](https://github.com/serizba/salad) (the model CliqueMining fine-tunes).
* A. Ali-bey, B. Chaib-draa, P. Giguère. *GSV-Cities: Toward Appropriate Supervised Visual Place Recognition.*
  Neurocomputing 2022. [arXiv:2210.10239](https://arxiv.org/abs/2210.10239); code:
  [github.com/amaralibey/gsv-cities](https://github.com/amaralibey/gsv-cities) (random-place batches, the baseline).
* X. Wang, X. Han, W. Huang, D. Dong, M. R. Scott. *Multi-Similarity Loss with General Pair Weighting for Deep
  Metric Learning.* CVPR 2019. [arXiv:1904.06627](https://arxiv.org/abs/1904.06627); code:
  [github.com/MalongTech/research-ms-loss](https://github.com/MalongTech/research-ms-loss),
  [github.com/KevinMusgrave/pytorch-metric-learning](https://github.com/KevinMusgrave/pytorch-metric-learning).
* F. Warburg, S. Hauberg, M. López-Antequera, P. Gargallo, Y. Kuang, J. Civera. *Mapillary Street-Level
  Sequences: A Dataset for Lifelong Place Recognition.* CVPR 2020 (the data CliqueMining mines cliques from);
  code: [github.com/mapillary/mapillary_sls](https://github.com/mapillary/mapillary_sls).
* A. Hagberg, D. Schult, P. Swart. *Exploring Network Structure, Dynamics, and Function using NetworkX.*
  SciPy 2008; code: [github.com/networkx/networkx](https://github.com/networkx/networkx) (`find_cliques`, used
  by the original code and by `bench/reference_clique.py`).
"""),
]


if __name__ == "__main__":
    write(NAME, CELLS)
