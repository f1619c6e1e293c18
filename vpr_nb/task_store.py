"""A result store keyed by a task's whole description: a finished fine-tune is reused only when every part of its
key matches, and a broken or foreign entry is never read as a result.

An entry is two files under ``root/<first two hex digits>/``:

- ``<key>.pt``: the tensors (``torch.save`` of ``{name: tensor}``), read back with ``weights_only=True``;
- ``<key>.json``: the manifest: the format, the key again, the SHA-256 of the ``.pt`` file's bytes, and the
  task's plain-data result (its history, its run time).

Both are written atomically (:mod:`vpr_nb.atomic`), the tensors first, so a reader sees a whole entry or none.
A read checks, in order: the manifest parses and holds the key asked for; the ``.pt`` file's bytes have the
SHA-256 the manifest names; the tensors load with ``weights_only=True`` and are a flat dict of tensors. Any
failure (a truncated file, a flipped bit, a file copied from another key, a hostile pickle) is a miss: the
task runs again and its new entry replaces the broken one (:meth:`TaskStore.get` says why on ``warn``).
Two runs that share a store write the same key with the same bytes (tasks are deterministic), so the last
rename wins and nothing tears; where they differ (a non-deterministic task), the hash check turns the
mismatched pair into a miss.

Where it lives: ``$VPR_NB_TASK_STORE`` (:data:`STORE_ENV`); :func:`store_from_env` returns None when it is unset
or ``off``, and then nothing is cached. ``make reproduce`` sets it to ``reports/task-store`` (``make clean``
removes it; so does deleting the folder). A store from another commit serves only the tasks whose code is the
same there: the key holds a digest of the package code a task runs (:mod:`vpr_nb.recipe.task`,
:mod:`vpr_nb.code_digest`), so a result made by other code is never read.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import re
import warnings
from collections.abc import Mapping
from pathlib import Path

import torch

from .atomic import atomic_write

STORE_ENV = "VPR_NB_TASK_STORE"
FORMAT = 1
_KEY = re.compile(r"[0-9a-f]{64}")


def key_digest(parts: Mapping) -> str:
    """The SHA-256 (hex) of ``parts`` as canonical JSON (sorted keys, no spaces): the task key."""
    if not isinstance(parts, Mapping):
        raise ValueError(f"key parts must be a dict of plain data, got {type(parts).__name__}")
    try:
        text = json.dumps(parts, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"key parts must be plain JSON data (str, int, float, bool, None, lists, dicts): {exc}") \
            from None
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _plain(value):
    """A numpy scalar as its Python number (json.dumps' ``default``); anything else is refused."""
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        return value.item()
    raise TypeError(f"task data must be plain JSON, got {type(value).__name__}")


def _check_key(key) -> str:
    if not isinstance(key, str) or not _KEY.fullmatch(key):
        raise ValueError(f"a task key is 64 lowercase hex digits (key_digest), got {key!r}")
    return key


class TaskStore:
    """A folder of finished tasks: :meth:`get` a key's entry (None on a miss), :meth:`put` a new one."""

    def __init__(self, root):
        if not isinstance(root, (str, os.PathLike)) or not str(root):
            raise ValueError(f"root must be a folder path, got {root!r}")
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"the task store {self.root} is a file, not a folder: set {STORE_ENV} to a folder")

    def _paths(self, key: str) -> tuple[Path, Path]:
        folder = self.root / key[:2]
        return folder / f"{key}.pt", folder / f"{key}.json"

    def get(self, key: str, *, warn: bool = True) -> tuple[dict, dict] | None:
        """``(tensors, data)`` of ``key``'s entry, or None when there is none or it fails a check (with a
        warning saying which, when ``warn``)."""
        key = _check_key(key)
        pt, js = self._paths(key)
        if not js.is_file():
            return None
        try:
            return self._read(key, pt, js)
        except (OSError, ValueError, RuntimeError, EOFError, KeyError, TypeError, AttributeError,
                pickle.UnpicklingError) as exc:
            if warn:
                warnings.warn(f"task store: entry {key[:12]} in {self.root} is unusable ({exc}); the task runs "
                              f"again and replaces it", stacklevel=2)
            return None

    @staticmethod
    def _read(key: str, pt: Path, js: Path) -> tuple[dict, dict]:
        manifest = json.loads(js.read_text(encoding="utf-8"))
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise ValueError(f"not a format-{FORMAT} manifest")
        if manifest.get("key") != key:
            raise ValueError("its manifest names another key (a copied or renamed file)")
        if not isinstance(manifest.get("data"), dict):
            raise ValueError("its manifest holds no result data")
        blob = pt.read_bytes()
        if hashlib.sha256(blob).hexdigest() != manifest.get("sha256"):
            raise ValueError("its tensor file does not have the SHA-256 its manifest names (truncated or changed)")
        tensors = torch.load(io.BytesIO(blob), map_location="cpu", weights_only=True)
        if not isinstance(tensors, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                    for k, v in tensors.items()):
            raise ValueError("its tensor file is not a flat dict of named tensors")
        return tensors, manifest["data"]

    def put(self, key: str, tensors: Mapping, data: Mapping) -> None:
        """Store ``tensors`` (``{name: tensor}``) and ``data`` (plain JSON) under ``key``, atomically."""
        key = _check_key(key)
        if not isinstance(tensors, Mapping) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                       for k, v in tensors.items()):
            raise ValueError("tensors must be a dict {name: torch.Tensor}")
        buf = io.BytesIO()
        torch.save({k: v.detach().cpu().clone() for k, v in tensors.items()}, buf)
        blob = buf.getvalue()
        manifest = json.dumps({"format": FORMAT, "key": key, "sha256": hashlib.sha256(blob).hexdigest(),
                               "data": dict(data)}, sort_keys=True, allow_nan=False, default=_plain)
        pt, js = self._paths(key)
        atomic_write(pt, lambda f: f.write(blob))
        atomic_write(js, lambda f: f.write(manifest), text=True)

    def keys(self) -> list[str]:
        """The keys that have a manifest (unchecked)."""
        if not self.root.is_dir():
            return []
        return sorted(p.stem for p in self.root.glob("??/*.json") if _KEY.fullmatch(p.stem))


def store_from_env(environ: Mapping | None = None) -> TaskStore | None:
    """The store ``$VPR_NB_TASK_STORE`` names, or None when it is unset, empty or ``off``."""
    value = (os.environ if environ is None else environ).get(STORE_ENV, "").strip()
    if not value or value.lower() == "off":
        return None
    return TaskStore(value)
