"""`swarmnav evaluate` end to end with the real estimators on a short smoke scenario, and --seeds parsing."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from services.commands.evaluate import config_seeds, parse_algos, parse_seeds
from swarmnav.config import load_config
from swarmnav.errors import ConfigError
from swarmnav.report import validate_report

ROOT = Path(__file__).resolve().parents[1]
RERUN = ROOT / ".venv" / "bin" / "rerun"
SHORT_S = 30  # smoke cut to 30 s: the module failure (15-25 s) and interference stay in, a few s per run


@pytest.fixture(scope="module")
def short_smoke(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "smoke_short.toml"
    p.write_text(f'base = "{(ROOT / "configs" / "smoke.toml").as_posix()}"\n[scenario]\nname = "smoke_short"\n'
                 f"duration_s = {SHORT_S}.0\n")
    return p


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


def test_evaluate_smoke_end_to_end(tmp_path, short_smoke):
    """The real atvfg and fg over two seeds: report contract, Monte-Carlo and consistency blocks,
    detection against the labels, figures, TUM files, .rrd."""
    from services.cli import main

    out = tmp_path / "run"
    rc = main(["evaluate", "--config", str(short_smoke), "--algos", "atvfg,fg",
               "--seeds", "1-2", "--out", str(out), "--quiet"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert validate_report(rep) == []
    assert rep["mode"] == "in-process" and rep["seeds"] == [1, 2] and rep["n_uavs"] == 5
    assert rep["events"] == []
    assert set(rep["algorithms"]) == {"atvfg", "fg"}
    a, f = rep["algorithms"]["atvfg"], rep["algorithms"]["fg"]
    # cooperative UWB fixes the slaves' 5-8 m GNSS to well under a metre; fg swallows the failed module
    assert 0.05 < a["pos_rmse_m"]["3d"] < 1.5
    assert f["pos_rmse_m"]["3d"] > a["pos_rmse_m"]["3d"]
    assert rep["improvement_pct"]["atvfg_vs_fg"] > 0
    assert "atvfg_vs_fkf" not in rep["improvement_pct"]
    det = a["detection"]
    assert det is not None and det["tp"] + det["fn"] > 0 and det["recall"] > 0.5  # the failed module is caught
    dh, dl = rep["thresholds"]["delta_h_m"]["p50"], rep["thresholds"]["delta_l_m"]
    assert dl is not None and dh is not None and 0 < dl < dh
    assert set(a["per_uav_pos_rmse_m"]) == {"1", "2", "3", "4", "5"}
    # the seeds are the scenario's report seeds (smoke inherits paper's [evaluation])
    assert rep["evaluation"]["seeds_role"] == "report" and rep["evaluation"]["tuning_seeds"][0] == 1001
    # Monte Carlo over the two seeds: per-seed RMSEs whose pooled RMS is the pooled figure
    mc = rep["monte_carlo"]
    assert mc["n_seeds"] == 2 and set(mc["per_algorithm"]) == {"atvfg", "fg"}
    ps = mc["per_algorithm"]["atvfg"]["per_seed"]
    assert set(ps) == {"1", "2"}
    assert np.sqrt(np.mean(np.square(list(ps.values())))) == pytest.approx(a["pos_rmse_m"]["3d"], rel=1e-9)
    lo, hi = mc["per_algorithm"]["atvfg"]["ci95"]
    assert lo < mc["per_algorithm"]["atvfg"]["mean"] < hi
    d = mc["paired"]["atvfg-fg"]
    assert d["n"] == 2 and d["mean"] == pytest.approx(np.mean([ps[s] - mc["per_algorithm"]["fg"]["per_seed"][s]
                                                               for s in ("1", "2")]))
    # consistency keys (the report contract) for every algorithm
    for blk in (a, f):
        assert blk["nees_mean"] == pytest.approx(blk["nees"]) and 0 <= blk["nees_in_band_share"] <= 1
        assert blk["nees_n"] == 2 * SHORT_S * 5
        assert blk["range_nis"]["nis_rows"] == "labelled clean" and blk["range_nis"]["nis_n"] > 100
    assert a["range_nis"]["nis_median"] < f["range_nis"]["nis_median"]  # fg is overconfident
    assert rep["provenance"]["config_sha256"] and "numpy" in rep["provenance"]["packages"]
    assert "/" not in rep["provenance"]["git"]
    md = (out / "report.md").read_text()
    assert "Table 2" in md and "atvfg" in md and "Monte Carlo over 2 seeds" in md and "Consistency" in md
    assert "Range NIS" in md
    for png in ("pos_error_uav1", "vel_error_uav1", "pos_error_swarm", "vel_error_swarm", "detection_atvfg"):
        assert (out / "figures" / f"{png}.png").stat().st_size > 1000
    for algo in ("truth", "atvfg", "fg"):
        for u in range(1, 6):
            rows = (out / "traj" / algo / f"uav{u}.tum").read_text().split("\n")
            rows = [r for r in rows if r]
            assert len(rows) == SHORT_S
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


def test_evaluate_dataset_same_numbers_as_config(tmp_path, short_smoke):
    """--dataset DIR written by `simulate --seed N` gives the same estimates as --config --seeds N."""
    from services.cli import main
    from swarmnav.sim import simulate

    ds_dir = tmp_path / "ds"
    simulate(load_config(short_smoke), 3).write(ds_dir)
    outs = []
    for src in (["--dataset", str(ds_dir)], ["--config", str(short_smoke), "--seeds", "3"]):
        out = tmp_path / src[0].strip("-")
        assert main(["evaluate", *src, "--algos", "atvfg", "--out", str(out), "--quiet", "--no-rrd", "--jobs", "1"]) == 0
        outs.append(json.loads((out / "report.json").read_text()))
    assert outs[0]["seeds"] == [3]
    assert outs[0]["algorithms"]["atvfg"]["pos_rmse_m"] == outs[1]["algorithms"]["atvfg"]["pos_rmse_m"]
    assert outs[0]["algorithms"]["atvfg"]["detection"] == outs[1]["algorithms"]["atvfg"]["detection"]
    assert outs[0]["algorithms"]["atvfg"]["nees_in_band_share"] == outs[1]["algorithms"]["atvfg"]["nees_in_band_share"]


def test_config_seeds_report_and_tuning(capsys):
    sc = load_config(ROOT / "configs" / "paper.toml")
    assert config_seeds("report", sc) == list(range(1, 11))
    assert config_seeds("tuning", sc) == list(range(1001, 1011))
    assert "are tuning seeds" in capsys.readouterr().err
    assert config_seeds("2-3", sc) == [2, 3] and "tuning seeds" not in capsys.readouterr().err
    config_seeds("1000-1001", sc)
    assert "[1001] are tuning seeds" in capsys.readouterr().err


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
