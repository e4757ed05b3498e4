"""The sensor-sim's streamed IMU (imu_source.ImuStream) gives exactly the in-memory slices."""

from __future__ import annotations

import numpy as np
import pytest

from swarmnav.config import load_config
from swarmnav.dataset import Dataset, EpochSlicer
from swarmnav.imu_source import ImuInMemory, ImuStream
from swarmnav.sim.simulate import simulate


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    ds = simulate(load_config("configs/smoke.toml"), 1)
    out = tmp_path_factory.mktemp("ds")
    ds.write(out)
    return ds, out


def _small_groups(path, monkeypatch_rows: int):
    """Rewrite imu.parquet with tiny row groups, so a short run crosses many of them."""
    import pyarrow.parquet as pq

    tab = pq.read_table(path / "imu.parquet")
    pq.write_table(tab, path / "imu.parquet", row_group_size=monkeypatch_rows)


def test_stream_equals_in_memory_epoch_by_epoch_and_after_going_back(written):
    ds, path = written
    _small_groups(path, 997)  # groups that end mid-epoch, mid-UAV
    uavs = ds.meta.uav_ids()
    stream = ImuStream.open(path / "imu.parquet", uavs)
    assert isinstance(stream, ImuStream) and stream._pf.num_row_groups > 10
    mem = EpochSlicer(ds)
    st = EpochSlicer(Dataset.read(path, skip=("imu",)), imu=stream)
    K = ds.meta.n_epochs()
    for k in list(range(1, K + 1)) + [3, 4, K]:  # then back to an earlier epoch (a re-sent one)
        for u in uavs:
            a, b = mem.epoch(k, u), st.epoch(k, u)
            assert np.array_equal(a.imu_t, b.imu_t) and np.array_equal(a.gyro, b.gyro) and np.array_equal(a.accel, b.accel)
    assert len(stream._groups) <= 4  # only the groups around the epoch are held


def test_stream_head_and_unsorted_fallback(written, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    ds, path = written
    imu = ds.table("imu")
    t_end = float(imu["t"][0]) + 1.0
    head = ImuStream.open(path / "imu.parquet", ds.meta.uav_ids()).head(t_end)
    m = imu["t"] <= t_end
    assert all(np.array_equal(head[c], imu[c][m]) for c in imu)
    # a file not sorted by time is held whole (same slices)
    order = np.argsort(imu["node"], kind="stable")
    pq.write_table(pa.table({c: imu[c][order] for c in imu}), tmp_path / "imu.parquet")
    src = ImuStream.open(tmp_path / "imu.parquet", ds.meta.uav_ids())
    assert isinstance(src, ImuInMemory)
    ref = ImuInMemory(imu, ds.meta.uav_ids())
    t0, t1 = float(imu["t"][0]), float(imu["t"][0]) + 2.0
    for u in ds.meta.uav_ids():
        a, b = ref.samples(u, t0, t1), src.samples(u, t0, t1)
        assert all(np.array_equal(x, y) for x, y in zip(a, b))
