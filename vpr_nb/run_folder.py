"""The ``--out`` folder of a run: one run at a time (an OS lock), refused when it holds another run, left as
it was found when the run fails before it has anything to resume.

:class:`FolderLock` is an OS file lock on ``<folder>/.lock``, taken through the ``filelock`` package's
:func:`filelock.lock_descriptor` (``flock`` on Linux and macOS, ``LockFileEx`` on byte 0 on Windows): the
kernel gives an exclusive lock to exactly one open file at a time and drops it when its process ends, however
it ends (a crash, ``kill -9``), so a lock left by a dead process is free to take without guessing from process
ids, and there is no window between checking and taking. The file holds the holder's process id, host and start
time, after one blank byte (Windows forbids other processes to read the locked byte 0), for the message a
second run gets. Releasing removes the file while still holding the lock (Windows refuses to remove an open
file: there it is removed just after, unless another process has it open); a process that locked a removed
file sees that the path no longer names its file and tries again, so two processes never both hold the folder.

:class:`OutputFolder` takes the lock, then checks the folder (empty, or ``resume`` with a ``config.json``;
``existing="allow"`` for ``evaluate``, which rewrites its own files) and removes the temporary files of a
killed writer (:func:`vpr_nb.atomic.remove_stale_temporaries`). Files the run writes through
:meth:`OutputFolder.write_text` are recorded; :meth:`OutputFolder.abandon` (a failed run) removes them again
when no checkpoint to resume from was written, so the corrected command can use the same ``--out``.
"""
from __future__ import annotations

import datetime
import os
import shutil
import socket
from pathlib import Path

from filelock import lock_descriptor, unlock_descriptor

from .atomic import atomic_write_text, remove_stale_temporaries, write_failed

LOCK_NAME = ".lock"
RESUMABLE = "checkpoints/last.pt"        # a run folder holding this can be continued with --resume
_HOLDER_AT = 1                           # the holder's line starts after byte 0, which Windows locks
_OPEN_FLAGS = os.O_RDWR | os.O_CREAT | getattr(os, "O_BINARY", 0)


