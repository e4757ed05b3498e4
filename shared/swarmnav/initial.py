"""Initial knowledge of every estimator: truth at the start perturbed as a coarse alignment leaves it.

Coarse alignment (a scenario's `[init]` table): position sigma = the node's own GNSS sigma (or 1 m per axis where it has none),
velocity sigma ``init.vel_sigma_mps``, roll/pitch ``init.roll_pitch_sigma_deg``, yaw
``init.yaw_sigma_deg``, zero bias. Drawn from the run seed, so every algorithm and both transports
start from the same numbers.

Optional (real recordings; simulated datasets do not set it): ``init.level_window_s`` = W > 0 says
every UAV is at rest over ``[t_start, t_start + W]`` (on the ground before take-off). Roll and pitch are then **levelled from the
UAV's own accelerometer** (mean specific force over that window: the coarse alignment a real INS does on the ground
before it starts navigating; the samples are the first W s of the run, so the alignment uses data
from up to W s after t_start — harmless while the UAV is really at rest, which the importer must check), not
taken from the truth: the truth attitude is that of the mocap body frame, which on MILUV is tilted
~3° from the IMU frame — an estimator started from it sees g·sin 3° ≈ 0.5 m/s² of false horizontal
acceleration. Yaw stays truth + ``yaw_sigma_deg`` noise (an accelerometer cannot give it). The
roll/pitch sigma becomes ``init.level_roll_pitch_sigma_deg`` (default: the accelerometer bias sigma
over g, the tilt a residual bias leaves). The random draws are the same as without levelling, so the
position/velocity/yaw draws do not change.
"""

from __future__ import annotations

import numpy as np

from .dataset import Dataset
from .estimators.base import InitialState
from .geometry import quat_from_euler_zyx, quat_from_rotvec, quat_mul, yaw_of


def level_roll_pitch(ds: Dataset, uav: int, t0: float, window_s: float) -> tuple[float, float] | None:
    """Roll, pitch (rad) from the mean accelerometer over [t0, t0 + window_s] (FLU: f = R^T [0,0,g])."""
    im = ds.table("imu")
    m = (im["node"] == uav) & (im["t"] >= t0) & (im["t"] <= t0 + window_s)
    if np.count_nonzero(m) < 10:
        return None
    f = np.array([im["ax"][m].mean(), im["ay"][m].mean(), im["az"][m].mean()])
    roll = float(np.arctan2(f[1], f[2]))
    pitch = float(np.arctan2(-f[0], np.hypot(f[1], f[2])))
    return roll, pitch


def initial_states(ds: Dataset, seed: int) -> dict[int, InitialState]:
    meta = ds.meta
    init = meta.init or {}
    vel_sigma = float(init.get("vel_sigma_mps", 0.1))
    rp = np.deg2rad(float(init.get("roll_pitch_sigma_deg", 0.5)))
    yaw = np.deg2rad(float(init.get("yaw_sigma_deg", 2.0)))
    level_w = float(init.get("level_window_s", 0.0) or 0.0)
    att_sigma = np.array([rp, rp, yaw])
    tr = ds.table("truth")
    rng = np.random.default_rng([int(seed), 0x1A17])  # stream separate from the simulator's
    out: dict[int, InitialState] = {}
    for u in meta.uav_ids():
        rows = np.flatnonzero(tr["node"] == u)
        i = rows[np.argmin(np.abs(tr["t"][rows] - meta.t_start))]
        node = meta.node(u)
        pos_sigma = np.asarray(node.gnss_pos_sigma_m if node.gnss_pos_sigma_m else (1.0, 1.0, 1.0), float)
        pos = np.array([tr["pe"][i], tr["pn"][i], tr["pu"][i]]) + rng.normal(0, 1, 3) * pos_sigma
        vel = np.array([tr["ve"][i], tr["vn"][i], tr["vu"][i]]) + rng.normal(0, vel_sigma, 3)
        q_true = np.array([tr["qw"][i], tr["qx"][i], tr["qy"][i], tr["qz"][i]])
        # attitude error as a small rotation in the navigation frame (ENU): roll/pitch ~ E/N, yaw ~ U
        draw = rng.normal(0, 1, 3)
        lv = level_roll_pitch(ds, u, float(tr["t"][i]), level_w) if level_w > 0 else None
        if lv is None:
            q0, sig = quat_mul(quat_from_rotvec(draw * att_sigma), q_true), att_sigma
        else:
            imu = node.imu
            rp_l = np.deg2rad(float(init["level_roll_pitch_sigma_deg"])) if "level_roll_pitch_sigma_deg" in init \
                else max((imu.accel_bias_sigma if imu else 0.05) / meta.earth.gravity_mps2, 1e-4)
            q_lev = quat_from_euler_zyx(yaw_of(q_true), lv[1], lv[0])
            q0 = quat_mul(quat_from_rotvec(np.array([0.0, 0.0, draw[2] * yaw])), q_lev)
            sig = np.array([rp_l, rp_l, yaw])
        out[u] = InitialState(t=float(tr["t"][i]), pos=pos, vel=vel, quat=q0,
                              pos_sigma=pos_sigma, vel_sigma=vel_sigma, att_sigma=sig)
    return out
