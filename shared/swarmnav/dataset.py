"""The swarmnav dataset: in-memory form, on-disk format (read/write) and per-epoch slicing.

A dataset is what the estimators see (measurements), plus truth and fault labels for scoring.
Simulated runs and converted real recordings use the same format, documented in
``docs/dataset-format.md``. On disk, a dataset directory holds::

    meta.json          DatasetMeta (schema "swarmnav.dataset/1"), sorted keys, no paths/times
    truth.parquet      t, node, pe, pn, pu, ve, vn, vu, qw, qx, qy, qz   (ENU m, m/s; q body FLU -> ENU)
    imu.parquet        t, node, gx, gy, gz, ax, ay, az   (body FLU, rad/s and m/s^2 specific force)
    gnss.parquet       t, node, lat_deg, lon_deg, h_m, ve, vn, vu, sig_pe, sig_pn, sig_pu, sig_v
    ranges.parquet     t, a, b, tag_a, tag_b, range, sigma, fault_kind, fault_err
    rel.parquet        t, observer, target, azimuth, elevation, sigma   (rad, eq. 27 in ENU)
    altitude.parquet   t, node, height, sigma   (optional; ENU up of the body origin, m)
    tdoa.parquet       t, node, tag, init, tag_init, resp, tag_resp, rdiff, sigma, fault_kind, fault_err
                       (optional; passive-listening range differences, m)

Conventions:

- ``t`` in seconds from the start of the run; every table sorted by (t, node/a/observer, ...).
- An IMU sample at time ``t`` holds over ``[t, t_next)`` (zero-order hold); any rate, may vary.
- GNSS is stored geodetic (as a receiver reports it); :func:`Dataset.gnss_enu` converts with
  pymap3d about ``meta.origin``. Missing GNSS = no row.
- A range row is one two-way ranging transaction between nodes ``a < b`` (UAVs or anchors) from
  tag ``tag_a`` on ``a`` to tag ``tag_b`` on ``b`` (lever arms in ``meta.nodes``). Both UAVs of the
  pair receive the same value. ``fault_kind``: see :class:`FaultKind`; ``fault_err`` is the error
  the fault adds in metres (NaN when unknown). A link-epoch is *faulty* for scoring when
  ``|fault_err|`` > 3 sigma of the row's ranging noise (``meta.fault_threshold_m`` × the row's
  sigma / ``meta.uwb_sigma_m``; evaluation.link_labels).
- A tdoa row is one passive-listening measurement: tag ``tag`` on UAV ``node`` overheard the
  two-way ranging transaction initiated by tag ``tag_init`` on node ``init`` and answered by tag
  ``tag_resp`` on node ``resp`` (UAVs or anchors; the listener's own other tag allowed) and
  measured ``rdiff`` = ‖resp tag − listener tag‖ − ‖init tag − listener tag‖ [m] at ``t``.
  ``fault_kind``/``fault_err`` as for ranges (``fault_err`` = measured − true, NaN when unknown).
- Relative angles follow eq. 27 with x = E, y = N, z = U, measured by ``observer`` of ``target``:
  azimuth = atan2(N_t - N_o, E_t - E_o) (from East, counter-clockwise, in (-pi, pi]),
  elevation = atan2(U_t - U_o, horizontal distance) (in [-pi/2, pi/2]).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .errors import DatasetError
from .imu_source import IMU_ROW_GROUP, ImuInMemory

SCHEMA = "swarmnav.dataset/1"

TABLE_COLUMNS: dict[str, tuple[str, ...]] = {
    "truth": ("t", "node", "pe", "pn", "pu", "ve", "vn", "vu", "qw", "qx", "qy", "qz"),
    "imu": ("t", "node", "gx", "gy", "gz", "ax", "ay", "az"),
    "gnss": ("t", "node", "lat_deg", "lon_deg", "h_m", "ve", "vn", "vu", "sig_pe", "sig_pn", "sig_pu", "sig_v"),
    "ranges": ("t", "a", "b", "tag_a", "tag_b", "range", "sigma", "fault_kind", "fault_err"),
    "rel": ("t", "observer", "target", "azimuth", "elevation", "sigma"),
    "altitude": ("t", "node", "height", "sigma"),
    "tdoa": ("t", "node", "tag", "init", "tag_init", "resp", "tag_resp", "rdiff", "sigma", "fault_kind", "fault_err"),
}
INT_COLUMNS = {"node", "a", "b", "tag_a", "tag_b", "fault_kind", "observer", "target", "tag", "init", "tag_init",
               "resp", "tag_resp"}
OPTIONAL_TABLES = {"altitude", "rel", "gnss", "tdoa"}


class FaultKind(IntEnum):
    NONE = 0
    INTERFERENCE = 1  # NLOS/interference: positive bias + inflated noise
    FAILURE = 2  # module failure: gross error
    STUCK = 3  # module repeats an old range
    DRIFT = 4  # slowly growing bias on one link
    NLOS_REAL = 5  # real recording: labelled from the recording's own bias/std


class _M(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GeoOrigin(_M):
    lat_deg: float
    lon_deg: float
    alt_m: float


class ImuNoise(_M):
    """Continuous-time IMU noise model in SI units (what the estimators use)."""

    gyro_noise_density: float  # rad/s/sqrt(Hz)  (ARW)
    accel_noise_density: float  # m/s^2/sqrt(Hz) (VRW)
    gyro_bias_sigma: float  # rad/s, initial (turn-on) bias 1-sigma
    accel_bias_sigma: float  # m/s^2
    gyro_bias_rw: float  # rad/s/sqrt(s)
    accel_bias_rw: float  # m/s^2/sqrt(s)


class Node(_M):
    id: int
    kind: Literal["uav", "anchor"]
    role: Literal["master", "slave", "anchor"] = "slave"
    position_enu: tuple[float, float, float] | None = None  # anchors: known position, m
    tags: dict[int, tuple[float, float, float]] = Field(default_factory=lambda: {0: (0.0, 0.0, 0.0)})  # body FLU lever arms, m
    imu: ImuNoise | None = None  # UAVs
    gnss_pos_sigma_m: tuple[float, float, float] | None = None  # nominal, for estimators' models / init
    gnss_vel_sigma_mps: float | None = None
    # per-axis σ of the time-correlated (first-order Gauss–Markov) part of the position error, m,
    # already included in gnss_pos_sigma_m; 0 = a white-noise receiver, None = not known
    gnss_correlated_sigma_m: float | None = None
    gnss_correlation_time_s: float | None = None  # its correlation time τ, s
    # UAVs: the vehicle type when the recording knows it ("multirotor": the graph estimators may
    # use the rotor-drag model, own_factors.OwnFactors.add_drag); None = unspecified (the simulator's UAVs)
    airframe: Literal["multirotor"] | None = None


class Earth(_M):
    gravity_mps2: float  # normal gravity magnitude at the origin (ENU: g = [0, 0, -gravity])
    earth_rate_radps: tuple[float, float, float]  # Earth rotation in ENU at the origin latitude


class Window(_M):
    start_s: float
    end_s: float
    uavs: list[int]


class EventSpec(_M):
    t: float
    kind: str  # "kill" | "restart"
    uav: int


class DatasetMeta(_M):
    schema_: str = Field(SCHEMA, alias="schema")
    name: str
    source: Literal["simulated", "recorded"]
    seed: int | None = None
    config: dict | None = None  # the resolved scenario config (simulated)
    config_sha256: str | None = None
    origin: GeoOrigin | None = None  # None = local frame without geodetic origin
    t_start: float = Field(0.0, allow_inf_nan=False)
    duration_s: float = Field(gt=0, allow_inf_nan=False)  # > 0: a dataset of no epoch has nothing to score
    epoch_dt_s: float = Field(gt=0, allow_inf_nan=False)
    nodes: list[Node]
    earth: Earth
    uwb_sigma_m: float
    rel_sigma_rad: float | None = None
    fault_threshold_m: float  # scoring threshold: 3 sigma of ranging noise (at uwb_sigma_m; scaled per row)
    gnss_outages: list[Window] = Field(default_factory=list)
    events: list[EventSpec] = Field(default_factory=list)  # scheduled process kills/restarts
    init: dict = Field(default_factory=dict)  # InitialKnowledge as dict (sigmas)

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    def uav_ids(self) -> list[int]:
        return sorted(n.id for n in self.nodes if n.kind == "uav")

    def anchors(self) -> dict[int, np.ndarray]:
        return {n.id: np.asarray(n.position_enu, float) for n in self.nodes if n.kind == "anchor"}

    def node(self, nid: int) -> Node:
        for n in self.nodes:
            if n.id == nid:
                return n
        raise KeyError(nid)

    def n_epochs(self) -> int:
        return int(round(self.duration_s / self.epoch_dt_s))

    def epoch_time(self, k: int) -> float:
        """Epoch k in 0..n_epochs: t_start + k * epoch_dt. Epoch 0 is the initial state."""
        return self.t_start + k * self.epoch_dt_s

    def fault_threshold_for(self, sigma) -> np.ndarray:
        """Scoring threshold (m) of range rows of ranging σ ``sigma`` (m, scalar or array): 3σ of
        that row's noise = fault_threshold_m × sigma / uwb_sigma_m; fault_threshold_m where sigma
        is unknown (NaN, ≤ 0) or uwb_sigma_m is unset. The simulator's rows all carry uwb_sigma_m,
        so there it is fault_threshold_m exactly; a recording's rows carry their own σ."""
        sig = np.asarray(sigma, float)
        thr = np.full(sig.shape, float(self.fault_threshold_m))
        if self.uwb_sigma_m and self.uwb_sigma_m > 0:
            ok = np.isfinite(sig) & (sig > 0)
            thr[ok] = self.fault_threshold_m * (sig[ok] / self.uwb_sigma_m)
        return thr


