"""Grading isolates or refuses (vpr_nb.grading.isolation, vpr_nb.grading.sandbox, vpr_nb.grading.owncode).

Without bubblewrap an untrusted submission is not graded: one ``error:`` line and exit 2 from the CLI,
:class:`NoSandboxError` from Python; ``--trusted`` grades it without a sandbox and every report says so.
In bubblewrap a submission reads no instructor file (not even one under a folder the sandbox shows) and
writes nowhere but its own folder. numpy's and torch's file functions break the own-code rule.
"""
import csv
import os
import shutil
import subprocess
import sys
import tempfile
import types
from pathlib import Path

import pytest
from grading_fixtures import NAME, submission, two_exercises, write

from vpr_nb.assignments import (BEGIN_HIDDEN, NO_SANDBOX, NoSandboxError, grade, grade_class, is_solution, main,
                                student_version)
from vpr_nb.grading import isolation, sandbox
from vpr_nb.grading.exercise import Source, grade_exercise
from vpr_nb.grading.owncode import source_violations
from vpr_nb.package_data import RESULTS_DIR_ENV

BWRAP = sandbox.backend_works("bwrap")
needs_bwrap = pytest.mark.skipif(not BWRAP, reason="bubblewrap is not installed or does not work here, so the "
                                 "sandbox cannot be tested (apt-get install -y bubblewrap; .ci/run installs it)")
SITE = Path(sandbox.__file__).resolve().parents[1]           # the vpr_nb package folder, shown read-only
SECRET = "answer-key-7c1e9b"                                 # only in the instructor notebook
TRUSTED = "graded WITHOUT a sandbox (--trusted)"


def _instructor():
    """two_exercises with SECRET in the cube solution and in the cube's hidden tests (the answer key)."""
    nb = two_exercises()
    sol = next(c for c in nb.cells if is_solution(c) and c.metadata["nbgrader"]["grade_id"] == "ex-cube")
    sol.source = sol.source.replace("return x ** 3", f"return x ** 3  # {SECRET}")
    nb.cells[-1].source = nb.cells[-1].source.replace(BEGIN_HIDDEN, f"{BEGIN_HIDDEN}\n# {SECRET}")
    return nb


def _class(root: Path, attacks: dict) -> dict:
    """The instructor notebook, an honest student and one attacker per entry (a cube cell; @SRC@ etc. filled)
    under ``root``; returns the paths."""
    paths = {"src_dir": root / "instructor", "sub": root / "submitted", "csv": root / "grades" / "scores.csv",
             "out": root / "outside"}
    paths["src"] = write(_instructor(), paths["src_dir"] / NAME)
    paths["out"].mkdir(parents=True)
    paths["csv"].parent.mkdir(parents=True)
    honest = write(submission(_instructor()), paths["sub"] / "a00_honest" / NAME)
    fill = {"@SRC@": str(paths["src"]), "@OUT@": str(paths["out"]), "@SUB@": str(paths["sub"]),
            "@CSVDIR@": str(paths["csv"].parent), "@SITE@": str(SITE), "@HONEST@": str(honest)}
    paths["students"] = {}
    for k, (name, body) in enumerate(attacks.items()):
        student = f"a{k + 1:02d}"
        for key, value in {**fill, "@ME@": student}.items():
            body = body.replace(key, value)
        write(submission(_instructor(), "return x * x", body), paths["sub"] / student / NAME)
        paths["students"][name] = student
    assert SECRET not in (paths["sub"] / "a00_honest" / NAME).read_text()   # the student version has no key
    return paths


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def _rows(csv_path: Path) -> dict:
    by: dict = {}
    for r in csv.DictReader(csv_path.open()):
        by.setdefault(r["student"], {})[r["exercise"]] = (float(r["points"]), r["reason"], r["sandbox"])
    return by


# --- without bubblewrap: refused, or --trusted and said on every report -----------------------------------

@pytest.fixture
def no_bwrap(monkeypatch):
    """This machine as a fresh Debian without bubblewrap (the grader's probe finds no bwrap)."""
    monkeypatch.delenv(sandbox.ENV_BACKEND, raising=False)
    monkeypatch.setattr(isolation, "backend_works", lambda backend: backend == "process")
    monkeypatch.setattr(isolation, "shutil", types.SimpleNamespace(which=lambda name: None))


