"""Fault campaign on configs/smoke.toml: ``python -m deploy.chaos [--out DIR] [--seed 1] [--quick]``.

Runs the smoke swarm (5 UAVs, 60 epochs of 1 s, master UAV 2, atvfg) unfaulted, then once per fault:
scheduled kills (a slave, two slaves, the master, the master restarted), a frozen node (SIGSTOP for
20 s), a SIGKILLed monitor (then ``swarmnav report``), a SIGKILLed sensor-sim, a SIGTERMed launcher,
and a standalone router SIGKILLed and restarted mid-run. Each run is a real ``swarmnav launch``
(or, for the router, the services started by hand as in docs/deployment.md); faults are injected
from here at an epoch read off the run's clock. Every wait is bounded; on a timeout everything
started here is stopped (SIGTERM, then SIGKILL of the process group). Writes DIR/chaos.json and
DIR/chaos.md (default DIR = runs/chaos-<timestamp>) and prints the table. ``--quick``: only none,
kill-master and router-restart.
"""

from __future__ import annotations

import argparse
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
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        env[v] = "1"
    return env


def _alive(p: psutil.Process) -> bool:
    """True while ``p`` (the same process: psutil checks its start time) runs and is not a zombie."""
    try:
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _arg(cmd: list[str], flag: str) -> str | None:
    return cmd[cmd.index(flag) + 1] if flag in cmd[:-1] else None


class Launch:
    """One ``swarmnav launch`` started from here in its own session (process group) + its children."""

    def __init__(self, run_dir: Path, seed: int, extra: list[str], log: Path):
        cmd = [sys.executable, "-m", "services.cli", "launch", "--config", str(CONFIG), "--algo", ALGO, "--seed", str(seed),
               "--out", str(run_dir), "--no-progress", *extra]
        with open(log, "wb") as f:
            self.p = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=f, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, start_new_session=True)
        self.t0 = time.monotonic()
        self.seen: dict[int, psutil.Process] = {}

    def alive(self) -> bool:
        return self.p.poll() is None

    def scan(self) -> list[psutil.Process]:
        """The launcher's live descendants; every one seen is remembered, so orphans are still found."""
        try:
            for k in psutil.Process(self.p.pid).children(recursive=True):
                self.seen.setdefault(k.pid, k)
        except psutil.Error:
            pass
        return [k for k in self.seen.values() if _alive(k)]

    def find(self, module: str, uav: int | None = None) -> psutil.Process | None:
        """The live child running ``python -m <module>`` (for a node: with ``--uav <uav>``)."""
        for k in self.scan():
            try:
                cmd = k.cmdline()
            except psutil.Error:
                continue
            if module in cmd and (uav is None or _arg(cmd, "--uav") == str(uav)):
                return k
        return None

    def run_id(self, timeout: float = EPOCH_WAIT_S) -> str | None:
        """The ``--run`` id on the children's command lines (they start once the router is open)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and self.alive():
            for k in self.scan():
                try:
                    run = _arg(k.cmdline(), "--run")
                except psutil.Error:
                    continue
                if run:
                    return run
            time.sleep(0.1)
        return None

    def gone_after(self, procs: list[psutil.Process], t0: float) -> float | None:
        """Seconds from ``t0`` until the launcher and ``procs`` are all gone (None: not within GONE_WAIT_S)."""
        while time.monotonic() - t0 < GONE_WAIT_S:
            if not self.alive() and not any(_alive(p) for p in procs):
                return round(time.monotonic() - t0, 2)
            time.sleep(0.02)
        return None

    def wait(self, timeout: float) -> int | None:
        """The launcher's exit status, or None after stopping everything when ``timeout`` passed."""
        end = time.monotonic() + timeout
        while self.alive() and time.monotonic() < end:
            self.scan()
            time.sleep(0.1)
        if self.alive():
            self.stop()
            return None
        return self.p.returncode

    def stop(self) -> None:
        """SIGCONT + SIGTERM to the launcher, then SIGKILL to its process group and every child seen."""
        for k in self.scan():
            _signal(k, signal.SIGCONT)
        if self.alive():
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout=8)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        for k in self.scan():
            _signal(k, signal.SIGKILL)
        self.p.wait()


