"""Results report: notebooks ``record`` their headline numbers; ``make reproduce`` gathers them.

Inside a notebook, ``record("03_dw_triplet", {"T-Loss R@1": 0.71, ...})`` is a no-op unless the
environment variable ``VPR_NB_RESULTS`` names a JSON-lines file, which the report runner
(``python -m vpr_nb.report``) sets while it executes the notebook sequence with papermill.

The runner::

    python -m vpr_nb.report --profile {ci,reproduce} --out reports [--notebooks PATTERN]

executes every ``notebooks/[0-9][0-9]_*.ipynb`` in order with ``PROFILE`` injected into the cell
tagged ``parameters``, and writes under ``--out``:

- ``notebooks/``  the executed copies (also of a notebook that failed, up to the failing cell);
- ``figures/``    every PNG output, named ``<notebook>_<cell>_<k>.png``;
- ``results.md``  a header (date, profile, commit, versions, cores), then per notebook its status,
  wall time and the recorded results as Markdown tables; ``results.json`` holds the same data.

A failing notebook is reported and the next one runs; the exit status is 1 if any failed.

``--notebook 03`` (``make reproduce NOTEBOOK=03``) runs that notebook alone (:func:`run_notebook_alone`), writes
its results to ``OUT/results/`` instead of ``notebooks/results/`` and shows them beside the committed ones
(``OUT/comparison.md``); :mod:`vpr_nb.reproduce_one` holds that run's parts.
"""
from __future__ import annotations

import argparse
import base64
import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import quote

from . import reproduce_one as one
from . import run_attempts, schedule
from .engine import DASK_ENV, TIMES_ENV, WORKERS_ENV, LocalEngine
from .kernels import cpu_description, pin_this_process
from .package_data import RESULTS_DIR_ENV, committed_results_dir
from .report_markdown import NON_FINITE, _table, escape_markdown, format_value, render_table  # noqa: F401 - re-exported
from .task_store import STORE_ENV

RESULTS_ENV = "VPR_NB_RESULTS"
PROFILES = ("ci", "reproduce")
DEFAULT_PATTERN = "[0-9][0-9]_*.ipynb"
INLINE_BACKEND = "module://matplotlib_inline.backend_inline"


def jsonable(value):
    """Numbers, strings, lists and dicts of them (numpy scalars/arrays are converted)."""
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"record() stores numbers, strings, lists and dicts; got {type(value).__name__}")


def record(notebook: str, results: Mapping) -> None:
    """Append ``results`` (a flat or nested dict of numbers/strings) under the key ``notebook``.

    Does nothing (and prints nothing) when ``VPR_NB_RESULTS`` is unset, so notebooks can call it
    unconditionally and stay identical under nbval.
    """
    if not isinstance(notebook, str) or not notebook:
        raise ValueError("record() needs a non-empty notebook key such as '01_retrieval_and_recall'")
    if not isinstance(results, Mapping) or not results:
        raise ValueError("record() needs a non-empty dict of results, e.g. {'R@1': 0.71}")
    payload = {"notebook": notebook, "results": jsonable(results)}
    path = os.environ.get(RESULTS_ENV)
    if not path:
        return
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(payload) + "\n")


