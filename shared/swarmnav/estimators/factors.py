"""Custom measurement models and gtsam factors for cooperative navigation (numpy + gtsam only).

Two layers, same maths:

* **numpy models** ``range_h``, ``azel_h`` (value + Jacobians w.r.t. both ENU positions). The
  distributed estimators' per-round cooperative solve uses these directly (a 3-D Gauss-Newton on the
  node's own position is ~50 µs in numpy, where ~34 Python ``CustomFactor`` linearisations would
  cost ~1 ms per round).
* **gtsam factors** built on them (``CustomFactor``), on ``Point3`` keys or on ``Pose3`` keys (then
  the position is ``pose.translation()`` and the Jacobian is ``[0 | R]`` in gtsam's Pose3 tangent
  ordering (rotation, translation)):

  - :func:`azel_factor` — relative azimuth/elevation of the paper's eq. 27 **in ENU**
    (``BearingRangeFactorPose3`` measures a body-frame bearing, so it is not eq. 27);
  - :func:`range_factor` — range between two unknown positions (central oracle);
  - :func:`range_to_point_factor` — range from a pose (with a body lever arm) to a point given
    with an uncertainty (a fixed anchor: covariance 0; a neighbour's broadcast: its covariance is
    folded into the noise along the line of sight, see :func:`effective_range_sigma`);
  - :func:`stacked_range_factor` — many ranges to known/uncertain points in one Python callback;
  - :func:`tdoa_factor` — a passive-listening range difference (``tdoa_h``) between up to three
    tags on poses or fixed points.

Conventions (dataset.py): azimuth = atan2(N_t - N_o, E_t - E_o) from East, counter-clockwise;
elevation = atan2(U_t - U_o, horizontal distance). Residuals are ``h(x) - z`` with the azimuth
residual wrapped to (-pi, pi].
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

__all__ = [
    "DRAG_SIGMA_SCALE",
    "rotor_drag_sigma",
    "rotor_drag_prior",
    "wrap_angle",
    "range_h",
    "azel_h",
    "effective_range_sigma",
    "effective_azel_cov",
    "azel_factor",
    "range_factor",
    "range_to_point_factor",
    "stacked_range_factor",
    "tdoa_h",
    "tdoa_factor",
]

_EPS = 1e-9


def wrap_angle(a):
    """Wrap to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, float), 2 * np.pi)


# -- numpy models ---------------------------------------------------------------------------


