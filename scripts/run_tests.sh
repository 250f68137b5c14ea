#!/usr/bin/env bash
# The test suite (the whole of it; CI runs this). Tests that start nodes use a private ROS_DOMAIN_ID and
# localhost-only discovery.  --quick leaves out the long end-to-end runs (marked slow) while developing;
# other arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
args=()
for a in "$@"; do
    if [[ "$a" == "--quick" ]]; then args+=(-m "not slow"); else args+=("$a"); fi
done
exec "${PIEZO_VENV:-.venv}/bin/python" -m pytest -q --durations=12 test "${args[@]+"${args[@]}"}"
