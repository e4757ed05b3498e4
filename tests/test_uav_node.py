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


def test_states_of_unopened_epochs_never_make_a_node_drop_its_epoch():
    n = _node()
    n.clock_k, n.k_done = 5, 4
    n.on_state(_state(3, 2**31 - 1))  # far beyond any opened epoch: forged, rejected and counted
    assert n.rejects.as_dict() == {"state:future": 1} and not n.states
    n.on_state(_state(3, 9))  # not yet opened: kept (the clock may be late) but not taken as the swarm's epoch
    assert n.newest_peer_k() == 0
    n.on_state(_state(1, 6))  # a peer one epoch ahead of the clock we have seen: legitimate
    assert n.newest_peer_k() == 6
    n.clock_k = 8  # the clock opened epoch 8: now the state of 9 counts
    assert n.newest_peer_k() == 9
    n.on_state(_state(1, 3))  # late state of an epoch already done: dropped quietly
    assert n.rejects.total == 1


def test_a_state_claiming_another_sender_is_rejected():
    n = _node()
    n.clock_k = 5
    item = _state(3, 5)
    item.key_expr = "swarmnav/r1/uav/1/state"  # UAV 3's frame on UAV 1's key
    n.on_state(item)
    assert n.rejects.as_dict() == {"state:wrong_uav": 1} and not n.states


def test_newest_peer_epoch_follows_each_peers_newest_state():
    """newest_peer_k (kept as a per-epoch count by the state pump, not a scan of the peers): the
    newest epoch any peer has reached among those the clock has opened; a peer that moves on no
    longer counts at its old epoch, and one ahead of the clock counts once the clock catches up."""
    n = _node()
    n.uav_ids = {1, 2, 3, 4}
    n.clock_k, n.k_done = 7, 1
    for u, k in ((1, 3), (3, 3), (4, 4)):
        n.on_state(_state(u, k))
    assert n.newest_peer_k() == 4 and n.newest_count == {3: 2, 4: 1}
    n.on_state(_state(4, 9))  # UAV 4 two epochs ahead of the opened clock + 1: not counted yet
    assert n.newest_peer_k() == 3 and n.newest_count == {3: 2, 9: 1}
    n.on_state(_state(1, 5))
    n.on_state(_state(1, 4))  # an older state of UAV 1 arriving late: its newest stays 5
    assert n.newest_peer_k() == 5 and n.newest_count == {3: 1, 5: 1, 9: 1}
    n.clock_k = 8
    assert n.newest_peer_k() == 9
    scan = max((v for v in n.peer_newest.values() if v <= n.clock_k + 1), default=0)
    assert n.newest_peer_k() == scan


def test_cpu_policy_batch_reaches_the_threads_started_after_it():
    """--cpu-policy batch (the default) puts the node's thread, and the threads it starts afterwards
    (Zenoh's runtime, the pumps), in SCHED_BATCH with a 50 ms GIL switch interval; normal leaves
    the inherited policy and Python's interval. In a child process: the policy must not leak into the runner."""
    import os
    import subprocess
    import sys

    code = ("import logging, os, threading\n"
            "from services.uav_node.node import parse_args, set_cpu_policy\n"
            "a = parse_args(['--router', 'tcp/127.0.0.1:1', '--run', 'r1', '--uav', '1', *__import__('sys').argv[1:]])\n"
            "set_cpu_policy(a.cpu_policy, logging.getLogger())\n"
            "seen = []\n"
            "t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0))); t.start(); t.join()\n"
            "print(os.sched_getscheduler(0), seen[0], __import__('sys').getswitchinterval())\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    from services.uav_node.node import SWITCH_INTERVAL_S

    # normal: whatever the runner has (a child inherits it)
    for extra, want, swi in (([], os.SCHED_BATCH, SWITCH_INTERVAL_S),
                             (["--cpu-policy", "normal"], os.sched_getscheduler(0), sys.getswitchinterval())):
        out = subprocess.run([sys.executable, "-c", code, *extra], capture_output=True, text=True, env=env, timeout=60)
        assert out.returncode == 0, out.stderr
        policy, thread_policy, interval = out.stdout.split()
        assert (int(policy), int(thread_policy)) == (want, want) and abs(float(interval) - swi) < 1e-9
