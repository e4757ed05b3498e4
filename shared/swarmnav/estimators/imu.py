"""IMU preintegration shared by every gtsam-based estimator (and the FKF propagation).

Noise model: continuous-time densities from the dataset's :class:`ImuNoise` (SI). Earth model:
ENU navigation frame, gravity [0, 0, -g] and Earth rotation at the origin latitude given to gtsam
as ``n_gravity`` / ``omegaCoriolis`` (the Earth model of sim/earth.py).

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


class InitialRest:
    """IMU-only detector of a node's initial rest phase (it starts on the ground, at rest).

    ``active`` starts True when the node is known to start at rest and turns False, for good, at
    the first epoch whose IMU shows motion: within the epoch the gyro-norm and specific-force-norm
    spreads (rad/s, m/s²) are above ``gyro_std`` / ``accel_std``, the mean rate above ``gyro_std``
    or |mean |f| − g| above 3·``accel_std``; or, across epochs, the velocity change (m/s)
    integrated from the specific force relative to the first epoch's mean exceeds ``max_speed``
    (a smooth acceleration has no spread but shows there). While active, the estimators hold a
    zero-velocity prior and keep the rotor-drag factor off (ground contact, not drag).
    """

    def __init__(self, active: bool, gravity_mps2: float, gyro_std: float = 0.01, accel_std: float = 0.1,
                 max_speed: float = 0.1, zupt_sigma: float = 0.02):
        self.active = bool(active)
        self.g0, self.gyro_std, self.accel_std, self.max_speed = float(gravity_mps2), gyro_std, accel_std, max_speed
        self.zupt_sigma = float(zupt_sigma)  # m/s, σ of the zero-velocity prior (prior)
        self._f0: np.ndarray | None = None
        self._dv = np.zeros(3)

    @classmethod
    def from_settings(cls, t, init_vel: np.ndarray, init_vel_sigma: float, gravity_mps2: float) -> "InitialRest":
        """The estimators' detector (``t``: the typed tuning, settings.EstimatorTuning): active when ``initial_rest_zupt`` (default on) and the node's
        initial velocity and its σ are both ≤ ``rest_max_speed_mps`` (0.1); thresholds
        ``rest_gyro_std`` (0.01 rad/s) and ``rest_accel_std`` (0.1 m/s²); prior σ ``zupt_sigma_mps``
        (0.02 m/s)."""
        vmax = t.rest_max_speed_mps
        active = (t.initial_rest_zupt and float(init_vel_sigma) <= vmax
                  and float(np.linalg.norm(init_vel)) <= vmax)
        return cls(active, gravity_mps2, t.rest_gyro_std, t.rest_accel_std, vmax,
                   t.zupt_sigma_mps)

    def update(self, inp: EpochInput) -> bool:
        """Feed one epoch's IMU samples; returns ``active`` after it."""
        if self.active and not self._still(inp):
            self.active = False
        return self.active

    def prior(self, key_v: int) -> gtsam.NonlinearFactor:
        """The zero-velocity prior on velocity key ``key_v`` (added while ``active``)."""
        return gtsam.PriorFactorVector(key_v, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, self.zupt_sigma))

    def _still(self, inp: EpochInput) -> bool:
        if len(inp.gyro) < 2:
            return True
        wn = np.linalg.norm(inp.gyro, axis=1)
        fn = np.linalg.norm(inp.accel, axis=1)
        if not (wn.std() < self.gyro_std and wn.mean() < self.gyro_std
                and fn.std() < self.accel_std and abs(fn.mean() - self.g0) < 3 * self.accel_std):
            return False
        f = np.asarray(inp.accel, float)
        if self._f0 is None:
            self._f0 = f.mean(axis=0)
        dt = np.diff(np.r_[np.asarray(inp.imu_t, float), float(inp.t)])
        self._dv = self._dv + ((f - self._f0) * dt[:, None]).sum(axis=0)
        return bool(np.linalg.norm(self._dv) < self.max_speed)
