"""Grading untrusted submissions: the pieces ``vpr_nb.assignments`` puts together.

* :mod:`~vpr_nb.grading.data`: answers as data only (numbers, strings, lists, dicts, numpy arrays, torch
  tensors), written and read without pickle, and compared with the instructor's reference;
* :mod:`~vpr_nb.grading.spec`: how a test cell declares an exercise (:class:`Case`, :func:`check`);
* :mod:`~vpr_nb.grading.static`: the "own code" rule, checked on the submitted source (AST);
* :mod:`~vpr_nb.grading.sandbox`: a throwaway folder, a process tree with limits, killed when it ends;
* :mod:`~vpr_nb.grading.runner`: the program that runs inside the sandbox.
"""
