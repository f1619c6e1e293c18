"""Run an untrusted program in a throwaway folder, with limits, and leave nothing of it running.

Two backends (:func:`vpr_nb.grading.isolation.choose_backend` picks one for a grading; ``VPR_NB_SANDBOX``
forces one):

* ``bwrap`` (Debian's ``bubblewrap``), the only sandbox: a new mount, PID, network, IPC and UTS namespace.
  The program sees a read-only system (``/usr``, ``/etc``, the Python installation, the ``vpr_nb`` package
  and the committed results) and nothing else of the machine: no instructor notebooks, no other
  submission, no grades file, no home folder; a teacher's path that one of those read-only folders would
  show (``private``: the instructor notebooks and their folder, the class folder, the grades file's
  folder) is covered (an empty file or folder in its place), or grading refuses to start. It gets an
  empty private ``/tmp``, no network, and its throwaway folder as the only writable place of the
  machine. As root it runs as a fresh user id per submission, without capabilities. When its first
  process ends, or bwrap or the grader dies (``--die-with-parent``), the kernel kills every process of
  the PID namespace, including ones that called ``setsid`` or double-forked.
* ``process`` (no OS sandbox; only for work the teacher trusts, ``trusted=True`` / ``--trusted``, and
  said so on every report): the program runs in its own session with the same limits; as root, and where
  the Python installation is readable by other users, under a fresh user id per submission; leftovers
  are found by that user id and by a token in their environment. It hides no file the grader's user can
  read, and without a separate user id a submission can write or kill what the grader can.

Without a working bubblewrap and without ``trusted``, grading refuses (:mod:`vpr_nb.grading.isolation`).
Both backends apply the limits of :class:`Limits` (CPU seconds, address space, processes, file size;
through ``prlimit``) and a wall-clock limit, after which the whole process tree is killed; both then kill
every process that is still alive and belongs to the run (leftovers are counted in :class:`Outcome`).
"""
from __future__ import annotations

import functools
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ..package_data import RESULTS_DIR_ENV, committed_results_dir

ENV_BACKEND = "VPR_NB_SANDBOX"
TOKEN_VAR = "VPR_NB_SANDBOX_TOKEN"
UID_BASE, UID_COUNT = 61000, 1000        # per-submission user ids, when the grader runs as root
BACKENDS = ("bwrap", "process")


