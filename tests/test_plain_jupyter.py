"""The stored numbers in any Jupyter: a notebook pins its own CPU kernels (vpr_nb.kernels.pin_before_start).

A student who opens the notebooks in a plain ``jupyter lab``, a hub or VS Code starts a kernel without the
pinned environment that ``make lab`` and nbval's conftest give it. The notebooks import ``vpr_nb.notebook``
first, which pins the kernels from inside the process before numpy and torch start; where that is impossible,
``setup`` says so in one line."""
from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from vpr_nb import kernels
from vpr_nb.notebook import unpinned_note

ROOT = Path(__file__).resolve().parents[1]
X86 = platform.machine().lower() in ("x86_64", "amd64")


def _native_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in kernels.PINNED and k != kernels.NATIVE_ENV}
    env.update(extra)
    return env


def _python(code: str, env: dict) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.skipif(not X86, reason="the pins choose x86-64 kernels")
def test_importing_the_notebook_front_door_first_pins_the_process():
    code = ("import vpr_nb.notebook as nb, os, torch; from vpr_nb import kernels; "
            "print(nb.UNPINNED, kernels.is_pinned(), torch.backends.cpu.get_cpu_capability())")
    assert _python(code, _native_env()) == "None True AVX2"


def test_a_library_started_first_is_said_not_hidden():
    code = "import numpy; import vpr_nb.notebook as nb; print(nb.UNPINNED)"
    reason = _python(code, _native_env())
    assert reason == "numpy started before vpr_nb.notebook could pin the kernels" or not X86
    note = unpinned_note(reason)
    assert note.startswith("note: ") and f"up to {kernels.UNPINNED_DIFFERENCE} (Recall@N" in note and "\n" not in note
    if X86:
        assert "Restart the kernel" in note


def test_native_kernels_on_request_and_the_setup_line(tmp_path):
    code = ("import vpr_nb.notebook as nb; s = nb.setup('ci'); "
            "print(repr((nb.UNPINNED, s.pinned, s.tolerance)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env=_native_env(**{kernels.NATIVE_ENV: "1"}))
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[0].startswith("note: this kernel runs on its processor's own CPU kernels (VPR_NB_NATIVE_KERNELS=1")
    assert lines[-1] == repr(("VPR_NB_NATIVE_KERNELS=1 asks for the processor's own kernels", False,
                              kernels.UNPINNED_DIFFERENCE))


def test_every_notebook_imports_the_front_door_before_numpy():
    for py in sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.py")):
        lines = py.read_text().splitlines()
        first = next(i for i, line in enumerate(lines) if line.startswith(("import ", "from ")))
        assert lines[first].startswith("import vpr_nb.notebook"), f"{py.name}: first import is {lines[first]!r}"


@pytest.mark.slow
@pytest.mark.skipif(not X86 or os.environ.get("VPR_NB_SKIP_SLOW_NOTEBOOK") == "1",
                    reason="the stored outputs were recorded with the x86-64 pins")
def test_a_notebook_in_a_plain_kernel_reproduces_its_stored_outputs():
    """Notebook 02 trains a small CNN from scratch (the numbers most sensitive to the kernels), run by nbval in a
    kernel whose environment has none of the pins and without the notebooks' conftest (which would pin it):
    every output must equal the stored one exactly."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--noconftest", "--nbval",
           "--nbval-current-env", "--nbval-sanitize-with", "notebooks/sanitize.cfg", "--nbval-cell-timeout", "600",
           "notebooks/02_triplet_baseline.ipynb"]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=_native_env(), timeout=1200)
    assert out.returncode == 0, out.stdout[-4000:]
