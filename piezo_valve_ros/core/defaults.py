"""The package's defaults, each in one place (SI units).

ROS-free; the nodes' parameter declarations, the tools and the core read them from here.
"""
import os
from typing import Mapping

from .errors import PiezoValveError

__all__ = ["CONTROL_PERIOD_S", "PAPER_CONTROL_PERIOD_S", "BAG_STORAGE", "ANALYSIS_THREADS_ENV",
           "MAX_ANALYSIS_THREADS", "AnalysisThreadsError", "analysis_threads"]

CONTROL_PERIOD_S = 1e-3        # a rig's control period [s]: the nodes', the tools' and the backend checks' default
PAPER_CONTROL_PERIOD_S = 1e-4  # the paper's 10 kHz loop [s]: the core's simulations and Table 1's gains
BAG_STORAGE = "mcap"           # the storage plugin bags are written with unless told otherwise (io.bags.STORAGES)
ANALYSIS_THREADS_ENV = "PIEZO_ANALYSIS_THREADS"   # the environment variable that sets analysis_threads()
MAX_ANALYSIS_THREADS = 4       # an identification's independent refits gain nothing from more threads


class AnalysisThreadsError(PiezoValveError, ValueError):
    """PIEZO_ANALYSIS_THREADS is set to something other than a whole number >= 1."""


def available_cpu_count() -> int:
    """The CPUs this process may run on (its affinity where the system has one, else every CPU)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def analysis_threads(environ: Mapping[str, str] = os.environ) -> int:
    """The threads an identification's independent refits run on (its result does not depend on how many).

    ``PIEZO_ANALYSIS_THREADS`` where it is set (a whole number >= 1: 1 where other work already fills the cores,
    e.g. one test process per core; a second thread then costs ~10 % more CPU and gains no time), else the CPUs
    this process may run on, at most MAX_ANALYSIS_THREADS.  Raises AnalysisThreadsError on any other value.
    """
    given = environ.get(ANALYSIS_THREADS_ENV)
    if given is None or given.strip() == "":
        return min(MAX_ANALYSIS_THREADS, available_cpu_count())
    try:
        threads = int(given)
    except ValueError:
        threads = 0
    if threads < 1:
        raise AnalysisThreadsError(f"{ANALYSIS_THREADS_ENV}={given!r}: the number of analysis threads must be a "
                                   f"whole number >= 1 (unset: the CPUs this process may use, at most "
                                   f"{MAX_ANALYSIS_THREADS})")
    return threads
