"""Small matrix products in one BLAS thread.

The output-error pass multiplies many small matrices (a chunk of Jacobian rows by itself). A threaded BLAS
splits each product over every core, and on a machine whose cores are busy (a test run, a second process)
that can cost a hundred times the product itself (measured: 8192 x 18 rows, 159 ms in the default threads
on two loaded cores, 0.4 ms in one). Products inside :func:`one_blas_thread` run in one thread.
"""

from __future__ import annotations

import contextlib
import functools

from threadpoolctl import ThreadpoolController

__all__ = ["one_blas_thread"]


@functools.lru_cache(maxsize=1)
def _controller() -> ThreadpoolController:
    return ThreadpoolController()  # inspects the loaded BLAS libraries once


@contextlib.contextmanager
def one_blas_thread():
    """A context in which every loaded BLAS library uses one thread."""
    with _controller().limit(limits=1, user_api="blas"):
        yield
