"""Talking to a running rig from another process or thread: references, parameters, samples.

The library behind ``valve_rig``'s demo, ``valve_command`` and the tests (a node never imports a CLI module).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile
from std_msgs.msg import Float64, Float64MultiArray

from ..ros import REFERENCE_QOS, SAMPLES_QOS, claim_pacing, make_executor, samples_from_message, spin_loop


RIG_NODES = ("hardware", "controller", "identification")


@dataclass(frozen=True)
class PlayResult:
    """What :meth:`RigClient.play_reference` did: references sent, seconds sending, seconds until every
    reader acknowledged them, number of readers."""

    sent: int
    sending_s: float
    acknowledged_after_s: float
    readers: int


DISCOVERY_SETTLE_S = 0.5      # a new publisher sends once its number of matched readers held this long
PROBE_TIMEOUT_S = 1.0         # a parameter request unanswered this long after discovery is sent again


def wait_until_answering(client: AsyncParameterClient, timeout_s: float = 10.0) -> bool:
    """True once the node behind ``client`` answers a harmless read (``use_sim_time``), repeated until one comes
    back; False after ``timeout_s`` [s].  Discovered services are not enough: a server that does not yet know
    the client's response reader drops the answer, so a request that must not be lost goes after this."""
    deadline = time.monotonic() + timeout_s
    if not client.wait_for_services(timeout_sec=timeout_s):
        return False
    while time.monotonic() < deadline and rclpy.ok():
        try:
            wait_future(client.get_parameters(["use_sim_time"]), min(PROBE_TIMEOUT_S, timeout_s), "probe")
            return True
        except TimeoutError:
            continue
    return False


def get_parameter_values(client: AsyncParameterClient, names: list[str], timeout_s: float = 10.0) -> dict:
    """Values of ``names`` on the node behind ``client`` (all of its parameters when empty); TimeoutError when
    it does not answer."""
    if not names:
        listed = wait_future(client.list_parameters(), timeout_s, "listing parameters")
        names = sorted(listed.result.names)
    values = wait_future(client.get_parameters(names), timeout_s, f"getting {', '.join(names)}").values
    return {n: parameter_value_to_python(v) for n, v in zip(names, values)}


