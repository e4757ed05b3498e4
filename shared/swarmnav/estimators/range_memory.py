"""Range memory (``range_memory_epochs`` W > 0; off by default): a node's clean ranges of the last W
epochs, moved to the current epoch by the two UAVs' displacements, as extra range rows of the
node's *reported* solve — a between-UAV (relative) memory across epochs that the node's 3-D
own-position commit cannot hold (docs/estimators.md "Range memory"). The rounds, what a node
broadcasts and what it commits are unchanged: fed into the rounds the same rows made the swarm's
common-mode error worse (measured: the relative error fell, the common mode rose more).

A range of epoch k−m between this node i and neighbour j is z = |x_i(k−m) + l − x_j(k−m)| + v
(l the tags' offset then). With x_u(k−m) = x_u(k) − D_u (D_u: u's displacement over the m epochs)
it is a range row of epoch k, z = |x_i(k) + l' − x_j(k)| + v with the lever l' = l − D_i + D_j.
The displacements come only from what the node holds or receives: each node's velocity in its
round-0 state (its smoother's, after its own factors), integrated by the trapezoid rule over
consecutive epochs, D̂_u = Σ ½(v_u(k'−1) + v_u(k'))·(t_k' − t_k'−1) (a chain broken by a missed
epoch starts again). The positions' differences (round-0 position minus last epoch's solution)
were measured twice as bad (tuning seed 1001, first 120 s, per axis: 0.096 / 0.094 / 0.065 m vs
0.046 / 0.048 / 0.026 m): each epoch's GNSS update moves p_loc, the velocity is smoother.

Transport error q_m = Var(uᵀ(D̂_i − D_i − D̂_j + D_j)), estimated online from the node's own ranges
(no truth): at any common positions, δ = (z_old − h(l')) − (z_now − h(l_now)) = v_old − v_now +
uᵀ(transport error) (the positions' errors and a link's constant bias cancel), so Var δ =
σ_old² + σ_now² + q_m; q̂_m = max(0, (1.4826·median|δ|)² − mean(σ_old² + σ_now²)) over the last
``STAT_EPOCHS`` epochs (robust to a missed fault). A moved row's noise is σ_old² + q̂_m.

Which rows: those whose link was H2 (weight 1) in the final round of their epoch and is H2 in the
current round, with |δ| ≤ 3·√(σ_old² + σ_now² + q̂_m). Weight: 1 − ``commit_weight`` — a share
``commit_weight`` of every range's information already went into the smoother (the commit) and
reaches this epoch through the prior; the moved row carries the rest, so an old range counts once.
Rows to one neighbour share its position error: the sandwich groups them (``Links.rng_group``).
With report = "round" and no relinked commit only.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace

import numpy as np

from ..models.uwb_range import ranges
from .rounds import Links, gauss_newton, normal_equations, sandwich_cov

STAT_EPOCHS = 30  # epochs of δ samples per lag for q̂_m
MIN_SAMPLES = 50  # a lag's rows are used once this many δ samples are pooled
GATE_SIGMAS = 3.0


class RangeMemory:
    """One node's range memory: the last ``epochs`` epochs' clean range rows and, per lag, the δ
    samples that give its transport variance."""

    def __init__(self, epochs: int, weight: float):
        self.epochs, self.weight = int(epochs), float(weight)
        self.reset()

    def reset(self) -> None:
        self.hist: deque = deque(maxlen=self.epochs)  # (k, owners, levers, σ², z, {node: (chain id, S)})
        self.stats = [deque(maxlen=STAT_EPOCHS) for _ in range(self.epochs + 1)]  # per lag: (δ, σ²+σ²) arrays
        self.k = None
        self.rows = None  # this epoch's moved rows: (owners, levers, σ², z)
        self.chain: dict[int, tuple] = {}  # node id -> (k, t, v, S, chain id): S = Σ trapezoid v·dt (m), 3 floats
        self._cid = 0

    def q_hat(self, m: int) -> float | None:
        """Transport variance of lag m (m²), None while fewer than MIN_SAMPLES δ are pooled."""
        st = self.stats[m]
        if not st:
            return None
        d = np.concatenate([x[0] for x in st])
        if len(d) < MIN_SAMPLES:
            return None
        s2 = np.concatenate([x[1] for x in st])
        return max(0.0, float((1.4826 * np.median(np.abs(d))) ** 2 - np.mean(s2)))

    def _advance(self, u: int, k: int, t: float, v: np.ndarray) -> None:
        """Node u's dead-reckoned displacement chain to epoch k (its velocity v at time t). In
        Python floats, component by component (the same operations as numpy's elementwise ones:
        ~3x cheaper for one 3-vector; it runs for every neighbourhood node every epoch)."""
        prev = self.chain.get(u)
        if prev is not None and prev[0] == k:
            return
        # a copy in Python floats (tolist: the same values, ~7x cheaper than float() per numpy scalar)
        vx, vy, vz = v = tuple(v.tolist()) if type(v) is np.ndarray and v.ndim == 1 else tuple(map(float, v))
        if prev is not None and prev[0] == k - 1 and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(vz):
            dt, (px, py, pz), (sx, sy, sz) = t - prev[1], prev[2], prev[3]
            S = (sx + 0.5 * (px + vx) * dt, sy + 0.5 * (py + vy) * dt, sz + 0.5 * (pz + vz) * dt)
            self.chain[u] = (k, t, v, S, prev[4])
        else:
            self._cid += 1
            self.chain[u] = (k, t, v, (0.0, 0.0, 0.0), self._cid)

    def begin(self, node, peers: dict, own) -> None:
        """Move the remembered rows to the node's epoch (first round: ``peers`` are round-0 states,
        ``own`` the node's round-0 state); update the displacement chains and the δ statistics."""
        self.k, self.rows = node.k, None
        self._advance(node.uav, node.k, own.t, own.vel)
        c = node.cache
        # only the neighbourhood's chains (the whole swarm's would be O(N) per node): a row is used
        # only while its neighbour is ranged now, so in the neighbourhood; with epochs > 1 one that
        # left the neighbourhood in between starts a new chain and its older rows are not used
        for o in c.nodes:
            s = peers.get(o)
            if s is not None and s.r == 0:
                self._advance(int(o), node.k, s.t, s.vel)
        if c.rng_z is None or not len(c.rng_z):
            return
        r0_own = own.pos
        now = self._residual_now(c, peers, r0_own)
        me, out = self.chain[node.uav], []
        for k_old, owners, levers, sig2, z, S_old in self.hist:
            lag = node.k - k_old
            if not 1 <= lag <= self.epochs or S_old.get(node.uav, (None,))[0] != me[4]:
                continue
            sel = [n for n, o in enumerate(owners.tolist())
                   if o in now and S_old.get(o, (None,))[0] == self.chain[o][4]]
            if not sel:
                continue
            o_s = owners[sel]
            o_list = o_s.tolist()
            d_own = np.subtract(me[3], S_old[node.uav][1])
            d_nb = np.array([self.chain[o][3] for o in o_list]) - np.array([S_old[o][1] for o in o_list])
            lev = levers[sel] - d_own + d_nb
            rr, _ = ranges(r0_own + lev - np.array([peers[o].pos for o in o_list]))
            delta = (z[sel] - rr) - np.array([now[o][0] for o in o_list])
            s2sum = sig2[sel] + np.array([now[o][1] for o in o_list])
            q = self.q_hat(lag)  # from earlier epochs only
            self.stats[lag].append((delta, s2sum))
            if q is None:
                continue
            ok = np.abs(delta) <= GATE_SIGMAS * np.sqrt(s2sum + q)
            out.append((o_s[ok], lev[ok], sig2[sel][ok] + q, z[sel][ok]))
        if out:
            self.rows = tuple(np.concatenate(x) for x in zip(*out))

    @staticmethod
    def _residual_now(c, peers: dict, p_own: np.ndarray) -> dict[int, tuple[float, float]]:
        """Per ranged neighbour with a round-0 state: the mean residual (m) of this epoch's range
        rows to it at the round-0 positions and the rows' mean σ² (m²)."""
        live = [o for o in c.nb if peers.get(o) is not None and peers[o].r == 0]
        if not live:
            return {}
        slot = {o: i for i, o in enumerate(live)}
        gi = np.array([slot.get(o, -1) for o in c.rng_owner.tolist()], int)
        m = gi >= 0
        gi = gi[m]
        pos = np.array([peers[o].pos for o in live])
        rr, _ = ranges(p_own + c.rng_lever[m] - pos[gi])
        cnt = np.bincount(gi, minlength=len(live))
        res = np.bincount(gi, c.rng_z[m] - rr, minlength=len(live))
        sig2 = np.bincount(gi, c.rng_sig2[m], minlength=len(live))
        res, sig2, cnt = res.tolist(), sig2.tolist(), cnt.tolist()  # Python floats: the same quotients
        return {o: (res[i] / cnt[i], sig2[i] / cnt[i]) for i, o in enumerate(live) if cnt[i]}

    def extend(self, node, L: Links, infl) -> Links:
        """A copy of ``L`` (the round's links, unchanged) with the moved rows of neighbours whose link
        is H2 now appended to its range rows, each neighbour's covariance × ``infl`` (a number or per
        node id), and every range row's neighbour index in ``rng_group``."""
        c = node.cache
        if self.rows is None or L.rng is None or self.k != node.k:
            return L
        owners, lev, sig2, z = self.rows
        use = np.array([node.weights.get(o, 0.0) >= 1.0 and o in c.idx for o in owners.tolist()])
        if not use.any():
            return L
        owners, lev, sig2, z = owners[use].tolist(), lev[use], sig2[use], z[use]
        n = np.array([c.idx[o] for o in owners], int)
        f = np.array([infl(o) for o in owners]) if callable(infl) else np.full(len(n), float(infl))
        w_cur = np.array([node.weights[o] for o in c.rng_owner.tolist()])
        g_cur = c.rng_node[w_cur > 0]
        pj, Pj, w, lv, s2, zz = L.rng
        rng = (np.concatenate([pj, node.P_round[n]]), np.concatenate([Pj, node.C_round[n] * f[:, None, None]]),
               np.concatenate([w, np.full(len(n), self.weight)]), np.concatenate([lv, lev]),
               np.concatenate([s2, sig2]), np.concatenate([zz, z]))
        return replace(L, rng=rng, rng_group=np.concatenate([g_cur, n]))

    def report(self, node) -> tuple[np.ndarray, np.ndarray]:
        """The node's reported position and its covariance: its last round's solve (prior, the
        epoch's links with the rounds' weights, neighbours at their last round positions) with the
        moved rows added, Gauss-Newton from the round solution, and the sandwich H⁻¹MH⁻¹ of it
        (neighbours' covariances × 1 in the error model, rows of a neighbour sharing its error).
        The rounds, the broadcasts and the commit do not see the moved rows."""
        infl = node._infl if node.round_infl is None else node.round_infl
        Lw = self.extend(node, node.L, infl)  # node.L: the last round's links, node._links(node.round_infl)
        if Lw.rng_group is None:  # no moved row is usable now: the round solution as it is
            H, _, M = normal_equations(node.L, node.p, node._info, node.p_loc, L_true=node._links(1.0))
            return node.p.copy(), sandwich_cov(H, M)
        p = gauss_newton(node.p, lambda q: normal_equations(Lw, q, node._info, node.p_loc), node.gn_iters)
        H, _, M = normal_equations(Lw, p, node._info, node.p_loc, L_true=self.extend(node, node._links(1.0), 1.0))
        return p, sandwich_cov(H, M)

    def push(self, node) -> None:
        """Remember the epoch's rows whose link was H2 (weight 1) in its final round, with the
        displacement chains of the node and its neighbours at this epoch."""
        c = node.cache
        if c is None or c.rng_z is None or not len(c.rng_z) or not node._links_ready:
            return
        keep = np.array([node.weights.get(int(o), 0.0) >= 1.0 for o in c.rng_owner])
        if not keep.any():
            return
        owners = c.rng_owner[keep]
        S = {u: (self.chain[u][4], self.chain[u][3]) for u in [node.uav] + [int(o) for o in np.unique(owners)]
             if u in self.chain and self.chain[u][0] == node.k}
        self.hist.append((node.k, owners.copy(), c.rng_lever[keep].copy(), c.rng_sig2[keep].copy(),
                          c.rng_z[keep].copy(), S))
