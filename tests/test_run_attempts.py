"""A run made in several attempts (vpr_nb.run_attempts): a killed attempt's wall time is kept, a finished run
starts the file again."""
import json
import os
import signal
import subprocess
import sys
import time

from vpr_nb import run_attempts as ra

INFO = {"commit": "abc1234", "profile": "reproduce", "notebooks": ["00_a.ipynb", "03_b.ipynb"], "store": "/s"}


def _lines(path, *records):
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def test_an_attempt_stopped_without_its_end_line_is_continued_by_the_next(tmp_path):
    path = tmp_path / "attempts.jsonl"
    _lines(path, {"kind": "start", "time": 1000.0, **INFO}, {"kind": "alive", "time": 1060.0},
           {"kind": "alive", "time": 1600.0})
    with path.open("a") as fh:
        fh.write('{"kind": "ali')                                    # killed while writing
    attempt = ra.Attempt(path)
    earlier = attempt.begin(**INFO)
    assert [(a["start"], a["last"], a["ended"]) for a in earlier] == [(1000.0, 1600.0, False)]
    attempt.end()
    got = ra.read(path)
    assert len(got) == 2 and got[1]["ended"] and not got[0]["ended"]
    s = ra.summary(got, cores=2)
    assert s["attempts"][0] == {"commit": "abc1234", "minutes": 10.0, "cpu minutes": None, "ended": False}
    assert s["minutes"] == 10.0 and s["last share"] < 0.01 and s["idle share"] is None    # attempt 1 had no CPU
    text = "\n".join(ra.summary_markdown(s))
    assert "2 attempt(s), 10.0 min of wall time in all" in text and "no (stopped)" in text


def test_a_finished_run_another_run_or_no_store_starts_again(tmp_path):
    path = tmp_path / "attempts.jsonl"
    _lines(path, {"kind": "start", "time": 1000.0, **INFO}, {"kind": "end", "time": 1100.0})
    assert ra.Attempt(path).begin(**INFO) == []                      # the earlier run had finished
    assert len(ra.read(path)) == 1
    for other in ({**INFO, "notebooks": ["03_b.ipynb"]}, {**INFO, "profile": "ci"}, {**INFO, "store": "/t"},
                  {**INFO, "store": None}):
        _lines(path, {"kind": "start", "time": 1000.0, **INFO})          # stopped, not finished
        assert ra.Attempt(path).begin(**other) == [], other
        assert len(ra.read(path)) == 1


def test_a_killed_attempt_keeps_its_alive_lines(tmp_path):
    path = tmp_path / "attempts.jsonl"
    code = ("import sys, time; from vpr_nb.run_attempts import Attempt; "
            f"Attempt(sys.argv[1], every=0.05).begin(**{INFO!r}); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], env={**os.environ})
    def beating():
        got = ra.read(path)
        return got and got[0]["last"] > got[0]["start"]

    deadline = time.time() + 30
    while time.time() < deadline and not beating():
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (attempt,) = ra.read(path)
    assert not attempt["ended"] and attempt["last"] > attempt["start"]


def test_the_idle_share_of_a_run_spans_its_attempts(tmp_path):
    path = tmp_path / "attempts.jsonl"
    _lines(path, {"kind": "start", "time": 0.0, **INFO}, {"kind": "alive", "time": 600.0, "cpu": 1080.0},
           {"kind": "start", "time": 1000.0, **INFO}, {"kind": "alive", "time": 1300.0, "cpu": 540.0},
           {"kind": "end", "time": 1600.0, "cpu": 1080.0})
    s = ra.summary(ra.read(path), cores=2)
    assert (s["minutes"], s["cpu minutes"], s["idle share"]) == (20.0, 36.0, 0.1)   # 2160 of 2 x 1200 CPU-seconds
    assert [a["cpu minutes"] for a in s["attempts"]] == [18.0, 18.0]


def test_the_cpu_of_the_process_tree_counts_a_live_child():
    before = ra.tree_cpu_seconds()
    child = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                              "while time.process_time() - t < 0.5: pass\ntime.sleep(30)"])
    try:
        deadline = time.time() + 30
        while time.time() < deadline and ra.tree_cpu_seconds() - before < 0.4:
            time.sleep(0.05)
        assert ra.tree_cpu_seconds() - before >= 0.4                   # the child is alive, not yet waited for
    finally:
        child.kill()
        child.wait()