def wait_future(future, timeout_s: float, what: str):
    """The result of an rclpy future answered by another thread's executor; TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not future.done():
        if time.monotonic() > deadline or not rclpy.ok():
            raise TimeoutError(f"{what}: no answer within {timeout_s:g} s")
        time.sleep(0.005)
    return future.result()


class RigClient(Node):
    """Drives a lockstep rig: reference, pause/resume through the hardware's step budget, samples."""

    def __init__(self, namespace: str = "", samples_per_period: int = 1, with_samples: bool = True,
                 name: str = "valve_rig_client", reference_history: int = REFERENCE_QOS.depth):
        super().__init__(name, namespace=namespace or None)
        self.samples_per_period = int(samples_per_period)  # rows of `samples` per control period
        self.rows: list[np.ndarray] = []
        self._rows_count = 0
        self._lock = threading.Lock()
        self._new_rows = threading.Condition(self._lock)
        if with_samples:
            self.create_subscription(Float64MultiArray, "samples", self._on_samples, SAMPLES_QOS)
        # a deeper history than the nodes' keeps a profile whole for a reader that falls behind (a recorder on
        # a busy computer): a reliable writer drops what leaves its history before every reader has it
        qos = QoSProfile(depth=max(int(reference_history), 1), reliability=REFERENCE_QOS.reliability,
                         history=REFERENCE_QOS.history, durability=REFERENCE_QOS.durability)
        self.reference_pub = self.create_publisher(Float64, "position_reference", qos)
        self._parameter_clients: dict[str, AsyncParameterClient] = {}
        self.hardware = self.parameter_client("hardware")
        self.controller = self.parameter_client("controller")

    def node_name(self, which: str) -> str:
        """Full name of a rig node: ``hardware``, ``controller``, ``identification`` (valve_<which> in this
        client's namespace), or any node name (relative names are taken in the namespace)."""
        name = f"valve_{which}" if which in RIG_NODES else which
        if name.startswith("/"):
            return name
        ns = self.get_namespace().rstrip("/")
        return f"{ns}/{name}"

    def parameter_client(self, which: str) -> AsyncParameterClient:
        name = self.node_name(which)
        if name not in self._parameter_clients:
            self._parameter_clients[name] = AsyncParameterClient(self, name)
        return self._parameter_clients[name]

    def wait_for_node(self, which: str, timeout_s: float = 10.0) -> AsyncParameterClient:
        """The parameter client of a node that answers a request; TimeoutError naming it otherwise.

        The services being discovered is not enough: a server may not yet know the client's response reader,
        and a request sent then goes unanswered.  So a harmless read (``use_sim_time``) is repeated until one
        comes back, and only then may a request that must not be repeated (a step budget) be sent."""
        client = self.parameter_client(which)
        if wait_until_answering(client, timeout_s):
            return client
        raise TimeoutError(f"{self.node_name(which)} does not answer (is it running, in this namespace and "
                           f"ROS domain?)")

    def _on_samples(self, msg: Float64MultiArray) -> None:
        rows = samples_from_message(msg)
        with self._new_rows:
            self.rows.append(rows)
            self._rows_count += rows.shape[0]
            self._new_rows.notify_all()

    @property
    def rows_count(self) -> int:
        with self._lock:
            return self._rows_count

    def all_rows(self) -> np.ndarray:
        with self._lock:
            return np.concatenate(self.rows) if self.rows else np.zeros((0, 3))

    def wait_rows(self, count: int, timeout_s: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._new_rows:
            while self._rows_count < count:
                left = deadline - time.monotonic()
                if left <= 0 or not rclpy.ok():
                    return False
                self._new_rows.wait(min(left, 0.1))
        return True

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Both nodes' parameter services answer and somebody (the controller) reads position_reference."""
        for which in ("hardware", "controller"):
            self.wait_for_node(which, timeout_s)
        self.wait_for_reference_readers(1, timeout_s, settle_s=0.0)

    def set_params(self, client: AsyncParameterClient, values: dict, timeout_s: float = 10.0):
        """Set ``values`` on the node behind ``client``; one SetParametersResult per value."""
        future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        return wait_future(future, timeout_s, f"setting {', '.join(values)}").results

    def set_params_atomically(self, client: AsyncParameterClient, values: dict, timeout_s: float = 10.0):
        """Set ``values`` on the node behind ``client`` in one update, all applied or none: the
        SetParametersResult (its reason when refused)."""
        future = client.set_parameters_atomically([Parameter(k, value=v) for k, v in values.items()])
        return wait_future(future, timeout_s, f"setting {len(values)} parameters atomically").result

    def reset_hardware(self, timeout_s: float = 10.0) -> tuple[bool, str]:
        """Call the hardware's ``~/reset`` (leave a latched fault once its cause is gone): (success, message);
        TimeoutError when the service does not answer."""
        from std_srvs.srv import Trigger
        name = f"{self.node_name('hardware')}/reset"
        client = self.create_client(Trigger, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                raise TimeoutError(f"{name} does not answer (is valve_hardware running, in this namespace and ROS "
                                   f"domain?)")
            result = wait_future(client.call_async(Trigger.Request()), timeout_s, name)
            return bool(result.success), str(result.message)
        finally:
            self.destroy_client(client)

    def get_params(self, client: AsyncParameterClient, names: list[str], timeout_s: float = 10.0) -> dict:
        """Values of ``names`` on the node behind ``client`` (all of its parameters when empty)."""
        return get_parameter_values(client, names, timeout_s)

    def run_periods(self, periods: int, timeout_s: float = 60.0) -> np.ndarray:
        """Grant ``periods`` control periods to a paused lockstep rig; returns one row per period (its last
        sample: the position the controller measured)."""
        start, k = self.rows_count, self.samples_per_period
        result = self.set_params(self.hardware, {"lockstep.step_budget": periods})
        if not result[0].successful:
            raise RuntimeError(f"hardware refused the step budget: {result[0].reason}")
        if not self.wait_rows(start + periods * k, timeout_s):
            raise TimeoutError(f"rig did not run {periods} periods within {timeout_s} s")
        time.sleep(0.1)  # let the controller answer the last position (its command is held)
        return self.all_rows()[start:start + periods * k][k - 1::k]

    def wait_for_reference_readers(self, min_readers: int = 1, timeout_s: float = 10.0,
                                   settle_s: float = DISCOVERY_SETTLE_S) -> int:
        """Wait until ``position_reference`` has ``min_readers`` matched readers and their number has not
        changed for ``settle_s`` (a process that has just started discovers the graph's readers one by one;
        a reliable message reaches only those matched when it is sent).  Returns the number of readers."""
        deadline = time.monotonic() + timeout_s
        count, since = -1, time.monotonic()
        while True:
            now = time.monotonic()
            matched = self.reference_pub.get_subscription_count()
            if matched != count:
                count, since = matched, now
            if count >= min_readers and now - since >= settle_s:
                return count
            if now > deadline:
                if count >= min_readers:
                    return count
                raise TimeoutError(f"{count} reader(s) of {self.reference_pub.topic_name} after {timeout_s:g} s, "
                                   f"{min_readers} wanted (is the controller running, in this namespace and ROS "
                                   "domain?)" if count else f"nobody subscribes to {self.reference_pub.topic_name} "
                                   "(is the controller running, in this namespace and ROS domain?)")
            time.sleep(0.02)

    def play_reference(self, times_s: np.ndarray, values_m: np.ndarray, timeout_s: float = 10.0,
                       progress=None, progress_every_s: float = 2.0, keep_going=lambda: True,
                       min_readers: int = 1) -> "PlayResult":
        """Publish ``values_m[k]`` at ``times_s[k]`` on the wall clock, once the readers are found (see
        :meth:`wait_for_reference_readers`), then wait until every reader has them (DDS acknowledges on its
        next heartbeat: up to a few seconds).  ``progress(sent, total, elapsed_s)`` is called every
        ``progress_every_s``; the profile stops early once ``keep_going()`` is False."""
        readers = self.wait_for_reference_readers(min_readers, timeout_s)
        start = time.monotonic()
        last_report = start
        sent = 0
        for k, (t, value) in enumerate(zip(times_s, values_m)):
            while (delay := start + float(t) - time.monotonic()) > 0 and keep_going():
                time.sleep(min(delay, 0.1))
            if not keep_going():
                break
            self.reference_pub.publish(Float64(data=float(value)))
            sent = k + 1
            now = time.monotonic()
            if progress is not None and now - last_report >= progress_every_s:
                last_report = now
                progress(k + 1, len(times_s), now - start)
        sent_s = time.monotonic() - start
        if not self.reference_pub.wait_for_all_acked(Duration(seconds=timeout_s)):
            raise TimeoutError(f"{self.reference_pub.topic_name} not acknowledged within {timeout_s} s")
        return PlayResult(sent, sent_s, time.monotonic() - start - sent_s, readers)

    def set_reference(self, reference_m: float, timeout_s: float = 10.0) -> None:
        """Publish a reference and return once every matched controller has received it (reliable ack).

        In lockstep nothing else moves until the next ``run_periods``: the reference is then in the
        controller's event queue ahead of the first position of the new budget, so it applies from that
        period on (ordered by the acknowledgement, not by a sleep)."""
        self.reference_pub.publish(Float64(data=float(reference_m)))
        if not self.reference_pub.wait_for_all_acked(Duration(seconds=timeout_s)):
            raise TimeoutError(f"position_reference not acknowledged within {timeout_s} s")


def run_in_background(nodes: list[Node]):
    """Spin ``nodes`` in a daemon thread (a real-time hardware node's tick included); returns
    (thread, stop, executor)."""
    executor = make_executor()
    for n in nodes:
        executor.add_node(n)
    stop = threading.Event()
    pacing = claim_pacing(nodes)

    def loop():
        try:
            spin_loop(executor, lambda: rclpy.ok() and not stop.is_set(), pacing)
        except Exception:
            if rclpy.ok() and not stop.is_set():
                raise
    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    return thread, stop, executor
