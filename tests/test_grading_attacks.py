"""Hostile submissions: every cheat scores 0, no harm reaches another submission, the grades file or the
instructor's files, and nothing a submission started outlives its grading (vpr_nb.grading).

One class is graded per backend with ``grade-class`` in a child process (so an attack on "the grader"
could only ever hit that process): honest students before and after a row of attackers. Each attack
lives in the solution of ``cube``, an exercise without the own-code rule, so that the sandbox (not the
static check) is what stops it; the cheats that need the library go into ``square``.
"""
import csv
import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from grading_fixtures import NAME, submission, two_exercises, write

from vpr_nb.grading import sandbox

ROOT = Path(__file__).resolve().parents[1]
MARK = "vpr-nb-attack-marker"            # in the command line of every process an attack leaves behind
TIMEOUT = 20                             # seconds per exercise in these classes
SITE = Path(sandbox.__file__).resolve().parents[1]     # the vpr_nb package folder

# a detached process: double fork, new session, exec python with an empty environment and MARK in argv
DETACH = """import os, sys
def detach(code):
    if os.fork() == 0:
        os.setsid()
        if os.fork() == 0:
            os.execve(sys.executable, [sys.executable, "-c", code, "{mark}"], {{}})
        os._exit(0)
    os.wait()
""".format(mark=MARK)

CHEATS = {   # name: (square body, cube body); each must score 0 on the exercise it attacks
    "read the instructor's solution": (None, """import glob, json
def cube(x):
    for path in ["@SRC@", "@NAME@", *glob.glob("/**/@NAME@", recursive=True)]:
        try:
            nb = json.load(open(path))
        except Exception:
            continue
        src = next(''.join(c["source"]) for c in nb["cells"] if "def cube" in ''.join(c["source"]))
        ns = {}
        exec(src, ns)
        return ns["cube"](x)
    return 0"""),
    "replace assert_own_code by a no-op": ("""import vpr_nb.assignments
vpr_nb.assignments.assert_own_code = lambda *a, **k: None
vpr_nb.assignments.library_references = lambda *a, **k: []
return x * x""", None),
    "patch builtins.abs": (None, """import builtins
builtins.abs = lambda v: 0.0
return 0"""),
    "patch numpy and torch": (None, """import numpy as np
np.isclose = lambda *a, **k: np.array(True)
np.allclose = lambda *a, **k: True
np.array_equal = lambda *a, **k: True
return 0"""),
    "silence tracebacks": (None, """@cell
get_ipython().showtraceback = lambda *a, **k: None
get_ipython()._showtraceback = lambda *a, **k: None
def cube(x):
    assert False, "no error output will show this"
"""),
    "a pickle for the grader": (None, """@cell
import os
import numpy as np
import vpr_nb.grading.data as data
class Boom:
    def __reduce__(self):
        return (os.system, ("touch @OUT@/unpickled-by-the-grader",))
def evil_write(value, folder, stem):
    import json, os
    np.savez(os.path.join(folder, stem + ".npz"), a0=np.array([Boom()], dtype=object))
    open(os.path.join(folder, stem + ".json"), "w").write(json.dumps({"$array": "a0"}))
data.write = evil_write
def cube(x):
    return x ** 3
"""),
}
HARMS = {   # name: cube body; each must score 0 and leave no trace
    "rewrite scores.csv after the grader exits": DETACH + """detach("import time; time.sleep(3); open('@CSV@', 'w').write('student,points\\\\nmallory,100\\\\n')")
return 0""",
    "break a later student's answer": DETACH + """import pathlib, site
for d in site.getsitepackages() + ["@SITE@"]:
    try:
        pathlib.Path(d, "zz_vpr_attack.pth").write_text("import builtins; builtins.abs = None")
    except OSError:
        pass
try:
    pathlib.Path("/tmp/zz_vpr_attack").write_text("x")
except OSError:
    pass
detach("import glob, time\\nwhile True:\\n    for d in glob.glob('/tmp/vpr_nb_grade_*'):\\n        try: open(d + '/job.json', 'w').write('{}')\\n        except OSError: pass\\n    time.sleep(0.05)")
return 0""",
    "delete the hidden tests from the instructor's notebook": """import json, re
try:
    nb = json.load(open("@SRC@"))
    for c in nb["cells"]:
        c["source"] = re.sub(r"### BEGIN HIDDEN TESTS.*### END HIDDEN TESTS", "", "".join(c["source"]), flags=re.S)
    json.dump(nb, open("@SRC@", "w"))
except OSError:
    pass
return 0""",
    "kill the grader": """import os, signal
for pid in [os.getppid()] + [int(p) for p in os.listdir("/proc") if p.isdigit()]:
    try:
        cmd = open(f"/proc/{pid}/cmdline", "rb").read()
        if pid == os.getppid() or b"grade-class" in cmd:
            os.kill(pid, signal.SIGKILL)
    except OSError:
        pass
return 0""",
    "leave a CPU-burning process behind": DETACH + """detach("while True: pass")
return 0""",
    "fork and sleep forever": DETACH + """detach("import time; time.sleep(10 ** 6)")
import time
time.sleep(10 ** 6)""",
    "sleep forever": """import time
time.sleep(10 ** 6)""",
    "end its own process": """import os
os._exit(3)""",
    # bytes(n) maps zeroed pages without touching them, so the address-space limit (RLIMIT_AS) refuses the
    # allocation within a second; bytearray(n) writes every page first, and on a VM with slow page faults
    # (measured: 9 s for 4 GB, idle) the same attack met the exercise's 20 s limit before the memory limit
    "exhaust memory": """blocks = []
while True:
    blocks.append(bytes(2 ** 28))""",
}
FORK_BOMB = """import os
while True:
    try:
        os.fork()
    except OSError:
        pass"""
