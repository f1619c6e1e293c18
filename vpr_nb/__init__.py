"""vpr_nb: the helper package behind the vpr-notebooks course.

The package is six layers; a module imports only from its own layer or the layers below it, never up
(``lint-imports`` checks it, with the contracts in ``pyproject.toml``; ``docs/architecture.md`` draws it):

1. **basics**: checks, errors and the command lines' diagnostic channel, seeding, threads, atomic writes,
   typed parsing, package data (:mod:`vpr_nb._checks`, :mod:`vpr_nb.errors`, :mod:`vpr_nb.cli`, ...), nothing of the
   course's ideas.
2. **data**: the images a method reads: the synthetic world (:mod:`vpr_nb.synthetic`), the real datasets'
   formats (:mod:`vpr_nb.datasets`), splits and positives (:mod:`vpr_nb.split`), images as tensors.
3. **methods**: what the course teaches, each idea in its own module: losses, aggregation, models,
   retrieval and Recall@N (:mod:`vpr_nb.evaluation`), GDS, mining, samplers, probes, plots of them, and each
   paper's premise measured (:mod:`vpr_nb.premise`).
4. **running**: how a method is run: the CPU kernels (a process setting), the frozen-feature cache, the
   training loop, run folders and logs.
5. **protocols**: the course's experiments as configurations: the typed run config, the fine-tuning
   recipe, pretraining the course backbone, a whole run (:mod:`vpr_nb.experiment`) and its summary, a machine's
   fingerprint.
6. **front doors**: what a person calls: the notebooks' setup (:mod:`vpr_nb.notebook`), the console
   scripts, the report, committed results and trained weights, widgets, authoring, assignments and grading.
   Each front door applies the process settings once (:func:`vpr_nb.kernels.apply_in_process`).
"""
from __future__ import annotations

from .seeding import seed_everything

__version__ = "0.1.0"

__all__ = ["__version__", "seed_everything"]
