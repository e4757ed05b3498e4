"""The realistic UWB error model (``[faults.uwb] model = "realistic"``, docs/uwb-errors.md): opt-in
(configs without the table simulate exactly as before), deterministic per seed, its statistics
(Student-t core of robust spread σ, NLOS share / bias / episode length) and its labels (NLOS
ranges faulty, the heavy-tailed core clean)."""

from pathlib import Path

import numpy as np
import pytest

from swarmnav.config import load_config, parse_config
from swarmnav.dataset import FaultKind
from swarmnav.errors import ConfigError
from swarmnav.evaluation import link_labels
from swarmnav.sim import simulate
from swarmnav.sim import sensors

REPO = Path(__file__).resolve().parents[1]


def _cfg(uwb: dict | None, n_uavs=8, duration=400.0, link_bias=0.0, **faults):
    """smoke with more UAVs and time, no module faults, interference off; ``uwb`` = [faults.uwb]."""
    d = load_config(REPO / "configs/smoke.toml").to_dict()
    d["scenario"]["duration_s"] = duration
    d["swarm"]["n_uavs"] = n_uavs
    d["trajectory"]["manoeuvres"] = [{"kind": "straight", "duration_s": duration}]
    d["sensors"]["uwb"]["link_bias_sigma_m"] = link_bias
    d["sensors"]["uwb"]["packet_loss"] = 0.0
    d["faults"] = {"interference": {"enabled": False}, **faults}
    if uwb is not None:
        d["faults"]["uwb"] = uwb
    return parse_config(d, "test")


def _errors(ds):
    """range − true distance of every range row."""
    tr, r = ds.tables["truth"], ds.tables["ranges"]
    U = len(ds.meta.uav_ids())
    K1 = len(np.unique(tr["t"]))
    P = np.stack([tr["pe"], tr["pn"], tr["pu"]], 1).reshape(K1, U, 3)
    k = np.rint((r["t"] - ds.meta.t_start) / ds.meta.epoch_dt_s).astype(int)
    return r["range"] - np.linalg.norm(P[k, r["a"] - 1] - P[k, r["b"] - 1], axis=1)


@pytest.fixture(scope="module")
def real():
    return simulate(_cfg({"model": "realistic"}), 3)


def test_without_the_table_nothing_changes():
    sc = load_config(REPO / "configs/paper.toml")
    assert "uwb" not in sc.to_dict()["faults"] and sc.faults.uwb is None
    # an explicit gaussian model draws exactly what no table draws (the dict differs, the data not)
    a = simulate(_cfg(None, duration=60.0), 2)
    b = simulate(_cfg({"model": "gaussian"}, duration=60.0), 2)
    for name in ("ranges", "truth", "imu", "gnss", "rel"):
        for c, v in a.tables[name].items():
            assert np.array_equal(v, b.tables[name][c]), (name, c)


def test_realistic_is_byte_deterministic(tmp_path):
    sc = _cfg({"model": "realistic"}, duration=60.0)
    simulate(sc, 5).write(tmp_path / "a")
    simulate(sc, 5).write(tmp_path / "b")
    simulate(sc, 6).write(tmp_path / "c")
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)
    assert (tmp_path / "a" / "ranges.parquet").read_bytes() != (tmp_path / "c" / "ranges.parquet").read_bytes()


def test_core_is_student_t_of_robust_spread_sigma_and_clean(real):
    r = real.tables["ranges"]
    e = _errors(real)
    clean = r["fault_kind"] == FaultKind.NONE
    assert np.all(r["fault_err"][clean] == 0.0)
    x = e[clean]
    spread = 1.4826 * np.median(np.abs(x - np.median(x)))
    assert spread == pytest.approx(0.10, rel=0.05)  # sensors.uwb.sigma_m (link bias off here)
    assert abs(np.median(x)) < 0.005
    tail = np.mean(np.abs(x) > 3 * 0.10)  # t3 scaled to spread 0.1: P(|x| > 0.3 m) = 4.2 %; Gaussian 0.27 %
    assert 0.03 < tail < 0.055
    # std/spread of t3 is 1.53 (sample std of a t3 converges slowly: a wide band)
    assert 1.3 < x.std() / spread < 2.0
    assert sensors.student_t_q75(3.0) == pytest.approx(0.7648923284043444, abs=1e-12)


