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
# # 00 · The synthetic world: what visual place recognition is
#
# **Aim.** Meet the task and the dataset of the whole course. *Visual place recognition* (VPR) answers "where
# was this photo taken?" by **retrieval**. A query image is compared with a database of geotagged images, and
# the geotag of the most similar one is the answer. The answer counts as correct when that image was taken
# within 25 m of the query (the convention of Pittsburgh and MSLS, two public street-view datasets). In this
# notebook you will
#
# * generate the course's two synthetic worlds (`make_dataset("city")`,
#   `make_dataset("route")`) and look at their maps, splits, conditions and geotags;
# * compute a query's *positives* (the database images that count as correct) by hand and with `vpr_nb`;
# * see in pixels why VPR is hard: **parallax**, **perceptual aliasing** and **condition change**;
# * see how much a few metres change an image, and read the difficulty knobs that notebook 01 sweeps.
#
# The cell below sets the *profile*: `"ci"`, the small budget whose outputs are stored, or `"reproduce"`, the
# full budget (larger worlds, more epochs and seeds).

# %% tags=["parameters"]
PROFILE = "ci"  # "ci": the tiny worlds (fast, what CI checks); "reproduce": the larger "small" worlds

# %%
import vpr_nb.notebook  # first, before numpy and torch start: it pins the CPU kernels (the stored numbers)
import dataclasses
import time

import matplotlib.pyplot as plt
import numpy as np

from vpr_nb import plots
from vpr_nb.evaluation import positives_within, raw_pixel_descriptors
from vpr_nb.probes import near_duplicate_probe
from vpr_nb.report import record
from vpr_nb.synthetic import SPLITS, WORLD_KINDS, WorldConfig, make_config, make_dataset

SETUP = vpr_nb.notebook.setup(PROFILE)   # checks PROFILE; one torch thread, everything seeded with 0
BUDGET = vpr_nb.notebook.budget(PROFILE, ci=dict(size="tiny"), reproduce=dict(size="small"))
SIZE = BUDGET["size"]
np.set_printoptions(precision=3, suppress=True)
print("world size:", SIZE)

# %% [markdown]
# ## Theory
#
# **Data.** A database $\mathcal{D} = \{(x_i, g_i)\}_{i=1}^{M}$ of images $x_i$ with geotags
# $g_i \in \mathbb{R}^2$ (easting, northing in metres on the UTM map grid), and queries $(x_q, g_q)$ whose
# geotag is hidden from the method and only used for scoring.
#
# **Positives.** The database images that count as a correct answer for query $q$ are those within a
# radius $r$ of it:
#
# $$\mathcal{P}(q) = \{\, i : \lVert g_q - g_i \rVert_2 \le r \,\} \tag{1}$$
#
# with $r = 25$ m for street-level datasets (Pittsburgh, MSLS; the `city` preset). For a frame-aligned route
# (Nordland, a Norwegian railway filmed in all four seasons; the `route` preset) it is the same frame $\pm 1$:
# Eq. (1) with $r$ just above the frame spacing.
#
# **Retrieval.** A model maps each image to a *global descriptor* (one vector for the whole image)
# $f(x) \in \mathbb{R}^D$ with $\lVert f(x) \rVert_2 = 1$ (unit length) and returns the nearest database image
#
# $$\hat{\imath}(q) = \arg\min_{i} \lVert f(x_q) - f(x_i) \rVert_2 , \tag{2}$$
#
# which is correct if and only if $\hat{\imath}(q) \in \mathcal{P}(q)$; Recall@N (notebook 01) generalises
# this to the top $N$.
#
# **Parallax.** A pinhole camera with horizontal field of view $\phi$ on a $W$-pixel-wide image has focal
# length $f_{px} = \tfrac{W/2}{\tan(\phi/2)}$. A point at depth $Z$ and lateral offset $X$ projects to
# column $u = f_{px} X / Z$, so moving the camera sideways by $t$ shifts it by
#
# $$\Delta u = f_{px}\, \frac{t}{Z}\ \text{pixels}. \tag{3}$$
#
# Near facades ($Z \approx 10$ m) slide across the image while the far skyline ($Z \approx 1000$ m)
# stays put: content changes *continuously* with distance, so a query 20 m from its positive can look quite different.
#
# **Perceptual aliasing.** Facades are drawn from a small library of $K$ styles (`num_facade_types`).
# With $B$ buildings each style appears about $B/K$ times, so two places far apart can look alike.
#
# **Condition change.** The database is rendered in one condition (summer daylight); queries in others
# (overcast, dusk, autumn, winter, rain), with occluders (cars, pedestrians) and camera jitter.

