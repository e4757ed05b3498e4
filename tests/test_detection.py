"""Double-threshold detection: residual matrix, K-means Δh with fault-free guard, eq. 24 weight."""

from __future__ import annotations

import numpy as np
import pytest

from swarmnav.estimators import detection as D
from swarmnav.estimators.base import LinkClass


def test_residual_matrix_sorted_and_exact():
    pos = {3: np.array([0.0, 0, 0]), 1: np.array([10.0, 0, 0]), 2: np.array([0.0, 20, 0])}
    ranges = {(2, 3): 21.0, (1, 2): np.hypot(10, 20), (1, 3): 9.5, (1, 9): 5.0}  # 9 has no position
    pairs, res = D.residual_matrix(pos, ranges)
    assert pairs.tolist() == [[1, 2], [1, 3], [2, 3]]
    np.testing.assert_allclose(res, [0.0, 0.5, 1.0], atol=1e-12)


@pytest.mark.parametrize("dl,dh", [(0.3, 5.0), (1.0, 1.5), (0.05, 100.0)])
def test_eq24_continuous_at_both_thresholds(dl, dh):
    eps = 1e-9
    w = D.weight_eq24([dl - eps, dl, dl + eps, dh - eps, dh, dh + eps], dl, dh)
    assert w[0] == 1.0
    assert abs(w[1] - 1.0) < 1e-12 and abs(w[2] - 1.0) < 1e-6
    assert abs(w[3]) < 1e-6 and w[4] == 0.0 and w[5] == 0.0
    # monotone non-increasing in between, in [0, 1]
    grid = np.linspace(0, 1.2 * dh, 2001)
    wg = D.weight_eq24(grid, dl, dh)
    assert np.all(np.diff(wg) <= 1e-12) and wg.min() >= 0 and wg.max() <= 1
    # the formula itself
    r = 0.5 * (dl + dh)
    assert D.weight_eq24([r], dl, dh)[0] == pytest.approx(dl / r * ((dh - r) / (dh - dl)) ** 2)


def test_classification_three_hypotheses():
    cls = D.classify([0.1, 0.3, 0.31, 4.9, 5.0, 5.01, 80.0], 0.3, 5.0)
    H0, H1, H2 = int(LinkClass.H0_FAILED), int(LinkClass.H1_INTERFERED), int(LinkClass.H2_NORMAL)
    assert cls.tolist() == [H2, H2, H1, H1, H1, H0, H0]
    assert D.classify_single([0.1, 4.0, 6.0], 5.0).tolist() == [H2, H2, H0]


@pytest.mark.parametrize("seed", range(5))
def test_exact_two_means_matches_sklearn(seed):
    rng = np.random.default_rng(seed)
    x = np.concatenate([np.abs(rng.normal(0, 0.15, 140)), rng.uniform(20, 150, 12), rng.uniform(1, 8, 10)])
    b_ex = D.two_means_boundary(x, "exact")
    b_sk = D.two_means_boundary(x, "sklearn")
    # K-means on raw residuals: every clean residual falls in the low cluster (the split may fall
    # inside the widely spread failures, whose low part then gets a tiny eq. 24 weight)
    for b in (b_ex, b_sk):
        assert 0.6 < b < 150.0
    # sklearn's Lloyd iteration reaches the exact 1-D optimum here, or a split no better than it
    assert b_ex == pytest.approx(b_sk) or _sse(x, b_sk) >= _sse(x, b_ex) - 1e-9


def _sse(x, b):
    lo, hi = x[x < b], x[x >= b]
    return float(((lo - lo.mean()) ** 2).sum() + ((hi - hi.mean()) ** 2).sum())


def test_fault_free_guard_keeps_clean_links():
    rng = np.random.default_rng(3)
    dl = 0.35
    x = np.abs(rng.normal(0, 0.12, 150))
    assert D.two_means_boundary(x) < dl  # K-means still splits the noise...
    dh, cls, w = D.detect(x, dl)
    assert dh == pytest.approx(D.DEFAULT_FLOOR_FACTOR * dl)  # ...the guard lifts Δh
    assert np.all(cls != int(LinkClass.H0_FAILED))
    assert np.all(w > 0.3)