def test_without_bubblewrap_grading_refuses_untrusted_work_with_one_line(tmp_path, no_bwrap, capsys):
    p = _class(tmp_path, {})
    stu = p["sub"] / "a00_honest" / NAME
    want = f"error: {NO_SANDBOX}\n"
    assert want == ("error: no sandbox for untrusted submissions: install bubblewrap (apt-get install bubblewrap) "
                    "or pass --trusted for work you trust\n")
    for argv in (["grade", str(stu), "--source", str(p["src"])],
                 ["grade", str(stu), "--source", str(p["src"]), "--sandbox", "process"],   # no sandbox either
                 ["grade-class", str(p["sub"]), "--source", str(p["src_dir"]), "--csv", str(p["csv"])]):
        assert main(argv) == 2, argv
        out, err = capsys.readouterr()
        assert (out, err) == ("", want), argv
    assert not p["csv"].exists(), "nothing is graded, no grades file written"
    with pytest.raises(NoSandboxError, match="install bubblewrap"):
        grade(stu, p["src"])
    with pytest.raises(NoSandboxError, match="install bubblewrap"):
        grade_class(p["sub"], p["src_dir"], p["csv"], log=lambda *_: None)
    with pytest.raises(NoSandboxError, match="install bubblewrap"):
        grade(stu, p["src"], backend="process")
    source = Source.read(p["src"])
    with pytest.raises(NoSandboxError):
        grade_exercise(source.exercises[0], student_version(_instructor()), b"", sandbox.Limits(), "process")


def test_a_fresh_machine_without_bwrap_on_its_path_is_refused_by_the_cli(tmp_path):
    """The real probe, in a child process whose PATH has no bwrap."""
    p = _class(tmp_path, {})
    (tmp_path / "empty_bin").mkdir()
    env = {k: v for k, v in os.environ.items() if k != sandbox.ENV_BACKEND}
    env["PATH"] = str(tmp_path / "empty_bin")
    for cmd in (["grade", str(p["sub"] / "a00_honest" / NAME), "--source", str(p["src"])],
                ["grade-class", str(p["sub"]), "--source", str(p["src_dir"]), "--csv", str(p["csv"])]):
        proc = subprocess.run([sys.executable, "-m", "vpr_nb.assignments", *cmd], capture_output=True, text=True,
                              env=env, cwd=tmp_path, timeout=300)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert proc.stderr == f"error: {NO_SANDBOX}\n" and proc.stdout == "", (proc.stdout, proc.stderr)
    assert not p["csv"].exists()


