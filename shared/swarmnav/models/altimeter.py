"""Altimeter (barometer or range finder, as the dataset reports it): height of the body origin.

Frames and units: ENU, up (m). h = p_U = e_Uᵀ p; in gtsam's Pose3 tangent ∂h/∂[δφ, δt] =
[0 | R[2, :]]. Noise σ (m): the dataset's ``altitude_sigma`` (0.1 m when absent).
Used by the per-UAV graph (``factors.altitude_factor``) and, as a prior on the pose's up
component, by the oracle.
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register, rotation_of

DEFAULT_SIGMA_M = 0.1


def height_jacobian(R: np.ndarray) -> np.ndarray:
    """∂h/∂[δφ, δt] (1, 6) at a pose of attitude R."""
    return np.hstack([np.zeros(3), R[2]]).reshape(1, 6)


@register
class Altimeter(MeasurementModel):
    """x = pose [φ (3), p (3)]; z = height (m)."""

    name = "altimeter"
    pose_state = True

    def __init__(self, sigma: float = DEFAULT_SIGMA_M):
        self.sigma = float(sigma)

    def evaluate(self, x):
        return np.array([x[5]], float)

    def jacobian(self, x):
        return height_jacobian(rotation_of(x))

    def covariance(self):
        return np.array([[self.sigma ** 2]])

    @classmethod
    def example(cls, rng):
        return cls(0.1), np.r_[rng.normal(0, 1, 3), rng.normal(0, 20, 3)]
