import os
import sys

# the package is installed editable (scripts/setup_venv.sh); the tests' own helpers live beside them, and the
# benches' harness of the whole loop (identify, compensate, track: bench/evaluation.py) beside the benches
sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(1, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "bench"))

import pytest  # noqa: E402

import shared  # noqa: E402  (found through the path set just above)
from ros_helpers import ros_env  # noqa: E402

# the workers analyse records: freed arrays kept for the next ones, as valve_identify keeps them (runtime.memory)
from piezo_valve_ros.runtime import keep_freed_memory  # noqa: E402
keep_freed_memory()

# ... and run BLAS on one thread, as the nodes do: its idle workers spin, and the workers share the machine (core.blas)
from piezo_valve_ros.core import one_blas_thread_for_process  # noqa: E402
one_blas_thread_for_process()

# ... and analyse on one thread: the suite's workers fill the cores already, and a second analysis thread then costs
# ~10 % more CPU for no time (core.defaults.analysis_threads); the tools the tests start inherit it
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("PIEZO_ANALYSIS_THREADS", "1")

# nodes created in the test process join the suite's private DDS domain, on this machine only
os.environ.update({k: ros_env()[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})

# ... and a reference a test publishes is acknowledged within milliseconds, as in valve_command and valve_rig
from piezo_valve_ros.runtime import use_fast_acknowledgements  # noqa: E402
use_fast_acknowledgements()


_SHARED_DIR = pytest.StashKey[str]()


def pytest_configure(config):
    """The controlling process makes the directory where workers share what tests only read (shared.py)."""
    if not hasattr(config, "workerinput") and shared.SHARED_DIR_ENV not in os.environ:
        config.stash[_SHARED_DIR] = shared.create_shared_directory()


def pytest_unconfigure(config):
    if _SHARED_DIR in config.stash:
        shared.remove_shared_directory(config.stash[_SHARED_DIR])


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist the tests marked ``wall_clock`` go first, the longest (its ``seconds``) at the head
    of each worker's share of the run (the work-stealing scheduler first hands each worker a contiguous share, in order): their waiting
    then overlaps the other tests' work instead of ending the run with the CPU idle.  Without xdist the order
    is left as it is."""
    workers = getattr(config, "workerinput", {}).get("workercount")
    if not workers or workers < 2:
        return
    waiting = sorted((item for item in items if item.get_closest_marker("wall_clock")),   # the longest first
                     key=lambda item: -item.get_closest_marker("wall_clock").kwargs.get("seconds", 0))
    if not waiting:
        return
    rest = iter([item for item in items if not item.get_closest_marker("wall_clock")])
    ordered, remaining = [], len(items)
    for worker in range(workers):
        share = remaining // (workers - worker)     # as xdist's work stealing splits the pending tests
        remaining -= share
        head = waiting[worker::workers]
        ordered += head + [next(rest) for _ in range(share - len(head))]
    ordered += list(rest)
    items[:] = ordered
