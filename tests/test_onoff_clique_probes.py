"""Tests of notebook 07's probes (vpr_nb.onoff.clique_probes): the batch profile on known geometry, each probe's
dense half changes what it says it changes (on a short 1 m route), input validation, and the stored probes file
against the premise file it pairs with and the notebook that shows it."""
import json
from pathlib import Path

import nbformat
import numpy as np
import pytest

from vpr_nb.onoff import clique as oc
from vpr_nb.onoff import clique_probes as cp
from vpr_nb.results import world_fingerprints
from vpr_nb.synthetic import make_dataset
from vpr_nb.verdict import family_note, verdicts

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "notebooks" / "results"
SMALL = dict(num_frames=160, image_size=(16, 24))


def test_batch_profile_on_known_geometry():
    utm = np.array([[0.0, 0], [1, 0], [3, 0], [4, 0], [10, 0], [12, 0]])
    batches = np.array([[[0, 1], [2, 3], [4, 5]]])            # one batch: places 1 m, 1 m and 2 m wide
    p = cp.batch_profile(batches, utm, pos_radius=1.01)
    # nearest other-place image: 3, 2, 2, 3, 6, 8 m -> median 3; within 2.5 m: 2 of 6; spread 12 m; 1 of 3 pairs > 1.01
    assert p == {"nearest other-place image (m)": 3.0, "images with a negative within 2.5 m": 0.333,
                 "batch spread (m)": 12.0, "place pairs beyond the positive radius": 0.333}
    with pytest.raises(ValueError, match="batches must be"):
        cp.batch_profile(np.zeros((2, 3), int), utm, 1.0)


def test_route_coverage_and_reordered_batches():
    clusters = np.repeat(np.arange(8), 2)                      # 16 images, 8 clusters along the track
    batches = np.array([[[0, 1], [2, 3]], [[4, 5], [14, 15]]])
    assert cp.route_coverage(batches, clusters) == {"clusters used": 0.5, "places in the first quarter": 0.5}
    order = np.arange(16)[::-1]
    back = cp.Reordered(lambda model, epoch, rng: np.array([[[0, 1]]]), order)(None, 0, None)
    np.testing.assert_array_equal(back, [[[15, 14]]])
    with pytest.raises(ValueError, match="batches must be"):
        cp.route_coverage(np.zeros(3, int), clusters)


@pytest.fixture(scope="module")
def dense():
    w = oc.WORLDS["on"]
    tr = make_dataset(w["preset"], w["seed"], splits=("train",), **w["overrides"], **SMALL).train
    route = oc.route_training_set(tr)
    rng = np.random.default_rng(0)
    gdesc = rng.normal(size=(route["clusters"].max() + 1, 8)).astype(np.float32)
    makers = cp.dense_makers(route, float(tr.pos_radius), gdesc)
    batches = {name: np.asarray(make(None, 0, np.random.default_rng(1))) for name, make in makers.items()}
    return route, float(tr.pos_radius), batches, makers


def test_each_probe_changes_its_one_thing(dense):
    route, radius, batches, makers = dense
    assert set(batches) == {cp.RANDOM, cp.CLIQUES, *cp.PROBES}
    assert all(b.shape == (oc.NB, oc.HALF, 4) for b in batches.values())
    prof = {n: cp.batch_profile(b, route["utm"], radius) for n, b in batches.items()}
    near = "images with a negative within 2.5 m"
    # at 1 m frames the world's threshold (1.01 m) leaves negatives 2 frames away; 2.5 m leaves none that close
    assert prof[cp.CLIQUES][near] > 0.3 and prof["cliques, τ 2.5 m"][near] == 0
    assert prof[cp.CLIQUES]["place pairs beyond the positive radius"] == 0
    assert prof["cliques, τ 2.5 m"]["place pairs beyond the positive radius"] > 0   # the side effect it names
    # the mix: its first 4 places are cliques, its last 4 random route places
    mix = batches["4 cliques + 4 random"]
    assert cp.batch_profile(mix[:, :4], route["utm"], radius)["place pairs beyond the positive radius"] == 0
    # the search scans the drawn groups in a seeded order, so clique places cover the route as random places do
    # (scanned by index, 0.94 of them sat in its first quarter); a shuffled image order spreads them too
    first = "places in the first quarter"
    cov = {n: cp.route_coverage(b, route["clusters"])[first] for n, b in batches.items()}
    assert all(abs(cov[n] - cov[cp.RANDOM]) < 0.1 for n in cov), cov
    assert cov["cliques, random image order"] < 0.45
    assert cp.batch_profile(batches["cliques, random image order"], route["utm"], radius)[
        "place pairs beyond the positive radius"] == 0
    # uniform Eq. (1): the batches do not depend on the descriptors it was given
    other = cp.dense_makers(route, radius, np.random.default_rng(5).normal(size=(route["clusters"].max() + 1, 8)))
    again = np.asarray(other["cliques, Eq. (1) uniform"](None, 0, np.random.default_rng(1)))
    np.testing.assert_array_equal(again, batches["cliques, Eq. (1) uniform"])
    assert not np.array_equal(np.asarray(other[cp.CLIQUES](None, 0, np.random.default_rng(1))), batches[cp.CLIQUES])


