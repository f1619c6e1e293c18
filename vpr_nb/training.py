"""One training loop for every notebook and reproduction run.

:func:`train` runs epochs of optimiser steps whose losses come from a *batch source*:

- :class:`TripletSource` — NetVLAD-style weakly supervised triplets (Arandjelović et al., CVPR 2016,
  Sec. 4): at the start of every epoch (and every ``cache_refresh`` queries) the descriptors of the
  training images are recomputed; each query gets its best potential positive (within the training
  radius) and its M hardest negatives (beyond the evaluation radius) from
  :func:`vpr_nb.mining.mine_triplets`; the loss is a :class:`vpr_nb.losses.TripletFamilyLoss` object,
  one of DW-T-Loss's Eqs. (3), (4)x(3), (5)-(8), (9).
- :class:`PlaceBatchSource` — GSV-Cities / CliqueMining-style batches of P places x K images
  (from :func:`vpr_nb.mining.random_place_batches` or :func:`vpr_nb.mining.clique_batches`) with a
  :class:`vpr_nb.losses.MultiSimilarityLoss` object (loss and miner).

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
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from . import losses as L
from ._checks import check_int, check_positive
from .evaluation import (as_image_array, compute_descriptors, evaluate_descriptors, images_to_tensor,
                         mean_pairwise_cosine)
from .mining import mine_triplets

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
        for name in ("restore_best", "amp"):
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
    """

    epochs: list[dict] = field(default_factory=list)
    best_epoch: int = -1
    best_recall: float = -1.0

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
        return {"epochs": [dict(e, val={int(k): float(v) for k, v in e["val"].items()}) for e in self.epochs],
                "best_epoch": self.best_epoch, "best_recall": self.best_recall}

    @classmethod
    def from_dict(cls, d: dict) -> "History":
        return cls(epochs=[dict(e, val={int(k): v for k, v in e["val"].items()}) for e in d["epochs"]],
                   best_epoch=int(d["best_epoch"]), best_recall=float(d["best_recall"]))

    def plot(self, axes=None, label: str | None = None):
        """Learning curves: training loss (left) and validation Recall@1 (right)."""
        import matplotlib.pyplot as plt
        if axes is None:
            _, axes = plt.subplots(1, 2, figsize=(9, 3))
        x = [e["epoch"] + 1 for e in self.epochs]
        axes[0].plot(x, self.losses, marker="o", label=label)
        axes[0].set(xlabel="epoch", ylabel="mean training loss", title="loss")
        axes[1].plot(x, self.recalls(1), marker="o", label=label)
        axes[1].set(xlabel="epoch", ylabel="val Recall@1", title="validation Recall@1", ylim=(0, 1))
        if label is not None:
            axes[1].legend()
        return axes


