"""``fkf`` — federated Kalman filter per UAV (baseline of the paper's §3.2; docs/baselines.md).

Error state (15, this order, all first order about the nominal INS solution)::

    x = [δθ (0:3), δv (3:6), δp (6:9), δb_a (9:12), δb_g (12:15)]

- δθ: attitude error in the **body (FLU)** frame, right perturbation: R = R̂ · Exp(δθ)
  (gtsam's Pose3/Rot3 tangent convention, so the preintegration Jacobians apply unchanged);
- δv, δp: velocity / position error in **ENU** (v = v̂ + δv, p = p̂ + δp);
- δb_a, δb_g: accelerometer / gyro bias error, body FLU (b = b̂ + δb).

Propagation (epoch rate, cheap): the nominal state is propagated with gtsam combined
preintegration of the epoch's IMU samples (``imu.preintegrate``; Earth rate and gravity as the
dataset's Earth model). The error covariance is propagated with the transition matrix taken from
the linearised ``CombinedImuFactor`` between the previous and the predicted state: with the
whitened factor Jacobians A_i (previous state) and A_j (predicted state), mapped to the error state
above, Φ = −A_j⁻¹A_i and Q = A_j⁻¹A_j⁻ᵀ (the preintegrated measurement covariance, incl. bias random
walk, carried to the state). One 100-sample preintegration + one linearisation per epoch.

Sub-filters (PSINS ``fkfinit``/``fkfupdate`` structure, common reference INS = the nominal state):

- master (no measurement) with information-sharing factor β_m;
- GNSS sub-filter (GNSS position + velocity; altitude when present) with β_g;
- UWB sub-filter (ranges to neighbour UAVs using their broadcast position and covariance, and to
  fixed anchors) with β_u.  Σβ = 1.

Each epoch every sub-filter starts from the fused estimate with P_i = P/β_i (``fkfinit`` / the
reset of ``fkfupdate``), updates with its own measurements, and the master fuses by information
sum: P_f⁻¹ = Σ P_i⁻¹, x_f = P_f Σ P_i⁻¹ x_i; the fused result is injected into the nominal state and
the error state reset to zero. With the reset every epoch and linear measurements this fusion
equals the centralised EKF update; what the federation adds is fault *isolation*: a sub-filter
whose innovations fail the chi-square test is left out of the fusion and the β's are renormalised
over the healthy sub-filters ("isolation and system reconstruction", paper §3.2).

Chi-square isolation (setting ``fkf_isolation``):

- ``"measurement"`` (default): each range is first tested alone (NIS with the sub-filter's own
  prior P/β_u against χ²₁ at ``fkf_chi2_p``) and a failing range is dropped (the link is isolated
  for this epoch); the remaining UWB sub-filter is then tested as a whole (χ²_m) and isolated when
  it fails. GNSS: whole-sub-filter test.
- ``"subfilter"``: only the whole-sub-filter test — one bad link isolates the whole UWB
  sub-filter for the epoch (closest to the paper's description of FKF).

Lock-out guard for fixed-anchor ranges (``fkf_anchor_max_reject`` N, default 3; 0 = off): when N
of the last 2N anchor ranges failed the χ²₁ test on their own, anchor ranges are fused untested
(both tests) until the record recovers. Without it a filter that drifted (MILUV: sparse anchor
ranges, no GNSS) rejected every later anchor range and diverged for good (253 m); anchors are the
absolute reference there, as GNSS is outdoors (whose isolation is off by default for the same
reason). No effect where there are no anchors (the simulated scenarios).

Rounds: round 0 (``begin_epoch``) = predicted state + GNSS sub-filter fused, and this node's
ranges. Round 1 takes the neighbours' round-0 states (GNSS-updated, *before* they used this epoch's
ranges, so the shared range is not counted twice); later rounds re-linearise the ranges about this
node's own updated estimate (iterated EKF) with the same neighbour states. Neighbour position
uncertainty enters as extra range noise uᵀP_j u (cross-covariance with the neighbour ignored — the
classic decentralised FKF simplification; consistency measured with NEES in the tests/docs).
"""

from __future__ import annotations

from collections import deque

import gtsam
import numpy as np
from scipy.stats import chi2

from ..dataset import DatasetMeta, EpochInput
from ..geometry import skew
from .base import InitialState, LinkClass, LinkInfo, NodeEstimate, NodeEstimator, NodeState
from .imu import preintegrate, preintegration_params
from .settings import tuning

ATT, VEL, POS, BA, BG = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


