"""Scale benchmark: ``python -m deploy.bench [--quick] [--out DIR]`` (``make bench``).

How the cost of the swarm grows with its size, on configs/scale.toml (the paper's sensors and
flight, the start box grown with N at a fixed density, so a UAV's UWB neighbourhood stays ~17-19
links whatever N is; atvfg, seed 1). A benchmark, not a test: it measures and writes, it asserts nothing.

1. In-process (the in-memory bus of ``swarmnav evaluate``), one fresh process per size N = 18, 50,
   100, 300, 1000: simulate, then ``run_algorithm(atvfg)`` over every epoch. Per size: the estimator
   step per UAV-epoch (``step_ms``, p50/p99: the estimator's own time, every round), wall per epoch
   and per UAV-epoch (everything the in-process run does: estimator, bus, epoch slicing), the part
   of that wall outside the estimator (bus + slicing + protocol), the simulate wall, peak RSS of the
   process, the real-time factor of the estimation, the 1-min load average before and after.
2. Distributed (``swarmnav launch``, one process per UAV) for N = 18, 50 (100 if the time budget
   allows), each measured back to back with ``swarmnav evaluate`` of the same scenario (N, duration,
   seed): wall of both whole commands and their ratio, the launcher's real-time factor, bytes sent
   per UAV-epoch (the monitor's figure), peak RSS (and PSS) per process kind, sampled with psutil.
3. One cProfile of an in-process N = 300 run: the top functions by own time and by cumulative time.

Writes DIR/bench.md (tables; the load average beside every figure), DIR/bench.json (everything)
and DIR/cost_vs_n.png (default DIR = bench/<timestamp>/). Durations are short for large N (the
whole bench must stay within ~15 min on a 2-core machine); per-UAV-epoch figures do not depend on
the duration once the first epochs (start-up) are a small share. ``--quick``: small sizes only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import pstats
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "scale.toml"
ALGO = "atvfg"
SEED = 1

# (N, scenario seconds) — in-process sizes; short scenarios for large N (the per-UAV-epoch cost is
# what is compared; epoch 1 bootstraps, so at least ~10 epochs)
# (epoch 1 bootstraps and is left out of the per-epoch figures). The largest size's duration is chosen
# from the time left (2..5 epochs): at N = 1000 one epoch costs ~2 min of CPU today.
INPROC = [(18, 60.0), (50, 30.0), (100, 20.0), (300, 10.0), (1000, 5.0)]
DIST = [(18, 60.0), (50, 20.0), (100, 20.0)]  # distributed, each with its in-process twin
PROFILE = [(100, 2.0), (300, 2.0)]  # CPU-time cProfile; the last is summarised, the pair gives the growth
QUICK_INPROC = [(5, 10.0), (18, 10.0), (50, 6.0)]
QUICK_DIST = [(5, 10.0)]
QUICK_PROFILE = [(5, 3.0), (18, 3.0)]
MIN_EPOCHS_LARGEST = 2
BUDGET_S = 14 * 60.0  # the whole bench; a stage that would not fit is skipped (and said so)


def _env() -> dict:
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "shared")]))
    env.update({v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")})
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    return env


def load1() -> float:
    return round(os.getloadavg()[0], 2)


def calibration() -> dict:
    """How fast this machine is right now (this VM's speed varies ~2x over hours by itself, docs/scale.md
    "Session 13"): a 3 M-iteration Python loop (ms) and a 200 x 200 Cholesky (µs, best of 50), each the
    best of 3 — so that benches of different days compare."""
    import numpy as np

    loops, code = [], compile("s = 0\nfor i in range(3_000_000):\n    s += i\n", "<calibration>", "exec")
    for _ in range(3):  # at module level (globals in a dict), as the figures in docs/scale.md were taken
        t = time.perf_counter()
        exec(code, {})
        loops.append(time.perf_counter() - t)
    A = np.random.default_rng(0).normal(size=(200, 200))
    A = A @ A.T + 200 * np.eye(200)
    chol = []
    for _ in range(50):
        t = time.perf_counter()
        np.linalg.cholesky(A)
        chol.append(time.perf_counter() - t)
    return {"py_loop_ms": round(min(loops) * 1e3, 1), "chol200_us": round(min(chol) * 1e6, 1), "load1": load1()}


def _overrides(n: int, dur: float) -> list[str]:
    return [f"swarm.n_uavs={n}", f"scenario.duration_s={dur:g}"]


def _pct(x, q) -> float | None:
    import numpy as np

    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if len(x) else None


# -- 1. one in-process size, in its own process -----------------------------------------------------


def inproc_one(n: int, dur: float, profile: str | None = None) -> dict:
    """Simulate configs/scale.toml at N UAVs for ``dur`` s and run atvfg in-process; the figures."""
    import numpy as np
    import psutil

    from swarmnav.config import load_config
    from swarmnav.estimators import registry
    from swarmnav.evaluation import run_algorithm
    from swarmnav.sim import simulate

    from services.settings import estimator_settings

    me = psutil.Process()
    out: dict = {"n": n, "duration_s": dur, "load1_before": load1()}
    sc = load_config(CONFIG, _overrides(n, dur))
    t0 = time.perf_counter()
    ds = simulate(sc, SEED)
    out["simulate_s"] = time.perf_counter() - t0
    out["rss_after_simulate_mb"] = me.memory_info().rss / 2**20
    r = ds.tables["ranges"]
    K = ds.meta.n_epochs()
    out["epochs"] = K
    out["links_per_uav_epoch"] = 2.0 * len(r["t"]) / (K * n)  # each range serves both ends
    settings = estimator_settings(sc.estimation, base_dirs=(REPO, REPO / "configs"))
    stamps = []

    def prog(k, KK):
        stamps.append(time.perf_counter())

    registry.estimator_class(ALGO)  # import the estimator (gtsam) before any timing or profiling
    pr = None
    if profile:
        import cProfile

        pr = cProfile.Profile(time.process_time)  # CPU time: on a shared machine wall time mostly measures waiting
        pr.enable()
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_algorithm(ds, ALGO, SEED, settings, prog, time.perf_counter)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if pr is not None:
        pr.disable()
        pr.dump_stats(profile)
    ep = np.diff([t0] + stamps)  # wall per epoch
    steady = ep[1:] if len(ep) > 2 else ep  # epoch 1 bootstraps every node
    st = res.step_ms[1:] if res.step_ms.shape[0] > 2 else res.step_ms
    busy = np.nansum(st, axis=1) / 1e3  # estimator seconds per epoch
    out.update({
        "wall_s": wall,
        "cpu_s": cpu,
        "cpu_per_uav_epoch_ms": cpu / (K * n) * 1e3,  # CPU time: robust to a shared machine, all epochs
        "epoch_wall_ms_p50": float(np.median(steady) * 1e3),
        "wall_per_uav_epoch_ms": float(np.median(steady) / n * 1e3),
        "step_ms_p50": _pct(st, 50), "step_ms_p99": _pct(st, 99), "step_ms_mean": float(np.nanmean(st)),
        "outside_estimator_per_uav_epoch_ms": float(np.median(steady - busy) / n * 1e3),
        "rounds_mean": float(np.mean(res.rounds)),
        "realtime_factor": dur / wall,
        "first_epoch_wall_s": float(ep[0]),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "pos_err_rms_m": float(np.sqrt(np.nanmean(np.sum((res.pos - _truth(ds).pos) ** 2, axis=-1)))),
        "load1_after": load1(),
    })
    if profile is None and (os.cpu_count() or 1) > 1:
        out.update(_with_workers(ds, settings, res, dur))
    return out


def _with_workers(ds, settings: dict, res, dur: float, workers: int = 2) -> dict:
    """The same run with its UAVs spread over ``workers`` forked processes (`swarmnav evaluate
    --jobs 2` with a single run): its wall, real-time factor and whether its estimates are res's."""
    import numpy as np

    from services.runtime.node_workers import worker_groups
    from swarmnav.evaluation import run_algorithm

    t0 = time.perf_counter()
    r2 = run_algorithm(ds, ALGO, SEED, settings, None, time.perf_counter, worker_groups(workers))
    wall = time.perf_counter() - t0
    same = all(np.array_equal(getattr(res, f), getattr(r2, f), equal_nan=True) for f in ("pos", "pos_cov", "vel"))
    return {"workers": workers, "workers_wall_s": wall, "workers_realtime_factor": dur / wall,
            "workers_identical": bool(same), "workers_load1_after": load1()}


