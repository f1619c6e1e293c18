"""The course's figures, drawn on matplotlib axes from the notebook's own arrays and tensors.

- :mod:`vpr_nb.plots.world`: the world map, image grids, retrieval grids, recall curves (shared by the notebooks);
- one module per method picture, each drawing the method from its own tensors (added with the notebook that
  teaches it).

Every function returns the figure (or axes), so a notebook can add a title or save it; nothing here calls
``plt.show()``.
"""
from __future__ import annotations

from .clique import plot_clique_batches
from .distance_weight import plot_distance_weight
from .gds import plot_gds_misordering
from .netvlad import plot_netvlad
from .salad import plot_salad_plan
from .triplet import plot_triplets
from .world import (CORRECT, SPLIT_COLOURS, WRONG, condition_grid, image_grid, plot_map, plot_recalls,
                    retrieval_grid)

__all__ = ["CORRECT", "WRONG", "SPLIT_COLOURS", "plot_map", "image_grid", "condition_grid", "retrieval_grid",
           "plot_recalls",
           "plot_triplets", "plot_distance_weight", "plot_netvlad",
           "plot_salad_plan", "plot_gds_misordering", "plot_clique_batches"]
