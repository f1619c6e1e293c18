"""The registry of real-data formats and the one entry point :func:`load` ``(root, format)``.

Each format is one module of :mod:`vpr_nb.datasets` with one loader ``load_<format>(root, *, ...,
check_files=True) -> GeoSplit`` and one line in :data:`_REGISTERED` below, which names the format,
its loader and its Recall@N convention. :data:`FORMATS`, :data:`FORMAT_RECALL`, the options that
:func:`load` accepts for a format and its error messages are all derived from that line, so adding a
format is: write ``vpr_nb/datasets/<format>.py``, add its line here.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Callable

from . import gmberton, gsv_cities, msls, nordland, pitts
from .split import GeoSplit

# Recall@N convention per format for queries without any positive within the radius:
# "all" divides by every query (pytorch-NetVlad, gmberton's benchmark / VPR-methods-evaluation, GSV-Cities'
# validation, VPR-Bench Nordland), "exclude" leaves them out (mapillary_sls evaluate.py; the notebooks).
RECALL_CONVENTIONS = ("all", "exclude")


@dataclass(frozen=True)
class DatasetFormat:
    """One registered real-data format: its ``format=`` name for :func:`load`, its loader and its
    Recall@N convention (``"all"`` or ``"exclude"``, see :data:`RECALL_CONVENTIONS`).

    The loader takes the dataset location as its first positional argument and ``check_files`` as a
    keyword; its other keyword parameters are the :attr:`options` that :func:`load` passes through.
    """

    name: str
    loader: Callable[..., GeoSplit]
    recall: str

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"a dataset format needs a non-empty name, got {self.name!r}")
        if not callable(self.loader):
            raise ValueError(f"format {self.name!r}: loader must be a function, got {type(self.loader).__name__}")
        if self.recall not in RECALL_CONVENTIONS:
            raise ValueError(f"format {self.name!r}: recall must be one of {RECALL_CONVENTIONS}, got {self.recall!r}")
        params = list(inspect.signature(self.loader).parameters.values())
        if not params or params[0].kind not in (params[0].POSITIONAL_ONLY, params[0].POSITIONAL_OR_KEYWORD):
            raise ValueError(f"format {self.name!r}: the loader's first parameter must be the dataset location")
        if "check_files" not in (p.name for p in params[1:]):
            raise ValueError(f"format {self.name!r}: the loader must take check_files=")

    @property
    def options(self) -> list[str]:
        """The loader's keyword options that :func:`load` passes through (all but the location and ``check_files``)."""
        return [p for p in list(inspect.signature(self.loader).parameters)[1:] if p != "check_files"]


# One line per format: adding a format is a new module and a line here.
_REGISTERED = (
    DatasetFormat("pitts", pitts.load_pitts, recall="all"),
    DatasetFormat("gmberton", gmberton.load_gmberton, recall="all"),
    DatasetFormat("msls", msls.load_msls, recall="exclude"),
    DatasetFormat("gsv-cities", gsv_cities.load_gsv_cities, recall="all"),
    DatasetFormat("nordland", nordland.load_nordland, recall="all"),
)

REGISTRY: dict[str, DatasetFormat] = {f.name: f for f in _REGISTERED}
FORMATS = tuple(REGISTRY)
# the synthetic world (vpr_nb.synthetic) is not loaded from disk but has a convention too
FORMAT_RECALL = {**{f.name: f.recall for f in _REGISTERED}, "synthetic": "exclude"}


def recall_convention(format: str) -> str:
    """The Recall@N convention of a dataset format (see :data:`FORMAT_RECALL`)."""
    if format not in FORMAT_RECALL:
        raise ValueError(f"unknown dataset format {format!r}; choose one of {sorted(FORMAT_RECALL)}")
    return FORMAT_RECALL[format]


def load(root, format: str, *, check_files: bool = True, images_root=None, **options) -> GeoSplit:
    """Load a real VPR dataset split as a :class:`GeoSplit`.

    ``format`` is one of :data:`FORMATS`: ``"pitts"`` (``root`` = the NetVLAD dbStruct ``.mat``;
    ``images_root`` defaults to the parent of its ``datasets/`` folder), ``"gmberton"``, ``"msls"``,
    ``"gsv-cities"`` (``images_root`` replaces ``root`` for ``Images/``), ``"nordland"``; each is
    described in its module (:mod:`vpr_nb.datasets.pitts`, ...). ``options`` go to the format's loader
    (:func:`load_pitts`, :func:`load_gmberton`, :func:`load_msls`, :func:`load_gsv_cities`,
    :func:`load_nordland`); an option the loader does not take raises ValueError listing those it
    accepts. ``check_files=True`` stats every listed image and names the first missing one.
    """
    if format not in REGISTRY:
        raise ValueError(f"unknown dataset format {format!r}; choose one of {FORMATS}")
    spec = REGISTRY[format]
    accepted = spec.options
    unknown = [k for k in options if k not in accepted]
    if unknown:
        raise ValueError(f"format {format!r} does not take option(s) {unknown}; it accepts {accepted}")
    if images_root is not None:
        if "images_root" not in accepted:
            users = " and ".join(repr(f.name) for f in _REGISTERED if "images_root" in f.options)
            raise ValueError(f"images_root is only used by the {users} formats, not {format!r}")
        options["images_root"] = images_root
    return spec.loader(root, check_files=bool(check_files), **options)


__all__ = ["DatasetFormat", "REGISTRY", "FORMATS", "RECALL_CONVENTIONS", "FORMAT_RECALL", "recall_convention", "load"]
