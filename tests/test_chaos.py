"""`python -m deploy.chaos --quick`: the baseline, a killed master and a restarted standalone router,
each a real multi-process swarm on `smoke` (about a minute on 2 cores)."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.integration
def test_chaos_quick(tmp_path):
    out = tmp_path / "chaos"
    env = dict(os.environ, PYTHONPATH=f"{REPO}:{REPO / 'shared'}")
    r = subprocess.run([sys.executable, "-m", "deploy.chaos", "--quick", "--out", str(out)], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    doc = json.loads((out / "chaos.json").read_text())
    faults = {f["fault"]: f for f in doc["faults"]}
    assert list(faults) == ["none", "kill-master", "router-restart"], list(faults)
    base, master, router = faults["none"], faults["kill-master"], faults["router-restart"]
    assert base["complete"] is True and (base["estimates_received"], base["estimates_expected"]) == (300, 300), base
    assert doc["baseline_rmse_m"] == base["swarm_rmse_m"] and math.isfinite(doc["baseline_rmse_m"])
    # the scheduled kill of the master is excused: complete, and the four survivors are still estimated
    assert master["complete"] is True, master
    assert master["survivors"] == [1, 3, 4, 5] and math.isfinite(master["survivors_rmse_m"]), master
    assert math.isfinite(master["survivors_rmse_change_pct"]), master
    assert any(e["kind"] == "dropout" and e["uav"] == 2 for e in master["events"]), master["events"]
    # the router came back and the run lost nothing
    assert router["complete"] is True and router["exit"] == 0, router
    assert router["estimates_received"] == router["estimates_expected"] > 0, router
    assert not any((router["missing_by_uav"] or {}).values()) and router["epochs_lost"] == 0, router
    md = (out / "chaos.md").read_text()
    for name in faults:
        assert sum(line.startswith(f"| {name} |") for line in md.splitlines()) == 1, (name, md)
