"""`import-miluv` on plausible variations of a MILUV experiment (no recording needed, ~2 s).

Each test copies the synthetic experiment of tests/test_miluv_synthetic.py and changes one thing a
real MILUV experiment other than the shipped one may have: the devkit's folder layout (config/ beside
data/), fewer robots than experiments.csv lists, mocap dropouts written as zeros, robots covering
different times, missing optional files, empty rows, a byte-order mark. The contract: a usable
variant imports (and says what it dropped), an unusable one fails with a DatasetError naming the
file and what to do, and a config that does not fit the recording is refused rather than imported
with wrong anchors.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from swarmnav.errors import DatasetError
from test_miluv_synthetic import _dist, _pose, _write_csv, build_folder  # noqa: E402  (the same synthetic experiment)

NAME = "synthetic_0"


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    return build_folder(tmp_path_factory.mktemp("base") / NAME)


@pytest.fixture
def src(base, tmp_path) -> Path:
    """A fresh copy of the synthetic experiment to edit."""
    return Path(shutil.copytree(base, tmp_path / "exp" / NAME))


def _convert(src, **kw):
    from services.importers.miluv import convert

    return convert(src, epoch_dt=0.1, estimation=None, **kw)


def _rows(p: Path) -> list[list[str]]:
    with open(p, newline="") as f:
        return list(csv.reader(f))


def _set_experiments(src: Path, header: list[str], rows: list[list]) -> None:
    _write_csv(src / "config" / "experiments.csv", header, rows)


def test_devkit_layout_config_beside_data(src, tmp_path):
    """The MILUV devkit keeps experiments in miluv/data/<exp>/ and the config in miluv/config/."""
    ds0, _ = _convert(src)
    root = tmp_path / "miluv"
    (root / "data").mkdir(parents=True)
    shutil.move(src / "config", root / "config")
    exp = Path(shutil.move(src, root / "data" / NAME))
    ds, _ = _convert(exp)
    assert ds.meta == ds0.meta  # same dataset, same provenance hash (config files named config/...)
    # or given explicitly, from anywhere
    moved = Path(shutil.move(root / "config", tmp_path / "elsewhere"))
    with pytest.raises(DatasetError, match=r"config/ folder not found .*--config-dir"):
        _convert(exp)
    assert _convert(exp, config_dir=moved)[0].meta == ds0.meta
    with pytest.raises(DatasetError, match="--config-dir .*no experiments.csv"):
        _convert(exp, config_dir=tmp_path)


def test_renamed_folder_needs_experiment_name(src, tmp_path):
    renamed = Path(shutil.move(src, src.parent / "my copy of it"))
    with pytest.raises(DatasetError, match=r"experiment 'my copy of it' not listed .*--experiment"):
        _convert(renamed)
    ds, summary = _convert(renamed, experiment=NAME)
    assert ds.meta.name == f"miluv/{NAME}" and summary["experiment"] == NAME


def test_fewer_robot_folders_than_experiments_csv(src):
    """A robot folder missing: the others are imported, the missing one and its tags' rows are said."""
    _set_experiments(src, ["experiment", "num_robots", "anchor_constellation"], [[NAME, 2, "0"]])
    shutil.rmtree(src / "ifo002")
    ds, summary = _convert(src)
    assert ds.meta.uav_ids() == [1]
    r = ds.table("ranges")
    assert r["b"].tolist() == [100]  # the ranges with tag 20 (ifo002) dropped, the anchor one kept
    assert summary["ranges"]["rows_with_robots_not_here"] == {"ifo002": 1}
    w = " | ".join(summary["warnings"])
    assert "lists 2 robot(s)" in w and "has 1 (ifo001)" in w and "tag of ifo002" in w and "dropped" in w
    assert summary["tdoa"]["dropped"]["robot_not_here"] == 0  # p1 (listener 10, anchors 0 -> 1) is kept
    assert summary["tdoa"]["kept"] == 1


def test_mocap_dropout_rows_are_gaps(src):
    """MILUV writes a lost mocap body as an all-zero pose (the devkit drops those rows)."""
    p = src / "ifo001" / "mocap.csv"
    rows = _rows(p)
    for r in rows[50:60]:
        r[1:] = ["0.0"] * 7
    _write_csv(p, rows[0], rows[1:])
    ds, summary = _convert(src)
    assert summary["mocap_dropout_rows"] == {"ifo001": 10}
    assert any("zero pose (mocap dropout)" in w for w in summary["warnings"])
    tr = ds.table("truth")
    s = tr["node"] == 1
    pos = np.column_stack([tr[c][s] for c in ("pe", "pn", "pu")])
    np.testing.assert_allclose(pos, [_pose(1, x)[0] for x in tr["t"][s]], atol=1e-9)  # linear motion: exact across the gap


def test_timestamps_not_in_seconds(src):
    for f in src.glob("ifo*/*.csv"):
        rows = _rows(f)
        for col in ("timestamp", "timestamp_n"):
            if col in rows[0]:
                i = rows[0].index(col)
                for r in rows[1:]:
                    r[i] = repr(int(float(r[i]) * 1e9))
        _write_csv(f, rows[0], rows[1:])
    with pytest.raises(DatasetError, match=r"ifo001/mocap.csv: median time step .* must be in seconds"):
        _convert(src)


