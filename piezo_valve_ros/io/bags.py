"""rosbag2 bags with ``rosbags`` (no ROS import): a crash-safe recorder and the ``samples`` reader.

Crash safety: the recorder buffers at most one segment (default 1 s) in memory; each segment is
written as a complete, closed storage file (``<bag>_<k>.mcap`` or ``.db3``) and the bag's
``metadata.yaml`` (rosbag2 version 9, as Jazzy writes) is rewritten atomically to list every
finished file.  Whatever kills the recorder, the bag on disk is a valid multi-file rosbag2 bag
holding everything up to the last finished segment, which ``ros2 bag play`` and ``rosbags`` read.
"""
from __future__ import annotations

import math
import os
import shutil
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_typestore

from ..core.defaults import BAG_STORAGE
from ..core.errors import PiezoValveError
from ..core.runs import WHOLE_RECORD, TimeWindow, receive_to_sample_time
from .params_yaml import dump as dump_yaml, load as load_yaml
from .samples import SAMPLES_COLUMNS, SAMPLES_LABEL, SamplesLayoutError, decode_samples

__all__ = ["BagError", "BagRecorder", "qos_profile", "read_samples", "write_samples_bag", "SAMPLES_TYPE",
           "FLOAT64_TYPE", "CLOCK_TYPE", "TYPESTORE", "serialize_samples", "serialize_float64", "SAMPLES_COLUMNS"]

BAG_VERSION = 9  # rosbag2 metadata version written by Jazzy
STORAGES = {"mcap": (StoragePlugin.MCAP, ".mcap"), "sqlite3": (StoragePlugin.SQLITE3, ".db3")}
SAMPLES_TYPE = "std_msgs/msg/Float64MultiArray"
FLOAT64_TYPE = "std_msgs/msg/Float64"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


class BagError(PiezoValveError, RuntimeError):
    """A bag that cannot be written or read (one-line message)."""


def qos_profile(reliable: bool, depth: int, transient_local: bool = False) -> Qos:
    """An offered QoS profile as rosbag2 stores it (so ``ros2 bag play`` offers the same)."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


def serialize_samples(rows: np.ndarray, label: str = SAMPLES_LABEL) -> bytes:
    """CDR bytes of a contract ``samples`` message (rows: N x k)."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    n, k = rows.shape
    T = TYPESTORE.types
    msg = T["std_msgs/msg/Float64MultiArray"](
        layout=T["std_msgs/msg/MultiArrayLayout"](
            dim=[T["std_msgs/msg/MultiArrayDimension"](label="sample", size=n, stride=n * k),
                 T["std_msgs/msg/MultiArrayDimension"](label=label, size=k, stride=k)], data_offset=0),
        data=rows.ravel())
    return bytes(TYPESTORE.serialize_cdr(msg, SAMPLES_TYPE))


def serialize_float64(value: float) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(TYPESTORE.types[FLOAT64_TYPE](data=float(value)), FLOAT64_TYPE))