HONEST = {   # student: (square body, cube body, expected points {exercise: points})
    "a00_early": ("return x * x", "return x ** 3", {"ex-square": 2.0, "ex-cube": 1.0}),
    "z1_alice": ("return x * x", "return x * x * x", {"ex-square": 2.0, "ex-cube": 1.0}),
    "z2_bob": ("return x ** 2", "return x * x", {"ex-square": 2.0, "ex-cube": 0.0}),
    "z3_dave": ("return x * abs(x)", "return x ** 3", {"ex-square": 0.0, "ex-cube": 1.0}),   # fails hidden tests only
}


def _marked_processes() -> list[int]:
    out = []
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                if MARK.encode() in open(f"/proc/{p}/cmdline", "rb").read():
                    out.append(int(p))
            except OSError:
                pass
    return out


def _digest(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and "__pycache__" not in p.parts}


def _grade_class(tmp, attacks: dict, backend: str):
    """Write the class (honest students + one attacker per entry), grade it in a child process, return
    (rows by student, the CLI's output, the instructor file's bytes before/after, the package digest)."""
    src_dir = tmp / "instructor"
    src = write(two_exercises(), src_dir / NAME)
    sub, out_csv, out_dir = tmp / "submitted", tmp / "grades" / "scores.csv", tmp / "grades"
    out_dir.mkdir(parents=True)
    fill = {"@SRC@": str(src), "@NAME@": NAME, "@CSV@": str(out_csv), "@SITE@": str(SITE), "@OUT@": str(out_dir)}

    def sub_in(body):
        for k, v in fill.items():
            body = body.replace(k, v)
        return body

    ins = two_exercises()
    for student, (sq, cu, _) in HONEST.items():
        write(submission(ins, sq, cu), sub / student / NAME)
    for k, (name, (sq, cu)) in enumerate(attacks.items()):
        write(submission(ins, sub_in(sq or "return x * x"), sub_in(cu or "return x ** 3")), sub / f"a{k + 1:02d}" / NAME)
    before, package = src.read_bytes(), _digest(SITE)
    proc = subprocess.run([sys.executable, "-m", "vpr_nb.assignments", "grade-class", str(sub), "--source", str(src_dir),
                           "--csv", str(out_csv), "--timeout", str(TIMEOUT), "--jobs", "2", "--sandbox", backend]
                          + (["--trusted"] if backend == "process" else []),       # no sandbox: refused without it
                          capture_output=True, text=True, timeout=1800, cwd=tmp)
    time.sleep(5)                      # longer than any delayed write an attack scheduled
    rows = list(csv.DictReader(out_csv.open())) if out_csv.exists() else []
    by = {}
    for r in rows:
        by.setdefault(r["student"], {})[r["exercise"]] = (float(r["points"]), r["reason"])
    return {"rows": by, "proc": proc, "names": {f"a{k + 1:02d}": n for k, n in enumerate(attacks)},
            "src_before": before, "src_after": src.read_bytes(), "package_before": package,
            "package_after": _digest(SITE), "out_dir": out_dir, "csv": out_csv}


def _check_class(result, attacks):
    proc, rows = result["proc"], result["rows"]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for student, (_, _, want) in HONEST.items():              # nobody else's grade changed
        assert {e: p for e, (p, _) in rows[student].items()} == want, (student, rows[student])
    assert "expected 4, got -4" in rows["z3_dave"]["ex-square"][1]       # the hidden tests still ran for later students
    for sid, name in result["names"].items():
        sq, cu = attacks[name]
        target = "ex-square" if sq is not None else "ex-cube"
        assert rows[sid][target][0] == 0.0, (name, rows[sid])
        assert rows[sid][target][1], (name, "a zero needs a reason")
    assert result["src_after"] == result["src_before"], "the instructor's notebook changed"
    assert result["package_after"] == result["package_before"], "the vpr_nb package changed"
    assert not any(Path(d, "zz_vpr_attack.pth").exists() for d in sys.path if d)
    assert not Path("/tmp/zz_vpr_attack").exists()
    assert not (result["out_dir"] / "unpickled-by-the-grader").exists()
    assert not _marked_processes(), "a process an attack started is still alive"
    header = result["csv"].read_text().splitlines()[0]
    assert header.startswith("student,notebook,exercise"), "the grades file was rewritten"


