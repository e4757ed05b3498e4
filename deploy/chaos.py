"""Fault campaign on configs/smoke.toml: ``python -m deploy.chaos [--out DIR] [--seed 1] [--quick]``.

Runs the smoke swarm (5 UAVs, 60 epochs of 1 s, master UAV 2, atvfg) unfaulted, then once per fault:
scheduled kills (a slave, two slaves, the master, the master restarted), a frozen node (SIGSTOP for
20 s), a SIGKILLed monitor (then ``swarmnav report``), a SIGKILLed sensor-sim, a SIGTERMed launcher,
and a standalone router SIGKILLed and restarted mid-run. Each run is a real ``swarmnav launch`` (for
the router: the services started by hand as in docs/deployment.md); faults are injected from here at
an epoch read off the run's clock. Every wait is bounded; on a timeout everything started here is
stopped (SIGTERM, then SIGKILL of the process group). Writes DIR/chaos.json and DIR/chaos.md (default
DIR = runs/chaos-<timestamp>) and prints the table. ``--quick``: only none, kill-master, router-restart.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "smoke.toml"
ALGO = "atvfg"
RUN_TIMEOUT_S = 300.0  # one launch, start to end
EPOCH_WAIT_S = 120.0  # waiting for the epoch at which a fault is injected
GONE_WAIT_S = 60.0  # waiting for every process to be gone after a kill
SERVICE_WAIT_S = 120.0  # router-restart: the services must end by themselves within this
QUICK = ("none", "kill-master", "router-restart")


def _env() -> dict:
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "shared")]))
    env.update({v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")})
    return env


def _until(cond, timeout: float, step: float = 0.05) -> bool:
    """Poll ``cond()`` until it is true (True) or ``timeout`` seconds passed (False)."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(step)
    return True


def _alive(p: psutil.Process) -> bool:
    """True while ``p`` (the same process: psutil checks its start time) runs and is not a zombie."""
    with contextlib.suppress(psutil.Error):
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    return False


def _arg(p: psutil.Process, flag: str) -> str | None:
    """The value of ``flag`` on ``p``'s command line."""
    with contextlib.suppress(psutil.Error, ValueError, IndexError):
        cmd = p.cmdline()
        return cmd[cmd.index(flag) + 1]
    return None


def _signal(p: psutil.Process, sig: int) -> None:
    with contextlib.suppress(psutil.Error):  # gone meanwhile
        p.send_signal(sig)


class Launch:
    """One ``swarmnav launch`` started from here in its own session (process group) + its children."""

    def __init__(self, run_dir: Path, seed: int, extra: list[str], log: Path):
        cmd = [sys.executable, "-m", "services.cli", "launch", "--config", str(CONFIG), "--algo", ALGO, "--seed", str(seed),
               "--out", str(run_dir), "--no-progress", *extra]
        with open(log, "wb") as f:
            self.p = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=f, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, start_new_session=True)
        self.t0, self.seen = time.monotonic(), {}

    def alive(self) -> bool:
        return self.p.poll() is None

    def scan(self) -> list[psutil.Process]:
        """The launcher's live descendants; every one seen is remembered, so orphans are still found."""
        with contextlib.suppress(psutil.Error):
            for k in psutil.Process(self.p.pid).children(recursive=True):
                self.seen.setdefault(k.pid, k)
        return [k for k in self.seen.values() if _alive(k)]

    def find(self, module: str, uav: int | None = None) -> psutil.Process | None:
        """The live child running ``python -m <module>`` (for a node: with ``--uav <uav>``)."""
        return next((k for k in self.scan() if _arg(k, "-m") == module and (uav is None or _arg(k, "--uav") == str(uav))), None)

    def run_id(self) -> str | None:
        """The ``--run`` id on the children's command lines (they start once the router is open)."""
        end = time.monotonic() + EPOCH_WAIT_S
        while self.alive() and time.monotonic() < end:
            for k in self.scan():
                if run := _arg(k, "--run"):
                    return run
            time.sleep(0.1)
        return None

    def gone_after(self, procs: list[psutil.Process], t0: float) -> float | None:
        """Seconds from ``t0`` until the launcher and ``procs`` are all gone (None: not within GONE_WAIT_S)."""
        ok = _until(lambda: not self.alive() and not any(_alive(p) for p in procs), GONE_WAIT_S, 0.02)
        return round(time.monotonic() - t0, 2) if ok else None

    def wait(self, timeout: float) -> int | None:
        """The launcher's exit status, or None after stopping everything when ``timeout`` passed."""
        def ended() -> bool:
            self.scan()  # remember the children while they live
            return not self.alive()

        if _until(ended, timeout, 0.1):
            return self.p.returncode
        self.stop()
        return None

    def stop(self) -> None:
        """SIGCONT + SIGTERM to the launcher, then SIGKILL to its process group and every child seen."""
        for k in self.scan():
            _signal(k, signal.SIGCONT)  # a stopped process would not act on SIGTERM
        if self.alive():
            self.p.terminate()
            _until(lambda: not self.alive(), 8.0)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.p.pid, signal.SIGKILL)
        for k in self.scan():
            _signal(k, signal.SIGKILL)
        self.p.wait()


