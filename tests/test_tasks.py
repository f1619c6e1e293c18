"""Tasks, their store and the engines that run them (vpr_nb.recipe.task, vpr_nb.task_store, vpr_nb.engine): a stored
result is reused only under the whole key, a broken entry is never read, and the results are the same bits on 1
and 2 local workers and on a 2-worker Dask cluster."""
import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import shutil
import warnings

import numpy as np
import pytest
import torch

from vpr_nb import engine as eng
from vpr_nb.losses import DWTripletLoss
from vpr_nb.recipe import RECIPE, FineTuneTask, Method, drive, run_task, search_methods, search_rounds
from vpr_nb.recipe import task as task_mod
from vpr_nb.synthetic import make_dataset
from vpr_nb.task_store import STORE_ENV, TaskStore, key_digest, store_from_env

pytestmark = pytest.mark.usefixtures("one_thread")
ONE = dataclasses.replace(RECIPE, max_epochs=1, patience=1, lr_grid=(1e-3,), search_seeds=1)
KEY = "ab" + "0" * 62


@pytest.fixture(scope="module")
def world():
    ds = make_dataset("city", seed=0, blocks=(5, 2))
    return ds.train.take_queries(np.arange(32)), ds.val


def same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


# --- the store -------------------------------------------------------------------------------------------------
def test_store_round_trip_and_what_it_refuses(tmp_path):
    store = TaskStore(tmp_path / "s")
    assert store.get(KEY) is None and store.keys() == []
    store.put(KEY, {"w": torch.arange(4.0)}, {"history": {"x": np.float64(0.5)}, "seconds": 1.0})
    tensors, data = store.get(KEY)
    assert torch.equal(tensors["w"], torch.arange(4.0)) and data["history"] == {"x": 0.5}
    assert store.keys() == [KEY]
    with pytest.raises(ValueError, match="64 lowercase hex"):
        store.get("../../etc/passwd")
    with pytest.raises(ValueError, match="tensors must be"):
        store.put(KEY, {"w": [1, 2]}, {})
    with pytest.raises(ValueError, match="plain JSON"):
        key_digest({"x": object()})
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        TaskStore(tmp_path / "file")
    assert store_from_env({}) is None and store_from_env({STORE_ENV: "off"}) is None
    assert store_from_env({STORE_ENV: str(tmp_path / "s")}).root == tmp_path / "s"


def _entry(store, key):
    return store._paths(key)


@pytest.mark.parametrize("damage", ["truncate", "flip", "other key", "hostile pickle", "bad json", "no tensors"])
def test_a_broken_entry_is_a_miss_never_a_result(tmp_path, damage):
    store = TaskStore(tmp_path)
    store.put(KEY, {"w": torch.ones(64)}, {"seconds": 1.0})
    pt, js = _entry(store, KEY)
    if damage == "truncate":
        pt.write_bytes(pt.read_bytes()[:100])
    elif damage == "flip":
        blob = bytearray(pt.read_bytes())
        blob[len(blob) // 2] ^= 1
        pt.write_bytes(bytes(blob))
    elif damage == "other key":
        other = "cd" + "1" * 62
        store.put(other, {"w": torch.zeros(64)}, {"seconds": 2.0})
        shutil.copy(_entry(store, other)[1], js)              # a manifest copied over from another entry
    elif damage in ("hostile pickle", "no tensors"):
        import pickle

        class Boom:
            def __reduce__(self):
                return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))
        blob = pickle.dumps(Boom()) if damage == "hostile pickle" else _torch_bytes({"w": [1, 2]})
        pt.write_bytes(blob)
        manifest = json.loads(js.read_text())
        manifest["sha256"] = hashlib.sha256(blob).hexdigest()   # an attacker rewrites the manifest too
        js.write_text(json.dumps(manifest))
    else:
        js.write_text("{not json")
    with pytest.warns(UserWarning, match="unusable"):
        assert store.get(KEY) is None
    assert not (tmp_path / "pwned").exists()
    store.put(KEY, {"w": torch.ones(64)}, {"seconds": 1.0})     # the re-run replaces it
    assert store.get(KEY) is not None