def _truth(ds):
    from swarmnav.evaluation import truth_at_epochs

    return truth_at_epochs(ds)


def run_inproc(n: int, dur: float, out_dir: Path, profile: str | None = None, timeout: float = 900.0) -> dict:
    """``inproc_one`` in a fresh interpreter (a clean heap: peak RSS is this size's own)."""
    j = out_dir / f"inproc-{n}{'-profile' if profile else ''}.json"
    cmd = [sys.executable, "-m", "deploy.bench", "--one", str(n), f"{dur:g}", "--json", str(j)]
    if profile:
        cmd += ["--profile", profile]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"n": n, "duration_s": dur, "error": f"not finished within {timeout:.0f} s", "load1_after": load1()}
    if p.returncode != 0 or not j.is_file():
        return {"n": n, "duration_s": dur, "error": (p.stderr.strip().splitlines() or ["?"])[-1][:200],
                "load1_after": load1()}
    r = json.loads(j.read_text())
    r["process_wall_s"] = time.perf_counter() - t0
    return r


# -- 2. distributed vs in-process, back to back ---------------------------------------------------


class Sampler(threading.Thread):
    """Peak RSS (every 0.5 s) and PSS (every ~4 s) per process of a process tree, by kind."""

    KINDS = (("uav_node", "uav"), ("sensor_sim", "sensor-sim"), ("monitor", "monitor"), ("router", "router"),
             ("services.cli", "launcher"))

    def __init__(self, pid: int):
        super().__init__(daemon=True)
        self.pid, self.stop, self.rss, self.pss, self.kind = pid, threading.Event(), {}, {}, {}
        self.max_load1 = load1()

    def _kind(self, p) -> str:
        try:
            cmd = " ".join(p.cmdline())
        except Exception:  # noqa: BLE001
            return "other"
        return next((k for s, k in self.KINDS if s in cmd), "other")

    def run(self):
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.Error:
            return
        i = 0
        while not self.stop.is_set():
            try:
                procs = [root] + root.children(recursive=True)
            except psutil.Error:
                break
            for p in procs:
                with contextlib.suppress(psutil.Error):
                    key = (p.pid, p.create_time())
                    if self.kind.get(key, "other") in ("other", "launcher"):  # a fork may not have exec'd yet
                        self.kind[key] = self._kind(p)
                    self.rss[key] = max(self.rss.get(key, 0), p.memory_info().rss)
                    if i % 8 == 0:
                        self.pss[key] = max(self.pss.get(key, 0), getattr(p.memory_full_info(), "pss", 0))
            self.max_load1 = max(self.max_load1, load1())
            i += 1
            self.stop.wait(0.5)

    def summary(self) -> dict:
        import numpy as np

        out = {}
        for kind in sorted(set(self.kind.values())):
            keys = [k for k, v in self.kind.items() if v == kind]
            rss = np.array([self.rss.get(k, 0) for k in keys]) / 2**20
            pss = np.array([self.pss.get(k, 0) for k in keys if k in self.pss]) / 2**20
            out[kind] = {"processes": len(keys), "peak_rss_mb_max": float(rss.max()), "peak_rss_mb_median": float(np.median(rss)),
                         "peak_pss_mb_max": float(pss.max()) if len(pss) else None,
                         "peak_pss_mb_median": float(np.median(pss)) if len(pss) else None}
        return out


