"""The timed whole runs of ``make reproduce``: each kept as the run's own report figures, and the docs' tables made
from them, so that no run time in the docs is typed by hand.

``python -m vpr_nb.timed_runs add reports/results.json`` checks a finished run's report (the reproduce profile,
every notebook ok, a clean commit) and keeps what the docs need in ``docs/timed_runs/<commit>.json``: the commit
and date, its attempts (:mod:`vpr_nb.run_attempts`) and their wall time, its CPU time and idle share, the wall time
simulated on 2, 8, 16 and 64 workers (:mod:`vpr_nb.schedule`), and per notebook its wall time in the last attempt,
its fine-tunes (run, reused) and their own minutes. ``python -m vpr_nb.timed_runs docs`` then rewrites the block
between the ``timed-runs`` markers of ``docs/reproduction.md`` and README's ``make reproduce`` time;
``tests/test_timed_runs.py`` fails when either differs from what the records give.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

from .report import task_summary

BEGIN, END = "<!-- timed-runs: begin (python -m vpr_nb.timed_runs docs) -->", "<!-- timed-runs: end -->"
README_LINE = re.compile(r"(make reproduce +# every notebook at its full budget, reports/ \()([^)]*)(\))")
WORKERS = ("2", "8", "16", "64")


def _number(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{what} must be a finite number >= 0, got {value!r}")
    return float(value)


def _text(value, what: str) -> str:
    if not isinstance(value, str) or not value or len(value) > 200:
        raise ValueError(f"{what} must be a short non-empty text, got {value!r}")
    return value


def record_of(report: dict) -> dict:
    """What the docs keep of a finished run's ``results.json`` (refused, naming why, unless it is a whole
    reproduce-profile run from a clean commit with every notebook ok)."""
    if not isinstance(report, dict):
        raise ValueError("a run's report must be a JSON object (reports/results.json)")
    header, tasks, attempts = report.get("header"), report.get("tasks"), report.get("attempts")
    if not all(isinstance(x, dict) for x in (header, tasks, attempts)):
        raise ValueError("the report lacks its header, tasks or attempts: it was written by an older vpr_nb, or "
                         "by hand; run make reproduce again")
    if header.get("profile") != "reproduce":
        raise ValueError(f"only a reproduce-profile run is a timed run, this one is {header.get('profile')!r}")
    commit = _text(header.get("git commit"), "the report's git commit")
    if not re.fullmatch(r"[0-9a-f]{7,40}", commit):
        raise ValueError(f"the run must come from a clean commit, its report says {commit!r}")
    notebooks = report.get("notebooks")
    if not isinstance(notebooks, list) or not notebooks:
        raise ValueError("the report lists no notebooks")
    failed = [nb.get("name") for nb in notebooks if not isinstance(nb, dict) or nb.get("status") != "ok"]
    if failed:
        raise ValueError(f"a timed run has every notebook ok; these were not: {failed}")
    per = tasks.get("notebooks") if isinstance(tasks.get("notebooks"), dict) else {}
    rows = {}
    for nb in notebooks:
        name = _text(nb.get("name"), "a notebook's name")
        t = per.get(name, {})
        rows[name] = {"wall minutes": round(_number(nb.get("seconds"), f"{name}'s seconds") / 60, 1),
                      "fine-tunes": int(_number(t.get("tasks", 0), f"{name}'s tasks")),
                      "reused": int(_number(t.get("reused", 0), f"{name}'s reused tasks")),
                      "task minutes": _number(t.get("task minutes", 0.0), f"{name}'s task minutes"),
                      "longest task (min)": _number(t.get("longest task (min)", 0.0), f"{name}'s longest task")}
    sim = tasks.get("simulated minutes")
    if not isinstance(sim, dict) or set(map(str, sim)) != set(WORKERS):
        raise ValueError(f"the report's simulated minutes must be given for {WORKERS} workers, got {sim!r}")
    fast = tasks.get("fastest possible minutes")
    runs = attempts.get("attempts")
    if not isinstance(runs, list) or not runs or not all(isinstance(a, dict) for a in runs):
        raise ValueError("the report lists no attempts")
    return {"commit": commit, "date": _text(header.get("date"), "the report's date"),
            "machine": _text(header.get("machine", "unknown"), "the report's machine"),
            "jobs": int(_number(report.get("jobs"), "jobs")),
            "attempts": [{"minutes": _number(a.get("minutes"), "an attempt's minutes"), "ended": bool(a.get("ended")),
                          "commit": _text(a.get("commit"), "an attempt's commit")} for a in runs],
            "wall minutes": _number(attempts.get("minutes"), "the attempts' minutes"),
            # the whole run's CPU and idle share (every attempt); a report without them: its last attempt's
            "cpu minutes": _number(attempts.get("cpu minutes") if attempts.get("cpu minutes") is not None
                                   else tasks.get("cpu minutes"), "the CPU minutes"),
            "idle share": _number(attempts.get("idle share") if attempts.get("idle share") is not None
                                  else tasks.get("idle share"), "the idle share"),
            "simulated minutes": {w: _number(sim.get(w, sim.get(int(w))), f"simulated minutes on {w}")
                                  for w in WORKERS},
            **({"fastest possible minutes": {w: _number(fast.get(w, fast.get(int(w))), f"fastest possible on {w}")
                                             for w in WORKERS}} if isinstance(fast, dict) and fast else {}),
            "notebooks": rows}


def with_task_summary(report: dict, folder) -> dict:
    """``report`` with its tasks' summary made again by this vpr_nb (:func:`vpr_nb.report.task_summary`) from the
    rounds and notebooks the run left in ``folder``, so a run's record has every figure this version gives (the
    waits between notebooks, the fastest possible schedule) from the same logged times; as it is when the run's
    ``records/`` are gone."""
    folder = Path(folder)
    tasks, notebooks = report.get("tasks"), report.get("notebooks")
    if not (folder / "records").is_dir() or not isinstance(tasks, dict) or not isinstance(notebooks, list):
        return report
    try:
        again = task_summary(folder, notebooks, _number(report.get("wall_seconds"), "the report's wall_seconds"),
                             _number(tasks.get("cpu minutes"), "the tasks' CPU minutes") * 60,
                             int(_number(tasks.get("cores"), "the tasks' cores")))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"the report's notebooks are not as make reproduce writes them ({exc!r})") from None
    return {**report, "tasks": again}


def read_records(folder) -> list[dict]:
    """Every kept record in ``folder``, oldest first (by date, then file name); a file that is not a record is
    refused naming it."""
    out = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(doc, dict) or not {"commit", "date", "attempts", "notebooks"} <= set(doc):
                raise ValueError("not a timed-run record")
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}; remove it or make it again with python -m vpr_nb.timed_runs add")
        out.append(doc)
    return sorted(out, key=lambda d: d["date"])


def hours(record: dict) -> float:
    """The record's wall time in hours (one decimal): every attempt's, summed."""
    return round(record["wall minutes"] / 60, 1)


def readme_text(records: list[dict]) -> str | None:
    """What README's ``make reproduce`` line says in its brackets, or None without a record."""
    if not records:
        return None
    r = records[-1]
    tail = "" if len(r["attempts"]) == 1 else f" in {len(r['attempts'])} attempts"
    return f"{hours(r)} h on 2 cores, measured{tail}; resumes if stopped"


