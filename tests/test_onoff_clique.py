"""Tests of CliqueMining's on/off experiment (vpr_nb.onoff.clique), its cheap parts: the two worlds, their test
worlds (>= 1,000 test queries each, counted from the cameras without rendering), the training sets' places and
clusters, the pooled near misses, input validation, and run_arms' ``extra`` scorer."""
from types import SimpleNamespace

import numpy as np
import pytest

from vpr_nb.evaluation import raw_pixel_descriptors
from vpr_nb.onoff import clique as oc
from vpr_nb.premise.clique import track_frames
from vpr_nb.premise.record import MIN_TEST_QUERIES
from vpr_nb.recipe.arms import _extra_values, pooled_recall, run_arms
from vpr_nb.results import world_fingerprints
from vpr_nb.synthetic import WORLD_KINDS, make_config, make_dataset

SMALL = dict(num_frames=60, image_size=(16, 24))   # a short route, small images: renders in well under a second


def test_the_worlds_are_notebook_07s_route_with_and_without_dense_frames():
    on, off = oc.WORLDS["on"], oc.WORLDS["off"]
    assert oc.ROUTE == {"num_facade_types": 60, "colour_variation": 0.3, "frame_spacing": 2.5, "frames_per_group": 2}
    for w in (on, off):
        assert (w["preset"], w["seed"], w["size"]) == ("route", 0, "tiny")
    assert off["overrides"] == oc.ROUTE
    assert on["overrides"] == {**oc.ROUTE, "camera_spacing": 1.0}
    assert make_config("route", **on["overrides"]).pos_radius == pytest.approx(1.01)
    assert make_config("route", **off["overrides"]).pos_radius == pytest.approx(2.525)
    assert oc.R07.max_epochs == 40 and oc.R07.patience == 8
    assert oc.EXPERIMENT["seeds"] == [0, 1, 2, 3, 4] and oc.EXPERIMENT["arms"] == list(oc.ARMS)


def test_every_world_of_the_experiment_is_fingerprinted_for_the_results_file():
    prints = world_fingerprints(oc.EXPERIMENT)
    assert set(prints) == {"worlds.on", "worlds.off", "worlds.sparse places", "worlds.on test, route seed 3",
                           "worlds.off test, route seed 3", "worlds.off test, route seed 4"}
    assert prints["worlds.on"]["fingerprint"] != prints["worlds.off"]["fingerprint"]


def _test_queries(world: dict) -> int:
    """The test split's queries of a route world, from its cameras (no rendering); every route query has a
    positive (it is tagged at its own frame), so all of them count."""
    cfg = make_config(world["preset"], world["size"], **world["overrides"])
    geo, cam, _, _ = (np.random.default_rng(s) for s in np.random.SeedSequence(world["seed"]).spawn(4))
    kind = WORLD_KINDS[world["preset"]]
    return int((kind.cameras(cfg, cam, kind.layout(cfg, geo)).q_split == 2).sum())


@pytest.mark.parametrize("world", sorted(oc.WORLDS))
def test_each_world_tests_on_at_least_1000_queries_with_the_fewest_extra_routes(world):
    worlds = oc.test_worlds(world)
    assert worlds[0] == oc.WORLDS[world]                      # its own route's test split first
    for w, seed in zip(worlds[1:], oc.TEST_SEEDS[world]):
        assert w["seed"] == seed and w["overrides"] == {**oc.WORLDS[world]["overrides"],
                                                        "split_fractions": oc.TEST_FRACTIONS}
    counts = [_test_queries(w) for w in worlds]
    assert counts == {"on": [448, 1797], "off": [179, 719, 719]}[world]
    assert sum(counts) >= MIN_TEST_QUERIES > sum(counts[:-1])


def test_world_names_are_checked():
    for fn in (oc.test_worlds, oc.world_splits):
        with pytest.raises(ValueError, match="world must be one of"):
            fn("dense")


@pytest.mark.parametrize("kwargs, match", [
    (dict(seeds=3), "seeds must be a list"), (dict(seeds=(0, 0)), "distinct"), (dict(seeds=(-1,)), "seed"),
    (dict(workers=0), "workers"), (dict(max_epochs=0), "max_epochs")])
def test_run_checks_its_arguments_before_any_work(kwargs, match):
    with pytest.raises(ValueError, match=match):
        oc.run(**kwargs)