def _run_cmd(cmd: list[str], timeout: float, log: Path, sample: bool) -> tuple[int | None, float, dict | None, float]:
    """Run ``cmd`` in its own session; (exit or None on timeout, wall s, memory summary, max load1)."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        p = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
    s = Sampler(p.pid) if sample else None
    if s:
        s.start()
    try:
        rc = p.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        rc = None
    wall = time.perf_counter() - t0
    if s:
        s.stop.set()
        s.join(timeout=5)
    return rc, wall, (s.summary() if s else None), (s.max_load1 if s else load1())


def run_dist(n: int, dur: float, out_dir: Path, timeout: float) -> dict:
    """``swarmnav evaluate`` then ``swarmnav launch`` of the same scenario, back to back (both within
    ``timeout`` seconds in all)."""
    deadline = time.perf_counter() + timeout
    cli = [sys.executable, "-m", "services.cli"]
    sets = sum((["--set", o] for o in _overrides(n, dur)), [])
    d: dict = {"n": n, "duration_s": dur}
    ev_dir, la_dir = out_dir / f"evaluate-{n}", out_dir / f"launch-{n}"
    d["load1_before_inproc"] = load1()
    rc, wall, _, _ = _run_cmd(cli + ["evaluate", "--config", str(CONFIG), *sets, "--algos", ALGO, "--seeds", str(SEED),
                                     "--jobs", "1", "--no-rrd", "--quiet", "--out", str(ev_dir)],
                              timeout, out_dir / f"evaluate-{n}.log", sample=False)
    d["inproc_exit"], d["inproc_command_wall_s"], d["load1_after_inproc"] = rc, wall, load1()
    with contextlib.suppress(Exception):
        rep = json.loads((ev_dir / "report.json").read_text())
        d["inproc_estimation_wall_s"] = rep["algorithms"][ALGO].get("wall_s")
        d["inproc_rmse_m"] = _rmse(rep["algorithms"][ALGO])
    d["load1_before_dist"] = load1()
    t_left = max(30.0, deadline - time.perf_counter())
    rc, wall, mem, lmax = _run_cmd(cli + ["launch", "--config", str(CONFIG), *sets, "--algo", ALGO, "--seed", str(SEED),
                                          "--out", str(la_dir), "--no-progress", "--timeout", f"{max(10.0, t_left - 15):.0f}"],
                                   t_left, out_dir / f"launch-{n}.log", sample=True)
    d.update({"dist_exit": rc, "dist_command_wall_s": wall, "memory": mem, "load1_max_during_dist": lmax,
              "load1_after_dist": load1()})
    d["dist_command_rtf"] = dur / wall
    with contextlib.suppress(Exception):
        rep = json.loads((la_dir / "report.json").read_text())
        di = rep.get("distributed") or {}
        d["dist_launcher_wall_s"] = di.get("wall_s")
        d["dist_launcher_rtf"] = di.get("realtime_factor")
        d["bytes_out_per_uav_epoch"] = di.get("bytes_out_per_uav_epoch")
        d["wait_ms"] = di.get("wait_ms")
        d["dist_complete"] = rep.get("complete")
        d["dist_rmse_m"] = _rmse((rep.get("algorithms") or {}).get(ALGO) or {})
        a = (rep.get("algorithms") or {}).get(ALGO) or {}
        d["dist_step_ms"] = a.get("step_ms")
    if d.get("inproc_command_wall_s"):
        d["wall_ratio_dist_over_inproc"] = d["dist_command_wall_s"] / d["inproc_command_wall_s"]
    # the run directories hold datasets and recordings (~MBs per UAV): keep only the reports
    import shutil

    for rd in (ev_dir, la_dir):
        for sub in ("dataset", "journal", "figures", "traj", "security", "recording"):  # no keys left behind
            shutil.rmtree(rd / sub, ignore_errors=True)
        for f in list(rd.glob("*.rrd")) + list(rd.glob("*.npz")):
            f.unlink(missing_ok=True)
    return d


def _rmse(a: dict):
    for k in ("pos_rmse_m", "rmse_3d_m", "position_rmse_m"):
        v = a.get(k)
        if isinstance(v, (int, float)):
            return v
        if isinstance(v, dict):
            for kk in ("all", "mean", "value"):
                if isinstance(v.get(kk), (int, float)):
                    return v[kk]
    return None


# -- 3. profile summary -------------------------------------------------------------------------


def profile_summary(prof: Path, top: int = 15) -> dict:
    st = pstats.Stats(str(prof))
    total = st.total_tt
    rows = []
    for (fn, line, name), (cc, nc, tt, ct, _callers) in st.stats.items():
        rows.append({"function": f"{_short(fn)}:{line}({name})", "calls": nc, "tottime_s": tt, "cumtime_s": ct})
    by_tt = sorted(rows, key=lambda r: -r["tottime_s"])[:top]
    by_ct = sorted([r for r in rows if "swarmnav" in r["function"] or "gtsam" in r["function"]],
                   key=lambda r: -r["cumtime_s"])[:top]
    return {"total_s": total, "by_tottime": by_tt, "by_cumtime": by_ct}


def profile_growth(small: Path, large: Path, n_small: int, n_large: int, top: int = 15) -> dict:
    """Own CPU time per function at two sizes: the ratio tells O(N) (≈ n_large/n_small: the swarm's
    cost grows with N, per UAV flat) from O(N²) (≈ (n_large/n_small)²: per UAV it grows with N)."""
    a, b = pstats.Stats(str(small)).stats, pstats.Stats(str(large)).stats
    rows = []
    for k, v in b.items():
        va = a.get(k)
        ta = va[2] if va else 0.0
        rows.append({"function": f"{_short(k[0])}:{k[1]}({k[2]})", "own_s_small": ta, "own_s_large": v[2],
                     "ratio": v[2] / ta if ta > 0 else None})
    rows.sort(key=lambda r: -r["own_s_large"])
    ta = sum(v[2] for v in a.values())
    tb = sum(v[2] for v in b.values())
    return {"n_small": n_small, "n_large": n_large, "total_small_s": ta, "total_large_s": tb, "rows": rows[:top]}


def _short(fn: str) -> str:
    for marker in ("/shared/", "/site-packages/", "/services/", "/deploy/"):
        if marker in fn:
            return fn.split(marker, 1)[1]
    return fn if len(fn) < 60 else "…" + fn[-57:]


# -- outputs ------------------------------------------------------------------------------------


def _f(x, fmt="{:.2f}", none="—"):
    return none if x is None else fmt.format(x)


def write_plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = sorted((r for r in res["inproc"] if "error" not in r), key=lambda r: r["n"])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    if ok:
        n = [r["n"] for r in ok]
        ax[0].plot(n, [r["wall_per_uav_epoch_ms"] for r in ok], "o-", label="wall per UAV-epoch (in-process)")
        ax[0].plot(n, [r["step_ms_p50"] for r in ok], "s-", label="atvfg step p50")
        ax[0].plot(n, [r["step_ms_p99"] for r in ok], "^--", label="atvfg step p99")
        ax[0].plot(n, [r["cpu_per_uav_epoch_ms"] for r in ok], "d-", label="CPU per UAV-epoch (in-process)")
        ax[0].plot(n, [r["outside_estimator_per_uav_epoch_ms"] for r in ok], "x:", label="outside the estimator (bus, slicing)")
        ax[0].set_xscale("log")
        ax[0].set_yscale("log")
        ax[0].set_xlabel("swarm size N (UAVs), fixed density")
        ax[0].set_ylabel("ms per UAV-epoch")
        ax[0].set_title(f"in-process cost per UAV-epoch (load1 {min(r['load1_before'] for r in ok):.1f}–"
                        f"{max(r['load1_after'] for r in ok):.1f})", fontsize=9)
        ax[0].grid(True, which="both", alpha=0.3)
        ax[0].legend(fontsize=7)
        ax[1].plot(n, [r["realtime_factor"] for r in ok], "o-", label="in-process estimation")
        ww = [r for r in ok if r.get("workers_realtime_factor")]
        if ww:
            ax[1].plot([r["n"] for r in ww], [r["workers_realtime_factor"] for r in ww], "^--",
                       label="in-process, UAVs over 2 worker processes")
    dd = [d for d in res["dist"] if d.get("dist_command_rtf")]
    if dd:
        ax[1].plot([d["n"] for d in dd], [d["dist_command_rtf"] for d in dd], "s-", label="distributed (whole launch)")
    ax[1].axhline(1.0, color="k", lw=0.8, ls=":")

    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("swarm size N (UAVs)")
    ax[1].set_ylabel("real-time factor (scenario s / wall s)")
    ax[1].set_title("real-time factor (atvfg)", fontsize=9)
    ax[1].grid(True, which="both", alpha=0.3)
    ax[1].legend(fontsize=7)
    from matplotlib.ticker import FixedLocator, NullLocator, ScalarFormatter

    sizes = sorted({r["n"] for r in ok} | {d["n"] for d in dd})
    for x in ax:  # after set_xscale, which resets the locators
        x.xaxis.set_major_locator(FixedLocator(sizes))
        x.xaxis.set_minor_locator(NullLocator())
        x.xaxis.set_major_formatter(ScalarFormatter())
    fig.suptitle(f"swarmnav scale bench {res['started']} — configs/scale.toml, atvfg, seed {SEED}, {res['host']['cpus']} CPUs",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def render_md(res: dict) -> str:
    """bench.md from bench.json: in-process cost against N, distributed against in-process, profiles."""
    ok = sorted((r for r in res["inproc"] if "error" not in r), key=lambda r: r["n"])
    L = _inproc_md(res) + _growth_md(ok) + _dist_md(res) + _profile_md(res.get("profile"))
    L += _profile_growth_md(res.get("profile_growth"))
    notes = res.get("notes") or []
    if notes:
        L += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    L += ["", "Figure: `cost_vs_n.png`. Raw figures: `bench.json`. Rebuild: `make bench` (or "
              "`python -m deploy.bench --out DIR`; `--quick` for a 1-minute check).", ""]
    return "\n".join(L)


def _speed_md(res: dict) -> str:
    """The machine's speed at the start and the end (calibration()), for comparing benches."""
    c0, c1 = res.get("calibration_start"), res.get("calibration_end")
    if not c0:
        return ""
    end = f", at the end {c1['py_loop_ms']:g} ms and {c1['chol200_us']:g} µs" if c1 else ""
    return (f"Machine speed: a 3 M-iteration Python loop took {c0['py_loop_ms']:g} ms and a 200 × 200 Cholesky "
            f"{c0['chol200_us']:g} µs at the start{end} (this VM measured 154–421 ms and 89–278 µs over sessions "
            "13–15: compare benches at like speeds).")


