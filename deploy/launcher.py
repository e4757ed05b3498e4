"""The process launcher/supervisor behind ``swarmnav launch``.

Opens an embedded Zenoh router in this process (mode router, loopback listen endpoint on a
free port, multicast scouting off), starts the monitor, N uav_node processes and the
sensor-sim, each its own OS process (``python -m services.<name>``) with its own log file under
``<run>/logs/``, OMP/BLAS threads = 1. It follows the sensor-sim's clock: a progress bar, and the
scheduled faults (``--kill ID@T`` SIGKILLs the UAV's process, ``--restart ID@T`` starts it again
with ``--rejoin``) at simulation time T, while the clock holds for them. Children get
PR_SET_PDEATHSIG=SIGTERM so none outlives a killed launcher; on exit every child still running is
sent SIGTERM, then SIGKILL after a grace period, and the router session is closed.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from deploy.zconf import free_port, router_config
from swarmnav.wire import keys
from swarmnav.wire import messages as M

REPO = Path(__file__).resolve().parents[1]


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
    p: subprocess.Popen | None = None
    expected_kill: bool = False
    history: list[int] = field(default_factory=list)  # exit codes of earlier incarnations


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
    sim_extra: list[str] = field(default_factory=list)  # extra sensor_sim arguments (test hooks)


def _env() -> dict:
    env = dict(os.environ)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        env[v] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(REPO / "shared")] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def start(proc: Proc) -> None:
    proc.log.parent.mkdir(parents=True, exist_ok=True)
    f = open(proc.log, "ab")
    proc.p = subprocess.Popen(proc.argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=str(REPO),
                              env=_env(), preexec_fn=_pdeathsig)
    f.close()


def stop_all(procs: list[Proc], grace: float = 8.0) -> None:
    live = [p for p in procs if p.p is not None and p.p.poll() is None]
    for p in live:
        p.p.send_signal(signal.SIGTERM)
    end = time.monotonic() + grace
    for p in live:
        try:
            p.p.wait(timeout=max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.p.kill()
            p.p.wait()


def launch(spec: LaunchSpec) -> tuple[int, dict]:
    """Run the swarm; returns (exit status, {process name: exit code summary})."""
    import zenoh

    run_id = f"r{uuid.uuid4().hex[:10]}"
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    logs = spec.run_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    prof = os.environ.get("SWARMNAV_PROFILE")  # dev hook: CPU-time cProfile of every service into <run>/logs/<name>.prof

    def pyrun(name: str) -> list[str]:
        return [py, "-m", "deploy.profrun", str(logs / f"{name}.prof")] if prof else [py]

    common = ["--router", router, "--run", run_id]
    mon = Proc("monitor", [*pyrun("monitor"), "-m", "services.monitor", *common, "--dataset", str(spec.dataset), "--seed", str(spec.seed),
                           "--algo", spec.algo, "--out", str(spec.run_dir)]
               + (["--config-sha256", spec.config_sha256] if spec.config_sha256 else []), logs / "monitor.log")
    nodes = {u: Proc(f"uav{u}", [*pyrun(f"uav{u}"), "-m", "services.uav_node", *common, "--uav", str(u), "--algo", spec.algo],
                     logs / f"uav{u}.log") for u in spec.uavs}
    sim_argv = [*pyrun("sensor_sim"), "-m", "services.sensor_sim", *common, "--dataset", str(spec.dataset), "--seed", str(spec.seed)]
    for u, t in spec.kills:
        sim_argv += ["--kill", f"{u}@{t}"]
    for u, t in spec.restarts:
        sim_argv += ["--restart", f"{u}@{t}"]
    sim_argv += spec.sim_extra
    if spec.rate:
        sim_argv += ["--rate", str(spec.rate)]
    sim = Proc("sensor_sim", sim_argv, logs / "sensor_sim.log")
    procs = [mon, *nodes.values(), sim]
    status = 0
    t0 = time.monotonic()
    from tqdm import tqdm

    bar = tqdm(total=spec.n_epochs, desc="epochs", unit="ep", disable=not spec.progress, file=sys.stderr)
    stopping = {"sig": None}

    def on_signal(signum, frame):
        stopping["sig"] = signum

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    with zenoh.open(router_config([router])) as session:
        clock = session.declare_subscriber(keys.clock(run_id), zenoh.handlers.FifoChannel(10000))
        try:
            for p in procs:
                start(p)
            done = False
            last_k = 0
            while not done:
                if stopping["sig"] is not None:
                    status = 130
                    break
                if time.monotonic() - t0 > spec.timeout_s:
                    print(f"swarmnav launch: timeout after {spec.timeout_s:.0f} s", file=sys.stderr)
                    status = 1
                    break
                s = clock.try_recv()
                if s is None:
                    if sim.p.poll() is not None:
                        break
                    if mon.p.poll() is not None:
                        print("swarmnav launch: monitor exited early", file=sys.stderr)
                        status = 1
                        break
                    time.sleep(0.02)
                    continue
                try:
                    c = M.decode(M.ClockMsg, s.payload.to_bytes())
                except M.WireError:
                    continue
                if c.k > last_k and not c.done:
                    bar.update(c.k - last_k)
                    last_k = c.k
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
                        n.argv = n.argv + (["--rejoin"] if "--rejoin" not in n.argv else [])
                        start(n)
                if c.done:
                    done = True
            bar.close()
            # the run is over: let the services finish on their own, then make sure
            for p in [sim, mon, *nodes.values()]:
                try:
                    p.p.wait(timeout=60 if p is mon else 15)
                except subprocess.TimeoutExpired:
                    pass
        finally:
            stop_all(procs)
            clock.undeclare()
            for s_, h in old.items():
                signal.signal(s_, h)
    summary = {}
    for p in procs:
        rc = p.p.returncode if p.p else None
        summary[p.name] = {"exit": rc, "killed_by_schedule": p.expected_kill, "earlier": p.history}
        if rc not in (0,) and status == 0:
            status = 1
    return status, summary
