"""Offline training of the lower detection threshold Δl (paper §2.3.2 step 3) — pure, no I/O.

Procedure (documented statistic): run the distributed ``fg`` estimator (every link Gaussian, no
detection) on *fault-free* data with **50 message-iteration rounds** per epoch (no early stop), over
a window of epochs after a warm-up; after each epoch take the range residuals
∂_ij = | d_ij − ‖p̂_i − p̂_j‖ | of every ranged pair on the converged estimates; Δl = the
**99th percentile** of those residuals. Where no training exists, Δl = ``delta_l_fallback_sigmas``
× σ_uwb (``fallback_delta_l``).
"""

from __future__ import annotations

import numpy as np

from .dataset import Dataset, EpochSlicer
from .initial import initial_states

PERCENTILE = 99.0
ROUNDS = 50


def fallback_delta_l(uwb_sigma_m: float, fallback_sigmas: float) -> float:
    return float(fallback_sigmas) * float(uwb_sigma_m)


def train_delta_l(ds: Dataset, seed: int, settings: dict, warmup_s: float = 20.0, window_s: float = 60.0,
                  rounds: int = ROUNDS, percentile: float = PERCENTILE) -> dict:
    """Δl from converged fault-free ``fg`` residuals (module docstring). Returns a JSON-able dict."""
    from .estimators.graph import FgEstimator
    from .protocol import node_epoch, run_epoch_in_process

    meta = ds.meta
    sl = EpochSlicer(ds)
    uavs = meta.uav_ids()
    inits = initial_states(ds, seed)
    st = dict(settings)
    st["rounds"] = rounds
    nodes = {u: FgEstimator(u, meta, st, inits[u]) for u in uavs}
    k_end = min(meta.n_epochs(), int(round((warmup_s + window_s) / meta.epoch_dt_s)))
    k_start = int(round(warmup_s / meta.epoch_dt_s)) + 1
    res_all = []
    for k in range(1, k_end + 1):
        out = run_epoch_in_process({u: node_epoch(nodes[u], sl.epoch(k, u), rounds, 0.0) for u in uavs})
        if k < k_start:
            continue
        lab = sl.range_labels(k)
        if len(lab["t"]) == 0:
            continue
        ok = np.isin(lab["a"], uavs) & np.isin(lab["b"], uavs)
        pa = np.array([out[int(a)].pos for a in lab["a"][ok]])
        pb = np.array([out[int(b)].pos for b in lab["b"][ok]])
        res_all.append(np.abs(lab["range"][ok] - np.linalg.norm(pa - pb, axis=1)))
    res = np.concatenate(res_all) if res_all else np.zeros(0)
    if len(res) == 0:
        return {"delta_l_m": None, "n_residuals": 0}
    return {
        "schema": "swarmnav.delta_l/1",
        "delta_l_m": float(np.percentile(res, percentile)),
        "statistic": f"p{percentile:g} of |d_ij - |p_i - p_j|| on converged fg estimates",
        "rounds": rounds,
        "epochs": [k_start, k_end],
        "n_residuals": int(len(res)),
        "residual_percentiles_m": {f"p{q}": float(np.percentile(res, q)) for q in (50, 90, 95, 99)},
        "dataset": meta.name,
        "seed": seed,
        "uwb_sigma_m": float(meta.uwb_sigma_m),
    }
