"""Multi-process integration on `smoke`: real embedded router on loopback, real processes, no mocks.

Two launches (module fixtures, ~10 s each on 2 cores):

* ``base``: a distributed lockstep run with garbage injected at epoch 3 on every key the nodes
  listen to. It must equal the in-process evaluation of the same checkout, dataset and seed:
  tolerance 1e-6 m / 1e-6 m/s absolute on every position / velocity estimate of every UAV and
  epoch (observed: bit-identical, 0.0). Every garbage message is rejected and counted by every
  node. The monitor's recording reads back with ``rerun.chunk.RrdReader`` with the expected
  entities and one row per epoch.
* ``drop``: UAV 2 SIGKILLed at t=15 s and restarted at t=25 s. Every other node estimates every
  epoch without stalling, nobody uses UAV 2's states while it is gone, the monitor records the
  dropout and the rejoin, the restarted node bootstraps from its peers by query and its error
  comes back; the whole run equals an in-process emulation of the same kill/restart schedule
  (1e-6 m; observed bit-identical).

Both launches must exit 0 in every process (no hang, no abort at exit) and leave no process behind.
"""

import ast
import json
import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.integration]
REPO = Path(__file__).resolve().parents[1]
SWARMNAV = [sys.executable, "-m", "services.cli"]
ALGO = "atvfg"
KILL_T, RESTART_T = 15.0, 25.0
PEER_TIMEOUT_S = 2.0  # estimation.peer_timeout_s default


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    d = tmp_path_factory.mktemp("smoke") / "dataset"
    simulate(load_config(REPO / "configs/smoke.toml"), 1).write(d)
    return d


def _leftovers(path) -> list[str]:
    r = subprocess.run(["pgrep", "-af", str(path)], capture_output=True, text=True)
    return [ln for ln in r.stdout.splitlines() if "pgrep" not in ln]


def _launch(dataset, out, *extra):
    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    r = subprocess.run([*SWARMNAV, "launch", "--dataset", str(dataset), "--algo", ALGO, "--seed", "1", "--out", str(out),
                        "--no-progress", *extra], cwd=REPO, env=env, capture_output=True, text=True, timeout=150)
    left = _leftovers(out)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rep = json.loads((out / "report.json").read_text())
    return {"rep": rep, "est": np.load(out / "estimates.npz"), "dir": out, "left": left}


@pytest.fixture(scope="module")
def base(smoke, tmp_path_factory):
    return _launch(smoke, tmp_path_factory.mktemp("base") / "run", "--garbage-at", "3")


@pytest.fixture(scope="module")
def drop(smoke, tmp_path_factory):
    return _launch(smoke, tmp_path_factory.mktemp("drop") / "run", "--kill", f"2@{KILL_T:g}", "--restart", f"2@{RESTART_T:g}")


@pytest.fixture(scope="module")
def truth(smoke):
    from swarmnav.dataset import Dataset
    from swarmnav.evaluation import truth_at_epochs

    return truth_at_epochs(Dataset.read(smoke))


def _in_process_dropout(dataset, uav, t_kill, t_restart):
    """The kill/restart run emulated in one process with the core's epoch protocol: the UAV takes no
    part in epochs with t_kill <= t < t_restart; before the first epoch with t >= t_restart it is
    rebuilt from the sensor-sim's restart alignment and bootstrapped from its peers' last states."""
    from services.sensor_sim.sim import restart_initial_state
    from services.settings import settings_for_dataset
    from swarmnav.dataset import Dataset, EpochSlicer, node_view
    from swarmnav.estimators import registry
    from swarmnav.evaluation import truth_at_epochs
    from swarmnav.initial import initial_states
    from swarmnav.protocol import node_epoch, run_epoch_in_process
    from swarmnav.scenario import estimation_values

    ds = Dataset.read(dataset)
    meta, uavs, K = ds.meta, ds.meta.uav_ids(), ds.meta.n_epochs()
    st = settings_for_dataset(meta)
    est = estimation_values(st)
    rounds, tol = est.rounds, est.convergence_m
    inits, tr, sl = initial_states(ds, 1), truth_at_epochs(ds), EpochSlicer(ds)
    nmeta = node_view(meta)  # what the sensor-sim's meta answer gives a node
    nodes = {u: registry.make_node(ALGO, u, nmeta, st, inits[u]) for u in uavs}
    last, pos, restarted = {}, np.full((K, len(uavs), 3), np.nan), False
    for k in range(1, K + 1):
        t = meta.epoch_time(k)
        if t >= t_restart and not restarted:
            restarted = True
            nodes[uav] = registry.make_node(ALGO, uav, nmeta, st, restart_initial_state(tr, inits, uavs, 1, uav, k))
            inp = sl.epoch(k, uav)
            nodes[uav].bootstrap(inp.t_prev, {u: s for u, s in sorted(last.items()) if u != uav}, inp)
        part = [u for u in uavs if u != uav or not (t_kill <= t < t_restart)]
        gens = {u: node_epoch(nodes[u], sl.epoch(k, u), rounds, tol) for u in part}
        for u, est in run_epoch_in_process(gens, last_states=last).items():
            pos[k - 1, uavs.index(u)] = est.pos
    return pos


