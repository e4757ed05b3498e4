"""fkf baseline: smoke accuracy, consistency, chi-square isolation (docs/baselines.md)."""

from __future__ import annotations

import numpy as np
import pytest

from swarmnav.config import load_config
from swarmnav.dataset import EpochSlicer
from swarmnav.estimators.base import LinkClass
from swarmnav.estimators.fkf import FkfEstimator
from swarmnav.initial import initial_states
from swarmnav.protocol import node_epoch, run_epoch_in_process

K = 30


@pytest.fixture(scope="module")
def smoke():
    from swarmnav.sim import simulate

    return simulate(load_config("configs/smoke.toml"), 1)


def _truth(ds):
    tr = ds.table("truth")
    return {(round(float(t), 6), int(n)): np.array([e, nn, u]) for t, n, e, nn, u in zip(tr["t"], tr["node"], tr["pe"], tr["pn"], tr["pu"])}


def _run(ds, settings, K=K, mutate=None):
    sl, inits, T = EpochSlicer(ds), initial_states(ds, 1), _truth(ds)
    ests = {u: FkfEstimator(u, ds.meta, settings, inits[u]) for u in sl.uavs}
    errs, nees, outs = [], [], []
    for k in range(1, K + 1):
        inputs = {u: sl.epoch(k, u) for u in sl.uavs}
        if mutate:
            mutate(k, inputs)
        res = run_epoch_in_process({u: node_epoch(ests[u], inputs[u], 3, 0.01) for u in sl.uavs})
        for u, r in res.items():
            e = r.pos - T[(round(r.t, 6), u)]
            errs.append(e @ e)
            nees.append(e @ np.linalg.solve(r.pos_cov, e))
            outs.append(r)
    return float(np.sqrt(np.mean(errs))), float(np.mean(nees)), outs


def test_fkf_beats_gnss_only_on_smoke(smoke):
    rmse, _, _ = _run(smoke, {})
    rmse_ins, _, _ = _run(smoke, {"fkf_beta_uwb": 1e-9})  # UWB sub-filter carries no prior share: IMU+GNSS
    assert rmse < rmse_ins, (rmse, rmse_ins)


def test_fkf_nees_on_smoke(smoke):
    """Loose bound on smoke (5 UAVs, 30 s). paper_faultfree 100 s with split CI: NEES 2.6
    (independent neighbours: ~10⁴, docs/baselines.md)."""
    _, nees, _ = _run(smoke, {})
    assert nees < 3 * 3.0, nees


def test_chi2_isolates_gross_range_fault(smoke):
    bad = {}

    def mutate(k, inputs):
        if k == 20:
            inp = inputs[1]
            j = 0
            inp.range_m = inp.range_m.copy()
            inp.range_m[j] += 60.0
            bad["other"] = int(inp.range_other[j])

    _, _, outs = _run(smoke, {}, K=20, mutate=mutate)
    r = [o for o in outs if o.uav == 1 and o.k == 20][0]
    cls = {l.other: l.cls for l in r.links}
    assert cls[bad["other"]] == LinkClass.H0_FAILED