class Clock:
    """Follows ``swarmnav/<run>/clock`` over Zenoh: the latest epoch seen and whether ``done`` came."""

    def __init__(self, conf, run: str):
        import zenoh

        from swarmnav.wire import keys

        self.session = zenoh.open(conf)
        self.sub = self.session.declare_subscriber(keys.clock(run), zenoh.handlers.FifoChannel(10000))
        self.k, self.done = 0, False

    def wait_epoch(self, k: float, alive, timeout: float) -> bool:
        """Follow the clock until epoch ``k`` opens (True), ``alive()`` turns false or ``timeout`` passes."""
        from swarmnav.wire import messages as M

        def reached() -> bool:
            while (s := self.sub.try_recv()) is not None:
                try:
                    c = M.decode(M.ClockMsg, s.payload.to_bytes())
                except M.WireError:
                    continue
                self.k, self.done = max(self.k, c.k), self.done or c.done
            return self.k >= k or not alive()

        return _until(reached, timeout, 0.01) and self.k >= k

    def close(self) -> None:
        """Undeclare the subscriber, then close the session (a declared subscriber hangs exit)."""
        for x in (self.sub.undeclare, self.session.close):
            with contextlib.suppress(Exception):  # already closed: nothing to release
                x()


def open_run_clock(L: Launch, run_dir: Path, notes: dict) -> Clock | None:
    """The launched run's clock, read with the run's monitor identity (the launch uses mutual TLS)."""
    import zenoh

    run, cfg = L.run_id(), run_dir / "security" / "monitor.json5"
    if run is None or not _until(cfg.is_file, 30.0):
        notes["error"] = "the run's children or security/monitor.json5 never appeared: fault not injected"
        return None
    conf = zenoh.Config.from_file(str(cfg))
    conf.insert_json5("connect/timeout_ms", "10000")
    return Clock(conf, run)


def _at_epoch(L: Launch, clock: Clock | None, k: int, notes: dict) -> bool:
    """Wait for epoch ``k``; False (and noted) when the run ended or EPOCH_WAIT_S passed first."""
    if clock is not None and clock.wait_epoch(k, L.alive, EPOCH_WAIT_S):
        notes["injected_at_epoch"] = clock.k
        return True
    notes.setdefault("error", f"epoch {k} never came: fault not injected")
    return False


def inject_freeze(L: Launch, clock: Clock | None, notes: dict) -> None:
    """SIGSTOP UAV 4's process at epoch 10, SIGCONT 20 s later."""
    if _at_epoch(L, clock, 10, notes) and (node := L.find("services.uav_node", 4)) is not None:
        node.suspend()
        try:
            clock.wait_epoch(float("inf"), lambda: True, 20.0)
        finally:
            node.resume()
        notes["resumed_at_epoch"] = clock.k


def _kill_at(module: str, k: int, sig: int = signal.SIGKILL, measure: bool = False):
    """An injection: at epoch ``k`` send ``sig`` to the child running ``module`` (``launcher``: the
    launcher itself); with ``measure``, note how long until every process of the run is gone."""

    def inject(L: Launch, clock: Clock | None, notes: dict) -> None:
        if _at_epoch(L, clock, k, notes):
            procs, t0 = L.scan(), time.monotonic()
            (L.p if module == "launcher" else L.find(module)).send_signal(sig)
            if measure:
                notes["all_gone_s"] = L.gone_after(procs, t0)

    return inject


