"""The middleware setting of the processes that wait for a reference's acknowledgement.  No ROS import.

With Fast DDS 2.x (ROS 2 Jazzy's default middleware) a reliable writer learns that its readers hold a sample
only from their answer to its periodic heartbeat, every 3 s by default, so ``Publisher.wait_for_all_acked``
returns up to 3 s after a publish even on one machine (Fast DDS sends a heartbeat from ``wait_for_all_acked``
itself from 2.14.6 and 3.3 on: eProsima/Fast-DDS#6098).  ``valve_command``, ``valve_rig`` and the tests publish
references and wait for them to be acknowledged (in lockstep that is what orders a reference before the next
period), so those processes load a profile whose writers send a heartbeat every ``HEARTBEAT_PERIOD_S``,
unless the user has chosen a Fast DDS profiles file or another middleware.  The nodes they start run on the
middleware's defaults (:func:`without_fast_acknowledgements`).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import MutableMapping, Optional

__all__ = ["FAST_ACK_PROFILE", "HEARTBEAT_PERIOD_S", "PROFILES_FILE_VARIABLES", "use_fast_acknowledgements",
           "without_fast_acknowledgements"]

FAST_ACK_PROFILE = Path(__file__).with_name("fast_ack_profile.xml")
HEARTBEAT_PERIOD_S = 0.02            # what the profile sets (its <heartbeatPeriod>)
PROFILES_FILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")  # Fast DDS 2.x, 3.x
_OURS = PROFILES_FILE_VARIABLES[0]   # the variable Fast DDS 2.x (Jazzy) reads


def use_fast_acknowledgements(environ: Optional[MutableMapping[str, str]] = None) -> bool:
    """Before ``rclpy.init``: choose the fast-acknowledgement profile for this process's Fast DDS writers.
    Nothing when another middleware is chosen (``RMW_IMPLEMENTATION``) or a profiles file already is.
    Returns whether the profile was chosen."""
    environ = os.environ if environ is None else environ
    if not environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        return False
    if any(environ.get(name) for name in PROFILES_FILE_VARIABLES):
        return environ.get(_OURS) == str(FAST_ACK_PROFILE)
    environ[_OURS] = str(FAST_ACK_PROFILE)
    return True


def without_fast_acknowledgements(environ: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """``environ`` (changed in place) without the profile :func:`use_fast_acknowledgements` chose: for the
    nodes a launcher starts.  A profiles file the user chose stays."""
    if environ.get(_OURS) == str(FAST_ACK_PROFILE):
        del environ[_OURS]
    return environ
