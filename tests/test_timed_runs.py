"""Timed whole runs (vpr_nb.timed_runs): a run's report kept as a record, the docs' and README's times made from
the records and checked against them."""
import copy
import json
from pathlib import Path

import pytest

from vpr_nb import timed_runs as tr

ROOT = Path(__file__).resolve().parents[1]
REPORT = {
    "header": {"profile": "reproduce", "git commit": "abc1234", "date": "2026-12-08", "machine": "x86_64, 2 cores"},
    "jobs": 2, "wall_seconds": 3000.0,
    "notebooks": [{"name": "00_world", "status": "ok", "seconds": 30.0, "results": {"x": 1}},
                  {"name": "03_loss", "status": "ok", "seconds": 2970.0, "results": {}}],
    "tasks": {"notebooks": {"00_world": {"tasks": 0, "reused": 0, "task minutes": 0.0, "longest task (min)": 0.0},
                            "03_loss": {"tasks": 150, "reused": 40, "task minutes": 600.0,
                                        "longest task (min)": 4.2}},
              "wall minutes": 50.0, "cpu minutes": 95.0, "cores": 2, "idle share": 0.05,
              "simulated minutes": {"2": 310.0, "8": 80.5, "16": 45.0, "64": 30.0}},
    "attempts": {"attempts": [{"commit": "abc1234", "minutes": 260.0, "ended": False},
                              {"commit": "abc1234", "minutes": 50.0, "ended": True}],
                 "minutes": 310.0, "cpu minutes": 589.0, "idle share": 0.05, "last share": 0.161}}


def test_a_report_becomes_a_record_and_the_docs_tables():
    record = tr.record_of(REPORT)
    assert record["wall minutes"] == 310.0 and record["notebooks"]["03_loss"]["reused"] == 40
    block = tr.docs_block([record])
    assert "| abc1234 | 2026-12-08 | 2 | **310** | 589 | 0.050 | 310 / 80.5 / 45 / 30 | not recorded |" in block
    assert "| 03_loss | 49.5 | 150 | 40 | 600 | 4.2 |" in block
    assert tr.readme_text([record]) == "5.2 h on 2 cores, measured in 2 attempts; resumes if stopped"
    assert "No whole" in tr.docs_block([])


@pytest.mark.parametrize("change, message", [
    (lambda r: r["header"].update(profile="ci"), "reproduce-profile"),
    (lambda r: r["header"].update({"git commit": "abc1234 (with uncommitted changes)"}), "clean commit"),
    (lambda r: r["notebooks"][1].update(status="failed"), "every notebook ok"),
    (lambda r: r.pop("attempts"), "older vpr_nb"),
    (lambda r: r["attempts"].update({"idle share": float("nan")}), "idle share"),
    (lambda r: r["notebooks"][0].update(seconds="30"), "seconds"),
    (lambda r: r["tasks"]["simulated minutes"].pop("64"), "simulated minutes"),
])
def test_a_report_that_is_not_a_whole_clean_run_is_refused(change, message):
    bad = copy.deepcopy(REPORT)
    change(bad)
    with pytest.raises(ValueError, match=message):
        tr.record_of(bad)


def test_the_command_keeps_a_record_and_rewrites_the_docs(tmp_path, capsys):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "reproduction.md").write_text(f"intro\n{tr.BEGIN}\nold\n{tr.END}\nrest\n")
    (tmp_path / "README.md").write_text("make reproduce   # every notebook at its full budget, reports/ (about 6 h)\n")
    (tmp_path / "results.json").write_text(json.dumps(REPORT))
    assert tr.main(["add", str(tmp_path / "results.json"), "--root", str(tmp_path)]) == 0
    assert (tmp_path / "docs" / "timed_runs" / "abc1234.json").is_file()
    assert tr.main(["docs", "--root", str(tmp_path)]) == 0
    docs = (tmp_path / "docs" / "reproduction.md").read_text()
    assert docs.startswith("intro\n") and docs.endswith("rest\n") and "**310**" in docs and "old" not in docs
    assert "(5.2 h on 2 cores, measured in 2 attempts; resumes if stopped)" in (tmp_path / "README.md").read_text()
    (tmp_path / "bad.json").write_text("{")
    assert tr.main(["add", str(tmp_path / "bad.json"), "--root", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("error: cannot read")


def test_a_run_folder_gives_its_summary_again_with_waits_and_the_fastest_schedule(tmp_path):
    run = tmp_path / "reports"
    (run / "records").mkdir(parents=True)
    (run / "notebooks").mkdir()
    report = copy.deepcopy(REPORT)
    report["notebooks"][1]["started"] = 1000.0
    for name, code in (("00_world", "x = 1"), ("03_loss", 'committed_experiment("00_world")')):
        cells = [{"cell_type": "code", "source": code, "metadata": {}, "outputs": [], "execution_count": None}]
        (run / "notebooks" / f"{name}.ipynb").write_text(json.dumps({"cells": cells}))
    (run / "records" / "03_loss.tasks.jsonl").write_text(
        json.dumps({"t0": 1000.0, "t1": 3970.0, "seconds": [2400.0] * 4, "reused": [True, False, False, False]})
        + "\n")
    (run / "results.json").write_text(json.dumps(report))
    (tmp_path / "docs").mkdir()
    assert tr.main(["add", str(run / "results.json"), "--root", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "docs" / "timed_runs" / "abc1234.json").read_text())
    assert record["notebooks"]["03_loss"] == {"wall minutes": 49.5, "fine-tunes": 4, "reused": 1,
                                              "task minutes": 160.0, "longest task (min)": 40.0}
    # 03 waits for 00 (0.5 min); then one round of four 40-min tasks; 2 workers: two after two
    assert record["simulated minutes"] == {"2": 80.5, "8": 40.5, "16": 40.5, "64": 40.5}
    assert record["fastest possible minutes"] == {"2": 80.2, "8": 40.5, "16": 40.5, "64": 40.5}
    assert "| 80.2 / 40.5 / 40.5 / 40.5 |" in tr.docs_block([record])


def test_the_docs_and_readme_say_what_the_committed_records_give():
    records = tr.read_records(ROOT / "docs" / "timed_runs")
    docs = (ROOT / "docs" / "reproduction.md").read_text(encoding="utf-8")
    assert tr.render_docs(docs, records) == docs, "stale: run python -m vpr_nb.timed_runs docs"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert tr.render_readme(readme, records) == readme, "stale: run python -m vpr_nb.timed_runs docs"
