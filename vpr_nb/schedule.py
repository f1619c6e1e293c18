"""How long a run would take on more workers, simulated from the times it recorded.

A notebook of a run is a sequence of **phases**: stretches of its own code (one worker, in order) and rounds of
tasks (:func:`vpr_nb.engine.log_round`), whose tasks may run on any free workers but whose next phase waits for
the whole round (the rounds are synchronous). :func:`notebook_phases` builds a notebook's phases from its start,
its wall time and its rounds; :func:`simulate` plays every notebook's phases at once on ``workers`` workers,
a free worker always taking the longest job that is ready (longest-processing-time list scheduling), and returns
the wall time. A notebook that reads another's results (``after``) starts when that one has finished, as in the
run. It ignores what sharing a machine costs (memory, caches), so it is a lower bound of what a real cluster of
that size gives. :func:`fastest_possible` is the bound no schedule of the same tasks can beat: the work divided
by the workers, or the longest chain of phases that must follow one another, whichever is longer.
"""
from __future__ import annotations

import heapq
import math
from collections.abc import Mapping, Sequence


def notebook_phases(start: float, seconds: float, rounds: Sequence[Mapping]) -> list:
    """The phases of one notebook that started at ``start`` (epoch seconds) and took ``seconds``, with
    ``rounds`` its logged rounds (``t0``, ``t1``, ``seconds`` per task): ``("code", s)`` for the time between
    rounds, ``("round", [s, ...])`` for a round."""
    if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"seconds must be a finite number >= 0, got {seconds!r}")
    phases, now = [], float(start)
    for r in sorted(rounds, key=lambda r: r["t0"]):
        if r["t0"] > now:
            phases.append(("code", r["t0"] - now))
        phases.append(("round", [float(x) for x in r["seconds"]]))
        now = max(now, float(r["t1"]))
    end = float(start) + float(seconds)
    if end > now:
        phases.append(("code", end - now))
    return phases


def _after(notebooks: Sequence[Sequence], after) -> list[set[int]]:
    after = [set() for _ in notebooks] if after is None else [set(a) for a in after]
    if len(after) != len(notebooks) or any(not all(isinstance(i, int) and 0 <= i < len(notebooks) for i in a)
                                           for a in after):
        raise ValueError(f"after must give, for each of the {len(notebooks)} notebooks, the indices of those it "
                         f"waits for; got {after!r}")
    return after


def simulate(notebooks: Sequence[Sequence], workers: int, after: Sequence | None = None) -> float:
    """The wall time of running ``notebooks`` (each a list of phases, :func:`notebook_phases`) at once on
    ``workers`` workers, by longest-first list scheduling with a barrier after each phase. ``after[i]``: the
    indices of the notebooks notebook ``i`` starts after (default: none); a circle among them is refused."""
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    after = _after(notebooks, after)
    phase_of = [0] * len(notebooks)
    left = [0] * len(notebooks)           # jobs of the current phase still running or waiting
    ready: list = []                      # (-seconds, notebook, k)
    running: list = []                    # (end time, notebook)
    now, free = 0.0, workers
    started: set[int] = set()
    finished: set[int] = set()

    def release(nb: int) -> None:         # queue the jobs of nb's next phase that has any, or finish nb
        while phase_of[nb] < len(notebooks[nb]):
            kind, value = notebooks[nb][phase_of[nb]]
            jobs = [float(value)] if kind == "code" else [float(x) for x in value]
            if jobs:
                left[nb] = len(jobs)
                for k, s in enumerate(jobs):
                    heapq.heappush(ready, (-s, nb, k))
                return
            phase_of[nb] += 1             # an empty round: nothing to wait for
        finished.add(nb)

    def start_ready() -> None:            # start every notebook whose predecessors have all finished
        progress = True
        while progress:
            progress = False
            for nb in range(len(notebooks)):
                if nb not in started and after[nb] <= finished:
                    started.add(nb)
                    release(nb)
                    progress = progress or nb in finished

    start_ready()
    while ready or running:
        while free and ready:
            s, nb, _ = heapq.heappop(ready)
            heapq.heappush(running, (now - s, nb))
            free -= 1
        now, nb = heapq.heappop(running)
        free += 1
        left[nb] -= 1
        if left[nb] == 0:
            phase_of[nb] += 1
            release(nb)
            if nb in finished:
                start_ready()
    if len(finished) != len(notebooks):
        raise ValueError("after has a circle: notebooks "
                         f"{sorted(set(range(len(notebooks))) - finished)} never start")
    return now


def fastest_possible(notebooks: Sequence[Sequence], workers: int, after: Sequence | None = None) -> float:
    """The least wall time any schedule of ``notebooks`` on ``workers`` workers can have (seconds): the larger of
    all their jobs' time divided by ``workers`` and the critical path (the wall time on as many workers as there
    are jobs, where every phase takes its longest job and a notebook waits for those in ``after``)."""
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    jobs = [float(x) for phases in notebooks for kind, v in phases for x in ([v] if kind == "code" else v)]
    return max(sum(jobs) / workers, simulate(notebooks, max(len(jobs), 1), after))


