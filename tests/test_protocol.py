"""The in-process bus's per-round view and index (protocol.py PeerView, RoundIndex)."""

import numpy as np

from swarmnav.estimators.base import NodeState
from swarmnav.protocol import PeerView, RoundIndex


def _states(n: int, seed: int = 3) -> dict[int, NodeState]:
    rng = np.random.default_rng(seed)
    ids = sorted(rng.choice(np.arange(1, 4 * n), n, replace=False).tolist())
    out = {}
    for j in ids:
        others = [o for o in ids if o != j]
        rg = {int(o): float(rng.uniform(10, 400)) for o in rng.choice(others, 5, replace=False)}
        br = {int(o): (0.1, 0.2, 0.01) for o in rng.choice(others, 3, replace=False)}
        out[j] = NodeState(j, 4, int(rng.random() < 0.2), 4.0, rng.uniform(-2000, 2000, 3) * [1, 1, 0.05],
                           np.eye(3), np.zeros(3), ranges=rg, bearings=br)
    return out


def test_peer_view_is_the_rounds_states_without_the_node_in_id_order():
    states = _states(30)
    u = sorted(states)[7]
    view = PeerView(states, u, RoundIndex(states))
    expect = {j: s for j, s in states.items() if j != u}
    assert list(view) == list(expect) and len(view) == len(expect) and dict(view.items()) == expect
    assert u not in view and view.get(u) is None and sorted(states)[0] in view


def test_round_index_answers_as_a_scan_of_every_state():
    states = _states(200)
    index = RoundIndex(states)
    radius = 400.0
    for u in list(states)[::17]:
        bearings, ranged = index.mentions(u)
        assert bearings == [(j, s.bearings[u]) for j, s in states.items() if u in s.bearings]
        assert ranged == [j for j, s in states.items() if u in s.ranges]
        p = states[u].pos + 50.0
        near = set(index.round0_near(p, radius))
        truth = {j for j, s in states.items() if s.r == 0 and np.sum((s.pos - p) ** 2) <= radius ** 2}
        assert truth <= near  # every one within the radius; the caller tests the distance
        assert all(states[j].r == 0 for j in near)