# %% [markdown]
# ## Build it: parallax and positives with plain numpy
#
# Eq. (3) for the camera of the synthetic world (48 px wide, 90° field of view), then Eq. (1) by brute
# force: all query-to-database distances, thresholded at $r$.

# %%
W, fov = 48, 90.0
f_px = (W / 2) / np.tan(np.radians(fov) / 2)             # focal length in pixels
print(f"focal length f_px = {f_px:.1f} px")
print("sideways move t  |  shift (px) of a point at depth Z = 5, 10, 20, 50, 1000 m   (Eq. 3)")
for t in (1.0, 5.0, 10.0, 25.0):
    shifts = f_px * t / np.array([5.0, 10.0, 20.0, 50.0, 1000.0])
    print(f"  t = {t:4.0f} m        |", "  ".join(f"{s:6.1f}" for s in shifts))


def positives_by_hand(db_utm, q_utm, radius):
    # Eq. (1): full (num_queries, num_db) distance matrix, then a threshold
    d = np.sqrt(((q_utm[:, None, :] - db_utm[None, :, :]) ** 2).sum(-1))
    return [np.flatnonzero(row <= radius) for row in d]


# %% [markdown]
# ## The two presets
#
# `make_dataset(preset, seed=0, size="tiny")` renders the whole world deterministically from the seed.
# `"city"` is Pittsburgh-like: a street grid, database images every 10 m in 4 headings, queries at random
# street positions in other conditions. `"route"` is Nordland-like: one long railway with roadside objects,
# a camera turned 45° to the side taking a frame every 5 m, database in summer, queries in winter, frame-aligned.

# %%
# NBVAL_IGNORE_OUTPUT
# (generation times vary from machine to machine)
t0 = time.perf_counter()
city = make_dataset("city", seed=0, size=SIZE)
t1 = time.perf_counter()
route = make_dataset("route", seed=0, size=SIZE)
t2 = time.perf_counter()
print(f"city generated in {t1 - t0:.1f} s, route in {t2 - t1:.1f} s")

# %%
for ds in (city, route):
    print(ds)
    print(f"  images {ds.db_images.dtype} {ds.db_images.shape[1:]}, geotags {ds.db_utm.dtype}, "
          f"conditions {ds.condition_names}")
    for k, s in enumerate(SPLITS):
        print(f"  {s:5s}: {int((ds.db_split == k).sum()):5d} database, {int((ds.q_split == k).sum()):5d} queries")

# %% [markdown]
# ### Maps and splits
#
# Train / val / test are **geographically disjoint** bands, with gaps wider than the positive radius, so
# memorising the training places cannot pass the test. Blue train, orange val, green test; dots database,
# crosses queries; grey lines walls, dark grey dots trees.

# %%
fig, axes = plt.subplots(2, 1, figsize=(10, 8.5))
plots.plot_map(city, ax=axes[0])
plots.plot_map(route, ax=axes[1])
fig.tight_layout()
plt.show()


def min_gap(ds, a, b):
    pa = np.concatenate([ds.db_utm[ds.db_split == a], ds.q_utm[ds.q_split == a]])
    pb = np.concatenate([ds.db_utm[ds.db_split == b], ds.q_utm[ds.q_split == b]])
    return min(np.sqrt(((pa[i:i + 500, None] - pb[None]) ** 2).sum(-1)).min() for i in range(0, len(pa), 500))


for ds in (city, route):
    gaps = {f"{SPLITS[a]}-{SPLITS[b]}": min_gap(ds, a, b) for a, b in ((0, 1), (1, 2), (0, 2))}
    print(ds.name, "closest images of different splits (m):", {k: round(float(v), 1) for k, v in gaps.items()},
          f"> pos_radius {ds.pos_radius:g} m:", all(v > ds.pos_radius for v in gaps.values()))

# %% [markdown]
# ### Conditions
#
# Row 0 is the database condition; the other rows are query conditions. Look for the season palette
# (foliage, snow on the ground), the illumination and sun direction, fog, rain noise, lit windows at
# dusk, and the occluders (coloured boxes).

