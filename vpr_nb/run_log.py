"""The record of a run as files: ``steps.csv`` (one row per optimiser step), ``epochs.csv`` (one row per epoch),
``train.log`` (the run in plain text) and, when the ``tensorboard`` package is installed, TensorBoard event
files in ``tensorboard/``.

:class:`RunLog` is what :func:`vpr_nb.training.train` calls (``train(..., log=RunLog(folder))``): ``step`` after
every optimiser step, ``epoch`` after every epoch's validation. ``steps.csv`` is appended and flushed at
every step (follow it with ``tail -f``); ``epochs.csv`` is rewritten whole (:func:`vpr_nb.atomic.atomic_write`)
after every epoch. A resumed run continues both files: rows of the epochs it runs again (those after its
last checkpoint) are dropped first, and TensorBoard is told to purge them (``purge_step``). The x axis of
TensorBoard is the optimiser step, counted over the whole run; epoch scalars sit at their epoch's last step.

``train.log`` is appended, never rewritten (a resumed run adds its own lines): one timestamped line per event,
:meth:`RunLog.text`; a run writes its config and environment first (:meth:`RunLog.begin`, else the file opens
at the first step; lines given before are kept until then), every epoch adds its losses and recalls, and the
warnings shown while :meth:`RunLog.capture_warnings` is on are added as ``warning: ...`` lines.
"""
from __future__ import annotations

import contextlib
import csv
import datetime
import io
import math
import warnings
from pathlib import Path

from .atomic import atomic_write
from .cli import one_line

STEP_FIELDS = ("epoch", "step", "global_step", "loss", "collapsed_loss", "lr", "seconds")
EPOCH_FIELDS = ("epoch", "steps", "loss", "collapsed_loss", "mean_cosine", "lr", "seconds")
TENSORBOARD_DIR = "tensorboard"
TEXT_LOG = "train.log"


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


def epoch_line(record: dict, epochs: int | None = None) -> str:
    """A :class:`vpr_nb.training.History` record as one line of ``train.log`` (epochs counted from 1)."""
    def num(v, fmt=".4f"):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)
    val = " ".join(f"R@{n} {num(v)}" for n, v in sorted(record.get("val", {}).items(), key=lambda kv: int(kv[0])))
    of = f"/{epochs}" if epochs else ""
    return (f"epoch {int(record['epoch']) + 1}{of}: loss {num(record.get('loss'))} (collapsed "
            f"{num(record.get('collapsed_loss'))}), mean cosine {num(record.get('mean_cosine'))}, lr "
            f"{num(record.get('lr'), 'g')}, val {val}, {num(record.get('seconds'), '.1f')} s")


class RunLog:
    """``steps.csv``, ``epochs.csv``, ``train.log`` and (optional) TensorBoard events of a run in ``folder``.

    ``tensorboard``: True (default) writes event files when the package is installed; :attr:`tensorboard`
    is then the folder, else None, and :attr:`note` says why (one line for the run's summary). ``epochs``:
    the run's number of epochs, for the epoch lines of ``train.log`` ("epoch 2/6")."""

    def __init__(self, folder, tensorboard: bool = True, epochs: int | None = None):
        self.folder = Path(folder)
        self.text_path = self.folder / TEXT_LOG
        self.epochs = epochs
        self._text = None
        self._pending: list[str] = []
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
        return ["steps.csv", "epochs.csv", TEXT_LOG] + ([TENSORBOARD_DIR] if self.tensorboard is not None else [])

    def text(self, line: str) -> None:
        """One timestamped line of ``train.log`` (kept in memory until :meth:`begin`)."""
        entry = f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M:%S')} {one_line(line)}\n"
        if self._text is None:
            self._pending.append(entry)
            return
        self._text.write(entry)
        self._text.flush()

    def begin(self, lines=()) -> None:
        """Open ``train.log`` for appending, write ``lines`` (the run's config, its environment), then the
        lines given before."""
        if self._text is not None:
            return
        pending, self._pending = self._pending, []
        self.folder.mkdir(parents=True, exist_ok=True)
        self._text = open(self.text_path, "a", encoding="utf-8", errors="backslashreplace")
        for line in lines:
            self.text(line)
        self._text.writelines(pending)
        self._text.flush()

    @contextlib.contextmanager
    def capture_warnings(self):
        """Within: every warning shown is also a ``warning: ...`` line of ``train.log``, then shown as before
        (through the ``warnings.showwarning`` in place: the command's one-line channel, or Python's own)."""
        shown = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            self.text(f"warning: {message}" + ("" if category is UserWarning else f" ({category.__name__})"))
            shown(message, category, filename, lineno, file, line)
        warnings.showwarning = show
        try:
            yield self
        finally:
            warnings.showwarning = shown

    def _start(self, epoch: int) -> None:
        """First record of this process (epoch ``epoch``): keep the rows of earlier epochs, drop the rest; open
        ``train.log`` if :meth:`begin` has not."""
        self.begin()
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
        self.text(epoch_line(record, self.epochs))
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
        if self._text is not None:
            self._text.close()
            self._text = None
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


__all__ = ["RunLog", "STEP_FIELDS", "EPOCH_FIELDS", "TEXT_LOG", "epoch_line", "tensorboard_writer_class"]
