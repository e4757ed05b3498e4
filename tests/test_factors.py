"""Every custom factor's Jacobian against central finite differences (on the gtsam manifold)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from swarmnav.estimators import factors as F

X = gtsam.symbol_shorthand.X
P = gtsam.symbol_shorthand.P


def _retract(v: gtsam.Values, key: int, delta: np.ndarray, pose: bool) -> gtsam.Values:
    out = gtsam.Values(v)
    if pose:
        out.update(key, v.atPose3(key).retract(delta))
    else:
        out.update(key, v.atPoint3(key) + delta)
    return out


def _check_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values, pose_keys: dict[int, bool], tol=1e-5):
    lin = factor.linearize(values)
    A, b = lin.jacobian()  # whitened [A_1 | A_2 ...], b = -whitened error
    e0 = factor.whitenedError(values) if hasattr(factor, "whitenedError") else -b
    np.testing.assert_allclose(-b, e0, atol=1e-9)
    col = 0
    h = 1e-6
    for key in factor.keys():
        pose = pose_keys[key]
        dim = 6 if pose else 3
        num = np.zeros((len(b), dim))
        for c in range(dim):
            d = np.zeros(dim)
            d[c] = h
            ep = factor.whitenedError(_retract(values, key, d, pose))
            em = factor.whitenedError(_retract(values, key, -d, pose))
            num[:, c] = (ep - em) / (2 * h)
        np.testing.assert_allclose(A[:, col:col + dim], num, atol=tol, rtol=1e-4)
        col += dim


def _pose(rng):
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.5, 3)), rng.normal(0, 50, 3))


@pytest.mark.parametrize("pose", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_azel_factor_jacobian(pose, seed):
    rng = np.random.default_rng(seed)
    v = gtsam.Values()
    for k in (X(0), X(1)):
        if pose:
            v.insert(k, _pose(rng))
        else:
            v.insert(k, rng.normal(0, 50, 3))
    noise = gtsam.noiseModel.Isotropic.Sigma(2, np.deg2rad(1.0))
    f = F.azel_factor(X(0), X(1), 0.3, -0.1, noise, pose=pose)
    _check_jacobians(f, v, {X(0): pose, X(1): pose}, tol=1e-4)


def test_azel_residual_wraps_and_matches_geometry():
    v = gtsam.Values()
    v.insert(P(0), np.array([0.0, 0.0, 0.0]))
    v.insert(P(1), np.array([-100.0, -1e-3, 10.0]))  # azimuth just below -pi
    az = np.arctan2(-1e-3, -100.0)
    el = np.arctan2(10.0, 100.0)
    f = F.azel_factor(P(0), P(1), np.pi - 1e-6, el, gtsam.noiseModel.Unit.Create(2), pose=False)
    e = f.unwhitenedError(v)
    assert abs(e[0] - F.wrap_angle(az - (np.pi - 1e-6))) < 1e-12
    assert abs(e[0]) < 1e-4 and abs(e[1]) < 1e-9


@pytest.mark.parametrize("pose", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_range_factor_jacobian(pose, seed):
    rng = np.random.default_rng(10 + seed)
    v = gtsam.Values()
    for k in (X(0), X(1)):
        v.insert(k, _pose(rng) if pose else rng.normal(0, 50, 3))
    f = F.range_factor(X(0), X(1), 80.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.1), pose=pose)
    _check_jacobians(f, v, {X(0): pose, X(1): pose})


@pytest.mark.parametrize("seed", range(3))
def test_range_to_point_factor_jacobian_with_lever(seed):
    rng = np.random.default_rng(20 + seed)
    v = gtsam.Values()
    v.insert(X(0), _pose(rng))
    f = F.range_to_point_factor(X(0), rng.normal(0, 50, 3), 60.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.2),
                                lever=np.array([0.3, -0.2, 0.1]))
    _check_jacobians(f, v, {X(0): True})


@pytest.mark.parametrize("seed", range(3))
def test_stacked_range_factor_jacobian_and_value(seed):
    rng = np.random.default_rng(30 + seed)
    v = gtsam.Values()
    pose = _pose(rng)
    v.insert(X(0), pose)
    n = 5
    pts = rng.normal(0, 80, (n, 3))
    levers = rng.normal(0, 0.3, (n, 3))
    z = rng.uniform(20, 100, n)
    sig = rng.uniform(0.1, 2.0, n)
    w = rng.uniform(0.1, 1.0, n)
    f = F.stacked_range_factor(X(0), pts, z, sig, levers, w)
    _check_jacobians(f, v, {X(0): True})
    R = pose.rotation().matrix()
    r = np.linalg.norm(pose.translation() + levers @ R.T - pts, axis=1)
    np.testing.assert_allclose(f.unwhitenedError(v), np.sqrt(w) * (r - z) / sig, atol=1e-10)


def test_numpy_models_match_finite_differences():
    rng = np.random.default_rng(5)
    for _ in range(5):
        a, b = rng.normal(0, 50, 3), rng.normal(0, 50, 3)
        h, Ja, Jb = F.azel_h(a, b)
        r, Ra, Rb = F.range_h(a, b)
        for c in range(3):
            d = np.zeros(3)
            d[c] = 1e-6
            num_a = (F.azel_h(a + d, b)[0] - F.azel_h(a - d, b)[0]) / 2e-6
            num_b = (F.azel_h(a, b + d)[0] - F.azel_h(a, b - d)[0]) / 2e-6
            np.testing.assert_allclose(Ja[:, c], num_a, atol=1e-7)
            np.testing.assert_allclose(Jb[:, c], num_b, atol=1e-7)
            assert abs(Ra[c] - (F.range_h(a + d, b)[0] - F.range_h(a - d, b)[0]) / 2e-6) < 1e-7
            assert abs(Rb[c] - (F.range_h(a, b + d)[0] - F.range_h(a, b - d)[0]) / 2e-6) < 1e-7


def test_effective_sigma_marginalises_line_of_sight():
    u = np.array([1.0, 0.0, 0.0])
    cov = np.diag([4.0, 100.0, 100.0])
    assert F.effective_range_sigma(0.1, u, cov) == pytest.approx(np.sqrt(0.01 + 4.0))
    assert F.effective_range_sigma(0.1, u, None) == pytest.approx(0.1)


@pytest.mark.parametrize("layout", ["three_poses", "own_tags_and_anchor", "anchor_pair"])
@pytest.mark.parametrize("seed", range(3))
def test_tdoa_factor_jacobian_and_value(layout, seed):
    """Passive range difference: listener, initiator, responder on poses (levers) or fixed points;
    two ends on one key (a robot's two tags) add up in its Jacobian."""
    rng = np.random.default_rng(40 + seed)
    v = gtsam.Values()
    poses = {k: _pose(rng) for k in (X(0), X(1), X(2))}
    lev = rng.normal(0, 0.3, (3, 3))
    fixed = rng.normal(0, 50, (3, 3))
    ends = {"three_poses": [(X(0), lev[0]), (X(1), lev[1]), (X(2), lev[2])],
            "own_tags_and_anchor": [(X(0), lev[0]), (None, fixed[1]), (X(0), lev[2])],
            "anchor_pair": [(X(0), lev[0]), (None, fixed[1]), (None, fixed[2])]}[layout]
    for k, _ in ends:
        if k is not None and not v.exists(k):
            v.insert(k, poses[k])
    f = F.tdoa_factor(ends, 3.0, gtsam.noiseModel.Isotropic.Sigma(1, 0.2))
    _check_jacobians(f, v, {k: True for k in f.keys()})
    pts = [x if k is None else poses[k].translation() + poses[k].rotation().matrix() @ x for k, x in ends]
    expected = np.linalg.norm(pts[2] - pts[0]) - np.linalg.norm(pts[1] - pts[0])
    np.testing.assert_allclose(f.unwhitenedError(v), [expected - 3.0], atol=1e-10)


def test_tdoa_h_matches_finite_differences():
    rng = np.random.default_rng(6)
    for _ in range(5):
        p = rng.normal(0, 20, (3, 3))
        h, *J = F.tdoa_h(*p)
        for e in range(3):
            for c in range(3):
                d = np.zeros((3, 3))
                d[e, c] = 1e-6
                num = (F.tdoa_h(*(p + d))[0] - F.tdoa_h(*(p - d))[0]) / 2e-6
                assert abs(J[e][c] - num) < 1e-7
