"""``make reproduce NOTEBOOK=03``: one notebook's reproduce profile alone, its estimate and progress lines, its
results written beside (never over) the committed ones and compared with them (vpr_nb.reproduce_one and
vpr_nb.report.run_notebook_alone). No real notebook runs here: the runner is replaced by a fake that writes
what a notebook's reproduce profile would."""
from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path

import pytest

from vpr_nb import report
from vpr_nb import reproduce_one as one
from vpr_nb.package_data import RESULTS_DIR_ENV

ROOT = Path(__file__).resolve().parents[1]
STEMS = ["00_world", "02_base", "03_loss", "04_netvlad", "05_salad"]


def _sources(folder: Path, stems=STEMS) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for stem in stems:
        path = folder / f"{stem}.ipynb"
        path.write_text(json.dumps({"cells": [], "metadata": {}, "nbformat": 4, "nbformat_minor": 5}))
        paths.append(path)
    return paths


def _results_file(path: Path, results: dict, commit: str = "abc1234", date: str = "2026-12-05") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"notebook": path.stem, "stamp": {"date": date, "git commit": commit,
                                                                "torch": "2.13.0+cpu"},
                                "config": {}, "course_backbone": "x", "results": results}))
    return path


# --- which notebooks run --------------------------------------------------------------------------------------

@pytest.mark.parametrize("which", ["03", "3", "03_loss", "03_loss.ipynb", " 03 "])
def test_a_notebook_is_named_by_its_number_or_its_name(tmp_path, which):
    assert one.select_notebook(_sources(tmp_path), which).name == "03_loss.ipynb"


@pytest.mark.parametrize("which", ["09", "loss", "", "03_los"])
def test_an_unknown_notebook_is_refused_with_the_choices(tmp_path, which):
    with pytest.raises(ValueError, match=r"no notebook .*\(00, 02, 03, 04, 05\)"):
        one.select_notebook(_sources(tmp_path), which)


def test_the_notebooks_it_reads_run_first_only_when_their_committed_results_are_missing(tmp_path):
    sources = _sources(tmp_path / "nbs")
    deps = {"00_world": set(), "02_base": set(), "03_loss": {"02_base"}, "04_netvlad": set(),
            "05_salad": {"04_netvlad"}}
    committed = tmp_path / "committed"
    committed.mkdir()
    names = lambda run: [p.stem for p in run]                                   # noqa: E731
    assert names(one.notebooks_to_run(sources[4], sources, deps, committed)) == ["04_netvlad", "05_salad"]
    _results_file(committed / "04_netvlad.json", {"R@1": 0.5})
    assert names(one.notebooks_to_run(sources[4], sources, deps, committed)) == ["05_salad"]
    # transitively: 05 reads 04 (missing), which reads 02 (missing)
    (committed / "04_netvlad.json").unlink()
    deps["04_netvlad"] = {"02_base"}
    assert names(one.notebooks_to_run(sources[4], sources, deps, committed)) == ["02_base", "04_netvlad", "05_salad"]


def test_the_real_notebooks_and_their_dependencies():
    """Every notebook 02-07 can be named, and with the committed results present it runs alone."""
    sources = report.find_notebooks(ROOT / "notebooks")
    deps = report.notebook_dependencies(sources)
    for nn in ("02", "03", "04", "05", "06", "07"):
        target = one.select_notebook(sources, nn)
        assert target.stem.startswith(nn + "_")
        assert one.notebooks_to_run(target, sources, deps, ROOT / "notebooks" / "results") == [target]


# --- the estimate and the progress line -----------------------------------------------------------------------

def test_the_estimate_comes_from_the_committed_run_and_the_last_timed_run(tmp_path):
    _results_file(tmp_path / "03_loss.json", {"rows": {}, "seconds": 3694.9}, commit="a464538")
    est = one.estimate("03_loss", "reproduce", tmp_path)
    assert (est.low, est.high) == (3694.9, one.MEASURED_MINUTES["03"] * 60)
    assert est.text() == "about 62–66 min"
    assert "its committed results took 62 min (2026-12-05, a464538)" in est.source
    assert f"the last timed make reproduce ({one.TIMED_COMMIT}): 66 min" in est.source
    line = one.plan_line("03_loss", "reproduce", est)
    assert line.startswith("[plan] 03_loss.ipynb, reproduce profile: about 62–66 min on 2 cores (its committed")


