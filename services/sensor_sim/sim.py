"""sensor_sim: plays a dataset onto Zenoh, epoch by epoch, and keeps the swarm clock.

For every epoch k and every participating UAV it publishes the EpochInput the in-process run
would build (``EpochSlicer.epoch(k, uav)``), as one binary frame on ``uav/<id>/input`` (with the epoch's participants = the UAV nodes live
when the epoch opens). Truth goes to ``truth/<id>``, which nodes never subscribe to. It also
answers ``meta`` (the dataset meta as a UAV may know it, ``dataset.node_view``: no fault, outage
or kill schedule; + the run seed) and ``uav/<id>/init`` (initial knowledge from
``initial_states(ds, seed)``; with ``?restart=1`` a fresh coarse alignment at the current epoch).

Clocks: ``lockstep`` (default) opens epoch k+1 once every participant of epoch k has published
its estimate or lost its liveliness (or ``--epoch-timeout`` passed); ``--rate R`` plays at R× real
time instead (an epoch every epoch_dt/R seconds, whatever the nodes do). Scheduled faults
(``--kill ID@T``/``--restart ID@T``) hold the clock at the first epoch with t >= T until the launcher
has acted (the UAV's token gone / back), so a fault always lands between the same two epochs.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from services.runtime.service import Deadline, Inbox, finish_process, install_signals, parse_key, setup_logging, undeclare_all
from services.runtime.zconf import client_config
from swarmnav.dataset import Dataset, EpochSlicer, node_view
from swarmnav.imu_source import ImuStream
from swarmnav.evaluation import truth_at_epochs
from swarmnav.geometry import quat_from_rotvec, quat_mul
from swarmnav.estimators.base import InitialState
from swarmnav.initial import initial_states
from swarmnav.wire import keys
from swarmnav.wire import messages as M


def parse_fault(s: str) -> tuple[int, float]:
    try:
        u, t = s.split("@")
        return int(u), float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID@T (e.g. 2@15), got {s!r}") from None


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="sensor_sim")
    p.add_argument("--router", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--dataset", required=True)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--rate", type=float, default=None, help="real-time factor (default: lockstep)")
    p.add_argument("--kill", type=parse_fault, action="append", default=[])
    p.add_argument("--restart", type=parse_fault, action="append", default=[])
    p.add_argument("--epoch-timeout", type=float, default=60.0)
    p.add_argument("--startup-timeout", type=float, default=180.0)
    p.add_argument("--fault-timeout", type=float, default=60.0)
    p.add_argument("--outage-timeout", type=float, default=120.0, help="give up when the bus stays down this long (s)")
    p.add_argument("--rejoin-grace", type=float, default=10.0,
                   help="after an outage, wait this long for the UAVs live before it to reconnect (s)")
    p.add_argument("--requery-s", type=float, default=3.0,
                   help="lockstep: query missing estimates and re-send the epoch after this long without them (s)")
    p.add_argument("--done-timeout", type=float, default=15.0, help="repeat 'done' until every service left, at most this long (s)")
    p.add_argument("--garbage-at", type=int, default=None,
                   help="test hook: at this epoch publish garbage on every key the nodes listen to")
    p.add_argument("--no-monitor", action="store_true", help="do not wait for a monitor at start")
    p.add_argument("--zenoh-config", default=None)
    return p.parse_args(argv)


def restart_initial_state(truth, inits: dict, uavs: list[int], seed: int, u: int, k: int) -> InitialState:
    """Initial knowledge of UAV ``u`` restarted before epoch ``k``: a coarse alignment at epoch k's
    time with the same sigmas as at t=0 (truth + noise, seeded by (seed, u, k)). Module-level so an
    in-process emulation of a kill/restart run (tests/test_services.py) uses the very same numbers."""
    j = uavs.index(u)
    i0 = inits[u]
    rng = np.random.default_rng([seed, u, k, 0x5EED])
    pos = truth.pos[k - 1, j] + rng.normal(0, 1, 3) * i0.pos_sigma
    vel = truth.vel[k - 1, j] + rng.normal(0, i0.vel_sigma, 3)
    q = quat_mul(quat_from_rotvec(rng.normal(0, 1, 3) * i0.att_sigma), truth.quat[k - 1, j])
    return InitialState(t=float(truth.t[k - 1]), pos=pos, vel=vel, quat=q, pos_sigma=np.asarray(i0.pos_sigma, float),
                        vel_sigma=float(i0.vel_sigma), att_sigma=np.asarray(i0.att_sigma, float))


LEVEL_MARGIN_S = 5.0  # IMU read beyond the levelling window: its start is the truth sample nearest t_start


class SensorSim:
    def __init__(self, args, session, log):
        self.a, self.s, self.log = args, session, log
        self.run = args.run
        # the IMU samples are streamed from the file epoch by epoch (imu_source.ImuStream): a 1000 s
        # paper dataset holds ~110 MB of them, which this process need not keep
        self.ds = Dataset.read(args.dataset, skip=("imu",))
        self.meta = self.ds.meta
        self.uavs = self.meta.uav_ids()
        self.uav_set = set(self.uavs)
        self.lost: list[tuple[int, int]] = []  # (first, last) epochs played into an outage (real-time mode)
        imu = ImuStream.open(Path(args.dataset) / "imu.parquet", self.uavs)
        self.slicer = EpochSlicer(self.ds, imu=imu)
        level_w = float((self.meta.init or {}).get("level_window_s", 0.0) or 0.0)
        # the initial levelling reads the first seconds of IMU (initial.level_roll_pitch)
        head = {"imu": imu.head(self.meta.t_start + level_w + LEVEL_MARGIN_S)} if level_w > 0 else {}
        self.inits = initial_states(Dataset(self.meta, {**self.ds.tables, **head}), args.seed)
        self.truth = truth_at_epochs(self.ds)
        self.K = self.meta.n_epochs()
        self.inbox = Inbox()
        self.rejects = M.Rejects(log)
        self.alive_uav: set[int] = set()
        self.gone_since: dict[int, float] = {}  # uav -> monotonic time its token went away
        self.monitor_alive = False
        self.estimates: dict[int, set[int]] = {}
        self.k = 0
        self.bytes_per_uav = 0
        # nodes get what a real UAV knows: no fault windows, GNSS outages or kill schedule (node_view)
        self.meta_msg = M.MetaMsg(run=self.run, seed=args.seed,
                                  meta=node_view(self.meta).model_dump(mode="json", by_alias=True)).encode()

    def setup(self):
        ib = self.inbox
        self.subs = [
            self.s.declare_queryable(keys.meta(self.run), ib.channel()),
            self.s.declare_queryable(keys.uav_all(self.run, "init"), ib.channel()),
            self.s.declare_subscriber(keys.uav_all(self.run, "estimate"), ib.channel()),
            self.s.liveliness().declare_subscriber(keys.alive_all(self.run), ib.channel(), history=True),
        ]
        for tag, sub in zip(("q", "q", "est", "alive"), self.subs):
            ib.attach(tag, sub)
        import zenoh

        bl = zenoh.CongestionControl.BLOCK
        self.pub_input = {u: self.s.declare_publisher(keys.uav(self.run, u, "input"), congestion_control=bl)
                          for u in self.uavs}
        self.pub_truth = {u: self.s.declare_publisher(keys.truth(self.run, u), congestion_control=bl) for u in self.uavs}
        self.pub_clock = self.s.declare_publisher(keys.clock(self.run), congestion_control=bl)
        self.token = self.s.liveliness().declare_token(keys.alive(self.run, "sensor_sim", 0))

    def restart_init(self, u: int, at: int | None = None) -> M.InitMsg:
        """Coarse alignment of UAV u restarted before epoch ``at`` (default: the current epoch)."""
        k = min(max(at if at is not None else self.k, 1), self.K)
        return M.init_to_msg(u, restart_initial_state(self.truth, self.inits, self.uavs, self.a.seed, u, k))

    def handle(self, tag, item):
        if tag == "q":
            try:
                kk = keys.parse(str(item.key_expr))
                if kk.kind == "meta":
                    item.reply(keys.meta(self.run), self.meta_msg)
                elif kk.kind == "uav" and kk.topic == "init" and kk.uav in self.inits:
                    params = dict(p.split("=", 1) for p in str(item.parameters).split(";") if "=" in p)
                    restart = params.get("restart") == "1"
                    at = int(params["k"]) if params.get("k", "").isdigit() else None
                    m = self.restart_init(kk.uav, at) if restart else M.init_to_msg(kk.uav, self.inits[kk.uav])
                    item.reply(keys.uav(self.run, kk.uav, "init"), m.encode())
            except Exception as e:
                self.rejects.add("query", M.WireError("bad_query", str(e)))
            finally:
                item.drop()
            return
        kk = parse_key(item.key_expr, self.rejects)
        if kk is None:
            return
        if tag == "alive":
            import zenoh

            put = item.kind == zenoh.SampleKind.PUT
            if kk.topic == "uav":
                if kk.uav not in self.uav_set:  # a token for a UAV the dataset does not have: never a participant
                    self.rejects.add("alive", M.WireError("unknown_uav", f"liveliness token of UAV {kk.uav}, not in the dataset {self.uavs}"))
                    return
                (self.alive_uav.add if put else self.alive_uav.discard)(kk.uav)
                if not put:
                    self.gone_since[kk.uav] = time.monotonic()
            elif kk.topic == "monitor":
                self.monitor_alive = put
            return
        if tag == "est":
            try:
                m = M.decode(M.EstimateMsg, item.payload.to_bytes(), uav=kk.uav)
            except M.WireError as e:
                self.rejects.add("estimate", e)
                return
            if m.uav in self.uav_set:
                self.estimates.setdefault(m.k, set()).add(m.uav)

    def pump(self, timeout: float) -> None:
        it = self.inbox.get(timeout)
        while it is not None:
            self.handle(*it)
            it = self.inbox.get(0)
        if self.inbox.stop.is_set():
            raise KeyboardInterrupt

    def wait_until(self, cond, timeout: float, what: str, quiet: bool = False) -> bool:
        dl = Deadline(timeout)
        while not cond():
            if dl.passed():
                if not quiet:
                    self.log.warning("timeout (%.0f s) waiting for %s", timeout, what)
                return False
            self.pump(min(0.2, dl.left() + 1e-3))
        return True

    def garbage(self, k: int) -> None:
        """Test hook: one bad message per key a node listens to (each must be rejected and counted)."""
        bad = [b"not json", b'{"v": 99}', json.dumps({"v": 1, "uav": 1, "k": k, "r": 0, "pos": [float("nan")] * 3}).encode()]
        bad_input = b"SNI" + bytes([M.SCHEMA_VERSION + 1]) + bytes(8)  # a binary frame of an unknown version
        bad_state = b"SNS" + bytes([M.SCHEMA_VERSION]) + bytes(13)  # a truncated state frame
        for u in self.uavs:
            for payload in bad + [bad_input]:
                self.pub_input[u].put(payload)
            self.s.put(keys.uav(self.run, u, "state"), bad_state)
        self.pub_clock.put(b'{"v": 1, "k": -3}')
        self.log.info("garbage published at epoch %d", k)

    def clock(self, k: int, **kw) -> None:
        t = self.meta.epoch_time(k)
        self.pub_clock.put(M.ClockMsg(k=k, t=t, n_epochs=self.K, **kw).encode())

    # -- connectivity ------------------------------------------------------------------------
    def connected(self) -> bool:
        """True while this session reaches a router and the monitor's token is seen (a router
        outage deletes every remote token at once, the monitor's included)."""
        try:
            up = bool(list(self.s.info.routers_zid()))
        except Exception:  # session closing
            return False
        return up and (self.monitor_alive or self.a.no_monitor)

    def ride_out_outage(self, k: int) -> bool:
        """If the bus is down, wait for it to come back (and for the UAVs live before the outage, up to
        ``--rejoin-grace``); returns True if there was an outage. Never plays into the void."""
        if self.connected():
            return False
        before = set(self.part_prev)
        t0 = time.monotonic()
        self.log.warning("epoch %d: lost the router/monitor (bus outage): holding the clock", k)
        while not self.connected():
            if time.monotonic() - t0 > self.a.outage_timeout:
                try:
                    up = bool(list(self.s.info.routers_zid()))
                except Exception:  # session closing
                    up = False
                what = "the monitor has been unreachable (frozen or gone)" if up else "no router has been reachable"
                raise OutageError(f"{what} for {self.a.outage_timeout:.0f} s at epoch {k}: stopping rather than "
                                  "playing epochs nobody records")
            self.pump(0.1)
        self.wait_until(lambda: before <= self.alive_uav, self.a.rejoin_grace, f"UAVs {sorted(before)} to reconnect")
        self.log.warning("epoch %d: bus back after %.1f s; live UAVs %s", k, time.monotonic() - t0, sorted(self.alive_uav))
        return True

    def gone(self, u: int) -> bool:
        """UAV u's token has been away for DROP_CONFIRM_S while the bus stayed up: a death or a
        freeze, not an outage (which deletes every token at once, the monitor's too)."""
        if u in self.alive_uav:
            return False
        while (left := DROP_CONFIRM_S - (time.monotonic() - self.gone_since.get(u, 0.0))) > 0:
            self.pump(left)  # let the rest of a burst of deletions (an outage) arrive
        return u not in self.alive_uav and self.connected()

    def settle_membership(self, k: int) -> None:
        """Before opening epoch k: if members of the last epoch vanished, tell a death from an
        outage (wait for the bus to come back in the latter)."""
        if set(self.part_prev) - self.alive_uav:
            for u in sorted(set(self.part_prev) - self.alive_uav):
                if not self.gone(u):
                    break
            self.ride_out_outage(k)

    def recover_estimates(self, k: int, missing: list[int]) -> None:
        """Ask the nodes' state queryables for epoch-k estimates that never arrived (published while
        the bus was down); replies carry the node's recent estimates."""
        for u in missing:
            try:
                for rep in self.s.get(keys.uav(self.run, u, "state") + f"?k={k};r=0", timeout=1.0):
                    if rep.ok is None:
                        continue
                    h = M.decode(M.HistoryMsg, rep.ok.payload.to_bytes(), uav=u)
                    for e in h.estimates:
                        if e.uav == u:
                            self.estimates.setdefault(e.k, set()).add(u)
            except M.WireError as e:
                self.rejects.add("state-query", e)

    def publish_epoch(self, k: int, part: list[int], only: list[int] | None = None) -> None:
        t = self.meta.epoch_time(k)
        self.clock(k, participants=part)
        for u in (part if only is None else only):
            j = self.uavs.index(u)
            tm = M.TruthMsg(uav=u, k=k, t=t, pos=list(map(float, self.truth.pos[k - 1, j])),
                            vel=list(map(float, self.truth.vel[k - 1, j])), quat=list(map(float, self.truth.quat[k - 1, j])))
            self.pub_truth[u].put(tm.encode())
            b = M.encode_input(self.slicer.epoch(k, u), part)
            self.bytes_per_uav += len(b)
            self.pub_input[u].put(b)

    def wait_estimates(self, k: int, part: list[int]) -> None:
        """Lockstep: wait until every participant of epoch k has published its estimate or lost its
        token; after an outage re-send the epoch to whoever has not answered and recover estimates
        sent into the outage by query."""
        dl = Deadline(self.a.epoch_timeout)
        last_try = time.monotonic()
        while True:
            missing = [u for u in part if u not in self.estimates.get(k, ()) and not self.gone(u)]
            if not missing:
                return
            if self.ride_out_outage(k) or time.monotonic() - last_try > self.a.requery_s:
                last_try = time.monotonic()
                self.recover_estimates(k, missing)
                missing = [u for u in part if u not in self.estimates.get(k, ()) and not self.gone(u)]
                if missing:
                    self.log.info("epoch %d: re-sending the epoch to %s (no estimate yet)", k, missing)
                    self.publish_epoch(k, part, only=missing)
                continue
            if dl.passed():
                self.log.warning("timeout (%.0f s) waiting for estimates of epoch %d from %s", self.a.epoch_timeout, k, missing)
                return
            self.pump(min(0.2, dl.left() + 1e-3))

    def play(self) -> int:
        a = self.a
        need_mon = not a.no_monitor
        self.wait_until(lambda: self.alive_uav >= set(self.uavs) and (self.monitor_alive or not need_mon),
                        a.startup_timeout, f"all {len(self.uavs)} UAV nodes and the monitor to come up")
        self.log.info("start: %d epochs, live UAVs %s", self.K, sorted(self.alive_uav))
        kills = sorted((t, u) for u, t in a.kill)
        restarts = sorted((t, u) for u, t in a.restart)
        t_wall0 = time.monotonic()
        self.part_prev = sorted(self.alive_uav)
        k = 1
        while k <= self.K:
            self.k = k
            t = self.meta.epoch_time(k)
            self.settle_membership(k)
            while kills and kills[0][0] <= t + 1e-9:
                _, u = kills.pop(0)
                self.clock(k, hold="kill", hold_uav=u, participants=sorted(self.alive_uav))
                self.wait_until(lambda: u not in self.alive_uav, a.fault_timeout, f"UAV {u} to be killed")
            while restarts and restarts[0][0] <= t + 1e-9:
                _, u = restarts.pop(0)
                self.clock(k, hold="restart", hold_uav=u, participants=sorted(self.alive_uav))
                self.wait_until(lambda: u in self.alive_uav, a.fault_timeout, f"UAV {u} to restart")
            if a.rate:
                due = t_wall0 + (t - self.meta.t_start) / a.rate
                while time.monotonic() < due:
                    self.pump(max(0.0, min(0.05, due - time.monotonic())))
                if not self.connected():  # real time goes on: the epochs of the outage are lost, and said so
                    t_out = time.monotonic()
                    self.ride_out_outage(k)
                    now_k = min(self.K, max(k, int((time.monotonic() - t_wall0) * a.rate / self.meta.epoch_dt_s) + 1))
                    if now_k > k:
                        self.lost.append((k, now_k - 1))
                        self.log.warning("epochs %d-%d lost in a %.1f s bus outage (real-time mode)", k, now_k - 1,
                                         time.monotonic() - t_out)
                        self.clock(now_k, participants=sorted(self.alive_uav), lost=[k, now_k - 1])
                        k = now_k
                        continue
            else:
                self.pump(0)
                self.settle_membership(k)
            part = sorted(self.alive_uav)
            self.part_prev = part
            if a.garbage_at == k:
                self.garbage(k)
            self.publish_epoch(k, part)
            if not a.rate:
                self.wait_estimates(k, part)
            self.estimates.pop(k - 2, None)
            k += 1
        if a.rate:
            self.wait_until(lambda: all(u in self.estimates.get(self.K, ()) or u not in self.alive_uav for u in self.uavs),
                            a.epoch_timeout, "the last estimates")
        self.finish_clock()
        self.log.info("done: %d epochs in %.1f s wall; sensor bytes per UAV-epoch %.0f; lost epochs %s; rejected %d %s",
                      self.K, time.monotonic() - t_wall0, self.bytes_per_uav / max(1, self.K * len(self.uavs)),
                      self.lost or "none", self.rejects.total, self.rejects.as_dict())
        return 0

    def finish_clock(self) -> None:
        """Publish ``done`` until every node and the monitor have gone (they exit on it), so a done
        sent into an outage is repeated; bounded by ``--done-timeout``."""
        dl = Deadline(self.a.done_timeout)
        while True:
            self.clock(self.K, done=True, participants=sorted(self.alive_uav))
            self.wait_until(lambda: not self.alive_uav and not self.monitor_alive, 1.0, "", quiet=True)
            if (not self.alive_uav and not self.monitor_alive) or dl.passed():
                break
        time.sleep(0.2)  # let the last clock message leave before the session closes


DROP_CONFIRM_S = 0.3


class OutageError(RuntimeError):
    """The bus stayed down longer than --outage-timeout."""


def main(argv=None) -> int:
    args = parse_args(argv)
    log = setup_logging("sensor_sim")
    import zenoh

    sim = None
    with zenoh.open(client_config(args.router, args.zenoh_config)) as session:
        sim = SensorSim(args, session, log)
        install_signals(sim.inbox)
        try:
            sim.setup()
            rc = sim.play()
        except KeyboardInterrupt:
            log.info("stopped by signal at epoch %d", sim.k)
            rc = 0
        except OutageError as e:
            log.error("%s: giving up", e)
            rc = 4
        finally:
            sim.inbox.stop.set()
            undeclare_all(getattr(sim, "subs", []))
    return finish_process(sim.inbox, log, rc) if sim is not None else rc
