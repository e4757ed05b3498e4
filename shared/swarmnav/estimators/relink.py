"""Relinked commit of the per-UAV graph (``relink_s`` > 0; off by default, on in configs/miluv.toml).

Instead of the one-shot commit, each epoch's cooperative links become one Gaussian position factor
on that epoch's pose, and the factors of the last ``relink_s`` seconds are *recomputed* every epoch —
removed from the smoother and added again, linearised at the own smoothed positions and with the
neighbours' latest smoothed positions of those epochs (``NodeState.traj``, broadcast in round 0).
The swarm thereby runs block-Jacobi sweeps on its joint fixed-lag problem: a link fused when both
ends knew little is re-fused once later anchors have refined them, as the centralised smoother
does (weight ``relink_weight``, neighbour covariance × ``relink_cov_scale``). For atvfg the window's
tdoa links also get the double-threshold test on these smoothed residuals, normalised by the
innovation σ (the row's σ and the ends' position covariances at that epoch, ``relink_tdoa_sigma``):
Δl = ``relink_tdoa_delta_l`` (default ``delta_l_fallback_sigmas``), Δh by 2-means over the window's
normalised residuals. Measured in docs/estimators.md "Relinked commit" and docs/miluv.md "Sixth pass".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from . import detection as det
from .rounds import RoundCache, normal_equations, prepare_links, tdoa_residuals


@dataclass
class RelinkRecord:
    """One epoch of the window: its links (cache ``c``, range weights ``w``, tdoa weights ``tw``),
    the round's positions P and covariances C, the own local covariance, and the index of its
    factor in the smoother (None: not in it)."""

    k: int
    n: int
    c: RoundCache
    w: dict
    tw: np.ndarray
    P: np.ndarray
    C: np.ndarray
    Pown: np.ndarray
    fidx: int | None = None


class RelinkedCommit:
    """The relink window of one node and its commit."""

    def __init__(self, t, est, epoch_dt: float, lag_s: float, detect: bool):
        """``t``: the node's EstimatorTuning; ``est``: its typed ``[estimation]`` values
        (``scenario.estimation_values``)."""
        relink_s = float(t.relink_s)
        # window in epochs (0 = off), kept inside the smoother's lag
        self.epochs = max(0, min(int(round(relink_s / epoch_dt)), int(lag_s / epoch_dt) - 2)) if relink_s > 0 else 0
        if relink_s > 0 and self.epochs < 1:
            raise ValueError(f"relink_s = {relink_s} s: no relink window with epochs of {epoch_dt} s and fixed_lag_s "
                             f"{lag_s} s (needs relink_s >= epoch_dt/2 and fixed_lag_s >= 3 epochs)")
        self.weight, self.cov_scale = t.relink_weight, t.relink_cov_scale
        self.detect = detect and t.relink_tdoa_detection
        dl = t.relink_tdoa_delta_l
        self.delta_l = float(est.delta_l_fallback_sigmas if dl is None else dl)
        self.innovation = t.relink_tdoa_sigma == "innovation"
        self.reset()

    def reset(self) -> None:
        self.records: list[RelinkRecord] = []
        self.peer_traj: dict[int, dict] = {}

    def traj_state(self, smoother) -> dict[int, np.ndarray]:
        """Smoothed positions (ENU m) of the epochs in the window, epoch k -> position, for the
        round-0 broadcast (empty when relinking is off)."""
        if self.epochs <= 0 or not self.records:
            return {}
        est = smoother.calculateEstimate()
        return {h.k: est.atPose3(X(h.n)).translation().copy() for h in self.records if est.exists(X(h.n))}

    def _summary(self, node: Any, h: RelinkRecord, p_own: np.ndarray, P: np.ndarray, tdoa_w: np.ndarray):
        """Epoch ``h``'s links as a Gaussian position factor on its pose, linearised at ``p_own``
        with the neighbours at P (covariance × ``relink_cov_scale``), information × ``relink_weight``;
        None without information."""
        L = prepare_links(h.c, P, h.C, h.w, tdoa_w, self.cov_scale, node.azel_weight, node.commit_azel(h.c))
        lam, gv = normal_equations(L, p_own)
        if not np.trace(lam) > 0:
            return None
        lam, gv = lam * self.weight + 1e-8 * np.eye(3), gv * self.weight
        z = p_own + np.linalg.solve(lam, gv)
        return gtsam.GPSFactor(X(h.n), z, gtsam.noiseModel.Gaussian.Information(0.5 * (lam + lam.T)))

    def _jobs(self, node: Any, est, cur: RelinkRecord) -> list:
        """(record, own position, positions, normalised tdoa residuals or None) of the window's epochs
        still in the smoother, at the latest smoothed positions."""
        jobs = []
        for h in self.records:
            if h is not cur and not est.exists(X(h.n)):
                continue
            p_own = node.p if h is cur else est.atPose3(X(h.n)).translation()
            P = h.P.copy()
            for i, u in enumerate(h.c.nodes):
                if u == node.uav:
                    P[i] = p_own
                elif h is not cur and h.k in self.peer_traj.get(u, {}):
                    P[i] = self.peer_traj[u][h.k]
            inn = self.innovation
            jobs.append((h, p_own, P, tdoa_residuals(h.c, P, P[h.c.idx[node.uav]], h.C if inn else None,
                                                     h.Pown if inn else None) if self.detect else None))
        return jobs

    def commit(self, node: Any) -> None:
        """Add this epoch's record, recompute the window's factors and update the node's smoother."""
        smoother = node.smoother
        est = smoother.calculateEstimate()
        cur = RelinkRecord(node.k, node.n, node.cache, dict(node.weights), np.array(node.tdoa_w, float),
                           node.P_round.copy(), node.C_round.copy(), node.P_loc.copy())
        self.records = [h for h in self.records if h.k > node.k - self.epochs] + [cur]
        jobs = self._jobs(node, est, cur)
        dh = None
        if self.detect:
            pool = np.concatenate([r for *_, r in jobs] + [np.zeros(0)])
            if len(pool):
                dh = det.upper_threshold(pool, self.delta_l, node.floor_factor, node.kmeans_backend, node.ceil_factor)
        g = gtsam.NonlinearFactorGraph()
        added = []
        for h, p_own, P, res in jobs:
            tw = h.tw
            if dh is not None and len(res):
                tw = tw * det.classify_and_weigh(res, self.delta_l, dh, node.cap_h1)[1]
            f = self._summary(node, h, p_own, P, tw)
            if f is not None:
                g.add(f)
                added.append(h)
        # indices are updated only once the smoother has taken the removal and the new factors
        remove = [h.fidx for h, *_ in jobs if h.fidx is not None]
        smoother.update(g, gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap(), remove)
        for h, *_ in jobs:
            h.fidx = None
        for h, i in zip(added, smoother.getISAM2Result().getNewFactorsIndices()):
            h.fidx = int(i)
