"""Each paper's premise, measured: the quantity its method exploits, as package functions the notebooks call.

A mechanism is taught by the quantity it exploits: measure it, run the method where it holds and in a twin
world where it is switched off, and let the gap follow it. One module per paper (imported by name, e.g.
``from vpr_nb.premise import dwt``):

- :mod:`~vpr_nb.premise.dwt` DW-T-Loss (notebook 03): the distances of the positives training mines and the
  spread of Eq. (4)'s weights over them;
- :mod:`~vpr_nb.premise.salad` SALAD (notebook 05): what the dustbin keeps, per content label;
- :mod:`~vpr_nb.premise.clique` CliqueMining (notebook 07): the share of near misses among a model's failures.
"""
