"""Builder of notebooks/06_gds.ipynb.

Run ``python notebooks/build/06_gds.py`` to (re)write the notebook from the cell sources below, then
execute it in place with nbconvert (see the Makefile); cells are assembled by ``_nb.py``.
"""
from _nb import write

NAME = "06_gds"

CELLS = [
    ("md", r"""
# 06 · Geographic Distance Sensitivity: close, but not there

**Aim.** CliqueMining (Izquierdo & Civera, ECCV 2024) starts from an observation: on densely sampled
routes (Nordland, MSLS) a good VPR model retrieves an image *near* the query, but not the *nearest* one,
because its descriptor distance hardly grows with geographic distance over the first tens of metres. The
paper calls this the **Geographic Distance Sensitivity (GDS)** and shows it as a plot (its Fig. 1). Here
you will

* turn that plot into numbers: per geographic-distance bin, the mean and spread of the descriptor
  distance, and the **slope** of the mean (`vpr_nb.gds.gds_profile`);
* compute the **mis-ordering probability**, the chance that an image farther away looks more similar,
  and see how it caps Recall@1 when positives are a single frame wide;
* compare an untrained and a trained model on the dense `route` world (Nordland-like, frames 5 m apart,
  positives = ±1 frame);
* pick a query with a widget and look at its top-k with their true distances.
"""),
    ("code", r"""
PROFILE = "ci"  # "ci": 6 training epochs (fast, what CI checks); "reproduce": 12 epochs
""", ["parameters"]),
    ("code", r"""
import time

import matplotlib.pyplot as plt
import numpy as np
import torch
from scipy.special import ndtr

import vpr_nb
from vpr_nb import plots
from vpr_nb.evaluation import compute_descriptors, evaluate_model
from vpr_nb.gds import gds_profile, misordering_matrix, misordering_probability, query_topk, topk_order_agreement
from vpr_nb.models import build_model
from vpr_nb.report import record
from vpr_nb.synthetic import make_dataset
from vpr_nb.mining import random_place_batches
from vpr_nb.training import PlaceBatchSource, TrainConfig, train

if PROFILE not in ("ci", "reproduce"):
    raise ValueError(f"PROFILE must be 'ci' or 'reproduce', got {PROFILE!r}")
EPOCHS = {"ci": 6, "reproduce": 12}[PROFILE]
SPACING = 5.0                # route frame spacing (m)
BIN = 0.96 * SPACING         # bin k = [4.8 k, 4.8 (k+1)) holds exactly the pairs k frames apart
NBINS = 12                   # frames 0..11 apart, i.e. 0..55 m
FIT = (0.0, 30.0)            # the slope is fitted over the first 30 m
torch.set_num_threads(1)     # same floats on every machine (and faster on a shared 2-core box)
vpr_nb.seed_everything(0)
print(f"profile {PROFILE}: {EPOCHS} training epochs; bins of {BIN:.1f} m up to {NBINS * BIN:.1f} m")
"""),
    ("md", r"""
## Theory

Take every (query, database) pair $(q, i)$ whose geotags $g_q, g_i$ (UTM, metres) are at most $d_{\max}$
apart. Its **geographic distance** is $\delta_{qi} = \lVert g_q - g_i \rVert_2$ and its **descriptor
distance** is $D_{qi} = \lVert \bar f(q) - \bar f(i) \rVert_2 \in [0, 2]$ for L2-normalised descriptors.
Bin the pairs by geographic distance, $B_b = \{(q,i) : b w \le \delta_{qi} < (b+1) w\}$, and summarise each bin:

$$\mu_b = \frac{1}{|B_b|} \sum_{(q,i) \in B_b} D_{qi}, \qquad \sigma_b^2 = \frac{1}{|B_b|} \sum_{(q,i) \in B_b} (D_{qi} - \mu_b)^2 . \tag{1}$$

The paper's Fig. 1 draws $\mu_b$ with a band $\mu_b \pm \sigma_b$ against the bin centre $c_b$. As a single
number, the **GDS slope** is the weighted least-squares line through the bin means over a small-distance
range $c_b \in [0, 30]$ m, with weights $n_b = |B_b|$:

$$(s, a) = \arg\min_{s, a} \sum_b n_b \,(\mu_b - a - s\, c_b)^2 , \qquad s = \frac{\sum_b n_b (c_b - \bar c)(\mu_b - \bar\mu)}{\sum_b n_b (c_b - \bar c)^2} . \tag{2}$$

A model with a large $s$ separates near from far images; $s \approx 0$ means that, within 30 m, all images
look equally (dis)similar to the query.

**Mis-ordering.** For two geographic distances $d_1 < d_2$ let $D_1, D_2$ be descriptor distances of pairs
from their bins. The probability that the farther image is ranked first is $p(d_1, d_2) = P(D_2 < D_1)$.
Modelling each bin as a Gaussian $\mathcal N(\mu_b, \sigma_b^2)$,

$$p(d_1, d_2) \approx \Phi\!\left(\frac{\mu_1 - \mu_2}{\sqrt{\sigma_1^2 + \sigma_2^2}}\right), \tag{3}$$

and empirically $p = \frac{1}{n_1 n_2} \sum_{x \in B_1} \sum_{y \in B_2} \big([y < x] + \tfrac12 [y = x]\big)$. Eq. (3) says
that what matters is the gap between means *relative to the spread*: the slope alone is not enough.

**Why it caps Recall@1 on dense data.** On the route a query's positives are the frames $0$ and $\pm1$
apart ($\le 5$ m) and the frames $\pm 2$ apart (10 m) are already negatives. Ignoring everything but the
best positive (at 0 m) and the two nearest negatives (10 m, one on each side), the query is solved at
rank 1 only if both negatives look less similar than that positive, so

$$\text{R@1} \lesssim \big(1 - p(0, 10)\big)^{2} \tag{4}$$

(treating the two comparisons as independent; more negatives only lower the bound, positives at 5 m raise
it a little). With $p(0, 10) = 0.4$ the cap is $0.36$ however good the descriptor is at recognising the
*area*: the model retrieves images that are close, but not there.
"""),
    ("md", r"""
## The data

The tiny `route` world: a summer database and winter queries every 5 m along a track; a query is
geotagged at its frame, so the (query, database) distances are multiples of the frame spacing and the bins
of width $0.96 \times 5$ m hold one frame offset each. Training uses the `train` split, the profiles the
`test` split.
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (generation time varies)
t0 = time.perf_counter()
ds = make_dataset("route", seed=0)
print(f"generated in {time.perf_counter() - t0:.1f} s")
"""),
    ("code", r"""
te = ds.test
print(ds.train, ds.test, sep="\n")
vpr_nb.seed_everything(0)
untrained = build_model("small_cnn", "gem")
desc_u = {"db": compute_descriptors(untrained, te.db_images), "q": compute_descriptors(untrained, te.q_images)}
"""),
    ("md", r"""
## Build it: Eqs. (1)–(3) in numpy

On the small test split all pairs fit in a dense matrix, so the profile is a few lines of numpy. (The
package uses a k-d tree range search instead and never forms an $N \times N$ matrix: 100k images take a
few seconds, see `bench/bench_gds.py`.)
"""),
    ("code", r"""
def gds_by_hand(db, q, db_utm, q_utm, width, nbins, fit):
    geo = np.linalg.norm(q_utm[:, None] - db_utm[None], axis=2)          # (Q, N) metres
    desc = np.linalg.norm(q[:, None] - db[None], axis=2)                  # (Q, N) descriptor distance
    keep = geo <= width * nbins
    b = np.minimum((geo[keep] // width).astype(int), nbins - 1)           # bin index, last bin closed
    n = np.bincount(b, minlength=nbins)
    mu = np.bincount(b, desc[keep], nbins) / n                            # Eq. (1)
    sd = np.sqrt(np.bincount(b, (desc[keep] - mu[b]) ** 2, nbins) / n)
    c = (np.arange(nbins) + 0.5) * width
    m = (c >= fit[0]) & (c <= fit[1]) & (n > 0)
    cbar, mbar = np.average(c[m], weights=n[m]), np.average(mu[m], weights=n[m])
    s = np.sum(n[m] * (c[m] - cbar) * (mu[m] - mbar)) / np.sum(n[m] * (c[m] - cbar) ** 2)   # Eq. (2)
    return n, mu, sd, s

def p_mis_by_hand(mu, sd, b1, b2):                                        # Eq. (3)
    return ndtr((mu[b1] - mu[b2]) / np.sqrt(sd[b1] ** 2 + sd[b2] ** 2))

n, mu, sd, s = gds_by_hand(desc_u["db"], desc_u["q"], te.db_utm, te.q_utm, BIN, NBINS, FIT)
prof_u = gds_profile(desc_u["db"], te.db_utm, BIN * NBINS, BIN, query_descriptors=desc_u["q"], query_utm=te.q_utm,
                     fit_range=FIT, keep_pairs=True)
assert np.array_equal(n, prof_u.count)
assert np.allclose(mu, prof_u.mean, atol=1e-6) and np.allclose(sd, prof_u.std, atol=1e-5)
assert np.isclose(s, prof_u.slope, rtol=1e-4, atol=1e-8)
assert np.isclose(p_mis_by_hand(mu, sd, 0, 2), misordering_probability(prof_u, 0.0, 10.0), atol=1e-5)
print("pairs per bin:", n.tolist())
print(f"untrained: slope {s:.5f} per m, p(0 m, 10 m) = {p_mis_by_hand(mu, sd, 0, 2):.3f}  (by hand == vpr_nb)")
"""),
    ("md", r"""
## Experiment: untrained vs trained

Train the small CNN + GeM on the route's training split (database + queries) with the Multi-Similarity
loss on batches of 16 random places x 4 images (the GSV-Cities recipe, the baseline of notebook 07; Adam,
lr $10^{-3}$, the last epoch's weights). On this dense route it learns faster than NetVLAD triplets with
hardest negatives, whose negatives (10 m away) are nearly indistinguishable from the positives. Then compare the two models' profiles, slopes, mis-ordering probabilities,
Recall@N and how well their top-5 is sorted by true distance (`topk_order_agreement`: the fraction of
retrieval pairs in the right geographic order, 0.5 = random, and Kendall's $\tau$).
"""),
    ("code", r"""
tr = ds.train
train_images = np.concatenate([tr.db_images, tr.q_images])
train_groups = np.concatenate([tr.db_place, tr.q_place])       # place ids: 5 consecutive frames (25 m)

def random_batches(model, epoch, rng):                          # PlaceBatchSource's make_batches
    return random_place_batches(train_groups, 16, 4, num_batches=10, seed=rng)

vpr_nb.seed_everything(0)
trained = build_model("small_cnn", "gem")
t0 = time.perf_counter()
history = train(trained, PlaceBatchSource(train_images, random_batches), ds.val,
                TrainConfig(epochs=EPOCHS, optimizer="adam", lr=1e-3, restore_best=False), progress=False)
train_seconds = time.perf_counter() - t0
print("validation R@1 per epoch:", [round(r, 3) for r in history.recalls(1)])
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
print(f"training took {train_seconds:.1f} s")
"""),
    ("code", r"""
desc_t = {"db": compute_descriptors(trained, te.db_images), "q": compute_descriptors(trained, te.q_images)}
prof_t = gds_profile(desc_t["db"], te.db_utm, BIN * NBINS, BIN, query_descriptors=desc_t["q"], query_utm=te.q_utm,
                     fit_range=FIT, keep_pairs=True)
rows = {}
for name, model, prof, d in (("untrained", untrained, prof_u, desc_u), ("trained", trained, prof_t, desc_t)):
    rec = evaluate_model(model, te, ns=(1, 5, 10))
    agree = topk_order_agreement(d["q"], d["db"], te.q_utm, te.db_utm, k=5)
    p010 = misordering_probability(prof, 0.0, 10.0)
    rows[name] = {"slope (1/m)": prof.slope, "p(0,10) gauss": p010,
                  "p(0,10) empirical": misordering_probability(prof, 0.0, 10.0, "empirical"),
                  "p(5,10) gauss": misordering_probability(prof, 5.0, 10.0),
                  "R@1 cap, Eq. (4)": (1 - p010) ** 2, "R@1": rec[1], "R@5": rec[5], "R@10": rec[10],
                  "top-5 ordered": agree.mean_fraction_correct, "top-5 tau": agree.mean_kendall_tau}
cols = list(rows["untrained"])
print(f"{'':>10} " + " ".join(f"{c:>17}" for c in cols))
for name, r in rows.items():
    print(f"{name:>10} " + " ".join(f"{r[c]:>17.3f}" if abs(r[c]) >= 0.01 else f"{r[c]:>17.5f}" for c in cols))
"""),
    ("code", r"""
fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
prof_u.plot(axes[0], label=f"untrained (slope {prof_u.slope:.4f}/m)")
prof_t.plot(axes[0], label=f"trained (slope {prof_t.slope:.4f}/m)")
axes[0].set_title("descriptor vs geographic distance (mean ± 1 std, dashed: fit)")
ds_m = np.arange(0, 55, 5.0)
im = axes[1].imshow(misordering_matrix(prof_t, ds_m), vmin=0, vmax=1, cmap="coolwarm")
axes[1].set_xticks(range(len(ds_m)), [f"{d:.0f}" for d in ds_m], fontsize=7)
axes[1].set_yticks(range(len(ds_m)), [f"{d:.0f}" for d in ds_m], fontsize=7)
axes[1].set(xlabel="$d_2$ (m)", ylabel="$d_1$ (m)", title="trained: $P(D(d_2) < D(d_1))$, Eq. (3)")
fig.colorbar(im, ax=axes[1], fraction=0.046)
plt.tight_layout()
plt.show()
"""),
    ("md", r"""
**Reading the numbers.** Training raises the slope (near images now look more similar than far ones),
lowers the mis-ordering probabilities, and Recall@N rises with them. But the band stays wide compared with
the gap between neighbouring bins: the trained model still ranks an image 10 m away before the right one a
large fraction of the time, so even a model that never confused the route with far-away places could not
exceed the cap of Eq. (4) (a rough, independence-based estimate). The measured R@1 lies below that cap
because images far away still win too (the top-k table below shows such queries); R@5 and R@10 recover
many more queries: the retrieval is often *close*, but the first result is *not there*. This is the gap
CliqueMining
(notebook 07) attacks by training on batches of places that are near each other and look alike.
"""),
    ("md", r"""
## Pick a query

`query_topk` (a pure function, tested in `tests/test_gds.py`) returns a query's top-k with descriptor and
true distances; the widget only calls it and draws the images.
"""),
    ("code", r"""
def show_query(query, k=5, model="trained"):
    d = desc_t if model == "trained" else desc_u
    res = query_topk(d["q"], d["db"], te.q_utm, te.db_utm, query, k=k, pos_radius=te.pos_radius)
    print(res.table())
    titles = ["query"] + [f"#{r + 1}: {g:.0f} m" for r, g in enumerate(res.geo_distance)]
    plots.image_grid(np.concatenate([te.q_images[[query]], te.db_images[res.db_index]]), titles, ncols=k + 1)
    plt.show()

geo_top1 = np.array([query_topk(desc_t["q"], desc_t["db"], te.q_utm, te.db_utm, q, k=1).geo_distance[0]
                     for q in range(len(te.q_images))])
demo = int(np.flatnonzero((geo_top1 > te.pos_radius) & (geo_top1 <= 20.0))[0])   # close, but not there
show_query(demo)
"""),
    ("code", r"""
# NBVAL_IGNORE_OUTPUT
# (an interactive widget: its output depends on the front end)
try:
    import ipywidgets as widgets
    widgets.interact(show_query, query=widgets.IntSlider(0, 0, len(te.q_images) - 1, 1),
                     k=widgets.IntSlider(5, 2, 10, 1), model=["trained", "untrained"])
except ImportError:
    print("install ipywidgets for the interactive version; show_query(q) works without it")
"""),
    ("code", r"""
record("06_gds", {
    "epochs": EPOCHS,
    "table (route test split)": {name: {k: round(float(v), 4) for k, v in r.items()} for name, r in rows.items()},
})
"""),
    ("md", r"""
## Graded exercise: Eq. (3) by hand

Write `misorder_gaussian(mu1, sd1, mu2, sd2)`, the Gaussian mis-ordering probability of Eq. (3) for two
bins with means `mu1, mu2` and standard deviations `sd1, sd2` (use `scipy.special.ndtr` for $\Phi$).
"""),
    ("solution", r"""
def misorder_gaussian(mu1, sd1, mu2, sd2):
    ### BEGIN SOLUTION
    return float(ndtr((mu1 - mu2) / np.sqrt(sd1 ** 2 + sd2 ** 2)))
    ### END SOLUTION
""", "ex-06-misorder"),
    ("tests", r"""
assert abs(misorder_gaussian(0.5, 0.1, 0.5, 0.1) - 0.5) < 1e-9
assert abs(misorder_gaussian(prof_t.mean[0], prof_t.std[0], prof_t.mean[2], prof_t.std[2])
           - misordering_probability(prof_t, 0.0, 10.0)) < 1e-6
### BEGIN HIDDEN TESTS
assert misorder_gaussian(1.0, 0.1, 0.0, 0.1) > 0.99 and misorder_gaussian(0.0, 0.1, 1.0, 0.1) < 0.01
### END HIDDEN TESTS
""", "ex-06-misorder", 1),
    ("md", r"""
## Exercises

1. **Bin width.** Recompute the profile with `bin_width=2.5`. Why do every other bin empty out on the route,
   and why does the notebook use $0.96 \times$ the frame spacing?
2. **Gaussian vs empirical.** Compare `misordering_matrix(prof_t, ds_m, "gaussian")` with the `"empirical"`
   version. Where does the Gaussian approximation of Eq. (3) fail, and why (hint: skewness near 0 m)?
3. **Check Eq. (4).** For the trained model, count per query how many of the two 10 m negatives beat the
   0 m positive, and compare the fraction of queries with none to $(1 - p(0, 10))^2$.
4. **City.** Repeat the profile on the `city` world (`pos_radius` 25 m, `bin_width=5`). Is the slope over
   $[0, 30]$ m steeper or flatter than on the route, and what does that mean for R@1 at 25 m?
5. **Pairs = "all".** Profile the database against itself (`pairs="all"`): same-condition pairs. How does
   the curve change compared with summer-vs-winter query-database pairs?

## Takeaways

* GDS is measurable: bin pairs by geographic distance, Eq. (1); summarise with the slope of Eq. (2) and the
  mis-ordering probability of Eq. (3). The package computes it with a range search in O(pairs) memory.
* What limits Recall@1 on densely sampled data is not recognising the area but *ordering* nearby frames:
  with positives one frame wide, a mis-ordering probability $p(0, 10)$ caps R@1 near $(1-p)^2$, Eq. (4).
* Training raises the slope and lowers $p$, but the spread stays large; notebook 07 changes the batches
  (CliqueMining) to push on exactly this.
"""),
]


if __name__ == "__main__":
    write(NAME, CELLS)
