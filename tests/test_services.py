"""Multi-process integration on `smoke`: real embedded router on loopback, real processes, no mocks.

One distributed run (with garbage injected on every key the nodes listen to) must equal the
in-process evaluation (tolerance 1e-6 m absolute on every position estimate, observed ~1e-12);
the recording must read back; a kill/restart run must record the dropout and rejoin, keep every
other node estimating every epoch and bring the restarted node's error back; nothing may be left.
"""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.integration]
REPO = Path(__file__).resolve().parents[1]
SWARMNAV = [sys.executable, "-m", "services.cli"]
ALGO = "atvfg"


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    d = tmp_path_factory.mktemp("smoke") / "dataset"
    simulate(load_config(REPO / "configs/smoke.toml"), 1).write(d)
    return d


def _launch(dataset, out, *extra):
    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    r = subprocess.run([*SWARMNAV, "launch", "--dataset", str(dataset), "--algo", ALGO, "--seed", "1", "--out", str(out),
                        "--no-progress", *extra], cwd=REPO, env=env, capture_output=True, text=True, timeout=150)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return json.loads((out / "report.json").read_text()), np.load(out / "estimates.npz")


def _leftovers(path) -> list[str]:
    r = subprocess.run(["pgrep", "-af", str(path)], capture_output=True, text=True)
    return [ln for ln in r.stdout.splitlines() if "pgrep" not in ln]


def test_distributed_equals_in_process_with_garbage(smoke, tmp_path):
    from swarmnav.dataset import Dataset
    from swarmnav.estimators import registry
    from swarmnav.evaluation import run_algorithm

    ds = Dataset.read(smoke)
    ref = run_algorithm(ds, ALGO, 1, registry.settings_for_dataset(ds.meta))
    rep, est = _launch(smoke, tmp_path / "run", "--garbage-at", "3")
    assert rep["mode"] == "distributed" and rep["events"] == []
    assert np.isfinite(est["pos"]).all()
    np.testing.assert_allclose(est["pos"], ref.pos, rtol=0, atol=1e-6)
    np.testing.assert_allclose(est["vel"], ref.vel, rtol=0, atol=1e-6)
    # every garbage message was rejected and counted by every node: 5 sensor keys + 4 peer states + clock
    for u in ds.meta.uav_ids():
        log = (tmp_path / "run" / "logs" / f"uav{u}.log").read_text()
        m = re.search(r"exiting after epoch 60; rejected messages: (\d+)", log)
        assert m and int(m.group(1)) == 10, log[-1500:]
    # the recording is a valid, complete .rrd with the entities we logged
    rrd = tmp_path / "run" / "swarm.rrd"
    subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "verify", str(rrd)], check=True, capture_output=True)
    import rerun as rr

    paths = set()
    for chunk in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        paths.add(str(chunk.entity_path))
    assert {f"/swarm/{ALGO}/uav1", "/swarm/truth/uav1", f"/links/{ALGO}", f"/errors/{ALGO}/pos_3d/swarm"} <= paths, paths
    assert not _leftovers(tmp_path)


def test_dropout_and_rejoin(smoke, tmp_path):
    base = np.load(tmp_path.parent / "test_distributed_equals_in_p0" / "run" / "estimates.npz") \
        if (tmp_path.parent / "test_distributed_equals_in_p0").exists() else None
    rep, est = _launch(smoke, tmp_path / "drop", "--kill", "2@15", "--restart", "2@25")
    ev = [e for e in rep["events"] if e["uav"] == 2]
    assert [e["kind"] for e in ev] == ["dropout", "rejoin"] and ev[0]["t"] == 15.0 and ev[1]["t"] == 25.0
    pos, t = est["pos"], est["t"]
    uavs = list(est["uavs"])
    j = uavs.index(2)
    others = [i for i in range(len(uavs)) if i != j]
    assert np.isfinite(pos[:, others]).all(), "another node missed an epoch"
    gone = (t > 15) & (t < 25)
    assert not np.isfinite(pos[gone, j]).any() and np.isfinite(pos[t >= 25, j]).all()
    from swarmnav.dataset import Dataset
    from swarmnav.evaluation import truth_at_epochs

    tr = truth_at_epochs(Dataset.read(smoke))
    err = np.linalg.norm(pos[:, j] - tr.pos[:, j], axis=1)
    normal = np.nanmedian(err[t < 15])
    assert np.nanmedian(err[(t >= 35) & (t <= 55)]) < max(3 * normal, 5.0), (normal, err)
    assert not _leftovers(tmp_path)