def test_the_estimate_adds_the_premise_experiment(tmp_path):
    _results_file(tmp_path / "03_loss.json", {"rows": {}, "seconds": 3694.9}, commit="a464538")
    _results_file(tmp_path / "03_premise.json", {"premise": {}, "seconds": 1200.0}, commit="b123456")
    est = one.estimate("03_loss", "reproduce", tmp_path)
    assert (est.low, est.high) == (3694.9 + 1200.0, one.MEASURED_MINUTES["03"] * 60 + 1200.0)
    assert "its premise experiment 20 min (2026-12-05, b123456)" in est.source
    _results_file(tmp_path / "03_probes.json", {"arms": {}, "seconds": 600.0}, commit="c123456")
    est = one.estimate("03_loss", "reproduce", tmp_path)
    assert (est.low, est.high) == (3694.9 + 1800.0, one.MEASURED_MINUTES["03"] * 60 + 1800.0)
    assert "its probes 10 min (2026-12-05, c123456)" in est.source


def test_the_estimate_of_a_run_started_again_counts_its_reused_fine_tunes_at_their_own_times(tmp_path):
    path = _results_file(tmp_path / "03_loss.json", {"rows": {}, "seconds": 120.0}, commit="a464538")
    doc = json.loads(path.read_text())
    doc["stamp"]["fine-tunes"] = {"run": 40, "reused": 30, "task seconds": 6000.0}
    path.write_text(json.dumps(doc))
    est = one.estimate("03_loss", "reproduce", tmp_path)
    assert est.low == 6000.0 / one.RUN_WORKERS                    # not the 2 min the restarted run took
    assert "30 fine-tunes reused, counted at their own times" in est.source
    doc["stamp"]["fine-tunes"] = {"run": 40, "reused": 0, "task seconds": 6000.0}
    path.write_text(json.dumps(doc))
    assert one.estimate("03_loss", "reproduce", tmp_path).low == 120.0   # nothing reused: its own seconds


def test_the_estimate_without_committed_results_or_without_any_timing(tmp_path):
    est = one.estimate("02_base", "reproduce", tmp_path)                        # 02 keeps no committed results
    assert est.low == est.high == one.MEASURED_MINUTES["02"] * 60 and est.text() == "about 6.6 min"
    (tmp_path / "07_x.json").write_text("{not json")                             # unreadable: the table only
    assert one.estimate("07_x", "reproduce", tmp_path).text() == "about 22 min"
    unknown = one.estimate("42_new", "reproduce", tmp_path)
    assert unknown.low is None and unknown.text() == "no recorded time"
    assert one.progress_line("42_new", 90, unknown) == "[....] 42_new.ipynb: 1.5 min so far"
    assert one.estimate("03_loss", "ci", tmp_path).text() == "about 1.0 min"


def test_progress_lines():
    est = one.Estimate(600.0, 720.0, "x")
    assert one.progress_line("03_loss", 300, est) == "[....] 03_loss.ipynb: 5.0 min so far of about 10–12 min"
    assert one.progress_line("03_loss", 800, est).startswith("[....] 03_loss.ipynb: 13 min so far, past the estimate")


def test_the_heartbeat_prints_every_running_notebook_until_it_stops():
    now, printed = [100.0], []
    beat = one.Heartbeat({"03_loss": one.Estimate(600.0, 600.0, "x")}, every=0.01,
                         echo=lambda line, flush: printed.append(line), clock=lambda: now[0])
    with beat:
        beat.start("03_loss")
        now[0] += 120
        assert beat.lines() == ["[....] 03_loss.ipynb: 2.0 min so far of about 10 min"]
        for _ in range(500):                                                     # the thread prints within 5 s
            if printed:
                break
            time.sleep(0.01)
        beat.stop("03_loss")
        assert beat.lines() == []
    assert printed and printed[0] == "[....] 03_loss.ipynb: 2.0 min so far of about 10 min"
    assert not beat._thread.is_alive()
    with one.Heartbeat({}, every=0) as quiet:                                    # 0: no thread, no line
        assert not quiet._thread.is_alive()


