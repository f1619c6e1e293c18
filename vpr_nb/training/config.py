"""The hyper-parameters of one training run: :class:`TrainConfig` and its optimiser and scheduler choices.

Defaults follow DW-T-Loss / NetVLAD: SGD (momentum 0.9, weight decay 1e-3) and StepLR(5, 0.5)
(:mod:`vpr_nb.training.optim` builds them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._checks import check_int, check_positive


OPTIMIZERS = ("sgd", "adam", "adamw")
SCHEDULERS = ("step", "linear")


@dataclass
class TrainConfig:
    """Hyper-parameters of :func:`train` (defaults: DW-T-Loss / NetVLAD, scaled to the tiny world)."""

    epochs: int = 10
    optimizer: str = "sgd"
    lr: float = 0.05                 # NetVLAD used 1e-3 for VGG16; 0.05 suits the small CNN + mean-per-query loss
    momentum: float = 0.9
    weight_decay: float = 1e-3
    scheduler: str = "step"          # "step": StepLR per epoch; "linear": LinearLR per optimiser step
    step_size: int = 5               # StepLR: multiply lr by gamma every step_size epochs
    gamma: float = 0.5
    linear_end_factor: float = 0.2   # LinearLR: lr goes 1 -> end_factor over linear_steps steps (SALAD)
    linear_steps: int = 4000
    seed: int = 0
    ns: tuple[int, ...] = (1, 5, 10)
    restore_best: bool = True        # end with the best-on-validation weights
    initial_candidate: bool = False  # the starting weights compete in the selection ("epoch 0", History.initial)
    patience: int | None = None      # stop after this many epochs without a better val R@ns[0] (None: never)
    device: str = "auto"             # "auto" (cuda if available), "cpu", "cuda", "cuda:1", ...
    amp: bool = False                # autocast: bfloat16 on CPU / bf16-capable GPUs, else float16 + GradScaler

    def __post_init__(self):
        self.epochs = check_int(self.epochs, "epochs")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        check_positive(self.lr, "lr")
        check_positive(self.momentum, "momentum", allow_zero=True)
        check_positive(self.weight_decay, "weight_decay", allow_zero=True)
        if self.scheduler not in SCHEDULERS:
            raise ValueError(f"scheduler must be one of {SCHEDULERS}, got {self.scheduler!r}")
        self.step_size = check_int(self.step_size, "step_size")
        check_positive(self.gamma, "gamma")
        check_positive(self.linear_end_factor, "linear_end_factor")
        self.linear_steps = check_int(self.linear_steps, "linear_steps")
        if not isinstance(self.device, str) or not (self.device in ("auto", "cpu") or self.device.startswith("cuda")):
            raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {self.device!r}")
        self.seed = check_int(self.seed, "seed", minimum=0)
        self.patience = None if self.patience is None else check_int(self.patience, "patience")
        for name in ("restore_best", "amp", "initial_candidate"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        self.ns = tuple(check_int(n, "ns entry") for n in self.ns)
        if not self.ns:
            raise ValueError("ns must list at least one N for Recall@N, e.g. (1, 5, 10)")
