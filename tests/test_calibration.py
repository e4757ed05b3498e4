"""Truth-free cross-validation (calibration.heldout_anchor_cv) on synthetic data: the held-out
ranges' error and NIS, by hand."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from swarmnav import evaluation as ev
from swarmnav.calibration import heldout_anchor_cv
from swarmnav.config import load_config
from swarmnav.dataset import Node
from swarmnav.sim import simulate

ANCHOR = np.array([300.0, -200.0, 50.0])


@pytest.fixture(scope="module")
def anchored():
    """smoke + one anchor (node 100) and, at every epoch, UAV 1's range to it with a known error."""
    ds = simulate(load_config("configs/smoke.toml"), 1)
    tr = ev.truth_at_epochs(ds)
    meta = ds.meta.model_copy(update={"nodes": list(ds.meta.nodes) + [
        Node(id=100, kind="anchor", role="anchor", position_enu=tuple(ANCHOR), tags={0: (0.0, 0.0, 0.0)})]})
    K = ds.meta.n_epochs()
    err = np.linspace(-0.3, 0.3, K)  # measured − true (m)
    j = list(tr.uavs).index(1)
    rng = {"t": np.array([meta.epoch_time(k) for k in range(1, K + 1)]), "a": np.ones(K, int), "b": np.full(K, 100),
           "tag_a": np.zeros(K, int), "tag_b": np.zeros(K, int),
           "range": np.linalg.norm(tr.pos[:, j] - ANCHOR, axis=1) + err, "sigma": np.full(K, 0.1),
           "fault_kind": np.zeros(K, int), "fault_err": err}
    return dataclasses.replace(ds, meta=meta, tables={**ds.tables, "ranges": rng}), err, tr


def _fake_run(tr, cov):
    """run_algorithm stand-in: the true positions, identity attitude, covariance ``cov``."""
    def run(part, algo, seed, settings, progress=None):
        r = ev.RunResult.empty(algo, seed, tr.uavs, tr.t)
        r.pos[:] = tr.pos
        r.quat[:] = [1.0, 0.0, 0.0, 0.0]
        r.pos_cov[:] = cov
        return r
    return run


def test_heldout_error_and_nis_by_hand(anchored, monkeypatch):
    """Estimates at the truth with covariance c·I: each held-out range's error is −err and its NIS
    err² / (σ² + c) (the line of sight is a unit vector, so uᵀ(cI)u = c)."""
    ds, err, tr = anchored
    c = 0.03
    monkeypatch.setattr(ev, "run_algorithm", _fake_run(tr, c * np.eye(3)))
    (res,) = heldout_anchor_cv(ds, 0, {}, [{}], folds=3)
    assert res["n"] == res["n_nis"] == len(err)
    assert res["rms_m"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-9)
    nis = err ** 2 / (0.1 ** 2 + c)
    assert res["nis_mean"] == pytest.approx(nis.mean(), rel=1e-9)
    assert res["nis_median"] == pytest.approx(np.median(nis), rel=1e-9)


def test_heldout_nis_without_covariance_is_none(anchored, monkeypatch):
    ds, err, tr = anchored
    monkeypatch.setattr(ev, "run_algorithm", _fake_run(tr, np.full((3, 3), np.nan)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (res,) = heldout_anchor_cv(ds, 0, {}, [{}], folds=2)
    assert res["nis_mean"] is None and res["nis_median"] is None and res["n_nis"] == 0 and res["n"] == len(err)