def test_faulty_links_excluded_and_interfered_downweighted():
    rng = np.random.default_rng(4)
    clean = np.abs(rng.normal(0, 0.12, 140))
    inter = rng.uniform(1.5, 6, 8)
    fail = rng.uniform(30, 150, 10)
    x = np.concatenate([clean, inter, fail])
    dl = 0.35
    dh, cls, w = D.detect(x, dl)
    assert D.DEFAULT_FLOOR_FACTOR * dl <= dh <= D.DEFAULT_CEIL_FACTOR * dl
    assert np.all(cls[-10:] == int(LinkClass.H0_FAILED)) and np.all(w[-10:] == 0)
    # interference: down-weighted (H1, weight < 0.3) or excluded (H0), never full weight
    assert np.all(cls[140:148] != int(LinkClass.H2_NORMAL)) and np.all(w[140:148] < 0.3)
    assert np.mean(cls[:140] == int(LinkClass.H2_NORMAL)) > 0.97
    # without the ceiling (plain 2-means) Δh may land above the interference: then all of it is H1
    dh0, cls0, _ = D.detect(x, dl, ceil_factor=None)
    assert dh0 > 6 and np.all(cls0[140:148] == int(LinkClass.H1_INTERFERED))


@pytest.mark.parametrize("seed", range(5))
def test_module_failure_spread_all_h0(seed):
    # paper fault 2: one module failed (17 links, range + U(20, 150) m) while ~10 % of links are
    # interfered (+U(1, 8) m); plain 2-means cuts INSIDE the failure spread, so low failures were H1
    rng = np.random.default_rng(100 + seed)
    dl = 0.7
    clean = np.abs(rng.normal(0, 0.2, 130))
    inter = rng.uniform(1, 8, 15)
    fail = rng.uniform(20, 150, 17)
    x = np.concatenate([clean, inter, fail])
    assert D.two_means_boundary(x) > 20  # the problem: the first split is inside the failures
    dh, cls, w = D.detect(x, dl)
    assert D.DEFAULT_FLOOR_FACTOR * dl <= dh <= D.DEFAULT_CEIL_FACTOR * dl
    assert np.all(cls[-17:] == int(LinkClass.H0_FAILED)) and np.all(w[-17:] == 0)
    assert np.all(cls[130:145] != int(LinkClass.H2_NORMAL))
    h1 = cls == int(LinkClass.H1_INTERFERED)
    assert np.all(w[h1] <= (dl / x[h1]) ** 2 + 1e-12)  # the eq. 25 cap
    assert np.all(cls[:130] == int(LinkClass.H2_NORMAL))
    # same with the failures alone beside clean links (no interference)
    dh2, cls2, _ = D.detect(np.concatenate([clean, fail]), dl)
    assert np.all(cls2[-17:] == int(LinkClass.H0_FAILED)) and np.all(cls2[:130] == int(LinkClass.H2_NORMAL))


def test_ceiling_descent_and_clamp():
    dl = 0.5
    # a single wide fault cluster: descent stops at the clean/fault split
    x = np.r_[np.linspace(0, 0.4, 50), np.linspace(3, 200, 20)]
    dh = D.upper_threshold(x, dl)
    assert D.DEFAULT_FLOOR_FACTOR * dl <= dh <= 3.0
    assert D.upper_threshold(x, dl, ceil_factor=None) > 3.0
    # clean only: the fault-free guard
    assert D.upper_threshold(np.linspace(0, 0.4, 50), dl) == pytest.approx(D.DEFAULT_FLOOR_FACTOR * dl)
    # ceiling never below the floor
    assert D.upper_threshold(x, dl, floor_factor=4.0, ceil_factor=2.0) == pytest.approx(4.0 * dl)


def test_h1_weight_cap_eq25():
    dl, dh = 0.7, 7.0
    r = np.linspace(0, 10, 1001)
    cap = D.weight_cap_eq25(r, dl)
    assert np.all(cap[r <= dl] == 1.0) and D.weight_cap_eq25([dl + 1e-9], dl)[0] == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.diff(cap) <= 1e-12)
    _, _, w = D.detect(r, dl, cap_h1=True, ceil_factor=None, floor_factor=dh / dl)
    assert np.all(w <= cap + 1e-12) and np.all(w <= D.weight_eq24(r, dl, dh) + 1e-12)
    # influence w·∂ (∝ pull on the estimate) decreases beyond Δl: redescending, not Huber-flat
    m = (r > dl) & (r < dh)
    assert np.all(np.diff((w * r)[m]) <= 1e-12)


