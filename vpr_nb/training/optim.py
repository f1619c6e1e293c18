"""The optimiser and learning-rate scheduler of a run: building them from a :class:`TrainConfig` and stepping them.

Defaults follow DW-T-Loss / NetVLAD: SGD (momentum 0.9, weight decay 1e-3) and StepLR(5, 0.5), stepped once
per epoch; SALAD's LinearLR is stepped once per optimiser step (:data:`SCHEDULER_STEPS`).
"""
from __future__ import annotations

import torch

from .config import TrainConfig


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """SGD (momentum, weight decay), Adam or AdamW over the model's trainable parameters (``cfg.optimizer``).

    Adam and AdamW run torch's fused update (one kernel for all parameters) where every parameter is a
    floating-point tensor on the CPU or a CUDA device: the unfused update takes the square root of its second
    moment through MKL's vector maths on the CPU, which rounds differently on Intel and AMD processors, so the
    same run trained other weights on the two (:mod:`vpr_nb.kernels`). The fused kernel is also faster."""
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError("the model has no trainable parameters")
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    fused = {"fused": True} if all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params) else {}
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, **fused)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, **fused)


def make_scheduler(opt: torch.optim.Optimizer, cfg: TrainConfig):
    """``cfg.scheduler="step"``: StepLR(step_size, gamma), stepped once per epoch (NetVLAD / DW-T-Loss);
    ``"linear"``: LinearLR(1 -> linear_end_factor over linear_steps), stepped per optimiser step (SALAD).
    :func:`scheduler_step` does the stepping."""
    if cfg.scheduler == "step":
        return torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.step_size, gamma=cfg.gamma)
    return torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0, end_factor=cfg.linear_end_factor,
                                             total_iters=cfg.linear_steps)


SCHEDULER_STEPS = {"step": "epoch", "linear": "batch"}    # when each scheduler of SCHEDULERS advances
# the schedulers whose learning rates depend on train.epochs (e.g. a decay spread over the whole run): a run of
# theirs cannot be resumed with more epochs (checkpoints.check_resume). None of SCHEDULERS: StepLR counts epochs
# from the start, LinearLR spans linear_steps optimiser steps, whatever the number of epochs.
EPOCH_SCHEDULERS: frozenset[str] = frozenset()


def scheduler_step(sched, cfg: TrainConfig, after: str) -> None:
    """Advance ``sched`` if ``cfg.scheduler`` steps ``after`` this point: ``"batch"`` (an optimiser step) or
    ``"epoch"`` (see :data:`SCHEDULER_STEPS`)."""
    if after not in ("batch", "epoch"):
        raise ValueError(f"after must be 'batch' or 'epoch', got {after!r}")
    if SCHEDULER_STEPS[cfg.scheduler] == after:
        sched.step()


def optimizer_step(loss: torch.Tensor, opt: torch.optim.Optimizer, scaler=None) -> None:
    """Back-propagate ``loss`` and take one optimiser step; with a float16 ``scaler`` the loss is scaled and
    the gradients unscaled before the step."""
    opt.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    else:
        loss.backward()
        opt.step()
