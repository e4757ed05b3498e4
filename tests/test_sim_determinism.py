"""Same seed -> byte-identical dataset directory; different seed -> different; the CLI contract."""

import hashlib
from pathlib import Path

import numpy as np
import pytest

from services import cli
from swarmnav.config import load_config
from swarmnav.dataset import Dataset
from swarmnav.sim import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SMOKE = str(CONFIGS / "smoke.toml")


def _digests(d: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir())}


def test_same_seed_same_bytes_different_seed_differs(tmp_path):
    sc = load_config(SMOKE)
    simulate(sc, 4).write(tmp_path / "a")
    simulate(sc, 4).write(tmp_path / "b")
    simulate(sc, 5).write(tmp_path / "c")
    a, b, c = (_digests(tmp_path / x) for x in "abc")
    assert set(a) == {"meta.json", "truth.parquet", "imu.parquet", "gnss.parquet", "ranges.parquet", "rel.parquet"}
    assert a == b
    assert all(a[k] != c[k] for k in a), "every file must change with the seed"


def test_only_uav1_start_is_fixed():
    sc = load_config(SMOKE)
    t1, t2 = simulate(sc, 1).tables["truth"], simulate(sc, 2).tables["truth"]
    first = t1["t"] == 0
    p1 = np.stack([t1["pe"], t1["pn"], t1["pu"]], -1)[first]
    p2 = np.stack([t2["pe"], t2["pn"], t2["pu"]], -1)[first]
    assert np.array_equal(p1[0], p2[0])
    assert not np.any(np.all(p1[1:] == p2[1:], axis=-1))


def test_roundtrip_and_meta(tmp_path):
    sc = load_config(SMOKE)
    ds = simulate(sc)
    ds.write(tmp_path / "d")
    back = Dataset.read(tmp_path / "d")
    assert back.meta == ds.meta
    for name, tab in ds.tables.items():
        for col, v in tab.items():
            assert np.array_equal(back.tables[name][col], v), (name, col)
    m = back.meta
    assert m.source == "simulated" and m.seed == sc.scenario.seed and m.config_sha256 == sc.sha256()
    assert m.config == sc.to_dict() and m.init == sc.init.model_dump(mode="json")
    assert m.n_epochs() == 60 and m.t_start == 0.0
    g = m.earth
    assert g.earth_rate_radps[0] == 0.0 and 9.79 < g.gravity_mps2 < 9.80
    text = (tmp_path / "d" / "meta.json").read_text()
    assert str(tmp_path) not in text and "/work" not in text
    for name, tab in ds.tables.items():  # sorted by time
        assert np.all(np.diff(tab["t"]) >= 0), name


def test_cli_simulate(tmp_path, capsys):
    assert cli.main(["simulate", "--config", SMOKE, "--seed", "3", "--out", str(tmp_path / "x")]) == 0
    out = capsys.readouterr().out
    assert "5 UAVs" in out and "60 epochs" in out and "faulty link-epochs" in out
    assert cli.main(["simulate", "--config", SMOKE, "--seed", "3", "--out", str(tmp_path / "y")]) == 0
    assert _digests(tmp_path / "x") == _digests(tmp_path / "y")
    assert Dataset.read(tmp_path / "x").meta.seed == 3


def test_cli_default_seed_is_config_seed(tmp_path):
    assert cli.main(["simulate", "--config", SMOKE, "--out", str(tmp_path / "x")]) == 0
    assert Dataset.read(tmp_path / "x").meta.seed == load_config(SMOKE).scenario.seed


def test_cli_bad_config_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(f'base = "{SMOKE}"\n[sensors.uwb]\nmax_range_m = "far"\n')
    assert cli.main(["simulate", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "sensors.uwb.max_range_m" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    assert cli.main(["simulate", "--config", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "not found" in capsys.readouterr().err
    assert cli.main(["simulate", "--config", SMOKE, "--seed", "-1", "--out", str(tmp_path / "o")]) == 2


def test_cli_help_lists_options(capsys):
    with pytest.raises(SystemExit):
        cli.main(["simulate", "--help"])
    out = capsys.readouterr().out
    for s in ("--config", "--seed", "--out", "byte-identical"):
        assert s in out


def test_write_over_a_dataset_removes_tables_it_lacks(tmp_path):
    """Writing into an existing dataset directory (a re-import) leaves no stale optional table."""
    import dataclasses

    ds = simulate(load_config("configs/smoke.toml"), 1)
    assert "gnss" in ds.tables
    ds.write(tmp_path / "d")
    assert (tmp_path / "d" / "gnss.parquet").exists()
    dataclasses.replace(ds, tables={k: v for k, v in ds.tables.items() if k != "gnss"}).write(tmp_path / "d")
    assert not (tmp_path / "d" / "gnss.parquet").exists() and "gnss" not in Dataset.read(tmp_path / "d").tables
