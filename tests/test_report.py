"""vpr_nb.report: record(), Markdown tables, PNG extraction and the papermill runner."""
from __future__ import annotations

import base64
import json
import os

import nbformat
import pytest

from vpr_nb import report
from vpr_nb.report import RESULTS_ENV, extract_figures, record, render_table

# a valid 1x1 PNG
PNG = base64.b64encode(bytes.fromhex(
    "89504e470d0a1a0a0000000d49484452000000010000000108060000001f15c489"
    "0000000d49444154789c6360000002000154a24f5f0000000049454e44ae426082")).decode()


def test_record_is_a_noop_without_env(monkeypatch, tmp_path):
    monkeypatch.delenv(RESULTS_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    record("01_x", {"R@1": 0.5})
    assert list(tmp_path.iterdir()) == []


def test_record_appends_json_lines(monkeypatch, tmp_path):
    np = pytest.importorskip("numpy")
    path = tmp_path / "r.jsonl"
    monkeypatch.setenv(RESULTS_ENV, str(path))
    record("01_x", {"R@1": np.float32(0.5), "ns": np.array([1, 5])})
    record("01_x", {"nested": {"a": 1}, "bad": float("nan")})
    lines = [json.loads(row) for row in path.read_text().splitlines()]
    assert lines[0] == {"notebook": "01_x", "results": {"R@1": 0.5, "ns": [1, 5]}}
    assert lines[1]["results"] == {"nested": {"a": 1}, "bad": "nan"}


@pytest.mark.parametrize("key, results", [("", {"a": 1}), ("k", {}), ("k", [1]), ("k", {"a": object()})])
def test_record_rejects_bad_input(monkeypatch, key, results):
    monkeypatch.delenv(RESULTS_ENV, raising=False)
    with pytest.raises(ValueError):
        record(key, results)


def test_render_flat_table():
    md = render_table({"R@1": 0.71234, "epochs": 3, "ns": [1, 5, 10], "name": "a|b", "tiny": 1.5e-5})
    lines = md.splitlines()
    assert lines[0] == "| name | value |"
    assert lines[1] == "|---|---|"
    assert "| R@1 | 0.712 |" in lines
    assert "| epochs | 3 |" in lines
    assert "| ns | 1, 5, 10 |" in lines
    assert "| name | a\\|b |" in lines
    assert "| tiny | 1.5e-05 |" in lines


def test_render_dict_of_dicts_is_one_grid():
    md = render_table({"raw pixels": {"R@1": 0.2, "R@5": 0.4}, "random CNN": {"R@1": 0.3, "R@10": 0.6}})
    assert md.splitlines() == [
        "|  | R@1 | R@5 | R@10 |",
        "|---|---|---|---|",
        "| raw pixels | 0.200 | 0.400 |  |",
        "| random CNN | 0.300 |  | 0.600 |",
    ]


def test_render_deeper_nesting_gets_its_own_grid():
    md = render_table({"R@1": 0.5, "sweep": {"jitter": {"0": 0.3, "3": 0.2}, "aliasing": {"4": 0.1}}})
    flat, title, grid = md.split("\n\n")
    assert flat.splitlines()[2] == "| R@1 | 0.500 |"
    assert title == "**sweep**"
    assert grid.splitlines() == ["|  | 0 | 3 | 4 |", "|---|---|---|---|",
                                 "| jitter | 0.300 | 0.200 |  |", "| aliasing |  |  | 0.100 |"]


def test_render_rejects_empty():
    with pytest.raises(ValueError):
        render_table({})


def test_extract_figures(tmp_path):
    nb = {"cells": [
        {"cell_type": "markdown", "source": "# t"},
        {"cell_type": "code", "outputs": [{"output_type": "stream", "text": "hi"},
                                          {"output_type": "display_data", "data": {"image/png": PNG}},
                                          {"output_type": "display_data", "data": {"image/png": [PNG]}}]},
    ]}
    paths = extract_figures(nb, "00_demo", tmp_path / "figs")
    assert [p.name for p in paths] == ["00_demo_01_0.png", "00_demo_01_1.png"]
    assert paths[0].read_bytes().startswith(b"\x89PNG")
    with pytest.raises(ValueError):
        extract_figures({"no": "cells"}, "x", tmp_path)


def _write_nb(path, cells):
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    for tags, src in cells:
        nb.cells.append(nbformat.v4.new_code_cell(src, metadata={"tags": tags}))
    nbformat.write(nb, path)


@pytest.mark.slow
def test_runner_end_to_end(tmp_path, monkeypatch):
    monkeypatch.delenv(RESULTS_ENV, raising=False)
    monkeypatch.setenv("MPLBACKEND", "Agg")  # as in .ci/run: the runner must still get inline PNGs
    nbdir = tmp_path / "nbs"
    nbdir.mkdir()
    _write_nb(nbdir / "00_ok.ipynb", [
        (["parameters"], 'PROFILE = "x"'),
        ([], "from vpr_nb.report import record\n"
             "record('00_ok', {'profile': PROFILE})\n"
             "record('00_ok', {'raw': {'R@1': 0.5}})"),
        ([], "import matplotlib.pyplot as plt\nplt.plot([0, 1]); plt.show()"),
    ])
    _write_nb(nbdir / "01_fails.ipynb", [(["parameters"], 'PROFILE = "x"'), ([], "raise RuntimeError('boom')")])
    _write_nb(nbdir / "helper.ipynb", [([], "raise SystemExit")])  # not NN_*: never run
    out = tmp_path / "reports"
    rc = report.main(["--profile", "ci", "--out", str(out), "--notebooks-dir", str(nbdir)])
    assert rc == 1  # one notebook failed, and the runner still ran both
    data = json.loads((out / "results.json").read_text())
    assert data["header"]["profile"] == "ci"
    ok, bad = data["notebooks"]
    assert (ok["name"], ok["status"]) == ("00_ok", "ok")
    assert ok["results"] == {"00_ok": {"profile": "ci", "raw": {"R@1": 0.5}}}
    assert bad["status"] == "failed" and "RuntimeError: boom" in bad["error"]
    assert (out / "notebooks" / "00_ok.ipynb").exists() and (out / "notebooks" / "01_fails.ipynb").exists()
    assert ok["figures"] == ["figures/00_ok_03_0.png"] and (out / ok["figures"][0]).exists()
    md = (out / "results.md").read_text()
    assert "| profile | ci |" in md and "| raw | 0.500 |" in md and "**failed**" in md
    assert RESULTS_ENV not in os.environ and os.environ["MPLBACKEND"] == "Agg"
    # a second run over a subset leaves nothing of the first run's other notebooks behind
    assert report.main(["--profile", "ci", "--out", str(out), "--notebooks-dir", str(nbdir),
                        "--notebooks", "01_*.ipynb"]) == 1
    assert sorted(p.name for p in (out / "notebooks").iterdir()) == ["01_fails.ipynb"]
    assert list((out / "figures").iterdir()) == []
    assert [nb["name"] for nb in json.loads((out / "results.json").read_text())["notebooks"]] == ["01_fails"]


def test_runner_validates_arguments(tmp_path):
    with pytest.raises(ValueError, match="unknown profile"):
        report.run_report("full", tmp_path / "out", tmp_path)
    with pytest.raises(FileNotFoundError):
        report.run_report("ci", tmp_path / "out", tmp_path)  # empty folder: no notebooks
    with pytest.raises(FileNotFoundError):
        report.run_report("ci", tmp_path / "out", tmp_path / "missing")


def test_cli_reports_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        report.main(["--profile", "full", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        report.main(["--profile", "ci", "--out", str(tmp_path), "--notebooks-dir", str(tmp_path)])
    assert exc.value.code == 2 and "no notebook" in capsys.readouterr().err


def test_find_notebooks_absolute_pattern_and_checkpoints(tmp_path):
    nbdir = tmp_path / "nbs"
    (nbdir / ".ipynb_checkpoints").mkdir(parents=True)
    for p in (nbdir / "00_a.ipynb", nbdir / "01_b.ipynb", nbdir / ".ipynb_checkpoints" / "00_a-checkpoint.ipynb"):
        _write_nb(p, [([], "1")])
    assert [p.name for p in report.find_notebooks(nbdir, "**/*.ipynb")] == ["00_a.ipynb", "01_b.ipynb"]
    assert [p.name for p in report.find_notebooks(nbdir, str(nbdir / "0[1]_*.ipynb"))] == ["01_b.ipynb"]
    assert [p.name for p in report.find_notebooks(nbdir, str(nbdir) + "/**/*.ipynb")] == ["00_a.ipynb", "01_b.ipynb"]
    with pytest.raises(FileNotFoundError, match="no notebook"):
        report.find_notebooks(nbdir, str(tmp_path / "elsewhere" / "*.ipynb"))
    with pytest.raises(ValueError, match="pattern"):
        report.find_notebooks(nbdir, "")


def test_dependencies_are_the_other_notebooks_a_notebook_names(tmp_path):
    _write_nb(tmp_path / "04_a.ipynb", [([], "x = 1")])
    _write_nb(tmp_path / "05_b.ipynb", [([], 'cfg = committed_experiment("04_a")')])
    _write_nb(tmp_path / "06_c.ipynb", [([], "# mentions 04_a only in a comment without quotes")])
    deps = report.notebook_dependencies(sorted(tmp_path.glob("*.ipynb")))
    assert deps == {"04_a": set(), "05_b": {"04_a"}, "06_c": set()}


@pytest.mark.slow
def test_parallel_run_waits_for_the_notebook_it_reads(tmp_path, monkeypatch):
    """With --jobs 2, 05 starts only after 04 has finished (04 writes a file that 05 reads), 06 runs beside;
    records of parallel notebooks stay apart and the report lists them in order."""
    monkeypatch.delenv(RESULTS_ENV, raising=False)
    nbdir, flag = tmp_path / "nbs", tmp_path / "04_done.txt"
    nbdir.mkdir()
    _write_nb(nbdir / "04_a.ipynb", [(["parameters"], 'PROFILE = "x"'),
                                     ([], f"import time; time.sleep(3); open({str(flag)!r}, 'w').write('ok')\n"
                                          "from vpr_nb.report import record; record('04_a', {'n': 4})")])
    _write_nb(nbdir / "05_b.ipynb", [(["parameters"], 'PROFILE = "x"'),
                                     ([], f"# reads '04_a'\nassert open({str(flag)!r}).read() == 'ok'\n"
                                          "from vpr_nb.report import record; record('05_b', {'n': 5})")])
    _write_nb(nbdir / "06_c.ipynb", [(["parameters"], 'PROFILE = "x"'),
                                     ([], "from vpr_nb.report import record; record('06_c', {'n': 6})")])
    out = tmp_path / "reports"
    assert report.main(["--profile", "ci", "--out", str(out), "--notebooks-dir", str(nbdir), "--jobs", "2"]) == 0
    data = json.loads((out / "results.json").read_text())
    assert [nb["name"] for nb in data["notebooks"]] == ["04_a", "05_b", "06_c"] and data["jobs"] == 2
    assert [nb["results"] for nb in data["notebooks"]] == [{"04_a": {"n": 4}}, {"05_b": {"n": 5}}, {"06_c": {"n": 6}}]


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_notebooks_that_read_each_other_run_in_order(tmp_path, monkeypatch, jobs):
    """A cycle of notebooks naming each other cannot wait for one another: the next in order starts."""
    monkeypatch.delenv(RESULTS_ENV, raising=False)
    nbdir = tmp_path / "nbs"
    nbdir.mkdir()
    for stem, other in (("04_a", "05_b"), ("05_b", "04_a")):
        _write_nb(nbdir / f"{stem}.ipynb", [(["parameters"], 'PROFILE = "x"'),
                                            ([], f"# reads '{other}'\nfrom vpr_nb.report import record; "
                                                 f"record('{stem}', {{'n': 1}})")])
    assert report.notebook_dependencies(sorted(nbdir.glob("*.ipynb"))) == {"04_a": {"05_b"}, "05_b": {"04_a"}}
    out = tmp_path / "reports"
    assert report.main(["--profile", "ci", "--out", str(out), "--notebooks-dir", str(nbdir), "--jobs", jobs]) == 0
    assert [nb["name"] for nb in json.loads((out / "results.json").read_text())["notebooks"]] == ["04_a", "05_b"]


def test_environment_header_records_the_cpu_kernels(monkeypatch):
    # trained numbers depend on the CPU kernels: the header says which, pinned (vpr_nb.kernels) or native
    import torch

    from vpr_nb import kernels

    monkeypatch.setattr(os, "environ", kernels.pinned_environ())
    head = report.environment_header("ci")
    assert head["cpu"].endswith("; pinned kernels (AVX2, MKL COMPATIBLE)")
    assert head["cpu"].split(";")[0].strip()          # a processor name, never empty
    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items() if k not in kernels.PINNED})
    assert kernels.cpu_description().endswith(f"; native kernels (torch {torch.backends.cpu.get_cpu_capability()})")

    def no_cpuinfo(*args, **kwargs):
        raise OSError("no /proc here")

    monkeypatch.setattr("builtins.open", no_cpuinfo)   # macOS / Windows: platform's name instead
    assert kernels.cpu_description().split(";")[0].strip()
