"""The course fine-tuning recipe (vpr_nb.recipe) and its hooks in vpr_nb.training (epoch-0 candidate,
early stopping)."""
import dataclasses

import numpy as np
import pytest
import torch

from vpr_nb.aggregation import AGGREGATOR_NAMES, SALAD
from vpr_nb.evaluation import images_to_tensor
from vpr_nb.losses import DWTripletLoss, MultiSimilarityLoss, TripletLoss
from vpr_nb.models import build_model, init_salad
from vpr_nb.pretrain import course_backbone
from vpr_nb.recipe import (RECIPE, Method, Recipe, build_start, fine_tune, lr_search, make_source, place_batch_labels,
                           search_methods)
from vpr_nb.recipe.search import ladder_step
from vpr_nb.recipe.task import _cache as task_cache
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import History, PlaceBatchSource, TrainConfig, TripletSource, train

pytestmark = pytest.mark.usefixtures("one_thread")
FAST = dataclasses.replace(RECIPE, max_epochs=2, patience=2)


@pytest.fixture(scope="module")
def world():
    ds = make_dataset("city", seed=0, blocks=(5, 2))
    tr = ds.train
    small = tr.take_queries(np.arange(32))            # 2 steps of 16 queries an epoch
    return small, ds.val


class HurtingSource:
    """Triplet batches whose loss is the negated triplet loss: every step makes retrieval worse."""

    def __init__(self, split):
        self.inner = TripletSource(split, TripletLoss(), max_heading_diff=45.0)

    def state_dict(self):
        return self.inner.state_dict()

    def load_state_dict(self, state):
        self.inner.load_state_dict(state)

    def steps(self, model, rng, shard=(0, 1), device=None):
        for loss in self.inner.steps(model, rng, shard, device):
            yield -loss


def test_recipe_defaults_are_the_measured_ones():
    r = Recipe()
    assert (r.optimizer, r.lr, r.weight_decay, r.step_size, r.gamma) == ("adam", 1e-3, 1e-3, 5, 0.5)      # notebook 04
    assert (r.batch_size, r.margin, r.num_negatives, r.num_candidates, r.max_heading_diff) == (16, 0.1, 5, 300, 45.0)
    assert r.trainable_blocks == 1 and set(r.after_relu) == set(AGGREGATOR_NAMES)   # notebook 04: the output
    assert r.salad_standardise and (r.salad_clusters, r.salad_cluster_dim, r.salad_token_dim) == (16, 32, 64)
    assert r.initial_candidate and r.lr in r.lr_grid and r.min_val_queries == 500
    cfg = r.train_config(3e-4, seed=2)
    assert isinstance(cfg, TrainConfig) and cfg.initial_candidate and cfg.patience == r.patience
    assert (cfg.epochs, cfg.lr, cfg.seed, cfg.optimizer) == (r.max_epochs, 3e-4, 2, "adam")
    assert r.to_dict()["lr_grid"] == r.lr_grid


def test_recipe_and_method_refuse_bad_settings():
    with pytest.raises(ValueError, match="optimizer"):
        Recipe(optimizer="lbfgs")
    with pytest.raises(ValueError, match="unknown aggregators"):
        Recipe(after_relu=("vlad",))
    with pytest.raises(ValueError, match="at least one"):
        Recipe(lr_grid=())
    with pytest.raises(ValueError, match="lr_grid entry"):
        Recipe(lr_grid=(1e-3, -1.0))
    with pytest.raises(ValueError, match="triplet-family"):
        Method("x", "gem", loss=MultiSimilarityLoss())
    with pytest.raises(ValueError, match="place batches"):
        Method("x", "gem", loss=TripletLoss(), batches="places")
    with pytest.raises(ValueError, match="unknown aggregator"):
        Method("x", "vlad")
    with pytest.raises(ValueError, match="recipe must be"):
        fine_tune(Method("x"), None, None, recipe={"lr": 1e-3}, lr=1e-3)


def test_method_grid_adds_the_paper_lr_and_describes_itself():
    m = Method("DW-T", "netvlad", loss=DWTripletLoss(), paper_lr=2e-4)
    assert m.lr_grid(RECIPE) == (2e-4, 3e-4, 1e-3, 3e-3)
    assert Method("T").lr_grid(RECIPE) == RECIPE.lr_grid
    d = m.to_dict()
    assert d["loss"]["class"] == "DWTripletLoss" and d["loss"]["sigma"] == 800.0 and d["paper_lr"] == 2e-4


