"""Small parsing helpers shared by the format modules: CSV columns, typed columns, image listing.

Private to :mod:`vpr_nb.datasets`: each raises FileNotFoundError / ValueError naming the file, the
column and the row that is wrong, so a loader's error says what to fix in the dataset on disk.
"""
from __future__ import annotations

import csv
import io
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")   # what list_images finds when no suffixes are given


def read_csv_columns(path: Path, required: Sequence[str]) -> tuple[list[str], dict[str, list[str]]]:
    """Read a CSV (leading unnamed pandas index column allowed) into columns of strings.

    Returns ``(header, {column: [values]})``; raises FileNotFoundError when the file is missing and
    ValueError naming the file for an empty file, a missing ``required`` column or a ragged row."""
    if not path.is_file():
        raise FileNotFoundError(f"CSV file not found: {path}")
    rows = list(csv.reader(io.StringIO(read_text(path), newline="")))
    if not rows or not any(h.strip() for h in rows[0]):
        raise ValueError(f"{path}: empty CSV file (no header)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; header is {header}")
    cols: dict[str, list[str]] = {h: [] for h in header if h}
    for line_no, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(header):
            raise ValueError(f"{path}, line {line_no}: {len(row)} fields but the header has {len(header)}")
        for h, v in zip(header, row):
            if h:
                cols[h].append(v.strip())
    return header, cols


def read_text(path: Path) -> str:
    """The UTF-8 text of ``path`` (a BOM is dropped); ValueError naming the file, the line and the
    re-encoding fix when it is not UTF-8 (e.g. a latin-1 export)."""
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise ValueError(f"{path}, line {line}: byte 0x{data[exc.start]:02x} at offset {exc.start} is not UTF-8; "
                         f"the file must be UTF-8 (as the dataset ships it): re-encode it, e.g. "
                         f"`iconv -f latin1 -t utf-8 {Path(path).name} > fixed.csv`") from None


def duplicates(values: Sequence[str]) -> dict[str, list[int]]:
    """``{value: [data rows, 1-based]}`` of every value that occurs more than once."""
    rows: dict[str, list[int]] = {}
    for i, v in enumerate(values, start=1):
        rows.setdefault(v, []).append(i)
    return {v: r for v, r in rows.items() if len(r) > 1}


def float_column(values: Sequence[str], path, column: str) -> np.ndarray:
    """The strings of CSV ``column`` of ``path`` as finite float64; ValueError names the first bad data row."""
    out = np.empty(len(values), dtype=np.float64)
    for i, v in enumerate(values):
        try:
            out[i] = float(v)
        except ValueError:
            raise ValueError(f"{path}: column {column!r}, data row {i + 1}: {v!r} is not a number") from None
    bad = np.flatnonzero(~np.isfinite(out))
    if len(bad):
        raise ValueError(f"{path}: column {column!r} is NaN/inf in {len(bad)} row(s), first data row "
                         f"{bad[0] + 1}; every image needs a valid geotag (drop those rows)")
    return out


def bool_column(values: Sequence[str], path, column: str) -> np.ndarray:
    """The strings of CSV ``column`` as bool (True/False/1/0 as pandas writes them); ValueError otherwise."""
    table = {"true": True, "false": False, "1": True, "0": False, "1.0": True, "0.0": False}
    try:
        return np.array([table[v.lower()] for v in values], dtype=bool)
    except KeyError as exc:
        raise ValueError(f"{path}: column {column!r} must be True/False, got {exc.args[0]!r}") from None


def list_images(folder: Path, suffixes: Sequence[str] | None = None) -> list[Path]:
    """Image files under ``folder`` (recursive, sorted). ``suffixes=None``: any of IMAGE_SUFFIXES in any
    case; otherwise exactly these (case-sensitive, as ``glob('**/*.jpg')``), other images are skipped
    with a warning that counts them."""
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder not found: {folder}")
    every = [p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and not p.is_dir()]
    if suffixes is None:
        files = sorted(every)
    else:
        files = sorted(p for p in every if p.suffix in suffixes)
        stray = len(every) - len(files)
        if stray:
            example = next(p.name for p in every if p.suffix not in suffixes)
            warnings.warn(f"{folder}: {stray} image file(s) not named *{'/*'.join(suffixes)} are ignored, "
                          f"as the reference code does (e.g. {example})", stacklevel=3)
    if not files:
        raise ValueError(f"no images ({', '.join(suffixes or IMAGE_SUFFIXES)}) found under {folder}")
    return files


def gmberton_split_dir(root: Path, split: str) -> Path:
    """The folder holding ``database/`` and ``queries/`` in gmberton's VPR-datasets-downloader layout, which
    the gmberton format and Nordland's gmberton copy share."""
    if (root / "database").is_dir() and (root / "queries").is_dir():
        return root
    for cand in (root / "images" / split, root / split):
        if (cand / "database").is_dir() and (cand / "queries").is_dir():
            return cand
    raise FileNotFoundError(f"{root}: expected images/{split}/{{database,queries}}/ (or database/ and queries/) "
                            f"in the gmberton VPR-datasets-downloader layout")
