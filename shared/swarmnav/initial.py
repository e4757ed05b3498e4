"""Initial knowledge of every estimator: truth at the start perturbed as a coarse alignment leaves it.

DESIGN.md §3: position sigma = the node's own GNSS sigma (or 1 m per axis where it has none),
velocity sigma ``init.vel_sigma_mps``, roll/pitch ``init.roll_pitch_sigma_deg``, yaw
``init.yaw_sigma_deg``, zero bias. Drawn from the run seed, so every algorithm and both transports
start from the same numbers.
"""

from __future__ import annotations

import numpy as np

from .dataset import Dataset
from .estimators.base import InitialState
from .geometry import quat_mul, quat_from_rotvec


def initial_states(ds: Dataset, seed: int) -> dict[int, InitialState]:
    meta = ds.meta
    init = meta.init or {}
    vel_sigma = float(init.get("vel_sigma_mps", 0.1))
    rp = np.deg2rad(float(init.get("roll_pitch_sigma_deg", 0.5)))
    yaw = np.deg2rad(float(init.get("yaw_sigma_deg", 2.0)))
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
        dq = quat_from_rotvec(rng.normal(0, 1, 3) * att_sigma)
        out[u] = InitialState(t=float(tr["t"][i]), pos=pos, vel=vel, quat=quat_mul(dq, q_true),
                              pos_sigma=pos_sigma, vel_sigma=vel_sigma, att_sigma=att_sigma)
    return out
