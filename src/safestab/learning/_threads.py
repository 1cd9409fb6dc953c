"""BLAS and LAPACK thread limits for the library's fits (internal).

OpenBLAS's threads spin while they wait for each other: on a machine whose cores are busy
with other work, a factorisation with two threads ran 8 times slower than with one (a
2000 x 2000 Cholesky, 1.14 s against 0.14 s), and a ``SparseGP`` fit at ``Q = 1e5`` 10 times
slower (489 likelihood evaluations at 0.12 to 0.18 s instead of 13 ms). Every fit the library
runs (:class:`~safestab.learning.GaussianProcessModel`'s ``fit``, ``from_hyperparameters`` and
``load``, ``FastGP``, ``SparseGP.fit``) therefore runs under :func:`fit_threads`: one BLAS
thread, as the studies and the Monte Carlo runner fit.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any

__all__ = ["blas_single_threaded", "fit_threads", "one_blas_thread"]


def one_blas_thread() -> Any:
    """A context in which BLAS and LAPACK (NumPy's, SciPy's and JAX's CPU LAPACK) use one thread.

    OpenBLAS's threads wait on each other while the cores are busy elsewhere: on two cores
    with other jobs running, a 2000 x 2000 Cholesky factorisation takes several times as long
    with two threads as with one. One thread also fixes the
    summation order, so a data set's GP is the same bits in this process and in a worker
    process whatever their thread settings; run several data sets in parallel as separate
    tasks instead.
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def blas_single_threaded() -> bool:
    """Whether every BLAS library loaded in this process (threadpoolctl's view) runs one thread."""
    from threadpoolctl import threadpool_info

    pools = [p.get("num_threads") for p in threadpool_info() if p.get("user_api") == "blas"]
    return bool(pools) and all(n == 1 for n in pools)  # none found: assume several


def fit_threads() -> Any:
    """The context every fit of the library runs in: :func:`one_blas_thread`, where it acts.

    Nothing to do where BLAS already runs one thread (a caller's ``one_blas_thread``, the
    studies', or ``OPENBLAS_NUM_THREADS=1``): the caller's limit stays as it is. From a thread
    other than the main one it sets nothing either: threadpoolctl's limit is process-wide
    (entering and leaving it in one thread would change the count under another thread's
    fit), and OpenBLAS 0.3.30 ignores a count set from another thread once the main thread has
    set one; set the limit in the main thread around such threads
    (``with learning.batched.one_blas_thread():``), as the Monte Carlo runner does.
    """
    if threading.current_thread() is not threading.main_thread() or blas_single_threaded():
        return contextlib.nullcontext()
    return one_blas_thread()
