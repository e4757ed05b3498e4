"""The process launcher/supervisor behind ``swarmnav launch``.

Opens an embedded Zenoh router in this process (loopback listen endpoint on a free port, multicast
scouting off) and starts the monitor, N uav_node processes and the sensor-sim, each its own OS
process (``python -m services.<name>``) with its own log file under ``<run>/logs/``, OMP/BLAS
threads = 1. The UAV node processes are forked by a zygote (deploy/zygote.py) that has imported
their modules once, unless ``SWARMNAV_ZYGOTE=0`` or ``SWARMNAV_PROFILE`` is set; if the zygote dies,
the run stops.

Secure by default (services/runtime/security.py): the router listens on mutual TLS only and enforces an ACL
generated from ``swarmnav.wire.keys``; every service connects with its own certificate
(``<run>/security/<principal>.json5``). ``insecure=True`` gives a plain TCP router without ACL.

Supervision: it follows the sensor-sim's clock (progress bar; scheduled ``--kill``/``--restart``
holds at simulation time T). An essential service (sensor-sim, monitor) that dies before the run is
done stops the run at once with a message naming it; a UAV node that dies unscheduled is reported
(the swarm goes on without it). SIGINT/SIGTERM stops every child (SIGTERM, SIGKILL after a short
grace) within seconds. Children get PR_SET_PDEATHSIG=SIGTERM so none outlives a killed launcher.
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from deploy.zygote import EXIT_UNKNOWN, Zygote, ZygoteLost, ZygoteProc
from services.runtime.zconf import free_port, router_config
from swarmnav.wire import keys
from swarmnav.wire import messages as M

REPO = Path(__file__).resolve().parents[1]
STOP_GRACE_S = 2.5  # SIGTERM -> SIGKILL for children when the run is stopped
MONITOR_GRACE_S = 4.0  # ... the monitor, which writes the run's report on SIGTERM, gets longer


def _pdeathsig():
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Proc:
    name: str
    argv: list[str]
    log: Path
    p: subprocess.Popen | ZygoteProc | None = None
    expected_kill: bool = False
    history: list[int] = field(default_factory=list)  # exit codes of earlier incarnations
    zygote: Zygote | None = None  # started as a fork of this zygote instead of with Popen


@dataclass
class LaunchSpec:
    run_dir: Path
    dataset: Path
    seed: int
    algo: str
    uavs: list[int]
    n_epochs: int
    kills: list[tuple[int, float]]
    restarts: list[tuple[int, float]]
    config_sha256: str | None = None
    rate: float | None = None
    progress: bool = True
    timeout_s: float = 3600.0
    secure: bool = True
    sim_extra: list[str] = field(default_factory=list)  # extra sensor_sim arguments (test hooks)
    live: tuple[str, int] | None = None  # the monitor also serves the recording live on (bind address, port)
    web_port: int | None = None  # ... and a Rerun web viewer is served on this port (when no display is there)


@dataclass
class LaunchResult:
    status: int
    processes: dict
    stop_reason: str | None  # None: the run reached its end; else why it was stopped, in words
    events: list[dict]
    security: dict


def _env() -> dict:
    env = dict(os.environ)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        env[v] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("MALLOC_ARENA_MAX", "2")  # glibc: 2 heaps, not one per thread (-16 MB RSS per UAV process)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(REPO / "shared")] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def start(proc: Proc) -> None:
    proc.log.parent.mkdir(parents=True, exist_ok=True)
    if proc.zygote is not None:
        proc.p = proc.zygote.spawn(proc.argv, proc.log)
        return
    f = open(proc.log, "ab")
    proc.p = subprocess.Popen(proc.argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=str(REPO),
                              env=_env(), preexec_fn=_pdeathsig)
    f.close()


def stop_all(procs: list[Proc], grace: float = STOP_GRACE_S) -> None:
    """SIGTERM every live child, SIGKILL whoever is still there after ``grace`` seconds (the
    monitor, writing the report, after ``MONITOR_GRACE_S``)."""
    live = [p for p in procs if p.p is not None and p.p.poll() is None]
    for p in live:
        try:
            p.p.send_signal(signal.SIGTERM)
        except ProcessLookupError:
            pass
    t0 = time.monotonic()
    for p in sorted(live, key=lambda p: p.name == "monitor"):  # the monitor last: it has the longest grace
        end = t0 + (max(grace, MONITOR_GRACE_S) if p.name == "monitor" else grace)
        try:
            p.p.wait(timeout=max(0.05, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.p.kill()
            p.p.wait()


def _last_error(log: Path) -> str:
    """``: <the last ERROR line of a service's log>`` (its own account of why it stopped), or ''."""
    try:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if " ERROR " in ln]
    except OSError:
        return ""
    return f" — it said: {lines[-1].split(' ERROR ', 1)[1][:200]}" if lines else ""


