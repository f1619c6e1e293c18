"""The learning curves of a run as files: ``steps.csv`` (one row per optimiser step), ``epochs.csv`` (one row
per epoch) and, when the ``tensorboard`` package is installed, TensorBoard event files in ``tensorboard/``.

:class:`RunLog` is what :func:`vpr_nb.training.train` calls (``train(..., log=RunLog(folder))``): ``step`` after
every optimiser step, ``epoch`` after every epoch's validation. ``steps.csv`` is appended and flushed at
every step (follow it with ``tail -f``); ``epochs.csv`` is rewritten whole (:func:`vpr_nb.atomic.atomic_write`)
after every epoch. A resumed run continues both files: rows of the epochs it runs again (those after its
last checkpoint) are dropped first, and TensorBoard is told to purge them (``purge_step``). The x axis of
TensorBoard is the optimiser step, counted over the whole run; epoch scalars sit at their epoch's last step.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from .atomic import atomic_write

STEP_FIELDS = ("epoch", "step", "global_step", "loss", "collapsed_loss", "lr", "seconds")
EPOCH_FIELDS = ("epoch", "steps", "loss", "collapsed_loss", "mean_cosine", "lr", "seconds")
TENSORBOARD_DIR = "tensorboard"


def tensorboard_writer_class():
    """``torch.utils.tensorboard.SummaryWriter``, or None when the ``tensorboard`` package is not installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter


def _number(v):
    """A CSV cell: floats in full precision, NaN / None empty."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return repr(float(v)) if isinstance(v, float) else v


def _read_rows(path: Path, before_epoch: int) -> list[dict]:
    """The complete rows of a CSV written by :class:`RunLog` whose epoch is below ``before_epoch``."""
    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        rows = list(csv.DictReader(f))
    keep = []
    for r in rows:
        try:
            if None not in r.values() and int(r["epoch"]) < before_epoch:
                keep.append(r)
        except (KeyError, TypeError, ValueError):
            break                                   # a row cut off by a crash: the rest is not trusted
    return keep


def _csv_text(fields, rows) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


class RunLog:
    """``steps.csv``, ``epochs.csv`` and (optional) TensorBoard events of a run in ``folder``.

    ``tensorboard``: True (default) writes event files when the package is installed; :attr:`tensorboard`
    is then the folder, else None, and :attr:`note` says why (one line for the run's summary)."""

    def __init__(self, folder, tensorboard: bool = True):
        self.folder = Path(folder)
        self.steps_path, self.epochs_path = self.folder / "steps.csv", self.folder / "epochs.csv"
        writer = tensorboard_writer_class() if tensorboard else None
        self._writer_class = writer
        self.tensorboard = self.folder / TENSORBOARD_DIR if writer is not None else None
        self.note = (f"TensorBoard: {TENSORBOARD_DIR}/ (tensorboard --logdir {self.folder / TENSORBOARD_DIR})"
                     if writer is not None else
                     "TensorBoard: not installed, no event files (pip install tensorboard to get them)"
                     if tensorboard else "TensorBoard: off")
        self._steps_file = None
        self._step_writer = None
        self._epochs: list[dict] | None = None
        self._tb = None
        self._epoch_steps: dict[int, int] = {}
        self.global_step = 0

    def files(self) -> list[str]:
        """The names this log writes in its folder."""
        return ["steps.csv", "epochs.csv"] + ([TENSORBOARD_DIR] if self.tensorboard is not None else [])

    def _start(self, epoch: int) -> None:
        """First record of this process (epoch ``epoch``): keep the rows of earlier epochs, drop the rest."""
        kept = _read_rows(self.steps_path, epoch)
        self._epochs = _read_rows(self.epochs_path, epoch)
        self.folder.mkdir(parents=True, exist_ok=True)
        atomic_write(self.steps_path, lambda f: f.write(_csv_text(STEP_FIELDS, kept)), text=True, newline="")
        self._steps_file = open(self.steps_path, "a", newline="", encoding="utf-8")
        self._step_writer = csv.DictWriter(self._steps_file, fieldnames=STEP_FIELDS, extrasaction="ignore",
                                           lineterminator="\n")
        self.global_step = len(kept)
        for r in kept:
            self._epoch_steps[int(r["epoch"])] = self._epoch_steps.get(int(r["epoch"]), 0) + 1
        if self._writer_class is not None:
            self._tb = self._writer_class(str(self.tensorboard), purge_step=self.global_step if kept else None)

    def step(self, record: dict) -> None:
        """One optimiser step: ``epoch``, ``step`` (in the epoch, from 0), ``loss``, ``collapsed_loss``,
        ``lr`` (the step's learning rate), ``seconds`` (since the epoch began)."""
        if self._steps_file is None:
            self._start(int(record["epoch"]))
        row = {k: _number(v) for k, v in dict(record, global_step=self.global_step).items()}
        self._step_writer.writerow(row)
        self._steps_file.flush()
        self._epoch_steps[int(record["epoch"])] = self._epoch_steps.get(int(record["epoch"]), 0) + 1
        if self._tb is not None:
            for key in ("loss", "collapsed_loss", "lr"):
                v = record.get(key)
                if v is not None and math.isfinite(v):
                    self._tb.add_scalar(f"train/{key}", v, self.global_step)
        self.global_step += 1

    def epoch(self, record: dict) -> None:
        """One epoch: a :class:`vpr_nb.training.History` record (``epoch``, ``loss``, ``collapsed_loss``,
        ``mean_cosine``, ``lr``, ``seconds``, ``val`` = {N: Recall@N}); the row adds ``steps``, the optimiser
        steps logged in that epoch, and one ``val_R@N`` column per N."""
        if self._epochs is None:
            self._start(int(record["epoch"]))
        val = {f"val_R@{n}": v for n, v in sorted(record.get("val", {}).items(), key=lambda kv: int(kv[0]))}
        steps = self._epoch_steps.get(int(record["epoch"]), 0)
        row = {k: _number(v) for k, v in dict(record, steps=steps, **val).items() if k != "val"}
        self._epochs.append(row)
        recalls = sorted({k for r in self._epochs for k in r if k.startswith("val_R@")}, key=lambda k: int(k[6:]))
        fields = list(EPOCH_FIELDS) + recalls
        atomic_write(self.epochs_path, lambda f: f.write(_csv_text(fields, self._epochs)), text=True, newline="")
        if self._tb is not None:
            at = max(self.global_step - 1, 0)
            for key in ("loss", "collapsed_loss", "mean_cosine"):
                v = record.get(key)
                if v is not None and math.isfinite(v):
                    self._tb.add_scalar(f"epoch/{key}", v, at)
            for key, v in val.items():
                self._tb.add_scalar(f"val/{key[4:]}", v, at)
            self._tb.flush()

    def close(self) -> None:
        if self._steps_file is not None:
            self._steps_file.close()
            self._steps_file = None
        if self._tb is not None:
            self._tb.close()
            self._tb = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["RunLog", "STEP_FIELDS", "EPOCH_FIELDS", "tensorboard_writer_class"]