def test_nlos_share_bias_and_labels(real):
    r = real.tables["ranges"]
    nl = r["fault_kind"] == FaultKind.INTERFERENCE
    assert set(np.unique(r["fault_kind"])) <= {FaultKind.NONE, FaultKind.INTERFERENCE}
    assert 0.02 < nl.mean() < 0.04  # nlos_fraction 0.03
    b = r["fault_err"][nl]
    assert b.min() >= 0.5 and b.max() <= 1.9
    assert np.median(b) == pytest.approx(0.75, abs=0.06)
    e = _errors(real)
    # the error of an NLOS range = its bias + the core noise
    assert np.median(e[nl] - b) == pytest.approx(0.0, abs=0.02)
    lab = link_labels(real)
    faulty = lab["err"] > lab["thr"]
    assert np.array_equal(faulty, lab["kind"] == FaultKind.INTERFERENCE)  # every NLOS range, nothing else


def test_nlos_episodes_short_and_stationary():
    rng = np.random.default_rng(0)
    st, en = sensors.nlos_episodes(0.0, 200_000.0, 0.03, 0.5, rng)
    keep = (st < 200_000.0) & (st > 0.0)
    dur = (en - st)[keep]
    assert dur.mean() == pytest.approx(0.5, rel=0.03)
    assert np.mean(dur > 2.0) == pytest.approx(np.exp(-4), abs=0.005)  # mostly well under 2 s
    share = np.sum(np.clip(en, 0.0, 200_000.0) - np.clip(st, 0.0, 200_000.0)) / 200_000.0
    assert share == pytest.approx(0.03, rel=0.05)
    assert np.all(st[1:] >= en[:-1])  # disjoint, sorted


def test_truncated_exponential_median():
    lam = sensors.truncexp_scale(0.5, 1.9, 0.75)
    x = sensors.truncexp_draw(np.random.default_rng(1).random(200_000), 0.5, 1.9, lam)
    assert x.min() >= 0.5 and x.max() <= 1.9
    assert np.median(x) == pytest.approx(0.75, abs=0.005)


def test_other_faults_still_apply_on_top():
    sc = _cfg({"model": "realistic"}, n_uavs=5, duration=60.0,
              module_failure=[{"uav": 5, "start_s": 15.0, "end_s": 25.0}])
    r = simulate(sc, 1).tables["ranges"]
    w = (r["t"] >= 15) & (r["t"] <= 25) & ((r["a"] == 5) | (r["b"] == 5))
    assert np.all(r["fault_kind"][w] == FaultKind.FAILURE) and np.all(r["fault_err"][w] >= 20)


def test_config_checks():
    with pytest.raises(ConfigError, match="interference"):
        d = load_config(REPO / "configs/paper.toml").to_dict()
        d["faults"]["uwb"] = {"model": "realistic"}  # paper's interference still on
        parse_config(d, "test")
    with pytest.raises(ConfigError, match="nlos_bias_median_m"):
        _cfg({"model": "realistic", "nlos_bias_median_m": 1.5})
    with pytest.raises(ConfigError, match="core_dof"):
        _cfg({"model": "realistic", "core_dof": 2.0})


def test_shipped_realistic_config():
    sc = load_config(REPO / "configs/paper_realistic_uwb.toml")
    base = load_config(REPO / "configs/paper.toml")
    assert sc.faults.uwb.model == "realistic" and not sc.faults.interference.enabled
    # everything else is paper: same swarm, sensors, module faults
    assert sc.swarm == base.swarm and sc.sensors == base.sensors and sc.trajectory == base.trajectory
    assert (sc.faults.module_failure, sc.faults.stuck, sc.faults.drift) == \
        (base.faults.module_failure, base.faults.stuck, base.faults.drift)
    assert sc.evaluation.role_of([1]) == "report"
    ff = load_config(REPO / "configs/paper_realistic_uwb_faultfree.toml")
    assert ff.scenario.seed in ff.evaluation.seeds("tuning") and ff.faults.uwb.nlos_fraction == 0
