"""What a run does with a :class:`vpr_nb.config.RunConfig`: the run logic of the reproduction commands.

``python -m vpr_nb.train`` calls :func:`train_run` and ``python -m vpr_nb.evaluate`` calls
:func:`evaluate_run`; both are built from the steps below, each usable on its own:

- :func:`build` / :func:`build_checked`: the model of ``cfg.model``, run on a dummy batch at the training
  and evaluation sizes (:func:`check_model`) before any data loads;
- :func:`load_split`: one split (train / val / test) of ``cfg.data`` as a :class:`vpr_nb.split.Split`: the
  synthetic world's, or a registered format's ``load_part`` (its line in :mod:`vpr_nb.datasets.registry`)
  with the image check (:func:`check_images`) in a :class:`vpr_nb.datasets.TrainingSplit`;
- :func:`build_source`: the batch source of ``cfg.source`` on the training split (triplets, or place batches
  from the split's place pool: random places, CliqueMining, or CliqueMining's GSV-Cities + clique batches
  with one loss per half) and :func:`steps_per_epoch`;
- :func:`train_run` / :func:`evaluate_run` take the ``--out`` folder (:class:`vpr_nb.run_folder.OutputFolder`:
  an OS lock held for the whole run, refused when another run holds it or it holds another run) only
  after everything that can be checked without data (config, device, model, checkpoint) was, write every
  file atomically (:mod:`vpr_nb.atomic`), log every step and epoch (:class:`vpr_nb.run_log.RunLog`: CSVs,
  TensorBoard and the plain-text ``train.log``, its lines from :mod:`vpr_nb.run_summary`) and print a short
  summary (:func:`config_summary`); :func:`read_run_config` reads a run's ``config.json``;
  :func:`check_resume_config` says what a resumed run may change (more epochs, another patience) and names
  every other change with the command that starts a new run. Ctrl-C ends a run with
  :class:`vpr_nb.training.TrainingInterrupted` (where it stopped), and ``train.log`` says how to resume.

Every Recall@N takes its positives from the split (``split.positives()``, per city where the split has
cities) under the split's convention unless ``eval.recall`` says otherwise (:func:`convention`).
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from .atomic import atomic_write, atomic_write_text
from .config import RunConfig, SourceConfig, build_loss, check_device, split_spec, validate
from .datasets import (GeoSplit, ImageArray, SplitSpec, TrainingSplit, dataset_format, drop_images,
                       find_unreadable_images)
from .datasets.registry import SYNTHETIC
from .evaluation import as_image_array, compute_descriptors, counted_queries, evaluate_model, recall_at_n, retrieve
from .models import build_model, init_netvlad
from .seeding import seed_everything
from .samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches
from .split import PlacePool, Split, check_split
from .synthetic import make_config, make_dataset
from .errors import CLI_ERRORS
from .run_folder import RESUMABLE, OutputFolder
from .run_log import RunLog
from .run_summary import (RESUME_FIELDS, changes_text, check_resume_config, config_lines, config_summary,
                          deviations, end_line, environment_line, interruption_line, new_run_command)
from .training import (PlaceBatchSource, TrainingInterrupted, TripletSource, check_resume, distributed_rank,
                       load_checkpoint, load_weights, resolve_device, train)


# ================================================================================================ models
def build(cfg: RunConfig):
    """The model of ``cfg.model`` (:func:`vpr_nb.models.build_model`)."""
    m = cfg.model
    return build_model(m.backbone, m.aggregator, backbone_kwargs=m.backbone_kwargs or None, **m.aggregator_kwargs)


@torch.no_grad()
def check_model(model, sizes) -> int:
    """Run ``model`` on a dummy image of each (H, W) in ``sizes`` (eval mode); returns the descriptor size."""
    was = model.training
    model.eval()
    try:
        dev = next(model.parameters()).device
        for h, w in sizes:
            try:
                out = model(torch.zeros(1, 3, int(h), int(w), device=dev))
            except (ValueError, RuntimeError) as exc:
                raise ValueError(f"the model does not run on {h}x{w} images ({str(exc)[:300]}); "
                                 "check data.image_size / eval.image_size and the model section") from None
            if out.ndim != 2 or out.shape[0] != 1 or not torch.isfinite(out).all():
                raise ValueError(f"the model gives {tuple(out.shape)} non-finite/odd descriptors on {h}x{w} images")
    finally:
        model.train(was)
    return int(out.shape[1])


def model_input_size(cfg: RunConfig) -> tuple[int, int]:
    """(H, W) of the training images: the synthetic world's, else ``data.image_size``."""
    d = cfg.data
    if d.format == SYNTHETIC:
        return tuple(make_config(d.preset, d.size, **d.overrides).image_size)
    return tuple(d.image_size)


