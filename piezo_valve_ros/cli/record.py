"""``valve_record``: record a running rig to a rosbag2 bag (no ``ros2 bag`` needed).

    valve_record run1                          # until Ctrl-C / SIGTERM
    valve_record --duration 20 run1            # 20 s
    valve_record --namespace /rig2 run1        # a rig started with valve_rig --namespace /rig2

Records ``samples``, ``voltage_command``, ``spool_position``, ``position_reference`` (and ``/clock``, which
only a lockstep rig publishes) with their offered QoS and the time DDS received them into a crash-safe bag (one storage file a second;
``valve_identify``, ``valve_plot`` and ``ros2 bag info`` read it) and ends with one line: duration,
messages per topic, size on disk, and the rows of ``samples`` missing between the first and the last one
(dropped).

It reads ``position_reference`` from the first recorded ``samples`` message on (or 5 s after start without
one), so a ``valve_command --wait-readers`` that counts it sends only references the bag places on the samples'
time axis.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor

from ..core.defaults import BAG_STORAGE
from ..io.bags import STORAGES, BagError, read_samples
from ..ros import close, init_ros, spin_loop, split_ros_args, stop_requested
from ..rig.recording import RigRecorder

NO_RIG_WARNING_S = 5.0   # warn when nothing publishes the rig's topics this long after start


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="valve_record", description=__doc__.split("\n\n")[0],
                                 epilog="ROS arguments may follow --ros-args.")
    ap.add_argument("out", help="bag directory to create (must not exist)")
    ap.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: Ctrl-C)")
    ap.add_argument("--namespace", default="", help="the rig's namespace (default: the root)")
    ap.add_argument("--storage", default=BAG_STORAGE, choices=sorted(STORAGES), help=f"storage plugin (default {BAG_STORAGE})")
    ap.add_argument("--json", action="store_true", help="end with one JSON object instead of the summary line")
    return ap.parse_args(argv)


def dropped_sample_rows(times_s: np.ndarray) -> int:
    """Rows missing from a ``samples`` time column [s] between its first and last row (gaps of the
    median sample period)."""
    if times_s.size < 3:
        return 0
    steps = np.diff(times_s)
    dt = float(np.median(steps))
    if not dt > 0:
        return 0
    return int(np.sum(np.maximum(np.rint(steps / dt) - 1, 0)))


def bag_size_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def summary(path: Path, elapsed_s: float, counts: dict[str, int]) -> dict:
    """What went into the bag: duration [s], messages per topic, size [bytes], samples rows, rows dropped."""
    rows = None
    if any(t.endswith("/samples") and n for t, n in counts.items()):
        try:
            rows, _ = read_samples(path)
        except BagError:
            pass
    return {"bag": str(path), "duration_s": round(elapsed_s, 3), "messages": dict(counts),
            "bytes": bag_size_bytes(path), "samples_rows": 0 if rows is None else int(rows.shape[0]),
            "dropped": dropped_sample_rows(rows[:, 0]) if rows is not None and rows.size else 0}


def summary_line(path: Path, elapsed_s: float, counts: dict[str, int]) -> str:
    """The closing line: what went into the bag."""
    s = summary(path, elapsed_s, counts)
    per_topic = ", ".join(f"{t} {n}" for t, n in counts.items())
    return (f"valve_record: {path}: {elapsed_s:.1f} s, {sum(counts.values())} messages ({per_topic or 'none'}), "
            f"{s['bytes'] / 1e6:.2f} MB, samples rows {s['samples_rows']}, dropped {s['dropped']}")


def main(argv=None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = parse_args(own)
    if args.duration is not None and not args.duration > 0:
        print(f"valve_record: --duration must be > 0, got {args.duration}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists():
        print(f"valve_record: {out} exists already; every recording gets a new bag directory", file=sys.stderr)
        return 2
    init_ros(["valve_record"] + ros_args, shutdown_deadline_s=None)   # (its bag is closed whole, however long)
    # no parameter services: the recorder has no parameters to serve, and each service is waited on in every
    # executor round (a recorder reads three messages a period from a lockstep rig)
    node = rclpy.create_node("valve_record", namespace=args.namespace or None, start_parameter_services=False)
    executor = SingleThreadedExecutor()  # passes message info: each message keeps DDS's receive time
    executor.add_node(node)
    recorder = RigRecorder(node, args.storage, with_clock=True, dds_receive_time=True, reference_after_samples=True)
    started = time.monotonic()
    try:
        recorder.start(out)
        print(f"valve_record: recording {', '.join(recorder.topics)} to {out}"
              + (f" for {args.duration:g} s" if args.duration else "; Ctrl-C or SIGTERM to stop"), flush=True)
        end = started + args.duration if args.duration else float("inf")
        warned = False

        def keep_going() -> bool:
            nonlocal warned
            now = time.monotonic()
            if not warned and now - started > NO_RIG_WARNING_S:   # asked once (a graph query on every spin costs)
                warned = True
                if not any(recorder.publishers().values()):
                    print(f"valve_record: nothing publishes {', '.join(recorder.topics)} yet (is the rig running in "
                          f"namespace {args.namespace or '/'}?); still recording", file=sys.stderr, flush=True)
            return now < end and rclpy.ok() and not stop_requested()
        spin_loop(executor, keep_going)
    except (BagError, OSError) as exc:
        print(f"valve_record: {exc}", file=sys.stderr)
        return 1
    finally:
        counts = recorder.stop()
        elapsed = time.monotonic() - started
        close([node], executor)
    print(json.dumps(summary(out, elapsed, counts)) if args.json else summary_line(out, elapsed, counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