def _clean_exit(run):
    """Every process exited 0 (a hang would have been killed: non-zero), none aborted, none left."""
    procs = run["rep"]["distributed"]["processes"]
    assert all(p["exit"] == 0 for p in procs.values()), procs
    for log in (run["dir"] / "logs").glob("*.log"):
        text = log.read_text()
        assert "FATAL" not in text and "Traceback" not in text, (log.name, text[-1500:])
    assert not run["left"], run["left"]


def test_distributed_equals_in_process_with_garbage(smoke, base):
    from swarmnav.dataset import Dataset
    from swarmnav.evaluation import run_algorithm

    from services.runtime.service import code_digest
    from services.settings import settings_for_dataset

    ds = Dataset.read(smoke)
    ref = run_algorithm(ds, ALGO, 1, settings_for_dataset(ds.meta))
    # both sides must have run the same estimator code (sources may be edited while tests run)
    mine = code_digest()
    theirs = {u: re.search(r"code ([0-9a-f]{12})", (base["dir"] / "logs" / f"uav{u}.log").read_text()).group(1)
              for u in ds.meta.uav_ids()}
    if set(theirs.values()) != {mine}:
        pytest.fail(f"swarmnav sources changed during the test (in-process ran {mine}, nodes ran {theirs}): "
                    "an edit in progress, not a transport difference; rerun")
    rep, est = base["rep"], base["est"]
    assert rep["mode"] == "distributed" and rep["security"] == {"mode": "mtls", "acl": True}
    # the only events: the garbage the monitor and the nodes saw, counted per reason in the report
    # (the monitor's own: a clock of an unknown version; each node's, carried in its estimates)
    assert {e["kind"] for e in rep["events"]} == {"rejected_messages"}, rep["events"]
    assert rep["rejected"]["clock:version"] == 1
    for u in (1, 2, 3, 4, 5):
        assert rep["rejected"][f"uav{u}/input:malformed"] == 3 and rep["rejected"][f"uav{u}/input:version"] == 1, rep["rejected"]
    assert rep["complete"] is True and rep["estimates_received"] == rep["estimates_expected"] == 300
    assert np.isfinite(est["pos"]).all()
    np.testing.assert_allclose(est["pos"], ref.pos, rtol=0, atol=1e-6)
    np.testing.assert_allclose(est["vel"], ref.vel, rtol=0, atol=1e-6)
    # every node used every peer in every epoch (no peer was ever timed out)
    n = len(ds.meta.uav_ids())
    assert est["peers"].sum(axis=2).min() == n - 1
    # the garbage did not change the result (above) and every node rejected and counted each
    # message it received: 4 on its input key (3 JSON/garbage, 1 binary frame of an unknown version)
    # + the clock = 5. The 4 truncated state frames the sensor-sim also put on uav/<id>/state never
    # arrived: the router's ACL drops them (only UAV <id> may write its state).
    for u in ds.meta.uav_ids():
        log = (base["dir"] / "logs" / f"uav{u}.log").read_text()
        m = re.search(rf"exiting after epoch {ds.meta.n_epochs()}; rejected messages: (\d+) (\{{.*?\}})", log)
        assert m and int(m.group(1)) == 5, log[-1500:]
        counts = ast.literal_eval(m.group(2))  # {"topic:reason": n}
        assert counts.get("input:malformed") == 3 and counts.get("input:version") == 1, counts
        assert any(k.startswith("clock:") for k in counts) and not any(k.startswith("state:") for k in counts), counts
    _clean_exit(base)


