"""The own-position solve's normal equations (estimators/rounds.py, C kernel ``own_system``)."""

import numpy as np
import pytest

from swarmnav.estimators import _kernels
from swarmnav.estimators.rounds import Links, normal_equations
from swarmnav.models.base import wrap_angle


def _links(seed: int):
    rng = np.random.default_rng(seed)
    p = rng.uniform([0, 0, 100], [300, 300, 200])
    R, A = 6, 4
    pj = p + rng.normal(0, 80, (R, 3))
    B = rng.normal(size=(R, 3, 3))
    Pj = np.einsum("nij,nkj->nik", B, B) * 0.05 + np.eye(3) * 0.01
    w, lev, sig2 = rng.uniform(0.2, 1, R), rng.normal(0, 0.2, (R, 3)), np.full(R, 0.01)
    z = np.linalg.norm(p + lev - pj, axis=1) + rng.normal(0, 0.3, R)
    pt = p + rng.normal(0, 80, (A, 3))
    C = rng.normal(size=(A, 3, 3))
    Pt = np.einsum("nij,nkj->nik", C, C) * 0.05 + np.eye(3) * 0.01
    wt, st2 = rng.uniform(0.2, 1, A), np.full(A, 1e-4)
    d = pt - p
    zt = np.column_stack([np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))])
    zt += rng.normal(0, 0.02, zt.shape)
    return p, Links(rng=(pj, Pj, w, lev, sig2, z), azel=(pt, Pt, wt, st2, zt))


@pytest.mark.parametrize("seed", [1, 2])
def test_normal_equations_are_the_gauss_newton_step_of_the_links_cost(seed):
    """H = JᵀWJ and g = −JᵀWr of the links' residuals r(p), J by central differences, W the
    weight over the noise with the neighbour's covariance along the Jacobian (held at p)."""
    p, L = _links(seed)
    pj, Pj, w, lev, sig2, z = L.rng
    pt, Pt, wt, st2, zt = L.azel
    info = np.diag([2.0, 3.0, 1.0])
    p_loc = p + np.array([0.3, -0.2, 0.5])

    def res(q):
        rr = z - np.linalg.norm(q + lev - pj, axis=1)
        d = pt - q
        az, el = np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        return rr, np.column_stack([wrap_angle(zt[:, 0] - az), zt[:, 1] - el])

    eps = 1e-6
    cols = [tuple((a - b) / (2 * eps) for a, b in zip(res(p + eps * e), res(p - eps * e))) for e in np.eye(3)]
    Jr = np.column_stack([c[0] for c in cols])                # (R, 3)
    Ja = np.stack([c[1] for c in cols], axis=-1)              # (A, 2, 3)
    var = sig2 + np.einsum("ni,nij,nj->n", Jr, Pj, Jr)        # ∂r/∂p = −u: the same quadratic form
    Ca = np.eye(2) * st2[:, None, None] + Ja @ Pt @ Ja.transpose(0, 2, 1)
    Wa = np.linalg.inv(Ca) * wt[:, None, None]
    rr, ra = res(p)
    H_ref = info + (Jr * (w / var)[:, None]).T @ Jr + np.einsum("mji,mjk,mkl->il", Ja, Wa, Ja)
    g_ref = info @ (p_loc - p) - Jr.T @ (w / var * rr) - np.einsum("mji,mjk,mk->i", Ja, Wa, ra)
    H, g = normal_equations(L, p, info, p_loc)
    np.testing.assert_allclose(H, H_ref, rtol=1e-5)
    np.testing.assert_allclose(g, g_ref, rtol=1e-5, atol=1e-6)


def test_own_system_rejects_inconsistent_arrays():
    p, L = _links(3)
    H, g = np.zeros((3, 3)), np.zeros(3)
    args = [np.asarray(a, float) for a in L.rng] + [np.asarray(a, float) for a in L.azel]
    _kernels.own_system(p, *args, H, g)
    bad = list(args)
    bad[1] = bad[1][:3]  # covariances of 3 links for 6 ranges
    with pytest.raises(ValueError):
        _kernels.own_system(p, *bad, H, g)
    with pytest.raises(ValueError):
        _kernels.own_system(p, *args, np.zeros((2, 2)), g)


