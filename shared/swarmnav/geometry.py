"""The rotation library of swarmnav (the only quaternion code outside the gtsam-based estimators).

**Convention**, everywhere in the code base (datasets, wire messages, estimators, simulator):
a quaternion is ``(w, x, y, z)`` — scalar first —, unit norm, Hamilton product, and *active body ->
nav*: ``q`` rotates a body-frame (FLU) vector into the local navigation frame (ENU),
``v_nav = R(q) v_body``; ``q_a ⊗ q_b`` applies ``q_b`` first. Arrays of quaternions have shape
``(..., 4)`` (vectors ``(..., 3)``) and every function broadcasts over the leading axes.
``scipy.spatial.transform.Rotation`` orders ``(x, y, z, w)``; cross only through
:func:`to_rotation` / :func:`from_rotation`.

Implementation: the operations the simulator applies to every IMU sample of every UAV
(``quat_mul``, ``quat_conj``, ``quat_rotate``, ``quat_from_rotvec``, ``quat_to_rotvec``) and
``quat_to_matrix`` (once per range row in calibration) are closed-form numpy: on simulate's
(100 001, 18) arrays they are about 2x faster than ``Rotation`` (which also renormalises and
changes the last bits of every simulated dataset), and a single call costs ~20 µs instead of ~120 µs.
Conversions that are not on a hot path (Euler angles, yaw) go through ``Rotation``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy.spatial is imported where used: it adds ~0.3 s to every simulate/launch start
    from scipy.spatial.transform import Rotation


def _norm(x: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis, keepdims. One vector's norm is computed as
    ``np.linalg.norm(x)`` does (a BLAS dot, whose last bit differs from the axis reduction in ~10 %
    of cases), so single-quaternion results are bit-for-bit those the recorded figures were made with."""
    return np.linalg.norm(x, keepdims=True) if x.ndim == 1 else np.linalg.norm(x, axis=-1, keepdims=True)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, float), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, float), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate = inverse of a unit quaternion."""
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q) v for unit quaternions q (..., 4) and vectors v (..., 3)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_from_rotvec(rv: np.ndarray) -> np.ndarray:
    """Exp map: rotation vector (..., 3) [rad] -> unit quaternion (..., 4)."""
    rv = np.asarray(rv, float)
    th = _norm(rv)
    half = 0.5 * th
    small = th < 1e-8  # sin(th/2)/th by its series for tiny angles
    s = np.where(small, 0.5 - th * th / 48.0, np.sin(half) / np.where(small, 1.0, th))
    return np.concatenate([np.cos(half), rv * s], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Log map: unit quaternion (..., 4) -> rotation vector (..., 3) of the shortest rotation, |·| <= π."""
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    th = 2.0 * np.arctan2(n, q[..., :1])
    small = n < 1e-12
    scale = np.where(small, 2.0 / q[..., :1], th / np.where(small, 1.0, n))
    return v * scale


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of q (normalised first)."""
    q = np.asarray(q, float)
    w, x, y, z = np.moveaxis(q / _norm(q), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def to_rotation(q: np.ndarray) -> Rotation:
    """scipy Rotation(s) of (w, x, y, z) quaternion(s)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, float), scalar_first=True)


def from_rotation(r: Rotation, canonical: bool = False) -> np.ndarray:
    """(w, x, y, z) quaternion(s) of a scipy Rotation; ``canonical``: the sign with w >= 0."""
    return r.as_quat(canonical=canonical, scalar_first=True)


def quat_from_euler_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """q of R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (body FLU -> ENU; yaw from East counter-clockwise)."""
    from scipy.spatial.transform import Rotation

    return from_rotation(Rotation.from_euler("ZYX", [yaw, pitch, roll]))


def yaw_of(q: np.ndarray) -> float:
    """Yaw [rad] of q in the Z-Y-X (yaw, pitch, roll) decomposition: heading of the body x axis
    from East counter-clockwise."""
    return float(to_rotation(q).as_euler("ZYX")[0])


def skew(t: np.ndarray) -> np.ndarray:
    """[t]×: the 3×3 matrix of the cross product t × · (t a 3-vector)."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