def test_start_models_read_the_backbone_where_the_recipe_says(world):
    tr, _ = world
    for agg in ("gem", "netvlad", "salad", "max", "mean"):
        for recipe, relu in ((RECIPE, True), (dataclasses.replace(RECIPE, after_relu=()), False)):
            model = build_start(Method(agg, agg), tr, recipe, seed=0)
            assert isinstance(model.backbone.features[-1], torch.nn.ReLU) == relu, agg
            assert model.backbone.num_frozen == 9                 # the last block (1x1 projection) trains
    netvlad = build_start(Method("n", "netvlad"), tr, RECIPE, seed=0)
    assert netvlad.aggregator.alpha > 0 and netvlad.out_dim == 16 * 128        # k-means initialised, K = 16
    # GeM gives the same descriptor before and after the ReLU (it clamps at eps)
    x = images_to_tensor(tr.db_images[:4])
    with torch.no_grad():
        a = build_model(course_backbone(final_relu=True), "gem")(x)
        b = build_model(course_backbone(final_relu=False), "gem")(x)
    assert torch.allclose(a, b, atol=1e-6)


def test_salad_standardised_inputs_fold_exactly(world):
    tr, _ = world
    torch.manual_seed(0)
    plain = build_model(course_backbone(trainable_blocks=1, final_relu=False), "salad", num_clusters=8,
                        cluster_dim=8, token_dim=8, hidden_dim=16)
    folded = build_model(course_backbone(trainable_blocks=1, final_relu=False), "salad", num_clusters=8,
                         cluster_dim=8, token_dim=8, hidden_dim=16)
    folded.load_state_dict(plain.state_dict())
    mean, std = init_salad(folded, tr.db_images)
    with torch.no_grad():
        x = plain.backbone(images_to_tensor(tr.db_images[:4]))
        z = (x - mean[None, :, None, None]) / std[None, :, None, None]
        for head in ("score", "cluster_features"):
            assert torch.allclose(getattr(folded.aggregator, head)[0](x), getattr(plain.aggregator, head)[0](z),
                                  atol=1e-4)
    assert torch.equal(folded.aggregator.token_features[0].weight, plain.aggregator.token_features[0].weight)
    layer = SALAD(num_channels=4, num_clusters=2, cluster_dim=2, token_dim=2, hidden_dim=4)
    with pytest.raises(ValueError, match="4 finite values"):
        layer.standardise_inputs(torch.zeros(3), torch.ones(3))
    with pytest.raises(ValueError, match="positive"):
        layer.standardise_inputs(torch.zeros(4), torch.zeros(4))
    with pytest.raises(ValueError, match="SALAD"):
        init_salad(build_model(course_backbone(), "gem"), tr.db_images)


def test_epoch_zero_candidate_wins_when_training_only_hurts(world):
    tr, va = world
    run = fine_tune(Method("GeM", "gem"), tr, va, FAST, seed=0, lr=1.0)      # Adam at lr 1: every epoch is worse
    h = run.history
    assert h.initial is not None and all(r < h.initial["val"][1] for r in h.recalls(1))
    assert h.initial_won and run.best_epoch == 0 and h.best_recall == h.initial["val"][1]
    for (k, a), b in zip(run.model.state_dict().items(), run.start.state_dict().values()):
        assert torch.equal(a, b), k                                         # the model ends as it started
    assert run.model.backbone.frozen_cache is None and run.start.backbone.frozen_cache is None
    back = History.from_dict(h.to_dict())
    assert back.initial == h.initial and back.initial_won and back.stopped_early == h.stopped_early


def test_without_the_candidate_the_same_run_reports_a_trained_epoch(world):
    tr, va = world
    run = fine_tune(Method("GeM", "gem"), tr, va, dataclasses.replace(FAST, initial_candidate=False), seed=0, lr=1.0)
    assert run.history.initial is None and not run.history.initial_won and run.best_epoch >= 1


def test_early_stopping_stops_after_patience_epochs_without_improvement(world, tmp_path):
    tr, va = world
    model = build_model(course_backbone(trainable_blocks=1, final_relu=False), "gem")
    cfg = TrainConfig(epochs=6, optimizer="adam", lr=1e-3, seed=0, ns=(1,), initial_candidate=True, patience=2)
    hist = train(model, HurtingSource(tr), va, cfg, checkpoint_dir=tmp_path, progress=False)
    assert hist.stopped_early and len(hist.epochs) == 2 and hist.initial_won
    assert torch.load(tmp_path / "best.pt", weights_only=True)["epoch"] == -1       # the start, written up front
    again = train(model, HurtingSource(tr), va, cfg, checkpoint_dir=tmp_path, progress=False)   # resume: nothing left
    assert len(again.epochs) == 2 and again.stopped_early
    with pytest.raises(ValueError, match="patience"):
        TrainConfig(patience=0)