def test_own_system_is_built_from_the_measurement_models():
    """The C kernel re-states models/uwb_range.py and models/bearing.py: H and g equal what those
    modules' functions give (ranges, variance_with_peer, azel_jacobians, noise_with_target,
    azel_residuals), so a change to a model that the kernel does not follow fails here."""
    from swarmnav.models.bearing import azel_jacobians, azel_residuals, noise_with_target
    from swarmnav.models.uwb_range import ranges, variance_with_peer

    p, L = _links(4)
    pj, Pj, w, lev, sig2, z = L.rng
    pt, Pt, wt, st2, zt = L.azel
    rr, u = ranges(p + lev - pj)
    a = w / variance_with_peer(sig2, u, Pj)
    az, el, J = azel_jacobians(pt - p)
    Ci = np.linalg.inv(noise_with_target(J, Pt, st2)) * wt[:, None, None]
    res = azel_residuals(zt, az, el)
    H_ref = (u * a[:, None]).T @ u + np.einsum("mji,mjk,mkl->il", J, Ci, J)
    g_ref = u.T @ (a * (z - rr)) - np.einsum("mji,mjk,mk->i", J, Ci, res)
    H, g = np.zeros((3, 3)), np.zeros(3)
    _kernels.own_system(p, *[np.asarray(x, float) for x in L.rng + L.azel], H, g)
    np.testing.assert_allclose(H, H_ref, rtol=1e-12)
    np.testing.assert_allclose(g, g_ref, rtol=1e-12, atol=1e-12)


def _meat_numpy(L: Links, p: np.ndarray, L_true: Links, info) -> np.ndarray:
    """The sandwich meat written out with numpy (the formulas of rounds.link_meat's docstring; what
    the C kernel own_meat replaced): the reference the kernel is held to."""
    meat = np.zeros((3, 3)) if info is None else info.copy()
    if L.rng is not None:
        pj, Pj, w, lev, sig2, _ = L.rng
        d = p + lev - pj
        u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        a = w / (sig2 + np.einsum("ni,nij,nj->n", u, Pj, u))
        Pt_rng = L_true.rng[1]
        if L.rng_group is None:
            meat += (u * (a * a * (sig2 + np.einsum("ni,nij,nj->n", u, Pt_rng, u)))[:, None]).T @ u
        else:
            meat += (u * (a * a * sig2)[:, None]).T @ u
            for g in np.unique(L.rng_group):
                rows = np.flatnonzero(L.rng_group == g)
                G = sum(a[r] * np.outer(u[r], u[r]) for r in rows)
                meat += G @ Pt_rng[rows[0]] @ G
    if L.azel is not None:
        pt, Pt, wt, st2, _ = L.azel
        d = pt - p
        e, n, up = d[:, 0], d[:, 1], d[:, 2]
        h2 = np.maximum(e * e + n * n, 1e-12)
        h, r2 = np.sqrt(h2), h2 + up * up
        J = np.zeros((len(d), 2, 3))
        J[:, 0, 0], J[:, 0, 1] = -n / h2, e / h2
        J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = -e * up / (h * r2), -n * up / (h * r2), h / r2
        I2 = np.eye(2) * st2[:, None, None]
        CiJ = (np.linalg.inv(J @ Pt @ J.transpose(0, 2, 1) + I2) * wt[:, None, None]) @ J
        meat += np.einsum("mji,mjk,mkl->il", CiJ, J @ L_true.azel[1] @ J.transpose(0, 2, 1) + I2, CiJ)
    return meat


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("grouped", [False, True])
def test_the_sandwich_meat_kernel_equals_its_formulas(seed, grouped):
    """rounds.link_meat (C kernel own_meat) against the numpy formulas: ranges with and without
    shared-error groups, az/el, a prior; the 'true' covariances differ from the solved ones."""
    from dataclasses import replace

    from swarmnav.estimators.rounds import link_meat

    rng = np.random.default_rng(seed)
    p, L = _links(seed)
    if grouped:
        L = replace(L, rng_group=np.array([7, 2, 7, 4, 2, 7]))
    pj, Pj, w, lev, sig2, z = L.rng
    pt, Pt, wt, st2, zt = L.azel
    L_true = replace(L, rng=(pj, Pj * rng.uniform(1, 3, (len(w), 1, 1)), w, lev, sig2, z),
                     azel=(pt, Pt * rng.uniform(1, 3, (len(wt), 1, 1)), wt, st2, zt))
    info = np.diag([2.0, 3.0, 1.0])
    for lnk, tru, inf in ((L, L_true, info), (L, L_true, None), (Links(rng=L.rng, rng_group=L.rng_group), L_true, info),
                          (Links(azel=L.azel), L_true, None), (Links(), Links(), info)):
        ref = _meat_numpy(lnk, p, tru, inf)
        got = link_meat(lnk, p, tru, inf)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    # inputs the kernel refuses
    args = [np.ascontiguousarray(a, float) for a in (p, pj, Pj, w, lev, sig2, Pj)]
    bad_group = np.array([0, 1, -1, 0, 0, 0], np.int64)
    with pytest.raises(ValueError):
        _kernels.own_meat(*args, bad_group, *(np.ascontiguousarray(a, float) for a in (pt, Pt, wt, st2, Pt)), np.zeros((3, 3)))
    with pytest.raises(ValueError):
        _kernels.own_meat(*args, np.zeros(2, np.int64), *(np.ascontiguousarray(a, float) for a in (pt, Pt, wt, st2, Pt)),
                          np.zeros((3, 3)))