def build_checked(cfg: RunConfig):
    """Build the model and run it on a dummy batch at the training and evaluation sizes."""
    model = build(cfg)
    sizes = [model_input_size(cfg)]
    if cfg.eval.image_size is not None and tuple(cfg.eval.image_size) != sizes[0]:
        sizes.append(tuple(cfg.eval.image_size))
    check_model(model, sizes)
    return model


# ================================================================================================ steps
def clique_places(s: SourceConfig) -> int:
    """Clique places per batch of ``sampler="clique+random"`` (``source.clique_places``, default half)."""
    return s.clique_places if s.clique_places is not None else s.places_per_batch // 2


def steps_per_epoch(cfg: RunConfig, *, num_queries: int | None = None, num_places: int | None = None,
                    num_extra_places: int | None = None) -> int:
    """Optimiser steps per epoch of ``cfg.source`` for data of this size.

    triplets: ceil(training queries / batch_size) (pytorch-NetVlad: every query once per epoch);
    places, ``batches_per_epoch`` unset: ceil(places / places_per_batch) (GSV-Cities: every place once);
    clique+random: the GSV-Cities loader of ``places_per_batch - clique_places`` places, cycled together
    with the clique loader (Lightning's max_size_cycle): max(ceil(GSV places / (P - C)), clique batches).
    """
    s = cfg.source
    if s.kind == "triplet":
        if num_queries is None:
            raise ValueError("triplet sources need num_queries (the training queries)")
        return math.ceil(num_queries / s.batch_size)
    if s.batches_per_epoch is not None:
        return int(s.batches_per_epoch)
    if s.sampler == "clique+random":
        if num_extra_places is None:
            raise ValueError("clique+random needs num_extra_places (GSV-Cities places)")
        gsv = math.ceil(num_extra_places / (s.places_per_batch - clique_places(s)))
        return max(gsv, s.clique_batches_per_epoch or 0)
    if num_places is None:
        raise ValueError("place sources need num_places")
    return math.ceil(num_places / s.places_per_batch)


def optimizer_steps(cfg: RunConfig, **sizes) -> int:
    """Total optimiser steps of the run: ``train.epochs × steps_per_epoch`` (see :func:`steps_per_epoch`)."""
    return cfg.train.epochs * steps_per_epoch(cfg, **sizes)


# ================================================================================================ data
def load_geo(spec: SplitSpec, data) -> GeoSplit:
    """The :class:`~vpr_nb.datasets.GeoSplit` of ``spec``: its format's ``load_part`` with the format's
    settings from ``data`` (the ``data.<setting>`` fields its registry line names)."""
    fmt = dataset_format(spec.format)
    if fmt.load_part is None:
        raise ValueError(f"format {fmt.name!r} has no load_part in its registry line, so a run cannot read its parts")
    settings = {name: getattr(data, name) for name in fmt.settings}
    return fmt.load_part(Path(spec.root), spec.part, check_files=data.check_files, **settings)


