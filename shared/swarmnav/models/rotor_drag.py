"""Rotor drag of a multirotor: the accelerometer's horizontal specific force.

A multirotor's accelerometer measures thrust along the rotor axis plus rotor drag, which opposes
the body-frame horizontal velocity (the model behind multicopter drag fusion in PX4's EKF2;
Leishman et al. 2014, "Quadrotors and accelerometers"). Frames and units: z = the epoch's mean
body-frame (FLU) horizontal specific force f̄_xy (m/s²); state the pose (R body -> ENU), the ENU
velocity v (m/s), the accelerometer bias b_a (m/s², body) and the drag state M = [μ (1/s), c_x,
c_y (m/s²)] — μ the drag coefficient over mass, c the tilt of the IMU against the rotor axis.

    h = −μ·(Rᵀv)_xy + b_a,xy + c,   residual z − h = μ·(Rᵀv)_xy + (f̄ − b_a)_xy − c

Jacobian (right-perturbed pose: ∂(Rᵀv)/∂δφ = [Rᵀv]×): ∂h/∂δφ = −μ[Rᵀv]×_xy, ∂h/∂v = −μRᵀ_xy,
∂h/∂b_a = I_xy, ∂h/∂M = [−(Rᵀv)_xy | I]. Noise: isotropic σ = ``drag_sigma_scale`` × the epoch
mean of the accelerometer's white noise, accel_noise_density/√Δt (:func:`rotor_drag_sigma`).
Used by the per-UAV graph and the oracle (``factors.rotor_drag_factor``).
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register, rotation_of, skew

# σ of the rotor-drag factor = this × the epoch mean of the accelerometer's white noise
# (accel_noise_density/√Δt): the drag model has its own error (unmodelled aerodynamics, IMU lever
# arm, time correlation). 1.5 = the lowest held-out anchor-range error of a truth-free 4-fold
# cross-validation over {1, 1.5, 2, 3} on MILUV (`swarmnav calibrate --dataset DS --grid
# drag_sigma_scale=1,1.5,2,3`, docs/miluv.md "Fifth pass")
DRAG_SIGMA_SCALE = 1.5


def rotor_drag_sigma(params, epoch_s: float, scale: float = DRAG_SIGMA_SCALE) -> float:
    """σ (m/s²) over an epoch of ``epoch_s`` s: ``scale`` × the epoch mean of the accelerometer
    white noise of the preintegration ``params`` (gtsam PreintegrationCombinedParams)."""
    return float(scale) * float(np.sqrt(params.getAccelerometerCovariance()[0, 0] / epoch_s))


def drag_residual(R: np.ndarray, vel: np.ndarray, ba: np.ndarray, m: np.ndarray, fxy: np.ndarray,
                  jacobian: bool = True):
    """Residual z − h (2,) and its Jacobians w.r.t. (pose tangent (2, 6), v (2, 3), bias tangent
    [acc, gyro] (2, 6), M (2, 3)) — the gtsam factor's error and H (None unless ``jacobian``)."""
    vb = R.T @ vel
    e = m[0] * vb[:2] + (fxy - ba[:2]) - m[1:3]
    if not jacobian:
        return e, None
    Hb = np.zeros((2, 6))
    Hb[0, 0] = Hb[1, 1] = -1.0
    return e, [np.hstack([m[0] * skew(vb)[:2], np.zeros((2, 3))]), m[0] * R.T[:2], Hb,
               np.array([[vb[0], -1.0, 0.0], [vb[1], 0.0, -1.0]])]


@register
class RotorDrag(MeasurementModel):
    """x = [pose φ (3), p (3), v (3), b_a (3), b_g (3), μ, c_x, c_y] (18); z = f̄_xy (m/s²)."""

    name = "rotor_drag"
    pose_state = True

    def __init__(self, sigma: float):
        self.sigma = float(sigma)

    def evaluate(self, x):
        return -drag_residual(rotation_of(x), x[6:9], x[9:12], x[15:18], np.zeros(2), jacobian=False)[0]

    def jacobian(self, x):
        _, H = drag_residual(rotation_of(x), x[6:9], x[9:12], x[15:18], np.zeros(2))
        return -np.hstack(H)

    def covariance(self):
        return np.eye(2) * self.sigma ** 2

    @classmethod
    def example(cls, rng):
        x = np.r_[rng.normal(0, 1, 3), rng.normal(0, 20, 3), rng.normal(0, 5, 3), rng.normal(0, 0.1, 6),
                  0.5 + rng.random(), rng.normal(0, 0.3, 2)]
        return cls(0.05), x
