"""Double-threshold link fault detection of the paper (§2.3.2) — pure numpy (+ scikit-learn K-means).

Step 1, residual matrix: ∂_ij = | d_ij − ‖p̂_i − p̂_j‖ | for every pair (i < j) that has a range this
epoch, on the *current* position estimates (every node's last broadcast), pairs sorted by UAV id so
every node of the swarm builds the same matrix from the same broadcasts.

Step 2, upper threshold Δh: 2-means clustering of the residuals (scikit-learn ``KMeans(2)``, or the
exact 1-D 2-means optimum — same objective, solved by scanning every split of the sorted values);
Δh = the decision boundary between the clusters = midpoint of the largest "low" residual and the
smallest "high" one.

*Fault-free guard.* K-means always splits, also when every link is clean (it then cuts the noise in
two). So Δh is never allowed below ``floor_factor × Δl`` (default 3): with no fault present every
residual is ≲ Δl (Δl is the 99th percentile of fault-free converged residuals), so nothing clean is
excluded, and a clean residual that does exceed Δl is only down-weighted (H1), not removed.

*Ceiling with 2-means descent* (``ceil_factor``, default 10). A failed module's residuals (paper
fault 2: range + U(20, 150) m on all of that UAV's links) form a wide cluster, and the SSE optimum
then cuts *inside* it: the lower failures became H1 with a small non-zero weight, which at
σ_eff = σ/√l ≈ 1 m still dragged the estimate by tens of metres. So while the boundary is above
``ceil_factor × Δl`` 2-means is re-run on the low cluster (the split was fault vs fault, not fault vs
clean), and the result is clamped to [floor, ceil]. Interference (1–8 m) then lands H1 or H0,
failures H0, clean links H2 (tests/test_detection.py::test_module_failure_spread_all_h0).

*H1 weight cap* (``cap_h1``, default on): weight = min(l(∂), (Δl/∂)²) — eq. 25 read literally
(l on the residual ⇒ l² on the squared one, l ≈ Δl/∂). It bounds an H1 link's pull: σ_eff ≥ σ·∂/Δl,
influence Δl²/(∂σ²) decreasing in ∂. Eq. 24 remains the weight function; the cap only bites when
Δh is large relative to ∂.

Step 3, Δl: offline training (``swarmnav.calibration``), or ``fallback_sigmas × σ_uwb``.

Classification: H0 (∂ > Δh, excluded), H1 (Δl < ∂ ≤ Δh, weight l(∂) of eq. 24), H2 (∂ ≤ Δl, full).

**Eq. 24 weight and how it enters the cost.** l(∂) = 1 below Δl; Δl/∂ · ((Δh − ∂)/(Δh − Δl))²
between; 0 from Δh. It is continuous at both thresholds (1 at Δl, 0 at Δh). We use l as an **IRLS
weight on the squared residual** — the link's cost is ``½ l (r/σ)²`` (equivalently its sigma is
divided by √l) — not as a factor on the residual as eq. 25 literally writes it (that would give
``½ l² (r/σ)²``). Reason: Δl/|∂| is exactly Huber's IRLS weight with threshold Δl and the squared
bracket is a Tukey-like taper to zero at Δh, so read as a weight, eq. 24 is a redescending
M-estimator and the iteration over rounds is IRLS. Tested in tests/test_detection.py.

Sparse data (real recordings): :class:`ResidualWindow` keeps the residuals of the last W epochs and
K-means runs on the window (``residual_window_epochs``); classification still uses the current
epoch's residuals.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from itertools import chain

import numpy as np

from . import _kernels  # C: built by `make setup` (setup.py)
from .base import LinkClass
from ..scenario import estimation_values

H0, H1, H2 = LinkClass.H0_FAILED, LinkClass.H1_INTERFERED, LinkClass.H2_NORMAL

DEFAULT_FLOOR_FACTOR = 3.0
DEFAULT_CEIL_FACTOR = 10.0


class RangePairs:
    """The ranged pairs of an epoch among ``nodes`` (pairs (a, b), a < b, sorted by id — the same
    order on every node), built once so the residuals can be evaluated on each round's positions."""

    def __init__(self, nodes: Sequence[int], ranges: Mapping[tuple[int, int], float]):
        ids = np.array(nodes, np.int64)
        members = set(nodes)
        keys = sorted(k for k in ranges if k[0] in members and k[1] in members)
        self.d = np.fromiter(map(ranges.__getitem__, keys), float, len(keys))
        self.pairs = np.fromiter(chain.from_iterable(keys), np.int64, 2 * len(keys)).reshape(-1, 2)
        order = np.argsort(ids, kind="stable")  # nodes need not be sorted: index by lookup
        self.ia = order[np.searchsorted(ids, self.pairs[:, 0], sorter=order)]
        self.ib = order[np.searchsorted(ids, self.pairs[:, 1], sorter=order)]

    def residuals(self, positions: np.ndarray) -> np.ndarray:
        """|d_ij − ‖p_i − p_j‖| with ``positions`` (len(nodes), 3) in the order of ``nodes``."""
        dv = positions[self.ia] - positions[self.ib]
        return np.abs(self.d - np.sqrt(np.add.reduce(dv * dv, axis=1)))  # = np.linalg.norm(dv, axis=1)


