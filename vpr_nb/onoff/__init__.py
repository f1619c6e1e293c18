"""Each paper's premise experiment: its method and baselines trained where the premise holds ("on") and in a
twin world where it is switched off ("off"), with the premise record stored beside the arms' numbers.

One module per paper, each with its ``EXPERIMENT`` (every setting, as the results file's config) and
``run(seeds, workers)`` (the reproduce profile's results, including ``"premise"``,
:func:`vpr_nb.premise.record.premise_record`):

- :mod:`~vpr_nb.onoff.dwt` DW-T-Loss (notebook 03): random positives over 15 m with sigma = 18 m (on) vs
  NetVLAD's best positive within 10 m with the paper's sigma = 800 m (off); and the paper's SGD table.
- :mod:`~vpr_nb.onoff.clique` CliqueMining (notebook 07): notebook 07's route with a frame every 1 m, where the
  frozen model's failures are often near misses (on), vs every 2.5 m as 07 trains (off); the paper's comparison
  (cliques vs sparse only) and the mining-only ablation (cliques vs dense random).
  :mod:`~vpr_nb.onoff.clique_probes` changes one thing in its premise-on clique arm per hypothesis for why
  cliques lose to random dense places there (``notebooks/results/07_probes.json``).
- :mod:`~vpr_nb.onoff.salad` SALAD (notebook 05): distractors that change at every visit, in database and
  queries (``distractor_rate`` 4, 0.064 of the test pixels; on) vs none (today's worlds; off); the same SALAD
  head from NetVLAD's k-means scores, assigning by Sinkhorn + dustbin vs softmax, with the trained dustbin's
  share per content label.
"""