def _torch_bytes(obj) -> bytes:
    import io
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _writer(root, n):
    store = TaskStore(root)
    for _ in range(n):
        store.put(KEY, {"w": torch.arange(1000.0)}, {"seconds": 3.0})


def test_two_runs_writing_one_store_at_once_leave_a_whole_entry(tmp_path):
    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(tmp_path, 20)) for _ in range(2)]
    for p in procs:
        p.start()
    with warnings.catch_warnings():
        warnings.simplefilter("error")                         # a reader never sees a torn entry
        while any(p.is_alive() for p in procs):
            got = TaskStore(tmp_path).get(KEY)
            assert got is None or torch.equal(got[0]["w"], torch.arange(1000.0))
    assert all(p.exitcode == 0 for p in procs)
    assert torch.equal(TaskStore(tmp_path).get(KEY)[0]["w"], torch.arange(1000.0))
    assert not list(tmp_path.rglob("*.tmp"))


# --- the key -----------------------------------------------------------------------------------------------------
def test_the_key_follows_the_code_the_task_runs(world):
    tr, va = world
    task = FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3)
    assert task.key_parts()["package"] == task_mod.package_digest(sorted(task_mod.code_modules(task.method, tr, va)))
    other = FineTuneTask(Method("DW-T", "netvlad", DWTripletLoss(sigma=18.0, eps=0.1)), tr, va, ONE, 0, 1e-3)
    assert "vpr_nb.losses.triplet" in task_mod.code_modules(other.method)  # the module of its loss (test_code_digest)


def test_the_key_holds_every_part_of_the_task(world):
    tr, va = world
    base = FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3)
    assert base.key() == FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3).key()
    changed = [FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 1, 1e-3),
               FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 3e-4),
               FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3, stop_after=1),
               FineTuneTask(Method("GeM", "max"), tr, va, ONE, 0, 1e-3),
               FineTuneTask(Method("GeM", "gem"), tr, va, dataclasses.replace(ONE, margin=0.2), 0, 1e-3),
               FineTuneTask(Method("GeM", "gem"), dataclasses.replace(tr, train_pos_radius=5.0), va, ONE, 0, 1e-3),
               FineTuneTask(Method("GeM", "gem"), tr, va.take_queries(np.arange(10)), ONE, 0, 1e-3),
               FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3, pinned=not base.pinned)]
    keys = {t.key() for t in changed}
    assert base.key() not in keys and len(keys) == len(changed)
    flipped = tr.db_images.copy()
    flipped[0, 0, 0, 0] ^= 1                                  # one bit of one pixel
    assert FineTuneTask(Method("GeM", "gem"), dataclasses.replace(tr, db_images=flipped), va, ONE, 0,
                        1e-3).key() != base.key()


# --- running tasks -------------------------------------------------------------------------------------------------
def test_a_stored_result_is_reused_only_under_its_whole_key(world, tmp_path, monkeypatch):
    tr, va = world
    monkeypatch.setenv(STORE_ENV, str(tmp_path))
    task = FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3)
    first = run_task(task)
    again = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3))
    assert not first.reused and again.reused
    assert same_weights(first.model, again.model) and same_weights(first.start, again.start)
    assert again.history.to_dict() == first.history.to_dict()
    # the package changed (a module the task runs): the key moves, the task runs again
    monkeypatch.setattr(task_mod, "package_digest", lambda modules=(), root=None: "0" * 64)
    rerun = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3))
    assert not rerun.reused and same_weights(rerun.model, first.model)
    # a damaged entry is run again, with the same bits
    pt = next(tmp_path.rglob(f"{task.key()}.pt"))
    pt.write_bytes(pt.read_bytes()[:50])
    monkeypatch.undo()
    monkeypatch.setenv(STORE_ENV, str(tmp_path))
    with pytest.warns(UserWarning, match="unusable"):
        fixed = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3))
    assert not fixed.reused and same_weights(fixed.model, first.model)
    # an entry that passes the store's checks but does not fit the task (a hand-written history, other weights)
    key = task.key()
    store = TaskStore(tmp_path)
    tensors, data = store.get(key)
    store.put(key, {"w": torch.zeros(3)}, data)
    with pytest.warns(UserWarning, match="does not fit this task"):
        refit = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3))
    assert not refit.reused and same_weights(refit.model, first.model)
    store.put(key, tensors, {**data, "history": {"epochs": "x"}})
    with pytest.warns(UserWarning, match="does not fit this task"):
        assert not run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3)).reused
    # with the store off, the same bits
    monkeypatch.setenv(STORE_ENV, "off")
    off = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3))
    assert not off.reused and same_weights(off.model, first.model)


