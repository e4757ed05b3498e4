"""`swarmnav calibrate`: offline training of the lower detection threshold Δl (paper §2.3.2 step 3)."""

from __future__ import annotations

import json
import time
from pathlib import Path

HELP = "train the lower detection threshold Δl on fault-free data (writes configs/delta_l.json)"

DESCRIPTION = """\
Simulate the given (fault-free) scenario, run the distributed `fg` estimator with 50 message
iterations per epoch over a window of epochs, and write Δl = the 99th percentile of the converged
range residuals |d_ij - |p_i - p_j|| as JSON (key "delta_l_m"). `atvfg` reads it through
`estimation.delta_l_file`; without it Δl = estimation.delta_l_fallback_sigmas × UWB sigma.

example:
  swarmnav calibrate --config configs/paper_faultfree.toml --out configs/delta_l.json
"""


def add_arguments(p) -> None:
    p.add_argument("--config", required=True, metavar="FILE", help="fault-free scenario TOML (e.g. configs/paper_faultfree.toml)")
    p.add_argument("--out", required=True, metavar="FILE", help="JSON file to write (e.g. configs/delta_l.json)")
    p.add_argument("--seed", type=int, default=None, metavar="N", help="seed (default: the config's)")
    p.add_argument("--warmup-s", type=float, default=20.0, help="seconds skipped before collecting residuals")
    p.add_argument("--window-s", type=float, default=60.0, help="seconds of residuals collected")


def run(args) -> int:
    from swarmnav.calibration import train_delta_l
    from swarmnav.config import load_config, parse_config
    from swarmnav.errors import ConfigError
    from swarmnav.sim import simulate

    t0 = time.perf_counter()
    sc = load_config(args.config)
    seed = sc.scenario.seed if args.seed is None else args.seed
    d = sc.model_dump()
    end = min(sc.scenario.duration_s, args.warmup_s + args.window_s)
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
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"Δl = {out['delta_l_m']:.3f} m from {out['n_residuals']} residuals "
          f"({time.perf_counter() - t0:.1f} s) -> {args.out}")
    return 0
