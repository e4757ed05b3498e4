"""`swarmnav import-miluv SRC_DIR --out DATASET_DIR`: convert a MILUV recording (docs/miluv.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

HELP = "convert a MILUV recording (3 quadrotors, UWB, IMU, mocap) into a swarmnav dataset"
DESCRIPTION = """Convert one MILUV experiment folder (ifo00N/*.csv + config/) into a swarmnav dataset directory.

MILUV's config/ folder (experiments.csv, uwb/, imu/, height/) is looked for in SRC_DIR/config, then
beside the experiment as the devkit lays it out (miluv/data/<experiment> and miluv/config:
SRC_DIR/../config, SRC_DIR/../../config), or given with --config-dir. The experiment's row of
experiments.csv is the folder's name (or --experiment). Warnings (a robot or a sensor file missing,
robots covering different times, rows dropped) are printed on stderr and kept in the summary.

UAV N = robot ifo00N; anchor k = static node 100+k at its surveyed position. Local frame = the
Vicon world frame (x->E, y->N, z->U), no geodetic origin, no GNSS. IMU = imu_px4.csv (body FLU,
every sample kept). Ranges = uwb_range.csv of all robots, deduplicated; sigma = the row's std;
fault label NLOS_REAL where |bias| > 3 std. Truth = mocap. See docs/miluv.md.

examples:
  swarmnav import-miluv ../shared/data/miluv/cirObstacles_3_random_0 --out runs/miluv-dataset
  swarmnav import-miluv SRC --out runs/miluv-dataset --estimation configs/miluv.toml   # estimator settings with it
  swarmnav import-miluv ~/miluv/data/default_3_random_0 --out runs/d3r0   # config found in ~/miluv/config
  swarmnav evaluate --dataset runs/miluv-dataset --algos atvfg,fg,central --seeds 0  # then evaluate it
"""


def add_arguments(p):
    p.add_argument("src", metavar="SRC_DIR", help="MILUV experiment folder, e.g. ../shared/data/miluv/cirObstacles_3_random_0")
    p.add_argument("--out", required=True, metavar="DATASET_DIR", help="output dataset directory (created)")
    p.add_argument("--epoch-dt", type=float, default=0.1, metavar="S",
                   help="epoch length in seconds (default 0.1; ranges keep their own timestamps inside the epoch)")
    p.add_argument("--config-dir", metavar="DIR", default=None,
                   help="MILUV's config/ folder (default: SRC_DIR/config, SRC_DIR/../config or SRC_DIR/../../config)")
    p.add_argument("--experiment", metavar="NAME", default=None,
                   help="the experiment's name in config/experiments.csv (default: SRC_DIR's folder name)")
    p.add_argument("--estimation", metavar="TOML", default=None,
                   help="estimator tuning embedded in the dataset (its [estimation] table; default "
                        "configs/miluv.toml; 'none' = the estimators' defaults)")


def run(args) -> int:
    from services.importers.miluv import DEFAULT_ESTIMATION, convert
    from swarmnav.errors import DatasetError

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out}: exists and is not a directory")
    est = DEFAULT_ESTIMATION if args.estimation is None else (None if args.estimation == "none" else args.estimation)
    ds, summary = convert(args.src, epoch_dt=args.epoch_dt, estimation=est, config_dir=args.config_dir,
                          experiment=args.experiment)
    ds.write(out)
    for w in summary.get("warnings", []):
        print(f"swarmnav import-miluv: warning: {w}", file=sys.stderr)
    r = summary["ranges"]
    print(f"imported {summary['experiment']}: {len(ds.meta.uav_ids())} UAVs, {len(ds.meta.anchors())} anchors, "
          f"{summary['n_epochs']} epochs of {summary['epoch_dt_s']} s from t={summary['t_start']} s; "
          f"{r['kept']} ranges ({r['inter_uav']} inter-UAV, {r['to_anchor']} to anchors, "
          f"{r['duplicates_removed']} duplicate rows removed, {r['nlos_real_rows']} NLOS_REAL) -> {out}")
    print(json.dumps(summary, indent=1, sort_keys=True, default=str))
    return 0
