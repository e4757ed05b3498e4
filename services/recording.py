"""Rerun logging helpers shared by ``swarmnav evaluate`` and the Zenoh monitor service (rerun-sdk 0.41).

Small ``log_*`` functions for one epoch (the live monitor), ``send_*`` bulk versions built on
``rr.send_columns`` (evaluate logs whole runs at once), two named timelines and one default
blueprint. Entity layout (algorithm names as in DESIGN.md §4)::

    /swarm/truth/uav<id>          Points3D  truth position
    /swarm/anchors                Points3D  fixed UWB anchors (static; recorded datasets)
    /swarm/<algo>/uav<id>         Points3D  estimate (trails: the 3-D view shows the last 30 s)
    /links/<algo>                 LineStrips3D  links of the epoch coloured by class (H2 green, H1 amber, H0 red)
    /errors/<algo>/pos_3d/uav1    Scalars   3-D position error of UAV 1 (m)
    /errors/<algo>/pos_3d/swarm   Scalars   RMS over UAVs of the 3-D position error (m)
    /errors/<algo>/vel_3d/swarm   Scalars   RMS over UAVs of the 3-D velocity error (m/s)
    /events                       TextLog   kills, rejoins, detections, ...

Timelines: ``sim_time`` (duration, seconds of simulation time) and ``epoch`` (sequence).
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

APP_ID = "swarmnav"
TIMELINE_T = "sim_time"
TIMELINE_EPOCH = "epoch"
TRAIL_S = 30.0

ALGO_COLORS: dict[str, tuple[int, int, int]] = {
    "truth": (230, 230, 230),
    "atvfg": (31, 119, 180),
    "fg": (255, 127, 14),
    "fkf": (148, 103, 189),
    "ins": (140, 86, 75),
    "central": (44, 160, 44),
}
CLASS_COLORS = {0: (220, 40, 40), 1: (255, 176, 0), 2: (60, 180, 75)}  # H0 failed, H1 interfered, H2 normal


def algo_color(algo: str) -> tuple[int, int, int]:
    if algo in ALGO_COLORS:
        return ALGO_COLORS[algo]
    h = sum(map(ord, algo))
    return (60 + h * 37 % 180, 60 + h * 91 % 180, 60 + h * 53 % 180)


def uav_path(algo: str, uav: int) -> str:
    return f"/swarm/{algo}/uav{int(uav)}"


def links_path(algo: str) -> str:
    return f"/links/{algo}"


def error_path(algo: str, quantity: str, who: str) -> str:
    return f"/errors/{algo}/{quantity}/{who}"


# -- recordings ---------------------------------------------------------------------------------


def open_recording(path, recording_id: str | None = None, blueprint: rrb.Blueprint | None = None) -> rr.RecordingStream:
    """A recording stream writing to ``path`` (.rrd). Send the blueprint from one process only."""
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    rec.save(str(path), default_blueprint=blueprint)
    return rec


class FileRecording:
    """A recording written to one .rrd by a file sink: valid once closed (``swarmnav evaluate``,
    ``swarmnav report``)."""

    def __init__(self, path, recording_id: str | None = None, blueprint: rrb.Blueprint | None = None):
        self.path = path
        self.rec = open_recording(path, recording_id, blueprint)

    def commit(self) -> None:
        self.rec.flush()

    def close(self) -> None:
        close_recording(self.rec)


class SegmentedRecording:
    """A live recording that is valid on disk whatever happens to the process (the monitor's).

    A file sink writes the .rrd footer only when it closes, so a SIGKILLed writer leaves a file
    that ``rerun rrd verify`` rejects. Here every :meth:`commit` (one per epoch) encodes what was
    logged since the last one as a complete stream (header, data, footer) and writes it atomically
    (temporary file + rename) to ``<dir>/seg_<n>.rrd``: every file on disk always verifies, and a
    crash loses at most the epoch in hand. :meth:`close` merges the segments into the final .rrd
    with ``rerun rrd merge`` (blueprint kept) and removes them. (Several complete streams in ONE
    file do not verify in rerun 0.41: "More than one RRD manifest".)
    """

    def __init__(self, seg_dir, final_path, recording_id: str | None = None, blueprint: rrb.Blueprint | None = None):
        from pathlib import Path

        self.dir, self.final = Path(seg_dir), Path(final_path)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        self.stream = self.rec.binary_stream()
        if blueprint is not None:
            self.rec.send_blueprint(blueprint)
        self.n = 0

    def commit(self) -> None:
        import os

        b = self.stream.read(flush=True)
        if not b:
            return
        seg = self.dir / f"seg_{self.n:06d}.rrd"
        tmp = seg.with_suffix(".rrd.tmp")
        with open(tmp, "wb") as f:
            f.write(b)
        os.replace(tmp, seg)
        self.n += 1

    def close(self) -> None:
        self.commit()
        merge_segments(self.dir, self.final)


def merge_segments(seg_dir, final_path) -> int:
    """``rerun rrd merge`` every ``seg_*.rrd`` of ``seg_dir`` into ``final_path`` (atomically), then
    remove the segments. Returns the number merged."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    segs = sorted(Path(seg_dir).glob("seg_*.rrd"))
    if segs:
        cli = Path(sys.executable).with_name("rerun")
        tmp = str(final_path) + ".tmp"
        r = subprocess.run([str(cli), "rrd", "merge", *map(str, segs), "-o", tmp], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"rerun rrd merge failed: {r.stderr.strip()[-500:]}")
        os.replace(tmp, final_path)
    shutil.rmtree(seg_dir, ignore_errors=True)
    return len(segs)


def close_recording(rec: rr.RecordingStream) -> None:
    """Flush and write the footer (call on normal exit and on SIGTERM)."""
    rec.flush()
    rec.disconnect()


def default_blueprint(algos: list[str]) -> rrb.Blueprint:
    """3-D truth vs estimates with trails, link graph, error time series, event log."""
    trail = rrb.VisibleTimeRange(TIMELINE_T, start=rrb.TimeRangeBoundary.cursor_relative(seconds=-TRAIL_S),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0))
    link_views = [rrb.Spatial3DView(origin="/", contents=[f"/links/{a}/**", "/swarm/truth/**", "/swarm/anchors"],
                                    name=f"links {a}")
                  for a in algos]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="/swarm", name="truth vs estimates (30 s trails)", time_ranges=[trail]),
                rrb.Tabs(*link_views, name="link classification") if link_views else rrb.TextLogView(origin="/events"),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/errors", contents="/errors/*/pos_3d/swarm", name="swarm 3-D position error (m)"),
                rrb.TimeSeriesView(origin="/errors", contents="/errors/*/pos_3d/uav1", name="UAV 1 3-D position error (m)"),
                rrb.TimeSeriesView(origin="/errors", contents="/errors/*/vel_3d/swarm", name="swarm 3-D velocity error (m/s)"),
                rrb.TextLogView(origin="/events", name="events"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


def point_radius(*positions) -> float:
    """Radius (m) of a UAV point in the 3-D view: 1 % of the scene's extent (the diagonal of the
    bounding box of all ``positions``: arrays or lists of any shape (..., 3), NaN ignored), between
    2 cm and 2 m — the paper's km-scale swarm keeps 2 m, an indoor flight a few metres across gets
    a few cm. Truth points are drawn at 0.75 ×, link lines at 0.15 × this."""
    p = np.concatenate([np.asarray(x, float).reshape(-1, 3) for x in positions] or [np.zeros((0, 3))])
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        return 2.0
    return float(np.clip(0.01 * np.linalg.norm(p.max(axis=0) - p.min(axis=0)), 0.02, 2.0))


def log_anchors(anchors: dict[int, np.ndarray], radius: float, rec: rr.RecordingStream | None = None) -> None:
    """The fixed UWB anchors (node id -> ENU position, m) as static grey points."""
    if not anchors:
        return
    ids = sorted(anchors)
    rr.log("/swarm/anchors", rr.Points3D([np.asarray(anchors[i], float) for i in ids], radii=[radius],
                                         colors=[(128, 128, 128)], labels=[f"anchor {i}" for i in ids]),
           static=True, recording=rec)


# -- per-epoch logging (live monitor) -------------------------------------------------------------


def set_epoch(k: int, t: float, rec: rr.RecordingStream | None = None) -> None:
    rr.set_time(TIMELINE_EPOCH, sequence=int(k), recording=rec)
    rr.set_time(TIMELINE_T, duration=float(t), recording=rec)


def log_styles(algos: list[str], rec: rr.RecordingStream | None = None) -> None:
    """Static series colours/names for every algorithm's error series."""
    for a in algos:
        for q in ("pos_3d", "vel_3d"):
            for who in ("uav1", "swarm"):
                rr.log(error_path(a, q, who), rr.SeriesLines(colors=[algo_color(a)], names=[a]), static=True, recording=rec)


def log_position(algo: str, uav: int, pos, rec: rr.RecordingStream | None = None, radius: float = 2.0) -> None:
    """One UAV's estimated (or, with algo "truth", true) position at the current time."""
    rr.log(uav_path(algo, uav), rr.Points3D([np.asarray(pos, float)], radii=[radius], colors=[algo_color(algo)],
                                            labels=[f"{uav}"]), recording=rec)


def log_links(algo: str, positions: dict[int, np.ndarray], links, rec: rr.RecordingStream | None = None,
              radius: float = 0.3) -> None:
    """The epoch's links as segments between the two UAVs' positions, coloured by class.

    ``links``: iterable of (a, b, cls) with cls 0/1/2 (H0/H1/H2)."""
    strips, colors = [], []
    for a, b, c in links:
        if a in positions and b in positions:
            strips.append(np.array([positions[a], positions[b]], float))
            colors.append(CLASS_COLORS.get(int(c), (128, 128, 128)))
    rr.log(links_path(algo), rr.LineStrips3D(strips, colors=colors, radii=[radius]), recording=rec)


def log_error(algo: str, quantity: str, who: str, value: float, rec: rr.RecordingStream | None = None) -> None:
    rr.log(error_path(algo, quantity, who), rr.Scalars([float(value)]), recording=rec)


def log_event(kind: str, uav: int, t: float, text: str | None = None, rec: rr.RecordingStream | None = None,
              level: str = "WARN") -> None:
    rr.log("/events", rr.TextLog(text or f"t={t:g} s: {kind} UAV {uav}", level=level), recording=rec)


# -- bulk logging (whole runs) ---------------------------------------------------------------------


def _indexes(t: np.ndarray, k: np.ndarray):
    return [rr.TimeColumn(TIMELINE_T, duration=np.asarray(t, float)), rr.TimeColumn(TIMELINE_EPOCH, sequence=np.asarray(k, np.int64))]


def send_positions(algo: str, uav: int, t: np.ndarray, k: np.ndarray, pos: np.ndarray,
                   rec: rr.RecordingStream | None = None, radius: float = 2.0, style: bool = True) -> None:
    """A whole trajectory of one UAV as one point per epoch (NaN epochs skipped); ``style=False``
    skips the static style (already logged by an earlier call for the same entity)."""
    pos = np.asarray(pos, float)
    ok = np.all(np.isfinite(pos), axis=1)
    if not ok.any():
        return
    path = uav_path(algo, uav)
    if style:
        rr.log(path, rr.Points3D.from_fields(radii=[radius], colors=[algo_color(algo)], labels=[str(uav)]),
               static=True, recording=rec)
    rr.send_columns(path, indexes=_indexes(np.asarray(t)[ok], np.asarray(k)[ok]),
                    columns=rr.Points3D.columns(positions=pos[ok]), recording=rec)


def send_series(path: str, t: np.ndarray, k: np.ndarray, values: np.ndarray, rec: rr.RecordingStream | None = None) -> None:
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if not ok.any():
        return
    rr.send_columns(path, indexes=_indexes(np.asarray(t)[ok], np.asarray(k)[ok]),
                    columns=rr.Scalars.columns(scalars=v[ok]), recording=rec)


def send_links(algo: str, t: np.ndarray, k: np.ndarray, segments: np.ndarray, classes: np.ndarray,
               counts: np.ndarray, rec: rr.RecordingStream | None = None, radius: float = 0.3) -> None:
    """Link graph over time: ``segments`` (M,2,3) of all epochs concatenated in epoch order, their
    classes (M,) and the number of segments of each epoch ``counts`` (len(t),)."""
    segments = np.asarray(segments, float).reshape(-1, 2, 3)
    if len(segments) == 0:
        return
    path = links_path(algo)
    rr.log(path, rr.LineStrips3D.from_fields(radii=[radius]), static=True, recording=rec)
    lut = np.array([CLASS_COLORS.get(c, (128, 128, 128)) for c in range(3)] + [(128, 128, 128)], np.uint8)
    colors = lut[np.clip(np.asarray(classes, int), 0, 3)]
    cols = rr.LineStrips3D.columns(strips=segments, colors=colors).partition(np.asarray(counts, int))
    rr.send_columns(path, indexes=_indexes(t, k), columns=cols, recording=rec)
