"""Checkpoints of a run: atomic writes, safe reads, and the full training state that an exact resume needs.

Checkpoints are written atomically (temporary file + rename) and read with ``torch.load(..., weights_only=True)``.
A resume continues ``last.pt`` under the TrainConfig it was written with, or one that changes only the fields of
:data:`EXTENDABLE` in a way that gives exactly what a run started with the new values gives
(:func:`check_resume`): more epochs, or another early-stopping patience that would not have stopped the run
before the epoch ``last.pt`` holds.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from ..atomic import atomic_write
from ..models import load_state_checked, read_weights
from .config import TrainConfig
from .history import History
from .optim import EPOCH_SCHEDULERS

# the TrainConfig fields a resumed run may change (checked by check_resume); any other change is another run
EXTENDABLE = ("epochs", "patience")


def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` with ``torch.save`` atomically (:func:`vpr_nb.atomic.atomic_write`): a temporary file in
    the same folder, then rename. A failed write (e.g. a full disk) raises one OSError naming the file and
    leaves the previous checkpoint and no temporary file."""
    # a file object: the archive is named "archive", not after the random temporary name, so equal states
    # give equal bytes
    return atomic_write(path, lambda f: torch.save(state, f))


RUN_HINT = ("build the model with the settings it was trained with (vpr_nb.evaluate: --run its run folder, "
            "or the same --set model.* values)")


def load_checkpoint(path) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: tensors and plain data
    only), through :func:`vpr_nb.models.read_weights`: one-line errors naming the file when it is missing,
    truncated, not a torch file or holds pickled objects (never unpickled)."""
    return dict(read_weights(path, "checkpoint"))


def load_weights(model: torch.nn.Module, state, path) -> None:
    """``model.load_state_dict(state)`` for the weights read from ``path``, checked by
    :func:`vpr_nb.models.load_state_checked`: a one-line ValueError naming the file and what differs
    (missing / unexpected tensors, shapes) when they belong to another architecture or width."""
    load_state_checked(model, state, path, hint=RUN_HINT)


def training_state(model, opt, sched, source, history: History, epoch: int, best_state: dict, cfg: TrainConfig,
                   scaler=None) -> dict:
    """Everything :func:`resume_state` needs to continue after ``epoch`` (plain tensors and containers)."""
    return {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
            "source": source.state_dict(), "history": history.to_dict(), "epoch": epoch,
            "best_model": best_state, "config": asdict(cfg),
            **({"scaler": scaler.state_dict()} if scaler is not None else {})}


def save_epoch_checkpoints(ckdir: Path, state: dict, improved: bool) -> None:
    """``ckdir/last.pt`` = the full training state; ``ckdir/best.pt`` = the best weights when this epoch
    ``improved`` on validation (both written atomically by :func:`save_checkpoint`)."""
    if improved:
        save_checkpoint(ckdir / "best.pt", {"model": state["best_model"], "epoch": state["epoch"]})
    save_checkpoint(ckdir / "last.pt", state)


def config_changes(saved: dict, cfg: TrainConfig) -> list[tuple[str, object, object]]:
    """``(field, saved value, value of cfg)`` for every TrainConfig field where ``cfg`` differs from ``saved``
    (a checkpoint's ``config``)."""
    return [(k, saved.get(k), v) for k, v in asdict(cfg).items() if saved.get(k) != v]


def _changes_text(changes) -> str:
    return ", ".join(f"{k}: {old!r} → {new!r}" for k, old, new in changes)


def _epochs_since_best(history: History, select_n: int) -> list[int]:
    """After each epoch of ``history``: the epochs since the selected one, the selection replayed
    (:meth:`History.add_epoch`, the epoch-0 candidate included)."""
    replay = History()
    if history.initial is not None:
        replay.add_initial(history.initial["val"], history.initial["mean_cosine"], select_n)
    since = []
    for e in history.epochs:
        replay.add_epoch(e["epoch"], e["loss"], e["collapsed_loss"], e["mean_cosine"], e["lr"], e["seconds"], e["val"],
                         select_n)
        since.append(replay.epochs_since_best)
    return since


def check_resume(ck: dict, cfg: TrainConfig, path) -> History:
    """The :class:`History` to continue ``ck`` (a ``last.pt``) with under ``cfg``; ValueError naming each
    differing field unless continuing gives exactly what a run started with ``cfg`` gives.

    Only :data:`EXTENDABLE` fields may differ. ``epochs``: at least the epochs ``ck`` has trained, and not
    with a scheduler whose learning rates depend on the number of epochs (:data:`EPOCH_SCHEDULERS`; StepLR
    counts epochs from the start and LinearLR spans ``linear_steps``, so neither does). ``patience``: the
    selection is replayed on the saved history; refused when the new patience would have stopped the run
    before the epoch ``ck`` holds, else the history's ``stopped_early`` is what the new patience says after it
    (a run stopped early by a smaller patience goes on)."""
    saved = ck["config"]
    changes = config_changes(saved, cfg)
    fixed = [c for c in changes if c[0] not in EXTENDABLE]
    if fixed:
        raise ValueError(f"{path} was written with a different TrainConfig ({_changes_text(fixed)}); a resumed run "
                         f"may change only {' and '.join(EXTENDABLE)}: resume with the TrainConfig it was written "
                         f"with, or start a new run (another checkpoint_dir, or resume=False)")
    history = History.from_dict(ck["history"])
    done = int(ck["epoch"]) + 1
    changed = {c[0] for c in changes}
    if "epochs" in changed and cfg.scheduler in EPOCH_SCHEDULERS:
        raise ValueError(f"{path}: the {cfg.scheduler!r} scheduler spreads its learning rates over the epochs, so a "
                         f"run of {cfg.epochs} epochs would have had other learning rates than this run of "
                         f"{saved['epochs']} from its first step: start a new run to train {cfg.epochs} epochs")
    if "epochs" in changed and cfg.epochs < done:
        raise ValueError(f"{path} holds {done} trained epochs, more than epochs={cfg.epochs}: resume with "
                         f"epochs >= {done}, or start a new run")
    if "patience" in changed:
        since = _epochs_since_best(history, cfg.ns[0])
        stops = [cfg.patience is not None and s >= cfg.patience for s in since]
        if any(stops[:-1]):
            first = history.epochs[stops.index(True)]["epoch"] + 1
            raise ValueError(f"{path}: with patience={cfg.patience} the run would have stopped after epoch {first}, "
                             f"but it has trained {done} epochs: resume with patience >= {max(since[:-1]) + 1} "
                             f"(or None), or start a new run")
        history.stopped_early = bool(stops and stops[-1])
    return history


def resume_state(ckdir: Path, cfg: TrainConfig, model, opt, sched, source, scaler=None):
    """Load ``ckdir/last.pt`` (written by :func:`save_epoch_checkpoints`) into the model, optimiser, scheduler,
    source and scaler; returns ``(history, first epoch to run, best weights)``, or ``None`` without a
    ``last.pt``. A checkpoint of another TrainConfig is refused unless :func:`check_resume` finds that
    continuing it gives exactly what a run of ``cfg`` gives (more epochs, another patience)."""
    path = Path(ckdir) / "last.pt"
    if not path.is_file():
        return None
    ck = load_checkpoint(path)
    history = check_resume(ck, cfg, path)
    model.load_state_dict(ck["model"])
    opt.load_state_dict(ck["optimizer"])
    sched.load_state_dict(ck["scheduler"])
    source.load_state_dict(ck["source"])
    if scaler is not None and "scaler" in ck:
        scaler.load_state_dict(ck["scaler"])
    return history, int(ck["epoch"]) + 1, ck["best_model"]
