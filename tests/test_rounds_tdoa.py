"""The tdoa links of the own-position solve in C (kernels ``own_tdoa``, ``tdoa_res``; rounds.py
``prepare_links`` / ``normal_equations`` / ``tdoa_residuals``) against the per-row numpy code they
replaced, bit for bit: the relink window re-solves every tdoa row of the last relink_s seconds
each epoch, which made that per-row Python loop the cost of dense passive listening."""

import numpy as np
import pytest

from swarmnav.estimators import _kernels
from swarmnav.estimators.rounds import (Links, RoundCache, TdoaLinks, normal_equations, prepare_links, tdoa_residuals,
                                        tdoa_residuals_py)


def _cache(seed: int, n_rows: int = 40):
    """A round cache of 4 live nodes (index 0 = this node) with tdoa rows of every end pattern:
    own tag(s), neighbours' tags (two ends on one neighbour too), anchors."""
    rng = np.random.default_rng(seed)
    nodes = [1, 2, 3, 4]
    c = RoundCache(key=(), k=7, nodes=nodes, idx={u: i for i, u in enumerate(nodes)}, pairs=None, mine=[], mine_other=[],
                   nb=[2, 3, 4], rng_owner=np.zeros(0, int), rng_node=np.zeros(0, int))
    anchors = rng.uniform(-5, 5, (6, 3))
    for _ in range(n_rows):
        ends = []
        pattern = rng.integers(0, 4)
        for e in range(3):
            if e == 0 or (pattern == 1 and e == 1):
                ends.append(("self", rng.normal(0, 0.2, 3), None))
            elif pattern == 2 and e == 2:
                ends.append(("fixed", anchors[rng.integers(0, 6)], None))
            else:
                j = 1 + (rng.integers(0, 3) if pattern != 3 else 1)  # pattern 3: both peer ends on node index 2
                ends.append(("peer", int(j), rng.normal(0, 0.2, 3)))
        rng.shuffle(ends)
        c.tdoa.append((ends, float(rng.normal(0, 2)), float(rng.uniform(0.01, 0.05))))
    P = rng.normal(0, 4, (4, 3))
    B = rng.normal(size=(4, 3, 3))
    C = np.einsum("nij,nkj->nik", B, B) * 0.05 + np.eye(3) * 0.01
    w = np.where(rng.random(n_rows) < 0.2, 0.0, rng.uniform(0.1, 1.0, n_rows))
    return c, P, C, w


def _legacy_links(c, P, C, w, infl):
    """prepare_links' tdoa part before the C kernel: a list of ([(kind, x, Cov)], z, σ², w) rows."""
    per_node = callable(infl)
    return Links(tdoa=[([(kind, P[x] + lev, C[x] * (infl(c.nodes[x]) if per_node else infl))
                         if kind == "peer" else (kind, x, None) for kind, x, lev in ends], z, sig2, wk)
                       for (ends, z, sig2), wk in zip(c.tdoa, w) if wk > 0])


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_tdoa_normal_equations_bit_identical_to_numpy(seed):
    c, P, C, w = _cache(seed)
    p = P[0] + np.array([0.1, -0.2, 0.05])
    info = np.diag([2.0, 3.0, 1.0])
    p_loc = p + np.array([0.3, -0.2, 0.5])
    for infl in (0.5, lambda u: 1.0 + 0.1 * u):
        L = prepare_links(c, P, C, {}, w, infl)
        Lt = prepare_links(c, P, C, {}, w, 1.0)
        assert isinstance(L.tdoa, TdoaLinks) and len(L.tdoa) == int((w > 0).sum())
        ref, ref_t = _legacy_links(c, P, C, w, infl), _legacy_links(c, P, C, w, 1.0)
        for a, b in ((normal_equations(L, p), normal_equations(ref, p)),
                     (normal_equations(L, p, info, p_loc), normal_equations(ref, p, info, p_loc)),
                     (normal_equations(L, p, info, p_loc, L_true=Lt), normal_equations(ref, p, info, p_loc, L_true=ref_t))):
            for x, y in zip(a, b):
                assert np.array_equal(x, y), (x, y)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_tdoa_residuals_bit_identical_to_numpy(seed):
    c, P, C, _ = _cache(seed)
    me = P[0] + np.array([0.1, -0.2, 0.05])
    P_own = C[0] * 0.7
    for args in ((), (C, P_own)):
        for normalise in (True, False):
            assert np.array_equal(tdoa_residuals(c, P, me, *args, normalise=normalise),
                                  tdoa_residuals_py(c, P, me, *args, normalise=normalise))


def test_tdoa_arrays_follow_the_rows():
    c, P, C, w = _cache(5, 3)
    first = c.tdoa_arrays()
    assert c.tdoa_arrays() is first  # cached
    c.tdoa.append(c.tdoa[0])
    assert len(c.tdoa_arrays()[3]) == 4  # rebuilt when rows were added


def test_tdoa_kernels_reject_inconsistent_arrays():
    z3 = np.zeros(3)
    with pytest.raises(ValueError):
        _kernels.own_tdoa(z3, np.zeros((2, 3), np.int64), np.zeros((2, 3, 3)), np.zeros((2, 3, 3, 3)), np.zeros(2),
                          np.zeros(2), np.zeros(1), np.zeros(0), np.zeros((3, 3)), z3.copy(), np.zeros(0))
    with pytest.raises(ValueError):  # a peer end's node index outside P
        _kernels.tdoa_res(z3, np.ones((1, 3), np.int64), np.full((1, 3), 5, np.int64), np.zeros((1, 3, 3)), np.zeros(1),
                          np.ones(1), np.zeros((2, 3)), np.zeros(0), np.zeros(0), np.zeros(1), np.zeros(1))
