"""Simulated noise and bias statistics match the config, within confidence bounds computed here.

Every check compares a normalised sum of squares with chi-square quantiles (two-sided, tail
probability 1e-6 each: an honest model passes, a wrong sigma by ~10 % on these sample sizes fails),
or a rate with a normal bound of 5 standard errors.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from swarmnav.config import _read_toml, parse_config
from swarmnav.dataset import FaultKind, ImuNoise
from swarmnav.sim import simulate_full
from swarmnav.sim.earth import DPH, DPHPSH, DPSH, UG
from swarmnav.sim.sensors import corrupt_imu, gnss_errors, gnss_sigma_total, imu_noise_si

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
P_TAIL = 1e-6


def chi2_ok(s, n):
    lo, hi = chi2.ppf(P_TAIL, n), chi2.isf(P_TAIL, n)
    assert lo < s < hi, f"chi2 statistic {s:.1f} outside [{lo:.1f}, {hi:.1f}] for {n} dof (ratio {s / n:.3f})"


@pytest.fixture(scope="module")
def run():
    d = _read_toml(CONFIGS / "smoke.toml")
    d["scenario"].update(name="stats", duration_s=200.0)
    d["swarm"].update(n_uavs=24, masters=[2, 9, 16], min_separation_m=5.0, box_u_m=[100.0, 150.0])
    sc = parse_config(d, "stats")
    return sc, simulate_full(sc, 11)


def _imu(ds, U):
    imu = ds.tables["imu"]
    g = np.stack([imu["gx"], imu["gy"], imu["gz"]], -1).reshape(-1, U, 3)
    a = np.stack([imu["ax"], imu["ay"], imu["az"]], -1).reshape(-1, U, 3)
    return g, a


def test_psins_units():
    assert DPH == pytest.approx(np.pi / 180 / 3600)
    assert DPSH == pytest.approx(np.pi / 180 / 60)
    assert UG == pytest.approx(9.7803267714e-6)
    assert DPHPSH == pytest.approx(np.pi / 180 / 3600 / 60)


def test_meta_carries_si_noise(run):
    sc, res = run
    meta = res.dataset.meta
    for n in meta.nodes:
        assert n.imu == imu_noise_si(sc.sensors.imu[sc.swarm.role(n.id)])
        assert n.role == sc.swarm.role(n.id)
    assert meta.node(2).imu.gyro_bias_sigma == pytest.approx(0.5 * DPH)
    assert meta.node(1).imu.accel_noise_density == pytest.approx(100 * UG)


@pytest.mark.parametrize("role", ["slave", "master"])
def test_imu_white_noise_and_constant_bias(run, role):
    sc, res = run
    tr, ds = res.truth, res.dataset
    U = sc.swarm.n_uavs
    cols = [i for i, u in enumerate(sc.uav_ids()) if sc.swarm.role(u) == role]
    nz = imu_noise_si(sc.sensors.imu[role])
    g, a = _imu(ds, U)
    dt = tr.dt
    N = g.shape[0]
    for meas, ideal, dens, rw, b0 in ((g, tr.gyro, nz.gyro_noise_density, nz.gyro_bias_rw, nz.gyro_bias_sigma),
                                      (a, tr.accel, nz.accel_noise_density, nz.accel_bias_rw, nz.accel_bias_sigma)):
        e = (meas - ideal)[:, cols]
        # white noise: non-overlapping first differences, var = 2 sigma_w^2 + sigma_rw^2 dt
        d = e[1::2] - e[0::2]
        var = 2 * dens**2 / dt + rw**2 * dt
        chi2_ok(np.sum(d**2) / var, d.size)
        # constant bias: the per-axis mean, var = sigma_b^2 + sigma_w^2 / N + sigma_rw^2 T / 3
        m = e.mean(axis=0)
        var_m = b0**2 + dens**2 / dt / N + rw**2 * (N * dt) / 3
        chi2_ok(np.sum(m**2) / var_m, m.size)


def test_imu_bias_random_walk():
    nz = ImuNoise(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_bias_sigma=0.0, accel_bias_sigma=0.0,
                  gyro_bias_rw=1.0 * DPHPSH, accel_bias_rw=10.0 * UG)
    dt = 0.01
    z = np.zeros((50000, 3))
    g, a, _ = corrupt_imu(z, z, nz, dt, np.random.default_rng(5))
    assert np.all(g[0] == 0) and np.all(a[0] == 0)  # the walk starts at the constant bias
    for x, rw in ((g, nz.gyro_bias_rw), (a, nz.accel_bias_rw)):
        inc = np.diff(x, axis=0)
        chi2_ok(np.sum(inc**2) / (rw**2 * dt), inc.size)


@pytest.mark.parametrize("role", ["slave", "master"])
def test_gnss_noise(run, role):
    sc, res = run
    ds, tr = res.dataset, res.truth
    spec = sc.sensors.gnss[role]
    g = ds.gnss_enu()
    U = sc.swarm.n_uavs
    nodes = [u for u in sc.uav_ids() if sc.swarm.role(u) == role]
    steps = int(round(sc.scenario.imu_rate_hz / spec.rate_hz))
    phi = np.exp(-1.0 / spec.gm_tau_s / spec.rate_hz)
    ep, ev = [], []
    for u in nodes:
        m = g["node"] == u
        k = np.rint(g["t"][m] * sc.scenario.imu_rate_hz).astype(int)
        ep.append(np.stack([g["pe"][m], g["pn"][m], g["pu"][m]], -1) - tr.pos[k, u - 1])
        ev.append(np.stack([g["ve"][m], g["vn"][m], g["vu"][m]], -1) - tr.vel[k, u - 1])
        assert np.all(np.diff(k) == steps)
        np.testing.assert_allclose([g["sig_pe"][m][0], g["sig_pn"][m][0], g["sig_pu"][m][0]], gnss_sigma_total(spec))
    ep, ev = np.array(ep), np.array(ev)  # (n_uav, T, 3)
    n2 = ep.shape[1] // 2 * 2
    d = ep[:, 1:n2:2] - ep[:, 0:n2:2]
    var = 2 * np.asarray(spec.pos_sigma_m) ** 2 + 2 * spec.gm_sigma_m**2 * (1 - phi)
    chi2_ok(np.sum(d**2 / var), d.size)
    chi2_ok(np.sum(ev**2) / spec.vel_sigma_mps**2, ev.size)
    assert U == 24


def test_gnss_gauss_markov_bias():
    from swarmnav.config import GnssSpec

    spec = GnssSpec(pos_sigma_m=(0.0, 0.0, 0.0), gm_sigma_m=3.0, gm_tau_s=120.0, vel_sigma_mps=0.2)
    n = 100000
    e, v = gnss_errors(spec, n, 1.0, np.random.default_rng(3))
    phi = np.exp(-1.0 / 120.0)
    x0, x1 = e[:-1].ravel(), e[1:].ravel()
    phi_hat = np.sum(x0 * x1) / np.sum(x0 * x0)
    assert abs(phi_hat - phi) < 5 * np.sqrt((1 - phi**2) / x0.size)
    # stationary variance; AR(1) sample variance has var 2 s^4 (1 + phi^2) / (1 - phi^2) / n
    s2 = np.mean(e**2)
    assert abs(s2 / 9.0 - 1) < 5 * np.sqrt(2 * (1 + phi**2) / (1 - phi**2) / e.size)


def test_uwb_noise_link_bias_and_loss(run):
    sc, res = run
    ds = res.dataset
    uw = sc.sensors.uwb
    r = ds.tables["ranges"]
    U = sc.swarm.n_uavs
    tr = ds.tables["truth"]
    P = np.stack([tr["pe"], tr["pn"], tr["pu"]], -1).reshape(-1, U, 3)
    k = np.rint(r["t"]).astype(int)
    e = r["range"] - np.linalg.norm(P[k, r["a"] - 1] - P[k, r["b"] - 1], axis=-1)
    clean = r["fault_kind"] == FaultKind.NONE
    link = (r["a"] * 100 + r["b"])[clean]
    ec = e[clean]
    ids, inv, cnt = np.unique(link, return_inverse=True, return_counts=True)
    mean = np.bincount(inv, ec) / cnt
    within = np.sum((ec - mean[inv]) ** 2) / uw.sigma_m**2
    chi2_ok(within, ec.size - ids.size)
    chi2_ok(np.sum(mean**2 / (uw.link_bias_sigma_m**2 + uw.sigma_m**2 / cnt)), ids.size)
    # packet loss among in-range link-epochs
    ia, ib = np.triu_indices(U, 1)
    dist = np.linalg.norm(P[1:, ia] - P[1:, ib], axis=-1)
    n_in = int((dist <= uw.max_range_m).sum())
    lost = n_in - len(r["t"])
    p = uw.packet_loss
    assert abs(lost / n_in - p) < 5 * np.sqrt(p * (1 - p) / n_in)
    assert np.all(r["sigma"] == uw.sigma_m)


def test_uwb_interference_rate_and_dwell(run):
    sc, res = run
    fi = sc.faults.interference
    r = res.dataset.tables["ranges"]
    other = {f.uav for f in sc.faults.module_failure + sc.faults.stuck}
    skip = np.isin(r["a"], list(other)) | np.isin(r["b"], list(other))
    for d in sc.faults.drift:
        skip |= (r["a"] == min(d.link)) & (r["b"] == max(d.link))
    r = {c: v[~skip] for c, v in r.items()}
    intf = r["fault_kind"] == FaultKind.INTERFERENCE
    f = fi.time_fraction
    T = sc.scenario.duration_s
    L = len(np.unique(r["a"] * 100 + r["b"]))
    lam_out = 1 / fi.mean_dwell_s
    lam_in = lam_out * f / (1 - f)
    tau_c = 1 / (lam_in + lam_out)
    assert abs(intf.mean() - f) < 5 * np.sqrt(2 * f * (1 - f) * tau_c / T / L)
    # exit rate from consecutive epochs of the same link
    key = r["a"] * 100 + r["b"]
    order = np.lexsort((r["t"], key))
    same = (np.diff(key[order]) == 0) & (np.diff(r["t"][order]) == 1.0)
    was = intf[order][:-1] & same
    left = was & ~intf[order][1:]
    p_exit = left.sum() / was.sum()
    assert abs(p_exit - lam_out) < 5 * np.sqrt(lam_out * (1 - lam_out) / was.sum())
    # episode bias ~ U(bias_m): the per-row error mean ~ midpoint (noise averages out)
    err = r["fault_err"][intf]
    assert fi.bias_m[0] - 2 < err.min() and err.max() < fi.bias_m[1] + 2
    assert abs(err.mean() - np.mean(fi.bias_m)) < 1.0


def test_rel_az_el_noise(run):
    sc, res = run
    ds = res.dataset
    U = sc.swarm.n_uavs
    rel = ds.tables["rel"]
    tr = ds.tables["truth"]
    P = np.stack([tr["pe"], tr["pn"], tr["pu"]], -1).reshape(-1, U, 3)
    k = np.rint(rel["t"]).astype(int)
    dvec = P[k, rel["target"] - 1] - P[k, rel["observer"] - 1]
    az = np.arctan2(dvec[:, 1], dvec[:, 0])
    el = np.arctan2(dvec[:, 2], np.hypot(dvec[:, 0], dvec[:, 1]))
    assert np.all(np.linalg.norm(dvec, axis=-1) <= sc.sensors.rel.max_range_m)
    assert np.all(rel["observer"] != rel["target"])
    assert np.all((rel["azimuth"] > -np.pi) & (rel["azimuth"] <= np.pi))
    daz = np.angle(np.exp(1j * (rel["azimuth"] - az)))
    sig = np.deg2rad(sc.sensors.rel.sigma_deg)
    chi2_ok(np.sum(daz**2) / sig**2, daz.size)
    chi2_ok(np.sum((rel["elevation"] - el) ** 2) / sig**2, el.size)
    # every in-range ordered pair observed at every epoch (no loss for az/el)
    dist = np.linalg.norm(P[1:, :, None] - P[1:, None], axis=-1)
    assert len(rel["t"]) == int(((dist <= sc.sensors.rel.max_range_m) & ~np.eye(U, dtype=bool)).sum())
