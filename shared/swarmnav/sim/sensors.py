"""Sensor models of the simulator: IMU errors, GNSS, UWB two-way ranging with faults, relative az/el.

All functions are pure and vectorised; randomness comes from the generators passed in (one
stream per purpose, derived from the run seed in ``simulate.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import GnssSpec, ImuSpec, Scenario
from ..dataset import FaultKind, ImuNoise
from ..models.bearing import azimuth_elevation
from ..models.uwb_range import distance
from .earth import DPH, DPHPSH, DPSH, UG, UGPSHZ, UGPSSH

EPS_T = 1e-9


# -- IMU ------------------------------------------------------------------------------------


def imu_noise_si(spec: ImuSpec) -> ImuNoise:
    """PSINS imuerrset(eb °/h, db µg, web °/√h, wdb µg/√Hz) + bias random walk -> SI."""
    return ImuNoise(
        gyro_noise_density=spec.arw_dpsh * DPSH,
        accel_noise_density=spec.vrw_ugpshz * UGPSHZ,
        gyro_bias_sigma=spec.gyro_bias_dph * DPH,
        accel_bias_sigma=spec.accel_bias_ug * UG,
        gyro_bias_rw=spec.gyro_bias_rw_dphpsh * DPHPSH,
        accel_bias_rw=spec.accel_bias_rw_ugpssh * UGPSSH,
    )


@dataclass
class ImuErrors:
    gyro_bias0: np.ndarray  # (3,) constant turn-on bias
    accel_bias0: np.ndarray


def corrupt_imu(gyro: np.ndarray, accel: np.ndarray, noise: ImuNoise, dt: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, ImuErrors]:
    """One UAV's (N,3) ideal samples -> measured: + constant bias N(0, σ_b) + random walk + white.

    Bias at sample k: b0 + Σ_{j<k} σ_rw √dt n_j (b at k = 0 is b0). White noise per sample:
    density / √dt (sample k is the average over its hold interval).
    """
    N = gyro.shape[0]
    bg0 = rng.normal(0.0, noise.gyro_bias_sigma, 3)
    ba0 = rng.normal(0.0, noise.accel_bias_sigma, 3)
    sq = np.sqrt(dt)

    def walk(sig):
        w = rng.normal(0.0, sig * sq, (N, 3))
        w = np.cumsum(w, axis=0)
        w[1:] = w[:-1].copy()
        w[0] = 0.0
        return w

    g = gyro + bg0 + walk(noise.gyro_bias_rw) + rng.normal(0.0, noise.gyro_noise_density / sq, (N, 3))
    a = accel + ba0 + walk(noise.accel_bias_rw) + rng.normal(0.0, noise.accel_noise_density / sq, (N, 3))
    return g, a, ImuErrors(bg0, ba0)


# -- GNSS -----------------------------------------------------------------------------------


def gnss_sigma_total(spec: GnssSpec) -> np.ndarray:
    """Per-axis 1-σ of the total position error (white ⊕ stationary Gauss–Markov bias)."""
    return np.sqrt(np.asarray(spec.pos_sigma_m, float) ** 2 + spec.gm_sigma_m**2)


def gnss_errors(spec: GnssSpec, n: int, dt: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n,3) position error (white + first-order GM bias, stationary from the start) and (n,3) velocity error."""
    white = rng.normal(0.0, 1.0, (n, 3)) * np.asarray(spec.pos_sigma_m, float)
    gm = np.zeros((n, 3))
    if spec.gm_sigma_m > 0:
        phi = np.exp(-dt / spec.gm_tau_s)
        drive = rng.normal(0.0, spec.gm_sigma_m * np.sqrt(1.0 - phi * phi), (n, 3))
        gm[0] = rng.normal(0.0, spec.gm_sigma_m, 3)
        for k in range(1, n):
            gm[k] = phi * gm[k - 1] + drive[k]
    vel = rng.normal(0.0, spec.vel_sigma_mps, (n, 3))
    return white + gm, vel


def outage_uavs(sel, sc: Scenario) -> list[int]:
    ids = sc.uav_ids()
    if sel == "all":
        return ids
    if sel == "masters":
        return [u for u in ids if u in sc.swarm.masters]
    if sel == "slaves":
        return [u for u in ids if u not in sc.swarm.masters]
    return sorted(int(u) for u in sel)


def in_window(t: np.ndarray, start: float, end: float) -> np.ndarray:
    """Closed window start <= t <= end (with a small tolerance for float epoch times)."""
    return (t >= start - EPS_T) & (t <= end + EPS_T)


# -- UWB ------------------------------------------------------------------------------------


