"""One training loop for every notebook and reproduction run.

:func:`train` runs epochs of optimiser steps whose losses come from a *batch source*:

- :class:`TripletSource` — NetVLAD-style weakly supervised triplets (Arandjelović et al., CVPR 2016,
  Sec. 4): at the start of every epoch (and every ``cache_refresh`` queries) the descriptors of the
  training images are recomputed; each query gets its best potential positive (within the training
  radius) and its M hardest negatives (beyond the evaluation radius) from
  :func:`vpr_nb.mining.mine_triplets`; the loss is a :class:`vpr_nb.losses.TripletFamilyLoss` object,
  one of DW-T-Loss's Eqs. (3), (4)x(3), (5)-(8), (9).
- :class:`PlaceBatchSource` — GSV-Cities / CliqueMining-style batches of P places x K images
  (from :func:`vpr_nb.samplers.random_place_batches` or :func:`vpr_nb.samplers.clique_batches`) with a
  :class:`vpr_nb.losses.MultiSimilarityLoss` object (loss and miner); with ``loss_groups`` one loss per
  slice of places, summed (CliqueMining's training step: GSV-Cities half + clique half).

A source builds batches; the loss object it is given holds the loss's parameters (margin, sigma, eps, ...).
:func:`train` is the loop; its parts are named helpers: :func:`setup_device` (device and AMP),
:func:`wrap_ddp` / :func:`unwrap_ddp`, :func:`resume_state`, :func:`make_scheduler` /
:func:`scheduler_step`, :func:`evaluate_epoch` and :func:`save_training_state` / :func:`save_checkpoint`.

Defaults follow DW-T-Loss / NetVLAD: SGD (momentum 0.9, weight decay 1e-3) and StepLR(5, 0.5).
Every epoch is seeded from ``(seed, epoch)``, so a run interrupted after epoch e and resumed from its
checkpoint ends with the same weights as an uninterrupted run. Checkpoints are written atomically
(temporary file + rename) and read with ``torch.load(..., weights_only=True)``.
"""
from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from . import losses as L
from ._checks import check_int, check_positive, validated_inputs
from .atomic import atomic_write
from .evaluation import as_image_array, compute_descriptors, evaluate_on_split, images_to_tensor, mean_pairwise_cosine
from .mining import mine_triplets
from .split import Split, check_split

OPTIMIZERS = ("sgd", "adam", "adamw")
SCHEDULERS = ("step", "linear")


