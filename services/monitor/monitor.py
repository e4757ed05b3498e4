"""monitor: records the swarm to Rerun and scores it with the in-process evaluation's metrics code.

A thin Zenoh adapter around :class:`services.monitor.core.MonitorCore`: it subscribes to every
node's ``estimate`` and ``links``, ``truth/*`` (sensor-sim), liveliness and the clock; validates
what arrives (rejected frames are counted per reason); journals every accepted message
(services/monitor/journal.py, flushed per record, so a SIGKILLed monitor loses nothing it had
accepted and ``swarmnav report RUN_DIR`` rebuilds the outputs); turns liveliness into events
(dropout, rejoin; a router outage, which deletes every token at once, is one ``bus_outage`` event,
not N dropouts); after an outage it recovers estimates published into it by querying the nodes'
state queryables. At the end (clock ``done``, SIGINT/SIGTERM, or the sensor-sim gone) it writes
report.json (``"mode": "distributed"``), report.md and estimates.npz, and closes the recording.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from services.runtime.service import Inbox, finish_process, install_signals, parse_key, setup_logging, undeclare_all
from services.runtime.zconf import client_config
from services.monitor import journal as J
from services.monitor.core import MonitorCore
from swarmnav.wire import keys
from swarmnav.wire import messages as M

DROP_CONFIRM_S = 0.5  # a token deletion becomes a dropout only if the bus is still up this long after
SIM_LOST_S = 30.0  # the sensor-sim gone this long (bus up): the run is over, report what there is
# An estimate of an epoch the clock (as this monitor has seen it) has not opened is held this long for
# the clock to catch up -- the clock and the estimates come through different pump threads, which a
# loaded machine schedules seconds apart -- then rejected as `future` (a forged estimate must not
# pre-empt the real one: only one held less than this before its epoch opened could). 5 s: a
# parity run at load ~15 still saw a genuine estimate rejected with the 1 s of session 7; the held
# list is capped (64 per UAV), so a flood costs nothing but rejects.
FUTURE_HOLD_S = 5.0
# A participant's estimate of epoch k-2 missing when the clock opens epoch k is queried for (recover)
# only once it is surely lost: a later estimate of the same UAV has arrived (one publisher's samples
# arrive in order), or it has been missing for RECOVER_WAIT epochs while nothing is queued here. An
# estimate merely still in flight (the estimates' pump thread behind the clock's on a loaded machine)
# is no reason to query every node: each reply holds 64 estimates, and a monitor that fell behind at
# the start of a run queried on every epoch (paper 1000 s: ~80 rounds of 18 queries, ~10 CPU-s), which
# kept it behind. A suspect stays one until its estimate arrives: a query that found nothing (the
# node not live yet after a router restart, a reply lost under load) is repeated every RECOVER_WAIT
# epochs, to the suspects' own nodes only, while the node still holds it (its last M.EST_HISTORY).
RECOVER_WAIT = 6


def _fault(s: str) -> tuple[int, float]:
    u, t = s.split("@")
    return int(u), float(t)


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="monitor")
    p.add_argument("--router", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--dataset", required=True, help="for scoring (truth, fault labels)")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--algo", default="atvfg")
    p.add_argument("--live", default=None, metavar="HOST:PORT",
                   help="also serve the recording live over gRPC on HOST:PORT (a Rerun viewer connects to it)")
    p.add_argument("--out", required=True, help="run directory (swarm.rrd, report.json, report.md)")
    p.add_argument("--config-sha256", default=None)
    p.add_argument("--kill", type=_fault, action="append", default=[], help="scheduled kill ID@T (estimates not expected)")
    p.add_argument("--restart", type=_fault, action="append", default=[], help="scheduled restart ID@T")
    p.add_argument("--security-mode", default="off", choices=["mtls", "usrpwd", "off"], help="for report.json")
    p.add_argument("--acl", default="off", choices=["on", "off"], help="for report.json")
    p.add_argument("--envelope-m", type=float, default=M.ENVELOPE_M, help="reject estimates farther than this (m, any axis)")
    p.add_argument("--sim-lost-timeout", type=float, default=SIM_LOST_S,
                   help="write what there is and exit (status 4) when the sensor-sim has been gone this long while a router is up (s)")
    p.add_argument("--zenoh-config", default=None)
    return p.parse_args(argv)


class Monitor:
    def __init__(self, args, session, log):
        from services import recording as R

        self.a, self.s, self.log = args, session, log
        self.run = args.run
        out = Path(args.out)
        header = {"run": args.run, "dataset": str(Path(args.dataset).resolve()), "seed": args.seed, "algo": args.algo,
                  "kills": args.kill, "restarts": args.restart, "config_sha256": args.config_sha256,
                  "security": {"mode": args.security_mode, "acl": args.acl == "on"}}
        jr = J.JournalWriter(J.journal_path(out), header)
        from services.monitor.core import LINK_ALGOS

        live = None
        if args.live:
            host, _, port = args.live.rpartition(":")
            live = (host or "127.0.0.1", int(port))
        sink = R.SegmentedRecording(out / "recording", out / "swarm.rrd", recording_id=args.run, live=live,
                                    blueprint=R.default_blueprint([args.algo], [args.algo] if args.algo in LINK_ALGOS else [],
                                                                  R.dataset_has_anchors(args.dataset)))
        self.core = MonitorCore(run=args.run, dataset=Path(args.dataset), seed=args.seed, algo=args.algo, out=out, sink=sink,
                                kills=args.kill, restarts=args.restart, security=header["security"],
                                config_sha256=args.config_sha256, journal=jr, log=log)
        self.uavs = self.core.uavs
        self.inbox = Inbox()
        self.rejects = M.Rejects(log)
        self.alive: set[int] = set()
        self.dropped: set[int] = set()
        self.pending_drop: dict[int, tuple[float, float]] = {}  # uav -> (monotonic, sim time) of its token deletion
        self.sim_alive = False
        self.sim_lost_at: float | None = None
        self.in_outage = False
        self.last_participants: list[int] = []
        self.prev_participants: list[int] = []
        self.clock_k = 0
        self.held: list[tuple[float, M.EstimateMsg, bytes]] = []  # (hold deadline, estimate, frame), arrival order
        self.recover_calls = self.recovered = 0  # state queries for missing estimates (logged at the end)
        # (uav, epoch) missing at its clock check -> (clock epoch then, clock epoch of the last query or None)
        self.suspect: dict[tuple[int, int], tuple[int, int | None]] = {}

    def setup(self):
        ib = self.inbox
        self.subs = [
            self.s.declare_subscriber(keys.uav_all(self.run, "estimate"), ib.channel()),
            self.s.declare_subscriber(keys.uav_all(self.run, "links"), ib.channel()),
            self.s.declare_subscriber(keys.truth_all(self.run), ib.channel()),
            self.s.declare_subscriber(keys.clock(self.run), ib.channel()),
            self.s.liveliness().declare_subscriber(keys.alive_all(self.run), ib.channel(), history=True),
        ]
        for tag, sub in zip(("est", "links", "truth", "clock", "alive"), self.subs):
            ib.attach(tag, sub)
        self.token = self.s.liveliness().declare_token(keys.alive(self.run, "monitor", 0))

    def routers(self) -> bool:
        try:
            return bool(list(self.s.info.routers_zid()))
        except Exception:  # session closing
            return False

    def bus_up(self) -> bool:
        return self.sim_alive and self.routers()

    def reject(self, topic: str, e: M.WireError) -> None:
        self.rejects.add(topic, e)
        self.core.reject(topic, e.reason)

    def on_alive(self, kk, put: bool) -> None:
        c = self.core
        if kk.topic == "sensor_sim":
            self.sim_alive, self.sim_lost_at = put, (None if put else time.monotonic())
            return
        if kk.topic != "uav":
            return
        if kk.uav not in self.uavs:
            self.reject("alive", M.WireError("unknown_uav", f"token of UAV {kk.uav}"))
            return
        if put:
            self.pending_drop.pop(kk.uav, None)
            if kk.uav in self.alive:
                return
            self.alive.add(kk.uav)
            if kk.uav in self.dropped:
                self.dropped.discard(kk.uav)
                c.event("rejoin", kk.uav)
        else:
            self.alive.discard(kk.uav)
            j = self.uavs.index(kk.uav)
            finished = c.k_now >= c.K and np.isfinite(c.res.pos[c.K - 1, j, 0])
            if not c.done and not finished:
                self.pending_drop[kk.uav] = (time.monotonic(), c.t_now)
                self.confirm_scheduled_drops()

    def confirm_scheduled_drops(self) -> None:
        """A token gone while its UAV's scheduled kill is on (the clock's kill hold seen, no dropout
        for it yet) is a dropout at once: the DROP_CONFIRM_S wait that tells a death from a bus
        outage is not needed, and a fast run could restart the UAV within it (then neither the
        dropout nor the rejoin was recorded)."""
        c = self.core
        for u, (_, t_sim) in list(self.pending_drop.items()):
            kills = sum(1 for e in c.events if e["uav"] == u and e["kind"] == "scheduled_kill")
            drops = sum(1 for e in c.events if e["uav"] == u and e["kind"] == "dropout")
            if kills > drops and u not in self.alive and u not in self.dropped:
                del self.pending_drop[u]
                self.dropped.add(u)
                c.event("dropout", u, t=t_sim)

    def confirm_drops(self) -> None:
        """Token deletions older than DROP_CONFIRM_S: dropouts if the bus is up, else one outage."""
        if not self.pending_drop:
            if self.in_outage and self.bus_up():
                self.in_outage = False
                self.core.event("bus_restored", 0)
                self.recover(self.core.k_now - 1)
            return
        now = time.monotonic()
        if not self.bus_up():
            if not self.in_outage:
                self.in_outage = True
                self.core.event("bus_outage", 0, detail="router or sensor-sim unreachable: every token lost at once")
            self.pending_drop.clear()
            return
        for u, (t0, t_sim) in list(self.pending_drop.items()):
            if now - t0 >= DROP_CONFIRM_S:
                del self.pending_drop[u]
                if u not in self.alive and u not in self.dropped:
                    self.dropped.add(u)
                    self.core.event("dropout", u, t=t_sim)

    def recover(self, k: int, only: set[int] | None = None) -> None:
        """Query the live nodes (``only``: these) for estimates of epochs up to k that never arrived
        (sent into an outage, or lost)."""
        c = self.core
        self.recover_calls += 1
        for u in self.uavs:
            if u not in self.alive or (only is not None and u not in only):
                continue
            j = self.uavs.index(u)
            if np.isfinite(c.res.pos[: max(k, 0), j, 0]).all():
                continue
            try:
                for rep in self.s.get(keys.uav(self.run, u, "state") + "?k=0;r=0", timeout=1.0):
                    if rep.ok is None:
                        continue
                    h = M.decode(M.HistoryMsg, rep.ok.payload.to_bytes(), uav=u)
                    for e in h.estimates:
                        if e.uav == u and c.on_estimate(e, e.encode()):
                            self.recovered += 1
                            self.log.info("recovered the estimate of UAV %d epoch %d by query", u, e.k)
            except M.WireError as e:
                self.reject("state-query", e)

    def check_missing(self, k: int, who: list[int]) -> None:
        """Epoch k's estimates of ``who`` (its participants) are due: recover the missing ones that are
        surely lost (see RECOVER_WAIT) from their own nodes, again every RECOVER_WAIT epochs until
        they arrive or their node no longer holds them (whatever is still missing at the end is
        reported missing: the run is then incomplete)."""
        c = self.core
        for u in c.missing(k, who):
            self.suspect.setdefault((u, k), (self.clock_k, None))
        due: set[int] = set()
        for (u, e), (since, asked) in list(self.suspect.items()):
            j = c.col[u]
            if np.isfinite(c.res.pos[e - 1, j, 0]) or self.clock_k - e > 2 * M.EST_HISTORY:  # came, or beyond reach
                del self.suspect[(u, e)]
            elif u in self.alive and not self.inbox.items and (
                    self.clock_k - asked >= RECOVER_WAIT if asked is not None
                    else np.isfinite(c.res.pos[e:, j, 0]).any() or self.clock_k - since >= RECOVER_WAIT):
                self.suspect[(u, e)] = (since, self.clock_k)
                due.add(u)
        if due:
            self.recover(k, due)

    def handle(self, tag, item):
        kk = parse_key(item.key_expr, self.rejects)
        if kk is None:
            self.core.reject(tag, "bad_key")
            return
        if tag == "alive":
            import zenoh

            self.on_alive(kk, item.kind == zenoh.SampleKind.PUT)
            return
        payload = item.payload.to_bytes()
        try:
            if tag == "clock":
                c = M.decode(M.ClockMsg, payload)
                new_epoch = c.k > self.clock_k and not c.hold and not c.done
                if new_epoch:
                    self.clock_k = c.k
                self.core.on_clock(c, payload)
                if c.hold == "kill":
                    self.confirm_scheduled_drops()
                if new_epoch:
                    self.release_held()
                if new_epoch:  # participants of epoch k-2: their estimates are surely due by now
                    prev = self.prev_participants
                    self.prev_participants, self.last_participants = self.last_participants, c.participants
                    if c.k >= 3:
                        self.check_missing(c.k - 2, prev)
            elif tag == "truth":
                M.decode(M.TruthMsg, payload, uav=kk.uav)  # validated; truth for scoring comes from the dataset
            elif tag == "est":
                m = M.decode(M.EstimateMsg, payload, uav=kk.uav)
                if max(abs(x) for x in m.pos) > self.a.envelope_m:
                    raise M.WireError("envelope", f"estimate of UAV {m.uav} outside the {self.a.envelope_m:g} m envelope")
                if m.k > self.clock_k + 1:  # an epoch the sensor-sim has not opened (as far as we know yet)
                    if len(self.held) >= 64 * len(self.uavs):
                        raise M.WireError("future", f"estimate of epoch {m.k}, clock at {self.clock_k}")
                    self.held.append((time.monotonic() + FUTURE_HOLD_S, m, payload))
                    return
                self.core.on_estimate(m, payload)
            elif tag == "links":
                M.decode(M.LinksMsg, payload, uav=kk.uav)  # validated; links are taken from the estimate
        except M.WireError as e:
            self.reject(tag, e)

    def release_held(self, expire: bool = False) -> None:
        """Held estimates whose epoch the clock has opened go to the core (in arrival order); those
        held past FUTURE_HOLD_S (or all, ``expire``) are rejected as forged (``future``)."""
        if not self.held:
            return
        now, keep = time.monotonic(), []
        for dl, m, payload in self.held:
            if m.k <= self.clock_k + 1:
                self.core.on_estimate(m, payload)
            elif expire or now > dl:
                self.reject("est", M.WireError("future", f"estimate of epoch {m.k}, clock at {self.clock_k}"))
            else:
                keep.append((dl, m, payload))
        self.held = keep

    def loop(self) -> int:
        last = time.monotonic()
        while not self.inbox.stop.is_set():
            it = self.inbox.get(0.2)
            if it is not None:
                self.handle(*it)
                last = time.monotonic()
            self.confirm_drops()
            self.release_held()
            if self.core.done and time.monotonic() - last > 0.3:
                self.recover(self.core.K)
                return 0
            if self.sim_lost_at is not None and self.routers() and time.monotonic() - self.sim_lost_at > self.a.sim_lost_timeout:
                self.core.event("sensor_sim_lost", 0)
                self.log.error("the sensor-sim has been gone for %.0f s: writing what there is", self.a.sim_lost_timeout)
                return 4
        return 0

    def finish(self):
        self.release_held(expire=True)
        rep = self.core.finish(figures=not self.inbox.stop.is_set() or self.core.done)
        self.log.info("report written: %s 3-D pos RMSE %s; complete %s (%s of %s estimates); recovery queries %d "
                      "(%d estimates recovered)", self.a.algo, rep["algorithms"][self.a.algo]["pos_rmse_m"]["3d"],
                      rep.get("complete"), rep.get("estimates_received"), rep.get("estimates_expected"), self.recover_calls,
                      self.recovered)


def main(argv=None) -> int:
    args = parse_args(argv)
    log = setup_logging("monitor")
    import zenoh

    rc = 0
    with zenoh.open(client_config(args.router, args.zenoh_config)) as session:
        mon = Monitor(args, session, log)
        install_signals(mon.inbox)
        try:
            mon.setup()
            rc = mon.loop()
        finally:
            mon.inbox.stop.set()
            undeclare_all(getattr(mon, "subs", []))
            mon.finish()
    return finish_process(mon.inbox, log, rc)
