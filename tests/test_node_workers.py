"""One in-process run's UAVs spread over forked worker processes (services/runtime/node_workers.py):
the same estimates as one process, bit for bit; a worker's error reaches the caller with its
traceback; a worker that dies stops the run loudly; no worker outlives the run."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np
import pytest

from services.runtime.node_workers import worker_groups
from swarmnav.config import load_config
from swarmnav.estimators.graph import GraphEstimator
from swarmnav.evaluation import run_algorithm
from swarmnav.sim import simulate

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def smoke():
    from services.settings import estimator_settings

    sc = load_config(REPO / "configs" / "smoke.toml", ["scenario.duration_s=12"])
    return simulate(sc, 1), estimator_settings(sc.estimation, base_dirs=(REPO, REPO / "configs"))


@pytest.mark.parametrize("workers", [2, 3])
def test_spread_over_workers_the_estimates_are_bit_identical(smoke, workers):
    ds, settings = smoke
    one = run_algorithm(ds, "atvfg", 1, settings, None, time.perf_counter)
    many = run_algorithm(ds, "atvfg", 1, settings, None, time.perf_counter, worker_groups(workers))
    for f in ("pos", "vel", "pos_cov", "quat", "rounds", "delta_h_m"):
        assert np.array_equal(getattr(one, f), getattr(many, f), equal_nan=True), f
    assert np.array_equal(np.sort(one.links, order=["k", "observer", "other"]),
                          np.sort(many.links, order=["k", "observer", "other"]))
    assert np.all(many.step_ms[1:] > 0)  # each worker times its own nodes
    assert not mp.active_children()


def test_a_workers_error_reaches_the_caller_and_every_worker_stops(smoke, monkeypatch):
    ds, settings = smoke
    real = GraphEstimator.iterate

    def failing(self, r, peers):
        if self.uav == 3 and self.k == 4:
            raise FloatingPointError("node 3 diverged")
        return real(self, r, peers)

    monkeypatch.setattr(GraphEstimator, "iterate", failing)  # inherited by the forked workers
    with pytest.raises(FloatingPointError, match="node 3 diverged") as err:
        run_algorithm(ds, "atvfg", 1, settings, None, None, worker_groups(2))
    assert any("in node worker" in n and "failing" in n for n in getattr(err.value, "__notes__", []))
    assert not mp.active_children()


def test_a_worker_that_dies_stops_the_run_loudly(smoke, monkeypatch):
    ds, settings = smoke
    real = GraphEstimator.begin_epoch

    def dying(self, inp):
        if self.uav == 2 and inp.k == 3:
            os._exit(7)
        return real(self, inp)

    monkeypatch.setattr(GraphEstimator, "begin_epoch", dying)
    with pytest.raises(RuntimeError, match=r"died \(exit code 7\)"):
        run_algorithm(ds, "atvfg", 1, settings, None, None, worker_groups(2))
    assert not mp.active_children()