def test_route_places_are_2_frames_and_clusters_10_frames():
    tr = make_dataset("route", 0, splits=("train",), **oc.ROUTE, **SMALL).train
    data = oc.route_training_set(tr)
    n_db = len(tr.db_images)
    assert len(data["images"]) == n_db + len(tr.q_images)
    frames = track_frames(tr)[0]                              # database image -> frame along the track
    for ids, size in ((data["groups"], 2), (data["clusters"], 10)):
        spans = [np.ptp(frames[ids[:n_db] == g]) + 1 for g in np.unique(ids[:n_db])[:-1]]
        assert set(spans) == {size}
    with pytest.raises(ValueError, match="'route' split"):
        oc.route_training_set(SimpleNamespace(config=SimpleNamespace(preset="city")))


def test_city_places_are_2_spots_and_one_quadrant():
    heading = np.array([10.0, 100.0, 10.0, 350.0, 200.0, 10.0])
    split = SimpleNamespace(config=SimpleNamespace(preset="city"), db_images=np.zeros((3, 2, 2, 3), np.uint8),
                            q_images=np.zeros((3, 2, 2, 3), np.uint8), db_utm=np.zeros((3, 2)), q_utm=np.zeros((3, 2)),
                            db_place=np.array([0, 1, 2]), q_place=np.array([1, 0, 1]),
                            db_heading=heading[:3], q_heading=heading[3:])
    data = oc.city_training_set(split)
    # spots 0 and 1 facing 10 deg share a place; 100, 350 and 200 deg and spot 2 do not
    g = data["groups"]
    assert g[0] == g[5] and len(set(g[[0, 1, 2, 3, 4]])) == 5
    assert data["clusters"][0] == data["clusters"][2] != data["clusters"][1]   # spots 0-4, one quadrant
    with pytest.raises(ValueError, match="'city' split"):
        oc.city_training_set(SimpleNamespace(config=SimpleNamespace(preset="route")))
    with pytest.raises(ValueError, match="one id per image"):
        oc.training_set(split, np.zeros(5), np.zeros(6))


def test_pooled_near_misses_pool_failures_over_splits_and_agree_with_pooled_recall():
    ds = make_dataset("route", 0, splits=("val", "test"), **oc.ROUTE, **SMALL)
    one = oc.pooled_near_misses(None, [ds.test], descriptors=raw_pixel_descriptors)
    both = oc.pooled_near_misses(None, [ds.val, ds.test], descriptors=raw_pixel_descriptors)
    assert both["R@1"] == pytest.approx(pooled_recall(None, [ds.val, ds.test], (1,),
                                                      descriptors=raw_pixel_descriptors)[1])
    assert both["queries"] == one["queries"] + len(ds.val.q_images)
    assert set(both) == {"queries", "failures", "R@1", "within 2 frames", "within 4 frames"}
    assert 0 <= both["within 2 frames"] <= both["within 4 frames"] <= 1
    with pytest.raises(ValueError, match="at least one test split"):
        oc.pooled_near_misses(None, [])
    with pytest.raises(ValueError, match="tests must be a dict"):
        oc.premise_values({"dense": [ds.test]})


def test_run_arms_extra_adds_per_seed_lists_and_refuses_its_own_keys():
    vals = _extra_values(lambda m, tests: {"share": m / 3}, [1, 2], [], 4, {"R@1": []})
    assert vals == {"share": [0.3333, 0.6667]}
    with pytest.raises(ValueError, match="run_arms' own"):
        _extra_values(lambda m, tests: {"R@1": 0.5}, [1], [], 4, {"R@1": []})
    with pytest.raises(ValueError, match="same keys"):
        _extra_values(lambda m, tests: {f"k{m}": 0.5}, [1, 2], [], 4, {})
    with pytest.raises(ValueError, match="extra must be a function"):
        run_arms({"on": {}}, None, [], (0,), extra="near misses")


@pytest.mark.slow
@pytest.mark.parametrize("world", sorted(oc.WORLDS))
def test_clique_places_cover_the_route_like_random_places(world):
    """The clique search scans the drawn groups in a seeded order, so in both worlds (the premise-off one is
    the main experiment's route) clique places are spread like random ones: the share in the route's first
    quarter within 0.05 of random places' (scanned by index it was 0.94), every cluster used."""
    from vpr_nb.onoff import clique_probes as cp

    ds = oc.world_splits(world)
    route = oc.route_training_set(ds.train)
    dense = cp.dense_makers(route, float(ds.train.pos_radius), oc.group_descriptors(oc.frozen_model(), route))
    cov = {name: cp.route_coverage(np.concatenate([dense[name](None, e, np.random.default_rng(e))
                                                   for e in range(cp.PROFILE_EPOCHS)]), route["clusters"])
           for name in (cp.RANDOM, cp.CLIQUES)}
    first = "places in the first quarter"
    assert abs(cov[cp.CLIQUES][first] - cov[cp.RANDOM][first]) < 0.05, cov
    assert cov[cp.CLIQUES]["clusters used"] > 0.95, cov
