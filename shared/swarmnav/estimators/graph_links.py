"""The per-UAV graph's cooperative links of an epoch: what a node measured of its neighbours (ranges,
az/el: broadcast in its round-0 state), where a neighbour's tag is, and the epoch's
:class:`~swarmnav.estimators.rounds.RoundCache` the rounds solve on.

Choices: range timestamps inside the epoch are treated as at the epoch time; the node's own tag
lever arm is applied with its current attitude, a neighbour's with its broadcast attitude
(``peer_levers``); an az/el observation is a separate sensor from UWB ranging (``azel_weight``).
The neighbours' az/el observations *of this node* enter turned around: the direction j -> i at
(az, el) is i -> j at (az + π, −el) (``reverse_azel``).
"""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np

from . import detection as det
from ..dataset import EpochInput
from ..models.base import wrap_angle
from .base import NodeState, range_pairs_of
from .rounds import RoundCache, tdoa_residuals

# the per-UAV graph estimator (graph.GraphEstimator) whose epoch state these functions read
GraphEstimator = Any


def rot3(q: np.ndarray) -> gtsam.Rot3:
    """gtsam rotation of a (w, x, y, z) quaternion."""
    return gtsam.Rot3.Quaternion(float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def detect_links(node: GraphEstimator, c: RoundCache, P: np.ndarray):
    """atvfg's double-threshold test on the round's residual matrix (positions P in ``c.nodes``
    order): (weight per ranged neighbour, (residual m, class) per own link, Δh m, the residuals);
    without detection every weight is 1 and Δh and the residuals are None."""
    weights, res_own = {o: 1.0 for o in c.nb}, {}
    if not (node.detect and c.nb):
        return weights, res_own, None, None
    res = c.pairs.residuals(P)
    if c.rng_has_lever:
        # own links: residual between the two tags (own lever arm with the own attitude, the
        # neighbour's with its broadcast one); other pairs stay origin-to-origin (no tag ids)
        res = res.copy()
        me = P[c.idx[node.uav]]
        for i, o in zip(c.mine, c.mine_other):
            m = c.rng_owner == o
            if m.any():
                d = me + c.rng_lever[m] - P[c.idx[o]]
                res[i] = abs(float(np.mean(c.rng_z[m] - np.linalg.norm(d, axis=1))))
    dh, cls, w = det.detect(res, node.delta_l, node.window, node.floor_factor, node.kmeans_backend, node.ceil_factor,
                            node.cap_h1)
    for i, o in zip(c.mine, c.mine_other):
        if o in weights:
            weights[o] = float(w[i])
            res_own[o] = (float(res[i]), int(cls[i]))
    return weights, res_own, dh, res


def tdoa_weights(node: GraphEstimator, c: RoundCache, P: np.ndarray) -> np.ndarray:
    """Weights of the cooperative tdoa links: 1 (Gaussian) by default; with ``tdoa_detection``
    (atvfg only) the double-threshold test on each link's residual at the round's positions,
    with Δl and the Δh of the ranges (this epoch's, or from the residual window) — measured
    worse on MILUV (docs/miluv.md "Fifth pass"), off by default."""
    w = np.ones(len(c.tdoa))
    if not (node.detect and node.tdoa_detection and c.tdoa):
        return w
    res = tdoa_residuals(c, P, P[c.idx[node.uav]], normalise=False)
    dh = node.delta_h
    if dh is None:
        dh = det.upper_threshold(node.window.values(np.zeros(0)), node.delta_l, node.floor_factor,
                                 node.kmeans_backend, node.ceil_factor)
    return det.classify_and_weigh(res, node.delta_l, dh, node.cap_h1)[1]


def own_ranges(inp: EpochInput, uav: int, uavs: set[int]) -> tuple[dict[int, float], dict[int, list[int]]]:
    """Inter-UAV ranges node ``uav`` took part in: (other UAV -> mean range m, other UAV -> rows)."""
    rows: dict[int, list[int]] = {}
    rm = inp.range_m.tolist()  # Python floats: the loop reads each once
    for i, (o, r) in enumerate(zip(map(int, inp.range_other.tolist()), rm)):
        if o in uavs and o != uav and math.isfinite(r) and r > 0:
            rows.setdefault(o, []).append(i)
    return {o: rm[r[0]] if len(r) == 1 else float(np.mean(inp.range_m[r])) for o, r in sorted(rows.items())}, rows


def own_bearings(inp: EpochInput, uav: int, rel_sigma: float) -> dict[int, tuple[float, float, float]]:
    """This epoch's az/el observations to other UAVs, one per target (the first), to broadcast:
    target -> (azimuth wrapped into [−π, π] (the state frame's range), elevation, σ) rad; an
    elevation beyond ±π/2 is not a direction and is not broadcast."""
    out: dict[int, tuple[float, float, float]] = {}
    az = wrap_angle(inp.rel_az).tolist()
    for o, a, el, sg in zip(map(int, inp.rel_target.tolist()), az, inp.rel_el.tolist(), inp.rel_sigma.tolist()):
        if o != uav and o not in out and abs(el) <= np.pi / 2:
            out[o] = (a, el, sg if sg > 0 else float(rel_sigma))
    return out


def peer_lever(node: GraphEstimator, peers: dict[int, NodeState], other: int, tag: int) -> np.ndarray:
    """ENU offset of a neighbour's tag from its broadcast position: R(q_peer)·lever (zero when
    ``peer_levers`` is off, the neighbour sends no attitude or the tag has no lever arm)."""
    q = peers[other].quat
    lev = node.tag_levers.get(other, {}).get(int(tag))
    if not node.peer_levers or q is None or lev is None or not np.any(lev):
        return np.zeros(3)
    return rot3(q).matrix() @ lev


def take_round0(node: GraphEstimator, peers: dict[int, NodeState]) -> tuple[int, ...]:
    """Read what the round's states carry for this node and return the live nodes of its
    neighbourhood, sorted (the round cache's ``nodes`` without the node itself).

    The neighbourhood: the node's 1-hop neighbours — the UAVs it ranged, observed (az/el) or shares
    a passive row with, those whose round-0 state reports a range to it or a bearing of it, and
    those whose round-0 position is within ``neighbourhood_radius_m`` of its epoch prior (None:
    every live UAV, the whole swarm) — plus the other ends of the ranges those neighbours report
    (2-hop: the residual matrix holds every ranged pair with at least one end among the 1-hop
    neighbours). Only 1-hop neighbours' ranges and link counts are read, so a node's work per round
    grows with its neighbourhood, not with the swarm (docs/scale.md)."""
    me = node.uav
    radius2 = None if node.hood_radius is None else node.hood_radius ** 2
    near = []
    index = getattr(peers, "index", None)  # the in-process bus's RoundIndex (protocol.py), if any
    # only round-0 states carry ranges, bearings and trajectories, and they are the first round's
    # peers: later rounds do not scan the swarm
    if node.round0_pending and index is not None:  # looked up: O(neighbourhood)
        bearings_of_me, ranged_me = index.mentions(me)
        for j, b in bearings_of_me:
            if j in peers:
                node.peer_bearings[j] = b
                node.hood1.add(j)
        node.hood1.update(j for j in ranged_me if j in peers)
        cand = index.round0_ids() if radius2 is None else index.round0_near(node.p_loc, node.hood_radius)
        near = [j for j in cand if j != me and j not in node.hood1 and j in peers]
    for j, s in (peers.items() if node.round0_pending and index is None else ()):  # O(live peers)
        if s.bearings and me in s.bearings:
            node.peer_bearings[j] = s.bearings[me]
            node.hood1.add(j)
        elif s.ranges and me in s.ranges:
            node.hood1.add(j)
        elif s.r == 0:
            near.append(j)
    if near and radius2 is None:
        node.hood1.update(near)  # no neighbourhood radius: the whole swarm
    elif near:
        d = np.array([peers[j].pos for j in near]) - node.p_loc
        node.hood1.update(j for j, d2 in zip(near, np.einsum("ij,ij->i", d, d).tolist()) if d2 <= radius2)
    if not node.round0_pending:
        return tuple(sorted(u for u in node.hood if u in peers))
    node.round0_pending = False
    reports = []  # the neighbours' ranges, (a, b), a ≤ b -> m, in id order (the peers' order)
    for j in sorted(node.hood1):
        s = peers.get(j)
        if s is not None and (s.ranges or s.n_links):  # round-0 states carry ranges and link count
            node.peer_links[j] = max(len(s.ranges), int(s.n_links))
            pairs, ends = s.range_pairs if s.uav == j else range_pairs_of(j, s.ranges)
            reports.append(pairs)
            node.hood.update(ends)
    merged: dict[tuple[int, int], float] = {}
    for pairs in reversed(reports):  # the first report of a pair (in id order) is the one kept
        merged.update(pairs)
    merged.update(node.peer_ranges)  # and a pair known already keeps its range
    node.peer_ranges = merged
    node.hood.update(node.hood1)
    node.hood.discard(me)
    nodes = tuple(sorted(u for u in node.hood if u in peers))
    if node.relink > 0:  # the trajectories only a relinked commit reads
        for j in nodes:
            if peers[j].r == 0:
                node.relinker.peer_traj[j] = peers[j].traj
    return nodes


def own_hood(inp: EpochInput, uav: int, range_rows: dict[int, list[int]], tdoa_coop: list[int], ends_of) -> set[int]:
    """The UAVs node ``uav`` measured this epoch: ranged, observed (az/el) or in a passive row with."""
    hood = set(range_rows)
    hood.update(int(o) for o in inp.rel_target)
    for i in tdoa_coop:
        hood.update(nd for nd, _ in ends_of(inp, i))
    hood.discard(uav)
    return hood


def round_cache(node: GraphEstimator, peers: dict[int, NodeState], hood: tuple[int, ...]) -> RoundCache:
    """The epoch's link structure among the node and its live neighbourhood ``hood`` (take_round0;
    reads the node's epoch state: its input, own ranges and rows, the neighbours' round-0 ranges
    and bearings, its attitude)."""
    nodes = sorted(set(hood) | {node.uav})
    idx = {u: i for i, u in enumerate(nodes)}
    ranges = dict(node.peer_ranges)
    for o, d in node.my_ranges.items():
        ranges[(min(node.uav, o), max(node.uav, o))] = d
    pairs = det.RangePairs(nodes, ranges)
    pl = pairs.pairs.tolist()
    mine = [i for i, (a, b) in enumerate(pl) if node.uav in (a, b)]
    nb = sorted(o for o in node.range_rows if o in peers)
    owner = [o for o in nb for _ in node.range_rows[o]]
    c = RoundCache(key=(hood, len(node.peer_ranges), len(node.peer_bearings)), k=node.k,
                   nodes=nodes, idx=idx, pairs=pairs, mine=mine,
                   mine_other=[int(pl[i][1] if pl[i][0] == node.uav else pl[i][0]) for i in mine], nb=nb,
                   rng_owner=np.array(owner, int), rng_node=np.array([idx[o] for o in owner], int))
    Rm = node.pose.rotation().matrix()
    _range_rows(node, peers, c, np.array([i for o in nb for i in node.range_rows[o]], int), owner, Rm)
    if node.use_azel and node.rel_sigma:
        _azel_rows(node, peers, c)
    if node.use_tdoa:
        _tdoa_rows(node, peers, c, Rm)
    return c


def _range_rows(node: GraphEstimator, peers, c: RoundCache, rows: np.ndarray, owner: list[int], Rm: np.ndarray):
    if not len(rows):
        return
    inp = node.inp
    c.rng_lever = np.array([node.tags.get(int(t), np.zeros(3)) for t in inp.range_tag_self[rows]]) @ Rm.T
    if node.peer_levers:
        # the neighbour's tag: lever arm rotated with its broadcast attitude (the own one enters
        # as rng_lever, so the range is between the two tags)
        c.rng_lever = c.rng_lever - np.array([peer_lever(node, peers, int(o), int(t))
                                              for o, t in zip(owner, inp.range_tag_other[rows])])
    c.rng_sig2 = np.where(inp.range_sigma[rows] > 0, inp.range_sigma[rows], node.uwb_sigma) ** 2
    c.rng_has_lever = bool(node.peer_levers and np.any(c.rng_lever))
    c.rng_z = inp.range_m[rows]


def _azel_rows(node: GraphEstimator, peers, c: RoundCache):
    # own observations (observer = this node), then the neighbours' observations of this node
    # turned around
    inp = node.inp
    targets, sigma = inp.rel_target.tolist(), inp.rel_sigma.tolist()  # Python numbers: read one by one
    az, el = inp.rel_az.tolist(), inp.rel_el.tolist()
    ai = [i for i, o in enumerate(targets) if int(o) in peers]
    tg = [int(targets[i]) for i in ai]
    sg = [sigma[i] if sigma[i] > 0 else node.rel_sigma for i in ai]
    z = [(az[i], el[i]) for i in ai]
    c.n_own_azel = len(tg)
    if node.reverse_azel != "off":
        rev = [(j, b) for j, b in sorted(node.peer_bearings.items()) if j in peers]
        if rev:
            tg += [j for j, _ in rev]
            sg += [b[2] for _, b in rev]
            back = np.array([b[:2] for _, b in rev], float)
            az_back = wrap_angle(back[:, 0] + np.pi)  # the bearing turned around: az + π, −el
            z += list(zip(az_back.tolist(), (-back[:, 1]).tolist()))
    if tg:
        c.azel_target = np.array(tg, int)
        c.azel_node = np.array([c.idx[o] for o in tg], int)
        c.azel_sig2 = np.array(sg, float) ** 2
        c.azel_z = np.array(z, float).reshape(-1, 2)


def _tdoa_rows(node: GraphEstimator, peers, c: RoundCache, Rm: np.ndarray):
    # cooperative tdoa rows whose neighbours are all live: per end ("self", world lever),
    # ("peer", node index, its tag's offset) or ("fixed", ENU point); listener, initiator, responder
    own = node.own
    for i in node.tdoa_coop:
        ends = []
        for nd, tg in own.tdoa_ends(node.inp, i):
            if nd == node.uav:
                ends.append(("self", Rm @ node.tags.get(tg, np.zeros(3)), None))
            elif nd in node.anchors:
                ends.append(("fixed", own.tdoa_end(nd, tg)[1], None))
            elif nd in peers:
                ends.append(("peer", c.idx[nd], peer_lever(node, peers, nd, tg)))
            else:
                break
        else:
            z, sig = own.tdoa_row(node.inp, i)
            c.tdoa.append((ends, z, sig ** 2))
