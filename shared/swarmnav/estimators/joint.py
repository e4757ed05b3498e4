"""The neighbourhood's joint snapshot: every position of a node's neighbourhood solved at once from
what round 0 carries (``[estimation.graph] round_solver = "joint"``).

In round 0 every node broadcasts its epoch prior (p_loc, P_loc: its smoother after its own sensors,
before any cooperative information of the epoch), its ranges and its az/el observations. A node then
holds the whole factor graph of the epoch's snapshot over its neighbourhood: a Gaussian prior per
UAV, a range factor per ranged pair (the residual matrix's pairs, σ the ranging σ, weighted by the
double-threshold test) and an eq. 27 az/el factor per observation. Its MAP is what the block-Jacobi
rounds (each node solving its own position against its neighbours' current ones, neighbour
covariance × 0 in the link noise) converge to; solving it directly takes one round instead of ~9
(and no covariance inflation to keep the iteration stable). The double-threshold test is iterated
with it (IRLS): weights from the residuals at the priors, solve, weights at the solution, solve.

Units and frames: positions ENU (m), angles rad. Pure numpy: no I/O, no gtsam.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from . import detection as det
from ..models.bearing import azel_jacobians, azel_residuals


def azel_observations(nodes: list[int], states: dict, own_uav: int, own_bearings: dict
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every az/el observation between two nodes of ``nodes`` that round 0 carries: (observer index,
    target index, z (M, 2) rad, σ² (M,) rad²). ``states``: the peers' round-0 states; the node's own
    observations are ``own_bearings`` (target -> (az, el, σ))."""
    idx = {u: i for i, u in enumerate(nodes)}
    obs: list[int] = []
    tgt: list[int] = []
    vals: list[float] = []  # az, el, σ per observation
    for u in nodes:
        b = own_bearings if u == own_uav else getattr(states.get(u), "bearings", None) or {}
        i = idx[u]
        for t in sorted(b):
            j = idx.get(t)
            if j is not None and t != u:
                obs.append(i)
                tgt.append(j)
                vals += b[t]
    v = np.array(vals, float).reshape(-1, 3)
    return np.array(obs, int), np.array(tgt, int), v[:, :2].copy(), v[:, 2] * v[:, 2]


def _lanes(idx: np.ndarray, width: int) -> np.ndarray:
    """Flat indices of ``width`` consecutive entries per index: idx·width + 0 … width − 1."""
    return (idx[:, None] * width + np.arange(width)).ravel()