class BagRecorder:
    """Records serialized messages into a crash-safe, segmented rosbag2 bag.

    ``topics`` maps topic name -> (message type, offered QoS).  ``write`` takes CDR bytes (e.g. from an
    rclpy subscription with ``raw=True``) and a receive time in ns.
    """

    def __init__(self, path: str | os.PathLike, topics: dict[str, tuple[str, Qos]], storage: str = BAG_STORAGE,
                 segment_s: float = 1.0, clock: Callable[[], float] = time.monotonic):
        if storage not in STORAGES:
            raise BagError(f"unknown storage {storage!r}; use one of {', '.join(STORAGES)}")
        if not segment_s > 0:
            raise BagError(f"segment_s must be > 0, got {segment_s}")
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path} exists already; every run gets a new bag directory")
        self.topics = dict(topics)
        self.storage = storage
        self.segment_s = float(segment_s)
        self._clock = clock
        self._buffer: list[tuple[str, int, bytes]] = []
        self._segment_started = clock()
        self._files: list[dict] = []
        self._counts = {t: 0 for t in self.topics}
        self._start_ns: Optional[int] = None
        self._end_ns = 0
        self._closed = False
        self.path.mkdir(parents=True)
        self._write_metadata()  # an empty but valid bag from the start

    # -- recording
    def write(self, topic: str, timestamp_ns: int, data: bytes) -> None:
        if self._closed:
            raise BagError("recorder is closed")
        if topic not in self.topics:
            raise BagError(f"topic {topic!r} was not declared to the recorder")
        self._buffer.append((topic, int(timestamp_ns), bytes(data)))
        self.maybe_roll()

    def maybe_roll(self) -> None:
        """Finish the segment when it is ``segment_s`` old (call it from a timer when messages may stop)."""
        if self._clock() - self._segment_started >= self.segment_s:
            self.roll()

    def roll(self) -> None:
        """Write the buffered messages as one complete storage file and update metadata.yaml."""
        self._segment_started = self._clock()
        if not self._buffer:
            return
        buffer, self._buffer = self._buffer, []
        plugin, suffix = STORAGES[self.storage]
        k = len(self._files)
        name = f"{self.path.name}_{k}"
        tmp = self.path / f".{name}.partial"
        if tmp.exists():
            shutil.rmtree(tmp)
        writer = Writer(tmp, version=BAG_VERSION, storage_plugin=plugin)
        writer.open()
        conns = {}
        for topic in sorted({t for t, _, _ in buffer}):
            msgtype, qos = self.topics[topic]
            conns[topic] = writer.add_connection(topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=[qos])
        counts: dict[str, int] = {}
        for topic, stamp, data in buffer:
            writer.write(conns[topic], stamp, data)
            counts[topic] = counts.get(topic, 0) + 1
        writer.close()
        final = self.path / (name + suffix)
        os.replace(tmp / (tmp.name + suffix), final)
        shutil.rmtree(tmp, ignore_errors=True)
        stamps = [s for _, s, _ in buffer]
        first, last = min(stamps), max(stamps)
        self._files.append({"path": final.name, "starting_time": {"nanoseconds_since_epoch": first},
                            "duration": {"nanoseconds": last - first}, "message_count": len(buffer)})
        for topic, c in counts.items():
            self._counts[topic] += c
        self._start_ns = first if self._start_ns is None else min(self._start_ns, first)
        self._end_ns = max(self._end_ns, last)
        self._write_metadata()

    def close(self) -> None:
        if self._closed:
            return
        self.roll()
        self._closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def message_counts(self) -> dict[str, int]:
        return dict(self._counts)

    def _write_metadata(self) -> None:
        start = self._start_ns or 0
        info = {
            "version": BAG_VERSION,
            "storage_identifier": self.storage,
            "relative_file_paths": [f["path"] for f in self._files],
            "duration": {"nanoseconds": max(self._end_ns - start, 0)},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(self._counts.values()),
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic, "type": msgtype, "serialization_format": "cdr",
                                    "offered_qos_profiles": dump_qos_v9([qos]),
                                    "type_description_hash": TYPESTORE.hash_rihs01(msgtype)},
                 "message_count": self._counts[topic]}
                for topic, (msgtype, qos) in self.topics.items() if self._counts[topic]],
            "compression_format": "",
            "compression_mode": "",
            "files": list(self._files),
            "custom_data": None,
            "ros_distro": "jazzy",
        }
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(dump_yaml({"rosbag2_bagfile_information": info}), "utf8")
        os.replace(tmp, self.path / "metadata.yaml")


def write_samples_bag(path, rows: np.ndarray, topic: str = "/samples", storage: str = BAG_STORAGE,
                      batch: int = 1000, start_ns: int = 1_700_000_000_000_000_000,
                      label: str = SAMPLES_LABEL) -> None:
    """A bag holding ``rows`` on a ``samples`` topic (offline use and tests)."""
    rows = np.asarray(rows, float)
    clock_state = [0.0]
    rec = BagRecorder(path, {topic: (SAMPLES_TYPE, qos_profile(True, 100))}, storage,
                      segment_s=float("inf"), clock=lambda: clock_state[0])
    for i in range(0, rows.shape[0], batch):
        chunk = rows[i:i + batch]
        rec.write(topic, start_ns + int(round(chunk[-1, 0] * 1e9)), serialize_samples(chunk, label))
    rec.close()


