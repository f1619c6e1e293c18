"""Which CPU kernels compute the course's numbers, pinned so that every x86-64 machine computes the same floats.

torch, numpy and faiss pick their CPU kernels when they start, by what the processor offers: torch's
vectorised ATen loops (AVX2 or AVX-512), oneDNN's convolutions, MKL's matrix products and vector maths
(``exp``, ``log``, ``sqrt`` of whole tensors: other code on Intel than on AMD processors) and faiss's distance
loops. Each choice rounds a little differently, and a few hundred training steps turn a last-bit difference
into another Recall@1 (notebook 05's CI profile, one SALAD row: R@1 0.437 with the native kernels of an
AVX-512 AMD processor, 0.330 with oneDNN limited to AVX2, 0.337 with MKL in its AVX2 reproducible mode).

Stored notebook outputs are compared exactly (nbval) and committed results should be what any machine
reproduces, so the course runs its notebooks (``make test``'s nbval, :mod:`vpr_nb.authoring`,
:mod:`vpr_nb.report`, ``make lab``, ``make pretrain``) with :data:`PINNED`: every library limited to AVX2
kernels (any x86-64 processor since 2013 has them) and MKL in its conditional-numerical-reproducibility
mode ``COMPATIBLE`` (the same code on Intel and AMD). The optimiser's update runs in torch's fused kernel
(:func:`vpr_nb.training.make_optimizer`), whose square root is the processor's exact one, not MKL's.

Measured with :func:`vpr_nb.fingerprint.fingerprint` (six Adam steps of NetVLAD and of SALAD fine-tuning) on an AMD EPYC
(AVX-512) and an Intel Xeon (AVX-512), same library versions: native kernels differ in both rows; these
pins with the fused update give the same bits on both; with MKL in its ``AVX2`` mode the SALAD row still
differs (its Sinkhorn's ``logsumexp``), and with the unfused update both rows differ (MKL's ``sqrt``).
Convolutions run without oneDNN and without NNPACK, whose blocks are sized by the processor's cache
(:func:`apply_in_process`), so an image's map is also the same bits in any batch. This last configuration
(convolutions as MKL products, the 1x1 layers as one product over rows) has been run on the AMD EPYC only;
``tests/test_kernels.py``'s fingerprint test says so, naming the processor, where it computes other bits.

The variables must be set before the libraries start, i.e. in the environment of the process that imports
them: :func:`pinned_environ` gives it for a child process (a kernel, a worker), ``python -m vpr_nb.kernels
--run CMD ...`` runs a command in it, and :func:`pin_this_process` sets it for the processes this one starts.
``python -m vpr_nb.kernels`` prints which kernels a process gets and ``python -m vpr_nb.fingerprint`` what a few
training steps compute with them, to compare machines.

This module is a process setting only: it imports no other part of the package, and importing it starts neither
torch nor numpy (their imports sit in the functions that need them), so that the pins can be set first.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from collections.abc import Mapping

# Environment variables read by the libraries when they start (each is ignored where it does not apply):
PINNED: dict[str, str] = {
    "ATEN_CPU_CAPABILITY": "avx2",          # torch's vectorised ATen kernels
    "ONEDNN_MAX_CPU_ISA": "AVX2",           # oneDNN (torch's convolutions on the CPU)
    "MKL_CBWR": "COMPATIBLE",               # MKL (matrix products, vector maths): the same code on Intel and AMD
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "OPENBLAS_CORETYPE": "Haswell",         # numpy's, scipy's and faiss's OpenBLAS
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",   # numpy's own SIMD loops (numpy >= 2.4 names)
    "FAISS_OPT_LEVEL": "avx2",              # faiss's distance loops
}


def pinned_environ(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default ``os.environ``) with :data:`PINNED` set: the environment to start a
    notebook kernel or a worker process in. Variables already set in ``base`` are overridden."""
    if base is not None and not isinstance(base, Mapping):
        raise ValueError(f"base must be a mapping of environment variables, got {type(base).__name__}")
    env = dict(os.environ if base is None else base)
    env.update(PINNED)
    return env


