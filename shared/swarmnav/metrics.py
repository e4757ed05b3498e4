"""Metrics (paper eq. 28 RMSE, NEES, detection; README "How to read the results") on plain arrays. Pure: numpy (and scipy.stats quantiles), no I/O.

Definitions (the report's keys keep exactly these meanings):

- **RMSE** (paper eq. 28), per ENU axis and 3-D, *pooled*: every (seed, epoch, UAV) sample counts
  once — RMSE_axis = sqrt(mean e_axis²), RMSE_3d = sqrt(mean ‖e‖²) over all samples of all seeds
  (not a mean of per-seed or per-UAV RMSEs). Samples without an estimate (NaN, e.g. a killed
  node in a distributed run) are left out and counted in ``n_missing``.
- **UAV 1** alone: the same pooling restricted to UAV id 1 (the paper's example UAV).
- **outage / nominal**: the UAVs listed in any GNSS outage window; ``outage`` = their samples with
  start_s <= t <= end_s of a window that lists them, ``nominal`` = the same UAVs' other samples.
- **NEES** of 3-D position: e^T P^-1 e with the estimator's own 3×3 marginal, averaged over every
  UAV, epoch and seed (expected value 3 for a consistent estimator). Non-positive-definite or
  missing covariances are skipped and counted.
- **Detection**, per classification decision: each UAV classifies each of its links each epoch
  (both ends of a pair decide independently, so a link-epoch yields up to two decisions). A decision
  is *positive* when the link is classified H1 or H0 (double threshold), or H0 only (single threshold
  at Δh). Truth: the link-epoch is *faulty* when its labelled |fault_err| > 3σ of its row's ranging
  noise (``fault_threshold_m`` × the row's σ / ``uwb_sigma_m``; = fault_threshold_m for the
  simulator, whose rows all carry uwb_sigma_m), clean otherwise; unknown labels (NaN) are not scored. precision = TP/(TP+FP), recall = TP/(TP+FN),
  false-alarm rate = FP/(FP+TN); ``None`` when the denominator is 0.
- **NEES consistency** (:func:`nees_consistency`, navlie / Bar-Shalom style): ``nees_mean``, the share
  of UAV-epochs whose NEES lies in the two-sided χ²(3) 95 % band [0.216, 9.35]
  (``nees_in_band_share``, expected 0.95) and the shares below/above it, the mean against its
  two-sided bounds χ²(3M)/M, and per epoch the NEES averaged over seeds × UAVs against its bounds.
- **Range NIS** (:func:`range_nis_values`, :func:`nis_summary`), no truth needed: each two-way range
  against the estimates of both ends at the epoch before it, ν²/S with S = σ² + uᵀ(P_a + P_b)u,
  expected χ²(1).
- **Monte Carlo** (:func:`monte_carlo`): per algorithm the mean over seeds of the per-seed swarm
  3-D RMSE with a Student-t 95 % CI; paired per-seed differences a − b with CI and paired t-test.
  Beside, never instead of, the pooled RMSE above.
- **step_ms**: p50/p99 over every (UAV, epoch, seed) of the wall time the estimator spent.
- **improvement_pct** = 100·(1 − RMSE_a / RMSE_b) on the swarm 3-D position RMSE.
"""

from __future__ import annotations

import numpy as np

from .geometry import quat_rotate

AXES = ("e", "n", "u")


def rmse(err: np.ndarray) -> dict[str, float]:
    """Pooled RMSE of error vectors ``err`` (..., 3): {"e","n","u","3d"}; NaN rows skipped."""
    e = np.asarray(err, float).reshape(-1, 3)
    e = e[np.all(np.isfinite(e), axis=1)]
    if len(e) == 0:
        return {a: None for a in (*AXES, "3d")}
    out = {a: float(np.sqrt(np.mean(e[:, i] ** 2))) for i, a in enumerate(AXES)}
    out["3d"] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    return out


