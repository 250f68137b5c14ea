"""``valve_composed``: ``valve_hardware`` and ``valve_controller`` in one process (the fastest loop).

    valve_composed --ros-args --params-file config/rig.yaml -p valve_hardware:clock:=realtime

Parameters are the two nodes' own (address one node with ``valve_hardware:name:=value`` or a
parameters file with a section per node).  With ``clock: realtime`` the position and the command
pass by function call, as rclcpp's intra-process communication would, and the spin loop ticks the
hardware itself: this is what runs the paper's 10 kHz loop in real time (bench/realtime_loop.py).
``spool_position`` and ``samples`` are still published, and ``voltage_command`` from other nodes is
still applied.  In lockstep the loop stays on the topics (in-process DDS).
"""
from __future__ import annotations

import sys

from ..core.validation import same_period
from ..ros import close, print_help, spin, start_node_process, wants_help
from .controller import CONTROLLER_PARAMETERS, ValveControllerNode
from .hardware import ValveHardwareNode, hardware_parameters_with_backends


def build(hardware_overrides=(), controller_overrides=(), **node_kwargs) -> tuple[ValveHardwareNode,
                                                                                ValveControllerNode]:
    """Both nodes (``node_kwargs``, e.g. ``namespace``, go to both), linked directly on the real-time
    clock; raises ValueError (nothing left open) when a node refuses its parameters or the two
    control periods differ."""
    hardware = ValveHardwareNode(parameter_overrides=list(hardware_overrides), **node_kwargs)
    controller = None
    try:
        controller = ValveControllerNode(siblings=[hardware], parameter_overrides=list(controller_overrides), **node_kwargs)
        dt = controller.controller.config.dt
        if not same_period(dt, hardware.control_period_s):
            raise ValueError(f"control_period_s differs: hardware {hardware.control_period_s} s, controller {dt} s")
    except Exception:
        hardware.shutdown_safely()
        hardware.destroy_node()
        if controller is not None:
            controller.destroy_node()
        raise
    if hardware.settings.clock == "realtime":
        hardware.attach_controller(controller.direct_link())
    return hardware, controller


def main(args=None) -> int:
    if wants_help(args):
        print_help("valve_composed", __doc__,
                   tuple(p.under("valve_hardware:") for p in hardware_parameters_with_backends())
                   + tuple(p.under("valve_controller:") for p in CONTROLLER_PARAMETERS))
        return 0
    start_node_process(args)
    try:
        hardware, controller = build()
    except Exception as exc:
        print(f"valve_composed: {exc}", file=sys.stderr)
        close()
        return 2
    return spin([hardware, controller], on_exit=hardware.shutdown_safely)


if __name__ == "__main__":
    sys.exit(main())
