"""The course's fine-tuning recipe: one protocol for every fine-tuning experiment of notebooks 03–07.

Each paper fine-tunes a pretrained backbone with its own aggregator and loss; what the course compares is
the *method* (a loss, an aggregator, a batch sampler), so everything else is fixed here, once:

- **Backbone**: the course backbone (:func:`vpr_nb.pretrain.course_backbone`) with its last block trainable
  (VGG16's conv5 in DW-T-Loss, DINOv2's last blocks in SALAD). Every aggregator reads its **output, after its
  final ReLU** (``after_relu``): the backbone is pretrained with a local contrastive term on the features
  before that ReLU (:mod:`vpr_nb.pretrain`), and measured on it, NetVLAD's k-means start reads the output
  better (notebook 04's untrained table, before vs after the ReLU), as does mean pooling (its signed mean
  cancels); max pooling and GeM give the same descriptor either way. SALAD reads what NetVLAD reads (notebook
  05). The public NetVLAD code reads VGG16's conv5_3 before its ReLU: the right side is an empirical question
  for each backbone, which notebook 04 asks.
- **Heads initialised from data**: NetVLAD by k-means (:func:`vpr_nb.models.init_netvlad`, 20 features per
  training-database image, 50 iterations, the training seed); SALAD with standardised head inputs
  (:func:`vpr_nb.models.init_salad`; the published initialisation starts collapsed here, notebook 05); with
  ``salad_kmeans_scores`` (off by default) SALAD's score head also starts from NetVLAD's k-means logits
  (:func:`vpr_nb.models.init_salad_scores_from_kmeans`, :mod:`vpr_nb.onoff.salad`).
- **Batches**: triplets (:class:`vpr_nb.training.TripletSource`, notebook 04: 16 queries per step, the 5 hardest
  of 300 negatives, margin 0.1, positives facing within 45°) or P × K place batches
  (:class:`vpr_nb.training.PlaceBatchSource`, notebook 05's MS recipe: 32 places × 4 images, 30 batches an
  epoch), or a method's own source.
- **Optimiser**: Adam, weight decay 1e-3, StepLR(5, 0.5) (notebook 04).
- **Selection**: the starting weights are the **epoch-0 candidate** (a fine-tune never reports worse than not
  training without saying so: ``History.initial_won``); training stops when validation Recall@1 has not
  improved for ``patience`` epochs (at most ``max_epochs``), and the best-on-validation weights are kept.
- **Learning rate per method** from a small grid (``lr_grid`` plus the method's ``paper_lr``, the paper's
  learning rate rescaled as the notebook explains), chosen on validation: the mean over the first
  ``search_seeds`` seeds of a multi-seed run, whose other seeds then train at the chosen rate only
  (:func:`lr_search`); on a split under ``min_val_queries`` queries the choice needs that many seeds.
- **Frozen blocks computed once** (:mod:`vpr_nb.feature_cache`): one cache per worker process, shared by every
  run it computes.

A notebook states only what deviates: ``dataclasses.replace(RECIPE, batch_size=4)``. In use::

    method = Method("T-Loss", "netvlad", loss=TripletLoss())
    search = lr_search(method, ds.train, ds.val, RECIPE, seeds=(0, 1, 2, 3, 4))
    for seed, run in search.runs.items():       # each: model, history, lr, start (the epoch-0 weights)
        ...

Modules, one job each:

- :mod:`~vpr_nb.recipe.protocol` :class:`Recipe` and :data:`RECIPE`, the settings above;
- :mod:`~vpr_nb.recipe.validation` :data:`VALIDATION_WORLD` and :func:`validation_split`;
- :mod:`~vpr_nb.recipe.method` :class:`Method` (a loss, an aggregator, a batch sampler) and :data:`BATCHES`;
- :mod:`~vpr_nb.recipe.start` :func:`build_start` (the epoch-0 candidate), :func:`make_source`,
  :func:`place_batch_labels`, :class:`PlaceBatches`, :class:`TripletBatches`;
- :mod:`~vpr_nb.recipe.task` :class:`FineTuneTask` (one fine-tune and its key), :func:`run_task` (runs it,
  or reuses its stored result, :mod:`vpr_nb.task_store`), :class:`FineTuneResult`;
- :mod:`~vpr_nb.recipe.segments` :func:`run_segment` and :func:`run_round` (a fine-tune a few epochs at a
  time, :data:`SEGMENT_EPOCHS`, the same bits as whole), :class:`Segment`;
- :mod:`~vpr_nb.recipe.search` :func:`fine_tune`, :func:`lr_search`, :func:`search_methods` (rounds of tasks on
  an engine, :mod:`vpr_nb.engine`), :class:`LRSearch`;
- :mod:`~vpr_nb.recipe.arms` :func:`run_arms` (on/off experiments, paired by seed), :func:`pooled_recall` and
  :data:`CITY_TEST_WORLDS` (test sets of 1,700+ queries).
"""
from __future__ import annotations

from .method import BATCHES, Method
from .protocol import RECIPE, Recipe
from .search import LRSearch, drive, fine_tune, lr_search, search_methods, search_rounds
from .segments import SEGMENT_EPOCHS, Segment, run_round, run_segment
from .task import FineTuneResult, FineTuneTask, run_task
from .start import PlaceBatches, TripletBatches, build_start, make_source, place_batch_labels
from .validation import VALIDATION_WORLD, validation_split

__all__ = ["BATCHES", "RECIPE", "SEGMENT_EPOCHS", "VALIDATION_WORLD", "Segment", "run_round", "run_segment", "FineTuneResult", "FineTuneTask", "LRSearch", "Method",
           "PlaceBatches", "Recipe", "TripletBatches", "build_start", "drive", "fine_tune", "lr_search", "make_source",
           "place_batch_labels", "run_task", "search_methods", "search_rounds", "validation_split"]
