"""The attempts of one run: a ``make reproduce`` stopped (Ctrl-C, ``kill -9``, a closed session) and started again
is one run made in several attempts, the later ones reusing the finished fine-tunes of the task store.

Each attempt appends to ``OUT/attempts.jsonl``: a ``start`` line (time, git commit, profile, notebooks, store), an
``alive`` line every minute while it runs, a ``notebook`` line with each notebook's report entry as it ends, and an
``end`` line when it finishes. An attempt started again from the same commit skips the notebooks an earlier one
finished ok (:func:`finished_notebooks`) and keeps their outputs. An attempt started after one that
ended, or with another profile, notebook list or store (or none), begins a new run (the file starts again). So a killed
attempt's wall time is known to within a minute, and the report of the attempt that finishes gives the whole
run's: :func:`read` lists the attempts, :func:`summary` their wall times and sum.
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

ALIVE_EVERY = 60.0          # seconds between two ``alive`` lines
SAME_RUN = ("profile", "notebooks", "store")


def read(path) -> list[dict]:
    """The attempts in ``path``: each ``{"start", "last", "ended", **start line}``, ``last`` its last line's time
    (a torn or foreign line is skipped)."""
    attempts: list[dict] = []
    path = Path(path)
    if not path.is_file():
        return attempts
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            r = json.loads(line)
            kind, t = r["kind"], float(r["time"])
        except (ValueError, KeyError, TypeError):
            continue
        if kind == "start":
            attempts.append({**r, "start": t, "last": t, "ended": False, "finished": {}})
        elif attempts and kind == "notebook" and isinstance(r.get("entry"), dict) \
                and isinstance(r["entry"].get("name"), str):
            attempts[-1]["finished"][r["entry"]["name"]] = r["entry"]
            attempts[-1]["last"] = max(attempts[-1]["last"], t)
        elif attempts and kind in ("alive", "end"):
            attempts[-1]["last"] = max(attempts[-1]["last"], t)
            attempts[-1]["ended"] = attempts[-1]["ended"] or kind == "end"
    return attempts


def finished_notebooks(attempts, commit) -> dict[str, dict]:
    """The report entries of the notebooks that ``attempts`` (the earlier ones of this run) finished ok from the
    commit ``commit``: a run started again keeps them and runs only the others (a notebook finished by other code
    runs again)."""
    out: dict[str, dict] = {}
    for a in attempts:
        if a.get("commit") == commit and "uncommitted" not in str(commit):
            out.update({name: e for name, e in a["finished"].items() if e.get("status") == "ok"})
    return out


def summary(attempts) -> dict:
    """``{"attempts": [{"commit", "minutes", "ended"}, ...], "minutes": sum, "last share": the last attempt's
    minutes / sum}`` (minutes to 0.1)."""
    rows = [{"commit": a.get("commit"), "minutes": round((a["last"] - a["start"]) / 60, 1), "ended": a["ended"]}
            for a in attempts]
    total = sum((a["last"] - a["start"]) for a in attempts) / 60
    last = (attempts[-1]["last"] - attempts[-1]["start"]) / 60 if attempts else 0.0
    return {"attempts": rows, "minutes": round(total, 1), "last share": round(last / total, 3) if total else 1.0}


class Attempt:
    """This attempt: :meth:`begin` writes its ``start`` line (starting the file again for a new run) and a thread
    its ``alive`` lines; :meth:`end` writes its ``end`` line and stops the thread."""

    def __init__(self, path, every: float = ALIVE_EVERY):
        self.path, self.every = Path(path), float(every)
        self._stop = threading.Event()
        self._thread = None

    def _write(self, record: dict, mode: str = "a") -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        torn = mode == "a" and self.path.is_file() and self.path.stat().st_size > 0 \
            and not self.path.read_bytes().endswith(b"\n")          # an attempt killed mid-line
        with self.path.open(mode, encoding="utf-8") as fh:
            line = json.dumps({**record, "time": round(time.time(), 3)}, default=str)
            fh.write(("\n" if torn else "") + line + "\n")

    def begin(self, **info) -> list[dict]:
        """Write the start line; returns the earlier attempts of the same run (empty for a new run)."""
        earlier = read(self.path)
        same = (earlier and not earlier[-1]["ended"] and info.get("store") is not None     # no store: nothing kept
                and all(earlier[-1].get(k) == info.get(k) for k in SAME_RUN))
        earlier = earlier if same else []
        self._write({"kind": "start", **info}, "a" if same else "w")
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()
        return earlier

    def _beat(self) -> None:
        while not self._stop.wait(self.every):
            self._write({"kind": "alive"})

    def notebook_done(self, entry: dict) -> None:
        """A notebook of this attempt ended (its report entry: name, status, seconds, results, figures)."""
        self._write({"kind": "notebook", "entry": entry})

    def end(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._write({"kind": "end"})


def summary_markdown(s: dict) -> list[str]:
    """The report's section on the run's attempts (its lines)."""
    lines = ["", "## Attempts", "",
             f"- {len(s['attempts'])} attempt(s), {s['minutes']} min of wall time in all; the last took "
             f"{s['last share']:.0%} of it", "", "| attempt | commit | wall (min) | finished |", "|---|---|---|---|"]
    lines += [f"| {i} | {a['commit']} | {a['minutes']} | {'yes' if a['ended'] else 'no (stopped)'} |"
              for i, a in enumerate(s["attempts"], 1)]
    return lines