def pairs(U: int) -> tuple[np.ndarray, np.ndarray]:
    """Unordered pairs (a < b), 0-based indices, lexicographic order."""
    a, b = np.triu_indices(U, k=1)
    return a, b


@dataclass
class UwbResult:
    range: np.ndarray  # (K,P) measured range (all link-epochs, before range limit and loss)
    true: np.ndarray  # (K,P)
    kind: np.ndarray  # (K,P) FaultKind
    err: np.ndarray  # (K,P) added error, m
    keep: np.ndarray  # (K,P) bool: row emitted (within max range and not lost)
    link_bias: np.ndarray  # (P,)
    interfered: np.ndarray  # (K,P) bool


# -- realistic UWB errors (``[faults.uwb] model = "realistic"``, docs/uwb-errors.md) ---------------


def student_t_q75(dof: float) -> float:
    """Upper quartile t_ν⁻¹(0.75) of the standard Student-t: bisection on ∫₀^q density = 1/4
    (composite Simpson, 2000 intervals; agrees with scipy's stdtrit to 1e-10 without importing it)."""
    from math import lgamma, log, pi

    c = lgamma((dof + 1) / 2) - lgamma(dof / 2) - 0.5 * log(dof * pi)
    x = np.linspace(0.0, 1.0, 2001)

    def mass(q):
        xs = q * x
        f = np.exp(c - (dof + 1) / 2 * np.log1p(xs * xs / dof))
        h = q / 2000
        return float(h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum()))

    lo, hi = 0.0, 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mass(mid) < 0.25 else (lo, mid)
    return 0.5 * (lo + hi)


def student_t_spread_scale(dof: float) -> float:
    """Factor c with robust spread (1.4826·MAD) of c·t_ν = 1: c = 1 / (1.4826 · t_ν⁻¹(0.75))."""
    return 1.0 / (1.482602218505602 * student_t_q75(dof))


def truncexp_scale(lo: float, hi: float, median: float) -> float:
    """Scale λ (m) of the exponential truncated to [lo, hi] whose median is ``median``
    (lo < median < (lo + hi)/2; bisection on the median, which grows with λ)."""
    w, m = hi - lo, median - lo

    def med(lam):
        return -lam * np.log(1.0 - 0.5 * (1.0 - np.exp(-w / lam)))

    a, b = 1e-6 * w, 1e6 * w
    for _ in range(200):
        c = np.sqrt(a * b)
        if med(c) < m:
            a = c
        else:
            b = c
    return float(np.sqrt(a * b))


def truncexp_draw(u: np.ndarray, lo: float, hi: float, lam: float) -> np.ndarray:
    """Inverse CDF of the exponential of scale ``lam`` truncated to [lo, hi] at uniforms ``u``."""
    return lo - lam * np.log(1.0 - u * (1.0 - np.exp(-(hi - lo) / lam)))


def nlos_episodes(t0: float, t1: float, fraction: float, mean_s: float, rng: np.random.Generator):
    """One link's NLOS episodes over [t0, t1]: an alternating renewal process in continuous time,
    on-times ~ Exp(mean_s), off-times ~ Exp(mean_s (1 − f)/f), so the long-run share of time inside
    an episode is f; stationary start (in an episode with probability f, memoryless residual).
    Returns (starts, ends) of the episodes, sorted; draws a fixed pattern from ``rng`` (one
    ``random()`` for the initial state, then blocks of 64 on/off pairs until past t1)."""
    mean_off = mean_s * (1.0 - fraction) / fraction
    on = bool(rng.random() < fraction)
    starts, ends = [], []
    tc = t0
    while tc <= t1:
        d_on = rng.exponential(mean_s, 64)
        d_off = rng.exponential(mean_off, 64)
        first, second = (d_on, d_off) if on else (d_off, d_on)
        seq = np.empty(128)
        seq[0::2], seq[1::2] = first, second
        edges = tc + np.concatenate([[0.0], np.cumsum(seq)])
        on_idx = np.arange(0 if on else 1, 128, 2)
        starts.append(edges[on_idx])
        ends.append(edges[on_idx + 1])
        tc = edges[-1]
    return np.concatenate(starts), np.concatenate(ends)


