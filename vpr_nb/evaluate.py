"""Evaluate a trained checkpoint: ``python -m vpr_nb.evaluate --run DIR [--set section.key=value ...] --out DIR``.

``--run`` is an output folder of ``python -m vpr_nb.train`` (its ``config.json`` rebuilds the model,
``checkpoints/best.pt`` holds the weights); alternatively ``--preset NAME --checkpoint FILE``. Only the
test data is read: the run's ``data.test_format``/``data.test_root`` (by default the format's test set,
e.g. MSLS-val for an MSLS run, so a folder holding only cph and sf suffices). ``--set data.format=gmberton
--set data.root=/path`` evaluates on another dataset (the test data then follows the new format unless
``data.test_*`` are set too). Writes ``recalls.json`` (Recall@N, the Recall@N convention used and
``num_queries`` = the queries it divides by), optionally ``predictions.csv`` (``--predictions``) and
``retrieval_grid.png``, each written atomically, into ``--out``, which is locked while it is written (the
lock of :mod:`vpr_nb.run_folder`: a folder a ``train`` or ``evaluate`` run is writing is refused). The
config, the device and the checkpoint (readable, and weights of the configured model) are checked before
``--out`` is touched; errors are one ``error: ...`` line and exit status 2, warnings one ``warning: ...`` line
and Ctrl-C one line and exit status 130 (:mod:`vpr_nb.cli`). The run logic is
:func:`vpr_nb.experiment.evaluate_run`; this module only parses the command line.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from . import cli
from .config import RunConfig, resolve, split_override, with_overrides
from .experiment import evaluate_run, read_run_config
from .kernels import apply_in_process

EXAMPLES = (("evaluate the best weights of a training run on its test data",
             "--run runs/city --out runs/city/eval"),
            ("the same run on another dataset, with each query's top retrievals in predictions.csv",
             "--run runs/city --set data.format=gmberton --set data.root=/data/pitts30k --out runs/city/pitts "
             "--predictions"),
            ("a checkpoint of a preset's model", "--preset synthetic-city-triplet --checkpoint best.pt --out ev"))


def run_config(run_dir: Path, overrides=()) -> RunConfig:
    """The config saved in ``run_dir/config.json`` with ``overrides``; moving ``data.format``/``data.root``
    without ``data.test_*`` resets the test data to the new format's default."""
    cfg_path = Path(run_dir) / "config.json"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path} not found: --run must be an output folder of vpr_nb.train")
    saved = read_run_config(cfg_path)
    keys = {split_override(o)[:2] for o in overrides}
    extra = []
    if keys & {("data", "format"), ("data", "root")} and not keys & {("data", "test_format"), ("data", "test_root")}:
        extra = ["data.test_format=none", "data.test_root=none"]
    return with_overrides(saved, extra + list(overrides))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = cli.parser("vpr-evaluate", "vpr_nb.evaluate", __doc__, EXAMPLES)
    ap.add_argument("--run", type=Path, help="output folder of a training run (vpr-train)")
    ap.add_argument("--preset", help="preset name (with --checkpoint, instead of --run)")
    ap.add_argument("--checkpoint", type=Path, help="checkpoint file (default: RUN/checkpoints/best.pt)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a config value (repeatable), e.g. --set data.root=/data/pitts30k")
    ap.add_argument("--out", type=Path, required=True, help="where recalls.json (and the figure) go")
    ap.add_argument("--predictions", action="store_true", help="also write predictions.csv")
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)
    if args.run is None and not (args.preset and args.checkpoint):
        ap.error("give --run DIR, or --preset NAME with --checkpoint FILE")

    def interrupted(exc):
        return (f"interrupted; {args.out / 'recalls.json'} was not written (it is written last); run the command "
                f"again: {cli.command_line(ap.prog, argv)}")
    return cli.run(lambda: _main(args), interrupted)


def _main(args) -> int:
    if args.run is not None:
        cfg = run_config(args.run, args.overrides)
        checkpoint = args.checkpoint or args.run / "checkpoints" / "best.pt"
    else:
        cfg, checkpoint = resolve(args.preset, args.overrides), args.checkpoint
    apply_in_process()  # in a pinned process, the convolutions that give the same bits on every CPU
    result = evaluate_run(cfg, checkpoint, args.out, predictions=args.predictions, device=args.device)
    print(json.dumps(result["recall"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
