"""Loaders for the real VPR datasets, all returning one geotagged split object, :class:`GeoSplit`.

One entry point, :func:`load` ``(root, format)``, with ``format`` one of :data:`FORMATS`; each format
is one module, which documents the convention it implements:

=====================  ==========================================================================
``"pitts"``            :mod:`~vpr_nb.datasets.pitts` Pittsburgh 30k/250k, NetVLAD ``dbStruct`` ``.mat``
``"gmberton"``         :mod:`~vpr_nb.datasets.gmberton` VPR-datasets-downloader ``@east@north@...@.jpg`` folders
``"msls"``             :mod:`~vpr_nb.datasets.msls` Mapillary SLS CSVs (``unique_cluster``, official val subset)
``"gsv-cities"``       :mod:`~vpr_nb.datasets.gsv_cities` GSV-Cities dataframes (a training set, no queries)
``"nordland"``         :mod:`~vpr_nb.datasets.nordland` Nordland, +-1 frame or +-10 frames (25 m)
=====================  ==========================================================================

The shared pieces, one module each:

- :mod:`~vpr_nb.datasets.registry` the format registry (one :class:`DatasetFormat` line per format:
  loader, ``load_part``, Recall@N convention, parts, places, queries, settings), :func:`load`,
  :func:`register`, :func:`recall_convention`;
- :mod:`~vpr_nb.datasets.split` :class:`GeoSplit` (a loader's listing) and :func:`drop_images`;
- :mod:`~vpr_nb.datasets.images` :func:`read_image`, :class:`ImageDataset`, the lazy
  :class:`ImageArray` and :func:`find_unreadable_images` (Pillow + torch ops, no torchvision; ImageNet
  normalisation by :func:`vpr_nb.image_tensors.normalize_imagenet`);
- :mod:`~vpr_nb.datasets.training_split` :class:`TrainingSplit`, a ``GeoSplit`` with its images: the
  :class:`vpr_nb.split.Split` that training and evaluation read (positives per region:
  :func:`vpr_nb.split.region_positives`, re-exported here);
- :mod:`~vpr_nb.datasets.utm` WGS84 lat/lon -> UTM (:func:`latlon_to_utm`, :func:`utm_zone`);
- :mod:`~vpr_nb.datasets.geotags` the geotag checks the formats run at load (Nordland has no geotag):
  an impossible UTM or lat/lon raises ValueError, an image far from its place, city or every other image
  is named in a warning.

Every loader checks that each listed image exists (``check_files=True``, one stat per file) and
names the first missing file; malformed inputs raise ``ValueError`` naming the file and field.

Adding a format: write ``vpr_nb/datasets/<format>.py`` with ``load_<format>(root, *, ...,
check_files=True) -> GeoSplit`` and ``load_part(root, part, *, check_files=True)`` and add one
:class:`DatasetFormat` line to ``registry._REGISTERED`` (or call :func:`register` from your own module);
the reproduction commands then train and evaluate on it (``--set data.format=<format>``).
"""
from __future__ import annotations

from ._parsing import IMAGE_SUFFIXES
from .gmberton import load_gmberton, parse_gmberton_name
from .gsv_cities import gsv_image_name, load_gsv_cities
from .images import ImageArray, ImageDataset, find_unreadable_images, read_image
from .msls import MSLS_CITIES, load_msls
from .nordland import NORDLAND_PROTOCOLS, load_nordland
from .pitts import load_pitts
from .registry import (
           FORMAT_RECALL,
           FORMATS,
           RECALL_CONVENTIONS,
           REGISTRY,
           DatasetFormat,
           SplitSpec,
           dataset_format,
           load,
           recall_convention,
           register,
           role_spec,
)
from .split import GeoSplit, drop_images
from .training_split import TrainingSplit
from .utm import latlon_to_utm, utm_zone
from ..split import region_positives

__all__ = ["FORMATS", "GeoSplit", "ImageDataset", "read_image", "load", "load_pitts", "load_gmberton", "load_msls",
           "load_gsv_cities", "load_nordland", "latlon_to_utm", "utm_zone", "parse_gmberton_name", "gsv_image_name",
           "ImageArray", "TrainingSplit", "RECALL_CONVENTIONS", "FORMAT_RECALL", "recall_convention",
           "find_unreadable_images", "drop_images",
           "MSLS_CITIES", "NORDLAND_PROTOCOLS", "IMAGE_SUFFIXES",
           # new with the package layout
           "DatasetFormat", "REGISTRY", "region_positives", "register", "dataset_format", "SplitSpec", "role_spec"]
