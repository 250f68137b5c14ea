"""Write the nodes' parameter tables (docs/handbook/parameters.md) from their one declaration each.

    python scripts/parameter_tables.py [--check]

``--check`` writes nothing and exits 1 when the file differs from what the declarations give (the tests
run it, so the tables cannot drift from the code).
"""
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "docs" / "handbook" / "parameters.md"


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|")


def tables() -> str:
    from piezo_valve_ros.nodes.controller import CONTROLLER_PARAMETERS
    from piezo_valve_ros.backends import backend_parameters
    from piezo_valve_ros.nodes.hardware import HARDWARE_PARAMETERS
    from piezo_valve_ros.nodes.identification import IDENTIFICATION_PARAMETERS
    from piezo_valve_ros.nodes.monitor import MONITOR_PARAMETERS
    lines = ["# Node parameters", "",
             "Written by `scripts/parameter_tables.py` from each node's declaration (the one the node declares, "
             "checks and prints for `--help` from); do not edit by hand. Read-only parameters are taken at "
             "start-up only. `valve_hardware`'s table ends with the built-in simulated backend's own `sim.*` "
             "parameters (a backend installed under the entry-point group adds its own; `valve_hardware --help` "
             "lists them); the controller's model schema is described in [the interface](interface.md).", ""]
    for node, specs in (("valve_hardware", HARDWARE_PARAMETERS + backend_parameters("sim")), ("valve_controller", CONTROLLER_PARAMETERS),
                        ("valve_identification", IDENTIFICATION_PARAMETERS), ("valve_monitor", MONITOR_PARAMETERS)):
        lines += [f"## `{node}`", "", "| name | type | default | range | read-only | description |",
                  "|---|---|---|---|---|---|"]
        for s in specs:
            lines.append(f"| `{s.name}` | {s.type_name} | `{s.default!r}` | {s.range_text() or '-'} | "
                         f"{'yes' if s.read_only else 'no'} | {_cell(s.description)} |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    from generated_page import main_for   # beside this script
    return main_for(OUT, tables, "parameter_tables.py", __doc__.split("\n\n")[0])


if __name__ == "__main__":
    sys.exit(main())
