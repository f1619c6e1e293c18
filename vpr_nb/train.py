"""The reproduction command: ``python -m vpr_nb.train --preset NAME [--set section.key=value ...] --out DIR``.

The config is one typed :class:`vpr_nb.config.RunConfig` (sections ``data``, ``model``, ``source``,
``train``, ``eval``; every default in :mod:`vpr_nb.config`); a preset holds only its deviations and
``--set`` changes any field, parsed by its type (``--set train.amp=false``, ``--set train.ns=[1,5]``,
``--set model.backbone_kwargs='{"width": 8}'``). Unknown keys are refused with the list of known ones,
and the whole config is validated and the model built on a dummy batch before any data loads.
The command prints a summary of the run (preset, data, model, steps, the deviations from the defaults,
the folder; ``--print-config`` prints the whole config as JSON) and, on a terminal, a bar of optimiser steps
with an ETA (``--no-progress``: none). ``DIR`` receives ``config.json`` (the full config), ``train.log`` (the
run in plain text: config, environment, every epoch's losses and recalls, warnings, the end; appended on
resume), ``history.json``, ``steps.csv`` and ``epochs.csv`` (one row per optimiser step / epoch),
TensorBoard event files in ``tensorboard/`` when the ``tensorboard`` package is installed, ``results.json``
(test Recall@N, steps, which data validated and tested, the Recall@N convention), ``checkpoints/``
(``last.pt``, ``best.pt``) and ``unreadable_images.txt`` when images had to be left out, each written
atomically. ``DIR`` is locked for the whole run (``DIR/.lock``, an OS lock that ends with the process); a
``DIR`` holding files is refused unless ``--resume`` continues the run saved there, and a run that fails
before its first checkpoint leaves ``DIR`` as it found it. ``--resume --set train.epochs=N`` (or
``train.patience``) extends the run: it ends exactly as a run started with that budget would; any other
change is refused naming each changed field and the command that starts a new run. Errors are one
``error: ...`` line and exit status 2, warnings one ``warning: ...`` line (:mod:`vpr_nb.cli`); Ctrl-C ends
with one line saying where it stopped and how to resume (status 130; the last checkpoint stays valid, and an
epoch stopped part-way is run again). Under ``torchrun --nproc_per_node N`` training runs with
DistributedDataParallel (gloo on CPU, nccl on GPU).

Presets (``--list``): ``synthetic-*`` (the notebooks' small CNN on the synthetic worlds, about a minute on
a laptop), ``dwt-pitts30k`` (DW-T-Loss / pytorch-NetVlad on Pittsburgh30k), ``salad-gsv`` (DINOv2-SALAD on
GSV-Cities, selected on Pitts30k-val, tested on MSLS-val) and ``salad-cliquemining-msls`` (CliqueMining:
30 GSV-Cities + 30 MSLS clique places per batch, one Multi-Similarity loss over each half, summed). The
run logic is :func:`vpr_nb.experiment.train_run`; this module only parses the command line.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

from . import cli
from .config import PRESETS as PRESET_DEVIATIONS
from .config import RunConfig, resolve, validate, with_overrides
from .experiment import check_resume_config, read_run_config, train_run
from .kernels import apply_in_process
from .run_folder import OutputFolder
from .run_summary import interruption_line

# every preset resolved (all fields, for reading and printing); the presets themselves, which hold only
# their deviations from the defaults, are vpr_nb.config.PRESETS
PRESETS: dict[str, dict] = {name: {k: v for k, v in resolve(name).to_dict().items() if k != "preset"}
                            for name in PRESET_DEVIATIONS}
EXAMPLES = (("train the notebooks' small CNN on the synthetic city (about a minute on a laptop)",
             "--preset synthetic-city-triplet --out runs/city"),
            ("the same with another learning rate and more epochs",
             "--preset synthetic-city-triplet --set train.lr=0.01 --set train.epochs=20 --out runs/city-lr"),
            ("continue runs/city to 20 epochs: it ends as a run started with 20 epochs would",
             "--resume --out runs/city --set train.epochs=20"))


def resolve_config(preset: str, overrides=()) -> dict:
    """The resolved config of ``preset`` with overrides, as plain data (what ``config.json`` holds)."""
    return resolve(preset, overrides).to_dict()


def run(cfg, out: Path | None = None, progress: bool = True) -> dict:
    """Train and test one config (a :class:`RunConfig` or its dict); results also written under ``out``."""
    if isinstance(cfg, dict):
        cfg = RunConfig.from_dict(cfg)
    return train_run(cfg, out, progress=progress)


def resume_config(out: Path, preset: str | None, overrides, command: str) -> RunConfig:
    """The config ``--resume --out out`` runs: the saved ``config.json`` with ``overrides`` (or, with
    ``preset``, that preset with them), refused unless it only extends the run
    (:func:`vpr_nb.experiment.check_resume_config`: each changed field named, and the new-run command)."""
    path = out / "config.json"
    saved = read_run_config(path)
    asked = resolve(preset, overrides) if preset else with_overrides(saved, overrides)
    check_resume_config(saved, asked, path, command)
    return asked


def parser() -> argparse.ArgumentParser:
    ap = cli.parser("vpr-train", "vpr_nb.train", __doc__, EXAMPLES)
    ap.add_argument("--preset", help="one of: " + ", ".join(sorted(PRESETS)))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a config value (repeatable), e.g. --set train.lr=0.01")
    ap.add_argument("--out", type=Path, help="output folder (must be empty or new, unless --resume)")
    ap.add_argument("--resume", action="store_true",
                    help="continue the run saved in --out (its config.json); --set train.epochs=N (or "
                         "train.patience=N) extends it as if it had been started so")
    ap.add_argument("--print-config", action="store_true", help="print the resolved config (JSON) and exit")
    ap.add_argument("--list", action="store_true", help="list the presets and exit")
    ap.add_argument("--no-progress", action="store_true",
                    help="no progress bar (there is none either when stderr is not a terminal)")
    ap.add_argument("--no-tensorboard", action="store_true", help="write no TensorBoard event files")
    return ap


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = parser()
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(sorted(PRESETS)))
        return 0
    if not args.resume and not args.preset:
        ap.error("--preset is required (use --list to see them)")
    if args.resume and args.out is None:
        ap.error("--resume needs --out DIR, the folder of the run to continue")
    rank = int(os.environ.get("RANK", "0"))

    def interrupted(exc):
        again = cli.command_line(ap.prog, argv)
        return interruption_line(exc, args.out, ap.prog, again) if rank == 0 else None
    return cli.run(lambda: _main(args, ap.prog), interrupted)


def _main(args, command: str) -> int:
    if args.resume:
        cfg = resume_config(args.out, args.preset, args.overrides, command)
    else:
        cfg = resolve(args.preset, args.overrides)
    if args.print_config:
        print(json.dumps(cfg.to_dict(), indent=1))
        return 0
    validate(cfg)
    apply_in_process()      # in a pinned process, the convolutions that give the same bits on every CPU
    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if distributed:
        backend = "nccl" if torch.cuda.is_available() and cfg.train.device != "cpu" else "gloo"
        torch.distributed.init_process_group(backend)
    rank = torch.distributed.get_rank() if distributed else 0
    folder = OutputFolder(args.out, resume=args.resume) if args.out is not None and rank == 0 else None
    progress = not args.no_progress and sys.stderr.isatty()       # a bar only on a terminal
    try:
        results = train_run(cfg, args.out, resume=args.resume, progress=progress, folder=folder,
                            tensorboard=not args.no_tensorboard, summary=rank == 0, command=command)
    finally:
        if distributed:
            torch.distributed.destroy_process_group()
    if rank == 0:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
