"""The training loop: :func:`train` runs epochs of optimiser steps on a batch source's losses, with validation.

Every epoch is seeded from ``(seed, epoch)``, so a run interrupted after epoch e and resumed from its
checkpoint ends with the same weights as an uninterrupted run. Ctrl-C raises :class:`TrainingInterrupted`
(where it stopped, what ``last.pt`` holds); the progress bar counts optimiser steps, with an ETA.
"""
from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .._checks import check_int
from ..evaluation import compute_descriptors, evaluate_on_split, mean_pairwise_cosine
from ..split import Split, check_split
from .checkpoints import resume_state, save_checkpoint, save_epoch_checkpoints, training_state
from .config import TrainConfig
from .device import DeviceSetup, distributed_rank, setup_device, unwrap_ddp, wrap_ddp
from .divergence import NotFinite
from .history import History
from .interruption import TrainingInterrupted
from .optim import make_optimizer, make_scheduler, optimizer_step, scheduler_step


def batch_loss(loss: torch.Tensor, world: int) -> float:
    """The whole batch's loss for the log: this process's share averaged over the ``world`` processes."""
    logged = loss.detach()
    if world > 1:
        logged = logged.clone()
        torch.distributed.all_reduce(logged)
        logged = logged / world
    return logged.item()


def _finite_weights(params) -> bool:
    """All of ``params`` finite (one reduction per tensor; NaN and inf propagate through the sums)."""
    sums = [p.detach().sum(dtype=torch.float32) for p in params if p.numel()]
    return not sums or bool(torch.isfinite(torch.stack(sums)).all())


def _no_step_reason(source, world: int) -> str:
    reason = getattr(source, "no_step_reason", None)
    text = reason() if callable(reason) else "the source gave no batch"
    if world > 1:
        text += f" (with {world} processes a step needs at least {world} valid triplets)"
    return text


def train_epoch(net: torch.nn.Module, source, epoch: int, cfg: TrainConfig, opt, sched, setup: DeviceSetup,
                shard: tuple[int, int] = (0, 1), log=None, on_step=None) -> tuple[float, float]:
    """One epoch of optimiser steps on the losses of ``source``, seeded from ``(cfg.seed, epoch)``.

    Returns the epoch's mean loss and mean collapsed loss (the loss if every descriptor were equal, as
    reported by the source after each step; NaN when it reports none). ``log.step(record)`` (e.g. a
    :class:`vpr_nb.run_log.RunLog`) gets every step's epoch, step, loss, collapsed loss, lr and seconds;
    ``on_step(steps, loss)`` is called after every optimiser step (the steps of the epoch done, its loss).
    ValueError when the loss, the weights or the descriptors become NaN/inf (naming the step and the
    learning rate) and when the epoch takes no optimiser step (saying why, e.g. no positives), since the
    model would then not be trained at all.
    """
    rng = np.random.default_rng([cfg.seed, epoch])
    torch.manual_seed(cfg.seed * 100_003 + epoch)
    if hasattr(source, "epoch"):
        source.epoch = epoch
    unwrap_ddp(net).train()
    total, collapsed, steps = 0.0, 0.0, 0
    params, t0 = [p for g in opt.param_groups for p in g["params"]], time.perf_counter()
    lr = opt.param_groups[0]["lr"]
    if not _finite_weights(params):
        raise ValueError(f"the model's weights hold NaN or inf at the start of epoch {epoch}, before any step of "
                         f"it: check the weights it started from (the backbone's file, a resumed checkpoint)")
    try:
        with setup.autocast():
            for loss in source.steps(net, rng, shard=shard, device=setup.device):
                lr = opt.param_groups[0]["lr"]
                if not torch.isfinite(loss):
                    raise NotFinite("loss", str(loss.item()))
                optimizer_step(loss, opt, setup.scaler)
                if not _finite_weights(params):
                    raise NotFinite("weights")
                scheduler_step(sched, cfg, "batch")
                logged = batch_loss(loss, shard[1])
                total, steps = total + logged, steps + 1
                last = float(getattr(source, "last_collapsed_loss", float("nan")))
                collapsed += last
                if log is not None:
                    log.step({"epoch": epoch, "step": steps - 1, "loss": logged, "collapsed_loss": last, "lr": lr,
                              "seconds": time.perf_counter() - t0})
                if on_step is not None:
                    on_step(steps, logged)
    except ValueError as exc:             # NotFinite, or a check of the model's own layers on its activations
        if not isinstance(exc, NotFinite) and "NaN or inf" not in str(exc):
            raise
        if epoch == 0 and steps == 0:
            raise ValueError(f"{exc} before the first optimiser step: the untrained model gives NaN/inf on the "
                             f"training images; check the images and the weights it started from") from None
        raise ValueError(f"training diverged: {exc} at optimiser step {steps + 1} of epoch {epoch} (lr {lr:g}); "
                         f"lower train.lr, e.g. --set train.lr={lr / 10:g}") from None
    if steps == 0:
        raise ValueError(f"epoch {epoch} took no optimiser step, so nothing would be trained: "
                         f"{_no_step_reason(source, shard[1])}")
    return total / steps, collapsed / steps


