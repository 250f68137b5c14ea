"""Write the identification report's schema (docs/handbook/report.md) from its one typed definition
(``piezo_valve_ros/core/identification/report.py``).

    python scripts/report_schema.py [--check]

``--check`` writes nothing and exits 1 when the file differs from what the definition gives (the tests run it).
"""
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "docs" / "handbook" / "report.md"


def page() -> str:
    from piezo_valve_ros.core.identification.report import schema_tables
    from piezo_valve_ros.identify import REPORT_SCHEMA, REPORT_SCHEMA_VERSION
    lines = ["# The identification report", "",
             f"`report.json` (`valve_identify --report`, the identification node's bags directory): schema "
             f"`{REPORT_SCHEMA}` version {REPORT_SCHEMA_VERSION}. Written by `scripts/report_schema.py` from the "
             "report's typed definition (`core/identification/report.py`, which the tests check every report "
             "against); do not edit by hand. Units: um, V, s, Hz; shares are fractions (0.2 = 20 %) unless a key "
             "ends in `_pct`.", ""]
    for name, rows in schema_tables():
        lines += [f"## {name}", "", "| key | type | what it holds |", "|---|---|---|"]
        lines += [f"| `{k}` | {t} | {d.replace('|', '/')} |" for k, t, d in rows]
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    from generated_page import main_for   # beside this script
    return main_for(OUT, page, "report_schema.py", __doc__.split("\n\n")[0])


if __name__ == "__main__":
    sys.exit(main())