def _signal(p: psutil.Process, sig: int) -> None:
    try:
        p.send_signal(sig)
    except psutil.Error:
        pass


class Clock:
    """Follows ``swarmnav/<run>/clock`` over Zenoh: the latest epoch seen and whether ``done`` came."""

    def __init__(self, conf, run: str):
        import zenoh

        from swarmnav.wire import keys

        self.session = zenoh.open(conf)
        self.sub = self.session.declare_subscriber(keys.clock(run), zenoh.handlers.FifoChannel(10000))
        self.k, self.done = 0, False

    def drain(self) -> None:
        from swarmnav.wire import messages as M

        while (s := self.sub.try_recv()) is not None:
            try:
                c = M.decode(M.ClockMsg, s.payload.to_bytes())
            except M.WireError:
                continue
            self.k, self.done = max(self.k, c.k), self.done or c.done

    def wait_epoch(self, k: float, alive, timeout: float) -> bool:
        """Follow the clock until epoch ``k`` opens (True), ``alive()`` turns false or ``timeout`` passes."""
        end = time.monotonic() + timeout
        while True:
            self.drain()
            if self.k >= k:
                return True
            if not alive() or time.monotonic() > end:
                return False
            time.sleep(0.01)

    def close(self) -> None:
        for x in (self.sub.undeclare, self.session.close):
            try:
                x()
            except Exception:  # already closed: nothing to release
                pass


def open_run_clock(L: Launch, run_dir: Path, notes: dict) -> Clock | None:
    """The launched run's clock, read with the run's monitor identity (the launch uses mutual TLS)."""
    import zenoh

    run, cfg = L.run_id(), run_dir / "security" / "monitor.json5"
    if run is None or not cfg.is_file():
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
    if not _at_epoch(L, clock, 10, notes):
        return
    node = L.find("services.uav_node", 4)
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
        if not _at_epoch(L, clock, k, notes):
            return
        procs = L.scan()
        target = None if module == "launcher" else L.find(module)
        t0 = time.monotonic()
        L.p.send_signal(sig) if target is None else target.send_signal(sig)
        if measure:
            notes["all_gone_s"] = L.gone_after(procs, t0)

    return inject


def rebuild_report(run_dir: Path, notes: dict) -> None:
    """After the monitor was killed: ``swarmnav report RUN_DIR`` and its outcome."""
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", "services.cli", "report", str(run_dir)], cwd=REPO, env=_env(),
                           capture_output=True, text=True, timeout=180)
        rc = r.returncode
    except subprocess.TimeoutExpired:
        rc = None
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


def run_launched(f: Fault, out: Path, seed: int) -> tuple[int | None, float, dict, Path]:
    """One launch with its fault: (launcher exit status or None on timeout, wall s, notes, dataset)."""
    run_dir, notes, clock = out / f.name, {}, None
    L = Launch(run_dir, seed, f.extra, out / f"{f.name}.launcher.log")
    try:
        if f.act is not None:
            clock = open_run_clock(L, run_dir, notes)
            f.act(L, clock, notes)
    except Exception as e:  # an injection that failed is a finding, not a reason to leave processes behind
        notes["error"] = f"injection failed: {e!r}"
    finally:
        if clock is not None:
            clock.close()
    rc = L.wait(max(1.0, RUN_TIMEOUT_S - (time.monotonic() - L.t0)))
    wall = round(time.monotonic() - L.t0, 1)
    if rc is None:
        notes["timeout"] = f"still running after {RUN_TIMEOUT_S:.0f} s: stopped"
    left = L.scan()
    if left:
        notes["left_behind"] = [" ".join(p.cmdline()[1:4]) for p in left if _alive(p)]
        L.stop()
    if f.after is not None:
        f.after(run_dir, notes)
    return rc, wall, notes, run_dir / "dataset"