def evaluate_epoch(model: torch.nn.Module, val_split: Split, ns: tuple[int, ...]) -> tuple[dict, float]:
    """Validation Recall@N of ``model`` on ``val_split`` (its positives and Recall@N convention,
    :func:`vpr_nb.evaluation.evaluate_on_split`) and the mean pairwise cosine of its database descriptors
    (:func:`mean_pairwise_cosine`; NaN for a one-image database)."""
    check_split(val_split, "val_split")
    val_db = compute_descriptors(model, val_split.db_images)
    val = evaluate_on_split(val_db, compute_descriptors(model, val_split.q_images), val_split, ns)
    return val, mean_pairwise_cosine(val_db) if len(val_db) > 1 else float("nan")


def train(model: torch.nn.Module, source, val_split, config: TrainConfig | None = None, *,
          checkpoint_dir=None, resume: bool = True, progress: bool = True,
          stop_after: int | None = None, log=None, steps_per_epoch: int | None = None) -> History:
    """Train ``model`` with losses from ``source`` (:class:`TripletSource` or :class:`PlaceBatchSource`).

    After every epoch: validation Recall@N on ``val_split`` (:func:`evaluate_epoch`), the
    best-on-validation weights kept in memory (and in ``checkpoint_dir/best.pt``), and, with a
    ``checkpoint_dir``, the full state in ``last.pt``. With ``resume`` an existing ``last.pt`` is
    continued, also with more ``epochs`` or another ``patience`` where that gives exactly what a run started
    with them gives (:func:`~vpr_nb.training.checkpoints.check_resume`). ``stop_after`` ends the run after that
    many epochs of this call (to simulate an interruption). ``log``: an object with ``step(record)`` and
    ``epoch(record)`` (e.g. :class:`vpr_nb.run_log.RunLog`, the CSV / TensorBoard files of a run), called on
    rank 0 after every optimiser step and every epoch, and ``text(line)`` when it has one (a resumed run, an
    early stop). ``progress``: a bar of optimiser steps with an ETA (``steps_per_epoch``, when known, gives
    its total from the start; else from the second epoch). Returns the :class:`History`; with
    ``config.restore_best`` the model ends with the best validation weights. With ``config.initial_candidate``
    the starting weights are evaluated first and compete as epoch 0 (:meth:`History.add_initial`); with
    ``config.patience`` the run stops after that many epochs without a better validation Recall@``ns[0]``
    (``History.stopped_early``). ValueError when training diverges (NaN/inf, naming the step and the learning
    rate) or an epoch takes no optimiser step (:func:`train_epoch`); Ctrl-C raises
    :class:`~vpr_nb.training.interruption.TrainingInterrupted` (a KeyboardInterrupt) naming the epoch and step
    and the last epoch saved in ``last.pt``, which stays valid (every checkpoint is written atomically).

    Distributed: when a ``torch.distributed`` process group is initialised (e.g. under ``torchrun``)
    the model is wrapped in ``DistributedDataParallel``; every process mines the same batches and
    computes its share of each batch's loss, gradients are averaged, and only rank 0 writes
    checkpoints and shows progress.
    """
    cfg = config or TrainConfig()
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(cfg).__name__}")
    if not hasattr(source, "steps"):
        raise ValueError("source must be a TripletSource or PlaceBatchSource (an object with steps(model, rng))")
    rank, world = distributed_rank()
    setup = setup_device(cfg)
    model.to(setup.device)
    opt = make_optimizer(model, cfg)
    sched = make_scheduler(opt, cfg)
    ckdir = None if checkpoint_dir is None else Path(checkpoint_dir)
    resumed = None if ckdir is None or not resume else resume_state(ckdir, cfg, model, opt, sched, source, setup.scaler)
    history, start, best_state = resumed or (History(), 0, copy.deepcopy(model.state_dict()))
    text = getattr(log, "text", None) if rank == 0 else None
    if resumed is not None and text is not None:
        text(f"resumed from {ckdir / 'last.pt'}: {start} of {cfg.epochs} epochs trained"
             + ("; it had stopped early" if history.stopped_early else ""))
    at = {"epoch": None, "steps": 0, "phase": "evaluating the starting weights",
          "saved": None if ckdir is None or resumed is None else start - 1}
    end = cfg.epochs if stop_after is None else min(cfg.epochs, start + check_int(stop_after, "stop_after"))
    end = start if history.stopped_early else end
    per_epoch = steps_per_epoch             # the bar counts the run's steps: those of earlier epochs as done
    bar = tqdm(total=None if per_epoch is None else end * per_epoch, initial=start * (per_epoch or 0), unit="step",
               leave=False, disable=not progress or rank != 0, dynamic_ncols=True,
               desc=f"epoch {start + 1}/{cfg.epochs}")

    def on_step(steps, loss):
        at["steps"] = steps
        bar.set_postfix_str(f"loss {loss:.4f}" + at.get("val", ""), refresh=False)
        bar.update(1)
    try:
        if cfg.initial_candidate and resumed is None:
            history.add_initial(*evaluate_epoch(model, val_split, cfg.ns), cfg.ns[0])
            if ckdir is not None and rank == 0:          # best.pt exists even if no epoch beats the start
                save_checkpoint(ckdir / "best.pt", {"model": best_state, "epoch": -1})
        net = wrap_ddp(model, setup.device, world)
        for epoch in range(start, end):
            at.update(epoch=epoch, steps=0, phase="training")
            bar.set_description(f"epoch {epoch + 1}/{cfg.epochs}", refresh=False)
            t0 = time.perf_counter()
            lr = opt.param_groups[0]["lr"]
            loss, collapsed = train_epoch(net, source, epoch, cfg, opt, sched, setup, shard=(rank, world),
                                          log=log if rank == 0 else None, on_step=on_step)
            at["phase"] = "validation"
            scheduler_step(sched, cfg, "epoch")
            val, cosine = evaluate_epoch(model, val_split, cfg.ns)
            improved = history.add_epoch(epoch, loss, collapsed, cosine, lr, time.perf_counter() - t0, val, cfg.ns[0])
            if improved:
                best_state = copy.deepcopy(model.state_dict())
            if log is not None and rank == 0:
                log.epoch(history.epochs[-1])
            history.stopped_early = cfg.patience is not None and history.epochs_since_best >= cfg.patience
            at["phase"] = "checkpoint"
            if ckdir is not None and rank == 0:
                save_epoch_checkpoints(ckdir, training_state(model, opt, sched, source, history, epoch, best_state,
                                                             cfg, setup.scaler), improved)
            at["saved"] = epoch if ckdir is not None else None
            at["val"] = f", val R@{cfg.ns[0]} {val[cfg.ns[0]]:.3f}"
            if per_epoch is None:        # the first epoch's steps: the bar's total (and ETA) from now on
                per_epoch = at["steps"]
                bar.total = bar.n + (end - epoch - 1) * per_epoch
            if history.stopped_early:
                if text is not None:
                    text(f"stopped early after epoch {epoch + 1}: no better val R@{cfg.ns[0]} for {cfg.patience} "
                         f"epochs (patience)")
                break
    except KeyboardInterrupt as exc:
        if isinstance(exc, TrainingInterrupted):
            raise
        raise TrainingInterrupted(at["epoch"], at["steps"], at["phase"], at["saved"]).with_traceback(
            exc.__traceback__) from None
    finally:
        bar.close()
    selected = history.best_epoch >= 0 or history.initial is not None
    if cfg.restore_best and selected and (end == cfg.epochs or history.stopped_early):
        model.load_state_dict(best_state)
    return history
