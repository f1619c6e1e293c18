"""Thread counts of the package's own numpy and faiss hot loops.

numpy, scipy and faiss each bring an OpenBLAS that starts one thread per core, and faiss runs its own
loops on OpenMP threads. For the products of this package (per-chunk Gram matrices, one query against
its candidates, k-means and exact search on course-sized sets) extra threads gain little on an idle
machine and lose badly on a busy one: a thread that waits for a core held by another process stalls the
whole product, and the spinning threads take CPU from everything else. Measured on a loaded 2-core
machine: a 100k-image GDS profile 6x slower, a 20k-point k-means 8-11x slower, a 20k x 2k exact search
2x slower than on one thread. So these loops run single-threaded, whatever the caller's environment
says, and restore the caller's settings on exit: no environment variable is needed.
"""
from __future__ import annotations

import contextlib
import functools
import sys
from typing import Callable, Iterator, TypeVar

from threadpoolctl import ThreadpoolController

_F = TypeVar("_F", bound=Callable)
_controller: ThreadpoolController | None = None


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """Run the body with every loaded BLAS library (numpy's, scipy's, faiss's OpenBLAS) on one thread, and
    faiss's OpenMP loops on one thread; the previous settings come back on exit.

    The BLAS libraries are looked up once, at the first call (the package imports numpy, scipy and faiss
    before any of its hot loops runs), so entering costs microseconds. Torch's threads are not touched
    (:func:`vpr_nb.notebook.setup` sets them once).
    """
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    faiss = sys.modules.get("faiss")
    omp = faiss.omp_get_max_threads() if faiss is not None else None
    with _controller.limit(limits=1, user_api="blas"):
        if omp is not None and omp != 1:
            faiss.omp_set_num_threads(1)
        try:
            yield
        finally:
            if omp is not None and omp != 1:
                faiss.omp_set_num_threads(omp)


def single_threaded_call(fn: _F) -> _F:
    """Decorator: run ``fn`` inside :func:`single_threaded`."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_threaded():
            return fn(*args, **kwargs)
    return wrapper  # type: ignore[return-value]
