"""`swarmnav calibrate`: offline training of the lower detection threshold Δl (paper §2.3.2 step 3)."""

from __future__ import annotations

import json
import time
from pathlib import Path

HELP = "train Δl on fault-free simulated data, or cross-validate settings on a recording (no truth)"

DESCRIPTION = """\
--config: simulate the given (fault-free) scenario, run the distributed `fg` estimator with 50
message iterations per epoch over a window of epochs, and write Δl = the 99th percentile of the
converged range residuals |d_ij - |p_i - p_j|| as JSON (key "delta_l_m"). `atvfg` reads it through
`estimation.delta_l_file`; without it Δl = estimation.delta_l_fallback_sigmas × UWB sigma.

--dataset: truth-free K-fold cross-validation of one estimator setting on a recording with fixed
anchors: every K-th anchor range is held out (with the passive-listening rows of the same
transactions), `fg` (or --algo atvfg) runs on the rest with each candidate value (--grid
KEY=V1,V2,..., an [estimation.graph] tuning key: docs/settings.md), and the held-out ranges are
predicted from the estimates.
Prints RMS and median prediction error per candidate (lower = the better model of the data), the
held-out ranges' NIS (error² over the range σ² plus the estimate's position variance along the line
of sight; a truth-free counterpart of NEES: mean 1 and median 0.455 when consistent, larger when
overconfident; the mean also grows with NLOS ranges among the held-out ones), and
writes them as JSON with --out. This is how drag_sigma_scale and the settings of
configs/miluv.toml were chosen for sparse real data (docs/miluv.md, "Fifth" to "Seventh pass").

examples:
  swarmnav calibrate --config configs/paper_faultfree.toml --out configs/delta_l.json
  swarmnav calibrate --dataset runs/miluv --grid drag_sigma_scale=1,1.5,2,3
"""


def add_arguments(p) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="FILE", help="fault-free scenario TOML (e.g. configs/paper_faultfree.toml): train Δl")
    src.add_argument("--dataset", metavar="DIR", help="recorded dataset with anchors: cross-validate the --grid setting")
    p.add_argument("--out", metavar="FILE", help="JSON file to write (required with --config, e.g. configs/delta_l.json)")
    p.add_argument("--grid", default="drag_sigma_scale=1,1.5,2,3", metavar="KEY=V1,V2",
                   help="--dataset: the setting and its candidate values (default drag_sigma_scale=1,1.5,2,3)")
    p.add_argument("--folds", type=int, default=4, help="--dataset: number of folds (default 4)")
    p.add_argument("--algo", choices=("fg", "atvfg"), default="fg",
                   help="--dataset: the estimator run on each fold (default fg; atvfg for its own settings)")
    p.add_argument("--seed", type=int, default=None, metavar="N", help="seed (default: the config's)")
    p.add_argument("--warmup-s", type=float, default=20.0, help="seconds skipped before collecting residuals")
    p.add_argument("--window-s", type=float, default=60.0, help="seconds of residuals collected")