def pin_this_process() -> list[str]:
    """Set :data:`PINNED` in ``os.environ`` so that child processes (kernels started after this call)
    inherit it; return the names that changed. Libraries already started in *this* process keep their kernels:
    call it before importing torch, numpy or faiss if this process itself must be pinned."""
    changed = [k for k, v in PINNED.items() if os.environ.get(k) != v]
    os.environ.update(PINNED)
    return changed


def is_pinned(env: Mapping[str, str] | None = None) -> bool:
    """True if ``env`` (default ``os.environ``) has every variable of :data:`PINNED` at its pinned value."""
    env = os.environ if env is None else env
    return all(env.get(k) == v for k, v in PINNED.items())


# The libraries that read PINNED when they start: once one of them runs, this process keeps the kernels it got.
NUMERICAL_LIBRARIES = ("numpy", "torch", "scipy", "faiss", "matplotlib")
NATIVE_ENV = "VPR_NB_NATIVE_KERNELS"     # =1: leave the kernels to the libraries (faster; other trained numbers)
# How far a trained number in [0, 1] (a Recall@N, a cosine, a probability) moved when the notebooks ran on this
# machine's own kernels instead of the pinned ones: the CI profiles of 02-07 executed both ways on one AMD EPYC
# (AVX-512), largest difference per notebook 0.090 (02), 0.000 (03), 0.000 (04), 0.005 (05), 0.000 (06),
# 0.034 (07) (with the earlier pins, NNPACK on: up to 0.087); rounded up. The reproduce profiles' multi-seed
# means were not measured this way.
UNPINNED_DIFFERENCE = 0.10


def pin_before_start() -> str | None:
    """Pin this process's CPU kernels from inside it, if no numerical library has started yet.

    Returns None when the process computes with the pinned kernels (it already did, or does from now on), else
    one phrase saying why it cannot: :data:`NATIVE_ENV` asks for the native kernels, the processor is not
    x86-64 (the pins choose x86-64 kernels), or a library of :data:`NUMERICAL_LIBRARIES` started first. A notebook
    calls it by importing :mod:`vpr_nb.notebook` before numpy and torch, so that a plain ``jupyter lab``, a hub
    or VS Code computes the stored numbers without ``make lab``."""
    if is_pinned():
        return None
    if os.environ.get(NATIVE_ENV) == "1":
        return f"{NATIVE_ENV}=1 asks for the processor's own kernels"
    machine = platform.machine().lower()
    if machine not in ("x86_64", "amd64"):
        return f"the pinned kernels are x86-64 kernels and this processor is {machine or 'unknown'}"
    started = [m for m in NUMERICAL_LIBRARIES if m in sys.modules]
    if started:
        return f"{', '.join(started)} started before vpr_nb.notebook could pin the kernels"
    os.environ.update(PINNED)
    return None


def apply_in_process() -> bool:
    """In a pinned process (:func:`is_pinned`), route torch's convolutions around oneDNN and NNPACK; return whether
    it did.

    oneDNN sizes its convolution blocks by the processor's cache, so even limited to AVX2 its gradients add in
    another order on another processor (measured: a from-scratch SmallCNN trained on an Intel Xeon diverged
    from the same run on an AMD EPYC in its first epoch, while both ran the pinned environment). Without oneDNN
    torch runs a stride-1 convolution of 16 or more images through NNPACK, which sums input channels in blocks
    of about L1d-per-thread / 256 bytes (so the course backbone's 1x1 projection summed 96 channels as 64 + 32
    on processors with 16 KiB of level-1 data cache per hardware thread) and gives a batch of 16 other bits
    than a batch of 15. Without both, every convolution is an unfold and one MKL matrix product per image,
    which MKL's ``COMPATIBLE`` mode computes identically on Intel and AMD and in any batch; the 1x1 layers of
    the backbone and the aggregators are one product over all positions (:class:`vpr_nb.pointwise.PointwiseConv2d`).

    Called once by each front door (:func:`vpr_nb.notebook.setup`, the console scripts, the tests' conftest).
    What it costs is measured by ``bench/bench_kernels.py`` (docs/performance.md)."""
    if not is_pinned():
        return False
    import torch   # at call time: importing this module must not start torch

    torch.backends.mkldnn.enabled = False
    torch.backends.nnpack.set_flags(False)     # (setting torch.backends.nnpack.enabled does nothing)
    return True


