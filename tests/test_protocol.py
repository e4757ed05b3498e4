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


def test_round_index_near_keeps_a_peer_at_exactly_the_radius_and_survives_a_diverged_node():
    """Edge cases an outside review found: a peer at exactly the radius whose cell, by rounding, lies
    two cells from the node's (the scan keeps it: d² <= R²); a NaN own position and a radius too
    small for the grid, which raised in the in-process run (the scan just finds no one near)."""
    s = {1: NodeState(1, 3, 0, 3.0, np.array([30.0, 0.0, 0.0]), np.eye(3), np.zeros(3)),
         2: NodeState(2, 3, 0, 3.0, np.array([500.0, 0.0, 0.0]), np.eye(3), np.zeros(3))}
    p = np.array([-1e-17, 0.0, 0.0])
    assert float(np.sum((s[1].pos - p) ** 2)) <= 30.0 ** 2  # the scan keeps peer 1
    assert 1 in RoundIndex(s).round0_near(p, 30.0)
    assert RoundIndex(s).round0_near(np.array([np.nan, 0.0, 0.0]), 30.0) == [1, 2]  # the scan's candidates
    assert RoundIndex(s).round0_near(p, 1e-310) == [1, 2]
    rng = np.random.default_rng(5)  # and at random: every peer within R is a candidate
    for _ in range(300):
        R = float(rng.choice([1.0, 30.0, 400.0]))
        p = rng.uniform(-3 * R, 3 * R, 3)
        d = rng.normal(size=3)
        q = p + R * d / np.linalg.norm(d)  # on the sphere, up to rounding
        st = {1: NodeState(1, 3, 0, 3.0, q, np.eye(3), np.zeros(3))}
        if float(np.sum((q - p) ** 2)) <= R * R:
            assert RoundIndex(st).round0_near(p, R) == [1]