def _inproc_md(res: dict) -> list[str]:
    """Header and the in-process table, one row per size."""
    L = [f"# swarmnav scale bench — {res['started']}", "",
         f"Host: {res['host']['cpus']} CPUs, {res['host']['mem_gb']:.0f} GB, Python {res['host']['python']}; "
         f"commit {res['commit']}. Scenario: configs/scale.toml (paper sensors and flight plan, the start box grown with "
         f"N at {res['density_per_km3']:g} UAV/km³, 100 m altitude band, UWB 400 m: ~17–19 links per UAV at every N; "
         f"masters every 8th UAV), atvfg, seed {SEED}. 1-min load average at the start {res['load1_start']}, "
         f"at the end {res.get('load1_end')}; the bench took {_f(res.get('bench_wall_s'), '{:.0f}')} s. "
         "Machine shared: the load average is given beside every figure. " + _speed_md(res), "",
         "## In-process cost against swarm size", "",
         "One fresh process per size: simulate, then atvfg over every epoch on the in-memory bus (`swarmnav evaluate`'s "
         "path). *step* = the estimator's own time per UAV-epoch (all rounds); *wall/UAV-epoch* = median epoch wall ÷ N "
         "(estimator + bus + epoch slicing + protocol); *outside* = the part of it outside the estimator. Epoch 1 "
         "(bootstrap) left out of the per-epoch figures. *real-time ×* = scenario s ÷ the run's wall (node set-up and "
         "epoch 1 included); *2 workers* = the same run right after with its UAVs spread over two forked worker "
         "processes (`swarmnav evaluate --jobs 2` with one run; services/runtime/node_workers.py), *same* = its "
         "estimates bit-identical to the one-process run's.", "",
         "| N | scenario s | links/UAV | step p50 ms | step p99 ms | wall/UAV-epoch ms | CPU/UAV-epoch ms | outside ms | "
         "epoch wall ms | real-time × | 2 workers: real-time × | same | rounds | simulate s | peak RSS MB | "
         "load1 before→after |",
         "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|"]
    for r in sorted(res["inproc"], key=lambda r: r["n"]):
        if "error" in r:
            L.append(f"| {r['n']} | {r['duration_s']:g} | — | — | — | — | — | — | — | — | — | — | — | — | — | failed: {r['error']} "
                     f"(load {r.get('load1_after')}) |")
            continue
        L.append(f"| {r['n']} | {r['duration_s']:g} | {r['links_per_uav_epoch']:.1f} | {r['step_ms_p50']:.2f} | "
                 f"{r['step_ms_p99']:.2f} | {r['wall_per_uav_epoch_ms']:.2f} | {r['cpu_per_uav_epoch_ms']:.2f} | "
                 f"{r['outside_estimator_per_uav_epoch_ms']:.2f} | "
                 f"{r['epoch_wall_ms_p50']:.0f} | {r['realtime_factor']:.2f} | {_f(r.get('workers_realtime_factor'))} | "
                 f"{ {True: 'yes', False: 'NO'}.get(r.get('workers_identical'), '—')} | {r['rounds_mean']:.1f} | {r['simulate_s']:.1f} | "
                 f"{r['peak_rss_mb']:.0f} | {r['load1_before']}→{r['load1_after']} |")
    return L


