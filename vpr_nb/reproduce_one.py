"""One notebook of ``make reproduce``, for a student who wants to re-make one conclusion.

``make reproduce NOTEBOOK=03`` runs ``python -m vpr_nb.report --profile reproduce --notebook 03``: the report
runner (:mod:`vpr_nb.report`) executes that notebook alone, after the notebooks whose results it reads only
when their committed results are missing. This module holds what is particular to such a run:

- which notebooks run (:func:`select_notebook`, :func:`notebooks_to_run`);
- the estimate printed before it starts (:func:`estimate`, from the time its committed results took and from
  the last timed ``make reproduce``, :data:`MEASURED_MINUTES`) and the progress line printed while it runs
  (:class:`Heartbeat`);
- where its results go (:func:`prepare_results_dir`): ``OUT/results/``, never ``notebooks/results/`` unless
  asked, holding copies of the committed results of the notebooks that do not run, which it may read;
- its numbers beside the committed ones (:func:`compare_results`, :func:`render_comparison`).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import threading
import time
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

# Minutes each notebook took in the last timed `make reproduce` (docs/reproduction.md's table, its last row:
# one run, --jobs 2, pinned kernels, on the 2-core machine); tests/test_reproduce_one.py keeps the two equal.
TIMED_COMMIT = "d55e43e"
MEASURED_MINUTES = {"00": 0.7, "01": 2.1, "02": 6.6, "03": 65.6, "04": 17.9, "05": 40.7, "06": 9.3, "07": 21.7,
                    "08": 1.8}
CI_MINUTES = 1.0                        # every notebook's ci profile runs in about a minute (README)
ALLOW_DIRTY_ENV = "VPR_NB_ALLOW_DIRTY"  # vpr_nb.results.ALLOW_DIRTY_ENV: results outside the repository may come
                                        # from a working tree with changes (a student's edited notebook)
TIME_KEY = "seconds"                    # a results entry that is a run time, not a result


# ---------------------------------------------------------------------------------------------
# Which notebooks run
# ---------------------------------------------------------------------------------------------
def select_notebook(sources: list[Path], which: str) -> Path:
    """The notebook ``which`` names among ``sources``: its number (``"03"`` or ``"3"``), its stem or its file name."""
    text = str(which).strip()
    stem = text[:-len(".ipynb")] if text.endswith(".ipynb") else text
    if stem.isdigit():
        found = [p for p in sources if p.stem.startswith(f"{int(stem):02d}_")]
    else:
        found = [p for p in sources if p.stem == stem]
    if len(found) != 1:
        numbers = ", ".join(p.stem.split("_", 1)[0] for p in sources)
        raise ValueError(f"no notebook {text!r}: name one by its number ({numbers}), e.g. NOTEBOOK=03")
    return found[0]


def notebooks_to_run(target: Path, sources: list[Path], deps: Mapping[str, set], committed_dir) -> list[Path]:
    """``target`` and, before it, every notebook it reads (``deps``, transitively) whose committed results
    (``committed_dir/<stem>.json``) are missing; in the order of ``sources``."""
    by_stem = {p.stem: p for p in sources}
    needed, todo = {target.stem}, [target.stem]
    while todo:
        for dep in deps.get(todo.pop(), set()):
            if dep not in needed and not (Path(committed_dir) / f"{dep}.json").is_file():
                needed.add(dep)
                todo.append(dep)
    return [p for p in sources if p.stem in needed and p.stem in by_stem]


# ---------------------------------------------------------------------------------------------
# The estimate and the progress line
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Estimate:
    """How long a notebook should take: ``low``–``high`` seconds (None: unknown), and where that comes from."""
    low: float | None
    high: float | None
    source: str

    def text(self) -> str:
        if self.low is None:
            return "no recorded time"
        a, b = _minutes(self.low), _minutes(self.high)
        return f"about {a}" if a == b else f"about {a.removesuffix(' min')}–{b}"


def _minutes(seconds: float) -> str:
    minutes = seconds / 60
    return f"{minutes:.0f} min" if minutes >= 10 else f"{minutes:.1f} min"


def read_results(path) -> dict | None:
    """The JSON object of a results file (``notebooks/results/<stem>.json``), or None when it is missing or unreadable."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


RUN_WORKERS = 2            # a reproduce run's fine-tunes run this many at a time on the 2 cores


