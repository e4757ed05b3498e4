"""A node's neighbourhood (``[estimation.graph] neighbourhood_radius_m``, graph_links.take_round0).

With a radius, a node reads the ranges of, and solves with, only the UAVs it measured or that
measured it, those within the radius, and the other ends of their ranges — so its work per round
is bounded by its neighbourhood, not the swarm (docs/scale.md). Without one (the default), or with
one wider than the swarm, every live UAV is in every neighbourhood and the estimates are those of
before, bit for bit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmnav.config import load_config
from swarmnav.dataset import EpochSlicer
from swarmnav.estimators.graph import AtvfgEstimator
from swarmnav.initial import initial_states
from swarmnav.protocol import node_epoch, run_epoch_in_process
from swarmnav.sim import simulate

REPO = Path(__file__).resolve().parents[1]


def _run(sc, ds, radius, epochs):
    s = sc.estimation.model_dump()
    s["delta_l_m"] = None
    s["graph"] = dict(s.get("graph") or {}, neighbourhood_radius_m=radius)
    inits = initial_states(ds, 1)
    uavs = ds.meta.uav_ids()
    nodes = {u: AtvfgEstimator(u, ds.meta, s, inits[u]) for u in uavs}
    sl = EpochSlicer(ds)
    pos, hoods = [], []
    for k in range(1, epochs + 1):
        out = run_epoch_in_process({u: node_epoch(nodes[u], sl.epoch(k, u), s["rounds"], s["convergence_m"])
                                    for u in uavs})
        pos.append(np.array([out[u].pos for u in uavs]))
        hoods.append({u: list(nodes[u].cache.nodes) if nodes[u].cache else [] for u in uavs})
    return np.array(pos), hoods, nodes


def test_a_radius_wider_than_the_swarm_changes_nothing():
    sc = load_config(REPO / "configs" / "smoke.toml")
    ds = simulate(sc, 1)
    a, _, _ = _run(sc, ds, None, 8)
    b, _, _ = _run(sc, ds, 1e6, 8)
    assert np.array_equal(a, b)


def test_neighbourhood_bounded_and_holds_every_measured_neighbour():
    sc = load_config(REPO / "configs" / "scale.toml", ["swarm.n_uavs=60", "scenario.duration_s=3"])
    ds = simulate(sc, 1)
    _, hoods, nodes = _run(sc, ds, 400.0, 3)
    uavs = ds.meta.uav_ids()
    sizes = [len(h) for h in hoods[-1].values()]
    # the 60-UAV box is ~1.2 km wide: a 400 m radius (+ the ends of the neighbours' ranges) leaves
    # most of the swarm out of each node's rounds
    assert max(sizes) < len(uavs) and np.median(sizes) < 0.8 * len(uavs)
    for u in uavs:
        nd = nodes[u]
        assert set(nd.range_rows) <= set(nd.cache.nodes)  # every ranged neighbour is solved with
        # the residual matrix: every pair has an end among the 1-hop neighbours (or the node itself)
        for a, b in nd.cache.pairs.pairs.tolist():
            assert a in nd.hood1 or b in nd.hood1 or u in (a, b)
    # and without a radius every live UAV is in every node's rounds
    _, full, _ = _run(sc, ds, None, 2)
    assert all(len(h) == len(uavs) for h in full[-1].values())


def test_round0_keeps_the_first_report_of_a_pair_in_id_order():
    """take_round0 merges its neighbours' ranges keyed by the unordered pair: where two neighbours
    report the same pair (each measured it: two numbers), the lower id's report is the one kept, a
    pair already known keeps its range, and a state filed under another id than its own is read as
    that id's (the merge goes through NodeState.range_pairs, built once per state)."""
    from types import SimpleNamespace

    from swarmnav.estimators.base import NodeState
    from swarmnav.estimators.graph_links import take_round0

    def state(u, ranges):
        return NodeState(u, 1, 0, 1.0, np.zeros(3), np.eye(3), np.zeros(3), ranges=ranges, n_links=len(ranges))

    peers = {2: state(2, {3: 10.0, 5: 20.0}), 3: state(3, {2: 11.0, 4: 30.0}), 4: state(9, {3: 31.0, 6: 40.0})}
    node = SimpleNamespace(uav=1, hood_radius=None, round0_pending=True, hood1={2, 3, 4}, hood=set(),
                           peer_bearings={}, peer_ranges={(5, 6): 99.0, (2, 5): 21.0}, peer_links={},
                           p_loc=np.zeros(3), relink=0)
    nodes = take_round0(node, peers)
    assert node.peer_ranges == {(2, 3): 10.0, (2, 5): 21.0, (3, 4): 30.0, (4, 6): 40.0, (5, 6): 99.0}
    assert nodes == (2, 3, 4) and node.hood == {2, 3, 4, 5, 6}
    assert node.peer_links == {2: 2, 3: 2, 4: 2}
    assert peers[2].range_pairs == ({(2, 3): 10.0, (2, 5): 20.0}, (3, 5))