def _growth_md(ok: list[dict]) -> list[str]:
    """How the per-UAV-epoch cost grows from the smallest (or N = 50) to the largest size, and the
    exponent b of cost ∝ N^b between consecutive sizes."""
    import math

    if len(ok) < 2:
        return []
    a, b = next((r for r in ok if r["n"] == 50), ok[0]), ok[-1]
    g = b["wall_per_uav_epoch_ms"] / a["wall_per_uav_epoch_ms"]
    L = ["", f"Per-UAV-epoch wall grows {g:.1f}× from N = {a['n']} to N = {b['n']} at fixed density "
             f"(the issue's target: flat within 1.5× from 50 to 1,000); the estimator step p50 grows "
             f"{b['step_ms_p50'] / a['step_ms_p50']:.1f}×."]
    L += ["", "Growth between consecutive sizes as an exponent b of cost per UAV-epoch ∝ N^b (b ≈ 0: the per-UAV "
              "cost is flat, O(neighbours); b ≈ 1: the swarm's cost per epoch grows O(N²)):", "",
          "| N from → to | b (wall/UAV-epoch) | b (CPU/UAV-epoch) | b (step p50) | b (outside the estimator) | "
          "b (simulate s / N) | load1 |", "|---|---:|---:|---:|---:|---:|---|"]
    for a, b in zip(ok, ok[1:]):
        def ex(key, per_n=False):
            x, y = a.get(key), b.get(key)
            if not x or not y or x <= 0 or y <= 0:
                return "—"
            if per_n:
                x, y = x / a["n"], y / b["n"]
            return f"{math.log(y / x) / math.log(b['n'] / a['n']):.2f}"
        L.append(f"| {a['n']} → {b['n']} | {ex('wall_per_uav_epoch_ms')} | {ex('cpu_per_uav_epoch_ms')} | "
                 f"{ex('step_ms_p50')} | {ex('outside_estimator_per_uav_epoch_ms')} | {ex('simulate_s', True)} | "
                 f"{a['load1_after']}→{b['load1_after']} |")
    return L