def test_a_pinned_task_is_refused_by_an_unpinned_worker(world, monkeypatch):
    tr, va = world
    task = FineTuneTask(Method("GeM", "gem"), tr, va, ONE, 0, 1e-3, pinned=True)
    monkeypatch.delenv("MKL_CBWR", raising=False)
    with pytest.raises(eng.KernelsNotPinned, match="vpr_nb.kernels --run dask worker"):
        run_task(task)


def test_engines_refuse_bad_settings():
    with pytest.raises(ValueError, match="workers"):
        eng.LocalEngine(0)
    with pytest.raises(ValueError, match="VPR_NB_WORKERS"):
        eng.engine_from_env(environ={eng.WORKERS_ENV: "two"})
    assert eng.engine_from_env(3, environ={}).workers == 3
    assert eng.engine_from_env(1, environ={eng.WORKERS_ENV: "2"}).workers == 2
    with pytest.raises(ValueError, match="address"):
        eng.DaskEngine("  ")


def _square(x):
    if x < 0:
        raise ValueError(f"negative {x}")
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_an_engines_executor_returns_each_result_or_raises_its_error(workers):
    """The report starts a notebook when another ends through ``engine.executor()``: one worker runs each call
    at once, in this process; two run them in forked processes. Either way a call's error reaches its caller."""
    from concurrent.futures import FIRST_COMPLETED, wait
    with eng.LocalEngine(workers).executor() as pool:
        if workers == 1:
            assert isinstance(pool, eng.InlineExecutor)
        futures = {pool.submit(_square, x): x for x in (1, 2, 3)}
        done, _ = wait(futures, return_when=FIRST_COMPLETED)
        assert done and all(f.result() == futures[f] ** 2 for f in done)
        assert sorted(f.result() for f in futures) == [1, 4, 9]
        with pytest.raises(ValueError, match="negative -1"):
            pool.submit(_square, -1).result()


def _searches(world, engine, segment_epochs=None):
    tr, va = world
    recipe = dataclasses.replace(ONE, max_epochs=4, patience=4, lr_grid=(3e-4, 1e-3, 3e-3), search_seeds=2,
                                 halving_epochs=1, lr_extend=1, min_val_queries=0)
    methods = [Method("GeM", "gem"), (Method("GeM, SGD", "gem"), dataclasses.replace(recipe, optimizer="sgd"))]
    return search_methods(methods, tr, va, recipe, seeds=(0, 1, 2), engine=engine, segment_epochs=segment_epochs)


def _untimed(history) -> dict:
    d = history.to_dict()
    return {**d, "epochs": [{k: v for k, v in e.items() if k != "seconds"} for e in d["epochs"]]}


def _fingerprint(found) -> dict:
    return {name: (s.lr, s.grid, s.halved, {seed: (_untimed(r.history), hashlib.sha256(b"".join(
        v.numpy().tobytes() for v in r.model.state_dict().values())).hexdigest()) for seed, r in s.runs.items()})
            for name, s in found.items()}


@pytest.mark.slow
def test_results_are_the_same_bits_on_one_and_two_workers_and_a_dask_cluster(world):
    """Successive halving and the grid's growth decide round by round, so the chosen lr and every run's weights
    do not depend on where or how many tasks ran at once, nor on how many epochs a task trains before the next
    round (segments)."""
    distributed = pytest.importorskip("distributed", reason="the Dask test needs pip install 'vpr_nb[cluster]'")
    one = _fingerprint(_searches(world, eng.LocalEngine(1)))
    assert one == _fingerprint(_searches(world, eng.LocalEngine(2)))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster, distributed.Client(cluster) as client:
        dask = eng.DaskEngine(client=client)
        assert one == _fingerprint(_searches(world, dask))
        assert one == _fingerprint(_searches(world, dask, segment_epochs=1))   # each fine-tune a segment per epoch
        with dask.executor() as pool:     # what the report would submit notebooks through
            assert [pool.submit(_square, x).result() for x in (2, 3)] == [4, 9]
    assert all(s[2] for s in one.values())                     # halving stopped a rate in both searches


