"""Helpers for tests that start nodes: private DDS domain, process cleanup, log capture."""
import os
import subprocess
import time

DOMAIN_ID = str(20 + os.getpid() % 80)


def ros_env() -> dict:
    env = dict(os.environ)
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