def _dist_md(res: dict) -> list[str]:
    """The distributed runs against their in-process twins, and the launch's peak memory per process kind."""
    L = ["", "## Distributed against in-process, back to back", "",
          "The same scenario (N, scenario seconds, seed) run by `swarmnav evaluate --algos atvfg --jobs 1` and then by "
          "`swarmnav launch` (one process per UAV, secure Zenoh, lockstep); walls of the whole commands (simulation, "
          "start-up and report included). *real-time ×* = scenario s / launch wall. Bytes = the monitor's mean bytes a "
          "node sends per epoch (its round states, estimate and links); every node subscribes to every other node's "
          "state (`uav/*/state`), so what a node receives is ≈ (N − 1) × that — O(N) per node, O(N²) through the router. "
          "Peak RSS/PSS sampled with psutil every 0.5 s / 4 s.", "",
          "| N | scenario s | in-process wall s | distributed wall s | ratio dist/in-proc | real-time × (launch) | "
          "launcher's own × | complete | bytes out/UAV-epoch | ≈ bytes in/UAV-epoch | wait p50 ms | "
          "load1 in-proc→dist (max during) |",
          "|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|"]
    for d in res["dist"]:
        if d.get("skipped"):
            L.append(f"| {d['n']} | {d['duration_s']:g} | — | — | — | — | — | — | — | — | — | skipped: {d['skipped']} |")
            continue
        w = d.get("wait_ms") or {}
        L.append(f"| {d['n']} | {d['duration_s']:g} | {_f(d.get('inproc_command_wall_s'), '{:.1f}')} | "
                 f"{_f(d.get('dist_command_wall_s'), '{:.1f}')} | {_f(d.get('wall_ratio_dist_over_inproc'), '{:.1f}')} | "
                 f"{_f(d.get('dist_command_rtf'))} | {_f(d.get('dist_launcher_rtf'))} | "
                 f"{d.get('dist_complete') if d.get('dist_exit') is not None else 'timed out'} | "
                 f"{_f(d.get('bytes_out_per_uav_epoch'), '{:,.0f}')} | "
                 f"{_f(d['bytes_out_per_uav_epoch'] * (d['n'] - 1) if d.get('bytes_out_per_uav_epoch') else None, '{:,.0f}')} | "
                 f"{_f(w.get('p50'), '{:.0f}')} | "
                 f"{d.get('load1_before_inproc')}→{d.get('load1_before_dist')} (max {d.get('load1_max_during_dist')}) |")
    mem = [d for d in res["dist"] if d.get("memory")]
    if mem:
        L += ["", "Peak memory per process during the launch (MB; max and median over the processes of a kind):", "",
              "| N | kind | processes | peak RSS max | peak RSS median | peak PSS max | peak PSS median | load1 max during |",
              "|---:|---|---:|---:|---:|---:|---:|---|"]
        for d in mem:
            for kind, m in d["memory"].items():
                L.append(f"| {d['n']} | {kind} | {m['processes']} | {m['peak_rss_mb_max']:.0f} | {m['peak_rss_mb_median']:.0f} | "
                         f"{_f(m['peak_pss_mb_max'], '{:.0f}')} | {_f(m['peak_pss_mb_median'], '{:.0f}')} | "
                         f"{d.get('load1_max_during_dist')} |")
    return L


def _profile_md(p: dict | None) -> list[str]:
    """The hot spots of the profiled size (own and cumulative CPU time)."""
    L: list[str] = []
    if p and "by_tottime" in p:
        L += ["", f"## Profile: in-process N = {p['n']}, {p['duration_s']:g} s (cProfile, {p['total_s']:.1f} s "
                  f"profiled; load1 {p.get('load1')})", "",
              "Top functions by own time:", "", "| function | calls | own s | own % | cumulative s |",
              "|---|---:|---:|---:|---:|"]
        for r in p["by_tottime"]:
            L.append(f"| `{r['function']}` | {r['calls']:,} | {r['tottime_s']:.2f} | {100 * r['tottime_s'] / p['total_s']:.1f} | "
                     f"{r['cumtime_s']:.2f} |")
        L += ["", "swarmnav/gtsam functions by cumulative time:", "", "| function | calls | cumulative s | cum % |",
              "|---|---:|---:|---:|"]
        for r in p["by_cumtime"]:
            L.append(f"| `{r['function']}` | {r['calls']:,} | {r['cumtime_s']:.2f} | {100 * r['cumtime_s'] / p['total_s']:.1f} |")
    elif p:
        L += ["", f"## Profile: failed ({p.get('error')})"]
    return L


