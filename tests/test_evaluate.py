"""`swarmnav evaluate` end to end on smoke with a cheap stand-in estimator, and --seeds parsing."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from services.commands.evaluate import parse_algos, parse_seeds
from swarmnav.errors import ConfigError
from swarmnav.estimators import registry
from swarmnav.estimators.base import LinkClass, LinkInfo, NodeEstimate, NodeEstimator, NodeState
from swarmnav.report import validate_report

ROOT = Path(__file__).resolve().parents[1]
RERUN = ROOT / ".venv" / "bin" / "rerun"


class GnssHold(NodeEstimator):
    """Test stand-in: GNSS position/velocity, dead-reckoned when GNSS is missing; classifies each
    range by its residual against the peers' round-0 states with fixed thresholds 1 m / 10 m."""

    name = "gnsshold"
    DL, DH = 1.0, 10.0

    def begin_epoch(self, inp):
        prev = getattr(self, "_est", None)
        if inp.gnss_pos is not None:
            pos, vel, sig = inp.gnss_pos, inp.gnss_vel, inp.gnss_pos_sigma
        elif prev is not None:
            pos, vel, sig = prev.pos + prev.vel * (inp.t - inp.t_prev), prev.vel, np.sqrt(np.diag(prev.pos_cov)) + 1.0
        else:
            pos, vel, sig = self.init.pos, self.init.vel, self.init.pos_sigma
        self._inp = inp
        self._links = []
        ranges = {int(o): float(r) for o, r in zip(inp.range_other, inp.range_m)}
        self._last_state = NodeState(self.uav, inp.k, 0, inp.t, np.asarray(pos, float), np.diag(np.asarray(sig, float) ** 2),
                                     np.asarray(vel, float), float("inf"), ranges)
        return self._last_state

    def iterate(self, r, peers):
        s = self._last_state
        self._links = []
        for o in sorted(s.ranges):
            if o in peers:
                res = abs(s.ranges[o] - float(np.linalg.norm(s.pos - peers[o].pos)))
                cls = LinkClass.H0_FAILED if res > self.DH else LinkClass.H1_INTERFERED if res > self.DL else LinkClass.H2_NORMAL
                self._links.append(LinkInfo(o, cls, res, float(cls == LinkClass.H2_NORMAL)))
        return NodeState(self.uav, s.k, r, s.t, s.pos, s.pos_cov, s.vel, 0.0)

    def end_epoch(self):
        s = self._last_state
        self._est = NodeEstimate(self.uav, s.k, s.t, s.pos, s.vel, s.pos_cov, links=self._links,
                                 delta_h_m=self.DH, delta_l_m=self.DL)
        return self._est


class GnssHoldWorse(GnssHold):
    name = "gnssworse"

    def end_epoch(self):
        e = super().end_epoch()
        return NodeEstimate(e.uav, e.k, e.t, e.pos + 2.0, e.vel, e.pos_cov, links=e.links)


@pytest.fixture
def stand_ins():
    # the stand-in takes atvfg's name so the atvfg-only parts (detection, thresholds) are exercised
    registry.register("atvfg", GnssHold)
    registry.register("fg", GnssHoldWorse)
    yield
    registry.unregister("atvfg")
    registry.unregister("fg")


def test_parse_seeds():
    assert parse_seeds("1-5") == [1, 2, 3, 4, 5]
    assert parse_seeds("1,3,7") == [1, 3, 7]
    assert parse_seeds("7,1-3, 2") == [1, 2, 3, 7]
    assert parse_seeds("0") == [0]
    for bad in ("", "a", "5-1", "1-", "-3"):
        with pytest.raises(ConfigError):
            parse_seeds(bad)


def test_parse_algos():
    assert parse_algos("atvfg,fg,atvfg") == ["atvfg", "fg"]
    with pytest.raises(ConfigError):
        parse_algos("atvfg,nope")


