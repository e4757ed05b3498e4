"""`simulate(scenario, seed) -> Dataset`: the seeded swarm simulator (pure: no I/O, no clocks).

Seeding: every random draw comes from ``np.random.default_rng([seed, STREAM, ...])`` streams, one per
purpose (and per UAV for the IMU), so the draws of one sensor do not depend on how another is
configured or on array chunking. Only UAV 1's start (``swarm.uav1_start_enu_m``) is fixed.

Output times: truth at every epoch t = k·epoch_dt_s, k = 0..K (the simulator keeps the full IMU-rate
truth internally, see :func:`simulate_full`); IMU at t = j/imu_rate_hz, j = 0..N−1 (sample j holds
over [t_j, t_j+1)); GNSS at t = j/gnss.rate_hz including t = 0; UWB ranges and relative
azimuth/elevation at every epoch k = 1..K (time-stamped at the epoch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..dataset import Dataset, DatasetMeta, Earth, EventSpec, GeoOrigin, Node, Window
from ..errors import ConfigError
from ..scenario import Scenario
from .sensors import (corrupt_imu, gnss_errors, gnss_sigma_total, imu_noise_si, in_window,
                      outage_uavs, pairs, simulate_rel, simulate_uwb)
from .trajectory import Truth, draw_wander, formation_offsets, simulate_truth

# stream ids (never reuse or renumber: datasets of a seed must stay the same)
S_FORMATION, S_WANDER, S_IMU, S_GNSS, S_UWB_BIAS, S_UWB_NOISE, S_UWB_LOSS, S_UWB_INTF, S_UWB_FAIL, S_REL = range(1, 11)
S_UWB_TAIL, S_UWB_NLOS = 11, 12  # realistic UWB model only ([faults.uwb], docs/uwb-errors.md)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), *stream])


@dataclass
class SimResult:
    truth: Truth
    dataset: Dataset


def _ratio(a: float, b: float, what: str) -> int:
    r = a / b
    n = int(round(r))
    if n < 1 or abs(r - n) > 1e-6:
        raise ConfigError(f"scenario: {what} must be a whole multiple (got {r})")
    return n


def simulate_full(sc: Scenario, seed: int | None = None) -> SimResult:
    """Simulate and return both the dataset and the full-rate truth / ideal IMU (for tests)."""
    seed = sc.scenario.seed if seed is None else int(seed)
    if seed < 0:
        raise ConfigError("seed must be >= 0")
    meta_s = sc.scenario
    ids = np.arange(1, sc.swarm.n_uavs + 1)
    step = _ratio(meta_s.epoch_dt_s * meta_s.imu_rate_hz, 1.0, "epoch_dt_s × imu_rate_hz (IMU samples per epoch)")
    K = _ratio(meta_s.duration_s, meta_s.epoch_dt_s, "duration_s / epoch_dt_s (number of epochs)")

    tr = simulate_truth(sc, formation_offsets(sc, _rng(seed, S_FORMATION)), draw_wander(sc, _rng(seed, S_WANDER)))
    roles = [sc.swarm.role(int(u)) for u in ids]
    noise = {r: imu_noise_si(sc.sensors.imu[r]) for r in ("master", "slave")}
    te = np.arange(K + 1) * meta_s.epoch_dt_s  # epoch times k = 0..K
    pe = tr.pos[np.arange(K + 1) * step]
    outages = [Window(start_s=o.start_s, end_s=o.end_s, uavs=outage_uavs(o.uavs, sc)) for o in sc.faults.gnss_outage]
    tables = {"truth": _truth_table(tr, ids, np.arange(K + 1) * step, te),
              "imu": _imu_table(tr, ids, roles, noise, seed),
              "gnss": _gnss_table(sc, tr, ids, roles, outages, _rng(seed, S_GNSS)),
              "ranges": _ranges_table(sc, ids, te, pe, seed),
              "rel": _rel_table(sc, ids, te[1:], pe[1:], _rng(seed, S_REL))}
    sigma = sc.sensors.uwb.sigma_m
    o = sc.origin
    meta = DatasetMeta(
        name=meta_s.name, source="simulated", seed=seed, config=sc.to_dict(), config_sha256=sc.sha256(),
        origin=GeoOrigin(lat_deg=o.lat_deg, lon_deg=o.lon_deg, alt_m=o.alt_m),
        t_start=0.0, duration_s=meta_s.duration_s, epoch_dt_s=meta_s.epoch_dt_s, nodes=_nodes(sc, ids, roles, noise),
        earth=Earth(gravity_mps2=tr.gravity, earth_rate_radps=tuple(float(x) for x in tr.earth_rate)),
        uwb_sigma_m=sigma, rel_sigma_rad=float(np.deg2rad(sc.sensors.rel.sigma_deg)), fault_threshold_m=3.0 * sigma,
        gnss_outages=outages, events=_kill_events(sc), init=sc.init.model_dump(mode="json"),
    )
    return SimResult(truth=tr, dataset=Dataset(meta, tables))


def _truth_table(tr: Truth, ids: np.ndarray, ke: np.ndarray, te: np.ndarray) -> dict[str, np.ndarray]:
    """Truth at the epoch times ``te`` (IMU sample indices ``ke``), one row per (epoch, UAV)."""
    U = len(ids)
    pe, ve, qe = tr.pos[ke], tr.vel[ke], tr.quat[ke]
    return {
        "t": np.repeat(te, U), "node": np.tile(ids, len(te)),
        **{c: pe[..., i].ravel() for i, c in enumerate(("pe", "pn", "pu"))},
        **{c: ve[..., i].ravel() for i, c in enumerate(("ve", "vn", "vu"))},
        **{c: qe[..., i].ravel() for i, c in enumerate(("qw", "qx", "qy", "qz"))},
    }


def _imu_table(tr: Truth, ids: np.ndarray, roles: list[str], noise: dict, seed: int) -> dict[str, np.ndarray]:
    """The ideal IMU corrupted per UAV (its own stream), one row per (sample, UAV)."""
    gm = np.empty_like(tr.gyro)
    am = np.empty_like(tr.accel)
    for i, u in enumerate(ids):
        gm[:, i], am[:, i], _ = corrupt_imu(tr.gyro[:, i], tr.accel[:, i], noise[roles[i]], tr.dt, _rng(seed, S_IMU, int(u)))
    N, U = tr.gyro.shape[0], len(ids)
    return {"t": np.repeat(tr.t[:N], U), "node": np.tile(ids, N),
            "gx": gm[..., 0].ravel(), "gy": gm[..., 1].ravel(), "gz": gm[..., 2].ravel(),
            "ax": am[..., 0].ravel(), "ay": am[..., 1].ravel(), "az": am[..., 2].ravel()}


def _gnss_table(sc: Scenario, tr: Truth, ids: np.ndarray, roles: list[str], outages: list[Window],
                rng_g: np.random.Generator) -> dict[str, np.ndarray]:
    """GNSS fixes (geodetic position, ENU velocity, sigmas) at each role's rate, none inside an
    outage of the UAV; sorted by (t, node). One stream for all UAVs, drawn in id order."""
    import pymap3d

    rate, N = sc.scenario.imu_rate_hz, tr.gyro.shape[0]
    rows = []
    for i, u in enumerate(ids):
        sp = sc.sensors.gnss[roles[i]]
        gstep = _ratio(rate / sp.rate_hz, 1.0, f"imu_rate_hz / sensors.gnss.{roles[i]}.rate_hz")
        kg = np.arange(0, N + 1, gstep)
        tg = kg / rate
        perr, verr = gnss_errors(sp, len(kg), gstep / rate, rng_g)
        ok = np.ones(len(kg), bool)
        for w in outages:
            if int(u) in w.uavs:
                ok &= ~in_window(tg, w.start_s, w.end_s)
        p = tr.pos[kg, i] + perr
        v = tr.vel[kg, i] + verr
        rows.append(dict(t=tg[ok], node=np.full(ok.sum(), u), p=p[ok], v=v[ok], sig=gnss_sigma_total(sp), sv=sp.vel_sigma_mps))
    t_all = np.concatenate([r["t"] for r in rows])
    node_all = np.concatenate([r["node"] for r in rows])
    order = np.lexsort((node_all, t_all))
    p_all = np.concatenate([r["p"] for r in rows])[order]
    v_all = np.concatenate([r["v"] for r in rows])[order]
    sig_all = np.concatenate([np.broadcast_to(r["sig"], (len(r["t"]), 3)) for r in rows])[order]
    sv_all = np.concatenate([np.full(len(r["t"]), r["sv"]) for r in rows])[order]
    o = sc.origin
    lat, lon, h = pymap3d.enu2geodetic(p_all[:, 0], p_all[:, 1], p_all[:, 2], o.lat_deg, o.lon_deg, o.alt_m)
    return {"t": t_all[order], "node": node_all[order],
            "lat_deg": np.asarray(lat, float), "lon_deg": np.asarray(lon, float), "h_m": np.asarray(h, float),
            "ve": v_all[:, 0], "vn": v_all[:, 1], "vu": v_all[:, 2],
            "sig_pe": sig_all[:, 0], "sig_pn": sig_all[:, 1], "sig_pu": sig_all[:, 2], "sig_v": sv_all}


def _ranges_table(sc: Scenario, ids: np.ndarray, te: np.ndarray, pe: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """UWB ranges at epochs k = 1..K (truth positions ``pe`` at times ``te``, k = 0..K), sorted by (t, a, b)."""
    tk = te[1:]
    uwb = simulate_uwb(sc, tk, pe[1:], _rng(seed, S_UWB_BIAS), _rng(seed, S_UWB_NOISE), _rng(seed, S_UWB_LOSS),
                       _rng(seed, S_UWB_INTF), _rng(seed, S_UWB_FAIL), _rng(seed, S_UWB_TAIL),
                       _rng(seed, S_UWB_NLOS), t0=float(te[0]))
    ia, ib = pairs(len(ids))
    kk, jj = np.nonzero(uwb.keep)  # row-major: sorted by (t, a, b)
    return {"t": tk[kk], "a": ids[ia[jj]], "b": ids[ib[jj]],
            "tag_a": np.zeros(len(kk), np.int64), "tag_b": np.zeros(len(kk), np.int64),
            "range": uwb.range[kk, jj], "sigma": np.full(len(kk), sc.sensors.uwb.sigma_m),
            "fault_kind": uwb.kind[kk, jj], "fault_err": uwb.err[kk, jj]}


def _rel_table(sc: Scenario, ids: np.ndarray, tk: np.ndarray, pk: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Relative azimuth / elevation at epochs k = 1..K."""
    az, el, mask = simulate_rel(sc, pk, rng)
    kr, orr, trr = np.nonzero(mask)
    rsig = float(np.deg2rad(sc.sensors.rel.sigma_deg))
    return {"t": tk[kr], "observer": ids[orr], "target": ids[trr],
            "azimuth": az[kr, orr, trr], "elevation": el[kr, orr, trr], "sigma": np.full(len(kr), rsig)}


