"""A fine-tune run a few epochs at a time (vpr_nb.recipe.segments) is the same bits as one run whole, for triplet,
place and CliqueMining batches; a run killed part-way goes on from the store's partial state; a partial state that
does not resume is set aside."""
import dataclasses
import warnings

import numpy as np
import pytest
import torch

from vpr_nb import engine as eng
from vpr_nb.losses import DWTripletLoss, MultiSimilarityLoss
from vpr_nb.recipe import RECIPE, FineTuneTask, Method, PlaceBatches, place_batch_labels, run_task
from vpr_nb.recipe import segments as sg
from vpr_nb.samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches
from vpr_nb.synthetic import make_dataset
from vpr_nb.task_store import STORE_ENV, TaskStore

pytestmark = pytest.mark.usefixtures("one_thread")
THREE = dataclasses.replace(RECIPE, max_epochs=3, patience=3, lr_grid=(1e-3,), search_seeds=1)


@pytest.fixture(scope="module")
def city():
    ds = make_dataset("city", seed=0, blocks=(5, 2))
    return ds.train.take_queries(np.arange(32)), ds.val


@pytest.fixture(scope="module")
def route():
    ds = make_dataset("route", seed=0)
    return ds.train, ds.val.take_queries(np.arange(40))


def _clique_method(tr):
    labels = place_batch_labels(tr)
    images = np.concatenate([tr.db_images, tr.q_images])
    utm = np.concatenate([tr.db_utm, tr.q_utm])
    clique = CliqueBatchMaker(images, utm, labels, 4, 2, images_per_place=2, same_place_threshold=6.0,
                              similar_groups=3, refresh_every=1)
    half = RandomPlaceBatches(labels, 4, 2, 2, each_place_once=False)
    return Method("mix", "gem", MultiSimilarityLoss(),
                  batches=PlaceBatches("mix", images, MixedPlaceBatches([half, clique], [0, 0]), (4, 4)))


def _same(a, b) -> bool:
    sa, sb = a.model.state_dict(), b.model.state_dict()
    ha, hb = a.history.to_dict(), b.history.to_dict()
    for h in (ha, hb):
        for e in h["epochs"]:
            e.pop("seconds")
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa) and ha == hb


def _segmented(task, epochs=1):
    item, seen = task, []
    while True:
        item = sg.run_segment(item, epochs=epochs)
        if not isinstance(item, sg.Segment):
            return item, seen
        seen.append(item.epochs)


@pytest.mark.parametrize("kind", ["triplets", "places", "cliques"])
def test_a_fine_tune_in_segments_is_the_same_bits_as_one_run_whole(kind, city, route, monkeypatch):
    monkeypatch.delenv(STORE_ENV, raising=False)
    if kind == "triplets":
        tr, va = city
        method = Method("DW-T", "netvlad", DWTripletLoss(sigma=18.0, eps=0.1))
    elif kind == "places":
        tr, va = city
        method = Method("SALAD", "salad", MultiSimilarityLoss(), batches="places")
        recipe = dataclasses.replace(THREE, places_per_batch=8, place_batches_per_epoch=4)
    else:
        tr, va = route
        method = _clique_method(tr)
    recipe = recipe if kind == "places" else THREE
    whole = run_task(FineTuneTask(method, tr, va, recipe, 0, 1e-3))
    parts, seen = _segmented(FineTuneTask(method, tr, va, recipe, 0, 1e-3))
    assert seen == [1, 2][:len(whole.history.epochs) - 1]          # it stopped after each epoch but the last
    assert _same(whole, parts) and not parts.reused