def _profile_growth_md(g: dict | None) -> list[str]:
    """Which functions' own CPU time grows O(N) or O(N²) between the two profiled sizes."""
    if not g:
        return []
    lin, quad = g["n_large"] / g["n_small"], (g["n_large"] / g["n_small"]) ** 2
    L = ["", f"### What grows with N: own CPU time per function, N = {g['n_small']} → {g['n_large']} (same seconds of "
              f"scenario; whole run {g['total_small_s']:.1f} → {g['total_large_s']:.1f} s CPU, "
              f"×{g['total_large_s'] / max(g['total_small_s'], 1e-9):.1f})", "",
          f"×{lin:.0f} = the swarm's cost grows O(N) (flat per UAV: O(neighbours)); ×{quad:.0f} = it grows O(N²) "
          "(every UAV does work for every other UAV).", "",
          "| function | own s (small N) | own s (large N) | growth | order |", "|---|---:|---:|---:|---|"]
    for r in g["rows"]:
        ratio = r["ratio"]
        order = "—" if ratio is None else ("O(N²)" if ratio > (lin * quad) ** 0.5 else "O(N)" if ratio > lin ** 0.5
                                           else "flat")
        L.append(f"| `{r['function']}` | {r['own_s_small']:.2f} | {r['own_s_large']:.2f} | "
                 f"{'—' if ratio is None else f'×{ratio:.1f}'} | {order} |")
    return L