def run_seconds(doc) -> float | None:
    """What the experiment of a results document (``{"results": ..., "stamp": ...}``) took on the 2 cores, in
    seconds: its recorded ``seconds``, or, when a run started again after an interruption made it (fine-tunes
    reused from the task store, ``stamp["fine-tunes"]``), its fine-tunes' own times run :data:`RUN_WORKERS` at a
    time, whichever is longer; None when it records no time."""
    res = doc.get("results") if isinstance(doc, Mapping) else None
    seconds = res.get(TIME_KEY) if isinstance(res, Mapping) else None
    if not (isinstance(seconds, (int, float)) and not isinstance(seconds, bool) and math.isfinite(seconds)
            and seconds > 0):
        return None
    stamp = doc.get("stamp") if isinstance(doc.get("stamp"), Mapping) else {}
    tasks = stamp.get("fine-tunes") if isinstance(stamp.get("fine-tunes"), Mapping) else {}
    task_seconds, reused = tasks.get("task seconds"), tasks.get("reused")
    if isinstance(reused, int) and reused > 0 and isinstance(task_seconds, (int, float)) \
            and not isinstance(task_seconds, bool) and math.isfinite(task_seconds):
        return max(float(seconds), float(task_seconds) / RUN_WORKERS)
    return float(seconds)


def _run_seconds(path: Path):
    """``(seconds, "date, commit")`` a committed results file records for its experiment (:func:`run_seconds`),
    or None."""
    doc = read_results(path)
    seconds = run_seconds(doc or {})
    if seconds is None:
        return None
    stamp = doc.get("stamp") if isinstance(doc.get("stamp"), dict) else {}
    where = ", ".join(str(stamp[k]) for k in ("date", "git commit") if stamp.get(k))
    reused = (stamp.get("fine-tunes") or {}).get("reused") if isinstance(stamp.get("fine-tunes"), dict) else None
    if seconds > doc["results"][TIME_KEY]:
        where += f"; {reused} fine-tunes reused, counted at their own times"
    return seconds, where


# a notebook's package experiments, each in its own results file NN_<kind>.json (vpr_nb.onoff), timed apart
EXTRAS = {"premise": "premise experiment", "probes": "probes", "control": "positive control",
          "nearmiss": "near-miss world", "fair_check": "fair design's check", "fair": "fair test",
          "paper": "paper's comparison", "paper_salad": "paper's comparison with SALAD",
          "paper_netvlad": "paper's comparison with NetVLAD-16", "paper_start": "paper's comparison from 05's SALAD"}


def estimate(stem: str, profile: str, committed_dir) -> Estimate:
    """The expected run time of notebook ``stem`` in ``profile``: for ``reproduce``, the run time its committed
    results record (``results.seconds``, the time of its experiment) and its time in the last timed
    ``make reproduce`` (:data:`MEASURED_MINUTES`), as a range, each plus its premise experiment's recorded time
    (``NN_premise.json``, :mod:`vpr_nb.onoff`) and its other package experiments (:data:`EXTRAS`) where it has
    them; for ``ci``,
    about a minute."""
    if profile != "reproduce":
        return Estimate(CI_MINUTES * 60, CI_MINUTES * 60, "the ci budget")
    times, parts = [], []
    extras = {what: _run_seconds(Path(committed_dir) / f"{stem[:2]}_{kind}.json") for kind, what in EXTRAS.items()}
    extras = {what: t for what, t in extras.items() if t}
    extra = sum(t[0] for t in extras.values())
    own = _run_seconds(Path(committed_dir) / f"{stem}.json")
    if own:
        times.append(own[0] + extra)
        parts.append(f"its committed results took {_minutes(own[0])}" + (f" ({own[1]})" if own[1] else ""))
    measured = MEASURED_MINUTES.get(stem[:2])
    if measured is not None:
        times.append(measured * 60 + extra)
        parts.append(f"the last timed make reproduce ({TIMED_COMMIT}): {_minutes(measured * 60)}")
    if times:
        parts += [f"its {what} {_minutes(t[0])}" + (f" ({t[1]})" if t[1] else "") for what, t in extras.items()]
    if not times:
        return Estimate(None, None, "no run of it was timed")
    return Estimate(min(times), max(times), "; ".join(parts))


def full_run_hours(committed_dir) -> float:
    """The expected wall time of a whole ``make reproduce`` on 2 cores, in hours (one decimal): half the sum of
    every notebook's :func:`estimate` (its upper end). The notebook times were measured two notebooks at a time
    on the 2 cores, so a run's wall is about half their sum (the last timed run: 166 min of notebook time in
    89.4 min wall). README states this figure; ``tests/test_reproduce_one.py`` keeps the two equal."""
    def stem(nb: str) -> str:
        own = [p.stem for p in Path(committed_dir).glob(f"{nb}_*.json")
               if not p.stem.endswith(tuple(f"_{kind}" for kind in EXTRAS))]
        return own[0] if own else f"{nb}_"
    total = sum(estimate(stem(nb), "reproduce", committed_dir).high or 0.0 for nb in MEASURED_MINUTES)
    return round(total / 2 / 3600, 1)