def rebuild_report(run_dir: Path, notes: dict) -> None:
    """After the monitor was killed: ``swarmnav report RUN_DIR`` and its outcome."""
    t0, rc = time.monotonic(), None
    try:
        rc = subprocess.run([sys.executable, "-m", "services.cli", "report", str(run_dir)], cwd=REPO, env=_env(),
                            capture_output=True, timeout=180).returncode
    except subprocess.TimeoutExpired:
        pass
    rep = _json(run_dir / "report.json") or {}
    notes["report_rebuild"] = {"exit": rc, "wall_s": round(time.monotonic() - t0, 1),
                               "epochs_recorded": rep.get("epochs_recorded"), "complete": rep.get("complete")}


@dataclass
class Fault:
    name: str
    injected: str
    extra: list[str] = field(default_factory=list)  # swarmnav launch arguments
    faulted: tuple[int, ...] = ()  # UAVs left out of the survivors' RMSE
    act: object = None  # injection from here while the run goes: f(launch, clock, notes)
    after: object = None  # after the launcher ended: f(run_dir, notes)


FAULTS = [
    Fault("none", "nothing (unfaulted lockstep run)"),
    Fault("kill-slave", "`--kill 4@20`: scheduled SIGKILL of UAV 4 at t = 20 s", ["--kill", "4@20"], (4,)),
    Fault("kill-two", "`--kill 4@20 --kill 5@30`", ["--kill", "4@20", "--kill", "5@30"], (4, 5)),
    Fault("kill-master", "`--kill 2@20`: the master (better IMU, GNSS)", ["--kill", "2@20"], (2,)),
    Fault("kill-master-restart", "`--kill 2@20 --restart 2@40`", ["--kill", "2@20", "--restart", "2@40"], (2,)),
    Fault("freeze", "`--rate 1`; SIGSTOP UAV 4 at epoch 10, SIGCONT 20 s later", ["--rate", "1"], (4,), inject_freeze),
    Fault("monitor-kill", "SIGKILL the monitor at epoch 30, then `swarmnav report`", [], (),
          _kill_at("services.monitor", 30), rebuild_report),
    Fault("sensor-sim-kill", "SIGKILL the sensor-sim at epoch 20", [], (), _kill_at("services.sensor_sim", 20, measure=True)),
    Fault("launcher-sigterm", "`--rate 1`; SIGTERM the launcher at epoch 10", ["--rate", "1"], (),
          _kill_at("launcher", 10, signal.SIGTERM, measure=True)),
    Fault("router-restart", "standalone router SIGKILLed at epoch 20, restarted on its port 2 s later"),
]


def run_launched(f: Fault, out: Path, seed: int) -> tuple[int | None, float, dict, Path, Path]:
    """One launch with its fault: (launcher exit status or None on timeout, wall s, notes, results, dataset)."""
    run_dir, notes, clock = out / f.name, {}, None
    L = Launch(run_dir, seed, f.extra, out / f"{f.name}.launcher.log")
    try:
        try:
            if f.act is not None and (clock := open_run_clock(L, run_dir, notes)) is not None:
                f.act(L, clock, notes)
        except Exception as e:  # a failed injection is a finding, not a reason to leave processes behind
            notes["error"] = f"injection failed: {e!r}"
        finally:
            clock.close() if clock is not None else None
        rc = L.wait(max(1.0, RUN_TIMEOUT_S - (time.monotonic() - L.t0)))
    finally:
        L.stop() if L.alive() else None  # interrupted: leave nothing behind
    wall = round(time.monotonic() - L.t0, 1)
    if rc is None:
        notes["timeout"] = f"still running after {RUN_TIMEOUT_S:.0f} s: stopped"
    if left := L.scan():
        notes["left_behind"] = [_arg(p, "-m") for p in left]
        L.stop()
    if f.after is not None:
        f.after(run_dir, notes)
    return rc, wall, notes, run_dir, run_dir / "dataset"


def _start(args: list[str], log: Path) -> subprocess.Popen:
    with open(log, "wb") as f:
        return subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env=_env(), stdout=f, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)


