"""``central`` — the centralised **ORACLE** (accuracy reference, not a deployable method).

One joint factor graph over every UAV and every measurement of the epoch, solved incrementally with
``gtsam.IncrementalFixedLagSmoother`` (ISAM2 inside; lag = ``fixed_lag_s``, so the per-epoch cost is
bounded). Per UAV and epoch k: Pose3 X, velocity V, bias B; factors:

- ``CombinedImuFactor`` X,V,B(k-1) -> X,V,B(k) from the epoch's IMU samples (imu.preintegrate);
- GNSS position (``GPSFactor``) and velocity (prior on V) when a fix exists;
- every UWB range of the epoch between two UAVs (``RangeFactorPose3``, or a lever-arm custom factor
  when the tags are not at the body origin) and to fixed anchors (``factors.range_to_point_factor``);
- every relative azimuth/elevation of eq. 27 (``factors.azel_factor``; setting ``central_use_rel``);
- the epoch's passive-listening range differences whose tags are on live UAVs or anchors
  (``factors.tdoa_factor``, from ``EpochSlicer.tdoa_labels``; a dataset's optional ``tdoa`` table).

**Oracle**: it reads the truth fault labels (``EpochSlicer.range_labels``, ``tdoa_labels``) and
drops every range or range difference that is labelled faulty: ``fault_kind != NONE`` **or**
``|fault_err| > meta.fault_threshold_for(row σ)`` (3σ of the row's noise: the scoring definition
of a faulty link-epoch, widened to every labelled fault episode, e.g. an interfered link whose bias
happens to be small still has 5x noise). No estimator that is compared
with it may see these labels. The labels are the dataset's (for a passive row: its measured rdiff
against truth, before the estimators' ``tdoa_offset_m``). Ranges are attached to the epoch's states;
one taken at t_r inside the epoch between a UAV and an anchor, or a passive row of one UAV's tags
and anchors, is fused with the anchor ends moved by v_pred·(t − t_r) (``anchor_time_shift``, as
graph.py; zero for the simulator, whose ranges are taken at the epoch time); inter-UAV rows are
not shifted.

It has the nodes' own-factor models too: the rotor-drag factor of multirotors, and the initial-rest
zero-velocity prior (``imu.InitialRest``) while a UAV that started at rest is still by its IMU.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from ..dataset import DatasetMeta, EpochInput, FaultKind
from ..geometry import skew
from ..models import bearing, uwb_range
from ..models.base import wrap_angle
from .base import InitialState, NodeEstimate, SwarmEstimator
from .factors import (range_to_point_factor, rotor_drag_factor, rotor_drag_prior, rotor_drag_sigma,
                      tdoa_factor, tdoa_row)
from .imu import InitialRest, mean_specific_force, preintegrate, preintegration_params
from .settings import tuning


def X(u: int, k: int) -> int:
    return gtsam.symbol("x", u * 10_000_000 + k)


def V(u: int, k: int) -> int:
    return gtsam.symbol("v", u * 10_000_000 + k)


def B(u: int, k: int) -> int:
    return gtsam.symbol("b", u * 10_000_000 + k)


def M(u: int) -> int:
    """Rotor-drag state [μ, c_x, c_y] of multirotor UAV u (constant; kept in the window)."""
    return gtsam.symbol("m", u)


def keep_range(fault_kind: int, fault_err: float, threshold: float) -> bool:
    """Oracle rule: keep a range only if it carries no fault label and no error above threshold."""
    if int(fault_kind) != int(FaultKind.NONE):
        return False
    return not (np.isfinite(fault_err) and abs(fault_err) > threshold)


def _pair_range_factor(ka: int, kb: int, la: np.ndarray, lb: np.ndarray, z: float, noise) -> gtsam.NonlinearFactor:
    """Range between tag la on pose ka and tag lb on pose kb (``models.uwb_range.range_h``)."""
    if not np.any(la) and not np.any(lb):
        return gtsam.RangeFactorPose3(ka, kb, float(z), noise)

    def err(this, v, H):
        Pa, Pb = v.atPose3(this.keys()[0]), v.atPose3(this.keys()[1])
        Ra, Rb = Pa.rotation().matrix(), Pb.rotation().matrix()
        # models.uwb_range: h = ‖tag_a − tag_b‖, ∂h/∂tag_a = u, ∂h/∂tag_b = −u; the chain rule
        # through each pose (tag = p + R l, right-perturbed) is here. Both tags relative to pose b's
        # origin (the range is translation-invariant; this order of sums is the one the figures
        # were pinned with)
        r, u_a, u_b = uwb_range.range_h(Pa.translation() + Ra @ la - Pb.translation(), Rb @ lb)
        if H is not None:
            H[0] = (u_a @ np.hstack([-Ra @ skew(la), Ra])).reshape(1, 6)
            H[1] = (u_b @ np.hstack([-Rb @ skew(lb), Rb])).reshape(1, 6)
        return np.array([r - z])

    return gtsam.CustomFactor(noise, [ka, kb], err)


def _altitude_factor(key: int, h: float, sigma: float) -> gtsam.NonlinearFactor:
    """Height of the body origin (ENU up) — a prior on the pose's up component only."""
    return gtsam.PoseTranslationPrior3D(key, gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, h])),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.array([1e6, 1e6, sigma])))


