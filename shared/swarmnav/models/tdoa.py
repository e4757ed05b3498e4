"""Passive-listening range difference (TDOA) heard by a listener tag from a two-way exchange.

Frames and units: tag positions ENU (m) — an own tag p + R·t, a neighbour's tag at its broadcast
position plus its rotated lever arm, or an anchor's fixed tag. h = ‖p_resp − p_l‖ − ‖p_init − p_l‖
(m); ∂h/∂p_l = u_i − u_r, ∂h/∂p_init = −u_i, ∂h/∂p_resp = u_r (unit vectors from the listener).
Noise σ (m): the row's σ, else the ranging σ, × ``tdoa_sigma_scale``; the measured value less
the passive path's constant offset ``tdoa_offset_m`` (:func:`tdoa_row`).

Used by the per-UAV graph (own rows: ``factors.tdoa_factor``; cooperative links in the rounds,
:func:`tdoa_h`) and the oracle.
"""

from __future__ import annotations

import numpy as np

from .base import MeasurementModel, register

_EPS = 1e-9


def tdoa_h(p_listener: np.ndarray, p_init: np.ndarray, p_resp: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """h (m) and its Jacobians (each (3,)) w.r.t. the listener, initiator and responder positions."""
    dr = np.asarray(p_resp, float) - np.asarray(p_listener, float)
    di = np.asarray(p_init, float) - np.asarray(p_listener, float)
    rr, ri = float(np.sqrt(dr @ dr)), float(np.sqrt(di @ di))
    ur, ui = dr / max(rr, _EPS), di / max(ri, _EPS)
    return rr - ri, ui - ur, -ui, ur


def tdoa_row(rdiff: float, sigma: float, fallback_sigma: float, sigma_scale: float = 1.0,
             offset_m: float = 0.0) -> tuple[float, float]:
    """(value, σ) in m of one row as the estimators fuse it: the measured rdiff less the passive
    path's offset (``tdoa_offset_m``), and the row's σ (else ``fallback_sigma``, the ranging σ)
    × ``tdoa_sigma_scale``. One place for the per-UAV graph and the oracle."""
    return float(rdiff) - offset_m, sigma_scale * (float(sigma) if sigma > 0 else float(fallback_sigma))


@register
class Tdoa(MeasurementModel):
    """x = [p_listener (3), p_init (3), p_resp (3)] ENU m."""

    name = "tdoa"

    def __init__(self, sigma: float):
        self.sigma = float(sigma)

    def evaluate(self, x):
        return np.array([tdoa_h(x[:3], x[3:6], x[6:9])[0]])

    def jacobian(self, x):
        return np.hstack(tdoa_h(x[:3], x[3:6], x[6:9])[1:])[None]

    def covariance(self):
        return np.array([[self.sigma ** 2]])

    @classmethod
    def example(cls, rng):
        return cls(0.15), rng.normal(0, 20, 9)
