"""uav_node: one UAV's estimator as its own process on Zenoh (docs/architecture.md).

Start-up: query the run's dataset meta and this UAV's initial knowledge from the sensor-sim
(``meta``, ``uav/<id>/init``), build the estimator with ``registry.make_node`` and the same
settings as the in-process run; declare subscribers (own sensor keys, every peer's ``state``,
liveliness, clock) and the ``state`` queryable; then declare the liveliness token.

Epoch k: the sensor-sim's ``input`` frame (one binary message: the EpochInput and the epoch's
participants), then drive :func:`swarmnav.protocol.node_epoch`: publish
each round's state, wait for the same round's state of every participant that is still live
(liveliness), hand them to the generator sorted by id; publish the final estimate and links.
A peer that is live is waited for; after ``peer_timeout_s`` its state is re-queried; a peer whose
liveliness token disappears is dropped at once. A restarted node (``--rejoin``) bootstraps
from its peers' latest states (queried) and its first epoch's input (``estimator.bootstrap``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque

from services.runtime.service import (Deadline, Inbox, code_digest, finish_process, install_signals, parse_key, setup_logging,
                            undeclare_all)
from services.runtime.zconf import client_config
from services.settings import settings_for_dataset
from swarmnav.dataset import DatasetMeta
from swarmnav.estimators import registry
from swarmnav.estimators.base import NodeState
from swarmnav.protocol import node_epoch
from swarmnav.scenario import estimation_values
from swarmnav.wire import keys
from swarmnav.wire import messages as M

HISTORY = 20
RECONNECT_GRACE_S = 3.0
SWITCH_INTERVAL_S = 0.05  # the GIL switch interval of --cpu-policy batch (set_cpu_policy)
FUTURE_SLACK = 50  # a peer state this many epochs beyond the clock (and our own) is forged: rejected
DROP_CONFIRM_S = 0.3  # a peer's token gone this long while the bus is up: dead (or frozen), not an outage  # after the bus comes back, peers' tokens reappear within ~1 s: wait for them


class StaleEpoch(RuntimeError):
    """The swarm finished later epochs without this node: the epoch in hand is stale."""


class OutageError(RuntimeError):
    """The bus stayed down longer than --outage-timeout."""


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="uav_node")
    p.add_argument("--router", required=True, help="zenoh endpoint of the router, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--run", required=True)
    p.add_argument("--uav", type=int, required=True)
    p.add_argument("--algo", default="atvfg")
    p.add_argument("--rejoin", action="store_true", help="restarted node: bootstrap from peers")
    p.add_argument("--zenoh-config", default=None)
    p.add_argument("--startup-timeout", type=float, default=120.0)
    p.add_argument("--sim-lost-timeout", type=float, default=30.0,
                   help="exit (status 4) when the sensor-sim has been gone this long while the bus is up (s)")
    p.add_argument("--outage-timeout", type=float, default=120.0, help="exit (status 4) when the bus stays down this long (s)")
    p.add_argument("--envelope-m", type=float, default=M.ENVELOPE_M,
                   help="reject peer states farther than this from the local origin (m, any axis)")
    p.add_argument("--cpu-policy", choices=("batch", "normal"), default="batch",
                   help="batch (default): SCHED_BATCH for the process and its threads and a 50 ms GIL switch "
                        "interval (a compute-bound process among many: not preempted by every peer's wake-up); "
                        "normal: the system's and Python's defaults")
    return p.parse_args(argv)


def set_cpu_policy(policy: str, log) -> None:
    """``batch``: tune the process for a crowd of compute-bound processes on few cores (100 UAV
    processes on 2): fewer switches between threads and processes, so warmer caches.

    * SCHED_BATCH for this thread and every thread it starts afterwards (Zenoh's, the pumps): the
      scheduler lets a batch process run out its time slice instead of switching to each thread
      that wakes up (a node of a 100-UAV swarm is woken by ~100 peer states per epoch, and so are
      all the others). 100-UAV scale launch, 3 A/B pairs: UAV CPU -4.0 %, wall -4.1 %.
    * The GIL switch interval 50 ms (Python's default 5 ms): the state pump decodes a peer state in
      ~15 µs and gives the GIL back; the longer interval only stops an idle pump's periodic wake-up
      (a pump blocked in Zenoh's recv wakes 10 times a second: its context switches, measured)
      from forcing the estimator off the GIL mid-solve. 4 interleaved A/B pairs on top of
      SCHED_BATCH: UAV CPU -3.2 %, wall -2.7 %, each pair faster (a gain about the size of the
      drift between separate experiments).

    Call before the Zenoh session opens (its threads inherit the policy). Best effort: where
    SCHED_BATCH cannot be set, a warning and the default policy."""
    if policy != "batch":
        return
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError) as e:
        log.warning("scheduling policy SCHED_BATCH not set (%s): the default policy (the 50 ms switch interval is set)", e)


def cpu_policy_now() -> str:
    """The calling thread's policy as set_cpu_policy leaves it, e.g. ``batch (switch 50 ms)``."""
    names = {getattr(os, "SCHED_BATCH", None): "batch", getattr(os, "SCHED_OTHER", None): "normal"}
    try:
        policy = names.get(os.sched_getscheduler(0), "other")
    except (AttributeError, OSError):
        policy = "unknown"
    return f"{policy} (switch {sys.getswitchinterval() * 1e3:.0f} ms)"


class Node:
    def __init__(self, args, session, log):
        self.a, self.s, self.log = args, session, log
        self.run, self.uav = args.run, args.uav
        self.inbox = Inbox()
        self.rejects = M.Rejects(log)
        self.dead: set[int] = set()  # peers whose liveliness token went away (and did not come back)
        self.dead_since: dict[int, float] = {}  # peer -> monotonic time its token went away
        self.inputs: dict[int, tuple] = {}  # k -> (EpochInput, participants)
        self.states: dict[tuple[int, int], dict[int, NodeState]] = {}  # (k, r) -> uav -> state
        self.history: deque[bytes] = deque(maxlen=HISTORY)  # our last state frames
        self.est_history: deque[M.EstimateMsg] = deque(maxlen=M.EST_HISTORY)  # recovered by the sensor-sim/monitor after an outage
        self.k_done = 0  # last completed epoch
        self.inc = 0  # incarnation: bumped at every (re-)bootstrap, carried in the estimates
        self.need_bootstrap = bool(args.rejoin)  # the next epoch starts from a fresh alignment + peers
        self.peer_newest: dict[int, int] = {}  # peer -> newest epoch seen in its states (the swarm moved on without us?)
        self.newest_count: dict[int, int] = {}  # epoch -> how many peers' newest it is (newest_peer_k without a scan)
        self.clock_k = 0  # newest epoch the sensor-sim's clock opened (states beyond it cannot be genuine)
        self.sim_alive = False
        self.sim_lost_at: float | None = None  # monotonic time the sensor-sim's token went away
        self.offline_since: float | None = None  # monotonic time this session was last seen without a router
        self.online_at = 0.0  # monotonic time connectivity was last seen restored
        self.peer_done_k: dict[int, int] = {}  # peer -> last epoch it is known to have finished (from a query reply)
        self.republish = False  # the bus came back: publish our current state again (it may have been lost)
        self.duplicates = 0  # re-sent inputs of epochs already done (after an outage): ignored
        self.done = False
        self.bytes_out = 0
        self.waiting = None  # ((k, r), peers) the loop waits for in gather()
        self.cpu_first = None  # process CPU time when the first epoch started
        self.cpu_est = self.cpu_wait = 0.0  # process CPU inside the estimator / while gathering peer states

    # -- setup ---------------------------------------------------------------------------
    def query_one(self, key: str, cls, timeout: float, params: str = ""):
        sel = key + (f"?{params}" if params else "")
        dl = Deadline(timeout)
        while not dl.passed() and not self.inbox.stop.is_set():
            for rep in self.s.get(sel, timeout=min(2.0, max(0.1, dl.left()))):
                if rep.ok is not None:
                    try:
                        return M.decode(cls, rep.ok.payload.to_bytes())
                    except M.WireError as e:
                        self.rejects.add(key, e)
            time.sleep(0.2)
        raise TimeoutError(f"no answer on {key}")

    def setup(self):
        a = self.a
        self.code = code_digest()  # right after the imports: the estimator code this process runs
        mm = self.query_one(keys.meta(self.run), M.MetaMsg, a.startup_timeout)
        self.meta = DatasetMeta.model_validate(mm.meta)
        self.uav_ids = set(self.meta.uav_ids())
        self.seed = mm.seed
        self.settings = settings_for_dataset(self.meta)
        est = estimation_values(self.settings)  # [estimation]: defaults in the scenario model only
        self.rounds, self.tol, self.peer_timeout = est.rounds, est.convergence_m, est.peer_timeout_s
        init = self.query_one(keys.uav(self.run, self.uav, "init"), M.InitMsg, a.startup_timeout,
                              "restart=1" if a.rejoin else "")
        self.est = registry.make_node(a.algo, self.uav, self.meta, self.settings, M.msg_to_init(init))
        import zenoh

        ib = self.inbox
        self.subs = [
            self.s.declare_subscriber(keys.uav(self.run, self.uav, "input"), ib.channel()),
            # peers only: our own publications are not echoed back to us
            self.s.declare_subscriber(keys.uav_all(self.run, "state"), ib.channel(), allowed_origin=zenoh.Locality.REMOTE),
            self.s.declare_subscriber(keys.clock(self.run), ib.channel()),
            self.s.liveliness().declare_subscriber(keys.alive_all(self.run), ib.channel(), history=True),
            self.s.declare_queryable(keys.uav(self.run, self.uav, "state"), ib.channel()),
        ]
        # peer states are stored and queries answered right in their pump threads: a query must be
        # answered even while this node's loop is blocked (e.g. in its own re-query of a peer)
        direct = {"state": self.on_state, "query": self.answer}
        for tag, sub in zip(("own", "state", "clock", "alive", "query"), self.subs):
            ib.attach(tag, sub, direct=direct.get(tag))
        self.pub_state = self.s.declare_publisher(keys.uav(self.run, self.uav, "state"))
        # BLOCK: the monitor must record every estimate (a DROP publisher lost one under load)
        bl = zenoh.CongestionControl.BLOCK
        self.pub_est = self.s.declare_publisher(keys.uav(self.run, self.uav, "estimate"), congestion_control=bl)
        self.pub_links = self.s.declare_publisher(keys.uav(self.run, self.uav, "links"), congestion_control=bl)
        self.token = self.s.liveliness().declare_token(keys.alive(self.run, "uav", self.uav))
        self.log.info("UAV %d up: algo %s, rounds %d, rejoin %s, code %s, cpu %s", self.uav, a.algo, self.rounds, a.rejoin,
                      self.code, cpu_policy_now())

    # -- inbox handling (light: decode + buffer) -------------------------------------------
    def handle(self, tag, item):
        if tag == "alive":
            try:
                kk = keys.parse(str(item.key_expr))
            except ValueError:
                return
            import zenoh

            if kk.topic == "sensor_sim":
                self.sim_alive = item.kind == zenoh.SampleKind.PUT
                self.sim_lost_at = None if self.sim_alive else time.monotonic()
                return
            if kk.topic != "uav" or kk.uav == self.uav:
                return
            if item.kind == zenoh.SampleKind.PUT:
                self.dead.discard(kk.uav)
            else:
                self.dead.add(kk.uav)
                self.dead_since[kk.uav] = time.monotonic()
                self.log.info("peer %d lost (liveliness)", kk.uav)
            return
        payload = item.payload.to_bytes()
        kk = parse_key(item.key_expr, self.rejects)
        if kk is None:
            return
        if tag == "clock":
            try:
                c = M.decode(M.ClockMsg, payload)
            except M.WireError as e:
                self.rejects.add("clock", e)
                return
            if c.done:
                self.done = True
            elif c.k > self.clock_k:
                self.clock_k = c.k
            return
        if kk.topic != "input":
            return
        try:
            inp, part = M.decode_input(payload, uav=self.uav)
        except M.WireError as e:
            self.rejects.add("input", e)
            return
        if inp.k <= self.k_done:  # an epoch re-sent after an outage, already done here
            self.duplicates += 1
            return
        # participants are the sensor-sim's to decide; ids the dataset does not have are ignored
        self.inputs[inp.k] = (inp, [u for u in part if u in self.uav_ids])

    def on_state(self, item) -> bool:
        """Peer state sample, in the state channel's pump thread (light: decode + store). True
        (wake the loop) only when the round the loop waits for is complete; a rejected sample is
        counted and returns False (nothing new to act on)."""
        kk = parse_key(item.key_expr, self.rejects)
        if kk is None:
            return False
        if kk.uav == self.uav:
            return False  # our own publication
        try:
            m = M.decode_state(item.payload.to_bytes(), uav=kk.uav, envelope_m=self.a.envelope_m)
        except M.WireError as e:
            self.rejects.add("state", e)
            return False
        if m.k <= self.k_done:  # late state of an epoch we finished (not hostile: peers may lag)
            return False
        if m.k > max(self.clock_k, self.k_done) + FUTURE_SLACK:  # far beyond any opened epoch: forged
            self.rejects.add("state", M.WireError("future", f"state of epoch {m.k}, clock at {self.clock_k}"))
            return False
        if m.k > (old := self.peer_newest.get(m.uav, 0)):
            self.peer_newest[m.uav] = m.k
            cnt = self.newest_count
            cnt[m.k] = cnt.get(m.k, 0) + 1
            if old and cnt.get(old, 0) > 1:
                cnt[old] -= 1
            elif old:
                cnt.pop(old, None)
        have = self.states.setdefault((m.k, m.r), {})
        have[m.uav] = m
        w = self.waiting
        return w is not None and w[0] == (m.k, m.r) and w[1] <= have.keys()

    def answer(self, q) -> bool:
        """State queryable (in its pump thread): ``?k=K;r=R`` -> that state if held, else the latest
        states; always the recent estimates (a peer learns that we finished an epoch)."""
        try:
            params = {p.split("=")[0]: p.split("=")[1] for p in str(q.parameters).split(";") if "=" in p}
            hist = list(self.history)
            if "k" in params and "r" in params:
                k, r = int(params["k"]), int(params["r"])
                hist = [b for b in hist if (s := M.decode_state(b)).k == k and s.r == r]
            msg = M.HistoryMsg.of(self.uav, hist, list(self.est_history))
            q.reply(keys.uav(self.run, self.uav, "state"), msg.encode())
        except Exception as e:  # a bad query must not kill the node
            self.rejects.add("query", M.WireError("bad_query", str(e)))
        finally:
            q.drop()
        return False

    def pump(self, timeout: float, clear: bool = True) -> bool:
        """Handle one inbox item (waiting up to timeout). False when stopping."""
        it = self.inbox.get(timeout, clear)
        if it is not None:
            self.handle(*it)
            # drain whatever else is queued without blocking
            while True:
                it = self.inbox.get(0)
                if it is None:
                    break
                self.handle(*it)
        return not self.inbox.stop.is_set()

    # -- epoch ---------------------------------------------------------------------------
    def ready_epoch(self):
        return min(self.inputs) if self.inputs else None

    def publish(self, pub, msg) -> None:
        b = msg if isinstance(msg, bytes) else msg.encode()
        self.bytes_out += len(b)
        pub.put(b)

    def requery(self, k: int, r: int, missing: list[int]) -> None:
        """Ask the missing peers for their state (k, r), all at once; a reply whose estimates show
        the peer already finished epoch k tells us to stop waiting for it."""
        pending = [(u, self.s.get(keys.uav(self.run, u, "state") + f"?k={k};r={r}", timeout=0.5)) for u in missing]
        for u, replies in pending:
            try:
                for rep in replies:
                    if rep.ok is None:
                        continue
                    h = M.decode(M.HistoryMsg, rep.ok.payload.to_bytes(), uav=u)
                    for s in h.node_states(envelope_m=self.a.envelope_m):
                        if s.k == k and s.r == r:
                            self.states.setdefault((k, r), {})[u] = s
                    if any(e.k >= k for e in h.estimates):
                        self.peer_done_k[u] = max(self.peer_done_k.get(u, 0), max(e.k for e in h.estimates))
            except M.WireError as e:
                self.rejects.add("state-query", e)

    def newest_peer_k(self) -> int:
        """The newest epoch a peer has reached, counting only epochs the sensor-sim's clock has
        opened (a forged state of a later epoch can never make us drop ours as stale)."""
        return max((v for v, n in list(self.newest_count.items()) if n > 0 and v <= self.clock_k + 1), default=0)

    def connected(self) -> bool:
        """This session reaches a router and the sensor-sim is there (a router outage deletes every
        remote liveliness token at once: peers that vanish then are not dead)."""
        now = time.monotonic()
        try:
            up = bool(list(self.s.info.routers_zid()))
        except Exception:  # session closing
            up = False
        if up and self.sim_alive:
            if self.offline_since is not None:
                self.offline_since = None
                self.online_at = now
                self.republish = True
            return True
        if self.offline_since is None:
            self.offline_since = now
        return False

    def abandoned(self) -> str | None:
        """Why this node should give up, if it should: the sensor-sim gone for --sim-lost-timeout
        while a router is reachable (the run is over without its clock), or no router for
        --outage-timeout."""
        now = time.monotonic()
        try:
            up = bool(list(self.s.info.routers_zid()))
        except Exception:  # session closing
            up = False
        if up and self.sim_lost_at is not None and now - self.sim_lost_at > self.a.sim_lost_timeout:
            return f"the sensor-sim has been gone for {now - self.sim_lost_at:.0f} s"
        if not up and self.offline_since is not None and now - self.offline_since > self.a.outage_timeout:
            return f"no router for {now - self.offline_since:.0f} s"
        return None

    def peer_gone(self, u: int) -> bool:
        """Peer u's token went away while this node was connected (a genuine death or freeze), not
        in a bus outage: waited for again for RECONNECT_GRACE_S after connectivity returns."""
        if u not in self.dead:
            return False
        now = time.monotonic()
        if now - self.dead_since.get(u, 0.0) < DROP_CONFIRM_S:  # an outage deletes every token: let the burst arrive
            return False
        return self.connected() and now - self.online_at > RECONNECT_GRACE_S

    def gather(self, k: int, r: int, participants: set[int]) -> dict[int, NodeState]:
        """Wait for state (k, r) of every participant still live; re-query after peer_timeout.
        Raises StaleEpoch when the swarm has moved on without this node (a peer's state two epochs
        ahead: they completed epoch k+1 without us, so we were frozen or cut off)."""
        t0 = time.monotonic()
        requeried = 0.0
        expect, dead_seen = None, True
        while True:
            self.inbox.ev.clear()  # before looking: a wake-up from here on is not lost
            if (newest := self.newest_peer_k()) >= k + 2:
                raise StaleEpoch(f"epoch {k}: peers are already at epoch {newest}")
            have = self.states.get((k, r), {})
            # a participant is waited for until its liveliness token goes away (the sensor-sim saw
            # it live when it opened the epoch, so a token we have not seen yet is not a death);
            # the set is computed again only while a peer is dead (peer_gone changes with time) or
            # after a re-query (peer_done_k): an O(swarm) scan per wake-up otherwise
            if expect is None or dead_seen or self.dead:
                dead_seen = bool(self.dead)
                expect = {u for u in participants if u != self.uav and not (u in self.dead and self.peer_gone(u))
                          and self.peer_done_k.get(u, 0) < k}
            if self.republish and self.history:  # our state of this round may have gone into the outage
                self.republish = False
                self.publish(self.pub_state, self.history[-1])
            self.waiting = ((k, r), expect)  # the state pump wakes us once all of these are in
            missing = expect - have.keys()  # one read of what the pump has stored so far
            if not missing:
                break
            missing = sorted(missing)
            waited = time.monotonic() - t0
            offline = not self.connected()
            if offline and (why := self.abandoned()):
                raise OutageError(why)
            if waited > self.peer_timeout * 10 and not offline:
                self.log.warning("epoch %d round %d: giving up on live peers %s after %.1f s", k, r, missing, waited)
                break
            if waited > self.peer_timeout and waited - requeried > self.peer_timeout and not offline:
                self.log.warning("epoch %d round %d: re-querying states of %s", k, r, missing)
                self.requery(k, r, missing)
                requeried, expect = waited, None  # the replies may say a peer finished epoch k
                continue
            if not self.pump(0.1 if self.dead else 0.2, clear=False):
                raise KeyboardInterrupt
        self.waiting = None
        have = self.states.get((k, r), {})
        return {u: have[u] for u in sorted(have) if u in participants and u != self.uav}

    def rebootstrap(self, k: int, inp) -> None:
        """Start afresh before epoch k, as a restarted node does: a coarse alignment at epoch k from
        the sensor-sim (``init?restart=1;k=K``) and the peers' latest states (queried); the
        incarnation goes up so the monitor can tell the new estimates from the old."""
        if self.k_done and k > self.k_done + 1:
            self.log.warning("missed epochs %d-%d (frozen or cut off): re-bootstrapping at epoch %d", self.k_done + 1, k - 1, k)
        init = self.query_one(keys.uav(self.run, self.uav, "init"), M.InitMsg, 10.0, f"restart=1;k={k}")
        self.est = registry.make_node(self.a.algo, self.uav, self.meta, self.settings, M.msg_to_init(init))
        peers = self.bootstrap_peers()
        self.log.info("bootstrapping at epoch %d from peers %s", k, sorted(peers))
        self.est.bootstrap(inp.t_prev, peers, inp)
        self.inc += 1
        self.need_bootstrap = False

    def run_epoch(self, k: int, first: bool) -> None:
        inp, part = self.inputs.pop(k)
        participants = set(part)
        if self.newest_peer_k() >= k + 2:  # buffered while we were frozen: the swarm is long past it
            self.log.warning("epoch %d is stale (peers at epoch %d): skipped", k, self.newest_peer_k())
            self.need_bootstrap = True
            self.skip_through(k)
            return
        if first and self.a.rejoin:  # restarted process: its estimator was built from init?restart=1
            peers = self.bootstrap_peers()
            self.log.info("bootstrapping at epoch %d from peers %s", k, sorted(peers))
            self.est.bootstrap(inp.t_prev, peers, inp)
            self.inc += 1
            self.need_bootstrap = False
        elif self.need_bootstrap or k != self.k_done + 1:
            self.rebootstrap(k, inp)
        bytes0 = self.bytes_out
        wait = 0.0
        c0 = time.process_time()
        gen = node_epoch(self.est, inp, self.rounds, self.tol, time.perf_counter)
        state = next(gen)
        self.cpu_est += time.process_time() - c0
        used: set[int] = set()
        try:
            while True:
                frame = M.encode_state(state)
                self.history.append(frame)  # the bytes sent (a snapshot), decoded only for a query
                self.publish(self.pub_state, frame)
                t0 = time.monotonic()
                c0 = time.process_time()
                try:
                    got = self.gather(k, state.r, participants)
                except StaleEpoch as e:
                    self.log.warning("%s: dropping the epoch (never published as current) and re-bootstrapping", e)
                    gen.close()
                    self.need_bootstrap = True
                    self.skip_through(k)
                    return
                c1 = time.process_time()
                self.cpu_wait += c1 - c0
                wait += time.monotonic() - t0
                used |= set(got)
                try:
                    state = gen.send(got)
                finally:  # the last send ends the epoch (StopIteration): its estimator time counts too
                    self.cpu_est += time.process_time() - c1
        except StopIteration as stop:
            est = stop.value
        if est.unsent is not None:  # not broadcast, but a restarting peer's query gets our newest state
            self.history.append(M.encode_state(est.unsent))
        em = M.estimate_to_msg(est, wait_ms=wait * 1e3, peers=sorted(used), bytes_out=0, inc=self.inc,
                               rejected=dict(list(self.rejects.as_dict().items())[:64]))
        links = M.LinksMsg(uav=self.uav, k=k, links=em.links).encode()
        size = len(em.encode())
        em.bytes_out = self.bytes_out - bytes0 + size + len(links)
        self.est_history.append(em)
        self.publish(self.pub_links, links)
        self.publish(self.pub_est, em)
        self.k_done = k
        self.skip_through(k)

    def skip_through(self, k: int) -> None:
        """Forget states and inputs of epochs up to k (done, or dropped as stale)."""
        for key in [kr for kr in list(self.states) if kr[0] <= k]:  # list(): the state pump inserts concurrently
            del self.states[key]
        for kk in [x for x in self.inputs if x <= k]:
            del self.inputs[kk]
        if self.need_bootstrap:  # stale: jump to the newest input, older ones are stale as well
            newest = max(self.inputs, default=None)
            for kk in [x for x in self.inputs if x != newest]:
                del self.inputs[kk]

    def bootstrap_peers(self):
        peers = {}
        import zenoh

        # REMOTE only: our own state queryable is declared but cannot answer while we block here,
        # and a local match would make the get wait for its full timeout (others wait for us)
        for rep in self.s.get(keys.uav_all(self.run, "state"), timeout=2.0, allowed_destination=zenoh.Locality.REMOTE):
            if rep.ok is None:
                continue
            try:
                kk = keys.parse(str(rep.ok.key_expr))
                h = M.decode(M.HistoryMsg, rep.ok.payload.to_bytes(), uav=kk.uav)
                states = h.node_states(envelope_m=self.a.envelope_m)
            except (ValueError, M.WireError) as e:
                self.rejects.add("bootstrap", e if isinstance(e, M.WireError) else M.WireError("bad_key", str(e)))
                continue
            if h.uav != self.uav and states:
                peers[h.uav] = states[-1]
        return dict(sorted(peers.items()))

    def loop(self) -> int:
        first = True
        while not self.inbox.stop.is_set():
            k = self.ready_epoch()
            if k is not None:
                if self.uav not in self.inputs[k][1]:
                    self.inputs.pop(k)
                    continue
                if first:
                    self.cpu_first = time.process_time()
                self.run_epoch(k, first)
                first = False
                continue
            if self.done:
                break
            if not self.connected() and (why := self.abandoned()):
                self.log.error("%s: stopping", why)
                return 4
            self.pump(0.5)
            if self.sim_lost_at is not None or self.offline_since is not None:
                self.connected()
        return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    log = setup_logging(f"uav{args.uav}")
    set_cpu_policy(args.cpu_policy, log)
    import zenoh

    node = None
    with zenoh.open(client_config(args.router, args.zenoh_config)) as session:
        node = Node(args, session, log)
        install_signals(node.inbox)
        try:
            node.setup()
            rc = node.loop()
        except (KeyboardInterrupt, TimeoutError) as e:
            log.info("stopping: %s", type(e).__name__)
            rc = 0 if isinstance(e, KeyboardInterrupt) else 3
        except OutageError as e:
            log.error("stopping: %s", e)
            rc = 4
        finally:
            node.inbox.stop.set()
            log.info("UAV %d exiting after epoch %d; rejected messages: %d %s; re-sent inputs ignored: %d; incarnation %d",
                     args.uav, node.k_done, node.rejects.total, node.rejects.as_dict(), node.duplicates, node.inc)
            cpu, c0 = time.process_time(), getattr(node, "cpu_first", None)
            log.info("messages received by kind: %s", node.inbox.counts)
            log.info("CPU %.2f s (start-up %s s, epochs %s s: estimator %.2f s, gathering peer states %.2f s)", cpu,
                     "-" if c0 is None else f"{c0:.2f}", "-" if c0 is None else f"{cpu - c0:.2f}", node.cpu_est,
                     node.cpu_wait)
            undeclare_all(getattr(node, "subs", []))
    return finish_process(node.inbox, log, rc) if node is not None else rc
