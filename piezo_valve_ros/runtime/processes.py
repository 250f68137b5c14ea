"""Child processes of a launcher (``valve_rig``, tests): start the package's nodes, stop them all, and make
them die with their parent.

A parent killed with SIGKILL cannot stop its children; on Linux each node started through
:class:`ProcessGroup` asks the kernel for SIGTERM when its parent dies (``PR_SET_PDEATHSIG``, see
:func:`die_with_parent`, called by every node's entry point), so its ordinary shutdown runs: the hardware
applies its safe voltage.  No ROS import here.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from .dds import without_fast_acknowledgements
from ..io.params_yaml import yaml_value

PARENT_PID_ENV = "PIEZO_VALVE_PARENT_PID"   # set by ProcessGroup: the pid the child must not outlive
STOP_GRACE_S = 3.0                          # each of SIGINT, SIGTERM, SIGKILL gets this long
PARENT_POLL_S = 0.2                         # a child checks this often whether its parent is still there ...
PARENT_DEATH_GRACE_S = 5.0                  # ... and ends itself this long after asking for an orderly stop
NODE_MODULES = {"valve_hardware": "hardware", "valve_controller": "controller",
                "valve_identification": "identification", "valve_composed": "composed", "valve_monitor": "monitor"}


def node_command(executable: str, params: dict, namespace: str = "") -> list[str]:
    """Command line that starts one of the package's nodes with ``params`` (optionally in a namespace)."""
    cmd = [sys.executable, "-m", f"piezo_valve_ros.nodes.{NODE_MODULES[executable]}", "--ros-args"]
    if namespace:
        cmd += ["-r", f"__ns:={namespace}"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={yaml_value(v)}"]
    return cmd


def die_with_parent() -> bool:
    """In a process started by :class:`ProcessGroup`: receive SIGTERM when the parent dies (Linux).  Returns
    False where that is not possible (not Linux, or not started by a ProcessGroup)."""
    parent = os.environ.get(PARENT_PID_ENV)
    if not parent or not sys.platform.startswith("linux"):
        return False
    import ctypes
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, int(signal.SIGTERM), 0, 0, 0) != 0:  # PR_SET_PDEATHSIG
            return False
    except (OSError, AttributeError):
        return False
    if os.getppid() != int(parent):  # the parent died before the request: act on it now
        os.kill(os.getpid(), signal.SIGTERM)
    _watch_parent(int(parent))
    return True


# The watcher: a separate, minimal Python process (``-I -S``: no site, no user paths), so that it acts even
# where the node is stuck in C code holding the GIL (a thread of the node could not).  It dies with the node
# (PR_SET_PDEATHSIG SIGKILL), reads the node's parent from /proc, and where the parent is gone: SIGTERM (an
# orderly stop), and PARENT_DEATH_GRACE_S later, if the node still lives, SIGUSR1 (faulthandler: every thread's
# stack to stderr), then SIGKILL.  argv: node pid, parent pid, poll period [s], grace [s].
_WATCHER = """
import ctypes, os, signal, sys, time
node, parent, poll, grace = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
ctypes.CDLL(None).prctl(1, int(signal.SIGKILL), 0, 0, 0)
if os.getppid() != node:
    sys.exit(0)
def parent_of(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None
while parent_of(node) == parent:
    time.sleep(poll)
os.kill(node, signal.SIGTERM)
time.sleep(grace)
print(f"parent {parent} gone and process {node} still alive {grace:g} s after SIGTERM: its shutdown hung; "
      "ending it (stacks follow)", file=sys.stderr, flush=True)
os.kill(node, signal.SIGUSR1)
time.sleep(0.5)
os.kill(node, signal.SIGKILL)
"""


def _watch_parent(parent: int) -> None:
    """Backstop for the death signal: a watcher process (``_WATCHER``) notices the parent gone, asks for an
    orderly stop (SIGTERM) and, if the process still lives PARENT_DEATH_GRACE_S later (its shutdown hung),
    dumps its threads' stacks and kills it.  A process whose parent was killed must not live on, holding a
    valve or a CPU, not even one stuck in C code that holds the GIL.  The watcher runs in a session of its own:
    the Ctrl-C a terminal sends its foreground process group is for the node, not for the watcher (whose
    KeyboardInterrupt would print a traceback on every Ctrl-C)."""
    import atexit
    import faulthandler
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    watcher = subprocess.Popen([sys.executable, "-I", "-S", "-c", _WATCHER, str(os.getpid()), str(parent),
                                str(PARENT_POLL_S), str(PARENT_DEATH_GRACE_S)], stdin=subprocess.DEVNULL,
                               close_fds=True, start_new_session=True)
    atexit.register(_end_watcher, watcher)


def _end_watcher(watcher: subprocess.Popen) -> None:
    """At an orderly exit: the watcher ended and reaped (it would die with this process anyway, but as an
    orphan that is left to init to reap)."""
    watcher.kill()
    watcher.wait()


class ProcessGroup:
    """Child processes that are always cleaned up, and that die with this process if it is killed."""

    def __init__(self):
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, cmd: list[str], env: dict | None = None, **kwargs) -> subprocess.Popen:
        env = without_fast_acknowledgements(dict(os.environ if env is None else env))   # nodes: DDS defaults
        env[PARENT_PID_ENV] = str(os.getpid())
        proc = subprocess.Popen(cmd, env=env, **kwargs)
        self.procs.append((name, proc))
        return proc

    def exited(self) -> list[tuple[str, int]]:
        """(name, exit code) of every process that has ended."""
        return [(name, p.returncode) for name, p in self.procs if p.poll() is not None]

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            alive = [p for _, p in self.procs if p.poll() is None]
            if not alive:
                break
            for p in alive:
                try:
                    p.send_signal(sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + grace_s
            for p in alive:
                try:
                    p.wait(max(deadline - time.monotonic(), 0.01))
                except subprocess.TimeoutExpired:
                    pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