def test_the_measured_minutes_are_the_last_row_of_the_timed_runs_in_the_docs():
    text = (ROOT / "docs" / "reproduction.md").read_text(encoding="utf-8")
    header = next(line for line in text.splitlines() if line.startswith("| commit | wall |"))
    rows = [line for line in text.splitlines() if re.match(r"\| [0-9a-f]{7} \| \*\*", line)]
    cells = [c.strip() for c in rows[-1].strip("|").split("|")]
    columns = [c.strip().split()[0] for c in header.strip("|").split("|")][3:]
    assert cells[0] == one.TIMED_COMMIT
    assert dict(zip(columns, map(float, cells[3:]))) == one.MEASURED_MINUTES


def test_the_allow_dirty_variable_is_the_one_results_reads():
    from vpr_nb import results
    assert one.ALLOW_DIRTY_ENV == results.ALLOW_DIRTY_ENV


# --- where the results go ---------------------------------------------------------------------------------------

def test_the_results_folder_gets_the_other_notebooks_committed_results_and_loses_the_runs_old_ones(tmp_path):
    committed, mine = tmp_path / "committed", tmp_path / "reports" / "results"
    for name in ("03_loss.json", "04_netvlad.json", "04_netvlad.netvlad-seed0.pt", "05_salad.json"):
        _results_file(committed / name, {"n": 1})
    (committed / "05_salad.json.tmp").write_text("half written")
    mine.mkdir(parents=True)
    (mine / "03_loss.json").write_text("an earlier run's")
    (mine / "notes.txt").write_text("the student's")
    copies = one.prepare_results_dir(mine, committed, ["03_loss"])
    assert sorted(p.name for p in copies) == ["04_netvlad.json", "04_netvlad.netvlad-seed0.pt", "05_salad.json"]
    assert sorted(p.name for p in mine.iterdir()) == ["04_netvlad.json", "04_netvlad.netvlad-seed0.pt",
                                                      "05_salad.json", "notes.txt"]
    assert (committed / "03_loss.json").is_file()                               # the committed folder is untouched
    with pytest.raises(ValueError, match="committed results folder"):
        one.prepare_results_dir(committed, committed, ["03_loss"])


# --- this run's numbers beside the committed ones --------------------------------------------------------------

COMMITTED = {"rows": {"T-Loss": {"R@1": [0.84, 0.86], "lr": 0.003, "file": "t.pt"}, "DW-T-Loss": {"R@1": [0.8, 0.9]}},
             "fixed": {"raw pixels": {"R@1": 0.2264}}, "seconds": 3694.9}
NEW = {"rows": {"T-Loss": {"R@1": [0.84, 0.86], "lr": 0.003, "file": "u.pt"}, "DW-T-Loss": {"R@1": [0.85, 0.91]}},
       "fixed": {"raw pixels": {"R@1": 0.2264}, "frozen": {"R@1": 0.7484}}, "seconds": 3500.0}


def test_numbers_are_flattened_with_means_of_lists():
    flat = one.flatten_numbers(COMMITTED)
    assert {k: (round(v, 9), n) for k, (v, n) in flat.items()} == ({"rows / T-Loss / R@1": (0.85, 2), "rows / T-Loss / lr": (0.003, 1),
                                  "rows / DW-T-Loss / R@1": (0.85, 2), "fixed / raw pixels / R@1": (0.2264, 1),
                                  "seconds": (3694.9, 1)})
    assert list(flat) == ["rows / T-Loss / R@1", "rows / T-Loss / lr", "rows / DW-T-Loss / R@1",
                          "fixed / raw pixels / R@1", "seconds"]                # the string "file" is left out


def test_the_comparison_rows():
    rows = {r["name"]: r for r in one.compare_results(COMMITTED, NEW)}
    assert list(rows) == ["rows / T-Loss / R@1", "rows / T-Loss / lr", "rows / DW-T-Loss / R@1",
                          "fixed / raw pixels / R@1", "seconds", "fixed / frozen / R@1"]
    assert rows["rows / T-Loss / R@1"]["difference"] == 0
    assert rows["rows / DW-T-Loss / R@1"]["difference"] == pytest.approx(0.03)
    assert rows["fixed / frozen / R@1"] == {"name": "fixed / frozen / R@1", "committed": None,
                                            "new": (0.7484, 1), "difference": None}


