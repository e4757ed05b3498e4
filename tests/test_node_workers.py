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


@pytest.mark.parametrize("workers, algo", [(2, "atvfg"), (3, "atvfg"), (2, "ins"), (2, "fkf")])
def test_spread_over_workers_the_estimates_are_bit_identical(smoke, workers, algo):
    """(ins: no links, no Δh; fkf: a whole-swarm estimator, run in one process whatever the groups)"""
    ds, settings = smoke
    one = run_algorithm(ds, algo, 1, settings, None, time.perf_counter)
    many = run_algorithm(ds, algo, 1, settings, None, time.perf_counter, worker_groups(workers))
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


class SolverDiverged(Exception):
    """Pickles (args = its message) but cannot be rebuilt from that: __init__ takes two arguments."""

    def __init__(self, uav, k):
        super().__init__(f"node {uav} diverged at epoch {k}")


def test_a_workers_error_that_cannot_be_rebuilt_still_reaches_the_caller(smoke, monkeypatch):
    ds, settings = smoke
    real = GraphEstimator.iterate

    def failing(self, r, peers):
        if self.uav == 3 and self.k == 4:
            raise SolverDiverged(3, 4)
        return real(self, r, peers)

    monkeypatch.setattr(GraphEstimator, "iterate", failing)
    with pytest.raises(Exception, match="SolverDiverged: node 3 diverged at epoch 4") as err:
        run_algorithm(ds, "atvfg", 1, settings, None, None, worker_groups(2))
    assert "failing" in str(err.value)  # the worker's traceback
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


_KILLED_PARENT = """
import os, signal, sys
from pathlib import Path
REPO = Path(sys.argv[1])
import multiprocessing as mp
from services.runtime.node_workers import worker_groups
from services.settings import estimator_settings
from swarmnav.config import load_config
from swarmnav.evaluation import run_algorithm
from swarmnav.sim import simulate

sc = load_config(REPO / "configs" / "smoke.toml", ["scenario.duration_s=12"])
settings = estimator_settings(sc.estimation, base_dirs=(REPO, REPO / "configs"))

def progress(k, K):
    if k == 2:
        print(" ".join(str(p.pid) for p in mp.active_children()), flush=True)
        os.kill(os.getpid(), signal.SIGKILL)  # no finally, no atexit: as the OOM killer or kill -9

run_algorithm(simulate(sc, 1), "atvfg", 1, settings, progress, None, worker_groups(3))
"""


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")  # an orphan's zombie waits for init to reap it: it has exited


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_workers_exit_when_the_parent_is_killed(tmp_path):
    """A SIGKILLed parent runs no cleanup: each worker must see EOF on its pipe. Forked, a worker
    also held the parent's end of its own pipe (and of the earlier workers'), so none ever did."""
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    out, err = tmp_path / "stdout", tmp_path / "stderr"
    with out.open("w") as fo, err.open("w") as fe:  # files, not pipes: orphans would hold a pipe open
        rc = subprocess.run([sys.executable, "-c", _KILLED_PARENT, str(REPO)], cwd=REPO, env=env,
                            stdout=fo, stderr=fe, timeout=120).returncode
    assert rc == -9, err.read_text()[-2000:]
    pids = [int(p) for p in out.read_text().split()]
    assert len(pids) == 3, out.read_text()
    deadline = time.monotonic() + 20.0
    while any(map(_running, pids)) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in pids if _running(p)]
    for p in alive:  # don't leave them behind on a failure
        os.kill(p, 9)
    assert not alive, f"orphaned node workers still running: {alive}"


def test_packed_estimates_of_the_wrong_shape_raise_instead_of_being_rechunked():
    """pack_estimates lays each estimate out as 19 numbers (pos, vel, pos_cov, quat): an estimate of
    another shape (here a 6 x 6 pos_cov, 46 numbers) must raise, as _store does in one process, not be
    reshaped into rows of 19 that mix the estimates (19 such estimates: 874 = 46 x 19 numbers)."""
    from services.runtime.node_workers import pack_estimates, unpack_estimates
    from swarmnav.estimators.base import NodeEstimate

    ests = {u: NodeEstimate(u, 1, 0.1, np.full(3, float(u)), np.zeros(3), np.eye(6)) for u in range(19)}
    with pytest.raises(ValueError):
        pack_estimates(ests)
    good = {u: NodeEstimate(u, 1, 0.1, np.full(3, float(u)), np.zeros(3), np.eye(3)) for u in range(19)}
    back = unpack_estimates(pack_estimates(good))
    assert all(np.array_equal(back[u].pos, good[u].pos) and np.array_equal(back[u].pos_cov, good[u].pos_cov)
               for u in good)
    assert unpack_estimates(pack_estimates({})) == {}
