"""Node parameters: declared with typed descriptors from their ``ParameterSpec``, read, refused with a reason,
and a misspelt name on the command line caught (rclpy ignores a name a node does not declare)."""
from __future__ import annotations

from typing import Any, Optional, Sequence

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.node import Node

from ..core.defaults import CONTROL_PERIOD_S
from ..core.validation import ParameterSpec, as_float


MAX_CONTROL_PERIOD_S = 0.1      # slower than 10 Hz is no control loop for this valve


def declare(node: Node, name: str, default: Any, description: str, *, read_only: bool = False,
            low: Optional[float] = None, high: Optional[float] = None, choices: tuple[str, ...] = ()):
    """Declare a parameter with a typed descriptor.

    Booleans and strings are statically typed (``enabled: 'false'`` is refused by rclpy with its reason);
    numbers and lists stay dynamically typed so ``kp: 1`` works as well as ``kp: 1.0`` (the node validates
    them itself).  ``read_only`` parameters can be given at start-up only; ``low``/``high`` document the
    admissible range in the descriptor (``ros2 param describe``) and are checked by rclpy for doubles;
    ``choices`` go into its additional constraints (the node checks them: ``ParameterSpec.checked``).
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=f"one of {', '.join(choices)}" if choices else "")
    if isinstance(default, bool):
        descriptor.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, str):
        descriptor.type = ParameterType.PARAMETER_STRING
    else:
        descriptor.dynamic_typing = True
        if low is not None and high is not None:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return node.declare_parameter(name, default, descriptor)


CONTROL_PERIOD = ParameterSpec(
    "control_period_s", CONTROL_PERIOD_S, "control period [s]: one spool_position and one command per period (a whole number "
    "of the hardware's sample periods); every node of a rig must use the same", read_only=True,
    low=0.0, high=MAX_CONTROL_PERIOD_S)


def realtime_specs() -> tuple[ParameterSpec, ...]:
    """The read-only ``realtime.*`` scheduling parameters of a real-time node (see :mod:`..realtime`)."""
    from ..runtime.realtime import (CPU_LATENCY_DEVICE, DEFAULT_SWITCH_INTERVAL_S, LEAVE_IDLE_STATES, PRIORITY_RANGE,
                                    SWITCH_INTERVAL_RANGE_S)
    lo, hi = SWITCH_INTERVAL_RANGE_S
    return (
        ParameterSpec("realtime.switch_interval_s", DEFAULT_SWITCH_INTERVAL_S,
                      "CPython's GIL switch interval in this process [s] (the interpreter's default 5 ms lets another "
                      "thread, e.g. DDS's, hold it for several control periods)", read_only=True, low=lo, high=hi),
        ParameterSpec("realtime.priority", 0, "SCHED_FIFO priority of the node's loop thread, the process's other "
                      "threads (DDS's) one below, at 1 on the normal scheduler (0 = the normal "
                      f"scheduler; {PRIORITY_RANGE[0]}..{PRIORITY_RANGE[1]}); refused at start-up when the OS does not "
                      "allow it", read_only=True),
        ParameterSpec("realtime.cpus", [], "CPUs the process may run on (e.g. [1]; empty = any)", read_only=True),
        ParameterSpec("realtime.cpu_wakeup_latency_us", LEAVE_IDLE_STATES,
                      f"the longest an idle CPU may take to wake [us], requested for every CPU while the process runs "
                      f"({CPU_LATENCY_DEVICE}); 0 keeps idle CPUs polling (as cyclictest does); {LEAVE_IDLE_STATES} = no "
                      "request; refused at start-up when the OS does not allow it", read_only=True),
    )


DIAGNOSTICS_PERIOD = ParameterSpec(
    "diagnostics_period_s", 1.0, "publish this node's health on /diagnostics (diagnostic_msgs) this often [s]; "
    "0: never", read_only=True, low=0.0, high=60.0)


def period_parameter(spec: ParameterSpec, value) -> float:
    """A reporting period [s] within the spec's range (0: off); ValueError naming the parameter otherwise (a
    negative, NaN or a string would otherwise switch the report off without a word)."""
    period = as_float(spec.name, value)
    if not spec.low <= period <= spec.high:
        raise ValueError(f"{spec.name} must lie in [{spec.low:g}, {spec.high:g}] s (0: off), got {period}")
    return period


def declare_all(node: Node, specs) -> None:
    """Declare every parameter of ``specs`` on ``node`` (:func:`declare`)."""
    for s in specs:
        declare(node, s.name, s.default, s.description, read_only=s.read_only, low=s.low, high=s.high,
                choices=s.choices)


def realtime_settings(p: dict):
    """Validated :class:`..realtime.RealtimeSettings` from a node's parameter values (ValueError)."""
    from ..runtime.realtime import RealtimeSettings
    return RealtimeSettings.from_values(p["realtime.switch_interval_s"], p["realtime.priority"],
                                        p["realtime.cpus"], p["realtime.cpu_wakeup_latency_us"])


