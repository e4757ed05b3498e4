"""In-process evaluation: run one algorithm over a Dataset and collect per-epoch estimates as arrays.

Pure (no files, no Rerun, no Zenoh). Per-UAV algorithms are driven by the one epoch protocol of
:mod:`swarmnav.protocol` over its in-memory transport (:class:`NodeGroup`, :func:`run_node_epoch`), with the
same initial states (:func:`swarmnav.initial.initial_states` with the run seed), the same settings
and UAVs in sorted id order as the Zenoh deployment, so both transports give the same numbers.
The central oracle (a :class:`SwarmEstimator`) is stepped once per epoch with the range labels.

Epochs scored are k = 1..K (epoch 0 is the initial knowledge, no estimate). Truth is the dataset's
truth table interpolated to the epoch times (linearly, the attitude by slerp; exact to the last bit or two
when the rows are at the epoch times).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .dataset import Dataset, EpochSlicer, epoch_of, node_view
from .estimators import registry
from .estimators.base import NodeEstimate
from .geometry import from_rotation, to_rotation
from .initial import initial_states
from .protocol import node_epoch, step_round
from .scenario import estimation_values

LINK_DTYPE = np.dtype([("k", np.int32), ("observer", np.int32), ("other", np.int32), ("cls", np.int8),
                       ("residual_m", np.float64), ("weight", np.float64)])


@dataclass
class RunResult:
    """One algorithm over one dataset/seed. Arrays indexed [epoch index, uav index]."""

    algo: str
    seed: int
    uavs: np.ndarray  # (N,) sorted UAV ids
    t: np.ndarray  # (K,) epoch times, epochs 1..K
    pos: np.ndarray  # (K,N,3) ENU m (NaN = no estimate)
    vel: np.ndarray  # (K,N,3)
    pos_cov: np.ndarray  # (K,N,3,3)
    quat: np.ndarray  # (K,N,4) w,x,y,z (NaN when the estimator gives none)
    step_ms: np.ndarray  # (K,N)
    rounds: np.ndarray  # (K,N)
    delta_h_m: np.ndarray  # (K,N) NaN when not reported
    delta_l_m: np.ndarray  # (K,N)
    links: np.ndarray = field(default_factory=lambda: np.zeros(0, LINK_DTYPE))  # LINK_DTYPE records
    wall_s: float = 0.0

    @classmethod
    def empty(cls, algo: str, seed: int, uavs, t) -> "RunResult":
        K, N = len(t), len(uavs)
        nan = lambda *s: np.full(s, np.nan)  # noqa: E731
        return cls(algo, seed, np.asarray(uavs, int), np.asarray(t, float), nan(K, N, 3), nan(K, N, 3),
                   nan(K, N, 3, 3), nan(K, N, 4), nan(K, N), np.zeros((K, N), int), nan(K, N), nan(K, N))


@dataclass
class Truth:
    uavs: np.ndarray  # (N,)
    t: np.ndarray  # (K,)
    pos: np.ndarray  # (K,N,3)
    vel: np.ndarray  # (K,N,3)
    quat: np.ndarray  # (K,N,4) w,x,y,z


def truth_at_epochs(ds: Dataset) -> Truth:
    """Truth of every UAV at the epoch times k = 1..K (positions and velocities linear, attitude slerp)."""
    meta = ds.meta
    uavs = np.array(meta.uav_ids(), int)
    K = meta.n_epochs()
    t = np.array([meta.epoch_time(k) for k in range(1, K + 1)])
    tr = ds.table("truth")
    pos = np.full((K, len(uavs), 3), np.nan)
    vel = np.full_like(pos, np.nan)
    quat = np.full((K, len(uavs), 4), np.nan)
    for j, u in enumerate(uavs):
        m = tr["node"] == u
        tt = tr["t"][m]
        if len(tt) == 0:
            continue
        order = np.argsort(tt, kind="stable")
        tt = tt[order]
        inside = (t >= tt[0] - 1e-9) & (t <= tt[-1] + 1e-9)
        for c, (arr, cols) in enumerate(((pos, ("pe", "pn", "pu")), (vel, ("ve", "vn", "vu")))):
            for a, col in enumerate(cols):
                arr[inside, j, a] = np.interp(t[inside], tt, tr[col][m][order])
        q = np.column_stack([tr[c][m][order] for c in ("qw", "qx", "qy", "qz")])
        quat[inside, j] = _slerp(tt, q, t[inside])
    return Truth(uavs, t, pos, vel, quat)


def _slerp(tt: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Attitudes q (M,4) at strictly increasing times tt, spherically interpolated to the times t
    (clipped to [tt[0], tt[-1]]); (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Slerp

    rot = to_rotation(q)
    if len(tt) == 1:
        return np.repeat(from_rotation(rot, canonical=True), len(t), axis=0)
    return from_rotation(Slerp(tt, rot)(np.clip(t, tt[0], tt[-1])), canonical=True)


def _store(res: RunResult, i: int, j: int, e: NodeEstimate, links: list) -> None:
    res.pos[i, j] = e.pos
    res.vel[i, j] = e.vel
    res.pos_cov[i, j] = e.pos_cov
    if e.quat is not None:
        res.quat[i, j] = e.quat
    res.step_ms[i, j] = e.step_ms
    res.rounds[i, j] = e.rounds
    if e.delta_h_m is not None:
        res.delta_h_m[i, j] = e.delta_h_m
    if e.delta_l_m is not None:
        res.delta_l_m[i, j] = e.delta_l_m
    k = i + 1
    for li in e.links:
        links.append((k, e.uav, int(li.other), int(li.cls), float(li.residual_m), float(li.weight)))


class NodeGroup:
    """Some (or all) of a run's per-UAV estimators, driven round by round over the in-memory bus:
    ``submit("start", k)`` builds their epoch-k generators and ``result()`` then returns their
    round-0 states; ``submit("step", snapshot)`` (the round's states of every live node of the run)
    and ``result()`` return (their next states, the estimates of those whose epoch ended). Two-phase,
    so that groups in other processes (services/runtime/node_workers.py) compute side by side."""

    def __init__(self, ds: Dataset, algo: str, settings: dict, inits: dict, uavs, clock: Callable[[], float] | None):
        nmeta = node_view(ds.meta)  # what a node of the deployment gets: no fault/outage/kill schedule
        self.slicer = EpochSlicer(ds)
        self.nodes = {u: registry.make_node(algo, u, nmeta, settings, inits[u]) for u in sorted(uavs)}
        est = estimation_values(settings)
        self.rounds, self.tol, self.clock = est.rounds, est.convergence_m, clock
        self.active: dict = {}
        self._out = None

    def submit(self, command: str, arg) -> None:
        if command == "start":
            self.active = {u: node_epoch(n, self.slicer.epoch(arg, u), self.rounds, self.tol, self.clock)
                           for u, n in self.nodes.items()}
            self._out = {u: next(g) for u, g in self.active.items()}
        elif command == "step":
            self._out = step_round(self.active, arg)
        else:
            raise ValueError(f"NodeGroup: unknown command {command!r}")

    def result(self):
        out, self._out = self._out, None
        return out


def run_node_epoch(groups: list, k: int) -> dict[int, NodeEstimate]:
    """Epoch k of every node of ``groups`` (:class:`NodeGroup` or alike) in lock-step rounds: each
    round every group gets the round's states of every live node in id order (a broadcast bus);
    the same numbers for any split of the nodes into groups. A group with ``shared_payload``
    (a worker process) is sent the states serialised once for all such groups."""
    for g in groups:
        g.submit("start", k)
    states: dict = {}
    for g in groups:
        states.update(g.result())
    results: dict[int, NodeEstimate] = {}
    while states:
        snapshot = dict(sorted(states.items()))
        payload = groups[0].shared_payload(snapshot) if hasattr(groups[0], "shared_payload") else snapshot
        for g in groups:
            g.submit("step", payload if hasattr(g, "shared_payload") else snapshot)
        states = {}
        for g in groups:
            new, done = g.result()
            states.update(new)
            results.update(done)
    return results


def run_algorithm(ds: Dataset, algo: str, seed: int, settings: dict,
                  progress: Callable[[int, int], None] | None = None,
                  clock: Callable[[], float] | None = None,
                  node_groups: Callable[..., list] | None = None) -> RunResult:
    """Run ``algo`` over every epoch of ``ds``; ``progress(k, K)`` is called after each epoch.
    ``clock`` (seconds, e.g. ``time.perf_counter``) times the steps and the run (``step_ms``,
    ``wall_s``); without one they are 0: the core reads no clock. ``node_groups(ds, algo,
    settings, inits, uavs, clock)``: how a per-UAV algorithm's nodes are split into groups (e.g.
    worker processes, services/runtime/node_workers.py); default one :class:`NodeGroup` of all."""
    tick = clock or (lambda: 0.0)
    meta = ds.meta
    slicer = EpochSlicer(ds)
    uavs = meta.uav_ids()
    K = meta.n_epochs()
    t = np.array([meta.epoch_time(k) for k in range(1, K + 1)])
    res = RunResult.empty(algo, seed, uavs, t)
    inits = initial_states(ds, seed)
    links: list[tuple] = []
    t_start = tick()
    if registry.kind(algo) == "swarm":
        est = registry.make_swarm(algo, meta, settings, inits)
        for k in range(1, K + 1):
            inputs = {u: slicer.epoch(k, u) for u in uavs}
            labels = slicer.range_labels(k)
            t0 = tick()
            out = est.step(inputs, labels, slicer.tdoa_labels(k))
            dt_ms = (tick() - t0) * 1e3
            for j, u in enumerate(uavs):
                e = out.get(u)
                if e is None:
                    continue
                if not e.step_ms:
                    e.step_ms = dt_ms  # the whole-swarm solve of this epoch
                _store(res, k - 1, j, e, links)
            if progress:
                progress(k, K)
    else:
        groups = (node_groups or _one_group)(ds, algo, settings, inits, uavs, clock)
        try:
            for k in range(1, K + 1):
                out = run_node_epoch(groups, k)
                for j, u in enumerate(uavs):
                    _store(res, k - 1, j, out[u], links)
                if progress:
                    progress(k, K)
        finally:
            for g in groups:
                getattr(g, "close", lambda: None)()
    res.wall_s = tick() - t_start
    res.links = np.array(links, dtype=LINK_DTYPE) if links else np.zeros(0, LINK_DTYPE)
    return res


def _one_group(ds, algo, settings, inits, uavs, clock) -> list:
    return [NodeGroup(ds, algo, settings, inits, uavs, clock)]


FAULT_RULE = "faulty when |fault_err| > fault_threshold_m * row sigma / uwb_sigma_m (3 sigma of the row's noise)"


def link_labels(ds: Dataset) -> np.ndarray:
    """Fault labels per (epoch, unordered pair): records (k, a, b, err, kind, thr).

    ``err`` = |fault_err| (m) and ``thr`` = the scoring threshold (m) of the link-epoch: it is
    *faulty* when err > thr. thr = ``meta.fault_threshold_for(row σ)``: 3σ of that row's own noise
    (README, "How to read the results"; the simulator's rows all carry uwb_sigma_m, so thr = fault_threshold_m exactly;
    MILUV: |bias| > 3·std, the issue's rule). Several range rows of one pair in one
    epoch (event-timestamped real data) are merged: the row with the largest err/thr counts, NaN
    (unknown) only if every row is unknown.
    """
    meta = ds.meta
    r = ds.table("ranges")
    dt = np.dtype([("k", np.int32), ("a", np.int32), ("b", np.int32), ("err", np.float64), ("kind", np.int16),
                   ("thr", np.float64)])
    if len(r["t"]) == 0:
        return np.zeros(0, dt)
    # epoch k covers (t_{k-1}, t_k]
    k = np.maximum(epoch_of(r["t"], meta.t_start, meta.epoch_dt_s), 1)
    a = np.minimum(r["a"], r["b"])
    b = np.maximum(r["a"], r["b"])
    err = np.abs(r["fault_err"])
    thr = meta.fault_threshold_for(r["sigma"])
    best: dict[tuple[int, int, int], tuple[float, int, float]] = {}
    for kk, aa, bb, ee, kind, th in zip(k.tolist(), a.tolist(), b.tolist(), err.tolist(), r["fault_kind"].tolist(),
                                        thr.tolist()):
        key = (kk, aa, bb)
        old = best.get(key)
        if old is None or (np.isnan(old[0]) and not np.isnan(ee)) or (ee * old[2] > old[0] * th):  # ee/th > old
            best[key] = (ee, kind, th)
    out = np.zeros(len(best), dt)
    for i, (key, (ee, kind, th)) in enumerate(sorted(best.items())):
        out[i] = (*key, ee, kind, th)
    return out
