"""The neighbourhood's joint snapshot (estimators/joint.py, ``round_solver = "joint"``)."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from swarmnav.estimators import joint
from swarmnav.estimators.settings import validate_tuning
from swarmnav.models.base import wrap_angle


def _problem(seed: int, n: int = 7, max_range_m: float | None = None):
    """n UAVs in a 300 m box with priors, ranges between 70 % of the pairs (only those closer than
    ``max_range_m``: a sparse neighbourhood) and five az/el observations."""
    rng = np.random.default_rng(seed)
    side = 300.0 if max_range_m is None else 300.0 * np.sqrt(n / 7)
    truth = rng.uniform([0, 0, 100], [side, side, 200], (n, 3))
    A = rng.normal(size=(n, 3, 3))
    cov = np.einsum("nij,nkj->nik", A, A) * 0.05 + np.eye(3) * 0.02
    mean = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    ia, ib = np.triu_indices(n, 1)
    keep = rng.random(len(ia)) < 0.7
    if max_range_m is not None:
        keep &= np.linalg.norm(truth[ia] - truth[ib], axis=1) < max_range_m
    ia, ib = ia[keep], ib[keep]
    d = np.linalg.norm(truth[ia] - truth[ib], axis=1) + rng.normal(0, 0.1, len(ia))
    w = rng.uniform(0.2, 1.0, len(ia))
    w[0] = 0.0  # an H0 link
    obs, tgt = np.array([0, 1, 2, 3, 5]), np.array([1, 0, 4, 6, 2])
    dv = truth[tgt] - truth[obs]
    z = np.column_stack([np.arctan2(dv[:, 1], dv[:, 0]), np.arctan2(dv[:, 2], np.hypot(dv[:, 0], dv[:, 1]))])
    z += rng.normal(0, 0.01, z.shape)
    s2 = np.full(len(obs), 0.01 ** 2)
    return truth, mean, np.linalg.inv(cov), ia, ib, d, w, (obs, tgt, z, s2)


@pytest.mark.parametrize("seed, n", [(1, 7), (2, 7), (3, 7), (4, 40), (5, 40)])
def test_joint_solve_is_the_map_of_its_factor_graph(seed, n, monkeypatch):
    """Against an independent solver of the same cost (scipy least_squares on whitened residuals);
    n = 40 sparse (120 unknowns): the block-sparse path (_kernels.joint_step) alone."""
    truth, mean, info, ia, ib, d, w, azel = _problem(seed, n, None if n < 10 else 150.0)
    if 3 * n > joint._SMALL_SYSTEM:
        monkeypatch.setattr(joint, "_dense_step", lambda *a: pytest.fail("the dense fallback ran"))
    obs, tgt, z, s2 = azel
    aw = np.linspace(0.5, 1.0, len(obs))
    Ls = np.linalg.cholesky(info)  # info = L Lᵀ: ‖Lᵀ(x − m)‖² = (x − m)ᵀ info (x − m)

    def residuals(v):
        x = v.reshape(n, 3)
        pr = np.einsum("nji,nj->ni", Ls, x - mean).ravel()
        r = np.linalg.norm(x[ia] - x[ib], axis=1)
        rr = np.sqrt(w / 0.01) * (d - r)
        dv = x[tgt] - x[obs]
        az, el = np.arctan2(dv[:, 1], dv[:, 0]), np.arctan2(dv[:, 2], np.hypot(dv[:, 0], dv[:, 1]))
        ra = np.sqrt(aw / s2)[:, None] * np.column_stack([wrap_angle(z[:, 0] - az), z[:, 1] - el])
        return np.concatenate([pr, rr, ra.ravel()])

    ref = least_squares(residuals, mean.ravel(), xtol=1e-14, ftol=1e-14, gtol=1e-14).x.reshape(n, 3)
    got = joint.solve(mean, info, ia, ib, d, w, 0.01, azel, mean, iterations=20, tol_m=1e-10, azel_w=aw)
    assert np.abs(got - ref).max() < 1e-6
    # and it is better than the priors
    assert np.sqrt(np.mean((got - truth) ** 2)) < np.sqrt(np.mean((mean - truth) ** 2))


def test_joint_snapshot_is_the_fixed_point_of_each_nodes_own_solve():
    """At the joint MAP every node's own-position problem (neighbours fixed there) is solved: its
    gradient vanishes — what the block-Jacobi rounds converge to, reached in one round."""
    truth, mean, info, ia, ib, d, w, azel = _problem(4)
    x = joint.snapshot(mean, info, ia, ib, d, 0.01, azel, lambda p: w, passes=0)
    x = joint.solve(mean, info, ia, ib, d, w, 0.01, azel, x, iterations=20, tol_m=1e-12)
    for i in range(len(x)):  # numerical gradient of the whole cost w.r.t. node i's position only
        def cost(p):
            y = x.copy()
            y[i] = p
            c = (y - mean)[:, None, :] @ info @ (y - mean)[:, :, None]
            r = d - np.linalg.norm(y[ia] - y[ib], axis=1)
            obs, tgt, z, s2 = azel
            dv = y[tgt] - y[obs]
            ra = np.column_stack([wrap_angle(z[:, 0] - np.arctan2(dv[:, 1], dv[:, 0])),
                                  z[:, 1] - np.arctan2(dv[:, 2], np.hypot(dv[:, 0], dv[:, 1]))])
            return 0.5 * (c.sum() + np.sum(w * r * r) / 0.01 + np.sum(ra * ra / s2[:, None]))
        g = [(cost(x[i] + e) - cost(x[i] - e)) / 2e-6 for e in np.eye(3) * 1e-6]
        assert np.abs(g).max() < 1e-3, (i, g)


def test_joint_needs_the_round0_priors():
    with pytest.raises(ValueError, match="round_warm_start = false"):
        validate_tuning({"round_solver": "joint", "round_warm_start": True})
    with pytest.raises(ValueError, match="round_solver"):
        validate_tuning({"round_solver": "jacobi"})
    assert validate_tuning({"round_solver": "joint"}) == {"round_solver": "joint"}


def test_the_c_kernels_normal_equations_are_the_gauss_newton_step_of_the_cost():
    """_kernels.joint_system: g = −½∇cost and H = JᵀWJ of the whitened residuals (J by central
    differences of an independent numpy cost), and H symmetric."""
    from swarmnav.estimators import _kernels

    truth, mean, info, ia, ib, d, w, (obs, tgt, z, s2) = _problem(5)
    n, sig2 = len(mean), 0.01
    aw = np.linspace(0.3, 1.0, len(obs))
    x = mean + 0.5  # away from the priors: every term non-zero
    Ls = np.linalg.cholesky(info)

    def whitened(v):
        y = v.reshape(n, 3)
        pr = np.einsum("nji,nj->ni", Ls, mean - y).ravel()
        rr = np.sqrt(w / sig2) * (d - np.linalg.norm(y[ia] - y[ib], axis=1))
        dv = y[tgt] - y[obs]
        az, el = np.arctan2(dv[:, 1], dv[:, 0]), np.arctan2(dv[:, 2], np.hypot(dv[:, 0], dv[:, 1]))
        ra = np.sqrt(aw / s2)[:, None] * np.column_stack([wrap_angle(z[:, 0] - az), z[:, 1] - el])
        return np.concatenate([pr, rr, ra.ravel()])

    eps = 1e-6
    J = np.column_stack([(whitened(x.ravel() + eps * e) - whitened(x.ravel() - eps * e)) / (2 * eps)
                         for e in np.eye(3 * n)])
    r = whitened(x.ravel())
    H, g = np.empty((3 * n, 3 * n)), np.empty(3 * n)
    _kernels.joint_system(x, mean, info, ia.astype(np.int64), ib.astype(np.int64), d, w / sig2,
                               obs.astype(np.int64), tgt.astype(np.int64), z, aw / s2, H, g)
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(g, -J.T @ r, rtol=1e-5, atol=1e-3)
    assert np.array_equal(H, H.T) or np.abs(H - H.T).max() < 1e-9 * np.abs(H).max()


@pytest.mark.parametrize("seed, n", [(6, 25), (7, 60), (8, 8)])
def test_the_block_sparse_step_is_the_dense_solve(seed, n):
    """_kernels.joint_step (minimum-degree block Cholesky) = H⁻¹g of joint_system's dense H, to
    rounding; an H that is not positive definite is refused with dx untouched."""
    from swarmnav.estimators import _kernels

    truth, mean, info, ia, ib, d, w, (obs, tgt, z, s2) = _problem(seed, n, 120.0)
    x = mean + 0.3
    args = [mean, info, ia.astype(np.int64), ib.astype(np.int64), d, w / 0.01, obs.astype(np.int64),
            tgt.astype(np.int64), z, 1.0 / s2]
    H, g = np.empty((3 * n, 3 * n)), np.empty(3 * n)
    _kernels.joint_system(x, *args, H, g)
    dx = np.empty((n, 3))
    assert _kernels.joint_step(x, *args, dx) is True
    ref = np.linalg.solve(H, g)
    np.testing.assert_allclose(dx.ravel(), ref, rtol=0, atol=1e-11 * np.abs(ref).max())
    args[1] = -info  # negative definite priors: refused, dx untouched
    dx[:] = 7.0
    assert _kernels.joint_step(x, *args, dx) is False and (dx == 7.0).all()


@pytest.mark.parametrize("n", [8, 25])
def test_a_factor_between_a_node_and_itself_adds_nothing_to_either_kernel(n):
    """A range or az/el row whose two ends are the same node cancels in H and g exactly, in the dense
    H (joint_system) as in the block-sparse step (joint_step): the dense and sparse paths of
    joint.solve (either side of _SMALL_SYSTEM) agree on it. (Added term by term, an az/el one left
    O(1) rounding on the dense H_AA: |J| ~ 1e6 at δ = 0.)"""
    from swarmnav.estimators import _kernels

    truth, mean, info, ia, ib, d, w, (obs, tgt, z, s2) = _problem(3, n, 150.0)
    x = mean + 0.3
    args = [mean, info, ia.astype(np.int64), ib.astype(np.int64), d, w / 0.01, obs.astype(np.int64),
            tgt.astype(np.int64), z, 1.0 / s2]
    selfed = list(args)
    selfed[2], selfed[3] = np.r_[args[2], 2], np.r_[args[3], 2]  # a range 2-2
    selfed[4], selfed[5] = np.r_[args[4], 40.0], np.r_[args[5], 100.0]
    selfed[6], selfed[7] = np.r_[args[6], 4, 1], np.r_[args[7], 4, 1]  # az/el 4 -> 4, 1 -> 1
    selfed[8], selfed[9] = np.vstack([args[8], [[0.3, 0.1], [-2.0, 0.4]]]), np.r_[args[9], 1e4, 3e5]
    for a in (args, selfed):
        a[:] = [np.ascontiguousarray(v) for v in a]
    H0, g0, H1, g1 = np.empty((3 * n, 3 * n)), np.empty(3 * n), np.empty((3 * n, 3 * n)), np.empty(3 * n)
    _kernels.joint_system(x, *args, H0, g0)
    _kernels.joint_system(x, *selfed, H1, g1)
    assert np.array_equal(H0, H1) and np.array_equal(g0, g1)
    dx0, dx1 = np.empty((n, 3)), np.empty((n, 3))
    assert _kernels.joint_step(x, *args, dx0) and _kernels.joint_step(x, *selfed, dx1)
    assert np.array_equal(dx0, dx1)


def test_joint_step_refuses_more_nodes_than_its_bookkeeping_allows():
    """Above JOINT_STEP_MAX_NODES (4096) joint_step returns False with dx untouched (its n x n slot
    table would be 4n² bytes and more); at 4096 it still solves (n priors and no factor: dx = μ − x)."""
    from swarmnav.estimators import _kernels

    e_i, e_f = np.zeros(0, np.int64), np.zeros(0)
    for n, solved in ((4096, True), (4097, False)):
        x, mean = np.zeros((n, 3)), np.ones((n, 3))
        info = np.tile(2.0 * np.eye(3), (n, 1, 1))
        dx = np.full((n, 3), 7.0)
        assert _kernels.joint_step(x, mean, info, e_i, e_i, e_f, e_f, e_i, e_i, np.zeros((0, 2)), e_f, dx) is solved
        assert np.allclose(dx, 1.0, rtol=0, atol=1e-15) if solved else (dx == 7.0).all()


def test_the_c_kernel_rejects_bad_arrays_without_touching_memory():
    from swarmnav.estimators import _kernels

    x = np.zeros((2, 3))
    info = np.tile(np.eye(3), (2, 1, 1))
    one, idx = np.ones(1), np.array([0], np.int64)
    H, g = np.empty((6, 6)), np.empty(6)
    none_i, none_f = np.zeros(0, np.int64), np.zeros(0)
    ok = (x, x, info, idx, idx + 1, one, one, none_i, none_i, np.zeros((0, 2)), none_f, H, g)
    _kernels.joint_system(*ok)
    bad = {3: np.array([5], np.int64),        # range end outside the n nodes
           4: np.array([1.0]),                # float indices
           6: np.ones(2),                     # weights of another length
           11: np.empty((5, 5)),              # H of the wrong size
           0: np.zeros((2, 3), np.float32)}   # wrong dtype
    for i, arr in bad.items():
        args = list(ok)
        args[i] = arr
        with pytest.raises(ValueError):
            _kernels.joint_system(*args)
    with pytest.raises((ValueError, TypeError)):  # read-only output
        ro = np.empty(6)
        ro.flags.writeable = False
        _kernels.joint_system(*ok[:12], ro)
    step = list(ok[:11]) + [np.empty((2, 3))]
    _kernels.joint_step(*step)
    for i, arr in {3: np.array([5], np.int64), 11: np.empty((3, 3)), 0: np.zeros((2, 3), np.float32)}.items():
        args = list(step)
        args[i] = arr
        with pytest.raises(ValueError):
            _kernels.joint_step(*args)


def test_the_c_kernels_refuse_aliased_misaligned_or_oversized_buffers(tmp_path):
    """Hostile buffers (found by an outside review): an output that shares memory with an input
    (the indices, checked before H is written, would be overwritten), an array that is not 8-byte
    aligned, and a system whose n*n*8 would overflow. Each raises ValueError; run in a subprocess so
    a crash would show as its exit status."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import numpy as np
        from swarmnav.estimators import _kernels
        fails = []
        def refused(f, *a):
            try:
                f(*a)
            except ValueError:
                return
            fails.append(f.__name__)
        x, info = np.zeros((1, 3)), np.eye(3)[None]
        H = np.empty((3, 3)); g = np.empty(3)
        ia = H.reshape(-1).view(np.int64)  # the indices live inside the output H
        ib = np.zeros(9, np.int64); w = np.ones(9)
        e_i, e_f = np.zeros(0, np.int64), np.zeros(0)
        refused(_kernels.joint_system, x, x, info, ia, ib, w, w, e_i, e_i, np.zeros((0, 2)), e_f, H, g)
        dx = np.empty((1, 3)); ia2 = dx.reshape(-1).view(np.int64)  # the indices inside the output dx
        refused(_kernels.joint_step, x, x, info, ia2, ia2, w[:3], w[:3], e_i, e_i, np.zeros((0, 2)), e_f, dx)
        raw = np.zeros(8 * 4 + 1, np.uint8)[1:].view(np.float64)  # 4 doubles at an odd address
        refused(_kernels.cho_solve, np.eye(2), raw[:2], np.empty(2))
        H2 = 2.0 * np.eye(2)
        refused(_kernels.spd_solve, H2, np.ones(2), H2.reshape(-1)[:2])  # x inside H
        big = np.memmap(r"{tmp_path / 'big.f8'}", np.float64, "w+", shape=(2 ** 31,))  # sparse file
        refused(_kernels.cho_solve, np.zeros((0, 0)), big, big)
        refused(_kernels.spd_solve, np.zeros((0, 0)), big, big)
        print("FAILS", fails)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert "FAILS []" in r.stdout, r.stdout


