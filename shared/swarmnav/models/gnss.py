"""GNSS position fix and velocity.

Frames and units: position ENU (m) of the body origin (the antenna lever arm is not modelled),
velocity ENU (m/s). Position: h = p, in gtsam's Pose3 tangent ∂h/∂[δφ, δt] = [0 | R] (the
``GPSFactor``); per-axis σ = ``gnss_sigma_scale`` × √(σ_fix² + ``gnss_extra_var_m2``)
(:func:`position_sigma`: the scale covers a receiver's time-correlated error, which the smoother
would otherwise average as if white). Velocity: h = v, ∂h/∂v = I, isotropic σ (m/s) of the fix.

Used by the per-UAV graph and the oracle (``GPSFactor``, ``PriorFactorVector``); the simulator
draws the fixes' errors (``sim/sensors.gnss_errors``) on the true position.
"""

from __future__ import annotations

import numpy as np

from .base import DirectVelocity, MeasurementModel, register, rotation_of


def position_sigma(sigma_fix, extra_var: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """Per-axis σ (m) the estimators give a fix reported with σ ``sigma_fix`` (m)."""
    return scale * np.sqrt(np.asarray(sigma_fix, float) ** 2 + extra_var)


@register
class GnssPosition(MeasurementModel):
    """x = pose [φ (3), p (3)]; z = p (ENU m)."""

    name = "gnss"
    pose_state = True

    def __init__(self, sigma_fix, extra_var: float = 0.0, scale: float = 1.0):
        self.sigma = position_sigma(sigma_fix, extra_var, scale) * np.ones(3)

    def evaluate(self, x):
        return np.asarray(x[3:6], float).copy()

    def jacobian(self, x):
        return np.hstack([np.zeros((3, 3)), rotation_of(x)])

    def covariance(self):
        return np.diag(self.sigma ** 2)

    @classmethod
    def example(cls, rng):
        return cls([1.5, 1.5, 3.0], 0.1, 2.5), np.r_[rng.normal(0, 1, 3), rng.normal(0, 20, 3)]


@register
class GnssVelocity(DirectVelocity):
    """x = v (ENU m/s); z = v."""

    name = "gnss_velocity"

    @classmethod
    def example(cls, rng):
        return cls(0.2), rng.normal(0, 5, 3)
