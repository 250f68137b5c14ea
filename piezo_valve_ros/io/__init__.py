"""Files and messages: rosbag2 bags (``bags``), ROS parameter values as YAML (``params_yaml``), the contract's
``samples`` matrix (``samples``) and PNG figures (``plots``, optional: needs matplotlib).  No ROS import."""
from __future__ import annotations

from ..core import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "BagError": "bags",
    "BagRecorder": "bags",
    "read_samples": "bags",
    "write_samples_bag": "bags",
    "node_section": "params_yaml",
    "yaml_value": "params_yaml",
    "SAMPLES_COLUMNS": "samples",
    "SamplesLayoutError": "samples",
    "decode_samples": "samples",
    "FLOAT64_TYPE": "bags",
    "SAMPLES_TYPE": "bags",
    "TYPESTORE": "bags",
    "qos_profile": "bags",
    "read_run": "bags",
    "require": "plots",
    "serialize_float64": "bags",
    "serialize_samples": "bags",
})
