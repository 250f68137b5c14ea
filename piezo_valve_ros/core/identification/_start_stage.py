"""Stage 1 of the residual loop (``residual``): the operators' state at the record's first sample, and what the
held-out part allows (its range, a validation session's start in motion, noise beyond the valve's response).
Nothing here imports ROS."""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np

from .fitting import uniform_thresholds
from .noise import estimate_noise_floor
from .initial_state import ESTIMATE_ROUNDS, ESTIMATE_STATE_GAIN, WIPE_STATE_GAIN, estimate_state
from .search import NoiseLevels
from .split import WIPE_MARGIN
from .valve_model import REST, InitialState
from .report import LeftOut
from .thresholds import (MID_CAPACITY, INITIAL_STATE_TOLERANCE, WIPE_GAIN, HELD_OUT_RANGE_MARGIN, KNOWN_MIN_SHARE,
                         RESOLUTION_SHARE, START_MOTION_MAX_S, START_MOTION_MAX_SHARE, START_MOTION_FIRST_ROWS,
                         START_MOTION_RATIO, MAD_TO_SIGMA)
from ._stages import StartChoice


class StartStage:
    """The loop's stage 1 (a part of ``residual._Loop``: its records, split, noise, pools and log)."""

    # ------------------------------------------------------------------ 1. the initial state
    def choose_initial_state(self) -> StartChoice:
        """The operators' state at the first sample: a valve started from rest, a record cut from running
        operation, estimated from the first rows, or unknown (a valve left off its loop by an unrecorded
        excitation): then the fit starts where the record's own input has wiped it out (``split`` is replaced by
        the cut).  ``starts`` and ``start_rms`` (each start tried -> its model, its held-out RMS) grow as the
        starts are tried."""
        starts, start_rms, chosen = self._rest_or_cycled()
        chosen, estimate = self._estimated_start(starts, start_rms, chosen)
        chosen, before_wipe = self._wiped_start(starts, start_rms, chosen)
        return self._describe_start(starts, start_rms, chosen, estimate, before_wipe)

    def _rest_or_cycled(self) -> tuple[dict, dict, str]:
        candidates = {"rest": REST, "cycled": InitialState("cycled")}
        fits = self.each([lambda h=h: self.fitted_and_scored(
            self.start_model(uniform_thresholds(self.fit.voltage_v, MID_CAPACITY), history=h), "baseline")
            for h in candidates.values()])
        starts = {h: m for h, (m, _) in zip(candidates, fits)}
        start_rms = {h: r for h, (_, r) in zip(candidates, fits)}
        return starts, start_rms, ("cycled" if start_rms["cycled"] < (1 - INITIAL_STATE_TOLERANCE) * start_rms["rest"]
                                   else "rest")

    def _estimated_start(self, starts: dict, start_rms: dict, chosen: str) -> tuple[str, dict]:
        """A state estimated from the rows before the input wiped it (rested elsewhere, or left off the loop):
        (the start chosen, what the estimate found)."""
        first_rows = self.split.first_rows(self.fit)
        estimated, estimate = estimate_state(starts["rest"], first_rows, self.fit)
        if estimate["rms_before_wipe_um"] > (1 - ESTIMATE_STATE_GAIN) * estimate["rms_before_wipe_from_rest_um"]:
            estimated = REST   # it cannot be taken (below): not fitted
        for round_ in range(ESTIMATE_ROUNDS):   # weights fitted from rest are bent by the wrong start: alternate
            if estimated.kind != "remanent":
                break
            starts["estimated"], start_rms["estimated"] = self.fitted_and_scored(
                self.mid_capacity_start(starts[chosen], estimated), "fixed")
            if round_ == ESTIMATE_ROUNDS - 1:
                break
            again, estimate_again = estimate_state(starts["estimated"], first_rows, self.fit)
            if again == estimated or again.kind != "remanent":
                estimate = estimate_again if again == estimated else estimate
                break
            estimated, estimate = again, estimate_again
        if "estimated" in start_rms:
            # as for the wipe below: a clear gain, and the state must explain the start (a slow effect cannot);
            # a valve that rested at one voltage until the record's first command moved it (a closed-loop record)
            # is one parameter beyond rest and shows in the first rows alone: there it must halve their misfit,
            # whatever the baseline's held-out RMS says (a baseline that lacks an effect, creep say, bends its
            # weights to the wrong start and scores better from it; the effect fitted later needs the right one)
            explains = estimate["rms_before_wipe_um"] / max(estimate["rms_before_wipe_from_rest_um"], 1e-12)
            clear_gain = (start_rms["estimated"] < (1 - WIPE_GAIN) * start_rms[chosen]
                          and explains <= 1 - ESTIMATE_STATE_GAIN)
            rested_elsewhere = estimated.rested_at_v is not None and explains <= 1 - WIPE_STATE_GAIN
            # held-out data that cannot tell the starts apart (a separate session has its own start): the
            # training record's first rows can, and a start they refute would bend every later fit to it
            indistinct = (explains <= 1 - ESTIMATE_STATE_GAIN and start_rms["estimated"]
                          <= (1 + INITIAL_STATE_TOLERANCE) * min(start_rms["rest"], start_rms["cycled"]))
            self.log(f"initial state: estimated {estimate['estimate']}; first rows' RMS "
                     f"{estimate['rms_before_wipe_um']:.4f} um against {estimate['rms_before_wipe_from_rest_um']:.4f} from rest")
            if clear_gain or rested_elsewhere or indistinct:
                chosen = "estimated"
                if indistinct and not (clear_gain or rested_elsewhere):
                    self.log(f"initial state: held-out data cannot tell the starts apart (within "
                             f"{100 * INITIAL_STATE_TOLERANCE:g} %); the estimate leaves {100 * explains:.0f} % of "
                             f"the training record's first rows' misfit from rest: estimated")
        return chosen, estimate

    def _wiped_start(self, starts: dict, start_rms: dict, chosen: str) -> tuple[str, Optional[dict]]:
        """Fitting only after the input has wiped out an unknown start, on the poles just fitted on the whole
        record (only the initial state differs): (the start chosen, the state before the record where that is
        the wipe)."""
        wiped = self.split.after_wipe()
        if wiped is None:
            return chosen, None
        cut, state = wiped
        starts["wiped"], start_rms["wiped"] = self.fitted_and_scored(
            replace(self.mid_capacity_start(starts[chosen], state, cut), t0=cut.t0), "fixed", cut)
        if start_rms["wiped"] < (1 - WIPE_GAIN) * start_rms[chosen]:
            # a start off the loop, or a slow effect (drift, creep) that the earlier rows show most: only an
            # initial state that explains the rows before the wipe makes it the former
            _, before_wipe = estimate_state(starts["wiped"], self.fit.slice(0, len(self.fit) - len(cut.fit)), self.fit)
            if before_wipe["rms_before_wipe_um"] <= (1 - WIPE_STATE_GAIN) * before_wipe["rms_before_wipe_from_rest_um"]:
                self.split = cut
                return "wiped", before_wipe
            else:
                self.log(f"initial state: fitting from the wipe on cuts the held-out RMS {start_rms[chosen]:.4f} "
                         f"-> {start_rms['wiped']:.4f} um, but no state before the record explains the rows before it "
                         f"({before_wipe['rms_before_wipe_um']:.4f} um RMS against "
                         f"{before_wipe['rms_before_wipe_from_rest_um']:.4f} from rest): a slow effect, not the start; "
                         f"the whole record is fitted")
        return chosen, None

    def _describe_start(self, starts: dict, start_rms: dict, chosen_state: str, estimate: dict,
                        before_wipe: Optional[dict]) -> StartChoice:
        split = self.split
        first = starts[chosen_state]
        assumed = {"assumed": first.history.describe(), "fit_starts_at_s": split.wiped_at_s}
        if chosen_state == "estimated":
            assumed["assumed"] += ": estimated from the record's rows before its input wiped the state out"
            assumed["before_the_record"] = estimate
        if chosen_state == "wiped":
            assumed = {"assumed": f"unknown before the record: the fit and every decision use the record from "
                                  f"t = {split.wiped_at_s:.6g} s, where its input has come within "
                                  f"{100 * WIPE_MARGIN:g} % of both its extremes and so wiped the state out; the "
                                  f"operators start there as the record's input since its first sample left them",
                       "fit_starts_at_s": split.wiped_at_s,
                       "before_the_record": before_wipe}
        if not split.held_out:
            assumed["validation_record_start"] = (
                "a separate session: each model's operator states at its first sample and the output G had settled "
                "to before it (estimated on the rows until the input has wiped them out) and the session's sensor "
                "offset (the whole record) estimated for it; its held-out error taken from that start, less that offset")
        self.log("initial state: " + ", ".join(f"{h} {r:.4f}" for h, r in start_rms.items())
                 + " um held-out RMS; chosen "
                 + (f"{chosen_state}: the state before the record is unknown, the fit starts at t = "
                    f"{split.wiped_at_s:.4g} s, where the input has wiped it out" if chosen_state == "wiped"
                    else chosen_state))
        self.log(f"G_v: {first.dynamics_note}")
        return StartChoice(first, chosen_state, start_rms, assumed)

    def check_held_out_range(self) -> None:
        """Warn when the held-out data drive the valve beyond the fit part's voltage range: the operators that
        only the held-out part moves (and whatever the valve does there) are not identified by the fit, and the
        held-out error there is extrapolation, which no effect explains.  Where they leave it after their first
        KNOWN_MIN_SHARE, the rows before are where every decision also asks an effect to do no worse
        (``known_rows``, ``search.support``)."""
        fit_v, held_v = self.split.fit.voltage_v, self.split.score.voltage_v[self.split.start:]
        lo, hi = float(np.min(fit_v)), float(np.max(fit_v))
        margin = HELD_OUT_RANGE_MARGIN * (hi - lo)
        below, above = float(np.min(held_v)), float(np.max(held_v))
        beyond = max(lo - below, above - hi)
        if beyond > margin:
            first_out = int(np.argmax((held_v < lo - margin) | (held_v > hi + margin)))
            if first_out >= KNOWN_MIN_SHARE * held_v.size:
                self.known_rows = first_out
            where = "the validation record" if not self.split.held_out else "the held-out part"
            self.warnings.append(f"{where} drives the valve to {below:.4g} .. {above:.4g} V, {beyond:.3g} V beyond the fit "
                                 f"part's {lo:.4g} .. {hi:.4g} V ({100 * beyond / (hi - lo):.0f} % of its range): the fit "
                                 f"cannot know the valve there, and the held-out error from there is extrapolation, "
                                 f"which no effect explains (a training record should span every voltage the valve "
                                 f"will see)" + (f"; an effect must also do no worse on its first "
                                                 f"{self.known_rows * self.split.score.dt:.3g} s, before it first "
                                                 f"leaves that range"
                                                 if self.known_rows is not None else ""))
            self.log("warning: " + self.warnings[-1])

    def leave_out_start_in_motion(self, start: StartChoice) -> None:
        """A separate validation session that starts in motion, still settling from a voltage nobody recorded (a
        jump just before it), shows an error at its first rows that no start estimated for the valve's memory takes
        away: the rows from the first to the last one, within START_MOTION_MAX_S, whose error (``start``'s model, at
        the record's rate) stands START_MOTION_RATIO times above the rest of the session's robust spread are left out
        of every held-out figure and decision (``split``'s start moves past them; the models still run from the
        session's first sample), and the report says so (``start_left_out``)."""
        split = self.split
        if split.held_out:
            return
        e = self.error(start.first, full=True)
        dt = split.score_full.dt
        reach = min(int(START_MOTION_MAX_S / dt), int(START_MOTION_MAX_SHARE * e.size))
        if reach < 1 or e.size <= 4 * reach:
            return
        rest = e[reach:]
        spread = max(MAD_TO_SIGMA * float(np.median(np.abs(rest - np.median(rest)))), self.noise)
        outside = np.flatnonzero(np.abs(e[:reach] - np.median(rest)) > START_MOTION_RATIO * spread)
        if outside.size == 0 or outside[0] > START_MOTION_FIRST_ROWS:
            return
        rows_full = int(outside[-1]) + 1
        ratio = split.score.block // max(split.score_full.block, 1)
        rows = -(-rows_full // ratio)   # whole analysis rows, so both rates leave out the same stretch
        rows_full = rows * ratio
        self.start_left_out = LeftOut(rows=rows_full, seconds=round(rows_full * dt, 6),
                                      peak_error_um=round(float(np.max(np.abs(e[:rows_full]))), 4),
                                      spread_um=round(spread, 5))
        self.split = replace(split, start=rows, start_full=rows_full)
        self.warnings.append(f"the validation session starts in motion (still settling from a voltage before it): its "
                             f"first {rows_full} rows ({1e3 * rows_full * dt:.0f} ms, error up to "
                             f"{self.start_left_out.peak_error_um:.3g} um against a spread of {spread:.3g} um after "
                             f"them) are left out of the held-out figures")
        self.log("warning: " + self.warnings[-1])

    def noise_beyond_response(self, start: StartChoice) -> None:
        """Where the records gave no direct evidence for the noise (a closed loop's drive is never still and feeds
        the sensor's noise back at every frequency), the band beyond the response of ``start``'s fitted G."""
        if self.floor.known:
            return
        tf = start.first.dynamics

        def response(f: np.ndarray) -> np.ndarray:
            return np.abs(tf.frequency_response(f)) ** 2
        floor = estimate_noise_floor(self.noise_records, response)
        if not floor.known:
            self.floor = floor
            return
        self.floor = floor
        self.warnings[:] = [w for w in self.warnings if not w.startswith("the records offer no evidence")]
        self.noise = max(floor.rms_um, RESOLUTION_SHARE * self.range_um)
        self.levels = NoiseLevels(self.noise, self.noise * self.levels.analysis_um / self.levels.record_um,
                                  known=True)
        self.log(f"sensor noise: {floor.describe()}")
