"""The program that runs a submission's code inside the sandbox (``vpr_nb.grading.sandbox``).

It reads ``job.json`` (the cells to run: the instructor's setup cells, then the student's solution
cells; the names to call or read) and ``inputs.json``/``inputs.npz`` (the instructor's inputs, as data)
from its working folder, runs the cells in an IPython shell, calls the student's function on every input
and writes ``out/result.json``/``out/result.npz``: for each case the returned value (as data) or the
error it raised. Nothing here decides a grade: the grader reads the result as untrusted data and
compares it with its own reference, so whatever the student's code patches in this process (builtins,
numpy, torch, ``vpr_nb``, IPython) can only change what is written, never how it is judged.
"""
from __future__ import annotations

import json
import os
import sys
import traceback
from pathlib import Path


def _drop_privileges(uid: int) -> None:
    os.setgroups([])
    os.setresgid(uid, uid, uid)
    os.setresuid(uid, uid, uid)
    if os.getuid() != uid or os.geteuid() != uid:
        raise SystemExit("could not switch to the sandbox's user id")


def _error(exc: BaseException) -> dict:
    return {"ename": type(exc).__name__, "evalue": str(exc)[:2000],
            "where": "".join(traceback.format_exception(exc)[-3:])[-1500:]}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--uid" in argv:
        i = argv.index("--uid")
        _drop_privileges(int(argv[i + 1]))
        argv = argv[:i] + argv[i + 2:]
    if argv == ["--probe"]:
        return 0
    work = Path.cwd()
    # imported here on purpose, not at the module top: only after ``--uid`` has dropped root (bwrap run by a
    # root grader starts the runner as root) and after ``--probe`` has returned, so nothing beyond the standard
    # library (numpy, which ``data`` imports, and IPython below) is ever imported with root's rights, and the
    # probe that picks the sandbox backend stays a bare interpreter start
    from vpr_nb.grading import data      # sandbox: imported after the privilege drop and --probe (see above)

    job = json.loads((work / "job.json").read_text())
    inputs = data.read(work, "inputs", make_tensor=_tensor)
    out_dir = work / "out"
    out_dir.mkdir(exist_ok=True)

    from IPython.core.interactiveshell import InteractiveShell
    from traitlets.config import Config

    config = Config()
    config.HistoryManager.enabled = False
    config.InteractiveShell.colors = "nocolor"
    shell = InteractiveShell.instance(config=config)
    result: dict = {"stage": "cells", "cells": len(job["cells"]), "checks": []}
    for i, cell in enumerate(job["cells"]):
        res = shell.run_cell(cell["source"], store_history=False)
        err = res.error_before_exec or res.error_in_exec
        if err is not None or not res.success:
            result.update(stage="cell", failed_cell=i, role=cell["role"],
                          error=_error(err) if err is not None else {"ename": "Error", "evalue": "the cell failed"})
            _write(result, out_dir, data)
            return 0
    result["stage"] = "calls"
    for check, cases in zip(job["checks"], inputs):
        name = check["function"]
        entry = {"function": name, "defined": name in shell.user_ns, "results": []}
        if entry["defined"]:
            target = shell.user_ns[name]
            for args, kwargs in cases:
                try:
                    value = target(*args, **kwargs) if check["call"] else target
                    data.encode(value)                   # refused here already: say which case
                    entry["results"].append({"value": value})
                except data.DataError as err:
                    entry["results"].append({"refused": str(err)})
                except BaseException as err:             # SystemExit, KeyboardInterrupt included
                    entry["results"].append({"error": _error(err)})
        result["checks"].append(entry)
    result["stage"] = "done"
    _write(result, out_dir, data)
    return 0


def _tensor(array):
    import torch
    return torch.from_numpy(array.copy())


def _write(result: dict, out_dir: Path, data) -> None:
    """Write ``result`` with ``data`` (the module :func:`main` imported after dropping privileges)."""
    try:
        data.write(result, out_dir, "result")
    except data.DataError as err:              # cannot happen for checked values; keep the reason anyway
        data.write({"stage": "write", "error": {"ename": "DataError", "evalue": str(err)}}, out_dir, "result")
    sys.stdout.flush()
    sys.stderr.flush()


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)        # skip atexit handlers a submission may have registered