@dataclass
class TrainConfig:
    """Hyper-parameters of :func:`train` (defaults: DW-T-Loss / NetVLAD, scaled to the tiny world)."""

    epochs: int = 10
    optimizer: str = "sgd"
    lr: float = 0.05                 # NetVLAD used 1e-3 for VGG16; 0.05 suits the small CNN + mean-per-query loss
    momentum: float = 0.9
    weight_decay: float = 1e-3
    scheduler: str = "step"          # "step": StepLR per epoch; "linear": LinearLR per optimiser step
    step_size: int = 5               # StepLR: multiply lr by gamma every step_size epochs
    gamma: float = 0.5
    linear_end_factor: float = 0.2   # LinearLR: lr goes 1 -> end_factor over linear_steps steps (SALAD)
    linear_steps: int = 4000
    seed: int = 0
    ns: tuple[int, ...] = (1, 5, 10)
    restore_best: bool = True        # end with the best-on-validation weights
    initial_candidate: bool = False  # the starting weights compete in the selection ("epoch 0", History.initial)
    patience: int | None = None      # stop after this many epochs without a better val R@ns[0] (None: never)
    device: str = "auto"             # "auto" (cuda if available), "cpu", "cuda", "cuda:1", ...
    amp: bool = False                # autocast: bfloat16 on CPU / bf16-capable GPUs, else float16 + GradScaler

    def __post_init__(self):
        self.epochs = check_int(self.epochs, "epochs")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        check_positive(self.lr, "lr")
        check_positive(self.momentum, "momentum", allow_zero=True)
        check_positive(self.weight_decay, "weight_decay", allow_zero=True)
        if self.scheduler not in SCHEDULERS:
            raise ValueError(f"scheduler must be one of {SCHEDULERS}, got {self.scheduler!r}")
        self.step_size = check_int(self.step_size, "step_size")
        check_positive(self.gamma, "gamma")
        check_positive(self.linear_end_factor, "linear_end_factor")
        self.linear_steps = check_int(self.linear_steps, "linear_steps")
        if not isinstance(self.device, str) or not (self.device in ("auto", "cpu") or self.device.startswith("cuda")):
            raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {self.device!r}")
        self.seed = check_int(self.seed, "seed", minimum=0)
        self.patience = None if self.patience is None else check_int(self.patience, "patience")
        for name in ("restore_best", "amp", "initial_candidate"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        self.ns = tuple(check_int(n, "ns entry") for n in self.ns)
        if not self.ns:
            raise ValueError("ns must list at least one N for Recall@N, e.g. (1, 5, 10)")


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


# ------------------------------------------------------------------------------ batch sources
class TripletSource:
    """NetVLAD triplets on a split: anchors are the split's queries (optionally also its database).

    Args:
        split: a :class:`vpr_nb.split.Split` with queries (headings if ``max_heading_diff`` is set);
            potential positives are ``split.positives(train_pos_radius)`` and the images never used as
            negatives ``split.positives(neg_radius)``, both inside each region (city) of the split.
        loss: a :class:`vpr_nb.losses.TripletFamilyLoss` object holding its parameters:
            ``TripletLoss(margin)`` (Eq. 3), ``WeightedTripletLoss(margin, sigma, eps)`` (Eq. 4 x Eq. 3),
            ``CETripletLoss()`` (Eqs. 5-8), ``DWTripletLoss(sigma, eps)`` (Eq. 9). Default: Eq. (3) with
            the paper's margin.
        batch_size: queries per optimiser step; num_negatives: M; num_candidates: random negatives
            sampled per query; cache_refresh: recompute the descriptor cache every this many queries
            (None: once per epoch). pytorch-NetVlad uses M=10, 1000 candidates and a refresh every
            1000 of Pittsburgh30k's 7416 training queries; the defaults here (M=5, 300 candidates,
            once per epoch = every ~580 queries of the tiny city) scale that to the tiny world.
        max_heading_diff: keep only positives facing the query's way (see ``mine_triplets``).
        neg_radius: negatives lie beyond this many metres (default: the split's evaluation radius,
            NetVLAD's 25 m). On a densely sampled route (positives = +-1 frame) a larger radius keeps
            near-duplicates of the positive out of the negatives.
    The per-step loss is the loss summed over the step's triplets divided by the number of queries.
    """

    def __init__(self, split, loss: L.TripletFamilyLoss = L.TripletLoss(), *, batch_size: int = 16,
                 num_negatives: int = 5, num_candidates: int = 300, cache_refresh: int | None = None,
                 max_heading_diff: float | None = None, neg_radius: float | None = None):
        if not isinstance(loss, L.TripletFamilyLoss):
            raise ValueError(f"loss must be a triplet-family loss object (vpr_nb.losses.TripletLoss(margin), "
                             f"WeightedTripletLoss(margin, sigma, eps), CETripletLoss(), DWTripletLoss(sigma, eps)), "
                             f"got {loss!r}")
        check_split(split, "the training split")
        if not split.has_queries or len(split.db_utm) == 0:
            raise ValueError(f"the training split {split.name} has no queries or no database images: triplets "
                             "need both (train on places instead)")
        self.split, self.loss = split, loss
        self.batch_size = check_int(batch_size, "batch_size")
        self.num_negatives = check_int(num_negatives, "num_negatives")
        self.num_candidates = check_int(num_candidates, "num_candidates")
        self.cache_refresh = None if cache_refresh is None else check_int(cache_refresh, "cache_refresh")
        self.max_heading_diff = max_heading_diff
        self.neg_radius = split.pos_radius if neg_radius is None else check_positive(neg_radius, "neg_radius")
        self.q, self.db = split.q_images, split.db_images
        self.positives = split.positives(split.train_pos_radius)   # per query, inside its region
        self.near = split.positives(self.neg_radius)
        self.neg_cache: dict[int, np.ndarray] = {}

    def state_dict(self) -> dict:
        keys = sorted(self.neg_cache)
        vals = np.stack([self.neg_cache[k] for k in keys]) if keys else np.zeros((0, self.num_negatives), np.int64)
        return {"keys": torch.as_tensor(np.asarray(keys, np.int64)), "values": torch.as_tensor(vals)}

    def load_state_dict(self, state: dict) -> None:
        self.neg_cache = {int(k): v.numpy() for k, v in zip(state["keys"], state["values"])}

    def _descriptors(self, model):
        model = unwrap_ddp(model)
        q, db = compute_descriptors(model, self.split.q_images), compute_descriptors(model, self.split.db_images)
        if not (np.isfinite(q).all() and np.isfinite(db).all()):
            raise NotFinite("descriptors of the training images")
        return q, db

    def untrainable(self) -> dict[str, int]:
        """Training queries that can never give a triplet, by reason, from the data alone: ``no_positive``
        (none within ``split.train_pos_radius``), ``heading`` (positives, none facing within
        ``max_heading_diff``), ``negatives`` (fewer than M database images beyond ``neg_radius``); and
        ``trainable``, the rest, out of ``queries``."""
        if getattr(self, "_untrainable", None) is None:
            n_db, no_pos, heading, few = len(self.db), 0, 0, 0
            s, h = self.split, self.max_heading_diff
            qh, dh = (None, None) if h is None or s.q_heading is None or s.db_heading is None else \
                (np.asarray(s.q_heading, dtype=np.float64), np.asarray(s.db_heading, dtype=np.float64))
            for i, (pos, near) in enumerate(zip(self.positives, self.near)):
                if len(pos) == 0:
                    no_pos += 1
                elif qh is not None and not (np.abs((dh[pos] - qh[i] + 180.0) % 360.0 - 180.0) <= h).any():
                    heading += 1
                elif n_db - len(near) < self.num_negatives:
                    few += 1
            q = len(self.positives)
            self._untrainable = {"queries": q, "no_positive": no_pos, "heading": heading, "negatives": few,
                                 "trainable": q - no_pos - heading - few}
        return self._untrainable

    def no_step_reason(self) -> str:
        """Why an epoch formed no triplet (for :func:`train_epoch`'s error)."""
        u, s = self.untrainable(), self.split
        parts = [f"no positives within {s.train_pos_radius:g} m for {u['no_positive']} of {u['queries']} "
                 f"training queries"]
        fixes = ["check the query and database positions or use a larger training radius (the split's "
                 "train_pos_radius)"] if u["no_positive"] else []
        if u["heading"]:
            parts.append(f"no positive facing within {self.max_heading_diff:g} degrees for {u['heading']} more")
            fixes.append("allow more heading difference (source.max_heading_diff)")
        if u["negatives"]:
            parts.append(f"fewer than {self.num_negatives} database images beyond {self.neg_radius:g} m (negatives) "
                         f"for {u['negatives']} more")
            fixes.append("use fewer negatives (source.num_negatives)")
        return "; ".join(parts) + f" (training split {s.name})" + (": " + ", or ".join(fixes) if fixes else "")

    def _collapsed_loss(self, b: int, m: int, dim: int, geo) -> float:
        """The loss of this step's triplets if every descriptor were the same unit vector."""
        e = torch.zeros(b, dim, dtype=geo.dtype)
        e[:, 0] = 1.0
        return float(self.loss(e, e, e.unsqueeze(1).expand(b, m, dim), geo.cpu()))

    def steps(self, model, rng: np.random.Generator, shard: tuple[int, int] = (0, 1), device=None):
        """Yield one loss tensor per optimiser step of an epoch.

        With ``shard=(rank, world)`` (distributed training) every process mines the whole batch
        (same random draws, same negative cache) and computes the loss of its share of the
        triplets, scaled so that the average over processes equals the single-process loss.
        """
        rank, world = shard
        s = self.split
        if self.untrainable()["trainable"] == 0:
            return                                 # no query can give a triplet: train_epoch says why
        heading = {}
        if self.max_heading_diff is not None:
            heading = dict(q_heading=s.q_heading, db_heading=s.db_heading, max_heading_diff=self.max_heading_diff)
        order = rng.permutation(len(self.q))
        refresh = self.cache_refresh or len(order)
        for start in range(0, len(order), self.batch_size):
            if start == 0 or start // refresh != (start - self.batch_size) // refresh:  # refresh point crossed
                q_desc, db_desc = self._descriptors(model)
            ids = order[start:start + self.batch_size]
            with validated_inputs():        # the descriptors were checked finite when computed (_descriptors)
                tb = mine_triplets(q_desc, db_desc, s.q_utm, s.db_utm, ids, train_pos_radius=s.train_pos_radius,
                                   neg_radius=self.neg_radius, num_negatives=self.num_negatives,
                                   num_candidates=min(self.num_candidates, len(self.db)),
                                   neg_cache=self.neg_cache, rng=rng, positives=[self.positives[i] for i in ids],
                                   near=[self.near[i] for i in ids], **heading)
            v = np.flatnonzero(tb.valid)
            total = len(v)
            if total < world:
                continue                       # every process skips the same steps
            v = v[rank::world]
            b, m = len(v), self.num_negatives
            x = images_to_tensor(np.concatenate([self.q[tb.query[v]], self.db[tb.positive[v]],
                                                 self.db[tb.negatives[v].reshape(-1)]])).to(device)
            out = model(x).float()
            if not torch.isfinite(out).all():
                raise NotFinite("descriptors")
            q, p, n = out[:b], out[b:2 * b], out[2 * b:].view(b, m, -1)
            geo = torch.as_tensor(tb.geo_qp[v], dtype=out.dtype, device=out.device)
            self.last_collapsed_loss = self._collapsed_loss(b, m, out.shape[1], geo) * (world / total)
            yield self.loss(q, p, n, geo) * (world / total)


class PlaceBatchSource:
    """Batches of P places x K images with the Multi-Similarity loss (Wang et al., CVPR 2019, Eq. 6).

    ``make_batches(model, epoch, rng)`` returns an int array ``(num_batches, P, K)`` of indices into
    ``images`` (for example :func:`vpr_nb.samplers.random_place_batches` or
    :func:`vpr_nb.samplers.clique_batches` on descriptors from ``model``); images in the same place slot
    share a label. ``loss`` is a :class:`vpr_nb.losses.MultiSimilarityLoss` object (its ``alpha``, ``beta``,
    ``base`` and ``miner_epsilon``; default: the SALAD / GSV-Cities recipe), called as
    ``loss(embeddings, labels)``.

    ``loss_groups=(P1, P2, ...)`` (summing to P) splits every batch into consecutive slices of places and
    computes one loss (with its own miner) per slice, then sums them: the places of two slices are never
    each other's negatives. This is CliqueMining's training step (``serizba/cliquemining``
    ``training_step``: one MS loss over the GSV-Cities places, one over the MSLS clique places, summed),
    ``PlaceBatchSource(images, make_batches, loss_groups=(30, 30))``. None: one loss over all P places.
    """

    def __init__(self, images, make_batches: Callable, *, loss: L.MultiSimilarityLoss = L.MultiSimilarityLoss(),
                 loss_groups: tuple[int, ...] | None = None):
        self.x = as_image_array(images)
        images_to_tensor(self.x[:1])           # validates shape and dtype
        if not callable(make_batches):
            raise ValueError("make_batches must be a callable (model, epoch, rng) -> (num_batches, P, K) indices")
        if isinstance(loss, L.TripletFamilyLoss) or not callable(loss):
            raise ValueError(f"loss must be a place-batch loss called as loss(embeddings, labels), e.g. "
                             f"vpr_nb.losses.MultiSimilarityLoss(alpha, beta, base, miner_epsilon), got {loss!r}; "
                             f"triplet-family losses go with TripletSource")
        if loss_groups is not None:
            loss_groups = tuple(check_int(g, "loss_groups entry") for g in loss_groups)
            if not loss_groups:
                raise ValueError("loss_groups must list the places of each loss, e.g. (30, 30), or be None")
        self.make_batches, self.loss, self.loss_groups = make_batches, loss, loss_groups
        self.epoch = 0

    def state_dict(self) -> dict:
        """The sampler's state when ``make_batches`` has one (e.g. CliqueMining's group descriptors), so
        that a resumed run draws the same batches as an uninterrupted one."""
        sd = getattr(self.make_batches, "state_dict", None)
        return {"sampler": sd()} if callable(sd) else {}

    def load_state_dict(self, state: dict) -> None:
        if "sampler" in state:
            load = getattr(self.make_batches, "load_state_dict", None)
            if not callable(load):
                raise ValueError("the checkpoint holds a sampler state but this make_batches has no "
                                 "load_state_dict; resume with the same source.sampler")
            load(state["sampler"])

    def no_step_reason(self) -> str:
        """Why an epoch took no step (for :func:`train_epoch`'s error)."""
        return ("make_batches gave no batch of places: check that enough places have images_per_place images "
                "(source.places_per_batch, source.images_per_place, source.batches_per_epoch)")

    def _groups(self, p: int, shard: tuple[int, int]) -> list[np.ndarray]:
        """The place slots of each loss group that this process (``shard=(rank, world)``) takes."""
        sizes = self.loss_groups or (p,)
        if sum(sizes) != p:
            raise ValueError(f"loss_groups {sizes} cover {sum(sizes)} places but make_batches gives {p} per batch")
        rank, world = shard
        if min(sizes) < world:
            raise ValueError(f"every loss group needs at least one place per process: loss_groups {sizes}, "
                             f"{world} processes")
        starts = np.concatenate([[0], np.cumsum(sizes)])
        return [np.arange(a, b)[rank::world] for a, b in zip(starts[:-1], starts[1:])]

    def steps(self, model, rng: np.random.Generator, shard: tuple[int, int] = (0, 1), device=None):
        """One loss per batch (the sum over ``loss_groups``); with ``shard=(rank, world)`` each process
        takes every world-th place of each group."""
        batches = np.asarray(self.make_batches(model, self.epoch, rng))
        if batches.ndim != 3 or not np.issubdtype(batches.dtype, np.integer):
            raise ValueError(f"make_batches must return an integer array (num_batches, P, K), got {batches.shape}")
        if batches.size and (batches.min() < 0 or batches.max() >= len(self.x)):
            raise ValueError(f"make_batches returned indices outside [0, {len(self.x) - 1}]")
        groups = self._groups(batches.shape[1], shard)
        batches = batches[:, np.concatenate(groups)]
        k = batches.shape[2]
        ends = np.cumsum([len(g) * k for g in groups])
        parts = [(slice(e - len(g) * k, e), torch.arange(len(g), device=device).repeat_interleave(k))
                 for g, e in zip(groups, ends)]
        for batch in batches:
            emb = model(images_to_tensor(self.x[batch.reshape(-1)]).to(device)).float()
            if not torch.isfinite(emb).all():
                raise NotFinite("descriptors")
            same = torch.nn.functional.normalize(torch.ones_like(emb.detach()), dim=1)   # every descriptor equal
            if len(parts) == 1:
                self.last_collapsed_loss = float(self.loss(same, parts[0][1]))
                yield self.loss(emb, parts[0][1])
            else:
                self.last_collapsed_loss = float(sum(self.loss(same[s], y) for s, y in parts))
                yield sum(self.loss(emb[s], y) for s, y in parts)


# ------------------------------------------------------------------------------ checkpoints
def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` with ``torch.save`` atomically (:func:`vpr_nb.atomic.atomic_write`): a temporary file in
    the same folder, then rename. A failed write (e.g. a full disk) raises one OSError naming the file and
    leaves the previous checkpoint and no temporary file."""
    # a file object: the archive is named "archive", not after the random temporary name, so equal states
    # give equal bytes
    return atomic_write(path, lambda f: torch.save(state, f))


RUN_HINT = ("build the model with the settings it was trained with (vpr_nb.evaluate: --run its run folder, "
            "or the same --set model.* values)")


def load_checkpoint(path) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: tensors and plain data
    only), through :func:`vpr_nb.models.read_weights`: one-line errors naming the file when it is missing,
    truncated, not a torch file or holds pickled objects (never unpickled)."""
    from .models import read_weights
    return dict(read_weights(path, "checkpoint"))


def load_weights(model: torch.nn.Module, state, path) -> None:
    """``model.load_state_dict(state)`` for the weights read from ``path``, checked by
    :func:`vpr_nb.models.load_state_checked`: a one-line ValueError naming the file and what differs
    (missing / unexpected tensors, shapes) when they belong to another architecture or width."""
    from .models import load_state_checked
    load_state_checked(model, state, path, hint=RUN_HINT)


def amp_dtype(device: torch.device) -> torch.dtype:
    """The autocast dtype of ``TrainConfig.amp``: bfloat16 on CPU and on GPUs that support it, else float16
    (then :func:`train` scales the loss with a ``GradScaler`` so that small gradients do not underflow)."""
    if device.type == "cuda" and not torch.cuda.is_bf16_supported():
        return torch.float16
    return torch.bfloat16


def resolve_device(name: str = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; a CUDA name without CUDA is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available; use device='cpu' or 'auto'")
    return torch.device(name)


# ------------------------------------------------------------------------------ the parts of train()
@dataclass(frozen=True)
class DeviceSetup:
    """Where and in which precision :func:`train` runs: ``amp_dtype`` is ``None`` without AMP; ``scaler``
    is a ``GradScaler`` only for float16 autocast (bfloat16 needs none)."""

    device: torch.device
    amp_dtype: torch.dtype | None
    scaler: torch.amp.GradScaler | None

    def autocast(self):
        """The autocast context of the training steps (disabled without AMP)."""
        return torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None)


def setup_device(cfg: TrainConfig) -> DeviceSetup:
    """The device of ``cfg.device`` (:func:`resolve_device`) and, with ``cfg.amp``, the autocast dtype
    (:func:`amp_dtype`) and, for float16, a ``GradScaler``."""
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(cfg).__name__}")
    device = resolve_device(cfg.device)
    dtype = amp_dtype(device) if cfg.amp else None
    scaler = torch.amp.GradScaler(device.type) if dtype == torch.float16 else None
    return DeviceSetup(device, dtype, scaler)


def distributed_rank() -> tuple[int, int]:
    """(rank, world size) of an initialised ``torch.distributed`` process group, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def wrap_ddp(model: torch.nn.Module, device: torch.device, world: int) -> torch.nn.Module:
    """``model`` in ``DistributedDataParallel`` when ``world`` > 1 (gradients averaged over processes), else
    ``model`` itself. ``find_unused_parameters``: e.g. SmallCNN's global-token layer is unused by pooling
    aggregators."""
    if world <= 1:
        return model
    ids = [device.index] if device.type == "cuda" else None
    return torch.nn.parallel.DistributedDataParallel(model, device_ids=ids, find_unused_parameters=True)


def unwrap_ddp(net: torch.nn.Module) -> torch.nn.Module:
    """The model inside a ``DistributedDataParallel`` wrapper (:func:`wrap_ddp`), or ``net`` itself."""
    return net.module if isinstance(net, torch.nn.parallel.DistributedDataParallel) else net


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """SGD (momentum, weight decay), Adam or AdamW over the model's trainable parameters (``cfg.optimizer``).

    Adam and AdamW run torch's fused update (one kernel for all parameters) where every parameter is a
    floating-point tensor on the CPU or a CUDA device: the unfused update takes the square root of its second
    moment through MKL's vector maths on the CPU, which rounds differently on Intel and AMD processors, so the
    same run trained other weights on the two (:mod:`vpr_nb.kernels`). The fused kernel is also faster."""
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError("the model has no trainable parameters")
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    fused = {"fused": True} if all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params) else {}
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, **fused)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, **fused)


def make_scheduler(opt: torch.optim.Optimizer, cfg: TrainConfig):
    """``cfg.scheduler="step"``: StepLR(step_size, gamma), stepped once per epoch (NetVLAD / DW-T-Loss);
    ``"linear"``: LinearLR(1 -> linear_end_factor over linear_steps), stepped per optimiser step (SALAD).
    :func:`scheduler_step` does the stepping."""
    if cfg.scheduler == "step":
        return torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.step_size, gamma=cfg.gamma)
    return torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0, end_factor=cfg.linear_end_factor,
                                             total_iters=cfg.linear_steps)


SCHEDULER_STEPS = {"step": "epoch", "linear": "batch"}    # when each scheduler of SCHEDULERS advances


def scheduler_step(sched, cfg: TrainConfig, after: str) -> None:
    """Advance ``sched`` if ``cfg.scheduler`` steps ``after`` this point: ``"batch"`` (an optimiser step) or
    ``"epoch"`` (see :data:`SCHEDULER_STEPS`)."""
    if after not in ("batch", "epoch"):
        raise ValueError(f"after must be 'batch' or 'epoch', got {after!r}")
    if SCHEDULER_STEPS[cfg.scheduler] == after:
        sched.step()


def optimizer_step(loss: torch.Tensor, opt: torch.optim.Optimizer, scaler=None) -> None:
    """Back-propagate ``loss`` and take one optimiser step; with a float16 ``scaler`` the loss is scaled and
    the gradients unscaled before the step."""
    opt.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    else:
        loss.backward()
        opt.step()


def batch_loss(loss: torch.Tensor, world: int) -> float:
    """The whole batch's loss for the log: this process's share averaged over the ``world`` processes."""
    logged = loss.detach()
    if world > 1:
        logged = logged.clone()
        torch.distributed.all_reduce(logged)
        logged = logged / world
    return logged.item()


class NotFinite(ValueError):
    """Training diverged: ``what`` (the loss, the weights, the descriptors) became NaN or inf. Raised by the
    sources and :func:`train_epoch`, which names the step and the learning rate."""

    def __init__(self, what: str, value: str = "NaN or inf"):
        super().__init__(f"the {what} became {value}")
        self.what, self.value = what, value


def _finite_weights(params) -> bool:
    """All of ``params`` finite (one reduction per tensor; NaN and inf propagate through the sums)."""
    sums = [p.detach().sum(dtype=torch.float32) for p in params if p.numel()]
    return not sums or bool(torch.isfinite(torch.stack(sums)).all())


def _no_step_reason(source, world: int) -> str:
    reason = getattr(source, "no_step_reason", None)
    text = reason() if callable(reason) else "the source gave no batch"
    if world > 1:
        text += f" (with {world} processes a step needs at least {world} valid triplets)"
    return text


def train_epoch(net: torch.nn.Module, source, epoch: int, cfg: TrainConfig, opt, sched, setup: DeviceSetup,
                shard: tuple[int, int] = (0, 1), log=None) -> tuple[float, float]:
    """One epoch of optimiser steps on the losses of ``source``, seeded from ``(cfg.seed, epoch)``.

    Returns the epoch's mean loss and mean collapsed loss (the loss if every descriptor were equal, as
    reported by the source after each step; NaN when it reports none). ``log.step(record)`` (e.g. a
    :class:`vpr_nb.run_log.RunLog`) gets every step's epoch, step, loss, collapsed loss, lr and seconds.
    ValueError when the loss, the weights or the descriptors become NaN/inf (naming the step and the
    learning rate) and when the epoch takes no optimiser step (saying why, e.g. no positives), since the
    model would then not be trained at all.
    """
    rng = np.random.default_rng([cfg.seed, epoch])
    torch.manual_seed(cfg.seed * 100_003 + epoch)
    if hasattr(source, "epoch"):
        source.epoch = epoch
    unwrap_ddp(net).train()
    total, collapsed, steps = 0.0, 0.0, 0
    params, t0 = [p for g in opt.param_groups for p in g["params"]], time.perf_counter()
    lr = opt.param_groups[0]["lr"]
    if not _finite_weights(params):
        raise ValueError(f"the model's weights hold NaN or inf at the start of epoch {epoch}, before any step of "
                         f"it: check the weights it started from (the backbone's file, a resumed checkpoint)")
    try:
        with setup.autocast():
            for loss in source.steps(net, rng, shard=shard, device=setup.device):
                lr = opt.param_groups[0]["lr"]
                if not torch.isfinite(loss):
                    raise NotFinite("loss", str(loss.item()))
                optimizer_step(loss, opt, setup.scaler)
                if not _finite_weights(params):
                    raise NotFinite("weights")
                scheduler_step(sched, cfg, "batch")
                logged = batch_loss(loss, shard[1])
                total, steps = total + logged, steps + 1
                last = float(getattr(source, "last_collapsed_loss", float("nan")))
                collapsed += last
                if log is not None:
                    log.step({"epoch": epoch, "step": steps - 1, "loss": logged, "collapsed_loss": last, "lr": lr,
                              "seconds": time.perf_counter() - t0})
    except ValueError as exc:             # NotFinite, or a check of the model's own layers on its activations
        if not isinstance(exc, NotFinite) and "NaN or inf" not in str(exc):
            raise
        if epoch == 0 and steps == 0:
            raise ValueError(f"{exc} before the first optimiser step: the untrained model gives NaN/inf on the "
                             f"training images; check the images and the weights it started from") from None
        raise ValueError(f"training diverged: {exc} at optimiser step {steps + 1} of epoch {epoch} (lr {lr:g}); "
                         f"lower train.lr, e.g. --set train.lr={lr / 10:g}") from None
    if steps == 0:
        raise ValueError(f"epoch {epoch} took no optimiser step, so nothing would be trained: "
                         f"{_no_step_reason(source, shard[1])}")
    return total / steps, collapsed / steps


def evaluate_epoch(model: torch.nn.Module, val_split: Split, ns: tuple[int, ...]) -> tuple[dict, float]:
    """Validation Recall@N of ``model`` on ``val_split`` (its positives and Recall@N convention,
    :func:`vpr_nb.evaluation.evaluate_on_split`) and the mean pairwise cosine of its database descriptors
    (:func:`mean_pairwise_cosine`; NaN for a one-image database)."""
    check_split(val_split, "val_split")
    val_db = compute_descriptors(model, val_split.db_images)
    val = evaluate_on_split(val_db, compute_descriptors(model, val_split.q_images), val_split, ns)
    return val, mean_pairwise_cosine(val_db) if len(val_db) > 1 else float("nan")


def training_state(model, opt, sched, source, history: History, epoch: int, best_state: dict, cfg: TrainConfig,
                   scaler=None) -> dict:
    """Everything :func:`resume_state` needs to continue after ``epoch`` (plain tensors and containers)."""
    return {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
            "source": source.state_dict(), "history": history.to_dict(), "epoch": epoch,
            "best_model": best_state, "config": asdict(cfg),
            **({"scaler": scaler.state_dict()} if scaler is not None else {})}


def save_epoch_checkpoints(ckdir: Path, state: dict, improved: bool) -> None:
    """``ckdir/last.pt`` = the full training state; ``ckdir/best.pt`` = the best weights when this epoch
    ``improved`` on validation (both written atomically by :func:`save_checkpoint`)."""
    if improved:
        save_checkpoint(ckdir / "best.pt", {"model": state["best_model"], "epoch": state["epoch"]})
    save_checkpoint(ckdir / "last.pt", state)


def resume_state(ckdir: Path, cfg: TrainConfig, model, opt, sched, source, scaler=None):
    """Load ``ckdir/last.pt`` (written by :func:`save_epoch_checkpoints`) into the model, optimiser, scheduler,
    source and scaler; returns ``(history, first epoch to run, best weights)``, or ``None`` without a
    ``last.pt``. A checkpoint of another TrainConfig is refused."""
    path = Path(ckdir) / "last.pt"
    if not path.is_file():
        return None
    ck = load_checkpoint(path)
    if ck["config"] != asdict(cfg):
        raise ValueError(f"{path} was written with a different TrainConfig; use another checkpoint_dir or resume=False")
    model.load_state_dict(ck["model"])
    opt.load_state_dict(ck["optimizer"])
    sched.load_state_dict(ck["scheduler"])
    source.load_state_dict(ck["source"])
    if scaler is not None and "scaler" in ck:
        scaler.load_state_dict(ck["scaler"])
    return History.from_dict(ck["history"]), int(ck["epoch"]) + 1, ck["best_model"]


def train(model: torch.nn.Module, source, val_split, config: TrainConfig | None = None, *,
          checkpoint_dir=None, resume: bool = True, progress: bool = True,
          stop_after: int | None = None, log=None) -> History:
    """Train ``model`` with losses from ``source`` (:class:`TripletSource` or :class:`PlaceBatchSource`).

    After every epoch: validation Recall@N on ``val_split`` (:func:`evaluate_epoch`), the
    best-on-validation weights kept in memory (and in ``checkpoint_dir/best.pt``), and, with a
    ``checkpoint_dir``, the full state in ``last.pt``. With ``resume`` an existing ``last.pt`` is
    continued. ``stop_after`` ends the run after that many epochs of this call (to simulate an
    interruption). ``log``: an object with ``step(record)`` and ``epoch(record)`` (e.g.
    :class:`vpr_nb.run_log.RunLog`, the CSV / TensorBoard files of a run), called on rank 0 after every
    optimiser step and every epoch. Returns the :class:`History`; with ``config.restore_best`` the model
    ends with the best validation weights. With ``config.initial_candidate`` the starting weights are
    evaluated first and compete as epoch 0 (:meth:`History.add_initial`); with ``config.patience`` the run
    stops after that many epochs without a better validation Recall@``ns[0]`` (``History.stopped_early``).
    ValueError when training diverges (NaN/inf, naming the step and the learning rate) or an epoch takes no
    optimiser step (:func:`train_epoch`).

    Distributed: when a ``torch.distributed`` process group is initialised (e.g. under ``torchrun``)
    the model is wrapped in ``DistributedDataParallel``; every process mines the same batches and
    computes its share of each batch's loss, gradients are averaged, and only rank 0 writes
    checkpoints and shows progress.
    """
    cfg = config or TrainConfig()
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(cfg).__name__}")
    if not hasattr(source, "steps"):
        raise ValueError("source must be a TripletSource or PlaceBatchSource (an object with steps(model, rng))")
    rank, world = distributed_rank()
    setup = setup_device(cfg)
    model.to(setup.device)
    opt = make_optimizer(model, cfg)
    sched = make_scheduler(opt, cfg)
    ckdir = None if checkpoint_dir is None else Path(checkpoint_dir)
    resumed = None if ckdir is None or not resume else resume_state(ckdir, cfg, model, opt, sched, source, setup.scaler)
    history, start, best_state = resumed or (History(), 0, copy.deepcopy(model.state_dict()))
    if cfg.initial_candidate and resumed is None:
        history.add_initial(*evaluate_epoch(model, val_split, cfg.ns), cfg.ns[0])
        if ckdir is not None and rank == 0:          # best.pt exists even if no epoch beats the start
            save_checkpoint(ckdir / "best.pt", {"model": best_state, "epoch": -1})
    net = wrap_ddp(model, setup.device, world)
    end = cfg.epochs if stop_after is None else min(cfg.epochs, start + check_int(stop_after, "stop_after"))
    end = start if history.stopped_early else end
    bar = tqdm(range(start, end), desc="epochs", disable=not progress or rank != 0, leave=False)
    for epoch in bar:
        t0 = time.perf_counter()
        lr = opt.param_groups[0]["lr"]
        loss, collapsed = train_epoch(net, source, epoch, cfg, opt, sched, setup, shard=(rank, world),
                                      log=log if rank == 0 else None)
        scheduler_step(sched, cfg, "epoch")
        val, cosine = evaluate_epoch(model, val_split, cfg.ns)
        improved = history.add_epoch(epoch, loss, collapsed, cosine, lr, time.perf_counter() - t0, val, cfg.ns[0])
        if improved:
            best_state = copy.deepcopy(model.state_dict())
        if log is not None and rank == 0:
            log.epoch(history.epochs[-1])
        history.stopped_early = cfg.patience is not None and history.epochs_since_best >= cfg.patience
        if ckdir is not None and rank == 0:
            save_epoch_checkpoints(ckdir, training_state(model, opt, sched, source, history, epoch, best_state, cfg,
                                                         setup.scaler), improved)
        bar.set_postfix(loss=f"{loss:.3f}", R1=f"{val[cfg.ns[0]]:.3f}")
        if history.stopped_early:
            break
    selected = history.best_epoch >= 0 or history.initial is not None
    if cfg.restore_best and selected and (end == cfg.epochs or history.stopped_early):
        model.load_state_dict(best_state)
    return history