def realistic_uwb_errors(fm, sigma: float, t: np.ndarray, t0: float, P: int, n: np.ndarray,
                         rng_tail: np.random.Generator, rng_nlos: np.random.Generator):
    """(core noise (K,P) m, NLOS mask (K,P), NLOS bias (K,P) m) of the realistic model.

    Core: σ·c_ν·n/√(χ²_ν/ν), a Student-t of robust spread σ (n: the standard normals of the
    gaussian model, so the two models share their noise draws). NLOS: per link an episode process
    (:func:`nlos_episodes`), one bias per episode from the truncated exponential on ``nlos_bias_m``
    with median ``nlos_bias_median_m``; a range taken at t is NLOS when t lies inside an episode.
    """
    K = len(t)
    nu = float(fm.core_dof)
    chi = rng_tail.chisquare(nu, (K, P))
    core = sigma * student_t_spread_scale(nu) * n / np.sqrt(chi / nu)
    mask = np.zeros((K, P), bool)
    bias = np.zeros((K, P))
    if fm.nlos_fraction > 0 and K:
        lo, hi = fm.nlos_bias_m
        lam = truncexp_scale(lo, hi, fm.nlos_bias_median_m)
        for j in range(P):
            st, en = nlos_episodes(t0, float(t[-1]), fm.nlos_fraction, fm.nlos_mean_duration_s, rng_nlos)
            b = truncexp_draw(rng_nlos.random(len(st)), lo, hi, lam)
            i = np.searchsorted(st, t, side="right") - 1
            ok = i >= 0
            ok[ok] = t[ok] < en[i[ok]]
            mask[:, j] = ok
            bias[ok, j] = b[i[ok]]
    return core, mask, bias


def interference_states(fi, t: np.ndarray, epoch_dt: float, P: int, rng_intf: np.random.Generator):
    """Fault 1, interference: per link a two-state Markov chain over the epochs t (K,) (stationary
    start, mean dwell in the interfered state ``fi.mean_dwell_s``, fraction ``fi.time_fraction``),
    one bias U(``fi.bias_m``) per episode. Returns the (K, P) interfered mask and bias (m)."""
    K = len(t)
    dtk = np.diff(t, prepend=t[0] - epoch_dt)
    p_exit_base = 1.0 / fi.mean_dwell_s
    frac = fi.time_fraction
    u_tr = rng_intf.random((K, P))
    b_draw = rng_intf.uniform(fi.bias_m[0], fi.bias_m[1], (K, P))
    state = rng_intf.random(P) < frac
    cur = b_draw[0].copy()
    intf = np.zeros((K, P), bool)
    bias_i = np.zeros((K, P))
    for k in range(K):
        if k > 0:
            p_exit = min(1.0, dtk[k] * p_exit_base)
            p_enter = min(1.0, p_exit * frac / (1.0 - frac))
            enter = ~state & (u_tr[k] < p_enter)
            leave = state & (u_tr[k] < p_exit)
            state = (state | enter) & ~leave
            cur = np.where(enter, b_draw[k], cur)
        intf[k] = state
        bias_i[k] = cur
    return intf, bias_i


def _add_drift(drifts, t, ia, ib, err, kind):
    """Fault 4, drift: + rate·(t − start) on the link for start <= t <= end (in place)."""
    for dr in drifts:
        a, b = sorted(dr.link)
        j = np.flatnonzero((ia == a - 1) & (ib == b - 1))[0]
        w = in_window(t, dr.start_s, dr.end_s)
        err[:, j] += np.where(w, dr.rate_mps * (t - dr.start_s), 0.0)
        kind[w, j] = FaultKind.DRIFT


def _add_module_failures(failures, t, ia, ib, rng_fail, err, kind):
    """Fault 2, module failure: + U(error_m), a new draw per measurement, on every link of the UAV
    in the window (in place)."""
    K, P = err.shape
    for mf in failures:
        w = in_window(t, mf.start_s, mf.end_s)[:, None] & ((ia == mf.uav - 1) | (ib == mf.uav - 1))[None, :]
        e2 = rng_fail.uniform(mf.error_m[0], mf.error_m[1], (K, P))
        err += np.where(w, e2, 0.0)
        kind[w] = FaultKind.FAILURE


def _apply_stuck(stuck, t, ia, ib, meas, nominal, err, kind):
    """Fault 3, stuck: every link of the UAV repeats its (fully faulted) measurement at the first
    epoch >= start_s; err = repeated value − nominal. Returns (meas, err); ``kind`` in place."""
    for st in stuck:
        w_t = in_window(t, st.start_s, st.end_s)
        if not w_t.any():
            continue
        k0 = int(np.flatnonzero(w_t)[0])
        links = (ia == st.uav - 1) | (ib == st.uav - 1)
        w = w_t[:, None] & links[None, :]
        frozen = np.broadcast_to(meas[k0], meas.shape)
        meas = np.where(w, frozen, meas)
        err = np.where(w, meas - nominal, err)
        kind[w] = FaultKind.STUCK
    return meas, err


