"""``valve_tune``: PID gains for a strategy, chosen on an identified model (a ``valve_identify --params-out`` file).

    valve_tune fitted.yaml [--strategy pid_hc] [--control-period-s 0.001] [--max-overshoot-pct 2]
               [--min-gain-margin-db 6] [--min-phase-margin-deg 45] [--max-noise-gain 3]
               [--compare] [--params-out tuned.yaml]

Prints the gains with their margins and the paper's three steps on the model; ``--compare`` also shows the
paper's Table 1 sets for the strategy on the same model.  ``--params-out`` writes the file's parameters with
the tuned strategy and gains (atomically; nothing is written when tuning fails), ready for
``ros2 run piezo_valve_ros valve_controller --ros-args --params-file tuned.yaml``.  The identification
node's ``tune`` step does the same on the rig and pushes the gains to the running controller.
A thin face over ``piezo_valve_ros.core.tuning.tuner``; no ROS import.  Exit codes: 0 done, 2 bad input or no
gains meet the limits, 1 anything else.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
import sys

from ..core.defaults import CONTROL_PERIOD_S
from ..core.control.compensation import CompensationModel
from ..core.control.strategies import TABLE1_GAINS, loop_settings
from ..core.control.forward import ModelValve
from ..core.tuning.tuner import (MAX_NOISE_GAIN, MIN_CROSSOVER_HZ, MIN_GAIN_MARGIN_DB, MIN_PHASE_MARGIN_DEG, OVERSHOOT_LIMIT_PCT,
                          TUNABLE_STRATEGIES, TuningLimits, loop_margins, step_score, tune)
from ..core.sim.signals import PAPER_STEPS_UM
from ..identify import (ParametersFileError, check_output_paths, parameters_yaml, read_parameters_file,
                        write_outputs)
from .tool import run_tool

__all__ = ["main"]



def _steps_text(score) -> list[str]:
    rows = []
    for (a, b), m in zip(PAPER_STEPS_UM, score.steps):
        rows.append(f"    {a:6.1f} -> {b:5.1f} um: settling {1e3 * m.settling_time_s:6.2f} ms, "
                    f"overshoot {m.overshoot_pct:5.2f} %")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="valve_tune", description=__doc__.split("\n\n")[0])
    ap.add_argument("params_file", help="valve_controller parameters file with the identified model "
                                        "(valve_identify --params-out)")
    ap.add_argument("--strategy", default="pid_hc", choices=TUNABLE_STRATEGIES)
    ap.add_argument("--control-period-s", type=float, help=f"control period [s] (default: the file's "
                                                           f"control_period_s, else {CONTROL_PERIOD_S:g})")
    ap.add_argument("--max-overshoot-pct", type=float, default=OVERSHOOT_LIMIT_PCT)
    ap.add_argument("--min-gain-margin-db", type=float, default=MIN_GAIN_MARGIN_DB)
    ap.add_argument("--min-phase-margin-deg", type=float, default=MIN_PHASE_MARGIN_DEG)
    ap.add_argument("--max-noise-gain", type=float, default=MAX_NOISE_GAIN,
                    help="PID gain at the Nyquist frequency [um of command per um of measurement]")
    ap.add_argument("--min-crossover-hz", type=float, default=MIN_CROSSOVER_HZ,
                    help="the loop's slowest gain crossover [Hz]: how fast feedback corrects creep and drift")
    ap.add_argument("--compare", action="store_true", help="also show Table 1's sets for the strategy on the model")
    ap.add_argument("--params-out", metavar="FILE", help="write the parameters with the tuned gains here")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object (no progress lines)")
    args = ap.parse_args(argv)
    log = (lambda s: None) if args.quiet or args.json else (lambda s: print(s, flush=True))

    def work() -> list[str]:
        params = read_parameters_file(args.params_file)
        if not any(name.startswith("gpim.") for name in params):   # else the controller's default (the paper's)
            raise ParametersFileError(f"{args.params_file}: no model in the valve_controller section (no gpim.* "
                                      "parameters): valve_tune tunes an identified model (valve_identify "
                                      "--params-out), or config/paper_model.yaml for the paper's")
        config = loop_settings(params, args.strategy, dt=args.control_period_s, default_dt=CONTROL_PERIOD_S)
        dt, v_min, v_max = config.dt, config.command_min_v, config.command_max_v
        try:  # the command range and period are checked by tune(), with the limits
            model = CompensationModel.from_parameters(params, v_min, v_max, dt)
        except ValueError as exc:
            raise ParametersFileError(f"{args.params_file}: {exc}") from None
        limits = TuningLimits(args.max_overshoot_pct, args.min_gain_margin_db, args.min_phase_margin_deg,
                              args.max_noise_gain, args.min_crossover_hz)
        check_output_paths([args.params_out] if args.params_out else [])   # before the search, not after it
        result = tune(args.strategy, model, dt, limits, config, log=log)
        lines = [f"tuned {result.summary()}", "  on the model:"] + _steps_text(result.score)
        if args.compare:
            lines.append(f"  Table 1's {args.strategy} sets on the same model:")
            v0 = config.centre_voltage_v
            for name, (strategy, gains) in TABLE1_GAINS.items():
                if strategy != args.strategy:
                    continue
                s = step_score(replace(config, strategy=strategy, gains=gains), model,
                               lambda: ModelValve(model, dt, v0), v0)
                lines.append(f"    {name}: settling {1e3 * s.settling_time_s:.2f} ms, overshoot {s.overshoot_pct:.2f} % "
                             f"(worst {s.worst_overshoot_pct:.2f} %); "
                             f"{loop_margins(strategy, gains, model, dt, v_min, v_max, config.derivative_filter_s).text()}")
        written = []
        if args.params_out:
            values = {**params, "control_period_s": float(dt), **result.parameters()}
            comments = [f"Tuned by valve_tune from {args.params_file}: {result.summary()}"]
            written = write_outputs({args.params_out: parameters_yaml(values, comments)})
        if args.json:
            return [json.dumps({**result.as_dict(), "control_period_s": float(dt), "written": written})]
        return lines + [f"wrote {path}" for path in written]
    return run_tool("valve_tune", work, (ValueError,))  # a parameter value that is not a number


if __name__ == "__main__":
    sys.exit(main())
