"""What the tests only read, computed once per test run however many pytest-xdist workers ask for it.

The first worker to ask computes it under a file lock and leaves it (pickled, or as files) in the run's shared
directory, which the controlling pytest process creates before the workers start and removes at the end
(``conftest.py``); the others wait for the lock and load it.  Within one process a result is also kept in
memory.  Keys name what is computed; they must differ for different inputs.
"""
from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, TypeVar

SHARED_DIR_ENV = "PIEZO_TEST_SHARED_DIR"
T = TypeVar("T")
_in_memory: dict[str, object] = {}


def create_shared_directory() -> str:
    """Make the run's shared directory and publish it to the workers (called by the controlling process)."""
    path = tempfile.mkdtemp(prefix="piezo-tests-shared-")
    os.environ[SHARED_DIR_ENV] = path
    return path


def remove_shared_directory(path: str) -> None:
    shutil.rmtree(path, ignore_errors=True)
    if os.environ.get(SHARED_DIR_ENV) == path:
        del os.environ[SHARED_DIR_ENV]


def _entry(key: str) -> Path:
    root = os.environ.get(SHARED_DIR_ENV)
    if not root:
        raise RuntimeError(f"{SHARED_DIR_ENV} is not set: the tests' conftest.py creates it")
    return Path(root) / hashlib.sha256(key.encode()).hexdigest()[:24]


@contextmanager
def _locked(entry: Path) -> Iterator[None]:
    with open(entry.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def computed_once(key: str, compute: Callable[[], T]) -> T:
    """``compute()``'s result, computed by the first process of the run that asks for ``key``."""
    if key not in _in_memory:
        entry = _entry(key).with_suffix(".pickle")
        with _locked(entry):
            if entry.exists():
                value = pickle.loads(entry.read_bytes())
            else:
                value = compute()
                partial = entry.with_suffix(".partial")
                partial.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
                partial.rename(entry)
        _in_memory[key] = value
    return _in_memory[key]  # type: ignore[return-value]


def directory_made_once(key: str, fill: Callable[[Path], None]) -> Path:
    """A directory ``fill(directory)`` wrote, by the first process of the run that asks for ``key``."""
    entry = _entry(key)
    with _locked(entry):
        if not entry.is_dir():
            partial = entry.with_suffix(".partial")
            shutil.rmtree(partial, ignore_errors=True)
            partial.mkdir()
            fill(partial)
            partial.rename(entry)
    return entry


def default_valve_analysis_1khz():
    """The default simulated valve at the rig's 1 kHz, identified (``bench/evaluation.simulated_analysis``): the
    tuning tests' model and the identification tests' poles come from this one analysis."""
    def compute():
        from evaluation import simulated_analysis
        from piezo_valve_ros.core.sim import ValveSimConfig
        return simulated_analysis(ValveSimConfig(dt=1e-3), log=lambda s: None)
    return computed_once("shared.default_valve_analysis_1khz", compute)
