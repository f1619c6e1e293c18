"""``python -m vpr_nb``: the course's commands, one line each (``--help`` on any of them says more)."""
from __future__ import annotations

import sys

from . import __version__

# (console script or None, module, what it does); the console scripts are declared in pyproject.toml
COMMANDS = (
    ("vpr-train", "vpr_nb.train", "train a preset (synthetic world or a real dataset) into --out, resumable"),
    ("vpr-evaluate", "vpr_nb.evaluate", "evaluate a trained run's checkpoint (Recall@N, optional predictions)"),
    ("vpr-pretrain", "vpr_nb.pretrain", "re-make the course backbone (about 6 min on 2 cores)"),
    (None, "vpr_nb.report", "execute the notebook sequence and write a results report (make reproduce)"),
    (None, "vpr_nb.assignments", "student versions of the notebooks; grade submissions"),
    (None, "vpr_nb.authoring", "re-execute a notebook in place for committing (make notebook)"),
    (None, "vpr_nb.kernels", "the CPU kernels this process gets; --run CMD runs a command with the pinned ones"),
    (None, "vpr_nb.fingerprint", "hashes of what a few course steps compute here, to compare two machines"),
)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if args and args[0] not in ("-h", "--help"):
        print(f"error: python -m vpr_nb takes no arguments (got {' '.join(args)}); run it alone for the list "
              f"of commands", file=sys.stderr)
        return 2
    print(f"vpr_nb {__version__}: the commands of the vpr-notebooks course (each has --help)")
    width = max(len(f"python -m {module}") for _, module, _ in COMMANDS)
    for script, module, what in COMMANDS:
        also = f"  (also: {script})" if script else ""
        print(f"  {'python -m ' + module:<{width}}  {what}{also}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
