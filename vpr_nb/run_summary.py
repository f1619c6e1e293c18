"""What a run says about itself in text: the summary it prints, the lines of its ``train.log``, how two configs
differ (and which differences a resumed run may have), and the commands that resume it or start it anew.

:func:`config_summary` is the screen a command prints before training (:func:`deviations`: what differs from
the defaults); :func:`config_lines`, :func:`environment_line` and :func:`end_line` open and close a run's
``train.log`` (:class:`vpr_nb.run_log.RunLog`); :func:`config_changes` / :func:`changes_text` name every field
two configs differ in (``train.lr: 0.001 → 0.01``), :func:`check_resume_config` refuses those a resume may not
make (:data:`RESUME_FIELDS` it may); :func:`set_arguments` gives the ``--set`` arguments that
rebuild a config from its preset (:func:`new_run_command`), :func:`resume_command` the command that continues
a run, and :func:`interruption_line` the line that ends an interrupted one.
"""
from __future__ import annotations

import json
import platform
import shlex
from pathlib import Path

import numpy as np
import torch

from . import __version__
from .config import SECTIONS, RunConfig, resolve, split_spec
from .datasets.registry import SYNTHETIC
from .kernels import cpu_description
from .run_folder import RESUMABLE
from .training import EXTENDABLE, TrainingInterrupted, resolve_device

ARROW = "→"
RESUME_FIELDS = tuple(f"train.{name}" for name in EXTENDABLE)    # what --resume may change (check_resume_config)


def deviations(cfg: RunConfig) -> dict[str, dict]:
    """``{section: {key: value}}`` of the fields of ``cfg`` that differ from the defaults (the preset's
    deviations and the ``--set`` overrides)."""
    defaults = RunConfig(cfg.preset, **{name: section() for name, section in SECTIONS.items()}).to_dict()
    mine = cfg.to_dict()
    return {s: {k: v for k, v in mine[s].items() if v != defaults[s][k]} for s in SECTIONS
            if any(v != defaults[s][k] for k, v in mine[s].items())}


def _fit(line: str, width: int = 118) -> str:
    return line if len(line) <= width else line[:width - 3] + "..."


def config_summary(cfg: RunConfig, model=None, per_epoch: int | None = None, out=None,
                   convention_name: str | None = None, log_note: str | None = None) -> list[str]:
    """The run at a glance (at most 15 lines, for stdout): preset and folder, data, model, batches, steps,
    test, the deviations from the defaults (one line per section) and the logs; ``config.json`` holds
    the full config."""
    d, m, s, t = cfg.data, cfg.model, cfg.source, cfg.train
    where = {w: split_spec(d, w).describe() for w in ("train", "val", "test")}
    world = f" (world {d.preset}/{d.size}, seed {d.seed})" if d.format == SYNTHETIC else ""
    lines = [f"{cfg.preset} -> {out}/ (full config in config.json)" if out is not None
             else f"{cfg.preset} (no --out: nothing is written)",
             _fit(f"  data:   train {where['train']}, val {where['val']}, test {where['test']}{world}")]
    if model is not None:
        params = sum(p.numel() for p in model.parameters())
        trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
        lines.append(f"  model:  {m.backbone} + {m.aggregator}, {model.out_dim}-D descriptors, {params:,} parameters "
                     f"({trainable:,} trainable)")
    else:
        lines.append(f"  model:  {m.backbone} + {m.aggregator}")
    if s.kind == "triplet":
        lines.append(f"  batch:  triplets, {s.loss} loss, {s.batch_size} queries x {s.num_negatives} negatives per step")
    else:
        lines.append(f"  batch:  places ({s.sampler}), multi-similarity loss, {s.places_per_batch} places x "
                     f"{s.images_per_place} images per step")
    steps = f"{per_epoch} = {t.epochs * per_epoch} optimiser steps" if per_epoch is not None else "? steps"
    lines.append(f"  steps:  {t.epochs} epochs x {steps}; {t.optimizer} lr {t.lr:g}, {t.scheduler} scheduler, "
                 f"device {t.device}{', AMP' if t.amp else ''}, seed {t.seed}")
    ns = ",".join(map(str, cfg.eval.ns or t.ns))
    lines.append(f"  test:   Recall@{ns}" + (f", {convention_name} convention" if convention_name else ""))
    changed = deviations(cfg)
    if changed:
        lines.append("  set (differs from the defaults):")
        lines += [_fit(f"    {sec}: " + ", ".join(f"{k}={json.dumps(v)}" for k, v in kv.items()))
                  for sec, kv in changed.items()]
    if out is not None:
        lines.append("  logs:   train.log, history.json, steps.csv, epochs.csv, checkpoints/"
                     + (f"; {log_note}" if log_note else ""))
    return lines


def config_changes(old: RunConfig, new: RunConfig) -> list[tuple[str, object, object]]:
    """``(name, old value, new value)`` for the preset name and every ``section.key`` where ``new`` differs
    from ``old`` (values as in ``config.json``)."""
    a, b = old.to_dict(), new.to_dict()
    changes = [("preset", a["preset"], b["preset"])] if a["preset"] != b["preset"] else []
    return changes + [(f"{s}.{k}", a[s].get(k), v) for s in SECTIONS for k, v in b[s].items() if a[s].get(k) != v]