def test_the_experiment_names_its_worlds_and_pairs_with_the_premise_arms():
    prints = world_fingerprints(cp.EXPERIMENT)
    assert set(prints) == {"worlds.on", "worlds.sparse places", "worlds.test, route seed 3"}
    assert cp.EXPERIMENT["worlds"]["on"] == oc.WORLDS["on"] and cp.EXPERIMENT["seeds"] == list(oc.SEEDS)
    assert cp.EXPERIMENT["paired with"] == [oc.ARMS[1], oc.ARMS[2]]


@pytest.mark.parametrize("baseline, match", [
    (None, "baseline must be"), ({oc.ARMS[1]: {"R@1": [0.5] * 5}}, "baseline must be"),
    ({oc.ARMS[1]: {"R@1": [0.5] * 5}, oc.ARMS[2]: {"R@1": [0.5] * 4}}, "one R@1 per seed")])
def test_run_checks_the_baseline_before_any_work(baseline, match):
    with pytest.raises(ValueError, match=match):
        cp.run(baseline)
    with pytest.raises(ValueError, match="seeds must be a list"):
        cp.run({}, seeds=3)


def test_the_stored_probes_pair_with_the_stored_premise_arms_and_the_notebook_prints_each_gap():
    path = RESULTS / "07_probes.json"
    if not path.exists():
        pytest.skip("07_probes.json is not committed yet")
    probes = json.loads(path.read_text(encoding="utf-8"))["results"]
    premise = json.loads((RESULTS / "07_premise.json").read_text(encoding="utf-8"))["results"]["arms"][cp.WORLD]
    assert probes["paired with"] == {a: premise[a]["R@1"] for a in (cp.RANDOM, cp.CLIQUES)}
    assert set(probes["arms"]) == set(cp.PROBES)
    for p, arm in probes["arms"].items():
        assert len(arm["R@1"]) == len(oc.SEEDS) and arm["test queries"] >= 1000
        for a in (cp.RANDOM, cp.CLIQUES):
            want = [round(x - y, 4) for x, y in zip(arm["R@1"], premise[a]["R@1"])]
            assert probes["gaps"][f"{p} − {a}"] == pytest.approx(want, abs=1e-9)
    nb = nbformat.read(ROOT / "notebooks" / "07_clique_mining.ipynb", as_version=4)
    out = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    # every gap's verdict, recomputed from the stored per-seed differences (one Holm family: the probes' table)
    family = verdicts(probes["gaps"])
    lines = [f"{name}: {v.text()}" for name, v in family.items()] + [family_note(family)]
    missing = [line for line in lines if line not in out]
    assert not missing, f"the stored notebook does not print: {missing}"


def test_the_stored_batch_profiles_come_back_from_todays_code():
    """The committed probes file's profile of each dense half is what today's samplers mine (the probes' batches
    have not moved since the file was made)."""
    path = RESULTS / "07_probes.json"
    if not path.exists():
        pytest.skip("07_probes.json is not committed yet")
    stored = json.loads(path.read_text(encoding="utf-8"))["results"]["batches"]
    ds = oc.world_splits(cp.WORLD)
    route = oc.route_training_set(ds.train)
    dense = cp.dense_makers(route, float(ds.train.pos_radius), oc.group_descriptors(oc.frozen_model(), route))
    assert set(dense) == set(stored)
    for name, make in dense.items():
        b = np.concatenate([make(None, e, np.random.default_rng(e)) for e in range(cp.PROFILE_EPOCHS)])
        got = {**cp.batch_profile(b, route["utm"], float(ds.train.pos_radius)), **cp.route_coverage(b, route["clusters"])}
        assert got == stored[name], name
