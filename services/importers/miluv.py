"""MILUV recording -> swarmnav dataset (``swarmnav import-miluv``). See ``docs/miluv.md``.

Reads one MILUV experiment folder (``ifo00N/*.csv`` plus ``config/``) with the csv module and numpy
(no pandas; the UWB files contain quoted fields such as ``"(11, 2)"``) and builds a
:class:`swarmnav.dataset.Dataset`:

- nodes: UAV ``N`` for robot ``ifo00N`` (tags and lever arms from ``config/uwb/tags.yaml``) and one
  static node ``100 + k`` per UWB anchor ``k`` (kind "anchor", position from
  ``config/uwb/anchors.yaml`` for the experiment's constellation; tag id = anchor id, zero lever arm);
- frame: the Vicon world frame (z up) is used as the local frame, x -> E, y -> N, z -> U; no geodetic
  origin, no GNSS;
- IMU: ``imu_px4.csv`` (mavros ``data_raw``, already ROS body FLU), every sample kept (variable rate);
- ranges: ``uwb_range.csv`` of all robots, deduplicated on (timestamp, unordered tag pair), sigma =
  the row's ``std``, labels from ``bias``/``std``;
- tdoa: ``uwb_passive.csv`` of all robots (a third tag overhearing a two-way ranging transaction)
  turned into range differences with the transaction's own timestamps (``_passive_rdiff``),
  deduplicated on (listener, initiator, responder, transaction time), labels from mocap;
- altitude: ``height.csv`` minus the per-robot bias, readings at the sensor floor dropped;
- truth: mocap, resampled to a 10-sub-step grid of the epochs, velocities by central differences.

Everything computes in memory; :func:`convert` returns the dataset and a summary dict.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np

from swarmnav.config import load_estimation
from swarmnav.dataset import (Dataset, DatasetMeta, Earth, FaultKind, ImuNoise, Node, TABLE_COLUMNS, epoch_of)
from swarmnav.errors import DatasetError

ANCHOR_NODE_OFFSET = 100  # anchor k -> node id 100 + k (UAVs are 1..9)
GRAVITY_MPS2 = 9.81
HEIGHT_MIN_VALID_M = 0.30  # the rangefinder reads a constant 0.29 m on the ground (below its minimum range)
HEIGHT_SIGMA_M = 0.10  # altitude sigma: in-flight (height - bias) vs mocap z spread 0.03-0.09 m per robot
TRUTH_SUBSTEPS = 10  # truth rows per epoch (epoch times themselves included exactly)
VEL_HALF_WINDOW_S = 0.05  # truth velocity = central difference over +-50 ms of interpolated mocap
MAX_TILT_DEG = 45.0  # mocap attitudes tilted more than this are marker-swap glitches (flight max ~11 deg)
GYRO_BIAS_SIGMA = 0.005  # rad/s, turn-on bias prior (not in config/imu; PX4 calibrates the gyro at boot)
ACCEL_BIAS_SIGMA = 0.3  # m/s^2, turn-on bias prior (not in config/imu; MEMS datasheet order ~30 mg)
INIT = {"vel_sigma_mps": 0.05, "roll_pitch_sigma_deg": 3.0, "yaw_sigma_deg": 3.0}
# Coarse alignment (initial.py ``init.level_window_s``): roll/pitch from each UAV's own accelerometer
# over the first LEVEL_WINDOW_S s, set only if every UAV is at rest then by its IMU alone (gyro-norm
# std and specific-force-norm std below these, mean |f| within LEVEL_MAX_G_DEV of g).
LEVEL_WINDOW_S = 1.0
LEVEL_MAX_GYRO_STD = 0.01  # rad/s
LEVEL_MAX_ACC_STD = 0.1  # m/s^2
LEVEL_MAX_G_DEV = 0.3  # m/s^2
# In-flight accelerometer white noise from the recording itself (no mocap): vibration = the signal
# minus its VIB_SMOOTH_S moving average, while the rangefinder says airborne; density = per-sample
# RMS std / sqrt(rate). Used when above the at-rest Allan value.
VIB_SMOOTH_S = 0.2
# Passive listening (uwb_passive.csv): timestamps in ns of the DW1000's 63.8976 GHz counter
# (15.65 ps ticks). The listener's logged rx timestamps wrap every 2**32 ticks = 67.216 ms (seen in
# the recording: ~15 % of the rows have rx2 - rx1 one wrap too long), so every interval is taken
# modulo PASSIVE_WRAP_NS. Clock-rate ratio sanity bound: DW1000 crystals are +-20 ppm.
SPEED_OF_LIGHT_M_PER_NS = 0.299792458
PASSIVE_WRAP_NS = 2.0**32 / (128 * 499.2e6) * 1e9
PASSIVE_MAX_SKEW = 1e-4

_ROBOT_RE = re.compile(r"^ifo0*(\d+)$")


# -- low-level readers -------------------------------------------------------------------


def read_csv(path: Path, columns: list[str]) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV file (csv module: quoted fields are fine), as float arrays.

    Rows are returned in file order. Raises DatasetError naming the file, column and line for a
    missing file/column or a value that is not a number.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: missing file")
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise DatasetError(f"{path}: empty file (no header)") from None
        missing = [c for c in columns if c not in header]
        if missing:
            raise DatasetError(f"{path}: missing columns {missing} (has {header[:12]}{'...' if len(header) > 12 else ''})")
        idx = [header.index(c) for c in columns]
        out: list[list[float]] = []
        for line, row in enumerate(reader, start=2):
            if not row or all(not x.strip() for x in row):
                continue  # blank line
            if len(row) != len(header):
                raise DatasetError(f"{path}:{line}: {len(row)} fields, header has {len(header)} (unquoted comma?)")
            vals = []
            for c, i in zip(columns, idx):
                s = row[i].strip()
                try:
                    vals.append(float(s) if s else math.nan)
                except ValueError:
                    raise DatasetError(f"{path}:{line}: column {c!r} is not a number: {s[:40]!r}") from None
            out.append(vals)
    arr = np.array(out, float).reshape(-1, len(columns))
    return {c: arr[:, j] for j, c in enumerate(columns)}


def read_simple_yaml(path: Path) -> dict:
    """The flat/nested ``key: "value"`` YAML subset MILUV's config uses (no PyYAML dependency).

    Nesting by indentation; comments (#) and blank lines ignored; a key with no value opens a
    mapping, a bare value line under a key (height/bias.yaml style) becomes that key's value.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: missing config file")
    root: dict = {}
    stack: list[tuple[int, dict, str | None]] = [(-1, root, None)]
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        text = line.strip()
        while stack and indent <= stack[-1][0]:
            stack.pop()
        if not stack:
            raise DatasetError(f"{path}:{line_no}: bad indentation")
        parent_indent, parent, pkey = stack[-1]
        m = re.match(r"""^("[^"]*"|'[^']*'|[^:]+?)\s*:(\s+(.*))?$""", text)
        if m is None or text.startswith(("'[", '"[')):
            # a bare value under the previous key
            gp = stack[-2][1] if len(stack) >= 2 else None
            if gp is None or pkey is None:
                raise DatasetError(f"{path}:{line_no}: cannot parse {text!r}")
            gp[pkey] = _unquote(text)
            continue
        key = _unquote(m.group(1))
        val = m.group(3)
        if val is None or val == "":
            child: dict = {}
            parent[key] = child
            stack.append((indent, child, key))
        else:
            parent[key] = _unquote(val)
    return root


def _unquote(s: str) -> str:
    s = s.strip()
    if len(s) >= 2 and s[0] == s[-1] and s[0] in "\"'":
        return s[1:-1]
    return s


def parse_vector(s: str, n: int, where: str) -> tuple[float, ...]:
    """'[a, b, c]' or '[a b c]' -> floats."""
    parts = [p for p in re.split(r"[\s,]+", s.strip().strip("[]()")) if p]
    try:
        v = tuple(float(p) for p in parts)
    except ValueError:
        raise DatasetError(f"{where}: not a vector of numbers: {s!r}") from None
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise DatasetError(f"{where}: expected {n} finite numbers, got {s!r}")
    return v


def _float(d: dict, key: str, where: str) -> float:
    if key not in d:
        raise DatasetError(f"{where}: missing key {key!r}")
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {key} is not a number: {d[key]!r}") from None
    if not math.isfinite(v) or v < 0:
        raise DatasetError(f"{where}: {key} must be finite and >= 0, got {v}")
    return v


def _clean_time_series(t: np.ndarray, cols: dict[str, np.ndarray], where: str, summary: dict) -> tuple[np.ndarray, dict]:
    """Drop non-finite rows, sort by time (stable), drop repeated timestamps (keep first)."""
    ok = np.isfinite(t)
    for v in cols.values():
        ok &= np.isfinite(v)
    n_bad = int((~ok).sum())
    t = t[ok]
    cols = {k: v[ok] for k, v in cols.items()}
    order = np.argsort(t, kind="stable")
    n_unsorted = int(np.any(np.diff(t) < 0))
    t = t[order]
    cols = {k: v[order] for k, v in cols.items()}
    keep = np.ones(len(t), bool)
    keep[1:] = np.diff(t) > 0
    n_dup = int((~keep).sum())
    if n_bad or n_dup or n_unsorted:
        summary.setdefault("cleaning", {})[where] = {"non_finite_rows": n_bad, "repeated_timestamps": n_dup, "was_unsorted": bool(n_unsorted)}
    if keep.sum() < 2:
        raise DatasetError(f"{where}: fewer than 2 valid rows")
    return t[keep], {k: v[keep] for k, v in cols.items()}


# -- rotations (x, y, z, w as in ROS) -----------------------------------------------------


def _rotmat_xyzw(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _slerp(t_src: np.ndarray, q_src: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    """Quaternion (x,y,z,w) interpolation at t_dst (clamped to the ends), sign-continuous."""
    q = q_src / np.linalg.norm(q_src, axis=1, keepdims=True)
    # hemisphere continuity: flip signs so consecutive quaternions have a positive dot product
    flips = np.concatenate([[1.0], np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0)])
    q = q * np.cumprod(flips)[:, None]
    j = np.clip(np.searchsorted(t_src, t_dst, side="right") - 1, 0, len(t_src) - 2)
    t0, t1 = t_src[j], t_src[j + 1]
    u = np.clip((t_dst - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0, 1.0)[:, None]
    a, b = q[j], q[j + 1]
    dot = np.clip(np.sum(a * b, axis=1, keepdims=True), -1.0, 1.0)
    th = np.arccos(dot)
    s = np.sin(th)
    small = s < 1e-9
    wa = np.where(small, 1 - u, np.sin((1 - u) * th) / np.where(small, 1.0, s))
    wb = np.where(small, u, np.sin(u * th) / np.where(small, 1.0, s))
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=1, keepdims=True)


# -- the conversion ----------------------------------------------------------------------


def _robots(src: Path) -> list[tuple[str, int]]:
    out = []
    for d in sorted(src.iterdir()):
        m = _ROBOT_RE.match(d.name)
        if d.is_dir() and m:
            out.append((d.name, int(m.group(1))))
    if not out:
        raise DatasetError(f"{src}: no robot folders (ifo001, ifo002, ...) — is this a MILUV experiment folder?")
    ids = [i for _, i in out]
    if len(set(ids)) != len(ids) or min(ids) < 1 or max(ids) >= ANCHOR_NODE_OFFSET:
        raise DatasetError(f"{src}: robot ids {ids} must be unique and in 1..{ANCHOR_NODE_OFFSET - 1}")
    return out


def _experiment_row(src: Path) -> dict[str, str]:
    p = src / "config" / "experiments.csv"
    if not p.is_file():
        raise DatasetError(f"{p}: missing (needed for the anchor constellation)")
    with open(p, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if r.get("experiment") == src.name:
            return r
    raise DatasetError(f"{p}: experiment {src.name!r} not listed (the source folder must keep its MILUV name)")


DEFAULT_ESTIMATION = Path(__file__).resolve().parents[2] / "configs" / "miluv.toml"


def convert(src: str | Path, epoch_dt: float = 0.1, estimation: str | Path | None = DEFAULT_ESTIMATION
            ) -> tuple[Dataset, dict]:
    """MILUV experiment folder -> (Dataset, import summary). ``estimation``: a TOML file whose
    ``[estimation]`` table (estimator tuning for this kind of data, configs/miluv.toml) is embedded
    in ``meta.config["estimation"]`` — as a simulated dataset carries its scenario's — so
    ``evaluate``/``launch``/``calibrate --dataset`` use it; None = the estimators' defaults."""
    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a directory")
    if not (0.001 <= epoch_dt <= 5.0):
        raise DatasetError(f"--epoch-dt {epoch_dt}: must be in [0.001, 5] s")
    summary: dict = {"experiment": src.name}
    robots = _robots(src)
    exp = _experiment_row(src)
    constellation = exp.get("anchor_constellation", "").strip()
    used_files: list[Path] = [src / "config" / "experiments.csv"]

    # -- config ---------------------------------------------------------------------------
    anchors_cfg = read_simple_yaml(src / "config" / "uwb" / "anchors.yaml")
    tags_cfg = read_simple_yaml(src / "config" / "uwb" / "tags.yaml")
    hbias_cfg = read_simple_yaml(src / "config" / "height" / "bias.yaml")
    used_files += [src / "config" / "uwb" / "anchors.yaml", src / "config" / "uwb" / "tags.yaml", src / "config" / "height" / "bias.yaml"]
    if constellation not in anchors_cfg:
        raise DatasetError(f"config/uwb/anchors.yaml: no constellation {constellation!r} (experiment {src.name})")
    anchors = {int(k): parse_vector(v, 3, f"anchors.yaml[{constellation}][{k}]") for k, v in anchors_cfg[constellation].items()}
    tag_owner: dict[int, int] = {}  # tag id -> node id
    nodes: list[Node] = []
    imu_noise: dict[int, ImuNoise] = {}
    for name, uid in robots:
        tcfg = tags_cfg.get(name)
        if not isinstance(tcfg, dict) or not tcfg:
            raise DatasetError(f"config/uwb/tags.yaml: no tags for {name}")
        tags = {int(k): parse_vector(v, 3, f"tags.yaml[{name}][{k}]") for k, v in tcfg.items()}
        for tg in tags:
            if tg in anchors or tg in tag_owner:
                raise DatasetError(f"tag id {tg} of {name} is not unique (anchor or other robot)")
            tag_owner[tg] = uid
        ip = src / "config" / "imu" / name / "px4_imu.yaml"
        used_files.append(ip)
        ic = read_simple_yaml(ip)
        w = f"{ip.relative_to(src)}"
        # Kalibr/Allan convention: noise densities [unit/sqrt(Hz)], random walks [unit/s/sqrt(Hz)] = SI as ImuNoise wants
        imu_noise[uid] = ImuNoise(
            gyro_noise_density=_float(ic, "gyroscope_noise_density", w),
            accel_noise_density=_float(ic, "accelerometer_noise_density", w),
            gyro_bias_sigma=GYRO_BIAS_SIGMA,
            accel_bias_sigma=ACCEL_BIAS_SIGMA,
            gyro_bias_rw=_float(ic, "gyroscope_random_walk", w),
            accel_bias_rw=_float(ic, "accelerometer_random_walk", w),
        )
        # the ifo robots are quadrotors (MILUV paper): declared so the rotor-drag model can apply
        nodes.append(Node(id=uid, kind="uav", role="slave", tags=tags, imu=imu_noise[uid], airframe="multirotor"))
    for k, pos in sorted(anchors.items()):
        nodes.append(Node(id=ANCHOR_NODE_OFFSET + k, kind="anchor", role="anchor", position_enu=pos, tags={k: (0.0, 0.0, 0.0)}))
        tag_owner[k] = ANCHOR_NODE_OFFSET + k

    # -- per-robot time series --------------------------------------------------------------
    mocap: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    imu: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    height: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    mcols = ["timestamp", "pose.position.x", "pose.position.y", "pose.position.z",
             "pose.orientation.x", "pose.orientation.y", "pose.orientation.z", "pose.orientation.w"]
    icols = ["timestamp", "angular_velocity.x", "angular_velocity.y", "angular_velocity.z",
             "linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z"]
    glitches = {}
    for name, uid in robots:
        p = src / name / "mocap.csv"
        used_files.append(p)
        c = read_csv(p, mcols)
        t, c = _clean_time_series(c.pop("timestamp"), c, f"{name}/mocap.csv", summary)
        pos = np.column_stack([c["pose.position.x"], c["pose.position.y"], c["pose.position.z"]])
        q = np.column_stack([c["pose.orientation.x"], c["pose.orientation.y"], c["pose.orientation.z"], c["pose.orientation.w"]])
        qn = np.linalg.norm(q, axis=1)
        if np.any(qn < 0.5):
            raise DatasetError(f"{p}: quaternion with norm {qn.min():.3g} (expected unit quaternions x,y,z,w)")
        # marker-swap glitches: body z-axis far from world up -> attitude interpolated across
        czz = _rotmat_xyzw(q)[:, 2, 2]
        bad = czz < math.cos(math.radians(MAX_TILT_DEG))
        if bad.all():
            raise DatasetError(f"{p}: every mocap attitude is tilted > {MAX_TILT_DEG} deg — not z-up?")
        if bad.any():
            idx = np.flatnonzero(bad)
            glitches[name] = {"samples": int(bad.sum()), "t_first": round(float(t[idx[0]]), 3), "t_last": round(float(t[idx[-1]]), 3)}
            q = q.copy()
            q[bad] = _slerp(t[~bad], q[~bad], t[bad])
        mocap[uid] = (t, pos, q)

        p = src / name / "imu_px4.csv"
        used_files.append(p)
        c = read_csv(p, icols)
        t, c = _clean_time_series(c.pop("timestamp"), c, f"{name}/imu_px4.csv", summary)
        data = np.column_stack([c[k] for k in icols[1:]])
        imu[uid] = (t, data)

        p = src / name / "height.csv"
        if p.is_file():
            used_files.append(p)
            c = read_csv(p, ["timestamp", "range"])
            t, c = _clean_time_series(c.pop("timestamp"), c, f"{name}/height.csv", summary)
            hb = hbias_cfg.get(name)
            try:
                hb = float(hb)
            except (TypeError, ValueError):
                raise DatasetError(f"config/height/bias.yaml: no numeric bias for {name} (got {hb!r})") from None
            h = c["range"]
            valid = h > HEIGHT_MIN_VALID_M
            height[uid] = (t[valid], h[valid] - hb)
            summary.setdefault("height_dropped_at_sensor_floor", {})[name] = int((~valid).sum())
        # in-flight accelerometer noise (vibration) measured from the IMU while the rangefinder reads airborne
        hv = height.get(uid)
        if hv is not None and len(hv[0]) > 100:
            ti, acc = imu[uid][0], imu[uid][1][:, 3:6]
            air = (ti >= hv[0][0]) & (ti <= hv[0][-1])
            rate = 1.0 / float(np.median(np.diff(ti)))
            nwin = max(3, int(round(VIB_SMOOTH_S * rate)))
            kern = np.ones(nwin) / nwin
            hf = np.column_stack([acc[:, j] - np.convolve(acc[:, j], kern, "same") for j in range(3)])[air][nwin:-nwin]
            sd = float(np.sqrt(np.mean(np.var(hf, axis=0))))
            dens = sd / math.sqrt(rate)
            summary.setdefault("accel_in_flight", {})[name] = {"vibration_std_mps2": round(sd, 3),
                                                              "density": round(dens, 4),
                                                              "allan_density": imu_noise[uid].accel_noise_density}
            if dens > imu_noise[uid].accel_noise_density:
                imu_noise[uid].accel_noise_density = dens
    if glitches:
        summary["mocap_attitude_glitches_interpolated"] = glitches

    # -- time span ------------------------------------------------------------------------
    first = max(max(mocap[u][0][0], imu[u][0][0]) for u in mocap)
    last = min(min(mocap[u][0][-1], imu[u][0][-1]) for u in mocap)
    t_start = math.ceil(first * 100.0 - 1e-9) / 100.0  # first common time, rounded up to 10 ms
    n_epochs = int(math.floor((last - t_start) / epoch_dt + 1e-9))
    if n_epochs < 2:
        raise DatasetError(f"{src}: robots' mocap and IMU overlap for only {last - first:.3f} s")
    duration = round(n_epochs * epoch_dt, 9)
    t_end = t_start + duration
    summary.update(t_start=t_start, duration_s=round(duration, 9), n_epochs=n_epochs, epoch_dt_s=epoch_dt)

    # -- IMU table (FLU already: mavros data_raw is ROS base_link FLU; a_z ~ +9.8 at rest) -----
    it, iu, idata = [], [], []
    imu_stats = {}
    for uid, (t, d) in sorted(imu.items()):
        lo = max(int(np.searchsorted(t, t_start, side="right")) - 1, 0)  # the sample in force at t_start
        hi = int(np.searchsorted(t, t_end, side="left"))
        t, d = t[lo:hi], d[lo:hi]
        it.append(t)
        iu.append(np.full(len(t), uid))
        idata.append(d)
        dt = np.diff(t)
        imu_stats[uid] = {"samples": int(len(t)), "rate_hz_median": round(float(1 / np.median(dt)), 1),
                          "max_gap_s": round(float(dt.max()), 4), "gaps_over_20ms": int((dt > 0.02).sum())}
    summary["imu"] = imu_stats
    # at rest over the first LEVEL_WINDOW_S s (IMU only)? -> coarse alignment of roll/pitch in initial.py
    at_rest = {}
    for uid, (t, d) in sorted(imu.items()):
        m = (t >= t_start) & (t <= t_start + LEVEL_WINDOW_S)
        gn, fn = np.linalg.norm(d[m, 0:3], axis=1), np.linalg.norm(d[m, 3:6], axis=1)
        at_rest[uid] = bool(m.sum() > 10 and gn.std() < LEVEL_MAX_GYRO_STD and fn.std() < LEVEL_MAX_ACC_STD
                            and abs(fn.mean() - GRAVITY_MPS2) < LEVEL_MAX_G_DEV)
    level = all(at_rest.values())
    summary["level_at_start"] = {str(u): v for u, v in at_rest.items()}
    imu_tab = _sorted_table("imu", np.concatenate(it), np.concatenate(iu), np.vstack(idata))

    # -- truth on a grid: epoch times exactly, TRUTH_SUBSTEPS per epoch --------------------------
    tt, tu, trows = [], [], []
    ks = np.repeat(np.arange(n_epochs + 1), TRUTH_SUBSTEPS)[: n_epochs * TRUTH_SUBSTEPS + 1]
    ms = np.tile(np.arange(TRUTH_SUBSTEPS), n_epochs + 1)[: n_epochs * TRUTH_SUBSTEPS + 1]
    grid = t_start + ks * epoch_dt + ms * (epoch_dt / TRUTH_SUBSTEPS)  # m == 0: bitwise meta.epoch_time(k)
    truth_fn = {}
    for uid, (t, pos, q) in sorted(mocap.items()):
        gap = np.diff(t).max()
        if gap > 0.5:
            summary.setdefault("warnings", []).append(f"ifo{uid:03d} mocap gap {gap:.2f} s (interpolated)")
        P = np.column_stack([np.interp(grid, t, pos[:, j]) for j in range(3)])
        lo_t = np.maximum(grid - VEL_HALF_WINDOW_S, t[0])
        hi_t = np.minimum(grid + VEL_HALF_WINDOW_S, t[-1])
        Plo = np.column_stack([np.interp(lo_t, t, pos[:, j]) for j in range(3)])
        Phi = np.column_stack([np.interp(hi_t, t, pos[:, j]) for j in range(3)])
        V = (Phi - Plo) / (hi_t - lo_t)[:, None]
        Q = _slerp(t, q, grid)  # x,y,z,w body -> Vicon world (= local ENU)
        Q *= np.where(Q[:, 3:4] < 0, -1.0, 1.0)  # w >= 0
        tt.append(grid)
        tu.append(np.full(len(grid), uid))
        trows.append(np.column_stack([P, V, Q[:, 3], Q[:, 0], Q[:, 1], Q[:, 2]]))
        truth_fn[uid] = (t, pos, q)
        sp = np.linalg.norm(V, axis=1)
        summary.setdefault("speed_mps", {})[uid] = {"p50": round(float(np.median(sp)), 3), "p99": round(float(np.percentile(sp, 99)), 3), "max": round(float(sp.max()), 3)}
    truth_tab = _sorted_table("truth", np.concatenate(tt), np.concatenate(tu), np.vstack(trows))

    # -- altitude ----------------------------------------------------------------------------
    at, au, ah = [], [], []
    for uid, (t, h) in sorted(height.items()):
        m = (t > t_start) & (t <= t_end)
        at.append(t[m])
        au.append(np.full(int(m.sum()), uid))
        ah.append(h[m])
    alt_tab = None
    if at:
        n = sum(len(x) for x in at)
        alt_tab = _sorted_table("altitude", np.concatenate(at), np.concatenate(au),
                                np.column_stack([np.concatenate(ah), np.full(n, HEIGHT_SIGMA_M)]))

    # -- UWB ranges ---------------------------------------------------------------------------
    rcols = ["timestamp", "from_id", "to_id", "range", "gt_range", "bias", "std"]
    seen: dict[tuple[float, int, int], tuple] = {}
    n_logged = 0
    n_dup = 0
    for name, uid in robots:
        p = src / name / "uwb_range.csv"
        if not p.is_file():
            continue
        used_files.append(p)
        c = read_csv(p, rcols)
        for i in range(len(c["timestamp"])):
            n_logged += 1
            ts, fr, to = float(c["timestamp"][i]), c["from_id"][i], c["to_id"][i]
            if not (math.isfinite(fr) and math.isfinite(to)) or fr != int(fr) or to != int(to):
                raise DatasetError(f"{p}: row {i + 2}: from_id/to_id not integers ({fr}, {to})")
            fr, to = int(fr), int(to)
            for tg in (fr, to):
                if tg not in tag_owner:
                    raise DatasetError(f"{p}: row {i + 2}: unknown tag/anchor id {tg} (tags.yaml/anchors.yaml)")
            key = (ts, min(fr, to), max(fr, to))
            vals = (c["range"][i], c["gt_range"][i], c["bias"][i], c["std"][i])
            if key in seen:
                n_dup += 1
                old = seen[key][1]
                if not np.allclose(old, vals, rtol=0, atol=1e-9, equal_nan=True):
                    raise DatasetError(f"{p}: row {i + 2}: transaction at t={ts} between {fr} and {to} also logged by another robot with different values {old} vs {vals}")
                continue
            seen[key] = ((fr, to), vals, name)
    rows = []
    dropped = {"outside_span": 0, "invalid_range": 0, "no_std": 0}
    for (ts, _, _), ((fr, to), (rng, gt, bias, std), _) in seen.items():
        if not (t_start < ts <= t_end) or not math.isfinite(ts):
            dropped["outside_span"] += 1
            continue
        if not math.isfinite(rng) or rng <= 0:
            dropped["invalid_range"] += 1
            continue
        na, nb = tag_owner[fr], tag_owner[to]
        if na == nb:
            raise DatasetError(f"range between two tags ({fr}, {to}) of the same robot at t={ts}")
        ta, tb = (fr, to) if na < nb else (to, fr)
        a, b = min(na, nb), max(na, nb)
        rows.append((ts, a, b, ta, tb, rng, std, bias, gt))
    rows.sort(key=lambda r: (r[0], r[1], r[2], r[3], r[4]))
    R = np.array(rows, float).reshape(-1, 9)
    std = R[:, 6]
    bias = R[:, 7]
    std_ok = np.isfinite(std) & (std > 0)
    sigma_nominal = float(np.median(std[std_ok])) if std_ok.any() else 0.19
    dropped["no_std"] = int((~std_ok).sum())  # kept, sigma = the median std
    sigma = np.where(std_ok, std, sigma_nominal)
    faulty = np.isfinite(bias) & (np.abs(bias) > 3 * sigma)
    threshold = 3 * sigma_nominal
    ranges_tab = {
        "t": R[:, 0], "a": R[:, 1].astype(np.int64), "b": R[:, 2].astype(np.int64),
        "tag_a": R[:, 3].astype(np.int64), "tag_b": R[:, 4].astype(np.int64),
        "range": R[:, 5], "sigma": sigma,
        "fault_kind": np.where(faulty, int(FaultKind.NLOS_REAL), int(FaultKind.NONE)).astype(np.int64),
        "fault_err": bias,
    }
    inter = ranges_tab["b"] < ANCHOR_NODE_OFFSET
    scored = np.abs(bias) > threshold
    summary["ranges"] = {
        "logged_rows": n_logged, "duplicates_removed": n_dup, "transactions": len(seen), "kept": int(len(R)),
        "inter_uav": int(inter.sum()), "to_anchor": int((~inter).sum()), "dropped": dropped,
        "sigma_median_m": round(sigma_nominal, 4),
        "nlos_real_rows": int(faulty.sum()), "nlos_real_inter_uav": int((faulty & inter).sum()),
        "fault_threshold_m": round(threshold, 4),
        "rows_where_threshold_disagrees_with_per_row_rule": int((scored != faulty).sum()),
        "max_gap_s": round(float(np.diff(R[:, 0]).max()), 3) if len(R) > 1 else None,
    }
    # motion inside the epoch: change of the true range between the range's time and its epoch end
    if len(R):
        k = epoch_of(R[:, 0], t_start, epoch_dt)
        t_ep = t_start + k * epoch_dt
        d_now = _true_range(truth_fn, anchors, nodes, ranges_tab, R[:, 0])
        d_ep = _true_range(truth_fn, anchors, nodes, ranges_tab, t_ep)
        dd = np.abs(d_ep - d_now)
        summary["ranges"]["range_change_to_epoch_end_m"] = {"p50": round(float(np.median(dd)), 4), "p95": round(float(np.percentile(dd, 95)), 4), "max": round(float(dd.max()), 4)}
        ok = np.isfinite(R[:, 8])
        summary["ranges"]["our_truth_minus_gt_range_m"] = {"max_abs": round(float(np.abs(d_now[ok] - R[ok, 8]).max()), 4)}

    # -- passive listening -> tdoa ------------------------------------------------------------
    tdoa_tab = _import_passive(src, robots, tag_owner, nodes, anchors, truth_fn, t_start, t_end, sigma_nominal,
                               used_files, summary)

    # -- meta --------------------------------------------------------------------------------
    h = hashlib.sha256()
    for f in sorted(set(used_files)):
        h.update(str(f.relative_to(src)).encode() + b"\0")
        h.update(f.read_bytes())
    est_table = load_estimation(estimation) if estimation is not None else None
    if est_table is not None:  # the embedded tuning is part of the dataset's provenance
        h.update(json.dumps(est_table, sort_keys=True).encode())
    meta = DatasetMeta(
        name=f"miluv/{src.name}",
        source="recorded",
        seed=None,
        config={"importer": "swarmnav import-miluv", "experiment": dict(sorted(exp.items())), "imu_source": "imu_px4.csv",
                "frame": "Vicon world (z up): x->E, y->N, z->U; no geodetic origin",
                "anchor_node_id": f"{ANCHOR_NODE_OFFSET} + MILUV anchor id", "uav_node_id": "N for ifo00N",
                **({"estimation": est_table} if est_table is not None else {})},
        config_sha256=h.hexdigest(),
        origin=None,
        t_start=t_start,
        duration_s=duration,
        epoch_dt_s=epoch_dt,
        nodes=nodes,
        earth=Earth(gravity_mps2=GRAVITY_MPS2, earth_rate_radps=(0.0, 0.0, 0.0)),
        uwb_sigma_m=sigma_nominal,
        rel_sigma_rad=None,
        fault_threshold_m=threshold,
        events=[],
        init=dict(INIT, **({"level_window_s": LEVEL_WINDOW_S} if level else {})),
    )
    tables = {"truth": truth_tab, "imu": imu_tab, "ranges": ranges_tab}
    if tdoa_tab is not None:
        tables["tdoa"] = tdoa_tab
    if alt_tab is not None:
        tables["altitude"] = alt_tab
        summary["altitude_rows"] = int(len(alt_tab["t"]))
    summary["truth_rows"] = int(len(truth_tab["t"]))
    return Dataset(meta, tables), summary


def _sorted_table(name: str, t: np.ndarray, node: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
    order = np.lexsort((node, t))
    cols = TABLE_COLUMNS[name]
    out = {"t": t[order], "node": node[order].astype(np.int64)}
    for j, c in enumerate(cols[2:]):
        out[c] = np.ascontiguousarray(data[order, j])
    return out


def _tag_point(truth_fn, anchors, levers, node: int, tag: int, t: float) -> np.ndarray:
    """True position of a tag at time t from mocap (linear position, slerped attitude) + lever arm."""
    if node >= ANCHOR_NODE_OFFSET:
        return np.asarray(anchors[node - ANCHOR_NODE_OFFSET], float)
    tt, pos, q = truth_fn[node]
    ti = np.array([t])
    p = np.array([np.interp(ti, tt, pos[:, j])[0] for j in range(3)])
    C = _rotmat_xyzw(_slerp(tt, q, ti))[0]
    return p + C @ np.asarray(levers[node][tag])


def _true_range(truth_fn, anchors, nodes, r, times) -> np.ndarray:
    """True tag-to-tag distance from mocap + lever arms."""
    levers = {n.id: n.tags for n in nodes}
    out = np.empty(len(times))
    for i in range(len(times)):
        pa = _tag_point(truth_fn, anchors, levers, int(r["a"][i]), int(r["tag_a"][i]), times[i])
        pb = _tag_point(truth_fn, anchors, levers, int(r["b"][i]), int(r["tag_b"][i]), times[i])
        out[i] = float(np.linalg.norm(pa - pb))
    return out


def _passive_rdiff(c: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Range difference d(resp, listener) − d(init, listener) [m] of passive-listening rows, and
    the listener/responder clock-rate ratio (for the sanity check).

    MILUV's two-way ranging (``*_n`` = the overheard active transaction): the initiator I sends a
    poll at tx1 (I's clock), the responder R receives it at rx1_n and sends two messages at tx2_n,
    tx3_n (R's clock). The listener L receives the three at rx1, rx2, rx3 (L's clock). In R's clock,
    rx2 − rx1 = (tx2_n − rx1_n) + ToF(I,R) + (d(R,L) − d(I,L))/c, with L's intervals converted to
    R's clock by the ratio (tx3_n − tx2_n)/(rx3 − rx2) (two messages from R on the same path), and
    c·ToF(I,R) = the transaction's calibrated range ``range_n``. Intervals modulo the counter wrap.
    """
    w = PASSIVE_WRAP_NS
    d_l12 = np.mod(c["rx2"] - c["rx1"], w)
    d_l23 = np.mod(c["rx3"] - c["rx2"], w)
    d_r = np.mod(c["tx3_n"] - c["tx2_n"], w)
    reply = np.mod(c["tx2_n"] - c["rx1_n"], w)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = d_r / d_l23
        rdiff = SPEED_OF_LIGHT_M_PER_NS * (d_l12 * ratio - reply) - c["range_n"]
    return rdiff, ratio


def _import_passive(src: Path, robots, tag_owner: dict[int, int], nodes, anchors, truth_fn, t_start: float,
                    t_end: float, sigma_nominal: float, used_files: list[Path], summary: dict):
    """``uwb_passive.csv`` of every robot -> the ``tdoa`` table (None if no robot has the file).

    A row is logged by several robots (identical values): deduplicated on (listener, initiator,
    responder, transaction time). Dropped, and counted in the summary: rows outside the span, a
    listener that is not a robot's tag or is one of the transaction's own tags, non-finite values,
    a clock-rate ratio beyond 1 ± PASSIVE_MAX_SKEW, and range differences that break the triangle
    inequality |d(R,L) − d(I,L)| <= d(I,R) by more than 3 σ. Time = the transaction's timestamp
    (``timestamp_n``, the active range's, which the row overheard); σ = the row's ``std`` (the
    recording's median range std where it is missing or not positive).
    """
    cols = ["my_id", "from_id", "to_id", "rx1", "rx2", "rx3", "rx1_n", "tx2_n", "tx3_n", "range_n", "std", "timestamp_n"]
    seen: dict[tuple[int, int, int, float], tuple[float, float, float, float]] = {}
    dropped = {"outside_span": 0, "not_a_listener": 0, "invalid": 0, "clock_ratio": 0, "triangle": 0}
    n_logged, n_dup, any_file = 0, 0, False
    for name, _ in robots:
        p = src / name / "uwb_passive.csv"
        if not p.is_file():
            continue
        any_file = True
        used_files.append(p)
        c = read_csv(p, cols)
        rdiff, ratio = _passive_rdiff(c)
        for i in range(len(c["timestamp_n"])):
            n_logged += 1
            ids = (c["my_id"][i], c["from_id"][i], c["to_id"][i])
            if not all(math.isfinite(x) and x == int(x) for x in ids):
                raise DatasetError(f"{p}: row {i + 2}: my_id/from_id/to_id not integers {ids}")
            lt, it, rt = (int(x) for x in ids)
            for tg in (lt, it, rt):
                if tg not in tag_owner:
                    raise DatasetError(f"{p}: row {i + 2}: unknown tag/anchor id {tg} (tags.yaml/anchors.yaml)")
            ts = float(c["timestamp_n"][i])
            if not (math.isfinite(ts) and t_start < ts <= t_end):
                dropped["outside_span"] += 1
                continue
            if tag_owner[lt] >= ANCHOR_NODE_OFFSET or lt in (it, rt):
                dropped["not_a_listener"] += 1
                continue
            z, sd, rng = float(rdiff[i]), float(c["std"][i]), float(c["range_n"][i])
            if not (math.isfinite(z) and math.isfinite(rng) and rng > 0):
                dropped["invalid"] += 1
                continue
            if abs(float(ratio[i]) - 1.0) > PASSIVE_MAX_SKEW:
                dropped["clock_ratio"] += 1
                continue
            sd = sd if math.isfinite(sd) and sd > 0 else sigma_nominal
            if abs(z) > rng + 3 * sd:
                dropped["triangle"] += 1
                continue
            key = (lt, it, rt, ts)
            if key in seen:
                n_dup += 1
                if abs(seen[key][0] - z) > 1e-9:
                    raise DatasetError(f"{p}: row {i + 2}: passive row {key} also logged by another robot with a different value")
                continue
            seen[key] = (z, sd, rng, float(ratio[i]))
    if not any_file:
        return None
    levers = {n.id: n.tags for n in nodes}
    rows = []
    for (lt, it, rt, ts), (z, sd, _, _) in seen.items():
        pl, pi, pr = (_tag_point(truth_fn, anchors, levers, tag_owner[x], x, ts) for x in (lt, it, rt))
        err = z - (float(np.linalg.norm(pr - pl)) - float(np.linalg.norm(pi - pl)))
        rows.append((ts, tag_owner[lt], lt, tag_owner[it], it, tag_owner[rt], rt, z, sd, err))
    rows.sort()
    T = np.array(rows, float).reshape(-1, 10)
    faulty = np.abs(T[:, 9]) > 3 * T[:, 8]
    ints = lambda j: T[:, j].astype(np.int64)  # noqa: E731
    tab = {"t": T[:, 0], "node": ints(1), "tag": ints(2), "init": ints(3), "tag_init": ints(4), "resp": ints(5),
           "tag_resp": ints(6), "rdiff": T[:, 7], "sigma": T[:, 8],
           "fault_kind": np.where(faulty, int(FaultKind.NLOS_REAL), int(FaultKind.NONE)).astype(np.int64),
           "fault_err": T[:, 9]}
    e = T[:, 9]
    summary["tdoa"] = {
        "logged_rows": n_logged, "duplicates_removed": n_dup, "kept": int(len(T)), "dropped": dropped,
        "with_anchor": int(((tab["init"] >= ANCHOR_NODE_OFFSET) | (tab["resp"] >= ANCHOR_NODE_OFFSET)).sum()),
        "error_m": ({"median": round(float(np.median(e)), 4),
                     "robust_sigma": round(float(1.4826 * np.median(np.abs(e - np.median(e)))), 4)} if len(e) else None),
        "nlos_real_rows": int(faulty.sum()),
    }
    return tab