def test_sliding_window_pools_sparse_epochs():
    win = D.ResidualWindow(3)
    win.push(np.array([0.1, 0.2]))
    win.push(np.array([50.0]))
    pooled = win.values(np.array([0.15]))
    assert sorted(pooled.tolist()) == [0.1, 0.15, 0.2, 50.0]
    dh, cls, _ = D.detect(np.array([0.15]), 0.3, window=win)
    assert dh >= 0.9 - 1e-9 and cls.tolist() == [int(LinkClass.H2_NORMAL)]
    win.push(np.array([0.1]))
    win.push(np.array([0.1]))
    assert 50.0 not in win.values(np.array([0.1])).tolist()


def test_adaptive_window_pools_until_enough_residuals():
    win = D.ResidualWindow(1, min_residuals=5, max_epochs=4)
    for v in ([0.1, 0.2], [0.3], [0.4, 0.5], [0.6]):
        win.push(np.array(v))
    # 1 current + newest first: [0.6], [0.4, 0.5], [0.3] -> 5 reached, [0.1, 0.2] evicted anyway (max 4)
    assert sorted(win.values(np.array([0.05])).tolist()) == [0.05, 0.3, 0.4, 0.5, 0.6]
    # a dense epoch is clustered alone
    dense = np.linspace(0, 1, 10)
    assert len(win.values(dense)) == 10
    # default (no min) keeps the old single-epoch behaviour
    w0 = D.ResidualWindow(1)
    w0.push(np.array([1.0]))
    assert w0.values(np.array([0.1])).tolist() == [0.1]


@pytest.mark.parametrize("seed", range(6))
def test_the_c_detect_is_the_numpy_detect_bit_for_bit(seed):
    """detection.detect (one C call, ``_kernels.detect``) against its numpy reference
    (detect_numpy) on residual sets with faults, ties, a pooled window, with and without the
    ceiling and the H1 cap: Δh, classes and weights identical to the last bit; a non-finite
    residual takes the numpy path."""
    rng = np.random.default_rng(seed)
    for _ in range(300):
        m = int(rng.integers(0, 120))
        res = np.abs(rng.normal(0, 0.3, m))
        bad = rng.random(m) < 0.15
        res[bad] = rng.uniform(0.5, 150.0, bad.sum())
        if rng.random() < 0.3:
            res = np.round(res, 1)  # ties
        pool = np.concatenate([res, np.abs(rng.normal(0, 0.3, int(rng.integers(0, 200))))])
        dl, ff = float(rng.uniform(0.1, 0.6)), float(rng.choice([1.0, 3.0]))
        cf, cap = [None, 10.0, 2.0][int(rng.integers(0, 3))], bool(rng.integers(0, 2))
        win = D.ResidualWindow(2)
        win.push(pool[m:])
        got = D.detect(res, dl, win, ff, "exact", cf, cap)
        want = D.detect_numpy(res, dl, win.values(res), ff, "exact", cf, cap)
        assert got[0] == want[0] and np.array_equal(got[1], want[1]) and np.array_equal(got[2], want[2])
    res = np.array([0.1, np.nan, 3.0, 0.2, 0.15])
    got, want = D.detect(res, 0.3), D.detect_numpy(res, 0.3, res)
    assert got[0] == want[0] and np.array_equal(got[1], want[1]) and np.array_equal(got[2], want[2], equal_nan=True)


@pytest.mark.parametrize("res,ff,cf", [([-1e154, -5e153, 1e154], 0.0, None), ([-1e154, -1e154, 2e154], 3.0, 1e160)])
def test_the_c_detect_follows_argmin_where_the_2_means_sums_overflow(res, ff, cf):
    """|x| > ~1e154 overflows the squared sums: some splits' SSE is NaN, and np.argmin takes the
    first NaN where the C loop (v < best) skipped them — a different Δh from finite input."""
    res = np.array(res)
    with np.errstate(all="ignore"):
        got, want = D.detect(res, 0.3, None, ff, "exact", cf), D.detect_numpy(res, 0.3, res, ff, "exact", cf)
    assert got[0] == want[0] and np.array_equal(got[1], want[1]) and np.array_equal(got[2], want[2])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_the_c_detect_refuses_non_finite_values(bad):
    """The kernel called directly (detection.detect sends such values to detect_numpy): a
    ValueError, not a NaN comparator inside qsort."""
    from swarmnav.estimators import _kernels

    r, cls, w = np.array([0.1, 5.0, 60.0]), np.empty(3, np.int64), np.empty(3)
    for which in ("res", "pool"):
        args = {"res": r.copy(), "pool": r.copy()}
        args[which][1] = bad
        with pytest.raises(ValueError, match=f"{which} has a non-finite value"):
            _kernels.detect(args["res"], args["pool"], 0.3, 3.0, 10.0, True, cls, w)
