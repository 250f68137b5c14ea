"""Mutation audit of the safety and judgement paths: each mutant is a plausible one-line bug, applied to a copy of
the repository (the committed tree), and the test suite is run on it: does it notice?

    python bench/mutants.py [--markdown docs/results/tests.md] [--full] [--only N ...]

Per mutant: where, what it breaks, whether the quick suite (``-m "not slow"``) fails on it and which test failed
first, and with ``--full`` whether the slow tests catch what the quick suite missed.  The copy imports its own
package (PYTHONPATH), executables included; the working tree is never touched.
"""
import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# (file, the line as it is, the bug, what the bug breaks)
MUTANTS = (
    ("piezo_valve_ros/core/control/strategies.py",
     "oscillating = abs(self._rail_high_at - self._rail_low_at) <= max(int(round(GUARD_WINDOW_S / c.dt)), 1)",
     "oscillating = abs(self._rail_high_at - self._rail_low_at) <= max(int(round(GUARD_WINDOW_S * c.dt)), 1)",
     "oscillation guard: both-rails window of one period instead of 20 ms"),
    ("piezo_valve_ros/core/control/strategies.py",
     "self._d_state += self._d_alpha * (g.kd * (e - self._last_error) / c.dt - self._d_state)",
     "self._d_state += self._d_alpha * (g.kd * (self._last_error - e) / c.dt - self._d_state)",
     "PID: derivative of the wrong sign"),
    ("piezo_valve_ros/core/identification/split.py",
     "        n_fit = cut // block\n",
     "        n_fit = cut // block + 1\n",
     "identification: the fit part overlaps the held-out part by a block"),
    ("piezo_valve_ros/core/identification/_effect_choice.py",
     "            failing = [n for n in current if not verdicts[n].support.supported]",
     "            failing = []",
     "identification: the confirmation never drops an effect"),
    ("piezo_valve_ros/core/identification/search.py",
     "    return share >= GAIN_THRESHOLD and c.loss_ratio <= MAX_LOSS_RATIO",
     "    return share >= 0.0 and c.loss_ratio <= MAX_LOSS_RATIO",
     "identification: an effect is supported by any share of the structured residual"),
    ("piezo_valve_ros/core/identification/search.py",
     "    return share >= GAIN_THRESHOLD and c.loss_ratio <= MAX_LOSS_RATIO",
     "    return share >= GAIN_THRESHOLD",
     "identification: an effect that pays for its cut in other held-out stretches is supported"),
    ("piezo_valve_ros/core/identification/_report_stage.py",
     "        by_spread = structure[\"share_of_spread\"] >= SPREAD_SHARE",
     "        by_spread = False",
     "identification: a held-out error near the output's own spread may be called noise"),
    ("piezo_valve_ros/core/identification/noise.py",
     "    direct = [e for e in evidence[:2] if e.rms_um is not None]",
     "    direct = [e for e in evidence[:3] if e.rms_um is not None]",
     "identification: the input-free band's estimate counts as direct evidence (it may be a record's largest)"),
    ("piezo_valve_ros/nodes/hardware.py",
     "        if silent < self.command_timeout_s:",
     "        if silent < 10 * self.command_timeout_s:",
     "hardware: the watchdog waits ten times its timeout"),
    ("piezo_valve_ros/nodes/hardware.py",
     "        if v < self.command_min_v or v > self.command_max_v:",
     "        if v < self.command_min_v or v > self.command_max_v + 1.0:",
     "hardware: commands up to 1 V above the range pass unclamped"),
    ("piezo_valve_ros/backends/faults.py",
     "        if not math.isfinite(float(rows.sum())):",
     "        if False:",
     "faults: non-finite samples pass"),
    ("piezo_valve_ros/backends/faults.py",
     "        if frozen_s >= self.limits.stuck_time_s and span >= self.limits.stuck_command_span_v:",
     "        if frozen_s >= 10 * self.limits.stuck_time_s and span >= self.limits.stuck_command_span_v:",
     "faults: a frozen sensor tolerated ten times longer"),
    ("piezo_valve_ros/nodes/hardware.py",
     "        if self.fault is not None:\n            self.refused_in_fault += 1",
     "        if False:\n            self.refused_in_fault += 1",
     "hardware: commands applied while in fault"),
    ("piezo_valve_ros/nodes/controller.py",
     "        if not self.enabled or self.hardware_fault is not None:",
     "        if not self.enabled:",
     "controller: keeps integrating while the hardware is in fault"),
    ("piezo_valve_ros/core/monitoring/health.py",
     "        if ratio < self.limits.warn_ratio:",
     "        if ratio < 3 * self.limits.warn_ratio:",
     "monitor: warns at three times its threshold"),
    ("piezo_valve_ros/core/identification/search.py",
     "    return structured_rms(without, noise) >= MIN_EFFECT_NOISE_RATIO * noise.record_um",
     "    return structured_rms(without, noise) >= 2 * MIN_EFFECT_NOISE_RATIO * noise.record_um",
     "identification: no exact check on top of a model within twice the sensor noise"),
    ("piezo_valve_ros/core/identification/effects/asymmetry.py",
     "        return 0.5 * gpim.a0 * self.betas(gpim)[0]",
     "        return gpim.a0 * self.betas(gpim)[0]",
     "identification: an asymmetry's shift taken as the thresholds' move whole, not halved"),
    ("piezo_valve_ros/core/model/hysteresis.py",
     "            return min((drive - self.model.a1) / self.model.a0, self.v_max)",
     "            return (drive - self.model.a1) / self.model.a0",
     "per-step inverse: the closed form's input not held to the drive range (13.5 V above a 10 V rail)"),
    ("piezo_valve_ros/core/control/strategies.py",
     "        self._hold_periods = min(2 * self._hold_periods, int(round(GUARD_MAX_HOLD_S / c.dt))) if recurs else base",
     "        self._hold_periods = min(1 * self._hold_periods, int(round(GUARD_MAX_HOLD_S / c.dt))) if recurs else base",
     "oscillation guard: the hold never doubles when the oscillation recurs"),
    ("piezo_valve_ros/core/control/strategies.py",
     "            direction = self._play.direction if self._play is not None else 0",
     "            direction = 0",
     "backlash: a model swapped in mid-run forgets the reference's direction"),
    ("piezo_valve_ros/backends/faults.py",
     "            self._command_lo = self._command_hi = float(rows[-1, 1])\n            self._moved_at_s = math.nan",
     "            self._command_lo = self._command_hi = float(rows[-1, 1])\n            pass",
     "faults: the frozen-sensor timer not restarted on its usual path (a live reading)"),
    ("piezo_valve_ros/nodes/hardware.py",
     "        problem = SampleCheck(self.fault_limits).check(rows)",
     "        problem = None",
     "hardware: ~/reset clears a fault without checking the samples it reads"),
    ("piezo_valve_ros/core/monitoring/health.py",
     "        self.model, self._valve, self._warm_up = model, None, self._step",
     "        self.model, self._valve, self._warm_up = model, None, self._step\n        self._offset = None",
     "monitor: a model swap measures the reference offset again (a refit that leaves an offset reads OK)"),
    ("piezo_valve_ros/core/monitoring/refits.py",
     "        return float(model_offset_um) + self.offset_change_um",
     "        return float(model_offset_um) - self.offset_change_um",
     "monitor: the offset pushed with the wrong sign"),
)


