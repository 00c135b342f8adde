"""BLAS and OpenMP thread control for the GP and mixture fits.

Every fit runs on one BLAS thread by default: small matrices are faster that way, and a
threaded matrix product sums in an order that depends on the thread count, so one thread
also makes results identical on any machine.
"""

from __future__ import annotations

import functools

from threadpoolctl import ThreadpoolController

__all__ = ["blas_threads", "one_blas_thread", "limit_blas", "controller"]


@functools.cache
def controller():
    """The BLAS thread-pool controller (built once: inspecting the libraries costs ~0.3 ms)."""
    return ThreadpoolController()


def blas_threads(n):
    """Context manager running BLAS on ``n`` threads (None: unchanged).

    One thread also makes results independent of the machine: a threaded matrix product sums
    in an order that depends on the thread count, and a last-bit change can move an optimiser
    to another local optimum (a ``paper`` K3 fold's ISO moves by 0.008; docs/decisions.md, section 12).
    """
    return controller().limit(limits=n, user_api="blas")


def one_blas_thread(func):
    """Decorator: run ``func`` under :func:`blas_threads` (1)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with blas_threads(1):
            return func(*args, **kwargs)
    return wrapper


def limit_blas(method):
    """Run an estimator method with ``self.blas_threads`` BLAS threads."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with blas_threads(self.blas_threads):
            return method(self, *args, **kwargs)
    return wrapper