def _largest_duration(done: list[dict], n: int, dur_max: float, left_s: float) -> float:
    """Scenario seconds for the largest size: as many epochs (2..) as fit in the time left, from the
    CPU per UAV-epoch of the two largest sizes measured (extrapolated as a power of N) and their
    wall/CPU ratio (the machine's load)."""
    import math

    ok = sorted((r for r in done if "error" not in r and r.get("cpu_per_uav_epoch_ms")), key=lambda r: r["n"])
    if len(ok) < 2:
        return dur_max
    a, b = ok[-2], ok[-1]
    ex = math.log(b["cpu_per_uav_epoch_ms"] / a["cpu_per_uav_epoch_ms"]) / math.log(b["n"] / a["n"])
    # the per-UAV cost grows faster at large N than between the two sizes measured (300 -> 1000 was
    # ~N^1.35 on 2026-12-02, 100 -> 300 ~N^0.7): assume at least linear, with a 1.5x margin
    cpu = 1.5 * b["cpu_per_uav_epoch_ms"] * (n / b["n"]) ** max(ex, 1.0) / 1e3 * n  # s per epoch
    slow = max(1.0, b["wall_s"] / max(b["cpu_s"], 1e-9))
    per_epoch = cpu * slow
    fixed = 10.0 + b["simulate_s"] * n / b["n"]  # simulate + building the nodes
    epochs = int((left_s - 150.0 - fixed) // per_epoch)  # ~150 s kept for a profile and one distributed run
    return float(max(MIN_EPOCHS_LARGEST, min(int(dur_max), epochs)))


def main(argv=None) -> int:
    """The scale bench within BUDGET_S: in-process sizes, two profiles, distributed runs with their
    in-process twins; bench.json and bench.md rewritten after every step, then the plot."""
    a = _parse_args(argv)
    if a.one:
        r = inproc_one(int(a.one[0]), float(a.one[1]), a.profile)
        Path(a.json).write_text(json.dumps(r, indent=1) + "\n")
        return 0

    t_start = time.perf_counter()
    started = time.strftime("%Y%m%d-%H%M%S")
    out = Path(a.out) if a.out else REPO / "bench" / started
    out.mkdir(parents=True, exist_ok=True)
    inproc, dist, prof = (QUICK_INPROC, QUICK_DIST, QUICK_PROFILE) if a.quick else (INPROC, DIST, PROFILE)
    res = _new_result(started)

    def left() -> float:
        return BUDGET_S - (time.perf_counter() - t_start)

    def save():
        res["bench_wall_s"] = time.perf_counter() - t_start
        res["load1_end"] = load1()
        (out / "bench.json").write_text(json.dumps(res, indent=1) + "\n")
        (out / "bench.md").write_text(render_md(res))

    _bench_inproc(res, inproc, out, left, save, a.quick)
    if not a.no_profile:
        _bench_profiles(res, prof, out, left, save)
    if not a.no_dist:
        _bench_dist(res, dist, out, left, save)
    res["calibration_end"] = calibration()
    save()
    try:
        write_plot(res, out / "cost_vs_n.png")
    except Exception as e:  # noqa: BLE001 - the tables are the result; the plot is a view of them
        res["notes"].append(f"plot failed: {e}")
        save()
    print(f"[bench] wrote {out}/bench.md, bench.json, cost_vs_n.png in {time.perf_counter() - t_start:.0f} s "
          f"(load1 {load1()})", flush=True)
    print((out / "bench.md").read_text())
    return 0


def _parse_args(argv):
    ap = argparse.ArgumentParser(prog="python -m deploy.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="output directory (default bench/<timestamp>)")
    ap.add_argument("--quick", action="store_true", help="small sizes only (a ~1-2 minute check of the harness)")
    ap.add_argument("--no-dist", action="store_true", help="skip the distributed runs")
    ap.add_argument("--no-profile", action="store_true", help="skip the cProfile run")
    ap.add_argument("--one", nargs=2, metavar=("N", "DURATION_S"), help=argparse.SUPPRESS)  # worker mode
    ap.add_argument("--json", help=argparse.SUPPRESS)
    ap.add_argument("--profile", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def _new_result(started: str) -> dict:
    """bench.json before any run: the commit (+dirty), the host, the load at the start."""
    import psutil

    from swarmnav.config import load_config

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                           text=True).stdout.strip()
    return {"started": started, "commit": commit + ("+dirty" if dirty else ""), "config": "configs/scale.toml",
            "algo": ALGO, "seed": SEED, "density_per_km3": load_config(CONFIG).swarm.density_per_km3,
            "host": {"cpus": os.cpu_count(), "mem_gb": psutil.virtual_memory().total / 2**30, "python": platform.python_version()},
            "load1_start": load1(), "calibration_start": calibration(), "inproc": [], "dist": [], "profile": None,
            "notes": []}


def _bench_inproc(res: dict, sizes, out: Path, left, save, quick: bool) -> None:
    """1. in-process sizes (the largest gets the epochs the budget allows: its row is the point)."""
    for i, (n, dur) in enumerate(sizes):
        last = i == len(sizes) - 1
        if last and len(res["inproc"]) >= 2 and not quick:
            dur = _largest_duration(res["inproc"], n, dur, left())
        print(f"[bench] in-process N={n} ({dur:g} s scenario) — load1 {load1()}, {left():.0f} s of budget left", flush=True)
        r = run_inproc(n, dur, out, timeout=max(60.0, left() - (20.0 if last else 60.0)))
        res["inproc"].append(r)
        print(f"[bench]   -> " + (f"failed: {r['error']}" if "error" in r else
                                 f"step p50 {r['step_ms_p50']:.2f} ms p99 {r['step_ms_p99']:.2f} ms, wall/UAV-epoch "
                                 f"{r['wall_per_uav_epoch_ms']:.2f} ms, CPU/UAV-epoch {r['cpu_per_uav_epoch_ms']:.2f} ms, "
                                 f"{r['realtime_factor']:.3f}x real time (2 workers: "
                                 f"{_f(r.get('workers_realtime_factor'), '{:.3f}')}x, same estimates: {r.get('workers_identical')}), "
                                 f"peak RSS {r['peak_rss_mb']:.0f} MB, "
                                 f"load1 {r['load1_after']}"), flush=True)
        save()


def _bench_profiles(res: dict, sizes, out: Path, left, save) -> None:
    """2. profiles (CPU time) at two sizes: the hot spots of the larger, and what grows with N."""
    profs = []
    for n, dur in sizes:
        if left() < 60:
            res["notes"].append(f"profile N = {n} skipped: the budget had {left():.0f} s left")
            break
        print(f"[bench] profile in-process N={n} ({dur:g} s) — load1 {load1()}", flush=True)
        pf = out / f"profile-{n}.prof"
        r = run_inproc(n, dur, out, profile=str(pf), timeout=max(60.0, min(400.0, left() - 30.0)))
        if "error" in r or not pf.is_file():
            res["profile"] = {"n": n, "duration_s": dur, "error": r.get("error", "no profile written")}
            break
        profs.append((n, pf))
        res["profile"] = {"n": n, "duration_s": dur, "load1": r.get("load1_after"), "clock": "CPU time",
                          **profile_summary(pf)}
        save()
    if len(profs) >= 2:
        res["profile_growth"] = profile_growth(profs[0][1], profs[-1][1], profs[0][0], profs[-1][0])
        save()


def _bench_dist(res: dict, sizes, out: Path, left, save) -> None:
    """3. distributed, each with its in-process twin, while the budget allows."""
    for n, dur in sizes:
        # rough need: launch start-up ~0.25 s per process + the run at ~1x, plus the in-process twin
        need = 40 + 0.6 * n + 1.5 * dur * max(1.0, n / 18)
        if left() < need:
            res["dist"].append({"n": n, "duration_s": dur, "skipped": f"time budget ({left():.0f} s left, ~{need:.0f} s needed)"})
            res["notes"].append(f"distributed N = {n} skipped: the 15-minute budget had {left():.0f} s left")
            continue
        print(f"[bench] distributed N={n} ({dur:g} s) + in-process twin — load1 {load1()}, {left():.0f} s left", flush=True)
        d = run_dist(n, dur, out, timeout=max(60.0, left() - 30.0))
        res["dist"].append(d)
        print(f"[bench]   -> launch {_f(d.get('dist_command_wall_s'), '{:.1f}')} s ({_f(d.get('dist_command_rtf'))}x), "
              f"in-process {_f(d.get('inproc_command_wall_s'), '{:.1f}')} s, ratio {_f(d.get('wall_ratio_dist_over_inproc'))}, "
              f"load1 {load1()}", flush=True)
        save()


if __name__ == "__main__":
    raise SystemExit(main())
