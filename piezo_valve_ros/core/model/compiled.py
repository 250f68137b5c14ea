"""Loading the package's numba kernels (``_iir_kernels``, ``_play_kernel``): compiled on first use and cached on
disk, next to the package or in the user's cache folder.  Where numba can write neither (a read-only install run by
a user without a writable home), it refuses to load a cached kernel at all; the kernels are then cached in a
temporary folder for the process, with a warning that names it and the remedy.

A kernel is compiled by one process at a time (a lock file in the temporary folder): processes that start together
on a cold cache (a rig's identification and monitor nodes, a test run's workers) would otherwise each compile the
same kernels, about 10 s of CPU for an analysis's; the others wait and load what the first wrote to the cache.
Nothing here imports ROS."""
from __future__ import annotations

import fcntl
import hashlib
import importlib
import os
import sys
import tempfile
import threading
import warnings
from types import ModuleType

__all__ = ["load", "NO_CACHE_FOLDER", "compile_lock_path"]

NO_CACHE_FOLDER = "no locator available"   # numba's RuntimeError where no cache folder can be written

_loaded: set[str] = set()          # kernel modules whose dispatchers compile under the lock
_in_process = threading.RLock()    # the threads of this process, one at a time (and a kernel's nested compiles)
_depth = 0                         # how deep this process's holder is in nested compiles (the file lock at 0 -> 1)
_lock_file = None


def compile_lock_path(module_file: str) -> str:
    """The lock file [path] the processes compiling the kernels of ``module_file`` share."""
    key = hashlib.sha1(os.path.abspath(module_file).encode()).hexdigest()[:16]
    return os.path.join(tempfile.gettempdir(), f"piezo_valve_ros-numba-{os.getuid()}-{key}.lock")


class _CompileOneAtATime:
    """A dispatcher's ``compile`` under the lock: numba looks in its disk cache inside ``compile``, so a process
    that waited finds there what the one before it compiled."""

    def __init__(self, compile_, lock_path: str):
        self._compile, self._path = compile_, lock_path

    def __call__(self, sig):
        global _depth, _lock_file
        with _in_process:
            if _depth == 0:
                try:
                    _lock_file = open(self._path, "a")
                    fcntl.flock(_lock_file, fcntl.LOCK_EX)
                except OSError:   # no lock to be had (a read-only temporary folder): compile as numba alone would
                    _lock_file = None
            _depth += 1
            try:
                return self._compile(sig)
            finally:
                _depth -= 1
                if _depth == 0 and _lock_file is not None:
                    _lock_file.close()   # releases the lock
                    _lock_file = None


def _one_at_a_time(kernels: ModuleType) -> ModuleType:
    """``kernels`` with each of its dispatchers compiling under the lock (once per module and process)."""
    if kernels.__name__ not in _loaded:
        import numba
        path = compile_lock_path(kernels.__file__)
        for value in vars(kernels).values():
            if isinstance(value, numba.core.registry.CPUDispatcher):
                value.compile = _CompileOneAtATime(value.compile, path)
        _loaded.add(kernels.__name__)
    return kernels


def load(module: str) -> ModuleType:
    """The kernels module ``module`` (a full dotted name), imported; see the module docstring for the cache."""
    try:
        return _one_at_a_time(importlib.import_module(module))
    except RuntimeError as exc:
        if NO_CACHE_FOLDER not in str(exc):
            raise
    import numba
    numba.config.CACHE_DIR = tempfile.mkdtemp(prefix="piezo_valve_numba_")
    warnings.warn(f"numba can write its cache neither next to the package nor in the user's cache folder: the "
                  f"kernels of {module} are compiled into {numba.config.CACHE_DIR} for this process (set "
                  f"NUMBA_CACHE_DIR to a writable folder to keep them)", RuntimeWarning, stacklevel=2)
    sys.modules.pop(module, None)
    _loaded.discard(module)
    return _one_at_a_time(importlib.import_module(module))
