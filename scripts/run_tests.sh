#!/usr/bin/env bash
# The test suite (the whole of it; CI runs this). Tests that start nodes use a private ROS_DOMAIN_ID and
# localhost-only discovery.  --quick leaves out the long end-to-end runs (marked slow) while developing;
# other arguments go to pytest.  The tests run on PIEZO_TEST_WORKERS processes (pytest-xdist; default: one
# more than the machine's cores, at most 4: the end-to-end runs wait on the wall clock part of the time;
# each worker claims its own ROS domain); -n 0 runs them in this process.
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")/.."
bash scripts/setup_venv.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
args=()
for a in "$@"; do
    if [[ "$a" == "--quick" ]]; then args+=(-m "not slow"); else args+=("$a"); fi
done
py="${PIEZO_VENV:-.venv}/bin/python"
workers=${PIEZO_TEST_WORKERS:-$("$py" -c 'import os; print(min(4, 1 + (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)))')}
# the package compiled once: each node and tool process the tests start imports it, and an
# interpreter that may not write bytecode (PYTHONDONTWRITEBYTECODE) would compile it in every one (~0.1 s each)
"$py" -m compileall -q -j 0 piezo_valve_ros > /dev/null
exec "$py" -m pytest -q --durations=12 -n "$workers" --dist worksteal test "${args[@]+"${args[@]}"}"
