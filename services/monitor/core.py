"""What the monitor does with what it receives, without Zenoh: store, record, score, report.

:class:`MonitorCore` is fed validated messages (estimates, clock) and events, by the live monitor
(services/monitor/monitor.py) or by a replay of its journal (``swarmnav report RUN_DIR``), and
writes the same outputs either way: the Rerun recording (services/recording.py), report.json /
report.md (swarmnav.report, the in-process evaluation's metrics) and estimates.npz.

Completeness (report.json top level): every UAV is expected to estimate every epoch except inside
a *scheduled* kill window (``--kill ID@T`` .. ``--restart ID@T``); ``complete`` is true only when every
expected estimate arrived, the run reached its end (the clock's ``done``) and no epoch was lost.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from services.settings import settings_for_dataset
from swarmnav.dataset import Dataset
from swarmnav.evaluation import RunResult, link_labels, truth_at_epochs
from swarmnav.wire import messages as M

from . import journal as J

LINK_ALGOS = ("atvfg", "atvfg_paper", "fg", "fkf")  # the estimators that classify links (ins reports none)
COMMIT_S = 1.0  # the live recording is committed (a valid segment on disk) at most this often
CLOSE_LAG = 10  # epochs: an epoch still missing estimates is closed in the recording this far behind the clock


def excused_epochs(meta, uavs: list[int], kills: list[tuple[int, float]], restarts: list[tuple[int, float]]) -> np.ndarray:
    """K x N bool: epochs a UAV is not expected to estimate (inside a scheduled kill window: from
    the first epoch with t >= T_kill up to the epoch before the first with t >= T_restart)."""
    K = meta.n_epochs()
    t = np.array([meta.epoch_time(k) for k in range(1, K + 1)])
    out = np.zeros((K, len(uavs)), bool)
    for u, tk in kills:
        if u not in uavs:
            continue
        later = [tr for uu, tr in restarts if uu == u and tr > tk]
        tr = min(later) if later else np.inf
        out[(t >= tk - 1e-9) & (t < tr - 1e-9), uavs.index(u)] = True
    return out


class MonitorCore:
    def __init__(self, *, run: str, dataset: Path, seed: int, algo: str, out: Path, sink,
                 kills=(), restarts=(), security: dict | None = None, config_sha256: str | None = None,
                 journal: J.JournalWriter | None = None, log=None):
        from services import recording as R

        self.R, self.sink, self.rec, self.log, self.journal = R, sink, sink.rec, log, journal
        self.run, self.seed, self.algo, self.out = run, seed, algo, Path(out)
        self.ds = Dataset.read(dataset)
        self.meta = self.ds.meta
        self.uavs = self.meta.uav_ids()
        self.col = {u: j for j, u in enumerate(self.uavs)}  # UAV id -> column (list.index on every message cost)
        self.truth = truth_at_epochs(self.ds)
        self.K = self.meta.n_epochs()
        self.kills, self.restarts = [tuple(x) for x in kills], [tuple(x) for x in restarts]
        self.excused = excused_epochs(self.meta, self.uavs, self.kills, self.restarts)
        self.security = security or {"mode": "off", "acl": False}
        self.config_sha256 = config_sha256
        self.res = RunResult.empty(algo, seed, self.uavs, self.truth.t)
        self.links: list[tuple] = []
        # the links of epochs not yet in the recording, by epoch (close_epochs draws them; scanning
        # every link ever received at each close grew with the run: ~300 links per epoch)
        self.links_to_draw: dict[int, list[tuple[int, int, int]]] = {}
        n = len(self.uavs)
        self.extra = {"wait_ms": np.full((self.K, n), np.nan), "bytes": np.full((self.K, n), np.nan)}
        self.inc = np.zeros((self.K, n), np.int64)
        # peers[k-1, j, l]: UAV j's estimate of epoch k used UAV l's states (who is in whose graph)
        self.peers = np.zeros((self.K, n, n), bool)
        self.events: list[dict] = []
        self.rejected: dict[str, int] = {}
        self.lost_epochs: set[int] = set()
        self.t_now = self.meta.t_start
        self.k_now = 0
        self.done = False
        self.last_inc: dict[int, int] = {}
        self.conflicts = 0  # estimates that contradict one already received for the same UAV and epoch
        self.conflicting: set[int] = set()
        # the recording: positions sent per epoch as they close
        self.sent = np.zeros((self.K, n), bool)
        self.logged_k = 0
        self.last_commit = -1e9
        self.styled: set[tuple[str, int]] = set()  # entities whose static style is in the recording
        self.radius = R.point_radius(self.truth.pos, list(self.meta.anchors().values()))
        R.log_styles([algo], rec=self.rec, link_algos=[algo] if algo in LINK_ALGOS else [])
        R.log_anchors(self.meta.anchors(), self.radius, rec=self.rec)
        R.set_epoch(0, self.meta.t_start, rec=self.rec)
        R.log_event("run_started", 0, self.meta.t_start, rec=self.rec, level="INFO",
                    text=f"distributed run {run}: {len(self.uavs)} UAVs, {algo}, security {self.security.get('mode')} "
                         f"(ACL {'on' if self.security.get('acl') else 'off'})")
        # a stopped run must get its report inside the launcher's SIGTERM grace (4 s): whatever the
        # report assembly imports lazily (scipy.stats for NEES bands: ~1-4 s) is loaded now, aside
        self._labels = None
        threading.Thread(target=self._warm_report, name="warm-report", daemon=True).start()

    def _warm_report(self) -> None:
        """Assemble (and discard) the report of two epochs of perfect estimates: every import and
        first-call cost of the report path is paid here, not when the run is stopped."""
        try:
            from swarmnav.assembly import assemble_report
            from swarmnav.evaluation import LINK_DTYPE

            tr, n = self.truth, min(2, self.K)
            r = RunResult.empty(self.algo, self.seed, self.uavs, tr.t[:n])
            r.pos[:], r.vel[:], r.pos_cov[:], r.step_ms[:] = tr.pos[:n], tr.vel[:n], np.eye(3), 1.0
            r.delta_l_m[:], r.delta_h_m[:] = 1.0, 3.0
            r.links = np.zeros(0, LINK_DTYPE)
            t = type(tr)(tr.uavs, tr.t[:n], tr.pos[:n], tr.vel[:n], tr.quat[:n])
            self._labels = link_labels(self.ds)  # the dataset's fault labels, for the real report too
            assemble_report(mode="distributed", meta=self.meta, seeds=[self.seed], runs={self.algo: [r]}, truths=[t],
                            labels=[self._labels[:0]], settings={}, provenance={}, source="dataset")
        except Exception as e:  # only a warm-up: the real report reports its own errors
            if self.log is not None:
                self.log.debug("report warm-up: %s", e)

    # -- inputs ---------------------------------------------------------------------------------
    def event(self, kind: str, uav: int = 0, t: float | None = None, **extra) -> None:
        ev = {"t": float(self.t_now if t is None else t), "kind": kind, "uav": int(uav), **extra}
        self.events.append(ev)
        if self.journal is not None:
            self.journal.event(ev)
        if self.log is not None:
            self.log.info("event %s", ev)
        self.R.set_epoch(max(self.k_now, 0), ev["t"], rec=self.rec)
        self.R.log_event(kind, uav, ev["t"], rec=self.rec)

    def reject(self, topic: str, reason: str) -> None:
        key = f"{topic}:{reason}"
        if key not in self.rejected:
            self.event("rejected_messages", 0, detail=key)
        self.rejected[key] = self.rejected.get(key, 0) + 1
        if self.journal is not None:
            self.journal.event({"t": float(self.t_now), "kind": "_rejected", "uav": 0, "counts": self.rejected})

    def on_clock(self, c: M.ClockMsg, raw: bytes | None = None) -> None:
        if self.journal is not None and raw is not None:
            self.journal.write(J.CLOCK, raw)
        if c.lost:
            a, b = c.lost
            self.lost_epochs.update(range(a, b + 1))
            self.event("epochs_lost", 0, t=self.meta.epoch_time(a), detail=f"epochs {a}-{b} played into a bus outage")
        if c.hold in ("kill", "restart") and c.hold_uav is not None:
            self.event(f"scheduled_{c.hold}", c.hold_uav, t=c.t)
        self.close_epochs(self.closable(c.k))
        self.k_now, self.t_now = max(self.k_now, c.k), c.t
        if c.done:
            self.done = True

    def on_estimate(self, m: M.EstimateMsg, raw: bytes | None = None) -> bool:
        """Store one estimate; False (counted) when it is out of the run's range or a duplicate."""
        if not 1 <= m.k <= self.K or m.uav not in self.col:
            self.reject("estimate", "range")
            return False
        i, j = m.k - 1, self.col[m.uav]
        r = self.res
        if np.isfinite(r.pos[i, j, 0]):
            # a duplicate: recovered by query after an outage (same content; the first one stands), or
            # a second sender with UAV m.uav's identity saying something else: never silently dropped
            if np.abs(np.asarray(m.pos) - r.pos[i, j]).max() > 1e-9:
                self.conflicts += 1
                if m.uav not in self.conflicting:
                    self.conflicting.add(m.uav)
                    self.event("conflicting_estimates", m.uav, t=m.t,
                               detail=f"two different estimates of epoch {m.k}: a second sender holds this UAV's identity")
                self.reject("estimate", "conflict")
            return False
        if self.journal is not None and raw is not None:
            self.journal.write(J.ESTIMATE, raw)
        # the validated message's floats straight into the arrays (what M.msg_to_estimate would
        # give, without building a NodeEstimate and a LinkInfo + LinkClass per link)
        r.pos[i, j], r.vel[i, j], r.pos_cov[i, j] = m.pos, m.vel, np.reshape(m.pos_cov, (3, 3))
        if m.quat is not None:
            r.quat[i, j] = m.quat
        r.step_ms[i, j], r.rounds[i, j] = m.step_ms, m.rounds
        if m.delta_h_m is not None:
            r.delta_h_m[i, j] = m.delta_h_m
        if m.delta_l_m is not None:
            r.delta_l_m[i, j] = m.delta_l_m
        links = [(int(li.other), int(li.cls), M.residual_or_nan(li.residual_m), float(li.weight)) for li in m.links]
        self.links.extend((m.k, m.uav, *li) for li in links)
        if links and m.k > self.logged_k:
            self.links_to_draw.setdefault(m.k, []).extend((m.uav, o, c) for o, c, _, _ in links)
        self.extra["wait_ms"][i, j] = m.wait_ms
        self.extra["bytes"][i, j] = m.bytes_out
        self.inc[i, j] = m.inc
        for key, n in m.rejected.items():  # what the node itself rejected (hostile input it saw)
            full = f"uav{m.uav}/{key}"
            if full not in self.rejected:
                self.event("rejected_messages", m.uav, t=m.t, detail=f"UAV {m.uav} rejected {key}")
            self.rejected[full] = max(self.rejected.get(full, 0), int(n))
        prev = self.last_inc.get(m.uav)
        if prev is not None and m.inc > prev:
            self.event("rebootstrap", m.uav, t=m.t, detail=f"incarnation {m.inc} from epoch {m.k}")
        self.last_inc[m.uav] = max(prev or 0, m.inc)
        for p in m.peers:
            if p in self.col:
                self.peers[i, j, self.col[p]] = True
        return True

    def missing(self, k: int, who: list[int]) -> list[int]:
        """Of ``who``, the UAVs without an estimate of epoch k."""
        got = np.isfinite(self.res.pos[k - 1, :, 0])
        return [u for u in who if u in self.col and not got[self.col[u]]]

    # -- recording -------------------------------------------------------------------------------
    def closable(self, k_clock: int) -> int:
        """The last epoch the recording may close with the clock at ``k_clock``: every epoch up to it
        holds every expected estimate (scheduled kill windows aside), or lies ``CLOSE_LAG`` epochs
        behind the clock (a dead or frozen UAV). Estimates and the clock come on different channels:
        an epoch closed early would miss its late estimates in its swarm error row for good."""
        hard = max(k_clock - CLOSE_LAG, 0)
        hi = min(k_clock - 2, self.K)
        for k in range(max(self.logged_k, hard) + 1, hi + 1):
            if not (np.isfinite(self.res.pos[k - 1, :, 0]) | self.excused[k - 1]).all():
                return k - 1
        return hi

    def close_epochs(self, upto: int, force: bool = False) -> None:
        """Send epochs up to ``upto`` to the recording (positions, truth, error series, links) and
        commit it, at most once per COMMIT_S of wall time unless ``force`` (the journal already
        holds every accepted message; this bounds the recording's cost to ~1 batch a second)."""
        upto = min(upto, self.K)
        if upto <= self.logged_k:
            return
        now = time.monotonic()
        if not force and now - self.last_commit < COMMIT_S:
            return
        self.last_commit = now
        R, a, rec, t, tr = self.R, self.algo, self.rec, self.truth.t, self.truth
        lo, hi = self.logged_k, upto
        ks = np.arange(lo + 1, hi + 1)
        sl = slice(lo, hi)
        pos = self.res.pos[sl]
        have = np.isfinite(pos[..., 0])
        # estimates of every epoch up to hi not yet in the recording (late ones of closed epochs too)
        new = np.isfinite(self.res.pos[:hi, :, 0]) & ~self.sent[:hi]
        kall = np.arange(1, hi + 1)
        for j, u in enumerate(self.uavs):
            m = new[:, j]
            if m.any():
                R.send_positions(a, u, t[:hi][m], kall[m], self.res.pos[:hi][m, j], rec=rec, radius=self.radius,
                                 style=(a, u) not in self.styled)
                self.styled.add((a, u))
            R.send_positions("truth", u, t[sl], ks, tr.pos[sl, j], rec=rec, radius=self.radius * 0.75,
                             style=("truth", u) not in self.styled)
            self.styled.add(("truth", u))
        ep = pos - tr.pos[sl]
        ev = self.res.vel[sl] - tr.vel[sl]
        with np.errstate(invalid="ignore"):
            swarm_p = np.array([np.sqrt(np.mean(np.sum(ep[i][have[i]] ** 2, axis=1))) if have[i].any() else np.nan for i in range(len(ks))])
            swarm_v = np.array([np.sqrt(np.mean(np.sum(ev[i][have[i]] ** 2, axis=1))) if have[i].any() else np.nan for i in range(len(ks))])
        tr3 = np.trace(self.res.pos_cov[sl], axis1=2, axis2=3)  # the estimators' own 3-D position variance
        ok = np.isfinite(swarm_p)
        if ok.any():
            R.send_series(R.error_path(a, "pos_3d", "swarm"), t[sl][ok], ks[ok], swarm_p[ok], rec=rec)
            R.send_series(R.error_path(a, "vel_3d", "swarm"), t[sl][ok], ks[ok], swarm_v[ok], rec=rec)
            with np.errstate(invalid="ignore"):
                R.send_series(R.error_path(a, "pos_3sigma", "swarm"), t[sl][ok], ks[ok], 3 * np.sqrt(np.nanmean(tr3[ok], axis=1)), rec=rec)
        R.send_labels(a, t[sl], ks, pos, self.uavs, rec=rec)
        if 1 in self.uavs:
            j1 = self.uavs.index(1)
            m = have[:, j1]
            if m.any():
                R.send_series(R.error_path(a, "pos_3d", "uav1"), t[sl][m], ks[m], np.linalg.norm(ep[m, j1], axis=1), rec=rec)
                R.send_series(R.error_path(a, "pos_3sigma", "uav1"), t[sl][m], ks[m], 3 * np.sqrt(tr3[m, j1]), rec=rec)
        by_k = {k: self.links_to_draw.pop(k) for k in list(self.links_to_draw) if k <= hi}
        # every link of the epochs in hand whose two ends have an estimate: one segment each, in
        # epoch order and, within an epoch, in arrival order (vectorised: ~300 links an epoch)
        col = self.col
        rows, ju, jo, cls, counts = [], [], [], [], []
        for i, k in enumerate(ks):
            n = 0
            for u, o, c in by_k.get(int(k), []):
                if u in col and o in col and have[i, col[u]] and have[i, col[o]]:
                    rows.append(i)
                    ju.append(col[u])
                    jo.append(col[o])
                    cls.append(c)
                    n += 1
            counts.append(n)
        if rows:
            segs = np.stack([pos[rows, ju], pos[rows, jo]], axis=1)
            R.send_links(a, t[sl], ks, segs, np.array(cls, int), np.array(counts), rec=rec, radius=0.15 * self.radius)
        else:
            for k in ks:
                R.set_epoch(int(k), float(t[k - 1]), rec=rec)
                R.log_links(a, {}, [], rec=rec, radius=0.15 * self.radius)
        self.sent[:hi] |= new
        self.logged_k = hi
        self.sink.commit()

    # -- report ------------------------------------------------------------------------------------
    def completeness(self) -> dict:
        from swarmnav.assembly import completeness

        return completeness({self.algo: [self.res]}, [self.excused], self.done, sorted(self.lost_epochs), self.conflicts)

    def report(self) -> dict:
        from swarmnav import metrics
        from swarmnav.assembly import assemble_report
        from swarmnav.evaluation import LINK_DTYPE
        from swarmnav.report import render_markdown, validate_report

        from services.provenance import dataset_sha256, provenance

        a, r, tr = self.algo, self.res, self.truth
        r.links = np.array(self.links, dtype=LINK_DTYPE) if self.links else np.zeros(0, LINK_DTYPE)
        b, w = self.extra["bytes"], self.extra["wait_ms"]
        comp = self.completeness()
        dist = {"run_id": self.run, "epochs_recorded": comp["epochs_recorded"],
                "missing_estimates": int((~np.isfinite(r.pos[..., 0])).sum()),
                "bytes_out_per_uav_epoch": float(np.nanmean(b)) if np.isfinite(b).any() else None,
                "wait_ms": metrics.percentiles(w, (50, 99)), "monitor_rejected": dict(self.rejected)}
        # the one report assembly, shared with `swarmnav evaluate` (swarmnav.assembly); the settings
        # are the nodes' own (services/uav_node/node.py), the thresholds those the nodes reported
        rep = assemble_report(mode="distributed", meta=self.meta, seeds=[self.seed], runs={a: [r]}, truths=[tr],
                              labels=[self._labels if self._labels is not None else link_labels(self.ds)],
                              settings=settings_for_dataset(self.meta),
                              provenance=provenance(self.config_sha256 or dataset_sha256(self.meta)),
                              source="config" if self.config_sha256 else "dataset", events=self.events,
                              excused=[self.excused], done=self.done, lost_epochs=sorted(self.lost_epochs),
                              conflicts=self.conflicts, rejected=self.rejected,
                              extra={"security": dict(self.security), "distributed": dist},
                              ranges=[self.ds.table("ranges")])
        dl = rep["thresholds"]["delta_l_m"]
        probs = validate_report(rep)
        if probs and self.log is not None:
            self.log.error("report.json does not meet the contract: %s", probs)
        (self.out / "report.json").write_text(json.dumps(rep, indent=1) + "\n")
        np.savez_compressed(self.out / "estimates.npz", t=r.t, uavs=r.uavs, pos=r.pos, vel=r.vel, pos_cov=r.pos_cov,
                            rounds=r.rounds, step_ms=r.step_ms, wait_ms=w, bytes_out=b, peers=self.peers, inc=self.inc)
        (self.out / "report.md").write_text(render_markdown(rep))
        self._figure_args = ({a: r}, tr, {a: [r]}, [tr], self.meta.gnss_outages, self.ds, self.meta, dl)
        return rep

    def write_figures(self) -> None:
        """The same figures/*.png as `swarmnav evaluate` (after the report and the recording: the
        slowest and least essential output)."""
        from services.figures import write_figures

        try:
            write_figures(self.out, *self._figure_args)
        except Exception as e:  # a figure must never cost the run its report
            if self.log is not None:
                self.log.warning("figures not written: %s", e)

    def finish(self, figures: bool = True) -> dict:
        """Write the report first (the essential output: a launcher stopping the run allows only
        seconds), then close every epoch in the recording and close it, then (unless stopping on a
        signal, when every second counts) the figures, drawn while ``rerun rrd merge`` joins the
        recording's segments in its own process (the run ends ~1-2 s sooner). Killed half-way, the journal and the
        recording's segments on disk let ``swarmnav report RUN_DIR`` rebuild what is missing."""
        merged, ok = None, False
        try:
            rep = self.report()
            self.close_epochs(self.K, force=True)
            ok = True
        finally:
            try:
                if ok and figures and hasattr(self.sink, "close_start"):  # merge (another process) while drawing
                    merged = self.sink.close_start()
                else:
                    self.sink.close()
            finally:
                if self.journal is not None:
                    self.journal.close()
        if merged is not None:
            try:
                self.write_figures()
            finally:
                merged()
        elif figures:
            self.write_figures()
        return rep
