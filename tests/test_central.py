"""central oracle: oracle rule, incremental vs batch (docs/baselines.md)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from swarmnav.config import load_config
from swarmnav.dataset import EpochSlicer, FaultKind
from swarmnav.estimators.central import CentralEstimator, X, keep_range
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
    c = CentralEstimator(smoke.meta, {"fixed_lag_s": 1e6, "central_use_rel": False}, inits)
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
