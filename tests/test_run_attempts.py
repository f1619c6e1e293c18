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
    s = ra.summary(got)
    assert s["attempts"][0] == {"commit": "abc1234", "minutes": 10.0, "ended": False}
    assert s["minutes"] == 10.0 and s["last share"] < 0.01
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
