"""Zero-velocity pseudo-measurement of a node at rest (the initial rest phase, ``imu.InitialRest``).

Frames and units: velocity ENU (m/s). z = 0, h = v, ∂h/∂v = I, isotropic σ ``zupt_sigma_mps``.
Used by the per-UAV graph and the oracle while a UAV that started at rest is still by its IMU.
"""

from __future__ import annotations

import numpy as np

from .base import DirectVelocity, register


@register
class ZeroVelocity(DirectVelocity):
    """x = v (ENU m/s); z = 0."""

    name = "zero_velocity"

    @classmethod
    def example(cls, rng):
        return cls(0.02), rng.normal(0, 0.05, 3)
