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
    # fixed margins for this layout (tight_layout measured every tick label: ~0.5 s per figure)
    fig.subplots_adjust(left=0.08, right=0.985, top=0.955, bottom=0.065, hspace=0.08)
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
    fig.subplots_adjust(left=0.08, right=0.985, top=0.945, bottom=0.08, hspace=0.1)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_figures(out: Path, res0: dict, truth, res_all: dict, truths: list, windows, ds, meta, dl) -> None:
    """figures/*.png of a run (the paper's Fig. 7-10): UAV 1 and swarm position/velocity errors,
    atvfg's detection over time. Written by ``swarmnav evaluate`` and by the monitor alike."""
    import warnings

    from swarmnav.evaluation import link_labels
    from swarmnav.metrics import match_links_to_labels

    from services.recording import algo_color

    fig = out / "figures"
    fig.mkdir(exist_ok=True)
    if not res0:
        return
    colors = {a: algo_color(a) for a in res0}
    t = truth.t
    uavs = list(truth.uavs)
    win = [(w.start_s, w.end_s) for w in windows]
    if 1 in uavs:
        j = uavs.index(1)
        error_figure(fig / "pos_error_uav1.png", t, {a: r.pos[:, j] - truth.pos[:, j] for a, r in res0.items()},
                     f"UAV 1 position error (seed {next(iter(res0.values())).seed})", "m", colors, win)
        error_figure(fig / "vel_error_uav1.png", t, {a: r.vel[:, j] - truth.vel[:, j] for a, r in res0.items()},
                     f"UAV 1 velocity error (seed {next(iter(res0.values())).seed})", "m/s", colors, win)

    def rms(arrs):  # list of (K,N,3) -> (K,3), RMS over UAVs and seeds
        e = np.concatenate(arrs, axis=1)
        return np.sqrt(np.nanmean(e**2, axis=1))

    error_figure(fig / "pos_error_swarm.png", t,
                 {a: rms([r.pos - tr.pos for r, tr in zip(rl, truths)]) for a, rl in res_all.items()},
                 "swarm position error (RMS over UAVs and seeds)", "m", colors, win, rms=True)
    error_figure(fig / "vel_error_swarm.png", t,
                 {a: rms([r.vel - tr.vel for r, tr in zip(rl, truths)]) for a, rl in res_all.items()},
                 "swarm velocity error (RMS over UAVs and seeds)", "m/s", colors, win, rms=True)
    if "atvfg" in res0 and len(res0["atvfg"].links):
        r = res0["atvfg"]
        lk = r.links
        lab = link_labels(ds)
        K = len(t)
        cls, faulty, _, valid = match_links_to_labels(lk, lab, meta.fault_threshold_m, return_mask=True)
        kk = lk["k"][valid].astype(int)
        cnt = lambda m: np.bincount(kk[m] - 1, minlength=K)[:K] if len(kk) else np.zeros(K)  # noqa: E731
        flagged = cls <= 1
        with warnings.catch_warnings():  # epochs without any Δh (no ranges, sparse real data): NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            dh = np.nanmedian(np.where(np.isfinite(r.delta_h_m), r.delta_h_m, np.nan), axis=1) \
                if np.isfinite(r.delta_h_m).any() else np.full(K, np.nan)
        detection_figure(fig / "detection_atvfg.png", t, cnt(faulty), cnt(flagged & faulty), cnt(flagged & ~faulty),
                         cnt(cls == 0), cnt(cls == 1), dh, dl)