def _router(cfg: Path, ep: str, log: Path) -> subprocess.Popen:
    """``python -m deploy.router`` on ``ep``, once it says it listens (bounded 30 s)."""
    r = _start(["deploy.router", "--config", str(cfg), "--listen", ep], log)
    _until(lambda: r.poll() is not None or b"listening on" in log.read_bytes(), 30.0, 0.1)
    return r


def _bounce_router(routers: list, cfg: Path, ep: str, run: str, alive, notes: dict, log: Path) -> None:
    """At epoch 20 (plain client session on the run's clock) SIGKILL the router, restart it 2 s later."""
    from services.runtime.zconf import client_config

    clock = None
    try:
        clock = Clock(client_config(ep), run)
        if not clock.wait_epoch(20, alive, EPOCH_WAIT_S):
            notes["error"] = "epoch 20 never came: fault not injected"
            return
        routers[0].kill()
        routers[0].wait()
        notes["injected_at_epoch"] = clock.k
        time.sleep(2.0)
        routers.append(_router(cfg, ep, log))
        notes["router_restarted"] = routers[-1].poll() is None
    except Exception as e:  # a failed injection is a finding, not a reason to leave processes behind
        notes["error"] = f"injection failed: {e!r}"
    finally:
        clock.close() if clock is not None else None


def run_router_restart(out: Path, seed: int) -> tuple[int | None, float, dict, Path, Path]:
    """The services by hand on a standalone router, which is SIGKILLed at epoch 20 and restarted on
    the same port 2 s later; every service must then end by itself (bounded SERVICE_WAIT_S)."""
    from services.runtime.zconf import free_port

    d, notes = out / "router-restart", {}
    (d / "logs").mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "services.cli", "simulate", "--config", str(CONFIG), "--seed", str(seed),
                    "--out", str(d / "data")], cwd=REPO, env=_env(), check=True, capture_output=True, timeout=120)
    ep, run, cfg = f"tcp/127.0.0.1:{free_port()}", f"chaos{os.getpid()}", d / "router.json5"
    cfg.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [ep]}, "connect": {"endpoints": []},
                               "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
                               "transport": {"link": {"tx": {"lease": 3000}}}}, indent=1) + "\n")
    t0 = time.monotonic()
    routers = [_router(cfg, ep, d / "logs" / "router.log")]
    common, ds = ["--router", ep, "--run", run], ["--dataset", str(d / "data"), "--seed", str(seed)]
    svc = {"monitor": ["services.monitor", *common, *ds, "--out", str(d / "run")],
           "sensor_sim": ["services.sensor_sim", *common, *ds],
           **{f"uav{u}": ["services.uav_node", *common, "--uav", str(u)] for u in range(1, 6)}}
    svc = {n: _start(a, d / "logs" / f"{n}.log") for n, a in svc.items()}

    def alive() -> bool:
        return any(p.poll() is None for p in svc.values())

    try:
        _bounce_router(routers, cfg, ep, run, alive, notes, d / "logs" / "router2.log")
        _until(lambda: not alive(), SERVICE_WAIT_S, 0.1)
    finally:
        wall = round(time.monotonic() - t0, 1)
        if stuck := [n for n, p in svc.items() if p.poll() is None]:
            notes["timeout"] = f"still running after {SERVICE_WAIT_S:.0f} s, stopped: {', '.join(stuck)}"
        for p in [*svc.values(), *routers]:
            p.terminate() if p.poll() is None else None
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    notes["service_exits"] = {n: p.returncode for n, p in svc.items()}
    rc = None if stuck else next((c for c in notes["service_exits"].values() if c != 0), 0)
    return rc, wall, notes, d / "run", d / "data"


def _json(p: Path) -> dict | None:
    with contextlib.suppress(OSError, ValueError):
        return json.loads(p.read_text())
    return None


