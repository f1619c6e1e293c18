"""The simulated schedule of a run (vpr_nb.schedule) and the rounds the engine logs (vpr_nb.engine.log_round)."""
import json

import pytest

from vpr_nb import engine as eng
from vpr_nb.schedule import fastest_possible, notebook_phases, read_rounds, run_summary, scaling_table, simulate


def test_simulate_known_schedules():
    two_rounds = [("code", 10.0), ("round", [30.0, 30.0, 20.0, 20.0]), ("code", 5.0)]
    assert simulate([two_rounds], 1) == 115.0                       # everything one after the other
    assert simulate([two_rounds], 2) == 10 + 50 + 5                 # longest first: 30+20 on each worker
    assert simulate([two_rounds], 4) == 10 + 30 + 5                 # the round's longest task bounds it
    assert simulate([two_rounds, two_rounds], 64) == 45.0           # notebooks run at once
    assert simulate([two_rounds, two_rounds], 1) == 230.0
    # a barrier: the next phase waits for the whole round, even with workers free
    assert simulate([[("round", [100.0, 1.0]), ("round", [1.0])]], 2) == 101.0
    assert simulate([[("round", [])]], 3) == 0.0
    assert scaling_table([two_rounds], (1, 2)) == {1: round(115 / 60, 1), 2: round(65 / 60, 1)}
    with pytest.raises(ValueError, match="workers"):
        simulate([two_rounds], 0)


def test_phases_from_logged_rounds():
    rounds = [{"t0": 110.0, "t1": 140.0, "seconds": [30.0, 25.0]}, {"t0": 150.0, "t1": 160.0, "seconds": [10.0]}]
    assert notebook_phases(100.0, 70.0, rounds) == [("code", 10.0), ("round", [30.0, 25.0]), ("code", 10.0),
                                                      ("round", [10.0]), ("code", 10.0)]
    assert notebook_phases(100.0, 5.0, []) == [("code", 5.0)]
    with pytest.raises(ValueError, match="seconds"):
        notebook_phases(0.0, float("nan"), [])


def test_rounds_are_logged_and_a_torn_line_is_skipped(tmp_path):
    path = tmp_path / "t.jsonl"
    env = {eng.TIMES_ENV: str(path)}
    eng.log_round(1.0, 3.0, [1.5, 2.0], [False, True], environ=env)
    eng.log_round(4.0, 5.0, [1.0], [False], environ=env)
    eng.log_round(4.0, 5.0, [1.0], [False], environ={})              # unset: nothing written
    with open(path, "a") as fh:
        fh.write('{"t0": 6.0, "t1"')                                 # a kernel killed mid-write
    rounds = read_rounds(path)
    assert [r["seconds"] for r in rounds] == [[1.5, 2.0], [1.0]] and rounds[0]["reused"] == [False, True]
    assert read_rounds(tmp_path / "missing.jsonl") == []
    summary = run_summary([{"name": "07_x", "started": 0.0, "seconds": 6.0}], {"07_x": rounds}, wall=6.0, cpu=9.0,
                          cores=2, workers=(1, 2))
    assert summary["notebooks"]["07_x"]["tasks"] == 3 and summary["notebooks"]["07_x"]["reused"] == 1
    assert summary["idle share"] == 0.25 and set(summary["simulated minutes"]) == {1, 2}
    json.dumps(summary)                                              # the report stores it in results.json


def test_one_parser_reads_the_round_log_for_the_report_and_for_results(tmp_path, monkeypatch):
    from vpr_nb import results
    from vpr_nb.schedule import parse_round

    path = tmp_path / "t.jsonl"
    eng.log_round(1.0, 3.0, [1.5, 2.0], [False, True], environ={eng.TIMES_ENV: str(path)})
    with open(path, "a") as fh:
        fh.write('{"t0": 1, "t1": 2, "seconds": [1.0, 2.0], "reused": [true]}\n')       # lengths differ
        fh.write('{"t0": 1, "t1": 2, "seconds": ["NaN"], "reused": [false]}\n')         # not a time
        fh.write('["a list"]\n{"t0": 6.0, "t1"')                                       # foreign, then torn
    assert parse_round('{"t0": 1, "t1": 2, "seconds": [3], "reused": [0]}') == {
        "t0": 1.0, "t1": 2.0, "seconds": [3.0], "reused": [False]}
    assert [r["seconds"] for r in read_rounds(path)] == [[1.5, 2.0]]
    monkeypatch.setenv(eng.TIMES_ENV, str(path))
    assert results.tasks_since_last_save() == {"run": 2, "reused": 1, "task seconds": 3.5}


def test_a_notebook_that_reads_another_starts_after_it_and_no_schedule_beats_the_bound():
    a = [("round", [60.0, 60.0])]
    b = [("code", 10.0), ("round", [30.0])]
    assert simulate([a, b], 64) == 60.0                             # side by side
    assert simulate([a, b], 64, after=[set(), {0}]) == 100.0        # b waits for a
    assert simulate([[], b], 4, after=[set(), {0}]) == 40.0         # nothing to wait for
    with pytest.raises(ValueError, match="circle"):
        simulate([a, b], 2, after=[{1}, {0}])
    with pytest.raises(ValueError, match="after"):
        simulate([a, b], 2, after=[{5}, set()])
    assert fastest_possible([a, b], 1) == 160.0                     # all the work on one worker
    assert fastest_possible([a, b], 64, after=[set(), {0}]) == 100.0   # the chain a -> b
    for w in (1, 2, 3, 8):                                          # the simulation never beats the bound
        assert simulate([a, b], w, after=[set(), {0}]) >= fastest_possible([a, b], w, after=[set(), {0}])
    summary = run_summary([{"name": "05_x", "started": 0.0, "seconds": 60.0},
                           {"name": "07_y", "started": 60.0, "seconds": 40.0}],
                          {"05_x": [{"t0": 0.0, "t1": 60.0, "seconds": [60.0, 60.0], "reused": [False, False]}],
                           "07_y": [{"t0": 70.0, "t1": 100.0, "seconds": [30.0], "reused": [True]}]},
                          wall=100.0, cpu=160.0, cores=2, workers=(2, 64), after={"07_y": {"05_x", "99_absent"}})
    assert summary["waits for"] == {"07_y": ["05_x"]}
    assert summary["simulated minutes"] == {2: round(100 / 60, 1), 64: round(100 / 60, 1)}
    assert summary["fastest possible minutes"] == {2: round(100 / 60, 1), 64: round(100 / 60, 1)}