# ------------------------------------------------------------------------------ batch sources
class TripletSource:
    """NetVLAD triplets on a split: anchors are the split's queries (optionally also its database).

    Args:
        split: a dataset split with ``q_images/q_utm/db_images/db_utm`` (and headings if
            ``max_heading_diff`` is set), ``train_pos_radius`` and ``pos_radius``.
        loss: a :class:`vpr_nb.losses.TripletFamilyLoss` object holding its parameters:
            ``TripletLoss(margin)`` (Eq. 3), ``WeightedTripletLoss(margin, sigma, eps)`` (Eq. 4 x Eq. 3),
            ``CETripletLoss()`` (Eqs. 5-8), ``DWTripletLoss(sigma, eps)`` (Eq. 9). Default: Eq. (3) with
            the paper's margin. (TEMPORARY: the names ``"triplet"``, ``"weighted"``, ``"ce"``, ``"dw"``
            with ``margin``/``sigma``/``eps`` keywords still build the same object.)
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
                 max_heading_diff: float | None = None, neg_radius: float | None = None, **string_loss_params):
        # TEMPORARY: string losses until the notebooks pass loss objects
        loss = _loss_from_string(loss, string_loss_params, ("margin", "sigma", "eps"), "triplet")
        if not isinstance(loss, L.TripletFamilyLoss):
            raise ValueError(f"loss must be a triplet-family loss object (vpr_nb.losses.TripletLoss(margin), "
                             f"WeightedTripletLoss(margin, sigma, eps), CETripletLoss(), DWTripletLoss(sigma, eps)), "
                             f"got {loss!r}")
        for name in ("q_images", "q_utm", "db_images", "db_utm"):
            if not hasattr(split, name):
                raise ValueError(f"split must provide {name} (a VPRDataset split or the like)")
        if len(split.q_images) == 0 or len(split.db_images) == 0:
            raise ValueError("the training split has no queries or no database images")
        self.split, self.loss = split, loss
        self.batch_size = check_int(batch_size, "batch_size")
        self.num_negatives = check_int(num_negatives, "num_negatives")
        self.num_candidates = check_int(num_candidates, "num_candidates")
        self.cache_refresh = None if cache_refresh is None else check_int(cache_refresh, "cache_refresh")
        self.max_heading_diff = max_heading_diff
        self.neg_radius = split.pos_radius if neg_radius is None else check_positive(neg_radius, "neg_radius")
        self.q, self.db = split.q_images, split.db_images
        self.neg_cache: dict[int, np.ndarray] = {}

    def state_dict(self) -> dict:
        keys = sorted(self.neg_cache)
        vals = np.stack([self.neg_cache[k] for k in keys]) if keys else np.zeros((0, self.num_negatives), np.int64)
        return {"keys": torch.as_tensor(np.asarray(keys, np.int64)), "values": torch.as_tensor(vals)}

    def load_state_dict(self, state: dict) -> None:
        self.neg_cache = {int(k): v.numpy() for k, v in zip(state["keys"], state["values"])}

    def _descriptors(self, model):
        model = getattr(model, "module", model)        # unwrap DistributedDataParallel
        return compute_descriptors(model, self.split.q_images), compute_descriptors(model, self.split.db_images)

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
        heading = {}
        if self.max_heading_diff is not None:
            heading = dict(q_heading=s.q_heading, db_heading=s.db_heading, max_heading_diff=self.max_heading_diff)
        order = rng.permutation(len(self.q))
        refresh = self.cache_refresh or len(order)
        for start in range(0, len(order), self.batch_size):
            if start == 0 or start // refresh != (start - self.batch_size) // refresh:  # refresh point crossed
                q_desc, db_desc = self._descriptors(model)
            ids = order[start:start + self.batch_size]
            tb = mine_triplets(q_desc, db_desc, s.q_utm, s.db_utm, ids, train_pos_radius=s.train_pos_radius,
                               neg_radius=self.neg_radius, num_negatives=self.num_negatives,
                               num_candidates=min(self.num_candidates, len(self.db)),
                               neg_cache=self.neg_cache, rng=rng, **heading)
            v = np.flatnonzero(tb.valid)
            total = len(v)
            if total < world:
                continue                       # every process skips the same steps
            v = v[rank::world]
            b, m = len(v), self.num_negatives
            x = images_to_tensor(np.concatenate([self.q[tb.query[v]], self.db[tb.positive[v]],
                                                 self.db[tb.negatives[v].reshape(-1)]])).to(device)
            out = model(x).float()
            q, p, n = out[:b], out[b:2 * b], out[2 * b:].view(b, m, -1)
            geo = torch.as_tensor(tb.geo_qp[v], dtype=out.dtype, device=out.device)
            self.last_collapsed_loss = self._collapsed_loss(b, m, out.shape[1], geo) * (world / total)
            yield self.loss(q, p, n, geo) * (world / total)


class PlaceBatchSource:
    """Batches of P places x K images with the Multi-Similarity loss (Wang et al., CVPR 2019, Eq. 6).

    ``make_batches(model, epoch, rng)`` returns an int array ``(num_batches, P, K)`` of indices into
    ``images`` (for example :func:`vpr_nb.mining.random_place_batches` or
    :func:`vpr_nb.mining.clique_batches` on descriptors from ``model``); images in the same place slot
    share a label. ``loss`` is a :class:`vpr_nb.losses.MultiSimilarityLoss` object (its ``alpha``, ``beta``,
    ``base`` and ``miner_epsilon``; default: the SALAD / GSV-Cities recipe), called as
    ``loss(embeddings, labels)``. (TEMPORARY: ``alpha``/``beta``/``base``/``miner_epsilon`` keywords still
    build the same object.)
    """

    def __init__(self, images, make_batches: Callable, *, loss: L.MultiSimilarityLoss = L.MultiSimilarityLoss(),
                 **string_loss_params):
        # TEMPORARY: string losses until the notebooks pass loss objects
        if string_loss_params:
            loss = _loss_from_string("multi-similarity", string_loss_params,
                                     ("alpha", "beta", "base", "miner_epsilon"), "places")
        self.x = as_image_array(images)
        images_to_tensor(self.x[:1])           # validates shape and dtype
        if not callable(make_batches):
            raise ValueError("make_batches must be a callable (model, epoch, rng) -> (num_batches, P, K) indices")
        if isinstance(loss, L.TripletFamilyLoss) or not callable(loss):
            raise ValueError(f"loss must be a place-batch loss called as loss(embeddings, labels), e.g. "
                             f"vpr_nb.losses.MultiSimilarityLoss(alpha, beta, base, miner_epsilon), got {loss!r}; "
                             f"triplet-family losses go with TripletSource")
        self.make_batches, self.loss = make_batches, loss
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

    def steps(self, model, rng: np.random.Generator, shard: tuple[int, int] = (0, 1), device=None):
        """One MS loss per batch; with ``shard=(rank, world)`` each process takes every world-th place."""
        rank, world = shard
        batches = np.asarray(self.make_batches(model, self.epoch, rng))
        if batches.ndim != 3 or not np.issubdtype(batches.dtype, np.integer):
            raise ValueError(f"make_batches must return an integer array (num_batches, P, K), got {batches.shape}")
        if batches.size and (batches.min() < 0 or batches.max() >= len(self.x)):
            raise ValueError(f"make_batches returned indices outside [0, {len(self.x) - 1}]")
        batches = batches[:, rank::world]
        num, p, k = batches.shape
        labels = torch.arange(p, device=device).repeat_interleave(k)
        for batch in batches:
            emb = model(images_to_tensor(self.x[batch.reshape(-1)]).to(device)).float()
            same = torch.nn.functional.normalize(torch.ones_like(emb.detach()), dim=1)   # every descriptor equal
            self.last_collapsed_loss = float(self.loss(same, labels))
            yield self.loss(emb, labels)

    def _ms_loss(self, emb, labels):
        """TEMPORARY: string losses until the notebooks pass loss objects (notebook 07 calls it; use ``self.loss``)."""
        return self.loss(emb, labels)


def _loss_from_string(loss, params: dict, names: tuple[str, ...], kind: str):
    """TEMPORARY: string losses until the notebooks pass loss objects.

    ``TripletSource(split, "dw", sigma=..., eps=...)`` and ``PlaceBatchSource(..., alpha=...)`` build the
    same object as the typed config's loss registry (:func:`vpr_nb.config.build_loss`). A loss object is
    returned unchanged (it must come without loose parameters).
    """
    unknown = sorted(set(params) - set(names))
    if unknown:
        raise ValueError(f"unexpected keyword argument(s) {unknown}; the loss parameters {names} belong to the "
                         f"loss object, e.g. loss=vpr_nb.losses.WeightedTripletLoss(margin=0.1, sigma=800.0)")
    if not isinstance(loss, str):
        if params:
            raise ValueError(f"{sorted(params)} given beside a loss object {loss!r}: set them on the loss object")
        return loss
    from .config import TRIPLET_LOSSES, SourceConfig, build_loss
    if kind == "triplet" and loss not in TRIPLET_LOSSES:
        raise ValueError(f"loss must be a loss object, or (temporarily) one of {TRIPLET_LOSSES}, got {loss!r}")
    return build_loss(SourceConfig(kind=kind, loss=loss, **params))


# ------------------------------------------------------------------------------ checkpoints
def save_checkpoint(path, state: dict) -> Path:
    """Write ``state`` with ``torch.save`` atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    os.close(fd)
    try:
        with open(tmp, "wb") as f:          # a file object: the archive is named "archive", not after the
            torch.save(state, f)            # random temporary name, so equal states give equal bytes
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def load_checkpoint(path) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: tensors and plain data only)."""
    import pickle

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}; train first or check the path")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise ValueError(
            f"{path} is not a checkpoint of plain tensors and containers (as vpr_nb writes): it holds pickled "
            f"Python objects ({first[:160]}). vpr_nb reads checkpoints with weights_only=True and will not "
            f"unpickle it, since unpickling can run arbitrary code. Save only the state dict, e.g. "
            f"torch.save({{'model': model.state_dict()}}, path), from code you trust.") from None
    except (RuntimeError, EOFError) as exc:
        raise ValueError(f"{path} is not a readable torch checkpoint ({str(exc)[:160]}); "
                         f"is the file truncated or of another format?") from None


def amp_dtype(device: torch.device) -> torch.dtype:
    """The autocast dtype of ``TrainConfig.amp``: bfloat16 on CPU and on GPUs that support it, else float16
    (then :func:`train` scales the loss with a ``GradScaler`` so that small gradients do not underflow)."""
    if device.type == "cuda" and not torch.cuda.is_bf16_supported():
        return torch.float16
    return torch.bfloat16


def _optimizer(model, cfg: TrainConfig):
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError("the model has no trainable parameters")
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)


def _scheduler(opt, cfg: TrainConfig):
    if cfg.scheduler == "step":
        return torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.step_size, gamma=cfg.gamma)
    return torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0, end_factor=cfg.linear_end_factor,
                                             total_iters=cfg.linear_steps)


def resolve_device(name: str = "auto") -> torch.device:
    """``"auto"`` → CUDA when available, else CPU; a CUDA name without CUDA is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available; use device='cpu' or 'auto'")
    return torch.device(name)


