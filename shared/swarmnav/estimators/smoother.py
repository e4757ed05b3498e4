"""The per-UAV graph's fixed-lag smoother and its IMU preintegration parameters."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from .imu import preintegration_params


def floored_params(imu, earth, gyro_rw_floor: float, accel_rw_floor: float) -> gtsam.PreintegrationCombinedParams:
    """Preintegration parameters of ``imu`` with its bias random walks floored (rad/s/√s, m/s²/√s).
    Conditioning: the tiny bias random walks of a good IMU (~1e-7 rad/s/√s) make the
    CombinedImuFactor's bias block ~1e14 times stiffer than the rest and ISAM2 reports an
    indeterminate system (settings ``bias_rw_floor``)."""
    params = preintegration_params(imu, earth)
    params.setBiasOmegaCovariance(np.eye(3) * max(imu.gyro_bias_rw, gyro_rw_floor) ** 2)
    params.setBiasAccCovariance(np.eye(3) * max(imu.accel_bias_rw, accel_rw_floor) ** 2)
    return params


def new_smoother(lag: float, relin_thresh: float, t: float, pose, vel, pos_sigma, vel_sigma, att_sigma,
                 bias_sigmas) -> gtsam.IncrementalFixedLagSmoother:
    """A fixed-lag smoother (ISAM2, QR; lag s) holding the priors on X(0), V(0), B(0) at ``t``: pose
    (attitude σ rad, position σ m ENU), velocity σ (m/s), bias σ (``bias_sigmas``: acc, gyro).
    ISAM2 relinearises a variable only when its delta exceeds ``relin_thresh`` (any component: rad,
    m, m/s, bias units; tests/test_graph.py::test_fixed_lag_matches_batch_solve)."""
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(relin_thresh)
    p.relinearizeSkip = 1
    p.setFactorization("QR")
    sm = gtsam.IncrementalFixedLagSmoother(lag, p)
    Rm = pose.rotation().matrix()
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.diag(np.maximum(att_sigma, 1e-4) ** 2)
    cov[3:, 3:] = Rm.T @ np.diag(np.maximum(pos_sigma, 1e-3) ** 2) @ Rm
    bias = gtsam.imuBias.ConstantBias()
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPose3(X(0), pose, gtsam.noiseModel.Gaussian.Covariance(cov)))
    g.add(gtsam.PriorFactorVector(V(0), vel, gtsam.noiseModel.Isotropic.Sigma(3, max(vel_sigma, 1e-3))))
    g.add(gtsam.PriorFactorConstantBias(B(0), bias, gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
    v = gtsam.Values()
    v.insert(X(0), pose)
    v.insert(V(0), vel)
    v.insert(B(0), bias)
    ts = gtsam.FixedLagSmootherKeyTimestampMap()
    for k in (X(0), V(0), B(0)):
        ts.insert((k, float(t)))
    sm.update(g, v, ts)
    return sm