class FolderLock:
    """An exclusive OS lock on ``folder/.lock`` (``flock`` / ``LockFileEx`` through ``filelock``), held from
    :meth:`acquire` to :meth:`release` (or the process's end). :meth:`acquire` raises ValueError naming the
    holder when another process has it."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.fd: int | None = None

    @property
    def held(self) -> bool:
        return self.fd is not None

    def _holder(self, fd: int) -> str:
        try:
            os.lseek(fd, _HOLDER_AT, os.SEEK_SET)
            text = os.read(fd, 200).decode("utf-8", "replace").split()
        except OSError:
            text = []
        if len(text) >= 3:
            return f"process {text[0]} on {text[1]}, started {text[2]}"
        return "another process"

    def _lock(self, fd: int) -> bool:
        """Lock ``fd`` without waiting: True when taken, False when another open file holds the lock."""
        try:
            return lock_descriptor(fd, blocking=False)
        except OSError as exc:
            os.close(fd)
            raise ValueError(f"cannot lock {self.path} ({exc.strerror or exc}): the file system of {self.folder} "
                             f"does not support file locks (a network share?); choose a folder on a local disk") from None

    def acquire(self) -> None:
        if self.held:
            return
        while True:
            try:
                fd = os.open(self.path, _OPEN_FLAGS, 0o644)
            except FileNotFoundError:    # the folder was removed (a failed start) since it was made
                self.folder.mkdir(parents=True, exist_ok=True)
                continue
            except OSError as exc:
                raise write_failed(self.path, exc) from None
            if not self._lock(fd):
                holder = self._holder(fd)
                os.close(fd)
                raise ValueError(f"{self.folder} is in use by another run ({holder}; {self.path}): wait for it to "
                                 f"finish or choose another folder")
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)                 # the holder released (removed) the file we locked: lock the new one
        started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f" {os.getpid()} {socket.gethostname()} {started}\n".encode())
        self.fd = fd

    def release(self) -> None:
        if self.fd is None:
            return
        fd, self.fd = self.fd, None
        try:
            os.unlink(self.path)         # while still locked: a waiter that locked this file retries
            removed = True
        except FileNotFoundError:
            removed = True
        except PermissionError:          # Windows: an open file cannot be removed; remove it once closed
            removed = False
            try:
                os.ftruncate(fd, 0)      # if it stays, it names no holder that has gone
            except OSError:
                pass
        try:
            unlock_descriptor(fd)        # closing drops the lock as well; unlock first, as Windows asks
        except OSError:
            pass
        os.close(fd)
        if not removed:
            try:
                os.unlink(self.path)     # fails while a waiting process has it open: it then takes it over
            except OSError:
                pass

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc):
        self.release()


class OutputFolder:
    """The ``--out`` folder of a run, locked while the run writes it (:class:`FolderLock`).

    ``existing="refuse"`` (``train``): a folder holding files is refused unless ``resume`` (which needs its
    ``config.json``); ``"allow"`` (``evaluate``): files are rewritten. Use as a context manager: on an
    exception the folder is :meth:`abandon`-ed, and the lock is always released."""

    def __init__(self, path, resume: bool = False, existing: str = "refuse"):
        if existing not in ("refuse", "allow"):
            raise ValueError(f"existing must be 'refuse' or 'allow', got {existing!r}")
        self.path = Path(path)
        self.resume = bool(resume)
        self.existing = existing
        self.lock = FolderLock(self.path)
        self.created = False
        self.written: list[str] = []

    @property
    def held(self) -> bool:
        return self.lock.held

    def check(self) -> None:
        """The folder's content allows this run (call it holding the lock)."""
        p = self.path
        content = sorted(c.name for c in p.iterdir() if c.name != LOCK_NAME) if p.is_dir() else []
        if content and not self.resume and self.existing == "refuse":
            raise ValueError(f"--out {p} is not empty ({', '.join(content[:4])}{', ...' if len(content) > 4 else ''}): "
                             "pass --resume to continue the run saved there, or choose a new folder")
        if self.resume and not (p / "config.json").is_file():
            raise ValueError(f"--resume: {p / 'config.json'} not found; there is no run to resume in {p}")

    def acquire(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise ValueError(f"--out {p} is a file, not a folder: choose a folder")
        if self.resume and not p.is_dir():
            raise ValueError(f"--resume: {p} does not exist; there is no run to resume")
        self.created = not p.exists()
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_failed(p, exc) from None
        try:
            self.lock.acquire()
            self.check()
        except BaseException:
            self.lock.release()
            self._remove_if_created()
            raise
        remove_stale_temporaries(p)
        remove_stale_temporaries(p / "checkpoints")

    def write_text(self, name: str, text: str, *, errors: str = "strict") -> Path:
        """Write ``folder/name`` atomically and record it as written by this run."""
        path = atomic_write_text(self.path / name, text, errors=errors)
        self.record(name)
        return path

    def record(self, name: str) -> None:
        """Note that this run wrote ``folder/name`` (a file or a folder) for :meth:`abandon`."""
        if name not in self.written:
            self.written.append(name)

    def resumable(self) -> bool:
        return (self.path / RESUMABLE).is_file()

    def abandon(self) -> None:
        """After a failed run: remove what this run wrote unless it can be resumed (a resumed run, or a
        ``checkpoints/last.pt``) or the folder keeps other files (``existing="allow"``), then the folder
        itself when this run created it and it is empty. The corrected command can then use it again."""
        if not self.resume and self.existing == "refuse" and not self.resumable():
            for name in self.written:
                target = self.path / name
                if target.is_dir():
                    shutil.rmtree(target, ignore_errors=True)
                else:
                    target.unlink(missing_ok=True)
            ck = self.path / "checkpoints"
            if ck.is_dir() and not any(ck.iterdir()):
                ck.rmdir()
        self.written = []

    def _remove_if_created(self) -> None:
        try:
            if self.created and self.path.is_dir() and not any(self.path.iterdir()):
                self.path.rmdir()
        except OSError:                  # another run has just started in it
            pass

    def release(self) -> None:
        self.lock.release()
        self._remove_if_created()

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, kind, exc, tb):
        try:
            if kind is not None:
                self.abandon()
        finally:
            self.release()


__all__ = ["FolderLock", "OutputFolder", "LOCK_NAME"]
