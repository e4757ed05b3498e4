"""Per-robot time series: mocap (positions, attitudes with marker-swap glitches bridged), the PX4
IMU, the rangefinder; the in-flight accelerometer noise; the span every robot covers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from swarmnav.errors import DatasetError

from .constants import HEIGHT_MIN_VALID_M, MAX_TILT_DEG, VIB_SMOOTH_S
from .nodes import Layout
from .readers import compressed_hint, clean_time_series, read_csv, warn

MOCAP_COLS = ["timestamp", "pose.position.x", "pose.position.y", "pose.position.z",
              "pose.orientation.x", "pose.orientation.y", "pose.orientation.z", "pose.orientation.w"]
IMU_COLS = ["timestamp", "angular_velocity.x", "angular_velocity.y", "angular_velocity.z",
            "linear_acceleration.x", "linear_acceleration.y", "linear_acceleration.z"]


@dataclass
class Mocap:
    t: np.ndarray  # (n,) s, strictly increasing
    pos: np.ndarray  # (n, 3) Vicon world [m]
    att: Rotation  # n attitudes, body -> Vicon world (= local ENU)


@dataclass
class Series:
    """Cleaned time series by UAV id."""

    mocap: dict[int, Mocap] = field(default_factory=dict)
    imu: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # t, (n, 6) gyro FLU, accel FLU
    height: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # t, height - bias [m]


@dataclass
class Span:
    """The dataset's time span: epochs 0..n_epochs over (t_start, t_end]."""

    t_start: float
    n_epochs: int
    duration: float
    t_end: float


def read_series(src: Path, robots: list[tuple[str, int]], layout: Layout, used_files: list[Path], summary: dict) -> Series:
    """Mocap, IMU and height of every robot; raises the IMU's accel noise density to the in-flight
    vibration level where that is higher (``layout.imu_noise``, shared with the nodes)."""
    s = Series()
    glitches = {}
    for name, uid in robots:
        for f, what in (("mocap.csv", "ground truth: it gives the initial state, the time span and every error figure"),
                        ("imu_px4.csv", "the PX4 IMU every estimator propagates with")):
            if not (src / name / f).is_file():
                raise DatasetError(f"{src / name / f}: missing file{compressed_hint(src / name / f)} — required for every "
                                   f"robot ({what}); restore it from the MILUV download, or remove the folder {name} "
                                   "to import the other robots without it")
        p = src / name / "mocap.csv"
        used_files.append(p)
        s.mocap[uid], g = read_mocap(p, name, summary)
        if g:
            glitches[name] = g
        p = src / name / "imu_px4.csv"
        used_files.append(p)
        c = read_csv(p, IMU_COLS)
        t, c = clean_time_series(c.pop("timestamp"), c, f"{name}/imu_px4.csv", summary)
        check_seconds(t, p, (20.0, 2000.0))
        s.imu[uid] = (t, np.column_stack([c[k] for k in IMU_COLS[1:]]))
        p = src / name / "height.csv"
        if not p.is_file():
            warn(summary, f"{name}/height.csv missing: no altitude for UAV {uid}")
        else:
            used_files.append(p)
            s.height[uid] = read_height(p, name, layout.height_bias.get(name), summary)
        if uid in s.height and len(s.height[uid][0]) > 100:
            noise = layout.imu_noise[uid]
            dens = accel_in_flight(s.imu[uid], s.height[uid], name, noise.accel_noise_density, summary)
            if dens > noise.accel_noise_density:
                noise.accel_noise_density = dens
    if glitches:
        summary["mocap_attitude_glitches_interpolated"] = glitches
    return s


def read_mocap(p: Path, name: str, summary: dict) -> tuple[Mocap, dict | None]:
    """One robot's mocap; attitudes tilted more than MAX_TILT_DEG (marker swaps: body z-axis far
    from world up) replaced by slerp between their good neighbours. Returns the glitch summary."""
    c = read_csv(p, MOCAP_COLS)
    # mocap dropouts: MILUV writes the pose as zeros while Vicon loses the body (the devkit's
    # get_mocap_splines drops the same rows): gaps, bridged by interpolation like any other
    pn = np.sqrt(sum(c[k] ** 2 for k in MOCAP_COLS[1:4]))
    qn = np.sqrt(sum(c[k] ** 2 for k in MOCAP_COLS[4:8]))
    lost = (pn < 1e-6) | (qn < 1e-6)
    if lost.any():
        c = {k: v[~lost] for k, v in c.items()}
        warn(summary, f"{name}/mocap.csv: {int(lost.sum())} rows with a zero pose (mocap dropout) dropped, "
                      "the truth interpolated across them")
        summary.setdefault("mocap_dropout_rows", {})[name] = int(lost.sum())
    t, c = clean_time_series(c.pop("timestamp"), c, f"{name}/mocap.csv", summary)
    check_seconds(t, p, (10.0, 1000.0))
    pos = np.column_stack([c["pose.position.x"], c["pose.position.y"], c["pose.position.z"]])
    q = np.column_stack([c["pose.orientation.x"], c["pose.orientation.y"], c["pose.orientation.z"], c["pose.orientation.w"]])
    qn = np.linalg.norm(q, axis=1)
    if np.any(qn < 0.5):
        raise DatasetError(f"{p}: quaternion with norm {qn.min():.3g} (expected unit quaternions x,y,z,w)")
    att = Rotation.from_quat(q)  # ROS (x, y, z, w) = scipy's order
    bad = att.as_matrix()[:, 2, 2] < math.cos(math.radians(MAX_TILT_DEG))
    if bad.sum() > len(bad) - 2:
        raise DatasetError(f"{p}: {int(bad.sum())} of {len(bad)} mocap attitudes tilted > {MAX_TILT_DEG} deg — not z-up?")
    if not bad.any():
        return Mocap(t, pos, att), None
    idx = np.flatnonzero(bad)
    good = Slerp(t[~bad], att[~bad])
    fixed = att.as_quat()
    fixed[bad] = good(np.clip(t[bad], t[~bad][0], t[~bad][-1])).as_quat()
    glitch = {"samples": int(bad.sum()), "t_first": round(float(t[idx[0]]), 3), "t_last": round(float(t[idx[-1]]), 3)}
    return Mocap(t, pos, Rotation.from_quat(fixed)), glitch