@pytest.mark.slow
def test_trusted_grades_without_a_sandbox_and_every_report_says_so(tmp_path, no_bwrap, capsys):
    p = _class(tmp_path, {})
    stu = p["sub"] / "a00_honest" / NAME
    assert main(["grade", str(stu), "--source", str(p["src"]), "--trusted"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"sandbox: {TRUSTED}") and out[-1].endswith(f"3 / 3  ({TRUSTED})"), out
    assert main(["grade-class", str(p["sub"]), "--source", str(p["src_dir"]), "--csv", str(p["csv"]), "--trusted"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"sandbox: {TRUSTED}") and out[-1].endswith(f"; {TRUSTED}"), out
    rows = _rows(p["csv"])
    assert rows == {"a00_honest": {"ex-square": (2.0, "", TRUSTED), "ex-cube": (1.0, "", TRUSTED)}}
    assert [g.backend for g in grade(stu, p["src"], trusted=True, only=["ex-square"])] == ["process"]


# --- in bubblewrap: no instructor file readable, no write outside its folder --------------------------------

FROMFILE = """@cell
import json
import numpy as np
def cube(x):
    raw = np.fromfile("@SRC@", dtype=np.uint8)
    try:
        raw.tofile("@OUT@/copied-by-tofile.ipynb")               # the hidden tests, copied out
    except OSError:
        pass
    nb = json.loads(raw.tobytes().decode())
    ns = {}
    exec("".join(next(c["source"] for c in nb["cells"] if "def cube" in "".join(c["source"]))), ns)
    return ns["cube"](x)"""
OPEN_RAISE = """@cell
def cube(x):
    text = open("@SRC@").read()
    raise ValueError(" | ".join(text[i:i + 300] for i in (text.index("def cube"), text.index("BEGIN HIDDEN"))))"""
OPEN_PRINT = """@cell
import os
import sys
def cube(x):
    text = open("@SRC@").read()
    sys.stdout.write(text[text.index("def cube"):][:300] + text[text.index("BEGIN HIDDEN"):][:300])
    sys.stdout.flush()
    os._exit(1)"""
SAVETXT = """@cell
import numpy as np
def cube(x):
    np.savetxt("/tmp/vpr-nb-@ME@-scratch.txt", [x])       # its private /tmp: allowed, never on the machine
    np.savetxt("@TARGET@", [x])
    return x ** 3"""
PROBE = """@cell
import os
def cube(x):
    seen = [p for p in ["@SRC@", "@HONEST@", "@CSVDIR@/scores.csv"] if os.path.exists(p)]
    seen += [d for d in ["@SRC_DIR@", "@SUB@", "@CSVDIR@", "@OUT@"] if os.path.isdir(d) and os.listdir(d)]
    if seen:
        raise ValueError(f"visible: {seen}")
    return x ** 3"""
WRITES = {"savetxt into another folder": "@OUT@/savetxt.txt", "savetxt into the class folder": "@SUB@/savetxt.txt",
          "savetxt into its own submission folder": "@SUB@/@ME@/savetxt.txt",
          "savetxt next to the grades file": "@CSVDIR@/savetxt.txt", "savetxt into the package": "@SITE@/zz_savetxt.txt"}
ATTACKS = {"np.fromfile the instructor notebook, .tofile it out": FROMFILE,
           "open().read() the instructor notebook, raise it": OPEN_RAISE,
           "open().read() the instructor notebook, print it and exit": OPEN_PRINT,
           **{name: SAVETXT.replace("@TARGET@", target) for name, target in WRITES.items()}}


def _grade_attacked_class(root: Path, capsys) -> tuple[dict, dict, str]:
    attacks = {**ATTACKS, "probe": PROBE.replace("@SRC_DIR@", str(root / "instructor"))}
    p = _class(root, attacks)
    before, src_bytes = _files(root), p["src"].read_bytes()
    try:
        rc = main(["grade-class", str(p["sub"]), "--source", str(p["src_dir"]), "--csv", str(p["csv"]),
                   "--timeout", "60", "--jobs", "2"])
        out, err = capsys.readouterr()
        assert rc == 0, out + err
        rows = _rows(p["csv"])
        assert rows["a00_honest"] == {"ex-square": (2.0, "", "bubblewrap"), "ex-cube": (1.0, "", "bubblewrap")}
        assert rows[p["students"]["probe"]]["ex-cube"][:2] == (1.0, ""), "an instructor or class file is visible"
        for name in ATTACKS:
            points, reason, _ = rows[p["students"][name]]["ex-cube"]
            assert points == 0.0 and reason, (name, reason)
        assert SECRET not in out + err + p["csv"].read_text(), "the answer key reached a report"
        assert _files(root) - before == {p["csv"]}, "a file appeared outside the submissions' folders"
        assert p["src"].read_bytes() == src_bytes
        assert not (SITE / "zz_savetxt.txt").exists()
        assert not list(Path("/tmp").glob("vpr-nb-a*-scratch.txt")), "the private /tmp reached the machine's"
        return p, rows, out
    finally:
        (SITE / "zz_savetxt.txt").unlink(missing_ok=True)
        for f in Path("/tmp").glob("vpr-nb-a*-scratch.txt"):
            f.unlink()


@pytest.mark.slow
@needs_bwrap
def test_in_bubblewrap_a_submission_reads_no_instructor_file_and_writes_only_its_own_folder(tmp_path, capsys):
    p, rows, _ = _grade_attacked_class(tmp_path, capsys)
    reason = rows[p["students"]["np.fromfile the instructor notebook, .tofile it out"]]["ex-cube"][1]
    assert "No such file or directory" in reason, reason
    reason = rows[p["students"]["savetxt into the package"]]["ex-cube"][1]
    assert "Read-only file system" in reason, reason
    # one notebook, graded alone: the same
    stu = p["sub"] / p["students"]["np.fromfile the instructor notebook, .tofile it out"] / NAME
    assert main(["grade", str(stu), "--source", str(p["src"])]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[-1].split() == ["total", "2", "/", "3"] and SECRET not in out, out
    assert not (p["out"] / "copied-by-tofile.ipynb").exists()


@pytest.fixture
def shown_folder(monkeypatch):
    """A folder outside /tmp that the sandbox shows read-only (the committed results, ``VPR_NB_RESULTS_DIR``),
    readable by every user as a checkout's folders are (a submission may run under its own user id)."""
    base = Path("/var/tmp")
    if not (base.is_dir() and os.access(base, os.W_OK)):
        pytest.skip("/var/tmp is not writable here")
    folder = Path(tempfile.mkdtemp(prefix="vpr_nb_shown_", dir=base)).resolve()
    folder.chmod(0o755)
    monkeypatch.setenv(RESULTS_DIR_ENV, str(folder))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.slow
@needs_bwrap
def test_in_bubblewrap_teacher_files_under_a_folder_the_sandbox_shows_are_covered(shown_folder, capsys):
    """The instructor notebooks, the class and the grades inside the (read-only, visible) results folder."""
    assert shown_folder in sandbox._shown()
    _grade_attacked_class(shown_folder, capsys)


def test_private_paths_under_a_shown_folder_are_covered_or_refused(tmp_path, monkeypatch):
    shown = tmp_path / "shown"
    monkeypatch.setenv(RESULTS_DIR_ENV, str(shown))
    notebook = write(_instructor(), shown / "instructor" / NAME)
    (shown / "submitted").mkdir()
    (tmp_path / "elsewhere").mkdir()
    args = sandbox._bwrap_args(tmp_path / "work", None, private=[notebook, shown / "submitted", tmp_path / "elsewhere"])
    joined = " ".join(args)
    assert f"--ro-bind /dev/null {notebook}" in joined and f"--tmpfs {shown / 'submitted'}" in joined
    assert "elsewhere" not in joined
    assert joined.index(f"--ro-bind {shown} {shown}") < joined.index(f"--tmpfs {shown / 'submitted'}")
    assert joined.index("--tmpfs /tmp ") < joined.index(f"--ro-bind {shown} {shown}"), "/tmp hides the results"
    folder_first = sandbox._bwrap_args(tmp_path / "work", None, private=[notebook, notebook.parent])
    assert f"--tmpfs {notebook.parent}" in " ".join(folder_first) and "/dev/null" not in folder_first
    with pytest.raises(ValueError, match="would be visible to every submission"):
        sandbox.check_private([shown])                # e.g. --csv into the results folder itself


# --- the own-code rule: numpy's and torch's file functions are file access ------------------------------------

FILE_IO = {
    "numpy binary": ["np.fromfile('/x', dtype=np.uint8)", "np.zeros(3).tofile('/x')", "np.memmap('/x')",
                     "np.lib.format.open_memmap('/x')"],
    "numpy text": ["np.savetxt('/x', [1])", "np.loadtxt('/x')", "np.genfromtxt('/x')", "np.fromregex('/x', 'a', 'f')"],
    "numpy npy and npz": ["np.save('/x', 1)", "np.load('/x')", "np.savez('/x', a=1)", "np.savez_compressed('/x', a=1)",
                          "np.zeros(1).dump('/x')", "np.lib.npyio.DataSource().open('/x')"],
    "torch": ["torch.save(1, '/x')", "torch.load('/x')", "torch.from_file('/x')", "torch.UntypedStorage.from_file('/x')",
              "torch.jit.load('/x')", "torch.serialization.load('/x')"],
    "imported by name": ["from numpy import fromfile", "from numpy import savetxt as keep", "from torch import save",
                         "from numpy.lib.npyio import loadtxt", "from numpy import *"],
}


@pytest.mark.parametrize("family", sorted(FILE_IO))
def test_the_own_code_rule_counts_numpy_and_torch_file_functions_as_file_access(family):
    for line in FILE_IO[family]:
        src = f"import numpy as np\nimport torch\ndef f(x):\n    {line}\n    return x" if "import" not in line else \
            f"{line}\ndef f(x):\n    return x"
        found = source_violations([src])
        assert found, line
        assert any("accesses files" in v or "imports *" in v for v in found), (line, found)
    plain = "import numpy as np\nimport torch\ndef f(x):\n    return np.frombuffer(np.asarray(x).tobytes()).sum() + len('{}'.format(x))"
    assert source_violations([plain]) == []


def test_a_solution_that_writes_with_numpy_scores_zero_by_the_rule_before_it_runs(tmp_path):
    """square has the own-code rule: the file function is refused on the source, so nothing runs (no sandbox
    run at all, and no file written, with or without bubblewrap)."""
    src = write(_instructor(), tmp_path / "instructor" / NAME)
    target = tmp_path / "written.txt"
    body = f"import numpy as np\nnp.savetxt({str(target)!r}, [x])\nreturn x * x"
    stu = write(submission(_instructor(), body), tmp_path / "s" / NAME)
    got = grade(stu, src, only=["ex-square"], trusted=True)
    assert got[0].points == 0.0 and "uses .savetxt, which accesses files (line 3)" in got[0].error, got[0].error
    assert not target.exists()
