"""Where the test suite's time goes: the suite as CI runs it (``scripts/run_tests.sh``), each test's CPU time in its
worker and in the processes it started (``suite_cpu_plugin.py``), summed by test module, the costliest tests, and the
run's wall time and total CPU.  On a 2-core machine the suite is bound by CPU: its wall time is about its CPU time
over the cores it keeps busy.

    python bench/suite_cpu.py [--markdown docs/results/suite_cpu.md] [--json FILE] [--top 15] [-- pytest arguments]
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import host_yardstick, yardstick_note

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = "suite_cpu_plugin"


def run_suite(extra: list[str]) -> tuple[list[dict], float, float, int]:
    """(one dict per test, wall time [s], CPU time of the run and everything it started [s], exit code)."""
    with tempfile.TemporaryDirectory(prefix="suite_cpu_") as directory:
        env = dict(os.environ, SUITE_CPU_DIR=directory,
                   PYTHONPATH=os.pathsep.join(p for p in (str(ROOT / "bench"), os.environ.get("PYTHONPATH")) if p))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.monotonic()
        code = subprocess.run(["bash", str(ROOT / "scripts" / "run_tests.sh"), "-p", PLUGIN, *extra], env=env,
                              cwd=ROOT).returncode
        wall = time.monotonic() - started
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        rows = [json.loads(line) for f in sorted(Path(directory).glob("*.jsonl")) for line in f.read_text().splitlines()]
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return rows, wall, cpu, code


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", metavar="FILE", help="write the page here")
    ap.add_argument("--json", metavar="FILE", help="write every test's figures here (a JSON list)")
    ap.add_argument("--top", type=int, default=15, help="the costliest tests listed (default 15)")
    ap.add_argument("pytest_args", nargs="*", help="after --: passed to the suite (e.g. --quick)")
    args = ap.parse_args(argv)
    started = host_yardstick()
    rows, wall, cpu, code = run_suite(args.pytest_args)
    ended = host_yardstick()
    if not rows:
        print("suite_cpu: no test reported its time (was the plugin loaded?)", file=sys.stderr)
        return 1
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    page = ["# Where the test suite's time goes", ""]
    line = page.append
    line(f"`python bench/suite_cpu.py` at {commit}: `scripts/run_tests.sh` as CI runs it (the venv already made), "
         f"on {len(os.sched_getaffinity(0))} CPUs; exit code {code}.")
    line("")
    line(yardstick_note(started, ended))
    line("")
    tests_cpu = sum(r["self_s"] + r["children_s"] for r in rows)
    line(f"- wall time {wall:.0f} s; CPU time of the run and every process it started {cpu:.0f} s "
         f"({cpu / wall:.2f} CPUs busy on average)")
    line(f"- {len(rows)} tests: {tests_cpu:.0f} CPU-s in them, {sum(r['self_s'] for r in rows):.0f} in the "
         f"workers and {sum(r['children_s'] for r in rows):.0f} in the processes they started (nodes, tools); "
         f"the rest of the run's CPU is start-up, collection and scheduling")
    ends = collections.defaultdict(float)
    for r in rows:
        ends[r["worker"]] = max(ends[r["worker"]], r["end"])
    if len(ends) > 1:
        first, last = min(ends.values()), max(ends.values())
        line(f"- the {len(ends)} workers finished their last tests within {last - first:.0f} s of each other "
             f"(the run's tail: fewer tests than workers left to run)")
    line("")
    modules: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0, 0.0, 0.0])
    for r in rows:
        m = modules[r["test"].split("::")[0]]
        m[0] += 1
        m[1] += r["self_s"] + r["children_s"]
        m[2] += r["children_s"]
        m[3] += r["wall_s"]
    line("| test module | tests | CPU [s] | of it in child processes [s] | wall [s] |")
    line("|---|---:|---:|---:|---:|")
    for name, (count, total, children, wall_s) in sorted(modules.items(), key=lambda kv: -kv[1][1]):
        line(f"| {name} | {count} | {total:.1f} | {children:.1f} | {wall_s:.1f} |")
    line("")
    line(f"The {args.top} costliest tests:")
    line("")
    line("| test | CPU [s] | wall [s] |")
    line("|---|---:|---:|")
    for r in sorted(rows, key=lambda r: -(r["self_s"] + r["children_s"]))[:args.top]:
        line(f"| `{r['test']}` | {r['self_s'] + r['children_s']:.1f} | {r['wall_s']:.1f} |")
    print("\n".join(page))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=0) + "\n")
    if args.markdown:
        Path(args.markdown).write_text("\n".join(page) + "\n")
    return code


if __name__ == "__main__":
    sys.exit(main())
