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

from collections.abc import Callable, Generator

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


def run_epoch_in_process(epochs: dict[int, NodeEpoch],
                         last_states: dict[int, NodeState] | None = None) -> dict[int, NodeEstimate]:
    """In-memory transport: drive every live node's epoch generator in lock-step rounds.

    Every node receives all other live nodes' states of the same round (a broadcast bus).
    Iteration is in UAV-id order; the result does not depend on it. If ``last_states`` is given,
    it is filled with each node's last broadcast state of the epoch (what a peer could query).
    """
    states: dict[int, NodeState] = {u: next(g) for u, g in sorted(epochs.items())}
    active = dict(sorted(epochs.items()))
    results: dict[int, NodeEstimate] = {}
    while active:
        snapshot = dict(states)
        for u, g in list(active.items()):
            try:
                states[u] = g.send({j: s for j, s in snapshot.items() if j != u})
            except StopIteration as stop:
                results[u] = stop.value
                if last_states is not None:
                    last_states[u] = snapshot[u]
                del active[u]
                states.pop(u, None)
    return results
