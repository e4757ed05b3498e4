"""gtsam factors of the measurement models (``swarmnav.models``: h, Jacobians, noise).

The maths lives in ``models/`` (one module per sensor, finite-difference tested once,
generically: tests/test_models.py); here it is wrapped as ``gtsam.CustomFactor``s on ``Point3``
keys or on ``Pose3`` keys (then the position is ``pose.translation()`` and the Jacobian is
``[0 | R]`` in gtsam's Pose3 tangent ordering (rotation, translation)):

- :func:`azel_factor` — relative azimuth/elevation of the paper's eq. 27 **in ENU**
  (``BearingRangeFactorPose3`` measures a body-frame bearing, so it is not eq. 27);
- :func:`range_factor` — range between two unknown positions (central oracle);
- :func:`range_to_point_factor` — range from a pose (with a body lever arm) to a point given
  with an uncertainty (a fixed anchor: covariance 0; a neighbour's broadcast: its covariance is
  folded into the noise along the line of sight, see :func:`effective_range_sigma`);
- :func:`stacked_range_factor` — many ranges to known/uncertain points in one Python callback;
- :func:`tdoa_factor` — a passive-listening range difference (``tdoa_h``) between up to three
  tags on poses or fixed points;
- :func:`altitude_factor`, :func:`rotor_drag_factor` / :func:`rotor_drag_prior`.

The numpy models are re-exported here (``range_h``, ``azel_h``, ``tdoa_h``, ...) for callers
that import them from this module. Residuals are ``h(x) - z`` with the azimuth wrapped.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from ..models.altimeter import height_jacobian
from ..models.anchor_range import pose_ranges
from ..models.base import skew, wrap_angle
from ..models.bearing import azel_h, effective_azel_cov
from ..models.rotor_drag import DRAG_SIGMA_SCALE, drag_residual, rotor_drag_sigma
from ..models.tdoa import tdoa_h, tdoa_row
from ..models.uwb_range import effective_range_sigma, range_h

__all__ = [
    "DRAG_SIGMA_SCALE",
    "rotor_drag_sigma",
    "rotor_drag_prior",
    "rotor_drag_factor",
    "wrap_angle",
    "range_h",
    "azel_h",
    "effective_range_sigma",
    "effective_azel_cov",
    "altitude_factor",
    "azel_factor",
    "range_factor",
    "range_to_point_factor",
    "stacked_range_factor",
    "tdoa_h",
    "tdoa_row",
    "tdoa_factor",
]

_EPS = 1e-9


# -- gtsam glue -----------------------------------------------------------------------------


def _position(v: gtsam.Values, key: int, pose: bool):
    """Position and d(position)/d(tangent) of a Point3 or Pose3 value."""
    if pose:
        P = v.atPose3(key)
        R = P.rotation().matrix()
        return P.translation(), np.hstack([np.zeros((3, 3)), R]), P, R
    return v.atPoint3(key), np.eye(3), None, None


def azel_factor(key_obs: int, key_tgt: int, azimuth: float, elevation: float,
                noise: gtsam.noiseModel.Base, pose: bool = True) -> gtsam.CustomFactor:
    """Eq. 27 relative azimuth/elevation factor between two unknown positions (ENU).

    ``pose=True``: keys are Pose3 (position = translation); otherwise Point3. Error = h − z with
    the azimuth wrapped. ``noise`` is 2-D (az, el) in radians.
    """
    z = np.array([azimuth, elevation], float)

    def err(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None):
        ko, kt = this.keys()[0], this.keys()[1]
        po, Do, *_ = _position(v, ko, pose)
        pt, Dt, *_ = _position(v, kt, pose)
        h, Jo, Jt = azel_h(po, pt)
        e = h - z
        e[0] = wrap_angle(e[0])
        if H is not None:
            H[0] = Jo @ Do
            H[1] = Jt @ Dt
        return e

    return gtsam.CustomFactor(noise, [key_obs, key_tgt], err)


def range_factor(key_i: int, key_j: int, measured: float, noise: gtsam.noiseModel.Base,
                 pose: bool = True) -> gtsam.CustomFactor:
    """Range between two unknown positions (no lever arms). Error = ‖p_i − p_j‖ − z."""

    def err(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None):
        ki, kj = this.keys()[0], this.keys()[1]
        pi, Di, *_ = _position(v, ki, pose)
        pj, Dj, *_ = _position(v, kj, pose)
        r, Ji, Jj = range_h(pi, pj)
        if H is not None:
            H[0] = (Ji @ Di).reshape(1, -1)
            H[1] = (Jj @ Dj).reshape(1, -1)
        return np.array([r - measured])

    return gtsam.CustomFactor(noise, [key_i, key_j], err)


def _lever_jac(R: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """d(p + R t)/d(Pose3 tangent) = [ -R [t]x | R ]."""
    return np.hstack([-R @ skew(lever), R])


def tdoa_factor(ends: Sequence[tuple[int | None, np.ndarray]], measured: float,
                noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Range-difference factor (``tdoa_h``) for the tags of listener, initiator and responder.

    ``ends`` = three (key, vector) pairs in that order: a Pose3 key and the tag's body lever arm,
    or ``None`` and the tag's fixed ENU position (an anchor). Two ends may share a key (a robot's
    two tags). Error = h − z; analytic Jacobians (checked numerically in tests/test_factors.py).
    """
    ends = [(None if k is None else int(k), np.asarray(x, float)) for k, x in ends]
    if len(ends) != 3:
        raise ValueError("tdoa_factor needs (listener, initiator, responder)")
    keys = sorted({k for k, _ in ends if k is not None})
    if not keys:
        raise ValueError("tdoa_factor: every end is fixed")

    def err(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None):
        pts, jac = [], []
        for k, x in ends:
            if k is None:
                pts.append(x)
                jac.append(None)
            else:
                P = v.atPose3(k)
                R = P.rotation().matrix()
                pts.append(P.translation() + R @ x)
                jac.append(_lever_jac(R, x))
        h, *g = tdoa_h(*pts)
        if H is not None:
            for j, kk in enumerate(keys):
                J = np.zeros(6)
                for (k, _), gi, D in zip(ends, g, jac):
                    if k == kk:
                        J += gi @ D
                H[j] = J.reshape(1, 6)
        return np.array([h - measured])

    return gtsam.CustomFactor(noise, keys, err)


