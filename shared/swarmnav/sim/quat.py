"""Vectorised quaternion helpers: arrays of (..., 4) quaternions (w, x, y, z), Hamilton, body -> nav."""

from __future__ import annotations

import numpy as np


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4): R(q) v."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def qexp(rv: np.ndarray) -> np.ndarray:
    """Exp map: rotation vector (..., 3) -> unit quaternion (..., 4)."""
    th = np.linalg.norm(rv, axis=-1, keepdims=True)
    half = 0.5 * th
    # sin(th/2)/th with a series for tiny angles
    small = th < 1e-8
    s = np.where(small, 0.5 - th * th / 48.0, np.sin(half) / np.where(small, 1.0, th))
    return np.concatenate([np.cos(half), rv * s], axis=-1)


def qlog(q: np.ndarray) -> np.ndarray:
    """Log map: unit quaternion (..., 4) -> rotation vector (..., 3), shortest rotation."""
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    th = 2.0 * np.arctan2(n, q[..., :1])
    small = n < 1e-12
    scale = np.where(small, 2.0 / q[..., :1], th / np.where(small, 1.0, n))
    return v * scale