def test_recording_reads_back(smoke, base):
    import rerun as rr
    from swarmnav.dataset import Dataset

    meta = Dataset.read(smoke).meta
    K, uavs = meta.n_epochs(), meta.uav_ids()
    rrd = base["dir"] / "swarm.rrd"
    subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(rrd)], check=True, capture_output=True)
    rows: Counter = Counter()
    for chunk in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] += chunk.num_rows
    for u in uavs:  # one estimate and one truth position per UAV per epoch
        assert rows[f"/swarm/{ALGO}/uav{u}"] == K, rows
        assert rows[f"/swarm/truth/uav{u}"] == K, rows
    assert rows[f"/links/{ALGO}"] == K, rows
    for series in ("pos_3d/swarm", "vel_3d/swarm", "pos_3d/uav1"):
        assert rows[f"/errors/{ALGO}/{series}"] == K, (series, rows)
    assert rows["/events"] == 1 + len(base["rep"]["events"]), rows  # the run's start line + one per event


def test_dropout_and_rejoin(smoke, drop, truth):
    rep, est = drop["rep"], drop["est"]
    ev = [e for e in rep["events"] if e["uav"] == 2]
    assert [e["kind"] for e in ev] == ["scheduled_kill", "dropout", "scheduled_restart", "rejoin", "rebootstrap"], ev
    assert [e["t"] for e in ev] == [KILL_T, KILL_T, RESTART_T, RESTART_T, RESTART_T], ev
    # the scheduled window is excused: the run is complete
    assert rep["complete"] is True and rep["missing_by_uav"]["2"] == 0, rep
    pos, t = est["pos"], est["t"]
    uavs = list(est["uavs"])
    j = uavs.index(2)
    others = [i for i in range(len(uavs)) if i != j]
    # every other node produced an estimate every epoch, without waiting out a peer timeout
    assert np.isfinite(pos[:, others]).all(), "another node missed an epoch"
    assert np.nanmax(est["wait_ms"][:, others]) < PEER_TIMEOUT_S * 1e3, np.nanmax(est["wait_ms"][:, others])
    gone = (t >= KILL_T) & (t < RESTART_T)
    assert not np.isfinite(pos[gone, j]).any() and np.isfinite(pos[t >= RESTART_T, j]).all()
    # the lost peer is out of every other node's graph from the first epoch after the kill, and back after the rejoin
    peers = est["peers"]
    k_kill = int(np.argmax(t >= KILL_T))
    assert peers[k_kill - 1, others, j].all() and not peers[gone][:, others, j].any()
    assert peers[t >= RESTART_T + 1][:, others, j].all()
    # the restarted node bootstrapped from its peers' states, queried over Zenoh
    log = (drop["dir"] / "logs" / "uav2.log").read_text()
    # every node, forked from the zygote at the start or restarted, ran with --cpu-policy batch
    for name in ("uav1.log", "uav2.log"):
        ups = re.findall(r"UAV \d+ up: .*cpu (.*)", (drop["dir"] / "logs" / name).read_text())
        assert ups and all(u == "batch (switch 50 ms)" for u in ups), (name, ups)
    m = re.search(r"rejoin True.*?bootstrapping at epoch (\d+) from peers \[([\d, ]+)\]", log, re.S)
    assert m and int(m.group(1)) == int(np.argmax(t >= RESTART_T)) + 1, log[-1500:]
    assert sorted(map(int, m.group(2).split(","))) == [u for u in uavs if u != 2]
    # the whole run, dropout and rejoin included, is the in-process emulation of the same schedule
    np.testing.assert_allclose(pos, _in_process_dropout(smoke, 2, KILL_T, RESTART_T), rtol=0, atol=1e-6)
    # and its error comes down (it restarts from a coarse alignment)
    err = np.linalg.norm(pos[:, j] - truth.pos[:, j], axis=1)
    back = t >= RESTART_T
    assert err[back][-1] < 0.5 * err[back][0] and err[back][-1] < 5.0, err[back]
    rows = Counter()
    import rerun as rr

    for chunk in rr.chunk.RrdReader(str(drop["dir"] / "swarm.rrd")).stream().to_chunks():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] += chunk.num_rows
    assert rows["/events"] == 1 + len(rep["events"]) and rows[f"/swarm/{ALGO}/uav2"] == int((~gone).sum()), rows
    _clean_exit(drop)