def range_to_point_factor(key: int, point: np.ndarray, measured: float, noise: gtsam.noiseModel.Base,
                          lever: np.ndarray | None = None, pose: bool = True) -> gtsam.CustomFactor:
    """Range from the tag at body lever arm ``lever`` on pose ``key`` to a given ENU point.

    The point is a fixed anchor, or a neighbour's broadcast position whose covariance the caller
    has folded into ``noise`` (:func:`effective_range_sigma`). Error = ‖p + R t − a‖ − z.
    """
    a = np.asarray(point, float)
    t = np.zeros(3) if lever is None else np.asarray(lever, float)
    if not pose and np.any(t):
        raise ValueError("a lever arm needs a Pose3 key")

    def err(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None):
        k = this.keys()[0]
        if pose:
            P = v.atPose3(k)
            R = P.rotation().matrix()
            p = P.translation() + R @ t
            D = _lever_jac(R, t)
        else:
            p, D = v.atPoint3(k), np.eye(3)
        r, J, _ = range_h(p, a)
        if H is not None:
            H[0] = (J @ D).reshape(1, -1)
        return np.array([r - measured])

    return gtsam.CustomFactor(noise, [key], err)


def stacked_range_factor(key: int, points: np.ndarray, measured: np.ndarray, sigmas: np.ndarray,
                         levers: np.ndarray | None = None, weights: np.ndarray | None = None) -> gtsam.CustomFactor:
    """N ranges from pose ``key`` (tags at ``levers``) to N given points, in one callback.

    Each row is whitened inside (``sqrt(w) (h − z) / sigma``) so the factor uses a unit noise model;
    ``weights`` are IRLS weights multiplying the squared residual (eq. 24, see detection.py).
    """
    A = np.asarray(points, float).reshape(-1, 3)
    z = np.asarray(measured, float).reshape(-1)
    n = len(z)
    T = np.zeros((n, 3)) if levers is None else np.asarray(levers, float).reshape(-1, 3)
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    scale = np.sqrt(w) / np.asarray(sigmas, float)

    def err(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None):
        P = v.atPose3(this.keys()[0])
        r, J = pose_ranges(P.translation(), P.rotation().matrix(), T, A, jacobian=H is not None)
        if H is not None:
            H[0] = J * scale[:, None]
        return (r - z) * scale

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n), [key], err)


def rotor_drag_prior(key_m: int, mu0: float, mu_sigma: float, f_xy0: np.ndarray, at_rest: bool):
    """Prior on a multirotor's drag state M = [μ, c_x, c_y]: μ0 ± mu_sigma; c = the first epoch's
    mean f_xy ± 0.1 m/s² for a vehicle that starts at rest on its landing gear (the rotor axis is
    then the floor normal), else 0 ± 0.5. Returns (factor, initial value of M)."""
    c0, cs = (np.asarray(f_xy0, float), 0.1) if at_rest else (np.zeros(2), 0.5)
    m0 = np.r_[mu0, c0]
    return gtsam.PriorFactorVector(key_m, m0, gtsam.noiseModel.Diagonal.Sigmas(np.array([mu_sigma, cs, cs]))), m0


def rotor_drag_factor(key_x: int, key_v: int, key_b: int, key_m: int, f_xy: np.ndarray,
                      sigma: float) -> gtsam.CustomFactor:
    """Multirotor rotor-drag factor (models/rotor_drag.py; graph.py, central.py).

    Residual μ(Rᵀv)_xy + (f_xy − b_a,xy) − c on Pose3 ``key_x`` (R), velocity ``key_v`` (ENU),
    ConstantBias ``key_b`` and the drag state ``key_m`` = [μ, c_x, c_y]; ``f_xy`` = the epoch's mean
    body-frame horizontal specific force; isotropic σ (m/s²). Analytic Jacobians (right-perturbed
    pose: d(Rᵀv)/dδθ = [Rᵀv]×), checked against numerical ones in tests/test_graph.py.
    """
    fxy = np.asarray(f_xy, float)[:2].copy()

    def err(this, vals, H):
        k = this.keys()
        e, J = drag_residual(vals.atPose3(k[0]).rotation().matrix(), vals.atVector(k[1]),
                             vals.atConstantBias(k[2]).accelerometer(), vals.atVector(k[3]), fxy, H is not None)
        if H is not None:
            H[0], H[1], H[2], H[3] = J
        return e

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma)), [key_x, key_v, key_b, key_m], err)



def altitude_factor(key: int, height: float, sigma: float) -> gtsam.CustomFactor:
    """Altimeter (models/altimeter.py): height of the body origin of Pose3 ``key``, σ (m)."""

    def err(this, v, H):
        P = v.atPose3(this.keys()[0])
        if H is not None:
            H[0] = height_jacobian(P.rotation().matrix())
        return np.array([P.translation()[2] - height])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, float(sigma)), [key], err)