def describe_exit(rc: int | None) -> str:
    if rc is None:
        return "still running"
    if rc == EXIT_UNKNOWN:
        return "exit status unknown (its zygote died)"
    if rc < 0:
        try:
            return f"killed by {signal.Signals(-rc).name}"
        except ValueError:
            return f"killed by signal {-rc}"
    return f"exit {rc}"


def _build_procs(spec: LaunchSpec, router: str, run_id: str, sec) -> tuple[Proc, dict[int, Proc], Proc]:
    logs = spec.run_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    prof = os.environ.get("SWARMNAV_PROFILE")  # dev hook: CPU-time cProfile of every service into <run>/logs/<name>.prof

    def pyrun(name: str) -> list[str]:
        return [py, "-m", "deploy.profrun", str(logs / f"{name}.prof")] if prof else [py]

    def common(principal: str) -> list[str]:
        c = ["--router", router, "--run", run_id]
        path = sec.client_config_path(principal)
        return c + (["--zenoh-config", str(path)] if path else [])

    mon = Proc("monitor", [*pyrun("monitor"), "-m", "services.monitor", *common("monitor"), "--dataset", str(spec.dataset),
                           "--seed", str(spec.seed), "--algo", spec.algo, "--out", str(spec.run_dir),
                           "--security-mode", sec.mode, "--acl", "on" if sec.acl else "off"]
               + [a for u, t in spec.kills for a in ("--kill", f"{u}@{t}")]
               + [a for u, t in spec.restarts for a in ("--restart", f"{u}@{t}")]
               + (["--config-sha256", spec.config_sha256] if spec.config_sha256 else [])
               + (["--live", f"{spec.live[0]}:{spec.live[1]}"] if spec.live else []), logs / "monitor.log")
    nodes = {u: Proc(f"uav{u}", [*pyrun(f"uav{u}"), "-m", "services.uav_node", *common(f"uav-{u}"), "--uav", str(u),
                                 "--algo", spec.algo], logs / f"uav{u}.log") for u in spec.uavs}
    sim_argv = [*pyrun("sensor_sim"), "-m", "services.sensor_sim", *common("sensor-sim"), "--dataset", str(spec.dataset),
                "--seed", str(spec.seed)]
    for u, t in spec.kills:
        sim_argv += ["--kill", f"{u}@{t}"]
    for u, t in spec.restarts:
        sim_argv += ["--restart", f"{u}@{t}"]
    sim_argv += spec.sim_extra
    if spec.rate:
        sim_argv += ["--rate", str(spec.rate)]
    return mon, nodes, Proc("sensor_sim", sim_argv, logs / "sensor_sim.log")


def use_zygote() -> bool:
    """UAV node processes are forked by a zygote unless ``SWARMNAV_ZYGOTE=0``, or under
    ``SWARMNAV_PROFILE`` (deploy/profrun.py runs each service under cProfile from its first import)."""
    return os.environ.get("SWARMNAV_ZYGOTE", "1") != "0" and not os.environ.get("SWARMNAV_PROFILE")