def test_a_run_killed_part_way_goes_on_from_the_stored_segment(city, tmp_path, monkeypatch):
    tr, va = city
    method = Method("DW-T", "netvlad", DWTripletLoss(sigma=18.0, eps=0.1))
    monkeypatch.delenv(STORE_ENV, raising=False)
    whole = run_task(FineTuneTask(method, tr, va, THREE, 0, 1e-3))
    monkeypatch.setenv(STORE_ENV, str(tmp_path / "store"))
    first = sg.run_segment(FineTuneTask(method, tr, va, THREE, 0, 1e-3), epochs=2)   # then the run is killed
    assert isinstance(first, sg.Segment) and first.epochs == 2
    store = TaskStore(tmp_path / "store")
    task = FineTuneTask(method, tr, va, THREE, 0, 1e-3)
    assert store.get(sg.partial_key(task))[1]["epochs"] == 2
    again = sg.run_segment(task, epochs=2)                     # a new process: the task alone, from the store
    assert not isinstance(again, sg.Segment) and len(again.history.epochs) == 3 and _same(whole, again)
    assert store.get(task.key())[1]["seconds"] >= again.seconds  # the whole task's time: both segments
    assert sg.run_segment(FineTuneTask(method, tr, va, THREE, 0, 1e-3)).reused       # now the stored result


def test_a_partial_state_that_does_not_resume_is_set_aside(city, tmp_path, monkeypatch):
    tr, va = city
    method = Method("DW-T", "netvlad", DWTripletLoss(sigma=18.0, eps=0.1))
    monkeypatch.setenv(STORE_ENV, str(tmp_path / "store"))
    other = FineTuneTask(method, tr, va, THREE, 0, 3e-4)                 # another lr: another TrainConfig
    partial = sg.run_segment(other, epochs=1)
    task = FineTuneTask(method, tr, va, THREE, 0, 1e-3)
    store = TaskStore(tmp_path / "store")
    state = torch.frombuffer(bytearray(partial.state), dtype=torch.uint8)
    store.put(sg.partial_key(task), {"last": state}, {**store.get(sg.partial_key(other))[1]})
    with pytest.warns(UserWarning, match="does not resume"):
        got = sg.run_segment(task, epochs=1)
    assert isinstance(got, sg.Segment) and got.epochs == 1               # it started again from its start
    monkeypatch.delenv(STORE_ENV)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        done, _ = _segmented(got)
    assert _same(done, run_task(FineTuneTask(method, tr, va, THREE, 0, 1e-3)))
    with pytest.raises(ValueError, match="epochs"):
        sg.run_segment(task, epochs=0)
    with pytest.raises(ValueError, match="FineTuneTask or a Segment"):
        sg.run_segment("task")


def test_a_round_runs_in_logged_segments_and_gives_what_whole_tasks_give(city, tmp_path, monkeypatch):
    tr, va = city
    monkeypatch.delenv(STORE_ENV, raising=False)
    tasks = [FineTuneTask(Method("GeM", "gem"), tr, va, THREE, s, 1e-3) for s in (0, 1)]
    log = tmp_path / "rounds.jsonl"
    monkeypatch.setenv(eng.TIMES_ENV, str(log))
    parts = sg.run_round(eng.LocalEngine(2), tasks, segment_epochs=2)
    assert len(log.read_text().splitlines()) == 2            # epochs 1-2, then epoch 3: one round each
    whole = sg.run_round(eng.LocalEngine(1), tasks, segment_epochs=None)
    assert all(_same(a, b) for a, b in zip(whole, parts))
    assert len(log.read_text().splitlines()) == 3            # and the whole tasks' one round


def test_a_sampler_with_state_carries_nothing_from_one_fine_tune_to_the_next(route, monkeypatch):
    """One method object (a CliqueMining sampler that refreshes its group descriptors) trained twice in this
    process gives the same bits twice, as two worker processes would: each source gets its own sampler."""
    monkeypatch.delenv(STORE_ENV, raising=False)
    tr, va = route
    method = _clique_method(tr)
    first = run_task(FineTuneTask(method, tr, va, THREE, 0, 1e-3))
    assert _same(first, run_task(FineTuneTask(method, tr, va, THREE, 0, 1e-3)))