def parameter_values(node: Node) -> dict[str, Any]:
    """Every parameter of ``node`` by name (public API)."""
    return {name: prm.value for name, prm in node.get_parameters_by_prefix("").items()}


def refuse(node: Node, reason: str) -> SetParametersResult:
    """One log line and the refusal a parameter client sees."""
    node.get_logger().warning(f"rejected parameter update: {reason}")
    return SetParametersResult(successful=False, reason=reason)


_ROS_ARGV: list[str] = []   # the process's command line as init_ros saw it (given_parameter_names)


def given_parameter_names(node_name: str, argv=None) -> tuple[set[str], set[str]]:
    """The parameter names a process's command line gives a node by name, as (for this node alone, for every node
    of the process): ``-p``/``--param NODE:NAME:=VALUE`` for this node and the sections of ``--params-file`` files
    for this node alone, then ``-p NAME:=VALUE`` (every node of the process takes it; a file's ``/**`` sections,
    which serve every node of every process, are left out).  rclpy ignores a name a node does not declare without
    a word: the nodes refuse it (a misspelt parameter)."""
    from ..io.params_yaml import node_section
    tokens = list(_ROS_ARGV if argv is None else argv)
    own: set[str] = set()
    shared: set[str] = set()
    in_ros = False
    k = 0
    while k < len(tokens):
        token = tokens[k]
        if token == "--ros-args":
            in_ros = True
        elif token == "--":
            in_ros = False
        elif in_ros and token in ("-p", "--param") and k + 1 < len(tokens):
            k += 1
            node, _, name = tokens[k].split(":=", 1)[0].rpartition(":")
            if not node:
                shared.add(name)
            elif node.rstrip("/").split("/")[-1] == node_name:
                own.add(name)
        elif in_ros and token == "--params-file" and k + 1 < len(tokens):
            k += 1
            try:
                own |= set(node_section(tokens[k], node_name, wildcard=False))
            except (OSError, ValueError):
                pass   # rclpy reports an unreadable file itself; a file without a section for this node gives none
        k += 1
    return own, shared


def nearest_parameter(name: str, nodes: Sequence[Node]) -> Optional[str]:
    """The declared parameter of ``nodes`` whose name is nearest ``name`` (a typo's intended name), or None."""
    import difflib
    declared = sorted({n for node in nodes for n in node.get_parameters_by_prefix("")})
    close_ = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
    return close_[0] if close_ else None


def undeclared_parameters(nodes: Sequence[Node], argv=None) -> list[str]:
    """Each parameter the process's command line (``-p``, ``--params-file`` sections) gives the nodes of this process
    that none of them declares, with the nearest declared name: rclpy ignores such a name without a word, so a
    misspelt one (``gain_sett``, ``plann``) would leave its default in force.  Names for one node by name are its own
    alone; names for every node of the process count where no node of it declares them."""
    unknown: list[str] = []
    shared_names: set[str] = set()
    for node in nodes:
        own, shared = given_parameter_names(node.get_name(), argv)
        unknown += [f"{node.get_name()}:{n}" if len(nodes) > 1 else n for n in sorted(own) if not node.has_parameter(n)]
        shared_names |= shared
    unknown += sorted(n for n in shared_names if not any(node.has_parameter(n) for node in nodes))
    return [named_with_nearest(u, nodes) for u in unknown]


def named_with_nearest(name: str, nodes: Sequence[Node]) -> str:
    """``name`` (``NODE:NAME`` or ``NAME``) with the nearest declared parameter of ``nodes``, if any, as a hint."""
    near = nearest_parameter(name.rpartition(":")[2], nodes)
    return name + (f" (did you mean {near}?)" if near else "")


def refuse_undeclared(nodes: Sequence[Node], tool: str, argv=None) -> None:
    """ValueError naming every parameter the command line gives ``nodes`` that none of them declares
    (``undeclared_parameters``), at start-up, before anything runs."""
    unknown = undeclared_parameters(nodes, argv)
    if unknown:
        raise ValueError(f"unknown parameter(s): {'; '.join(unknown)} (every parameter: {tool} --help)")
