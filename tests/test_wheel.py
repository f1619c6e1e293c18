"""The wheel, installed as Binder, Colab or `pip install .` install it: not editable, used from any folder.

The wheel is built from a copy of the working tree (so nothing is written into the repository) and
installed with ``--no-deps`` into a fresh venv. Installing torch, numpy, JupyterLab & co. into that venv
would cost minutes and GBs, so the fresh venv borrows them from the running environment instead: a
``.pth`` file in its site-packages lists this environment's site-packages folders. Python only *adds*
the folders a ``.pth`` line names to ``sys.path``, after the venv's own site-packages; it does not run
the ``.pth`` files inside them, so the editable install of ``vpr_nb`` (``__editable__*.pth`` and its
import finder, in this environment's site-packages) is never activated, and the wheel's ``vpr_nb``,
found first, is the one imported. The notebook checks exactly that before anything else.
"""
import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _copy_worktree(dst: Path) -> None:
    """The files git tracks or would track (committed or not, ignored ones left out) copied to ``dst``."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs a git checkout to list the project's files")
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, check=True).stdout
    for name in filter(None, out.decode().split("\0")):
        src = ROOT / name
        if src.is_file():                 # a file deleted in the working tree is still in the index
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / name)


def _notebook(purelib: Path, names: list[str]):
    cells = [
        f"""\
        import sys
        from pathlib import Path
        import vpr_nb
        from vpr_nb import package_data
        PURELIB = Path({str(purelib)!r})
        print("vpr_nb from", Path(vpr_nb.__file__).parent.relative_to(PURELIB), "of the fresh venv")
        assert Path(vpr_nb.__file__).resolve().is_relative_to(PURELIB.resolve()), vpr_nb.__file__
        assert not any("editable" in type(f).__module__ for f in sys.meta_path), sys.meta_path
        assert package_data.checkout_root() is None""",
        """\
        from vpr_nb.pretrain import CHECKPOINT, card, course_backbone
        backbone = course_backbone(trainable_blocks=1)
        assert CHECKPOINT.resolve().is_relative_to(PURELIB.resolve()), CHECKPOINT
        print("course backbone", card()["sha256"][:12], sum(p.numel() for p in backbone.parameters()), "parameters")""",
        f"""\
        import json
        from vpr_nb import results
        folder = package_data.committed_results_dir()
        assert folder.resolve().is_relative_to(PURELIB.resolve()), folder
        names = sorted(p.stem for p in folder.glob("*.json"))
        assert names == {names!r}, names
        for name in names:        # the committed config, so load() checks the file and the backbone fingerprint
            doc = results.load(name, json.loads((folder / f"{{name}}.json").read_text())["config"])
            print(name, "committed", doc["stamp"]["date"])
            for entry in doc["results"].get("trained weights", {{}}).values():   # installed beside it
                assert (folder / entry["file"]).stat().st_size == entry["bytes"], entry["file"]""",
        """\
        try:
            results.save("99_demo", {"epochs": 1}, {"R@1": 0.5})
        except ValueError as e:
            assert "VPR_NB_RESULTS_DIR" in str(e) and "not run from a clone" in str(e), e
            print("save refused:", str(e)[:40])
        else:
            raise AssertionError("an installed vpr_nb wrote reproduce results into site-packages")""",
    ]
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell(textwrap.dedent(c)) for c in cells]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"}
    return nb


@pytest.mark.slow
def test_the_wheel_carries_the_backbone_and_results_and_runs_a_notebook_from_any_folder(tmp_path):
    src, dist, venv, work = (tmp_path / d for d in ("src", "dist", "venv", "work"))
    _copy_worktree(src)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(dist),
                    str(src)], check=True, cwd=tmp_path)
    (wheel,) = dist.glob("vpr_nb-*.whl")

    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    purelib = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", "--no-index",
                    str(wheel)], check=True)
    ours = [p for p in dict.fromkeys(site.getsitepackages() + [sysconfig.get_paths()["purelib"]]) if Path(p).is_dir()]
    (purelib / "borrowed_dependencies.pth").write_text("".join(f"{p}\n" for p in ours))

    # a kernelspec that runs the fresh venv's python, first on JUPYTER_PATH (no other python3 kernel is found)
    kernels = tmp_path / "jupyter" / "kernels" / "python3"
    kernels.mkdir(parents=True)
    (kernels / "kernel.json").write_text(json.dumps({
        "argv": [str(py), "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (ipykernel)", "language": "python"}))
    names = sorted(p.stem for p in (ROOT / "notebooks" / "results").glob("*.json"))
    work.mkdir()
    nbformat.write(_notebook(purelib, names), work / "installed.ipynb")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VPR_NB_RESULTS_DIR", "JUPYTER_PATH")}
    env.update(JUPYTER_PATH=str(tmp_path / "jupyter"), MPLBACKEND="Agg")
    run = subprocess.run([str(py), "-c", textwrap.dedent("""\
        import nbformat, sys
        from nbclient import NotebookClient
        nb = nbformat.read("installed.ipynb", as_version=4)
        NotebookClient(nb, timeout=300, kernel_name="python3").execute()
        for cell in nb.cells:
            for out in cell.outputs:
                sys.stdout.write(out.get("text", ""))
        """)], cwd=work, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "vpr_nb from vpr_nb of the fresh venv" in run.stdout and "save refused" in run.stdout, run.stdout
    assert all(f"{name} committed" in run.stdout for name in names), run.stdout

    # the commands: python -m vpr_nb lists them, the console scripts run, vpr-pretrain keeps the installed weights
    listing = subprocess.run([str(py), "-m", "vpr_nb"], cwd=work, env=env, capture_output=True, text=True, check=True)
    assert all(s in listing.stdout for s in ("vpr-train", "vpr-evaluate", "vpr-pretrain")), listing.stdout
    for script in ("vpr-train", "vpr-evaluate", "vpr-pretrain"):
        helped = subprocess.run([str(venv / "bin" / script), "--help"], cwd=work, env=env, capture_output=True, text=True)
        assert helped.returncode == 0 and "usage" in helped.stdout, (script, helped.stdout, helped.stderr)
    refused = subprocess.run([str(venv / "bin" / "vpr-pretrain")], cwd=work, env=env, capture_output=True, text=True)
    assert refused.returncode == 2 and "--out is required" in refused.stderr, refused.stderr
