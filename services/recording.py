"""Rerun logging helpers shared by ``swarmnav evaluate`` and the Zenoh monitor service (rerun-sdk 0.41).

Small ``log_*`` functions for one epoch (the live monitor), ``send_*`` bulk versions built on
``rr.send_columns`` (evaluate logs whole runs at once), two named timelines and one default
blueprint. Entity layout (algorithm names as in estimators/registry.py)::

    /swarm/truth/uav<id>            Points3D  truth position (grey, smaller)
    /swarm/anchors                  Points3D  fixed UWB anchors (static; recorded datasets)
    /swarm/<algo>/uav<id>           Points3D  estimate, unlabelled (the trail view shows the last 30 s)
    /labels/<algo>                  Points3D  every UAV's current estimate with its label (latest-at view only)
    /links                          AnnotationContext  the link-class legend: 0 H0 failed, 1 H1 interfered, 2 H2 normal
    /links/<algo>                   LineStrips3D  links of the epoch by class id (H2 green, H1 amber, H0 red)
    /detection/<algo>/H<c>          Scalars   links classified H<c> in the epoch
    /errors/<algo>/pos_3d/uav1      Scalars   3-D position error of UAV 1 (m)
    /errors/<algo>/pos_3sigma/uav1  Scalars   3·sqrt(trace P) of UAV 1: the estimator's own 3σ bound (m)
    /errors/<algo>/pos_3d/swarm     Scalars   RMS over UAVs of the 3-D position error (m)
    /errors/<algo>/pos_3sigma/swarm Scalars   3·sqrt(mean over UAVs of trace P) (m)
    /errors/<algo>/vel_3d/swarm     Scalars   RMS over UAVs of the 3-D velocity error (m/s)
    /events                         TextLog   dropouts, rejoins, outages, lost data, rejects (as sentences, with levels)

Timelines: ``sim_time`` (duration, seconds of simulation time) and ``epoch`` (sequence).
"""

from __future__ import annotations

from dataclasses import dataclass

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
    "atvfg_paper": (23, 190, 207),
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


def detection_path(algo: str) -> str:
    return f"/detection/{algo}"


def labels_path(algo: str) -> str:
    return f"/labels/{algo}"


CLASS_LABELS = {0: "H0 failed (dropped)", 1: "H1 interfered (down-weighted)", 2: "H2 normal"}
EVENT_LEVELS = {"dropout": "WARN", "process_died": "ERROR", "bus_outage": "ERROR", "epochs_lost": "ERROR",
                "monitor_lost": "ERROR", "sensor_sim_lost": "ERROR", "rejected_messages": "WARN",
                "rejoin": "INFO", "rebootstrap": "INFO", "bus_restored": "INFO", "scheduled_kill": "INFO",
                "scheduled_restart": "INFO"}


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


LIVE_MEMORY_LIMIT = "512MiB"  # what a live server keeps for viewers that connect late (oldest dropped first)


def live_url(host: str, port: int) -> str:
    """The address a Rerun viewer opens to follow a live run."""
    return f"rerun+http://{host}:{int(port)}/proxy"


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

    def __init__(self, seg_dir, final_path, recording_id: str | None = None, blueprint: rrb.Blueprint | None = None,
                 live: tuple[str, int] | None = None):
        from pathlib import Path

        self.dir, self.final = Path(seg_dir), Path(final_path)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        self.stream = self.rec.binary_stream()
        if live is not None:
            # the live view: the same log calls also go to a gRPC server that viewers connect to
            # (``rerun rerun+http://HOST:PORT/proxy``); it buffers what was logged for late viewers
            self.rec.set_sinks(self.stream, rr.GrpcServerSink(bind_ip=live[0], port=int(live[1]),
                                                              server_memory_limit=LIVE_MEMORY_LIMIT))
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
        self.close_start()()

    def close_start(self):
        """Commit the last segment and start merging (a ``rerun rrd merge`` process); returns the
        function that waits for the merge to end (and raises if it failed). The caller may work in
        the meantime: the monitor draws its figures while the merge runs on the other core."""
        self.commit()
        return merge_segments(self.dir, self.final, wait=False)