def _rrd_entities(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    ents = set()
    for ch in RrdReader(str(path)).stream().to_chunks():
        ents.add(str(ch.entity_path))
    return ents


def test_evaluate_smoke_end_to_end(tmp_path, stand_ins):
    pytest.importorskip("swarmnav.sim")
    from services.cli import main

    out = tmp_path / "run"
    rc = main(["evaluate", "--config", str(ROOT / "configs" / "smoke.toml"), "--algos", "atvfg,fg",
               "--seeds", "1-2", "--out", str(out), "--quiet"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert validate_report(rep) == []
    assert rep["mode"] == "in-process" and rep["seeds"] == [1, 2] and rep["n_uavs"] == 5
    assert rep["events"] == []
    assert set(rep["algorithms"]) == {"atvfg", "fg"}
    a, f = rep["algorithms"]["atvfg"], rep["algorithms"]["fg"]
    # GNSS-only stand-in: error is the GNSS error, slaves 5/5/8 m white + 3 m GM -> a few metres
    assert 1.0 < a["pos_rmse_m"]["3d"] < 20.0
    # fg stand-in = atvfg + 2 m on every axis: exactly sqrt(3)*2 m worse in the mean squared sense
    assert f["pos_rmse_m"]["3d"] > a["pos_rmse_m"]["3d"]
    assert rep["improvement_pct"]["atvfg_vs_fg"] > 0
    assert "atvfg_vs_fkf" not in rep["improvement_pct"]
    det = a["detection"]
    assert det is not None and det["tp"] + det["fn"] > 0  # smoke has labelled faults
    assert rep["thresholds"]["delta_h_m"]["p50"] == pytest.approx(10.0)
    assert rep["thresholds"]["delta_l_m"] is not None
    assert set(a["per_uav_pos_rmse_m"]) == {"1", "2", "3", "4", "5"}
    assert rep["provenance"]["config_sha256"] and "numpy" in rep["provenance"]["packages"]
    assert "/" not in rep["provenance"]["git"]
    md = (out / "report.md").read_text()
    assert "Table 2" in md and "atvfg" in md
    for png in ("pos_error_uav1", "vel_error_uav1", "pos_error_swarm", "vel_error_swarm", "detection_atvfg"):
        assert (out / "figures" / f"{png}.png").stat().st_size > 1000
    for algo in ("truth", "atvfg", "fg"):
        for u in range(1, 6):
            rows = (out / "traj" / algo / f"uav{u}.tum").read_text().split("\n")
            rows = [r for r in rows if r]
            assert len(rows) == 60
            vals = np.array(rows[0].split(), float)
            assert len(vals) == 8 and abs(np.linalg.norm(vals[4:]) - 1) < 1e-6
    assert (out / "traj" / "seed2" / "atvfg" / "uav1.tum").exists()
    assert (out / "evaluate.log").stat().st_size > 0
    rrd = out / "evaluate.rrd"
    if RERUN.exists():
        v = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=60)
        assert v.returncode == 0, v.stderr
    ents = _rrd_entities(rrd)
    for e in ("/swarm/truth/uav1", "/swarm/atvfg/uav1", "/swarm/fg/uav5", "/links/atvfg",
              "/errors/atvfg/pos_3d/swarm", "/errors/fg/pos_3d/uav1", "/events"):
        assert e in ents, (e, sorted(ents))


def test_evaluate_dataset_same_numbers_as_config(tmp_path, stand_ins):
    """--dataset DIR written by `simulate --seed N` gives the same estimates as --config --seeds N."""
    sim = pytest.importorskip("swarmnav.sim")
    from services.cli import main
    from swarmnav.config import load_config

    ds_dir = tmp_path / "ds"
    sim.simulate(load_config(ROOT / "configs" / "smoke.toml"), 3).write(ds_dir)
    outs = []
    for src in (["--dataset", str(ds_dir)], ["--config", str(ROOT / "configs" / "smoke.toml"), "--seeds", "3"]):
        out = tmp_path / src[0].strip("-")
        assert main(["evaluate", *src, "--algos", "atvfg", "--out", str(out), "--quiet", "--no-rrd", "--jobs", "1"]) == 0
        outs.append(json.loads((out / "report.json").read_text()))
    assert outs[0]["seeds"] == [3]
    assert outs[0]["algorithms"]["atvfg"]["pos_rmse_m"] == outs[1]["algorithms"]["atvfg"]["pos_rmse_m"]
    assert outs[0]["algorithms"]["atvfg"]["detection"] == outs[1]["algorithms"]["atvfg"]["detection"]


def test_recording_scales_points_to_the_scene_and_draws_anchors(tmp_path):
    """UAV points are 1 % of the scene's extent within [2 cm, 2 m] (a km-scale swarm keeps 2 m, an
    indoor flight gets a few cm); anchors are one static entity with every anchor."""
    from rerun.chunk import RrdReader

    from services import recording as R

    assert R.point_radius(np.array([[0, 0, 0], [3000.0, 4000.0, 0]])) == 2.0
    assert R.point_radius(np.array([[0, 0, 0], [3.0, 4.0, 0], [np.nan, 1, 1]])) == pytest.approx(0.05)
    assert R.point_radius(np.zeros((4, 3))) == 0.02 and R.point_radius(np.full((2, 3), np.nan)) == 2.0
    rec = R.open_recording(tmp_path / "a.rrd")
    R.log_anchors({100: np.array([1.0, 2.0, 3.0]), 105: np.array([-1.0, 0.0, 2.0])}, 0.05, rec)
    R.log_anchors({}, 0.05, rec)  # no anchors (a simulated swarm): nothing logged
    R.close_recording(rec)
    chunks = [c for c in RrdReader(str(tmp_path / "a.rrd")).stream().to_chunks() if str(c.entity_path) == "/swarm/anchors"]
    assert len(chunks) == 1 and chunks[0].is_static