def _shift(src: Path, robot: str, dt: float, t_min: float = -1e18) -> None:
    """Every file of ``robot``: rows before ``t_min`` dropped, the rest's times moved by ``dt``."""
    for f in (src / robot).glob("*.csv"):
        rows = _rows(f)
        ti = [rows[0].index(c) for c in ("timestamp", "timestamp_n") if c in rows[0]]
        keep = [r for r in rows[1:] if float(r[ti[0]]) >= t_min]
        for r in keep:
            for i in ti:
                r[i] = repr(float(r[i]) + dt)
        _write_csv(f, rows[0], keep)


def test_robots_on_different_clocks(src):
    _shift(src, "ifo002", 1000.0)
    with pytest.raises(DatasetError, match=r"do not overlap .*ifo001 0\.005-5\.995 s, ifo002 1000\.005-1005\.995 s"):
        _convert(src)


def test_robot_starting_later_is_said(src):
    _shift(src, "ifo002", 0.0, t_min=2.0)
    ds, summary = _convert(src)
    assert ds.meta.t_start == 2.01  # ifo002's first IMU sample 2.005 s, up to 10 ms
    assert any("robots cover different times" in w and "ifo002 2.005-5.995 s" in w for w in summary["warnings"])


def _anchor_ranges(src: Path) -> None:
    """Three ranges to each anchor with the recording's gt_range (the config check needs >= 3)."""
    p = src / "ifo001" / "uwb_range.csv"
    rows = _rows(p)
    for t in (4.0, 4.5, 5.0):
        for tag, anchor in ((10, 0), (11, 1)):
            d = _dist(tag, anchor, t)
            rows.append([t, f"({tag}, {anchor})", tag, anchor, d, d, 0.0, 0.1])
    _write_csv(p, rows[0], rows[1:])


def test_config_checked_against_gt_range(src):
    _anchor_ranges(src)
    _, summary = _convert(src)
    assert summary["ranges"]["config_check"]["anchor 0"] == {"median_abs_m": 0.0, "rows": 4}  # + r_nlos
    # the experiment pointed at another constellation whose anchor 0 is 1 m away: refused, not imported
    (src / "config" / "uwb" / "anchors.yaml").write_text(
        '"0":\n    "0": "[0.0, 0.0, 2.0]"\n    "1": "[4.0, 0.0, 2.0]"\n"2":\n    "0": "[1.0, 0.0, 2.0]"\n    "1": "[4.0, 0.0, 2.0]"\n')
    _set_experiments(src, ["experiment", "anchor_constellation"], [[NAME, "2"]])
    with pytest.raises(DatasetError, match=r"config does not match the recording.*anchor 0: median 0\.\d\d m over 4 ranges.*"
                                           r"anchor_constellation \('2'\)") as e:
        _convert(src)
    assert "anchor 1" not in str(e.value)


def test_unknown_uwb_id_names_the_config(src):
    p = src / "ifo001" / "uwb_range.csv"
    rows = _rows(p)
    rows[2][3] = "7"  # to_id of r_uav: no anchor 7, no tag 7
    _write_csv(p, rows[0], rows[1:])
    with pytest.raises(DatasetError, match=r"ifo001/uwb_range.csv: row 3: UWB id 7 is neither an anchor .*\[0, 1\].*"
                                           r"nor a tag of a robot \(\[10, 11, 20, 21\]"):
        _convert(src)


def test_missing_optional_files_empty_rows_and_bom(src):
    (src / "ifo002" / "uwb_range.csv").unlink()
    (src / "ifo002" / "uwb_passive.csv").unlink()
    p = src / "ifo001" / "uwb_range.csv"
    rows = _rows(p)
    rows.insert(2, ["nan"] * len(rows[0]))
    rows.insert(3, [""] * len(rows[0]))
    _write_csv(p, rows[0], rows[1:])
    m = src / "ifo001" / "mocap.csv"
    m.write_bytes(b"\xef\xbb\xbf" + m.read_bytes())  # a byte-order mark before 'timestamp'
    ds, summary = _convert(src)
    assert ds.table("ranges")["t"].tolist() == [1.0, 2.0]  # r_uav still in ifo001's file; r_nostd was only in ifo002's
    w = " | ".join(summary["warnings"])
    assert "ifo002/uwb_range.csv missing" in w and "ifo002/uwb_passive.csv missing" in w
    assert "1 uwb_range.csv rows without a timestamp or UWB ids" in w  # the blank line is no row at all
    assert "ifo002/height.csv missing" in w


def test_required_file_missing_says_what_to_do(src):
    (src / "ifo002" / "mocap.csv").rename(src / "ifo002" / "mocap.csv.gz")
    with pytest.raises(DatasetError, match=r"ifo002/mocap.csv: missing file \(found mocap.csv.gz: decompress it.*"
                                           r"required for every robot \(ground truth.*remove the folder ifo002"):
        _convert(src)


def test_cli_warnings_on_stderr_and_errors_without_traceback(src, tmp_path, capsys):
    from services.cli import main

    shutil.rmtree(src / "ifo002")
    assert main(["import-miluv", str(src), "--out", str(tmp_path / "ds")]) == 0
    err = capsys.readouterr().err
    assert "swarmnav import-miluv: warning:" in err and "tag of ifo002" in err
    assert main(["import-miluv", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "error: " in err and "no robot folders" in err and "Traceback" not in err
