"""How a process that analyses records keeps the memory it frees for its next arrays (glibc's malloc).  No ROS
import.

An analysis makes and drops arrays of tens of MB thousands of times (the design's rows through G, filtered bases,
held-out predictions).  glibc returns every block above its mmap threshold (adjusted as it goes, 32 MB at the most)
to the operating system when it is freed, gives each thread an arena of its own, and trims the free top of its
heaps; the next array of that size is then fresh memory, which the kernel faults in and zeroes page by page (on a
virtual machine the host may have to fault it in too, at a cost that varies with the host's state).  Measured on
this 2-core virtual machine, one analysis of a zoo record (60 s at 10 kHz, ``bench/zoo.py``'s Hammerstein with an
extra lag): 1.3-3.9 s of its 12-14 s of CPU in the kernel from run to run, a filter's 25 MB output costing up to 20x
its arithmetic in page faults.  With the settings below: 0.7-0.8 s in the kernel, 11.2-11.4 s in all, the same
peak memory (1.8 GB) and the same result.  The thresholds are what keeps the peak of a long record's analysis
within its 2 GB target (``bench/identify_scale.py``: 1.9 GB; with blocks of up to 128 MB kept, 2.1 GB).

Processes that analyse records call :func:`keep_freed_memory` once at start-up (``valve_identify``, the
identification and monitor nodes, the tests' workers; a notebook may too).  The real-time nodes do not: their
threads (DDS's among them) keep arenas of their own.
"""
from __future__ import annotations

import ctypes

__all__ = ["keep_freed_memory", "MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "ARENAS"]

MMAP_THRESHOLD_BYTES = 64 << 20    # blocks below this come from the heap and go back to it when freed ...
TRIM_THRESHOLD_BYTES = 64 << 20    # ... which keeps up to this much free memory at its top
ARENAS = 1                         # one heap for every thread: a block one thread frees serves the next one's

# mallopt's parameter numbers (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8


def keep_freed_memory() -> bool:
    """Ask glibc's allocator to keep freed blocks of up to MMAP_THRESHOLD_BYTES in the process (the module's
    docstring says why).  Call it before the process starts its threads.  Returns whether the allocator took
    every setting (False where the C library is not glibc: nothing changed)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    settings = ((_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
                (_M_ARENA_MAX, ARENAS))
    return all([mallopt(parameter, value) == 1 for parameter, value in settings])   # a list: every one is tried
