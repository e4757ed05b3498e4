"""``central`` — the centralised **ORACLE** (accuracy reference, not a deployable method).

One joint factor graph over every UAV and every measurement of the epoch, solved incrementally with
``gtsam.IncrementalFixedLagSmoother`` (ISAM2 inside; lag = ``fixed_lag_s``, so the per-epoch cost is
bounded). Per UAV and epoch k: Pose3 X, velocity V, bias B; factors:

- ``CombinedImuFactor`` X,V,B(k-1) -> X,V,B(k) from the epoch's IMU samples (imu.preintegrate);
- GNSS position (``GPSFactor``) and velocity (prior on V) when a fix exists;
- every UWB range of the epoch between two UAVs (``RangeFactorPose3``, or a lever-arm custom factor
  when the tags are not at the body origin) and to fixed anchors (``factors.range_to_point_factor``);
- every relative azimuth/elevation of eq. 27 (``factors.azel_factor``; setting ``central_use_rel``).

**Oracle**: it reads the truth fault labels (``EpochSlicer.range_labels``) and drops every range
that is labelled faulty: ``fault_kind != NONE`` **or** ``|fault_err| > meta.fault_threshold_m``
(the scoring definition of a faulty link-epoch, widened to every labelled fault episode, e.g. an
interfered link whose bias happens to be small still has 5x noise). No estimator that is compared
with it may see these labels. Ranges are attached to the epoch's states (event times inside the
epoch are not interpolated — exact for the simulator, where ranges are taken at the epoch time).
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..dataset import DatasetMeta, EpochInput, FaultKind
from .base import InitialState, NodeEstimate, SwarmEstimator
from .imu import preintegrate, preintegration_params


def X(u: int, k: int) -> int:
    return gtsam.symbol("x", u * 10_000_000 + k)


def V(u: int, k: int) -> int:
    return gtsam.symbol("v", u * 10_000_000 + k)


def B(u: int, k: int) -> int:
    return gtsam.symbol("b", u * 10_000_000 + k)


def keep_range(fault_kind: int, fault_err: float, threshold: float) -> bool:
    """Oracle rule: keep a range only if it carries no fault label and no error above threshold."""
    if int(fault_kind) != int(FaultKind.NONE):
        return False
    return not (np.isfinite(fault_err) and abs(fault_err) > threshold)


def _pair_range_factor(ka: int, kb: int, la: np.ndarray, lb: np.ndarray, z: float, noise) -> gtsam.NonlinearFactor:
    """Range between tag la on pose ka and tag lb on pose kb."""
    if not np.any(la) and not np.any(lb):
        return gtsam.RangeFactorPose3(ka, kb, float(z), noise)

    def skew(t):
        return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])

    def err(this, v, H):
        Pa, Pb = v.atPose3(this.keys()[0]), v.atPose3(this.keys()[1])
        Ra, Rb = Pa.rotation().matrix(), Pb.rotation().matrix()
        d = Pa.translation() + Ra @ la - Pb.translation() - Rb @ lb
        r = float(np.linalg.norm(d))
        u = d / max(r, 1e-9)
        if H is not None:
            H[0] = (u @ np.hstack([-Ra @ skew(la), Ra])).reshape(1, 6)
            H[1] = (-u @ np.hstack([-Rb @ skew(lb), Rb])).reshape(1, 6)
        return np.array([r - z])

    return gtsam.CustomFactor(noise, [ka, kb], err)


class CentralEstimator(SwarmEstimator):
    """Joint fixed-lag smoother over the whole swarm with truly faulty ranges removed (ORACLE)."""

    name = "central"

    def __init__(self, meta: DatasetMeta, settings: dict, inits: dict[int, InitialState]):
        s = settings or {}
        self.meta = meta
        self.uavs = sorted(inits)
        self.lag = float(s.get("fixed_lag_s", 5.0))
        self.use_rel = bool(s.get("central_use_rel", True))
        self.with_cov = bool(s.get("central_covariance", True))
        self.anchors = meta.anchors()
        self.tags = {n.id: {k: np.asarray(v, float) for k, v in n.tags.items()} for n in meta.nodes}
        self.params = {u: preintegration_params(meta.node(u).imu, meta.earth) for u in self.uavs}
        self.pims = {u: gtsam.PreintegratedCombinedMeasurements(self.params[u], gtsam.imuBias.ConstantBias()) for u in self.uavs}
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(0.01)
        p.relinearizeSkip = 1
        p.setFactorization("QR")  # the bias random-walk rows make the system too stiff for Cholesky
        self.smoother = gtsam.IncrementalFixedLagSmoother(self.lag, p)
        self.k = 0
        self.dropped = 0  # ranges removed by the oracle so far
        self.nav: dict[int, gtsam.NavState] = {}
        self.bias: dict[int, gtsam.imuBias.ConstantBias] = {}
        g, vals, ts = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        for u in self.uavs:
            ini = inits[u]
            R = gtsam.Rot3.Quaternion(*np.asarray(ini.quat, float))
            pose = gtsam.Pose3(R, np.asarray(ini.pos, float))
            Rm = R.matrix()
            C = np.zeros((6, 6))
            C[0:3, 0:3] = Rm.T @ np.diag(np.asarray(ini.att_sigma, float) ** 2) @ Rm  # body-frame tangent
            C[3:6, 3:6] = Rm.T @ np.diag(np.asarray(ini.pos_sigma, float) ** 2) @ Rm
            g.add(gtsam.PriorFactorPose3(X(u, 0), pose, gtsam.noiseModel.Gaussian.Covariance(C)))
            g.add(gtsam.PriorFactorVector(V(u, 0), np.asarray(ini.vel, float), gtsam.noiseModel.Isotropic.Sigma(3, max(ini.vel_sigma, 1e-3))))
            imu = meta.node(u).imu
            bs = np.r_[np.full(3, max(imu.accel_bias_sigma, 1e-5)), np.full(3, max(imu.gyro_bias_sigma, 1e-7))]
            g.add(gtsam.PriorFactorConstantBias(B(u, 0), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(bs)))
            vals.insert(X(u, 0), pose)
            vals.insert(V(u, 0), np.asarray(ini.vel, float))
            vals.insert(B(u, 0), gtsam.imuBias.ConstantBias())
            for key in (X(u, 0), V(u, 0), B(u, 0)):
                ts[key] = ini.t
            self.nav[u] = gtsam.NavState(pose, np.asarray(ini.vel, float))
            self.bias[u] = gtsam.imuBias.ConstantBias()
        self._pending = (g, vals, ts)

    def step(self, inputs: dict[int, EpochInput], range_labels: dict[str, np.ndarray]) -> dict[int, NodeEstimate]:
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
            if self.use_rel and len(inp.rel_target):
                from .factors import azel_factor

                for j in range(len(inp.rel_target)):
                    tgt = int(inp.rel_target[j])
                    if tgt in inputs and tgt != u:
                        sg = float(inp.rel_sigma[j]) if np.isfinite(inp.rel_sigma[j]) else (self.meta.rel_sigma_rad or 0.0175)
                        g.add(azel_factor(X(u, k), X(tgt, k), float(inp.rel_az[j]), float(inp.rel_el[j]),
                                          gtsam.noiseModel.Isotropic.Sigma(2, sg)))
        self._add_ranges(g, range_labels, k, set(inputs))
        self.smoother.update(g, vals, ts)
        est = self.smoother.calculateEstimate()
        self.k = k
        out: dict[int, NodeEstimate] = {}
        for u in self.uavs:
            pose, vel, b = est.atPose3(X(u, k)), est.atVector(V(u, k)), est.atConstantBias(B(u, k))
            self.nav[u] = gtsam.NavState(pose, vel)
            self.bias[u] = b
            R = pose.rotation().matrix()
            if self.with_cov:
                C = self.smoother.marginalCovariance(X(u, k))[3:6, 3:6]
                pc = R @ C @ R.T
            else:
                pc = np.full((3, 3), np.nan)
            q = pose.rotation().toQuaternion()
            out[u] = NodeEstimate(u, k, t, pose.translation().copy(), np.asarray(vel, float).copy(), pc,
                                  np.array([q.w(), q.x(), q.y(), q.z()]))
        return out

    def _add_ranges(self, g: gtsam.NonlinearFactorGraph, lab: dict[str, np.ndarray], k: int, live: set[int]) -> None:
        from .factors import range_to_point_factor

        thr = self.meta.fault_threshold_m
        n = len(lab.get("range", []))
        for i in range(n):
            if not keep_range(int(lab["fault_kind"][i]), float(lab["fault_err"][i]), thr):
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
                g.add(range_to_point_factor(X(a, k), self.anchors[b] + lb, z, noise, lever=la))
            elif b in live and a in self.anchors:
                g.add(range_to_point_factor(X(b, k), self.anchors[a] + la, z, noise, lever=lb))
