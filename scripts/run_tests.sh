#!/usr/bin/env bash
# The test suite. Tests that start nodes use a private ROS_DOMAIN_ID and localhost-only discovery.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
exec "${PIEZO_VENV:-.venv}/bin/python" -m pytest -q --durations=12 test "$@"
