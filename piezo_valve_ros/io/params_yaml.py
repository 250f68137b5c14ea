"""ROS parameter values as YAML, the one way this package reads and writes them (ROS-free).

ROS reads ``-p NAME:=VALUE`` and parameters files as YAML 1.1 through libyaml; so does PyYAML, which is
what every part of this package uses (parameters files, ``valve_command set``, ``node_command`` and the
bags' ``metadata.yaml``).
"""
from __future__ import annotations

import json
from typing import Any

import yaml

__all__ = ["YAMLError", "yaml_value", "load", "dump", "node_section"]

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


def node_section(path, node: str, wildcard: bool = True) -> dict:
    """The ``ros__parameters`` a ROS parameters file gives the node called ``node`` (e.g. ``valve_controller``):
    its ``/**`` section (unless not ``wildcard``: what the file names for this node alone), then every section
    whose last name element is the node's (``valve_controller``, ``/**/valve_controller``,
    ``/ns/valve_controller``), later ones winning.  ValueError (or OSError) with the reason when the file is not
    YAML, has no such section, or a section is not a parameters mapping."""
    name = node.rstrip("/").split("/")[-1]
    try:
        with open(path) as f:
            doc = load(f)
    except YAMLError as exc:
        raise ValueError(f"{path} is not YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a mapping of node names, got {type(doc).__name__}")
    keys = ([k for k in doc if str(k) == "/**"] if wildcard else []) + [
        k for k in doc if str(k).rstrip("/").split("/")[-1] == name]
    if not keys:
        raise ValueError(f"{path}: no section for {name} (sections: {', '.join(map(str, doc)) or 'none'})")
    values = {}
    for k in keys:
        section = doc[k].get("ros__parameters") if isinstance(doc[k], dict) else None
        if not isinstance(section, dict):
            raise ValueError(f"{path}: section {k} has no ros__parameters mapping")
        values.update(section)
    return values