def test_the_comparison_table_from_results_files(tmp_path):
    committed = one.read_results(_results_file(tmp_path / "c" / "03_loss.json", COMMITTED, commit="a464538"))
    new = one.read_results(_results_file(tmp_path / "n" / "03_loss.json", NEW, commit="2341719 (with uncommitted changes)"))
    md = one.render_comparison("03_loss", committed, new, "notebooks/results", "reports/results/03_loss.json")
    lines = md.splitlines()
    assert lines[0] == "## 03_loss: this run beside the committed results"
    assert lines[2] == "- committed: notebooks/results/03_loss.json (2026-12-05, a464538, 2.13.0+cpu)"
    assert lines[3].startswith("- this run: reports/results/03_loss.json (2026-12-05, 2341719 (with uncommitted")
    table = lines[lines.index("| number | committed | this run | difference |"):]
    assert table[1:7] == ["|---|---|---|---|",
                          "| rows / T-Loss / R@1 | 0.8500 (mean of 2) | 0.8500 (mean of 2) | same |",
                          "| rows / T-Loss / lr | 0.0030 | 0.0030 | same |",
                          "| rows / DW-T-Loss / R@1 | 0.8500 (mean of 2) | 0.8800 (mean of 2) | +0.0300 |",
                          "| fixed / raw pixels / R@1 | 0.2264 | 0.2264 | same |",
                          "| seconds | 3694.9 | 3500 | -194.9 |"]
    assert table[7] == "| fixed / frozen / R@1 | — | 0.7484 | — |"
    assert lines[-1] == ("5 numbers (run times left out): 3 the same, 2 different; the largest difference: "
                         "rows / DW-T-Loss / R@1 (+0.0300).")


def test_numbers_in_the_table():
    rows = one.compare_results({"dim": [128, 128], "best epoch": [3, 4], "seconds": 295.7, "R@1": 0.5},
                               {"dim": [128, 128], "best epoch": [3, 5], "seconds": 301.2, "R@1": 0.25})
    assert [(one._cell(r["committed"]), one._cell(r["new"]), one._difference(r)) for r in rows] == [
        ("128 (mean of 2)", "128 (mean of 2)", "same"), ("3.5000 (mean of 2)", "4 (mean of 2)", "+0.5000"),
        ("295.7", "301.2", "+5.5"), ("0.5000", "0.2500", "-0.2500")]


def test_paths_are_shown_relative_to_the_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert one.shown_path(tmp_path / "reports" / "results") == "reports/results"
    assert one.shown_path("/") == "/"


def test_the_comparison_says_why_there_is_nothing_to_compare():
    assert "no committed results for 02_base" in one.render_comparison("02_base", None, {"results": {}})
    assert "only the reproduce profile saves results" in one.render_comparison("03_loss", {"results": {}}, None)


# --- the runner: one notebook, its results beside the committed ones -------------------------------------------

