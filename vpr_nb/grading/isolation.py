"""Grading isolates or refuses: which backend of :mod:`vpr_nb.grading.sandbox` grades the submissions.

Untrusted submissions are graded only inside the OS sandbox (bubblewrap). Where it is missing or does not
start, grading refuses with one line (:data:`NO_SANDBOX`, :class:`NoSandboxError`) unless the teacher says
the work is trusted (``trusted=True``, ``--trusted``); the ``process`` backend, which hides no file and
blocks no write, then grades, and every report says so (:data:`TRUSTED_LABEL`, :func:`label`).
"""
from __future__ import annotations

import os
import shutil

from .sandbox import BACKENDS, ENV_BACKEND, backend_works, process_uid_switch_works

NO_SANDBOX = ("no sandbox for untrusted submissions: install bubblewrap (apt-get install bubblewrap) "
              "or pass --trusted for work you trust")
TRUSTED_LABEL = "graded WITHOUT a sandbox (--trusted)"     # on every report of the process backend


class NoSandboxError(RuntimeError):
    """No OS sandbox works here, and the teacher did not say the work is trusted (``trusted=True``)."""


def choose_backend(requested: str | None = None, trusted: bool = False) -> str:
    """The backend that grades: ``requested``, else ``$VPR_NB_SANDBOX``, else ``bwrap`` where it works; the
    ``process`` backend, which is no sandbox, only for work the teacher trusts (``trusted``).

    Raises:
        NoSandboxError: bubblewrap does not work here (or ``process`` was asked for) and ``trusted`` is false,
            or ``bwrap`` was asked for and does not work.
        ValueError: an unknown backend name.
    """
    forced = requested or os.environ.get(ENV_BACKEND, "").strip() or None
    if forced is not None and forced not in BACKENDS:
        raise ValueError(f"unknown sandbox backend {forced!r}: use one of {BACKENDS}")
    if forced in (None, "bwrap") and backend_works("bwrap"):
        return "bwrap"
    installed = shutil.which("bwrap")
    why = (f"bubblewrap ({installed}) does not start here (user namespaces disabled?)" if installed
           else "bubblewrap is not installed (apt-get install bubblewrap)")
    if forced == "bwrap":
        raise NoSandboxError(f"the bwrap sandbox was asked for, but {why}")
    if installed and forced is None and not trusted:
        raise NoSandboxError(f"no sandbox for untrusted submissions: {why}; fix it or pass --trusted for work "
                             "you trust")
    if not trusted:
        raise NoSandboxError(NO_SANDBOX)
    return "process"


def label(backend: str) -> str:
    """How a grade report names the backend that graded it (a CSV column, the summary line)."""
    return "bubblewrap" if backend == "bwrap" else TRUSTED_LABEL


def describe(backend: str) -> str:
    """One line on what the backend protects, for the grader's report."""
    if backend == "bwrap":
        root = hasattr(os, "geteuid") and os.geteuid() == 0
        who = "a separate user id per submission" if root else "the grader's user id (not root)"
        return (f"OS sandbox (bubblewrap): read-only system, no network, only its throwaway folder visible and "
                f"writable, own PID namespace, {who}")
    if process_uid_switch_works():
        return (f"{TRUSTED_LABEL}: own session, limits, leftovers killed, a separate user id per submission; "
                "files readable by every user stay readable to submissions")
    return (f"{TRUSTED_LABEL}, no separate user id: limits and leftover cleanup only; a submission can read "
            "and write what the grader can, and signal it")