def _is_samples_topic(conn, topic: Optional[str]) -> bool:
    if conn.msgtype != SAMPLES_TYPE:
        return False
    return conn.topic == topic if topic is not None else conn.topic.rstrip("/").split("/")[-1] == "samples"


class _SamplesDecoder:
    """CDR ``samples`` messages -> (N, 3) blocks of time, voltage, position (``samples.decode_samples``)."""

    def __init__(self, name: str):
        self.name = name

    def __call__(self, raw: bytes, msgtype: str) -> np.ndarray:
        msg = TYPESTORE.deserialize_cdr(raw, msgtype)
        try:
            return decode_samples(msg.layout.dim, msg.data, self.name)
        except SamplesLayoutError as exc:
            raise BagError(str(exc)) from None


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def _read_file_by_file(path: Path, topic: Optional[str], skipped: list[str]) -> tuple[list[np.ndarray], str]:
    """The bag's storage files one at a time (a crash or a copy can damage one segment of a multi-file bag):
    the blocks of every readable file and the topic's name; each unreadable file is named in ``skipped``.
    No blocks when nothing is readable (or the bag is compressed)."""
    from rosbags.rosbag2.reader import DirectoryReader
    try:
        meta = load_yaml((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        plugin = DirectoryReader.STORAGE_PLUGINS[meta["storage_identifier"]]
        files = [path / Path(x).name for x in meta["relative_file_paths"]]
        if meta.get("compression_mode"):
            return [], ""
    except Exception:
        return [], ""
    decode: Optional[_SamplesDecoder] = None
    parts: list[np.ndarray] = []
    for f in files:
        storage = None
        try:
            storage = plugin(f)
            storage.open()
            conns = [c for c in storage.connections if _is_samples_topic(c, topic)]
            names = sorted({c.topic for c in conns})
            if len(names) > 1:
                raise BagError(f"bag {path} has several samples topics ({', '.join(names)}); choose one with --topic")
            if decode is None and names:
                decode = _SamplesDecoder(names[0])
            if decode is not None:
                conns = [c for c in conns if c.topic == decode.name]
            blocks = [decode(raw, conn.msgtype) for conn, _, raw in storage.messages(conns)] if conns else []
        except BagError:
            raise
        except Exception as exc:
            skipped.append(f"{f.name} ({_first_line(exc)})")
            continue
        finally:
            if storage is not None:
                try:
                    storage.close()
                except Exception:
                    pass
        parts += blocks
    return parts, decode.name if decode is not None else ""


def _time_ordered(parts: list[np.ndarray]) -> np.ndarray:
    rows = np.concatenate(parts) if parts else np.zeros((0, len(SAMPLES_COLUMNS)))
    if rows.shape[0] == 0:
        return rows
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    keep = np.concatenate(([True], np.diff(rows[:, 0]) > 0))  # a batch delivered twice counts once
    return rows[keep]


def _in_window(path: Path, rows: np.ndarray, window: TimeWindow, first_s: float, last_s: float) -> np.ndarray:
    if rows.shape[0] == 0:
        raise BagError(f"bag {path}: no samples from {window.describe()} (its samples run from {first_s:.3f} s to "
                       f"{last_s:.3f} s on their own time axis, {last_s - first_s:.3f} s long)")
    return rows


def _damaged(path: Path, topic: Optional[str], skipped: Optional[list[str]], reason: str,
             window: TimeWindow = WHOLE_RECORD, extent: Optional[dict] = None,
             each_block: Optional[Callable[[np.ndarray], None]] = None) -> tuple[np.ndarray, str]:
    """The whole-bag read failed: what the intact files hold (in ``window``), or the one-line error."""
    skips: list[str] = []
    parts, name = _read_file_by_file(path, topic, skips)
    if not parts:
        raise BagError(f"cannot read bag {path} (truncated or corrupt?): {reason}")
    if skipped is not None:
        skipped += skips
    rows = _time_ordered(parts)
    if each_block is not None:
        each_block(rows)
    if extent is not None:
        extent.update(first_s=float(rows[0, 0]), last_s=float(rows[-1, 0]))
    return _in_window(path, window.rows(rows, rows[0, 0]), window, rows[0, 0], rows[-1, 0]), name


def read_samples(path, topic: Optional[str] = None, skipped: Optional[list[str]] = None,
                 window: TimeWindow = WHOLE_RECORD, extent: Optional[dict] = None,
                 each_block: Optional[Callable[[np.ndarray], None]] = None) -> tuple[np.ndarray, str]:
    """Rows (time [s], voltage [V], position [m]) of the bag's ``samples`` topic, time-ordered; and its name.

    Any namespace is accepted (a topic whose last name is ``samples``); ``topic`` picks one explicitly.
    ``window``: only the rows in that stretch are kept as the messages are decoded (and reading stops past
    its end), so a window of a long bag costs the window's memory, not the bag's; ``extent`` (a dict) receives the
    whole record's first and last sample times (``first_s``, ``last_s`` [s]: the messages past the window are
    skipped undecoded but the last).  A multi-file bag with
    damaged storage files is read file by file: the intact ones are used and each file left out is appended
    to ``skipped`` (name and reason).  ``each_block`` receives every block of rows of the whole bag as it is decoded
    (in the bag's order; after a damaged read, all the intact files hold in one block: a receiver that drops rows
    at or before the last it took, as ``BlockMeans`` does, continues where it was), so the part past ``window`` is
    streamed through it instead of skipped (``core.identification.whole_record.BlockMeans`` reduces a long record so).  Raises BagError with a one-line reason when nothing is readable or the
    window holds no samples.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"no bag at {path}")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises several types; the message is what matters
        if (path / "metadata.yaml").exists():
            return _damaged(path, topic, skipped, _first_line(exc), window, extent, each_block)
        raise BagError(f"cannot read bag {path}: {_first_line(exc)}") from None
    try:
        conns = [c for c in reader.connections if c.msgtype == SAMPLES_TYPE]
        if topic is not None:
            chosen = [c for c in conns if c.topic == topic]
            if not chosen:
                raise BagError(f"bag {path} has no Float64MultiArray topic {topic!r} "
                               f"(topics: {', '.join(sorted({c.topic for c in reader.connections})) or 'none'})")
        else:
            chosen = [c for c in conns if c.topic.rstrip("/").split("/")[-1] == "samples"]
            names = sorted({c.topic for c in chosen})
            if not chosen:
                raise BagError(f"bag {path} has no samples topic (topics: "
                               f"{', '.join(sorted({c.topic for c in reader.connections})) or 'none'})")
            if len(names) > 1:
                raise BagError(f"bag {path} has several samples topics ({', '.join(names)}); choose one with --topic")
        name = chosen[0].topic
        decode = _SamplesDecoder(name)
        parts: list[np.ndarray] = []
        first_s = last_s = math.nan
        hi = math.inf
        past: Optional[tuple] = None   # the last message past the window, undecoded
        try:
            for conn, _, raw in reader.messages(connections=chosen):
                if past is not None:
                    past = (raw, conn.msgtype)
                    continue
                block = decode(raw, conn.msgtype)
                if block.shape[0] == 0:
                    continue
                if each_block is not None:
                    each_block(block)
                if math.isnan(first_s):
                    first_s = float(block[0, 0])
                    hi = window.bounds(first_s)[1]
                last_s = max(float(block[-1, 0]), last_s) if not math.isnan(last_s) else float(block[-1, 0])
                if block[0, 0] > hi:   # messages come in time order: the rest lies past the window
                    if each_block is not None:
                        continue
                    if extent is None:
                        break
                    past = (raw, conn.msgtype)
                    continue
                parts.append(block if window.whole else window.rows(block, first_s))
            if past is not None:
                tail = decode(*past)
                last_s = max(last_s, float(tail[-1, 0])) if tail.shape[0] else last_s
        except BagError:
            raise
        except Exception as exc:
            return _damaged(path, topic, skipped, _first_line(exc), window, extent, each_block)
        if math.isnan(first_s):
            raise BagError(f"bag {path}: topic {name} holds no messages")
        if extent is not None:
            extent.update(first_s=first_s, last_s=last_s)
        return _in_window(path, _time_ordered(parts), window, first_s, last_s), name
    finally:
        reader.close()


def read_run(path, topic: Optional[str] = None,
             window: TimeWindow = WHOLE_RECORD) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """A recorded run for plotting: the ``samples`` rows in ``window`` (see :func:`read_samples`), and the
    references sent up to the window's end
    on the ``position_reference`` topic of the same namespace as (times [s] on the samples' time axis,
    positions [m]); its samples topic's name.

    References carry only their receive time.  They are put on the samples' axis through messages that pair a
    receive time with a sample time (``core.runs.receive_to_sample_time``): each ``spool_position`` message
    (the hardware publishes the sample's own position value, found among the rows), each lockstep ``/clock``
    message, and each ``samples`` message's last row.  Piecewise, so the map follows a lockstep rig whose
    simulated time runs at a varying share of the wall clock.  No reference topic or no messages: empty arrays.
    """
    rows, name = read_samples(path, topic, window=window)
    namespace = name.rsplit("/", 1)[0]
    ref_topic, position_topic, clock_topic = (f"{namespace}/position_reference", f"{namespace}/spool_position",
                                              "/clock")
    pair_stamps, pair_times, stamps, values, positions = [], [], [], [], []
    sample_period = float(np.median(np.diff(rows[:, 0]))) if rows.shape[0] > 1 else 0.0
    try:
        with Reader(Path(path)) as reader:
            samples = [c for c in reader.connections if c.topic == name]
            others = [c for c in reader.connections if (c.topic in (ref_topic, position_topic) and c.msgtype == FLOAT64_TYPE)
                      or (c.topic == clock_topic and c.msgtype == CLOCK_TYPE)]
            decode = _SamplesDecoder(name)
            for conn, stamp, raw in reader.messages(connections=samples + others):
                if conn.topic == name:
                    block = decode(raw, conn.msgtype)
                    if block.size:
                        pair_stamps.append(stamp * 1e-9)
                        pair_times.append(block[-1, 0])
                elif conn.topic == clock_topic:
                    clock = TYPESTORE.deserialize_cdr(raw, CLOCK_TYPE).clock
                    pair_stamps.append(stamp * 1e-9)
                    pair_times.append(clock.sec + clock.nanosec * 1e-9 - sample_period)  # /clock: the next sample's
                elif conn.topic == position_topic:
                    positions.append((stamp * 1e-9, TYPESTORE.deserialize_cdr(raw, FLOAT64_TYPE).data))
                else:
                    stamps.append(stamp * 1e-9)
                    values.append(TYPESTORE.deserialize_cdr(raw, FLOAT64_TYPE).data)
    except BagError:
        raise
    except Exception as exc:
        raise BagError(f"cannot read the references in {path}: {_first_line(exc)}") from None
    if not values or not pair_stamps:
        return rows, np.zeros(0), np.zeros(0), name
    if positions:   # a published position is a sample's own value: the sample it was published for
        unique, first, counts = np.unique(rows[:, 2], return_index=True, return_counts=True)
        at = dict(zip(unique[counts == 1].tolist(), rows[first[counts == 1], 0].tolist()))
        for stamp, value in positions:
            if value in at:
                pair_stamps.append(stamp)
                pair_times.append(at[value])
    order = np.argsort(stamps, kind="stable")
    to_sample_time = receive_to_sample_time(np.asarray(pair_stamps), np.asarray(pair_times))
    ref_t, ref_m = to_sample_time(np.asarray(stamps)[order]), np.asarray(values, float)[order]
    keep = ref_t <= rows[-1, 0]   # those before the window too: the one in force at its start
    return rows, ref_t[keep], ref_m[keep], name

