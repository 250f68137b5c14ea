"""Shared ROS plumbing: QoS profiles, parameter helpers, spinning with clean shutdown."""
from __future__ import annotations

import math
from typing import Any, Callable, Optional

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy, qos_profile_sensor_data
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

SENSOR_QOS = qos_profile_sensor_data  # spool_position: best effort, keep last
COMMAND_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
REFERENCE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
SAMPLES_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.VOLATILE)
SAMPLES_LABEL = "time,voltage_command,spool_position"


def declare(node: Node, name: str, default: Any, description: str):
    """Declare a parameter; numbers are dynamically typed so ``kp: 1`` works as well as ``kp: 1.0``."""
    return node.declare_parameter(name, default, ParameterDescriptor(description=description,
                                                                     dynamic_typing=True))


def as_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def as_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or float(value) != int(value):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(value)


def as_float_list(name: str, value: Any) -> list[float]:
    try:
        return [as_float(name, x) for x in list(value)]
    except TypeError:
        raise ValueError(f"{name} must be a list of numbers, got {value!r}") from None


def samples_message(rows: np.ndarray, label: str = SAMPLES_LABEL) -> Float64MultiArray:
    """Pack (N, k) rows as the contract's row-major ``samples`` matrix."""
    msg = Float64MultiArray()
    n, k = rows.shape
    msg.layout.dim = [MultiArrayDimension(label="sample", size=n, stride=n * k),
                      MultiArrayDimension(label=label, size=k, stride=k)]
    msg.data = np.ascontiguousarray(rows, dtype=float).ravel().tolist()
    return msg


def samples_from_message(msg: Float64MultiArray) -> tuple[np.ndarray, list[str]]:
    """Inverse of :func:`samples_message`: (rows, column names)."""
    dims = msg.layout.dim
    if len(dims) != 2:
        raise ValueError("samples message must have two layout dimensions")
    n, k = dims[0].size, dims[1].size
    data = np.asarray(msg.data, dtype=float)
    if data.size != n * k:
        raise ValueError(f"samples message holds {data.size} values, layout says {n}x{k}")
    return data.reshape(n, k), dims[1].label.split(",")


def make_executor(context=None):
    """EventsExecutor where available (about 2.5x the round trips of SingleThreadedExecutor)."""
    try:
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    except Exception:  # pragma: no cover - older rclpy
        return SingleThreadedExecutor(context=context)


def spin(nodes, on_exit: Optional[Callable[[], None]] = None, executor=None) -> int:
    """Spin until shutdown (Ctrl-C / SIGTERM); ``on_exit`` runs whatever ends the loop.

    EventsExecutor's blocking ``spin()`` ignores signals, so this loops on ``spin_once``.
    """
    executor = executor or make_executor()
    for node in nodes:
        executor.add_node(node)
    code = 0
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            code = 1
            raise
        # a callback ran into the context a signal had just shut down: that is the shutdown itself
    finally:
        _ignore_signals_while_cleaning_up()
        if on_exit is not None:
            on_exit()
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        try:
            executor.shutdown()
        except Exception:
            pass
        if rclpy.ok():
            rclpy.try_shutdown()
    return code


def _ignore_signals_while_cleaning_up() -> None:
    """The loop has ended: a second Ctrl-C/SIGTERM must not interrupt the cleanup half-way (it would abort
    inside rclpy's C++ destructors)."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


def run_node(factory: Callable[[], Node], name: str, args=None, on_exit_of=None) -> int:
    """Console-script body: init, build the node (one clear line and exit 2 if that fails), spin.

    ``on_exit_of(node)`` gives the callable run when spinning ends (e.g. apply safe_voltage).
    """
    import sys
    rclpy.init(args=args)
    try:
        node = factory()
    except Exception as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    return spin([node], on_exit=on_exit_of(node) if on_exit_of else None)
