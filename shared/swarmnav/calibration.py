"""Offline calibration — pure, no I/O: the lower detection threshold Δl (paper §2.3.2 step 3)
and, for recorded data without truth, a held-out-range cross-validation of estimator settings.

Procedure (documented statistic): run the distributed ``fg`` estimator (every link Gaussian, no
detection) on *fault-free* data with **50 message-iteration rounds** per epoch (no early stop), over
a window of epochs after a warm-up; after each epoch take the range residuals
∂_ij = | d_ij − ‖p̂_i − p̂_j‖ | of every ranged pair on the converged estimates; Δl = the
**99th percentile** of those residuals. Where no training exists, Δl = ``delta_l_fallback_sigmas``
× σ_uwb (``fallback_delta_l``).
"""

from __future__ import annotations

import numpy as np

import dataclasses

from .dataset import Dataset, EpochSlicer, epoch_of, node_view
from .estimators.detection import fallback_delta_l  # noqa: F401  (re-exported: Δl's fallback lives with detection)
from .geometry import quat_to_matrix
from .initial import initial_states

PERCENTILE = 99.0
ROUNDS = 50


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
    nodes = {u: FgEstimator(u, node_view(meta), st, inits[u]) for u in uavs}  # what a UAV knows
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


def heldout_anchor_cv(ds: Dataset, seed: int, settings: dict, candidates: list[dict], folds: int = 4,
                      algo: str = "fg", progress=None) -> list[dict]:
    """Truth-free cross-validation of estimator settings on a recording with fixed anchors.

    For each fold f of ``folds``, every ``folds``-th range to an anchor (offset f, in time order)
    is removed from the dataset, with the passive-listening rows of the same transactions (a
    ``tdoa`` row at the range's time between the same two tags: its rdiff contains that range);
    ``algo`` runs on the rest with ``settings`` updated by each candidate; each held-out range is predicted from the estimate of its epoch (tag at
    pos + R·lever, the anchor's tag position) and scored by its error. Returns, per candidate, the
    RMS and median |error| over all folds (m) and the count — lower is a better model of the data,
    and no truth is used — and the normalised innovation squared of the held-out ranges,
    e² / (σ² + uᵀ P u) with the estimate's ENU position covariance P along the line of sight u
    (a truth-free counterpart of NEES, over ``n_nis`` ranges with a finite covariance): for a
    consistent covariance and Gaussian errors its mean is 1 and its median 0.455 (χ²₁). The mean
    is sensitive to NLOS ranges among the held-out ones; the median much less. ``progress(i, n)``
    is called after each run.
    """
    from .evaluation import run_algorithm

    meta = ds.meta
    anchors = meta.anchors()
    r = ds.table("ranges")
    t_end = meta.epoch_time(meta.n_epochs())
    idx = np.flatnonzero(np.isin(r["b"], list(anchors)) & np.isin(r["a"], meta.uav_ids())
                         & (r["t"] > meta.t_start) & (r["t"] <= t_end))
    if len(idx) < folds:
        raise ValueError(f"{len(idx)} anchor ranges: too few for {folds}-fold cross-validation")
    uavs = meta.uav_ids()
    out = []
    n_runs, done = len(candidates) * folds, 0
    for cand in candidates:
        errs, nis = [], []
        for f in range(folds):
            held = np.zeros(len(r["t"]), bool)
            held[idx[f::folds]] = True
            tables = {**ds.tables, "ranges": {c: v[~held] for c, v in r.items()}}
            if "tdoa" in ds.tables:
                # a passive row overheard the same transaction (same time): its rdiff contains the
                # held-out range's error (range_n), so it is held out too — else it leaks
                td = ds.table("tdoa")
                gone = {(float(t), frozenset((int(a), int(b))))
                        for t, a, b in zip(r["t"][held], r["tag_a"][held], r["tag_b"][held])}
                keep = np.array([(float(t), frozenset((int(a), int(b)))) not in gone
                                 for t, a, b in zip(td["t"], td["tag_init"], td["tag_resp"])], bool)
                tables["tdoa"] = {c: v[keep] for c, v in td.items()}
            part = dataclasses.replace(ds, tables=tables)
            st = dict(settings)
            st.update(cand)  # and over the [estimation.graph] overrides, which win in tuned_settings
            st["graph"] = {**(st.get("graph") or {}), **cand}
            res = run_algorithm(part, algo, seed, st)
            for i in np.flatnonzero(held):
                k = epoch_of(r["t"][i], meta.t_start, meta.epoch_dt_s)
                j = uavs.index(int(r["a"][i]))
                q, p = res.quat[k - 1, j], res.pos[k - 1, j]
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
                    continue
                tag = p + quat_to_matrix(q) @ np.asarray(meta.node(int(r["a"][i])).tags.get(int(r["tag_a"][i]), (0.0, 0.0, 0.0)))
                b = int(r["b"][i])
                anchor = anchors[b] + np.asarray(meta.node(b).tags.get(int(r["tag_b"][i]), (0.0, 0.0, 0.0)))
                d = tag - anchor
                errs.append(float(np.linalg.norm(d) - r["range"][i]))
                # the error's predicted variance: the range σ² plus the estimate's position
                # variance along the line of sight (NaN when the estimator reports no covariance)
                u_los = d / max(float(np.linalg.norm(d)), 1e-9)
                sig = float(r["sigma"][i]) if np.isfinite(r["sigma"][i]) and r["sigma"][i] > 0 else meta.uwb_sigma_m
                nis.append(errs[-1] ** 2 / (sig ** 2 + float(u_los @ res.pos_cov[k - 1, j] @ u_los)))
            done += 1
            if progress:
                progress(done, n_runs)
        e, z = np.array(errs), np.array(nis)
        z = z[np.isfinite(z)]
        out.append({"settings": dict(cand), "rms_m": float(np.sqrt(np.mean(e ** 2))) if len(e) else None,
                    "median_abs_m": float(np.median(np.abs(e))) if len(e) else None, "n": int(len(e)),
                    "nis_mean": float(np.mean(z)) if len(z) else None,
                    "nis_median": float(np.median(z)) if len(z) else None, "n_nis": int(len(z))})
    return out