def check_images(geo, data, report: list):
    """``geo`` without its undecodable images (``data.check_images=skip``; they are appended to ``report``),
    refused (``fail``) or unchecked (``off``)."""
    if data.check_images == "off":
        return geo
    bad = find_unreadable_images(geo.db_paths + geo.q_paths, data.image_check_workers)
    if not bad:
        return geo
    if data.check_images == "fail":
        raise ValueError(f"{geo.name}: {len(bad)} image(s) cannot be decoded, first: {bad[0][0]} ({bad[0][1]}); "
                         "replace them, or set data.check_images=skip to leave them out")
    print(f"{geo.name}: skipping {len(bad)} unreadable image(s), first: {bad[0][0]} ({bad[0][1]})")
    report.extend((geo.name, p, err) for p, err in bad)
    return drop_images(geo, [p for p, _ in bad])


def synthetic_world(data):
    """The synthetic dataset of ``data`` (all three splits)."""
    return make_dataset(data.preset, data.seed, data.size, **data.overrides)


def load_split(cfg: RunConfig, which: str, *, image_size=None, report: list | None = None, synthetic=None) -> Split:
    """One split (``train``/``val``/``test``) of ``cfg.data`` as a :class:`~vpr_nb.split.Split`.

    Only this split's data is read (``synthetic``: the world, when already made). Images that cannot be
    decoded are dropped and appended to ``report`` (``data.check_images=skip``) or refused (``fail``)."""
    d = cfg.data
    spec = split_spec(d, which)
    if spec.format == SYNTHETIC:
        return getattr(synthetic if synthetic is not None else synthetic_world(d), spec.part)
    if not spec.root:
        raise ValueError(f"preset needs the dataset location: --set data.root=/path/to/{spec.format} "
                         "(see docs/reproduction.md, 'Real datasets')")
    geo = check_images(load_geo(spec, d), d, report if report is not None else [])
    return TrainingSplit(geo, tuple(image_size) if image_size is not None else tuple(d.image_size))


def convention(cfg: RunConfig, split: Split) -> str:
    """The Recall@N convention for ``split``: ``eval.recall`` or, with ``auto``, the split's own."""
    return cfg.eval.recall if cfg.eval.recall != "auto" else check_split(split).recall_convention


# ================================================================================================ sources
def _places_with(pool: PlacePool, k: int) -> int:
    """Places of the pool with at least ``k`` images."""
    return int((np.unique(pool.places, return_counts=True)[1] >= k).sum())


def _clique_maker(pool: PlacePool, s: SourceConfig, num_batches: int, places: int) -> CliqueBatchMaker:
    """CliqueMining over the pool (cities as regions); its state holds the group descriptors for resume."""
    return CliqueBatchMaker.from_pool(pool, places, num_batches, images_per_place=s.images_per_place,
                                      same_place_threshold=s.same_place_threshold, similar_groups=s.similar_groups,
                                      refresh_every=s.refresh_every)


