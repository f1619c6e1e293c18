"""Tests of SALAD's on/off experiment (vpr_nb.onoff.salad), its cheap parts: the worlds (off = today's), their
fingerprints, the recipe switch that starts SALAD's score head from NetVLAD's k-means, the level start of the two
arms, the premise quantity and the dustbin measurement on small inputs, and input validation."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from vpr_nb.models import SmallCNN, build_model
from vpr_nb.onoff import salad as os_
from vpr_nb.recipe import RECIPE, VALIDATION_WORLD, Recipe, build_start
from vpr_nb.recipe.arms import CITY_TEST_WORLDS
from vpr_nb.results import world_fingerprints
from vpr_nb.synthetic import LABEL_NAMES, make_config, make_dataset

pytestmark = pytest.mark.usefixtures("one_thread")   # tests/conftest.py
OBJ, GROUND, SKYLINE, SKY, OCC, DIS = range(6)


def test_the_off_world_is_todays_and_the_on_world_only_adds_distractors():
    off, on = os_.world_specs("off"), os_.world_specs("on")
    assert off == {"train": {"preset": "city", "seed": 0, "size": "tiny"}, "validation": VALIDATION_WORLD,
                   "test": list(CITY_TEST_WORLDS)}
    assert on["train"] == {**off["train"], "overrides": {"distractor_rate": os_.DISTRACTOR_RATE}}
    for a, b in [(on["validation"], off["validation"]), *zip(on["test"], off["test"])]:
        assert {k: v for k, v in a.items() if k != "overrides"} == {k: v for k, v in b.items() if k != "overrides"}
        assert a["overrides"] == {**b["overrides"], "distractor_rate": os_.DISTRACTOR_RATE}
    assert os_.RATES == {"on": os_.DISTRACTOR_RATE, "off": 0.0} and os_.DISTRACTOR_RATE > 0
    with pytest.raises(ValueError, match="world must be one of"):
        os_.world_specs("half")


def test_every_world_of_the_experiment_is_fingerprinted_and_off_matches_today():
    prints = world_fingerprints(os_.EXPERIMENT)
    roles = ["train", "validation", "test, city seed 2", "test, city seed 3"]
    assert set(prints) == {f"worlds.{w} {r}" for w in ("on", "off") for r in roles}
    today = [make_config("city").fingerprint(), make_config("city", **VALIDATION_WORLD["overrides"]).fingerprint(),
             *(make_config("city", **t["overrides"]).fingerprint() for t in CITY_TEST_WORLDS)]
    assert [prints[f"worlds.off {r}"]["fingerprint"] for r in roles] == today
    assert all(prints[f"worlds.on {r}"]["fingerprint"] != prints[f"worlds.off {r}"]["fingerprint"] for r in roles)
    assert os_.EXPERIMENT["seeds"] == [0, 1, 2, 3, 4] and os_.EXPERIMENT["recipe"]["search_seeds"] == 1
    assert [a["aggregator_kwargs"] for a in os_.EXPERIMENT["arms"]] == [{"assignment": "sinkhorn"},
                                                                       {"assignment": "softmax"}]


def test_the_kmeans_switch_is_off_by_default_and_out_of_todays_recipe_dict():
    assert not RECIPE.salad_kmeans_scores and "salad_kmeans_scores" not in RECIPE.to_dict()
    assert os_.RECIPE_ARMS.to_dict()["salad_kmeans_scores"] is True
    assert dataclasses.replace(os_.RECIPE_ARMS, salad_kmeans_scores=False).to_dict() == \
        dataclasses.replace(RECIPE, search_seeds=1).to_dict()
    with pytest.raises(ValueError, match="salad_kmeans_scores"):
        Recipe(salad_kmeans_scores=1)


@pytest.fixture(scope="module")
def train_split():
    return make_dataset("city", seed=0, splits=("train",)).train


def test_both_arms_start_from_the_same_weights_with_netvlads_kmeans_scores(train_split):
    sink, soft = (build_start(m, train_split, os_.RECIPE_ARMS, seed=0) for m in os_.methods())
    assert (sink.aggregator.assignment, soft.aggregator.assignment) == ("sinkhorn", "softmax")
    a, b = sink.state_dict(), soft.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    netvlad = build_start(dataclasses.replace(os_.methods()[0], name="NetVLAD", aggregator="netvlad",
                                              aggregator_kwargs={}), train_split, os_.RECIPE_ARMS, seed=0)
    m = sink.aggregator.num_clusters
    rows = sink.aggregator.score[0].weight[:m, :, 0, 0]                     # alpha * the unit centroids
    cents = netvlad.aggregator.centroids
    cos = torch.nn.functional.cosine_similarity(rows, cents, dim=1)
    assert torch.allclose(cos, torch.ones(m), atol=1e-4)                     # the same k-means as NetVLAD's start
    plain = build_start(os_.methods()[0], train_split, RECIPE, seed=0)      # the switch off: the recipe's start
    assert not torch.allclose(plain.aggregator.score[0].weight[:m], sink.aggregator.score[0].weight[:m])


def _fake_split(n, h=8, w=12, seed=0, distractor_rows=0):
    rng = np.random.default_rng(seed)
    lab = np.full((n, h, w), OBJ, np.uint8)
    lab[:, :h // 4] = SKY                                               # the top quarter, the bottom quarter and
    lab[:, -(h // 4):] = GROUND                                        # a block under the sky: whole cells of
    lab[:, h // 4:h // 4 + distractor_rows, :w // 4] = DIS             # 4 x 4 pixels at h = 16, w = 24
    img = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    return SimpleNamespace(q_images=img, q_labels=lab, db_images=img, db_labels=lab)


def test_premise_values_count_distractor_pixels_of_database_and_queries():
    tests = [_fake_split(2, distractor_rows=2), _fake_split(2, distractor_rows=0)]
    v = os_.premise_values(tests)
    assert v["value"] == pytest.approx(24 / 768, abs=1e-4) and v["distractor share, queries"] == v["value"]
    assert v["distractor share, database"] == v["value"]
    assert sum(v["label shares"].values()) == pytest.approx(1.0, abs=1e-3) and list(v["label shares"]) == list(LABEL_NAMES)
    with pytest.raises(ValueError, match="labels"):
        os_.premise_values([SimpleNamespace(q_labels=None, db_labels=None)])
    with pytest.raises(ValueError, match="labels"):
        os_.labelled_sample([SimpleNamespace(q_images=np.zeros((1, 8, 12, 3), np.uint8), q_labels=None)])


def _small_salad(assignment):
    torch.manual_seed(0)
    return build_model(SmallCNN(width=8, out_channels=16), "salad", num_clusters=4, cluster_dim=4, token_dim=4,
                       hidden_dim=8, assignment=assignment)


def test_dustbin_values_measure_sinkhorn_and_skip_softmax():
    split = _fake_split(3, h=16, w=24, distractor_rows=4)
    images, labels = os_.labelled_sample([split], n=2)
    assert len(images) == len(labels) == 2
    assert os_.dustbin_values(_small_salad("softmax"), images, labels) == {}
    v = os_.dustbin_values(_small_salad("sinkhorn"), images, labels)
    assert set(v) == {os_.AUC, os_.MEAN, *(os_.SHARE.format(n) for n in ("object", "ground", "sky", "distractor"))}
    assert 0 <= v[os_.AUC] <= 1 and all(0 <= x <= 1 for x in v.values())


@pytest.mark.parametrize("kwargs, match", [
    ({"seeds": ()}, "distinct training seeds"), ({"seeds": (0, 0)}, "distinct training seeds"),
    ({"seeds": 3}, "list of training seeds"), ({"seeds": (-1,)}, "seed"),
    ({"workers": 0}, "workers"), ({"max_epochs": 0}, "max_epochs")])
def test_run_refuses_bad_inputs_before_rendering(kwargs, match):
    with pytest.raises(ValueError, match=match):
        os_.run(**kwargs)
