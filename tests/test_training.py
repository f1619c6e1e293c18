"""The training loop: determinism, resume-after-interruption, checkpoints, bad input."""
import numpy as np
import pytest
import torch

from vpr_nb import seed_everything
from vpr_nb.mining import random_place_batches
from vpr_nb.models import build_model
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import (History, PlaceBatchSource, TrainConfig, TripletSource, load_checkpoint,
                             save_checkpoint, train)

WORLD = dict(blocks=(5, 2), image_size=(16, 24), queries_per_place=1.0)


@pytest.fixture(scope="module")
def world():
    return make_dataset("city", 0, **WORLD)


def _model():
    seed_everything(0)
    return build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))


def _run(world, tmp_path=None, stop_after=None, loss="triplet", epochs=3):
    model = _model()
    src = TripletSource(world.train, loss, batch_size=8, num_negatives=3, num_candidates=50, max_heading_diff=45)
    hist = train(model, src, world.val, TrainConfig(epochs=epochs, lr=0.05, step_size=1), checkpoint_dir=tmp_path,
                 progress=False, stop_after=stop_after)
    return model, hist


def _same_weights(a, b):
    return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def test_training_is_deterministic_and_learns(world):
    m1, h1 = _run(world)
    m2, h2 = _run(world)
    assert _same_weights(m1, m2)
    assert h1.losses == h2.losses and h1.recalls(1) == h2.recalls(1) and h1.best_epoch == h2.best_epoch
    assert len(h1.epochs) == 3 and 0 <= h1.best_epoch < 3
    assert h1.epochs[1]["lr"] == pytest.approx(0.05 * 0.5)       # StepLR(step_size=1, gamma=0.5)
    assert all(np.isfinite(h1.losses))


def test_interrupted_run_resumes_to_the_same_weights(world, tmp_path):
    full, hist_full = _run(world)
    _, partial = _run(world, tmp_path, stop_after=1)
    assert len(partial.epochs) == 1 and (tmp_path / "last.pt").is_file() and (tmp_path / "best.pt").is_file()
    resumed, hist = _run(world, tmp_path)                           # picks up last.pt, runs epochs 2 and 3
    assert [e["epoch"] for e in hist.epochs] == [0, 1, 2]
    assert _same_weights(full, resumed)
    assert hist.recalls(1) == hist_full.recalls(1)


def test_resume_refuses_a_different_config(world, tmp_path):
    _run(world, tmp_path, stop_after=1)
    with pytest.raises(ValueError, match="different TrainConfig"):
        _run(world, tmp_path, epochs=4)


@pytest.mark.parametrize("loss", ["weighted", "ce", "dw"])
def test_every_triplet_loss_trains(world, loss):
    _, hist = _run(world, loss=loss, epochs=1)
    assert np.isfinite(hist.losses).all()


def test_place_batch_source(world):
    tr = world.train
    images = np.concatenate([tr.db_images, tr.q_images])
    groups = np.concatenate([tr.db_place, tr.q_place])

    def batches(model, epoch, rng):
        return random_place_batches(groups, places_per_batch=8, images_per_place=2, num_batches=3,
                                    seed=int(rng.integers(1 << 30)))
    model = _model()
    hist = train(model, PlaceBatchSource(images, batches), world.val, TrainConfig(epochs=1), progress=False)
    assert np.isfinite(hist.losses).all()


def test_checkpoint_roundtrip_is_atomic_and_weights_only(tmp_path):
    state = {"model": {"w": torch.arange(3.0)}, "epoch": 2}
    path = save_checkpoint(tmp_path / "sub" / "ck.pt", state)
    assert sorted(p.name for p in path.parent.iterdir()) == ["ck.pt"]        # no temp file left behind
    back = load_checkpoint(path)
    assert back["epoch"] == 2 and torch.equal(back["model"]["w"], state["model"]["w"])
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    torch.save({"obj": History()}, tmp_path / "unsafe.pt")                    # arbitrary objects are refused
    with pytest.raises(Exception):
        load_checkpoint(tmp_path / "unsafe.pt")


@pytest.mark.parametrize("kwargs, match", [
    (dict(epochs=0), "epochs"), (dict(optimizer="rmsprop"), "optimizer"), (dict(lr=-1.0), "lr"),
    (dict(ns=()), "ns"), (dict(gamma=0.0), "gamma"),
])
def test_bad_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**kwargs)


def test_bad_sources(world):
    with pytest.raises(ValueError, match="loss must be one of"):
        TripletSource(world.train, "contrastive")
    with pytest.raises(ValueError, match="must provide"):
        TripletSource(object())
    with pytest.raises(ValueError, match="make_batches"):
        PlaceBatchSource(world.train.db_images, make_batches=None)
    with pytest.raises(ValueError, match="TrainConfig"):
        train(_model(), TripletSource(world.train), world.val, config={"epochs": 1})
    bad = PlaceBatchSource(world.train.db_images, lambda m, e, r: np.full((1, 2, 2), 10**6))
    with pytest.raises(ValueError, match="outside"):
        train(_model(), bad, world.val, TrainConfig(epochs=1), progress=False)