# %%
plots.condition_grid(city.test, per_condition=8, seed=0)
plt.show()

# %%
plots.condition_grid(route.test, per_condition=8, seed=0)
plt.show()

# %% [markdown]
# ### The difficulty knobs
#
# Every knob lives in the dataclass `WorldConfig`; `make_dataset(..., **overrides)` changes any of them
# (an unknown name raises a `ValueError`). Notebook 01 sweeps the *difficulty knobs*.

# %%
DIFFICULTY = {
    "condition_strength": "0 = queries in the database condition, 1 = full condition change",
    "position_jitter": "std (m) of query position noise (route: along the track)",
    "heading_jitter": "std (deg) of query heading noise",
    "pitch_jitter": "std (px) of the horizon shift of queries",
    "occluder_rate": "mean number of cars / pedestrians per query",
    "num_facade_types": "facade styles in the library (fewer = more aliasing)",
    "colour_variation": "per-building colour noise (less = more aliasing)",
}
cfg_city, cfg_route = make_config("city", SIZE), make_config("route", SIZE)
print(f"{'knob':20s} {'city':>10s} {'route':>10s}   meaning")
for name, meaning in DIFFICULTY.items():
    print(f"{name:20s} {getattr(cfg_city, name)!s:>10s} {getattr(cfg_route, name)!s:>10s}   {meaning}")
# the other knobs (layout, cameras, rendering, splits); each world kind reads some of its own
other = [f.name for f in dataclasses.fields(WorldConfig) if f.name not in DIFFICULTY and f.name not in ("preset", "size")]
differ = [n for n in other if getattr(cfg_city, n) != getattr(cfg_route, n)]
print(f"\n{len(other)} other knobs (geometry, rendering, splits); the {len(differ)} whose values differ "
      f"between the presets ('-' = not read by that preset):")
for n in differ:
    a = "-" if n in WORLD_KINDS["route"].fields else getattr(cfg_city, n)
    b = "-" if n in WORLD_KINDS["city"].fields else getattr(cfg_route, n)
    print(f"  {n:24s} city: {a!s:28s} route: {b!s}")

# %% [markdown]
# ## Use `vpr_nb`: positives
#
# `dataset.positives()` and `positives_within` (a range search in a KD-tree, an index of points in space that
# skips far-away ones) must give exactly the sets of Eq. (1) computed by hand above.

# %%
city_test, route_test = city.test, route.test
for ds in (city_test, route_test):
    mine = positives_by_hand(ds.db_utm, ds.q_utm, ds.pos_radius)
    lib = ds.positives()
    assert len(mine) == len(lib) and all(np.array_equal(a, b) for a, b in zip(mine, lib))
    lib2 = positives_within(ds.db_utm, ds.q_utm, ds.pos_radius)
    assert all(np.array_equal(a, b) for a, b in zip(lib, lib2))
print("hand-made positives == vpr_nb positives for", city_test.name, "and", route_test.name, "test splits")

# %% [markdown]
# ## Experiment: geotags, positives, parallax, aliasing
#
# ### How many positives does a query have?
#
# In the city, database images stand every 10 m in 4 headings. A 25 m radius holds a few dozen,
# **most of them looking another way**. On the route a query has its own frame and its neighbour(s).

# %%
n_city = np.array([len(p) for p in city_test.positives()])
n_route = np.array([len(p) for p in route_test.positives()])
for name, n in (("city", n_city), ("route", n_route)):
    print(f"{name:5s} test: {len(n)} queries, positives per query mean {n.mean():.2f}, "
          f"min {n.min()}, max {n.max()}, queries without positive {int((n == 0).sum())}")
print("route positives per query (count: queries):", dict(zip(*[x.tolist() for x in np.unique(n_route, return_counts=True)])))

fig, axes = plt.subplots(1, 2, figsize=(10, 3))
axes[0].hist(n_city, bins=np.arange(n_city.max() + 2) - 0.5, color="tab:green")
axes[0].set(title=f"city test: positives within {city.pos_radius:g} m", xlabel="positives per query", ylabel="queries")
axes[1].hist(n_route, bins=np.arange(n_route.max() + 2) - 0.5, color="tab:purple", rwidth=0.6)
axes[1].set(title=f"route test: positives within {route.pos_radius:g} m", xlabel="positives per query")
fig.tight_layout()
plt.show()

