"""Re-initialisation of a restarted per-UAV node (``GraphEstimator.bootstrap``)."""

from __future__ import annotations

import numpy as np

from ..dataset import EpochInput
from .base import NodeState

ATT_SIGMA_RAD = np.deg2rad([0.5, 0.5, 10.0])  # coarse alignment: roll/pitch σ 0.5°, yaw σ 10°


def restart_position(t: float, peers: dict[int, NodeState], inp: EpochInput | None, anchors: dict,
                     gnss_extra_var: float, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position ENU m, per-axis σ m) of a node restarting at ``t``: from GNSS if present (the fix
    of ``inp.t`` moved back to ``t`` along the GNSS velocity), else a multilateration on the peers'
    states and the anchors with this epoch's ranges when there are ≥ 4 (else the peers' centroid,
    or the anchors' without peers, at the altimeter's height when there is one), else ``fallback``."""
    pos_sigma = np.array([10.0, 10.0, 10.0])
    if inp is not None and inp.gnss_pos is not None:
        pos = np.asarray(inp.gnss_pos, float)
        pos_sigma = np.sqrt(np.asarray(inp.gnss_pos_sigma, float) ** 2 + gnss_extra_var)
        # the fix is at the end of the epoch (inp.t), the node restarts at t (= inp.t_prev when
        # the service rejoins): move it back along the GNSS velocity, else the node starts one
        # epoch of motion ahead (~15 m on smoke)
        dt = float(inp.t) - float(t)
        if dt > 0 and inp.gnss_vel is not None:
            pos = pos - np.asarray(inp.gnss_vel, float) * dt
        return pos, pos_sigma
    if not (peers or anchors):
        return fallback, pos_sigma
    pos = np.mean([s.pos for s in peers.values()] if peers else list(anchors.values()), axis=0)
    if inp is not None and inp.altitude is not None and np.isfinite(inp.altitude):
        pos[2] = float(inp.altitude)
    if inp is not None:
        pts = {**{o: s.pos for o, s in peers.items()}, **anchors}
        rows = [(pts[int(o)], float(d)) for o, d in zip(inp.range_other, inp.range_m) if int(o) in pts]
        if len(rows) >= 4:
            for _ in range(10):
                A, b = [], []
                for pt, d in rows:
                    dv = pos - pt
                    rr = max(np.linalg.norm(dv), 1e-6)
                    A.append(dv / rr)
                    b.append(d - rr)
                pos = pos + np.linalg.lstsq(np.array(A), np.array(b), rcond=None)[0]
            pos_sigma = np.array([3.0, 3.0, 3.0])
    return pos, pos_sigma


def restart_velocity(peers: dict[int, NodeState], inp: EpochInput | None, current: np.ndarray):
    """(velocity ENU m/s, σ m/s, attitude quaternion (w, x, y, z)) of a restarting node: velocity from
    GNSS or the peers' mean (else ``current``); attitude level with yaw along the velocity."""
    if inp is not None and inp.gnss_vel is not None:
        vel, vs = np.asarray(inp.gnss_vel, float), float(inp.gnss_vel_sigma or 0.2)
    elif peers:
        vel, vs = np.mean([s.vel for s in peers.values()], axis=0), 1.0
    else:
        vel, vs = current, 1.0
    yaw = float(np.arctan2(vel[1], vel[0])) if np.hypot(vel[0], vel[1]) > 1.0 else 0.0
    # body FLU x along the velocity: rotation about U by the azimuth of the velocity
    return vel, vs, np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