def azel_block_factor(key_obs: int, key_tgts: list[int], az: np.ndarray, el: np.ndarray,
                      sigmas: np.ndarray) -> gtsam.CustomFactor:
    """All of one observer's eq. 27 azimuth/elevation measurements of an epoch in one factor.

    The model is ``models.bearing`` (``azel_jacobians``: ENU az/el and ∂/∂(p_tgt − p_obs); azimuth
    residual wrapped, error h − z), as in ``factors.azel_factor``, but vectorised over the targets:
    one Python callback per observer instead of one per pair (the 306 single factors per paper
    epoch cost ~60 µs each at every relinearisation). Rows are whitened here (noise model Unit), so
    each pair keeps its own σ.
    """
    n = len(key_tgts)
    z = np.stack([np.asarray(az, float), np.asarray(el, float)], axis=1)  # (n,2)
    w = 1.0 / np.asarray(sigmas, float)
    rows = np.arange(n)

    def err(this, v, H):
        # one Pose3.matrix() (4x4, world <- body) per pose: its rotation block and translation are
        # the very numbers rotation().matrix() / translation() return
        To = v.atPose3(key_obs).matrix()
        Ts = np.stack([v.atPose3(kt).matrix() for kt in key_tgts])  # (n,4,4)
        az_h, el_h, Jd = bearing.azel_jacobians(Ts[:, :3, 3] - To[:3, 3])  # h, ∂h/∂(p_tgt − p_obs)
        res = np.stack([az_h, el_h], axis=1) - z
        res[:, 0] = wrap_angle(res[:, 0])
        if H is not None:
            Jd *= w[:, None, None]
            Ho = np.zeros((2 * n, 6))
            Ho[:, 3:6] = -(Jd @ To[:3, :3]).reshape(2 * n, 3)
            H[0] = Ho
            # ∂/∂ξ_tgt (right-perturbed translation) = Jd_i R_i, each in its own two rows
            Ht = np.zeros((n, 2 * n, 6))
            Ht.reshape(n, n, 2, 6)[rows, rows, :, 3:6] = Jd @ Ts[:, :3, :3]
            for i in range(n):
                H[i + 1] = Ht[i]
        return (res * w[:, None]).reshape(2 * n)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), [key_obs, *key_tgts], err)


ITERATION_TOL_M = 0.01  # central_first_epoch_iterations: iterate until no UAV's position moves this much (m)


