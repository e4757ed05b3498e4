"""Formation trajectories, attitude and the ideal (noiseless) IMU — one discrete scheme for both.

Continuous design (all schedules C² "smootherstep" blends, so acceleration and attitude are smooth):

- Formation centre, starting at the ENU origin at rest with compass heading ψ (0 = N, 90° = E,
  positive clockwise): horizontal speed s(t) rises from 0 to ``cruise_speed_mps`` over
  ``accel_time_s``; after that the ``manoeuvres`` are flown back to back (straight; turn = heading
  change blended over the leg; climb = vertical speed ramped in/out over min(5 s, D/4); s_turn =
  heading deviation A·sin(2πτ/P) under an envelope ramped over min(P/2, D/4), so it starts and ends
  on the leg's heading); once the list ends the centre flies straight.
  a_c = ṡ·[sin ψ, cos ψ, 0] + s·ψ̇·[cos ψ, −sin ψ, 0] + [0, 0, ċ].
- UAV i = centre + fixed ENU formation offset (its start position) + wander w_i(t): per axis
  (A/√3)·E(t)·sin(2πt/P + φ), E a septic ramp over 30 s (E and its first three derivatives 0 at
  t = 0), so the wander vector never exceeds ``wander_amplitude_m`` and every UAV starts at rest with
  zero acceleration and jerk (hence zero attitude rate).
- Attitude (body FLU -> ENU), multirotor-like: body z along the specific force a + [0, 0, g]
  (coordinated: no lateral specific force, bank in turns, nose down when accelerating), body x
  toward the scheduled heading: q = q_z(π/2 − ψ) ⊗ q_tilt, q_tilt the shortest rotation e3 -> z.

Discrete scheme at the IMU rate (dt = 1/imu_rate_hz, sample k holds over [t_k, t_k+1)) — the truth
*is* this scheme, so integrating the ideal IMU with it reproduces the truth to round-off:

    a_k   = continuous acceleration sampled at t_k
    v_k+1 = v_k + a_k dt
    p_k+1 = p_k + v_k dt + ½ a_k dt²
    q_k   = designed attitude at t_k;  ω_nb,k = Log(q_k* ⊗ q_k+1) / dt   so  q_k+1 = q_k ⊗ Exp(ω_nb,k dt)
    gyro_k  = ω_ib = ω_nb,k + R_kᵀ Ω_ie
    accel_k = f = R_kᵀ (a_k − g + 2 Ω_ie × v_k),     g = [0, 0, −γ]

with γ the normal gravity and Ω_ie the Earth rate at the origin (see ``earth.py``); the inverse,
used by the consistency test, is ``integrate_imu``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scenario import Scenario
from ..errors import ConfigError
from .earth import earth_rate_enu, normal_gravity
from ..geometry import quat_conj as qconj, quat_mul as qmul, quat_rotate as qrot, quat_to_rotvec as qlog

WANDER_RAMP_S = 30.0


def _S(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def _dS(x):
    x = np.clip(x, 0.0, 1.0)
    return 30.0 * x * x * (1.0 - x) ** 2


def _window(tau, D, r):
    """Envelope that ramps 0->1 over r, holds, ramps 1->0 over the last r of a leg of length D."""
    e = _S(tau / r) - _S((tau - D + r) / r)
    de = (_dS(tau / r) - _dS((tau - D + r) / r)) / r
    return e, de


def centre_schedule(sc: Scenario, t: np.ndarray):
    """Formation-centre schedules at times t: heading ψ (rad, compass), ψ̇, speed s, ṡ, climb c, ċ."""
    tr = sc.trajectory
    V, Ta = tr.cruise_speed_mps, tr.accel_time_s
    s = V * _S(t / Ta)
    ds = V * _dS(t / Ta) / Ta
    psi = np.full_like(t, np.deg2rad(tr.initial_heading_deg))
    dpsi = np.zeros_like(t)
    c = np.zeros_like(t)
    dc = np.zeros_like(t)
    t0 = Ta
    for m in tr.manoeuvres:
        D = m.duration_s
        tau = t - t0
        inside = (tau >= 0) & (tau <= D)
        if m.kind == "turn":
            d = np.deg2rad(m.turn_deg)
            psi += d * _S(tau / D)
            dpsi += d * _dS(tau / D) / D
        elif m.kind == "climb":
            r = min(5.0, D / 4)
            e = _S(tau / r) - _S((tau - D + r) / r)
            de = (_dS(tau / r) - _dS((tau - D + r) / r)) / r
            c += m.climb_rate_mps * e
            dc += m.climb_rate_mps * de
        elif m.kind == "s_turn":
            P = m.s_period_s
            if P <= 0:
                raise ConfigError("trajectory.manoeuvres: s_turn needs s_period_s > 0")
            A = np.deg2rad(m.s_amplitude_deg)
            r = min(P / 2, D / 4)
            e, de = _window(tau, D, r)
            w = 2 * np.pi / P
            sn, cs = np.sin(w * tau), np.cos(w * tau)
            psi += np.where(inside, A * sn * e, 0.0)
            dpsi += np.where(inside, A * (w * cs * e + sn * de), 0.0)
        t0 += D
    return psi, dpsi, s, ds, c, dc


def centre_acceleration(sc: Scenario, t: np.ndarray):
    """(T,3) ENU acceleration of the formation centre and the compass heading ψ (T,)."""
    psi, dpsi, s, ds, c, dc = centre_schedule(sc, t)
    sp, cp = np.sin(psi), np.cos(psi)
    a = np.stack([ds * sp + s * dpsi * cp, ds * cp - s * dpsi * sp, dc], axis=-1)
    return a, psi


def formation_offsets(sc: Scenario, rng: np.random.Generator) -> np.ndarray:
    """(U,3) start positions: UAV 1 at uav1_start_enu_m, the rest uniform in the box
    (``swarm.formation_box()``: the box as given, or grown with n_uavs at ``density_per_km3``),
    ≥ min_separation apart.

    Rejection sampling, one ``rng.random(3)`` per candidate; the distance test is vectorised over
    the points placed so far (O(N) numpy per candidate instead of a Python loop over them), and a
    candidate within 1e-9 relative of the separation is decided by the original per-point
    expression, so every config draws exactly the offsets it drew before (same decisions).
    """
    sw = sc.swarm
    lo, hi = sw.formation_box()
    sep = float(sw.min_separation_m)
    U = sw.n_uavs
    pts = np.empty((U, 3))
    pts[0] = np.asarray(sw.uav1_start_enu_m, float)
    for i in range(1, U):
        placed = pts[:i]
        for _ in range(20000):
            c = lo + (hi - lo) * rng.random(3)
            dd = placed - c
            dmin = float(np.sqrt(np.min(np.einsum("ij,ij->i", dd, dd))))
            if abs(dmin - sep) <= 1e-9 * sep:  # borderline: the original expression decides
                dmin = min(np.linalg.norm(c - p) for p in placed)
            if dmin >= sep:
                pts[i] = c
                break
        else:
            raise ConfigError(
                f"swarm: cannot place UAV {i + 1} inside the box at least min_separation_m = "
                f"{sw.min_separation_m} m from the others; enlarge box_*_m (or lower density_per_km3) "
                f"or reduce min_separation_m")
    return pts


@dataclass
class Wander:
    amp: np.ndarray  # (U,3) per-axis amplitude, m
    omega: np.ndarray  # (U,3) rad/s
    phase: np.ndarray  # (U,3) rad


def draw_wander(sc: Scenario, rng: np.random.Generator) -> Wander:
    U = sc.swarm.n_uavs
    lo, hi = sc.trajectory.wander_period_s
    if not 0 < lo <= hi:
        raise ConfigError(f"trajectory.wander_period_s: need 0 < low <= high, got {(lo, hi)}")
    period = rng.uniform(lo, hi, (U, 3))
    phase = rng.uniform(0.0, 2 * np.pi, (U, 3))
    amp = np.full((U, 3), sc.trajectory.wander_amplitude_m / np.sqrt(3.0))
    return Wander(amp, 2 * np.pi / period, phase)


def _S7(x):
    """Septic smoothstep: value, first three derivatives zero at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x**4 * (35.0 + x * (-84.0 + x * (70.0 - 20.0 * x)))