def test_drive_runs_rounds_of_several_searches_together(world):
    tr, va = world
    seen = []

    class Recording(eng.LocalEngine):
        def map(self, fn, items):
            seen.append(len(items))
            return super().map(fn, items)

    gens = [search_rounds(Method(n, "gem"), tr, va, ONE, (0, 1)) for n in ("A", "B")]
    a, b = drive(gens, Recording(1))
    assert seen == [4] and a.runs[0].lr == b.runs[0].lr == 1e-3   # one round: both searches' four runs at once


# --- re-making one committed number ----------------------------------------------------------------------------
def test_selection_picks_arms_by_pattern_and_refuses_foreign_seeds():
    from vpr_nb.recipe.arms import Selection, run_arms

    methods = [Method("sparse only", "gem"), (Method("sparse + dense cliques", "gem"), ONE),
               Method("cliques, τ 2.5 m", "gem")]
    assert [m if isinstance(m, Method) else m[0] for m in Selection("*cliques*").methods(methods)] == \
        [methods[1][0], methods[2]]
    assert Selection("sparse only").methods(methods) == [methods[0]]
    with pytest.raises(ValueError, match="pattern"):
        Selection("")
    with pytest.raises(ValueError, match="not among"):
        run_arms({"on": {"train": None, "methods": methods}}, None, [], (0, 1), select=Selection("*", (7,)))


