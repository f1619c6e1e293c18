"""The console scripts' one diagnostic channel: their help, their ``error:`` / ``warning:`` lines and exit statuses.

Every console script (``vpr-train``, ``vpr-evaluate``, ``vpr-pretrain``) builds its parser with :func:`parser` and
runs its work through :func:`run`:

- ``--help`` names the script as it was called (:func:`script_name`: ``vpr-train``, or ``python -m vpr_nb.train``),
  reads as plain text (the module docstring's first paragraph without its reST markup, :func:`plain_text`) and
  ends with example commands;
- a wrong command line, a refused input (:data:`vpr_nb.errors.CLI_ERRORS`) or a failed write is one
  ``error: ...`` line on stderr and exit status 2; any other exception is a bug and keeps its traceback;
- a warning (:mod:`warnings`, or a ``logging`` record of level WARNING and above) is one ``warning: ...`` line on
  stderr, without the file name and source line Python prints (:func:`diagnostics`, installed for the command's
  run only and restored after it, so the library in a notebook warns as usual);
- Ctrl-C (KeyboardInterrupt) ends with the one line the script composes (where it stopped, how to go on) and
  exit status 130, the shell's status of a process ended by SIGINT.

Lines go through ``tqdm.write``, so that a progress bar on the terminal is cleared first and redrawn after.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import shlex
import shutil
import sys
import textwrap
import warnings
from typing import Callable

from tqdm import tqdm

from .errors import CLI_ERRORS

ERROR = 2            # exit status of an error line
INTERRUPTED = 130    # exit status after Ctrl-C: 128 + SIGINT, what a shell reports for a process SIGINT ended


def script_name(script: str, module: str, argv0: str | None = None) -> str:
    """``script`` when this process was started as that console script (``sys.argv[0]``'s name), else
    ``python -m module``: the command a message should tell the user to type."""
    name = os.path.basename(sys.argv[0] if argv0 is None else argv0)
    name = name[:-4] if name.lower().endswith(".exe") else name
    return script if name == script else f"python -m {module}"


def command_line(prog: str, argv) -> str:
    """``prog`` and ``argv`` as one command to paste into a shell (each argument quoted where needed)."""
    return " ".join([prog] + [shlex.quote(str(a)) for a in argv])


_ROLE = re.compile(r":[\w.:+-]+:`(~?)([^`]*)`")      # :func:`x`, :class:`~a.b.C`, :mod:`title <target>`


def _role(m: re.Match) -> str:
    tilde, body = m.group(1), m.group(2).strip()
    titled = re.fullmatch(r"(.*?)\s*<[^>]*>", body)
    if titled:
        return titled.group(1)
    return body.rsplit(".", 1)[-1] if tilde else body


def plain_text(text: str) -> str:
    """``text`` (reST, as in a docstring) as plain text: ``:role:`x``` -> x (``~a.b.c`` -> c, ``title <target>``
    -> title), double backticks, single backticks and ``**bold**`` dropped, a ``::`` that opens a literal block
    -> ``:``."""
    text = _ROLE.sub(_role, text)
    text = re.sub(r"``(.+?)``", r"\1", text, flags=re.S)
    text = re.sub(r"`([^`]+)`_{0,2}", r"\1", text)
    text = re.sub(r"\*\*(.+?)\*\*", r"\1", text, flags=re.S)
    return re.sub(r"(\S)::(\s|$)", r"\1:\2", text)


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose command-line errors are one ``error: ...`` line (status 2), like every other."""

    def error(self, message):
        self.exit(ERROR, f"error: {one_line(message)} (see {self.prog} --help)\n")


def parser(script: str, module: str, doc: str, examples=()) -> argparse.ArgumentParser:
    """The ArgumentParser of a console script: ``prog`` from :func:`script_name`, the description the first
    paragraph of ``doc`` (the module docstring) as plain text with ``python -m module`` said as ``prog``, and
    ``examples``, pairs of (what it does, the arguments after the command), in the epilog."""
    prog = script_name(script, module)
    first = plain_text(doc.strip().split("\n\n")[0])
    first = re.sub(rf"python -m {re.escape(module)}\b", prog, " ".join(first.split()))
    width = max(min(shutil.get_terminal_size().columns, 100) - 2, 40)
    epilog = ("examples:\n" + "\n".join(f"  # {what}\n  {prog} {args}".rstrip() for what, args in examples)
              if examples else None)
    return _Parser(prog=prog, description=textwrap.fill(first, width), epilog=epilog,
                   formatter_class=argparse.RawDescriptionHelpFormatter)


def one_line(text) -> str:
    """``text`` on one line: its non-empty lines joined by a space."""
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip())


def say(kind: str, text) -> None:
    """One ``kind: text`` line on stderr (``kind``: error, warning; or "" for the text alone)."""
    tqdm.write(f"{kind}: {one_line(text)}" if kind else one_line(text), file=sys.stderr)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    named = "" if category is UserWarning else f" ({category.__name__})"
    say("warning", f"{one_line(message)}{named}")


class _LogLines(logging.Handler):
    """``logging`` records of level WARNING and above as ``warning: ...`` / ``error: ...`` lines."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            say("error" if record.levelno >= logging.ERROR else "warning", record.getMessage())
        except Exception:  # noqa: BLE001 - logging must never raise; its own handler reports it
            self.handleError(record)


@contextlib.contextmanager
def diagnostics():
    """Within: warnings and log records of level WARNING and above are one line each on stderr
    (``warning: ...``), with no file name or source line. Restored on exit (the library warns as usual)."""
    saved = warnings.showwarning
    handler = _LogLines(logging.WARNING)
    root = logging.getLogger()
    warnings.showwarning = _show_warning
    root.addHandler(handler)
    try:
        yield
    finally:
        warnings.showwarning = saved
        root.removeHandler(handler)


def run(work: Callable[[], int], interrupted: Callable[[KeyboardInterrupt], str | None]) -> int:
    """``work()`` under :func:`diagnostics`; returns its exit status. A refused input or failed write
    (:data:`~vpr_nb.errors.CLI_ERRORS`) is one ``error: ...`` line and status 2; Ctrl-C is the one line
    ``interrupted(exc)`` gives (None: no line) and status 130."""
    with diagnostics():
        try:
            return work()
        except CLI_ERRORS as exc:
            say("error", exc)
            return ERROR
        except KeyboardInterrupt as exc:
            line = interrupted(exc)
            if line:
                say("", line)
            return INTERRUPTED


__all__ = ["ERROR", "INTERRUPTED", "script_name", "command_line", "plain_text", "parser", "one_line", "say",
           "diagnostics", "run"]