def _dS7(x):
    x = np.clip(x, 0.0, 1.0)
    return 140.0 * x**3 * (1.0 - x) ** 3


def _ddS7(x):
    x = np.clip(x, 0.0, 1.0)
    return 420.0 * x * x * (1.0 - x) ** 2 * (1.0 - 2.0 * x)


def wander_acceleration(w: Wander, t: np.ndarray) -> np.ndarray:
    """(T,U,3) second derivative of A·E(t)·sin(Ωt + φ), E the septic ramp (jerk 0 at t = 0 too)."""
    x = (t / WANDER_RAMP_S)[:, None, None]
    E, dE, ddE = _S7(x), _dS7(x) / WANDER_RAMP_S, _ddS7(x) / WANDER_RAMP_S**2
    arg = w.omega * t[:, None, None] + w.phase
    sn, cs = np.sin(arg), np.cos(arg)
    return w.amp * (ddE * sn + 2.0 * dE * w.omega * cs - E * w.omega**2 * sn)


def attitude(a: np.ndarray, psi: np.ndarray, gravity: float) -> np.ndarray:
    """(T,U,4) body FLU -> ENU quaternions: z along a + [0,0,γ], x toward compass heading ψ (T,)."""
    f = a.copy()
    f[..., 2] += gravity
    yaw = 0.5 * np.pi - psi  # ENU yaw, from East counter-clockwise
    cy, sy = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    # express the thrust direction in the yaw-only frame
    zx = cy * f[..., 0] + sy * f[..., 1]
    zy = -sy * f[..., 0] + cy * f[..., 1]
    zz = f[..., 2]
    n = np.sqrt(zx * zx + zy * zy + zz * zz)
    zx, zy, zz = zx / n, zy / n, zz / n
    qt = np.stack([1.0 + zz, -zy, zx, np.zeros_like(zz)], axis=-1)
    qt /= np.linalg.norm(qt, axis=-1, keepdims=True)
    h = 0.5 * yaw
    qy = np.stack([np.cos(h), np.zeros_like(h), np.zeros_like(h), np.sin(h)], axis=-1)[:, None, :]
    return qmul(np.broadcast_to(qy, qt.shape), qt)


