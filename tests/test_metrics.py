"""Metrics on hand-computed examples (the definitions of README "How to read the results")."""

import math

import numpy as np
import pytest

from swarmnav import metrics as M
from swarmnav.evaluation import LINK_DTYPE
from swarmnav.geometry import to_rotation


def test_rmse_axes_and_3d():
    e = np.array([[3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    r = M.rmse(e)
    assert r["e"] == pytest.approx(math.sqrt(9 / 2))
    assert r["n"] == pytest.approx(math.sqrt(16 / 2))
    assert r["u"] == 0.0
    assert r["3d"] == pytest.approx(math.sqrt((9 + 16) / 2))


def test_rmse_pools_samples_not_rmses():
    # seed A: 1 sample of error 1; seed B: 3 samples of error 3 -> pooled sqrt((1+27)/4) = sqrt(7),
    # not the mean of per-seed RMSEs (2) nor their RMS (sqrt(5))
    a = np.array([[[1.0, 0, 0]]])  # (K=1, N=1, 3)
    b = np.array([[[3.0, 0, 0]], [[3.0, 0, 0]], [[3.0, 0, 0]]])
    pooled = M.rmse(np.concatenate([a.reshape(-1, 3), b.reshape(-1, 3)]))
    assert pooled["3d"] == pytest.approx(math.sqrt(7))


def test_rmse_skips_nan_and_all_nan_is_none():
    e = np.array([[1.0, 1.0, 1.0], [np.nan, 0, 0]])
    assert M.rmse(e)["3d"] == pytest.approx(math.sqrt(3))
    assert M.rmse(np.full((2, 3), np.nan))["3d"] is None


def test_algorithm_metrics_pooling_uav1_per_uav():
    uavs = [1, 2]
    t = np.array([1.0, 2.0])
    # seed 1: uav1 errors (1,0,0),(1,0,0); uav2 (0,2,0),(0,2,0); seed 2: uav1 (3,0,0) x2, uav2 0
    e1 = np.array([[[1, 0, 0], [0, 2, 0]], [[1, 0, 0], [0, 2, 0]]], float)
    e2 = np.array([[[3, 0, 0], [0, 0, 0]], [[3, 0, 0], [0, 0, 0]]], float)
    cov = np.broadcast_to(np.eye(3), (2, 2, 3, 3)).copy()
    step = np.array([[1.0, 2.0], [3.0, 100.0]])
    m = M.algorithm_metrics(uavs, t, [e1, e2], [e1 * 0, e2 * 0], [cov, cov], [step, step])
    assert m["pos_rmse_m"]["3d"] == pytest.approx(math.sqrt((1 + 1 + 4 + 4 + 9 + 9 + 0 + 0) / 8))
    assert m["pos_rmse_m"]["e"] == pytest.approx(math.sqrt((1 + 1 + 9 + 9) / 8))
    assert m["uav1_pos_rmse_m"]["3d"] == pytest.approx(math.sqrt((1 + 1 + 9 + 9) / 4))
    assert m["per_uav_pos_rmse_m"] == {"1": pytest.approx(math.sqrt(5)), "2": pytest.approx(math.sqrt(2))}
    # NEES with identity covariance = squared error norm, averaged
    assert m["nees"] == pytest.approx((1 + 1 + 4 + 4 + 9 + 9) / 8)
    assert m["step_ms"]["p50"] == pytest.approx(2.5)
    assert m["step_ms"]["p99"] == pytest.approx(np.percentile([1, 2, 3, 100] * 2, 99))
    assert "outage_pos_rmse_m" not in m


def test_nees_uses_covariance():
    e = np.array([[2.0, 0, 0], [0, 0, 3.0]])
    P = np.array([np.diag([4.0, 1, 1]), np.diag([1.0, 1, 9])])
    n, skipped = M.nees(e, P)
    assert n == pytest.approx(1.0) and skipped == 0
    # a full covariance: e^T P^-1 e
    P2 = np.array([[2.0, 1, 0], [1, 2, 0], [0, 0, 1]])
    e2 = np.array([1.0, 1.0, 0.0])
    assert M.nees(e2[None], P2[None])[0] == pytest.approx(e2 @ np.linalg.solve(P2, e2))


def test_nees_skips_singular_and_nan():
    e = np.array([[1.0, 0, 0], [1.0, 0, 0], [np.nan, 0, 0]])
    P = np.array([np.eye(3), np.zeros((3, 3)), np.eye(3)])
    n, skipped = M.nees(e, P)
    assert n == pytest.approx(1.0) and skipped == 2


def test_outage_masks():
    t = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    windows = [{"start_s": 2.0, "end_s": 3.0, "uavs": [2]}]
    out, nom = M.outage_masks(t, [1, 2, 3], windows)
    assert out[:, 1].tolist() == [False, True, True, False, False]
    assert nom[:, 1].tolist() == [True, False, False, True, True]
    assert not out[:, [0, 2]].any() and not nom[:, [0, 2]].any()  # UAVs that keep GNSS are in neither
    assert M.outage_masks(t, [1], []) is None


def test_outage_rmse_in_algorithm_metrics():
    t = np.array([1.0, 2.0, 3.0])
    e = np.zeros((3, 2, 3))
    e[1, 1] = [0, 0, 6.0]  # UAV 2 during its outage
    e[0, 1] = [0, 0, 2.0]  # UAV 2 nominal
    e[:, 0] = [5.0, 0, 0]  # UAV 1 never loses GNSS: in neither figure
    cov = np.broadcast_to(np.eye(3), (3, 2, 3, 3))
    m = M.algorithm_metrics([1, 2], t, [e], [e], [cov], [np.ones((3, 2))],
                            [{"start_s": 2.0, "end_s": 2.0, "uavs": [2]}])
    assert m["outage_pos_rmse_m"]["3d"] == pytest.approx(6.0)
    assert m["outage_pos_rmse_m"]["u"] == pytest.approx(6.0)
    assert m["nominal_pos_rmse_m"]["3d"] == pytest.approx(math.sqrt(4 / 2))


def _links(rows):
    return np.array([(k, o, x, c, 0.0, 1.0) for k, o, x, c in rows], dtype=LINK_DTYPE)


def _labels(rows):
    dt = np.dtype([("k", np.int32), ("a", np.int32), ("b", np.int32), ("err", np.float64), ("kind", np.int16)])
    return np.array([(k, a, b, e, 0) for k, a, b, e in rows], dtype=dt)


def test_detection_counts_double_and_single():
    thr = 0.3
    labels = _labels([(1, 1, 2, 5.0), (1, 1, 3, 0.1), (1, 2, 3, 50.0), (2, 1, 2, 0.0), (2, 1, 3, np.nan)])
    links = _links([
        (1, 1, 2, 1),  # faulty (5 m), H1: detected by double, missed by single
        (1, 2, 1, 2),  # same link seen from UAV 2, H2: missed
        (1, 1, 3, 0),  # clean (0.1 m), H0: false alarm in both
        (1, 3, 2, 0),  # faulty (50 m), H0: detected by both (pair looked up unordered)
        (2, 2, 1, 2),  # clean, H2: true negative
        (2, 1, 2, 1),  # clean, H1: false alarm for double only
        (2, 1, 3, 0),  # unknown label: not scored
        (3, 1, 2, 0),  # no label row at all: not scored
    ])
    d, s = M.detection_report(links, labels, thr)
    assert (d["tp"], d["fp"], d["fn"], d["tn"]) == (2, 2, 1, 1)
    assert d["precision"] == pytest.approx(2 / 4)
    assert d["recall"] == pytest.approx(2 / 3)
    assert d["false_alarm_rate"] == pytest.approx(2 / 3)
    assert (s["tp"], s["fp"], s["fn"], s["tn"]) == (1, 1, 2, 2)
    assert s["recall"] == pytest.approx(1 / 3)
    assert s["false_alarm_rate"] == pytest.approx(1 / 3)
    assert d["n_unlabelled"] == 2


def test_detection_undefined_is_none():
    s = M.detection_scores(np.array([False, False]), np.array([False, False]))
    assert s["precision"] is None and s["recall"] is None and s["false_alarm_rate"] == 0.0
    assert M.detection_report(np.zeros(0, LINK_DTYPE), _labels([]), 0.3) == (None, None)


def test_improvement_pct():
    assert M.improvement_pct(5.0, 10.0) == pytest.approx(50.0)
    assert M.improvement_pct(12.0, 10.0) == pytest.approx(-20.0)
    assert M.improvement_pct(None, 10.0) is None and M.improvement_pct(1.0, 0.0) is None


def test_link_labels_merge_rows_per_epoch():
    """Rows merge per (epoch, pair); each link-epoch carries its own threshold, 3σ of its row's
    noise (fault_threshold_m × σ_row / uwb_sigma_m), and the scoring uses it."""
    from swarmnav.dataset import DatasetMeta
    from swarmnav.evaluation import link_labels

    class _Meta:
        t_start = 0.0
        epoch_dt_s = 1.0
        uwb_sigma_m = 0.2
        fault_threshold_m = 0.6
        fault_threshold_for = DatasetMeta.fault_threshold_for

    class _DS:
        meta = _Meta()

        def table(self, name):
            return {"t": np.array([0.5, 0.9, 1.0, 1.5, 2.5, 2.6]), "a": np.array([2, 1, 1, 1, 1, 1]),
                    "b": np.array([1, 2, 3, 2, 2, 2]), "fault_err": np.array([0.1, -4.0, np.nan, 0.0, 0.5, 0.7]),
                    "fault_kind": np.array([0, 1, 0, 0, 0, 0]), "sigma": np.array([0.2, 0.2, 0.2, np.nan, 0.1, 0.4])}

    lab = link_labels(_DS())
    got = {(int(k), int(a), int(b)): (float(e), float(th)) for k, a, b, e, _, th in lab.tolist()}
    assert got[(1, 1, 2)] == (4.0, 0.6)  # two rows in (0, 1]: the larger |err| / thr
    assert math.isnan(got[(1, 1, 3)][0])  # t = 1.0 belongs to epoch 1 ((0, 1])
    assert got[(2, 1, 2)] == (0.0, 0.6)  # no σ: the dataset's threshold
    # epoch 3: 0.5 m on a σ 0.1 row (thr 0.3: faulty) beats 0.7 m on a σ 0.4 row (thr 1.2: clean)
    assert got[(3, 1, 2)][0] == 0.5 and abs(got[(3, 1, 2)][1] - 0.3) < 1e-12
    links = np.array([(k, 1, 2, 1, 0.0, 1.0) for k in (1, 2, 3)], dtype=LINK_DTYPE)
    _, faulty, _ = M.match_links_to_labels(links, lab, 0.6)
    assert faulty.tolist() == [True, False, True]  # by the per-row thresholds (0.5 < 0.6 alone)


def _block(x):
    d = {a: x for a in ("e", "n", "u", "3d")}
    return {"pos_rmse_m": d, "vel_rmse_mps": d, "uav1_pos_rmse_m": d, "per_uav_pos_rmse_m": {"1": x},
            "nees": 3.0, "nees_mean": 3.0, "nees_in_band_share": 0.95, "step_ms": {"p50": 1.0, "p99": 2.0}}


def test_report_contract_and_improvement_keys():
    from swarmnav.report import build_report, render_markdown, validate_report

    kw = dict(mode="in-process", scenario="s", seeds=[1], n_uavs=1, duration_s=1.0, detection_single=None,
              delta_l_m=0.3, delta_h_m={"p50": 1.0, "p95": 2.0},
              provenance={"git": "abc", "config_sha256": "x", "packages": {}}, events=[])
    det = {"precision": 1.0, "recall": 0.5, "false_alarm_rate": float("nan")}
    rep = build_report(algorithms={"atvfg": _block(5.0), "fg": _block(10.0)}, detection=det, **kw)
    assert validate_report(rep) == ["missing thresholds.delta_l_used_m"]  # assembly adds what the nodes used
    rep["thresholds"]["delta_l_used_m"] = 0.3
    assert validate_report(rep) == []
    assert rep["improvement_pct"] == {"atvfg_vs_fg": 50.0}  # fkf did not run: no key
    assert rep["algorithms"]["atvfg"]["detection"]["false_alarm_rate"] is None  # NaN -> null
    assert "Table 2" in render_markdown(rep)
    rep2 = build_report(algorithms={"fg": _block(10.0)}, detection=None, **kw)
    rep2["thresholds"]["delta_l_used_m"] = None
    assert rep2["improvement_pct"] == {} and validate_report(rep2) == []
    bad = dict(rep)
    bad.pop("thresholds")
    del bad["algorithms"]["fg"]["nees"]
    del bad["algorithms"]["atvfg"]["nees_in_band_share"]
    errs = validate_report(bad)
    assert any("thresholds" in e for e in errs) and any("fg.nees" in e for e in errs)
    assert "missing algorithms.atvfg.nees_in_band_share" in errs
    assert "missing thresholds.delta_l_used_m" in errs


# -- consistency (NEES band) and Monte-Carlo statistics ------------------------------------------


def _synthetic(scale, S=4, K=200, N=5, seed=0):
    """Errors drawn from a known covariance P; the estimator reports scale * P."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(S, K, N, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)  # random full covariances
    e = (np.linalg.cholesky(P) @ rng.normal(size=(S, K, N, 3, 1)))[..., 0]
    return e, scale * P


def test_chi2_band_matches_the_contract():
    lo, hi = M.chi2_band(3)
    assert lo == pytest.approx(0.216, abs=5e-4) and hi == pytest.approx(9.35, abs=5e-3)
    assert (lo, hi) == pytest.approx(M.CHI2_3_BAND95)


def test_nees_consistency_passes_a_consistent_covariance():
    c = M.nees_consistency(*_synthetic(1.0))
    assert c["nees_n"] == 4 * 200 * 5
    lo, hi = c["nees_mean_bounds"]
    assert lo < 3.0 < hi and lo < c["nees_mean"] < hi
    assert c["nees_verdict"] == "consistent"
    assert c["nees_in_band_share"] == pytest.approx(0.95, abs=0.015)
    assert c["nees_below_band_frac"] == pytest.approx(0.025, abs=0.01)
    assert c["nees_above_band_frac"] == pytest.approx(0.025, abs=0.01)
    assert c["nees_epochs_in_bounds_frac"] > 0.9


@pytest.mark.parametrize("scale, verdict, side", [(0.25, "overconfident", "nees_above_band_frac"),
                                                  (4.0, "conservative", "nees_below_band_frac")])
def test_nees_consistency_is_two_sided(scale, verdict, side):
    """An overconfident (P/4) and an over-conservative (4P) covariance both fail: the mean outside
    its bounds on the right side, the in-band share below 90 %, misses on that side of the band."""
    c = M.nees_consistency(*_synthetic(scale))
    lo, hi = c["nees_mean_bounds"]
    assert not lo <= c["nees_mean"] <= hi
    assert c["nees_mean"] == pytest.approx(3.0 / scale, rel=0.1)
    assert c["nees_verdict"] == verdict
    assert c["nees_in_band_share"] < 0.90
    assert c[side] > 0.1
    assert c["nees_epochs_in_bounds_frac"] < 0.5


def test_nees_consistency_skips_missing_and_empty():
    e, P = _synthetic(1.0, S=1, K=3, N=2)
    e[0, 1, 0] = np.nan
    P[0, 2, 1] = 0.0  # not positive definite
    c = M.nees_consistency(e, P)
    assert c["nees_n"] == 4
    empty = M.nees_consistency(np.full((1, 2, 1, 3), np.nan), np.full((1, 2, 1, 3, 3), np.nan))
    assert empty["nees_mean"] is None and empty["nees_in_band_share"] is None and empty["nees_n"] == 0


def test_algorithm_metrics_carries_consistency_and_per_seed_rmse():
    e, P = _synthetic(1.0, S=2, K=20, N=2)
    m = M.algorithm_metrics([1, 2], np.arange(20.0), list(e), list(e), list(P), [np.ones((20, 2))] * 2)
    assert m["nees_mean"] == pytest.approx(m["nees"])
    assert 0 < m["nees_in_band_share"] <= 1
    assert m["per_seed_pos_rmse_3d_m"] == [pytest.approx(M.rmse(e[0])["3d"]), pytest.approx(M.rmse(e[1])["3d"])]


def test_mean_ci_student_t():
    x = [1.0, 2.0, 3.0, 4.0, None]
    r = M.mean_ci(x)
    assert r["n"] == 4 and r["mean"] == pytest.approx(2.5)
    h = 3.182446305284263 * np.std([1, 2, 3, 4], ddof=1) / 2  # t(0.975, 3)
    assert r["ci95"] == pytest.approx([2.5 - h, 2.5 + h])
    one = M.mean_ci([0.7])
    assert one["mean"] == 0.7 and one["ci95"] is None and one["std"] is None


def test_monte_carlo_paired_differences():
    seeds = [1, 2, 3, 4]
    per_seed = {"atvfg": [1.0, 1.1, 0.9, None], "fg": [2.0, 2.3, 1.8, 2.0], "central": [0.9, 1.0, 0.9, 1.0]}
    mc = M.monte_carlo(seeds, per_seed)
    assert mc["n_seeds"] == 4 and mc["seeds"] == seeds
    a = mc["per_algorithm"]["atvfg"]
    assert a["n"] == 3 and a["mean"] == pytest.approx(1.0) and a["per_seed"]["4"] is None
    d = mc["paired"]["atvfg-fg"]
    # per seed differences -1.0, -1.2, -0.9 (seed 4 has no atvfg): paired, not the difference of means
    assert d["n"] == 3 and d["mean"] == pytest.approx(-31 / 30)
    assert d["ci95"][1] < 0 and d["p_value"] < 0.01 and d["a_better_seeds"] == 3
    assert d["ratio"]["mean"] == pytest.approx(np.mean([0.5, 1.1 / 2.3, 0.5]))
    assert "atvfg-fkf" not in mc["paired"]  # fkf did not run
    c = mc["paired"]["atvfg-central"]
    assert c["ci95"][0] < c["mean"] < c["ci95"][1] and c["p_value"] > 0.05


def test_report_monte_carlo_and_consistency_sections():
    from swarmnav.report import build_report, render_markdown, validate_report

    kw = dict(mode="in-process", scenario="s", seeds=[1, 2, 3], n_uavs=2, duration_s=1.0, detection=None,
              detection_single=None, delta_l_m=0.3, delta_h_m={"p50": 1.0, "p95": 2.0},
              provenance={"git": "abc", "config_sha256": "x", "packages": {}}, events=[])
    e, P = _synthetic(1.0, S=3, K=10, N=2)
    blocks = {a: M.algorithm_metrics([1, 2], np.arange(10.0), list(e * f), list(e), list(P), [np.ones((10, 2))] * 3)
              for a, f in (("atvfg", 1.0), ("fg", 2.0))}
    rep = build_report(algorithms=blocks, **kw)
    rep["thresholds"]["delta_l_used_m"] = 0.3  # assembly adds what the nodes used
    assert validate_report(rep) == []
    mc = rep["monte_carlo"]
    assert mc["n_seeds"] == 3 and set(mc["per_algorithm"]) == {"atvfg", "fg"} and set(mc["paired"]) == {"atvfg-fg"}
    assert mc["per_algorithm"]["fg"]["per_seed"]["2"] == pytest.approx(2 * mc["per_algorithm"]["atvfg"]["per_seed"]["2"])
    assert mc["paired"]["atvfg-fg"]["ratio"]["mean"] == pytest.approx(0.5)
    assert "per_seed_pos_rmse_3d_m" not in rep["algorithms"]["atvfg"]  # moved to monte_carlo
    # the pooled figures keep their meaning
    assert rep["algorithms"]["atvfg"]["pos_rmse_m"]["3d"] == pytest.approx(M.rmse(e)["3d"])
    for k in ("nees_mean", "nees_in_band_share", "nees_mean_bounds"):
        assert k in rep["algorithms"]["fg"]
    md = render_markdown(rep)
    assert "Monte Carlo over 3 seeds" in md and "atvfg − fg" in md and "Consistency" in md
    one = build_report(algorithms={"atvfg": M.algorithm_metrics([1, 2], np.arange(10.0), [e[0]], [e[0]], [P[0]],
                                                                [np.ones((10, 2))])}, **{**kw, "seeds": [7]})
    assert one["monte_carlo"]["per_algorithm"]["atvfg"]["ci95"] is None
    assert "Monte Carlo" not in render_markdown(one)


def _range_world(cov_scale, K=400, seed=1, lever=(0.2, 0.0, 0.1)):
    """Two UAVs flying at constant velocity and one anchor; estimates = truth + N(0, P) with P known;
    ranges between tags (lever arms) drawn from the truth at their own times. The estimator
    reports cov_scale * P."""
    rng = np.random.default_rng(seed)
    t = np.arange(1, K + 1, dtype=float)
    v = np.array([[3.0, 1.0, 0.0], [-1.0, 2.0, 0.5]])
    p0 = np.array([[0.0, 0.0, 10.0], [40.0, -20.0, 15.0]])
    true = p0[None] + t[:, None, None] * v[None]  # (K,2,3)
    A = rng.normal(size=(K, 2, 3, 3)) * 0.3
    P = A @ np.swapaxes(A, -1, -2) + 0.01 * np.eye(3)
    pos = true + (np.linalg.cholesky(P) @ rng.normal(size=(K, 2, 3, 1)))[..., 0]
    quat = np.zeros((K, 2, 4))
    quat[..., 0] = np.cos(0.3)
    quat[..., 3] = np.sin(0.3)  # yaw 0.6 rad
    anchor = np.array([10.0, 30.0, 0.0])
    tags = {1: {0: lever}, 2: {0: (0.0, 0.0, 0.0)}, 100: {0: (0.0, 0.0, 0.0)}}
    rows = []
    sigma = 0.1
    for k in range(1, K + 1):  # epoch 1's rows have no earlier estimate: skipped
        for frac in (0.3, 1.0):
            tt = k - 1 + frac
            pt = p0 + tt * v
            arm = to_rotation(quat[0, 0]).apply(lever)  # scipy, independent of the code under test
            a1 = pt[0] + arm
            for b, pb in ((2, pt[1]), (100, anchor)):
                rows.append((tt, 1, b, np.linalg.norm(a1 - pb) + sigma * rng.normal(), sigma, 0.0))
    r = np.array(rows)
    ranges = {"t": r[:, 0], "a": r[:, 1].astype(int), "b": r[:, 2].astype(int), "tag_a": np.zeros(len(r), int),
              "tag_b": np.zeros(len(r), int), "range": r[:, 3], "sigma": r[:, 4], "fault_err": r[:, 5]}
    vel = np.broadcast_to(v, (K, 2, 3))
    return t, pos, vel, cov_scale * P, quat, ranges, tags, {100: anchor}


def test_range_nis_consistent_and_two_sided():
    """Range NIS against the prior estimate (no truth): chi2(1) for the true covariance; too large for
    an overconfident one, too small for an over-conservative one."""
    def run(scale):
        t, pos, vel, cov, quat, ranges, tags, anchors = _range_world(scale)
        nis, label = M.range_nis_values(t, [1, 2], pos, vel, cov, quat, ranges, tags, anchors, thr=0.3)
        assert len(nis) == 2 * 2 * (400 - 1)  # 2 ranges to 2 nodes per epoch, epoch 1 skipped
        return M.nis_summary(nis, label)

    good = run(1.0)
    assert good["nis_rows"] == "labelled clean"
    assert good["nis_mean"] == pytest.approx(1.0, abs=0.12) and good["nis_in_band_share"] == pytest.approx(0.95, abs=0.03)
    lo, hi = good["nis_band"]
    assert lo == pytest.approx(0.000982, rel=1e-2) and hi == pytest.approx(5.024, rel=1e-3)
    over, cons = run(0.1), run(10.0)
    assert over["nis_mean"] > 3 and over["nis_above_band_frac"] > 0.15
    assert cons["nis_mean"] < 0.3 and cons["nis_median"] < 0.1
    assert cons["nis_below_band_frac"] > 0.04 and cons["nis_in_band_share"] < good["nis_in_band_share"]


def test_range_nis_labels_and_unknown_nodes():
    t, pos, vel, cov, quat, ranges, tags, anchors = _range_world(1.0, K=20)
    ranges["fault_err"] = ranges["fault_err"].copy()
    ranges["fault_err"][4:10] = 5.0  # faulty rows (epochs 2 and 3): left out of the summary
    ranges["range"] = ranges["range"].copy()
    ranges["range"][4:10] += 5.0
    nis, label = M.range_nis_values(t, [1, 2], pos, vel, cov, quat, ranges, tags, anchors, thr=0.3)
    assert (label == 0).sum() == 6 and M.nis_summary(nis, label)["nis_n"] == (label == 1).sum()
    unl = M.nis_summary(nis, np.full(len(nis), -1))
    assert unl["nis_rows"] == "all (no labels)" and unl["nis_n"] == len(nis)
    nis2, _ = M.range_nis_values(t, [1, 2], pos, vel, cov, quat, ranges, tags, {}, thr=0.3)  # anchor unknown
    assert len(nis2) == len(nis) // 2
