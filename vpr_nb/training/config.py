"""The hyper-parameters of one training run: :class:`TrainConfig`, its optimiser and scheduler choices, and
:func:`train_config_from`, the one way a TrainConfig is made from another configuration.

Defaults follow DW-T-Loss / NetVLAD: SGD at :data:`DEFAULT_LR` (1e-3; momentum 0.9, weight decay 1e-3) and
StepLR(5, 0.5) (:mod:`vpr_nb.training.optim` builds them). :data:`DEFAULT_LR` is the package's only
learning-rate default: :class:`TrainConfig`, the ``train`` section of a run config (:mod:`vpr_nb.config`, whose
section *is* a TrainConfig) and :class:`vpr_nb.recipe.Recipe` take it from here; a preset or a notebook that
trains at another rate sets ``lr`` itself.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass

import numpy as np

from .._checks import check_int, check_positive


OPTIMIZERS = ("sgd", "adam", "adamw")
SCHEDULERS = ("step", "linear")
DEFAULT_LR = 1e-3    # the one learning-rate default: NetVLAD's SGD rate for VGG16 and notebook 04's Adam rate


@dataclass
class TrainConfig:
    """Hyper-parameters of :func:`train` (defaults: DW-T-Loss / NetVLAD; ``lr``: :data:`DEFAULT_LR`)."""

    epochs: int = 10
    optimizer: str = "sgd"
    lr: float = DEFAULT_LR           # 1e-3; notebook 02 and the synthetic-city presets set 0.05 (the small CNN)
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


def train_config_from(settings, **chosen) -> TrainConfig:
    """The :class:`TrainConfig` of a run described by ``settings``, a dataclass instance (e.g. a
    :class:`vpr_nb.recipe.Recipe`): every TrainConfig field that ``settings`` has by name, then the fields in
    ``chosen`` (set on purpose; they win), TrainConfig's defaults for the rest. A run config's ``train``
    section is itself a TrainConfig (``train_config_from(cfg.train) == cfg.train``)."""
    if not is_dataclass(settings) or isinstance(settings, type):
        raise ValueError(f"settings must be a dataclass instance (e.g. a Recipe or a TrainConfig), got "
                         f"{type(settings).__name__}; pass the other values as keyword arguments")
    names = [f.name for f in fields(TrainConfig)]
    unknown = sorted(set(chosen) - set(names))
    if unknown:
        raise ValueError(f"unknown TrainConfig field(s) {unknown}; known fields: {', '.join(names)}")
    own = {f.name for f in fields(settings)}
    return TrainConfig(**{n: getattr(settings, n) for n in names if n in own and n not in chosen}, **chosen)