@dataclass
class Truth:
    """Full-rate truth and ideal IMU. Arrays are (T, U, ·) with T = n_imu + 1 states (t = 0..duration);
    the IMU arrays have n_imu rows (sample k holds over [t_k, t_k+1))."""

    t: np.ndarray  # (T,)
    uav_ids: np.ndarray  # (U,)
    pos: np.ndarray  # (T,U,3) ENU m
    vel: np.ndarray  # (T,U,3) ENU m/s
    quat: np.ndarray  # (T,U,4) w,x,y,z body FLU -> ENU
    acc: np.ndarray  # (T-1,U,3) ENU acceleration used by the scheme
    gyro: np.ndarray  # (T-1,U,3) ideal ω_ib in body, rad/s
    accel: np.ndarray  # (T-1,U,3) ideal specific force in body, m/s^2
    gravity: float
    earth_rate: np.ndarray  # (3,) ENU rad/s
    dt: float


def simulate_truth(sc: Scenario, offsets: np.ndarray, wander: Wander) -> Truth:
    """Integrate the formation kinematics at the IMU rate (see module docstring)."""
    rate = sc.scenario.imu_rate_hz
    n = int(round(sc.scenario.duration_s * rate))
    if abs(n - sc.scenario.duration_s * rate) > 1e-6:
        raise ConfigError("scenario: duration_s × imu_rate_hz must be a whole number of IMU samples")
    dt = 1.0 / rate
    t = np.arange(n + 1) / rate
    g = normal_gravity(sc.origin.lat_deg, sc.origin.alt_m)
    om = earth_rate_enu(sc.origin.lat_deg)
    ac, psi = centre_acceleration(sc, t)
    a = wander_acceleration(wander, t)
    a += ac[:, None, :]
    U = offsets.shape[0]
    # v_k+1 = v_k + a_k dt ; p_k+1 = p_k + v_k dt + ½ a_k dt²   (sequential sums: np.cumsum)
    vel = np.empty_like(a)
    vel[0] = 0.0
    np.cumsum(a[:-1] * dt, axis=0, out=vel[1:])
    inc = vel[:-1] * dt + 0.5 * dt * dt * a[:-1]
    pos = np.empty_like(a)
    pos[0] = offsets
    np.cumsum(inc, axis=0, out=pos[1:])
    pos[1:] += offsets
    del inc
    q = attitude(a, psi, g)
    dq = qmul(qconj(q[:-1]), q[1:])
    w_nb = qlog(dq) / dt
    del dq
    acc = a[:-1]
    qk = q[:-1]
    gyro = w_nb + qrot(qconj(qk), np.broadcast_to(om, w_nb.shape))
    fn = acc - np.array([0.0, 0.0, -g]) + 2.0 * np.cross(om, vel[:-1])
    accel = qrot(qconj(qk), fn)
    return Truth(t=t, uav_ids=np.arange(1, U + 1), pos=pos, vel=vel, quat=q, acc=acc, gyro=gyro,
                 accel=accel, gravity=g, earth_rate=om, dt=dt)