@dataclass(frozen=True)
class Limits:
    """What one sandboxed run may use."""
    wall_s: float = 120.0         # wall-clock seconds, then the whole tree is killed
    cpu_s: float = 120.0          # CPU seconds per process (RLIMIT_CPU)
    memory_mb: int = 4096         # address space per process (RLIMIT_AS); torch alone maps ~1.2 GB
    processes: int = 64           # processes and threads of the run's user (RLIMIT_NPROC; needs its own uid)
    file_mb: int = 64             # largest file it may write (RLIMIT_FSIZE)

    def __post_init__(self):
        for name in ("wall_s", "cpu_s", "memory_mb", "processes", "file_mb"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Limits.{name} must be positive, got {getattr(self, name)!r}")


@dataclass
class Outcome:
    """How a sandboxed run ended."""
    returncode: int | None        # None: killed at the wall-clock limit
    timed_out: bool
    seconds: float
    leftovers: int                # processes still alive after the program ended (all killed)
    log: str                      # the tail of its stdout and stderr
    backend: str


# --------------------------------------------------------------------------------------------------
# which backend


def _python_roots() -> list[Path]:
    """What the sandboxed Python needs to see: its installation, the vpr_nb package (with the course
    backbone, its package data) and the committed results the notebooks read, nothing else."""
    pkg = Path(__file__).resolve().parents[1]                      # .../vpr_nb
    roots = {Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve(), Path(sys.executable).resolve().parent,
             pkg}
    results = _results_dir()
    if results is not None:                                        # a checkout's notebooks/results/ (read-only)
        roots.add(results)
    for entry in sys.path:                                         # site-packages outside the prefixes
        p = Path(entry).resolve() if entry else None
        if p is not None and p.is_dir() and "site-packages" in p.parts:
            roots.add(p)
    keep = []
    for r in sorted(roots, key=lambda p: len(p.parts)):
        if not any(r.is_relative_to(k) for k in keep):
            keep.append(r)
    return keep


def _results_dir() -> Path | None:
    """The committed results folder the grader itself reads (:func:`vpr_nb.package_data.committed_results_dir`),
    shown to the submission read-only and named to it by ``VPR_NB_RESULTS_DIR``: inside the OS sandbox the
    checkout around it is not visible, so the runner could not find it on its own."""
    path = committed_results_dir().resolve()
    return path if path.is_dir() else None


def _is_root() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


def python_command() -> list[str]:
    """Start the runner with ``-I`` (no user site, no PYTHON* variables, no cwd on sys.path) and the
    package's parent folder on sys.path (inside bwrap that folder holds only the package)."""
    parent = str(Path(__file__).resolve().parents[2])
    boot = (f"import sys; sys.path.insert(0, {parent!r}); import runpy; "
            "runpy.run_module('vpr_nb.grading.runner', run_name='__main__')")
    return [sys.executable, "-I", "-c", boot]


_TOPS = ("bin", "sbin", "lib", "lib32", "lib64", "libx32")    # merged-/usr links or real folders


def _shown() -> list[Path]:
    """The machine's folders a bwrap run sees (read-only): the system and :func:`_python_roots`."""
    tops = [Path("/") / t for t in _TOPS if (Path("/") / t).is_dir() and not (Path("/") / t).is_symlink()]
    return tops + [Path("/usr"), Path("/etc")] + [r for r in _python_roots()
                                                  if not any(r.is_relative_to(m) for m in ("/usr", "/etc"))]


def _covers(private, workdir: Path) -> list[str]:
    """bwrap arguments that cover each ``private`` path (the teacher's: instructor notebooks, folders of
    submissions and grades) that a read-only folder of :func:`_shown` would show: an empty file over a file,
    an empty tmpfs over a folder.

    Raises:
        ValueError: a private folder holds a folder the run must see (the package, the Python
            installation, the results, the run's own folder), so it cannot be covered.
    """
    shown, args, covered = _shown(), [], []
    for path in sorted({Path(p).resolve() for p in private}, key=lambda p: len(p.parts)):   # folders first
        if (not path.exists() or not any(path.is_relative_to(r) for r in shown)
                or any(path.is_relative_to(c) for c in covered)):
            continue
        if not path.is_dir():
            args += ["--ro-bind", "/dev/null", str(path)]
            continue
        inner = [r for r in shown + [workdir] if r.is_relative_to(path)]
        if inner:
            raise ValueError(f"{path} would be visible to every submission: it holds {inner[0]}, which the sandbox "
                             "shows read-only; keep the instructor notebooks, the submissions and the grades file "
                             "in another folder")
        args += ["--tmpfs", str(path)]
        covered.append(path)
    return args


def check_private(private) -> None:
    """Refuse (ValueError) before grading starts when a ``private`` path could not be hidden from a bwrap run."""
    _covers(private, Path(tempfile.gettempdir()).resolve() / "vpr_nb_grade_")


def _bwrap_args(workdir: Path, uid: int | None, private=()) -> list[str]:
    args = ["bwrap", "--die-with-parent", "--new-session", "--unshare-pid", "--unshare-net", "--unshare-ipc",
            "--unshare-uts", "--unshare-cgroup-try"]
    if uid is None:                       # not root: an unprivileged user namespace
        args += ["--unshare-user"]
    made: set[str] = {"/"}

    def parents(path: Path):
        for anc in reversed(path.parents):
            a = str(anc)
            if a not in made:
                made.add(a)
                args.extend(["--perms", "0755", "--dir", a])

    for top in _TOPS:
        p = Path("/") / top
        if p.is_symlink():
            args.extend(["--symlink", os.readlink(p), str(p)])
        elif p.is_dir():
            args.extend(["--ro-bind", str(p), str(p)])
    # /tmp before the Python roots: one of them under /tmp (VPR_NB_RESULTS_DIR) is bound into the tmpfs, not hidden by it
    args += ["--ro-bind", "/usr", "/usr", "--ro-bind", "/etc", "/etc", "--proc", "/proc", "--dev", "/dev",
             "--perms", "1777", "--tmpfs", "/tmp"]
    made.update({"/usr", "/etc", "/proc", "/dev", "/tmp"})
    for root in _python_roots():
        if not any(root.is_relative_to(m) for m in ("/usr", "/etc")):
            parents(root)
            args.extend(["--ro-bind", str(root), str(root)])
            made.add(str(root))
    args += _covers(private, workdir)     # after the binds they cover
    parents(workdir)
    args += ["--bind", str(workdir), str(workdir), "--chdir", str(workdir)]
    if uid is not None:                   # root: the runner drops to the submission's uid itself
        args += ["--cap-add", "CAP_SETUID", "--cap-add", "CAP_SETGID"]
    return args + ["--"]


def _probe(backend: str, uid_switch: bool) -> bool:
    """Whether the runner starts under ``backend`` (with a separate uid when ``uid_switch``)."""
    if backend == "bwrap" and shutil.which("bwrap") is None:
        return False
    try:
        with Workdir(UID_BASE + UID_COUNT - 1 if uid_switch else None) as wd:
            wd.hand_over()
            return _run(["--probe"], wd, Limits(wall_s=120), backend).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


@functools.lru_cache(maxsize=None)
def backend_works(backend: str) -> bool:
    """Whether ``backend`` can run the grader's Python here (tried once, then remembered)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown sandbox backend {backend!r}: use one of {BACKENDS}")
    if not sys.platform.startswith("linux"):
        return backend == "process"
    return True if backend == "process" else _probe("bwrap", _is_root())


@functools.lru_cache(maxsize=None)
def process_uid_switch_works() -> bool:
    """Whether the process backend can run the grader's Python under another user id (root only)."""
    return _is_root() and sys.platform.startswith("linux") and _probe("process", True)


# --------------------------------------------------------------------------------------------------
# user ids and leftovers

_uid_lock = threading.Lock()
_uids_in_use: set[int] = set()


def _processes():
    """(pid, real uid, environ bytes) of every process we can see."""
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        pid = int(entry.name)
        try:
            with open(f"/proc/{pid}/status", "rb") as fh:
                uid = next(int(line.split()[1]) for line in fh if line.startswith(b"Uid:"))
        except (OSError, StopIteration, ValueError):
            continue
        try:
            with open(f"/proc/{pid}/environ", "rb") as fh:
                env = fh.read()
        except OSError:
            env = b""
        yield pid, uid, env


def _allocate_uid() -> int:
    with _uid_lock:
        busy = {uid for _, uid, _ in _processes()} | _uids_in_use
        for uid in range(UID_BASE, UID_BASE + UID_COUNT - 1):
            if uid not in busy:
                _uids_in_use.add(uid)
                return uid
    raise RuntimeError(f"no free user id in {UID_BASE}..{UID_BASE + UID_COUNT - 2} for the sandbox")


def _release_uid(uid: int | None) -> None:
    with _uid_lock:
        _uids_in_use.discard(uid)


_live_lock = threading.Lock()
_live_children: set[int] = set()      # the runs' first processes, while they run


def _become_subreaper() -> bool:
    """Make this process the "subreaper" of its descendants (Linux ``PR_SET_CHILD_SUBREAPER``): a process of
    a run that double-forks or calls ``setsid`` is then re-parented to the grader, not to init, and found."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(36, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _orphans() -> list[int]:
    """Processes re-parented to the grader (it is their subreaper) that are not a run's first process."""
    me = str(os.getpid()).encode()
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                with open(f"/proc/{entry.name}/status", "rb") as fh:
                    ppid = next(line.split()[1] for line in fh if line.startswith(b"PPid:"))
            except (OSError, StopIteration, IndexError):
                continue
            if ppid == me:
                found.append(int(entry.name))
    with _live_lock:
        return [p for p in found if p not in _live_children]


def kill_run(token: str, uid: int | None, orphans: bool = False, before: frozenset = frozenset()) -> int:
    """SIGKILL every process of the run (its uid, the token in its environment, or, with ``orphans``, a
    process re-parented to the grader that was not its child ``before`` the run) until none is left;
    returns how many were killed."""
    needle = f"{TOKEN_VAR}={token}".encode()
    me = os.getpid()
    killed: set[int] = set()
    for _ in range(200):
        found = [pid for pid, puid, env in _processes()
                 if pid != me and ((uid is not None and puid == uid) or needle in env.split(b"\0"))]
        strays = [p for p in _orphans() if p not in before] if orphans else []
        if not found and not strays:
            break
        for pid in found + strays:
            try:
                os.kill(pid, signal.SIGKILL)
                killed.add(pid)
            except (ProcessLookupError, PermissionError):
                pass
        for pid in strays:                 # our children now: reap them
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass
        time.sleep(0.02)
    return len(killed)


# --------------------------------------------------------------------------------------------------
# a run


class Workdir:
    """A fresh private folder (mode 0700) for one submission and the user id it runs as.

    ``Workdir(backend="bwrap")`` picks a free uid where the backend switches users (None otherwise);
    ``Workdir(uid)`` uses the given one. On exit the folder is deleted and the uid freed.
    """

    def __init__(self, uid: int | None = None, parent=None, backend: str | None = None):
        self.uid = new_uid(backend) if backend is not None else uid
        self.path = Path(tempfile.mkdtemp(prefix="vpr_nb_grade_", dir=parent)).resolve()
        os.chmod(self.path, 0o700)

    def hand_over(self) -> None:
        """Give the folder and every file written so far to the run's uid (after writing its inputs)."""
        if self.uid is None:
            return
        for root, dirs, files in os.walk(self.path):
            for name in dirs + files:
                os.lchown(os.path.join(root, name), self.uid, self.uid)
        os.chown(self.path, self.uid, self.uid)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        shutil.rmtree(self.path, ignore_errors=True)
        _release_uid(self.uid)


def _rlimit_prefix(limits: Limits) -> tuple[list[str], object]:
    cpu = int(max(1, limits.cpu_s))
    values = {"--cpu": f"{cpu}:{cpu + 5}", "--as": str(limits.memory_mb * 2 ** 20),
              "--nproc": str(limits.processes), "--fsize": str(limits.file_mb * 2 ** 20), "--core": "0"}
    if shutil.which("prlimit"):
        return ["prlimit"] + [f"{k}={v}" for k, v in values.items()] + ["--"], None
    import resource

    def preexec():                        # no prlimit binary: the same limits from the forked child
        resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
        resource.setrlimit(resource.RLIMIT_AS, (limits.memory_mb * 2 ** 20,) * 2)
        resource.setrlimit(resource.RLIMIT_NPROC, (limits.processes,) * 2)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limits.file_mb * 2 ** 20,) * 2)
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    return [], preexec