# %% [markdown]
# A query and its 15 nearest positives (title: distance in metres and relative heading). Only the framed
# positives, which look roughly the query's way, share content with it.

# %%
qi = 5
pos = city_test.positives()[qi]
dist = np.linalg.norm(city_test.db_utm[pos] - city_test.q_utm[qi], axis=1)
dhead = (city_test.db_heading[pos] - city_test.q_heading[qi] + 180) % 360 - 180
order = np.argsort(dist)[:15]
images = np.concatenate([city_test.q_images[qi:qi + 1], city_test.db_images[pos[order]]])
cond = city_test.condition_names[city_test.q_condition[qi]]
titles = [f"query ({cond})"] + [f"{dist[j]:.0f} m, {dhead[j]:+.0f}°" for j in order]
frames = ["0.2"] + [plots.CORRECT if abs(dhead[j]) < 45 else None for j in order]
plots.image_grid(images, titles=titles, ncols=8, frame_colours=frames)
plt.show()

# %% [markdown]
# ### Parallax: one place seen from nearby positions
#
# Top: consecutive route frames (5 m apart), all in the database condition. Roadside objects, trees and
# houses near the track slide across and out of view; the hills on the horizon stay fixed (Eq. 3).
# Bottom: city database images that look the same way from places 0, 10, 20, … m down the street.

# %%
start = 40
frames_ = route_test.db_images[start:start + 8]
titles = [f"frame {start + k}: {5 * k} m" for k in range(8)]
plots.image_grid(frames_, titles=titles, ncols=8)
plt.show()

# city: database images with the same heading (45 deg: diagonal to an east-west street) on one street
def angle_diff(a, b):
    return np.abs((a - b + 180) % 360 - 180)


ew = np.flatnonzero(angle_diff(city_test.db_heading, 45.0) < 10)           # heading ~45 deg
y0 = np.round(city_test.db_utm[ew, 1]).min()                                 # the southern-most street
on_street = ew[np.abs(city_test.db_utm[ew, 1] - y0) < 2]
on_street = on_street[np.argsort(city_test.db_utm[on_street, 0])][:8]
dd = city_test.db_utm[on_street, 0] - city_test.db_utm[on_street[0], 0]
plots.image_grid(city_test.db_images[on_street], titles=[f"{x:.0f} m" for x in dd], ncols=8)
plt.show()

# %% [markdown]
# How quickly does appearance change with distance? Below: the cosine similarity (the dot product of two
# unit-length descriptors; 1 for identical images) of same-heading database images against the distance
# between their cameras. Two pixel descriptors: raw pixels (flattened and scaled to unit length, i.e.
# *L2-normalised*: notebook 01's baseline) and *centred* pixels (minus the mean database image). Raw cosines
# all sit near 0.85 (a shared layout of sky, facades and road); centring shows the decay. Either way,
# similarity falls to the level of unrelated pairs within a few tens of metres.

# %%
x = city.db_images.reshape(len(city.db_images), -1).astype(np.float32) / 255.0
x = x - x.mean(0)
descs = {"raw pixels": raw_pixel_descriptors(city.db_images),
         "centred pixels": x / np.linalg.norm(x, axis=1, keepdims=True)}
rng = np.random.default_rng(0)
sub = np.sort(rng.choice(len(city.db_images), min(1500, len(city.db_images)), replace=False))
ia, ib = np.triu_indices(len(sub), 1)
keep = angle_diff(city.db_heading[sub[ia]], city.db_heading[sub[ib]]) < 10
ia, ib = ia[keep], ib[keep]
dist = np.linalg.norm(city.db_utm[sub[ia]] - city.db_utm[sub[ib]], axis=1)
bins = np.array([0, 5, 15, 25, 40, 60, 100, 200, 400, 1000])
which = np.digitize(dist, bins) - 1
curves = {}
for name, dsc in descs.items():
    sim = (dsc[sub] @ dsc[sub].T)[ia, ib]
    curves[name] = np.array([sim[which == k].mean() if (which == k).any() else np.nan for k in range(len(bins) - 1)])
print(f"{'distance':>12s} {'pairs':>7s}" + "".join(f"{k:>16s}" for k in descs))
for k in range(len(bins) - 1):
    print(f"{bins[k]:5d}-{bins[k + 1]:4d} m {int((which == k).sum()):7d}" + "".join(f"{curves[n][k]:16.3f}" for n in descs))
