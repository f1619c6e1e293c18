"""The run-folder lock (vpr_nb.run_folder): processes released together at a barrier get exactly one holder,
a lock never has two holders while they take and release it in a loop, the lock of a killed process
is free to take, and the lock (filelock's, not fcntl's) behaves the same under Windows' file rules (emulated)."""
import multiprocessing as mp
import os
import signal
import time

import filelock
import pytest

from vpr_nb import run_folder
from vpr_nb.run_folder import FolderLock, OutputFolder

CONTENDERS, TRIALS = 4, 50


def _contend(root, barrier, start, results, rank):
    """At every trial: wait for all, spin until the common start time (so that the processes run into the
    lock together, not one after the other as the barrier wakes them), try to take the trial's fresh
    --out, report, wait, let go."""
    for t in range(TRIALS):
        folder = OutputFolder(os.path.join(root, f"trial{t}"))
        barrier.wait()
        while time.monotonic() < start.value:
            pass
        try:
            folder.acquire()
            got = True
        except ValueError as exc:
            got = False
            assert "is in use by another run" in str(exc), exc
        results.put((t, rank, got))
        barrier.wait()                   # everyone has tried before the holder lets go
        folder.release()


def _run(target, args, n):
    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=target, args=args + (r,)) for r in range(n)]
    for p in procs:
        p.start()
    return procs


def _join(procs):
    for p in procs:
        p.join(60)
    assert all(p.exitcode == 0 for p in procs), [p.exitcode for p in procs]


def test_processes_released_together_get_one_holder_every_time(tmp_path):
    """A check-then-write lock (the file's pid read, then written) fails this in several of the 50 trials."""
    ctx = mp.get_context("fork")
    start, results = ctx.Value("d", 0.0), ctx.Queue()

    def go():                                    # run by the last process to reach the barrier
        start.value = time.monotonic() + 0.01
    barrier = ctx.Barrier(CONTENDERS, action=go, timeout=60)
    procs = _run(_contend, (str(tmp_path), barrier, start, results), CONTENDERS)
    got = [results.get(timeout=60) for _ in range(CONTENDERS * TRIALS)]
    _join(procs)
    holders = [sum(g for t, _, g in got if t == trial) for trial in range(TRIALS)]
    assert holders == [1] * TRIALS, holders
    assert len({r for _, r, g in got if g}) > 1 or CONTENDERS == 1     # not always the same process
    assert not list(tmp_path.rglob(".lock"))                             # all released


def _churn(path, barrier, inside, most, guard, refused, rank):
    """Take and release the lock as fast as possible until taken 100 times; count how many hold it at once."""
    lock, taken = FolderLock(path), 0
    barrier.wait()
    while taken < 100:
        try:
            lock.acquire()
        except ValueError:
            with guard:
                refused.value += 1
            continue
        with guard:
            inside.value += 1
            most.value = max(most.value, inside.value)
        with guard:
            inside.value -= 1
        lock.release()
        taken += 1


def test_taking_and_releasing_in_a_loop_never_gives_two_holders(tmp_path):
    """Releasing removes .lock; a process that locked the removed file must notice (without that check
    this fails at once)."""
    ctx = mp.get_context("fork")
    inside, most, refused = ctx.Value("i", 0), ctx.Value("i", 0), ctx.Value("i", 0)
    procs = _run(_churn, (str(tmp_path), ctx.Barrier(CONTENDERS, timeout=60), inside, most, ctx.Lock(), refused),
                 CONTENDERS)
    _join(procs)
    assert most.value == 1, most.value
    assert not (tmp_path / ".lock").exists()


def _hold_and_wait(path, ready):
    FolderLock(path).acquire()
    ready.set()
    time.sleep(60)


def test_the_lock_of_a_killed_process_is_taken_over(tmp_path):
    ctx = mp.get_context("fork")
    ready = ctx.Event()
    p = ctx.Process(target=_hold_and_wait, args=(str(tmp_path), ready))
    p.start()
    assert ready.wait(30)
    with pytest.raises(ValueError, match=f"in use by another run \\(process {p.pid} on "):
        FolderLock(tmp_path).acquire()
    os.kill(p.pid, signal.SIGKILL)                  # dies holding it: no release, .lock stays
    p.join(30)
    assert (tmp_path / ".lock").read_text().split()[0] == str(p.pid)
    with FolderLock(tmp_path) as lock:              # the kernel dropped the lock with the process
        assert lock.held and (tmp_path / ".lock").read_text().split()[0] == str(os.getpid())
    (tmp_path / ".lock").write_text(f"{os.getppid()} host 2020-01-01T00:00:00\n")   # a live pid, but no lock
    with FolderLock(tmp_path):
        pass