def range_h(p_i: np.ndarray, p_j: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Range ‖p_i − p_j‖ and its Jacobians (1×3 as (3,)) w.r.t. p_i and p_j."""
    d = np.asarray(p_i, float) - np.asarray(p_j, float)
    r = float(np.sqrt(d @ d))
    u = d / max(r, _EPS)
    return r, u, -u


def azel_h(p_obs: np.ndarray, p_tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 27 azimuth/elevation of ``p_tgt`` seen from ``p_obs`` (ENU) and 2×3 Jacobians (obs, tgt)."""
    d = np.asarray(p_tgt, float) - np.asarray(p_obs, float)
    e, n, u = d
    h2 = e * e + n * n
    h = np.sqrt(max(h2, _EPS * _EPS))
    r2 = max(h2 + u * u, _EPS * _EPS)
    az = np.arctan2(n, e)
    el = np.arctan2(u, h)
    # d az / d d = [-n, e, 0] / h^2 ; d el / d d = [-e u, -n u, h^2] / (h r^2)
    Jd = np.array([[-n / (h * h), e / (h * h), 0.0],
                   [-e * u / (h * r2), -n * u / (h * r2), h / r2]])
    return np.array([az, el]), -Jd, Jd


def effective_range_sigma(sigma: float, u: np.ndarray, cov_other: np.ndarray | None) -> float:
    """Range sigma with the other end's position uncertainty marginalised along the line of sight."""
    if cov_other is None:
        return float(sigma)
    return float(np.sqrt(sigma * sigma + u @ cov_other @ u))


def effective_azel_cov(sigma: float, J_tgt: np.ndarray, cov_tgt: np.ndarray | None) -> np.ndarray:
    """2×2 az/el covariance with the target position uncertainty marginalised."""
    c = np.eye(2) * sigma * sigma
    if cov_tgt is not None:
        c = c + J_tgt @ cov_tgt @ J_tgt.T
    return c


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
    t = lever
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.hstack([-R @ tx, R])


def tdoa_row(rdiff: float, sigma: float, fallback_sigma: float, sigma_scale: float = 1.0,
             offset_m: float = 0.0) -> tuple[float, float]:
    """(value, σ) in m of one passive-listening row as the estimators fuse it: the measured rdiff
    less the passive path's offset (``tdoa_offset_m``), and the row's σ (else ``fallback_sigma``,
    the ranging σ) × ``tdoa_sigma_scale``. One place for graph.py and central.py."""
    return float(rdiff) - offset_m, sigma_scale * (float(sigma) if sigma > 0 else float(fallback_sigma))


def tdoa_h(p_listener: np.ndarray, p_init: np.ndarray, p_resp: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Passive-listening range difference ‖p_resp − p_l‖ − ‖p_init − p_l‖ (m) and its Jacobians
    (each (3,)) w.r.t. the listener, initiator and responder ENU positions."""
    dr = np.asarray(p_resp, float) - np.asarray(p_listener, float)
    di = np.asarray(p_init, float) - np.asarray(p_listener, float)
    rr, ri = float(np.sqrt(dr @ dr)), float(np.sqrt(di @ di))
    ur, ui = dr / max(rr, _EPS), di / max(ri, _EPS)
    return rr - ri, ui - ur, -ui, ur


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
        R = P.rotation().matrix()
        tags = P.translation() + T @ R.T  # (n,3)
        d = tags - A
        r = np.sqrt(np.einsum("ij,ij->i", d, d))
        u = d / np.maximum(r, _EPS)[:, None]
        if H is not None:
            # d r / d rot = -u^T R [t]x = (R^T u) x t ... computed as u^T (-R [t]x) per row
            ub = u @ R  # rows: R^T u
            Jrot = np.cross(T, ub)  # u^T(-R[t]x) = -(R^T u)^T [t]x = (t x R^T u)^T
            H[0] = (np.hstack([Jrot, ub]) * scale[:, None])
        return (r - z) * scale

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n), [key], err)


# σ of the rotor-drag factor = this × the epoch mean of the accelerometer's white noise
# (accel_noise_density/√Δt): the drag model has its own error (unmodelled aerodynamics, IMU lever
# arm, time correlation). 1.5 = the lowest held-out anchor-range error of a truth-free 4-fold
# cross-validation over {1, 1.5, 2, 3} on MILUV (`swarmnav calibrate --dataset DS --grid
# drag_sigma_scale=1,1.5,2,3`, docs/miluv.md "Fifth pass")
DRAG_SIGMA_SCALE = 1.5


def rotor_drag_sigma(params, epoch_s: float, scale: float = DRAG_SIGMA_SCALE) -> float:
    """σ (m/s²) of the rotor-drag factor over an epoch of ``epoch_s`` s: ``scale`` × the epoch mean
    of the accelerometer white noise of the preintegration ``params``."""
    return float(scale) * float(np.sqrt(params.getAccelerometerCovariance()[0, 0] / epoch_s))


def rotor_drag_prior(key_m: int, mu0: float, mu_sigma: float, f_xy0: np.ndarray, at_rest: bool):
    """Prior on a multirotor's drag state M = [μ, c_x, c_y]: μ0 ± mu_sigma; c = the first epoch's
    mean f_xy ± 0.1 m/s² for a vehicle that starts at rest on its landing gear (the rotor axis is
    then the floor normal), else 0 ± 0.5. Returns (factor, initial value of M)."""
    c0, cs = (np.asarray(f_xy0, float), 0.1) if at_rest else (np.zeros(2), 0.5)
    m0 = np.r_[mu0, c0]
    return gtsam.PriorFactorVector(key_m, m0, gtsam.noiseModel.Diagonal.Sigmas(np.array([mu_sigma, cs, cs]))), m0


def rotor_drag_factor(key_x: int, key_v: int, key_b: int, key_m: int, f_xy: np.ndarray,
                      sigma: float) -> gtsam.CustomFactor:
    """Multirotor rotor-drag factor (graph.py ``_drag_factor``, central.py).

    Residual μ(Rᵀv)_xy + (f_xy − b_a,xy) − c on Pose3 ``key_x`` (R), velocity ``key_v`` (ENU),
    ConstantBias ``key_b`` and the drag state ``key_m`` = [μ, c_x, c_y]; ``f_xy`` = the epoch's mean
    body-frame horizontal specific force; isotropic σ (m/s²). Analytic Jacobians (right-perturbed
    pose: d(Rᵀv)/dδθ = [Rᵀv]×), checked against numerical ones in tests/test_graph.py.
    """
    fxy = np.asarray(f_xy, float)[:2].copy()

    def err(this, vals, H):
        P = vals.atPose3(this.keys()[0])
        vel = vals.atVector(this.keys()[1])
        ba = vals.atConstantBias(this.keys()[2]).accelerometer()
        m = vals.atVector(this.keys()[3])
        Rm = P.rotation().matrix()
        vb = Rm.T @ vel
        if H is not None:
            sk = np.array([[0.0, -vb[2], vb[1]], [vb[2], 0.0, -vb[0]], [-vb[1], vb[0], 0.0]])
            H[0] = np.hstack([m[0] * sk[:2], np.zeros((2, 3))])
            H[1] = m[0] * Rm.T[:2]
            Hb = np.zeros((2, 6))
            Hb[0, 0] = Hb[1, 1] = -1.0
            H[2] = Hb
            H[3] = np.array([[vb[0], -1.0, 0.0], [vb[1], 0.0, -1.0]])
        return m[0] * vb[:2] + (fxy - ba[:2]) - m[1:3]

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma)), [key_x, key_v, key_b, key_m], err)

