"""UWB two-way range between two tags on two nodes (inter-UAV ranging).

Frames and units: positions ENU (m); a tag's lever arm rotated into ENU by its body's attitude.
h = ‖(p_i + l_i) − (p_j + l_j)‖ (m), the distance between the tags; noise σ (m), the dataset's
ranging σ (a row's own σ when given). ∂h/∂p_i = uᵀ, ∂h/∂p_j = −uᵀ with u the unit vector j → i.
A neighbour's position known only as a broadcast N(p_j, P_j) folds into the noise along the line
of sight: σ_eff² = σ² + uᵀP_j u (:func:`variance_with_peer`, "factor to an uncertain neighbour").

Used by the simulator (``sim/sensors.simulate_uwb``: :func:`distance`), the per-UAV rounds
(``estimators/rounds.py``: :func:`ranges` over every link at once) and the oracle's factors.
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register

_EPS = 1e-9


def distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """h: ‖a − b‖ over the last axis (m) — the simulator's true range."""
    return np.linalg.norm(np.asarray(a, float) - np.asarray(b, float), axis=-1)


def ranges(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h and its Jacobian for N links at once: d (N, 3) = tag_i − tag_j (m) -> (r (N,), u (N, 3)),
    r = ‖d‖ and u = ∂r/∂p_i = d/r (= −∂r/∂p_j)."""
    r = np.sqrt(np.einsum("ij,ij->i", d, d))
    return r, d / np.maximum(r, _EPS)[:, None]


def variance_with_peer(sig2: np.ndarray, u: np.ndarray, P: np.ndarray) -> np.ndarray:
    """σ² + uᵀPu per link (m²): the ranging variance with the far end's position covariance
    P (N, 3, 3) marginalised along the line of sight u (N, 3)."""
    return sig2 + np.einsum("ni,nij,nj->n", u, P, u)


def range_h(p_i: np.ndarray, p_j: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """One range ‖p_i − p_j‖ (m) and its Jacobians (3,) w.r.t. p_i and p_j."""
    d = np.asarray(p_i, float) - np.asarray(p_j, float)
    r = float(np.sqrt(d @ d))
    u = d / max(r, _EPS)
    return r, u, -u


def effective_range_sigma(sigma: float, u: np.ndarray, cov_other: np.ndarray | None) -> float:
    """Range σ (m) with the other end's position covariance marginalised along the line of sight."""
    if cov_other is None:
        return float(sigma)
    return float(np.sqrt(sigma * sigma + u @ cov_other @ u))


@register
class UwbRange(MeasurementModel):
    """x = [p_i (3), p_j (3)] ENU m; ``lever_i``, ``lever_j`` the tags' ENU offsets (m)."""

    name = "uwb_range"

    def __init__(self, sigma: float, lever_i=(0.0, 0.0, 0.0), lever_j=(0.0, 0.0, 0.0)):
        self.sigma = float(sigma)
        self.lever_i, self.lever_j = np.asarray(lever_i, float), np.asarray(lever_j, float)

    def evaluate(self, x):
        return np.atleast_1d(distance(x[:3] + self.lever_i, x[3:6] + self.lever_j))

    def jacobian(self, x):
        _, u = ranges((x[:3] + self.lever_i - x[3:6] - self.lever_j)[None])
        return np.hstack([u, -u])

    def covariance(self):
        return np.array([[self.sigma ** 2]])

    @classmethod
    def example(cls, rng):
        return cls(0.1, rng.normal(0, 0.2, 3), rng.normal(0, 0.2, 3)), rng.normal(0, 20, 6)