def rmse_masked(err: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Pooled RMSE over the samples where ``mask`` (same leading shape as err[..., 0]) is true."""
    return rmse(np.asarray(err)[np.asarray(mask, bool)])


def per_uav_rmse_3d(err: np.ndarray, uavs) -> dict[str, float]:
    """{"<id>": 3-D RMSE} for err shaped (..., N, 3) (any leading axes: seeds, epochs)."""
    e = np.asarray(err, float)
    return {str(int(u)): rmse(e[..., j, :])["3d"] for j, u in enumerate(uavs)}


def outage_masks(t: np.ndarray, uavs, windows) -> tuple[np.ndarray, np.ndarray] | None:
    """(outage, nominal) boolean masks shaped (K, N), or None without outage windows.

    ``windows``: objects or dicts with start_s, end_s, uavs (list of ids).
    """
    if not windows:
        return None
    t = np.asarray(t, float)
    uavs = list(int(u) for u in uavs)
    out = np.zeros((len(t), len(uavs)), bool)
    affected = np.zeros(len(uavs), bool)
    for w in windows:
        get = (lambda k: w[k]) if isinstance(w, dict) else (lambda k: getattr(w, k))
        inside = (t >= get("start_s")) & (t <= get("end_s"))
        for u in get("uavs"):
            if int(u) in uavs:
                j = uavs.index(int(u))
                affected[j] = True
                out[:, j] |= inside
    nominal = affected[None, :] & ~out
    return out, nominal


def nees_samples(err: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-sample 3-D position NEES e^T P^-1 e of ``err`` (..., 3) with ``cov`` (..., 3, 3).

    Returns (values (M,), their sample indices into the flattened leading shape, n_skipped): samples
    with NaN error or covariance, or a covariance that is not positive definite, are skipped."""
    e = np.asarray(err, float).reshape(-1, 3)
    P = np.asarray(cov, float).reshape(-1, 3, 3)
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    idx = np.flatnonzero(ok)
    skipped = int((~ok).sum())
    if not len(idx):
        return np.zeros(0), idx, skipped
    Pk = 0.5 * (P[idx] + np.transpose(P[idx], (0, 2, 1)))
    ek = e[idx]
    try:
        L = np.linalg.cholesky(Pk)
        z = np.linalg.solve(L, ek[..., None])[..., 0]
        return np.sum(z**2, axis=1), idx, skipped
    except np.linalg.LinAlgError:  # some not positive definite: fall back one by one
        v, keep = [], []
        for i, Pi, ei in zip(idx, Pk, ek):
            try:
                Li = np.linalg.cholesky(Pi)
            except np.linalg.LinAlgError:
                skipped += 1
                continue
            zi = np.linalg.solve(Li, ei)
            v.append(float(zi @ zi))
            keep.append(i)
        return np.array(v), np.array(keep, int), skipped


def nees(err: np.ndarray, cov: np.ndarray) -> tuple[float | None, int]:
    """Mean 3-D position NEES over all samples; returns (mean, n_skipped)."""
    vals, _, skipped = nees_samples(err, cov)
    if len(vals) == 0:
        return None, skipped
    return float(np.mean(vals)), skipped


# two-sided 95 % band of chi2(3) (scipy.stats.chi2.ppf([0.025, 0.975], 3)), used when scipy is absent
CHI2_3_BAND95 = (0.2157952826238981, 9.348403604496148)


def chi2_band(dof: int, p: float = 0.95) -> tuple[float, float]:
    """Two-sided ``p`` interval of a chi-square with ``dof`` degrees of freedom."""
    a = (1.0 - p) / 2.0
    try:
        from scipy.stats import chi2
    except ImportError:  # pragma: no cover - scipy is a dependency; constants / Wilson-Hilferty at 95 %
        if abs(p - 0.95) > 1e-12:
            raise
        if dof == 3:
            return CHI2_3_BAND95
        f = lambda z: dof * (1 - 2 / (9 * dof) + z * np.sqrt(2 / (9 * dof))) ** 3  # noqa: E731
        return float(f(-1.959963984540054)), float(f(1.959963984540054))
    return float(chi2.ppf(a, dof)), float(chi2.ppf(1 - a, dof))


def nees_consistency(err: np.ndarray, cov: np.ndarray, p: float = 0.95) -> dict:
    """Consistency of the 3-D position covariance, navlie / Bar-Shalom style.

    ``err`` (S, K, N, 3) and ``cov`` (S, K, N, 3, 3) (seeds, epochs, UAVs; fewer leading axes are
    read as a single seed / epoch). For a consistent estimator each NEES is chi2(3):

    - ``nees_mean``: mean over every UAV-epoch of every seed (expected 3);
    - ``nees_mean_bounds``: the two-sided ``p`` interval of that mean for M independent samples,
      chi2(3M)/M — narrow for large M and optimistic, because errors are correlated in time;
    - ``nees_in_band_share``: share of UAV-epochs whose NEES lies in the two-sided chi2(3) band
      ``nees_band`` ([0.216, 9.35] at 95 %; expected 0.95); ``nees_below_band_frac`` (too small:
      covariance over-conservative) and ``nees_above_band_frac`` (too large: overconfident);
    - ``nees_epochs_in_bounds_frac``: the Monte-Carlo test per epoch: the NEES averaged over the
      R = seeds × UAVs runs at each epoch against chi2(3R)/R (expected 0.95);
    - ``nees_verdict``: the two-sided test of the mean: "overconfident" above ``nees_mean_bounds``,
      "conservative" below, "consistent" inside.
    """
    e = np.asarray(err, float)
    P = np.asarray(cov, float)
    while e.ndim < 4:
        e, P = e[None], P[None]
    S, K, N = e.shape[:3]
    vals, idx, skipped = nees_samples(e, P)
    lo, hi = chi2_band(3, p)
    out: dict = {"nees_mean": None, "nees_mean_bounds": None, "nees_in_band_share": None,
                 "nees_band": [lo, hi], "nees_below_band_frac": None, "nees_above_band_frac": None,
                 "nees_epochs_in_bounds_frac": None, "nees_n": int(len(vals)), "nees_verdict": None}
    if not len(vals):
        return out
    M = len(vals)
    mlo, mhi = chi2_band(3 * M, p)
    inb = (vals >= lo) & (vals <= hi)
    below, above = float(np.mean(vals < lo)), float(np.mean(vals > hi))
    out.update(nees_mean=float(np.mean(vals)), nees_mean_bounds=[mlo / M, mhi / M],
               nees_in_band_share=float(np.mean(inb)), nees_below_band_frac=below, nees_above_band_frac=above)
    # per epoch: average over seeds x UAVs (the Monte-Carlo runs of that epoch)
    grid = np.full(S * K * N, np.nan)
    grid[idx] = vals
    grid = grid.reshape(S, K, N).transpose(1, 0, 2).reshape(K, S * N)
    cnt = np.sum(np.isfinite(grid), axis=1)
    good = cnt > 0
    if good.any():
        avg = np.nansum(grid[good], axis=1) / cnt[good]
        bounds = {int(c): chi2_band(3 * int(c), p) for c in np.unique(cnt[good])}
        blo = np.array([bounds[int(c)][0] / c for c in cnt[good]])
        bhi = np.array([bounds[int(c)][1] / c for c in cnt[good]])
        out["nees_epochs_in_bounds_frac"] = float(np.mean((avg >= blo) & (avg <= bhi)))
    m = out["nees_mean"]
    out["nees_verdict"] = "overconfident" if m > mhi / M else "conservative" if m < mlo / M else "consistent"
    return out


def mean_ci(x, p: float = 0.95) -> dict:
    """Mean of ``x`` (None/NaN dropped) with its two-sided ``p`` Student-t confidence interval.

    {"n", "mean", "std" (sample, ddof 1), "ci95": [lo, hi]}; std and ci95 are None for n < 2."""
    v = np.array([np.nan if a is None else float(a) for a in np.ravel(np.asarray(x, dtype=object))], float)
    v = v[np.isfinite(v)]
    n = len(v)
    out: dict = {"n": int(n), "mean": float(np.mean(v)) if n else None, "std": None, "ci95": None}
    if n >= 2:
        from scipy.stats import t as student_t

        sd = float(np.std(v, ddof=1))
        h = float(student_t.ppf(0.5 + p / 2, n - 1)) * sd / np.sqrt(n)
        out.update(std=sd, ci95=[out["mean"] - h, out["mean"] + h])
    return out


MC_PAIRS = (("atvfg", "fg"), ("atvfg", "fkf"), ("atvfg", "central"), ("atvfg", "ins"), ("atvfg", "atvfg_paper"),
            ("atvfg_paper", "fg"), ("atvfg_paper", "fkf"), ("atvfg_paper", "central"))


def monte_carlo(seeds, per_seed: dict[str, list], pairs=MC_PAIRS, p: float = 0.95) -> dict:
    """Monte-Carlo headline over seeds: per algorithm the mean of the per-seed 3-D position RMSE with
    its Student-t CI, and paired per-seed differences a − b (mean, CI, two-sided paired t-test p
    value; negative = a better) and ratios a / b, for each pair in ``pairs`` where both ran.

    ``per_seed[algo]``: per-seed RMSE (m) in the order of ``seeds`` (None = no estimate that seed).
    A seed missing for either algorithm of a pair is left out of that pair."""
    seeds = [int(s) for s in seeds]
    out: dict = {"n_seeds": len(seeds), "seeds": seeds, "metric": "pos_rmse_m.3d per seed", "confidence": p,
                 "per_algorithm": {}, "paired": {}}
    for a, vals in per_seed.items():
        out["per_algorithm"][a] = {**mean_ci(vals, p), "per_seed": {str(s): v for s, v in zip(seeds, vals)}}
    for a, b in pairs:
        if a not in per_seed or b not in per_seed:
            continue
        d, r = [], []
        for va, vb in zip(per_seed[a], per_seed[b]):
            if va is None or vb is None or not (np.isfinite(va) and np.isfinite(vb)):
                continue
            d.append(va - vb)
            r.append(va / vb if vb > 0 else np.nan)
        st = mean_ci(d, p)
        pv = None
        if st["n"] >= 2:
            if st["std"] and st["std"] > 0:
                from scipy.stats import t as student_t

                tt = st["mean"] / (st["std"] / np.sqrt(st["n"]))
                pv = float(2 * student_t.sf(abs(tt), st["n"] - 1))
            else:
                pv = 0.0 if st["mean"] else 1.0
        out["paired"][f"{a}-{b}"] = {**st, "p_value": pv, "ratio": mean_ci(r, p),
                                     "a_better_seeds": int(sum(x < 0 for x in d))}
    return out


def range_nis_values(t_epochs, uavs, pos, vel, cov, quat, ranges, tags: dict, anchors: dict,
                     thr=None) -> tuple[np.ndarray, np.ndarray]:
    """NIS of each two-way range against the estimate the swarm had *before* it (no truth needed).

    A range at t in epoch k (t_{k-1} < t <= t_k) is predicted from the epoch k-1 estimates of both
    ends: p + v (t − t_{k-1}) + R(q)·lever arm (UAVs; anchors: known position + lever arm). Innovation
    ν = range − ‖p_a − p_b‖, S = σ_row² + uᵀ(P_a + P_b)u (u the unit line of sight), NIS = ν²/S,
    expected χ²(1). Neglected: the cross-covariance of the two ends (errors common to both, e.g. a
    formation-wide shift, make S too large: NIS biased low), attitude uncertainty and the process
    noise over t − t_{k-1} (S too small: NIS biased high on fast-moving, loosely tracked UAVs). Rows of epoch 1 (no earlier estimate), rows touching an unknown node or a UAV
    without an estimate, and rows with a lever arm but no attitude are skipped.

    ``t_epochs`` (K,), ``pos``/``vel`` (K,N,3), ``cov`` (K,N,3,3), ``quat`` (K,N,4) as in
    :class:`swarmnav.evaluation.RunResult`; ``ranges`` the dataset's ranges table; ``tags``
    {node: {tag: lever arm}}; ``anchors`` {id: ENU position}; ``thr`` per-row fault thresholds
    (m) or None. Returns (nis (M,), label (M,): 1 clean, 0 faulty, -1 unknown)."""
    t_ep = np.asarray(t_epochs, float)
    K = len(t_ep)
    col = {int(u): j for j, u in enumerate(uavs)}
    tr = np.asarray(ranges["t"], float)
    if K < 2 or not len(tr):
        return np.zeros(0), np.zeros(0, int)
    dt = t_ep[1] - t_ep[0]
    k = np.ceil((tr - (t_ep[0] - dt)) / dt - 1e-9).astype(int)  # epoch k covers (t_{k-1}, t_k]
    i = k - 2  # index of epoch k-1 in the (epochs 1..K) arrays
    ok = (i >= 0) & (i < K)
    ids = [int(x) for x in col] + [int(x) for x in anchors] + [int(x) for x in tags]
    nmax = max(ids + [int(np.max(ranges["a"])), int(np.max(ranges["b"]))]) + 1
    tmax = max([int(g) for d in tags.values() for g in d] + [int(np.max(ranges["tag_a"])), int(np.max(ranges["tag_b"]))]) + 1
    col_lut = np.full(nmax, -1)
    for u, j in col.items():
        col_lut[u] = j
    anc_lut = np.full((nmax, 3), np.nan)
    for n, x in anchors.items():
        anc_lut[int(n)] = np.asarray(x, float)
    lev_lut = np.full((nmax, tmax, 3), np.nan)
    for n, d in tags.items():
        for g, arm in d.items():
            lev_lut[int(n), int(g)] = np.asarray(arm, float)
    ends = []
    for node_col, tag_col in (("a", "tag_a"), ("b", "tag_b")):
        nid = np.asarray(ranges[node_col], int)
        lev = lev_lut[nid, np.asarray(ranges[tag_col], int)]
        jcol = col_lut[nid]
        is_uav = jcol >= 0
        p = anc_lut[nid] + lev  # anchors (NaN elsewhere)
        m = np.flatnonzero(is_uav & ok)
        ii, jj = i[m], jcol[m]
        p[m] = pos[ii, jj] + vel[ii, jj] * (tr[m] - t_ep[ii])[:, None] + lev[m]
        arm = np.flatnonzero(np.any(lev[m] != 0, axis=1))  # lever arms to rotate (NaN arm: row dropped)
        if len(arm):
            q = quat[ii[arm], jj[arm]]
            qn = np.linalg.norm(q, axis=1, keepdims=True)
            p[m[arm]] += quat_rotate(q / qn, lev[m[arm]]) - lev[m[arm]]  # NaN without attitude: row dropped
        ends.append((p, m, ii, jj))
    (pa, ma, ia, ja), (pb, mb, ib, jb) = ends
    d = pa - pb
    rng = np.linalg.norm(d, axis=1)
    ok &= np.all(np.isfinite(d), axis=1) & (rng > 1e-9)
    u = np.zeros_like(d)
    u[ok] = d[ok] / rng[ok, None]
    var = np.zeros(len(tr))
    for m, ii, jj in ((ma, ia, ja), (mb, ib, jb)):
        var[m] += np.einsum("mi,mij,mj->m", u[m], cov[ii, jj], u[m])
    S = np.asarray(ranges["sigma"], float)[ok] ** 2 + var[ok]
    nu = np.asarray(ranges["range"], float)[ok] - rng[ok]
    good = np.isfinite(S) & (S > 0)
    nis = nu[good] ** 2 / S[good]
    err = np.abs(np.asarray(ranges["fault_err"], float))[ok][good]
    th = np.full(len(err), np.inf) if thr is None else np.broadcast_to(np.asarray(thr, float), tr.shape)[ok][good]
    label = np.where(np.isnan(err), -1, np.where(err > th, 0, 1))
    return nis, label


def nis_summary(nis: np.ndarray, label: np.ndarray, p: float = 0.95) -> dict:
    """Range NIS summary: over the rows labelled clean when the data have labels, else over every
    row (faults then inflate the mean; the median and the in-band share are robust to a few).
    Expected for a consistent estimator: mean 1, median 0.455, 95 % inside the chi2(1) band."""
    nis, label = np.asarray(nis, float), np.asarray(label, int)
    lo, hi = chi2_band(1, p)
    if (label >= 0).any():
        v, rows = nis[label == 1], "labelled clean"
    else:
        v, rows = nis, "all (no labels)"
    out = {"nis_rows": rows, "nis_n": int(len(v)), "nis_band": [lo, hi], "nis_mean": None, "nis_median": None,
           "nis_in_band_share": None, "nis_below_band_frac": None, "nis_above_band_frac": None}
    if len(v):
        out.update(nis_mean=float(np.mean(v)), nis_median=float(np.median(v)),
                   nis_in_band_share=float(np.mean((v >= lo) & (v <= hi))),
                   nis_below_band_frac=float(np.mean(v < lo)), nis_above_band_frac=float(np.mean(v > hi)))
    return out


def detection_counts(flagged: np.ndarray, faulty: np.ndarray) -> dict[str, int]:
    f = np.asarray(flagged, bool)
    y = np.asarray(faulty, bool)
    return {"tp": int(np.sum(f & y)), "fp": int(np.sum(f & ~y)), "fn": int(np.sum(~f & y)), "tn": int(np.sum(~f & ~y))}


def detection_scores(flagged: np.ndarray, faulty: np.ndarray) -> dict:
    """precision / recall / false_alarm_rate (None when undefined) plus the raw counts."""
    c = detection_counts(flagged, faulty)
    div = lambda a, b: (a / b) if b else None  # noqa: E731
    return {"precision": div(c["tp"], c["tp"] + c["fp"]), "recall": div(c["tp"], c["tp"] + c["fn"]),
            "false_alarm_rate": div(c["fp"], c["fp"] + c["tn"]), **c}


def match_links_to_labels(links: np.ndarray, labels: np.ndarray, threshold_m: float, return_mask: bool = False):
    """Join classification decisions with link-epoch labels.

    links: records with fields k, observer, other, cls (LINK_DTYPE); labels: records k, a, b, err
    with a < b and one row per (k, a, b), and optionally thr, the link-epoch's own threshold (see
    :func:`swarmnav.evaluation.link_labels`; ``threshold_m`` applies when absent). Returns
    (cls, faulty) arrays of the decisions that have a known label, the number of decisions without
    one, and with ``return_mask`` the boolean mask of those decisions within ``links``.
    """
    n = len(links)
    if n == 0 or len(labels) == 0:
        r = (np.zeros(0, int), np.zeros(0, bool), n)
        return (*r, np.zeros(n, bool)) if return_mask else r
    o = links["observer"].astype(np.int64)
    x = links["other"].astype(np.int64)
    M = int(max(o.max(), x.max(), labels["a"].max(), labels["b"].max())) + 1
    key_l = (links["k"].astype(np.int64) * M + np.minimum(o, x)) * M + np.maximum(o, x)
    key_b = (labels["k"].astype(np.int64) * M + labels["a"].astype(np.int64)) * M + labels["b"].astype(np.int64)
    order = np.argsort(key_b, kind="stable")
    sk = key_b[order]
    pos = np.minimum(np.searchsorted(sk, key_l), len(sk) - 1)
    found = sk[pos] == key_l
    err = np.where(found, np.asarray(labels["err"], float)[order][pos], np.nan)
    # the link-epoch's own threshold (link_labels: 3σ of the row's noise) where the labels carry one
    thr = (np.asarray(labels["thr"], float)[order][pos] if labels.dtype.names and "thr" in labels.dtype.names
           else np.full(len(err), float(threshold_m)))
    valid = found & ~np.isnan(err)
    r = (np.asarray(links["cls"])[valid].astype(int), err[valid] > thr[valid], int((~valid).sum()))
    return (*r, valid) if return_mask else r


def detection_report(links: np.ndarray, labels: np.ndarray, threshold_m: float) -> tuple[dict | None, dict | None]:
    """(double-threshold scores, single-threshold-at-Δh scores), None when nothing is scorable.

    Double: positive = H1 or H0. Single at Δh: positive = H0 (residual above Δh)."""
    cls, faulty, unlabelled = match_links_to_labels(links, labels, threshold_m)
    if len(cls) == 0:
        return None, None
    double = detection_scores(cls <= 1, faulty)  # H0 = 0, H1 = 1
    single = detection_scores(cls == 0, faulty)
    double["n_unlabelled"] = single["n_unlabelled"] = unlabelled
    return double, single


def percentiles(x: np.ndarray, qs=(50, 99)) -> dict[str, float | None]:
    v = np.asarray(x, float).ravel()
    v = v[np.isfinite(v)]
    return {f"p{q}": (float(np.percentile(v, q)) if len(v) else None) for q in qs}


def improvement_pct(rmse_a: float | None, rmse_b: float | None) -> float | None:
    """100·(1 − a/b): how much better algorithm a is than b (positive = a better)."""
    if rmse_a is None or rmse_b is None or not rmse_b > 0:
        return None
    return float(100.0 * (1.0 - rmse_a / rmse_b))


def algorithm_metrics(uavs, t, pos_err: list[np.ndarray], vel_err: list[np.ndarray], cov: list[np.ndarray],
                      step_ms: list[np.ndarray], outage_windows=None) -> dict:
    """The per-algorithm block of report.json from per-seed arrays (each (K,N,3) / (K,N,3,3) / (K,N)).

    Seeds are pooled by concatenation, so every (seed, epoch, UAV) sample weighs the same.
    """
    uavs = [int(u) for u in uavs]
    pe = np.stack(pos_err)  # (S,K,N,3)
    ve = np.stack(vel_err)
    out: dict = {"pos_rmse_m": rmse(pe), "vel_rmse_mps": rmse(ve)}
    out["uav1_pos_rmse_m"] = rmse(pe[:, :, uavs.index(1)]) if 1 in uavs else {a: None for a in (*AXES, "3d")}
    out["uav1_vel_rmse_mps"] = rmse(ve[:, :, uavs.index(1)]) if 1 in uavs else {a: None for a in (*AXES, "3d")}
    out["per_uav_pos_rmse_m"] = per_uav_rmse_3d(pe, uavs)
    masks = outage_masks(t, uavs, outage_windows)
    if masks is not None:
        mo, mn = masks
        S = pe.shape[0]
        out["outage_pos_rmse_m"] = rmse_masked(pe, np.broadcast_to(mo, (S, *mo.shape)))
        out["nominal_pos_rmse_m"] = rmse_masked(pe, np.broadcast_to(mn, (S, *mn.shape)))
        out["outage_vel_rmse_mps"] = rmse_masked(ve, np.broadcast_to(mo, (S, *mo.shape)))
        out["nominal_vel_rmse_mps"] = rmse_masked(ve, np.broadcast_to(mn, (S, *mn.shape)))
    n, skipped = nees(pe, np.stack(cov))
    out["nees"] = n
    out["nees_skipped"] = skipped
    out.update(nees_consistency(pe, np.stack(cov)))
    # per-seed swarm 3-D RMSE, in the caller's seed order (report.build_report moves it to monte_carlo)
    out["per_seed_pos_rmse_3d_m"] = [rmse(pe[s])["3d"] for s in range(pe.shape[0])]
    out["step_ms"] = percentiles(np.stack(step_ms), (50, 99))
    out["n_samples"] = int(np.all(np.isfinite(pe), axis=-1).sum())
    out["n_missing"] = int((~np.all(np.isfinite(pe), axis=-1)).sum())
    return out
