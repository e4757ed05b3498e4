"""UWB range from one of the node's own tags to a known point (a fixed anchor).

Frames and units: pose (R body FLU -> ENU, p ENU m), tag lever arm t in the body frame (m), anchor
position a ENU (m). h = ‖p + R·t − a‖ (m); noise σ (m), the row's σ else the dataset's ranging σ,
under a robust kernel in the per-UAV graph (``anchor_kernel``). Jacobian in gtsam's Pose3 tangent
[δφ, δt] (models/base.py): with u = (p + R t − a)/h, ∂h/∂δφ = (t × Rᵀu)ᵀ, ∂h/∂δt = (Rᵀu)ᵀ.
A range taken at t_r inside an epoch at t is fused with the anchor moved by v·(t − t_r)
(``anchor_time_shift``; the caller moves ``a``).

Used by the per-UAV graph (``factors.stacked_range_factor``: :func:`pose_ranges` over every row at
once) and the oracle (``factors.range_to_point_factor``).
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register, rotation_of

_EPS = 1e-9


def pose_ranges(p: np.ndarray, R: np.ndarray, levers: np.ndarray, points: np.ndarray,
                jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """h and its Jacobian for N rows at once: ranges (N,) from the tags at body ``levers`` (N, 3)
    of pose (R, p) to ``points`` (N, 3), and ∂h/∂[δφ, δt] (N, 6) (None unless ``jacobian``)."""
    d = p + levers @ R.T - points
    r = np.sqrt(np.einsum("ij,ij->i", d, d))
    if not jacobian:
        return r, None
    u = d / np.maximum(r, _EPS)[:, None]
    ub = u @ R  # rows: Rᵀu
    return r, np.hstack([np.cross(levers, ub), ub])


@register
class AnchorRange(MeasurementModel):
    """x = pose [φ (3), p (3)]; ``anchor`` ENU m, ``lever`` body m."""

    name = "anchor_range"
    pose_state = True

    def __init__(self, anchor, sigma: float, lever=(0.0, 0.0, 0.0)):
        self.anchor, self.sigma, self.lever = np.asarray(anchor, float), float(sigma), np.asarray(lever, float)

    def evaluate(self, x):
        return pose_ranges(x[3:6], rotation_of(x), self.lever[None], self.anchor[None], jacobian=False)[0]

    def jacobian(self, x):
        return pose_ranges(x[3:6], rotation_of(x), self.lever[None], self.anchor[None])[1]

    def covariance(self):
        return np.array([[self.sigma ** 2]])

    @classmethod
    def example(cls, rng):
        return cls(rng.normal(0, 20, 3), 0.1, rng.normal(0, 0.3, 3)), np.r_[rng.normal(0, 1, 3), rng.normal(0, 20, 3)]
