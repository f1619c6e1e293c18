"""The setup every course notebook runs first: profile, budgets, threads, seeds, paths.

A notebook's second cell (tagged ``parameters``) holds ``PROFILE = "ci"``; its setup cell then calls::

    SETUP = vpr_nb.notebook.setup(PROFILE)                  # one torch thread, seed 0, the course's paths
    BUDGET = vpr_nb.notebook.budget(PROFILE, ci=dict(epochs=1, seeds=[0]),
                                    reproduce=dict(epochs=8, seeds=[0, 1, 2, 3, 4]))

Importing this module first in a notebook, before numpy and torch, pins the CPU kernels from inside the kernel
process (:func:`vpr_nb.kernels.pin_before_start`), so that a plain ``jupyter lab``, a hub or VS Code computes the
stored numbers, as ``make lab`` does. Where it cannot (Colab, an ARM or Apple processor, numpy imported first),
:func:`setup` says so in one line with the measured size of the difference.

* :func:`setup` checks the profile, sets torch to one CPU thread (a determinism setting: the stored
  outputs are the same floats on any machine, whatever its core count) and seeds Python, numpy and torch
  (:func:`vpr_nb.seed_everything`). BLAS threads are not a notebook's business: the package runs its own
  numpy hot loops on one BLAS thread (:mod:`vpr_nb._threads`), so no environment variable is needed.
* :func:`budget` is the one shape in which a notebook declares what differs between its two profiles:
  the same keys for ``ci`` and ``reproduce``, and the chosen profile's values come back.
* :func:`committed_experiment` reads the experiment settings another notebook's committed
  reproduce-profile results were computed with, for a notebook that reuses another's setting.
"""
from __future__ import annotations

# first, before anything imports numpy or torch: the kernels they start with are the pinned ones
from .kernels import UNPINNED_DIFFERENCE, apply_in_process, pin_before_start

UNPINNED = pin_before_start()   # None: pinned; else why this kernel computes with the processor's own kernels

import copy
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

from ._checks import check_int
from .package_data import committed_results_dir
from .seeding import seed_everything

PROFILES = ("ci", "reproduce")


@dataclass(frozen=True)
class Setup:
    """What :func:`setup` did and the folders a notebook reads.

    Attributes:
        profile: ``"ci"`` or ``"reproduce"``.
        seed: the seed given to :func:`vpr_nb.seed_everything`.
        results_dir: the committed reproduce-profile results (:mod:`vpr_nb.results`): the clone's
            ``notebooks/results/``, or the copy installed with the package (:mod:`vpr_nb.package_data`).
        pinned: whether this kernel computes with the pinned CPU kernels (the stored outputs' numbers).
        tolerance: how far a trained number in [0, 1] may move from the stored one here: 0 when pinned, else
            :data:`vpr_nb.kernels.UNPINNED_DIFFERENCE`.
    """

    profile: str
    seed: int
    results_dir: Path
    pinned: bool = True
    tolerance: float = 0.0


def check_profile(profile) -> str:
    """Return ``profile`` if it is one of :data:`PROFILES`, else raise ``ValueError``."""
    if profile not in PROFILES:
        raise ValueError(f"PROFILE must be 'ci' or 'reproduce', got {profile!r}")
    return profile


def setup(profile: str, seed: int = 0) -> Setup:
    """Check ``profile``, use one torch CPU thread, seed everything with ``seed``; return the :class:`Setup`."""


    check_profile(profile)
    seed = check_int(seed, "seed", minimum=0)
    torch.set_num_threads(1)   # same floats on every machine (nbval compares them), and fast on a shared CPU
    apply_in_process()         # with the pinned kernels: no oneDNN convolutions (vpr_nb.kernels)
    seed_everything(seed)
    if UNPINNED is not None:
        print(unpinned_note(UNPINNED))
    return Setup(profile=profile, seed=seed, results_dir=committed_results_dir(), pinned=UNPINNED is None,
                 tolerance=0.0 if UNPINNED is None else UNPINNED_DIFFERENCE)


def unpinned_note(reason: str) -> str:
    """The one line :func:`setup` prints where the kernels could not be pinned (``reason`` says why)."""
    fix = (" Restart the kernel and run this cell first for the stored numbers." if "started before" in reason else "")
    return (f"note: this kernel runs on its processor's own CPU kernels ({reason}), so trained numbers may differ "
            f"from the stored ones by up to {UNPINNED_DIFFERENCE} (Recall@N, cosines).{fix}")


def budget(profile: str, *, ci: Mapping, reproduce: Mapping) -> dict:
    """The budget of ``profile``: a copy of ``ci`` or ``reproduce``, which must have the same keys.

    Example: ``budget(PROFILE, ci=dict(epochs=5, step_size=2), reproduce=dict(epochs=14, step_size=5))``.
    """
    check_profile(profile)
    if not isinstance(ci, Mapping) or not isinstance(reproduce, Mapping):
        raise ValueError(f"ci and reproduce must be dicts of budget values, got {type(ci).__name__} and "
                         f"{type(reproduce).__name__}")
    if set(ci) != set(reproduce):
        raise ValueError(f"the ci and reproduce budgets must set the same keys; only in ci: "
                         f"{sorted(set(ci) - set(reproduce))}, only in reproduce: {sorted(set(reproduce) - set(ci))}")
    return copy.deepcopy(dict(ci if profile == "ci" else reproduce))


def committed_experiment(notebook: str, results_dir=None) -> dict:
    """The experiment config that notebook ``notebook``'s committed reproduce-profile results were made with.

    ``notebook`` is a stem such as ``"04_netvlad"``; the file is ``notebooks/results/<notebook>.json``
    (see :func:`vpr_nb.results.save`). A notebook that reuses another's setting reads it here, so the
    setting is written once; :func:`vpr_nb.results.load` with it then checks the results are current.
    """

    if not isinstance(notebook, str) or not notebook or "/" in notebook:
        raise ValueError(f"notebook must be a stem such as '04_netvlad', got {notebook!r}")
    path = Path(results_dir if results_dir is not None else committed_results_dir()) / f"{notebook}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no committed reproduce-profile results at notebooks/results/{path.name}; run "
                                f"notebook {notebook} with PROFILE = 'reproduce' (make reproduce) and commit the file")
    config = json.loads(path.read_text(encoding="utf-8")).get("config")
    if not isinstance(config, dict):
        raise ValueError(f"notebooks/results/{path.name} holds no experiment config; re-run notebook {notebook} "
                         f"with PROFILE = 'reproduce' and commit the file")
    return config
