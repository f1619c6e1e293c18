"""vpr_nb.kernels: the pinned CPU kernels that make trained numbers the same on every x86-64 machine."""
import os
import platform
import subprocess
import sys

import pytest
import torch

from vpr_nb import kernels
from vpr_nb.training import TrainConfig, make_optimizer

# The fingerprint of the pinned kernels with torch 2.13.0 on x86-64, recorded on an AMD EPYC. (On an Intel Xeon the
# native kernels trained other NetVLAD and SALAD rows; the pinned ones gave these rows' bits while oneDNN still
# ran the convolutions, and the convolutions' own hashes without oneDNN were equal on both.)
PINNED_FINGERPRINT = {"render": "c36f5ce5cd2919bf", "features": "c8812f8c02abb5d2", "kmeans": "e596a08891f84160",
                      "search": "8445c3bda879edef", "netvlad": "ea8c15eab8db26bb", "salad": "4025595ba05635fd"}
FINGERPRINT_BACKBONE = "b561b563a1cbb616cc1bb3813e113de089ea41b5119b884ba0ec5840e5c662eb"   # its card's sha256


def _python(code, env):
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                          timeout=300).stdout


def test_pinned_environ_adds_the_pins_and_leaves_the_base_alone():
    base = {"PATH": "/bin", "MKL_CBWR": "AVX512"}
    env = kernels.pinned_environ(base)
    assert env["PATH"] == "/bin" and all(env[k] == v for k, v in kernels.PINNED.items())
    assert base == {"PATH": "/bin", "MKL_CBWR": "AVX512"}
    assert kernels.is_pinned(env) and not kernels.is_pinned(base)
    with pytest.raises(ValueError, match="mapping of environment variables"):
        kernels.pinned_environ(["MKL_CBWR=COMPATIBLE"])


def test_the_test_session_runs_pinned():
    # tests/conftest.py pins before torch starts, so the pinned numbers of the tests are the notebooks' numbers
    assert kernels.is_pinned()
    # conftest.py also applies the in-process part of the pins, as every front door does (vpr_nb.kernels)

    assert not torch.backends.mkldnn.enabled
    if platform.machine() == "x86_64" and torch.backends.cpu.get_cpu_capability() != "DEFAULT":
        assert torch.backends.cpu.get_cpu_capability() == "AVX2"


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the pins choose x86-64 kernels")
def test_a_child_started_with_the_pinned_environment_uses_the_avx2_kernels():
    native = {k: v for k, v in os.environ.items() if k not in kernels.PINNED}
    code = "import torch; print(torch.backends.cpu.get_cpu_capability())"
    assert _python(code, kernels.pinned_environ(native)).strip() == "AVX2"


def test_adam_runs_the_fused_update_sgd_the_plain_one():
    model = torch.nn.Linear(3, 2)
    for name in ("adam", "adamw"):
        assert make_optimizer(model, TrainConfig(optimizer=name, lr=1e-3)).defaults["fused"] is True
    assert not make_optimizer(model, TrainConfig(optimizer="sgd")).defaults.get("fused")


def test_cli_errors_are_one_line_and_exit_2(capsys):
    assert kernels.main(["--run"]) == 2
    assert capsys.readouterr().err.startswith("error: --run needs a command")
    assert kernels.main(["--run", "/no/such/program"]) == 2
    assert capsys.readouterr().err.startswith("error: cannot run '/no/such/program'")
    from vpr_nb import fingerprint

    assert fingerprint.main(["--steps", "0"]) == 2
    assert capsys.readouterr().err.startswith("error: --steps must be at least 1")
    assert kernels.main(["--env"]) == 0
    assert capsys.readouterr().out.splitlines() == [f"{k}={v}" for k, v in kernels.PINNED.items()]


def test_run_starts_the_command_in_the_pinned_environment():
    out = subprocess.run([sys.executable, "-m", "vpr_nb.kernels", "--run", sys.executable, "-c",
                          "import os; print(os.environ['MKL_CBWR'], os.environ['ATEN_CPU_CAPABILITY'])"],
                         env={k: v for k, v in os.environ.items() if k not in kernels.PINNED},
                         capture_output=True, text=True, check=True, timeout=120).stdout
    assert out.split() == ["COMPATIBLE", "avx2"]


@pytest.mark.skipif(platform.machine() != "x86_64" or torch.__version__ != "2.13.0+cpu",
                    reason="the fingerprint was recorded with torch 2.13.0+cpu on x86-64")
def test_the_pinned_fingerprint_is_the_recorded_one():
    # fails where this machine's pinned kernels compute other bits than the recording's: nbval's trained numbers
    # would then differ from the stored outputs too, and this says why
    from vpr_nb.pretrain import card

    assert card()["sha256"] == FINGERPRINT_BACKBONE, "the course backbone changed: re-record PINNED_FINGERPRINT"
    code = "from vpr_nb.fingerprint import fingerprint; import json; print(json.dumps(fingerprint()))"
    import json

    got = json.loads(_python(code, kernels.pinned_environ()).strip().splitlines()[-1])
    l1d = kernels.l1d_per_thread()
    hint = ("" if l1d is None or l1d >= kernels.NNPACK_ONE_BLOCK_L1D else
            f"; this processor has {l1d // 1024} KiB of L1 data cache per hardware thread, so NNPACK sums the "
            f"backbone's 1x1 projection in two blocks (vpr_nb.kernels.apply_in_process)")
    assert got == PINNED_FINGERPRINT, (
        f"the pinned CPU kernels give other numbers on this machine ({kernels.processor_name()}): {got}; "
        f"the notebooks' stored trained numbers will differ here{hint}")


def test_l1d_per_thread_reads_sysfs(tmp_path):
    def cache(index, level, kind, size, shared):
        d = tmp_path / "cache" / f"index{index}"
        d.mkdir(parents=True)
        for name, value in (("level", level), ("type", kind), ("size", size), ("shared_cpu_list", shared)):
            (d / name).write_text(value + "\n")

    cache(0, "1", "Instruction", "32K", "0,8")
    cache(1, "1", "Data", "32K", "0,8")          # 32 KiB shared by two hyper-threads: NNPACK's two blocks
    cache(2, "2", "Unified", "1024K", "0,8")
    assert kernels.l1d_per_thread(str(tmp_path)) == 16 * 1024 < kernels.NNPACK_ONE_BLOCK_L1D
    (tmp_path / "cache" / "index1" / "size").write_text("48K\n")
    (tmp_path / "cache" / "index1" / "shared_cpu_list").write_text("0-1\n")
    assert kernels.l1d_per_thread(str(tmp_path)) == kernels.NNPACK_ONE_BLOCK_L1D
    (tmp_path / "cache" / "index1" / "size").write_text("garbage\n")
    assert kernels.l1d_per_thread(str(tmp_path)) is None
    assert kernels.l1d_per_thread(str(tmp_path / "missing")) is None
