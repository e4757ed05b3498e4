"""Relative azimuth/elevation of a neighbour (the paper's eq. 27), in ENU.

Frames and units: positions ENU (m); azimuth = atan2(N_t − N_o, E_t − E_o) from East,
counter-clockwise, in (−π, π]; elevation = atan2(U_t − U_o, horizontal distance) in [−π/2, π/2]
(rad). Noise: independent σ (rad) on each angle. With d = p_tgt − p_obs = (e, n, u), h² = e² + n²,
r² = h² + u²: ∂az/∂d = [−n, e, 0]/h², ∂el/∂d = [−e·u, −n·u, h²]/(h·r²); ∂/∂p_obs = −∂/∂d.
Residuals z − h wrap the azimuth. The far end's covariance P folds into the noise: C = σ²I + J P Jᵀ.

Used by the simulator (``sim/sensors.simulate_rel``: :func:`azimuth_elevation`), the rounds
(:func:`azel_jacobians` over every link at once) and the gtsam factors (``factors.azel_factor``).
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register, wrap_angle

_EPS = 1e-9


def azimuth_elevation(p_obs: np.ndarray, p_tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h: (azimuth, elevation) of p_tgt seen from p_obs (rad; broadcasts over leading axes)."""
    d = np.asarray(p_tgt, float) - np.asarray(p_obs, float)
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return az, el


def azel_jacobians(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """h and its Jacobian for N links at once: d (N, 3) = p_tgt − p_obs (m) ->
    (az (N,), el (N,), J (N, 2, 3) = ∂(az, el)/∂p_tgt = −∂(az, el)/∂p_obs)."""
    e, nn, uu = d[:, 0], d[:, 1], d[:, 2]
    h2 = np.maximum(e * e + nn * nn, 1e-12)
    h = np.sqrt(h2)
    r2 = h2 + uu * uu
    neg_n, hr2 = -nn, h * r2
    J = np.empty((len(e), 2, 3))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = neg_n / h2, e / h2, 0.0
    J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = -e * uu / hr2, neg_n * uu / hr2, h / r2
    return np.arctan2(nn, e), np.arctan2(uu, h), J


def noise_with_target(J: np.ndarray, P: np.ndarray, sig2: np.ndarray) -> np.ndarray:
    """C = J P Jᵀ + σ² I (N, 2, 2): the angles' covariance with the target's position covariance
    P (N, 3, 3) marginalised (rad²)."""
    C = (J @ P) @ J.transpose(0, 2, 1)  # two stacked matmuls: ~4x cheaper than one 3-operand einsum
    C[:, 0, 0] += sig2
    C[:, 1, 1] += sig2
    return C


def azel_h(p_obs: np.ndarray, p_tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One observation: (az, el) and its 2×3 Jacobians w.r.t. p_obs and p_tgt (gtsam factors)."""
    d = np.asarray(p_tgt, float) - np.asarray(p_obs, float)
    e, n, u = d
    h2 = e * e + n * n
    h = np.sqrt(max(h2, _EPS * _EPS))
    r2 = max(h2 + u * u, _EPS * _EPS)
    Jd = np.array([[-n / (h * h), e / (h * h), 0.0],
                   [-e * u / (h * r2), -n * u / (h * r2), h / r2]])
    return np.array([np.arctan2(n, e), np.arctan2(u, h)]), -Jd, Jd


def effective_azel_cov(sigma: float, J_tgt: np.ndarray, cov_tgt: np.ndarray | None) -> np.ndarray:
    """2×2 az/el covariance (rad²) with the target position covariance marginalised."""
    c = np.eye(2) * sigma * sigma
    if cov_tgt is not None:
        c = c + J_tgt @ cov_tgt @ J_tgt.T
    return c


@register
class Bearing(MeasurementModel):
    """x = [p_obs (3), p_tgt (3)] ENU m; z = (azimuth, elevation) rad."""

    name = "bearing"
    angle_rows = (0,)

    def __init__(self, sigma: float):
        self.sigma = float(sigma)

    def evaluate(self, x):
        return np.array(azimuth_elevation(x[:3], x[3:6]), float)

    def jacobian(self, x):
        J = azel_jacobians((x[3:6] - x[:3])[None])[2][0]
        return np.hstack([-J, J])

    def covariance(self):
        return np.eye(2) * self.sigma ** 2

    @classmethod
    def example(cls, rng):
        return cls(np.deg2rad(1.0)), rng.normal(0, 20, 6)


def azel_residuals(z: np.ndarray, az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """z − h (N, 2) of N observations z (N, 2) = (az, el) rad, the azimuth wrapped."""
    res = np.empty((len(az), 2))
    res[:, 0] = wrap_angle(z[:, 0] - az)
    res[:, 1] = z[:, 1] - el
    return res
