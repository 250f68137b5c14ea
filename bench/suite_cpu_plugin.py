"""A pytest plugin for ``bench/suite_cpu.py``: each test's CPU time in its worker process (``self``) and in the child
processes it started and waited for (``children``: nodes, tools), its wall time and when it started and ended (the
epoch's seconds, comparable across the workers), one JSON line per test in
``$SUITE_CPU_DIR/<pid>.jsonl``.  Loaded with ``-p suite_cpu_plugin`` (this folder on PYTHONPATH); not part of the
package or of the suite."""
from __future__ import annotations

import json
import os
import resource
import time

import pytest

DIR_VARIABLE = "SUITE_CPU_DIR"


def _cpu_s() -> tuple[float, float]:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    directory = os.environ.get(DIR_VARIABLE)
    if not directory:
        yield
        return
    own, children = _cpu_s()
    started, started_at = time.monotonic(), time.time()
    yield
    own_after, children_after = _cpu_s()
    with open(os.path.join(directory, f"{os.getpid()}.jsonl"), "a") as out:
        out.write(json.dumps({"test": item.nodeid, "self_s": own_after - own, "children_s": children_after - children,
                              "wall_s": time.monotonic() - started, "start": started_at, "end": time.time(),
                              "worker": os.environ.get("PYTEST_XDIST_WORKER", "main")}) + "\n")