def run(args) -> int:
    from swarmnav.calibration import train_delta_l
    from swarmnav.config import load_config, parse_config
    from swarmnav.errors import ConfigError
    from swarmnav.sim import simulate

    import math

    if not (math.isfinite(args.warmup_s) and args.warmup_s >= 0):
        raise ConfigError(f"--warmup-s {args.warmup_s:g}: seconds skipped before collecting residuals, a number >= 0 (default 20)")
    if not (math.isfinite(args.window_s) and args.window_s > 0):
        raise ConfigError(f"--window-s {args.window_s:g}: seconds of residuals collected, a number > 0 (default 60)")
    if args.dataset:
        return _cross_validate(args)
    if not args.out:
        raise ConfigError("--config needs --out FILE (where to write Δl, e.g. configs/delta_l.json)")
    from ._checks import check_out_dir, make_out_dir

    if Path(args.out).is_dir():
        raise ConfigError(f"--out {args.out}: is a directory; give the JSON file to write, e.g. configs/delta_l.json")
    check_out_dir(Path(args.out).parent)
    t0 = time.perf_counter()
    sc = load_config(args.config)
    seed = sc.scenario.seed if args.seed is None else args.seed
    d = sc.model_dump()
    dt = sc.scenario.epoch_dt_s  # a whole number of epochs (--warmup-s 20.5 --window-s 10 was refused as 30.5 s)
    end = min(sc.scenario.duration_s, math.ceil((args.warmup_s + args.window_s) / dt - 1e-9) * dt)
    d["scenario"]["duration_s"] = end  # simulate only what is used
    sc_short = parse_config(d, args.config)
    r = sc_short.faults
    if r.interference.enabled or r.module_failure or r.stuck or r.drift:
        print("swarmnav calibrate: warning: the scenario has UWB faults; Δl should be trained on fault-free data")
    ds = simulate(sc_short, seed)
    st = sc.estimation.model_dump()
    st["delta_l_m"] = None
    out = train_delta_l(ds, seed, st, args.warmup_s, args.window_s)
    if out.get("delta_l_m") is None:
        raise ConfigError("no ranges in the training window: cannot train Δl")
    out["config"] = Path(args.config).name
    make_out_dir(Path(args.out).parent)
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"Δl = {out['delta_l_m']:.3f} m from {out['n_residuals']} residuals "
          f"({time.perf_counter() - t0:.1f} s) -> {args.out}")
    return 0


def _cross_validate(args) -> int:
    from swarmnav.calibration import heldout_anchor_cv
    from swarmnav.dataset import Dataset
    from swarmnav.errors import ConfigError
    from services.settings import settings_for_dataset

    t0 = time.perf_counter()
    key, _, vals = args.grid.partition("=")
    key = key.strip()
    try:
        values = [float(x) for x in vals.split(",") if x.strip()]
    except ValueError:
        values = []
    if not key or not values or any(not (x >= 0 and x < float("inf")) for x in values):
        raise ConfigError(f"--grid {args.grid!r}: expected KEY=V1,V2,... with numbers >= 0, "
                          "e.g. drag_sigma_scale=1,1.5,2")
    if args.folds < 2:
        raise ConfigError(f"--folds {args.folds}: at least 2")
    ds = Dataset.read(args.dataset)
    if not ds.meta.anchors():
        raise ConfigError(f"{args.dataset}: no anchors — the cross-validation predicts held-out anchor ranges")
    seed = ds.meta.seed or 0
    n = len(values) * args.folds

    def progress(i, total):
        print(f"\r  run {i}/{total} ({time.perf_counter() - t0:.0f} s)", end="", flush=True)

    try:
        res = heldout_anchor_cv(ds, seed, settings_for_dataset(ds.meta), [{key: x} for x in values],
                                args.folds, algo=args.algo, progress=progress)
    except ValueError as e:
        raise ConfigError(f"{args.dataset}: {e}") from None
    print()
    f = lambda x, spec: format(x, spec) if x is not None else "—"  # noqa: E731
    print(f"{key:>16}  {'held-out RMS [m]':>16}  {'median |e| [m]':>14}  {'NIS mean (1)':>12}  {'NIS median (0.455)':>18}"
          f"  {'n':>5}")
    for r in res:
        print(f"{r['settings'][key]:>16g}  {f(r['rms_m'], '>16.3f')}  {f(r['median_abs_m'], '>14.3f')}"
              f"  {f(r['nis_mean'], '>12.2f')}  {f(r['nis_median'], '>18.3f')}  {r['n']:>5d}")
    if len({r["rms_m"] for r in res}) == 1 and len(res) > 1:
        print(f"swarmnav calibrate: warning: every {key} value gave the same result — is {key!r} a graph "
              "estimator settings key (docs/estimators.md)?")
    best = min(res, key=lambda r: r["rms_m"] if r["rms_m"] is not None else float("inf"))
    print(f"lowest held-out RMS: {key} = {best['settings'][key]:g} ({n} {args.algo} runs, {time.perf_counter() - t0:.0f} s)")
    if args.out:
        out = {"schema": "swarmnav.cv/1", "dataset": ds.meta.name, "algo": args.algo, "folds": args.folds, "seed": seed,
               "score": "held-out anchor-range prediction error (truth-free)", "candidates": res,
               "best": best["settings"]}
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
        print(f"-> {args.out}")
    return 0
