"""PNG figures of an identification (optional: needs matplotlib, ``pip install piezo_valve_ros[plots]``).

Nodes never import this module.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .core.residual import Analysis

__all__ = ["require", "write_all"]


def require():
    """Import matplotlib (Agg) or raise a one-line error."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RuntimeError("--plots needs matplotlib (pip install matplotlib, or the package's [plots] extra)") from None
    return plt


def _diagnostic_variable(name: str, t: np.ndarray, v: np.ndarray, H: np.ndarray):
    """(values, axis label, log x?) of the variable an effect's signature depends on."""
    if name == "creep":
        moving = np.flatnonzero(np.abs(np.diff(v)) > 1e-9 * (1 + np.abs(v[1:])))
        last = np.full(t.size, t[0])
        if moving.size:
            idx = np.searchsorted(moving + 1, np.arange(t.size), side="right") - 1
            ok = idx >= 0
            last[ok] = t[moving[idx[ok]] + 1]
        return np.maximum(t - last, 1e-4), "time since the input last moved [s]", True
    if name == "dynamics":
        return np.gradient(H, t), "model output rate [um/s]", False
    if name == "asymmetry":
        return v, "voltage [V]", False
    if name == "drift":
        return t - t[0], "time [s]", False
    return H, "model output [um]", False


def write_all(analysis: Analysis, directory) -> list[str]:
    plt = require()
    out_dir = Path(directory)
    out_dir.mkdir(parents=True, exist_ok=True)
    val = analysis.validate
    rec = val.record
    sl = slice(val.start, None)
    t, v, y = rec.time_s[sl], rec.voltage_v[sl], rec.position_um[sl]
    y_base = val.predict(analysis.baseline)
    y_final = val.predict(analysis.final)
    label_b, label_f = "baseline " + analysis.report["baseline"]["fit"], analysis.final.name
    written = []

    def save(fig, name):
        path = out_dir / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(str(path))

    fig, ax = plt.subplots(figsize=(7, 5))
    ax.plot(v, y, color="0.6", lw=0.8, label="measured")
    ax.plot(v, y_base, lw=0.8, label=label_b)
    ax.plot(v, y_final, lw=0.8, ls="--", label=label_f)
    ax.set_xlabel("voltage [V]")
    ax.set_ylabel("spool position [um]")
    ax.set_title("Hysteresis loop, held-out data")
    ax.legend()
    save(fig, "hysteresis_loop.png")

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, y - y_base, lw=0.6, label=f"{label_b} (RMS {analysis.report['baseline']['validate']['rms_um']:.3f} um)")
    ax.plot(t, y - y_final, lw=0.6, label=f"{label_f} (RMS {analysis.report['final']['validate']['rms_um']:.3f} um)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("residual [um]")
    ax.set_title("Residual before and after, held-out data")
    ax.legend()
    save(fig, "residual_time.png")

    names = analysis.report["effects_added"] or ["saturation"]
    fig, axes = plt.subplots(1, len(names), figsize=(5 * len(names), 4), squeeze=False)
    step = max(t.size // 5000, 1)
    for i, (ax, name) in enumerate(zip(axes[0], names)):
        before = val.predict(analysis.history[i]) if analysis.report["effects_added"] else y_base
        after = val.predict(analysis.history[i + 1]) if analysis.report["effects_added"] else y_final
        x, xlabel, logx = _diagnostic_variable(name, t, v, before)
        ax.plot(x[::step], (y - before)[::step], ".", ms=2, alpha=0.5, label=f"before adding {name}")
        ax.plot(x[::step], (y - after)[::step], ".", ms=2, alpha=0.5, label="after")
        if logx:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("residual [um]")
        ax.set_title(f"{name}" + ("" if analysis.report["effects_added"] else " (none added)"))
        ax.legend()
    save(fig, "residual_diagnostic.png")

    # step-and-hold: the longest stretch of constant input and what precedes it
    flat = np.concatenate(([False], np.abs(np.diff(v)) <= 1e-9 * (1 + np.abs(v[1:]))))
    edges = np.flatnonzero(np.diff(np.concatenate(([0], flat.astype(int), [0]))))
    runs = edges.reshape(-1, 2) if edges.size else np.zeros((0, 2), int)
    fig, ax = plt.subplots(figsize=(9, 4))
    if runs.size:
        long_runs = runs[np.argsort(runs[:, 1] - runs[:, 0])[::-1][:4]]
        a = max(int(long_runs[:, 0].min()) - 20, 0)
        b = int(long_runs[:, 1].max())
        ax.plot(t[a:b], y[a:b], color="0.5", lw=0.8, label="measured")
        ax.plot(t[a:b], y_base[a:b], lw=0.8, label=label_b)
        ax.plot(t[a:b], y_final[a:b], lw=0.8, ls="--", label=label_f)
        ax.legend()
    ax.set_xlabel("time [s]")
    ax.set_ylabel("spool position [um]")
    ax.set_title("Step and hold, held-out data")
    save(fig, "step_hold.png")
    return written
