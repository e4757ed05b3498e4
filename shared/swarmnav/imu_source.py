"""Where an epoch's IMU samples come from: the whole table in memory (evaluate), or the dataset's
``imu.parquet`` read row group by row group as the epochs advance (the sensor-sim: a 1000 s paper
dataset holds ~110 MB of IMU samples, the stream a few MB).

Both give, for UAV u and the epoch (t_prev, t], the samples with t_prev <= t_s < t plus the sample
in force at t_prev (the last one before it, if none is exactly at t_prev): the zero-order hold the
preintegration needs. Times in s, gyro rad/s, specific force m/s² (body FLU), as in dataset.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IMU_COLUMNS = ("t", "node", "gx", "gy", "gz", "ax", "ay", "az")
IMU_ROW_GROUP = 1 << 16  # rows per parquet row group of imu.parquet (~3.6 s of an 18-UAV 100 Hz swarm)


def _columns(tab) -> dict[str, np.ndarray]:
    """An Arrow table of the IMU columns as arrays: node int64, the rest float64 (as dataset.py)."""
    return {c: tab.column(c).to_numpy().astype(np.int64 if c == "node" else np.float64) for c in IMU_COLUMNS}


def _hold_window(it: np.ndarray, t_prev: float, t: float) -> tuple[int, int]:
    """Index range [lo, hi) of the samples of one UAV (times ``it``, sorted) for (t_prev, t]."""
    lo, hi = np.searchsorted(it, t_prev, "left"), np.searchsorted(it, t, "left")
    # the sample in force at t_prev (if it started earlier) is needed for the hold
    if lo > 0 and (lo == len(it) or it[lo] > t_prev):
        lo -= 1
    return int(lo), int(hi)


class ImuInMemory:
    """The IMU table held whole: per UAV its rows' indices (time order kept by a stable sort) and
    times; samples are gathered per epoch, so no second copy of the table is made."""

    def __init__(self, imu: dict[str, np.ndarray], uavs: list[int]):
        self._table = imu
        order = np.argsort(imu["node"], kind="stable")
        sorted_nodes = imu["node"][order]
        self._rows = {}
        for u in uavs:
            rows = order[np.searchsorted(sorted_nodes, u, "left"):np.searchsorted(sorted_nodes, u, "right")]
            self._rows[u] = (imu["t"][rows], rows)
        self._gyro = (imu["gx"], imu["gy"], imu["gz"])
        self._accel = (imu["ax"], imu["ay"], imu["az"])

    def samples(self, uav: int, t_prev: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(times (n,), gyro (n, 3), specific force (n, 3)) of UAV ``uav`` for the epoch (t_prev, t]."""
        it, rows = self._rows[uav]
        lo, hi = _hold_window(it, t_prev, t)
        sel = rows[lo:hi]
        return it[lo:hi], np.column_stack([c[sel] for c in self._gyro]), np.column_stack([c[sel] for c in self._accel])

    def head(self, t_end: float) -> dict[str, np.ndarray]:
        """Every sample with t <= t_end, as a table."""
        m = self._table["t"] <= t_end
        return {c: v[m] for c, v in self._table.items()}