def test_lr_search_refuses_a_small_validation_split_on_one_seed(world):
    tr, va = world
    assert len(va.q_images) < RECIPE.min_val_queries
    with pytest.raises(ValueError, match="too few to choose a learning rate"):
        lr_search(Method("GeM", "gem"), tr, va, FAST, seeds=(0,))
    with pytest.raises(ValueError, match="too few to choose a learning rate"):
        fine_tune(Method("GeM", "gem"), tr, va, FAST, seed=0)
    with pytest.raises(ValueError, match="distinct"):
        lr_search(Method("GeM", "gem"), tr, va, FAST, seeds=(1, 1, 1))


@pytest.mark.slow
def test_lr_search_picks_the_best_grid_point_on_validation(world):
    tr, va = world
    recipe = dataclasses.replace(FAST, max_epochs=1, lr_grid=(1e-3, 1.0), search_seeds=2, lr_extend=0)
    cache = task_cache(recipe)                        # this process's frozen-block cache, shared by every task
    before = cache.stats()
    search = lr_search(Method("GeM", "gem", paper_lr=1e-4), tr, va, recipe, seeds=(0, 1, 2))
    assert search.grid == (1e-4, 1e-3, 1.0)
    assert search.search_seeds == (0, 1) and all(len(v) == 2 for v in search.val_recall.values())
    means = {lr: np.mean(v) for lr, v in search.val_recall.items()}
    assert search.lr == max(search.grid, key=lambda lr: (means[lr], -lr))
    assert set(search.runs) == {0, 1, 2} and all(r.lr == search.lr and r.search is search
                                                  for r in search.runs.values())
    assert all(search.runs[s].history.best_recall == v for s, v in zip((0, 1), search.val_recall[search.lr]))
    # seed 2 took no part in the choice: it ran at the chosen lr only, as the same fine-tune on its own would
    assert set(search.histories[search.lr]) == {0, 1, 2}
    assert all(set(search.histories[lr]) == {0, 1} for lr in search.grid if lr != search.lr)
    alone = fine_tune(Method("GeM", "gem", paper_lr=1e-4), tr, va, recipe, seed=2, lr=search.lr)
    for (k, x), (_, y) in zip(alone.model.state_dict().items(), search.runs[2].model.state_dict().items()):
        assert torch.equal(x, y), k
    assert cache.resets == before["resets"] and cache.hits - before["hits"] > cache.misses - before["misses"]
    assert "<- chosen" in search.table() and "mean over seeds [0, 1]; grid" in search.table()
    # a validation split of min_val_queries queries lets one seed choose
    one = fine_tune(Method("GeM", "gem"), tr, va, dataclasses.replace(recipe, min_val_queries=len(va.q_images)), 0)
    assert one.lr in recipe.lr_grid and one.search.seeds == (0,)


def test_ladder_steps_of_the_lr_grid():
    assert ladder_step(3e-4, up=True) == 1e-3 and ladder_step(1e-3, up=True) == 3e-3
    assert ladder_step(1e-4, up=False) == 3e-5 and ladder_step(3e-5, up=False) == 1e-5
    assert ladder_step(2e-4, up=True) == 3e-4 and ladder_step(2e-4, up=False) == 1e-4
    with pytest.raises(ValueError, match="lr"):
        ladder_step(0.0, up=True)


@pytest.mark.slow
def test_halving_stops_the_worse_half_and_the_grid_grows_until_the_choice_is_interior(world):
    tr, va = world
    recipe = dataclasses.replace(FAST, max_epochs=3, patience=3, lr_grid=(1e-4, 1e-3, 1e-2), search_seeds=1,
                                 halving_epochs=1, lr_extend=2, min_val_queries=0)
    search = lr_search(Method("GeM", "gem"), tr, va, recipe, seeds=(0,))
    assert sum(lr in recipe.lr_grid for lr in search.halved) == 1                 # ceil(3 / 2) = 2 train on
    assert set(search.halved.values()) == {1} and set(search.halved) <= set(search.grid)
    for lr, epochs in search.halved.items():
        assert len(search.histories[lr][0].epochs) == epochs and lr != search.lr
    assert all(len(search.histories[lr][0].epochs) == 3 for lr in search.grid if lr not in search.halved)
    assert set(search.grid) == set(recipe.lr_grid) | set(search.extended)
    assert search.interior or len(search.extended) == recipe.lr_extend
    # the chosen run was stopped after the rung and continued: the same weights as one uninterrupted run
    alone = fine_tune(Method("GeM", "gem"), tr, va, recipe, seed=0, lr=search.lr)
    assert alone.history.best_recall == search.runs[0].history.best_recall
    for (k, x), (_, y) in zip(alone.model.state_dict().items(), search.runs[0].model.state_dict().items()):
        assert torch.equal(x, y), k
    assert "halving" in search.table() or search.lr in search.extended