def scaling_table(notebooks: Sequence[Sequence], workers=(2, 8, 16, 64), after: Sequence | None = None) -> dict:
    """``{workers: simulated minutes}`` for each worker count (rounded to 0.1 min)."""
    return {int(w): round(simulate(notebooks, int(w), after) / 60, 1) for w in workers}


def parse_round(line: str | bytes) -> dict | None:
    """One line of ``$VPR_NB_TASK_TIMES`` (:func:`vpr_nb.engine.log_round`) as ``{"t0", "t1", "seconds",
    "reused"}`` (and ``"process"``, the token of the process that logged it, where the line has one), with
    ``seconds`` as floats and ``reused`` as bools of equal length; None for a line that is not a whole round (a
    kernel killed mid-write, or something else written there)."""
    import json

    try:
        r = json.loads(line)
        seconds = [float(x) for x in r["seconds"]]
        reused = [bool(x) for x in r["reused"]]
        t0, t1 = float(r["t0"]), float(r["t1"])
    except (ValueError, KeyError, TypeError):    # JSONDecodeError is a ValueError
        return None
    if len(seconds) != len(reused) or not all(math.isfinite(x) for x in (t0, t1, *seconds)):
        return None
    out = {"t0": t0, "t1": t1, "seconds": seconds, "reused": reused}
    if isinstance(r.get("process"), str):
        out["process"] = r["process"]
    return out


def read_rounds(path) -> list[dict]:
    """The rounds a notebook logged (``$VPR_NB_TASK_TIMES``), each read by :func:`parse_round`, skipping a line
    that is not a whole round."""
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        return []
    rounds = (parse_round(line) for line in path.read_text(encoding="utf-8", errors="replace").splitlines())
    return [r for r in rounds if r is not None]


def run_summary(notebooks: Sequence[Mapping], rounds: Mapping[str, list], wall: float, cpu: float,
                cores: int, workers=(2, 8, 16, 64), after: Mapping[str, set] | None = None) -> dict:
    """What a run's report says of its tasks: per notebook its tasks, how many were reused and their longest;
    the run's CPU time against ``wall`` × ``cores`` (the idle share); and, on each of ``workers``, the simulated
    wall time (:func:`scaling_table`) and the least any schedule could take (:func:`fastest_possible`), from each
    notebook's ``started`` and ``seconds`` and its ``rounds``. ``after``: {notebook: the notebooks it waits for}
    (:func:`vpr_nb.report.notebook_dependencies`); names not in the run are ignored."""
    per, phases = {}, []
    for nb in notebooks:
        rs = rounds.get(nb["name"], [])
        times = [s for r in rs for s in r["seconds"]]
        per[nb["name"]] = {"tasks": len(times), "reused": sum(sum(r["reused"]) for r in rs),
                           "task minutes": round(sum(times) / 60, 1),
                           "longest task (min)": round(max(times, default=0.0) / 60, 2),
                           "wall minutes": round(nb["seconds"] / 60, 1)}
        phases.append(notebook_phases(nb.get("started", 0.0), nb["seconds"], rs))
    index = {nb["name"]: i for i, nb in enumerate(notebooks)}
    waits = [{index[o] for o in (after or {}).get(nb["name"], ()) if o in index} for nb in notebooks]
    try:
        simulate(phases, 1, waits)
    except ValueError:                    # a circle: the run went in order, each waiting only for earlier ones
        waits = [{j for j in w if j < i} for i, w in enumerate(waits)]
    idle = 1.0 - cpu / (wall * cores) if wall > 0 and cores > 0 else 0.0
    return {"notebooks": per, "wall minutes": round(wall / 60, 1), "cpu minutes": round(cpu / 60, 1),
            "cores": cores, "idle share": round(max(idle, 0.0), 3),
            "simulated minutes": scaling_table(phases, workers, waits) if phases else {},
            "fastest possible minutes": {int(w): round(fastest_possible(phases, int(w), waits) / 60, 1)
                                         for w in workers} if phases else {},
            "waits for": {nb["name"]: sorted(notebooks[i]["name"] for i in w) for nb, w in zip(notebooks, waits)
                          if w}}


def summary_markdown(summary: Mapping) -> list[str]:
    """The report's section on the run's tasks (its lines)."""
    lines = ["", "## Tasks, idle share and simulated scaling", "",
             f"- wall {summary['wall minutes']} min, CPU {summary['cpu minutes']} min on {summary['cores']} cores: "
             f"idle share {summary['idle share']:.3f}",
             "- simulated wall time (min) by workers: "
             + ", ".join(f"{w}: {m}" for w, m in summary["simulated minutes"].items()),
             "- the least any schedule of these tasks could take (min; the work over the workers, or the longest "
             "chain of rounds that wait for each other): "
             + ", ".join(f"{w}: {m}" for w, m in summary.get("fastest possible minutes", {}).items()), "",
             "| notebook | wall (min) | tasks | reused | task time (min) | longest task (min) |", "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {v['wall minutes']} | {v['tasks']} | {v['reused']} | {v['task minutes']} | "
              f"{v['longest task (min)']} |" for name, v in summary["notebooks"].items()]
    return lines