def check_resume_config(saved: RunConfig, cfg: RunConfig, where, command: str = "python -m vpr_nb.train") -> list:
    """The changes (:func:`~vpr_nb.run_summary.config_changes`) from ``saved`` (the config in ``where``, a
    run's ``config.json``) to ``cfg`` that resuming the run may make: :data:`RESUME_FIELDS` (more epochs,
    another patience; :func:`vpr_nb.training.check_resume` checks them against ``last.pt``). Any other change
    is a ValueError naming every changed field (``train.lr: 0.001 → 0.01``) and the command that starts a new
    run of ``cfg`` (``command --preset P --set ... --out NEW_DIR``)."""
    changes = config_changes(saved, cfg)
    other = [c for c in changes if c[0] not in RESUME_FIELDS]
    if other:
        raise ValueError(f"--resume: {where} holds another config ({changes_text(other)}); a resumed run may change "
                         f"only {' and '.join(RESUME_FIELDS)}. To train with these settings, start a new run: "
                         f"{new_run_command(command, cfg)}")
    return changes


def set_value(value) -> str:
    """The text of a ``--set`` value that parses back to ``value`` (:func:`vpr_nb.typed_parsing.parse_value`)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value
    return json.dumps(value, separators=(",", ":"))


def changes_text(changes) -> str:
    """``train.lr: 0.001 → 0.01, ...`` (values as ``--set`` spells them)."""
    return ", ".join(f"{name}: {set_value(old)} {ARROW} {set_value(new)}" for name, old, new in changes)


def set_arguments(cfg: RunConfig) -> list[str]:
    """``["--set", "section.key=value", ...]`` for every field of ``cfg`` that differs from its preset."""
    base = resolve(cfg.preset)
    return [arg for name, _, value in config_changes(base, cfg) for arg in ("--set", f"{name}={set_value(value)}")]


def new_run_command(command: str, cfg: RunConfig, out: str = "NEW_DIR") -> str:
    """The command that starts a run of ``cfg`` in ``out``: ``command --preset P --set ... --out out``."""
    return " ".join([command, "--preset", shlex.quote(cfg.preset)] + [shlex.quote(a) for a in set_arguments(cfg)]
                    + ["--out", shlex.quote(str(out))])


def resume_command(command: str, out) -> str:
    """The command that continues the run saved in ``out``."""
    return f"{command} --resume --out {shlex.quote(str(out))}"


def config_lines(cfg: RunConfig) -> list[str]:
    """The resolved config, one ``train.log`` line per section (JSON)."""
    d = cfg.to_dict()
    return [f"config: preset {d['preset']}"] + [f"config {s}: {json.dumps(d[s])}" for s in SECTIONS]


def environment_line(device: str = "auto") -> str:
    """vpr_nb, Python, torch and numpy versions, the training device and the CPU and its kernels."""
    dev = resolve_device(device)
    gpu = f" ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else ""
    return (f"environment: vpr_nb {__version__}, Python {platform.python_version()}, torch {torch.__version__}, "
            f"numpy {np.__version__}, device {dev}{gpu}, {torch.get_num_threads()} torch threads, CPU "
            f"{cpu_description()}")


def end_line(results: dict, history, seconds: float) -> str:
    """The last ``train.log`` line of a finished run: the selected epoch, the test Recall@N, steps and time."""
    test = " ".join(f"R@{n} {v:.4f}" for n, v in results["test"].items())
    best = "the starting weights" if history.initial_won else f"epoch {history.best_epoch + 1}"
    stop = ", stopped early" if history.stopped_early else ""
    return (f"end: {len(history.epochs)} epochs{stop}, selected {best} (val {history.best_recall:.4f}), test "
            f"{test}; {results['optimizer_steps']} optimiser steps planned, {seconds:.1f} s")


def interruption_line(exc: KeyboardInterrupt, out, command: str, again: str | None = None) -> str:
    """``interrupted at epoch N, step S; resume with: COMMAND --resume --out OUT`` when ``out`` holds a
    checkpoint to continue; else says nothing was saved and, with ``again``, the command to start over."""
    where = exc.where() if isinstance(exc, TrainingInterrupted) else "before training started"
    if out is None:
        return f"interrupted {where} (no --out: nothing was saved)"
    if (Path(out) / RESUMABLE).is_file() and (Path(out) / "config.json").is_file():
        return f"interrupted {where}; resume with: {resume_command(command, out)}"
    return f"interrupted {where}; nothing to resume in {out} (no epoch was saved)" + (
        f"; start again with: {again}" if again else "")


__all__ = ["RESUME_FIELDS", "deviations", "config_summary", "config_changes", "check_resume_config", "set_value",
           "changes_text", "set_arguments",
           "new_run_command", "resume_command", "config_lines", "environment_line", "end_line",
           "interruption_line"]
