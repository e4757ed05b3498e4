"""central oracle: oracle rule, incremental vs batch (docs/baselines.md)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from swarmnav.config import load_config
from swarmnav.dataset import EpochSlicer, FaultKind
from swarmnav.estimators.central import CentralEstimator, X, azel_block_factor, keep_range
from swarmnav.initial import initial_states


def test_keep_range_rule():
    assert keep_range(FaultKind.NONE, 0.0, 0.3)
    assert not keep_range(FaultKind.NONE, 0.5, 0.3)
    assert not keep_range(FaultKind.INTERFERENCE, 0.1, 0.3)
    assert not keep_range(FaultKind.FAILURE, float("nan"), 0.3)


@pytest.fixture(scope="module")
def smoke():
    from swarmnav.sim import simulate

    return simulate(load_config("configs/smoke.toml"), 1)


def test_central_accuracy_and_incremental_vs_batch(smoke):
    """A lag longer than the run keeps every variable, so ISAM2 must match batch LM on all factors."""
    sl, inits = EpochSlicer(smoke), initial_states(smoke, 1)
    K = 8
    c = CentralEstimator(smoke.meta, {"central_lag_s": 1e6, "central_use_rel": False}, inits)
    graph, vals = gtsam.NonlinearFactorGraph(), gtsam.Values()
    real = c.smoother

    class Spy:
        def update(self, g, v, ts):
            graph.push_back(g)
            vals.insert(v)
            return real.update(g, v, ts)

        def __getattr__(self, name):
            return getattr(real, name)

    c.smoother = Spy()
    tr = smoke.table("truth")
    for k in range(1, K + 1):
        out = c.step({u: sl.epoch(k, u) for u in sl.uavs}, sl.range_labels(k))
    batch = gtsam.LevenbergMarquardtOptimizer(graph, vals).optimize()
    for u in sl.uavs:
        p_inc = out[u].pos
        p_b = batch.atPose3(X(u, K)).translation()
        assert np.linalg.norm(p_inc - p_b) < 0.05, (u, p_inc, p_b)
        i = np.flatnonzero((tr["node"] == u) & np.isclose(tr["t"], out[u].t))[0]
        assert np.linalg.norm(p_inc - [tr["pe"][i], tr["pn"][i], tr["pu"][i]]) < 5.0


def test_central_smoke_accuracy_and_nees(smoke):
    """Oracle on smoke (5 UAVs, 60 s, faults removed by label): near truth and NEES chi-square-ish."""
    sl, inits = EpochSlicer(smoke), initial_states(smoke, 1)
    c = CentralEstimator(smoke.meta, {}, inits)
    tr = smoke.table("truth")
    T = {(round(float(t), 6), int(n)): np.array([e, nn, u]) for t, n, e, nn, u in zip(tr["t"], tr["node"], tr["pe"], tr["pn"], tr["pu"])}
    err2, nees = [], []
    for k in range(1, smoke.meta.n_epochs() + 1):
        out = c.step({u: sl.epoch(k, u) for u in sl.uavs}, sl.range_labels(k))
        for u, r in out.items():
            e = r.pos - T[(round(r.t, 6), u)]
            err2.append(e @ e)
            nees.append(e @ np.linalg.solve(r.pos_cov, e))
    rmse, m = float(np.sqrt(np.mean(err2))), float(np.mean(nees))
    assert rmse < 1.0, rmse
    # mean of N chi2_3 draws: 3 ± a few sigma; epochs are correlated, so a loose [0.5, 9] band
    assert 0.5 < m < 9.0, m


def test_azel_block_factor_jacobian():
    rng = np.random.default_rng(0)
    v = gtsam.Values()
    poses = [gtsam.Pose3(gtsam.Rot3.RzRyRx(*rng.normal(size=3)), rng.normal(size=3) * 50) for _ in range(4)]
    for i, p in enumerate(poses):
        v.insert(i, p)
    f = azel_block_factor(0, [1, 2, 3], rng.normal(size=3), rng.normal(size=3) * 0.3, np.array([0.01, 0.02, 0.03]))
    A, b = f.linearize(v).jacobian()
    eps = 1e-6
    e0 = f.unwhitenedError(v)
    for i in range(4):
        for d in range(6):
            dv = np.zeros(6)
            dv[d] = eps
            v2 = gtsam.Values(v)
            v2.update(i, poses[i].retract(dv))
            num = (f.unwhitenedError(v2) - e0) / eps
            assert np.allclose(A[:, 6 * i + d], num, atol=1e-4), (i, d)
