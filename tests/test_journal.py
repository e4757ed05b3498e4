"""The monitor's journal: every record durable, a record cut short by a crash ignored, and the
replay (`swarmnav report`) fed the same messages as the live monitor."""

import json

import pytest

from services.monitor import journal as J


def test_round_trip_and_torn_tail(tmp_path):
    p = J.journal_path(tmp_path)
    w = J.JournalWriter(p, {"run": "r1"})
    w.write(J.ESTIMATE, b'{"a": 1}')
    w.event({"t": 1.0, "kind": "dropout", "uav": 3})
    # no close(): each record is flushed as written (a SIGKILLed writer loses nothing it accepted)
    data = p.read_bytes()
    recs = list(J.read_journal(p))
    assert [k for k, _ in recs] == [J.HEADER, J.ESTIMATE, J.EVENT]
    assert json.loads(recs[0][1]) == {"run": "r1"} and json.loads(recs[2][1])["kind"] == "dropout"
    p.write_bytes(data + J._REC.pack(J.ESTIMATE, 100) + b'{"cut short')  # a crash mid-write
    assert [k for k, _ in J.read_journal(p)] == [J.HEADER, J.ESTIMATE, J.EVENT]
    p.write_bytes(data + b"\xff\x00")  # garbage tail
    assert len(list(J.read_journal(p))) == 3


def test_never_appends_to_another_runs_journal(tmp_path):
    J.JournalWriter(J.journal_path(tmp_path), {"run": "a"}).close()
    with pytest.raises(FileExistsError):
        J.JournalWriter(J.journal_path(tmp_path), {"run": "b"})


def test_monitor_core_flags_a_second_different_estimate(tmp_path):
    """A second sender holding a UAV's identity cannot silently replace or pre-empt its estimates:
    a different estimate for the same UAV and epoch is a conflict, and the run is never complete."""
    import numpy as np

    from services import recording as R
    from services.monitor.core import MonitorCore
    from swarmnav.config import load_config
    from swarmnav.estimators.base import NodeEstimate
    from swarmnav.sim import simulate
    from swarmnav.wire import messages as M

    ds = tmp_path / "ds"
    simulate(load_config("configs/smoke.toml"), 1).write(ds)
    core = MonitorCore(run="r1", dataset=ds, seed=1, algo="atvfg", out=tmp_path, sink=R.FileRecording(tmp_path / "x.rrd"))

    def est(pos, rejected=None):
        e = NodeEstimate(3, 1, 1.0, np.array(pos, float), np.zeros(3), np.eye(3), None, [], 1, 1.0, None, None)
        return M.estimate_to_msg(e, rejected=rejected or {})

    assert core.on_estimate(est([1.0, 2.0, 3.0]))
    assert not core.on_estimate(est([1.0, 2.0, 3.0]))  # the same one again (recovered by query): fine
    assert core.conflicts == 0
    assert not core.on_estimate(est([51.0, 2.0, 3.0], {"state:future": 2}))  # a forged one
    assert core.conflicts == 1 and core.rejected["estimate:conflict"] == 1
    assert [e["kind"] for e in core.events].count("conflicting_estimates") == 1
    core.done = True
    assert core.completeness()["complete"] is False
    core.sink.close()


def test_monitor_core_closes_an_epoch_in_the_recording_only_when_its_estimates_are_in(tmp_path):
    """A late estimate must reach its epoch's swarm error row: an epoch is closed once every
    expected estimate is in (a scheduled kill excused), or CLOSE_LAG epochs behind the clock."""
    import numpy as np

    from services import recording as R
    from services.monitor.core import CLOSE_LAG, MonitorCore
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    ds = tmp_path / "ds"
    simulate(load_config("configs/smoke.toml"), 1).write(ds)
    core = MonitorCore(run="r1", dataset=ds, seed=1, algo="atvfg", out=tmp_path, sink=R.FileRecording(tmp_path / "x.rrd"),
                       kills=[(4, 8.0)])
    core.res.pos[:12] = 0.0  # epochs 1..12 complete
    core.res.pos[5, 2] = np.nan  # epoch 6: UAV 3's estimate still on its way
    core.res.pos[7:, 3] = np.nan  # UAV 4 killed at 8 s: excused from epoch 8 on
    assert core.closable(5) == 3  # the clock's slack of two epochs
    assert core.closable(12) == 5  # not epoch 6 while UAV 3's estimate is missing
    core.res.pos[5, 2] = 0.0
    assert core.closable(12) == 10  # it came: epochs 6..10 (UAV 4 excused) close
    core.res.pos[12:] = 0.0
    core.res.pos[13, 0] = np.nan  # epoch 14 never gets UAV 1's estimate (frozen)
    assert core.closable(20) == 13
    assert core.closable(14 + CLOSE_LAG) == 12 + CLOSE_LAG  # closed anyway, CLOSE_LAG behind the clock