def test_remake_says_which_notebooks_it_can_remake(capsys):
    from vpr_nb import remake

    with pytest.raises(ValueError, match="03, 05, 07"):
        remake.remake("04")
    assert remake.main(["02", "--arms", "x"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("error: notebook '02' has no experiment")
    flat = remake._flat({"arms": {"a": {"R@1": [0.5]}}}, probes=True)
    assert flat == {("arms", "on", "a"): [0.5]}
    assert remake._flat({"arms": {"on": {"a": {"R@1": [0.5]}}}, "sgd": {"0.001": {"b": {"R@1": [0.1]}}}}, False) == \
        {("arms", "on", "a"): [0.5], ("SGD lr 0.001", "off", "b"): [0.1]}


def test_remake_skips_a_file_without_the_asked_seed(monkeypatch):
    """``make reproduce NOTEBOOK=03 SEEDS=6``: 03_premise.json has 8 seeds, 03_control.json 5; seed 6 is re-made
    from the first and the second is skipped with a note, not refused."""
    from vpr_nb import remake

    calls, said = [], []

    class Fake:
        def __init__(self, seeds):
            self.EXPERIMENT = {"seeds": list(seeds)}

        def run(self, seeds, workers, select):
            calls.append((tuple(seeds), select.seeds))
            return {"arms": {"on": {"a": {"R@1": [0.25] * len(select.seeds)}}}}

    docs = {"03_x": {"arms": {"on": {"a": {"R@1": [0.5] * 8, "lr": 1e-3}}}},
            "03_y": {"arms": {"on": {"a": {"R@1": [0.5] * 5, "lr": 1e-3}}}}}
    monkeypatch.setattr(remake, "EXPERIMENTS", {"03_x": Fake(range(8)), "03_y": Fake(range(5))})
    monkeypatch.setattr(remake.results, "load", lambda name, _exp: {"results": docs[name]})
    rows = remake.remake("03", "a", [6], echo=said.append)
    assert calls == [(tuple(range(8)), (6,))] and [(r["file"], r["seed"], r["re-made"]) for r in rows] == \
        [("03_x", 6, 0.25)]
    assert any("03_y: seeds [6] are not among its seeds [0, 1, 2, 3, 4]; skipped" in line for line in said)
    with pytest.raises(ValueError, match="on seeds \\[9\\]"):
        remake.remake("03", "a", [9], echo=said.append)


# --- an interrupted run resumes ----------------------------------------------------------------------------------
RUN_TASKS = """
import sys, hashlib, numpy as np
from vpr_nb.kernels import apply_in_process
apply_in_process()
import dataclasses, torch
torch.set_num_threads(1)
from vpr_nb.recipe import RECIPE, FineTuneTask, Method, run_task
from vpr_nb.synthetic import make_dataset
ds = make_dataset("city", seed=0, blocks=(5, 2))
tr, va = ds.train.take_queries(np.arange(32)), ds.val
one = dataclasses.replace(RECIPE, max_epochs=2, patience=2, lr_grid=(1e-3,), search_seeds=1)
for seed in range(4):
    r = run_task(FineTuneTask(Method("GeM", "gem"), tr, va, one, seed, 1e-3))
    digest = hashlib.sha256(b"".join(v.numpy().tobytes() for v in r.model.state_dict().values())).hexdigest()
    print(seed, "reused" if r.reused else "trained", digest, flush=True)
"""


@pytest.mark.slow
def test_a_run_killed_with_sigkill_resumes_with_only_what_is_missing(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from vpr_nb.kernels import pinned_environ

    env = {**pinned_environ(), STORE_ENV: str(tmp_path / "store")}
    script = tmp_path / "run.py"
    script.write_text(RUN_TASKS)
    proc = subprocess.Popen([sys.executable, str(script)], env=env, stdout=subprocess.PIPE, text=True)
    first = proc.stdout.readline()                       # one task finished and stored ...
    os.kill(proc.pid, signal.SIGKILL)                    # ... then the run is killed
    proc.wait()
    assert first.startswith("0 trained")
    again = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600)
    lines = [line.split() for line in again.stdout.splitlines()]
    assert [(s, how) for s, how, _ in lines][0] == ("0", "reused")   # only what is missing is trained
    assert all(how == "trained" for _, how, _ in lines[1:]) and len(lines) == 4
    clean = subprocess.run([sys.executable, str(script)], env={**env, STORE_ENV: "off"}, capture_output=True,
                           text=True, timeout=600)
    assert [d for *_, d in (line.split() for line in clean.stdout.splitlines())] == [d for *_, d in lines]
    assert first.split()[2] == lines[0][2]               # the reused result is the bits it stored
    time.sleep(0)


KEYS = """
from vpr_nb.kernels import apply_in_process
apply_in_process()
import numpy as np
from vpr_nb.losses import MultiSimilarityLoss
from vpr_nb.recipe import RECIPE, FineTuneTask, Method, PlaceBatches, place_batch_labels
from vpr_nb.samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches
from vpr_nb.synthetic import make_dataset
ds = make_dataset("route", seed=0)                   # its scene holds a k-d tree of the track
tr, va = ds.train, ds.val
labels = place_batch_labels(tr)
images = np.concatenate([tr.db_images, tr.q_images])
utm = np.concatenate([tr.db_utm, tr.q_utm])
desc = np.random.default_rng(0).normal(size=(labels.max() + 1, 4)).astype(np.float32)
clique = CliqueBatchMaker(images, utm, labels, 4, 2, same_place_threshold=6.0, similar_groups=3, group_descriptors=desc)
half = RandomPlaceBatches(labels, 4, 2, 2, each_place_once=False)
method = Method("mix", "gem", MultiSimilarityLoss(), batches=PlaceBatches("mix", images, MixedPlaceBatches([half, clique], [0, 0]), (4, 4)))
print(FineTuneTask(method, tr, va, RECIPE, 0, 1e-3).key())
"""


def test_a_task_has_the_same_key_in_every_process(tmp_path):
    """The key is a content digest: the route world's scene (with a k-d tree) and a clique batch maker give the
    same key in two fresh processes, so a run started again finds what the first one stored."""
    import subprocess
    import sys

    from vpr_nb.kernels import pinned_environ

    script = tmp_path / "keys.py"
    script.write_text(KEYS)
    keys = [subprocess.run([sys.executable, str(script)], env=pinned_environ(), capture_output=True, text=True,
                           timeout=300, check=True).stdout.strip() for _ in range(2)]
    assert keys[0] == keys[1] and len(keys[0]) == 64
