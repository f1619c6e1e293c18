"""The reproduction command: ``python -m vpr_nb.train --preset NAME [--set section.key=value ...] --out DIR``.

The config is one typed :class:`vpr_nb.config.RunConfig` (sections ``data``, ``model``, ``source``,
``train``, ``eval``; every default in :mod:`vpr_nb.config`); a preset holds only its deviations and
``--set`` changes any field, parsed by its type (``--set train.amp=false``, ``--set train.ns=[1,5]``,
``--set model.backbone_kwargs='{"width": 8}'``). Unknown keys are refused with the list of known ones,
and the whole config is validated and the model built on a dummy batch before any data loads.
The command prints a summary of the run (preset, data, model, steps, the deviations from the defaults,
the folder; ``--print-config`` prints the whole config as JSON). ``DIR`` receives ``config.json`` (the full
config), ``history.json``, ``steps.csv`` and ``epochs.csv`` (one row per optimiser step / epoch),
TensorBoard event files in ``tensorboard/`` when the ``tensorboard`` package is installed, ``results.json``
(test Recall@N, steps, which data validated and tested, the Recall@N convention), ``checkpoints/``
(``last.pt``, ``best.pt``) and ``unreadable_images.txt`` when images had to be left out, each written
atomically. ``DIR`` is locked for the whole run (``DIR/.lock``, an OS lock that ends with the process); a
``DIR`` holding files is refused unless ``--resume`` continues the run saved there, and a run that fails
before its first checkpoint leaves ``DIR`` as it found it. Errors are one ``error: ...`` line and exit
status 2. Under ``torchrun --nproc_per_node N`` training runs with DistributedDataParallel (gloo on CPU,
nccl on GPU).

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

from .config import PRESETS as PRESET_DEVIATIONS
from .config import RunConfig, resolve, validate
from .experiment import CLI_ERRORS, OutputFolder, read_run_config, train_run

# every preset resolved (all fields, for reading and printing); the presets themselves, which hold only
# their deviations from the defaults, are vpr_nb.config.PRESETS
PRESETS: dict[str, dict] = {name: {k: v for k, v in resolve(name).to_dict().items() if k != "preset"}
                            for name in PRESET_DEVIATIONS}


def resolve_config(preset: str, overrides=()) -> dict:
    """The resolved config of ``preset`` with overrides, as plain data (what ``config.json`` holds)."""
    return resolve(preset, overrides).to_dict()


def run(cfg, out: Path | None = None, progress: bool = True) -> dict:
    """Train and test one config (a :class:`RunConfig` or its dict); results also written under ``out``."""
    if isinstance(cfg, dict):
        cfg = RunConfig.from_dict(cfg)
    return train_run(cfg, out, progress=progress)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.train", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", help="one of: " + ", ".join(sorted(PRESETS)))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a config value (repeatable), e.g. --set train.lr=0.01")
    ap.add_argument("--out", type=Path, help="output folder (must be empty or new, unless --resume)")
    ap.add_argument("--resume", action="store_true", help="continue the run saved in --out (its config.json)")
    ap.add_argument("--print-config", action="store_true", help="print the resolved config (JSON) and exit")
    ap.add_argument("--list", action="store_true", help="list the presets and exit")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--no-tensorboard", action="store_true", help="write no TensorBoard event files")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(sorted(PRESETS)))
        return 0
    try:
        if args.resume:
            if args.out is None:
                raise ValueError("--resume needs --out DIR, the folder of the run to continue")
            saved = read_run_config(args.out / "config.json")
            cfg = saved
            if args.preset or args.overrides:
                asked = resolve(args.preset or saved.preset, args.overrides)
                if asked.to_dict() != saved.to_dict():
                    raise ValueError(f"--resume: the config differs from {args.out / 'config.json'}; resume with "
                                     "the same --preset/--set (or none), or start a new --out")
        else:
            if not args.preset:
                ap.error("--preset is required (use --list to see them)")
            cfg = resolve(args.preset, args.overrides)
        if args.print_config:
            print(json.dumps(cfg.to_dict(), indent=1))
            return 0
        validate(cfg)
    except CLI_ERRORS as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if distributed:
        backend = "nccl" if torch.cuda.is_available() and cfg.train.device != "cpu" else "gloo"
        torch.distributed.init_process_group(backend)
    rank = torch.distributed.get_rank() if distributed else 0
    folder = OutputFolder(args.out, resume=args.resume) if args.out is not None and rank == 0 else None
    try:
        results = train_run(cfg, args.out, resume=args.resume, progress=not args.no_progress, folder=folder,
                            tensorboard=not args.no_tensorboard, summary=rank == 0)
    except CLI_ERRORS as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    finally:
        if distributed:
            torch.distributed.destroy_process_group()
    if rank == 0:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