def error_state_map(R: np.ndarray) -> np.ndarray:
    """(15, 15) map error state x -> gtsam tangent [pose(ω, t_body) 6, vel 3, bias(acc, gyro) 6]."""
    M = np.zeros((15, 15))
    M[0:3, ATT] = np.eye(3)
    M[3:6, POS] = R.T  # Pose3 translation tangent is in the body frame: δp = R t_body
    M[6:9, VEL] = np.eye(3)
    M[9:12, BA] = np.eye(3)
    M[12:15, BG] = np.eye(3)
    return M


def imu_transition(pim: gtsam.PreintegratedCombinedMeasurements, nav_i: gtsam.NavState,
                   bias_i: gtsam.imuBias.ConstantBias, nav_j: gtsam.NavState) -> tuple[np.ndarray, np.ndarray]:
    """Φ, Q of the error state over one preintegration interval, from the linearised CombinedImuFactor."""
    f = gtsam.CombinedImuFactor(0, 1, 2, 3, 4, 5, pim)
    v = gtsam.Values()
    v.insert(0, nav_i.pose())
    v.insert(1, nav_i.velocity())
    v.insert(2, nav_j.pose())
    v.insert(3, nav_j.velocity())
    v.insert(4, bias_i)
    v.insert(5, bias_i)
    A, _ = f.linearize(v).jacobian()  # whitened, columns: pose_i 6, vel_i 3, pose_j 6, vel_j 3, b_i 6, b_j 6
    Ai = np.hstack([A[:, 0:6], A[:, 6:9], A[:, 18:24]]) @ error_state_map(nav_i.attitude().matrix())
    Aj = np.hstack([A[:, 9:15], A[:, 15:18], A[:, 24:30]]) @ error_state_map(nav_j.attitude().matrix())
    Aj_inv = np.linalg.inv(Aj)
    return -Aj_inv @ Ai, Aj_inv @ Aj_inv.T