class Scatter:
    """The normal equations' (3n × 3n) H and g of n positions from factors between two ends, the
    factors given as index pairs (``ends``: one (ia, ib) per kind, e.g. ranges, then (target,
    observer) of az/el). A factor with block B and gradient v adds B to blocks (a, a) and (b, b),
    −B to (a, b) and (b, a), v to g_a and −v to g_b. Summed per ordered pair first (one
    ``bincount`` over the q ordered pairs that have a factor either way, sorted by (a, b)): with
    S(a, b) = P(a, b) + P(b, a), H(a, b) = −S(a, b) and H(a, a) = Σ_b S(a, b) in b order. Built
    once per snapshot, used by every Gauss–Newton iteration of its solves."""

    def __init__(self, n: int, ends: list[tuple[np.ndarray, np.ndarray]]):
        self.n = n
        self.first = np.concatenate([np.asarray(a, int) for a, _ in ends]) if ends else np.zeros(0, int)
        self.second = np.concatenate([np.asarray(b, int) for _, b in ends]) if ends else np.zeros(0, int)
        code, reverse_code = self.first * n + self.second, self.second * n + self.first
        has_factor = np.zeros(n * n, bool)
        has_factor[code] = has_factor[reverse_code] = True
        slots = np.flatnonzero(has_factor)  # sorted by (a, b)
        slot_of = np.zeros(n * n, np.intp)
        slot_of[slots] = np.arange(len(slots))
        sa, sb = slots // n, slots % n
        self.q = len(slots)
        factor_slot = slot_of[code]
        self.block_idx = _lanes(factor_slot, 9)
        self.grad_idx = _lanes(factor_slot, 3)
        self.reverse = slot_of[sb * n + sa]  # slot of (b, a) per slot (a, b)
        self.diag_idx = _lanes(sa, 9)
        self.row_idx, self.col_idx = _lanes(sa, 3), _lanes(sb, 3)
        # the flat (3n × 3n) H gathered from [−S (q, 9), diagonal blocks (n, 9), 0]: built block-major
        # (a, b, i, j), then laid out as rows 3a + i, columns 3b + j
        gather = np.full((n * n, 9), 9 * (self.q + n), np.intp)
        gather[slots] = np.arange(9 * self.q).reshape(-1, 9)
        gather[np.arange(n) * (n + 1)] = 9 * self.q + np.arange(9 * n).reshape(n, 9)
        self.gather = gather.reshape(n, n, 3, 3).transpose(0, 2, 1, 3).ravel()
        self._zero = np.zeros(1)

    def assemble(self, B: list[np.ndarray], gv: list[np.ndarray], prior_info: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """H (3n, 3n) (+ the priors' block-diagonal information (n, 3, 3)) and g (3n,) from each
        kind's symmetric blocks B (m, 3, 3) and gradients gv (m, 3), in the order of ``ends``."""
        n, q = self.n, self.q
        P = np.bincount(self.block_idx, np.concatenate([b.ravel() for b in B]), minlength=q * 9).reshape(q, 9)
        S = P + P.take(self.reverse, axis=0)
        diag = np.bincount(self.diag_idx, S.ravel(), minlength=n * 9)
        if prior_info is not None:
            diag = prior_info.ravel() + diag
        H = np.concatenate((-S.ravel(), diag, self._zero)).take(self.gather)
        G = np.bincount(self.grad_idx, np.concatenate([v.ravel() for v in gv]), minlength=q * 3)
        g = np.bincount(self.row_idx, G, minlength=3 * n) - np.bincount(self.col_idx, G, minlength=3 * n)
        return H.reshape(3 * n, 3 * n), g


def solve(prior_mean: np.ndarray, prior_info: np.ndarray, ia: np.ndarray, ib: np.ndarray, d: np.ndarray,
          w: np.ndarray, sig2: float, azel: tuple, x0: np.ndarray, iterations: int = 5, tol_m: float = 1e-3,
          azel_w: np.ndarray | None = None, scatter: Scatter | None = None) -> np.ndarray:
    """Gauss–Newton MAP of n positions (n, 3): priors N(prior_mean[i], prior_info[i]⁻¹), ranges
    d between ia and ib with weights w and variance sig2 (m²), az/el observations ``azel`` =
    (observer, target, z, σ²) (:func:`azel_observations`) with weights ``azel_w`` (None: 1); from x0,
    until a step is below ``tol_m`` (Gauss–Newton converges quadratically here: after a 1 mm step
    the solution is within ~10 µm of converged, measured on paper). A non-finite step keeps the last
    finite solution. ``scatter``: :class:`Scatter` of (ia, ib) and (target, observer), if the caller
    solves the same structure several times (a weight of 0 drops a factor)."""
    n, m = len(prior_mean), len(ia)
    x = x0.copy()
    obs, tgt, z, s2 = azel
    a = (np.asarray(w, float) / sig2)[:, None]
    inv_s2 = (1.0 / s2 if azel_w is None else np.asarray(azel_w, float) / s2)[:, None, None]
    sc = scatter or Scatter(n, [(ia, ib), (tgt, obs)])
    for _ in range(iterations):
        g0 = (prior_info @ (prior_mean - x)[:, :, None]).ravel()
        diff = x.take(sc.first, axis=0) - x.take(sc.second, axis=0)  # ranges' p_a − p_b, then az/el's p_tgt − p_obs
        dv = diff[:m]
        r = np.sqrt((dv * dv).sum(axis=1))
        u = dv / np.maximum(r, 1e-9)[:, None]
        ua = u * a
        az, el, J = azel_jacobians(diff[m:])  # J = ∂(az, el)/∂p_tgt = −∂/∂p_obs
        Jw = J * inv_s2
        JwT = Jw.transpose(0, 2, 1)
        H, g = sc.assemble([u[:, :, None] * ua[:, None, :], J.transpose(0, 2, 1) @ Jw],
                           [ua * (d - r)[:, None], (JwT @ azel_residuals(z, az, el)[:, :, None])[:, :, 0]], prior_info)
        dx = np.linalg.solve(H, g + g0).reshape(n, 3)
        if not np.all(np.isfinite(dx)):
            break
        x = x + dx
        if np.abs(dx).max() < tol_m:
            break
    return x


def pair_index(ia: np.ndarray, ib: np.ndarray, obs: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """For each az/el observation, the index of the ranged pair (ia < ib) between its two ends (-1: none)."""
    n = int(max(ia.max(initial=-1), ib.max(initial=-1), obs.max(initial=-1), tgt.max(initial=-1))) + 1
    where = np.full(n * n, -1)
    where[ia * n + ib] = np.arange(len(ia))
    return where[np.minimum(obs, tgt) * n + np.maximum(obs, tgt)]


def snapshot(prior_mean: np.ndarray, prior_info: np.ndarray, ia: np.ndarray, ib: np.ndarray, d: np.ndarray,
             sig2: float, azel: tuple, weigh: Callable[[np.ndarray], np.ndarray], passes: int = 2,
             azel_follows_range: bool = False) -> np.ndarray:
    """The neighbourhood's positions (n, 3): ``passes`` + 1 solves, the range weights from
    ``weigh(positions)`` (the double-threshold test on the residual matrix at those positions)
    before each: first at the priors, then at the last solution. ``azel_follows_range``: an az/el
    observation takes the weight of the range between its ends (the paper: an H0 link loses every
    factor); else weight 1."""
    x = prior_mean.copy()
    pidx = pair_index(ia, ib, azel[0], azel[1]) if azel_follows_range else None
    sc = Scatter(len(x), [(ia, ib), (azel[1], azel[0])])
    for _ in range(passes + 1):
        w = weigh(x)
        aw = None if pidx is None else np.where(pidx >= 0, w[np.maximum(pidx, 0)], 1.0)
        x = solve(prior_mean, prior_info, ia, ib, d, w, sig2, azel, x, azel_w=aw, scatter=sc)
    return x


def neighbourhood_snapshot(node: Any, c, peers: dict) -> np.ndarray:
    """Round 1 of ``round_solver = "joint"`` on a per-UAV graph estimator (graph.py ``node``, its
    round cache ``c`` and the peers' round-0 states): the joint snapshot of ``c.nodes`` (positions
    in that order). Priors: each peer's broadcast epoch prior, the node's own (p_loc, P_loc); range
    pairs: the residual matrix's, weighted by the node's double-threshold test (1 without detection);
    az/el: every observation round 0 carries between two nodes of the neighbourhood."""
    own = c.idx[node.uav]
    mean = node.P_round.copy()
    mean[own] = node.p_loc
    info = np.linalg.inv(node.C_round + np.eye(3)[None] * 1e-12)
    info[own] = node._info
    azel = azel_observations(c.nodes, peers, node.uav, node._last_state.bearings)  # round 1: ours of round 0
    pairs = c.pairs

    def weigh(x: np.ndarray) -> np.ndarray:
        if not (node.detect and len(pairs.d)):
            return np.ones(len(pairs.d))
        return det.detect(pairs.residuals(x), node.delta_l, node.window, node.floor_factor, node.kmeans_backend,
                          node.ceil_factor, node.cap_h1)[2]

    # without detection every pass has the same weights (1): one solve is the whole snapshot
    return snapshot(mean, info, pairs.ia, pairs.ib, pairs.d, node.uwb_sigma ** 2, azel, weigh,
                    node.joint_passes if node.detect else 0, azel_follows_range=node.azel_weight == "range")