def plan_line(stem: str, profile: str, est: Estimate, why: str = "") -> str:
    """The line printed before a notebook starts: what runs, for how long, and why it runs."""
    return (f"[plan] {stem}.ipynb, {profile} profile: {est.text()} on 2 cores ({est.source})"
            + (f"; {why}" if why else ""))


def progress_line(stem: str, elapsed: float, est: Estimate | None) -> str:
    """``[....] 03_x.ipynb: 5.0 min so far of about 62–64 min`` (or past it, or with no estimate)."""
    line = f"[....] {stem}.ipynb: {_minutes(elapsed)} so far"
    if est is None or est.high is None:
        return line
    if elapsed <= est.high:
        return f"{line} of {est.text()}"
    return f"{line}, past the estimate ({est.text()}): a busy or slower machine takes longer"


class Heartbeat:
    """A thread that prints :func:`progress_line` for every running notebook each ``every`` seconds.

    ``with Heartbeat(estimates, 60) as beat:`` ... ``beat.start(stem)`` when a notebook starts, ``beat.stop(stem)``
    when it ends; ``every`` <= 0 prints nothing."""

    def __init__(self, estimates: Mapping[str, Estimate], every: float = 60.0, echo=print, clock=time.monotonic):
        self.estimates, self.every, self.echo, self.clock = dict(estimates), float(every), echo, clock
        self._running: dict[str, float] = {}
        self._lock, self._done = threading.Lock(), threading.Event()
        self._thread = threading.Thread(target=self._beat, name="reproduce-heartbeat", daemon=True)

    def start(self, stem: str) -> None:
        with self._lock:
            self._running[stem] = self.clock()

    def stop(self, stem: str) -> None:
        with self._lock:
            self._running.pop(stem, None)

    def lines(self) -> list[str]:
        now = self.clock()
        with self._lock:
            running = sorted(self._running.items())
        return [progress_line(stem, now - t0, self.estimates.get(stem)) for stem, t0 in running]

    def _beat(self) -> None:
        while not self._done.wait(self.every):
            for line in self.lines():
                self.echo(line, flush=True)

    def __enter__(self):
        if self.every > 0:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._done.set()
        if self._thread.is_alive():
            self._thread.join()
        return False


# ---------------------------------------------------------------------------------------------
# Where the results go
# ---------------------------------------------------------------------------------------------
def _owner(path: Path) -> str:
    return path.name.split(".", 1)[0]      # 04_netvlad.json, 04_netvlad.netvlad-seed0.pt -> 04_netvlad


def prepare_results_dir(results_dir, committed_dir, run_stems) -> list[Path]:
    """Make ``results_dir`` ready for a run of ``run_stems``: their earlier files there are removed, and the
    committed results of every other notebook are copied in (a notebook may read another's). Returns the copies."""
    results_dir, committed_dir, run_stems = Path(results_dir), Path(committed_dir), set(run_stems)
    if results_dir.resolve() == committed_dir.resolve():
        raise ValueError(f"{results_dir} is the committed results folder; a student's run writes elsewhere")
    results_dir.mkdir(parents=True, exist_ok=True)
    for old in results_dir.iterdir():
        if old.is_file() and _owner(old) in run_stems:
            old.unlink()
    copies = []
    for src in sorted(committed_dir.glob("[0-9][0-9]_*")):
        if src.is_file() and _owner(src) not in run_stems and not src.name.endswith(".tmp"):
            copies.append(Path(shutil.copy2(src, results_dir / src.name)))
    return copies


def shown_path(path) -> str:
    """``path`` as a student reads it: relative to the working folder when it lies inside it."""
    path = Path(path).resolve()
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