# ------------------------------------------------------------------------------ training health
def test_mean_pairwise_cosine_matches_the_pairwise_definition():
    from vpr_nb.training import mean_pairwise_cosine
    rng = np.random.default_rng(0)
    d = rng.normal(size=(7, 5))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sims = d @ d.T
    assert mean_pairwise_cosine(d) == pytest.approx(sims[~np.eye(7, dtype=bool)].mean())
    assert mean_pairwise_cosine(np.tile(d[:1], (4, 1))) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="N >= 2"):
        mean_pairwise_cosine(d[:1])


@pytest.mark.parametrize("loss, collapsed", [("triplet", 3 * 0.1), ("ce", 3 * np.log(2))])
def test_history_records_collapsed_loss_and_mean_cosine(world, loss, collapsed):
    """Eq. (3) with equal descriptors gives the margin per negative, Eq. (8) log 2 per negative (M = 3)."""
    _, hist = _run(world, loss=loss, epochs=1)
    e = hist.epochs[0]
    assert e["collapsed_loss"] == pytest.approx(collapsed, rel=1e-5)
    assert -1.0 <= e["mean_cosine"] <= 1.0 and hist.mean_cosines == [e["mean_cosine"]]
    assert hist.collapsed_losses == [e["collapsed_loss"]]
    assert History.from_dict(hist.to_dict()).epochs[0]["collapsed_loss"] == e["collapsed_loss"]


def test_place_batches_record_the_ms_collapsed_loss(world):
    """Multi-Similarity loss with every similarity 1: (1/α)·log(1 + (K-1)e^{-α(1-λ)}) + (1/β)·log(1 + (N-K)e^{β(1-λ)})."""
    from vpr_nb import losses as L
    seed_everything(0)
    model = build_model("small_cnn", "gem", backbone_kwargs=dict(width=8, out_channels=16))
    tr = world.train
    src = PlaceBatchSource(tr.db_images, lambda m, e, rng: random_place_batches(tr.db_place, 4, 2, num_batches=2, seed=rng))
    hist = train(model, src, world.val, TrainConfig(epochs=1, optimizer="adam", lr=1e-3), progress=False)
    labels = torch.arange(4).repeat_interleave(2)
    same = torch.nn.functional.normalize(torch.ones(8, 16), dim=1)
    want = float(L.multi_similarity_loss(same, labels, 1.0, 50.0, 0.0))
    assert hist.epochs[0]["collapsed_loss"] == pytest.approx(want, rel=1e-5)


def test_amp_trains_in_bfloat16_on_cpu(world):
    from vpr_nb.training import amp_dtype
    assert amp_dtype(torch.device("cpu")) == torch.bfloat16
    model = _model()
    src = TripletSource(world.train, "triplet", batch_size=8, num_negatives=3, num_candidates=50)
    hist = train(model, src, world.val, TrainConfig(epochs=1, lr=0.05, amp=True, device="cpu"), progress=False)
    assert np.isfinite(hist.losses).all() and all(p.dtype == torch.float32 for p in model.parameters())
    for bad in ("False", 1):
        with pytest.raises(ValueError, match="amp must be True or False"):
            TrainConfig(amp=bad)
    with pytest.raises(ValueError, match="restore_best must be True or False"):
        TrainConfig(restore_best="no")


def test_pickled_checkpoint_is_refused_with_a_clear_message(tmp_path):
    torch.save({"model": torch.nn.Linear(2, 2)}, tmp_path / "pickled.pt")
    with pytest.raises(ValueError, match="will not unpickle it"):
        load_checkpoint(tmp_path / "pickled.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")


def test_place_batch_source_keeps_its_sampler_state(world):
    class Sampler:
        def __init__(self):
            self.state = {"d": torch.zeros(2)}

        def __call__(self, model, epoch, rng):
            return random_place_batches(np.arange(4).repeat(4), 2, 2, num_batches=1, seed=0)

        def state_dict(self):
            return self.state

        def load_state_dict(self, state):
            self.state = state

    s = Sampler()
    src = PlaceBatchSource(world.train.db_images[:16], s)
    assert src.state_dict() == {"sampler": s.state}
    src.load_state_dict({"sampler": {"d": torch.ones(2)}})
    assert torch.equal(s.state["d"], torch.ones(2))
    plain = PlaceBatchSource(world.train.db_images[:16], lambda m, e, r: None)
    assert plain.state_dict() == {}
    with pytest.raises(ValueError, match="sampler state"):
        plain.load_state_dict({"sampler": {}})
