"""The IMU and altitude tables, the at-rest test for coarse alignment, and table sorting."""

from __future__ import annotations

import numpy as np

from swarmnav.dataset import TABLE_COLUMNS

from .constants import (GRAVITY_MPS2, HEIGHT_SIGMA_M, LEVEL_MAX_ACC_STD, LEVEL_MAX_G_DEV, LEVEL_MAX_GYRO_STD,
                        LEVEL_WINDOW_S)


def sorted_table(name: str, t: np.ndarray, node: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
    """Table ``name`` (columns TABLE_COLUMNS[name]: t, node, then data's columns) sorted by (t, node)."""
    order = np.lexsort((node, t))
    cols = TABLE_COLUMNS[name]
    out = {"t": t[order], "node": node[order].astype(np.int64)}
    for j, c in enumerate(cols[2:]):
        out[c] = np.ascontiguousarray(data[order, j])
    return out


def imu_table(imu: dict[int, tuple[np.ndarray, np.ndarray]], t_start: float, t_end: float, summary: dict) -> dict[str, np.ndarray]:
    """Every IMU sample in [the one in force at t_start, t_end) — FLU already: mavros data_raw is ROS
    base_link FLU (a_z ~ +9.8 at rest)."""
    it, iu, idata = [], [], []
    stats = {}
    for uid, (t, d) in sorted(imu.items()):
        lo = max(int(np.searchsorted(t, t_start, side="right")) - 1, 0)  # the sample in force at t_start
        hi = int(np.searchsorted(t, t_end, side="left"))
        t, d = t[lo:hi], d[lo:hi]
        it.append(t)
        iu.append(np.full(len(t), uid))
        idata.append(d)
        dt = np.diff(t)
        stats[uid] = {"samples": int(len(t)), "rate_hz_median": round(float(1 / np.median(dt)), 1),
                      "max_gap_s": round(float(dt.max()), 4), "gaps_over_20ms": int((dt > 0.02).sum())}
    summary["imu"] = stats
    return sorted_table("imu", np.concatenate(it), np.concatenate(iu), np.vstack(idata))


def level_at_start(imu: dict[int, tuple[np.ndarray, np.ndarray]], t_start: float, summary: dict) -> bool:
    """Is every UAV at rest over the first LEVEL_WINDOW_S s by its IMU alone? Then initial.py levels
    roll/pitch from the accelerometer (coarse alignment)."""
    at_rest = {}
    for uid, (t, d) in sorted(imu.items()):
        m = (t >= t_start) & (t <= t_start + LEVEL_WINDOW_S)
        gn, fn = np.linalg.norm(d[m, 0:3], axis=1), np.linalg.norm(d[m, 3:6], axis=1)
        at_rest[uid] = bool(m.sum() > 10 and gn.std() < LEVEL_MAX_GYRO_STD and fn.std() < LEVEL_MAX_ACC_STD
                            and abs(fn.mean() - GRAVITY_MPS2) < LEVEL_MAX_G_DEV)
    summary["level_at_start"] = {str(u): v for u, v in at_rest.items()}
    return all(at_rest.values())


def altitude_table(height: dict[int, tuple[np.ndarray, np.ndarray]], t_start: float, t_end: float,
                   summary: dict) -> dict[str, np.ndarray] | None:
    """Height readings in (t_start, t_end], sigma HEIGHT_SIGMA_M; None without any rangefinder."""
    at, au, ah = [], [], []
    for uid, (t, h) in sorted(height.items()):
        m = (t > t_start) & (t <= t_end)
        at.append(t[m])
        au.append(np.full(int(m.sum()), uid))
        ah.append(h[m])
    if not at:
        return None
    n = sum(len(x) for x in at)
    tab = sorted_table("altitude", np.concatenate(at), np.concatenate(au),
                       np.column_stack([np.concatenate(ah), np.full(n, HEIGHT_SIGMA_M)]))
    summary["altitude_rows"] = int(len(tab["t"]))
    return tab