def new_uid(backend: str) -> int | None:
    """A fresh user id for one run (None where the backend runs as the grader's user)."""
    if backend == "bwrap" and _is_root():
        return _allocate_uid()
    if backend == "process" and process_uid_switch_works():
        return _allocate_uid()
    return None


def run(args: list[str], workdir: Workdir, limits: Limits = Limits(), backend: str | None = None,
        env: dict | None = None, private=()) -> Outcome:
    """Run the runner (``python -I -m vpr_nb.grading.runner`` + ``args``) in ``workdir`` under ``backend``
    (default ``bwrap``; :func:`vpr_nb.grading.isolation.choose_backend` picks it for a grading), with the
    ``private`` paths hidden (bwrap).

    The program's stdout and stderr go to a file outside ``workdir`` (never to a pipe that a leftover
    child could hold open), the wall-clock limit is enforced here, and every process of the run is gone
    when this returns.
    """
    backend = backend or "bwrap"
    if not backend_works(backend):
        raise ValueError(f"the sandbox backend {backend!r} does not work on this machine")
    return _run(args, workdir, limits, backend, env, private)


def _run(args: list[str], workdir: Workdir, limits: Limits, backend: str, env: dict | None = None,
         private=()) -> Outcome:
    uid = workdir.uid
    token = secrets.token_hex(12)
    full_env = {"PATH": "/usr/bin:/bin", "HOME": str(workdir.path), "LANG": "C.UTF-8", "MPLBACKEND": "Agg",
                "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                "IPYTHONDIR": str(workdir.path / ".ipython"), "MPLCONFIGDIR": str(workdir.path / ".matplotlib"),
                "TMPDIR": "/tmp" if backend == "bwrap" else str(workdir.path), "PYTHONDONTWRITEBYTECODE": "1",
                TOKEN_VAR: token, **(env or {})}
    results = _results_dir()
    if results is not None:
        full_env.setdefault(RESULTS_DIR_ENV, str(results))
    prefix, preexec = _rlimit_prefix(limits)
    runner_args = list(args)
    kw: dict = {}
    if backend == "bwrap":
        cmd = prefix + _bwrap_args(workdir.path, uid, private) + python_command() + runner_args
        if uid is not None:
            cmd += ["--uid", str(uid)]
    else:
        cmd = prefix + python_command() + runner_args
        if uid is not None:
            kw = {"user": uid, "group": uid, "extra_groups": []}
    reaper = backend == "process" and _become_subreaper()
    before = frozenset(_orphans()) if reaper else frozenset()
    log_dir = tempfile.mkdtemp(prefix="vpr_nb_log_")
    log_path = Path(log_dir) / "log.txt"
    start = time.monotonic()
    timed_out = False
    try:
        with open(log_path, "wb") as log:
            with _live_lock:          # registered before another run's cleanup can take it for an orphan
                proc = subprocess.Popen(cmd, cwd=workdir.path, env=full_env, stdin=subprocess.DEVNULL, stdout=log,
                                        stderr=subprocess.STDOUT, start_new_session=True, preexec_fn=preexec,
                                        close_fds=True, **kw)
                _live_children.add(proc.pid)
            try:
                proc.wait(timeout=limits.wall_s)
            except subprocess.TimeoutExpired:
                timed_out = True
            finally:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
                proc.kill()
                proc.wait()
                with _live_lock:
                    _live_children.discard(proc.pid)
        leftovers = kill_run(token, uid, orphans=reaper, before=before)
        seconds = time.monotonic() - start
        with open(log_path, "rb") as fh:
            fh.seek(max(0, log_path.stat().st_size - 4000))
            tail = fh.read().decode("utf-8", "replace")
    finally:
        shutil.rmtree(log_dir, ignore_errors=True)
    return Outcome(None if timed_out else proc.returncode, timed_out, seconds, leftovers, tail, backend)