def _listed(numbers: list[int]) -> str:
    """1, 2 and 3."""
    words = [str(n) for n in numbers]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def copy_of_head(dest: str) -> None:
    """The committed tree into ``dest``."""
    archive = subprocess.run(["git", "-C", ROOT, "archive", "HEAD"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", dest], input=archive, check=True)


FIRST = ("test_simulator_and_control.py", "test_identification.py", "test_faults.py", "test_node_safety.py",
         "test_monitoring.py")   # the safety and judgement tests first: a caught mutant stops early


def run_suite(tree: str, marker: str, workers: int) -> tuple[bool, str, float]:
    """(caught, first failing test or '', seconds) of the suite's ``marker`` part on ``tree`` (every test file, the
    safety and judgement ones first)."""
    files = sorted(f for f in os.listdir(os.path.join(tree, "test")) if f.startswith("test_") and f.endswith(".py"))
    ordered = [f for f in FIRST if f in files] + [f for f in files if f not in FIRST]
    env = dict(os.environ, PYTHONPATH=tree, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    started = time.monotonic()
    # (the docs' links are left out: this bench writes one of the files they point at)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-m", marker,
                           "-n", str(workers), "--deselect",
                           "test/test_architecture.py::test_every_relative_link_in_the_docs_points_at_a_file",
                           *(os.path.join(tree, "test", f) for f in ordered)], cwd=tree, env=env,
                          capture_output=True, text=True)
    failed = [line.split(" ")[1] for line in proc.stdout.splitlines() if line.startswith("FAILED ")]
    return proc.returncode != 0, (failed[0].split("::", 1)[-1] if failed else ""), time.monotonic() - started


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", help="also write the table here")
    ap.add_argument("--full", action="store_true", help="run the slow tests on what the quick suite missed")
    ap.add_argument("--only", type=int, nargs="*", help="mutant numbers (1-based); with --markdown the other rows "
                                                          "are kept from the file as it is")
    ap.add_argument("--workers", type=int, default=3)
    args = ap.parse_args()
    later = set(args.only or ())   # mutants run on a later commit than the rest of the page: these and the page's own
    if args.only and args.markdown and os.path.exists(args.markdown):
        said = re.search(r"Mutant(?:\(s\)|s)? ([\d, and]+) (?:re-)?r[au]ns? on (?:a )?later commits?",
                         open(args.markdown).readline())
        later |= {int(x) for x in re.findall(r"\d+", said.group(1))} if said else set()
    rows = []
    for k, (path, old, new, what) in enumerate(MUTANTS, 1):
        if args.only and k not in args.only:
            continue
        with tempfile.TemporaryDirectory(prefix=f"mutant{k}_") as tree:
            copy_of_head(tree)
            target = os.path.join(tree, path)
            text = open(target).read()
            if text.count(old) != 1:
                raise SystemExit(f"mutant {k}: the line is not in {path} exactly once: {old!r}")
            open(target, "w").write(text.replace(old, new))
            caught, first, seconds = run_suite(tree, "not slow", args.workers)
            full = ""
            if args.full and not caught:
                slow_caught, slow_first, slow_s = run_suite(tree, "slow", args.workers)
                full = f"{'caught: ' + slow_first if slow_caught else 'missed'} ({slow_s:.0f} s)"
            shutil.rmtree(os.path.join(tree, "test", "__pycache__"), ignore_errors=True)
        rows.append((k, what, path, caught, first, seconds, full))
        print(f"{k:2d} {'caught' if caught else 'MISSED'} {seconds:5.0f} s  {what}  {first}", flush=True)
    lines = [f"Output of `python bench/mutants.py{' --full' if args.full else ''}`: each mutant is one plausible "
             f"one-line bug in the safety and judgement paths, applied to a copy of the committed tree; the quick "
             f"suite (`-m \"not slow\"`, stopping at the first failure) is run on it"
             + (", and the slow tests where the quick suite missed it" if args.full else "") + "."
             + ((f" Mutant {_listed(sorted(later))} ran on a later commit than the others." if len(later) == 1 else
                 f" Mutants {_listed(sorted(later))} ran on later commits than the others.") if later else ""), "",
             "| # | mutant | file | quick suite | first failing test | s |" + (" slow tests |" if args.full else ""),
             "|---|---|---|---|---|---|" + ("---|" if args.full else "")]
    for k, what, path, caught, first, seconds, full in rows:
        lines.append(f"| {k} | {what} | `{path}` | {'caught' if caught else 'MISSED'} | {first} | {seconds:.0f} |"
                     + (f" {full} |" if args.full else ""))
    if args.only and args.markdown and os.path.exists(args.markdown):   # the rows not rerun, as they were
        kept = {int(line.split("|")[1]): line for line in open(args.markdown).read().splitlines()
                if line.startswith("| ") and line.split("|")[1].strip().isdigit()}
        kept.update({int(line.split("|")[1]): line for line in lines[4:]})
        lines = lines[:4] + [kept[k] for k in sorted(kept)]
    caught = sum(" | caught | " in line for line in lines[4:])
    lines += ["", f"{caught} of {len(lines) - 4} mutants caught by the quick suite."]
    print("\n".join(lines))
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