# ---------------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------------
def extract_figures(nb: Mapping, stem: str, out_dir) -> list[Path]:
    """Write every ``image/png`` output of notebook ``nb`` to ``out_dir/<stem>_<cell>_<k>.png``.

    ``nb`` is a notebook as a dict (nbformat v4 or a plain ``json.load``); ``cell`` is the cell's
    index in the notebook (2 digits), ``k`` counts the PNGs within that cell. Returns the paths.
    """
    if not isinstance(nb, Mapping) or "cells" not in nb:
        raise ValueError("extract_figures() needs a notebook dict with a 'cells' list (nbformat v4)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for c, cell in enumerate(nb["cells"]):
        k = 0
        for output in cell.get("outputs", []):
            png = output.get("data", {}).get("image/png")
            if not png:
                continue
            if isinstance(png, list):  # nbformat allows multi-line strings as lists
                png = "".join(png)
            path = out_dir / f"{stem}_{c:02d}_{k}.png"
            path.write_bytes(base64.b64decode(png))
            paths.append(path)
            k += 1
    return paths


# ---------------------------------------------------------------------------------------------
# Runner
# ---------------------------------------------------------------------------------------------
RESULTS_PATHS = "notebooks/results"   # what a reproduce run writes: not a change to the code it ran


def uncommitted_changes() -> list[str]:
    """Tracked files that differ from HEAD, except the committed results a reproduce run rewrites
    (``notebooks/results/``), so a run of the whole sequence stays clean after its first notebook.
    Raises OSError / CalledProcessError outside a git checkout."""
    out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                         capture_output=True, text=True, check=True).stdout
    paths = [line[3:].strip() for line in out.splitlines() if line.strip()]
    return [p for p in paths if not p.startswith(RESULTS_PATHS + "/")]


