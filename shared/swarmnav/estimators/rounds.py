"""The per-UAV graph's round solve: the epoch's cooperative links as normal equations on the own position.

Every round (graph.py ``iterate``) the epoch's UWB part is rebuilt from the neighbours' broadcast
states — the time-varying graph. A small Gauss–Newton solve on the node's own position p combines
the local prior N(p_loc, P_loc) with the range, eq. 27 az/el and passive-tdoa factors to the
neighbours, whose broadcast positions enter with their covariance marginalised into each factor's
noise ("factor to an uncertain neighbour"). The models are ``swarmnav.models`` (uwb_range, bearing,
tdoa), called vectorised over all links of a kind at once; no smoother work per round (~0.1 ms).

* :class:`RoundCache` — what does not change between an epoch's rounds (rows, tag offsets, σ);
* :func:`prepare_links` — the active links (weights > 0) at the round's positions, as :class:`Links`;
* :func:`normal_equations` — (H, g) of prior + links at p, and the sandwich "meat" M for the
  covariance of the solution (docs/estimators.md "Double counting");
* :func:`gauss_newton`, :func:`sandwich_cov`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from . import _kernels  # C: built by `make setup` (setup.py)
from . import detection as det
from ..models.tdoa import tdoa_h


@dataclass
class RoundCache:
    """An epoch's link structure, rebuilt only when the live peers or the known ranges change.

    ``nodes``: every live node, sorted (positions P and covariances C of a round are in this
    order); ``pairs``: the residual matrix's ranged pairs (detection); ``mine``: the indices of this
    node's pairs in it and ``mine_other`` their other ends; ``nb``: the ranged live neighbours.
    Range rows (one per measured range to a neighbour): owner, node index, tag offset between the
    two tags (ENU m), σ² (m²), z (m). Az/el rows (own observations first, ``n_own_azel`` of them,
    then the neighbours' observations of this node turned around): target, node index, σ² (rad²),
    z (rad). Tdoa rows: ([(kind, x, lever)] of listener, initiator, responder — kind "self" (x =
    the tag's world offset), "peer" (x = node index) or "fixed" (x = ENU point) —, z, σ²)."""

    key: tuple
    k: int
    nodes: list[int]
    idx: dict[int, int]
    pairs: det.RangePairs
    mine: list[int]
    mine_other: list[int]
    nb: list[int]
    rng_owner: np.ndarray
    rng_node: np.ndarray
    rng_lever: np.ndarray | None = None
    rng_sig2: np.ndarray | None = None
    rng_z: np.ndarray | None = None
    rng_has_lever: bool = False
    n_own_azel: int = 0
    azel_target: np.ndarray | None = None
    azel_node: np.ndarray | None = None
    azel_sig2: np.ndarray | None = None
    azel_z: np.ndarray | None = None
    tdoa: list = field(default_factory=list)
    _tdoa_arr: tuple | None = field(default=None, repr=False, compare=False)

    def tdoa_arrays(self) -> tuple:
        """The tdoa rows as arrays for the C kernels, built once per cache (the relink window
        re-reads an epoch's cache every epoch): kind (n, 3) int64 (0 self, 1 peer, 2 fixed), node
        index (n, 3) int64 (peer ends, else 0), offset (n, 3, 3) (self: the tag's world offset; peer:
        its tag's offset from the broadcast position; fixed: the ENU point), z (n,), σ² (n,)."""
        if self._tdoa_arr is None or len(self._tdoa_arr[3]) != len(self.tdoa):
            n = len(self.tdoa)
            kind, idx, off = np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64), np.zeros((n, 3, 3))
            for r, (ends, _, _) in enumerate(self.tdoa):
                for e, (k, x, lev) in enumerate(ends):
                    kind[r, e] = _TDOA_KIND[k]
                    if k == "peer":
                        idx[r, e], off[r, e] = x, lev
                    else:
                        off[r, e] = x
            z = np.array([z for _, z, _ in self.tdoa], float)
            sig2 = np.array([s2 for _, _, s2 in self.tdoa], float)
            self._tdoa_arr = (kind, idx, off, z, sig2)
        return self._tdoa_arr


_TDOA_KIND = {"self": 0, "peer": 1, "fixed": 2}


@dataclass
class TdoaLinks:
    """The active tdoa links of a solve as arrays (:func:`prepare_links`): kind (n, 3) as
    :meth:`RoundCache.tdoa_arrays`; pos (n, 3, 3) the ends' points (self: the own tag's offset from
    the own position; peer: the neighbour's tag; fixed: the anchor); cov (n, 3, 3, 3) the peer ends'
    covariances (zero for the others); w, z, σ² (n,)."""

    kind: np.ndarray
    pos: np.ndarray
    cov: np.ndarray
    w: np.ndarray
    z: np.ndarray
    sig2: np.ndarray

    def __len__(self) -> int:
        return len(self.w)


@dataclass
class Links:
    """The active links of one solve. ``rng`` = (p_j, P_j, w, lever, σ², z) and ``azel`` = (p_t,
    P_t, w, σ², z), arrays over the links, or None; ``tdoa`` = [(ends, z, σ², w)] with ends
    (kind, position, covariance). ``rng_group`` (None: one row per neighbour, as without the range
    memory): each range row's neighbour index; rows of one neighbour share its position error in
    the sandwich (range_memory.py)."""

    rng: tuple | None = None
    azel: tuple | None = None
    tdoa: list = field(default_factory=list)
    rng_group: np.ndarray | None = None


def prepare_links(c: RoundCache, P: np.ndarray, C: np.ndarray, weights: dict[int, float], tdoa_w: np.ndarray,
                  infl: float | Callable[[int], float], azel_weight: str = "full", commit_azel: int | None = None) -> Links:
    """The links of cache ``c`` with weight > 0 at positions P / covariances C (``c.nodes`` order),
    each neighbour's covariance × ``infl`` (a number, or per node id). ``weights``: the range
    links' weight per neighbour (eq. 24); az/el links keep weight 1 (``azel_weight`` "full") or
    take their range link's ("range"); ``commit_azel``: use only the first that many az/el rows."""
    L = Links()
    per_node = callable(infl)
    if len(c.rng_owner):
        owners = c.rng_owner.tolist()
        w = np.array([weights[o] for o in owners])
        keep = _kept(w)
        if keep is not None:
            f = np.array([infl(o) for o in owners]) if per_node else np.full(len(w), infl)
            n = c.rng_node[keep]
            L.rng = (P[n], C[n] * f[keep][:, None, None], w[keep], c.rng_lever[keep], c.rng_sig2[keep], c.rng_z[keep])
    if c.azel_target is not None:
        na = len(c.azel_target) if commit_azel is None else commit_azel
        tg = c.azel_target[:na].tolist()
        w = np.ones(len(tg)) if azel_weight == "full" else np.array([weights.get(o, 1.0) for o in tg])
        keep = _kept(w)
        if keep is not None:
            f = np.array([infl(o) for o in tg]) if per_node else np.full(len(w), infl)
            n = c.azel_node[:na][keep]
            L.azel = (P[n], C[n] * f[keep][:, None, None], w[keep], c.azel_sig2[:na][keep], c.azel_z[:na][keep])
    if c.tdoa:
        kind, idx, off, z, sig2 = c.tdoa_arrays()
        w = np.asarray(tdoa_w, float)
        n = min(len(w), len(z))  # as zip(c.tdoa, tdoa_w)
        keep = np.zeros(len(z), bool)
        keep[:n] = w[:n] > 0
        w = np.concatenate([w[:n], np.zeros(len(z) - n)])
        if keep.any():
            kind, idx, off, z, sig2, w = kind[keep], idx[keep], off[keep], z[keep], sig2[keep], w[keep]
            peer = kind == 1
            pos = off.copy()
            pos[peer] = P[idx[peer]] + off[peer]  # a neighbour's tag: its position + the tag's offset
            cov = np.zeros(kind.shape + (3, 3))
            f = np.array([infl(u) for u in c.nodes], float) if per_node else np.full(len(c.nodes), float(infl))
            cov[peer] = C[idx[peer]] * f[idx[peer]][:, None, None]
            L.tdoa = TdoaLinks(kind, pos, cov, w, z, sig2)
    return L


def _kept(w: np.ndarray) -> slice | np.ndarray | None:
    """The rows with weight > 0: every row (a slice: no copies), a mask, or None when none is."""
    keep = w > 0
    if keep.all():
        return slice(None) if len(w) else None
    return keep if keep.any() else None


def normal_equations(L: Links, p: np.ndarray, info: np.ndarray | None = None, p_loc: np.ndarray | None = None,
                     L_true: Links | None = None):
    """Gauss-Newton normal equations (H, g) at own position p of the prior N(p_loc, info⁻¹) (none
    when ``info`` is None: the links only) and the links ``L``.

    With ``L_true`` (the same links, with the neighbours' covariances the error model assigns
    them) also the sandwich "meat" M = Σ JᵀW·R·WJ (+ info), W the weight of a factor in ``L`` and
    R its error covariance in ``L_true``: the solution's covariance is H⁻¹MH⁻¹."""
    if info is None:
        H, gv = np.zeros((3, 3)), np.zeros(3)
    else:
        H, gv = info.copy(), info @ (p_loc - p)
    _kernels.own_system(np.ascontiguousarray(p, float), *_rng_arrays(L.rng), *_azel_arrays(L.azel), H, gv)
    meat = None if L_true is None else link_meat(L, p, L_true, info)
    if isinstance(L.tdoa, TdoaLinks):
        T = L.tdoa
        cov_t = _EMPTY if L_true is None else np.ascontiguousarray(L_true.tdoa.cov, float)
        _kernels.own_tdoa(np.ascontiguousarray(p, float), np.ascontiguousarray(T.kind, np.int64),
                          np.ascontiguousarray(T.pos, float), np.ascontiguousarray(T.cov, float),
                          np.ascontiguousarray(T.w, float), np.ascontiguousarray(T.z, float),
                          np.ascontiguousarray(T.sig2, float), cov_t, H, gv, _EMPTY if meat is None else meat)
        return (H, gv) if L_true is None else (H, gv, meat)
    # a list of ([(kind, x, Cov)], z, σ², w) rows: the reference the C kernel own_tdoa reproduces bit for bit
    tdoa_t = L_true.tdoa if L_true is not None else [None] * len(L.tdoa)
    for (ends, z, sig2, w), true in zip(L.tdoa, tdoa_t):
        # own position p: this node's tag(s) among the three; neighbours' broadcast covariance
        # folded into the variance along their gradient; w = the link's weight
        pts = [p + x if kind == "self" else x for kind, x, _ in ends]
        h, *grads = tdoa_h(*pts)
        j = sum(gi for (kind, _, _), gi in zip(ends, grads) if kind == "self")
        var = sig2 + sum(gi @ Ce @ gi for (kind, _, Ce), gi in zip(ends, grads) if kind == "peer")
        H += (w / var) * np.outer(j, j)
        gv += (w * (z - h) / var) * j
        if true is not None:
            var_t = sig2 + sum(gi @ Ce @ gi for (kind, _, Ce), gi in zip(true[0], grads) if kind == "peer")
            meat += (w * w * var_t / var ** 2) * np.outer(j, j)
    return (H, gv) if L_true is None else (H, gv, meat)


_EMPTY = np.zeros(0)
_NONE = (np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
_NONE_AZEL = (np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, 2)))


def _rng_arrays(rng: tuple | None) -> tuple:
    """(p_j, P_j, w, lever, σ², z) as C-contiguous float64 arrays for the C kernel (empty: none)."""
    return _NONE if rng is None else tuple(np.ascontiguousarray(a, float) for a in rng)


def _azel_arrays(azel: tuple | None) -> tuple:
    """(p_t, P_t, w, σ², z) as C-contiguous float64 arrays for the C kernel (empty: none)."""
    return _NONE_AZEL if azel is None else tuple(np.ascontiguousarray(a, float) for a in azel)


def link_meat(L: Links, p: np.ndarray, L_true: Links, info: np.ndarray | None) -> np.ndarray:
    """The sandwich "meat" M = Σ JᵀW·R·WJ (+ info) of the range and az/el links ``L`` at p, R from
    the neighbours' covariances in ``L_true`` (:func:`normal_equations`; the tdoa rows' share is
    added there). Range rows of one neighbour (``L.rng_group``) share its position error:
    Σ a²σ² uuᵀ + Σ_groups G P G, G = Σ_group a uuᵀ. Built by the C kernel ``own_meat`` (the models
    of uwb_range and bearing; tests/test_rounds.py holds the numpy formulas it is checked against)."""
    meat = np.zeros((3, 3)) if info is None else np.array(info, float, order="C")
    pj, Pj, w, lev, sig2, _ = _rng_arrays(L.rng)
    Pj_true = _NONE[1] if L.rng is None else np.ascontiguousarray(L_true.rng[1], float)
    group = np.zeros(0, np.int64) if L.rng is None or L.rng_group is None else np.ascontiguousarray(L.rng_group, np.int64)
    pt, Pt, wt, st2, _ = _azel_arrays(L.azel)
    Pt_true = _NONE_AZEL[1] if L.azel is None else np.ascontiguousarray(L_true.azel[1], float)
    _kernels.own_meat(np.ascontiguousarray(p, float), pj, Pj, w, lev, sig2, Pj_true, group, pt, Pt, wt, st2, Pt_true, meat)
    return meat


def gauss_newton(p: np.ndarray, normal_eq: Callable[[np.ndarray], tuple], iterations: int) -> np.ndarray:
    """Gauss-Newton from p on ``normal_eq(p) -> (H, g)``: at most ``iterations`` steps, stopping
    below 0.1 mm; a non-finite step (a degenerate or corrupt link set) keeps the last finite p."""
    p = p.copy()
    for _ in range(iterations):
        H, gv = normal_eq(p)
        dp = np.linalg.solve(H, gv)
        if not np.all(np.isfinite(dp)):
            break
        p = p + dp
        if np.sqrt(dp @ dp) < 1e-4:  # = np.linalg.norm(dp)
            break
    return p


def one_hop_belief(L: Links, p0: np.ndarray, info: np.ndarray, p_loc: np.ndarray, iterations: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian-BP belief after one message exchange from the epoch priors (report "belief",
    docs/estimators.md "Double counting"): links ``L`` with the neighbours' epoch-prior covariances,
    linearised at their last round positions. The mean (Gauss-Newton from p0) and the inverse
    Hessian there."""
    p = gauss_newton(p0, lambda q: normal_equations(L, q, info, p_loc), iterations)
    H = normal_equations(L, p, info, p_loc)[0]
    return p, np.linalg.inv(0.5 * (H + H.T))


def sandwich_cov(H: np.ndarray, M: np.ndarray) -> np.ndarray:
    """H⁻¹MH⁻¹ (H symmetrised)."""
    Hi = np.linalg.inv(0.5 * (H + H.T))
    return Hi @ M @ Hi


def tdoa_residuals(c: RoundCache, P: np.ndarray, me: np.ndarray, C: np.ndarray | None = None,
                   P_own: np.ndarray | None = None, normalise: bool = True) -> np.ndarray:
    """|z − h| / σ of the cooperative tdoa rows of ``c`` at positions P (``c.nodes`` order), the own
    body origin at ``me``. With covariances (``C`` per node, ``P_own`` for this node) σ is the
    innovation's: σ² = σ_row² + Σ gᵀ·Cov·g over the ends; else the row's σ. ``normalise`` False:
    |z − h| in metres. The C kernel ``tdoa_res`` (:func:`tdoa_residuals_py` is the reference it
    reproduces bit for bit)."""
    if not c.tdoa:
        return np.zeros(0)
    kind, idx, off, z, sig2 = c.tdoa_arrays()
    n = len(z)
    absres, var = np.empty(n), np.empty(n)
    with_cov = C is not None
    _kernels.tdoa_res(np.ascontiguousarray(me, float), kind, idx, off, z, sig2, np.ascontiguousarray(P, float).reshape(-1, 3),
                      np.ascontiguousarray(C, float) if with_cov else _EMPTY,
                      np.ascontiguousarray(P_own, float) if with_cov else _EMPTY, absres, var)
    return absres / np.sqrt(var) if normalise else absres


def tdoa_residuals_py(c: RoundCache, P: np.ndarray, me: np.ndarray, C: np.ndarray | None = None,
                      P_own: np.ndarray | None = None, normalise: bool = True) -> np.ndarray:
    """The numpy reference of :func:`tdoa_residuals` (tests)."""
    out = []
    for ends, z, sig2 in c.tdoa:
        pts = [me + x if kind == "self" else (P[x] + lev if kind == "peer" else x) for kind, x, lev in ends]
        h, *grads = tdoa_h(*pts)
        var = sig2
        if C is not None:
            # ends on the same body (two own tags, a neighbour's two tags) move together: their
            # gradients are summed before the quadratic form
            body: dict = {}
            for (kind, x, _), g in zip(ends, grads):
                if kind != "fixed":
                    key = "self" if kind == "self" else int(x)
                    body[key] = body.get(key, 0.0) + g
            var += sum(g @ (P_own if key == "self" else C[key]) @ g for key, g in body.items())
        out.append(abs(z - h) / np.sqrt(var) if normalise else abs(z - h))
    return np.array(out, float)
