"""Key-expression grammar: build/parse round trips and rejection of foreign keys."""

import pytest

from swarmnav.wire import keys


@pytest.mark.parametrize("topic", keys.UAV_TOPICS)
@pytest.mark.parametrize("uav", [1, 7, 18, 123])
def test_uav_round_trip(topic, uav):
    k = keys.uav("run-1.a_b", uav, topic)
    assert k == f"swarmnav/run-1.a_b/uav/{uav}/{topic}"
    p = keys.parse(k)
    assert (p.run, p.kind, p.topic, p.uav) == ("run-1.a_b", "uav", topic, uav)
    assert keys.build(p) == k


@pytest.mark.parametrize("service", keys.SERVICES)
def test_alive_truth_meta_clock_round_trip(service):
    for k in (keys.alive("r", service, 3), keys.truth("r", 5), keys.meta("r"), keys.clock("r")):
        assert keys.build(keys.parse(k)) == k
    assert keys.parse(keys.alive("r", service, 3)).topic == service


@pytest.mark.parametrize("bad", ["other/r/uav/1/imu", "swarmnav/r/uav/0/imu", "swarmnav/r/uav/01/imu",
                                 "swarmnav/r/uav/x/imu", "swarmnav/r/uav/1/nope", "swarmnav/r/uav/*/state",
                                 "swarmnav/r/alive/zz/1", "swarmnav/r", "swarmnav/r/truth/1/x", ""])
def test_parse_rejects(bad):
    with pytest.raises(ValueError):
        keys.parse(bad)


@pytest.mark.parametrize("run", ["a/b", "a*", "", "r$", "x?y"])
def test_bad_run_ids(run):
    with pytest.raises(ValueError):
        keys.uav(run, 1, "imu")


def test_wildcards():
    assert keys.uav_all("r", "state") == "swarmnav/r/uav/*/state"
    assert keys.uav_any("r", 4) == "swarmnav/r/uav/4/*"
    assert keys.alive_all("r", "uav") == "swarmnav/r/alive/uav/*"
    assert keys.truth_all("r") == "swarmnav/r/truth/*"
    with pytest.raises(ValueError):
        keys.uav("r", 0, "imu")
