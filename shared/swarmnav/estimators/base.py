"""Per-UAV estimator interface driven round by round by the epoch protocol (``swarmnav.protocol``).

Every distributed algorithm (atvfg, fg, fkf, ins) implements :class:`NodeEstimator`; the Zenoh
``uav_node`` service hosts them unchanged. The centralised oracle implements
:class:`SwarmEstimator` (one object for the whole swarm; in-process only).

Epoch k of one node, as the protocol drives it::

    s0  = est.begin_epoch(inp)               # predict with IMU k-1 -> k, add own GNSS etc.; round-0 state
    s_r = est.iterate(r, peers_{r-1})         # r = 1..R: solve with the neighbours' round r-1 states
    e   = est.end_epoch()                     # final estimate, link classes, timing

``peers`` maps UAV id -> that node's NodeState of the previous round, for every *live* node
(including nodes out of ranging reach: the estimator decides whom to use). Anything
order-sensitive must iterate peers sorted by id, so the in-process and Zenoh transports give
identical results. States are plain float64 numbers so they cross the wire unchanged.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cached_property

import numpy as np

from ..dataset import DatasetMeta, EpochInput


class LinkClass(IntEnum):
    """Double-threshold hypotheses of the paper (§2.3.2)."""

    H0_FAILED = 0  # residual > Δh: excluded from the graph
    H1_INTERFERED = 1  # Δl < residual <= Δh: down-weighted with eq. 24
    H2_NORMAL = 2  # residual <= Δl: full weight


def tuned_settings(settings: dict | None) -> dict:
    """The estimator settings with the optional ``[estimation.graph]`` table (``settings["graph"]``:
    tuning overrides by settings key) merged over the top level — one place for every estimator."""
    s = dict(settings or {})
    s.update(s.get("graph") or {})
    return s


@dataclass
class NodeState:
    """What a node broadcasts each round. Positions ENU m, velocities ENU m/s."""

    uav: int
    k: int
    r: int
    t: float
    pos: np.ndarray  # (3,)
    pos_cov: np.ndarray  # (3,3) m^2 — as the sender wants receivers to use it (see double counting)
    vel: np.ndarray  # (3,)
    delta_m: float = float("inf")  # position change since the previous round (swarm-wide convergence)
    # round 0 only: the ranges this node measured this epoch, other id -> metres (for the residual matrix)
    ranges: dict[int, float] = field(default_factory=dict)
    # round 0 only: this node's relative az/el observations (eq. 27, ENU), target id ->
    # (azimuth rad, elevation rad, sigma rad), so the target can use them too
    bearings: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    # body FLU -> ENU attitude (w, x, y, z) of the sender, None = not given: receivers place the
    # sender's UWB tags (lever arms in meta) with it; constant over an epoch's rounds
    quat: np.ndarray | None = None
    # round 0: the number of cooperative links the sender fuses this epoch (ranged neighbours +
    # tdoa links; 0 = not given, receivers count ``ranges``) — the split-CI inflation of its state
    n_links: int = 0
    # round 0: the sender's smoothed positions (ENU m) of the epochs in its relink window, epoch k
    # -> (3,) (relink.py RelinkedCommit; empty when relinking is off)
    traj: dict[int, np.ndarray] = field(default_factory=dict)

    @cached_property
    def bearing_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """``bearings`` as arrays, sorted by target: (targets (K,) int, (az, el, σ) (K, 3) rad) —
        read by every receiver's joint snapshot (joint.azel_observations), built once per state."""
        if not self.bearings:
            return _NO_TARGETS, _NO_BEARINGS
        targets = sorted(self.bearings)
        return np.array(targets, np.int64), np.array([self.bearings[t] for t in targets], float).reshape(-1, 3)

    @cached_property
    def range_pairs(self) -> tuple[dict[tuple[int, int], float], tuple[int, ...]]:
        """``ranges`` keyed by the unordered pair (lower id, higher id) -> m (floats), and the other
        ends' ids — merged by every receiver's round 0 (graph_links.take_round0), built once per state."""
        return range_pairs_of(self.uav, self.ranges)


