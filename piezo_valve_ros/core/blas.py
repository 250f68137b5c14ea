"""BLAS on one thread for the package's numerics.  Nothing here imports ROS.

The package's matrices are tall and narrow (an analysis's least squares: a record's rows by some twenty columns)
or small (a filter's state space in ``scipy.signal.cont2discrete``'s matrix exponential, a companion matrix).
BLAS threads gain nothing on them, and they cost: OpenBLAS hands a call to its worker threads, which then spin on
a core waiting for the next one before they sleep, so work that calls BLAS often keeps a second core busy for
nothing (``tune``'s candidates discretise thousands of filters: with the default threads it took twice the CPU
for the same time and gains; ``bench/tuning_table.py`` prints each tuning's time and CPU).

* :func:`one_blas_thread`: every loaded BLAS on one thread while a long computation runs (``analyse``,
  ``tune``), as a context manager;
* :func:`one_blas_thread_for_process`: for the rest of the process, also for a BLAS loaded later (the nodes at
  start-up and ``valve_rig``, which hosts them with ``--composed``: a spinning worker would take the CPU of the
  real-time loop beside it; the tests' workers).
"""
from __future__ import annotations

import os

from threadpoolctl import threadpool_limits

__all__ = ["one_blas_thread", "one_blas_thread_for_process", "THREAD_VARIABLES"]

# what a BLAS reads when it is loaded: OpenBLAS (numpy's and scipy's wheels), OpenMP builds, MKL
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> threadpool_limits:
    """Every BLAS loaded so far on one thread until the ``with`` block it opens ends (then as before)."""
    return threadpool_limits(limits=1, user_api="blas")


def one_blas_thread_for_process() -> None:
    """Every BLAS on one thread for the rest of the process: those loaded (``threadpoolctl``) and those loaded
    later, through the variables they read when they load (``THREAD_VARIABLES``; inherited by child processes)."""
    os.environ.update({name: "1" for name in THREAD_VARIABLES})
    threadpool_limits(limits=1, user_api="blas")
