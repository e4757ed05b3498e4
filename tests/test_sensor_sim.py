"""The sensor-sim's own decisions, on its real class with a real dataset (no session needed for
these: the samples are handed to its ``handle`` as the pump thread would)."""

import logging
from types import SimpleNamespace
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from services.sensor_sim.sim import SensorSim, parse_args
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    d = tmp_path_factory.mktemp("smoke") / "dataset"
    simulate(load_config(REPO / "configs/smoke.toml"), 1).write(d)
    return SensorSim(parse_args(["--router", "tcp/127.0.0.1:1", "--run", "r1", "--dataset", str(d), "--seed", "1"]),
                     session=None, log=logging.getLogger("test"))


def _token(uav, put=True):
    import zenoh

    return SimpleNamespace(key_expr=f"swarmnav/r1/alive/uav/{uav}", kind=zenoh.SampleKind.PUT if put else zenoh.SampleKind.DELETE)


def test_liveliness_of_an_unknown_uav_is_counted_not_a_crash(sim):
    sim.handle("alive", _token(9))
    sim.handle("alive", _token(3))
    assert sim.alive_uav == {3}
    assert sim.rejects.as_dict() == {"alive:unknown_uav": 1}
    sim.handle("alive", _token(3, put=False))
    assert sim.alive_uav == set() and 3 in sim.gone_since


def test_restart_alignment_is_the_epoch_asked_for(sim):
    a = sim.restart_init(2, 17)
    b = sim.restart_init(2, 17)
    c = sim.restart_init(2, 18)
    assert a == b and a.t == sim.meta.epoch_time(17) and c.t == sim.meta.epoch_time(18) and a.pos != c.pos
    assert sim.restart_init(2, 10_000).t == sim.meta.epoch_time(sim.K)  # clamped to the run