def _start(cmd: list[str], log: Path) -> subprocess.Popen:
    with open(log, "wb") as f:
        return subprocess.Popen([sys.executable, "-m", *cmd], cwd=REPO, env=_env(), stdout=f,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def _router(cfg: Path, ep: str, log: Path) -> subprocess.Popen:
    """``python -m deploy.router`` on ``ep``, once it says it listens (bounded 30 s)."""
    r = _start(["deploy.router", "--config", str(cfg), "--listen", ep], log)
    end = time.monotonic() + 30
    while time.monotonic() < end and r.poll() is None and b"listening on" not in log.read_bytes():
        time.sleep(0.1)
    return r


def run_router_restart(out: Path, seed: int) -> tuple[int | None, float, dict, Path]:
    """The services by hand on a standalone router, which is SIGKILLed at epoch 20 and restarted on
    the same port 2 s later; every service must then end by itself (bounded SERVICE_WAIT_S)."""
    from deploy.zconf import client_config, free_port

    d = out / "router-restart"
    (d / "logs").mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "services.cli", "simulate", "--config", str(CONFIG), "--seed", str(seed),
                    "--out", str(d / "data")], cwd=REPO, env=_env(), check=True, capture_output=True, timeout=120)
    port = free_port()
    ep, run = f"tcp/127.0.0.1:{port}", f"chaos{os.getpid()}"
    cfg = d / "router.json5"
    cfg.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [ep]}, "connect": {"endpoints": []},
                               "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
                               "transport": {"link": {"tx": {"lease": 3000}}}}, indent=1) + "\n")
    t0 = time.monotonic()
    routers = [_router(cfg, ep, d / "logs" / "router.log")]
    common, ds = ["--router", ep, "--run", run], ["--dataset", str(d / "data"), "--seed", str(seed)]
    svc = {"monitor": _start(["services.monitor", *common, *ds, "--out", str(d / "run")], d / "logs" / "monitor.log"),
           "sensor_sim": _start(["services.sensor_sim", *common, *ds], d / "logs" / "sensor_sim.log")}
    for u in range(1, 6):
        svc[f"uav{u}"] = _start(["services.uav_node", *common, "--uav", str(u)], d / "logs" / f"uav{u}.log")
    notes, clock = {}, None
    try:
        clock = Clock(client_config(ep), run)
        alive = lambda: any(p.poll() is None for p in svc.values())  # noqa: E731
        if clock.wait_epoch(20, alive, EPOCH_WAIT_S):
            routers[0].kill()
            routers[0].wait()
            notes["injected_at_epoch"] = clock.k
            clock.close()
            clock = None
            time.sleep(2.0)
            routers.append(_router(cfg, ep, d / "logs" / "router2.log"))
            notes["router_restarted"] = routers[-1].poll() is None
        else:
            notes["error"] = "epoch 20 never came: fault not injected"
        end = time.monotonic() + SERVICE_WAIT_S
        while alive() and time.monotonic() < end:
            time.sleep(0.1)
    finally:
        if clock is not None:
            clock.close()
        wall = round(time.monotonic() - t0, 1)
        stuck = [n for n, p in svc.items() if p.poll() is None]
        if stuck:
            notes["timeout"] = f"still running after {SERVICE_WAIT_S:.0f} s, stopped: {', '.join(stuck)}"
        for p in [*svc.values(), *routers]:
            if p.poll() is None:
                p.terminate()
        for p in [*svc.values(), *routers]:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    notes["exits"] = {n: p.returncode for n, p in svc.items()}
    rc = None if stuck else next((c for c in notes["exits"].values() if c != 0), 0)
    return rc, wall, notes, d / "data"