def test_run_notebook_alone_writes_beside_the_committed_results_and_compares(tmp_path, monkeypatch, capsys):
    nbdir, committed, out = tmp_path / "notebooks", tmp_path / "notebooks" / "results", tmp_path / "reports"
    _sources(nbdir)
    committed_file = _results_file(committed / "03_loss.json", COMMITTED, commit="a464538")
    _results_file(committed / "04_netvlad.json", {"R@1": 0.5})
    before = committed_file.read_bytes()
    seen = {}

    def fake_run_report(profile, out_, notebooks_dir, jobs=1, *, sources=None, heartbeat=None, store=None):
        seen.update(profile=profile, sources=[p.name for p in sources], env=os.environ.get(RESULTS_DIR_ENV),
                    dirty=os.environ.get(one.ALLOW_DIRTY_ENV), copies=sorted(os.listdir(os.environ[RESULTS_DIR_ENV])))
        heartbeat.start("03_loss")
        _results_file(Path(os.environ[RESULTS_DIR_ENV]) / "03_loss.json", NEW, commit="2341719")   # what save() writes
        heartbeat.stop("03_loss")
        return {"notebooks": [{"name": "03_loss", "status": "ok"}]}

    monkeypatch.setattr(report, "run_report", fake_run_report)
    monkeypatch.delenv(RESULTS_DIR_ENV, raising=False)
    report.run_notebook_alone("3", "reproduce", out, nbdir, jobs=2, committed_dir=committed, progress_every=0)
    assert seen == {"profile": "reproduce", "sources": ["03_loss.ipynb"], "env": str((out / "results").resolve()),
                    "dirty": "1", "copies": ["04_netvlad.json"]}
    assert RESULTS_DIR_ENV not in os.environ and one.ALLOW_DIRTY_ENV not in os.environ
    assert committed_file.read_bytes() == before                                # the committed results are kept
    printed = capsys.readouterr().out
    assert printed.startswith("[plan] 03_loss.ipynb, reproduce profile: about 62–66 min on 2 cores")
    assert f"[plan] results go to {out / 'results'}/ ({committed}/ is not touched)" in printed   # outside the cwd
    assert "| rows / DW-T-Loss / R@1 | 0.8500 (mean of 2) | 0.8800 (mean of 2) | +0.0300 |" in printed
    assert (out / "comparison.md").read_text(encoding="utf-8") in printed


def test_run_notebook_alone_into_committed_compares_with_the_file_it_replaced(tmp_path, monkeypatch, capsys):
    nbdir, committed, out = tmp_path / "notebooks", tmp_path / "notebooks" / "results", tmp_path / "reports"
    _sources(nbdir)
    _results_file(committed / "03_loss.json", COMMITTED)

    def fake_run_report(profile, out_, notebooks_dir, jobs=1, *, sources=None, heartbeat=None, store=None):
        assert RESULTS_DIR_ENV not in os.environ
        if profile == "reproduce":
            os.utime(_results_file(committed / "03_loss.json", NEW), ns=(1, 1))
        return {"notebooks": []}

    monkeypatch.setattr(report, "run_report", fake_run_report)
    monkeypatch.delenv(RESULTS_DIR_ENV, raising=False)
    report.run_notebook_alone("03", "ci", out, nbdir, into_committed=True, committed_dir=committed, progress_every=0)
    assert "only the reproduce profile saves results" in capsys.readouterr().out   # ci: the file was not rewritten
    report.run_notebook_alone("03", "reproduce", out, nbdir, into_committed=True, committed_dir=committed,
                              progress_every=0)
    assert "| rows / DW-T-Loss / R@1 | 0.8500 (mean of 2) | 0.8800 (mean of 2) | +0.0300 |" in capsys.readouterr().out
    assert not (out / "results").exists()


def test_run_report_tells_the_heartbeat_and_runs_the_given_notebooks(tmp_path, monkeypatch):
    sources = _sources(tmp_path / "nbs")
    events = []

    class Beat:
        def start(self, stem):
            events.append(("start", stem))

        def stop(self, stem):
            events.append(("stop", stem))

    def fake_run_one(src, out, profile):
        return {"name": src.stem, "status": "ok", "error": "", "seconds": 0.1, "results": {}, "figures": []}

    monkeypatch.setattr(report, "_run_one", fake_run_one)
    monkeypatch.setattr(report, "pin_this_process", lambda: [])
    monkeypatch.setattr(report, "environment_header", lambda profile: {"profile": profile})
    payload = report.run_report("ci", tmp_path / "out", tmp_path / "nbs", sources=sources[2:3], heartbeat=Beat())
    assert [nb["name"] for nb in payload["notebooks"]] == ["03_loss"]
    assert events == [("start", "03_loss"), ("stop", "03_loss")]
    assert [a["ended"] for a in payload["attempts"]["attempts"]] == [True]      # one attempt, finished