def describe() -> dict:
    """What this process computes with: processor, torch's ATen capability, the library versions and whether
    the environment is pinned. For results stamps and for comparing two machines."""
    import numpy as np
    import torch

    l1d = l1d_per_thread()
    info = {"machine": platform.machine(), "processor": processor_name(),
            "torch": torch.__version__, "numpy": np.__version__,
            "aten_capability": torch.backends.cpu.get_cpu_capability(),
            "onednn_convolutions": bool(torch.backends.mkldnn.enabled),
            "pinned": is_pinned(), "l1d_per_thread_kib": None if l1d is None else l1d / 1024}
    faiss = sys.modules.get("faiss")
    if faiss is not None:
        info["faiss"] = getattr(faiss, "__version__", "?")
    return info


def l1d_per_thread(cpu_dir: str = "/sys/devices/system/cpu/cpu0") -> int | None:
    """Bytes of level-1 data cache per hardware thread of the first processor (its size over the logical
    processors sharing it, from Linux's sysfs), the figure cache-blocked kernels (oneDNN, NNPACK) size their
    blocks by; None where sysfs does not say. Recorded in :func:`describe` for comparing machines."""
    import glob

    for index in sorted(glob.glob(os.path.join(cpu_dir, "cache", "index*"))):
        try:
            fields = {}
            for name in ("level", "type", "size", "shared_cpu_list"):
                with open(os.path.join(index, name), encoding="ascii") as f:
                    fields[name] = f.read().strip()
            if fields["level"] != "1" or fields["type"] not in ("Data", "Unified"):
                continue
            size = fields["size"].upper()
            scale = {"K": 1024, "M": 1024 ** 2}.get(size[-1:], 1)
            size_bytes = int(size.rstrip("KM")) * scale
            threads = 0
            for part in fields["shared_cpu_list"].split(","):
                lo, _, hi = part.partition("-")
                threads += int(hi or lo) - int(lo) + 1
        except (OSError, ValueError):
            return None
        return size_bytes // max(threads, 1)
    return None


def processor_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def cpu_description() -> str:
    """The processor and the CPU kernels this process computes with, e.g. ``"AMD EPYC; pinned kernels (AVX2, MKL
    COMPATIBLE)"`` or ``"Intel(R) Xeon(R) Processor; native kernels (torch AVX512)"``.

    Trained numbers depend on the kernels: with the native ones, a fine-tune amplifies the last-bit differences
    between processors into another model; :func:`vpr_nb.report.run_report` pins them, so that a results file
    says whether another machine should give the same numbers."""
    if is_pinned():
        return f"{processor_name()}; pinned kernels (AVX2, MKL COMPATIBLE)"
    try:
        import torch   # at call time: importing this module must not start torch (see the module docstring)

        kernels = torch.backends.cpu.get_cpu_capability()
    except Exception:  # noqa: BLE001 - an old or missing torch: the processor alone is still worth recording
        kernels = "unknown"
    return f"{processor_name()}; native kernels (torch {kernels})"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--run"]:
        if len(argv) < 2:
            print("error: --run needs a command, e.g. python -m vpr_nb.kernels --run jupyter lab", file=sys.stderr)
            return 2
        try:
            os.execvpe(argv[1], argv[1:], pinned_environ())
        except OSError as exc:
            print(f"error: cannot run {argv[1]!r}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.kernels", description=__doc__.split("\n\n")[0],
                                     epilog="--run CMD [ARGS ...]: run a command with the pinned environment "
                                            "(must come first)")
    parser.add_argument("--env", action="store_true", help="print the pinned environment as NAME=value lines")
    args = parser.parse_args(argv)
    if args.env:
        for k, v in PINNED.items():
            print(f"{k}={v}")
        return 0
    apply_in_process()
    for k, v in describe().items():
        print(f"{k}: {v}")
    print("fingerprint: python -m vpr_nb.fingerprint (what a few training steps compute here)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
