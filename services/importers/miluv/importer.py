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
from .ranges import check_config_against_gt_range, range_truth_summary, ranges_table, read_ranges
from .readers import experiment_row, find_config, robot_folders, warn
from .series import Span, read_series, time_span
from .tables import altitude_table, imu_table, level_at_start
from .truth import TagTruth, truth_table

DEFAULT_ESTIMATION = Path(__file__).resolve().parents[3] / "configs" / "miluv.toml"


def convert(src: str | Path, epoch_dt: float = 0.1, estimation: str | Path | None = DEFAULT_ESTIMATION,
            config_dir: str | Path | None = None, experiment: str | None = None) -> tuple[Dataset, dict]:
    """MILUV experiment folder -> (Dataset, import summary). ``estimation``: a TOML file whose
    ``[estimation]`` table (estimator tuning for this kind of data, configs/miluv.toml) is embedded
    in ``meta.config["estimation"]`` — as a simulated dataset carries its scenario's — so
    ``evaluate``/``launch``/``calibrate --dataset`` use it; None = the estimators' defaults.
    ``config_dir``: MILUV's config/ folder (default: found beside the experiment, readers.find_config);
    ``experiment``: its name in config/experiments.csv (default: the folder's name).
    Anything the user should know (a robot or a file missing, robots covering different times,
    rows dropped) is in ``summary["warnings"]``."""
    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: not a directory")
    if not (0.001 <= epoch_dt <= 5.0):
        raise DatasetError(f"--epoch-dt {epoch_dt}: must be in [0.001, 5] s")
    name = experiment or src.resolve().name
    summary: dict = {"experiment": name}
    robots = robot_folders(src)
    cfg = find_config(src, config_dir)
    exp = experiment_row(cfg, name)
    used_files: list[Path] = [cfg / "experiments.csv"]
    layout = read_layout(cfg, name, robots, exp.get("anchor_constellation", ""), used_files)
    _check_robots(src, exp, robots, layout, summary)
    series = read_series(src, robots, layout, used_files, summary)
    span = time_span(series, epoch_dt, src, summary)

    tables = {"truth": truth_table(series.mocap, span, epoch_dt, summary),
              "imu": imu_table(series.imu, span.t_start, span.t_end, summary)}
    level = level_at_start(series.imu, span.t_start, summary)
    truth = TagTruth(series.mocap, layout)
    _check_optional_files(src, robots, summary)
    log = read_ranges(src, robots, layout.tag_owner, used_files, layout.absent_tags)
    tables["ranges"], gt_range, sigma_nominal = ranges_table(log, layout.tag_owner, span, summary)
    range_truth_summary(tables["ranges"], gt_range, truth, span, epoch_dt, summary)
    check_config_against_gt_range(tables["ranges"], gt_range, truth, cfg, exp, summary)
    plog = read_passive(src, robots, layout.tag_owner, span, sigma_nominal, used_files, layout.absent_tags)
    if plog is not None:
        tables["tdoa"] = tdoa_table(plog, layout.tag_owner, truth, summary)
    for what, n in (("uwb_range.csv rows", log.n_bad_ids), ("uwb_passive.csv rows", plog.dropped["no_ids"] if plog else 0)):
        if n:
            warn(summary, f"{n} {what} without a timestamp or UWB ids (empty/NaN) dropped")
    n_pass = plog.dropped["robot_not_here"] if plog else 0
    if log.absent or n_pass:
        gone = sorted(set(layout.absent_tags.values()))
        warn(summary, f"{sum(log.absent.values())} range rows and {n_pass} passive rows involve a tag of "
                      f"{', '.join(gone)} (config/uwb/tags.yaml), which has no folder in {src}: dropped")
    alt = altitude_table(series.height, span.t_start, span.t_end, summary)
    if alt is not None:
        tables["altitude"] = alt

    est_table = load_estimation(estimation) if estimation is not None else None
    meta = _meta(src, name, cfg, exp, layout, span, epoch_dt, sigma_nominal, level, est_table, used_files)
    summary["truth_rows"] = int(len(tables["truth"]["t"]))
    return Dataset(meta, tables), summary


def _check_robots(src: Path, exp: dict[str, str], robots: list[tuple[str, int]], layout: Layout, summary: dict) -> None:
    """The robot folders against the experiment's ``num_robots``: a missing robot is said, and its
    tags' rows are dropped (counted in the ranges/tdoa summaries), not silently."""
    here = [n for n, _ in robots]
    try:
        n_exp = int(exp.get("num_robots", ""))
    except ValueError:
        n_exp = None
    if n_exp is not None and n_exp != len(here):
        warn(summary, f"config/experiments.csv lists {n_exp} robot(s) for {summary['experiment']}, {src} has "
                      f"{len(here)} ({', '.join(here)}): importing those")
    summary["robots"] = here


def _check_optional_files(src: Path, robots: list[tuple[str, int]], summary: dict) -> None:
    """uwb_range.csv / uwb_passive.csv missing for some robot: say what is lost."""
    for f, lost in (("uwb_range.csv", "its anchor ranges (inter-UAV ranges are also in the other robot's file)"),
                    ("uwb_passive.csv", "the passive-listening rows it logged")):
        missing = [n for n, _ in robots if not (src / n / f).is_file()]
        if len(missing) == len(robots):
            warn(summary, f"no robot has {f}: " + ("no UWB ranges at all, the UAVs navigate on their IMU (and height) alone"
                                                  if f == "uwb_range.csv" else "no passive-listening range differences"))
        elif missing:
            warn(summary, f"{', '.join(m + '/' + f for m in missing)} missing: {lost} not imported")


def _provenance(src: Path, cfg: Path, used_files: list[Path], est_table: dict | None) -> str:
    """sha256 over every file read (name relative to the experiment folder, config files as
    ``config/...``, and bytes) and the embedded estimator tuning."""
    h = hashlib.sha256()
    for f in sorted(set(used_files)):
        rel = f.relative_to(src) if f.is_relative_to(src) else Path("config") / f.relative_to(cfg)
        h.update(str(rel).encode() + b"\0")
        h.update(f.read_bytes())
    if est_table is not None:  # the embedded tuning is part of the dataset's provenance
        h.update(json.dumps(est_table, sort_keys=True).encode())
    return h.hexdigest()


def _meta(src: Path, name: str, cfg: Path, exp: dict[str, str], layout: Layout, span: Span, epoch_dt: float,
          sigma_nominal: float, level: bool, est_table: dict | None, used_files: list[Path]) -> DatasetMeta:
    return DatasetMeta(
        name=f"miluv/{name}",
        source="recorded",
        seed=None,
        config={"importer": "swarmnav import-miluv", "experiment": dict(sorted(exp.items())), "imu_source": "imu_px4.csv",
                "frame": "Vicon world (z up): x->E, y->N, z->U; no geodetic origin",
                "anchor_node_id": f"{ANCHOR_NODE_OFFSET} + MILUV anchor id", "uav_node_id": "N for ifo00N",
                **({"estimation": est_table} if est_table is not None else {})},
        config_sha256=_provenance(src, cfg, used_files, est_table),
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
