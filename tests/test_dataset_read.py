"""A damaged dataset directory is one clear DatasetError naming the file, not a traceback (hold-out review)."""

import json
import shutil
from pathlib import Path

import pytest

from swarmnav.config import load_config
from swarmnav.dataset import Dataset
from swarmnav.errors import DatasetError
from swarmnav.sim import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("ds") / "good"
    simulate(load_config(CONFIGS / "smoke.toml", ["scenario.duration_s=3"]), 1).write(d)
    return d


def _meta(d: Path, **change) -> str:
    m = json.loads((d / "meta.json").read_text())
    m.update(change)
    return json.dumps(m)


@pytest.mark.parametrize("damage, says", [
    (lambda d: (d / "meta.json").write_text("{not json"), "cannot read the dataset's meta.json"),
    (lambda d: (d / "meta.json").write_bytes(b"\xff\xfe\x00"), "cannot read the dataset's meta.json"),
    (lambda d: (d / "meta.json").write_text("[1, 2]"), "unknown schema"),
    (lambda d: (d / "meta.json").write_text(_meta(d, duration_s=0)), "field 'duration_s'"),
    (lambda d: (d / "meta.json").write_text(_meta(d, epoch_dt_s=-1.0)), "field 'epoch_dt_s'"),
    (lambda d: (d / "imu.parquet").write_bytes((d / "imu.parquet").read_bytes()[:100]), "imu.parquet: cannot read the table"),
    (lambda d: (d / "gnss.parquet").write_text("not parquet"), "gnss.parquet: cannot read the table"),
])
def test_damaged_dataset_is_a_dataset_error(good, tmp_path, damage, says):
    d = tmp_path / "ds"
    shutil.copytree(good, d)
    Dataset.read(d)  # intact
    damage(d)
    with pytest.raises(DatasetError) as ei:
        Dataset.read(d)
    assert says in str(ei.value), str(ei.value)
