"""Talking to a running rig from another process or thread: references, parameters and samples (``client``), and
recording its topics into crash-safe bags (``recording``).  Used by the command-line tools and the
identification node."""
from __future__ import annotations

from ..core import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "RigClient": "client",
    "run_in_background": "client",
    "RigRecorder": "recording",
})