def test_a_run_started_again_reports_its_earlier_attempts(tmp_path, monkeypatch, capsys):
    sources = _sources(tmp_path / "nbs")
    monkeypatch.setattr(report, "_run_one", lambda src, out, profile: {
        "name": src.stem, "status": "ok", "error": "", "seconds": 0.1, "results": {}, "figures": []})
    monkeypatch.setattr(report, "pin_this_process", lambda: [])
    monkeypatch.setattr(report, "environment_header", lambda profile: {"profile": profile, "git commit": "abc1234"})
    out, store = tmp_path / "out", tmp_path / "store"
    out.mkdir()
    killed = {"kind": "start", "time": 1000.0, "commit": "abc1234", "profile": "reproduce",
              "notebooks": ["03_loss.ipynb"], "store": str(store.resolve())}
    (out / "attempts.jsonl").write_text(json.dumps(killed) + "\n" + json.dumps({"kind": "alive", "time": 1300.0})
                                        + "\n")
    payload = report.run_report("reproduce", out, tmp_path / "nbs", sources=sources[2:3], store=store)
    assert "attempt 2 of this run: 1 earlier attempt(s) stopped after 5.0 min" in capsys.readouterr().out
    runs = payload["attempts"]
    assert [(a["minutes"], a["ended"]) for a in runs["attempts"]][0] == (5.0, False) and runs["minutes"] >= 5.0
    assert "| 1 | abc1234 | 5.0 |  | no (stopped) |" in (out / "results.md").read_text()   # no CPU recorded
    again = report.run_report("reproduce", out, tmp_path / "nbs", sources=sources[2:3], store=store)
    assert len(again["attempts"]["attempts"]) == 1                    # the run had finished: a new run