class FkfEstimator(NodeEstimator):
    """Federated Kalman filter (GNSS + UWB sub-filters, information sharing, chi-square isolation)."""

    name = "fkf"

    def __init__(self, uav: int, meta: DatasetMeta, settings: dict, init: InitialState):
        super().__init__(uav, meta, settings, init)
        t = tuning(settings)  # the [estimation.graph] table merged over the top level, typed
        node = meta.node(uav)
        if node.imu is None:
            raise ValueError(f"fkf: UAV {uav} has no IMU noise model in the dataset meta")
        self.params = preintegration_params(node.imu, meta.earth)
        self.beta_m = t.fkf_beta_master
        self.beta_g = t.fkf_beta_gnss
        self.beta_u = t.fkf_beta_uwb
        tot = self.beta_m + self.beta_g + self.beta_u
        self.beta_m, self.beta_g, self.beta_u = self.beta_m / tot, self.beta_g / tot, self.beta_u / tot
        p = t.fkf_chi2_p
        self.chi2_p = p
        self.isolation = t.fkf_isolation
        if self.isolation not in ("measurement", "subfilter"):
            raise ValueError(f"fkf_isolation must be 'measurement' or 'subfilter', not {self.isolation!r}")
        self._chi2_cache: dict[int, float] = {}
        # GNSS is the only absolute reference of a slave: isolating it on a chi-square failure lets
        # a filter that became over-confident lock itself out for good, so it is off by default
        self.gnss_isolation = t.fkf_gnss_isolation
        self.nb_cov_scale = t.fkf_neighbour_cov_scale
        # "ci": local and UWB sub-filters fused with adaptive information-sharing factors
        # (ω, 1-ω) that need no independence (covariance intersection); "independent": plain
        # information sum (optimal only if neighbour estimates were independent of ours)
        self.nb_fusion = t.fkf_neighbour_fusion
        if self.nb_fusion not in ("ci", "independent"):
            raise ValueError(f"fkf_neighbour_fusion must be 'ci' or 'independent', not {self.nb_fusion!r}")
        self._omegas = np.linspace(0.05, 0.95, 19)
        # neighbour errors are correlated with EACH OTHER (they all carry the swarm's common-mode
        # error, which ranges cannot see): "split" = split covariance intersection over the N
        # neighbours (each neighbour's position variance along the line of sight × N, consistent
        # for any cross-correlation); "none" = independent (the old behaviour: NEES ~10⁴ on
        # paper_faultfree 100 s, then the chi-square test rejected every range).
        self.nb_corr = t.fkf_neighbour_corr
        if self.nb_corr not in ("split", "none"):
            raise ValueError(f"fkf_neighbour_corr must be 'split' or 'none', not {self.nb_corr!r}")
        self.anchors = meta.anchors()
        # chi-square lock-out guard for fixed-anchor ranges (the absolute reference without GNSS):
        # when N (fkf_anchor_max_reject) of the last 2N anchor ranges failed the test on their own,
        # the filter, not the ranges, is the suspect (a consistent filter rejects ~0.1 % of clean
        # ranges at p 0.999), and anchor ranges are fused untested until the record recovers;
        # 0 disables the guard
        self.anchor_max_reject = t.fkf_anchor_max_reject
        self._anchor_fails: deque[bool] = deque(maxlen=max(1, 2 * self.anchor_max_reject))
        self.tags_self = {k: np.asarray(v, float) for k, v in node.tags.items()}
        self.tags_all = {n.id: {k: np.asarray(v, float) for k, v in n.tags.items()} for n in meta.nodes}
        # nominal state
        self.nav = gtsam.NavState(gtsam.Rot3.Quaternion(*np.asarray(init.quat, float)),
                                  np.asarray(init.pos, float), np.asarray(init.vel, float))
        self.bias = gtsam.imuBias.ConstantBias()
        R = self.nav.attitude().matrix()
        P = np.zeros((15, 15))
        Pn = np.diag(np.asarray(init.att_sigma, float) ** 2)  # roll/pitch/yaw ~ rotation about E/N/U
        P[ATT, ATT] = R.T @ Pn @ R
        P[VEL, VEL] = np.eye(3) * init.vel_sigma**2
        P[POS, POS] = np.diag(np.asarray(init.pos_sigma, float) ** 2)
        P[BA, BA] = np.eye(3) * max(node.imu.accel_bias_sigma, 1e-5) ** 2
        P[BG, BG] = np.eye(3) * max(node.imu.gyro_bias_sigma, 1e-7) ** 2
        self.P = P
        self.t = init.t
        self.k = 0
        self._pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.bias)
        self._last_state = NodeState(uav, 0, 0, init.t, self.nav.position(), P[POS, POS].copy(), self.nav.velocity())

    # -- helpers --------------------------------------------------------------------------

    def _chi2(self, dof: int) -> float:
        v = self._chi2_cache.get(dof)
        if v is None:
            v = self._chi2_cache[dof] = float(chi2.ppf(self.chi2_p, dof))
        return v

    def _predict(self, inp: EpochInput) -> None:
        self._pim.resetIntegrationAndSetBias(self.bias)
        preintegrate(self._pim, inp)
        if self._pim.deltaTij() <= 0.0:
            return
        nav_j = self._pim.predict(self.nav, self.bias)
        Phi, Q = imu_transition(self._pim, self.nav, self.bias, nav_j)
        self.P = Phi @ self.P @ Phi.T + Q
        self.P = 0.5 * (self.P + self.P.T)
        self.nav = nav_j

    def _gnss_subfilter(self, inp: EpochInput) -> tuple[np.ndarray, np.ndarray] | None:
        """Information contribution (H'R⁻¹H, H'R⁻¹r) of the GNSS sub-filter, or None (no data/isolated)."""
        rows, res, var = [], [], []
        p, v = self.nav.position(), self.nav.velocity()
        if inp.gnss_pos is not None and np.all(np.isfinite(inp.gnss_pos)):
            sig = inp.gnss_pos_sigma if inp.gnss_pos_sigma is not None else np.ones(3)
            for a in range(3):
                h = np.zeros(15)
                h[6 + a] = 1.0
                rows.append(h)
                res.append(inp.gnss_pos[a] - p[a])
                var.append(sig[a] ** 2)
        if inp.gnss_vel is not None and np.all(np.isfinite(inp.gnss_vel)):
            sv = inp.gnss_vel_sigma if inp.gnss_vel_sigma is not None else 0.2
            for a in range(3):
                h = np.zeros(15)
                h[3 + a] = 1.0
                rows.append(h)
                res.append(inp.gnss_vel[a] - v[a])
                var.append(sv**2)
        if inp.altitude is not None and np.isfinite(inp.altitude):
            h = np.zeros(15)
            h[8] = 1.0
            rows.append(h)
            res.append(inp.altitude - p[2])
            var.append((inp.altitude_sigma or 1.0) ** 2)
        if not rows:
            return None
        H, r, Rv = np.array(rows), np.array(res), np.array(var)
        S = H @ (self.P / self.beta_g) @ H.T + np.diag(Rv)
        nis = float(r @ np.linalg.solve(S, r))
        self._gnss_nis = nis
        if self.gnss_isolation and nis > self._chi2(len(r)):
            self._gnss_isolated = True
            return None
        Hw = H / Rv[:, None]
        return H.T @ Hw, Hw.T @ r

    def _uwb_subfilter(self, x_lin: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray] | None, list[LinkInfo]]:
        """UWB sub-filter linearised at error state x_lin; returns info contribution and link flags."""
        inp = self._inp
        R = self.nav.attitude().matrix() @ gtsam.Rot3.Expmap(x_lin[ATT]).matrix()
        p = self.nav.position() + x_lin[POS]
        v = self.nav.velocity() + x_lin[VEL]
        Pu = self.P / self.beta_u
        scale = self.nb_cov_scale
        # the far ends, read row by row (dicts); the measurement model below, for every row at once
        use, pb, Pb, lever, other_ids = [], [], [], [], []
        zero3, zero33 = np.zeros(3), np.zeros((3, 3))
        for j in range(len(inp.range_m)):
            other = int(inp.range_other[j])
            if not np.isfinite(inp.range_m[j]):
                continue
            dt = inp.t - float(inp.range_t[j])
            if other in self.anchors:
                pb.append(self.anchors[other] + self.tags_all.get(other, {}).get(int(inp.range_tag_other[j]), zero3))
                Pb.append(zero33)
            else:
                st = self._nb.get(other)
                if st is None:
                    continue  # neighbour not live: no position to range to
                pb.append(np.asarray(st.pos, float) - np.asarray(st.vel, float) * dt)
                Pb.append(np.asarray(st.pos_cov, float) * scale)
            use.append(j)
            other_ids.append(other)
            lever.append(self.tags_self.get(int(inp.range_tag_self[j]), zero3))
        if not use:
            return None, []
        use = np.array(use)
        dt = inp.t - np.asarray(inp.range_t, float)[use]
        lever, Pb = np.array(lever, float), np.array(Pb)
        d = (p - v * dt[:, None] + lever @ R.T) - np.array(pb)  # own tag − far end (ENU m)
        rng = np.sqrt(np.einsum("ij,ij->i", d, d))
        ok = rng >= 1e-3
        use, d, rng, lever, Pb, dt = use[ok], d[ok], rng[ok], lever[ok], Pb[ok], dt[ok]
        other_ids = [o for o, k in zip(other_ids, ok.tolist()) if k]
        if not len(use):
            return None, []
        u = d / rng[:, None]
        H = np.zeros((len(use), 15))
        H[:, POS] = u
        H[:, ATT] = -np.cross(u @ R, lever)  # −uᵀ R [lever]× = −(Rᵀu) × lever
        sig = np.asarray(inp.range_sigma, float)[use]
        sig = np.where(np.isfinite(sig) & (sig > 0), sig, self.meta.uwb_sigma_m)
        q = np.einsum("ni,nij,nj->n", u, Pb, u)  # neighbour position variance along each line of sight
        Rv = sig ** 2 + q
        innov = np.asarray(inp.range_m, float)[use] - rng
        r = innov + H @ x_lin  # innovation of the (iterated) linearisation: z − h(x_lin) + H x_lin, prior mean 0
        s_pred = np.einsum("ni,ij,nj->n", H, Pu, H) + Rv
        links = [[o, i, sp] for o, i, sp in zip(other_ids, innov.tolist(), s_pred.tolist())]
        n_nb = int(np.count_nonzero(q))
        if self.nb_corr == "split" and n_nb > 1:
            # neighbours' errors are mutually correlated by an unknown amount: split-CI bound
            # cov([e_1..e_N]) <= blockdiag(N·P_j) for ANY correlation, i.e. information-sharing
            # factor 1/N per neighbour; then CI of the whole UWB part with the local part (_fuse)
            Rv = Rv + (n_nb - 1) * q
            for m in range(len(links)):
                links[m][2] += (n_nb - 1) * q[m]
        keep, flags, Rfull = self._isolate(H, r, Rv, links, x_lin, Pu)
        if not keep.any():
            return None, flags
        Hk, rk, Rk = H[keep], r[keep], Rfull[np.ix_(keep, keep)]
        Hw = np.linalg.solve(Rk, Hk)  # R⁻¹H
        return (Hk.T @ Hw, Hw.T @ rk), flags

    def _isolate(self, H: np.ndarray, r: np.ndarray, Rv: np.ndarray, links: list, x_lin: np.ndarray, Pu: np.ndarray):
        """χ² isolation of the UWB rows (per measurement, then the sub-filter's NIS): (rows kept,
        LinkInfo per row, the rows' noise covariance)."""
        keep = np.ones(len(r), bool)
        anchor = np.array([lk[0] in self.anchors for lk in links])
        # lock-out guard: anchor ranges exempt from both tests while the failure record is at the limit
        forced = anchor & (self.anchor_max_reject > 0 and sum(self._anchor_fails) >= self.anchor_max_reject)
        self._anchor_gate = np.zeros(len(r), bool)  # anchor ranges that would pass the test alone
        flags = []
        thr1 = self._chi2(1)
        for m, (other, innov, s) in enumerate(links):
            ok = innov * innov / s <= thr1
            self._anchor_gate[m] = bool(anchor[m] and ok)
            if self.isolation == "measurement" and not ok and not forced[m]:
                keep[m] = False
        Rfull = np.diag(Rv)
        tested = keep & ~forced
        if tested.any():
            Hk, rk = H[tested], r[tested] - H[tested] @ x_lin  # innovation about the prior (x = 0)
            S = Hk @ Pu @ Hk.T + Rfull[np.ix_(tested, tested)]
            nis = float(rk @ np.linalg.solve(S, rk))
            self._uwb_nis = nis
            if nis > self._chi2(int(tested.sum())):
                keep[tested] = False
                self._uwb_isolated = True
        for m, (other, innov, s) in enumerate(links):
            flags.append(LinkInfo(other, LinkClass.H2_NORMAL if keep[m] else LinkClass.H0_FAILED,
                                  abs(innov), 1.0 if keep[m] else 0.0))
        return keep, flags, Rfull

    def _fuse(self, g: tuple[np.ndarray, np.ndarray] | None,
              u: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Master fusion of the healthy sub-filters (an isolated one is passed as None).

        A sub-filter's contribution is its measurement information (HᵀR⁻¹H, HᵀR⁻¹r) about the
        common prior (error state 0, covariance P). Local part: prior + GNSS, an information sum
        (β's of the healthy sub-filters renormalised, so the prior counts exactly once — the
        "reconstruction" after isolating one). UWB part: its information depends on neighbour
        estimates that are correlated with ours by an unknown amount, so with
        ``fkf_neighbour_fusion = "ci"`` it is fused by covariance intersection
        Y = ω·Y_local + (1-ω)·Y_uwb, ω picked from a grid to minimise the trace of the fused position
        covariance — an adaptive information-sharing factor that is consistent whatever the
        correlation. ``"independent"`` adds it like the GNSS information.
        """
        Y = np.linalg.inv(self.P)
        y = np.zeros(15)
        if g is not None:
            Y = Y + g[0]
            y = y + g[1]
        if u is not None and self.nb_fusion == "independent":
            Y, y = Y + u[0], y + u[1]
        elif u is not None:
            Pa = np.linalg.inv(Y)
            xa = Pa @ y
            return self._ci_position(xa, Pa, u[0][POS, POS], u[1][POS])
        Pf = np.linalg.inv(Y)
        Pf = 0.5 * (Pf + Pf.T)
        return Pf @ y, Pf

    def _ci_position(self, xa, Pa, Yu, yu):
        """Covariance intersection on the position subspace, the rest conditioned on position.

        The UWB information (position block; the lever-arm attitude coupling is neglected here)
        is fused with the local position marginal by CI, ω minimising the trace of the result;
        the other states follow through the local posterior's conditional on position, so only
        the position marginal — the part correlated with the neighbours — is treated
        conservatively.
        """
        Ppp = Pa[POS, POS]
        Ypp = np.linalg.inv(Ppp)
        w_all = self._omegas
        try:  # every ω of the grid at once: the same inverses and traces as one by one
            P_all = np.linalg.inv(w_all[:, None, None] * Ypp + (1.0 - w_all)[:, None, None] * Yu)
            i = int(np.argmin(np.trace(P_all, axis1=1, axis2=2)))  # the first of equal minima
            w, Pc = float(w_all[i]), P_all[i]
        except np.linalg.LinAlgError:  # a singular mix: skip it, as the grid search one by one
            best = None
            for w in w_all:
                try:
                    Pc = np.linalg.inv(w * Ypp + (1.0 - w) * Yu)
                except np.linalg.LinAlgError:
                    continue
                tr = float(np.trace(Pc))
                if best is None or tr < best[0]:
                    best = (tr, w, Pc)
            _, w, Pc = best
        self.omega = float(w)
        xc = Pc @ (w * Ypp @ xa[POS] + (1.0 - w) * yu)
        G = Pa[:, POS] @ Ypp  # (15,3), G[POS] = I
        x = xa + G @ (xc - xa[POS])
        P = Pa + G @ (Pc - Ppp) @ G.T
        return x, 0.5 * (P + P.T)

    def _state(self, r: int, x: np.ndarray, Pf: np.ndarray, delta: float) -> NodeState:
        pos = self.nav.position() + x[POS]
        vel = self.nav.velocity() + x[VEL]
        st = NodeState(self.uav, self.k, r, self.t, pos, Pf[POS, POS].copy(), vel, delta)
        self._last_state = st
        return st

    # -- protocol -------------------------------------------------------------------------

    def begin_epoch(self, inp: EpochInput) -> NodeState:
        self._inp = inp
        self.k, self.t = inp.k, inp.t
        self._gnss_isolated = self._uwb_isolated = False
        self._gnss_nis = self._uwb_nis = None
        self._predict(inp)
        self._g = self._gnss_subfilter(inp)
        self._x, self._Pf = self._fuse(self._g)
        self._links: list[LinkInfo] = []
        self._nb: dict[int, NodeState] | None = None
        st = self._state(0, self._x, self._Pf, float("inf"))
        st.ranges = {int(o): float(z) for o, z in zip(inp.range_other, inp.range_m) if o not in self.anchors}
        return st

    def iterate(self, r: int, peers: dict[int, NodeState]) -> NodeState:
        if self._nb is None:  # round 1: keep the neighbours' round-0 (pre-range) states for all rounds
            self._nb = {j: peers[j] for j in sorted(peers)}
        self._uwb_isolated = False
        u, self._links = self._uwb_subfilter(self._x)
        x, Pf = self._fuse(self._g, u)
        delta = float(np.linalg.norm(x[POS] - self._x[POS]))
        self._x, self._Pf = x, Pf
        return self._state(r, x, Pf, delta)

    def end_epoch(self) -> NodeEstimate:
        x = self._x
        # record of anchor ranges failing the χ² test on their own (lock-out guard, _uwb_subfilter)
        gate = getattr(self, "_anchor_gate", np.zeros(0, bool))
        for m, li in enumerate(self._links):
            if int(li.other) in self.anchors:
                self._anchor_fails.append(not (m < len(gate) and gate[m]))
        # inject the fused error state into the nominal INS solution and reset (error-state KF)
        rot = self.nav.attitude().compose(gtsam.Rot3.Expmap(x[ATT]))
        self.nav = gtsam.NavState(rot, self.nav.position() + x[POS], self.nav.velocity() + x[VEL])
        self.bias = gtsam.imuBias.ConstantBias(self.bias.accelerometer() + x[BA], self.bias.gyroscope() + x[BG])
        self.P = self._Pf
        self._x = np.zeros(15)
        q = rot.toQuaternion()
        return NodeEstimate(self.uav, self.k, self.t, self.nav.position().copy(), self.nav.velocity().copy(),
                            self.P[POS, POS].copy(), np.array([q.w(), q.x(), q.y(), q.z()]), list(self._links))

    def bootstrap(self, t: float, peers: dict[int, NodeState], inp: EpochInput | None) -> None:
        """Restart: position/velocity from GNSS if present, else the mean of the peers' (coarse)."""
        if inp is not None and inp.gnss_pos is not None:
            pos, psig = np.asarray(inp.gnss_pos, float), np.asarray(inp.gnss_pos_sigma if inp.gnss_pos_sigma is not None else np.full(3, 5.0))
            vel = np.asarray(inp.gnss_vel, float) if inp.gnss_vel is not None else self.nav.velocity()
        elif peers:
            pos = np.mean([np.asarray(s.pos) for s in peers.values()], axis=0)
            vel = np.mean([np.asarray(s.vel) for s in peers.values()], axis=0)
            psig = np.full(3, 100.0)
        else:
            raise ValueError("fkf: cannot bootstrap without GNSS or peers")
        self.nav = gtsam.NavState(self.nav.attitude(), pos, vel)
        self.P[POS, :] = 0.0
        self.P[:, POS] = 0.0
        self.P[VEL, :] = 0.0
        self.P[:, VEL] = 0.0
        self.P[POS, POS] = np.diag(psig**2)
        self.P[VEL, VEL] = np.eye(3) * 1.0
        self.t = t