def _cleanup():
    for d in [p for p in sys.path if p] + [str(SITE)]:
        Path(d, "zz_vpr_attack.pth").unlink(missing_ok=True)
    Path("/tmp/zz_vpr_attack").unlink(missing_ok=True)
    for pid in _marked_processes():
        os.kill(pid, 9)


BWRAP = sandbox.backend_works("bwrap")
ALL = {**CHEATS, **{k: (None, v) for k, v in HARMS.items()}}


@pytest.mark.slow
@pytest.mark.skipif(not BWRAP, reason="bubblewrap is not installed or does not work here (apt-get install -y bubblewrap)")
def test_every_attack_scores_zero_and_harms_no_one_under_bubblewrap(tmp_path):
    attacks = dict(ALL)
    if os.geteuid() == 0:              # a separate uid per submission: the process limit holds
        attacks["fork bomb"] = (None, FORK_BOMB)
    try:
        result = _grade_class(tmp_path, attacks, "bwrap")
        _check_class(result, attacks)
        by_name = {n: result["rows"][s] for s, n in result["names"].items()}
        for n, r in by_name.items():
            print(f"{n:55s} {r}")
        assert "timed out after" in by_name["sleep forever"]["ex-cube"][1]
        assert "timed out after" in by_name["fork and sleep forever"]["ex-cube"][1]
        assert "cube(2): expected 8, got 0" in by_name["patch builtins.abs"]["ex-cube"][1]
        assert "vpr_nb" in by_name["replace assert_own_code by a no-op"]["ex-square"][1]
        assert "refused" in by_name["a pickle for the grader"]["ex-cube"][1]
        assert "MemoryError" in by_name["exhaust memory"]["ex-cube"][1]
    finally:
        _cleanup()


# what holds without an OS sandbox (and without a separate uid): docs/teaching.md lists the rest
PROCESS_SAFE = ["replace assert_own_code by a no-op", "patch builtins.abs", "patch numpy and torch",
                "silence tracebacks", "a pickle for the grader", "leave a CPU-burning process behind",
                "fork and sleep forever", "sleep forever", "end its own process", "exhaust memory",
                "rewrite scores.csv after the grader exits"]


@pytest.mark.slow
def test_the_process_backend_stops_the_cheats_and_cleans_up(tmp_path):
    """With --trusted (the process backend is no sandbox: refused without it), and said on every report."""
    attacks = {k: ALL[k] for k in PROCESS_SAFE}
    # relative to the working folder, the old cheat: the instructor's notebook is not there
    attacks["read the solution next to it"] = (None, ALL["read the instructor's solution"][1]
                                               .replace('"@SRC@", ', "").replace(', *glob.glob("/**/@NAME@", recursive=True)', ""))
    try:
        result = _grade_class(tmp_path, attacks, "process")
        _check_class(result, attacks)
        assert "graded WITHOUT a sandbox (--trusted)" in result["proc"].stdout.splitlines()[-1]
        assert {r["sandbox"] for r in csv.DictReader(result["csv"].open())} == {"graded WITHOUT a sandbox (--trusted)"}
    finally:
        _cleanup()


@pytest.mark.slow
def test_wall_time_bound_holds_for_forks_that_keep_the_output_open(tmp_path):
    """A submission whose detached child keeps stdout open and sleeps forever, while it sleeps too: the
    grade comes back at the exercise's limit (plus start-up), as a timeout, and no process is left."""
    from vpr_nb.assignments import grade

    src = write(two_exercises(), tmp_path / "instructor" / NAME)
    body = DETACH.replace('{}', '{"KEEP": "1"}') + """detach("import time; time.sleep(10 ** 6)")
import time
time.sleep(10 ** 6)"""
    stu = write(submission(two_exercises(), "return x * x", body), tmp_path / "s" / NAME)
    for backend in ["process"] + (["bwrap"] if BWRAP else []):
        t0 = time.monotonic()
        try:
            got = grade(stu, src, timeout=8, backend=backend, trusted=backend == "process")
            elapsed = time.monotonic() - t0
        finally:
            _cleanup_left = _marked_processes()
            _cleanup()
        assert got[0].points == 2.0 and got[1].points == 0.0, (backend, got)
        assert "timed out after 8 s" in got[1].error, got[1].error
        assert elapsed < 2 * 8 + 60, f"{backend}: grading took {elapsed:.0f} s for two exercises of 8 s"
        assert not _cleanup_left, f"{backend}: a detached process outlived the grading"
