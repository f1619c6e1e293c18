"""Reading torch weight files (weights only, one-line errors) and loading a state dict that must fit exactly."""
from __future__ import annotations

import pickle
import re
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

_UNSUPPORTED_GLOBAL = re.compile(r"Unsupported global: GLOBAL ([\w.]+)")


def read_weights(path, what: str = "checkpoint") -> Mapping:
    """Read a torch weights file with ``torch.load(path, map_location="cpu", weights_only=True)``.

    The one reader of weight files (checkpoints, the course backbone, VGG16 weights). Errors are one
    line naming the file: :class:`FileNotFoundError` when it is missing; :class:`ValueError` when it
    holds pickled Python objects (it is not a weights-only file and is never unpickled, since unpickling
    runs code from the file), when it is truncated or not a torch file, or when it holds no mapping.
    ``what`` names the file's role in the messages ("checkpoint", "course backbone", ...).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}; check the path")
    if path.stat().st_size == 0:
        raise ValueError(f"{path} is empty (0 bytes), not a torch {what}: restore it or write it again")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        with open(path, "rb") as f:
            head = f.read(4)
        if head != b"PK\x03\x04" and head[:1] != b"\x80":   # neither torch's zip archive nor its legacy pickle
            raise ValueError(f"{path} is not a readable torch {what} ({path.stat().st_size} bytes, not a torch "
                             f"archive): the file is truncated or corrupted, or was not written by torch.save; "
                             f"restore it or write it again") from None
        m = _UNSUPPORTED_GLOBAL.search(str(exc))
        held = (f"pickled Python objects (class {m.group(1)})" if m else
                "data that is not plain tensors and containers (or a corrupted file)")
        raise ValueError(f"{path} is not a weights-only {what}: it holds {held}, and vpr_nb will not unpickle it "
                         f"(unpickling can run code from the file). If you trust the code that made it, re-save "
                         f"only its tensors there, e.g. torch.save(model.state_dict(), path)") from None
    except PermissionError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch raises RuntimeError, OSError, EOFError, KeyError... on bad bytes
        first = str(exc).split(". ")[0].strip()[:120] or "no detail"
        raise ValueError(f"{path} is not a readable torch {what} ({type(exc).__name__}: {first}): the file is "
                         f"truncated or corrupted, or was not written by torch.save; restore it or write it "
                         f"again") from None
    if not isinstance(state, Mapping):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a state dict (a mapping name -> tensor) "
                         f"as a {what} is")
    return state


def _few(keys, n: int = 3) -> str:
    keys = list(keys)
    return ", ".join(keys[:n]) + (f", ... ({len(keys)} in all)" if len(keys) > n else "")


def load_state_checked(module: nn.Module, state, source, *, hint: str | None = None) -> nn.Module:
    """``module.load_state_dict(state)`` after checking that ``state`` fits ``module`` exactly.

    ``state`` must hold the module's keys, no others, each a tensor of the module's shape (dtypes are
    cast as ``load_state_dict`` does). Otherwise a one-line :class:`ValueError` names ``source`` (the
    file or object the state came from), the missing and unexpected keys and the first shape mismatches
    (file vs model), then ``hint`` (default: build the model with the settings the weights were
    trained with). Returns ``module``.
    """
    if not isinstance(state, Mapping):
        raise ValueError(f"{source} holds a {type(state).__name__}, not a state dict (a mapping name -> tensor)")
    own = module.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [str(k) for k in state if k not in own]
    wrong = [f"{k} is {type(state[k]).__name__}, not a tensor" for k in own
             if k in state and not isinstance(state[k], torch.Tensor)]
    wrong += [f"{k} is {tuple(state[k].shape)} in the file but {tuple(own[k].shape)} in the model" for k in own
              if k in state and isinstance(state[k], torch.Tensor) and state[k].shape != own[k].shape]
    if not (missing or unexpected or wrong):
        module.load_state_dict(state)
        return module
    parts = []
    if wrong:
        parts.append(f"{len(wrong)} tensor(s) differ: {_few(wrong, 2)}")
    if missing:
        parts.append(f"{len(missing)} key(s) of the model are missing: {_few(missing)}")
    if unexpected:
        parts.append(f"{len(unexpected)} key(s) are not in the model: {_few(unexpected)}")
    if hint is None:
        if missing and unexpected and all(k.startswith("module.") for k in unexpected):
            hint = "the keys carry DistributedDataParallel's 'module.' prefix: strip it before loading"
        else:
            hint = ("the weights were written for another architecture or width: build the model with the "
                    "settings they were trained with (e.g. the run's config.json)")
    raise ValueError(f"{source} does not fit this {type(module).__name__}: {'; '.join(parts)}; {hint}")