def launch(spec: LaunchSpec) -> LaunchResult:
    """Run the swarm; returns the exit status, per-process summary, why it stopped and the
    launcher's own events (unscheduled deaths)."""
    import zenoh
    from tqdm import tqdm

    from services.runtime import security

    run_id = f"r{uuid.uuid4().hex[:10]}"
    port = free_port()
    sec = security.for_run(spec.run_dir, run_id, spec.uavs, port, secure=spec.secure)
    if not spec.secure:
        print("swarmnav launch: WARNING: --insecure: the router accepts any client on "
              f"{sec.endpoint} and enforces no access control (debugging only)", file=sys.stderr)
    mon, nodes, sim = _build_procs(spec, sec.endpoint, run_id, sec)
    procs = [mon, *nodes.values(), sim]
    viewer = live_viewer(spec) if spec.live else None
    if viewer is not None:
        viewer.expected_kill = True  # stopped with the run on purpose: its exit status says nothing
        procs.append(viewer)
    zygote = None
    events: list[dict] = []
    t0 = time.monotonic()  # --timeout counts from here
    bar = tqdm(total=spec.n_epochs, desc="epochs", unit="ep", disable=not spec.progress, file=sys.stderr)
    stopping = {"sig": None}

    def on_signal(signum, frame):
        stopping["sig"] = signum

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        try:
            session = zenoh.open(sec.router_config())
        except zenoh.ZError as e:  # e.g. the port was taken between free_port() and now
            from swarmnav.errors import SwarmnavError

            why = str(e).split(" at /")[0]
            raise SwarmnavError(f"cannot open the run's Zenoh router on {sec.endpoint} ({why}); no process was "
                                "started: run again (a new port is chosen)") from None
        with session:
            clock = session.declare_subscriber(keys.clock(run_id), zenoh.handlers.FifoChannel(10000))
            try:
                if use_zygote():
                    zygote = Zygote(spec.run_dir, spec.algo, [n.argv + ["--rejoin"] for n in nodes.values()],
                                    spec.run_dir / "logs" / "zygote.log", cwd=str(REPO), env=_env(), preexec_fn=_pdeathsig)
                    for n in nodes.values():
                        n.zygote = zygote
                try:
                    for p in procs:
                        start(p)
                    done, status, reason = _supervise(spec, t0, clock, sim, mon, nodes, bar, stopping, events, zygote)
                except ZygoteLost as e:
                    done, status, reason = False, 1, _zygote_lost(str(e), zygote)
                bar.close()
                if done:  # the run is over: let the services finish on their own (the monitor writes its report)
                    _wait_finish(sim, mon, nodes, stopping)
                else:
                    print(f"\nswarmnav launch: {reason}", file=sys.stderr)
            finally:
                stop_all(procs)
                if zygote is not None:
                    zygote.close()
                    if zygote.hung:
                        print(f"\nswarmnav launch: the UAV zygote {zygote.hung} (see {zygote.log})", file=sys.stderr)
                try:
                    clock.undeclare()
                except Exception:  # session already closing
                    pass
    finally:
        for s_, h in old.items():
            signal.signal(s_, h)
    summary = {}
    for p in procs + ([Proc("zygote", zygote.argv, zygote.log, zygote.p)] if zygote else []):
        rc = p.p.returncode if p.p else None
        summary[p.name] = {"exit": rc, "killed_by_schedule": p.expected_kill, "earlier": p.history}
        if rc != 0 and status == 0 and not p.expected_kill:
            status = 1
    return LaunchResult(status, summary, reason, events, sec.report_block())


def _zygote_lost(why: str, zygote: Zygote) -> str:
    return f"the UAV zygote failed ({why}): its UAV processes die with it; stopping the run (see {zygote.log})"


def _supervise(spec: LaunchSpec, t0: float, clock, sim: Proc, mon: Proc, nodes: dict[int, Proc], bar, stopping: dict,
               events: list[dict], zygote: Zygote | None) -> tuple[bool, int, str | None]:
    """Follow the sensor-sim's clock until it says done: progress, scheduled kills and restarts
    (``hold``), unscheduled deaths (appended to ``events``). Stops early on a signal, the timeout or
    the death of the sensor-sim, the monitor or the UAV zygote (``t0``: time.monotonic() at the
    launch). -> (done, status, reason)."""
    last_k, last_t = 0, 0.0
    while True:
        if stopping["sig"] is not None:
            return False, 130, f"stopped by {signal.Signals(stopping['sig']).name}"
        if time.monotonic() - t0 > spec.timeout_s:
            return False, 1, f"timed out after {spec.timeout_s:.0f} s (--timeout)"
        dead = [p for p in (sim, mon) if p.p.poll() is not None]
        if dead:
            p = dead[0]
            return False, 1, (f"the {p.name.replace('_', '-')} died ({describe_exit(p.p.returncode)}) at epoch "
                              f"{last_k} before the run was done: stopping the run{_last_error(p.log)} (see {p.log})")
        if zygote is not None and zygote.check():
            return False, 1, _zygote_lost(f"{zygote.lost}, at epoch {last_k}", zygote)
        # every clock message already here first: a node that exits on ``done`` must not be taken for a death
        got = 0
        while (s := clock.try_recv()) is not None:
            got += 1
            try:
                c = M.decode(M.ClockMsg, s.payload.to_bytes())
            except M.WireError:
                continue
            last_t = c.t
            if c.k > last_k and not c.done:
                bar.update(c.k - last_k)
                last_k = c.k
            _act_on_hold(c, nodes)
            if c.done:
                return True, 0, None
        _note_unscheduled_deaths(nodes, events, last_t, last_k)
        if not got:
            time.sleep(0.02)


