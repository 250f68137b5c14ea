#!/usr/bin/env bash
# The main job: a simulated rig (hardware + controller in separate processes, lockstep at 10 kHz)
# running the paper's three step tests. Extra arguments go to valve_rig (see valve_rig --help).
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")/.."
bash scripts/setup_venv.sh
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-42}
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
# said out loud: a second shell's valve_command or valve_record finds this rig only in the same domain
echo "run_demo: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE (export the same in another shell to talk to this rig)" >&2
exec "${PIEZO_VENV:-.venv}/bin/valve_rig" "$@"