def node_view(meta: DatasetMeta) -> DatasetMeta:
    """The meta a UAV node gets (the sensor-sim's ``meta`` answer; in-process, every per-UAV
    estimator): what a real UAV knows before take-off and nothing of the scenario's schedule.

    Kept: ids, kinds and roles of the nodes, their sensor noise specs and lever arms, anchor
    positions, origin, Earth model, epoch length and span, the nominal ranging σ and the scoring
    threshold derived from it, the initial-knowledge sigmas, ``config_sha256`` (provenance) and the
    estimator settings (``config["estimation"]``, read by ``services.settings.settings_for_dataset``).
    Dropped: ``gnss_outages`` (outage windows), ``events`` (kill/restart schedule), the rest of
    ``config`` (fault windows, NLOS/interference parameters, outages, kills, trajectory, the
    simulator's sensor specs) and ``seed`` (with the config it would regenerate the whole run,
    truth included). Scoring (evaluate, the monitor) reads labels and truth from the dataset."""
    est = (meta.config or {}).get("estimation")
    return meta.model_copy(deep=True, update={
        "config": {"estimation": est} if est is not None else None,
        "gnss_outages": [], "events": [], "seed": None})


Table = dict[str, np.ndarray]


def epoch_of(t, t_start: float, epoch_dt: float):
    """Epoch k whose interval (t_{k-1}, t_k] holds time t (array or scalar; int)."""
    k = np.ceil((np.asarray(t, float) - t_start) / epoch_dt - 1e-9).astype(int)
    return int(k) if k.ndim == 0 else k


