"""The rig's messages: labelled ``samples`` rows (Float64MultiArray) and a node's health on ``/diagnostics``."""
from __future__ import annotations

import array
from typing import Callable, Optional

import numpy as np
from rclpy.node import Node
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from ..io.samples import SAMPLES_LABEL, decode_samples


DIAGNOSTICS_LEVELS = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN, "ERROR": DiagnosticStatus.ERROR,
                      "STALE": DiagnosticStatus.STALE}


class Diagnostics:
    """A node's health on ``/diagnostics`` (the ROS convention: a DiagnosticArray, one DiagnosticStatus named
    after the node) every ``period_s``; ``status()`` gives (level "OK"/"WARN"/"ERROR", one-line message, values
    by name).  Logs one line when the level or the message's kind changes."""

    def __init__(self, node: Node, period_s: float, status: Callable[[], tuple[str, str, dict]]):
        self.node, self.status = node, status
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.last_level: Optional[str] = None
        self.timer = node.create_timer(period_s, self.publish) if period_s > 0 else None

    def publish(self) -> DiagnosticArray:
        level, message, values = self.status()
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(level=DIAGNOSTICS_LEVELS[level], name=self.node.get_fully_qualified_name(),
                                       message=message, hardware_id="piezo_valve",
                                       values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        self.publisher.publish(msg)
        if level != self.last_level:
            if level == "OK":   # rclpy ties a call site to one severity: one call per severity
                self.node.get_logger().info(f"health {level}: {message}")
            elif level == "ERROR":
                self.node.get_logger().error(f"health {level}: {message}")
            else:
                self.node.get_logger().warning(f"health {level}: {message}")
            self.last_level = level
        return msg


def samples_message(rows: np.ndarray, label: str = SAMPLES_LABEL) -> Float64MultiArray:
    """Pack (N, k) rows as the contract's row-major ``samples`` matrix."""
    msg = Float64MultiArray()
    n, k = rows.shape
    msg.layout.dim = [MultiArrayDimension(label="sample", size=n, stride=n * k),
                      MultiArrayDimension(label=label, size=k, stride=k)]
    data = array.array("d")  # an array.array is taken as it is; a list is checked element by element
    data.frombytes(np.ascontiguousarray(rows, dtype=np.float64).tobytes())
    msg.data = data
    return msg


class SamplesBuffer:
    """One ``samples``-layout message of ``n`` rows by ``k`` columns, made once and refilled in place: ``rows`` is a
    writable (n, k) view of its data.  For what a real-time loop publishes on a period (the hardware's full batches,
    the controller's state): building the message anew (its dimensions, its data array) costs tens of microseconds
    there, where the loop's caches are cold for it, and a publication that outlasts the slack of a 10 kHz period
    costs that period.  rclpy copies the message when it publishes, so refilling it after ``publish`` returns is
    safe."""

    def __init__(self, n: int, k: int, label: str = SAMPLES_LABEL):
        self.message = samples_message(np.zeros((n, k)), label)
        self.rows = np.frombuffer(self.message.data, dtype=np.float64).reshape(n, k)   # the message's own data


def samples_from_message(msg: Float64MultiArray) -> np.ndarray:
    """Inverse of :func:`samples_message`: (N, 3) rows time [s], voltage [V], position [m]
    (``samples.decode_samples``; SamplesLayoutError, a ValueError, when the layout is not the contract's)."""
    return decode_samples(msg.layout.dim, msg.data)
