"""One training loop for every notebook and reproduction run.

:func:`train` runs epochs of optimiser steps whose losses come from a *batch source*:

- :class:`TripletSource` — NetVLAD-style weakly supervised triplets mined on a split (hardest negatives from
  a descriptor cache refreshed every epoch), with a :class:`vpr_nb.losses.TripletFamilyLoss` object
  (DW-T-Loss's Eqs. (3), (4)x(3), (5)-(8), (9)); :mod:`vpr_nb.training.triplet_source`.
- :class:`PlaceBatchSource` — GSV-Cities / CliqueMining-style batches of P places x K images with a
  :class:`vpr_nb.losses.MultiSimilarityLoss` object, optionally one loss per slice of places
  (``loss_groups``); :mod:`vpr_nb.training.place_source`.

A source builds batches; the loss object it is given holds the loss's parameters (margin, sigma, eps, ...).
:func:`train` is the loop; its parts are named helpers: :func:`setup_device` (device and AMP),
:func:`wrap_ddp` / :func:`unwrap_ddp`, :func:`resume_state`, :func:`make_scheduler` /
:func:`scheduler_step`, :func:`evaluate_epoch` and :func:`training_state` / :func:`save_epoch_checkpoints`.

==============================================  ================================================================
:mod:`~vpr_nb.training.config`                  :class:`TrainConfig` (defaults: DW-T-Loss / NetVLAD, SGD +
                                                StepLR), :data:`DEFAULT_LR` (the package's one lr default),
                                                :func:`train_config_from`, :data:`OPTIMIZERS`, :data:`SCHEDULERS`
:mod:`~vpr_nb.training.history`                 :class:`History`: per-epoch loss, collapsed loss, mean cosine,
                                                lr, validation Recall@N, the selected epoch
:mod:`~vpr_nb.training.triplet_source`          :class:`TripletSource` (NetVLAD triplets, triplet-family losses)
:mod:`~vpr_nb.training.place_source`            :class:`PlaceBatchSource` (P places x K images, MS loss)
:mod:`~vpr_nb.training.checkpoints`             :func:`save_checkpoint`, :func:`load_checkpoint`,
                                                :func:`load_weights`, :func:`training_state`,
                                                :func:`save_epoch_checkpoints`, :func:`resume_state`,
                                                :func:`check_resume` (what a resume may change,
                                                :data:`EXTENDABLE`)
:mod:`~vpr_nb.training.device`                  :func:`resolve_device`, :func:`amp_dtype`, :func:`setup_device`
                                                (:class:`DeviceSetup`), :func:`distributed_rank`,
                                                :func:`wrap_ddp`, :func:`unwrap_ddp`
:mod:`~vpr_nb.training.optim`                   :func:`make_optimizer`, :func:`make_scheduler`,
                                                :func:`scheduler_step`, :func:`optimizer_step`,
                                                :data:`EPOCH_SCHEDULERS`
:mod:`~vpr_nb.training.divergence`              :class:`NotFinite` (the loss, weights or descriptors became
                                                NaN or inf)
:mod:`~vpr_nb.training.interruption`            :class:`TrainingInterrupted` (Ctrl-C: the epoch, the step, what
                                                ``last.pt`` holds)
:mod:`~vpr_nb.training.loop`                    :func:`train`, :func:`train_epoch`, :func:`evaluate_epoch`,
                                                :func:`batch_loss`
==============================================  ================================================================

Defaults follow DW-T-Loss / NetVLAD: SGD (momentum 0.9, weight decay 1e-3) and StepLR(5, 0.5).
Every epoch is seeded from ``(seed, epoch)``, so a run interrupted after epoch e and resumed from its
checkpoint ends with the same weights as an uninterrupted run, and one resumed with more epochs ends
with the weights of a run started with them. Checkpoints are written atomically (temporary file + rename)
and read with ``torch.load(..., weights_only=True)``.
"""
from __future__ import annotations

from ..evaluation import mean_pairwise_cosine  # re-exported: the notebooks import it from here
from .checkpoints import (EXTENDABLE, RUN_HINT, check_resume, config_changes, load_checkpoint, load_weights,
                          resume_state, save_checkpoint, save_epoch_checkpoints, training_state)
from .config import DEFAULT_LR, OPTIMIZERS, SCHEDULERS, TrainConfig, train_config_from
from .device import DeviceSetup, amp_dtype, distributed_rank, resolve_device, setup_device, unwrap_ddp, wrap_ddp
from .divergence import NotFinite
from .interruption import TrainingInterrupted
from .history import History
from .loop import batch_loss, evaluate_epoch, train, train_epoch
from .optim import EPOCH_SCHEDULERS, SCHEDULER_STEPS, make_optimizer, make_scheduler, optimizer_step, scheduler_step
from .place_source import PlaceBatchSource
from .triplet_source import TripletSource

__all__ = ["TrainConfig", "DEFAULT_LR", "train_config_from", "OPTIMIZERS", "SCHEDULERS", "History", "TripletSource", "PlaceBatchSource",
           "save_checkpoint", "load_checkpoint", "load_weights", "RUN_HINT", "training_state",
           "save_epoch_checkpoints", "resume_state", "check_resume", "config_changes", "EXTENDABLE",
           "EPOCH_SCHEDULERS", "TrainingInterrupted", "amp_dtype", "resolve_device", "DeviceSetup", "setup_device",
           "distributed_rank", "wrap_ddp", "unwrap_ddp", "make_optimizer", "make_scheduler", "SCHEDULER_STEPS",
           "scheduler_step", "optimizer_step", "batch_loss", "NotFinite", "train_epoch", "evaluate_epoch", "train",
           "mean_pairwise_cosine"]
