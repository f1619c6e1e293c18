"""vpr_nb.kernels: the pinned CPU kernels that make trained numbers the same on every x86-64 machine."""
import os
import platform
import subprocess
import sys

import pytest
import torch

from vpr_nb import kernels
from vpr_nb.training import TrainConfig, make_optimizer

# The fingerprint of the pinned kernels with torch 2.13.0 on x86-64, recorded on an AMD EPYC with convolutions
# through neither oneDNN nor NNPACK. (On an Intel Xeon the native kernels trained other NetVLAD and SALAD rows; the
# pinned ones gave the same bits as the EPYC while oneDNN still ran the convolutions, and the convolutions' own
# hashes without oneDNN were equal on both; this configuration has not been run there yet.)
PINNED_FINGERPRINT = {"render": "c36f5ce5cd2919bf", "features": "3353aa044943d204", "kmeans": "e385dd85c75faf86",
                      "search": "8f99548501f57c5e", "netvlad": "51539dd49d2ce43f", "salad": "b2880f0f1e55b9c6"}
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
    assert got == PINNED_FINGERPRINT, (
        f"the pinned CPU kernels give other numbers on this machine ({kernels.processor_name()}): {got}; "
        f"the notebooks' stored trained numbers will differ here")


def test_pinned_maps_and_descriptors_do_not_depend_on_the_batch_or_the_threads():
    # no NNPACK and no oneDNN: a convolution is an unfold and one product per image, the 1x1 layers one product
    # over rows (vpr_nb.pointwise), so an image's map is the same bits in a batch of 1 or of 112
    from vpr_nb.models import build_model
    from vpr_nb.pretrain import course_backbone

    assert not torch._C._get_nnpack_enabled() and not torch.backends.mkldnn.enabled
    x = torch.rand(112, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    threads = torch.get_num_threads()
    try:
        for aggregator in ("netvlad", "gem", "salad"):
            model = build_model(course_backbone(trainable_blocks=1), aggregator).eval()
            with torch.no_grad():
                torch.set_num_threads(1)
                maps, full = model.backbone(x), model(x)
                for b in (1, 5, 16):
                    assert torch.equal(torch.cat([model.backbone(x[i:i + b]) for i in range(0, 112, b)]), maps)
                    if aggregator != "salad":     # SALAD's token MLP is an MKL product over the batch's tokens
                        assert torch.equal(torch.cat([model(x[i:i + b]) for i in range(0, 112, b)]), full)
                torch.set_num_threads(2)
                assert torch.equal(model(x), full), aggregator
    finally:
        torch.set_num_threads(threads)


def test_l1d_per_thread_reads_sysfs(tmp_path):
    def cache(index, level, kind, size, shared):
        d = tmp_path / "cache" / f"index{index}"
        d.mkdir(parents=True)
        for name, value in (("level", level), ("type", kind), ("size", size), ("shared_cpu_list", shared)):
            (d / name).write_text(value + "\n")

    cache(0, "1", "Instruction", "32K", "0,8")
    cache(1, "1", "Data", "32K", "0,8")          # 32 KiB shared by two hyper-threads
    cache(2, "2", "Unified", "1024K", "0,8")
    assert kernels.l1d_per_thread(str(tmp_path)) == 16 * 1024
    (tmp_path / "cache" / "index1" / "size").write_text("48K\n")
    (tmp_path / "cache" / "index1" / "shared_cpu_list").write_text("0-1\n")
    assert kernels.l1d_per_thread(str(tmp_path)) == 24 * 1024
    (tmp_path / "cache" / "index1" / "size").write_text("garbage\n")
    assert kernels.l1d_per_thread(str(tmp_path)) is None
    assert kernels.l1d_per_thread(str(tmp_path / "missing")) is None