def test_place_labels_keep_a_route_place_whole():
    route = make_dataset("route", seed=0, num_frames=120).train
    labels = place_batch_labels(route, RECIPE)
    places = np.concatenate([route.db_place, route.q_place])
    assert np.array_equal(labels, places)                    # headings straddle 0/360: no quadrant split
    city = make_dataset("city", seed=0, blocks=(3, 2)).train
    assert len(place_batch_labels(city, RECIPE)) == len(city.db_images) + len(city.q_images)


def test_place_batches_and_custom_sources(world):
    tr, _ = world
    src = make_source(Method("MS", "gem", batches="places"), tr, dataclasses.replace(RECIPE, places_per_batch=8))
    assert isinstance(src, PlaceBatchSource) and isinstance(src.loss, MultiSimilarityLoss)
    assert make_source(Method("T", "gem"), tr, RECIPE).batch_size == RECIPE.batch_size
    made = make_source(Method("custom", "gem", batches=lambda split, recipe, loss: HurtingSource(split)), tr)
    assert isinstance(made, HurtingSource)


def test_search_methods_gives_the_same_runs_in_one_process_and_in_two(world):
    tr, va = world
    recipe = dataclasses.replace(FAST, max_epochs=1, lr_grid=(1e-3,), search_seeds=1)
    sgd = dataclasses.replace(recipe, optimizer="sgd")
    methods = [Method("GeM", "gem"), (Method("GeM, SGD", "gem"), sgd)]
    one = search_methods(methods, tr, va, recipe, seeds=(0,))
    two = search_methods(methods, tr, va, recipe, seeds=(0,), workers=2)
    assert list(one) == list(two) == ["GeM", "GeM, SGD"]
    for name in one:
        a, b = one[name].runs[0], two[name].runs[0]
        assert a.history.best_recall == b.history.best_recall
        for (k, x), (_, y) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
            assert torch.equal(x, y), (name, k)
    # the SGD row really ran SGD: its weights differ from the Adam row's after the same steps
    adam, sgd_run = one["GeM"].runs[0].history, one["GeM, SGD"].runs[0].history
    assert adam.epochs[-1]["loss"] != sgd_run.epochs[-1]["loss"]
    fixed = search_methods([Method("GeM", "gem")], tr, va, recipe, seeds=(0, 1), lr=3e-4)
    assert fixed["GeM"].grid == (3e-4,) and set(fixed["GeM"].runs) == {0, 1}


def test_search_methods_refuses_bad_arguments(world):
    tr, va = world
    with pytest.raises(ValueError, match="distinct names"):
        search_methods([Method("A", "gem"), Method("A", "max")], tr, va)
    with pytest.raises(ValueError, match="distinct names"):
        search_methods([], tr, va)
    with pytest.raises(ValueError, match="workers"):
        search_methods([Method("A", "gem")], tr, va, workers=0)
    with pytest.raises(ValueError, match="recipe"):
        search_methods([(Method("A", "gem"), "adam")], tr, va)


def test_place_batches_of_package_samplers_train_in_worker_processes(world):
    from vpr_nb.recipe import PlaceBatches
    from vpr_nb.samplers import MixedPlaceBatches, RandomPlaceBatches

    tr, va = world
    labels = place_batch_labels(tr)
    images = np.concatenate([tr.db_images, tr.q_images])
    half = RandomPlaceBatches(labels, 4, 4, 2, each_place_once=False)
    make = MixedPlaceBatches([half, half], [0, 0])
    methods = [Method(name, "gem", MultiSimilarityLoss(), batches=PlaceBatches(name, images, make, (4, 4)))
               for name in ("two halves", "two halves again")]
    assert methods[0].to_dict()["batches"] == "two halves"
    recipe = dataclasses.replace(FAST, max_epochs=1)
    one = search_methods(methods, tr, va, recipe, seeds=(0,), lr=1e-3)
    two = search_methods(methods, tr, va, recipe, seeds=(0,), lr=1e-3, workers=2)
    for name in one:
        assert one[name].runs[0].history.epochs[0]["loss"] == two[name].runs[0].history.epochs[0]["loss"]


def test_validation_world_is_a_large_separate_split():
    from vpr_nb.recipe import VALIDATION_WORLD, validation_split

    va = validation_split()
    assert len(va.q_images) >= RECIPE.min_val_queries == 500
    assert VALIDATION_WORLD["seed"] not in (0, 97, 98) and VALIDATION_WORLD["seed"] < 100   # test, selection, pretraining
    with pytest.raises(ValueError, match="'preset' and 'seed'"):
        validation_split({"preset": "city"})
