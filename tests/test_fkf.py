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


def _locked_out_run(smoke, max_reject):
    """One UAV at rest at the origin, 4 fixed anchors, an initial position 3 m off with a claimed
    σ of 5 cm (an over-confident filter): every anchor range fails the χ² test."""
    import dataclasses

    from swarmnav.dataset import EpochInput

    u = smoke.meta.uav_ids()[0]
    init = dataclasses.replace(initial_states(smoke, 1)[u], pos=np.array([3.0, 0.0, 0.0]),
                               pos_sigma=np.full(3, 0.05), vel=np.zeros(3), vel_sigma=0.01,
                               quat=np.array([1.0, 0.0, 0.0, 0.0]), att_sigma=np.full(3, 1e-3))
    est = FkfEstimator(u, smoke.meta, {"fkf_anchor_max_reject": max_reject}, init)
    est.anchors = {100: np.array([10.0, 0, 0]), 101: np.array([0, 10.0, 0]), 102: np.array([-10.0, 0, 0]),
                   103: np.array([0, -10.0, 5.0])}
    est.tags_self = {0: np.zeros(3)}
    g0 = float(np.linalg.norm(est.params.n_gravity))
    for k in range(1, 41):
        t_prev, t = init.t + (k - 1) * 0.1, init.t + k * 0.1
        a = 100 + k % 4
        inp = EpochInput(u, k, t, t_prev, t_prev + np.arange(10) * 0.01, np.zeros((10, 3)),
                         np.tile([0.0, 0.0, g0], (10, 1)), range_t=np.array([t]), range_other=np.array([a]),
                         range_tag_self=np.array([0]), range_tag_other=np.array([0]),
                         range_m=np.array([np.linalg.norm(est.anchors[a])]), range_sigma=np.array([0.1]))
        est.begin_epoch(inp)
        for r in (1, 2):
            est.iterate(r, {})
        out = est.end_epoch()
    return float(np.linalg.norm(out.pos))


def test_anchor_lockout_guard(smoke):
    """χ² lock-out (MILUV fkf: 253 m): without the guard an over-confident filter rejects every
    anchor range for good; with it (default: 3 of the last 6 anchor ranges failed) they are fused again."""
    assert _locked_out_run(smoke, 0) > 2.5
    assert _locked_out_run(smoke, 3) < 1.0
