"""What the package's offline tools (``valve_identify``, ``valve_tune``, ``valve_plot``) share: how they end (one
clear line, an exit code) and the window of a long record they may read.

ROS-free; a tool's ``main`` parses its arguments and hands its work to :func:`run_tool`.
"""
from __future__ import annotations

import argparse
import sys
from typing import Callable

from ..core.errors import PiezoValveError
from ..core.runs import TimeWindow

__all__ = ["run_tool", "add_window_arguments", "window_from"]


def add_window_arguments(ap: argparse.ArgumentParser, what: str) -> None:
    """``--from``/``--to`` [s] and ``--stamps``: a stretch of a long record (``core.runs.TimeWindow``)."""
    group = ap.add_argument_group("a window of a long record", what)
    group.add_argument("--from", dest="from_s", type=float, metavar="S",
                       help="start of the window [s] (default: the record's start)")
    group.add_argument("--to", dest="to_s", type=float, metavar="S", help="end of the window [s] (default: the record's end)")
    group.add_argument("--stamps", action="store_true", help="--from/--to are on the samples' own time axis (the "
                       "times the hardware stamped them with), not seconds from the record's first sample")


def window_from(ap: argparse.ArgumentParser, args: argparse.Namespace) -> TimeWindow:
    """The window the arguments ask for; a malformed one ends the tool as a usage error (exit 2, one line)."""
    window = TimeWindow(args.from_s, args.to_s, args.stamps)
    if args.stamps and window.whole:
        ap.error("--stamps needs --from or --to")
    if window.problems():
        ap.error("; ".join(window.problems()))
    return window


def run_tool(prog: str, work: Callable[[], list[str]], bad_input: tuple[type[BaseException], ...] = ()) -> int:
    """Run ``work`` (it returns the lines to print when it succeeds); any failure ends with one line on
    stderr and never a traceback.  Exit codes: 0 done, 2 bad input (a ``PiezoValveError``, one of
    ``bad_input`` or an OSError: a path), 130 interrupted (nothing written), 1 anything else."""
    try:
        lines = work()
    except (PiezoValveError, *bad_input, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; nothing written", file=sys.stderr)
        return 130
    except Exception as exc:  # one clear line, never a traceback
        print(f"{prog}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print("\n".join(lines))
    return 0