def test_a_run_started_again_skips_the_notebooks_an_attempt_finished_from_the_same_commit(tmp_path, monkeypatch,
                                                                                          capsys):
    sources = _sources(tmp_path / "nbs")
    ran = []

    def fake_run_one(src, out, profile):
        ran.append(src.stem)
        (out / "notebooks" / f"{src.stem}.ipynb").write_text("{}")
        (out / "figures" / f"{src.stem}_1_0.png").write_bytes(b"png")
        return {"name": src.stem, "status": "ok", "error": "", "seconds": 0.1, "results": {}, "figures": []}

    monkeypatch.setattr(report, "_run_one", fake_run_one)
    monkeypatch.setattr(report, "pin_this_process", lambda: [])
    monkeypatch.setattr(report, "environment_header", lambda profile: {"profile": profile, "git commit": "abc1234"})
    out, store = tmp_path / "out", tmp_path / "store"
    (out / "notebooks").mkdir(parents=True)
    (out / "figures").mkdir()
    (out / "notebooks" / "03_loss.ipynb").write_text("{}")       # what the killed attempt left of 03
    (out / "figures" / "03_loss_4_0.png").write_bytes(b"png")
    (out / "figures" / "05_salad_2_0.png").write_bytes(b"png")  # 05 had not finished
    names = [p.name for p in sources[2:5]]
    entry = {"name": "03_loss", "status": "ok", "error": "", "seconds": 600.0, "results": {}, "figures": []}
    lines = [{"kind": "start", "time": 1000.0, "commit": "abc1234", "profile": "reproduce", "notebooks": names,
              "store": str(store.resolve())}, {"kind": "notebook", "time": 1600.0, "entry": entry},
             {"kind": "alive", "time": 1700.0}]
    (out / "attempts.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    payload = report.run_report("reproduce", out, tmp_path / "nbs", sources=sources[2:5], store=store)
    assert sorted(ran) == ["04_netvlad", "05_salad"]                     # 03 was finished: kept, not run
    assert "the notebooks they finished: 03_loss" in capsys.readouterr().out
    assert [nb["name"] for nb in payload["notebooks"]] == ["03_loss", "04_netvlad", "05_salad"]
    assert payload["notebooks"][0]["seconds"] == 600.0                     # its entry from the earlier attempt
    assert (out / "figures" / "03_loss_4_0.png").exists() and not (out / "figures" / "05_salad_2_0.png").exists()
    # another commit: every notebook runs again
    (out / "attempts.jsonl").write_text("".join(json.dumps({**r, "commit": "def5678"} if r["kind"] == "start" else r)
                                                + "\n" for r in lines))
    ran.clear()
    report.run_report("reproduce", out, tmp_path / "nbs", sources=sources[2:5], store=store)
    assert sorted(ran) == ["03_loss", "04_netvlad", "05_salad"]


def test_the_command_line_options(tmp_path, capsys):
    for argv, message in ((["--into-committed"], "goes with --notebook"),
                          (["--notebook", "03", "--notebooks", "0*.ipynb"], "not both"),
                          (["--notebook", "09", "--notebooks-dir", str(tmp_path)], "no notebook")):
        _sources(tmp_path)
        with pytest.raises(SystemExit) as exc:
            report.main(["--profile", "ci", "--out", str(tmp_path / "out"), *argv])
        assert exc.value.code == 2 and message in capsys.readouterr().err


# --- make reproduce NOTEBOOK=03 ---------------------------------------------------------------------------------

@pytest.mark.parametrize("variables, command", [
    ([], ".venv/bin/python -m vpr_nb.report --profile reproduce --out reports --jobs 2"),
    (["NOTEBOOK=03"], ".venv/bin/python -m vpr_nb.report --profile reproduce --out reports --jobs 2 --notebook 03"),
    (["NOTEBOOK=02", "PROFILE=ci"], ".venv/bin/python -m vpr_nb.report --profile ci --out reports --jobs 2 --notebook 02"),
])
def test_make_passes_the_notebook_through(variables, command):
    out = subprocess.run(["make", "-n", "reproduce", *variables], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    runs = [line for line in out.stdout.splitlines() if "vpr_nb.report" in line]
    assert runs == [command]


@pytest.mark.slow
def test_one_notebook_end_to_end_saves_into_the_reports_folder(tmp_path, monkeypatch, capsys):
    """A real kernel: the notebook's ``results.save`` writes into OUT/results/ (VPR_NB_RESULTS_DIR), the committed
    file stays as it was, and the numbers are compared."""
    import nbformat

    nbdir, committed, out = tmp_path / "nbs", tmp_path / "committed", tmp_path / "reports"
    nbdir.mkdir()
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.cells = [nbformat.v4.new_code_cell('PROFILE = "ci"', metadata={"tags": ["parameters"]}),
                nbformat.v4.new_code_cell("from vpr_nb import results\n"
                                          "if PROFILE == 'reproduce':\n"
                                          "    results.save('03_x', {}, {'R@1': [0.5, 0.7], 'seconds': 2.0})")]
    nbformat.write(nb, nbdir / "03_x.ipynb")
    committed_file = _results_file(committed / "03_x.json", {"R@1": [0.5, 0.6], "seconds": 1.0})
    before = committed_file.read_bytes()
    monkeypatch.setenv(RESULTS_DIR_ENV, str(committed))          # where the committed results are read from
    assert report.main(["--profile", "reproduce", "--out", str(out), "--notebooks-dir", str(nbdir),
                        "--notebook", "03", "--jobs", "1"]) == 0
    assert committed_file.read_bytes() == before and os.environ[RESULTS_DIR_ENV] == str(committed)
    assert json.loads((out / "results" / "03_x.json").read_text())["results"]["R@1"] == [0.5, 0.7]
    printed = capsys.readouterr().out
    assert "| R@1 | 0.5500 (mean of 2) | 0.6000 (mean of 2) | +0.0500 |" in printed
    assert "1 number (run times left out): 0 the same, 1 different" in printed


def test_readme_states_the_full_run_time_the_committed_files_give():
    import re

    from vpr_nb.package_data import committed_results_dir
    from vpr_nb.reproduce_one import full_run_hours

    from vpr_nb.timed_runs import read_records

    root = Path(__file__).resolve().parents[1]
    if read_records(root / "docs" / "timed_runs"):
        pytest.skip("a whole run is timed: README states its measured time (tests/test_timed_runs.py)")
    readme = (root / "README.md").read_text(encoding="utf-8")
    stated = re.search(r"make reproduce +# every notebook at its full budget, reports/ \(about ([\d.]+) h on 2 cores",
                       readme)
    assert stated, "README's make reproduce line must state its time as 'about N h on 2 cores'"
    assert float(stated.group(1)) == full_run_hours(committed_results_dir()), \
        "README's make reproduce time is stale: set it to vpr_nb.reproduce_one.full_run_hours()"