def read_height(p: Path, name: str, bias, summary: dict) -> tuple[np.ndarray, np.ndarray]:
    """Rangefinder minus the robot's bias (config/height/bias.yaml); readings at the sensor floor dropped."""
    c = read_csv(p, ["timestamp", "range"])
    t, c = clean_time_series(c.pop("timestamp"), c, f"{name}/height.csv", summary)
    try:
        hb = float(bias)
    except (TypeError, ValueError):
        raise DatasetError(f"config/height/bias.yaml: no numeric bias for {name} (got {bias!r})") from None
    h = c["range"]
    valid = h > HEIGHT_MIN_VALID_M
    summary.setdefault("height_dropped_at_sensor_floor", {})[name] = int((~valid).sum())
    return t[valid], h[valid] - hb


def accel_in_flight(imu: tuple[np.ndarray, np.ndarray], height: tuple[np.ndarray, np.ndarray], name: str,
                    allan_density: float, summary: dict) -> float:
    """Accelerometer white-noise density [m/s^2/sqrt(Hz)] in flight (while the rangefinder reads
    airborne): the signal minus its VIB_SMOOTH_S moving average, RMS std / sqrt(rate)."""
    ti, acc = imu[0], imu[1][:, 3:6]
    air = (ti >= height[0][0]) & (ti <= height[0][-1])
    rate = 1.0 / float(np.median(np.diff(ti)))
    nwin = max(3, int(round(VIB_SMOOTH_S * rate)))
    kern = np.ones(nwin) / nwin
    hf = np.column_stack([acc[:, j] - np.convolve(acc[:, j], kern, "same") for j in range(3)])[air][nwin:-nwin]
    sd = float(np.sqrt(np.mean(np.var(hf, axis=0))))
    dens = sd / math.sqrt(rate)
    summary.setdefault("accel_in_flight", {})[name] = {"vibration_std_mps2": round(sd, 3), "density": round(dens, 4),
                                                      "allan_density": allan_density}
    return dens


def check_seconds(t: np.ndarray, p: Path, rate_hz: tuple[float, float]) -> None:
    """MILUV timestamps are seconds from the start of the recording: refuse other units (ns, us, ms —
    an older devkit export) or an absolute clock, naming the file, instead of building a span of
    years."""
    med = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    lo, hi = rate_hz
    if not (1.0 / hi <= med <= 1.0 / lo):
        raise DatasetError(f"{p}: median time step {med:.6g} (a {1 / med if med > 0 else float('inf'):.3g} Hz sensor "
                           f"in seconds, expected {lo:g}-{hi:g} Hz): the 'timestamp' column must be in seconds "
                           "(MILUV's unit); convert ns/us/ms first")
    if t[-1] - t[0] > MAX_RECORDING_S:
        raise DatasetError(f"{p}: timestamps span {t[-1] - t[0]:.0f} s (more than {MAX_RECORDING_S:.0f} s): "
                           "not one MILUV experiment in seconds")


MAX_RECORDING_S = 4 * 3600.0
LATE_START_WARN_S = 1.0  # a robot whose data start/end this much inside the span of another: say so


def time_span(series: Series, epoch_dt: float, src: Path, summary: dict) -> Span:
    """From the first time every robot has mocap and IMU (rounded up to 10 ms) to the last, in whole
    epochs. Robots that start later or stop earlier than others shorten everyone's span: said in a
    warning."""
    per = {u: (max(series.mocap[u].t[0], series.imu[u][0][0]), min(series.mocap[u].t[-1], series.imu[u][0][-1]))
           for u in series.mocap}
    first = max(a for a, _ in per.values())
    last = min(b for _, b in per.values())
    desc = ", ".join(f"ifo{u:03d} {a:.3f}-{b:.3f} s" for u, (a, b) in sorted(per.items()))
    if last - first < 2 * epoch_dt:
        raise DatasetError(f"{src}: the robots' mocap and IMU (each robot: the time both cover) do not overlap for "
                           f"two epochs of {epoch_dt} s: {desc}. MILUV files share one time base (seconds from the "
                           "start of the recording); check that every robot's files come from this experiment")
    for u, (a, b) in sorted(per.items()):
        if first - a > LATE_START_WARN_S or b - last > LATE_START_WARN_S:
            warn(summary, f"robots cover different times ({desc}): the dataset is the common span "
                          f"{first:.3f}-{last:.3f} s; data of a robot outside it are not used")
            break
    t_start = math.ceil(first * 100.0 - 1e-9) / 100.0
    n_epochs = int(math.floor((last - t_start) / epoch_dt + 1e-9))
    if n_epochs < 2:
        raise DatasetError(f"{src}: robots' mocap and IMU overlap for only {last - first:.3f} s ({desc})")
    duration = round(n_epochs * epoch_dt, 9)
    summary.update(t_start=t_start, duration_s=round(duration, 9), n_epochs=n_epochs, epoch_dt_s=epoch_dt)
    return Span(t_start, n_epochs, duration, t_start + duration)