def build_source(cfg: RunConfig, train_split: Split, extra_split: Split | None = None):
    """The batch source of ``cfg.source`` on ``train_split`` (``extra_split``: the GSV-Cities split of
    ``sampler="clique+random"``). Returns ``(source, steps_per_epoch)``.

    ``clique+random`` is CliqueMining's training step: every batch holds ``P - C`` GSV-Cities places
    (every place once per epoch, as the GSV-Cities loader) followed by ``C`` clique places of the
    training split, and the loss is one Multi-Similarity loss over each half, summed
    (``PlaceBatchSource(..., loss_groups=(P - C, C))``)."""
    s = cfg.source
    check_split(train_split, "the training split")
    if s.kind == "triplet":
        src = TripletSource(train_split, build_loss(s), batch_size=s.batch_size, num_negatives=s.num_negatives,
                            num_candidates=s.num_candidates, cache_refresh=s.cache_refresh,
                            max_heading_diff=s.max_heading_diff, neg_radius=s.neg_radius)
        return src, steps_per_epoch(cfg, num_queries=len(train_split.q_utm))
    pool, p, k = train_split.place_pool(), s.places_per_batch, s.images_per_place
    if s.sampler == "random":
        per_epoch = steps_per_epoch(cfg, num_places=_places_with(pool, k))
        make = RandomPlaceBatches(pool.places, p, k, per_epoch, regions=pool.regions, one_city=s.one_city_per_batch)
        return PlaceBatchSource(pool.images, make, loss=build_loss(s)), per_epoch
    if s.sampler == "clique":
        per_epoch = steps_per_epoch(cfg, num_places=len(np.unique(pool.places)))
        return PlaceBatchSource(pool.images, _clique_maker(pool, s, per_epoch, p), loss=build_loss(s)), per_epoch
    if extra_split is None:
        raise ValueError("sampler 'clique+random' needs the GSV-Cities pool: set data.gsv_root")
    gsv = check_split(extra_split, "the GSV-Cities split").place_pool()
    if not (isinstance(pool.images, ImageArray) and isinstance(gsv.images, ImageArray)):
        raise ValueError("sampler 'clique+random' mixes two on-disk datasets (MSLS + GSV-Cities)")
    c = clique_places(s)
    per_epoch = steps_per_epoch(cfg, num_extra_places=_places_with(gsv, k))
    rand = RandomPlaceBatches(gsv.places, p - c, k, per_epoch, regions=gsv.regions, one_city=s.one_city_per_batch)
    make = MixedPlaceBatches([rand, _clique_maker(pool, s, per_epoch, c)], offsets=[len(pool.images), 0])
    images = ImageArray(pool.images.paths + gsv.images.paths, pool.images.size)
    return PlaceBatchSource(images, make, loss=build_loss(s), loss_groups=(p - c, c)), per_epoch


# ================================================================================================ runs


def read_run_config(path) -> RunConfig:
    """The :class:`RunConfig` saved in ``path`` (a run's ``config.json``); ValueError naming the file when
    it is not UTF-8, not JSON or not a run config, FileNotFoundError when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: the folder holds no run of vpr_nb.train")
    fix = "restore it, or start a new --out (the run's settings are --preset and --set)"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path} is not UTF-8 text (byte {exc.start}), so not a config.json of vpr_nb.train: "
                         f"{fix}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc.msg}, line {exc.lineno} column {exc.colno}): {fix}") from None
    except OSError as exc:
        raise ValueError(f"{path} cannot be read ({exc.strerror}): {fix}") from None
    try:
        return RunConfig.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path} is not a run config ({exc}): {fix}") from None


def _files(split: Split):
    """The real paths of a split's database and query images (None for images held in memory)."""
    if split.db_paths is None:
        return None
    return frozenset(map(os.path.realpath, split.db_paths)), frozenset(map(os.path.realpath, split.q_paths or []))


def _unreadable_text(bad: list) -> str:
    return "".join(f"{n}\t{p}\t{e}\n" for n, p, e in bad)


def train_run(cfg: RunConfig, out=None, *, resume: bool = False, progress: bool = True,
              folder: OutputFolder | None = None, tensorboard: bool = True, summary: bool | None = None,
              command: str = "python -m vpr_nb.train") -> dict:
    """Validate ``cfg`` and build its model (before anything is read or written), then load the data, train,
    select on the validation split, and test. ``out`` receives ``history.json``, ``results.json``,
    ``checkpoints/`` and ``unreadable_images.txt`` (images left out), each written atomically.

    ``folder`` (the ``train`` command's, an :class:`~vpr_nb.run_folder.OutputFolder` of ``out``) makes it a
    run of the command: the folder is taken once the model is built (locked for the whole run, refused when
    it holds another run unless ``resume``), ``config.json`` (the full config), ``steps.csv`` /
    ``epochs.csv`` / ``train.log`` (and TensorBoard events when installed, :class:`~vpr_nb.run_log.RunLog`)
    are written too, and a run that fails before its first checkpoint removes what it wrote, so the folder
    can be used again. ``resume`` with more ``train.epochs`` or another ``train.patience`` continues the run
    as if it had been started with them, where that gives the same result (:func:`check_resume_config`,
    checked before any data loads). ``summary`` (default: ``progress``) prints :func:`config_summary`;
    ``command`` is how messages spell the command that resumes the run. Ctrl-C raises
    :class:`~vpr_nb.training.TrainingInterrupted`. Under ``torch.distributed`` only rank 0 writes the folder."""
    validate(cfg)
    out = None if out is None else Path(out)
    rank = distributed_rank()[0]
    seed_everything(cfg.train.seed)
    model = build_checked(cfg)             # the model is built and run before any data loads
    folder = folder if rank == 0 else None
    with folder if folder is not None else contextlib.nullcontext():
        return _train_in(cfg, model, out, folder, resume=resume, progress=progress, rank=rank, command=command,
                         tensorboard=tensorboard, summary=progress if summary is None else summary)


