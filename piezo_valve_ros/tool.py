"""How the package's offline tools (``valve_identify``, ``valve_tune``) end: one clear line, an exit code.

ROS-free; a tool's ``main`` parses its arguments and hands its work to :func:`run_tool`.
"""
from __future__ import annotations

import sys
from typing import Callable

from .core.errors import PiezoValveError

__all__ = ["run_tool"]


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