def test_azel_observations_takes_every_bearing_inside_the_neighbourhood_in_order():
    """Observer in ``nodes`` order, then target; targets outside the neighbourhood, a bearing of
    itself and a node without a state are left out."""
    from swarmnav.estimators.base import NodeState

    rng = np.random.default_rng(7)

    def state(u, targets):
        b = {int(t): (float(rng.uniform(-3, 3)), float(rng.uniform(-1, 1)), 0.01 * (1 + u)) for t in targets}
        return NodeState(u, 3, 0, 3.0, np.zeros(3), np.eye(3), np.zeros(3), bearings=b)

    nodes = [2, 4, 5, 9]
    states = {4: state(4, [9, 2, 7, 4]), 5: state(5, []), 9: state(9, [5, 11]), 12: state(12, [2])}
    own = state(2, [5, 4, 3])
    obs, tgt, z, s2 = joint.azel_observations(nodes, states, own)
    expect = [(2, 4), (2, 5), (4, 2), (4, 9), (9, 5)]  # (observer id, target id)
    assert [(nodes[o], nodes[t]) for o, t in zip(obs, tgt)] == expect
    for (u, t), zz, ss in zip(expect, z, s2):
        az, el, sig = (own if u == 2 else states[u]).bearings[t]
        assert tuple(zz) == (az, el) and ss == sig * sig


