"""Loading the package's numba kernels (``_iir_kernels``, ``_play_kernel``): compiled on first use and cached on
disk, next to the package or in the user's cache folder.  Where numba can write neither (a read-only install run by
a user without a writable home), it refuses to load a cached kernel at all; the kernels are then cached in a
temporary folder for the process, with a warning that names it and the remedy.  Nothing here imports ROS."""
from __future__ import annotations

import importlib
import sys
import tempfile
import warnings
from types import ModuleType

__all__ = ["load", "NO_CACHE_FOLDER"]

NO_CACHE_FOLDER = "no locator available"   # numba's RuntimeError where no cache folder can be written


def load(module: str) -> ModuleType:
    """The kernels module ``module`` (a full dotted name), imported; see the module docstring for the cache."""
    try:
        return importlib.import_module(module)
    except RuntimeError as exc:
        if NO_CACHE_FOLDER not in str(exc):
            raise
    import numba
    numba.config.CACHE_DIR = tempfile.mkdtemp(prefix="piezo_valve_numba_")
    warnings.warn(f"numba can write its cache neither next to the package nor in the user's cache folder: the "
                  f"kernels of {module} are compiled into {numba.config.CACHE_DIR} for this process (set "
                  f"NUMBA_CACHE_DIR to a writable folder to keep them)", RuntimeWarning, stacklevel=2)
    sys.modules.pop(module, None)
    return importlib.import_module(module)