@contextmanager
def environment(values: Mapping[str, str]):
    """Set the environment variables ``values`` for the duration (the notebooks' kernels inherit them)."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# ---------------------------------------------------------------------------------------------
# This run's numbers beside the committed ones
# ---------------------------------------------------------------------------------------------
def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def flatten_numbers(results, prefix: str = "") -> dict[str, tuple[float, int]]:
    """{``"rows / T-Loss / R@1"``: (value, n)} for every number of a results dict: a list of numbers (one per
    seed) gives its mean and length, a single number itself and 1. Strings (file names, hashes) are left out."""
    out: dict[str, tuple[float, int]] = {}
    if isinstance(results, Mapping):
        for k, v in results.items():
            out.update(flatten_numbers(v, f"{prefix} / {k}" if prefix else str(k)))
    elif _is_number(results):
        out[prefix] = (float(results), 1)
    elif isinstance(results, list) and results and all(_is_number(x) for x in results):
        out[prefix] = (sum(results) / len(results), len(results))
    return out


def compare_results(committed: Mapping | None, new: Mapping | None) -> list[dict]:
    """One row per number of either results dict (the ``results`` entry of a results file), committed order
    first: ``{"name", "committed", "new", "difference"}``, each value ``(value, n)`` or None, the difference
    ``new − committed`` of the values (means for lists) or None when one is missing."""
    a, b = flatten_numbers(committed or {}), flatten_numbers(new or {})
    rows = []
    for name in [*a, *(k for k in b if k not in a)]:
        old, cur = a.get(name), b.get(name)
        rows.append({"name": name, "committed": old, "new": cur,
                     "difference": None if old is None or cur is None else cur[0] - old[0]})
    return rows


def _number(x: float, sign: str = "", size: float | None = None) -> str:
    """4 decimals (a recall, a cosine), 1 when ``size`` (default ``x``) is 10 or more (seconds), none for a whole
    number."""
    if float(x).is_integer():
        return f"{int(x):{sign}d}"
    return f"{x:{sign}.1f}" if abs(x if size is None else size) >= 10 else f"{x:{sign}.4f}"


def _cell(value) -> str:
    if value is None:
        return "—"
    x, n = value
    return _number(x) if n == 1 else f"{_number(x)} (mean of {n})"


def _difference(row: Mapping) -> str:
    d = row["difference"]
    if d is None:
        return "—"
    return "same" if abs(d) < 5e-5 else _number(d, "+", max(abs(row["committed"][0]), abs(row["new"][0])))


def _stamp(doc: Mapping | None) -> str:
    stamp = (doc or {}).get("stamp") if isinstance((doc or {}).get("stamp"), Mapping) else {}
    return ", ".join(str(stamp[k]) for k in ("date", "git commit", "torch", "cpu") if stamp.get(k)) or "no stamp"


def render_comparison(stem: str, committed_doc: Mapping | None, new_doc: Mapping | None,
                      committed_where: str = "notebooks/results", new_where: str = "this run") -> str:
    """This run's numbers beside the committed ones, as Markdown: a header naming both files, a table
    ``| number | committed | this run | difference |`` and a one-line summary; or a sentence saying why there is
    nothing to compare."""
    lines = [f"## {stem}: this run beside the committed results", ""]
    if committed_doc is None:
        lines.append(f"There are no committed results for {stem} ({committed_where}/{stem}.json): nothing to "
                     f"compare with. Its numbers are in the report (results.md).")
        return "\n".join(lines) + "\n"
    if new_doc is None:
        lines.append(f"This run wrote no {stem}.json: only the reproduce profile saves results (PROFILE=reproduce), "
                     f"and a notebook that fails saves none. The report (results.md) has what it recorded.")
        return "\n".join(lines) + "\n"
    rows = compare_results(committed_doc.get("results"), new_doc.get("results"))
    lines += [f"- committed: {committed_where}/{stem}.json ({_stamp(committed_doc)})",
              f"- this run: {new_where} ({_stamp(new_doc)})", "",
              "| number | committed | this run | difference |", "|---|---|---|---|"]
    lines += [f"| {r['name'].replace('|', '/')} | {_cell(r['committed'])} | {_cell(r['new'])} | "
              f"{_difference(r)} |" for r in rows]
    results = [r for r in rows if r["name"].rsplit(" / ", 1)[-1] != TIME_KEY]
    differ = [r for r in results if r["difference"] is None or abs(r["difference"]) >= 5e-5]
    summary = (f"{len(results)} number{'' if len(results) == 1 else 's'} (run times left out): "
               f"{len(results) - len(differ)} the same")
    if differ:
        worst = max((r for r in differ if r["difference"] is not None), key=lambda r: abs(r["difference"]),
                    default=None)
        summary += f", {len(differ)} different" + (
            f"; the largest difference: {worst['name']} ({worst['difference']:+.4f})" if worst else "")
    lines += ["", summary + "."]
    return "\n".join(lines) + "\n"
