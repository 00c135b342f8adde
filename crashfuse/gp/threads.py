"""BLAS and OpenMP thread control for the GP and mixture fits.

Every fit runs on one BLAS thread by default: small matrices are faster that way, and a
threaded matrix product sums in an order that depends on the thread count, so one thread
also makes results independent of the thread settings. Not of the processor: BLAS and numpy's own
vector loops pick their code by instruction set, and other code sums in another order (docs/decisions.md,
sections 56 and 60); :func:`cpu_kernels` names both, and every diagnosis and validation table records it.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = ["blas_threads", "one_blas_thread", "limit_blas", "controller", "cpu_kernels"]


@functools.cache
def controller():
    """The BLAS thread-pool controller (built once: inspecting the libraries costs ~0.3 ms)."""
    return ThreadpoolController()


def blas_threads(n):
    """Context manager running BLAS on ``n`` threads (None: unchanged).

    One thread also makes results independent of the thread settings: a threaded matrix product
    sums in an order that depends on the thread count, and a last-bit change can move an optimiser
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


def cpu_kernels() -> str:
    """The machine code numpy and scipy run here: numpy's vector-loop targets in use and each BLAS library
    with its kernels, e.g. ``numpy 2.4.6 SIMD X86_V3 X86_V4 AVX512_ICL; numpy: openblas 0.3.31 SkylakeX;
    scipy: openblas 0.3.30 SkylakeX``. Other code (another processor, ``OPENBLAS_CORETYPE``,
    ``NPY_DISABLE_CPU_FEATURES``) sums in another order and can end a fit in another local optimum of
    the same problem (docs/decisions.md, sections 56 and 60)."""
    import scipy.linalg  # noqa: F401 - loads scipy's BLAS (the fits use it) wherever this is asked first
    libs = sorted({f"{Path(lib['filepath']).parent.name.removesuffix('.libs')}: {lib['internal_api']} "
                   f"{lib.get('version') or '?'} {lib.get('architecture') or '?'}"
                   for lib in ThreadpoolController().info()  # not controller(): it may predate scipy's BLAS
                   if lib["user_api"] == "blas"})
    return "; ".join([f"numpy {np.__version__} SIMD {_simd_targets()}", *libs])


def _simd_targets() -> str:
    """numpy's runtime-dispatched instruction-set targets this machine runs (``?`` where numpy does not say)."""
    try:  # numpy has no public accessor; ``numpy.show_runtime`` reads the same two lists
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:
        return "?"
    return " ".join(t for t in __cpu_dispatch__ if __cpu_features__.get(t)) or "baseline"