fig, axes = plt.subplots(1, 2, figsize=(10, 3))
for ax, (name, c) in zip(axes, curves.items()):
    ax.semilogx(np.sqrt(np.maximum(bins[:-1], 1) * bins[1:]), c, marker="o")
    ax.axvline(city.pos_radius, color="0.5", ls="--", label="25 m")
    ax.set(xlabel="distance between the two cameras (m)", ylabel="mean cosine", title=f"{name}, same heading")
    ax.legend()
fig.tight_layout()
plt.show()

# %% [markdown]
# ### Close, but not there: how much do a few metres change?
#
# A model can tell the right frame from one a few metres away only if a few metres change the image.
# Below, two versions of the route:
#
# * **Without near content**: the camera looks along the track, with only trees and the odd pole near it
#   (`roadside_spacing=0`, `camera_yaw=0`).
# * The **default route**: roadside objects (posts, boards, signs) every metre on each side
#   (`roadside_spacing=1`) and the camera turned 45° to the side (`camera_yaw=45`), so near content
#   sweeps across the image.
#
# The printout gives the share of test frames whose same-season frame $s$ metres ahead is *closer* in raw
# pixels than their own cross-season query (the course's near-duplicate probe, used again in notebook 07).

# %%
NO_NEAR_CONTENT = {"roadside_spacing": 0.0, "camera_yaw": 0.0}
strips = {"without near content": make_dataset("route", seed=0, frame_spacing=2.5, splits=("test",),
                                               **NO_NEAR_CONTENT).test,
          "default route": make_dataset("route", seed=0, frame_spacing=2.5, splits=("test",)).test}
first = 40
for label, part in strips.items():
    print(label)
    plots.image_grid(np.concatenate([part.db_images[first:first + 6], part.q_images[first:first + 1]]),
                     titles=[f"+{2.5 * k:.1f} m" for k in range(6)] + ["query, +0 m"], ncols=7)
    plt.show()
NEAR_DUPLICATES = {label: near_duplicate_probe(part, None, steps=(2.5, 5.0, 10.0)) for label, part in strips.items()}
print("share of test frames whose same-season frame s metres ahead is closer (raw pixels) than their "
      "cross-season query")
for label, shares in NEAR_DUPLICATES.items():
    print(f"{label:>24}: " + "   ".join(f"s = {k:4.1f} m: {v:.3f}" for k, v in shares.items()))

# %% [markdown]
# **Figure.** Route frames 2.5 m apart in summer, then the first frame's winter query. Top: without near
# content, frames differ in a few far pixels. Bottom: each step moves the near objects across the image.

# %% [markdown]
# ### Perceptual aliasing: two places, one facade style
#
# For every city database image we cast the central ray and find the building it hits, with its facade
# `style` (`dataset.extra["scene"]`). Among pairs **more than 100 m apart** sharing a style, we show the
# most alike in raw pixels, and beside them each image's true neighbour 10 m down the street.

# %%
scene = city.extra["scene"]
desc = descs["raw pixels"]
utm, head, desc_s = city.db_utm[sub], city.db_heading[sub], desc[sub]
walls = np.flatnonzero(scene.kind == 0)
A, E = scene.a[walls], scene.b[walls] - scene.a[walls]
D = np.stack([np.cos(np.radians(head)), np.sin(np.radians(head))], 1)
AO = A[None] - utm[:, None]
den = D[:, None, 0] * E[None, :, 1] - D[:, None, 1] * E[None, :, 0]
with np.errstate(divide="ignore", invalid="ignore"):
    t = (AO[..., 0] * E[None, :, 1] - AO[..., 1] * E[None, :, 0]) / den     # distance along the ray
    s = (AO[..., 0] * D[:, None, 1] - AO[..., 1] * D[:, None, 0]) / den     # position along the wall
t = np.where((t > 0) & (s >= 0) & (s <= 1), t, np.inf)
hit = np.argmin(t, 1)
style = np.where(np.isfinite(t.min(1)), scene.style[walls[hit]], -1)
print("facade styles hit by the central ray (style: images):",
      dict(zip(*[x.tolist() for x in np.unique(style, return_counts=True)])))

