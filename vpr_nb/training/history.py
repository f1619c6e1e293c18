"""The record of a run: :class:`History`, per-epoch losses, training health and validation Recall@N."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class History:
    """Per-epoch records of a run: ``epochs[i]`` = {epoch, loss, collapsed_loss, mean_cosine, lr,
    seconds, val: {N: recall}}.

    Training health: ``collapsed_loss`` is the epoch's mean loss *if every descriptor were the same
    vector* (same batches, same miner): a run whose loss sits at it has learned nothing, e.g.
    M × margin for the triplet loss of Eq. (3) or M·log 2 for the CE loss of Eq. (8).
    ``mean_cosine`` is the mean pairwise cosine of the validation database descriptors
    (:func:`mean_pairwise_cosine`): near 1 means a collapsed embedding.

    Epoch-0 candidate (``TrainConfig.initial_candidate``): ``initial`` = {val, mean_cosine} of the starting
    weights, evaluated before any step; an epoch must *beat* it to be selected, and ``initial_won`` says
    when none did (then ``best_epoch`` stays -1 and the run ends with its starting weights). Printed
    1-based, ``best_epoch + 1`` is then 0. ``stopped_early``: the run ended by ``TrainConfig.patience``.
    """

    epochs: list[dict] = field(default_factory=list)
    best_epoch: int = -1
    best_recall: float = -1.0
    initial: dict | None = None
    stopped_early: bool = False

    def add_initial(self, val: dict, mean_cosine: float, select_n: int) -> None:
        """Record the starting weights' validation Recall@N as the epoch-0 candidate of the selection."""
        if self.epochs or self.initial is not None:
            raise ValueError("the epoch-0 candidate is recorded once, before the first epoch")
        if select_n not in val:
            raise ValueError(f"val holds Recall@N for N in {sorted(val)}, not the selection N={select_n}")
        self.initial = {"val": val, "mean_cosine": mean_cosine}
        self.best_epoch, self.best_recall = -1, float(val[select_n])

    @property
    def initial_won(self) -> bool:
        """True when the starting weights (the epoch-0 candidate) beat every trained epoch on validation."""
        return self.initial is not None and self.best_epoch == -1

    @property
    def epochs_since_best(self) -> int:
        """Epochs run since the selected one (the epoch-0 candidate counts as epoch -1)."""
        return (self.epochs[-1]["epoch"] - self.best_epoch) if self.epochs else 0

    def add_epoch(self, epoch: int, loss: float, collapsed_loss: float, mean_cosine: float, lr: float,
                  seconds: float, val: dict, select_n: int) -> bool:
        """Append one epoch's record; returns whether its validation Recall@``select_n`` (``TrainConfig.ns[0]``)
        beats the best so far (then ``best_epoch`` / ``best_recall`` move to this epoch)."""
        if select_n not in val:
            raise ValueError(f"val holds Recall@N for N in {sorted(val)}, not the selection N={select_n}; "
                             f"evaluate with ns that include it")
        self.epochs.append({"epoch": epoch, "loss": loss, "collapsed_loss": collapsed_loss,
                            "mean_cosine": mean_cosine, "lr": lr, "seconds": seconds, "val": val})
        if val[select_n] > self.best_recall:
            self.best_epoch, self.best_recall = epoch, float(val[select_n])
            return True
        return False

    @property
    def losses(self) -> list[float]:
        return [e["loss"] for e in self.epochs]

    def recalls(self, n: int = 1) -> list[float]:
        return [e["val"][n] for e in self.epochs]

    @property
    def collapsed_losses(self) -> list[float]:
        return [e["collapsed_loss"] for e in self.epochs]

    @property
    def mean_cosines(self) -> list[float]:
        return [e["mean_cosine"] for e in self.epochs]

    def to_dict(self) -> dict:
        initial = None if self.initial is None else \
            dict(self.initial, val={int(k): float(v) for k, v in self.initial["val"].items()})
        return {"epochs": [dict(e, val={int(k): float(v) for k, v in e["val"].items()}) for e in self.epochs],
                "best_epoch": self.best_epoch, "best_recall": self.best_recall,
                "initial": initial, "stopped_early": self.stopped_early}

    @classmethod
    def from_dict(cls, d: dict) -> "History":
        initial = d.get("initial")
        if initial is not None:
            initial = dict(initial, val={int(k): v for k, v in initial["val"].items()})
        return cls(epochs=[dict(e, val={int(k): v for k, v in e["val"].items()}) for e in d["epochs"]],
                   best_epoch=int(d["best_epoch"]), best_recall=float(d["best_recall"]),
                   initial=initial, stopped_early=bool(d.get("stopped_early", False)))

    def plot(self, axes=None, label: str | None = None):
        """Learning curves: training loss (left) and validation Recall@1 (right)."""
        import matplotlib.pyplot as plt   # only when plotting (a CLI run never draws)
        if axes is None:
            _, axes = plt.subplots(1, 2, figsize=(9, 3))
        x = [e["epoch"] + 1 for e in self.epochs]
        axes[0].plot(x, self.losses, marker="o", label=label)
        axes[0].set(xlabel="epoch", ylabel="mean training loss", title="loss")
        r1 = self.recalls(1)
        if self.initial is not None and 1 in self.initial["val"]:      # the epoch-0 candidate at x = 0
            x, r1 = [0] + x, [self.initial["val"][1]] + r1
        axes[1].plot(x, r1, marker="o", label=label)
        axes[1].set(xlabel="epoch", ylabel="val Recall@1", title="validation Recall@1", ylim=(0, 1))
        if label is not None:
            axes[1].legend()
        return axes