def _note_unscheduled_deaths(nodes: dict[int, Proc], events: list[dict], last_t: float, last_k: int) -> None:
    """A node process that died without being killed on schedule: an event, reported once; the swarm goes on."""
    for u, n in nodes.items():
        if n.p.poll() is not None and not n.expected_kill and not getattr(n, "_reported", False):
            n._reported = True
            events.append({"t": last_t, "kind": "process_died", "uav": u, "detail": describe_exit(n.p.returncode)})
            print(f"\nswarmnav launch: UAV {u}'s process died unscheduled ({describe_exit(n.p.returncode)}) "
                  f"at epoch {last_k}; the swarm goes on without it (see {n.log})", file=sys.stderr)


def _act_on_hold(c, nodes: dict[int, Proc]) -> None:
    """The clock holds for a scheduled fault: SIGKILL the UAV's process, or restart it (``--rejoin``)."""
    if c.hold == "kill" and c.hold_uav in nodes:
        n = nodes[c.hold_uav]
        if n.p.poll() is None:
            n.expected_kill = True
            n.p.send_signal(signal.SIGKILL)
            n.history.append(n.p.wait())
    elif c.hold == "restart" and c.hold_uav in nodes:
        n = nodes[c.hold_uav]
        if n.p.poll() is not None:
            if not n.expected_kill:
                n.history.append(n.p.returncode)
            n.expected_kill = False
            n._reported = False
            n.argv = n.argv + (["--rejoin"] if "--rejoin" not in n.argv else [])
            start(n)


def rerun_binary() -> Path:
    """The Rerun viewer's executable itself: the venv's ``rerun`` script is a Python wrapper that
    runs it as a child, which a SIGTERM to the wrapper would leave running."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file():
            return exe
    except ImportError:
        pass
    return Path(sys.executable).with_name("rerun")


def live_viewer(spec: LaunchSpec) -> Proc | None:
    """Say where the live recording is served; open a native Rerun viewer on it when there is a
    display (it outlives the run), else return a web-viewer process to start with the run (a browser
    anywhere that reaches this machine shows it; it stops with the run, the page keeps its data)."""
    from services.recording import live_url

    bind, port = spec.live
    local = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
    shown = socket.gethostname() if bind in ("0.0.0.0", "::") else bind
    url = live_url(local, port)
    rerun = rerun_binary()
    print(f"swarmnav launch: live recording served at {live_url(shown, port)} "
          f"(a viewer anywhere: rerun {live_url(shown, port)})", file=sys.stderr)
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        with open(spec.run_dir / "logs" / "viewer.log", "ab") as f:
            subprocess.Popen([str(rerun), url], stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             start_new_session=True)
        print("swarmnav launch: opened a Rerun viewer on it", file=sys.stderr)
        return None
    if spec.web_port is None:
        return None
    web = f"http://{shown}:{spec.web_port}/?url=" + urllib.parse.quote(live_url(shown, port), safe="")
    print(f"swarmnav launch: no display here: web viewer at {web}", file=sys.stderr)
    return Proc("web_viewer", [str(rerun), "--serve-web", "--bind", bind, "--web-viewer-port", str(spec.web_port),
                               live_url(shown, port)], spec.run_dir / "logs" / "web_viewer.log")


def _wait_finish(sim: Proc, mon: Proc, nodes: dict[int, Proc], stopping: dict) -> None:
    """After the clock's ``done``: every service ends by itself (the monitor writes its report);
    bounded waits, and a signal to the launcher cuts them short."""
    limits = [(sim, 15.0), (mon, 120.0)] + [(n, 15.0) for n in nodes.values()]
    for p, lim in limits:
        end = time.monotonic() + lim
        while p.p.poll() is None and time.monotonic() < end and stopping["sig"] is None:
            time.sleep(0.05)