def docs_block(records: list[dict]) -> str:
    """The Markdown between the markers: every run, then the last run's notebooks."""
    if not records:
        return "No whole `make reproduce` has been timed yet."
    lines = ["| commit | date | attempts | wall (min) | CPU (min) | idle share | simulated on 2 / 8 / 16 / 64 "
             "workers (min) | fastest possible on 2 / 8 / 16 / 64 (min) |", "|---|---|---|---|---|---|---|---|"]
    for r in records:
        sim = " / ".join(f"{r['simulated minutes'][w]:g}" for w in WORKERS)
        fast = " / ".join(f"{r['fastest possible minutes'][w]:g}" for w in WORKERS) \
            if "fastest possible minutes" in r else "not recorded"
        lines.append(f"| {r['commit']} | {r['date']} | {len(r['attempts'])} | **{r['wall minutes']:g}** | "
                     f"{r['cpu minutes']:g} | {r['idle share']:.3f} | {sim} | {fast} |")
    last = records[-1]
    lines += ["", f"Per notebook, run {last['commit']} (wall: its last attempt; fine-tunes reused from earlier attempts "
              "count at the time each took when it ran):", "",
              "| notebook | wall (min) | fine-tunes | reused | fine-tune time (min) | longest (min) |",
              "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {v['wall minutes']:g} | {v['fine-tunes']} | {v['reused']} | {v['task minutes']:g} | "
              f"{v['longest task (min)']:g} |" for name, v in last["notebooks"].items()]
    return "\n".join(lines)


def render_docs(text: str, records: list[dict]) -> str:
    """``text`` (docs/reproduction.md) with its block between the markers made from ``records``."""
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise ValueError(f"the docs need one {BEGIN!r} line and one {END!r} line after it")
    head, rest = text.split(BEGIN)
    _, tail = rest.split(END)
    return f"{head}{BEGIN}\n{docs_block(records)}\n{END}{tail}"


def render_readme(text: str, records: list[dict]) -> str:
    """``text`` (README.md) with its ``make reproduce`` time from ``records`` (left as it is without one)."""
    said = readme_text(records)
    if not README_LINE.search(text):
        raise ValueError("README has no 'make reproduce   # every notebook at its full budget, reports/ (...)' line")
    return text if said is None else README_LINE.sub(lambda m: m.group(1) + said + m.group(3), text, count=1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.timed_runs", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    add = sub.add_parser("add", help="keep a finished run's report figures in docs/timed_runs/")
    add.add_argument("report", help="the run's reports/results.json")
    sub.add_parser("docs", help="rewrite docs/reproduction.md's timed-runs block and README's time from the records")
    for p in sub.choices.values():
        p.add_argument("--root", default=".", help="the course repository (default: here)")
    args = parser.parse_args(argv)
    root = Path(args.root)
    folder = root / "docs" / "timed_runs"
    try:
        if args.command == "add":
            try:
                report = json.loads(Path(args.report).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise ValueError(f"cannot read {args.report} as a report ({exc})") from None
            record = record_of(with_task_summary(report, Path(args.report).parent))
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{record['commit']}.json").write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
            print(f"kept {folder / (record['commit'] + '.json')}; now run python -m vpr_nb.timed_runs docs")
        else:
            records = read_records(folder)
            for name, render in (("docs/reproduction.md", render_docs), ("README.md", render_readme)):
                path = root / name
                path.write_text(render(path.read_text(encoding="utf-8"), records), encoding="utf-8")
            print(f"rewrote docs/reproduction.md and README.md from {len(records)} timed run(s)")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
