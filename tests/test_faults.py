"""No silent corruption: real processes, a real router, real faults (SIGKILL, SIGSTOP, a router
restart) on `smoke`, and what the run says about them afterwards.

Each test launches its own swarm (lockstep unless it says otherwise), follows the run's clock as the
monitor identity (secured runs) or as a plain client (the standalone router), injects the fault at
an epoch and then checks the processes, the exit status and report.json.
"""

import functools
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import psutil
import pytest

pytestmark = [pytest.mark.integration]
REPO = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
           MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    d = tmp_path_factory.mktemp("smoke") / "dataset"
    simulate(load_config(REPO / "configs/smoke.toml"), 1).write(d)
    return d


class Clock:
    """Follows swarmnav/<run>/clock (JSON ClockMsg) on a Zenoh session."""

    def __init__(self, session, run):
        self.k, self.done, self.s = 0, False, session
        self.sub = session.declare_subscriber(f"swarmnav/{run}/clock", self._cb)

    def _cb(self, sample):
        c = json.loads(sample.payload.to_bytes())
        self.done |= bool(c.get("done"))
        if not c.get("done"):
            self.k = max(self.k, c["k"])

    def wait(self, k, timeout=120):
        end = time.monotonic() + timeout
        while self.k < k and time.monotonic() < end:
            time.sleep(0.02)
        assert self.k >= k, f"the run never reached epoch {k} (last {self.k})"

    def close(self):
        self.sub.undeclare()
        self.s.close()


class Run:
    """One `swarmnav launch` in its own process group."""

    def __init__(self, out, *args, dataset):
        self.out = Path(out)
        self.log = open(str(out) + ".log", "w")
        self.p = subprocess.Popen([sys.executable, "-m", "services.cli", "launch", "--dataset", str(dataset), "--algo", "atvfg",
                                   "--seed", "1", "--out", str(out), "--no-progress", *args], cwd=REPO, env=ENV,
                                  stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)

    def children(self) -> dict[str, psutil.Process]:
        out = {}
        try:
            for c in psutil.Process(self.p.pid).children(recursive=True):
                cmd = c.cmdline()
                if "services.uav_node" in cmd:
                    out[f"uav{cmd[cmd.index('--uav') + 1]}"] = c
                elif "services.sensor_sim" in cmd:
                    out["sensor_sim"] = c
                elif "services.monitor" in cmd:
                    out["monitor"] = c
        except psutil.NoSuchProcess:
            pass
        return out

    def clock(self) -> Clock:
        import zenoh

        end = time.monotonic() + 60
        while time.monotonic() < end and len(self.children()) < 7:
            time.sleep(0.1)
        cmd = self.children()["monitor"].cmdline()
        run = cmd[cmd.index("--run") + 1]
        return Clock(zenoh.open(zenoh.Config.from_file(str(self.out / "security" / "monitor.json5"))), run)

    def freeze(self, name: str, at_epoch: int, seconds: float) -> int:
        """SIGSTOP the service ``name`` once the clock reaches ``at_epoch``, SIGCONT it ``seconds``
        later; returns the epoch the clock had reached by then."""
        clk = self.clock()
        clk.wait(at_epoch)
        p = self.children()[name]
        p.send_signal(signal.SIGSTOP)
        time.sleep(seconds)
        p.send_signal(signal.SIGCONT)
        k = clk.k
        clk.close()
        return k

    def wait(self, timeout=180):
        try:
            return self.p.wait(timeout)
        finally:
            self.log.close()
            if self.p.poll() is None:
                os.killpg(self.p.pid, signal.SIGKILL)

    def output(self):
        return Path(str(self.out) + ".log").read_text()

    def report(self):
        return json.loads((self.out / "report.json").read_text())


def _spawn(logs: Path, name: str, argv: list[str]) -> subprocess.Popen:
    """A service started by hand (as on another host), its output in logs/<name>.log."""
    return subprocess.Popen(argv, cwd=REPO, env=ENV, stdout=open(logs / f"{name}.log", "w"), stderr=subprocess.STDOUT)


def _all_gone(procs, t0, limit):
    while time.monotonic() - t0 < limit:
        if not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in procs):
            return time.monotonic() - t0
        time.sleep(0.05)
    return None


def test_out_on_an_existing_run_is_refused(tmp_path):
    old = tmp_path / "old"
    (old / "logs").mkdir(parents=True)
    (old / "report.json").write_text('{"an": "earlier run"}')
    r = subprocess.run([sys.executable, "-m", "services.cli", "launch", "--config", "configs/smoke.toml", "--out", str(old)],
                       cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--force" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert (old / "report.json").read_text() == '{"an": "earlier run"}' and sorted(os.listdir(old)) == ["logs", "report.json"]


def test_force_clears_only_a_run_directory(tmp_path):
    from services.commands.launch import prepare_run_dir
    from swarmnav.errors import SwarmnavError

    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)
    (run / "swarm.rrd").write_bytes(b"x")
    prepare_run_dir(run, force=True)
    assert list(run.iterdir()) == []
    home = tmp_path / "home"
    home.mkdir()
    (home / "thesis.tex").write_text("years of work")
    with pytest.raises(SwarmnavError, match="not a swarmnav run"):
        prepare_run_dir(home, force=True)
    assert (home / "thesis.tex").exists()