def _train_in(cfg: RunConfig, model, out: Path | None, folder: OutputFolder | None, *, resume: bool,
              progress: bool, rank: int, tensorboard: bool, summary: bool, command: str) -> dict:
    """:func:`train_run` once the model is built and ``folder`` (if any) is held: the run's ``train.log``
    (warnings, errors, Ctrl-C) around :func:`_train_steps`."""
    log = RunLog(out, tensorboard=tensorboard, epochs=cfg.train.epochs) if folder is not None else None
    at = {"phase": "checking the saved run" if resume else "loading the data"}
    with contextlib.ExitStack() as stack:
        if log is not None:
            stack.enter_context(log)
            stack.enter_context(log.capture_warnings())
        try:
            return _train_steps(cfg, model, out, folder, log, at, resume=resume, progress=progress, rank=rank,
                                summary=summary, command=command)
        except KeyboardInterrupt as exc:
            stopped = exc if isinstance(exc, TrainingInterrupted) else TrainingInterrupted(phase=at["phase"])
            if log is not None:                  # what last.pt holds, when it stopped in an epoch
                saved = f" ({stopped.saved()})" if stopped.epoch is not None else ""
                log.text(f"{interruption_line(stopped, out, command)}{saved}")
            if stopped is exc:
                raise
            raise stopped.with_traceback(exc.__traceback__) from None
        except BaseException as exc:
            if log is not None:
                log.text(f"error: {exc}" if isinstance(exc, CLI_ERRORS) else f"failed: {type(exc).__name__}: {exc}")
            raise