def _distributed() -> tuple[int, int]:
    """(rank, world size) of an initialised ``torch.distributed`` process group, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def train(model: torch.nn.Module, source, val_split, config: TrainConfig | None = None, *,
          checkpoint_dir=None, resume: bool = True, progress: bool = True,
          stop_after: int | None = None) -> History:
    """Train ``model`` with losses from ``source`` (:class:`TripletSource` or :class:`PlaceBatchSource`).

    After every epoch: validation Recall@N on ``val_split`` (:func:`vpr_nb.evaluation.evaluate_model`),
    the best-on-validation weights kept in memory (and in ``checkpoint_dir/best.pt``), and, with a
    ``checkpoint_dir``, the full state in ``last.pt``. With ``resume`` an existing ``last.pt`` is
    continued. ``stop_after`` ends the run after that many epochs of this call (to simulate an
    interruption). Returns the :class:`History`; with ``config.restore_best`` the model ends with
    the best validation weights.

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
    rank, world = _distributed()
    device = resolve_device(cfg.device)
    model.to(device)
    opt = _optimizer(model, cfg)
    sched = _scheduler(opt, cfg)
    history, start = History(), 0
    best_state = copy.deepcopy(model.state_dict())
    ckdir = None if checkpoint_dir is None else Path(checkpoint_dir)
    if ckdir is not None and resume and (ckdir / "last.pt").is_file():
        ck = load_checkpoint(ckdir / "last.pt")
        if ck["config"] != asdict(cfg):
            raise ValueError(f"{ckdir / 'last.pt'} was written with a different TrainConfig; "
                             "use another checkpoint_dir or resume=False")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        source.load_state_dict(ck["source"])
        history, start, best_state = History.from_dict(ck["history"]), int(ck["epoch"]) + 1, ck["best_model"]
    net = model
    if world > 1:
        # find_unused_parameters: e.g. SmallCNN's global-token layer is unused by pooling aggregators
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                                        find_unused_parameters=True)
    amp = bool(cfg.amp)
    dtype = amp_dtype(device) if amp else None
    scaler = torch.amp.GradScaler(device.type) if amp and dtype == torch.float16 else None
    if scaler is not None and ckdir is not None and resume and start > 0 and "scaler" in ck:
        scaler.load_state_dict(ck["scaler"])
    end = cfg.epochs if stop_after is None else min(cfg.epochs, start + check_int(stop_after, "stop_after"))
    bar = tqdm(range(start, end), desc="epochs", disable=not progress or rank != 0, leave=False)
    for epoch in bar:
        t0 = time.perf_counter()
        rng = np.random.default_rng([cfg.seed, epoch])
        torch.manual_seed(cfg.seed * 100_003 + epoch)
        if hasattr(source, "epoch"):
            source.epoch = epoch
        model.train()
        total, collapsed, steps = 0.0, 0.0, 0
        lr = opt.param_groups[0]["lr"]
        with torch.autocast(device.type, dtype=dtype, enabled=amp):
            for loss in source.steps(net, rng, shard=(rank, world), device=device):
                if not torch.isfinite(loss):
                    raise ValueError(f"the loss became {loss.item()} at epoch {epoch}; lower the learning rate")
                opt.zero_grad(set_to_none=True)
                if scaler is not None:          # float16: scale the loss, unscale before the step
                    scaler.scale(loss).backward()
                    scaler.step(opt)
                    scaler.update()
                else:
                    loss.backward()
                    opt.step()
                if cfg.scheduler == "linear":
                    sched.step()
                logged = loss.detach()
                if world > 1:                   # log the whole batch's loss, not this process's share
                    logged = logged.clone()
                    torch.distributed.all_reduce(logged)
                    logged = logged / world
                total, steps = total + logged.item(), steps + 1
                collapsed += float(getattr(source, "last_collapsed_loss", float("nan")))
        if cfg.scheduler == "step":
            sched.step()
        val_db = compute_descriptors(model, val_split.db_images)
        val = evaluate_descriptors(val_db, compute_descriptors(model, val_split.q_images), val_split.db_utm,
                                   val_split.q_utm, val_split.pos_radius, cfg.ns)
        history.epochs.append({"epoch": epoch, "loss": total / max(steps, 1),
                               "collapsed_loss": collapsed / max(steps, 1),
                               "mean_cosine": mean_pairwise_cosine(val_db) if len(val_db) > 1 else float("nan"),
                               "lr": lr, "seconds": time.perf_counter() - t0, "val": val})
        if val[cfg.ns[0]] > history.best_recall:
            history.best_epoch, history.best_recall = epoch, float(val[cfg.ns[0]])
            best_state = copy.deepcopy(model.state_dict())
            if ckdir is not None and rank == 0:
                save_checkpoint(ckdir / "best.pt", {"model": best_state, "epoch": epoch})
        if ckdir is not None and rank == 0:
            save_checkpoint(ckdir / "last.pt", {
                "model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                "source": source.state_dict(), "history": history.to_dict(), "epoch": epoch,
                "best_model": best_state, "config": asdict(cfg),
                **({"scaler": scaler.state_dict()} if scaler is not None else {})})
        bar.set_postfix(loss=f"{total / max(steps, 1):.3f}", R1=f"{val[cfg.ns[0]]:.3f}")
    if cfg.restore_best and history.best_epoch >= 0 and end == cfg.epochs:
        model.load_state_dict(best_state)
    return history
