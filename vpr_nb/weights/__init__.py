"""Trained weights that ship with the package (installed as package data, found with importlib.resources).

``course_backbone.pt`` + ``course_backbone.json``: the course backbone and its card, written by
``python -m vpr_nb.pretrain`` (see :mod:`vpr_nb.pretrain`).
"""