def environment_header(profile: str) -> dict:
    """Date, profile, git commit (if available), library versions and core count."""
    head = {"date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "profile": profile}
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=True).stdout.strip()
        head["git commit"] = commit + (" (with uncommitted changes)" if uncommitted_changes() else "")
    except (OSError, subprocess.CalledProcessError):
        head["git commit"] = "unavailable"
    head["python"] = platform.python_version()
    for mod in ("torch", "faiss", "numpy"):
        try:
            head[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - a missing library is reported, not fatal
            head[mod] = "not importable"
    head["machine"] = f"{platform.machine()}, {os.cpu_count()} cores ({platform.system()})"
    head["cpu"] = cpu_description()
    return head


def find_notebooks(notebooks_dir, pattern: str = DEFAULT_PATTERN) -> list[Path]:
    """Notebooks in ``notebooks_dir`` matching ``pattern``, sorted by name (00, 01, ...).

    ``pattern`` is a glob relative to ``notebooks_dir`` (``**`` recurses), or an absolute glob
    (e.g. ``/repo/notebooks/0[01]_*.ipynb``). Jupyter's autosave copies under
    ``.ipynb_checkpoints/`` are never run.
    """
    import glob as _glob

    notebooks_dir = Path(notebooks_dir)
    if not notebooks_dir.is_dir():
        raise FileNotFoundError(f"notebook folder {notebooks_dir} does not exist; run from the repository root")
    if not isinstance(pattern, str) or not pattern:
        raise ValueError(f"pattern must be a non-empty glob string, got {pattern!r}")
    if Path(pattern).is_absolute():
        hits = (Path(p) for p in _glob.glob(pattern, recursive=True))
    else:
        hits = notebooks_dir.glob(pattern)
    found = sorted((p for p in hits if p.suffix == ".ipynb" and p.is_file()
                    and ".ipynb_checkpoints" not in p.parts), key=lambda p: (p.name, str(p)))
    if not found:
        raise FileNotFoundError(f"no notebook in {notebooks_dir} matches {pattern!r}; "
                                f"try the default {DEFAULT_PATTERN!r}")
    return found


def _read_records(path: Path, start: int) -> tuple[dict, int]:
    """Merge the records appended to ``path`` after line ``start``: ``{key: results}``."""
    if not path.exists():
        return {}, start
    lines = path.read_text(encoding="utf-8").splitlines()
    merged: dict = {}
    for line in lines[start:]:
        entry = json.loads(line)
        merged.setdefault(entry["notebook"], {}).update(entry["results"])
    return merged, len(lines)


def run_notebook(src: Path, out_path: Path, profile: str, results_file: Path) -> dict:
    """Execute one notebook with papermill; return ``{status, error, seconds}`` (never raises on a cell error)."""
    import papermill

    start = time.perf_counter()
    status, error = "ok", ""
    # figures as PNG outputs even if the shell set Agg
    with one.environment({RESULTS_ENV: str(results_file.resolve()), "MPLBACKEND": INLINE_BACKEND}):
        try:
            papermill.execute_notebook(str(src), str(out_path), parameters={"PROFILE": profile},
                                       cwd=str(src.parent), kernel_name="python3", progress_bar=False)
        except Exception as exc:  # noqa: BLE001 - report any failure and go on with the next notebook
            status = "failed"
            if hasattr(exc, "ename"):
                error = f"{exc.ename}: {exc.evalue} (cell {getattr(exc, 'cell_index', '?')})"
            else:
                error = f"{type(exc).__name__}: {exc}"
    return {"status": status, "error": error, "seconds": round(time.perf_counter() - start, 1)}


def render_markdown(header: Mapping, notebooks: list[dict]) -> str:
    """The whole ``results.md``: every name, key, error and recorded string escaped (:func:`escape_markdown`),
    so that the only links and images in it are the report's own figures (``figures/...png``)."""
    lines = ["# vpr-notebooks results report", "", render_table(dict(header)), "", "## Summary", ""]
    lines.append(_table(["notebook", "status", "wall time (s)"],
                        [[escape_markdown(nb["name"]), escape_markdown(nb["status"]), f"{nb['seconds']:.1f}"]
                         for nb in notebooks]))
    for nb in notebooks:
        name = escape_markdown(nb["name"])
        lines += ["", f"## {name}", "", f"- status: **{escape_markdown(nb['status'])}**"]
        if nb["error"]:
            lines.append(f"- error: {escape_markdown(nb['error'])}")
        lines.append(f"- wall time: {nb['seconds']:.1f} s")
        lines.append(f"- executed copy: notebooks/{name}.ipynb, figures: {len(nb['figures'])}")
        if not nb["results"]:
            lines += ["", "_No results recorded._"]
        for key, results in nb["results"].items():
            if len(nb["results"]) > 1 or key != nb["name"]:
                lines += ["", f"### {escape_markdown(key)}"]
            lines += ["", render_table(results)]
        if nb["figures"]:       # relative paths the runner wrote (figures/<stem>_<cell>_<k>.png), percent-encoded
            lines += [""] + [f"![{escape_markdown(Path(f).stem)}]({quote(Path(f).as_posix())})" for f in nb["figures"]]
    return "\n".join(lines) + "\n"


def notebook_dependencies(sources: list[Path]) -> dict[str, set[str]]:
    """{stem: stems of the other notebooks of the run it reads}: a notebook depends on another when its code
    names the other's stem (e.g. ``committed_experiment("04_netvlad")``, whose committed results it shows),
    so in a parallel run it starts only after that one has finished (and rewritten its results)."""
    stems = [p.stem for p in sources]
    deps = {}
    for src in sources:
        cells = json.loads(src.read_text(encoding="utf-8")).get("cells", [])
        code = "\n".join("".join(c.get("source", "")) for c in cells if c.get("cell_type") == "code")
        deps[src.stem] = {o for o in stems if o != src.stem and (f'"{o}"' in code or f"'{o}'" in code)}
    return deps


def task_summary(out, entries: list[dict], wall: float, cpu: float, cores: int) -> dict:
    """The run's tasks, idle share and simulated scaling (:func:`vpr_nb.schedule.run_summary`) from what the run
    in ``out`` left: each notebook's logged rounds (``records/<stem>.tasks.jsonl``) and, for which notebook waits
    for which, the executed copies in ``notebooks/`` (:func:`notebook_dependencies`)."""
    out = Path(out)
    copies = [out / "notebooks" / f"{e['name']}.ipynb" for e in entries]
    deps = notebook_dependencies([p for p in copies if p.is_file()])
    rounds = {e["name"]: schedule.read_rounds(out / "records" / f"{e['name']}.tasks.jsonl") for e in entries}
    return schedule.run_summary(entries, rounds, wall, cpu, cores, after=deps)


def _run_one(src: Path, out: Path, profile: str) -> dict:
    """Execute one notebook of the run (in a worker process when ``jobs`` > 1); its records go to a file
    of its own, so parallel notebooks never write one file."""
    out_nb = out / "notebooks" / src.name
    records = out / "records" / f"{src.stem}.jsonl"
    records.write_text("", encoding="utf-8")
    started = time.time()
    with one.environment({TIMES_ENV: str((out / "records" / f"{src.stem}.tasks.jsonl").resolve())}):
        entry = {"name": src.stem, "started": round(started, 3), **run_notebook(src, out_nb, profile, records)}
    entry["results"], _ = _read_records(records, 0)
    figures = extract_figures(json.loads(out_nb.read_text(encoding="utf-8")), src.stem, out / "figures") \
        if out_nb.exists() else []
    entry["figures"] = [str(p.relative_to(out)) for p in figures]
    return entry


def run_report(profile: str, out="reports", notebooks_dir="notebooks", pattern: str = DEFAULT_PATTERN,
               jobs: int = 1, *, sources: list[Path] | None = None, heartbeat: one.Heartbeat | None = None,
               store=None) -> dict:
    """Run the notebook sequence and write the report; returns the ``results.json`` payload.

    ``jobs`` > 1 runs that many notebooks at once (each kernel uses one torch thread), a notebook starting
    only after the notebooks it reads (:func:`notebook_dependencies`); the report lists them in order.
    ``sources`` runs those notebooks instead of ``pattern``'s; ``heartbeat`` is told when each starts and ends.
    ``store``: the task store the kernels reuse finished fine-tunes from (:mod:`vpr_nb.task_store`; None: off), so
    a run started again after an interruption trains only what is missing. Every round of tasks is logged, and
    ``results.json`` / ``results.md`` give the idle share and the simulated scaling (:mod:`vpr_nb.schedule`)."""
    import resource
    from concurrent.futures import FIRST_COMPLETED, wait

    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; choose one of {PROFILES} "
                         f"('ci' is small and quick, 'reproduce' the full report)")
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
        raise ValueError(f"jobs must be a whole number >= 1 (notebooks run at once), got {jobs!r}")
    sources = list(sources) if sources is not None else find_notebooks(notebooks_dir, pattern)
    deps = notebook_dependencies(sources)
    pin_this_process()      # every kernel (and its workers) computes with the same kernels on any x86-64 machine
    out = Path(out)
    for sub in ("notebooks", "figures", "records"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    header = environment_header(profile)
    os.environ[STORE_ENV] = str(Path(store).resolve()) if store else "off"     # the kernels inherit it
    start, cpu0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    attempt = run_attempts.Attempt(out / "attempts.jsonl")
    earlier = attempt.begin(commit=header.get("git commit"), profile=profile, notebooks=[p.name for p in sources],
                            store=os.environ[STORE_ENV] if store else None)
    resumed = run_attempts.finished_notebooks(earlier, header.get("git commit"))
    # a run over a subset of the notebooks must not leave copies and figures of an earlier run beside it; a run
    # started again keeps those of the notebooks an earlier attempt of it finished (from the same commit)
    for old in [*(out / "notebooks").glob("*.ipynb"), *(out / "figures").glob("*.png"), *(out / "records").glob("*"),
                out / "results.json", out / "results.md", out / "results.jsonl", out / "comparison.md"]:
        if not any(old.parent.parent == out and (old.name.startswith(f"{n}.") or old.name.startswith(f"{n}_"))
                   for n in resumed):
            old.unlink(missing_ok=True)
    if earlier:
        print(f"[....] attempt {len(earlier) + 1} of this run: {len(earlier)} earlier attempt(s) stopped after "
              f"{sum(a['last'] - a['start'] for a in earlier) / 60:.1f} min; finished fine-tunes are reused"
              + (f", and the notebooks they finished: {', '.join(sorted(resumed))}" if resumed else ""),
              flush=True)
    done: dict[str, dict] = dict(resumed)

    def started(src):
        print(f"[run ] {src.name} (profile {profile})", flush=True)
        if heartbeat is not None:
            heartbeat.start(src.stem)

    def report(entry):
        if heartbeat is not None:
            heartbeat.stop(entry["name"])
        print(f"[{entry['status']:>4}] {entry['name']}.ipynb {entry['seconds']:.1f} s"
              + (f"  {entry['error']}" if entry["error"] else ""), flush=True)
        done[entry["name"]] = entry
        attempt.notebook_done(entry)

    pending, running = [p for p in sources if p.stem not in resumed], {}
    with LocalEngine(jobs).executor() as pool:    # jobs = 1: each notebook runs here, one after another
        while pending or running:
            ready = [p for p in pending if deps[p.stem] <= set(done)] or pending[:not running]   # a cycle: in order
            for src in ready[:jobs - len(running)]:
                pending.remove(src)
                started(src)
                running[pool.submit(_run_one, src, out, profile)] = src
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                del running[fut]
                report(fut.result())
    entries = [done[p.stem] for p in sources]
    wall = time.perf_counter() - start
    attempt.end()
    attempts = run_attempts.summary(run_attempts.read(out / "attempts.jsonl"))
    print(f"[done] {len(entries)} notebooks in {wall / 60:.1f} min wall ({profile} profile, {jobs} at once; "
          f"{sum(e['seconds'] for e in entries) / 60:.1f} min of notebook time)", flush=True)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    tasks = task_summary(out, entries, wall, cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime,
                         os.cpu_count() or 1)
    payload = {"header": header, "notebooks": entries, "wall_seconds": round(wall, 1), "jobs": jobs, "tasks": tasks,
               "attempts": attempts}
    (out / "results.json").write_text(json.dumps(payload, indent=1) + "\n", encoding="utf-8")
    (out / "results.md").write_text(render_markdown(header, entries) + "\n".join(schedule.summary_markdown(tasks))
                                    + "\n" + "\n".join(run_attempts.summary_markdown(attempts)) + "\n",
                                    encoding="utf-8")
    return payload


def run_notebook_alone(which: str, profile: str = "reproduce", out="reports", notebooks_dir="notebooks",
                       jobs: int = 1, *, into_committed: bool = False, committed_dir=None,
                       progress_every: float = 60.0, store=None) -> dict:
    """Run notebook ``which`` (``"03"``) alone, after the notebooks it reads whose committed results are missing:
    print an estimate first and a progress line every ``progress_every`` seconds, then its numbers beside the
    committed ones (also written to ``OUT/comparison.md``). Its results go to ``OUT/results/`` (which holds copies
    of the other notebooks' committed results), or, with ``into_committed``, into the committed folder."""
    sources = find_notebooks(notebooks_dir)
    target = one.select_notebook(sources, which)
    committed = Path(committed_dir) if committed_dir is not None else committed_results_dir()
    run = one.notebooks_to_run(target, sources, notebook_dependencies(sources), committed)
    committed_file = committed / f"{target.stem}.json"
    before = one.read_results(committed_file)
    before_mtime = committed_file.stat().st_mtime_ns if committed_file.is_file() else None
    results_dir = committed if into_committed else Path(out) / "results"
    estimates = {p.stem: one.estimate(p.stem, profile, committed) for p in run}
    for p in run:
        why = "" if p == target else f"{target.stem} reads its results and {one.shown_path(committed)} has none"
        print(one.plan_line(p.stem, profile, estimates[p.stem], why), flush=True)
    print(f"[plan] results go to {one.shown_path(results_dir)}/" + ("" if into_committed else
          f" ({one.shown_path(committed)}/ is not touched); then this run's numbers beside the committed ones"),
          flush=True)
    env = {}
    if not into_committed:
        one.prepare_results_dir(results_dir, committed, [p.stem for p in run])
        env = {RESULTS_DIR_ENV: str(results_dir.resolve()), one.ALLOW_DIRTY_ENV: "1"}
    with one.environment(env), one.Heartbeat(estimates, progress_every) as beat:
        payload = run_report(profile, out, notebooks_dir, jobs=jobs, sources=run, heartbeat=beat, store=store)
    new_file = results_dir / f"{target.stem}.json"
    rewritten = new_file.is_file() and (not into_committed or new_file.stat().st_mtime_ns != before_mtime)
    text = one.render_comparison(target.stem, before, one.read_results(new_file) if rewritten else None,
                                 one.shown_path(committed), one.shown_path(new_file))
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "comparison.md").write_text(text, encoding="utf-8")
    print("\n" + text + f"\n(also in {Path(out) / 'comparison.md'})", flush=True)
    return payload


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", required=True, choices=PROFILES, help="budget profile injected as PROFILE")
    parser.add_argument("--out", default="reports", help="output folder (default: reports)")
    parser.add_argument("--notebooks", default=DEFAULT_PATTERN, metavar="PATTERN",
                        help=f"glob of notebooks to run (default: {DEFAULT_PATTERN!r})")
    parser.add_argument("--notebooks-dir", default="notebooks", help="folder holding the notebooks")
    parser.add_argument("--jobs", type=int, default=1, help="notebooks run at once (default 1; a notebook waits "
                        "for those whose results it reads)")
    parser.add_argument("--notebook", metavar="NN", help="run only notebook NN (e.g. 03), after the notebooks it "
                        "reads whose committed results are missing; its results go to OUT/results/ and are shown "
                        "beside the committed ones")
    parser.add_argument("--into-committed", action="store_true", help="with --notebook: write its results into "
                        "notebooks/results/ (the committed results), as a run of every notebook does")
    parser.add_argument("--store", default=None, metavar="DIR", help="task store: finished fine-tunes are reused "
                        "from it, so a run started again trains only what is missing (default: OUT/task-store; "
                        "'off': none)")
    parser.add_argument("--dask", default=None, metavar="ADDRESS", help="run the fine-tunes on the Dask scheduler "
                        "at ADDRESS (docs/reproduction.md); default: local processes")
    parser.add_argument("--workers", type=int, default=None, help="local processes per notebook for its fine-tunes")
    parser.add_argument("--progress-every", type=float, default=60.0, metavar="SECONDS",
                        help="with --notebook: a progress line this often (default 60; 0 for none)")
    args = parser.parse_args(argv)
    if args.notebook is None and args.into_committed:
        parser.error("--into-committed goes with --notebook NN")
    if args.notebook is not None and args.notebooks != DEFAULT_PATTERN:
        parser.error("give --notebook NN or --notebooks PATTERN, not both")
    store = None if (args.store or "").lower() == "off" else (args.store or str(Path(args.out) / "task-store"))
    env = {k: str(v) for k, v in ((DASK_ENV, args.dask), (WORKERS_ENV, args.workers)) if v is not None}
    try:
        if args.workers is not None and args.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {args.workers}")
        with one.environment(env):
            payload = _run(args, store)
    except (ValueError, FileNotFoundError) as exc:
        parser.error(str(exc))  # exits with status 2 and the message
    failed = [nb["name"] for nb in payload["notebooks"] if nb["status"] != "ok"]
    print(f"report: {Path(args.out) / 'results.md'}"
          + (f"; FAILED: {', '.join(failed)}" if failed else "; all notebooks ok"))
    return 1 if failed else 0


def _run(args, store) -> dict:
    if args.notebook is not None:
        return run_notebook_alone(args.notebook, args.profile, args.out, args.notebooks_dir, args.jobs,
                                  into_committed=args.into_committed, progress_every=args.progress_every,
                                  store=store)
    return run_report(args.profile, args.out, args.notebooks_dir, args.notebooks, jobs=args.jobs, store=store)


if __name__ == "__main__":
    sys.exit(main())