def integrate_imu(gyro: np.ndarray, accel: np.ndarray, dt: float, p0: np.ndarray, v0: np.ndarray,
                  q0: np.ndarray, gravity: float, earth_rate: np.ndarray, every: int = 1):
    """Strapdown integration with the simulator's discrete scheme (the inverse of the IMU model).

    gyro/accel: (N,U,3) samples (zero-order hold, step dt); p0/v0 (U,3), q0 (U,4). Returns the
    states at k = 0, every, 2·every, ..., N as arrays (K,U,3), (K,U,3), (K,U,4). Per step::

        ω_nb = gyro − R_kᵀ Ω_ie;   a = R_k f + g − 2 Ω_ie × v_k
        p += v dt + ½ a dt²;  v += a dt;  q ⊗= Exp(ω_nb dt)

    Written as a plain-float loop per UAV (≈ 0.3 s per 100 000 steps; numpy per-step overhead on
    tiny arrays is ~20× slower). The Earth rate must have a zero East component (ENU).
    """
    N, U = gyro.shape[0], gyro.shape[1]
    om = np.asarray(earth_rate, float)
    if abs(om[0]) > 0:
        raise ValueError("earth_rate must be [0, ω cos φ, ω sin φ] in ENU")
    K = N // every + 1
    P, V, Q = np.empty((K, U, 3)), np.empty((K, U, 3)), np.empty((K, U, 4))
    for u in range(U):
        P[:, u], V[:, u], Q[:, u] = _integrate_one(gyro[:, u].tolist(), accel[:, u].tolist(), dt, p0[u], v0[u], q0[u],
                                                   float(gravity), float(om[1]), float(om[2]), every, K)
    return P, V, Q


def _integrate_one(gyro, accel, dt, p0, v0, q0, g, oy, oz, every, K):
    import math

    px, py, pz = map(float, p0)
    vx, vy, vz = map(float, v0)
    qw, qx, qy, qz = map(float, q0)
    hdt2 = 0.5 * dt * dt
    P, V, Q = [(px, py, pz)], [(vx, vy, vz)], [(qw, qx, qy, qz)]
    for k, ((gx, gy, gz), (fx, fy, fz)) in enumerate(zip(gyro, accel)):
        xx, yy, zz = qx * qx, qy * qy, qz * qz
        xy, xz, yz = qx * qy, qx * qz, qy * qz
        wx, wy, wz = qw * qx, qw * qy, qw * qz
        r00, r01, r02 = 1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)
        r10, r11, r12 = 2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)
        r20, r21, r22 = 2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)
        # ω_nb = ω_ib − Rᵀ Ω_ie   (Ω_ie = [0, oy, oz])
        wbx = gx - (r10 * oy + r20 * oz)
        wby = gy - (r11 * oy + r21 * oz)
        wbz = gz - (r12 * oy + r22 * oz)
        # a = R f + g − 2 Ω_ie × v
        ax = r00 * fx + r01 * fy + r02 * fz - 2 * (oy * vz - oz * vy)
        ay = r10 * fx + r11 * fy + r12 * fz - 2 * (oz * vx)
        az = r20 * fx + r21 * fy + r22 * fz - g + 2 * (oy * vx)
        px += vx * dt + hdt2 * ax
        py += vy * dt + hdt2 * ay
        pz += vz * dt + hdt2 * az
        vx += ax * dt
        vy += ay * dt
        vz += az * dt
        rx, ry, rz = wbx * dt, wby * dt, wbz * dt
        th = math.sqrt(rx * rx + ry * ry + rz * rz)
        c = math.cos(0.5 * th)
        s = math.sin(0.5 * th) / th if th > 1e-8 else 0.5 - th * th / 48.0
        dw, dx, dy, dz = c, rx * s, ry * s, rz * s
        qw, qx, qy, qz = (qw * dw - qx * dx - qy * dy - qz * dz, qw * dx + qx * dw + qy * dz - qz * dy,
                          qw * dy - qx * dz + qy * dw + qz * dx, qw * dz + qx * dy - qy * dx + qz * dw)
        if (k + 1) % every == 0:
            P.append((px, py, pz))
            V.append((vx, vy, vz))
            Q.append((qw, qx, qy, qz))
    return np.array(P[:K]), np.array(V[:K]), np.array(Q[:K])
