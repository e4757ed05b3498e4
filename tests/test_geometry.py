"""swarmnav.geometry, the one rotation library: its closed forms agree with scipy's Rotation, and the
(w, x, y, z) active body -> nav convention holds."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from swarmnav import geometry as G


def _random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_convention_yaw_90_deg_turns_body_x_to_north():
    q = G.quat_from_euler_zyx(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15)  # (w, x, y, z)
    np.testing.assert_allclose(G.quat_rotate(q, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-15)  # body x -> N
    assert G.yaw_of(q) == np.pi / 2


def test_closed_forms_match_scipy():
    rng = np.random.default_rng(0)
    a, b = _random_quats(rng, 200), _random_quats(rng, 200)
    v = rng.normal(size=(200, 3))
    Ra, Rb = G.to_rotation(a), G.to_rotation(b)
    np.testing.assert_allclose(G.quat_to_matrix(3.0 * a), Ra.as_matrix(), atol=1e-14)  # normalises first
    np.testing.assert_allclose(G.quat_rotate(a, v), Ra.apply(v), atol=1e-14)
    np.testing.assert_allclose(G.quat_to_matrix(G.quat_mul(a, b)), (Ra * Rb).as_matrix(), atol=1e-14)  # b first
    np.testing.assert_allclose(G.quat_to_matrix(G.quat_conj(a)), Ra.inv().as_matrix(), atol=1e-14)
    rv = rng.normal(size=(200, 3))
    np.testing.assert_allclose(G.quat_to_matrix(G.quat_from_rotvec(rv)), Rotation.from_rotvec(rv).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(G.quat_to_rotvec(a), Ra.as_rotvec(), atol=1e-12)  # shortest rotation, |.| <= pi
    np.testing.assert_allclose(G.from_rotation(Ra, canonical=True), a * np.sign(a[:, :1]), atol=1e-15)


def test_exp_log_round_trip_and_tiny_angles():
    rng = np.random.default_rng(1)
    for scale in (1e-12, 1e-9, 1e-3, 0.5):  # |rv| < pi: the log returns it back
        rv = rng.normal(size=(50, 3)) * scale
        q = G.quat_from_rotvec(rv)
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
        np.testing.assert_allclose(G.quat_to_rotvec(q), rv, rtol=1e-9, atol=1e-20)
    one = G.quat_from_rotvec(np.array([0.1, -0.2, 0.3]))  # one vector in, one quaternion out
    assert one.shape == (4,)
    np.testing.assert_allclose(one, G.quat_from_rotvec(np.array([[0.1, -0.2, 0.3]]))[0], atol=1e-16)


def test_euler_zyx_matches_the_matrix_product():
    rng = np.random.default_rng(2)
    for yaw, pitch, roll in rng.uniform(-1.2, 1.2, size=(20, 3)):
        cz, sz, cy, sy, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        q = G.quat_from_euler_zyx(yaw, pitch, roll)
        np.testing.assert_allclose(G.quat_to_matrix(q), Rz @ Ry @ Rx, atol=1e-14)
        assert abs(G.yaw_of(q) - yaw) < 1e-14