@dataclass
class Dataset:
    meta: DatasetMeta
    tables: dict[str, Table]  # name -> column -> 1-D array (see TABLE_COLUMNS)

    def table(self, name: str) -> Table:
        t = self.tables.get(name)
        if t is None:
            return {c: np.zeros(0, dtype=np.int64 if c in INT_COLUMNS else float) for c in TABLE_COLUMNS[name]}
        return t

    def gnss_enu(self) -> Table:
        """GNSS table with ENU position columns pe, pn, pu (pymap3d geodetic -> ENU about the origin)."""
        import pymap3d

        g = dict(self.table("gnss"))
        if self.meta.origin is None:
            raise DatasetError("GNSS rows need a geodetic origin in meta.json")
        o = self.meta.origin
        e, n, u = pymap3d.geodetic2enu(g["lat_deg"], g["lon_deg"], g["h_m"], o.lat_deg, o.lon_deg, o.alt_m)
        g["pe"], g["pn"], g["pu"] = np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)
        return g

    # -- on disk -------------------------------------------------------------------------

    def write(self, out: str | Path) -> None:
        """Write deterministically: same content -> same bytes (no timestamps, no paths)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        meta = self.meta.model_dump(mode="json", by_alias=True)
        (out / "meta.json").write_text(json.dumps(meta, sort_keys=True, indent=1) + "\n")
        for name, cols in TABLE_COLUMNS.items():
            tab = self.tables.get(name)
            if tab is None:
                # an optional table this dataset does not have: a file left by an earlier write to
                # the same directory (e.g. a re-import) must not come back with it
                (out / f"{name}.parquet").unlink(missing_ok=True)
                continue
            arrays = []
            for c in cols:
                a = np.asarray(tab[c])
                arrays.append(pa.array(a.astype(np.int32 if c in INT_COLUMNS else np.float64)))
            pq.write_table(
                pa.Table.from_arrays(arrays, names=list(cols)),
                out / f"{name}.parquet",
                compression="zstd",
                row_group_size=IMU_ROW_GROUP if name == "imu" else None,  # streamed by the sensor-sim
                use_dictionary=False,
                write_statistics=False,
                store_schema=False,
            )

    @classmethod
    def read(cls, path: str | Path, skip: tuple[str, ...] = ()) -> "Dataset":
        """The dataset in ``path``; tables named in ``skip`` are not read (e.g. "imu" for a reader
        that streams it: ``imu_source.ImuStream``)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = Path(path)
        mp = path / "meta.json"
        if not mp.is_file():
            raise DatasetError(f"{path}: not a dataset directory (no meta.json); create one with `swarmnav simulate` or `swarmnav import-miluv`")
        try:
            raw = json.loads(mp.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as e:
            raise DatasetError(f"{mp}: cannot read the dataset's meta.json ({e}); re-create the dataset with "
                               "`swarmnav simulate` or `swarmnav import-miluv`") from None
        if not isinstance(raw, dict) or raw.get("schema") != SCHEMA:
            got = raw.get("schema") if isinstance(raw, dict) else type(raw).__name__
            raise DatasetError(f"{mp}: unknown schema {got!r}, expected {SCHEMA!r}")
        try:
            meta = DatasetMeta.model_validate(raw)
        except ValidationError as e:
            probs = "; ".join(f"field '{'.'.join(str(p) for p in err['loc'])}': {err['msg']}" for err in e.errors()[:5])
            raise DatasetError(f"{mp}: invalid dataset meta ({e.error_count()} problem(s)): {probs}") from None
        tables: dict[str, Table] = {}
        for name, cols in TABLE_COLUMNS.items():
            f = path / f"{name}.parquet"
            if name in skip and f.is_file():
                continue
            if not f.is_file():
                if name in OPTIONAL_TABLES:
                    continue
                raise DatasetError(f"{path}: missing required table {name}.parquet")
            try:
                missing = [c for c in cols if c not in pq.read_schema(f).names]
                if missing:
                    raise DatasetError(f"{f}: missing columns {missing}")
                tables[name] = _read_columns(pq, pa, f, cols)
            except (OSError, pa.ArrowException) as e:  # truncated or not a parquet file
                raise DatasetError(f"{f}: cannot read the table ({e}); re-create the dataset") from None
        return cls(meta, tables)


def _read_columns(pq, pa, f: Path, cols) -> dict[str, np.ndarray]:
    """The columns of one parquet table as int64/float64 arrays, read one column at a time: the
    Arrow copy of a column lives only while it is converted, and the freed buffers go back to the
    OS (with the whole table at once the sensor-sim of a 1000 s paper run peaked at 565 MB)."""
    out = {c: pq.read_table(f, columns=[c]).column(c).to_numpy().astype(np.int64 if c in INT_COLUMNS else np.float64)
           for c in cols}
    pa.default_memory_pool().release_unused()
    return out


# -- per-epoch view: what one UAV receives for epoch k ------------------------------------


@dataclass
class EpochInput:
    """Everything UAV ``uav`` measures for epoch k (interval (t_prev, t]).

    imu_t/gyro/accel: IMU samples with t_prev <= imu_t < t (zero-order hold to the next sample;
    the last one holds until t). gnss_*: the fix at t if any (ENU). ranges: rows this UAV takes
    part in, ``other`` = the other node id, with event time ``range_t`` inside (t_prev, t].
    rel: this UAV's own azimuth/elevation observations. tdoa: the passive-listening rows this UAV
    takes part in as listener, initiator or responder (like a range, which both ends receive; see
    the ``tdoa`` table). Labels are NOT
    included (estimators must not see them); the central oracle gets them separately.
    """

    uav: int
    k: int
    t: float
    t_prev: float
    imu_t: np.ndarray
    gyro: np.ndarray  # (M,3) rad/s
    accel: np.ndarray  # (M,3) m/s^2
    gnss_pos: np.ndarray | None = None  # (3,) ENU m
    gnss_vel: np.ndarray | None = None  # (3,) ENU m/s
    gnss_pos_sigma: np.ndarray | None = None  # (3,)
    gnss_vel_sigma: float | None = None
    range_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    range_other: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    range_tag_self: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    range_tag_other: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    range_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    range_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rel_target: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    rel_az: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rel_el: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rel_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    altitude: float | None = None
    altitude_sigma: float | None = None
    tdoa_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tdoa_listener: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # listener node id
    tdoa_tag: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # the listener's tag
    tdoa_init: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # initiator node id
    tdoa_tag_init: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tdoa_resp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # responder node id
    tdoa_tag_resp: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tdoa_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # range difference resp − init, m
    tdoa_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))


