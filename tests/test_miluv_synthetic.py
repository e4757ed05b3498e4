"""`import-miluv` pinned on a tiny synthetic MILUV-like folder (no recording needed, < 1 s).

Two robots, two anchors, 6 s. Every number asserted here follows from the geometry written into the
folder: robot 1 moves along x at 0.1 m/s yawing at 0.2 rad/s, robot 2 moves along y at 0.05 m/s with
one marker-swap glitch in its attitude; ranges and passive rows are generated from the true tag
positions, so labels, range differences and errors against mocap are known exactly.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from swarmnav.dataset import Dataset, FaultKind
from swarmnav.errors import DatasetError

C = 0.299792458  # m/ns
WRAP = 2.0**32 / (128 * 499.2e6) * 1e9
ANCHORS = {0: (0.0, 0.0, 2.0), 1: (4.0, 0.0, 2.0)}
LEVERS = {10: (0.1, 0.0, 0.0), 11: (-0.1, 0.0, 0.0), 20: (0.0, 0.1, 0.0), 21: (0.0, -0.1, 0.0)}
OWNER = {10: 1, 11: 1, 20: 2, 21: 2, 0: 100, 1: 101}


def _pose(uid: int, t: float) -> tuple[np.ndarray, float]:
    """True position and yaw of robot uid at time t."""
    if uid == 1:
        return np.array([1.0 + 0.1 * t, 0.0, 1.0]), 0.2 * t
    return np.array([2.0, 1.0 + 0.05 * t, 1.0]), 0.0


def _tag(tag: int, t: float) -> np.ndarray:
    if OWNER[tag] >= 100:
        return np.array(ANCHORS[tag])
    p, yaw = _pose(OWNER[tag], t)
    c, s = np.cos(yaw), np.sin(yaw)
    lx, ly, lz = LEVERS[tag]
    return p + np.array([c * lx - s * ly, s * lx + c * ly, lz])


def _dist(a: int, b: int, t: float) -> float:
    return float(np.linalg.norm(_tag(a, t) - _tag(b, t)))


def _write_csv(path: Path, header: list[str], rows) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def _passive_row(listener: int, init: int, resp: int, t: float, rx1: float) -> list:
    """A passive-listening row with equal clocks: the listener hears I's poll and R's two replies."""
    reply, d_r = 1.0e6, 5.0e5  # ns, in R's clock
    rng = _dist(init, resp, t)
    rdiff = _dist(resp, listener, t) - _dist(init, listener, t)
    rx2 = rx1 + reply + (rng + rdiff) / C
    wrap = lambda x: x - WRAP if x >= WRAP else x  # noqa: E731  (the listener's counter wraps)
    return [listener, init, resp, rx1, wrap(rx2), wrap(rx2 + d_r), 3.0e6, 3.0e6 + reply, 3.0e6 + reply + d_r,
            rng, 0.1, t]


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return build_folder(tmp_path_factory.mktemp("miluv") / "synthetic_0")


def build_folder(src: Path) -> Path:
    """The synthetic experiment (also the base of tests/test_miluv_variants.py), written at ``src``."""
    cfg = src / "config"
    for d in (cfg / "uwb", cfg / "height", cfg / "imu" / "ifo001", cfg / "imu" / "ifo002", src / "ifo001", src / "ifo002"):
        d.mkdir(parents=True)
    _write_csv(cfg / "experiments.csv", ["experiment", "anchor_constellation"], [["other_0", "1"], ["synthetic_0", "0"]])
    (cfg / "uwb" / "anchors.yaml").write_text(  # quoted strings as MILUV writes them, a YAML list, another constellation
        '# anchors\n"0":\n    "0": "[0.0, 0.0, 2.0]"\n    1: [4.0, 0.0, 2.0]\n"1":\n    "0": "[9, 9, 9]"\n')
    (cfg / "uwb" / "tags.yaml").write_text(
        'ifo001:\n  "10": "[0.1, 0.0, 0.0]"\n  "11": "[-0.1, 0.0, 0.0]"  # comment\n'
        'ifo002:\n  "20": [0.0, 0.1, 0.0]\n  "21": "[0.0 -0.1 0.0]"\n')
    (cfg / "height" / "bias.yaml").write_text('ifo001:\n  "-0.1"\n\nifo002:\n  0.05\n')
    for name, nd in (("ifo001", 0.002), ("ifo002", 0.004)):
        (cfg / "imu" / name / "px4_imu.yaml").write_text(
            f"accelerometer_noise_density: {nd}\naccelerometer_random_walk: 0.0002\n"
            "gyroscope_noise_density: 0.0005\ngyroscope_random_walk: 3.0e-05\nrostopic: '/x/mavros/imu/data_raw'\n")
    tm = np.round(np.arange(301) * 0.02, 10)
    ti = np.round(0.005 + np.arange(600) * 0.01, 10)
    for uid, name in ((1, "ifo001"), (2, "ifo002")):
        rows = []
        for k, t in enumerate(tm):
            p, yaw = _pose(uid, t)
            q = [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]
            if uid == 2 and k == 100:
                q = [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)]  # marker swap: rolled 90 deg
            rows.append([t, *p, *q])
        _write_csv(src / name / "mocap.csv", ["timestamp", "pose.position.x", "pose.position.y", "pose.position.z",
                                              "pose.orientation.x", "pose.orientation.y", "pose.orientation.z",
                                              "pose.orientation.w"], rows)
        gz = 0.2 if uid == 1 else 0.0
        _write_csv(src / name / "imu_px4.csv", ["timestamp", "angular_velocity.x", "angular_velocity.y", "angular_velocity.z",
                                                "linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z"],
                   [[t, 0.0, 0.0, gz, 0.0, 0.0, 9.81] for t in ti])
    th = np.round(np.arange(121) * 0.05, 10)
    _write_csv(src / "ifo001" / "height.csv", ["timestamp", "range"], [[t, 0.29 if t < 0.2 else 1.1] for t in th])
    hdr = ["timestamp", "pair", "from_id", "to_id", "range", "gt_range", "bias", "std"]
    r_uav = [1.0, "(10, 20)", 10, 20, _dist(10, 20, 1.0), _dist(10, 20, 1.0), 0.0, 0.1]
    r_nlos = [2.0, "(11, 0)", 11, 0, _dist(11, 0, 2.0) + 0.5, _dist(11, 0, 2.0), 0.5, 0.1]
    r_nostd = [3.0, "(21, 1)", 21, 1, _dist(21, 1, 3.0), _dist(21, 1, 3.0), 0.0, ""]
    r_early = [0.005, "(10, 0)", 10, 0, 1.0, 1.0, 0.0, 0.1]
    _write_csv(src / "ifo001" / "uwb_range.csv", hdr, [r_early, r_uav, r_nlos])
    _write_csv(src / "ifo002" / "uwb_range.csv", hdr, [r_uav, r_nostd])  # r_uav: the same transaction, logged twice
    phdr = ["my_id", "from_id", "to_id", "rx1", "rx2", "rx3", "rx1_n", "tx2_n", "tx3_n", "range_n", "std", "timestamp_n"]
    p1 = _passive_row(10, 0, 1, 1.5, 1000.0)
    p2 = _passive_row(20, 0, 1, 2.5, WRAP - 2.0e5)  # rx2, rx3 wrapped
    p_anchor = _passive_row(0, 10, 1, 3.5, 1000.0)  # an anchor does not listen
    _write_csv(src / "ifo001" / "uwb_passive.csv", phdr, [p1, p_anchor])
    _write_csv(src / "ifo002" / "uwb_passive.csv", phdr, [p1, p2])
    return src


@pytest.fixture(scope="module")
def converted(folder):
    from services.importers.miluv import convert

    return convert(folder, epoch_dt=0.1, estimation=None)


def test_nodes_from_yaml(converted):
    ds, _ = converted
    m = ds.meta
    assert m.name == "miluv/synthetic_0" and m.uav_ids() == [1, 2]
    assert {k: tuple(v) for k, v in m.anchors().items()} == {100: ANCHORS[0], 101: ANCHORS[1]}
    assert m.node(1).tags == {10: LEVERS[10], 11: LEVERS[11]} and m.node(2).tags == {20: LEVERS[20], 21: LEVERS[21]}
    assert m.node(1).imu.accel_noise_density == 0.002 and m.node(2).imu.gyro_bias_rw == 3.0e-05
    assert m.init["level_window_s"] == 1.0  # both at rest by their IMU (constant readings)
    assert len(m.config_sha256) == 64 and "estimation" not in m.config


def test_span_truth_and_glitch(converted):
    ds, summary = converted
    m = ds.meta
    assert m.t_start == 0.01 and m.n_epochs() == 59  # IMU from 0.005 s to 5.995 s, 10 ms rounding
    tr = ds.table("truth")
    assert len(tr["t"]) == 2 * (59 * 10 + 1)
    for uid in (1, 2):
        s = tr["node"] == uid
        t = tr["t"][s]
        pos = np.column_stack([tr[c][s] for c in ("pe", "pn", "pu")])
        np.testing.assert_allclose(pos, [_pose(uid, x)[0] for x in t], atol=1e-12)
        vel = np.column_stack([tr[c][s] for c in ("ve", "vn", "vu")])
        np.testing.assert_allclose(vel, [[0.1, 0, 0] if uid == 1 else [0, 0.05, 0]] * len(t), atol=1e-9)
        yaw = np.array([_pose(uid, x)[1] for x in t])
        q = np.column_stack([tr[c][s] for c in ("qw", "qx", "qy", "qz")])
        np.testing.assert_allclose(q, np.column_stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)]), atol=1e-12)
    assert summary["mocap_attitude_glitches_interpolated"] == {"ifo002": {"samples": 1, "t_first": 2.0, "t_last": 2.0}}


def test_imu_and_altitude(converted):
    ds, _ = converted
    imu = ds.table("imu")
    for uid, gz in ((1, 0.2), (2, 0.0)):
        s = imu["node"] == uid
        assert s.sum() == 591 and imu["t"][s][0] == 0.005  # the sample in force at t_start, up to t_end
        assert np.all(imu["gz"][s] == gz) and np.all(imu["az"][s] == 9.81)
    al = ds.table("altitude")
    assert set(al["node"]) == {1} and np.all(al["height"] == 1.1 + 0.1) and np.all(al["sigma"] == 0.1)
    assert al["t"][0] == 0.2 and al["t"][-1] <= 5.91  # floor readings (0.29 m) dropped, span kept


def test_ranges(converted):
    ds, summary = converted
    r = ds.table("ranges")
    assert r["t"].tolist() == [1.0, 2.0, 3.0]
    assert r["a"].tolist() == [1, 1, 2] and r["b"].tolist() == [2, 100, 101]
    assert r["tag_a"].tolist() == [10, 11, 21] and r["tag_b"].tolist() == [20, 0, 1]
    assert r["sigma"].tolist() == [0.1, 0.1, 0.1]  # no std: the recording's median
    assert r["fault_kind"].tolist() == [int(FaultKind.NONE), int(FaultKind.NLOS_REAL), int(FaultKind.NONE)]
    np.testing.assert_allclose(r["range"], [_dist(10, 20, 1.0), _dist(11, 0, 2.0) + 0.5, _dist(21, 1, 3.0)])
    s = summary["ranges"]
    assert (s["logged_rows"], s["duplicates_removed"], s["transactions"], s["kept"]) == (5, 1, 4, 3)
    assert s["dropped"] == {"outside_span": 1, "invalid_range": 0, "no_std": 1}
    assert s["our_truth_minus_gt_range_m"]["max_abs"] == 0.0  # our lever-arm truth = the generator's
    assert ds.meta.uwb_sigma_m == 0.1 and ds.meta.fault_threshold_m == pytest.approx(0.3)


def test_passive_tdoa(converted):
    ds, summary = converted
    td = ds.table("tdoa")
    assert td["t"].tolist() == [1.5, 2.5]
    assert td["node"].tolist() == [1, 2] and td["tag"].tolist() == [10, 20]
    assert td["init"].tolist() == [100, 100] and td["resp"].tolist() == [101, 101]
    want = [_dist(1, 10, 1.5) - _dist(0, 10, 1.5), _dist(1, 20, 2.5) - _dist(0, 20, 2.5)]
    np.testing.assert_allclose(td["rdiff"], want, atol=1e-6)  # the second across the counter wrap
    np.testing.assert_allclose(td["fault_err"], 0.0, atol=1e-6)
    assert td["fault_kind"].tolist() == [int(FaultKind.NONE)] * 2
    s = summary["tdoa"]
    assert (s["logged_rows"], s["duplicates_removed"], s["kept"]) == (4, 1, 2)
    assert s["dropped"]["not_a_listener"] == 1


def test_write_read_roundtrip(converted, tmp_path):
    ds, _ = converted
    ds.write(tmp_path / "ds")
    back = Dataset.read(tmp_path / "ds")
    assert back.meta == ds.meta
    np.testing.assert_array_equal(back.table("tdoa")["rdiff"], ds.table("tdoa")["rdiff"])


def test_bad_yaml_and_vectors(folder, tmp_path):
    from services.importers.miluv import parse_vector, read_yaml

    y = tmp_path / "bad.yaml"
    y.write_text("a: [1, 2\n")
    with pytest.raises(DatasetError, match="bad.yaml: not valid YAML"):
        read_yaml(y)
    y.write_text("- 1\n- 2\n")
    with pytest.raises(DatasetError, match="expected a mapping"):
        read_yaml(y)
    assert read_yaml(folder / "config" / "height" / "bias.yaml") == {"ifo001": "-0.1", "ifo002": 0.05}
    assert parse_vector([1, 2, 3], 3, "w") == parse_vector("[1 2 3]", 3, "w") == (1.0, 2.0, 3.0)
    with pytest.raises(DatasetError, match="expected 3 finite numbers"):
        parse_vector("[1, 2]", 3, "w")
