"""Where and in which precision a run computes: the device, AMP and DistributedDataParallel helpers of :func:`train`."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .config import TrainConfig


def amp_dtype(device: torch.device) -> torch.dtype:
    """The autocast dtype of ``TrainConfig.amp``: bfloat16 on CPU and on GPUs that support it, else float16
    (then :func:`train` scales the loss with a ``GradScaler`` so that small gradients do not underflow)."""
    if device.type == "cuda" and not torch.cuda.is_bf16_supported():
        return torch.float16
    return torch.bfloat16


def resolve_device(name: str = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; a CUDA name without CUDA is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available; use device='cpu' or 'auto'")
    return torch.device(name)


@dataclass(frozen=True)
class DeviceSetup:
    """Where and in which precision :func:`train` runs: ``amp_dtype`` is ``None`` without AMP; ``scaler``
    is a ``GradScaler`` only for float16 autocast (bfloat16 needs none)."""

    device: torch.device
    amp_dtype: torch.dtype | None
    scaler: torch.amp.GradScaler | None

    def autocast(self):
        """The autocast context of the training steps (disabled without AMP)."""
        return torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None)


def setup_device(cfg: TrainConfig) -> DeviceSetup:
    """The device of ``cfg.device`` (:func:`resolve_device`) and, with ``cfg.amp``, the autocast dtype
    (:func:`amp_dtype`) and, for float16, a ``GradScaler``."""
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(cfg).__name__}")
    device = resolve_device(cfg.device)
    dtype = amp_dtype(device) if cfg.amp else None
    scaler = torch.amp.GradScaler(device.type) if dtype == torch.float16 else None
    return DeviceSetup(device, dtype, scaler)


def distributed_rank() -> tuple[int, int]:
    """(rank, world size) of an initialised ``torch.distributed`` process group, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def wrap_ddp(model: torch.nn.Module, device: torch.device, world: int) -> torch.nn.Module:
    """``model`` in ``DistributedDataParallel`` when ``world`` > 1 (gradients averaged over processes), else
    ``model`` itself. ``find_unused_parameters``: e.g. SmallCNN's global-token layer is unused by pooling
    aggregators."""
    if world <= 1:
        return model
    ids = [device.index] if device.type == "cuda" else None
    return torch.nn.parallel.DistributedDataParallel(model, device_ids=ids, find_unused_parameters=True)


def unwrap_ddp(net: torch.nn.Module) -> torch.nn.Module:
    """The model inside a ``DistributedDataParallel`` wrapper (:func:`wrap_ddp`), or ``net`` itself."""
    return net.module if isinstance(net, torch.nn.parallel.DistributedDataParallel) else net
