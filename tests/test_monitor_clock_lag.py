"""The monitor's Zenoh adapter when its clock lags its estimates: the clock and the estimates arrive
through different pump threads, which a loaded machine schedules seconds apart, so an estimate of an
epoch the monitor has not yet seen opened is held (FUTURE_HOLD_S) for the clock, not rejected; one
the clock never opens in time is still rejected as `future` (a forged estimate never pre-empts)."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from services.monitor import monitor as MON
from swarmnav.estimators.base import NodeEstimate
from swarmnav.wire import keys
from swarmnav.wire import messages as M


@pytest.fixture
def mon(tmp_path):
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    ds = tmp_path / "ds"
    simulate(load_config("configs/smoke.toml"), 1).write(ds)
    args = MON.parse_args(["--router", "tcp/127.0.0.1:1", "--run", "r1", "--dataset", str(ds), "--seed", "1",
                           "--out", str(tmp_path / "run")])
    (tmp_path / "run").mkdir()
    m = MON.Monitor(args, session=None, log=logging.getLogger("t"))
    yield m
    m.core.sink.close()


def _item(key: str, payload: bytes):
    return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload))


def _est(uav: int, k: int) -> bytes:
    e = NodeEstimate(uav, k, float(k), np.array([1.0, 2.0, 3.0]), np.zeros(3), np.eye(3), None, [], 1, 1.0, None, None)
    return M.estimate_to_msg(e).encode()


def _clock(k: int) -> bytes:
    return M.ClockMsg(k=k, t=float(k), n_epochs=60, participants=[1, 2, 3, 4, 5]).encode()


def test_an_estimate_ahead_of_a_late_clock_is_held_then_taken(mon):
    mon.handle("clock", _item(keys.clock("r1"), _clock(17)))
    mon.handle("est", _item(keys.uav("r1", 3, "estimate"), _est(3, 19)))  # the clock of 18, 19 still in its pump
    assert mon.held and not mon.core.rejected
    mon.handle("clock", _item(keys.clock("r1"), _clock(18)))  # epoch 19 is now at most one ahead
    assert not mon.held and not mon.core.rejected
    assert np.isfinite(mon.core.res.pos[18, 2, 0])


def test_an_estimate_the_clock_never_opens_is_rejected_as_future(mon):
    mon.handle("clock", _item(keys.clock("r1"), _clock(5)))
    mon.handle("est", _item(keys.uav("r1", 3, "estimate"), _est(3, 40)))  # forged, far ahead
    assert mon.held
    mon.release_held()  # within its hold: still waiting
    assert mon.held and not mon.core.rejected
    mon.held = [(0.0, m, p) for _, m, p in mon.held]  # its hold is over
    mon.release_held()
    assert not mon.held and mon.core.rejected == {"est:future": 1}
    assert not np.isfinite(mon.core.res.pos[39, 2, 0])
    # held at the end of the run: rejected too, never taken
    mon.handle("est", _item(keys.uav("r1", 2, "estimate"), _est(2, 50)))
    mon.release_held(expire=True)
    assert mon.core.rejected == {"est:future": 2} and not mon.held


def test_a_lost_estimate_is_asked_for_again_until_its_node_answers(mon):
    """An estimate lost while its node's liveliness token is not (yet) seen (e.g. right after a
    router restart) is recovered once the node is live: a suspect stays one until its estimate
    arrives, and only the suspects' own nodes are queried, at most every RECOVER_WAIT epochs."""
    queried = []

    def get(sel, timeout):
        u = keys.parse(sel.split("?")[0]).uav
        queried.append((mon.clock_k, u))
        h = M.HistoryMsg.of(u, [], [M.decode(M.EstimateMsg, _est(u, 5))]).encode() if u == 2 else b""
        return [SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: h)))] if u == 2 else []

    mon.s = SimpleNamespace(get=get)
    who = [1, 2, 3, 4, 5]
    for k in range(1, 18):
        for u in who:
            if (u, k) != (2, 5):  # UAV 2's estimate of epoch 5 is lost
                mon.core.on_estimate(M.decode(M.EstimateMsg, _est(u, k)), _est(u, k))
    mon.alive = {1, 3, 4, 5}  # UAV 2 not seen live yet
    for clock in range(7, 9):
        mon.clock_k = clock
        mon.check_missing(clock - 2, who)
    assert queried == []  # nobody to ask: UAV 2 is not live, and the others are not asked
    mon.alive.add(2)
    for clock in range(9, 20):
        mon.clock_k = clock
        mon.check_missing(clock - 2, who)
    assert queried == [(9, 2)]  # asked once it is live, only it, and answered
    assert np.isfinite(mon.core.res.pos[4, mon.core.col[2], 0]) and not mon.suspect


def test_a_scheduled_kill_and_a_fast_restart_are_a_dropout_and_a_rejoin(mon):
    """A UAV killed by schedule and restarted within DROP_CONFIRM_S (a fast lockstep run plays the
    10 s between them in a fraction of a second) was neither a dropout nor a rejoin; with the clock's
    kill hold seen, the token's deletion is a dropout at once — in either order of the two."""
    two, three = SimpleNamespace(topic="uav", uav=2), SimpleNamespace(topic="uav", uav=3)
    mon.alive = {1, 2, 3, 4, 5}

    def hold(u, t):
        return M.ClockMsg(k=5, t=t, n_epochs=60, participants=[1, 2, 3, 4, 5], hold="kill", hold_uav=u).encode()

    mon.handle("clock", _item(keys.clock("r1"), hold(2, 5.0)))  # the hold first, then the token goes
    mon.on_alive(two, False)
    mon.on_alive(two, True)  # restarted before DROP_CONFIRM_S
    mon.on_alive(three, False)  # the token first, then the hold
    mon.handle("clock", _item(keys.clock("r1"), hold(3, 6.0)))
    mon.on_alive(three, True)
    kinds = [(e["kind"], e["uav"]) for e in mon.core.events]
    assert kinds == [("scheduled_kill", 2), ("dropout", 2), ("rejoin", 2),
                     ("scheduled_kill", 3), ("dropout", 3), ("rejoin", 3)], kinds
    mon.on_alive(SimpleNamespace(topic="uav", uav=4), False)  # unscheduled: waits for DROP_CONFIRM_S as before
    assert 4 in mon.pending_drop and ("dropout", 4) not in [(e["kind"], e["uav"]) for e in mon.core.events]
