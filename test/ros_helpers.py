"""Helpers for tests that start nodes: private DDS domain, process cleanup, log capture."""
import os
import subprocess
import time

DOMAIN_RANGE = range(20, 100)   # ROS_DOMAIN_IDs the tests may use (Fast DDS ports stay valid below 233)


def _claim_domain_id() -> str:
    """A domain id no other test suite on this machine holds: the first of DOMAIN_RANGE whose lock file this
    process can lock (the lock is held until the process ends, whatever way it ends); under pytest-xdist one per
    worker.  ``PIEZO_TEST_DOMAIN_ID`` (without pytest-xdist)
    overrides; a child process of a suite inherits the id through ROS_DOMAIN_ID in its environment."""
    # under pytest-xdist each worker process claims its own (the controller's claim reaches the workers
    # through the environment, so a worker keys its claim by its name)
    key = "PIEZO_TEST_DOMAIN_ID" + (f"_{os.environ['PYTEST_XDIST_WORKER']}" if os.environ.get("PYTEST_XDIST_WORKER") else "")
    if os.environ.get(key):
        return os.environ[key]
    import fcntl
    import tempfile
    for domain in DOMAIN_RANGE:
        handle = open(os.path.join(tempfile.gettempdir(), f"piezo_valve_ros_test_domain_{domain}.lock"), "a")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _held.append(handle)
        os.environ[key] = str(domain)  # the same id for every test module of this suite (or worker)
        return str(domain)
    raise RuntimeError(f"every test ROS domain ({DOMAIN_RANGE.start}..{DOMAIN_RANGE.stop - 1}) is in use")


_held: list = []
DOMAIN_ID = _claim_domain_id()


def ros_env() -> dict:
    """The environment of a process a test starts: the suite's domain, this machine only; the middleware's
    defaults (the fast-acknowledgement profile of the test process is not passed on: a tool chooses it)."""
    from piezo_valve_ros.runtime import without_fast_acknowledgements
    env = without_fast_acknowledgements(dict(os.environ))
    env["ROS_DOMAIN_ID"] = DOMAIN_ID
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def wait_for_text(path, text, timeout_s=20.0) -> float:
    """Wall time at which ``text`` appeared in the file at ``path``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if os.path.exists(path) and text in open(path, errors="replace").read():
            return time.monotonic()
        time.sleep(0.01)
    raise AssertionError(f"{text!r} not in {path} after {timeout_s} s:\n" + (open(path).read() if os.path.exists(path) else ""))


def start(procs, name, cmd, log_dir):
    log = open(os.path.join(log_dir, f"{name}.log"), "w")
    return procs.start(name, cmd, env=ros_env(), stdout=log, stderr=subprocess.STDOUT)
