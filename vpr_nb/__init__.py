"""vpr_nb: the helper package behind the vpr-notebooks course.

Each module keeps one idea that a notebook derives by hand:

- :mod:`vpr_nb.synthetic`   the procedural VPR world (the teaching dataset)
- :mod:`vpr_nb.evaluation`  positives, faiss retrieval and Recall@N
- :mod:`vpr_nb.plots`       maps, image grids, retrieval grids
- :mod:`vpr_nb.notebook`    the setup every notebook runs (profile, budgets, one torch thread, seeds)
"""
from __future__ import annotations

import os
import random

__version__ = "0.1.0"


def seed_everything(seed: int = 0) -> None:
    """Seed Python, numpy and torch (CPU and CUDA) so a notebook gives the same outputs.

    A notebook calls it through :func:`vpr_nb.notebook.setup`, which also sets torch's thread count once.
    """
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    os.environ["PYTHONHASHSEED"] = str(seed)