class EpochSlicer:
    """Cuts a dataset into EpochInput per (epoch, UAV) with precomputed indices (O(1) per call).
    ``imu``: where the IMU samples come from (``imu_source``: default the dataset's table, held
    whole; the sensor-sim streams them from the file instead)."""

    def __init__(self, ds: Dataset, imu=None):
        self.ds = ds
        self.meta = ds.meta
        self.uavs = ds.meta.uav_ids()
        self.K = ds.meta.n_epochs()
        self.edges = np.array([ds.meta.epoch_time(k) for k in range(self.K + 1)])
        self.imu = imu if imu is not None else ImuInMemory(ds.table("imu"), self.uavs)
        self._gnss = {}
        if "gnss" in ds.tables and len(ds.tables["gnss"]["t"]):
            g = ds.gnss_enu()
            kk = np.rint((g["t"] - self.meta.t_start) / self.meta.epoch_dt_s).astype(int)
            ontime = np.abs(g["t"] - self.edges[np.clip(kk, 0, self.K)]) < 1e-6
            for i in np.flatnonzero(ontime):
                self._gnss[(int(kk[i]), int(g["node"][i]))] = i
            self._g = g
        r = ds.table("ranges")
        self._r = r
        # tables are sorted by t, so each epoch (t_prev, t] is one contiguous slice of rows
        self._rs = np.searchsorted(r["t"], self.edges, side="right")
        self._rel = ds.table("rel")
        self._rels = np.searchsorted(self._rel["t"], self.edges, side="right")
        self._alt = ds.table("altitude")
        self._alts = np.searchsorted(self._alt["t"], self.edges, side="right")
        self._td = ds.table("tdoa")
        self._tds = np.searchsorted(self._td["t"], self.edges, side="right")

    def epoch(self, k: int, uav: int) -> EpochInput:
        t_prev, t = self.edges[k - 1], self.edges[k]
        imu_t, gyro, accel = self.imu.samples(uav, t_prev, t)
        inp = EpochInput(uav=uav, k=k, t=float(t), t_prev=float(t_prev), imu_t=imu_t, gyro=gyro, accel=accel)
        gi = self._gnss.get((k, uav))
        if gi is not None:
            g = self._g
            inp.gnss_pos = np.array([g["pe"][gi], g["pn"][gi], g["pu"][gi]])
            inp.gnss_vel = np.array([g["ve"][gi], g["vn"][gi], g["vu"][gi]])
            inp.gnss_pos_sigma = np.array([g["sig_pe"][gi], g["sig_pn"][gi], g["sig_pu"][gi]])
            inp.gnss_vel_sigma = float(g["sig_v"][gi])
        r = self._r
        lo, hi = self._rs[k - 1], self._rs[k]
        sel = lo + np.flatnonzero((r["a"][lo:hi] == uav) | (r["b"][lo:hi] == uav))
        if len(sel):
            a, b = r["a"][sel], r["b"][sel]
            me_a = a == uav
            inp.range_t = r["t"][sel]
            inp.range_other = np.where(me_a, b, a)
            inp.range_tag_self = np.where(me_a, r["tag_a"][sel], r["tag_b"][sel])
            inp.range_tag_other = np.where(me_a, r["tag_b"][sel], r["tag_a"][sel])
            inp.range_m = r["range"][sel]
            inp.range_sigma = r["sigma"][sel]
        rel = self._rel
        lo, hi = self._rels[k - 1], self._rels[k]
        sel = lo + np.flatnonzero(rel["observer"][lo:hi] == uav)
        if len(sel):
            inp.rel_target = rel["target"][sel]
            inp.rel_az, inp.rel_el, inp.rel_sigma = rel["azimuth"][sel], rel["elevation"][sel], rel["sigma"][sel]
        al = self._alt
        lo, hi = self._alts[k - 1], self._alts[k]
        sel = lo + np.flatnonzero(al["node"][lo:hi] == uav)
        if len(sel):
            inp.altitude, inp.altitude_sigma = float(al["height"][sel[-1]]), float(al["sigma"][sel[-1]])
        td = self._td
        lo, hi = self._tds[k - 1], self._tds[k]
        sel = lo + np.flatnonzero((td["node"][lo:hi] == uav) | (td["init"][lo:hi] == uav) | (td["resp"][lo:hi] == uav))
        if len(sel):
            inp.tdoa_t, inp.tdoa_listener, inp.tdoa_tag = td["t"][sel], td["node"][sel], td["tag"][sel]
            inp.tdoa_init, inp.tdoa_tag_init = td["init"][sel], td["tag_init"][sel]
            inp.tdoa_resp, inp.tdoa_tag_resp = td["resp"][sel], td["tag_resp"][sel]
            inp.tdoa_m, inp.tdoa_sigma = td["rdiff"][sel], td["sigma"][sel]
        return inp

    def tdoa_labels(self, k: int) -> Table:
        """tdoa rows of epoch k with their fault labels (for scoring and the central oracle only)."""
        lo, hi = self._tds[k - 1], self._tds[k]
        return {c: v[lo:hi] for c, v in self._td.items()}

    def range_labels(self, k: int) -> Table:
        """Range rows of epoch k with their fault labels (for scoring and the central oracle only)."""
        lo, hi = self._rs[k - 1], self._rs[k]
        return {c: v[lo:hi] for c, v in self._r.items()}
