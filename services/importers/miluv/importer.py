"""``convert``: one MILUV experiment folder -> (Dataset, import summary), table by table."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from swarmnav.config import load_estimation
from swarmnav.dataset import Dataset, DatasetMeta, Earth
from swarmnav.errors import DatasetError

from .constants import ANCHOR_NODE_OFFSET, GRAVITY_MPS2, INIT, LEVEL_WINDOW_S
from .nodes import Layout, read_layout
from .passive import read_passive, tdoa_table
from .ranges import range_truth_summary, ranges_table, read_ranges
from .readers import experiment_row, robot_folders
from .series import Span, read_series, time_span
from .tables import altitude_table, imu_table, level_at_start
from .truth import TagTruth, truth_table

DEFAULT_ESTIMATION = Path(__file__).resolve().parents[3] / "configs" / "miluv.toml"


def convert(src: str | Path, epoch_dt: float = 0.1, estimation: str | Path | None = DEFAULT_ESTIMATION
            ) -> tuple[Dataset, dict]:
    """MILUV experiment folder -> (Dataset, import summary). ``estimation``: a TOML file whose
    ``[estimation]`` table (estimator tuning for this kind of data, configs/miluv.toml) is embedded
    in ``meta.config["estimation"]`` — as a simulated dataset carries its scenario's — so
    ``evaluate``/``launch``/``calibrate --dataset`` use it; None = the estimators' defaults."""
    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a directory")
    if not (0.001 <= epoch_dt <= 5.0):
        raise DatasetError(f"--epoch-dt {epoch_dt}: must be in [0.001, 5] s")
    summary: dict = {"experiment": src.name}
    robots = robot_folders(src)
    exp = experiment_row(src)
    used_files: list[Path] = [src / "config" / "experiments.csv"]
    layout = read_layout(src, robots, exp.get("anchor_constellation", "").strip(), used_files)
    series = read_series(src, robots, layout, used_files, summary)
    span = time_span(series, epoch_dt, src, summary)

    tables = {"truth": truth_table(series.mocap, span, epoch_dt, summary),
              "imu": imu_table(series.imu, span.t_start, span.t_end, summary)}
    level = level_at_start(series.imu, span.t_start, summary)
    truth = TagTruth(series.mocap, layout)
    log = read_ranges(src, robots, layout.tag_owner, used_files)
    tables["ranges"], gt_range, sigma_nominal = ranges_table(log, layout.tag_owner, span, summary)
    range_truth_summary(tables["ranges"], gt_range, truth, span, epoch_dt, summary)
    plog = read_passive(src, robots, layout.tag_owner, span, sigma_nominal, used_files)
    if plog is not None:
        tables["tdoa"] = tdoa_table(plog, layout.tag_owner, truth, summary)
    alt = altitude_table(series.height, span.t_start, span.t_end, summary)
    if alt is not None:
        tables["altitude"] = alt

    est_table = load_estimation(estimation) if estimation is not None else None
    meta = _meta(src, exp, layout, span, epoch_dt, sigma_nominal, level, est_table, used_files)
    summary["truth_rows"] = int(len(tables["truth"]["t"]))
    return Dataset(meta, tables), summary


def _provenance(src: Path, used_files: list[Path], est_table: dict | None) -> str:
    """sha256 over every file read (relative name and bytes) and the embedded estimator tuning."""
    h = hashlib.sha256()
    for f in sorted(set(used_files)):
        h.update(str(f.relative_to(src)).encode() + b"\0")
        h.update(f.read_bytes())
    if est_table is not None:  # the embedded tuning is part of the dataset's provenance
        h.update(json.dumps(est_table, sort_keys=True).encode())
    return h.hexdigest()


def _meta(src: Path, exp: dict[str, str], layout: Layout, span: Span, epoch_dt: float, sigma_nominal: float,
          level: bool, est_table: dict | None, used_files: list[Path]) -> DatasetMeta:
    return DatasetMeta(
        name=f"miluv/{src.name}",
        source="recorded",
        seed=None,
        config={"importer": "swarmnav import-miluv", "experiment": dict(sorted(exp.items())), "imu_source": "imu_px4.csv",
                "frame": "Vicon world (z up): x->E, y->N, z->U; no geodetic origin",
                "anchor_node_id": f"{ANCHOR_NODE_OFFSET} + MILUV anchor id", "uav_node_id": "N for ifo00N",
                **({"estimation": est_table} if est_table is not None else {})},
        config_sha256=_provenance(src, used_files, est_table),
        origin=None,
        t_start=span.t_start,
        duration_s=span.duration,
        epoch_dt_s=epoch_dt,
        nodes=layout.nodes,
        earth=Earth(gravity_mps2=GRAVITY_MPS2, earth_rate_radps=(0.0, 0.0, 0.0)),
        uwb_sigma_m=sigma_nominal,
        rel_sigma_rad=None,
        fault_threshold_m=3 * sigma_nominal,
        events=[],
        init=dict(INIT, **({"level_window_s": LEVEL_WINDOW_S} if level else {})),
    )