sim = desc_s @ desc_s.T
far = np.linalg.norm(utm[:, None] - utm[None], axis=-1) > 100
same = (style[:, None] == style[None]) & (style[:, None] >= 0)
i, j = np.unravel_index(np.argmax(np.where(far & same, sim, -1)), sim.shape)
print(f"most alike pair: images {sub[i]} and {sub[j]}, {np.linalg.norm(utm[i] - utm[j]):.0f} m apart, "
      f"style {style[i]}, raw-pixel cosine {sim[i, j]:.3f}")


def neighbour(k):  # the most similar database image with the same heading, 5-15 m away
    d = np.linalg.norm(city.db_utm - utm[k], axis=1)
    ok = np.flatnonzero((angle_diff(city.db_heading, head[k]) < 10) & (d > 5) & (d < 15))
    return int(ok[np.argmax(desc[ok] @ desc_s[k])])


ni, nj = neighbour(i), neighbour(j)
plots.image_grid(city.db_images[[sub[i], sub[j], ni, nj]],
                 titles=[f"place A ({sim[i, j]:.3f} to B)", "place B, far away",
                         f"A + 10 m ({desc[ni] @ desc_s[i]:.3f} to A)", f"B + 10 m ({desc[nj] @ desc_s[j]:.3f} to B)"],
                 ncols=4, scale=2.2)
plt.show()

# %%
record("00_synthetic_world", {
    "city db images": int(len(city.db_images)), "city queries": int(len(city.q_images)),
    "route db images": int(len(route.db_images)), "route queries": int(len(route.q_images)),
    "city test positives per query (mean)": round(float(n_city.mean()), 3),
    "route test positives per query (mean)": round(float(n_route.mean()), 3),
    "near duplicates (raw pixels)": {label: {f"{k} m": round(v, 3) for k, v in shares.items()}
                                     for label, shares in NEAR_DUPLICATES.items()},
})

# %% [markdown]
# ## Exercises
#
# 1. **Radius** (no training). Recompute the city positives with $r = 10$ m and $r = 50$ m
#    (`ds.positives(radius)`). How does the mean number of positives scale with $r$? Why roughly like $r$
#    rather than $r^2$?
#    <details><summary>Hint</summary><code>np.mean([len(p) for p in city_test.positives(10.0)])</code>, and
#    the same with 50.0. Cameras stand only on the streets: how many positions does a disc of radius $r$
#    cover on one straight street?</details>
# 2. **Parallax** (pen and paper). With Eq. (3), how far must the camera move for a facade 10 m away to shift
#    by half the image width? And the skyline at 1000 m? Check the first against the route frames above.
#    <details><summary>Hint</summary>Solve Eq. (3) for $t$ with $\Delta u = W/2 = 24$ px and the printed
#    $f_{px} = 24.0$ px. The table's columns for $Z = 10$ m and $Z = 1000$ m check your answer. The route's
#    camera is turned 45° to the side, so about 3.5 m of each 5 m step is sideways to its view.</details>
# 3. **Aliasing** (no training; under 1 min). Regenerate the city with `num_facade_types=2` and with
#    `num_facade_types=40`. Which setting makes VPR harder? Compare the cosine of the most alike far-apart
#    pair.
#    <details><summary>Hint</summary><code>city = make_dataset("city", seed=0, size=SIZE, num_facade_types=2)</code>.
#    Then rerun the cosine-vs-distance cell and the aliasing cell (the default 10 styles give 0.965).
#    Regenerate the default city afterwards.</details>
# 4. **Conditions** (no training). Generate `make_dataset("city", condition_strength=0.0)`. What do the
#    queries look like now, and which difficulties remain?
#    <details><summary>Hint</summary>Make
#    <code>c0 = make_dataset("city", seed=0, size=SIZE, condition_strength=0.0)</code>. Show
#    <code>plots.condition_grid(c0.test, per_condition=8, seed=0)</code> and compare each query row with row 0,
#    the database condition. The knob table above lists what <code>condition_strength</code> leaves
#    alone.</details>
# 5. **Splits** (no code). Why would a random train/test assignment (not geographic bands) give an
#    over-optimistic test score?
#    <details><summary>Hint</summary>A random split puts training images a few metres from each test query.
#    In the cosine table above, images less than 15 m apart are the most alike. What could a model that
#    memorised its training images answer? Would that work in a city it has never seen?</details>
#
# ## Takeaways
#
# * VPR is retrieval: descriptor of the query → nearest database descriptors → their geotags. A result is
#   correct when it lies within $r$ (25 m, or ±1 frame on a route) of the query, Eq. (1)–(2).
# * A positive by geotag need not look like the query (other headings, other conditions); a wrong
#   answer can look very much like it (aliasing). Both make raw pixels a weak descriptor.
# * Content changes continuously with distance because of parallax, Eq. (3): near structure moves, the skyline
#   does not. A few metres change an image only when there is content near the camera. Without it, the
#   same-season frame 5 m ahead is closer in raw pixels than the cross-season query for 0.91 of the test
#   frames; on the default route for 0.16.
# * Every difficulty knob sits in `WorldConfig`; splits are geographically disjoint; the same seed gives
#   the same world. Notebook 01 turns these images into descriptors and measures Recall@N.