def merge_segments(seg_dir, final_path, wait: bool = True):
    """``rerun rrd merge`` every ``seg_*.rrd`` of ``seg_dir`` into ``final_path`` (atomically), then
    remove the segments. Returns the number merged; with ``wait=False`` the merge is started and a
    function is returned that waits for it, finishes the same way and returns that number."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    segs = sorted(Path(seg_dir).glob("seg_*.rrd"))
    proc = None
    tmp = str(final_path) + ".tmp"
    if segs:
        cli = Path(sys.executable).with_name("rerun")
        proc = subprocess.Popen([str(cli), "rrd", "merge", *map(str, segs), "-o", tmp], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)

    def finish() -> int:
        if proc is not None:
            _, err = proc.communicate()
            if proc.returncode != 0:
                raise RuntimeError(f"rerun rrd merge failed: {err.strip()[-500:]}")
            os.replace(tmp, final_path)
        shutil.rmtree(seg_dir, ignore_errors=True)
        return len(segs)

    return finish() if wait else finish


def close_recording(rec: rr.RecordingStream) -> None:
    """Flush and write the footer (call on normal exit and on SIGTERM)."""
    rec.flush()
    rec.disconnect()


@dataclass(frozen=True)
class ViewSpec:
    """One view of the default blueprint: what it shows (entity queries: exact paths or a trailing
    ``/**``, never another ``*``) and the component its entities must carry to draw anything.
    tests/test_recording_blueprint.py holds every view of a real recording to having data."""

    kind: str  # "3d" | "timeseries" | "textlog"
    name: str
    contents: tuple[str, ...]
    data: str  # e.g. "Scalars:scalars": the component an entity needs to show in this view
    trail: bool = False  # 3-D: the last TRAIL_S seconds instead of the latest position


def blueprint_views(algos: list[str], link_algos: list[str] | None = None, anchors: bool = False) -> list[ViewSpec]:
    """The default layout: the swarm now (labelled) and with 30 s trails, link classes per
    algorithm (with the fixed UWB anchors when the data has any), error series with the
    estimator's own 3σ bound, link classes per epoch, events."""
    link_algos = list(algos if link_algos is None else link_algos)
    v = [ViewSpec("3d", "swarm now: truth (grey) vs estimates, labelled", ("/swarm/**", "/labels/**"), "Points3D:positions"),
         ViewSpec("3d", f"last {TRAIL_S:g} s: truth (grey) vs estimates", ("/swarm/**",), "Points3D:positions", trail=True)]
    v += [ViewSpec("3d", f"links {a}: H2 normal / H1 interfered / H0 failed", (links_path(a), "/swarm/truth/**") + (("/swarm/anchors",) if anchors else ()),
                   "LineStrips3D:strips") for a in link_algos]
    ts = [("swarm 3-D position error and 3σ bound (m)", ("pos_3d", "pos_3sigma"), "swarm"),
          ("UAV 1 3-D position error and 3σ bound (m)", ("pos_3d", "pos_3sigma"), "uav1"),
          ("swarm 3-D velocity error (m/s)", ("vel_3d",), "swarm")]
    v += [ViewSpec("timeseries", name, tuple(error_path(a, q, who) for a in algos for q in qs), "Scalars:scalars")
          for name, qs, who in ts]
    if link_algos:
        v.append(ViewSpec("timeseries", "link classifications per epoch", tuple(f"{detection_path(a)}/**" for a in link_algos),
                          "Scalars:scalars"))
    v.append(ViewSpec("textlog", "events", ("/events",), "TextLog:text"))
    return v


def dataset_has_anchors(dataset_dir) -> bool:
    """Whether a dataset directory's meta.json lists fixed UWB anchors (they get drawn)."""
    import json
    from pathlib import Path

    try:
        meta = json.loads((Path(dataset_dir) / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    return any(n.get("kind") == "anchor" for n in meta.get("nodes", []))


def default_blueprint(algos: list[str], link_algos: list[str] | None = None, anchors: bool = False) -> rrb.Blueprint:
    """The blueprint built from :func:`blueprint_views`: 3-D views left, series and events right."""
    trail = rrb.VisibleTimeRange(TIMELINE_T, start=rrb.TimeRangeBoundary.cursor_relative(seconds=-TRAIL_S),
                                 end=rrb.TimeRangeBoundary.cursor_relative(seconds=0.0))

    def view(spec: ViewSpec):
        if spec.kind == "3d":
            return rrb.Spatial3DView(origin="/", contents=list(spec.contents), name=spec.name,
                                     **({"time_ranges": [trail]} if spec.trail else {}))
        if spec.kind == "timeseries":
            return rrb.TimeSeriesView(origin="/", contents=list(spec.contents), name=spec.name)
        return rrb.TextLogView(origin="/", contents=list(spec.contents), name=spec.name)

    views = blueprint_views(algos, link_algos, anchors)
    spatial = [view(x) for x in views if x.kind == "3d"]
    right = [view(x) for x in views if x.kind != "3d"]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Tabs(*spatial[:2], name="swarm"), rrb.Tabs(*spatial[2:], name="link classification")
                         if spatial[2:] else right.pop(), row_shares=[3, 2]),
            rrb.Vertical(*right),
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


def log_styles(algos: list[str], rec: rr.RecordingStream | None = None, link_algos: list[str] | None = None) -> None:
    """Static series colours/names (every series named here receives data): error series per
    algorithm (3σ bounds dashed-looking: thinner, lighter), link-class counts, and the link-class
    legend (an AnnotationContext: class id -> label and colour)."""
    for a in algos:
        c = algo_color(a)
        light = tuple(int(x + (255 - x) * 0.5) for x in c)
        for who in ("uav1", "swarm"):
            rr.log(error_path(a, "pos_3d", who), rr.SeriesLines(colors=[c], names=[f"{a} error"]), static=True, recording=rec)
            rr.log(error_path(a, "pos_3sigma", who), rr.SeriesLines(colors=[light], names=[f"{a} 3σ"], widths=[0.75]),
                   static=True, recording=rec)
        rr.log(error_path(a, "vel_3d", "swarm"), rr.SeriesLines(colors=[c], names=[a]), static=True, recording=rec)
    for a in (algos if link_algos is None else link_algos):
        for cls, label in CLASS_LABELS.items():
            rr.log(f"{detection_path(a)}/H{cls}", rr.SeriesLines(colors=[CLASS_COLORS[cls]], names=[f"{a} {label}"]),
                   static=True, recording=rec)
    rr.log("/links", rr.AnnotationContext([rr.AnnotationInfo(id=c, label=lbl, color=CLASS_COLORS[c])
                                           for c, lbl in CLASS_LABELS.items()]), static=True, recording=rec)


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


def log_event(kind: str, uav: int, t: float, text: str | None = None, rec: rr.RecordingStream | None = None,
              level: str | None = None) -> None:
    """One event as a sentence, at a level by kind (ERROR: data lost; WARN: a fault; INFO: recovery)."""
    who = f" of UAV {uav}" if uav else ""
    rr.log("/events", rr.TextLog(text or f"t = {t:g} s: {kind.replace('_', ' ')}{who}", level=level or EVENT_LEVELS.get(kind, "WARN")),
           recording=rec)


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
        rr.log(path, rr.Points3D.from_fields(radii=[radius], colors=[algo_color(algo)], show_labels=False),
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
    rr.log(path, rr.LineStrips3D.from_fields(radii=[radius], show_labels=False), static=True, recording=rec)
    # class ids resolve through the AnnotationContext at /links (label + colour: the legend)
    ids = np.clip(np.asarray(classes, int), 0, 2).astype(np.uint16)
    cols = rr.LineStrips3D.columns(strips=segments, class_ids=ids).partition(np.asarray(counts, int))
    rr.send_columns(path, indexes=_indexes(t, k), columns=cols, recording=rec)
    # link classifications per epoch, one series per class
    kk = np.repeat(np.arange(len(counts)), np.asarray(counts, int))
    for c in range(3):
        n = np.bincount(kk[ids == c], minlength=len(counts)).astype(float)
        send_series(f"{detection_path(algo)}/H{c}", t, k, n, rec=rec)


def send_labels(algo: str, t: np.ndarray, k: np.ndarray, pos: np.ndarray, uavs: list[int],
                rec: rr.RecordingStream | None = None) -> None:
    """The current position of every UAV with its label (pos: K x N x 3), one row per epoch; shown
    only by the latest-at 3-D view, so a trail never carries labels."""
    pos = np.asarray(pos, float)
    ok = np.all(np.isfinite(pos), axis=2)
    if not ok.any():
        return
    rows = [i for i in range(len(t)) if ok[i].any()]
    pts = np.concatenate([pos[i][ok[i]] for i in rows])
    lbl = [f"{algo} {u}" for i in rows for u, o in zip(uavs, ok[i]) if o]
    cols = rr.Points3D.columns(positions=pts, labels=lbl).partition([int(ok[i].sum()) for i in rows])
    rr.send_columns(labels_path(algo), indexes=_indexes(np.asarray(t)[rows], np.asarray(k)[rows]), columns=cols, recording=rec)
