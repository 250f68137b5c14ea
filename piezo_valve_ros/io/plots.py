"""PNG figures of an identification (optional: needs matplotlib, ``pip install piezo_valve_ros[plots]``).

Nodes never import this module.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..core.identification.residual import Analysis

__all__ = ["require", "write_all", "write_run", "MIN_HOLD_SAMPLES", "MAX_PLOT_POINTS"]

MIN_HOLD_SAMPLES = 20   # a step-and-hold figure needs a constant-input stretch at least this long
MAX_PLOT_POINTS = 200_000   # longer series are thinned (every k-th sample) before plotting


def require():
    """Import matplotlib (Agg) or raise a one-line error."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RuntimeError("plots need matplotlib (pip install matplotlib, or the package's [plots] extra)") from None
    return plt


class _FigureWriter:
    """Saves figures as PNGs into one directory (created if needed) and keeps the paths written."""

    def __init__(self, directory):
        self.plt = require()
        self.out_dir = Path(directory)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.written: list[str] = []

    def save(self, fig, name: str) -> None:
        path = self.out_dir / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        self.plt.close(fig)
        self.written.append(str(path))


class _HeldOut:
    """The held-out data at the analysis rate and the two models' predictions of it."""

    def __init__(self, analysis: Analysis):
        self.analysis = analysis
        split = analysis.split
        self.record, self.start, self.t0 = split.score, split.start, split.score_t0
        rec, start = self.record, self.start
        self.t, self.v, self.y = rec.time_s[start:], rec.voltage_v[start:], rec.position_um[start:]
        self.y_base, self.y_final = self.predict(analysis.baseline), self.predict(analysis.final)
        self.label_base, self.label_final = f"baseline {analysis.baseline.name}", analysis.final.name

    def predict(self, model) -> np.ndarray:
        """What ``model`` predicts on the held-out data, as the report scores it (its own start and the session's
        offset on a validation record)."""
        return self.y - self.analysis.held_out_error(model)


def write_all(analysis: Analysis, directory, log: Callable[[str], None] = lambda s: None) -> list[str]:
    """Hysteresis loop, residual in time, one residual diagnostic per added effect (before: the final model
    refitted without it) and a step-and-hold stretch (when the input holds still somewhere), all on held-out
    data at the analysis rate.  Returns the paths written."""
    figures = _FigureWriter(directory)
    data = _HeldOut(analysis)
    _loop_figure(figures, data)
    _residual_time_figure(figures, data)
    _diagnostic_figure(figures, data)
    if not _step_hold_figure(figures, data):
        log(f"no step_hold.png: the held-out input never holds still for {MIN_HOLD_SAMPLES} samples")
    return figures.written


def _loop_figure(figures: _FigureWriter, d: _HeldOut) -> None:
    fig, ax = figures.plt.subplots(figsize=(7, 5))
    ax.plot(d.v, d.y, color="0.6", lw=0.8, label="measured")
    ax.plot(d.v, d.y_base, lw=0.8, label=d.label_base)
    ax.plot(d.v, d.y_final, lw=0.8, ls="--", label=d.label_final)
    ax.set_xlabel("voltage [V]")
    ax.set_ylabel("spool position [um]")
    ax.set_title("Hysteresis loop, held-out data")
    ax.legend()
    figures.save(fig, "hysteresis_loop.png")


def _residual_time_figure(figures: _FigureWriter, d: _HeldOut) -> None:
    report = d.analysis.report
    fig, ax = figures.plt.subplots(figsize=(9, 4))
    ax.plot(d.t, d.y - d.y_base, lw=0.6, label=f"{d.label_base} (RMS {report.baseline.validate.rms_um:.3f} um)")
    ax.plot(d.t, d.y - d.y_final, lw=0.6, label=f"{d.label_final} (RMS {report.final.validate.rms_um:.3f} um)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("residual [um]")
    ax.set_title("Residual before and after, held-out data")
    ax.legend()
    figures.save(fig, "residual_time.png")


def _diagnostic_figure(figures: _FigureWriter, d: _HeldOut) -> None:
    """Per added effect: the residual without it and with the final model against the effect's own axis."""
    analysis = d.analysis
    added = [(e, analysis.drop_one.get(e.name, analysis.baseline)) for e in analysis.final.effects]
    panels = added or [(None, analysis.baseline)]
    fig, axes = figures.plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), squeeze=False)
    step = max(d.t.size // 5000, 1)
    for ax, (effect, without) in zip(axes[0], panels):
        ctx = without.context(d.record, d.t0)
        if effect is None:
            x, xlabel, logx = ctx.H[d.start:], "model output [um]", False
            title = "no effect added"
        else:
            x, xlabel, logx = effect.plot_axis(ctx)
            x, title = x[d.start:], effect.name
        ax.plot(x[::step], (d.y - d.predict(without))[::step], ".", ms=2, alpha=0.5,
                label="without it" if effect is not None else "baseline")
        ax.plot(x[::step], (d.y - d.y_final)[::step], ".", ms=2, alpha=0.5, label="final model")
        if logx:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("residual [um]")
        ax.set_title(title)
        ax.legend()
    figures.save(fig, "residual_diagnostic.png")


def _step_hold_figure(figures: _FigureWriter, d: _HeldOut) -> bool:
    """The longest stretches of constant input and what precedes them; False when the input never holds."""
    v = d.v
    flat = np.concatenate(([False], np.abs(np.diff(v)) <= 1e-9 * (1 + np.abs(v[1:]))))
    edges = np.flatnonzero(np.diff(np.concatenate(([0], flat.astype(int), [0]))))
    runs = edges.reshape(-1, 2) if edges.size else np.zeros((0, 2), int)
    runs = runs[runs[:, 1] - runs[:, 0] >= MIN_HOLD_SAMPLES]
    if not runs.size:
        return False
    fig, ax = figures.plt.subplots(figsize=(9, 4))
    long_runs = runs[np.argsort(runs[:, 1] - runs[:, 0])[::-1][:4]]
    a = max(int(long_runs[:, 0].min()) - 20, 0)
    b = int(long_runs[:, 1].max())
    ax.plot(d.t[a:b], d.y[a:b], color="0.5", lw=0.8, label="measured")
    ax.plot(d.t[a:b], d.y_base[a:b], lw=0.8, label=d.label_base)
    ax.plot(d.t[a:b], d.y_final[a:b], lw=0.8, ls="--", label=d.label_final)
    ax.legend()
    ax.set_xlabel("time [s]")
    ax.set_ylabel("spool position [um]")
    ax.set_title("Step and hold, held-out data")
    figures.save(fig, "step_hold.png")
    return True


def write_run(time_s: np.ndarray, voltage_v: np.ndarray, position_m: np.ndarray, reference_m: np.ndarray,
              directory, title: str = "") -> list[str]:
    """Figures of a recorded closed-loop run: position and reference, command, tracking error (where a
    reference is known) in time, and the hysteresis loop (command vs position).  Positions are plotted in
    um.  Returns the paths written."""
    figures = _FigureWriter(directory)
    plt, save = figures.plt, figures.save
    k = max(time_s.size // MAX_PLOT_POINTS, 1)
    t, v, y, r = time_s[::k] - time_s[0], voltage_v[::k], position_m[::k] * 1e6, reference_m[::k] * 1e6
    has_ref = bool(np.isfinite(r).any())

    fig, axes = plt.subplots(3 if has_ref else 2, 1, figsize=(10, 8 if has_ref else 6), sharex=True)
    axes[0].plot(t, y, lw=0.7, label="spool position")
    if has_ref:
        axes[0].plot(t, r, lw=0.9, ls="--", label="reference")
    axes[0].set_ylabel("position [um]")
    axes[0].legend(loc="upper right")
    axes[0].set_title(title or "Recorded run")
    axes[1].plot(t, v, lw=0.7, color="C2")
    axes[1].set_ylabel("command [V]")
    if has_ref:
        axes[2].plot(t, y - r, lw=0.7, color="C3")
        axes[2].set_ylabel("tracking error [um]")
    axes[-1].set_xlabel("time [s]")
    save(fig, "run_time.png")

    fig, ax = plt.subplots(figsize=(7, 5))
    ax.plot(v, y, lw=0.6)
    ax.set_xlabel("command [V]")
    ax.set_ylabel("spool position [um]")
    ax.set_title("Hysteresis loop (command vs position)")
    save(fig, "hysteresis_loop.png")
    return figures.written
