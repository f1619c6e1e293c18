"""The errors every command-line front door reports as one ``error: ...`` line (exit status 2).

The library refuses bad input with :class:`ValueError` or :class:`FileNotFoundError`, each naming what was
wrong and how to fix it; the file system's own failures (a full disk, a folder without permission) arrive as
:class:`OSError`. A console script catches exactly these and prints the message; anything else is a bug and
keeps its traceback.
"""
from __future__ import annotations

CLI_ERRORS: tuple[type[Exception], ...] = (ValueError, FileNotFoundError, OSError)
