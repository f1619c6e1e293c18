"""Grading untrusted submissions: the pieces ``vpr_nb.assignments`` puts together.

* :mod:`~vpr_nb.grading.markers`: nbgrader's cell markers (solution, test, ``grade-deps`` and parameters cells);
* :mod:`~vpr_nb.grading.data`: answers as data only (numbers, strings, lists, dicts, numpy arrays, torch
  tensors), written and read without pickle, and compared with the instructor's reference;
* :mod:`~vpr_nb.grading.spec`: how a test cell declares an exercise (:class:`Case`, :func:`check`);
* :mod:`~vpr_nb.grading.owncode`: the "own code" rule, checked on the submitted source (AST);
* :mod:`~vpr_nb.grading.sandbox`: a throwaway folder, a process tree with limits, killed when it ends;
* :mod:`~vpr_nb.grading.isolation`: bubblewrap grades untrusted work, or grading refuses (``--trusted`` aside);
* :mod:`~vpr_nb.grading.runner`: the program that runs inside the sandbox;
* :mod:`~vpr_nb.grading.exercise`: one exercise graded (spec from the instructor notebook, sandbox run, verdict);
* :mod:`~vpr_nb.grading.submission`: one submitted notebook graded, exercise by exercise;
* :mod:`~vpr_nb.grading.classroom`: a class folder of submissions graded into one CSV.
"""