def truth_at(dataset: Path, t: np.ndarray, uavs: list[int]) -> np.ndarray:
    """K x N x 3 true ENU positions at ``t`` (interpolated in truth.parquet: t, node, pe, pn, pu)."""
    import pyarrow.parquet as pq

    tab = {k: np.asarray(v) for k, v in pq.read_table(dataset / "truth.parquet", columns=["t", "node", "pe", "pn", "pu"])
           .to_pydict().items()}
    out = np.full((len(t), len(uavs), 3), np.nan)
    for j, u in enumerate(uavs):
        s = np.flatnonzero(tab["node"] == u)
        s = s[np.argsort(tab["t"][s])]
        out[:, j] = np.stack([np.interp(t, tab["t"][s], tab[c][s]) for c in ("pe", "pn", "pu")], axis=1)
    return out


def _schedule(extra: list[str], flag: str) -> list[tuple[int, float]]:
    return [(int(a.split("@")[0]), float(a.split("@")[1])) for f, a in zip(extra, extra[1:]) if f == flag]


def measure(f: Fault, res: Path, dataset: Path, rc, wall: float, notes: dict, base_err) -> tuple[dict, np.ndarray | None]:
    """The chaos.json entry of one fault, and its K x N 3-D position errors (NaN: no estimate)."""
    from services.monitor.core import excused_epochs
    from swarmnav.dataset import Dataset

    rep = _json(res / "report.json") or {}
    row = {"fault": f.name, "injected": f.injected, "exit": rc, "wall_s": wall, "complete": rep.get("complete"),
           **{k: rep.get(k) for k in ("estimates_received", "estimates_expected", "missing_by_uav", "epochs_expected")},
           "epochs_lost": None, "swarm_rmse_m": (rep.get("algorithms", {}).get(ALGO, {}).get("pos_rmse_m") or {}).get("3d"),
           "survivors": None, "survivors_rmse_m": None, "baseline_survivors_rmse_m": None,
           "survivors_rmse_change_pct": None, "events": rep.get("events", []), "notes": notes,
           "stop_reason": rep.get("distributed", {}).get("stop_reason"),
           "process_exits": {n: x.get("exit") for n, x in rep.get("distributed", {}).get("processes", {}).items()} or None}
    if not (res / "estimates.npz").is_file():
        return row, None
    est = np.load(res / "estimates.npz")
    uavs, pos = [int(u) for u in est["uavs"]], est["pos"]
    excused = excused_epochs(Dataset.read(dataset).meta, uavs, _schedule(f.extra, "--kill"), _schedule(f.extra, "--restart"))
    row["epochs_lost"] = int(len(pos) - (np.isfinite(pos).all(axis=2) | excused).all(axis=1).sum())
    err = np.linalg.norm(pos - truth_at(dataset, est["t"], uavs), axis=2)
    keep = np.isfinite(err) & np.array([u not in f.faulted for u in uavs])[None, :]
    row["survivors"] = [u for u in uavs if u not in f.faulted]
    if keep.any():  # the baseline over the same UAVs and epochs
        row["survivors_rmse_m"] = float(np.sqrt(np.mean(err[keep] ** 2)))
        row["baseline_survivors_rmse_m"] = float(np.sqrt(np.mean((err if base_err is None else base_err)[keep] ** 2)))
        row["survivors_rmse_change_pct"] = 100.0 * (row["survivors_rmse_m"] / row["baseline_survivors_rmse_m"] - 1.0)
    return row, err


def _exit_text(rc) -> str:
    return "timeout" if rc is None else f"{rc} ({signal.Signals(-rc).name})" if rc < 0 else str(rc)


def _fmt(x, spec: str = ".3f", unit: str = "") -> str:
    return "—" if x is None else format(x, spec) + unit


def _notes_text(n: dict) -> str:
    """Notes in words; a dict whose values are all equal (e.g. every service's exit 0) as "all <n>: <value>"."""
    def text(v) -> str:
        if isinstance(v, dict) and len(set(map(str, v.values()))) == 1:
            return f"all {len(v)}: {next(iter(v.values()))}"
        return json.dumps(v) if isinstance(v, (dict, list)) else str(v)

    return "; ".join(f"{k.replace('_', ' ')}: {text(v)}" for k, v in n.items())


