"""How the package's processes run: the real-time settings a loop asks the operating system for (``realtime``),
the loop's timing as the hardware sees it (``loop_timing``), the middleware setting for acknowledged references
(``dds``), child processes that die with their parent (``processes``), the allocator's settings for processes
that analyse records (``memory``), and the hardware's loop over a backend (``hardware_loop``: read, check, write, the
watchdog, the fault latch, the batch, the pacing).  No ROS import."""
from __future__ import annotations

from ..core import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "RealtimeSettings": "realtime",
    "LoopTiming": "loop_timing",
    "LoopSummary": "loop_timing",
    "use_fast_acknowledgements": "dds",
    "ProcessGroup": "processes",
    "node_command": "processes",
    "keep_freed_memory": "memory",
    "Throttle": "throttle",
    "HardwareLoop": "hardware_loop",
    "LoopSettings": "hardware_loop",
    "FAST_ACK_PROFILE": "dds",
    "HEARTBEAT_PERIOD_S": "dds",
    "NODE_MODULES": "processes",
    "PARENT_DEATH_GRACE_S": "processes",
    "available_cpus": "realtime",
    "pin": "realtime",
    "release_cpu_wakeup_latency": "realtime",
    "without_fast_acknowledgements": "dds",
})