def _json(p: Path) -> dict | None:
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def truth_at(dataset: Path, t: np.ndarray, uavs: list[int]) -> np.ndarray:
    """K x N x 3 true ENU positions at ``t`` (interpolated in truth.parquet: t, node, pe, pn, pu)."""
    import pyarrow.parquet as pq

    tab = pq.read_table(dataset / "truth.parquet", columns=["t", "node", "pe", "pn", "pu"]).to_pydict()
    tt, node = np.asarray(tab["t"]), np.asarray(tab["node"])
    out = np.full((len(t), len(uavs), 3), np.nan)
    for j, u in enumerate(uavs):
        s = np.flatnonzero(node == u)
        s = s[np.argsort(tt[s])]
        for c, col in enumerate(("pe", "pn", "pu")):
            out[:, j, c] = np.interp(t, tt[s], np.asarray(tab[col])[s])
    return out


def _schedule(extra: list[str], flag: str) -> list[tuple[int, float]]:
    return [(int(a.split("@")[0]), float(a.split("@")[1])) for f, a in zip(extra, extra[1:]) if f == flag]


def measure(f: Fault, res_dir: Path, dataset: Path, rc, wall: float, notes: dict, base_err) -> tuple[dict, np.ndarray | None]:
    """The chaos.json entry of one fault, and its K x N 3-D position errors (NaN: no estimate)."""
    rep = _json(res_dir / "report.json") or {}
    row = {"fault": f.name, "injected": f.injected, "exit": rc, "wall_s": wall, "complete": rep.get("complete"),
           "estimates_received": rep.get("estimates_received"), "estimates_expected": rep.get("estimates_expected"),
           "missing_by_uav": rep.get("missing_by_uav"), "epochs_expected": rep.get("epochs_expected"),
           "epochs_lost": None, "swarm_rmse_m": (rep.get("algorithms", {}).get(ALGO, {}).get("pos_rmse_m") or {}).get("3d"),
           "survivors": None, "survivors_rmse_m": None, "baseline_survivors_rmse_m": None,
           "survivors_rmse_change_pct": None, "events": rep.get("events", []), "notes": notes}
    if not (res_dir / "estimates.npz").is_file():
        return row, None
    from services.monitor.core import excused_epochs
    from swarmnav.dataset import Dataset

    est = np.load(res_dir / "estimates.npz")
    uavs, pos = [int(u) for u in est["uavs"]], est["pos"]
    excused = excused_epochs(Dataset.read(dataset).meta, uavs, _schedule(f.extra, "--kill"), _schedule(f.extra, "--restart"))
    row["epochs_lost"] = int(len(pos) - (np.isfinite(pos).all(axis=2) | excused).all(axis=1).sum())
    err = np.linalg.norm(pos - truth_at(dataset, est["t"], uavs), axis=2)
    keep = np.isfinite(err) & np.array([u not in f.faulted for u in uavs])[None, :]
    row["survivors"] = [u for u in uavs if u not in f.faulted]
    if keep.any():
        row["survivors_rmse_m"] = float(np.sqrt(np.mean(err[keep] ** 2)))
        b = (base_err if base_err is not None else err)[keep]  # the baseline over the same UAVs and epochs
        row["baseline_survivors_rmse_m"] = float(np.sqrt(np.mean(b ** 2)))
        row["survivors_rmse_change_pct"] = 100.0 * (row["survivors_rmse_m"] / row["baseline_survivors_rmse_m"] - 1.0)
    return row, err


def _exit_text(rc) -> str:
    if rc is None:
        return "timeout"
    return f"{rc} ({signal.Signals(-rc).name})" if rc < 0 else str(rc)


def _fmt(x, spec: str = ".3f", none: str = "—") -> str:
    return none if x is None else format(x, spec)


