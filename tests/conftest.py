"""Fixtures shared by several test modules."""
import pytest
import torch


@pytest.fixture(scope="module")
def one_thread():
    """Tiny ops: one thread avoids OpenMP spin-waits when the CPU is shared (and gives the same floats
    as the notebooks, which pin one thread); restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
