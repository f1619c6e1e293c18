"""A run stopped by Ctrl-C: :class:`TrainingInterrupted`, the KeyboardInterrupt that says where it stopped."""
from __future__ import annotations


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`vpr_nb.training.train` or a run around it, saying where.

    ``epoch``: the epoch it stopped in (0-based; None outside the epochs), ``steps``: the optimiser steps of that
    epoch completed, ``phase``: what it was doing ("training", "validation", "checkpoint"; outside the epochs e.g.
    "loading the data", "testing"), ``saved_epoch``: the last epoch (0-based) whose full state is in ``last.pt``
    (None: none yet, or no checkpoint folder). A resumed run restarts after ``saved_epoch``: an epoch stopped
    part-way is run again from the start. A KeyboardInterrupt, so whatever catches one still catches it.
    """

    def __init__(self, epoch: int | None = None, steps: int = 0, phase: str = "training",
                 saved_epoch: int | None = None):
        self.epoch, self.steps, self.phase, self.saved_epoch = epoch, int(steps), phase, saved_epoch
        super().__init__(self.where())

    def where(self) -> str:
        """``at epoch N, step S`` (N counted from 1, S the optimiser steps of epoch N done; the phase added
        when it was not training), or ``while <phase>`` outside the epochs."""
        if self.epoch is None:
            return f"while {self.phase}"
        phase = "" if self.phase == "training" else f" ({self.phase})"
        return f"at epoch {self.epoch + 1}, step {self.steps}{phase}"

    def saved(self) -> str:
        """What ``last.pt`` holds, for a log line."""
        return "nothing saved yet" if self.saved_epoch is None else f"last saved: epoch {self.saved_epoch + 1}"


__all__ = ["TrainingInterrupted"]
