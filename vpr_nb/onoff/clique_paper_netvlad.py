"""CliqueMining's own comparison with a head that starts near the frozen reference and trains (notebook 07):
:mod:`vpr_nb.onoff.clique_paper` with NetVLAD-16 in all three arms.

GeM from the frozen reference never leaves its start under the Multi-Similarity loss
(``notebooks/results/07_paper.json``), and SALAD starts far below the frozen model and ends below it
(``07_paper_salad.json``): with either head sparse only fails its gate. NetVLAD-16 from the recipe's k-means
start scores 0.80 R@1 on the near-miss test split (seed 0), within 0.02 of the frozen backbone + GeM (0.816),
and trains with this loss (notebook 05). The paper trains DINOv2 + SALAD; here one head for all three arms is
what keeps the comparison fair. The rest is :mod:`vpr_nb.onoff.clique_paper`'s: the near-miss world, sparse
places from the route 25 m apart, each arm's lr searched, 8 paired seeds, the gate against the frozen
backbone + GeM.
"""
from __future__ import annotations

from . import clique_paper as cp

HEAD = "netvlad"
SEEDS, ARMS, COMPARISONS = cp.SEEDS, cp.ARMS, cp.COMPARISONS
EXPERIMENT = {**cp.EXPERIMENT, "aggregator": "netvlad-16 (the recipe's k-means start), the course backbone's last "
                                             "block trained"}
gate, verdicts_of = cp.gate, cp.verdicts_of


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """:func:`vpr_nb.onoff.clique_paper.run` with NetVLAD-16 in every arm."""
    return cp.run(seeds, workers, max_epochs, select, head=HEAD)
