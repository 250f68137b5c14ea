"""ROS parameter values as YAML, the one way this package reads and writes them (ROS-free).

ROS reads ``-p NAME:=VALUE`` and parameters files as YAML 1.1 through libyaml; so does PyYAML, which is
what every part of this package uses (parameters files, ``valve_command set``, ``node_command`` and the
bags' ``metadata.yaml``).
"""
from __future__ import annotations

import json
from typing import Any

import yaml

__all__ = ["YAMLError", "yaml_value", "load", "dump"]

YAMLError = yaml.YAMLError


def yaml_value(value: Any) -> str:
    """One parameter value as YAML, keeping its ROS type (bool, integer, double, string, double array)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(repr(float(x)) for x in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)  # a double-quoted YAML scalar, also when empty
    if isinstance(value, int):
        return str(value)
    return repr(float(value))


def load(text_or_stream) -> Any:
    """YAML text (or an open file) as Python values (YAMLError when it is not YAML)."""
    return yaml.safe_load(text_or_stream)


def dump(data: Any) -> str:
    """Python values as block-style YAML text, keys in the order given."""
    return yaml.safe_dump(data, default_flow_style=False, sort_keys=False)