# %% [markdown]
# ## Self-check
#
# 1. A city test query has 29.31 positives on average. In the grid of a query and its nearest positives, why
#    do only a few share content with it?
#    <details><summary>Answer</summary>Positives are defined by geotag alone, Eq. (1), in all 4 headings.
#    Only those looking roughly the query's way (within 45°, framed) see the same facades.</details>
# 2. Raw-pixel cosines between images of the same heading are about 0.85 whether their cameras are 20 m or
#    500 m apart. Why, and what does the centred version show?
#    <details><summary>Answer</summary>Every image shares the same layout of sky, facades and road, which
#    dominates the raw cosine. Subtracting the mean database image removes that shared part. The centred cosine
#    falls from 0.258 (0–5 m) to 0.101 (5–15 m), then to about 0 (unrelated pairs) from 15 m on.</details>
# 3. The same-season frame 5 m ahead is closer in raw pixels than the frame's winter query for 0.910 of the
#    test frames without near content, and for 0.164 on the default route. What does that mean for a
#    training loss, and what makes the difference?
#    <details><summary>Answer</summary>Without near content the frame 5 m ahead is a near-duplicate. A loss
#    treating it as a negative pushes apart images that differ less than a query and its positive. On the
#    default route near content sweeps across the image (parallax, Eq. 3).</details>

# %% [markdown]
# ## References
#
# * S. Lowry, N. Sünderhauf, P. Newman, J. J. Leonard, D. Cox, P. Corke, M. J. Milford. *Visual Place
#   Recognition: A Survey.* IEEE Transactions on Robotics 32(1), 2016.
#   [doi:10.1109/TRO.2015.2496823](https://doi.org/10.1109/TRO.2015.2496823) (the task, "place", conditions).
# * R. Arandjelović, P. Gronat, A. Torii, T. Pajdla, J. Sivic. *NetVLAD: CNN architecture for weakly supervised
#   place recognition.* CVPR 2016. [arXiv:1511.07247](https://arxiv.org/abs/1511.07247) (Pittsburgh, positives
#   within 25 m, geographically split evaluation); code: [Relja/netvlad](https://github.com/Relja/netvlad),
#   [Nanne/pytorch-NetVlad](https://github.com/Nanne/pytorch-NetVlad).
# * A. Torii, J. Sivic, T. Pajdla, M. Okutomi. *Visual Place Recognition with Repetitive Structures.* CVPR 2013
#   (the Pittsburgh 250k street-view database the `city` preset imitates; repetitive facades = aliasing).
# * F. Warburg, S. Hauberg, M. López-Antequera, P. Gargallo, Y. Kuang, J. Civera. *Mapillary Street-Level
#   Sequences: A Dataset for Lifelong Place Recognition.* CVPR 2020 (conditions, the 25 m threshold);
#   code: [mapillary/mapillary_sls](https://github.com/mapillary/mapillary_sls).
# * N. Sünderhauf, P. Neubert, P. Protzel. *Are We There Yet? Challenging SeqSLAM on a 3000 km Journey Across
#   All Four Seasons.* ICRA 2013 Workshop on Long-Term Autonomy (the Nordland railway the `route` preset imitates).
# * G. Berton, R. Mereu, G. Trivigno, C. Masone, G. Csurka, T. Sattler, B. Caputo. *Deep Visual Geo-localization
#   Benchmark.* CVPR 2022. [arXiv:2204.03444](https://arxiv.org/abs/2204.03444); code:
#   [gmberton/deep-visual-geo-localization-benchmark](https://github.com/gmberton/deep-visual-geo-localization-benchmark)
#   (dataset formats and evaluation conventions).