def _train_steps(cfg: RunConfig, model, out: Path | None, folder: OutputFolder | None, log: RunLog | None,
                 at: dict, *, resume: bool, progress: bool, rank: int, summary: bool, command: str) -> dict:
    """The run: check a resume, load the data, write the folder's config and logs, train, test."""
    t0 = time.perf_counter()
    changes = []
    if resume and out is not None and (out / "config.json").is_file():   # before any data loads
        changes = check_resume_config(read_run_config(out / "config.json"), cfg, out / "config.json", command)
        if changes and (out / RESUMABLE).is_file():
            try:
                check_resume(load_checkpoint(out / RESUMABLE), cfg.train, out / RESUMABLE)
            except ValueError as exc:
                raise ValueError(f"--resume: {exc}: {new_run_command(command, cfg)}") from None
    at["phase"] = "loading the data"
    world = synthetic_world(cfg.data) if cfg.data.format == SYNTHETIC else None
    bad: list = []
    train_split = load_split(cfg, "train", report=bad, synthetic=world)
    val_split = load_split(cfg, "val", report=bad, synthetic=world)
    test_split = load_split(cfg, "test", image_size=cfg.eval.image_size, report=bad, synthetic=world)
    if _files(val_split) is not None and _files(val_split) == _files(test_split):
        raise ValueError(f"validation and test are the same images ({val_split.name} = {test_split.name}, "
                         "e.g. gmberton's MSLS where test is a link to val): the best epoch would be chosen on "
                         "the test set. Set data.val_format / data.val_root to a published validation set")
    extra = None
    if cfg.source.kind == "places" and cfg.source.sampler == "clique+random":
        gsv = check_images(load_geo(SplitSpec("gsv-cities", cfg.data.gsv_root, "train"), cfg.data), cfg.data, bad)
        extra = TrainingSplit(gsv, tuple(cfg.data.image_size))
    if cfg.model.aggregator == "netvlad":            # NetVLAD's cluster step: k-means centroids and alpha
        init_netvlad(model, train_split.db_images, per_image=cfg.model.init_per_image, seed=cfg.train.seed,
                     max_images=cfg.model.init_max_images)
    source, per_epoch = build_source(cfg, train_split, extra)
    total = cfg.train.epochs * per_epoch
    conv = convention(cfg, test_split)
    val_data, test_data = split_spec(cfg.data, "val").describe(), split_spec(cfg.data, "test").describe()
    if rank == 0 and summary:
        print("\n".join(config_summary(cfg, model, per_epoch, out, conv, log.note if log else None)), flush=True)
    writes = out is not None and rank == 0
    if folder is not None:                           # the data is there: the run starts writing its folder
        folder.write_text("config.json", json.dumps(cfg.to_dict(), indent=1))
        for name in log.files() + ["checkpoints", "unreadable_images.txt"]:
            folder.record(name)
        log.begin([f"start: {'resuming the run in' if resume else 'a new run in'} {out}"
                   + (f", changed: {changes_text(changes)}" if changes else ""), *config_lines(cfg),
                   environment_line(cfg.train.device),
                   f"data: train {split_spec(cfg.data, 'train').describe()}, val {val_data}, test {test_data} "
                   f"(Recall@N convention {conv}); {per_epoch} optimiser steps per epoch, {total} in all"])
    if writes and bad:
        atomic_write_text(out / "unreadable_images.txt", _unreadable_text(bad), errors="surrogateescape")
    at["phase"] = "training"
    history = train(model, source, val_split, cfg.train, checkpoint_dir=None if out is None else out / "checkpoints",
                    resume=resume, progress=progress, log=log, steps_per_epoch=per_epoch)
    at["phase"] = "testing"
    test = evaluate_model(model, test_split, ns=cfg.eval.ns or cfg.train.ns, batch_size=cfg.eval.batch_size,
                          no_positive=conv)
    results = {"preset": cfg.preset, "best_epoch": history.best_epoch, "val_best_recall": history.best_recall,
               "test": {str(k): v for k, v in test.items()}, "steps_per_epoch": per_epoch,
               "optimizer_steps": total, "val": val_data, "test_data": test_data, "recall_convention": conv,
               "unreadable_images": len(bad)}
    if writes:
        atomic_write_text(out / "history.json", json.dumps(history.to_dict(), indent=1))
        atomic_write_text(out / "results.json", json.dumps(results, indent=1))
    if log is not None:
        log.text(end_line(results, history, time.perf_counter() - t0))
    return results


def _retrieval_grid(test: Split, idx: np.ndarray, pos: list, queries: int, top: int) -> bytes:
    """``retrieval_grid.png`` (its bytes): the first ``queries`` queries and their top retrievals."""
    import matplotlib       # only when a figure is written: importing this module must not pick a backend
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import retrieval_grid   # optional library: plots imports pyplot, so only after the backend is chosen
    qi = list(range(queries))
    needed = sorted({int(j) for i in qi for j in idx[i, :top]})
    remap = {j: r for r, j in enumerate(needed)}
    q_imgs = np.asarray(as_image_array(test.q_images)[qi])
    db_imgs = np.asarray(as_image_array(test.db_images)[needed])
    sub_pred = np.array([[remap[int(j)] for j in idx[i, :top]] for i in qi])
    sub_pos = [np.array([remap[int(j)] for j in pos[i] if int(j) in remap], dtype=np.int64) for i in qi]
    retrieval_grid(q_imgs, db_imgs, sub_pred, sub_pos, qi, k=top)
    buf = io.BytesIO()
    plt.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close("all")
    return buf.getvalue()