def test_rejoined_error_normal_within_30_epochs(base, drop, truth):
    t = drop["est"]["t"]
    j = list(drop["est"]["uavs"]).index(2)
    after = t >= RESTART_T + 30 * (t[1] - t[0])
    assert after.any()
    e_drop = np.linalg.norm(drop["est"]["pos"][after, j] - truth.pos[after, j], axis=1)
    e_base = np.linalg.norm(base["est"]["pos"][after, j] - truth.pos[after, j], axis=1)
    assert e_drop.mean() <= 1.5 * e_base.mean() + 0.3, (e_drop, e_base)


def test_multi_host_config_files_router_and_client(tmp_path):
    """deploy/zenoh-router.json5 + `python -m deploy.router` and deploy/zenoh-client.json5 + client_config
    (what a node on another host uses) connect, route a sample, and the router exits 0 on SIGTERM."""
    import signal
    import time

    import zenoh

    from services.runtime.zconf import client_config, free_port

    ep = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    log = open(tmp_path / "router.log", "w")
    r = subprocess.Popen([sys.executable, "-m", "deploy.router", "--config", str(REPO / "deploy/zenoh-router.json5"),
                          "--listen", ep, "--tag", str(tmp_path)], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        cfg = str(REPO / "deploy/zenoh-client.json5")
        with zenoh.open(client_config(ep, cfg)) as a, zenoh.open(client_config(ep, cfg)) as b:
            for _ in range(100):
                if a.info.routers_zid() and b.info.routers_zid():
                    break
                time.sleep(0.1)
            assert a.info.routers_zid() and b.info.routers_zid(), "client did not reach the router"
            sub = b.declare_subscriber("swarmnav/t/uav/1/state", zenoh.handlers.FifoChannel(10))
            time.sleep(0.3)
            a.put("swarmnav/t/uav/1/state", b"x")
            s = sub.recv()
            assert s.payload.to_bytes() == b"x"
            sub.undeclare()
    finally:
        r.send_signal(signal.SIGTERM)
        rc = r.wait(timeout=10)
        log.close()
    assert rc == 0, (tmp_path / "router.log").read_text()
    assert "listening on" in (tmp_path / "router.log").read_text()
    assert not _leftovers(tmp_path)


def test_default_run_dir_is_one_level():
    """A recorded dataset's name may contain '/' (MILUV: "miluv/<experiment>"): the default run
    directory stays one level below runs/, so runs/latest (a link by base name) resolves."""
    from services.commands.launch import default_run_dir

    d = default_run_dir("miluv/cirObstacles_3_random_0")
    assert d.parent == Path("runs") and d.name.endswith("-miluv-cirObstacles_3_random_0")
    assert default_run_dir("paper").name.endswith("-paper") and default_run_dir("//").name.endswith("-run")


def test_every_view_of_the_launch_recording_has_data(base):
    """The monitor's recording (per-epoch segments merged at the end) against its own blueprint."""
    sys.path.insert(0, str(Path(__file__).parent))
    import rrdcheck

    from services import recording as R

    rows, static = rrdcheck.recorded(base["dir"] / "swarm.rrd")
    assert rrdcheck.view_problems(R.blueprint_views([ALGO], [ALGO]), rows, static) == []
    assert rows[R.labels_path(ALGO)]["Points3D:labels"] == 60 and "Points3D:labels" not in rows[R.uav_path(ALGO, 1)]
