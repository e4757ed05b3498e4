"""Faults and outages appear exactly where and when the config says, with the right labels."""

from pathlib import Path

import numpy as np
import pytest

from swarmnav.config import load_config, parse_config
from swarmnav.config import _read_toml
from swarmnav.dataset import FaultKind
from swarmnav.sim import simulate, simulate_full

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _variant(name, **patch):
    d = _read_toml(CONFIGS / f"{name}.toml")
    for path, v in patch.items():
        cur = d
        keys = path.split("__")
        for k in keys[:-1]:
            cur = cur.setdefault(k, {})
        cur[keys[-1]] = v
    return parse_config(d, f"{name} variant")


def _true_ranges(ds):
    """(t, a, b) -> true distance from the truth table (epoch times)."""
    tr = ds.tables["truth"]
    U = len(ds.meta.uav_ids())
    P = np.stack([tr["pe"], tr["pn"], tr["pu"]], -1).reshape(-1, U, 3)
    r = ds.tables["ranges"]
    k = np.rint(r["t"] / ds.meta.epoch_dt_s).astype(int)
    return np.linalg.norm(P[k, r["a"] - 1] - P[k, r["b"] - 1], axis=-1)


@pytest.fixture(scope="module")
def smoke_clean():
    """smoke without interference and packet loss: every other fault is exactly checkable."""
    sc = _variant("smoke", faults__interference={"enabled": False}, sensors__uwb={"packet_loss": 0.0})
    return sc, simulate(sc)


def test_module_failure_where_and_when(smoke_clean):
    sc, ds = smoke_clean
    mf = sc.faults.module_failure[0]
    r = ds.tables["ranges"]
    involved = (r["a"] == mf.uav) | (r["b"] == mf.uav)
    win = (r["t"] >= mf.start_s) & (r["t"] <= mf.end_s)
    assert np.all(r["fault_kind"][involved & win] == FaultKind.FAILURE)
    assert np.all(r["fault_kind"][~(involved & win)] != FaultKind.FAILURE)
    n_links = sc.swarm.n_uavs - 1
    assert (involved & win).sum() == n_links * (int(mf.end_s) - int(mf.start_s) + 1)
    e = r["fault_err"][involved & win]
    assert e.min() >= mf.error_m[0] and e.max() <= mf.error_m[1]
    assert len(np.unique(e)) == len(e)  # a new draw per measurement
    resid = r["range"] - _true_ranges(ds) - r["fault_err"]  # what is left is the nominal noise + link bias
    assert np.abs(resid).max() < 0.1 * 6 + 0.05 * 5


def test_stuck_module_repeats_start_range(smoke_clean):
    sc, ds = smoke_clean
    st = sc.faults.stuck[0]
    r = ds.tables["ranges"]
    involved = (r["a"] == st.uav) | (r["b"] == st.uav)
    win = (r["t"] >= st.start_s) & (r["t"] <= st.end_s)
    sel = involved & win
    assert np.all(r["fault_kind"][sel] == FaultKind.STUCK)
    assert not np.any(r["fault_kind"][~sel] == FaultKind.STUCK)
    for other in sorted((set(r["a"][sel]) | set(r["b"][sel])) - {st.uav}):
        link = sel & (((r["a"] == other) | (r["b"] == other)))
        vals = r["range"][link]
        assert len(vals) == int(st.end_s - st.start_s) + 1
        assert np.all(vals == vals[0])  # repeats the range measured at start_s
        at0 = link & (r["t"] == st.start_s)
        assert r["fault_err"][at0][0] == 0.0  # the measurement at start_s itself is genuine
    true = _true_ranges(ds)
    np.testing.assert_allclose(r["fault_err"][sel], r["range"][sel] - true[sel], atol=0.1 * 6 + 0.05 * 5)


def test_drift_grows_then_clears(smoke_clean):
    sc, ds = smoke_clean
    dr = sc.faults.drift[0]
    a, b = sorted(dr.link)
    r = ds.tables["ranges"]
    link = (r["a"] == a) & (r["b"] == b)
    win = (r["t"] >= dr.start_s) & (r["t"] <= dr.end_s)
    assert np.all(r["fault_kind"][link & win] == FaultKind.DRIFT)
    assert not np.any(r["fault_kind"][~(link & win)] == FaultKind.DRIFT)
    np.testing.assert_allclose(r["fault_err"][link & win], dr.rate_mps * (r["t"][link & win] - dr.start_s), atol=1e-12)
    after = link & (r["t"] > dr.end_s)
    assert after.any() and np.all(r["fault_err"][after] == 0.0) and np.all(r["fault_kind"][after] == 0)


