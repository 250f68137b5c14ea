#!/usr/bin/env bash
# A day on the rig with the package's commands only (docs/handbook/day_on_the_rig.md): bring up a real-time rig,
# record it, send references and parameters, stop the recording, plot the run, identify the valve from it.
#   bash scripts/day_on_the_rig.sh [OUT_DIR]      (default: day_on_the_rig/; about a minute)
# Uses SCHED_FIFO priority 50 for the rig when the OS allows it (else the normal scheduler).
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
bash "$ROOT/scripts/setup_venv.sh" >/dev/null
B="$ROOT/.venv/bin"
OUT=${1:-day_on_the_rig}
mkdir -p "$OUT" && cd "$OUT" && rm -rf run1 run1_plots
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-42} ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
RT="--priority 50 --pin"
python3 -c "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))" 2>/dev/null || RT=""
run() { echo "\$ $*"; "$B/$@"; }
echo "\$ valve_rig --demo none --clock realtime --control-period-s 0.001 $RT --namespace /valve1 &"
"$B/valve_rig" --demo none --clock realtime --control-period-s 0.001 $RT --namespace /valve1 > rig.log 2>&1 &
RIG=$!
trap 'kill -INT $RIG 2>/dev/null; wait $RIG' EXIT
until grep -q "running; Ctrl-C" rig.log; do sleep 0.2; done
echo "\$ valve_record --namespace /valve1 run1 &"
"$B/valve_record" --namespace /valve1 run1 > record.log 2>&1 &
REC=$!
until grep -q "recording" record.log; do sleep 0.2; done
sleep 1
run valve_command --namespace /valve1 --wait-readers 2 step 20e-6
sleep 1
run valve_command --namespace /valve1 --wait-readers 2 sine --amplitude 40e-6 --frequency 1 --duration 6
run valve_command --namespace /valve1 set controller kp:=2.0
run valve_command --namespace /valve1 set controller gain_set:=ff_pid_1
run valve_command --namespace /valve1 get controller strategy kp ki
run valve_command --namespace /valve1 --wait-readers 2 step -20e-6
sleep 1
run valve_command --namespace /valve1 --wait-readers 2 ramp -20e-6 30e-6 --duration 2
sleep 1
echo "\$ kill -INT %2    # Ctrl-C on valve_record"
kill -INT $REC; wait $REC; tail -1 record.log
run valve_plot run1
run valve_identify run1 --report run1_report.json --quiet
