"""Golden figures: the atvfg 3-D position RMSE on `smoke` seed 1 and on the MILUV flight (seed 0).

Refactoring changes no figure. Only a commit that says why (an estimator change, named with the new
figure in its message) may change these numbers; they are the same references the architecture
acceptance check holds the project to.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMOKE_S1_ATVFG_RMSE_M = 0.6069565575842713
MILUV_S0_ATVFG_RMSE_M = 0.4880373523373317
MILUV = Path(os.environ.get("SWARMNAV_MILUV_DIR")
             or ROOT / ".." / "shared" / "data" / "miluv" / "cirObstacles_3_random_0").resolve()


def _atvfg_rmse(out: Path) -> float:
    return json.loads((out / "report.json").read_text())["algorithms"]["atvfg"]["pos_rmse_m"]["3d"]


def test_smoke_seed1_atvfg_figure_unchanged(tmp_path):
    from services.cli import main

    rc = main(["evaluate", "--config", str(ROOT / "configs" / "smoke.toml"), "--algos", "atvfg", "--seeds", "1",
               "--out", str(tmp_path / "out"), "--no-rrd", "--jobs", "1"])
    assert rc in (0, None)
    assert _atvfg_rmse(tmp_path / "out") == pytest.approx(SMOKE_S1_ATVFG_RMSE_M, abs=1e-9)


@pytest.mark.slow
@pytest.mark.skipif(not MILUV.is_dir(), reason=f"MILUV recording not available at {MILUV}")
def test_miluv_atvfg_figure_unchanged(tmp_path):
    from services.cli import main

    assert main(["import-miluv", str(MILUV), "--out", str(tmp_path / "ds")]) in (0, None)
    rc = main(["evaluate", "--dataset", str(tmp_path / "ds"), "--algos", "atvfg", "--seeds", "0",
               "--out", str(tmp_path / "out"), "--no-rrd", "--jobs", "1"])
    assert rc in (0, None)
    assert _atvfg_rmse(tmp_path / "out") == pytest.approx(MILUV_S0_ATVFG_RMSE_M, abs=1e-9)