def _predictions_writer(qn: list, dn: list, idx: np.ndarray, k: int):
    def write(f):
        w = csv.writer(f)
        w.writerow(["query"] + [f"top{i + 1}" for i in range(k)])
        for i, row in enumerate(idx):
            w.writerow([qn[i]] + [dn[j] for j in row])
    return write


def evaluate_run(cfg: RunConfig, checkpoint, out=None, *, predictions: bool = False, grid_queries: int = 8,
                 device: str = "auto") -> dict:
    """Recall@N of the weights in ``checkpoint`` (a ``{"model": state_dict}`` file) on the test data of
    ``cfg`` only (``data.test_format``/``data.test_root``, by default the format's test set). The config,
    ``device``, the checkpoint and its fit to the model are checked before ``out`` is touched; ``out`` is
    then locked (:class:`~vpr_nb.run_folder.OutputFolder`, ``existing="allow"``) and receives, each written
    atomically, optionally ``predictions.csv`` (file names that are not UTF-8 are written as their original
    bytes) and ``retrieval_grid.png``, then ``recalls.json`` (``num_queries`` = the queries Recall@N
    divides by)."""
    validate(cfg, for_training=False)
    check_device(device, "--device")
    test_data = split_spec(cfg.data, "test").describe()   # where the test data is, before reading anything
    state = load_checkpoint(checkpoint)
    if not isinstance(state, dict) or "model" not in state:
        raise ValueError(f"{checkpoint} has no 'model' entry; pass a best.pt/last.pt written by vpr_nb.training")
    model = build_checked(cfg)
    load_weights(model, state["model"], checkpoint)
    model.to(resolve_device(device))
    folder = OutputFolder(out, existing="allow") if out is not None else None
    with folder if folder is not None else contextlib.nullcontext():
        bad: list = []
        test = load_split(cfg, "test", image_size=cfg.eval.image_size or None, report=bad)
        conv = convention(cfg, test)
        db = compute_descriptors(model, test.db_images, cfg.eval.batch_size)
        q = compute_descriptors(model, test.q_images, cfg.eval.batch_size)
        ns = cfg.eval.ns or (1, 5, 10, 20)
        k = min(max(cfg.eval.k, max(ns)), len(db))
        _, idx = retrieve(db, q, k)
        pos = test.positives()
        recalls = recall_at_n(idx, pos, [n for n in ns if n <= k], no_positive=conv)
        n_no_pos = sum(1 for p in pos if len(p) == 0)
        print(f"Recall@N convention: {conv} ({'every query counts' if conv == 'all' else 'queries without a positive are left out'}; "
              f"{n_no_pos} of {len(pos)} queries have no positive)")
        result = json.loads(json.dumps({
            "checkpoint": str(checkpoint), "data": cfg.to_dict()["data"], "test_data": test_data, "num_db": len(db),
            "num_queries": counted_queries(pos, conv), "num_queries_total": len(q), "queries_without_positive": n_no_pos,
            "recall_convention": conv, "pos_radius": test.pos_radius, "unreadable_images": len(bad),
            "recall": {str(n): v for n, v in recalls.items()}}))
        if folder is not None:
            if bad:
                folder.write_text("unreadable_images.txt", _unreadable_text(bad), errors="surrogateescape")
            if predictions:
                atomic_write(out / "predictions.csv", _predictions_writer(test.image_names("q"), test.image_names("db"),
                                                                          idx, k),
                             text=True, errors="surrogateescape", newline="")
            if grid_queries:
                png = _retrieval_grid(test, idx, pos, min(grid_queries, len(q)), min(5, k))
                atomic_write(out / "retrieval_grid.png", lambda f: f.write(png))
            folder.write_text("recalls.json", json.dumps(result, indent=1))   # last: the evaluation is complete
    return result


__all__ = ["build", "build_checked", "check_model", "model_input_size", "steps_per_epoch", "optimizer_steps",
           "clique_places", "load_geo", "check_images", "load_split", "convention", "build_source", "OutputFolder",
           "read_run_config", "deviations", "config_summary", "RESUME_FIELDS", "check_resume_config", "train_run",
           "evaluate_run"]