@pytest.mark.parametrize("n", [1, 6, 54, 61, 150])
def test_spd_solve_on_both_sides_of_the_small_system_threshold(n):
    """joint._spd_solve (C Cholesky up to _SMALL_SYSTEM unknowns, numpy's Cholesky + C triangular
    solves above) against LU; an indefinite H falls back to LU, a singular one gives NaNs."""
    from swarmnav.estimators import _kernels

    rng = np.random.default_rng(n)
    A = rng.normal(size=(n, n))
    H, g = A @ A.T + n * np.eye(n), rng.normal(size=n)
    np.testing.assert_allclose(joint._spd_solve(H, g), np.linalg.solve(H, g), rtol=1e-10, atol=1e-12)
    x = np.zeros(n)
    assert _kernels.spd_solve(-H, g, x) is False and not x.any()  # indefinite: refused, x untouched
    np.testing.assert_allclose(joint._spd_solve(-H, g), np.linalg.solve(-H, g), rtol=1e-10, atol=1e-12)
    if n > 1:
        assert np.isnan(joint._spd_solve(np.zeros((n, n)), g)).all()


@pytest.mark.parametrize("seed, n", [(6, 25), (7, 60)])
def test_a_plan_gives_the_same_step_bit_for_bit_and_refuses_other_factors(seed, n):
    """joint_step with a joint_plan (the symbolic phase done once per snapshot) = joint_step doing its
    own, bit for bit, at any x and weights; a plan of other factors (another n, another pair, the
    same pairs in another order) or not a plan is refused before anything is written."""
    from swarmnav.estimators import _kernels

    truth, mean, info, ia, ib, d, w, (obs, tgt, z, s2) = _problem(seed, n, 120.0)
    ia, ib, obs, tgt = (np.ascontiguousarray(v, np.int64) for v in (ia, ib, obs, tgt))
    plan = _kernels.joint_plan(n, ia, ib, obs, tgt)
    rng = np.random.default_rng(seed)
    for _ in range(5):
        x = mean + rng.normal(0, 1.0, mean.shape)
        args = [mean, info, ia, ib, d, rng.uniform(0.1, 1, len(d)) / 0.01, obs, tgt, z, 1.0 / s2]
        a, b = np.empty((n, 3)), np.empty((n, 3))
        assert _kernels.joint_step(x, *args, a) is True
        assert _kernels.joint_step(x, *args, b, plan) is True
        assert np.array_equal(a, b)
    others = [_kernels.joint_plan(n + 1, ia, ib, obs, tgt),
              _kernels.joint_plan(n, ia, np.where(ib == ib[0], (ib[0] + 1) % n, ib), obs, tgt),
              _kernels.joint_plan(n, ib, ia, obs, tgt)]
    dx = np.full((n, 3), 7.0)
    for bad in others:
        with pytest.raises(ValueError, match="plan"):
            _kernels.joint_step(x, *args, dx, bad)
    for bad in (None, 3, np.zeros(3)):
        with pytest.raises((ValueError, TypeError)):
            _kernels.joint_step(x, *args, dx, bad)
    assert (dx == 7.0).all()
    with pytest.raises(ValueError):
        _kernels.joint_plan(n, np.r_[ia[:-1], n], ib, obs, tgt)  # an end outside the n nodes
    with pytest.raises(ValueError):
        _kernels.joint_plan(0, ia[:0], ib[:0], obs[:0], tgt[:0])
    with pytest.raises(ValueError):
        _kernels.joint_plan(n, ia, ib[:-1], obs, tgt)  # pairs of two lengths
    assert _kernels.joint_plan(4097, ia, ib, obs, tgt) is None  # joint_step refuses so many nodes
