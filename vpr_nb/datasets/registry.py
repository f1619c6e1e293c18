"""The registry of real-data formats and the one entry point :func:`load` ``(root, format)``.

Each format is one module of :mod:`vpr_nb.datasets` with a loader ``load_<format>(root, *, ...,
check_files=True) -> GeoSplit`` and a ``load_part(root, part, *, <settings>, check_files=True)`` that
reads one part (``train`` / ``val`` / ``test``) of a dataset folder, plus one :class:`DatasetFormat`
line in :data:`_REGISTERED` below. That line holds every fact about the format that the rest of the
package uses: its Recall@N convention, which parts it has and which one validates or tests, whether
its images carry place ids and whether it has queries, and the run-config settings its ``load_part``
reads with their allowed values. :data:`REGISTRY`, the choices of the reproduction commands'
``data.format``, the default validation and test data and the error messages are all derived from it,
so adding a format is: write ``vpr_nb/datasets/<format>.py``, add its line here (or, from outside the
package, :func:`register` it).
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Callable, Mapping

from . import gmberton, gsv_cities, msls, nordland, pitts
from .split import GeoSplit

# Recall@N convention per format for queries without any positive within the radius:
# "all" divides by every query (pytorch-NetVlad, gmberton's benchmark / VPR-methods-evaluation, GSV-Cities'
# validation, VPR-Bench Nordland), "exclude" leaves them out (mapillary_sls evaluate.py; the notebooks).
RECALL_CONVENTIONS = ("all", "exclude")
SYNTHETIC = "synthetic"   # the synthetic world (vpr_nb.synthetic) is generated, not registered; its convention:
SYNTHETIC_RECALL = "exclude"


@dataclass(frozen=True)
class DatasetFormat:
    """One registered real-data format.

    Attributes:
        name: the ``format=`` name of :func:`load` and of ``data.format``.
        loader: ``loader(location, *, <options>, check_files=True) -> GeoSplit``; its keyword options
            (:attr:`options`) are what :func:`load` passes through.
        recall: Recall@N convention, ``"all"`` or ``"exclude"`` (:data:`RECALL_CONVENTIONS`).
        load_part: ``load_part(root, part, *, <settings>, check_files=True) -> GeoSplit``: one part of a
            dataset folder, as the reproduction commands read it (None: :func:`load` only).
        train: whether the format has a training part.
        val_part / test_part: the part read when this format is the validation / test data (None: it has
            none). A run trained on the format validates on its own ``val_part`` unless that is also
            its ``test_part`` (MSLS-val is MSLS's only labelled evaluation data): :attr:`own_val`.
        places: whether its images carry place ids (needed for place batches).
        queries: whether it has queries (needed for triplets and for evaluation).
        settings: the ``data.<name>`` fields of the run config that ``load_part`` takes as keywords,
            each with its allowed values (None: any value).
    """

    name: str
    loader: Callable[..., GeoSplit]
    recall: str
    load_part: Callable[..., GeoSplit] | None = None
    train: bool = True
    val_part: str | None = "val"
    test_part: str | None = "test"
    places: bool = False
    queries: bool = True
    settings: Mapping[str, tuple | None] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name or self.name == SYNTHETIC:
            raise ValueError(f"a dataset format needs a non-empty name other than {SYNTHETIC!r}, got {self.name!r}")
        if not callable(self.loader):
            raise ValueError(f"format {self.name!r}: loader must be a function, got {type(self.loader).__name__}")
        if self.recall not in RECALL_CONVENTIONS:
            raise ValueError(f"format {self.name!r}: recall must be one of {RECALL_CONVENTIONS}, got {self.recall!r}")
        params = list(inspect.signature(self.loader).parameters.values())
        if not params or params[0].kind not in (params[0].POSITIONAL_ONLY, params[0].POSITIONAL_OR_KEYWORD):
            raise ValueError(f"format {self.name!r}: the loader's first parameter must be the dataset location")
        if "check_files" not in (p.name for p in params[1:]):
            raise ValueError(f"format {self.name!r}: the loader must take check_files=")
        if self.load_part is not None:
            part_params = set(inspect.signature(self.load_part).parameters)
            missing = [k for k in ("check_files", *self.settings) if k not in part_params]
            if missing:
                raise ValueError(f"format {self.name!r}: load_part must take {missing} as keywords")

    @property
    def options(self) -> list[str]:
        """The loader's keyword options that :func:`load` passes through (all but the location and ``check_files``)."""
        return [p for p in list(inspect.signature(self.loader).parameters)[1:] if p != "check_files"]

    @property
    def own_val(self) -> bool:
        """Whether a run trained on this format validates on its own data by default."""
        return self.val_part is not None and self.val_part != self.test_part


# One line per format: adding a format is a new module and a line here.
_REGISTERED = (
    DatasetFormat("pitts", pitts.load_pitts, recall="all", load_part=pitts.load_part,
                  settings={"pitts_set": pitts.PITTS_SETS}),
    DatasetFormat("gmberton", gmberton.load_gmberton, recall="all", load_part=gmberton.load_part),
    DatasetFormat("msls", msls.load_msls, recall="exclude", load_part=msls.load_part, test_part="val", places=True,
                  settings={"msls_val_subset": msls.MSLS_VAL_SUBSETS}),
    DatasetFormat("gsv-cities", gsv_cities.load_gsv_cities, recall="all", load_part=gsv_cities.load_part,
                  val_part=None, test_part=None, places=True, queries=False,
                  settings={"gsv_cities": None, "min_img_per_place": None}),
    DatasetFormat("nordland", nordland.load_nordland, recall="all", load_part=nordland.load_part, train=False,
                  val_part=None, settings={"nordland_protocol": ("auto", *nordland.NORDLAND_PROTOCOLS)}),
)

REGISTRY: dict[str, DatasetFormat] = {f.name: f for f in _REGISTERED}
FORMATS = tuple(REGISTRY)      # the formats of this package (REGISTRY also holds those registered later)
FORMAT_RECALL = {**{f.name: f.recall for f in _REGISTERED}, SYNTHETIC: SYNTHETIC_RECALL}


def register(fmt: DatasetFormat) -> DatasetFormat:
    """Add a format defined outside this package to :data:`REGISTRY` (a name already taken is refused)."""
    if not isinstance(fmt, DatasetFormat):
        raise ValueError(f"register takes a DatasetFormat, got {type(fmt).__name__}")
    if fmt.name in REGISTRY:
        raise ValueError(f"format {fmt.name!r} is already registered")
    REGISTRY[fmt.name] = fmt
    return fmt


def dataset_format(name: str) -> DatasetFormat:
    """The registered format ``name``; ValueError listing the known ones."""
    if name not in REGISTRY:
        raise ValueError(f"unknown dataset format {name!r}; choose one of {tuple(REGISTRY)}")
    return REGISTRY[name]


def recall_convention(format: str) -> str:
    """The Recall@N convention of a dataset format (the synthetic world's is ``"exclude"``)."""
    if format == SYNTHETIC:
        return SYNTHETIC_RECALL
    if format not in REGISTRY:
        raise ValueError(f"unknown dataset format {format!r}; choose one of {sorted((*REGISTRY, SYNTHETIC))}")
    return REGISTRY[format].recall


@dataclass(frozen=True)
class SplitSpec:
    """Which data a split is: format, folder and part (``train`` / ``val`` / ``test``)."""

    format: str
    root: str | None
    part: str

    def describe(self) -> str:
        return f"{self.format}:{self.part} ({self.root})" if self.root else f"{self.format}:{self.part}"


_HINT = {"val": ("a published validation set, e.g. --set data.val_format=pitts --set data.val_root=/data/Pittsburgh "
                 "(Pitts30k-val, as SALAD selects)"),
         "test": "e.g. --set data.test_format=msls --set data.test_root=/data/msls (MSLS-val)"}


def role_spec(train_format: str, train_root, role: str, format: str | None = None, root=None) -> SplitSpec:
    """The data a run trained on ``train_format`` (in ``train_root``) reads as ``role`` (train / val / test):
    ``format`` in ``root`` when given (``root`` None: ``train_root`` if the format is the training one),
    else the training format's own data when its line has it (:attr:`DatasetFormat.own_val`,
    :attr:`DatasetFormat.test_part`); the part is the format's ``val_part`` / ``test_part``. ValueError,
    with the setting to give, when there is no such data."""
    if role == "train":
        if train_format != SYNTHETIC and not dataset_format(train_format).train:
            raise ValueError(f"data.format={train_format!r} is a test set (no training part): train on another dataset "
                             f"and run python -m vpr_nb.evaluate --set data.test_format={train_format} --set data.test_root=...")
        return SplitSpec(train_format, train_root, "train")
    if format is None:
        f = None if train_format == SYNTHETIC else dataset_format(train_format)
        if f is not None and not (f.own_val if role == "val" else f.test_part is not None):
            why = "it is a training set only" if f.test_part is None else "its only labelled evaluation data is the test set"
            raise ValueError(f"data.format={train_format!r} has no default {role} data ({why}); give {_HINT[role]}")
        format = train_format
    if root is None and format != SYNTHETIC:
        if format != train_format:
            raise ValueError(f"data.{role}_format={format!r} needs its folder: set data.{role}_root=/path/to/{format}")
        root = train_root
    part = role if format == SYNTHETIC else getattr(dataset_format(format), f"{role}_part")
    if part is None:
        raise ValueError(f"data.{role}_format={format!r} has no {role} data; give {_HINT[role]}")
    return SplitSpec(format, None if root is None else str(root), part)


def load(root, format: str, *, check_files: bool = True, images_root=None, **options) -> GeoSplit:
    """Load a real VPR dataset split as a :class:`GeoSplit`.

    ``format`` is one of :data:`REGISTRY`: ``"pitts"`` (``root`` = the NetVLAD dbStruct ``.mat``;
    ``images_root`` defaults to the parent of its ``datasets/`` folder), ``"gmberton"``, ``"msls"``,
    ``"gsv-cities"`` (``images_root`` replaces ``root`` for ``Images/``), ``"nordland"``; each is
    described in its module (:mod:`vpr_nb.datasets.pitts`, ...). ``options`` go to the format's loader
    (:func:`load_pitts`, :func:`load_gmberton`, :func:`load_msls`, :func:`load_gsv_cities`,
    :func:`load_nordland`); an option the loader does not take raises ValueError listing those it
    accepts. ``check_files=True`` stats every listed image and names the first missing one.
    """
    spec = dataset_format(format)
    accepted = spec.options
    unknown = [k for k in options if k not in accepted]
    if unknown:
        raise ValueError(f"format {format!r} does not take option(s) {unknown}; it accepts {accepted}")
    if images_root is not None:
        if "images_root" not in accepted:
            users = " and ".join(repr(f.name) for f in REGISTRY.values() if "images_root" in f.options)
            raise ValueError(f"images_root is only used by the {users} formats, not {format!r}")
        options["images_root"] = images_root
    return spec.loader(root, check_files=bool(check_files), **options)


__all__ = ["DatasetFormat", "REGISTRY", "FORMATS", "RECALL_CONVENTIONS", "FORMAT_RECALL", "recall_convention", "load",
           "register", "dataset_format", "SYNTHETIC", "SplitSpec", "role_spec"]