class ImuStream:
    """``imu.parquet`` read forward a row group at a time. Needs the file sorted by time (the
    simulator's and the importer's are; checked on opening: :meth:`open` falls back to the whole
    table otherwise). Keeps the row groups that reach into the current epoch and, per UAV, the last
    sample before them (the hold); asking for an earlier epoch starts again from the first group.
    Gives exactly what :class:`ImuInMemory` gives."""

    def __init__(self, pf, uavs: list[int], group_t_max: np.ndarray):
        self._pf = pf  # pyarrow.parquet.ParquetFile of imu.parquet
        self._uavs = list(uavs)
        self._group_t_max = group_t_max  # last time of each row group (s)
        self.reset()

    @classmethod
    def open(cls, path: str | Path, uavs: list[int]) -> "ImuStream | ImuInMemory":
        """A stream over ``path``, or the whole table in memory when it is not sorted by time."""
        import pyarrow.parquet as pq

        pf = pq.ParquetFile(path)
        t = pf.read(columns=["t"]).column("t").to_numpy()
        if len(t) and not np.all(np.diff(t) >= 0):
            return ImuInMemory(_columns(pf.read(columns=list(IMU_COLUMNS))), uavs)
        sizes = [pf.metadata.row_group(i).num_rows for i in range(pf.num_row_groups)]
        ends = np.cumsum(sizes)
        t_max = np.array([t[e - 1] if n else -np.inf for e, n in zip(ends, sizes)], float)
        return cls(pf, uavs, t_max)

    def reset(self) -> None:
        self._next = 0  # next row group to read
        self._groups: list[dict[str, np.ndarray]] = []  # loaded groups, oldest first
        self._carry: dict[int, tuple] = {}  # uav -> (t, gyro, accel) of its last sample before the groups
        self._index: dict[int, tuple] | None = None  # per UAV (times, gyro, accel) over carry + groups
        self._t_prev = -np.inf

    def _read_group(self, i: int) -> dict[str, np.ndarray]:
        return _columns(self._pf.read_row_group(i, columns=list(IMU_COLUMNS)))

    def _drop(self, g: dict[str, np.ndarray]) -> None:
        for u in self._uavs:
            rows = np.flatnonzero(g["node"] == u)
            if len(rows):
                j = rows[-1]
                self._carry[u] = (g["t"][j], np.array([g["gx"][j], g["gy"][j], g["gz"][j]]),
                                  np.array([g["ax"][j], g["ay"][j], g["az"][j]]))

    def _advance(self, t_prev: float, t: float) -> None:
        if t_prev < self._t_prev:  # an earlier epoch again (a re-sent one): from the start
            self.reset()
        self._t_prev = t_prev
        changed = False
        while self._next < len(self._group_t_max) and (not self._groups or self._groups[-1]["t_max"] < t):
            g = self._read_group(self._next)
            g["t_max"] = self._group_t_max[self._next]
            self._groups.append(g)
            self._next += 1
            changed = True
        # a group wholly before t_prev is needed only for the hold sample: keep that, drop the rows
        while len(self._groups) > 1 and self._groups[0]["t_max"] < t_prev:
            self._drop(self._groups.pop(0))
            changed = True
        if changed or self._index is None:
            self._build_index()

    def _build_index(self) -> None:
        cat = {c: np.concatenate([g[c] for g in self._groups]) if self._groups else np.zeros(0) for c in IMU_COLUMNS}
        self._index = {}
        for u in self._uavs:
            m = cat["node"] == u
            it = cat["t"][m]
            gyro = np.column_stack([cat["gx"][m], cat["gy"][m], cat["gz"][m]])
            acc = np.column_stack([cat["ax"][m], cat["ay"][m], cat["az"][m]])
            if u in self._carry:
                ct, cg, ca = self._carry[u]
                it, gyro, acc = np.r_[ct, it], np.vstack([cg, gyro]), np.vstack([ca, acc])
            self._index[u] = (it, gyro, acc)

    def samples(self, uav: int, t_prev: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`ImuInMemory.samples`; epochs are expected in time order."""
        self._advance(t_prev, t)
        it, gyro, acc = self._index[uav]
        lo, hi = _hold_window(it, t_prev, t)
        return it[lo:hi], gyro[lo:hi], acc[lo:hi]

    def head(self, t_end: float) -> dict[str, np.ndarray]:
        """Every sample with t <= t_end, as a table (the initial levelling window)."""
        out, i = [], 0
        while i < len(self._group_t_max):
            g = self._read_group(i)
            out.append(g)
            if self._group_t_max[i] > t_end:
                break
            i += 1
        cat = {c: np.concatenate([g[c] for g in out]) if out else np.zeros(0) for c in IMU_COLUMNS}
        m = cat["t"] <= t_end
        return {c: v[m] for c, v in cat.items()}
