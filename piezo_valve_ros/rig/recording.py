"""Recording a rig's topics into crash-safe rosbag2 bags (``io.bags.BagRecorder``): one recorder for
``valve_record`` and the identification node.

Messages are taken as serialized CDR (``raw=True`` subscriptions) and written with their receive time; a
timer finishes a storage file every ``segment_s`` so that a crash loses at most that much.  The offered QoS
stored for each topic is the rig's own (``common``), so ``ros2 bag play`` offers what the nodes offer.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Optional

from rclpy.node import Node
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_policy_name_from_kind
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64, Float64MultiArray

from ..core.defaults import BAG_STORAGE
from ..io.bags import CLOCK_TYPE, FLOAT64_TYPE, SAMPLES_TYPE, BagRecorder, qos_profile
from ..ros import COMMAND_QOS, REFERENCE_QOS, SAMPLES_QOS, SENSOR_QOS

# topic (relative to the rig's namespace) -> (message type, QoS it is offered with, reliable)
RIG_TOPICS = {"samples": (SAMPLES_TYPE, SAMPLES_QOS, True),
              "voltage_command": (FLOAT64_TYPE, COMMAND_QOS, True),
              "spool_position": (FLOAT64_TYPE, SENSOR_QOS, False),
              "position_reference": (FLOAT64_TYPE, REFERENCE_QOS, True)}
CLOCK_QOS_DEPTH = 10                      # the lockstep hardware's /clock publisher
RECORDER_HISTORY = 1000                   # messages a recorder's reader holds while its executor is busy
REFERENCE_AFTER_SAMPLES_WAIT_S = 5.0      # a deferred reference reader opens this long after start without samples
DEFERRED_TOPIC = "position_reference"
_MESSAGE_CLASSES = {SAMPLES_TYPE: Float64MultiArray, FLOAT64_TYPE: Float64, CLOCK_TYPE: Clock}


class RigRecorder:
    """Subscribes ``node`` to the rig's topics (and ``/clock`` when ``with_clock``); :meth:`start` opens a
    bag, :meth:`stop` closes it.  Messages arriving while no bag is open are not kept."""

    def __init__(self, node: Node, storage: str = BAG_STORAGE, with_clock: bool = False, roll_period_s: float = 0.2,
                 dds_receive_time: bool = False, reference_after_samples: bool = False):
        """``dds_receive_time``: stamp each message with the time DDS received it (what rosbag2 stores),
        not the time the callback ran, which lags whenever the executor is busy; needs an executor that
        passes message info (rclpy's SingleThreadedExecutor does, the EventsExecutor does not).

        ``reference_after_samples``: the ``position_reference`` reader opens only once a ``samples`` message has
        been recorded (or ``REFERENCE_AFTER_SAMPLES_WAIT_S`` after :meth:`start` without one).  A sender that
        waits for its readers (``valve_command --wait-readers``) then sends nothing the bag cannot place on the
        samples' time axis: on a loaded computer discovery matches the topics one by one, seconds apart."""
        self.node = node
        self._deferred: Optional[tuple] = None
        self._samples_recorded = False
        self._started_at: Optional[float] = None
        self._samples_topic = node.resolve_topic_name("samples")
        self.dds_receive_time = dds_receive_time
        self.storage = storage
        self._lock = threading.Lock()
        self._recorder: Optional[BagRecorder] = None
        self.topics: dict[str, tuple[str, object]] = {}
        subscriptions = dict(RIG_TOPICS)
        if with_clock:
            subscriptions["/clock"] = (CLOCK_TYPE, CLOCK_QOS_DEPTH, True)
        for topic, (msgtype, qos, reliable) in subscriptions.items():
            full = node.resolve_topic_name(topic)
            depth = qos if isinstance(qos, int) else qos.depth
            self.topics[full] = (msgtype, qos_profile(reliable, depth))  # what the rig offers, stored in the bag
            # the recorder's own reader keeps more than the rig's depth: on a busy computer its executor falls
            # behind now and then, and a reader's full history drops the oldest message
            reader_qos = QoSProfile(depth=max(depth, RECORDER_HISTORY), history=HistoryPolicy.KEEP_LAST,
                                    reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
            subscription = (_MESSAGE_CLASSES[msgtype], topic, self._callback(full), reader_qos)
            if reference_after_samples and topic == DEFERRED_TOPIC:
                self._deferred = subscription
            else:
                self._subscribe(subscription)
        node.create_timer(roll_period_s, self._roll)

    def _subscribe(self, subscription: tuple) -> None:
        """A raw reader with one event handler: a publisher offering an incompatible QoS is logged (rclpy's default
        handlers also watch for an incompatible type, which these fixed topics cannot meet: each handler is waited on
        in every executor round, a tenth of a recorder's CPU at 1 kHz)."""
        topic = self.node.resolve_topic_name(subscription[1])
        logger = self.node.get_logger()

        def incompatible(event) -> None:
            logger.warning(f"a publisher of {topic} offers a QoS this recorder cannot read "
                           f"({qos_policy_name_from_kind(event.last_policy_kind)}): none of its messages is recorded")
        self.node.create_subscription(*subscription, raw=True, event_callbacks=SubscriptionEventCallbacks(
            incompatible_qos=incompatible, use_default_callbacks=False))

    def _callback(self, topic: str):
        is_samples = topic == self._samples_topic

        def on_message(data: bytes) -> None:
            with self._lock:
                if self._recorder is not None:
                    self._recorder.write(topic, time.time_ns(), data)
                    self._samples_recorded |= is_samples

        def on_message_with_info(data: bytes, info: dict) -> None:
            stamp = info.get("received_timestamp") or time.time_ns()
            with self._lock:
                if self._recorder is not None:
                    self._recorder.write(topic, stamp, data)
                    self._samples_recorded |= is_samples
        return on_message_with_info if self.dds_receive_time else on_message

    def _roll(self) -> None:
        with self._lock:
            if self._recorder is not None:
                self._recorder.maybe_roll()
            open_reference = self._deferred is not None and self._started_at is not None and (
                self._samples_recorded or time.monotonic() - self._started_at >= REFERENCE_AFTER_SAMPLES_WAIT_S)
        if open_reference:
            self.reference_reader_open()

    def reference_reader_open(self) -> None:
        """Open a deferred ``position_reference`` reader now (see ``reference_after_samples``)."""
        if self._deferred is not None:
            subscription, self._deferred = self._deferred, None
            self._subscribe(subscription)

    @property
    def reading_references(self) -> bool:
        """Whether the ``position_reference`` reader is open."""
        return self._deferred is None

    @property
    def recording(self) -> bool:
        with self._lock:
            return self._recorder is not None

    def publishers(self) -> dict[str, int]:
        """How many publishers each recorded topic has now (0 everywhere: no rig in this namespace)."""
        return {topic: self.node.count_publishers(topic) for topic in self.topics}

    def start(self, path: str | Path) -> Path:
        """Open a new bag at ``path`` (which must not exist); BagError otherwise."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        recorder = BagRecorder(path, self.topics, self.storage)
        with self._lock:
            if self._recorder is not None:
                recorder.close()
                raise RuntimeError("a bag is open already")
            self._recorder = recorder
            self._started_at = time.monotonic()
        return path

    def stop(self) -> dict[str, int]:
        """Close the bag (idempotent); messages per topic."""
        with self._lock:
            recorder, self._recorder = self._recorder, None
        if recorder is None:
            return {}
        recorder.close()
        return recorder.message_counts
