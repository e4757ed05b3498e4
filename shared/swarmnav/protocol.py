"""The per-epoch message-iteration protocol, written once for both transports.

:func:`node_epoch` is one node's side of epoch k as a generator: it yields each state the node
must broadcast and receives, in return, the dict of the other live nodes' states of that same
round. The in-process transport (:func:`run_epoch_in_process`) and the Zenoh ``uav_node``
service both drive this generator, so with synchronous rounds they compute the same numbers.

Round structure (docs/architecture.md): round 0 = predicted state (+ own ranges); round r = 1..R uses the
neighbours' round r-1 states. Convergence is decided swarm-wide from the round's states, which
every node receives, so every node stops after the same round; an estimator whose last round is
known in advance (``last_round``: the joint snapshot's round 1) does not broadcast that round's
state, so an epoch is then one message round.

Pure: the core reads no clock. A caller that wants the estimator's time per epoch passes its clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Iterator, Mapping

import numpy as np

from .dataset import EpochInput
from .estimators.base import NodeEstimate, NodeEstimator, NodeState

NodeEpoch = Generator[NodeState, dict[int, NodeState], NodeEstimate]


def swarm_converged(own: NodeState, peers: dict[int, NodeState], tol_m: float) -> bool:
    """True when every live node's last position change is below tol_m."""
    return own.delta_m < tol_m and all(s.delta_m < tol_m for s in peers.values())


def _no_clock() -> float:
    return 0.0


def node_epoch(est: NodeEstimator, inp: EpochInput, rounds: int, tol_m: float,
               clock: Callable[[], float] | None = None) -> NodeEpoch:
    """One node's epoch. Yields states to broadcast; receives peers' same-round states.

    The returned NodeEstimate carries ``step_ms``: time spent in the estimator for this epoch
    (every round and the final covariance), excluding time suspended waiting for peers, measured
    with ``clock`` (seconds, e.g. the service's ``time.perf_counter``); 0 without a clock.
    """
    clock = clock or _no_clock
    busy = 0.0
    t0 = clock()
    state = est.begin_epoch(inp)
    busy += clock() - t0
    peers = yield state
    done, unsent = 0, None
    last = est.last_round()
    for r in range(1, rounds + 1):
        t0 = clock()
        state = est.iterate(r, peers)
        busy += clock() - t0
        done = r
        if r == last:  # every node ends here: a state nobody reads now is not sent
            unsent = state
            break
        peers = yield state
        if swarm_converged(state, peers, tol_m):
            break
    t0 = clock()
    out = est.end_epoch()
    busy += clock() - t0
    out.rounds, out.unsent = done, unsent
    out.step_ms = busy * 1e3
    return out