def test_sensor_sim_killed_stops_the_run_loudly(smoke, tmp_path):
    run = Run(tmp_path / "run", dataset=smoke)
    clk = run.clock()
    clk.wait(10)
    procs = [psutil.Process(run.p.pid), *run.children().values()]
    run.children()["sensor_sim"].send_signal(signal.SIGKILL)
    t0 = time.monotonic()
    gone = _all_gone(procs, t0, 10)
    clk.close()
    rc = run.wait(10)
    assert gone is not None and gone <= 5.0, gone
    assert rc != 0 and "the sensor-sim died (killed by SIGKILL)" in run.output(), run.output()[-1500:]
    rep = run.report()
    assert rep["complete"] is False and rep["epochs_recorded"] < 60


def test_monitor_killed_recording_valid_and_report_rebuilt(smoke, tmp_path):
    run = Run(tmp_path / "run", dataset=smoke)
    clk = run.clock()
    clk.wait(30)
    run.children()["monitor"].send_signal(signal.SIGKILL)
    k_kill = clk.k
    clk.close()
    assert run.wait(30) != 0
    assert "the monitor died" in run.output()
    rerun = str(Path(sys.executable).with_name("rerun"))
    segs = sorted((run.out / "recording").glob("*.rrd"))
    assert segs and not (run.out / "swarm.rrd").exists()
    for f in segs:  # every recording file on disk is valid, whatever the monitor was doing
        subprocess.run([rerun, "rrd", "verify", str(f)], check=True, capture_output=True)
    r = subprocess.run([sys.executable, "-m", "services.cli", "report", str(run.out)], cwd=REPO, env=ENV,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    rep = run.report()
    assert rep["complete"] is False and rep["epochs_recorded"] >= k_kill - 2, (rep["epochs_recorded"], k_kill)
    assert any(e["kind"] == "monitor_lost" for e in rep["events"])
    subprocess.run([rerun, "rrd", "verify", str(run.out / "swarm.rrd")], check=True, capture_output=True)
    assert not (run.out / "recording").exists()


def test_launcher_sigterm_stops_every_child(smoke, tmp_path):
    run = Run(tmp_path / "run", "--rate", "2", dataset=smoke)
    clk = run.clock()
    clk.wait(5)
    procs = [psutil.Process(run.p.pid), *run.children().values()]
    run.p.send_signal(signal.SIGTERM)
    gone = _all_gone(procs, time.monotonic(), 10)
    clk.close()
    assert gone is not None and gone <= 5.0, gone
    assert run.wait(5) not in (0, None)


def test_frozen_node_rebootstraps_and_run_says_it_is_incomplete(smoke, tmp_path):
    """UAV 4 SIGSTOPped for 8 s under --rate 2 (16 epochs): it must come back through a
    re-bootstrap (never publishing its stale state as current), its error back to normal, the swarm
    not poisoned, and the report must call the run incomplete and name the missed estimates."""
    run = Run(tmp_path / "run", "--rate", "2", dataset=smoke)
    k_cont = run.freeze("uav4", 10, 8.0)
    rc = run.wait(120)
    rep = run.report()
    kinds = [(e["kind"], e["uav"]) for e in rep["events"]]
    assert ("dropout", 4) in kinds and ("rejoin", 4) in kinds and ("rebootstrap", 4) in kinds, kinds
    assert rc != 0 and rep["complete"] is False and rep["missing_by_uav"]["4"] > 5, rep["missing_by_uav"]
    assert "INCOMPLETE RUN" in run.output()
    assert "re-bootstrapping" in (run.out / "logs" / "uav4.log").read_text()
    from swarmnav.dataset import Dataset
    from swarmnav.evaluation import truth_at_epochs

    tr = truth_at_epochs(Dataset.read(smoke))
    est = np.load(run.out / "estimates.npz")
    err = np.linalg.norm(est["pos"] - tr.pos, axis=2)
    assert np.nanmax(err[:, [0, 1, 2, 4]]) < 5.0, np.nanmax(err[:, [0, 1, 2, 4]])  # peers not poisoned
    assert np.sqrt(np.nanmean(err[-5:, 3] ** 2)) < 2.0, err[:, 3]  # UAV 4 back to normal by the end
    assert k_cont < 55


def test_standalone_router_restart_loses_nothing(smoke, tmp_path):
    """docs/deployment.md's multi-host path: a router started by hand, the services as its clients
    (no identities: security lives in the router's config). SIGKILL the router at epoch 20, restart
    it on the same port 2 s later: every service ends by itself and nothing is missing."""
    import zenoh

    from services.runtime.zconf import client_config

    with socket.socket() as s_:
        s_.bind(("127.0.0.1", 0))
        port = s_.getsockname()[1]
    ep = f"tcp/127.0.0.1:{port}"
    router = [sys.executable, "-m", "deploy.router", "--listen", ep]
    logs = tmp_path / "logs"
    logs.mkdir()

    spawn = functools.partial(_spawn, logs)
    r1 = spawn("router1", router)
    time.sleep(1.5)
    run = "t" + uuid.uuid4().hex[:8]
    common = ["--router", ep, "--run", run]
    out = tmp_path / "run"
    out.mkdir()
    procs = {"monitor": spawn("monitor", [sys.executable, "-m", "services.monitor", *common, "--dataset", str(smoke), "--seed", "1", "--out", str(out)]),
             "sensor_sim": spawn("sim", [sys.executable, "-m", "services.sensor_sim", *common, "--dataset", str(smoke), "--seed", "1"])}
    for u in range(1, 6):
        procs[f"uav{u}"] = spawn(f"uav{u}", [sys.executable, "-m", "services.uav_node", *common, "--uav", str(u)])
    r2 = None
    try:
        clk = Clock(zenoh.open(client_config(ep)), run)
        clk.wait(20)
        r1.send_signal(signal.SIGKILL)
        r1.wait()
        time.sleep(2.0)
        r2 = spawn("router2", router)
        end = time.monotonic() + 120
        while time.monotonic() < end and any(p.poll() is None for p in procs.values()):
            time.sleep(0.2)
        clk.close()
        assert {n: p.poll() for n, p in procs.items()} == {n: 0 for n in procs}
    finally:
        for p in [*procs.values(), r1] + ([r2] if r2 else []):
            if p.poll() is None:
                p.kill()
    rep = json.loads((out / "report.json").read_text())
    assert rep["complete"] is True and rep["estimates_received"] == 300, rep
    assert [e["kind"] for e in rep["events"]][:2] == ["bus_outage", "bus_restored"], rep["events"]


def test_frozen_monitor_in_real_time_loses_the_outage_and_says_so(smoke, tmp_path):
    """--rate 2, the monitor SIGSTOPped 6 s: the sensor-sim holds (nothing would record the epochs),
    real time goes on, so the epochs of the outage are lost — recorded as lost, the nodes
    re-bootstrap after the jump, the run is incomplete and exits non-zero; no process crashes."""
    run = Run(tmp_path / "run", "--rate", "2", dataset=smoke)
    run.freeze("monitor", 8, 6.0)
    rc = run.wait(120)
    rep = run.report()
    kinds = [e["kind"] for e in rep["events"]]
    assert "bus_outage" in kinds and "epochs_lost" in kinds and "rebootstrap" in kinds, kinds
    assert rc != 0 and rep["complete"] is False and rep["epochs_lost"], rep
    for log in (run.out / "logs").glob("*.log"):
        assert "Traceback" not in log.read_text(), log.name


def test_standalone_services_stop_by_themselves_when_the_sensor_sim_dies(smoke, tmp_path):
    """No launcher to stop them (multi-host): the nodes and the monitor notice the sensor-sim is
    gone while the router is up, stop with status 4, and the monitor writes an incomplete report."""
    import zenoh

    from services.runtime.zconf import client_config, free_port

    ep = f"tcp/127.0.0.1:{free_port()}"
    logs = tmp_path / "logs"
    logs.mkdir()

    spawn = functools.partial(_spawn, logs)
    router = spawn("router", [sys.executable, "-m", "deploy.router", "--listen", ep])
    time.sleep(1.5)
    run, out = "t" + uuid.uuid4().hex[:8], tmp_path / "run"
    out.mkdir()
    common = ["--router", ep, "--run", run, "--sim-lost-timeout", "4"]
    procs = {"monitor": spawn("monitor", [sys.executable, "-m", "services.monitor", *common, "--dataset", str(smoke),
                                          "--seed", "1", "--out", str(out)])}
    for u in range(1, 6):
        procs[f"uav{u}"] = spawn(f"uav{u}", [sys.executable, "-m", "services.uav_node", *common, "--uav", str(u)])
    sim = spawn("sim", [sys.executable, "-m", "services.sensor_sim", "--router", ep, "--run", run, "--dataset", str(smoke),
                        "--seed", "1", "--rate", "4"])
    try:
        clk = Clock(zenoh.open(client_config(ep)), run)
        clk.wait(10)
        sim.kill()
        end = time.monotonic() + 60
        while time.monotonic() < end and any(p.poll() is None for p in procs.values()):
            time.sleep(0.2)
        clk.close()
        assert {n: p.poll() for n, p in procs.items()} == {n: 4 for n in procs}
    finally:
        for p in [*procs.values(), sim, router]:
            if p.poll() is None:
                p.kill()
    rep = json.loads((out / "report.json").read_text())
    assert rep["complete"] is False and "sensor_sim_lost" in [e["kind"] for e in rep["events"]]
