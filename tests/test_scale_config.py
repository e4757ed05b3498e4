"""Scale family (issue 17): `--set KEY=VALUE` overrides, configs/scale.toml, formation generation up
to 1,000 UAVs, and the existing configs unchanged by it."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from swarmnav.config import apply_overrides, load_config, parse_override
from swarmnav.errors import ConfigError
from swarmnav.sim.simulate import S_FORMATION, _rng
from swarmnav.sim.trajectory import formation_offsets

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
SCALE = str(CONFIGS / "scale.toml")


def _old_formation(sc, rng):
    """The formation generator as it was before the scale family (Python loop over placed points)."""
    sw = sc.swarm
    lo = np.array([sw.box_e_m[0], sw.box_n_m[0], sw.box_u_m[0]])
    hi = np.array([sw.box_e_m[1], sw.box_n_m[1], sw.box_u_m[1]])
    pts = [np.asarray(sw.uav1_start_enu_m, float)]
    for _ in range(1, sw.n_uavs):
        for _ in range(20000):
            c = lo + (hi - lo) * rng.random(3)
            if min(np.linalg.norm(c - p) for p in pts) >= sw.min_separation_m:
                pts.append(c)
                break
    return np.array(pts)


@pytest.mark.parametrize("name", ["paper", "smoke", "gnss_denied", "dropout", "paper_faultfree",
                                  "paper_realistic_uwb"])
def test_existing_configs_draw_the_same_formation(name):
    sc = load_config(CONFIGS / f"{name}.toml")
    d = sc.to_dict()["swarm"]
    assert "masters_every" not in d and "density_per_km3" not in d  # so sha256 / meta.json unchanged
    for seed in (1, 7, 1001):
        a = _old_formation(sc, _rng(seed, S_FORMATION))
        b = formation_offsets(sc, _rng(seed, S_FORMATION))
        assert a.tobytes() == b.tobytes(), (name, seed)


def test_set_overrides_before_validation():
    sc = load_config(SCALE, ["swarm.n_uavs=100", "scenario.duration_s=20", "estimation.rounds=4",
                             "faults.interference.enabled=false", "scenario.name=big"])
    assert sc.swarm.n_uavs == 100 and sc.scenario.duration_s == 20.0 and sc.estimation.rounds == 4
    assert not sc.faults.interference.enabled and sc.scenario.name == "big"
    assert sc.swarm.masters == list(range(1, 101, 8))
    # later wins; lists are TOML values
    sc = load_config(CONFIGS / "paper.toml", ["swarm.masters=[1, 2]", "swarm.masters=[3]"])
    assert sc.swarm.masters == [3]
    # the raw dict is not modified in place
    raw = {"swarm": {"n_uavs": 5}}
    assert apply_overrides(raw, ["swarm.n_uavs=7"])["swarm"]["n_uavs"] == 7 and raw["swarm"]["n_uavs"] == 5
    assert parse_override("sensors.imu.slave.arw_dpsh=0.2") == (["sensors", "imu", "slave", "arw_dpsh"], 0.2)


@pytest.mark.parametrize("over, says", [
    ("swarm.n_uavz=100", "unknown field 'swarm.n_uavz'"),
    ("swarm.n_uavs=abc", "field 'swarm.n_uavs'"),
    ("swarm.n_uavs=5000", "less than or equal to 2000"),
    ("scenario.duration_s=-1", "field 'scenario.duration_s'"),
    ("sensors.imu.boss.arw_dpsh=1", "unknown key 'sensors.imu.boss'"),
    ("scenario.name.x=1", "not a table"),
    ("n_uavs", "expected KEY=VALUE"),
    ("swarm.density_per_km3=1e9", "too dense"),
])
def test_set_errors_name_the_field(over, says):
    with pytest.raises(ConfigError) as e:
        load_config(SCALE, [over])
    assert says in str(e.value) and len(str(e.value).splitlines()) == 1, str(e.value)


@pytest.mark.parametrize("cmd", ["simulate", "evaluate", "launch"])
def test_cli_bad_set_one_line_exit_2_nothing_written(tmp_path, cmd):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "services.cli", cmd, "--config", SCALE, "--set", "swarm.n_uavz=3",
                        "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "swarm.n_uavz" in r.stderr and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not out.exists()
    h = subprocess.run([sys.executable, "-m", "services.cli", cmd, "--help"], cwd=REPO, capture_output=True, text=True,
                       timeout=60)
    assert "--set KEY=VALUE" in h.stdout


def test_cli_simulate_with_set(tmp_path):
    from services import cli
    from swarmnav.dataset import Dataset

    assert cli.main(["simulate", "--config", SCALE, "--set", "swarm.n_uavs=12", "--set", "scenario.duration_s=3",
                     "--out", str(tmp_path / "d")]) == 0
    m = Dataset.read(tmp_path / "d").meta
    assert len(m.uav_ids()) == 12 and m.n_epochs() == 3
    assert [n.id for n in m.nodes if n.role == "master"] == [1, 9]
    assert m.config["swarm"]["n_uavs"] == 12


def test_formation_1000_valid_and_fast():
    sc = load_config(SCALE, ["swarm.n_uavs=1000"])
    t0 = time.perf_counter()
    off = formation_offsets(sc, _rng(1, S_FORMATION))
    dt = time.perf_counter() - t0
    assert dt < 5.0, f"formation of 1,000 UAVs took {dt:.1f} s"
    assert off.shape == (1000, 3) and np.array_equal(off[0], sc.swarm.uav1_start_enu_m)
    lo, hi = sc.swarm.formation_box()
    assert np.all(off[1:] >= lo) and np.all(off[1:] <= hi)
    # fixed density: volume = n / density, the altitude band kept
    assert np.prod(hi - lo) == pytest.approx(1000 / 400.0 * 1e9, rel=1e-9)
    assert (lo[2], hi[2]) == (100.0, 200.0)
    d = np.sqrt(((off[:, None, :] - off[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    assert d.min() >= sc.swarm.min_separation_m
    # bounded neighbourhoods: links within the UWB range do not grow with N
    nb = (d <= sc.sensors.uwb.max_range_m).sum(1)
    assert 10 <= nb.mean() <= 30 and nb.max() < 60, (nb.mean(), nb.max())
    assert len(sc.swarm.masters) == 125 and sc.swarm.masters[:3] == [1, 9, 17]


def test_scale_family_valid_for_small_and_large_n():
    for n in (2, 5, 18, 50, 300, 2000):
        sc = load_config(SCALE, [f"swarm.n_uavs={n}"])
        assert sc.swarm.masters[0] == 1 and all(1 <= m <= n for m in sc.swarm.masters)