def fallback_delta_l(uwb_sigma_m: float, fallback_sigmas: float) -> float:
    """Δl (m) where no offline training applies: ``fallback_sigmas`` × the ranging σ (m)."""
    return float(fallback_sigmas) * float(uwb_sigma_m)


def node_delta_l(settings: dict, uwb_sigma_m: float, tolerance: float) -> float:
    """Δl (m) a node uses: the trained ``delta_l_m`` of the settings if it applies, else the
    fallback (``delta_l_fallback_sigmas`` × σ). A trained Δl is a statistic of residuals at the
    training data's ranging σ (``delta_l_uwb_sigma_m``); on data whose σ differs by more than
    ``tolerance`` (relative, ``delta_l_sigma_tolerance``) it does not apply (MILUV: trained at
    0.10 m, recording 0.19 m -> Δl 0.557 m instead of 0.269 m)."""
    dl, dl_sig = settings.get("delta_l_m"), settings.get("delta_l_uwb_sigma_m")
    if dl and dl_sig and abs(float(dl_sig) / uwb_sigma_m - 1.0) > float(tolerance):
        dl = None
    return float(dl) if dl else fallback_delta_l(uwb_sigma_m, estimation_values(settings).delta_l_fallback_sigmas)


def residual_matrix(positions: Mapping[int, np.ndarray], ranges: Mapping[tuple[int, int], float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of every ranged pair whose both ends have a position.

    ``ranges`` maps (a, b) with a < b to the measured range. Returns (pairs (m,2) int sorted by
    (a, b), residuals (m,)).
    """
    nodes = sorted(positions)
    rp = RangePairs(nodes, ranges)
    if not len(rp.d):
        return np.zeros((0, 2), np.int64), np.zeros(0)
    return rp.pairs, rp.residuals(np.array([positions[u] for u in nodes], float))


def two_means_boundary(x: np.ndarray, backend: str = "exact") -> float | None:
    """Boundary between the two K-means clusters of scalars ``x`` (None if < 2 distinct values).

    backend "sklearn": ``KMeans(2, n_init=1)`` initialised at (min, max) — deterministic;
    "exact": the global optimum of the same 1-D objective (every split of the sorted values).
    """
    x = np.sort(np.asarray(x, float).ravel())
    if len(x) < 2 or x[-1] - x[0] <= 1e-12:
        return None
    if backend == "sklearn":
        from sklearn.cluster import KMeans

        km = KMeans(2, n_init=1, init=np.array([[x[0]], [x[-1]]]), max_iter=100, tol=0.0)
        lab = km.fit_predict(x[:, None])
        hi_lab = int(np.argmax(km.cluster_centers_[:, 0]))
        low, high = x[lab != hi_lab], x[lab == hi_lab]
        if len(low) == 0 or len(high) == 0:
            return None
        return 0.5 * (float(low.max()) + float(high.min()))
    if backend != "exact":
        raise ValueError(f"unknown K-means backend {backend!r}")
    n = len(x)
    c1 = np.cumsum(x)
    c2 = np.cumsum(x * x)
    s = np.arange(1.0, n)  # split: low = x[:s], high = x[s:]
    c1_lo, c2_lo = c1[:-1], c2[:-1]  # the cumulative sums at s − 1
    sse_lo = c2_lo - c1_lo ** 2 / s
    sse_hi = (c2[-1] - c2_lo) - (c1[-1] - c1_lo) ** 2 / (n - s)
    i = int(np.argmin(sse_lo + sse_hi))
    return 0.5 * (x[i] + x[i + 1])


def upper_threshold(residuals: np.ndarray, delta_l: float, floor_factor: float = DEFAULT_FLOOR_FACTOR,
                    backend: str = "exact", ceil_factor: float | None = DEFAULT_CEIL_FACTOR) -> float:
    """Δh = the 2-means boundary, descended and clamped to [floor_factor·Δl, ceil_factor·Δl].

    *Descent* (when ``ceil_factor`` is set): while the boundary lies above ``ceil_factor·Δl`` the
    split separated a wide fault cluster from the rest, not faults from clean links (a failed
    module's residuals, 20–150 m, make 2-means cut *inside* their own spread); 2-means is re-run on
    the low cluster. Then the result is clamped: the fault-free guard from below, the ceiling from
    above (module docstring).
    """
    floor = floor_factor * delta_l
    x = np.asarray(residuals, float).ravel()
    b = two_means_boundary(x, backend)
    if ceil_factor is not None:
        ceil = max(ceil_factor * delta_l, floor)
        while b is not None and b > ceil:
            x = x[x <= b]
            nb = two_means_boundary(x, backend)
            if nb is None or nb >= b:
                break
            b = nb
        if b is not None:
            b = min(b, ceil)
    return floor if b is None else max(b, floor)


def classify(residuals: np.ndarray, delta_l: float, delta_h: float) -> np.ndarray:
    """H0 / H1 / H2 per residual (array of LinkClass ints)."""
    r = np.abs(np.asarray(residuals, float))
    out = np.full(r.shape, int(H2), np.int64)
    out[r > delta_l] = int(H1)
    out[r > delta_h] = int(H0)
    return out


def classify_single(residuals: np.ndarray, delta_h: float) -> np.ndarray:
    """Single-threshold test at Δh (the paper's motivation): H0 above Δh, H2 otherwise."""
    r = np.abs(np.asarray(residuals, float))
    return np.where(r > delta_h, int(H0), int(H2)).astype(np.int64)


def weight_eq24(residuals, delta_l: float, delta_h: float) -> np.ndarray:
    """Eq. 24: 1 (∂ < Δl); Δl/∂ ((Δh − ∂)/(Δh − Δl))² (Δl ≤ ∂ < Δh); 0 (∂ ≥ Δh).

    Used as an IRLS weight on the squared whitened residual (module docstring).
    """
    r = np.abs(np.asarray(residuals, float))
    w = np.ones_like(r)
    if delta_h <= delta_l:
        w[r >= delta_l] = 0.0
        return w
    mid = (r >= delta_l) & (r < delta_h)
    rm = r[mid]
    w[mid] = delta_l / rm * ((delta_h - rm) / (delta_h - delta_l)) ** 2
    w[r >= delta_h] = 0.0
    return w


def weight_cap_eq25(residuals, delta_l: float) -> np.ndarray:
    """Bound on an H1 link's IRLS weight: (Δl/∂)² (1 below Δl) — eq. 25 read literally.

    With weight w the link's effective sigma is σ/√w; capping w at (Δl/∂)² makes that sigma at
    least σ·∂/Δl, i.e. a link whose residual is n times Δl is trusted n times less in sigma, and
    its influence w·∂/σ² = Δl²/(∂σ²) decreases with ∂ (redescending) instead of staying at the
    Huber level Δl/σ². Continuous at Δl (1); below eq. 24 only where eq. 24's taper is still near
    1 (Δh well above ∂), i.e. it matters when Δh is large.
    """
    r = np.abs(np.asarray(residuals, float))
    w = np.ones_like(r)
    m = r > delta_l
    w[m] = (delta_l / r[m]) ** 2
    return w


class ResidualWindow:
    """Recent epochs' residuals for clustering on sparse data.

    Fixed (``epochs`` > 1): the current epoch plus the previous ``epochs`` − 1. Adaptive
    (``epochs`` == 1, the default, with ``min_residuals`` > 0): the current epoch alone when it has
    at least ``min_residuals`` residuals (the paper: ~150 per epoch, so unchanged), else the most
    recent earlier epochs are added, newest first, until that count is reached or ``max_epochs``
    epochs are pooled — so a sparse recording (MILUV: ~1.6 inter-UAV ranges per epoch) needs no
    per-dataset window setting.
    """

    def __init__(self, epochs: int = 1, min_residuals: int = 0, max_epochs: int = 30):
        self.epochs = max(1, int(epochs))
        self.min_residuals = max(0, int(min_residuals)) if self.epochs == 1 else 0
        n = self.epochs - 1 if self.epochs > 1 else (max(1, int(max_epochs)) - 1 if self.min_residuals else 0)
        self._hist: deque[np.ndarray] = deque(maxlen=n)

    def values(self, current: np.ndarray) -> np.ndarray:
        """The current epoch's residuals together with the pooled earlier ones."""
        cur = np.asarray(current, float)
        if not self._hist:
            return cur
        if self.min_residuals:
            parts, n = [cur], len(cur)
            for h in reversed(self._hist):
                if n >= self.min_residuals:
                    break
                parts.append(h)
                n += len(h)
            return np.concatenate(parts)
        return np.concatenate([*self._hist, cur])

    def push(self, final: np.ndarray) -> None:
        """Store an epoch's final (last-round) residuals."""
        if self._hist.maxlen:
            self._hist.append(np.asarray(final, float).copy())


def detect(pairs_res: np.ndarray, delta_l: float, window: ResidualWindow | None = None,
           floor_factor: float = DEFAULT_FLOOR_FACTOR, backend: str = "exact",
           ceil_factor: float | None = DEFAULT_CEIL_FACTOR, cap_h1: bool = True
           ) -> tuple[float, np.ndarray, np.ndarray]:
    """Δh, classes and weights for the current residuals (convenience wrapper).

    Weights: eq. 24, and with ``cap_h1`` at most (Δl/∂)² (:func:`weight_cap_eq25`). With the
    "exact" backend and finite residuals it is one C call (``_kernels.detect``: the same operations,
    bit-identical; ~10x cheaper than the ~25 numpy calls of :func:`detect_numpy`)."""
    pool = window.values(pairs_res) if window is not None else pairs_res
    if backend == "exact" and (ceil_factor is None or ceil_factor > 0):
        res = np.ascontiguousarray(pairs_res, float)
        pool = np.ascontiguousarray(pool, float)
        if np.isfinite(pool).all() and np.isfinite(res).all():
            cls, w = np.empty(len(res), np.int64), np.empty(len(res))
            dh = _kernels.detect(res, pool, float(delta_l), float(floor_factor),
                                 -1.0 if ceil_factor is None else float(ceil_factor), bool(cap_h1), cls, w)
            return dh, cls, w
    return detect_numpy(pairs_res, delta_l, pool, floor_factor, backend, ceil_factor, cap_h1)


def detect_numpy(pairs_res: np.ndarray, delta_l: float, pool: np.ndarray, floor_factor: float = DEFAULT_FLOOR_FACTOR,
                 backend: str = "exact", ceil_factor: float | None = DEFAULT_CEIL_FACTOR, cap_h1: bool = True
                 ) -> tuple[float, np.ndarray, np.ndarray]:
    """:func:`detect` in numpy (the reference of the C kernel; any backend, non-finite values),
    with the pooled residuals ``pool`` given."""
    dh = upper_threshold(pool, delta_l, floor_factor, backend, ceil_factor)
    cls, w = classify_and_weigh(pairs_res, delta_l, dh, cap_h1)
    return dh, cls, w


def classify_and_weigh(res: np.ndarray, delta_l: float, delta_h: float, cap_h1: bool = True
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Classes and weights of residuals at given thresholds: eq. 24 (capped at (Δl/∂)² with
    ``cap_h1``), 0 for H0. Also used for links outside the residual matrix (graph.py: passive
    range differences, classified at the ranges' Δh)."""
    r = np.abs(np.asarray(res, float))
    cls = classify(r, delta_l, delta_h)
    w = weight_eq24(r, delta_l, delta_h)
    if cap_h1:  # the cap only binds on the H1 band: both are 1 below Δl, eq. 24 is 0 from Δh
        band = (r > delta_l) & (w > 0)
        w[band] = np.minimum(w[band], weight_cap_eq25(r[band], delta_l))
    w[cls == int(H0)] = 0.0
    return cls, w
