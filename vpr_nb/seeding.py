"""Seeding: one call that seeds Python, numpy and torch, so that a run gives the same outputs."""
from __future__ import annotations

import os
import random


def seed_everything(seed: int = 0) -> None:
    """Seed Python, numpy and torch (CPU and CUDA) so a notebook gives the same outputs.

    A notebook calls it through :func:`vpr_nb.notebook.setup`, which also sets torch's thread count once.
    """
    # numpy and torch are imported here, not at the top: importing vpr_nb must not start them, so that
    # vpr_nb.kernels can pin their CPU kernels first (tests/conftest.py, make lab)
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    os.environ["PYTHONHASHSEED"] = str(seed)