def render(doc: dict) -> str:
    """chaos.md: intro, table, one paragraph per fault with its events in words."""
    lines = [f"# Chaos campaign: `{doc['scenario']}`, seed {doc['seed']}, {ALGO}", "",
             "Each fault is one real swarm run compared with the unfaulted baseline (swarm 3-D RMSE "
             f"{_fmt(doc['baseline_rmse_m'])} m). Exit: the launcher's status (router-restart: the first non-zero "
             "status of the services, else 0). Epochs lost: epochs without every expected estimate. Survivors: the UAVs "
             "not faulted; their RMSE change is against the same UAVs and epochs of the baseline.", "",
             "| fault | injected | exit | complete | estimates | epochs lost | swarm RMSE (m) | survivors' RMSE change "
             "vs baseline | wall s | notes/events |", "|---|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in doc["faults"]:
        est = f"{r['estimates_received']}/{r['estimates_expected']}" if r["estimates_expected"] is not None else "—"
        evs = [f"{e['kind']}" + (f" U{e['uav']}" if e.get("uav") else "") + f" @{e['t']:g}" for e in r["events"]]
        note = "; ".join(x for x in (", ".join(evs[:5]) + (f", +{len(evs) - 5} more" if len(evs) > 5 else ""),
                                     _notes_text(r["notes"])) if x) or "no events"
        comp = {True: "yes", False: "no"}.get(r["complete"], "—")
        lines.append(f"| {r['fault']} | {r['injected']} | {_exit_text(r['exit'])} | {comp} | {est} | {_fmt(r['epochs_lost'], 'd')} | "
                     f"{_fmt(r['swarm_rmse_m'])} | {_fmt(r['survivors_rmse_change_pct'], '+.1f', ' %')} | "
                     f"{r['wall_s']:.1f} | {note} |")
    for r in doc["faults"]:
        evs = "; ".join(f"at t = {e['t']:g} s, {e['kind'].replace('_', ' ')}" + (f" of UAV {e['uav']}" if e.get("uav") else "")
                        + (f" ({e['detail']})" if e.get("detail") else "") for e in r["events"])
        miss = {u: n for u, n in (r["missing_by_uav"] or {}).items() if n}
        lines += ["", f"**{r['fault']}** — {r['injected']}. Exit {_exit_text(r['exit'])} after {r['wall_s']:.1f} s; "
                  f"survivors {r['survivors']}: RMSE {_fmt(r['survivors_rmse_m'])} m against "
                  f"{_fmt(r['baseline_survivors_rmse_m'])} m in the baseline. Events: {evs or 'none'}."
                  + (f" Missing estimates by UAV: {miss}." if miss else "")
                  + (f" The launcher stopped the run: {r['stop_reason']}." if r["stop_reason"] else "")
                  + (f" Process exits: {r['process_exits']}." if r["process_exits"] else "")
                  + (f" Notes: {_notes_text(r['notes'])}." if r["notes"] else "")]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.chaos", description=__doc__.splitlines()[0])
    p.add_argument("--out", default=None, help="output directory (default runs/chaos-<timestamp>)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    a = p.parse_args(argv)
    out = Path(a.out or Path("runs") / f"chaos-{time.strftime('%Y%m%d-%H%M%S')}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    faults = [f for f in FAULTS if not a.quick or f.name in QUICK]
    rows, base_err = [], None
    for i, f in enumerate(faults, 1):
        print(f"[{i}/{len(faults)}] {f.name}: {f.injected} ...", file=sys.stderr, flush=True)
        if f.name == "router-restart":
            rc, wall, notes, res, ds = run_router_restart(out, a.seed)
        else:
            rc, wall, notes, res, ds = run_launched(f, out, a.seed)
        row, err = measure(f, res, ds, rc, wall, notes, base_err)
        base_err = err if f.name == "none" else base_err
        rows.append(row)
        print(f"    exit {_exit_text(rc)}, complete {row['complete']}, {wall:.1f} s", file=sys.stderr, flush=True)
    scenario = (_json(out / faults[0].name / "report.json") or {}).get("scenario")
    doc = {"scenario": scenario, "seed": a.seed, "baseline_rmse_m": rows[0]["swarm_rmse_m"], "faults": rows}
    (out / "chaos.json").write_text(json.dumps(doc, indent=1) + "\n")
    (out / "chaos.md").write_text((md := render(doc)) + "\n")
    print(md)
    print(f"wrote {out / 'chaos.md'} and {out / 'chaos.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