def simulate_uwb(sc: Scenario, t: np.ndarray, pos: np.ndarray, rng_bias, rng_noise, rng_loss,
                 rng_intf, rng_fail, rng_tail=None, rng_nlos=None, t0: float = 0.0) -> UwbResult:
    """Two-way ranges at epoch times t (K,) from ENU positions pos (K,U,3).

    Nominal: d + b_link + σ n, b_link ~ N(0, link_bias_sigma) per link. Faults (a scenario's [faults] table),
    applied in this order, each adding to ``err`` (the error beyond the nominal model):
      1 interference: per-link two-state Markov chain (stationary start, mean dwell in the
        interfered state ``mean_dwell_s``, fraction ``time_fraction``); per episode a bias
        U(bias_m), noise ×noise_scale (err = bias + (noise_scale−1) σ n);
      4 drift: + rate·(t − start) on the link for start <= t <= end;
      2 failure: + U(error_m), a new draw per measurement, every link of the UAV in the window;
      3 stuck: every link of the UAV repeats its (fully faulted) measurement at the first epoch
        >= start_s; err = repeated value − (d + b_link + σ n) now.
    Label precedence (kind of a link-epoch with several): stuck > failure > drift > interference;
    ``err`` is always the total. Windows are closed [start_s, end_s].

    ``faults.uwb.model = "realistic"`` (docs/uwb-errors.md; needs ``rng_tail``, ``rng_nlos`` and
    the process start ``t0``): the core σ n becomes a Student-t of robust spread σ (nominal: never
    a fault, err 0), and fault 1 is replaced by short NLOS episodes (:func:`realistic_uwb_errors`):
    err = the episode's bias, kind INTERFERENCE, ``interfered`` = the NLOS mask. Without a
    ``[faults.uwb]`` table nothing here changes (same draws, same bytes).
    """
    uw = sc.sensors.uwb
    K, U = pos.shape[0], pos.shape[1]
    ia, ib = pairs(U)
    P = len(ia)
    d = distance(pos[:, ia], pos[:, ib])  # models/uwb_range.py: h
    bias = rng_bias.normal(0.0, uw.link_bias_sigma_m, P)
    n = rng_noise.normal(0.0, 1.0, (K, P))
    fm = sc.faults.uwb
    realistic = fm is not None and fm.model == "realistic"
    err = np.zeros((K, P))
    kind = np.zeros((K, P), np.int64)
    intf = np.zeros((K, P), bool)
    if realistic:
        core, intf, b_nlos = realistic_uwb_errors(fm, uw.sigma_m, t, t0, P, n, rng_tail, rng_nlos)
        nominal = d + bias + core
        err += np.where(intf, b_nlos, 0.0)
        kind[intf] = FaultKind.INTERFERENCE
    else:
        nominal = d + bias + uw.sigma_m * n

    fi = sc.faults.interference
    if fi.enabled and fi.time_fraction > 0 and not realistic:
        intf, bias_i = interference_states(fi, t, sc.scenario.epoch_dt_s, P, rng_intf)
        err += np.where(intf, bias_i + (fi.noise_scale - 1.0) * uw.sigma_m * n, 0.0)
        kind[intf] = FaultKind.INTERFERENCE
    _add_drift(sc.faults.drift, t, ia, ib, err, kind)
    _add_module_failures(sc.faults.module_failure, t, ia, ib, rng_fail, err, kind)
    meas, err = _apply_stuck(sc.faults.stuck, t, ia, ib, nominal + err, nominal, err, kind)
    keep = (d <= uw.max_range_m) & (rng_loss.random((K, P)) >= uw.packet_loss)
    return UwbResult(range=meas, true=d, kind=kind, err=err, keep=keep, link_bias=bias, interfered=intf)


# -- relative azimuth / elevation -----------------------------------------------------------


def simulate_rel(sc: Scenario, pos: np.ndarray, rng: np.random.Generator):
    """Paper eq. 27 per observer per target within rel.max_range, independent N(0, σ) on each angle.

    Returns (K,U,U) azimuth, elevation and the (K,U,U) mask of emitted observations (diagonal off).
    """
    rs = sc.sensors.rel
    sig = np.deg2rad(rs.sigma_deg)
    po = pos[:, :, None, :]
    pt = pos[:, None, :, :]
    az, el = azimuth_elevation(po, pt)
    rng_d = np.linalg.norm(pt - po, axis=-1)
    U = pos.shape[1]
    mask = (rng_d <= rs.max_range_m) & ~np.eye(U, dtype=bool)[None]
    az = az + rng.normal(0.0, sig, az.shape)
    el = el + rng.normal(0.0, sig, el.shape)
    az = np.mod(az + np.pi, 2 * np.pi) - np.pi
    az = np.where(az <= -np.pi, az + 2 * np.pi, az)  # (−π, π]
    el = np.clip(el, -np.pi / 2, np.pi / 2)
    return az, el, mask
