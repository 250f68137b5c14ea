"""The ROS plumbing every node, the rig client and the tools stand on: QoS profiles (``qos``), parameters
(``parameters``), messages and diagnostics (``messages``), a node's process and its spin loop (``spin``).  The
nodes, ``rig`` and ``cli`` import it through this face; nothing in ``core`` does."""
from .qos import (SENSOR_QOS, LATEST_SENSOR_QOS, COMMAND_QOS, REFERENCE_QOS, SAMPLES_QOS, STATE_QOS)
from .parameters import (MAX_CONTROL_PERIOD_S, declare, CONTROL_PERIOD, realtime_specs, DIAGNOSTICS_PERIOD,
                         period_parameter, declare_all, realtime_settings, parameter_values, refuse,
                         given_parameter_names, nearest_parameter, undeclared_parameters, named_with_nearest,
                         refuse_undeclared)
from .messages import (DIAGNOSTICS_LEVELS, Diagnostics, samples_message, SamplesBuffer, samples_from_message)
from ..runtime.throttle import Throttle
from .spin import (tighten_timer_slack, make_executor, Pacing, claim_pacing, RANK_THREADS_S, spin_loop,
                   SHUTDOWN_DEADLINE_S, init_ros, stop_requested, split_ros_args, close, spin, wants_help,
                   print_help, start_node_process, run_node)

__all__ = ['SENSOR_QOS', 'LATEST_SENSOR_QOS', 'COMMAND_QOS', 'REFERENCE_QOS', 'SAMPLES_QOS', 'STATE_QOS',
           'MAX_CONTROL_PERIOD_S', 'declare', 'CONTROL_PERIOD', 'realtime_specs', 'DIAGNOSTICS_PERIOD',
           'period_parameter', 'declare_all', 'realtime_settings', 'parameter_values', 'refuse',
           'given_parameter_names', 'nearest_parameter', 'undeclared_parameters', 'named_with_nearest',
           'refuse_undeclared', 'DIAGNOSTICS_LEVELS', 'Diagnostics', 'samples_message', 'SamplesBuffer',
           'samples_from_message', 'tighten_timer_slack', 'make_executor', 'Pacing', 'Throttle', 'claim_pacing',
           'RANK_THREADS_S', 'spin_loop', 'SHUTDOWN_DEADLINE_S', 'init_ros', 'stop_requested', 'split_ros_args',
           'close', 'spin', 'wants_help', 'print_help', 'start_node_process', 'run_node']
