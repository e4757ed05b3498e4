"""The node's own decisions on what it receives, on its real class (samples handed to the pump
functions as the pump threads would; no session needed for these)."""

import logging
from types import SimpleNamespace

import numpy as np

from services.uav_node.node import Node, parse_args
from swarmnav.estimators.base import NodeState
from swarmnav.wire import messages as M


def _node():
    n = Node(parse_args(["--router", "tcp/127.0.0.1:1", "--run", "r1", "--uav", "2"]), session=None, log=logging.getLogger("t"))
    n.uav_ids = {1, 2, 3}
    return n


def _state(uav, k, r=0):
    s = NodeState(uav, k, r, float(k), np.array([10.0, 20.0, 30.0]), np.eye(3), np.zeros(3))
    return SimpleNamespace(key_expr=f"swarmnav/r1/uav/{uav}/state", payload=SimpleNamespace(to_bytes=lambda: M.encode_state(s)))


def test_states_of_unopened_epochs_are_rejected_not_taken_as_the_swarm_moving_on():
    n = _node()
    n.clock_k, n.k_done = 5, 4
    n.on_state(_state(3, 9))  # forged: the sensor-sim has not opened epoch 9
    assert n.newest_peer_k == 0 and n.rejects.as_dict() == {"state:future": 1}
    n.on_state(_state(3, 6))  # a peer one epoch ahead of the clock we have seen: legitimate
    n.on_state(_state(1, 5))
    assert n.newest_peer_k == 6 and set(n.states) == {(6, 0), (5, 0)}
    n.on_state(_state(1, 3))  # late state of an epoch already done: dropped quietly
    assert n.rejects.total == 1


def test_a_state_claiming_another_sender_is_rejected():
    n = _node()
    n.clock_k = 5
    item = _state(3, 5)
    item.key_expr = "swarmnav/r1/uav/1/state"  # UAV 3's frame on UAV 1's key
    n.on_state(item)
    assert n.rejects.as_dict() == {"state:wrong_uav": 1} and not n.states
