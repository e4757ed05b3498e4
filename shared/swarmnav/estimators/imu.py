"""IMU preintegration shared by every gtsam-based estimator (and the FKF propagation).

Noise model: continuous-time densities from the dataset's :class:`ImuNoise` (SI). Earth model:
ENU navigation frame, gravity [0, 0, -g] and Earth rotation at the origin latitude given to gtsam
as ``n_gravity`` / ``omegaCoriolis`` (DESIGN.md §3 "Earth model").

Samples are a zero-order hold (dataset convention): the sample at ``imu_t[j]`` holds over
``[imu_t[j], imu_t[j+1])``, the last one until the epoch end ``t``; only the part inside
``[t_prev, t)`` of the epoch is integrated, so any (varying) rate and a sample that started before
``t_prev`` are handled exactly.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..dataset import EpochInput, Earth, ImuNoise


def preintegration_params(imu: ImuNoise, earth: Earth, integration_sigma: float = 1e-4) -> gtsam.PreintegrationCombinedParams:
    p = gtsam.PreintegrationCombinedParams(np.array([0.0, 0.0, -earth.gravity_mps2]))
    p.setGyroscopeCovariance(np.eye(3) * imu.gyro_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * imu.accel_noise_density**2)
    p.setIntegrationCovariance(np.eye(3) * integration_sigma**2)
    # floor the random walks so the bias stays observable-but-movable even for a perfect model
    p.setBiasOmegaCovariance(np.eye(3) * max(imu.gyro_bias_rw, 1e-7) ** 2)
    p.setBiasAccCovariance(np.eye(3) * max(imu.accel_bias_rw, 1e-6) ** 2)
    p.setOmegaCoriolis(np.asarray(earth.earth_rate_radps, float))
    return p


def hold_intervals(inp: EpochInput) -> np.ndarray:
    """Durations (s) each IMU sample of the epoch is in force inside [t_prev, t)."""
    ts = inp.imu_t
    if len(ts) == 0:
        return np.zeros(0)
    start = np.maximum(ts, inp.t_prev)
    end = np.minimum(np.append(ts[1:], inp.t), inp.t)
    return np.clip(end - start, 0.0, None)


def mean_specific_force(inp: EpochInput) -> tuple[np.ndarray, float] | None:
    """The epoch's time-weighted mean specific force (body frame, m/s²) and the IMU time T (s) it
    covers; None when no sample is in force inside the epoch."""
    dts = hold_intervals(inp)
    T = float(dts.sum())
    if T <= 0:
        return None
    return (np.asarray(inp.accel, float) * dts[:, None]).sum(axis=0) / T, T


def preintegrate(pim: gtsam.PreintegratedCombinedMeasurements, inp: EpochInput) -> gtsam.PreintegratedCombinedMeasurements:
    """Integrate the epoch's samples into ``pim`` (reset by the caller). Returns ``pim``."""
    dts = hold_intervals(inp)
    gyro, acc = inp.gyro, inp.accel
    for j in np.flatnonzero(dts > 1e-9):
        pim.integrateMeasurement(acc[j], gyro[j], float(dts[j]))
    return pim