class RoundIndex:
    """What every node of an in-process round looks up in that round's states, built once for the
    round (lazily) instead of once per node: who reports a range to or a bearing of a node, and
    whose round-0 position lies near a point. With it a node's reading of the swarm
    (graph_links.take_round0) costs O(its neighbourhood), not O(N) — the broadcast bus knows every
    state anyway; a node of the Zenoh transport, which receives them one by one, scans them."""

    def __init__(self, states: dict[int, NodeState]):
        self.states = states
        self._mentions: dict[int, tuple[list, list]] | None = None
        self._grids: dict[float, tuple[dict, np.ndarray, np.ndarray]] = {}

    def mentions(self, uav: int) -> tuple[list[tuple[int, tuple]], list[int]]:
        """([(j, j's bearing of ``uav``)], [j that reports a range to ``uav``]), j in id order."""
        if self._mentions is None:
            self._mentions = {}
            for j, s in self.states.items():  # in id order
                for t, b in (s.bearings or {}).items():
                    self._mentions.setdefault(t, ([], []))[0].append((j, b))
                for t in (s.ranges or {}):
                    self._mentions.setdefault(t, ([], []))[1].append(j)
        return self._mentions.get(uav, ([], []))

    def round0_near(self, p: np.ndarray, radius: float) -> list[int]:
        """The nodes with a round-0 state whose position may lie within ``radius`` of p (ENU m): every
        one that does, and some that do not (the caller tests the distance)."""
        if radius not in self._grids:
            ids = [j for j, s in self.states.items() if s.r == 0]
            pos = np.array([self.states[j].pos for j in ids], float).reshape(-1, 3)
            cells: dict[tuple, list[int]] = {}
            with np.errstate(over="ignore", invalid="ignore"):  # a NaN or far position: a cell never searched
                cell_of = np.floor(pos / radius).astype(np.int64).tolist()
            for n, c in enumerate(map(tuple, cell_of)):
                cells.setdefault(c, []).append(n)
            self._grids[radius] = (cells, np.array(ids, np.int64), pos)
        cells, ids, _ = self._grids[radius]
        # every cell the ball may touch, bounds padded against the divisions' rounding (a peer at
        # exactly the radius can land two cells away): extra candidates are fine, a missed one is not
        pad = radius * (1.0 + 1e-9)
        lo = [(float(v) - pad) / radius for v in p]
        hi = [(float(v) + pad) / radius for v in p]
        if not all(abs(v) < 2.0 ** 52 for v in lo + hi):  # a diverged (NaN) p, or a radius too small
            return self.round0_ids()  # for the grid: the caller's distance test decides, as in the scan
        (x0, y0, z0), (x1, y1, z1) = map(math.floor, lo), map(math.floor, hi)
        rows = [n for cx in range(x0, x1 + 1) for cy in range(y0, y1 + 1) for cz in range(z0, z1 + 1)
                for n in cells.get((cx, cy, cz), ())]
        return ids[sorted(rows)].tolist()

    def round0_ids(self) -> list[int]:
        return [j for j, s in self.states.items() if s.r == 0]


class PeerView(Mapping):
    """The round's states of every live node but ``own`` (a read-only dict view, in id order: no
    copy per node) and the round's :class:`RoundIndex` as ``index``."""

    __slots__ = ("_states", "_own", "index")

    def __init__(self, states: dict[int, NodeState], own: int, index: RoundIndex | None = None):
        self._states, self._own, self.index = states, own, index

    def __getitem__(self, j: int) -> NodeState:
        if j == self._own:
            raise KeyError(j)
        return self._states[j]

    def __iter__(self) -> Iterator[int]:
        return (j for j in self._states if j != self._own)

    def __len__(self) -> int:
        return len(self._states) - (self._own in self._states)

    def __contains__(self, j: object) -> bool:
        return j != self._own and j in self._states

    def get(self, j, default=None):  # Mapping.get goes through __getitem__ and an exception: ~3x slower
        return default if j == self._own else self._states.get(j, default)


def step_round(epochs: dict[int, NodeEpoch], snapshot: dict[int, NodeState]) \
        -> tuple[dict[int, NodeState], dict[int, NodeEstimate]]:
    """One round of the in-memory bus for the nodes of ``epochs`` (each a node's epoch generator,
    in id order; a node whose epoch ends is removed): every one receives ``snapshot``, the round's
    states of every live node (of these and of any other group of the same run), in id order.
    Returns (the next state of each node still in the epoch, the estimate of each that ended)."""
    index = RoundIndex(snapshot)  # shared by every node's view of this round
    states: dict[int, NodeState] = {}
    done: dict[int, NodeEstimate] = {}
    for u, g in list(epochs.items()):
        try:
            states[u] = g.send(PeerView(snapshot, u, index))
        except StopIteration as stop:
            done[u] = stop.value
            del epochs[u]
    return states, done


def run_epoch_in_process(epochs: dict[int, NodeEpoch],
                         last_states: dict[int, NodeState] | None = None) -> dict[int, NodeEstimate]:
    """In-memory transport: drive every live node's epoch generator in lock-step rounds.

    Every node receives all other live nodes' states of the same round (a broadcast bus).
    Iteration is in UAV-id order; the result does not depend on it. If ``last_states`` is given,
    it is filled with each node's last broadcast state of the epoch (what a peer could query).
    """
    active = dict(sorted(epochs.items()))
    states: dict[int, NodeState] = {u: next(g) for u, g in active.items()}
    results: dict[int, NodeEstimate] = {}
    while active:
        snapshot = states
        states, done = step_round(active, snapshot)
        results.update(done)
        if last_states is not None:
            last_states.update((u, snapshot[u]) for u in done)
    return results
