"""CliqueMining's own comparison with a head that trains (notebook 07): :mod:`vpr_nb.onoff.clique_paper` with
SALAD in all three arms.

With GeM from the frozen reference (``notebooks/results/07_paper.json``) every run of every arm keeps its start
(best epoch 0 on all 8 seeds): GeM with the Multi-Similarity loss never improves validation recall (notebook 05
finds the same), so sparse only cannot pass its gate. Here every arm is the course backbone + SALAD, the head
with which sparse + dense random beats the frozen model in the near-miss world
(:mod:`vpr_nb.onoff.clique_nearmiss`); the rest is :mod:`vpr_nb.onoff.clique_paper`'s: the near-miss world,
sparse places from the route 25 m apart, each arm's lr searched, 8 paired seeds, the gate against the frozen
backbone + GeM.
"""
from __future__ import annotations

from . import clique_paper as cp

HEAD = "salad"
SEEDS, ARMS, COMPARISONS = cp.SEEDS, cp.ARMS, cp.COMPARISONS
EXPERIMENT = {**cp.EXPERIMENT, "aggregator": "salad (the course's start), the course backbone's last block trained"}
gate, verdicts_of = cp.gate, cp.verdicts_of


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """:func:`vpr_nb.onoff.clique_paper.run` with SALAD in every arm."""
    return cp.run(seeds, workers, max_epochs, select, head=HEAD)