def _events_short(evs: list[dict], cap: int = 4) -> str:
    s = [f"{e['kind']} U{e['uav']}@{e['t']:g}" if e.get("uav") else f"{e['kind']}@{e['t']:g}" for e in evs[:cap]]
    return ", ".join(s) + (f", +{len(evs) - cap} more" if len(evs) > cap else "") if s else "no events"


def _notes_text(n: dict) -> str:
    parts = [f"{k.replace('_', ' ')}: {json.dumps(v) if isinstance(v, (dict, list)) else v}" for k, v in n.items()]
    return "; ".join(parts) if parts else ""


def render(doc: dict) -> str:
    """chaos.md: intro, table, one paragraph per fault."""
    lines = [f"# Chaos campaign: `{doc['scenario']}`, seed {doc['seed']}, {ALGO}",
             f"Each fault is one real swarm run compared with the unfaulted baseline (swarm 3-D RMSE "
             f"{_fmt(doc['baseline_rmse_m'])} m). Survivors: the UAVs that were not faulted; their RMSE change is "
             f"against the same UAVs and epochs of the baseline.", "",
             "| fault | injected | exit | complete | estimates | epochs lost | swarm RMSE (m) | survivors' RMSE change "
             "vs baseline | wall s | notes/events |", "|---|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in doc["faults"]:
        est = f"{r['estimates_received']}/{r['estimates_expected']}" if r["estimates_expected"] is not None else "—"
        comp = {True: "yes", False: "no", None: "—"}[r["complete"]]
        chg = _fmt(r["survivors_rmse_change_pct"], "+.1f") + (" %" if r["survivors_rmse_change_pct"] is not None else "")
        note = "; ".join(x for x in (_events_short(r["events"]), _notes_text(r["notes"])) if x)
        lines.append(f"| {r['fault']} | {r['injected']} | {_exit_text(r['exit'])} | {comp} | {est} | "
                     f"{_fmt(r['epochs_lost'], 'd')} | {_fmt(r['swarm_rmse_m'])} | {chg} | {r['wall_s']:.1f} | {note} |")
    lines.append("")
    for r in doc["faults"]:
        evs = "; ".join(f"at t = {e['t']:g} s, {e['kind'].replace('_', ' ')}" + (f" of UAV {e['uav']}" if e.get("uav") else "")
                        + (f" ({e['detail']})" if e.get("detail") else "") for e in r["events"])
        miss = {u: n for u, n in (r["missing_by_uav"] or {}).items() if n}
        lines += [f"**{r['fault']}** — {r['injected']}. Exit {_exit_text(r['exit'])} after {r['wall_s']:.1f} s; "
                  f"survivors {r['survivors']} RMSE {_fmt(r['survivors_rmse_m'])} m vs {_fmt(r['baseline_survivors_rmse_m'])} m "
                  f"in the baseline. Events: {evs or 'none'}." + (f" Missing estimates by UAV: {miss}." if miss else "")
                  + (f" Notes: {_notes_text(r['notes'])}." if r["notes"] else ""), ""]
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
            rc, wall, notes, ds = run_router_restart(out, a.seed)
            res_dir = out / f.name / "run"
        else:
            rc, wall, notes, ds = run_launched(f, out, a.seed)
            res_dir = out / f.name
        row, err = measure(f, res_dir, ds, rc, wall, notes, base_err)
        base_err = err if f.name == "none" else base_err
        rows.append(row)
        print(f"    exit {_exit_text(rc)}, complete {row['complete']}, {wall:.1f} s", file=sys.stderr, flush=True)
    scenario = (_json(out / faults[0].name / "report.json") or {}).get("scenario")
    doc = {"scenario": scenario, "seed": a.seed, "baseline_rmse_m": rows[0]["swarm_rmse_m"], "faults": rows}
    (out / "chaos.json").write_text(json.dumps(doc, indent=1) + "\n")
    md = render(doc)
    (out / "chaos.md").write_text(md + "\n")
    print(md)
    print(f"wrote {out / 'chaos.md'} and {out / 'chaos.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
