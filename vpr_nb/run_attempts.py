"""The attempts of one run: a ``make reproduce`` stopped (Ctrl-C, ``kill -9``, a closed session) and started again
is one run made in several attempts, the later ones reusing the finished fine-tunes of the task store.

Each attempt appends to ``OUT/attempts.jsonl``: a ``start`` line (time, git commit, profile, notebooks, store), an
``alive`` line every minute while it runs (with the CPU time of the attempt's process tree so far,
:func:`tree_cpu_seconds`), a ``notebook`` line with each notebook's report entry as it ends, and an
``end`` line when it finishes. An attempt started again from the same commit skips the notebooks an earlier one
finished ok (:func:`finished_notebooks`) and keeps their outputs. An attempt started after one that
ended, or with another profile, notebook list or store (or none), begins a new run (the file starts again). So a killed
attempt's wall time is known to within a minute, and the report of the attempt that finishes gives the whole
run's: :func:`read` lists the attempts, :func:`summary` their wall and CPU times, their sums and the idle share
of the whole run.
"""
from __future__ import annotations

import json
import os
import resource
import threading
import time
from pathlib import Path

ALIVE_EVERY = 60.0          # seconds between two ``alive`` lines
SAME_RUN = ("profile", "notebooks", "store")


def tree_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process, of its children that ended, and of every live descendant
    (read from ``/proc``; where there is none, the live ones are left out)."""
    own, ended = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    total = own.ru_utime + own.ru_stime + ended.ru_utime + ended.ru_stime
    try:
        parents, times, tick = {}, {}, os.sysconf("SC_CLK_TCK")
        for entry in os.scandir("/proc"):
            if entry.name.isdigit():
                try:
                    with open(f"/proc/{entry.name}/stat", encoding="ascii", errors="replace") as fh:
                        fields = fh.read().rsplit(")", 1)[1].split()
                except OSError:
                    continue                          # ended meanwhile
                parents[int(entry.name)] = int(fields[1])
                times[int(entry.name)] = sum(int(x) for x in fields[11:15]) / tick   # utime stime cutime cstime
    except (OSError, ValueError, IndexError):
        return total
    mine, todo = set(), [os.getpid()]
    while todo:
        pid = todo.pop()
        kids = [p for p, parent in parents.items() if parent == pid and p not in mine]
        mine.update(kids)
        todo.extend(kids)
    return total + sum(times[p] for p in mine)


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
            if isinstance(r.get("cpu"), (int, float)):
                attempts[-1]["cpu"] = float(r["cpu"])
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


def summary(attempts, cores: int | None = None) -> dict:
    """``{"attempts": [{"commit", "minutes", "cpu minutes", "ended"}, ...], "minutes": sum, "cpu minutes": sum,
    "idle share": 1 − CPU / (wall × cores) over every attempt, "last share": the last attempt's minutes / sum}``
    (minutes to 0.1; CPU from each attempt's last line that carries it, None where none does)."""
    cores = cores or os.cpu_count() or 1
    rows = [{"commit": a.get("commit"), "minutes": round((a["last"] - a["start"]) / 60, 1),
             "cpu minutes": round(a["cpu"] / 60, 1) if "cpu" in a else None, "ended": a["ended"]} for a in attempts]
    wall = sum((a["last"] - a["start"]) for a in attempts)
    cpu = sum(a["cpu"] for a in attempts) if attempts and all("cpu" in a for a in attempts) else None
    last = (attempts[-1]["last"] - attempts[-1]["start"]) if attempts else 0.0
    return {"attempts": rows, "minutes": round(wall / 60, 1),
            "cpu minutes": None if cpu is None else round(cpu / 60, 1),
            "idle share": None if cpu is None or not wall else round(max(0.0, 1 - cpu / (wall * cores)), 3),
            "last share": round(last / wall, 3) if wall else 1.0}


class Attempt:
    """This attempt: :meth:`begin` writes its ``start`` line (starting the file again for a new run) and a thread
    its ``alive`` lines; :meth:`end` writes its ``end`` line and stops the thread."""

    def __init__(self, path, every: float = ALIVE_EVERY):
        self.path, self.every = Path(path), float(every)
        self._stop = threading.Event()
        self._thread = None
        self._cpu0 = tree_cpu_seconds()

    def _cpu(self) -> float:
        return round(tree_cpu_seconds() - self._cpu0, 1)

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
            self._write({"kind": "alive", "cpu": self._cpu()})

    def notebook_done(self, entry: dict) -> None:
        """A notebook of this attempt ended (its report entry: name, status, seconds, results, figures)."""
        self._write({"kind": "notebook", "entry": entry})

    def end(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._write({"kind": "end", "cpu": self._cpu()})


def summary_markdown(s: dict) -> list[str]:
    """The report's section on the run's attempts (its lines)."""
    idle = "" if s.get("idle share") is None else f", CPU {s['cpu minutes']} min: idle share {s['idle share']:.3f}"
    lines = ["", "## Attempts", "",
             f"- {len(s['attempts'])} attempt(s), {s['minutes']} min of wall time in all{idle}; the last took "
             f"{s['last share']:.0%} of it", "", "| attempt | commit | wall (min) | CPU (min) | finished |",
             "|---|---|---|---|---|"]
    lines += [f"| {i} | {a['commit']} | {a['minutes']} | {'' if a.get('cpu minutes') is None else a['cpu minutes']} | "
              f"{'yes' if a['ended'] else 'no (stopped)'} |" for i, a in enumerate(s["attempts"], 1)]
    return lines
