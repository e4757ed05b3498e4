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

Units and frames: positions ENU (m), angles rad. numpy and the C kernels of _kernels.c (a
Gauss–Newton step, its symbolic phase once per snapshot, the double-threshold test): no I/O, no gtsam.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from . import _kernels  # C: built by `make setup` (setup.py)
from . import detection as det


def azel_observations(nodes: list[int], states: dict, own_state) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every az/el observation between two nodes of ``nodes`` (sorted ids) that round 0 carries:
    (observer index, target index, z (M, 2) rad, σ² (M,) rad²), by observer in ``nodes`` order,
    then by target. ``states``: the peers' round-0 states; ``own_state``: the node's own round-0
    state (its own observations)."""
    ids = np.asarray(nodes, np.int64)
    own = own_state.uav
    present = [(i, (own_state if u == own else states.get(u))) for i, u in enumerate(nodes)]
    rows = [(i, s.bearing_rows) for i, s in present if s is not None and s.bearings]
    if not rows:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0)
    targets = np.concatenate([r[1][0] for r in rows])
    vals = np.concatenate([r[1][1] for r in rows])
    obs = np.repeat(np.array([r[0] for r in rows], np.int64), [len(r[1][0]) for r in rows])
    j = np.minimum(np.searchsorted(ids, targets), len(ids) - 1)
    keep = (ids[j] == targets) & (targets != ids[obs])  # a target in the neighbourhood, not itself
    v = vals[keep]
    return obs[keep], j[keep], v[:, :2].copy(), v[:, 2] * v[:, 2]


def solve(prior_mean: np.ndarray, prior_info: np.ndarray, ia: np.ndarray, ib: np.ndarray, d: np.ndarray,
          w: np.ndarray, sig2: float, azel: tuple, x0: np.ndarray, iterations: int = 5, tol_m: float = 1e-3,
          azel_w: np.ndarray | None = None, plan: Any = None) -> np.ndarray:
    """Gauss–Newton MAP of n positions (n, 3): priors N(prior_mean[i], prior_info[i]⁻¹), ranges
    d between ia and ib with weights w and variance sig2 (m²), az/el observations ``azel`` =
    (observer, target, z, σ²) (:func:`azel_observations`) with weights ``azel_w`` (None: 1); from x0,
    until a step is below ``tol_m`` (Gauss–Newton converges quadratically here: after a 1 mm step
    the solution is within ~10 µm of converged, measured on paper). A non-finite step keeps the last
    finite solution. Each step is one C kernel call (``_kernels``: the models of uwb_range and
    bearing, one loop over the factors): above ``_SMALL_SYSTEM`` unknowns ``joint_step``, a
    block-sparse Cholesky that never forms the dense H (a node is coupled to its ~15 ranged
    neighbours of ~50), else ``joint_system``'s dense H solved by :func:`_spd_solve`. H is
    symmetric positive definite (every node has a prior); LU on the dense H where Cholesky fails
    (a degenerate set). ``plan``: :func:`plan` of these factors (the symbolic phase of
    ``joint_step``, shared by a snapshot's solves), else each step does its own."""
    n = len(prior_mean)
    x = np.array(x0, float, order="C")
    obs, tgt, z, s2 = azel
    args = (np.ascontiguousarray(prior_mean, float), np.ascontiguousarray(prior_info, float),
            np.ascontiguousarray(ia, np.int64), np.ascontiguousarray(ib, np.int64),
            np.ascontiguousarray(d, float), np.ascontiguousarray(np.asarray(w, float) / sig2),
            np.ascontiguousarray(obs, np.int64), np.ascontiguousarray(tgt, np.int64),
            np.ascontiguousarray(z, float).reshape(-1, 2),
            np.ascontiguousarray((1.0 if azel_w is None else np.asarray(azel_w, float)) / np.asarray(s2, float)))
    dx, sparse, planned = np.empty((n, 3)), 3 * n > _SMALL_SYSTEM, () if plan is None else (plan,)
    for _ in range(iterations):
        # block-sparse Cholesky above _SMALL_SYSTEM unknowns (~1.5-2x faster at ~50 nodes; below, the dense
        # solve in C is as fast); refused (H not numerically positive definite, a non-finite step, more
        # than 4096 nodes): the dense path (Cholesky, LU where that fails), for the rest of this solve
        if not (sparse and _kernels.joint_step(x, *args, dx, *planned)):
            sparse, dx = False, _dense_step(x, args)
        if not np.all(np.isfinite(dx)):
            break
        x += dx
        if np.abs(dx).max() < tol_m:
            break
    return x


def plan(n: int, ia: np.ndarray, ib: np.ndarray, azel: tuple) -> Any:
    """The symbolic phase of :func:`solve`'s block-sparse steps (elimination order and fill: they
    depend on which nodes the ranges ``ia``-``ib`` and the az/el rows ``azel`` couple, not on x or
    the weights) for n nodes, computed once for every step of a snapshot (~10 steps; 18% of a step,
    measured on configs/scale.toml at 1,000 UAVs); None where :func:`solve` takes the dense path."""
    if 3 * n <= _SMALL_SYSTEM:
        return None
    return _kernels.joint_plan(n, np.ascontiguousarray(ia, np.int64), np.ascontiguousarray(ib, np.int64),
                               np.ascontiguousarray(azel[0], np.int64), np.ascontiguousarray(azel[1], np.int64))


def _dense_step(x: np.ndarray, args: tuple) -> np.ndarray:
    """The Gauss–Newton step from the dense H (3n x 3n): where the block-sparse Cholesky refuses H."""
    n = len(x)
    H, g = np.empty((3 * n, 3 * n)), np.empty(3 * n)
    _kernels.joint_system(x, *args, H, g)
    return _spd_solve(H, g).reshape(n, 3)


_SMALL_SYSTEM = 60  # unknowns up to which the whole Cholesky solve in C beats LAPACK through numpy


def _spd_solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """H⁻¹g for a symmetric positive definite H by Cholesky (~2× cheaper than LU here): all in C
    (``_kernels.spd_solve``) up to ``_SMALL_SYSTEM`` unknowns, where call overhead dominates; above,
    the factorisation in LAPACK through numpy and the two triangular solves in C (not scipy.linalg:
    its import costs every UAV process 17 MB of RSS). LU if H is not numerically positive definite;
    NaNs if singular."""
    x = np.empty_like(g)
    if len(g) <= _SMALL_SYSTEM:
        if _kernels.spd_solve(H, g, x):
            return x
    else:
        try:
            _kernels.cho_solve(np.linalg.cholesky(H), g, x)
            return x
        except np.linalg.LinAlgError:
            pass
    try:
        return np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return np.full_like(g, np.nan)


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
    structure = plan(len(x), ia, ib, azel)  # every pass couples the same nodes
    for _ in range(passes + 1):
        w = weigh(x)
        aw = None if pidx is None else np.where(pidx >= 0, w[np.maximum(pidx, 0)], 1.0)
        x = solve(prior_mean, prior_info, ia, ib, d, w, sig2, azel, x, azel_w=aw, plan=structure)
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
    azel = azel_observations(c.nodes, peers, node._last_state)  # round 1: our state is round 0's
    pairs = c.pairs

    def weigh(x: np.ndarray) -> np.ndarray:
        if not (node.detect and len(pairs.d)):
            return np.ones(len(pairs.d))
        return det.detect(pairs.residuals(x), node.delta_l, node.window, node.floor_factor, node.kmeans_backend,
                          node.ceil_factor, node.cap_h1)[2]

    # without detection every pass has the same weights (1): one solve is the whole snapshot
    return snapshot(mean, info, pairs.ia, pairs.ib, pairs.d, node.uwb_sigma ** 2, azel, weigh,
                    node.joint_passes if node.detect else 0, azel_follows_range=node.azel_weight == "range")