class _WindowsLikeOs:
    """``os`` as vpr_nb.run_folder sees it on Windows: no ``pread`` / ``pwrite`` (POSIX only), an open file cannot
    be removed (no FILE_SHARE_DELETE), and the byte 0 that ``LockFileEx`` locks cannot be read through another
    handle while it is held. Everything else is the real ``os``."""

    def __init__(self):
        self.open_fds: dict[int, str] = {}

    def __getattr__(self, name):
        if name in ("pread", "pwrite"):
            raise AttributeError(f"module 'os' has no attribute {name!r} (Windows)")
        return getattr(os, name)

    def open(self, path, flags, mode=0o777):
        fd = os.open(path, flags, mode)
        self.open_fds[fd] = str(path)
        return fd

    def close(self, fd):
        self.open_fds.pop(fd, None)
        os.close(fd)

    def unlink(self, path):
        st = os.stat(path)
        if any(os.path.samestat(os.fstat(fd), st) for fd in self.open_fds):
            raise PermissionError(13, "The process cannot access the file because it is being used by another "
                                      "process", str(path))
        os.unlink(path)

    def read(self, fd, n):
        if os.lseek(fd, 0, os.SEEK_CUR) == 0:
            raise PermissionError(13, "The process cannot access the file because another process has locked a "
                                      "portion of the file")
        return os.read(fd, n)


def test_the_lock_works_where_there_is_no_fcntl_as_on_windows(tmp_path, monkeypatch):
    """The lock is filelock's portable one (flock / LockFileEx), not ``fcntl`` (absent on Windows), and it keeps its
    behaviour under Windows' file rules: the second run is refused naming the holder, release removes .lock, the
    next run takes it. Today's code refuses at once ("fcntl.flock, which this platform lacks")."""
    fake = _WindowsLikeOs()
    monkeypatch.setattr(run_folder, "fcntl", None, raising=False)
    monkeypatch.setattr(run_folder, "os", fake)
    first = FolderLock(tmp_path)
    first.acquire()
    assert first.held and fake.open_fds
    with pytest.raises(ValueError, match=rf"{tmp_path} is in use by another run \(process {os.getpid()} on .+, "
                                         r"started \d{4}-.*: wait for it to finish or choose another folder"):
        FolderLock(tmp_path).acquire()
    assert len(fake.open_fds) == 1                     # the refused contender closed its file
    first.release()
    assert not first.held and not fake.open_fds and not (tmp_path / ".lock").exists()
    with OutputFolder(tmp_path / "run") as out:        # the whole --out protocol on top of it
        assert out.held and (tmp_path / "run" / ".lock").read_text().split()[0] == str(os.getpid())
    assert not (tmp_path / "run").exists() and not fake.open_fds


def test_a_waiter_holding_the_file_open_on_windows_keeps_it_and_takes_over(tmp_path, monkeypatch):
    """Windows cannot remove a file another process has open: the releasing run then leaves .lock in place and
    the process that opened it takes the lock on that same file (never two holders)."""
    fake = _WindowsLikeOs()
    monkeypatch.setattr(run_folder, "os", fake)
    holder = FolderLock(tmp_path)
    holder.acquire()
    waiter_fd = fake.open(tmp_path / ".lock", os.O_RDWR)          # a second run between its open and its lock
    holder.release()
    assert (tmp_path / ".lock").read_text() == ""                # kept (the waiter has it open), naming no one
    assert filelock.lock_descriptor(waiter_fd, blocking=False)            # the waiter's lock, on the file .lock names
    assert os.path.samestat(os.fstat(waiter_fd), os.stat(tmp_path / ".lock"))
    with pytest.raises(ValueError, match=r"in use by another run \(another process;"):
        FolderLock(tmp_path).acquire()
    filelock.unlock_descriptor(waiter_fd)
    fake.close(waiter_fd)
    with FolderLock(tmp_path) as lock:
        assert lock.held
    assert not (tmp_path / ".lock").exists()


def test_the_lock_is_the_one_filelock_takes(tmp_path):
    """A FolderLock and a filelock.FileLock on the same .lock exclude each other (one OS primitive everywhere)."""
    with FolderLock(tmp_path):
        with pytest.raises(filelock.Timeout):
            filelock.FileLock(str(tmp_path / ".lock")).acquire(timeout=0)