class CentralEstimator(SwarmEstimator):
    """Joint fixed-lag smoother over the whole swarm with truly faulty ranges removed (ORACLE)."""

    name = "central"

    def __init__(self, meta: DatasetMeta, settings: dict, inits: dict[int, InitialState]):
        t = tuning(settings)  # [estimation.graph] overrides merged, typed, as for graph.py
        self.meta = meta
        self.uavs = sorted(inits)
        # own lag (not the distributed estimators' ``fixed_lag_s``): the joint window is dense (every
        # pair ranges), so ISAM2 re-eliminates ~18 x 15 states per epoch in the window; measured on
        # paper_faultfree 40 s: lag 5 s 124 ms/epoch, 2.5 s 59 ms, 1.5 s 35 ms, with the same
        # current-epoch RMSE (0.407 m) and NEES (4.1) — the filtered estimate is what is scored.
        self.lag = t.central_lag_s
        self.use_rel = t.central_use_rel
        self.with_cov = t.central_covariance
        self.anchors = meta.anchors()
        self.tags = {n.id: {k: np.asarray(v, float) for k, v in n.tags.items()} for n in meta.nodes}
        # bias random-walk floors (rad/s/√s, m/s²/√s) for the joint graph only: the shared imu.py
        # floors (1e-7, 1e-6) give whitened bias rows ~1e7 next to GNSS rows ~0.2, which Cholesky
        # rejects (IndeterminateLinearSystem; measured: still at 1e-5 / 1e-4 on paper_faultfree
        # epoch 2); 3e-5 / 3e-4 works and gives the same RMSE/NEES as 1e-4 / 1e-3 (0.407 m, 4.1).
        # Paper slaves: 8e-8 rad/s/√s, 1e-4 m/s²/√s true — the floor only loosens the gyro RW.
        self.gyro_rw_floor = t.central_gyro_rw_floor
        self.accel_rw_floor = t.central_accel_rw_floor
        self.integration_sigma = t.central_integration_sigma
        self.params = {}
        for u in self.uavs:
            imu = meta.node(u).imu
            # integration σ 1e-3 (imu.py default 1e-4): with 0.1 s epochs (MILUV) the preintegrated
            # position covariance ~3e-9 m² made Cholesky throw IndeterminateLinearSystem at the
            # first bias key; 1e-3 is still negligible beside the accelerometer white noise.
            pp = preintegration_params(imu, meta.earth, integration_sigma=self.integration_sigma)
            pp.setBiasOmegaCovariance(np.eye(3) * max(imu.gyro_bias_rw, self.gyro_rw_floor) ** 2)
            pp.setBiasAccCovariance(np.eye(3) * max(imu.accel_bias_rw, self.accel_rw_floor) ** 2)
            self.params[u] = pp
        self.pims = {u: gtsam.PreintegratedCombinedMeasurements(self.params[u], gtsam.imuBias.ConstantBias()) for u in self.uavs}
        self.relin = (t.central_relin_threshold, t.central_relin_skip)
        self.first_epoch_iterations = t.central_first_epoch_iterations
        self.factorization = t.central_factorization
        self.smoother = self._new_smoother()
        # Cholesky may refuse a joint graph that QR solves (an ill-conditioned or weakly constrained
        # window: no inter-UAV link, every UAV without GNSS, short epochs): then the oracle switches
        # to QR for good, replaying every update so far (``_update``); kept only while on Cholesky
        self._updates: list[tuple] | None = [] if self.factorization == "CHOLESKY" else None
        self.switched_to_qr_at: int | None = None  # the epoch at which it did (None: never)
        # rotor-drag model of multirotor UAVs, as in the per-UAV graph (own_factors.OwnFactors.add_drag;
        # same settings keys), off during a UAV's initial rest phase
        self.drag = {u for u in self.uavs if t.rotor_drag
                     and getattr(meta.node(u), "airframe", None) == "multirotor"}
        self.drag_mu0 = t.drag_mu_prior
        self.drag_mu_sigma = t.drag_mu_prior_sigma
        self.drag_sigma_scale = t.drag_sigma_scale
        self.tdoa_scale = t.tdoa_sigma_scale  # passive rows σ × this, as graph.py
        self.tdoa_offset = t.tdoa_offset_m  # subtracted from every rdiff (m), as graph.py
        # a range or own tdoa row taken at t_r < t is fused with its anchor ends moved by
        # v_pred·(t − t_r), as graph.py's anchor_time_shift (zero when rows are stamped at the epoch)
        self.anchor_time_shift = t.anchor_time_shift
        self._v_pred: dict[int, np.ndarray] = {}
        self._drag_started: set[int] = set()
        # initial rest phase, as graph.py (imu.InitialRest; same settings keys): V = 0 (σ
        # zupt_sigma_mps) while a UAV that started at rest is still by its IMU
        self._rest = {u: InitialRest.from_settings(t, inits[u].vel, inits[u].vel_sigma, meta.earth.gravity_mps2)
                      for u in self.uavs}
        self.k = 0
        self.dropped = 0  # ranges removed by the oracle so far
        self.nav: dict[int, gtsam.NavState] = {}
        self.bias: dict[int, gtsam.imuBias.ConstantBias] = {}
        self._pending = self._initial_priors(inits)

    def _initial_priors(self, inits: dict[int, InitialState]):
        """(graph, values, timestamps) of every UAV's prior on X, V, B at epoch 0; sets nav and bias."""
        g, vals, ts = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        for u in self.uavs:
            ini = inits[u]
            R = gtsam.Rot3.Quaternion(*np.asarray(ini.quat, float))
            pose = gtsam.Pose3(R, np.asarray(ini.pos, float))
            Rm = R.matrix()
            C = np.zeros((6, 6))
            # body-frame tangent; a sigma of 0 ("known exactly") floored at 1e-4 rad as in graph.py
            C[0:3, 0:3] = Rm.T @ np.diag(np.maximum(np.asarray(ini.att_sigma, float), 1e-4) ** 2) @ Rm
            C[3:6, 3:6] = Rm.T @ np.diag(np.asarray(ini.pos_sigma, float) ** 2) @ Rm
            g.add(gtsam.PriorFactorPose3(X(u, 0), pose, gtsam.noiseModel.Gaussian.Covariance(C)))
            g.add(gtsam.PriorFactorVector(V(u, 0), np.asarray(ini.vel, float), gtsam.noiseModel.Isotropic.Sigma(3, max(ini.vel_sigma, 1e-3))))
            imu = self.meta.node(u).imu
            bs = np.r_[np.full(3, max(imu.accel_bias_sigma, 1e-5)), np.full(3, max(imu.gyro_bias_sigma, 1e-7))]
            g.add(gtsam.PriorFactorConstantBias(B(u, 0), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(bs)))
            vals.insert(X(u, 0), pose)
            vals.insert(V(u, 0), np.asarray(ini.vel, float))
            vals.insert(B(u, 0), gtsam.imuBias.ConstantBias())
            for key in (X(u, 0), V(u, 0), B(u, 0)):
                ts[key] = ini.t
            self.nav[u] = gtsam.NavState(pose, np.asarray(ini.vel, float))
            self.bias[u] = gtsam.imuBias.ConstantBias()
        return g, vals, ts

    def step(self, inputs: dict[int, EpochInput], range_labels: dict[str, np.ndarray],
             tdoa_labels: dict[str, np.ndarray] | None = None) -> dict[int, NodeEstimate]:
        g, vals, ts = self._pending if self._pending is not None else (gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
        self._pending = None
        k0 = self.k
        k = next(iter(inputs.values())).k
        t = next(iter(inputs.values())).t
        for u in self.uavs:
            inp = inputs.get(u)
            if inp is None:
                raise ValueError(f"central: no input for UAV {u} at epoch {k} (the oracle needs every UAV)")
            pim = self.pims[u]
            pim.resetIntegrationAndSetBias(self.bias[u])
            preintegrate(pim, inp)
            g.add(gtsam.CombinedImuFactor(X(u, k0), V(u, k0), X(u, k), V(u, k), B(u, k0), B(u, k), pim))
            pred = pim.predict(self.nav[u], self.bias[u])
            self._v_pred[u] = np.asarray(pred.velocity(), float)
            vals.insert(X(u, k), pred.pose())
            vals.insert(V(u, k), pred.velocity())
            vals.insert(B(u, k), self.bias[u])
            for key in (X(u, k), V(u, k), B(u, k)):
                ts[key] = t
            if inp.gnss_pos is not None:
                sig = inp.gnss_pos_sigma if inp.gnss_pos_sigma is not None else np.ones(3)
                g.add(gtsam.GPSFactor(X(u, k), np.asarray(inp.gnss_pos, float), gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sig, float))))
            if inp.gnss_vel is not None:
                sv = inp.gnss_vel_sigma if inp.gnss_vel_sigma is not None else 0.2
                g.add(gtsam.PriorFactorVector(V(u, k), np.asarray(inp.gnss_vel, float), gtsam.noiseModel.Isotropic.Sigma(3, sv)))
            if inp.altitude is not None and np.isfinite(inp.altitude):
                g.add(_altitude_factor(X(u, k), float(inp.altitude), float(inp.altitude_sigma or 1.0)))
            if self._rest[u].update(inp):
                g.add(self._rest[u].prior(V(u, k)))
            if u in self.drag:
                self._add_drag(g, vals, ts, u, k, t, inp)
            if self.use_rel and len(inp.rel_target):
                sel = [j for j in range(len(inp.rel_target)) if int(inp.rel_target[j]) in inputs and int(inp.rel_target[j]) != u]
                if sel:
                    default = self.meta.rel_sigma_rad or 0.0175
                    sg = np.array([float(inp.rel_sigma[j]) if np.isfinite(inp.rel_sigma[j]) and inp.rel_sigma[j] > 0 else default for j in sel])
                    g.add(azel_block_factor(X(u, k), [X(int(inp.rel_target[j]), k) for j in sel],
                                            np.asarray(inp.rel_az)[sel], np.asarray(inp.rel_el)[sel], sg))
        self._add_ranges(g, range_labels, k, t, set(inputs))
        if tdoa_labels is not None:
            self._add_tdoa(g, tdoa_labels, k, t, set(inputs))
        est, covs = self._update(g, vals, ts, k)
        if k0 == 0 and self.first_epoch_iterations:  # the first measurements meet the initial state's error
            est, covs = self._iterate(k, est, covs)
        self.k = k
        out: dict[int, NodeEstimate] = {}
        for u in self.uavs:
            pose, vel, b = est.atPose3(X(u, k)), est.atVector(V(u, k)), est.atConstantBias(B(u, k))
            self.nav[u] = gtsam.NavState(pose, vel)
            self.bias[u] = b
            R = pose.rotation().matrix()
            C = covs.get(u)
            pc = R @ C @ R.T if C is not None else np.full((3, 3), np.nan)
            q = pose.rotation().toQuaternion()
            out[u] = NodeEstimate(u, k, t, pose.translation().copy(), np.asarray(vel, float).copy(), pc,
                                  np.array([q.w(), q.x(), q.y(), q.z()]))
        return out

    def _new_smoother(self) -> gtsam.IncrementalFixedLagSmoother:
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(self.relin[0])
        p.relinearizeSkip = self.relin[1]
        p.setFactorization(self.factorization)
        return gtsam.IncrementalFixedLagSmoother(self.lag, p)

    def _update(self, g, vals, ts, k: int):
        """The smoother's update with epoch k's factors; its estimate and (``central_covariance``) the
        UAVs' position covariances. On Cholesky's "Indeterminate linear system" the smoother is rebuilt
        with QR and every update so far replayed in order (the same fixed-lag window and
        marginalisation), then this one applied; QR's own failure is raised."""
        try:
            self.smoother.update(g, vals, ts)
            out = self._estimate(k)
        except RuntimeError as e:
            if self._updates is None or "Indeterminate linear system" not in str(e):
                raise
            self._switch_to_qr(k, e)
            self.smoother.update(g, vals, ts)
            return self._estimate(k)
        if self._updates is not None:
            self._updates.append((g, vals, ts))
        return out

    def _estimate(self, k: int):
        return self.smoother.calculateEstimate(), self._position_covariances(k) if self.with_cov else {}

    def _switch_to_qr(self, k: int, e: RuntimeError) -> None:
        """A QR smoother in place of the Cholesky one, every update so far replayed in order."""
        self.factorization, self.switched_to_qr_at = "QR", k
        logging.getLogger("swarmnav.central").warning(
            "central: Cholesky refused the joint graph at epoch %d (%s); switched to QR, %d updates replayed",
            k, str(e).strip().splitlines()[0], len(self._updates))
        self.smoother = self._new_smoother()
        for past in self._updates:
            self.smoother.update(*past)
        self._updates = None

    def _iterate(self, k: int, est, covs):
        """More Gauss–Newton iterations of the window (empty ISAM2 updates: each relinearises what
        moved beyond the threshold and solves again) until no UAV's position moves more than
        ``ITERATION_TOL_M``, at most ``central_first_epoch_iterations`` more. One step from the
        initial state's error can overshoot by metres where the first epoch brings many ranges
        (docs/baselines.md)."""
        empty = (gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
        for _ in range(self.first_epoch_iterations):
            before = np.array([est.atPose3(X(u, k)).translation() for u in self.uavs])
            est, covs = self._update(*empty, k)
            after = np.array([est.atPose3(X(u, k)).translation() for u in self.uavs])
            if np.abs(after - before).max() < ITERATION_TOL_M:
                break
        return est, covs

    def _add_drag(self, g, vals, ts, u: int, k: int, t: float, inp: EpochInput) -> None:
        mf = mean_specific_force(inp)
        if mf is None:
            return
        fbar, T = mf
        if u not in self._drag_started:
            self._drag_started.add(u)
            prior, m0 = rotor_drag_prior(M(u), self.drag_mu0, self.drag_mu_sigma, fbar[:2], self._rest[u].active)
            g.add(prior)
            vals.insert(M(u), m0)
        ts[M(u)] = t  # constant state: never leaves the window
        if self._rest[u].active:
            return  # ground contact, not drag (as graph.py)
        sig = rotor_drag_sigma(self.params[u], T, self.drag_sigma_scale)
        g.add(rotor_drag_factor(X(u, k), V(u, k), B(u, k), M(u), fbar[:2], sig))

    def _position_covariances(self, k: int) -> dict[int, np.ndarray]:
        """Body-frame translation marginals of every UAV's epoch-k pose, from ONE joint marginal
        of the 18 newest pose keys (one pass over the Bayes tree instead of 18 separate
        ``marginalCovariance`` calls, each of which re-walks the shortcuts)."""
        keys = [X(u, k) for u in self.uavs]
        J = self.smoother.getISAM2().jointMarginalCovariance(keys)
        return {u: J.at(X(u, k), X(u, k))[3:6, 3:6] for u in self.uavs}

    def _shift(self, u: int, t: float, t_r: float) -> np.ndarray:
        """How far (m, ENU) UAV u's anchor ends move for a row taken at t_r and fused at t."""
        if not self.anchor_time_shift or not np.isfinite(t_r):
            return np.zeros(3)
        return self._v_pred[u] * (t - t_r)

    def _add_ranges(self, g: gtsam.NonlinearFactorGraph, lab: dict[str, np.ndarray], k: int, t: float,
                    live: set[int]) -> None:
        n = len(lab.get("range", []))
        thr = self.meta.fault_threshold_for(lab["sigma"]) if n else None  # 3σ of each row's noise
        for i in range(n):
            if not keep_range(int(lab["fault_kind"][i]), float(lab["fault_err"][i]), float(thr[i])):
                self.dropped += 1
                continue
            a, b, z = int(lab["a"][i]), int(lab["b"][i]), float(lab["range"][i])
            if not np.isfinite(z):
                continue
            sig = float(lab["sigma"][i]) if np.isfinite(lab["sigma"][i]) and lab["sigma"][i] > 0 else self.meta.uwb_sigma_m
            noise = gtsam.noiseModel.Isotropic.Sigma(1, sig)
            la = self.tags.get(a, {}).get(int(lab["tag_a"][i]), np.zeros(3))
            lb = self.tags.get(b, {}).get(int(lab["tag_b"][i]), np.zeros(3))
            if a in live and b in live:
                g.add(_pair_range_factor(X(a, k), X(b, k), la, lb, z, noise))
            elif a in live and b in self.anchors:
                g.add(range_to_point_factor(X(a, k), self.anchors[b] + lb + self._shift(a, t, float(lab["t"][i])),
                                            z, noise, lever=la))
            elif b in live and a in self.anchors:
                g.add(range_to_point_factor(X(b, k), self.anchors[a] + la + self._shift(b, t, float(lab["t"][i])),
                                            z, noise, lever=lb))

    def _add_tdoa(self, g: gtsam.NonlinearFactorGraph, lab: dict[str, np.ndarray], k: int, t: float,
                  live: set[int]) -> None:
        """Passive-listening range differences of the epoch (every end live or an anchor), the
        truly faulty ones removed like the ranges (oracle). A row of one UAV's tags and anchors
        is time-shifted like an anchor range."""
        n = len(lab.get("rdiff", []))
        thr = self.meta.fault_threshold_for(lab["sigma"]) if n else None  # 3σ of each row's noise
        for i in range(n):
            if not keep_range(int(lab["fault_kind"][i]), float(lab["fault_err"][i]), float(thr[i])):
                self.dropped += 1
                continue
            ends = []
            for nc, tc in (("node", "tag"), ("init", "tag_init"), ("resp", "tag_resp")):
                n, tag = int(lab[nc][i]), int(lab[tc][i])
                lever = self.tags.get(n, {}).get(tag, np.zeros(3))
                if n in self.anchors:
                    ends.append((None, self.anchors[n] + lever))
                elif n in live:
                    ends.append((X(n, k), lever))
                else:
                    break
            else:
                if all(key is None for key, _ in ends):
                    continue  # every tag fixed: nothing to estimate
                uavs = {int(lab[nc][i]) for nc in ("node", "init", "resp")} - set(self.anchors)
                if len(uavs) == 1:
                    d = self._shift(uavs.pop(), t, float(lab["t"][i]))
                    ends = [(key, x if key is not None else x + d) for key, x in ends]
                z, sig = tdoa_row(lab["rdiff"][i], lab["sigma"][i], self.meta.uwb_sigma_m, self.tdoa_scale, self.tdoa_offset)
                g.add(tdoa_factor(ends, z, gtsam.noiseModel.Isotropic.Sigma(1, sig)))
