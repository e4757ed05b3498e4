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
    obs, tgt, z, s2 = [], [], [], []
    for u in nodes:
        b = own_bearings if u == own_uav else getattr(states.get(u), "bearings", None) or {}
        for t, (az, el, sg) in sorted(b.items()):
            if t in idx and t != u:
                obs.append(idx[u])
                tgt.append(idx[t])
                z.append((az, el))
                s2.append(sg * sg)
    return (np.array(obs, int), np.array(tgt, int), np.array(z, float).reshape(-1, 2), np.array(s2, float))


def solve(prior_mean: np.ndarray, prior_info: np.ndarray, ia: np.ndarray, ib: np.ndarray, d: np.ndarray,
          w: np.ndarray, sig2: float, azel: tuple, x0: np.ndarray, iterations: int = 5, tol_m: float = 1e-3,
          azel_w: np.ndarray | None = None) -> np.ndarray:
    """Gauss–Newton MAP of n positions (n, 3): priors N(prior_mean[i], prior_info[i]⁻¹), ranges
    d between ia and ib with weights w and variance sig2 (m²), az/el observations ``azel`` =
    (observer, target, z, σ²) (:func:`azel_observations`) with weights ``azel_w`` (None: 1); from x0,
    until a step is below ``tol_m`` (Gauss–Newton converges quadratically here: after a 1 mm step
    the solution is within ~10 µm of converged, measured on paper). A non-finite step keeps the last
    finite solution."""
    n = len(prior_mean)
    x = x0.copy()
    obs, tgt, z, s2 = azel
    if azel_w is not None:
        ka = azel_w > 0
        obs, tgt, z, s2 = obs[ka], tgt[ka], z[ka], s2[ka] / azel_w[ka]
    keep = w > 0
    ia, ib, d, a = ia[keep], ib[keep], d[keep], w[keep] / sig2
    nodes = np.arange(n)
    # one-hot incidence of each factor's two ends: the diagonal blocks and g are sums over factors,
    # taken as matmuls; an off-diagonal block (i, j) comes from factors between i and j only, and
    # within one kind each ordered pair occurs once, so fancy-indexed += adds them exactly
    ea, eb = np.eye(n)[ia].T, np.eye(n)[ib].T  # (n, m)
    eo, et = np.eye(n)[obs].T, np.eye(n)[tgt].T
    for _ in range(iterations):
        Hb = np.zeros((n, n, 3, 3))
        Hb[nodes, nodes] = prior_info
        g = np.einsum("nij,nj->ni", prior_info, prior_mean - x)
        if len(d):
            dv = x[ia] - x[ib]
            r = np.sqrt(np.einsum("ij,ij->i", dv, dv))
            u = dv / np.maximum(r, 1e-9)[:, None]
            B = (u[:, :, None] * u[:, None, :]) * a[:, None, None]
            gb = u * (a * (d - r))[:, None]
            Hb[nodes, nodes] += ((ea + eb) @ B.reshape(-1, 9)).reshape(n, 3, 3)
            Hb[ia, ib] -= B
            Hb[ib, ia] -= B
            g += ea @ gb - eb @ gb
        if len(obs):
            az, el, J = azel_jacobians(x[tgt] - x[obs])  # J = ∂(az, el)/∂p_tgt = −∂/∂p_obs
            res = azel_residuals(z, az, el)
            B = np.einsum("mki,mkj->mij", J, J) / s2[:, None, None]
            gj = np.einsum("mki,mk->mi", J, res) / s2[:, None]
            Hb[nodes, nodes] += ((eo + et) @ B.reshape(-1, 9)).reshape(n, 3, 3)
            Hb[tgt, obs] -= B
            Hb[obs, tgt] -= B
            g += et @ gj - eo @ gj
        dx = np.linalg.solve(Hb.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n), g.ravel()).reshape(n, 3)
        if not np.all(np.isfinite(dx)):
            break
        x = x + dx
        if np.abs(dx).max() < tol_m:
            break
    return x


def pair_index(ia: np.ndarray, ib: np.ndarray, obs: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """For each az/el observation, the index of the ranged pair between its two ends (-1: none)."""
    where = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(ia.tolist(), ib.tolist()))}
    return np.array([where.get((min(o, t), max(o, t)), -1) for o, t in zip(obs.tolist(), tgt.tolist())], int)


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
    for _ in range(passes + 1):
        w = weigh(x)
        aw = None if pidx is None else np.where(pidx >= 0, w[np.maximum(pidx, 0)], 1.0)
        x = solve(prior_mean, prior_info, ia, ib, d, w, sig2, azel, x, azel_w=aw)
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

    return snapshot(mean, info, pairs.ia, pairs.ib, pairs.d, node.uwb_sigma ** 2, azel, weigh,
                    node.joint_passes, azel_follows_range=node.azel_weight == "range")