def _nodes(sc: Scenario, ids: np.ndarray, roles: list[str], noise: dict) -> list[Node]:
    """What the dataset says about each UAV's sensors (its role's IMU noise and GNSS sigmas)."""
    nodes = []
    for i, u in enumerate(ids):
        sp = sc.sensors.gnss[roles[i]]
        nodes.append(Node(id=int(u), kind="uav", role=roles[i], imu=noise[roles[i]],
                          gnss_pos_sigma_m=tuple(float(x) for x in gnss_sigma_total(sp)),
                          gnss_vel_sigma_mps=float(sp.vel_sigma_mps),
                          gnss_correlated_sigma_m=float(sp.gm_sigma_m),
                          gnss_correlation_time_s=float(sp.gm_tau_s) if sp.gm_sigma_m > 0 else None))
    return nodes


def _kill_events(sc: Scenario) -> list[EventSpec]:
    """The scheduled process kills and restarts (distributed runs), sorted by (t, uav, kind)."""
    events = []
    for pk in sc.faults.process_kill:
        events.append(EventSpec(t=pk.at_s, kind="kill", uav=pk.uav))
        if pk.restart_s is not None:
            events.append(EventSpec(t=pk.restart_s, kind="restart", uav=pk.uav))
    events.sort(key=lambda e: (e.t, e.uav, e.kind))
    return events


def simulate(scenario: Scenario, seed: int | None = None) -> Dataset:
    """Simulate ``scenario`` with ``seed`` (default: the config's) and return the dataset."""
    return simulate_full(scenario, seed).dataset