def range_pairs_of(uav: int, ranges: dict) -> tuple[dict[tuple[int, int], float], tuple[int, ...]]:
    """UAV ``uav``'s ``ranges`` (other id -> m) keyed by the unordered pair (lower id, higher id), as
    floats, and the other ends' ids (:attr:`NodeState.range_pairs`)."""
    u = int(uav)
    ids = tuple(map(int, ranges))
    return {((u, o) if u < o else (o, u)): float(d) for o, d in zip(ids, ranges.values())}, ids


_NO_TARGETS, _NO_BEARINGS = np.zeros(0, np.int64), np.zeros((0, 3))


@dataclass
class LinkInfo:
    """One link's classification in an epoch, as seen by the classifying node."""

    other: int
    cls: LinkClass
    residual_m: float
    weight: float  # eq. 24 weight actually applied (1 for H2, 0 for H0)


@dataclass
class NodeEstimate:
    """Final per-epoch output of one node."""

    uav: int
    k: int
    t: float
    pos: np.ndarray  # (3,) ENU m
    vel: np.ndarray  # (3,) ENU m/s
    pos_cov: np.ndarray  # (3,3) m^2 (the node's own marginal, for NEES)
    quat: np.ndarray | None = None  # (4,) w,x,y,z body FLU -> ENU
    links: list[LinkInfo] = field(default_factory=list)
    rounds: int = 0
    step_ms: float = 0.0  # wall time of this epoch's estimator work, excluding waits for peers
    delta_h_m: float | None = None  # the upper threshold used this epoch (atvfg)
    delta_l_m: float | None = None
    unsent: "NodeState | None" = None  # the last round's state when it was not broadcast (last_round)


@dataclass
class InitialState:
    """A node's initial knowledge at epoch 0 (coarse alignment: initial.py)."""

    t: float
    pos: np.ndarray
    vel: np.ndarray
    quat: np.ndarray  # w,x,y,z body FLU -> ENU
    pos_sigma: np.ndarray  # (3,)
    vel_sigma: float
    att_sigma: np.ndarray  # (3,) rad roll, pitch, yaw


class NodeEstimator(abc.ABC):
    """One UAV's estimator. No I/O; deterministic given its inputs."""

    name: str = "base"

    def __init__(self, uav: int, meta: DatasetMeta, settings: dict, init: InitialState):
        self.uav = uav
        self.meta = meta
        self.settings = settings
        self.init = init

    @abc.abstractmethod
    def begin_epoch(self, inp: EpochInput) -> NodeState: ...

    def iterate(self, r: int, peers: dict[int, NodeState]) -> NodeState:
        """One message-iteration round. Default: nothing cooperative, re-publish the state."""
        s = self._last_state
        return NodeState(self.uav, s.k, r, s.t, s.pos, s.pos_cov, s.vel, 0.0)

    def last_round(self) -> int | None:
        """The round after which every node of the swarm ends the epoch, known before it is run
        (the same for every node of a configuration), so that round's state is not broadcast:
        nobody would read it. None: the swarm decides after each round whether it converged."""
        return None

    @abc.abstractmethod
    def end_epoch(self) -> NodeEstimate: ...

    def bootstrap(self, t: float, peers: dict[int, NodeState], inp: EpochInput | None) -> None:
        """Restarted node: re-initialise position/velocity from peers' states and GNSS (optional)."""
        raise NotImplementedError(f"{self.name} cannot rejoin after a restart")


class SwarmEstimator(abc.ABC):
    """A whole-swarm estimator (the centralised oracle). In-process only."""

    name: str = "central"

    @abc.abstractmethod
    def step(self, inputs: dict[int, EpochInput], range_labels: dict[str, np.ndarray],
             tdoa_labels: dict[str, np.ndarray] | None = None) -> dict[int, NodeEstimate]: ...
