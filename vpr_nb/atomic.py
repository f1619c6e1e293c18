"""Files written whole or not at all: a temporary file in the same folder, then one rename over the target.

:func:`atomic_write` is how every file of a run (``config.json``, ``history.json``, the CSVs, checkpoints,
``recalls.json``, ``predictions.csv``) and the course backbone's checkpoint are written: a reader sees the
previous file or the new one, never a truncated one, and a write that fails (a full disk, a name that cannot
be encoded, an interruption) leaves the previous file unchanged and removes its temporary file. The
temporary files are hidden (``.<name>.<random>.tmp``); :func:`remove_stale_temporaries` clears those of a
process that was killed mid-write. A failed write raises one :class:`OSError` naming the file and the fix.
"""
from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

_UMASK = os.umask(0o022)           # read once: files get the mode open() would give them (0o666 & ~umask),
os.umask(_UMASK)                   # not mkstemp's private 0o600
FILE_MODE = 0o666 & ~_UMASK
TEMP_SUFFIX = ".tmp"


def _os_error(exc: BaseException) -> OSError | None:
    """The OSError behind ``exc``: itself, or the one it was raised while handling (torch.save raises a
    RuntimeError from its zip writer after the OSError of the failed write)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, OSError):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def write_failed(path: Path, exc: BaseException) -> OSError:
    """One OSError for a failed write of ``path``: what went wrong and what to do."""
    cause = _os_error(exc)
    code = cause.errno if cause is not None else None
    what = (cause.strerror or str(cause)) if cause is not None else f"{type(exc).__name__}: {str(exc)[:200]}"
    fix = {errno.ENOSPC: "the disk is full: free space or write to another folder",
           errno.EDQUOT: "the disk quota is exhausted: free space or write to another folder",
           errno.EACCES: "no permission to write there: choose a folder you can write to",
           errno.EROFS: "the file system is read-only: choose another folder"}.get(code, "check the folder and retry")
    return OSError(code, f"could not write {path} ({what}); {fix}. The previous {path.name} (if any) is unchanged")


def atomic_write(path, write: Callable, *, text: bool = False, encoding: str = "utf-8",
                 errors: str = "strict", newline: str | None = None) -> Path:
    """Write ``path`` by calling ``write(file)`` on a temporary file beside it, then rename it over ``path``.

    ``text=True`` opens the temporary file in text mode (``encoding``, ``errors``, ``newline`` as for
    :func:`open`), else binary. Creates the parent folder. On any failure the temporary file is removed,
    ``path`` keeps its previous content, and a failure of the file system (an OSError, also one behind
    another exception) is raised as one :class:`OSError` from :func:`write_failed`; other exceptions of
    ``write`` propagate unchanged."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    except OSError as exc:
        raise write_failed(path, exc) from None
    try:
        mode = "w" if text else "wb"
        kw = dict(encoding=encoding, errors=errors, newline=newline) if text else {}
        with os.fdopen(fd, mode, **kw) as f:
            write(f)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.remove(tmp)
        except OSError:
            pass
        if _os_error(exc) is not None:
            raise write_failed(path, exc) from None
        raise
    return path


def atomic_write_text(path, text: str, *, errors: str = "strict") -> Path:
    """``atomic_write`` of a UTF-8 text."""
    return atomic_write(path, lambda f: f.write(text), text=True, errors=errors)


def remove_stale_temporaries(folder) -> list[Path]:
    """Remove the temporary files :func:`atomic_write` left in ``folder`` (not recursive) when a process
    was killed mid-write, and those of the older naming ``<name>.pt<random>.tmp``. Only call this while
    no other process writes the folder (e.g. holding its run lock). Returns the removed paths."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = [p for p in folder.iterdir() if p.is_file() and p.name.endswith(TEMP_SUFFIX)
             and (p.name.startswith(".") or ".pt" in p.name)]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


__all__ = ["atomic_write", "atomic_write_text", "write_failed", "remove_stale_temporaries", "FILE_MODE"]
