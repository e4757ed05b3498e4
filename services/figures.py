"""Matplotlib figures of an evaluation (the paper's Fig. 7-10 layout). Files only; no computation beyond plotting."""

from __future__ import annotations

from pathlib import Path

import numpy as np

AXES = ("E", "N", "U")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, windows):
    for w in windows or []:
        ax.axvspan(w[0], w[1], color="0.85", zorder=0)


def error_figure(path: Path, t: np.ndarray, series: dict[str, np.ndarray], title: str, unit: str,
                 colors: dict[str, tuple], windows=None, rms: bool = False) -> None:
    """3 stacked panels (E, N, U); one line per algorithm. ``series[algo]``: (K, 3) errors."""
    plt = _plt()
    fig, axs = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    for i, ax in enumerate(axs):
        _shade(ax, windows)
        for algo, e in series.items():
            c = np.array(colors.get(algo, (0, 0, 0))) / 255.0
            ax.plot(t, e[:, i], lw=0.9, color=c, label=algo)
        ax.set_ylabel(f"{AXES[i]} {'RMS ' if rms else ''}error ({unit})")
        ax.grid(True, lw=0.3)
        if not rms:
            ax.axhline(0, color="k", lw=0.5)
    axs[0].legend(loc="upper right", ncol=len(series), fontsize=8)
    axs[0].set_title(title)
    axs[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def detection_figure(path: Path, t: np.ndarray, faulty: np.ndarray, tp: np.ndarray, fp: np.ndarray,
                     h0: np.ndarray, h1: np.ndarray, dh_p50: np.ndarray, dl: float | None) -> None:
    """atvfg detection over time: decisions per epoch and thresholds."""
    plt = _plt()
    fig, axs = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax = axs[0]
    ax.plot(t, faulty, color="k", lw=0.9, label="faulty link decisions (labels)")
    ax.plot(t, tp, color="tab:green", lw=0.9, label="detected (H0 or H1)")
    ax.plot(t, fp, color="tab:red", lw=0.9, label="false alarms")
    ax.plot(t, h0, color="tab:purple", lw=0.7, ls="--", label="classified H0")
    ax.plot(t, h1, color="tab:orange", lw=0.7, ls="--", label="classified H1")
    ax.set_ylabel("link decisions / epoch")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(True, lw=0.3)
    ax.set_title("atvfg double-threshold detection")
    ax = axs[1]
    ax.plot(t, dh_p50, color="tab:blue", lw=0.9, label="Δh (median over UAVs)")
    if dl is not None:
        ax.axhline(dl, color="tab:orange", lw=0.9, label=f"Δl = {dl:.3g} m")
    ax.set_yscale("log")
    ax.set_ylabel("threshold (m)")
    ax.set_xlabel("time (s)")
    ax.legend(fontsize=8)
    ax.grid(True, lw=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
