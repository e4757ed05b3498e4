"""monitor: records the swarm to Rerun and scores it with the in-process evaluation's metrics code.

Subscribes to every node's ``estimate`` and ``links``, ``truth/*`` (sensor-sim), liveliness and
the clock. Writes ``swarm.rrd`` through services/recording.py (same entities and blueprint as
``evaluate``), records dropouts/rejoins from liveliness as events (sim time of the clock), and at
the end (clock ``done``, or SIGINT/SIGTERM) builds report.json (``"mode": "distributed"``) with
swarmnav.metrics/report exactly as ``swarmnav evaluate`` does, then flushes and closes the file.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from deploy.service import Inbox, finish_process, install_signals, parse_key, setup_logging, undeclare_all
from deploy.zconf import client_config
from swarmnav.dataset import Dataset
from swarmnav.estimators import registry
from swarmnav.evaluation import FAULT_RULE, RunResult, link_labels, truth_at_epochs
from swarmnav.wire import keys
from swarmnav.wire import messages as M

FLUSH_EVERY = 50  # closed epochs per column batch sent to the recording


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="monitor")
    p.add_argument("--router", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--dataset", required=True, help="for scoring (truth, fault labels)")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--algo", default="atvfg")
    p.add_argument("--out", required=True, help="run directory (swarm.rrd, report.json, report.md)")
    p.add_argument("--config-sha256", default=None)
    p.add_argument("--settings-base", action="append", default=[])
    p.add_argument("--zenoh-config", default=None)
    return p.parse_args(argv)


class Monitor:
    def __init__(self, args, session, log):
        from services import recording as R

        self.R = R
        self.a, self.s, self.log = args, session, log
        self.run = args.run
        self.out = Path(args.out)
        self.ds = Dataset.read(args.dataset)
        self.meta = self.ds.meta
        self.uavs = self.meta.uav_ids()
        self.truth = truth_at_epochs(self.ds)
        self.K = self.meta.n_epochs()
        self.res = RunResult.empty(args.algo, args.seed, self.uavs, self.truth.t)
        self.links: list[tuple] = []
        self.extra = {"wait_ms": np.full((self.K, len(self.uavs)), np.nan), "bytes": np.full((self.K, len(self.uavs)), np.nan)}
        # peers[k-1, j, l]: UAV j's estimate of epoch k used UAV l's states (who is in whose graph)
        self.peers = np.zeros((self.K, len(self.uavs), len(self.uavs)), bool)
        self.inbox = Inbox()
        self.rejects = M.Rejects(log)
        self.events: list[dict] = []
        self.alive: set[int] = set()
        self.dropped: set[int] = set()
        self.t_now = self.meta.t_start
        self.k_now = 0
        self.done = False
        self.logged_k = 0
        self.positions: dict[int, dict[int, np.ndarray]] = {}
        self.pending_links: dict[int, list[tuple[int, int, int]]] = {}
        # rows waiting for the next column batch (send_batch)
        n = len(self.uavs)
        self.truth_rx = np.full((self.K, n, 3), np.nan)
        self.sent_est = np.zeros((self.K, n), bool)
        self.sent_truth = np.zeros((self.K, n), bool)
        self.swarm_err = np.full((self.K, 2), np.nan)
        self.link_rows: list[tuple[int, list]] = []
        self.sent_k = 0
        self.rec = R.open_recording(self.out / "swarm.rrd", recording_id=args.run,
                                    blueprint=R.default_blueprint([args.algo]))
        R.log_styles([args.algo, "truth"], rec=self.rec)
        # point sizes scaled to the scene (km-scale swarm or an indoor flight), anchors drawn once
        self.radius = R.point_radius(self.truth.pos, list(self.meta.anchors().values()))
        R.log_anchors(self.meta.anchors(), self.radius, rec=self.rec)

    def setup(self):
        ib = self.inbox
        self.subs = [
            self.s.declare_subscriber(keys.uav_all(self.run, "estimate"), ib.channel()),
            self.s.declare_subscriber(keys.uav_all(self.run, "links"), ib.channel()),
            self.s.declare_subscriber(keys.truth_all(self.run), ib.channel()),
            self.s.declare_subscriber(keys.clock(self.run), ib.channel()),
            self.s.liveliness().declare_subscriber(keys.alive_all(self.run, "uav"), ib.channel(), history=True),
        ]
        for tag, sub in zip(("est", "links", "truth", "clock", "alive"), self.subs):
            ib.attach(tag, sub)
        self.token = self.s.liveliness().declare_token(keys.alive(self.run, "monitor", 0))

    def event(self, kind: str, uav: int):
        ev = {"t": float(self.t_now), "kind": kind, "uav": int(uav)}
        self.events.append(ev)
        self.log.info("event %s", ev)
        self.R.set_epoch(max(self.k_now, 0), self.t_now, rec=self.rec)
        self.R.log_event(kind, uav, self.t_now, rec=self.rec)

    def handle(self, tag, item):
        kk = parse_key(item.key_expr, self.rejects)
        if kk is None:
            return
        if tag == "alive":
            import zenoh

            if item.kind == zenoh.SampleKind.PUT:
                if kk.uav in self.alive:
                    return
                self.alive.add(kk.uav)
                if kk.uav in self.dropped:
                    self.dropped.discard(kk.uav)
                    self.event("rejoin", kk.uav)
            else:
                self.alive.discard(kk.uav)
                j = self.uavs.index(kk.uav) if kk.uav in self.uavs else None
                finished = j is not None and self.k_now >= self.K and np.isfinite(self.res.pos[self.K - 1, j, 0])
                if not self.done and not finished:
                    self.dropped.add(kk.uav)
                    self.event("dropout", kk.uav)
            return
        payload = item.payload.to_bytes()
        try:
            if tag == "clock":
                c = M.decode(M.ClockMsg, payload)
                self.flush_epochs(c.k - 1)
                self.k_now, self.t_now = c.k, c.t
                if c.done:
                    self.done = True
            elif tag == "truth":
                m = M.decode(M.TruthMsg, payload, uav=kk.uav)
                if 1 <= m.k <= self.K and m.uav in self.uavs:
                    self.truth_rx[m.k - 1, self.uavs.index(m.uav)] = m.pos
            elif tag == "est":
                m = M.decode(M.EstimateMsg, payload, uav=kk.uav)
                self.store(m)
            elif tag == "links":
                M.decode(M.LinksMsg, payload, uav=kk.uav)  # validated; links are taken from the estimate
        except M.WireError as e:
            self.rejects.add(tag, e)

    def store(self, m: M.EstimateMsg):
        if not 1 <= m.k <= self.K or m.uav not in self.uavs:
            self.rejects.add("estimate", M.WireError("range", f"epoch {m.k} / uav {m.uav}"))
            return
        i, j = m.k - 1, self.uavs.index(m.uav)
        e = M.msg_to_estimate(m)
        r = self.res
        r.pos[i, j], r.vel[i, j], r.pos_cov[i, j] = e.pos, e.vel, e.pos_cov
        if e.quat is not None:
            r.quat[i, j] = e.quat
        r.step_ms[i, j], r.rounds[i, j] = e.step_ms, e.rounds
        if e.delta_h_m is not None:
            r.delta_h_m[i, j] = e.delta_h_m
        if e.delta_l_m is not None:
            r.delta_l_m[i, j] = e.delta_l_m
        for li in e.links:
            self.links.append((m.k, m.uav, int(li.other), int(li.cls), float(li.residual_m), float(li.weight)))
        self.extra["wait_ms"][i, j] = m.wait_ms
        self.extra["bytes"][i, j] = m.bytes_out
        for p in m.peers:
            if p in self.uavs:
                self.peers[i, j, self.uavs.index(p)] = True
        self.positions.setdefault(m.k, {})[m.uav] = e.pos
        self.pending_links.setdefault(m.k, []).extend((m.uav, li.other, int(li.cls)) for li in e.links)

    def epoch_complete(self, k: int) -> bool:
        """True when every live UAV's estimate of epoch k has been received."""
        got = np.all(np.isfinite(self.res.pos[k - 1]), axis=1)
        return all(got[self.uavs.index(u)] for u in self.alive if u in self.uavs)

    def flush_epochs(self, upto: int, force: bool = False):
        """Close epochs up to ``upto``: their swarm error series and link graph are final. Rows go
        to the recording in column batches (``send_columns``) every FLUSH_EVERY closed epochs and at
        :meth:`finish` (also on SIGTERM): one ``rr.log`` per UAV and epoch cost ~34 ms per epoch.

        The clock and the estimates arrive on different pump threads, so the clock of epoch k+1 can
        be handled before the last estimate of epoch k: the newest epoch ``upto`` is closed only once
        every live UAV's estimate is in; otherwise it waits for the next clock (or ``force``)."""
        a = self.a.algo
        while self.logged_k < min(upto, self.K):
            k = self.logged_k + 1
            if k == upto and not force and not self.epoch_complete(k):
                break
            self.logged_k = k
            i = k - 1
            ep = self.res.pos[i] - self.truth.pos[i]
            ev = self.res.vel[i] - self.truth.vel[i]
            ok = np.all(np.isfinite(ep), axis=1)
            if ok.any():
                self.swarm_err[i] = (np.sqrt(np.mean(np.sum(ep[ok] ** 2, axis=1))), np.sqrt(np.mean(np.sum(ev[ok] ** 2, axis=1))))
            pos = self.positions.pop(k, {})
            segs = [(pos[x], pos[y], c) for x, y, c in self.pending_links.pop(k, []) if x in pos and y in pos]
            self.link_rows.append((k, segs))
        if self.logged_k - self.sent_k >= FLUSH_EVERY:
            self.send_batch()

    def send_batch(self):
        """Send every row not yet in the recording as columns (positions and truth per UAV: those
        received since the last batch, whatever their epoch; series and links: the closed epochs)."""
        R, a, rec, t = self.R, self.a.algo, self.rec, self.truth.t
        ks = np.arange(1, self.K + 1)
        sent_now = []
        for arr, sent, name in ((self.res.pos, self.sent_est, a), (self.truth_rx, self.sent_truth, "truth")):
            new = np.all(np.isfinite(arr), axis=2) & ~sent
            for j, u in enumerate(self.uavs):
                m = new[:, j]
                if m.any():
                    R.send_positions(name, u, t[m], ks[m], arr[m, j], rec=rec,
                                     radius=self.radius * (0.75 if name == "truth" else 1.0))
            sent |= new
            sent_now.append(new)
        if 1 in self.uavs:  # UAV 1's error series: the estimates sent in this batch
            j1 = self.uavs.index(1)
            m = sent_now[0][:, j1]
            if m.any():
                e1 = np.linalg.norm(self.res.pos[m, j1] - self.truth.pos[m, j1], axis=1)
                R.send_series(R.error_path(a, "pos_3d", "uav1"), t[m], ks[m], e1, rec=rec)
        lo, hi = self.sent_k, self.logged_k
        if hi > lo:
            sl = slice(lo, hi)
            R.send_series(R.error_path(a, "pos_3d", "swarm"), t[sl], ks[sl], self.swarm_err[sl, 0], rec=rec)
            R.send_series(R.error_path(a, "vel_3d", "swarm"), t[sl], ks[sl], self.swarm_err[sl, 1], rec=rec)
            rows = self.link_rows
            segs = np.array([[s0, s1] for _, ss in rows for s0, s1, _c in ss], float).reshape(-1, 2, 3)
            cls = np.array([c for _, ss in rows for *_x, c in ss], int)
            kk = np.array([k for k, _ in rows], np.int64)
            if len(segs):
                R.send_links(a, t[kk - 1], kk, segs, cls, np.array([len(ss) for _, ss in rows]), rec=rec,
                             radius=0.15 * self.radius)
            else:  # no link at all in the batch: still one (empty) row per epoch
                for k in kk:
                    R.set_epoch(int(k), float(t[k - 1]), rec=rec)
                    R.log_links(a, {}, [], rec=rec, radius=0.15 * self.radius)
            self.link_rows = []
            self.sent_k = hi

    def loop(self):
        last = time.monotonic()
        while not self.inbox.stop.is_set():
            it = self.inbox.get(0.5)
            if it is not None:
                self.handle(*it)
                last = time.monotonic()
            elif self.done and time.monotonic() - last > 0.3:
                break

    def report(self) -> dict:
        from swarmnav import metrics
        from swarmnav.report import build_report, render_markdown, validate_report

        from services.provenance import dataset_sha256, provenance

        a, r, tr = self.a.algo, self.res, self.truth
        block = metrics.algorithm_metrics(tr.uavs, tr.t, [r.pos - tr.pos], [r.vel - tr.vel], [r.pos_cov], [r.step_ms],
                                          self.meta.gnss_outages)
        block["rounds_mean"] = float(np.mean(r.rounds))
        settings = registry.settings_for_dataset(self.meta, tuple(Path(b) for b in self.a.settings_base))
        det = single = None
        dl = settings.get("delta_l_m")
        dh = {"p50": None, "p95": None}
        from swarmnav.evaluation import LINK_DTYPE

        r.links = np.array(self.links, dtype=LINK_DTYPE) if self.links else np.zeros(0, LINK_DTYPE)
        if a == "atvfg":
            det, single = metrics.detection_report(r.links, link_labels(self.ds), self.meta.fault_threshold_m)
            dh = metrics.percentiles(r.delta_h_m.ravel(), (50, 95))
            if dl is None:
                v = r.delta_l_m.ravel()
                v = v[np.isfinite(v)]
                dl = float(np.median(v)) if len(v) else None
        b = self.extra["bytes"]
        w = self.extra["wait_ms"]
        dist = {"run_id": self.run, "epochs_recorded": int(np.isfinite(r.pos[..., 0]).any(axis=1).sum()),
                "missing_estimates": int((~np.isfinite(r.pos[..., 0])).sum()),
                "bytes_out_per_uav_epoch": float(np.nanmean(b)) if np.isfinite(b).any() else None,
                "wait_ms": metrics.percentiles(w, (50, 99)),
                "monitor_rejected": self.rejects.as_dict()}
        rep = build_report(mode="distributed", scenario=self.meta.name, seeds=[self.a.seed], n_uavs=len(self.uavs),
                           duration_s=self.meta.duration_s, algorithms={a: block}, detection=det, detection_single=single,
                           delta_l_m=dl, delta_h_m=dh,
                           provenance=provenance(self.a.config_sha256 or dataset_sha256(self.meta)),
                           events=self.events, extra={"distributed": dist, "fault_threshold_m": self.meta.fault_threshold_m,
                                                          "fault_threshold_rule": FAULT_RULE})
        probs = validate_report(rep)
        if probs:
            self.log.error("report.json does not meet the contract: %s", probs)
        (self.out / "report.json").write_text(json.dumps(rep, indent=1) + "\n")
        np.savez_compressed(self.out / "estimates.npz", t=r.t, uavs=r.uavs, pos=r.pos, vel=r.vel, pos_cov=r.pos_cov,
                            rounds=r.rounds, step_ms=r.step_ms, wait_ms=w, bytes_out=b, peers=self.peers)
        (self.out / "report.md").write_text(render_markdown(rep))
        return rep

    def finish(self):
        try:
            self.flush_epochs(self.K, force=True)
            self.send_batch()
            rep = self.report()
            self.log.info("report written: %s 3-D pos RMSE %s", self.a.algo,
                          rep["algorithms"][self.a.algo]["pos_rmse_m"]["3d"])
        finally:
            self.R.close_recording(self.rec)


def main(argv=None) -> int:
    args = parse_args(argv)
    log = setup_logging("monitor")
    import zenoh

    with zenoh.open(client_config(args.router, args.zenoh_config)) as session:
        mon = Monitor(args, session, log)
        install_signals(mon.inbox)
        try:
            mon.setup()
            mon.loop()
        finally:
            mon.inbox.stop.set()
            undeclare_all(getattr(mon, "subs", []))
            mon.finish()
    return finish_process(mon.inbox, log, 0)
