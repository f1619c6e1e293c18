"""Fixtures shared by several test modules.

The tests run on the pinned CPU kernels (:mod:`vpr_nb.kernels`), set here before torch and numpy start
(unless a plugin imported them first), as the notebooks run: pinned numbers are then the same on any
x86-64 machine."""
from vpr_nb.kernels import apply_in_process, pin_this_process

pin_this_process()
apply_in_process()   # as every front door does (vpr_nb.notebook.setup, the CLIs): no oneDNN convolutions

import pytest  # noqa: E402 - after the pins, which must precede torch's and numpy's start
import torch  # noqa: E402


@pytest.fixture(scope="module")
def one_thread():
    """Tiny ops: one thread avoids OpenMP spin-waits when the CPU is shared (and gives the same floats
    as the notebooks, which pin one thread); restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
