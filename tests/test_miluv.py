"""`swarmnav import-miluv` on the real MILUV recording (../shared/data/miluv/cirObstacles_3_random_0).

Numbers asserted here were counted from the recording's CSVs (see docs/miluv.md): 440 logged
uwb_range rows, 123 of them the second copy of an inter-UAV transaction logged by both robots,
317 transactions of which 2 fall before the first common mocap/IMU time.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest

from swarmnav.dataset import Dataset, EpochSlicer, FaultKind
from swarmnav.errors import DatasetError

ROOT = Path(__file__).resolve().parents[1]
# the recording beside the repository (read-only reference data), or wherever SWARMNAV_MILUV_DIR says
SRC = Path(os.environ.get("SWARMNAV_MILUV_DIR")
           or ROOT / ".." / "shared" / "data" / "miluv" / "cirObstacles_3_random_0").resolve()

pytestmark = pytest.mark.skipif(not SRC.is_dir(), reason=f"MILUV recording not available at {SRC} "
                                "(set SWARMNAV_MILUV_DIR to the cirObstacles_3_random_0 folder)")


@pytest.fixture(scope="module")
def converted():
    from services.importers.miluv import convert

    return convert(SRC, epoch_dt=0.1)


def _quat_to_matrix_wxyz(w, x, y, z):
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_nodes_and_anchors(converted):
    ds, _ = converted
    m = ds.meta
    assert m.source == "recorded" and m.origin is None and m.events == []
    assert m.uav_ids() == [1, 2, 3]
    assert [m.node(u).airframe for u in (1, 2, 3)] == ["multirotor"] * 3  # quadrotors: rotor-drag model
    assert all(n.airframe is None for n in m.nodes if n.kind == "anchor")
    anchors = m.anchors()
    assert sorted(anchors) == [100, 101, 102, 103, 104, 105]
    # constellation "0" of config/uwb/anchors.yaml
    np.testing.assert_allclose(anchors[100], [3.273827392578125, 3.46404736328125, 1.8093309326171875])
    np.testing.assert_allclose(anchors[105], [-2.734676513671875, 3.65854248046875, 1.890254638671875])
    assert m.node(1).tags == {10: (0.13189, -0.17245, -0.05249), 11: (-0.17542, 0.15712, -0.05307)}
    assert all(m.node(u).gnss_pos_sigma_m is None for u in m.uav_ids())
    # config/imu/ifo002/px4_imu.yaml, already SI (Kalibr densities); the accelerometer white noise is
    # the in-flight vibration measured from the IMU itself (~0.5 m/s^2 per 250 Hz sample -> ~0.03/sqrt(Hz))
    assert 0.02 < m.node(2).imu.accel_noise_density < 0.05
    assert m.node(2).imu.gyro_noise_density == pytest.approx(0.0003788371581429991)
    assert m.node(2).imu.gyro_bias_rw == pytest.approx(0.0004488771790143709)
    assert m.earth.gravity_mps2 == 9.81 and m.earth.earth_rate_radps == (0.0, 0.0, 0.0)
    assert set(m.init) == {"vel_sigma_mps", "roll_pitch_sigma_deg", "yaw_sigma_deg", "level_window_s"}


def test_time_span_and_counts(converted):
    ds, summ = converted
    m = ds.meta
    assert m.t_start == pytest.approx(0.98)  # ifo003 mocap starts at 0.974 s, rounded up to 10 ms
    assert m.epoch_dt_s == 0.1 and m.n_epochs() == 778 and m.duration_s == pytest.approx(77.8)
    t_end = m.epoch_time(m.n_epochs())
    for name in ("truth", "imu", "ranges", "altitude"):
        t = ds.table(name)["t"]
        assert np.all(np.diff(t) >= 0), name
        assert t[-1] <= t_end + 1e-9, name
    # truth holds every epoch time exactly, for each UAV, at 10 rows per epoch
    tr = ds.table("truth")
    assert len(tr["t"]) == 3 * (778 * 10 + 1)
    edges = np.array([m.epoch_time(k) for k in range(m.n_epochs() + 1)])
    assert np.isin(edges, tr["t"][tr["node"] == 1]).all()
    # IMU: ~250 Hz for ~78 s per UAV, variable rate kept
    imu = ds.table("imu")
    for u in (1, 2, 3):
        t = imu["t"][imu["node"] == u]
        assert 15000 < len(t) < 16000
        assert t[0] <= m.t_start < t[1]  # the sample in force at t_start is included
        dt = np.diff(t)
        assert 0.0035 < np.median(dt) < 0.0045 and dt.max() < 0.06
    # ranges: 440 logged rows -> 317 transactions -> 315 inside the span
    r = ds.table("ranges")
    assert summ["ranges"]["logged_rows"] == 440 and summ["ranges"]["duplicates_removed"] == 123
    assert len(r["t"]) == 315
    inter = r["b"] < 100
    assert inter.sum() == 123 and (~inter).sum() == 192
    assert np.all(r["a"] < r["b"])
    keys = set(zip(r["t"].tolist(), r["tag_a"].tolist(), r["tag_b"].tolist()))
    assert len(keys) == len(r["t"])  # no transaction twice
    # labels: NLOS_REAL exactly where |bias| > 3 std (the rule); fault_err = the bias
    nlos = r["fault_kind"] == int(FaultKind.NLOS_REAL)
    assert nlos.sum() == 14
    np.testing.assert_array_equal(nlos, np.abs(r["fault_err"]) > 3 * r["sigma"])
    assert 0.06 < r["sigma"].min() and r["sigma"].max() < 0.21
    # each range lands in exactly one epoch, seen by each UAV taking part
    sl = EpochSlicer(ds)
    seen = sum(len(sl.epoch(k, u).range_m) for k in range(1, sl.K + 1) for u in (1, 2, 3))
    assert seen == 2 * 123 + 192
    # altitude: 30 Hz per UAV, readings at the 0.29 m sensor floor removed
    al = ds.table("altitude")
    assert 5000 < len(al["t"]) < 7000 and al["height"].min() > 0.3


def test_imu_units_and_frame(converted):
    ds, _ = converted
    imu, tr = ds.table("imu"), ds.table("truth")
    for u in (1, 2, 3):
        t = imu["t"][imu["node"] == u]
        acc = np.column_stack([imu[c][imu["node"] == u] for c in ("ax", "ay", "az")])
        gyr = np.column_stack([imu[c][imu["node"] == u] for c in ("gx", "gy", "gz")])
        still = t < 2.0  # on the ground before take-off (mocap speed < 1 cm/s)
        tm = tr["node"] == u
        assert np.abs(tr["ve"][tm][tr["t"][tm] < 2.0]).max() < 0.05
        g = np.linalg.norm(acc[still].mean(axis=0))
        assert g == pytest.approx(9.81, abs=0.1)  # m/s^2, specific force
        assert acc[still, 2].mean() > 9.5  # body z up: FLU, not FRD
        assert np.abs(gyr[still].mean(axis=0)).max() < 0.005  # rad/s (deg/s would not be this small in flight below)
        # gyro z against the mocap yaw rate: same axis, same sign, same units (rad/s)
        tt = tr["t"][tm]
        yaw = np.unwrap(np.arctan2(2 * (tr["qw"][tm] * tr["qz"][tm] + tr["qx"][tm] * tr["qy"][tm]),
                                   1 - 2 * (tr["qy"][tm] ** 2 + tr["qz"][tm] ** 2)))
        rate = np.gradient(yaw, tt)
        gz = np.interp(tt, t, gyr[:, 2])
        k = np.ones(10) / 10
        a, b = np.convolve(gz, k, "same"), np.convolve(rate, k, "same")
        assert np.corrcoef(a, b)[0, 1] > 0.9
        slope = np.dot(a, b) / np.dot(b, b)
        assert 0.8 < slope < 1.2


def test_one_range_by_hand(converted):
    """ifo003/uwb_range.csv, first row: t = 2.835312604904175 s, tag 30 (ifo003) <-> tag 11 (ifo001).

    gt_range = 2.4625833484964765 m. By hand: p_tag = r_iw_a + C(q_ai) * lever, with the row's own
    mocap pose strings (q as x y z w, body -> Vicon world) and the lever arms of tags.yaml.
    Tolerance 1e-6 m (the pose strings are printed with 8 significant digits). Then the same range
    from our converted truth (10 ms grid, linear/slerp interpolation) and meta lever arms: 1 cm.
    """
    with open(SRC / "ifo003" / "uwb_range.csv", newline="") as f:
        row = next(csv.DictReader(f))
    assert (row["from_id"], row["to_id"], row["pair"]) == ("30", "11", "(30, 11)")  # quoted field parsed
    p3 = np.array([0.00990028, -2.03674879, 0.14020044])  # r_iw_a_ifo003
    q3 = (9.99955640e-01, 7.63877e-03, -5.05982e-03, -2.18388e-03)  # q_ai_ifo003 as w, x, y, z
    p1 = np.array([-0.05851259, 0.05194755, 0.12971022])  # r_iw_a_ifo001
    q1 = (9.99898555e-01, 1.40104941e-02, 2.52193712e-03, 4.56941221e-04)
    assert row["r_iw_a_ifo003"] == "[ 0.00990028 -2.03674879  0.14020044]"
    lever30 = np.array([0.16685, -0.18113, -0.05576])
    lever11 = np.array([-0.17542, 0.15712, -0.05307])
    tag30 = p3 + _quat_to_matrix_wxyz(*q3) @ lever30
    tag11 = p1 + _quat_to_matrix_wxyz(*q1) @ lever11
    by_hand = float(np.linalg.norm(tag30 - tag11))
    assert by_hand == pytest.approx(float(row["gt_range"]), abs=1e-6)
    assert float(row["gt_range"]) == pytest.approx(2.4625833484964765)

    ds, _ = converted
    t = float(row["timestamp"])
    r = ds.table("ranges")
    i = np.flatnonzero(np.isclose(r["t"], t))
    assert len(i) == 1
    i = int(i[0])
    assert (r["a"][i], r["b"][i], r["tag_a"][i], r["tag_b"][i]) == (1, 3, 11, 30)
    assert r["range"][i] == pytest.approx(float(row["range"]))
    assert r["fault_err"][i] == pytest.approx(float(row["bias"]))
    tr = ds.table("truth")

    def tag_pos(node, tag):
        m = tr["node"] == node
        tt = tr["t"][m]
        p = np.array([np.interp(t, tt, tr[c][m]) for c in ("pe", "pn", "pu")])
        j = int(np.searchsorted(tt, t))
        q = np.array([tr[c][m][j] for c in ("qw", "qx", "qy", "qz")])
        return p + _quat_to_matrix_wxyz(*q) @ np.asarray(ds.meta.node(node).tags[tag])

    ours = float(np.linalg.norm(tag_pos(1, 11) - tag_pos(3, 30)))
    assert ours == pytest.approx(by_hand, abs=0.01)


def test_passive_range_difference_by_hand(converted):
    """One passive-listening row by hand: tag 21 (ifo002) overheard the transaction of the range
    above (initiator 30 on ifo003, responder 11 on ifo001, t = 2.835312604904175 s).

    rdiff = c·[(rx2 − rx1)·(tx3_n − tx2_n)/(rx3 − rx2) − (tx2_n − rx1_n)] − range_n, timestamps in
    ns (the listener's rx stamps convert to the responder's clock by the ratio of the two responder
    messages' intervals). True value from the range row's mocap pose strings + tags.yaml levers.
    """
    c = 0.299792458
    rx1, rx2, rx3 = 2255702569.271391, 2256007516.6651454, 2257546231.0565853
    rx1n, tx2n, tx3n, range_n = 303414837.0391433, 303719784.5456783, 305258502.49439627, 2.548996385022064
    by_hand = c * ((rx2 - rx1) * (tx3n - tx2n) / (rx3 - rx2) - (tx2n - rx1n)) - range_n
    p1, q1 = np.array([-0.05851259, 0.05194755, 0.12971022]), (9.99898555e-01, 1.40104941e-02, 2.52193712e-03, 4.56941221e-04)
    p2, q2 = np.array([0.02159937, 2.25925379, 0.11046071]), (0.9999907, -0.00347175, 0.00225827, 0.00119651)
    p3, q3 = np.array([0.00990028, -2.03674879, 0.14020044]), (9.99955640e-01, 7.63877e-03, -5.05982e-03, -2.18388e-03)
    tag21 = p2 + _quat_to_matrix_wxyz(*q2) @ np.array([-0.15467, 0.16972, -0.01680])
    tag30 = p3 + _quat_to_matrix_wxyz(*q3) @ np.array([0.16685, -0.18113, -0.05576])
    tag11 = p1 + _quat_to_matrix_wxyz(*q1) @ np.array([-0.17542, 0.15712, -0.05307])
    truth = float(np.linalg.norm(tag11 - tag21) - np.linalg.norm(tag30 - tag21))
    assert abs(by_hand - truth) < 0.3  # a good measurement: within ~1.5 sigma (std 0.189 m)

    ds, summ = converted
    d = ds.table("tdoa")
    i = np.flatnonzero(np.isclose(d["t"], 2.835312604904175) & (d["tag"] == 21))
    assert len(i) == 1
    i = int(i[0])
    assert (d["node"][i], d["init"][i], d["tag_init"][i], d["resp"][i], d["tag_resp"][i]) == (2, 3, 30, 1, 11)
    assert d["rdiff"][i] == pytest.approx(by_hand, abs=1e-9)
    assert d["sigma"][i] == pytest.approx(0.1887484319162718)
    assert d["fault_err"][i] == pytest.approx(by_hand - truth, abs=0.01)  # our truth: interpolated mocap
    # counts (docs/miluv.md "Fifth pass"): 980 logged rows in the three files, 249 second copies,
    # 5 before t_start, 37 breaking the triangle inequality by > 3 sigma
    s = summ["tdoa"]
    assert (s["logged_rows"], s["duplicates_removed"], s["kept"]) == (980, 249, 689)
    assert s["dropped"] == {"outside_span": 5, "not_a_listener": 0, "invalid": 0, "clock_ratio": 0, "triangle": 37,
                            "no_ids": 0, "robot_not_here": 0}
    # the counter wrap (2**32 ticks = 67.2 ms) is undone: ~15 % of the rows have rx2 - rx1 one wrap
    # long; without it they would be ~2e7 m off and dropped. Kept rows are good to ~0.17 m (robust)
    e = d["fault_err"]
    assert abs(np.median(e)) < 0.1 and 1.4826 * np.median(np.abs(e - np.median(e))) < 0.2
    assert np.all(np.diff(d["t"]) >= 0)
    # every row reaches listener, initiator and responder (as both ends of a range get it)
    sl = EpochSlicer(ds)
    k = int(np.ceil((2.835312604904175 - ds.meta.t_start) / ds.meta.epoch_dt_s - 1e-9))
    for u in (1, 2, 3):
        inp = sl.epoch(k, u)
        assert np.any(np.isclose(inp.tdoa_m, by_hand, atol=1e-9)), u


def test_central_holds_the_initial_rest(converted, monkeypatch):
    """The oracle has the nodes' initial-rest model (imu.InitialRest, as graph.py): on the real
    flight's first 8 s every UAV starts at rest, its estimated speed stays near zero while the
    detector holds (no IMU drift), the detector lets go before the UAV really moves, and the
    rotor-drag factor is added only after it has (ground contact is not drag)."""
    from swarmnav.dataset import EpochSlicer
    from swarmnav.estimators import central as central_mod
    from swarmnav.estimators.central import CentralEstimator
    from services.settings import settings_for_dataset
    from swarmnav.evaluation import truth_at_epochs
    from swarmnav.initial import initial_states

    ds, _ = converted
    sl, tr = EpochSlicer(ds), truth_at_epochs(ds)
    c = CentralEstimator(ds.meta, settings_for_dataset(ds.meta), initial_states(ds, 0))
    assert all(r.active for r in c._rest.values())
    held = {u: 0 for u in sl.uavs}
    drag_keys = []  # the pose key of every drag factor added
    real = central_mod.rotor_drag_factor
    monkeypatch.setattr(central_mod, "rotor_drag_factor", lambda kx, *a: drag_keys.append(kx) or real(kx, *a))
    for k in range(1, 81):
        was = {u: c._rest[u].active for u in sl.uavs}
        drag_keys.clear()
        out = c.step({u: sl.epoch(k, u) for u in sl.uavs}, sl.range_labels(k), sl.tdoa_labels(k))
        assert sorted(drag_keys) == sorted(central_mod.X(u, k) for u in sl.uavs if not c._rest[u].active), k
        assert all(was[u] or not c._rest[u].active for u in sl.uavs)  # over for good
        for j, u in enumerate(sl.uavs):
            if c._rest[u].active:
                held[u] += 1
                assert np.linalg.norm(out[u].vel) < 0.05, (u, k, out[u].vel)
                assert np.linalg.norm(tr.vel[k - 1, j]) < 0.2, (u, k)  # really still
    assert all(n >= 10 for n in held.values()), held


@pytest.mark.slow  # > 15 s: `make test-fast` leaves it out, `make test` runs it
def test_heldout_cross_validation(converted):
    """The truth-free cross-validation behind the drag σ default (`swarmnav calibrate --dataset`):
    every anchor range of the span is held out exactly once and scored; on the first 20 s."""
    import dataclasses

    from swarmnav.calibration import heldout_anchor_cv
    from services.settings import settings_for_dataset

    ds, _ = converted
    short = dataclasses.replace(ds, meta=ds.meta.model_copy(update={"duration_s": 20.0}))
    r = ds.table("ranges")
    n_anchor = int(((r["b"] >= 100) & (r["t"] <= short.meta.epoch_time(short.meta.n_epochs()))).sum())
    res = heldout_anchor_cv(short, 0, settings_for_dataset(short.meta),
                            [{"drag_sigma_scale": 1.0}, {"drag_sigma_scale": 3.0}], folds=2)
    assert [c["settings"] for c in res] == [{"drag_sigma_scale": 1.0}, {"drag_sigma_scale": 3.0}]
    assert [c["n"] for c in res] == [n_anchor, n_anchor] and n_anchor > 20
    assert all(0.05 < c["median_abs_m"] <= c["rms_m"] * 3 < 30 for c in res)
    assert res[0]["rms_m"] != res[1]["rms_m"]  # the candidate setting reaches the estimator
    # held-out NIS: finite and of the order of 1 (the estimate reports a covariance)
    assert all(0.1 < c["nis_mean"] < 100 for c in res), [c["nis_mean"] for c in res]


def test_heldout_cv_holds_out_the_transactions_passive_rows(converted, monkeypatch):
    """A passive row overheard the held-out range's transaction (same time, same two tags) and
    carries its error in rdiff: the cross-validation removes it with the range (no leak), and only
    those rows."""
    import dataclasses

    import swarmnav.evaluation as ev
    from swarmnav.calibration import heldout_anchor_cv
    from services.settings import settings_for_dataset

    ds, _ = converted
    short = dataclasses.replace(ds, meta=ds.meta.model_copy(update={"duration_s": 10.0}))
    seen = []
    real = ev.run_algorithm
    monkeypatch.setattr(ev, "run_algorithm", lambda part, *a, **k: seen.append(part) or real(part, *a, **k))
    heldout_anchor_cv(short, 0, settings_for_dataset(short.meta), [{}], folds=2)
    r, td = ds.table("ranges"), ds.table("tdoa")
    key = lambda t, a, b: (float(t), frozenset((int(a), int(b))))  # noqa: E731
    for part in seen:
        pr = part.table("ranges")
        held = {key(*x) for x in zip(r["t"], r["tag_a"], r["tag_b"])} - {key(*x) for x in zip(pr["t"], pr["tag_a"], pr["tag_b"])}
        kept = {key(*x) for x in zip(*(part.table("tdoa")[c] for c in ("t", "tag_init", "tag_resp")))}
        every = [key(*x) for x in zip(td["t"], td["tag_init"], td["tag_resp"])]
        assert held and not kept & held
        assert len(part.table("tdoa")["t"]) == sum(k not in held for k in every) < len(every)


@pytest.mark.slow  # > 15 s: `make test-fast` leaves it out, `make test` runs it
def test_calibrate_dataset_cli(converted, tmp_path, capsys):
    """`swarmnav calibrate --dataset DIR --grid KEY=...`: a table and JSON; a bad grid is a clear error."""
    import dataclasses
    import json

    from services.cli import main

    ds, _ = converted
    dataclasses.replace(ds, meta=ds.meta.model_copy(update={"duration_s": 10.0})).write(tmp_path / "ds")
    assert main(["calibrate", "--dataset", str(tmp_path / "ds"), "--grid", "drag_sigma_scale=1,3", "--folds", "2",
                 "--out", str(tmp_path / "cv.json")]) == 0
    out = json.loads((tmp_path / "cv.json").read_text())
    assert [c["settings"] for c in out["candidates"]] == [{"drag_sigma_scale": 1.0}, {"drag_sigma_scale": 3.0}]
    printed = capsys.readouterr().out
    assert out["best"] in [c["settings"] for c in out["candidates"]] and "lowest held-out RMS" in printed
    assert "NIS median (0.455)" in printed and all(c["nis_mean"] > 0 for c in out["candidates"])
    assert out["algo"] == "fg"
    assert main(["calibrate", "--dataset", str(tmp_path / "ds"), "--grid", "relink_weight=0.3", "--folds", "2",
                 "--algo", "atvfg", "--out", str(tmp_path / "cv2.json")]) == 0
    assert json.loads((tmp_path / "cv2.json").read_text())["algo"] == "atvfg"
    assert main(["calibrate", "--dataset", str(tmp_path / "ds"), "--grid", "drag_sigma_scale"]) != 0
    assert "expected KEY=V1,V2" in capsys.readouterr().err


def test_write_read_deterministic(converted, tmp_path):
    ds, _ = converted
    ds.write(tmp_path / "a")
    ds.write(tmp_path / "b")
    for f in sorted((tmp_path / "a").iterdir()):
        assert f.read_bytes() == (tmp_path / "b" / f.name).read_bytes(), f.name
    back = Dataset.read(tmp_path / "a")
    assert back.meta == ds.meta
    np.testing.assert_array_equal(back.table("ranges")["tag_b"], ds.table("ranges")["tag_b"])
    assert "/" not in (tmp_path / "a" / "meta.json").read_text().split('"name"')[0]  # no paths before name


def test_cli(tmp_path):
    from services.cli import main

    assert main(["import-miluv", str(SRC), "--out", str(tmp_path / "ds")]) == 0
    meta = Dataset.read(tmp_path / "ds").meta
    assert meta.n_epochs() == 778
    # configs/miluv.toml's [estimation] table travels in the dataset and reaches the estimators
    from swarmnav.config import load_estimation
    from services.settings import settings_for_dataset

    assert meta.config["estimation"] == load_estimation(ROOT / "configs" / "miluv.toml")
    st = settings_for_dataset(meta)
    assert st["graph"]["relink_s"] == 3.0 and st["fixed_lag_s"] == 5.0 and st["convergence_m"] == 0.01  # unset: default
    assert main(["import-miluv", str(SRC), "--out", str(tmp_path / "plain"), "--estimation", "none"]) == 0
    plain = Dataset.read(tmp_path / "plain").meta
    assert "estimation" not in plain.config and plain.config_sha256 != meta.config_sha256  # in the provenance
    bad = tmp_path / "bad.toml"
    bad.write_text("[estimation]\nrounds = 0\n")
    assert main(["import-miluv", str(SRC), "--out", str(tmp_path / "y"), "--estimation", str(bad)]) == 2
    assert main(["import-miluv", str(tmp_path), "--out", str(tmp_path / "x")]) == 2  # no robot folders


def test_bad_input_messages(tmp_path):
    from services.importers.miluv import convert, read_csv, read_yaml

    p = tmp_path / "bad.csv"
    p.write_text('timestamp,range,pair\n0.1,2.0,"(1, 2)"\n0.2,oops,"(1, 2)"\n')
    with pytest.raises(DatasetError, match=r"bad.csv:3: column 'range' is not a number"):
        read_csv(p, ["timestamp", "range"])
    with pytest.raises(DatasetError, match="missing columns"):
        read_csv(p, ["timestamp", "std"])
    p.write_text("timestamp,range\n0.1,2.0,3.0\n")
    with pytest.raises(DatasetError, match="3 fields, header has 2"):
        read_csv(p, ["timestamp", "range"])
    y = tmp_path / "b.yaml"
    y.write_text('# c\nifo001:\n  "-0.0924"\n\nifo002:\n  "10": "[1, 2, 3]"\n')
    assert read_yaml(y) == {"ifo001": "-0.0924", "ifo002": {"10": "[1, 2, 3]"}}
    with pytest.raises(DatasetError, match="not a directory"):
        convert(tmp_path / "nope")
