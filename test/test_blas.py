"""BLAS on one thread where the package computes (``core.blas``): during an analysis and a tuning, and in every node's
process, also for a BLAS loaded after start-up.  Each case runs in a child process with the BLAS thread variables
unset (the tests' own workers run on one thread, ``conftest.py``); where the machine has one CPU the default is one
thread already, and only the "on one thread" half can show."""
import json
import os
import subprocess
import sys

import pytest

from ros_helpers import ros_env

from piezo_valve_ros.core import THREAD_VARIABLES

# prints the BLAS libraries' thread counts, e.g. {"numpy": 2, "scipy": 2} (by the wheel that bundles each)
REPORT = ("def threads():\n"
          "    from threadpoolctl import threadpool_info\n"
          "    return sorted(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas')\n")
MANY = len(os.sched_getaffinity(0)) > 1


def _child(body: str) -> dict:
    env = {k: v for k, v in ros_env().items() if k not in THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", REPORT + body], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_one_blas_thread_while_a_block_runs_and_for_the_rest_of_a_process_also_for_a_blas_loaded_later():
    grandchild = "import numpy, scipy.linalg\n" + REPORT + "print(threads())\n"
    seen = _child("import json, numpy, subprocess, sys\n"
                  "from piezo_valve_ros.core.blas import one_blas_thread, one_blas_thread_for_process\n"
                  "before = threads()\n"
                  "with one_blas_thread():\n"
                  "    inside = threads()\n"
                  "after = threads()\n"
                  "one_blas_thread_for_process()\n"
                  "import scipy.linalg  # its own OpenBLAS, loaded only now\n"
                  f"child = subprocess.run([sys.executable, '-c', {grandchild!r}], capture_output=True, text=True)\n"
                  "print(json.dumps(dict(before=before, inside=inside, after=after, process=threads(),\n"
                  "                      child=child.stdout)))\n")
    assert len(seen["before"]) >= 1 and seen["inside"] == [1] * len(seen["before"])
    assert seen["after"] == seen["before"] and (not MANY or max(seen["before"]) > 1)
    assert len(seen["process"]) == 2 and seen["process"] == [1, 1], seen   # numpy's and scipy's
    assert json.loads(seen["child"]) == [1, 1], seen   # the variables reach the processes it starts


@pytest.mark.parametrize("entry", ["run_node", "valve_composed", "valve_rig"])
def test_a_node_process_runs_blas_on_one_thread(entry):
    """Every node's process (``ros.spin.run_node``, ``valve_composed``'s own main, and ``valve_rig``, which hosts
    the nodes with --composed) sets one BLAS thread before it builds its nodes: seen where they would be built, for
    numpy's BLAS and scipy's loaded after."""
    build = ("def build():\n"
             "    import scipy.linalg\n"
             "    print(json.dumps(threads()), flush=True)\n"
             "    raise RuntimeError('built no node')\n")
    run = {"run_node": "from piezo_valve_ros.ros import run_node\n"
                       "code = run_node(build, 'probe', args=[])\n",
           "valve_composed": "from piezo_valve_ros.nodes import composed\n"
                             "composed.build = build\n"
                             "code = composed.main(args=[])\n",
           "valve_rig": "import rclpy\n"   # the first thing it does after its settings: ROS up, then the nodes
                        "from piezo_valve_ros.cli import rig\n"
                        "rclpy.init = build\n"
                        "try:\n"
                        "    rig.main(['--composed', '--demo', 'none'])\n"
                        "except RuntimeError:\n"
                        "    code = 2\n"}[entry]
    seen = _child("import json, numpy\n" + build + run + "assert code == 2, code\n")
    assert seen == [1, 1]


def test_tune_runs_blas_on_one_thread_and_leaves_it_as_it_was():
    """``tune``'s search (its candidates' closed loops) runs with BLAS on one thread; the caller's setting returns
    after it."""
    seen = _child("import json, numpy, scipy.linalg\n"
                  "from piezo_valve_ros.core.control.compensation import CompensationModel\n"
                  "from piezo_valve_ros.core.tuning import tuner\n"
                  "tuner._Tuner.run = lambda self, starts: threads()\n"
                  "before = threads()\n"
                  "inside = tuner.tune('pid_hc', CompensationModel(), 1e-3)\n"
                  "print(json.dumps(dict(before=before, inside=inside, after=threads())))\n")
    assert seen["inside"] == [1, 1] and seen["after"] == seen["before"], seen
    assert not MANY or max(seen["before"]) > 1, seen