def test_no_faults_elsewhere_and_threshold(smoke_clean):
    sc, ds = smoke_clean
    r = ds.tables["ranges"]
    assert ds.meta.fault_threshold_m == pytest.approx(3 * sc.sensors.uwb.sigma_m)
    clean = r["fault_kind"] == 0
    assert np.all(r["fault_err"][clean] == 0.0)


def test_interference_labels_and_size():
    sc = load_config(CONFIGS / "smoke.toml")
    sc = _variant("smoke", scenario={"name": "smoke", "duration_s": 300.0},
                  faults={"interference": {"enabled": True, "mean_dwell_s": 5.0, "time_fraction": 0.1}})
    ds = simulate(sc, 7)
    fi = sc.faults.interference
    r = ds.tables["ranges"]
    m = r["fault_kind"] == FaultKind.INTERFERENCE
    assert m.any()
    resid = r["range"] - _true_ranges(ds)
    sig = sc.sensors.uwb.sigma_m
    # err = episode bias U(1, 8) + (noise_scale - 1) sigma n; the range carries it
    lo = fi.bias_m[0] - 6 * (fi.noise_scale - 1) * sig
    hi = fi.bias_m[1] + 6 * (fi.noise_scale - 1) * sig
    assert r["fault_err"][m].min() > lo and r["fault_err"][m].max() < hi
    np.testing.assert_allclose(resid[m] - r["fault_err"][m], 0.0, atol=6 * sig + 5 * 0.05)
    # inside an interfered link-epoch the extra noise is noise_scale x: the residual spread within
    # episodes (consecutive epochs, same bias) is about noise_scale * sigma * sqrt(2) per difference
    k = np.rint(r["t"] / ds.meta.epoch_dt_s).astype(int)
    key = r["a"] * 100 + r["b"]
    order = np.lexsort((k, key))
    same = (np.diff(key[order]) == 0) & (np.diff(k[order]) == 1) & m[order][1:] & m[order][:-1]
    d_err = np.diff(r["fault_err"][order])[same]
    d_err = d_err[np.abs(d_err) < 1.5]  # drop episode boundaries (new bias draw)
    s = np.std(d_err) / np.sqrt(2) / ((fi.noise_scale - 1) * sig)
    assert 0.8 < s < 1.2


@pytest.mark.slow  # > 15 s: `make test-fast` leaves it out, `make test` runs it
def test_gnss_absent_exactly_in_outage_windows():
    sc = load_config(CONFIGS / "gnss_denied.toml")
    res = simulate_full(sc)
    ds = res.dataset
    g = ds.tables["gnss"]
    o = sc.faults.gnss_outage[0]
    slaves = [u for u in sc.uav_ids() if u not in sc.swarm.masters]
    assert ds.meta.gnss_outages[0].uavs == slaves
    assert (ds.meta.gnss_outages[0].start_s, ds.meta.gnss_outages[0].end_s) == (o.start_s, o.end_s)
    all_t = np.arange(0, int(sc.scenario.duration_s) + 1, dtype=float)
    for u in sc.uav_ids():
        have = g["t"][g["node"] == u]
        if u in slaves:
            expect = all_t[(all_t < o.start_s) | (all_t > o.end_s)]
        else:
            expect = all_t
        assert np.array_equal(have, expect), u
    # the rest of the data is untouched by the outage: same IMU as the paper run
    paper = simulate(load_config(CONFIGS / "paper.toml"))
    assert np.array_equal(paper.tables["imu"]["gx"][:1000], ds.tables["imu"]["gx"][:1000])


def test_paper_fault_schedule_labels():
    """The paper's four faults, as configured (interference rates checked in the statistics tests)."""
    sc = load_config(CONFIGS / "paper.toml")
    sc = _variant("paper", scenario={"name": "paper", "duration_s": 800.0}, faults__interference={"enabled": False},
                  sensors__uwb={"packet_loss": 0.0})
    ds = simulate(sc)
    r = ds.tables["ranges"]
    kinds = r["fault_kind"]
    t = r["t"]
    inv = lambda u: (r["a"] == u) | (r["b"] == u)  # noqa: E731
    fail = kinds == FaultKind.FAILURE
    assert np.array_equal(fail, inv(5) & (t >= 300) & (t <= 500) & ~(inv(12) & (t >= 700) & (t <= 760)))
    stuck = kinds == FaultKind.STUCK
    assert np.array_equal(stuck, inv(12) & (t >= 700) & (t <= 760))
    drift = kinds == FaultKind.DRIFT
    assert np.array_equal(drift, (r["a"] == 3) & (r["b"] == 11) & (t >= 600) & (t <= 800) & ~stuck)
    assert np.all(r["fault_err"][fail] >= 20) and np.all(r["fault_err"][fail] <= 150)
    assert r["fault_err"][drift].max() == pytest.approx(0.05 * 200)
