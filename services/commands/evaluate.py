"""`swarmnav evaluate`: run estimators in-process (in-memory transport of the one epoch protocol).

Thin adapter: datasets (simulated per seed, or one directory as-is) -> swarmnav.evaluation (pure)
-> swarmnav.metrics / swarmnav.report (pure) -> files: report.json, report.md, figures/*.png,
traj/<algo>/uav<id>.tum (+ traj/truth), evaluate.rrd, evaluate.log.

Algorithm × seed runs are spread over ``--jobs`` worker processes (fork; OMP/BLAS limited to one
thread each); a single run of a per-UAV algorithm spreads its UAVs over them instead
(``services/runtime/node_workers.py``, bit-identical estimates). Estimation is identical to the distributed run: same ``initial_states(ds, seed)``,
the same settings dict (``services.settings``: the [estimation] table and the trained Δl), UAVs in sorted order.
With ``--dataset`` the seed only drives the initial-state draw; it defaults to the dataset's seed.
Multi-seed runs pool every metric over the seeds; figures, TUM files at ``traj/<algo>/`` and the
.rrd show the first seed (other seeds' TUM files go to ``traj/seed<N>/<algo>/``).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
import traceback
from pathlib import Path

HELP = "run estimators in-process over simulated seeds or a dataset; write report, figures, TUM, .rrd"
DESCRIPTION = HELP + """.

Runs each algorithm over each seed in one process with the same epoch protocol as the swarm (an
in-memory bus), so a seed gives the numbers `swarmnav launch` gives. Writes report.json, report.md,
figures/*.png, traj/<algo>/uav<id>.tum (for evo) and evaluate.rrd (every algorithm side by side).
Algorithms: atvfg (the paper's method as we run it), atvfg_paper (the paper's method exactly as
published), fg (plain distributed factor graph), fkf (federated Kalman filter), ins (each UAV alone),
central (oracle: one joint graph, faulty links removed). The default runs the first five but atvfg_paper.
Over several seeds the report leads with a Monte Carlo: per algorithm the mean of the per-seed 3-D
position RMSE with its 95 % confidence interval, and paired per-seed differences (atvfg − fg, − fkf,
− central); `--seeds report` runs the seeds the config reports on, `--seeds tuning` those it was
tuned on ([evaluation] in the config).

examples:
  swarmnav evaluate --config configs/smoke.toml                               # the default five, the config's seed
  swarmnav evaluate --config configs/paper.toml --algos atvfg,fg,fkf,ins,central --seeds 1-3
  swarmnav evaluate --config configs/paper.toml --seeds report --jobs 2         # the Monte-Carlo headline
  swarmnav evaluate --dataset runs/miluv-dataset --algos atvfg,fg,central --seeds 0
  swarmnav evaluate --config configs/scale.toml --set swarm.n_uavs=1000 --set scenario.duration_s=10 \
      --algos atvfg --seeds 1 --jobs 2                                         # one run: its UAVs over 2 workers
"""
ALL_ALGOS = "atvfg,fg,fkf,ins,central"

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

log = logging.getLogger("swarmnav.evaluate")


def parse_seeds(text: str) -> list[int]:
    """'1-5' -> [1..5]; '1,3,7' -> [1,3,7]; mixes like '1-3,7' allowed; sorted, duplicates removed
    (``swarmnav.config.parse_seed_spec``; a bad spec is a ConfigError naming --seeds)."""
    from swarmnav.config import parse_seed_spec
    from swarmnav.errors import ConfigError

    try:
        return parse_seed_spec(str(text))
    except ValueError as e:
        raise ConfigError(f"--seeds: {e}") from None


def config_seeds(text: str, sc) -> list[int]:
    """--seeds with a config: 'report' / 'tuning' name the [evaluation] seed sets; else parse_seeds.
    A warning on stderr when seeds the settings were tuned on are evaluated (numbers not to report)."""
    text = str(text).strip()
    seeds = sc.evaluation.seeds(text) if text in ("report", "tuning") else parse_seeds(text)
    role = sc.evaluation.role_of(seeds)
    if role in ("tuning", "mixed"):
        print(f"swarmnav evaluate: note: seeds {sorted(set(seeds) & set(sc.evaluation.seeds('tuning')))} are "
              f"tuning seeds of {sc.scenario.name} ([evaluation] tuning_seeds): numbers not to report", file=sys.stderr)
    return seeds


def parse_algos(text: str) -> list[str]:
    from swarmnav.errors import ConfigError
    from swarmnav.estimators import registry

    algos = []
    for a in text.split(","):
        a = a.strip()
        if not a:
            continue
        if a not in registry.known():
            raise ConfigError(f"--algos: unknown algorithm {a!r}; known: {', '.join(registry.known())}")
        if a not in algos:
            algos.append(a)
    if not algos:
        raise ConfigError("--algos: no algorithm given")
    return algos


def add_arguments(p):
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", help="scenario TOML; each seed's dataset is simulated exactly as `simulate --seed N`")
    src.add_argument("--dataset", help="dataset directory, used as-is (simulated or imported real data)")
    p.add_argument("--algos", default=ALL_ALGOS, help=f"comma-separated algorithms (default {ALL_ALGOS})")
    p.add_argument("--seeds", default=None, help="seeds: 1-5, 1,3,7 or mixes, or 'report' / 'tuning' (the config's "
                   "[evaluation] report_seeds / tuning_seeds; default: the config's / dataset's seed)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set",
                   help="override a config field before validation (repeatable), e.g. --set swarm.n_uavs=100 "
                        "--set scenario.duration_s=60 (configs/scale.toml is made for this)")
    p.add_argument("--out", default="runs/evaluate", help="output directory (default runs/evaluate)")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes (default 2): algorithm x seed runs side by side, or, for a single run, "
                   "its UAVs")
    p.add_argument("--no-rrd", action="store_true", help="skip the Rerun recording")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


# -- worker side (fork: datasets and settings are inherited, not pickled) -------------------------

_DATASETS: dict = {}
_SETTINGS: dict = {}
_QUEUE = None


def _limit_threads():
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # threadpoolctl comes with scikit-learn; OMP_NUM_THREADS=1 is set anyway
        pass


def _run_task(task):
    tid, algo, seed = task
    from swarmnav.evaluation import run_algorithm

    q = _QUEUE
    last = [0]

    def prog(k, K):
        if q is not None and (k - last[0] >= max(1, K // 100) or k == K):
            q.put((tid, k - last[0]))
            last[0] = k

    try:
        return tid, run_algorithm(_DATASETS[seed], algo, seed, _SETTINGS, prog, time.perf_counter), None
    except Exception as e:  # noqa: BLE001 - reported by the parent: first line for the user, then the traceback
        from swarmnav.errors import describe_estimator_failure

        return tid, None, describe_estimator_failure(algo, seed, e) + "\n" + traceback.format_exc()


def _simulate(args_tuple):
    cfg_path, seed, overrides = args_tuple
    from swarmnav.config import load_config
    from swarmnav.sim import simulate

    return seed, simulate(load_config(cfg_path, overrides), seed)


# -- main ---------------------------------------------------------------------------------------


def _setup_log(out: Path) -> logging.Handler:
    h = logging.FileHandler(out / "evaluate.log", mode="w")
    h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    root = logging.getLogger("swarmnav")
    root.setLevel(logging.INFO)
    root.addHandler(h)
    return h


def _load_inputs(args):
    """-> (scenario_name, seeds, settings, config_sha256, datasets by seed, outage windows)."""
    from swarmnav.dataset import Dataset

    from services.settings import estimator_settings, lookup_dirs, settings_for_dataset, warn_missing_delta_l

    if args.config:
        from swarmnav.config import load_config

        cfg_path = Path(args.config)
        sc = load_config(cfg_path, args.set)
        from ._checks import note_faults_after_end

        note_faults_after_end(sc, "evaluate")
        seeds = config_seeds(args.seeds, sc) if args.seeds else [sc.scenario.seed]
        base_dirs = lookup_dirs(cfg_path)[-2:]  # the config's parent's parent and its own directory
        warn_missing_delta_l(sc.estimation, "evaluate", base_dirs)
        settings = estimator_settings(sc.estimation, base_dirs=base_dirs)
        return sc.scenario.name, seeds, settings, sc.sha256(), None, cfg_path
    from services.provenance import dataset_sha256

    if args.set:
        from swarmnav.errors import ConfigError

        raise ConfigError("--set overrides a config's fields: use it with --config, not --dataset")
    ds = Dataset.read(args.dataset)
    if args.seeds and args.seeds.strip() in ("report", "tuning"):
        from swarmnav.errors import ConfigError

        raise ConfigError(f"--seeds {args.seeds.strip()}: names the seeds of a config's [evaluation] table; use --config")
    seeds = parse_seeds(args.seeds) if args.seeds else [ds.meta.seed if ds.meta.seed is not None else 0]
    settings = settings_for_dataset(ds.meta)
    return ds.meta.name, seeds, settings, dataset_sha256(ds.meta), ds, None


def _check_run_args(args) -> tuple[int, list[str]]:
    """(jobs, algorithms), every one checked before anything is written; ConfigError otherwise."""
    from swarmnav.errors import ConfigError
    from swarmnav.estimators import registry

    if args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: the number of worker processes must be >= 1 (default 2)")
    algos = parse_algos(args.algos)
    for a in algos:  # fail fast (and import once here, so forked workers inherit the modules)
        registry.estimator_class(a)
    return int(args.jobs), algos


def _make_datasets(seeds, ds_given, cfg_path, overrides, jobs: int, ctx, quiet: bool) -> None:
    """Fill _DATASETS: the given dataset for every seed, or each seed simulated (in parallel)."""
    _DATASETS.clear()
    if ds_given is not None:
        for s in seeds:
            _DATASETS[s] = ds_given
        return
    t0 = time.perf_counter()
    todo = [(str(cfg_path), s, list(overrides)) for s in seeds]
    if len(todo) > 1 and jobs > 1:
        with ctx.Pool(min(jobs, len(todo)), initializer=_limit_threads) as pool:
            for s, ds in pool.imap_unordered(_simulate, todo):
                _DATASETS[s] = ds
    else:
        for item in todo:
            s, ds = _simulate(item)
            _DATASETS[s] = ds
    log.info("simulated %d seed(s) in %.1f s", len(seeds), time.perf_counter() - t0)
    if not quiet:
        print(f"simulated {len(seeds)} seed(s) in {time.perf_counter() - t0:.1f} s", file=sys.stderr)


def _tasks(algos: list[str], seeds: list[int]) -> list[tuple[int, str, int]]:
    """(task id, algorithm, seed), longest runs first so that the workers finish together."""
    cost = {"central": 0, "atvfg": 1, "fg": 2, "fkf": 3, "ins": 4}
    runs = sorted(((a, s) for a in algos for s in seeds), key=lambda x: (cost.get(x[0], 5), x[1]))
    return [(i, a, s) for i, (a, s) in enumerate(runs)]


def _run_tasks(tasks, settings: dict, jobs: int, ctx, n_epochs: int, quiet: bool) -> tuple[dict, dict]:
    """Run every (algorithm, seed) task, in this process or over a worker pool, with progress bars.
    -> (results by (algorithm, seed), failures 'algo/seedN' -> first line of the error)."""
    from tqdm import tqdm

    results: dict[tuple[str, int], object] = {}
    failures: dict[str, str] = {}

    def handle(tid, res, err):
        _, a, s = tasks[tid]
        if err:
            failures[f"{a}/seed{s}"] = err.strip().splitlines()[0]
            log.error("%s seed %d failed:\n%s", a, s, err)
            tqdm.write(f"swarmnav evaluate: FAILED: {failures[f'{a}/seed{s}']}", file=sys.stderr)
        else:
            results[(a, s)] = res
            log.info("%s seed %d: %.1f s wall", a, s, res.wall_s)

    if jobs == 1 or len(tasks) == 1:
        _limit_threads()  # numpy may have been imported before OPENBLAS_NUM_THREADS was set
        # one run and several jobs: its UAVs spread over the workers (node_workers.py; same numbers)
        _run_serial(tasks, settings, n_epochs, quiet, handle, jobs if len(tasks) == 1 else 1)
    else:
        _run_pool(tasks, jobs, ctx, n_epochs, quiet, handle)
    return results, failures


def _run_serial(tasks, settings: dict, n_epochs: int, quiet: bool, handle, node_workers: int = 1) -> None:
    from swarmnav.errors import describe_estimator_failure
    from swarmnav.evaluation import run_algorithm
    from tqdm import tqdm

    from ..runtime.node_workers import worker_groups

    groups = worker_groups(node_workers) if node_workers > 1 else None
    for tid, a, s in tasks:
        bar = tqdm(total=n_epochs, desc=f"{a:>7} seed {s}", disable=quiet, leave=True)
        try:
            res = run_algorithm(_DATASETS[s], a, s, settings, lambda k, KK: bar.update(1), time.perf_counter, groups)
            handle(tid, res, None)
        except Exception as e:  # noqa: BLE001
            handle(tid, None, describe_estimator_failure(a, s, e) + "\n" + traceback.format_exc())
        bar.close()


def _run_pool(tasks, jobs: int, ctx, n_epochs: int, quiet: bool, handle) -> None:
    """Forked workers (they inherit _DATASETS and _SETTINGS) report progress through _QUEUE."""
    global _QUEUE
    import queue as _q

    from tqdm import tqdm

    _QUEUE = ctx.Queue()
    with ctx.Pool(min(jobs, len(tasks)), initializer=_limit_threads) as pool:
        pending = [pool.apply_async(_run_task, (t,)) for t in tasks]
        bars = {tid: tqdm(total=n_epochs, desc=f"{a:>7} seed {s}", position=pos, disable=quiet, leave=True)
                for pos, (tid, a, s) in enumerate(tasks)}
        while pending:
            try:
                while True:
                    tid, n = _QUEUE.get(timeout=0.2)
                    bars[tid].update(n)
            except _q.Empty:
                pass
            for p in [p for p in pending if p.ready()]:
                pending.remove(p)
                handle(*p.get())
        for b in bars.values():
            b.close()
    _QUEUE = None


def run(args) -> int:
    """Load (datasets, settings) -> run every algorithm over every seed -> assemble and write the report."""
    global _SETTINGS
    import multiprocessing as mp

    from swarmnav.assembly import assemble_report
    from swarmnav.evaluation import link_labels, truth_at_epochs
    from swarmnav.report import render_markdown, summary_table, validate_report

    from services.provenance import provenance

    t_wall = time.perf_counter()
    jobs, algos = _check_run_args(args)
    name, seeds, settings, cfg_sha, ds_given, cfg_path = _load_inputs(args)
    from ._checks import make_out_dir

    out = make_out_dir(args.out)
    # a report left by an earlier run in this directory must not pass for this one's if this run
    # is interrupted or fails before writing its own (they are written together at the end)
    for stale in ("report.json", "report.md", "evaluate.rrd"):
        (out / stale).unlink(missing_ok=True)
    handler = _setup_log(out)
    _SETTINGS = settings
    log.info("evaluate %s: algos=%s seeds=%s settings=%s", name, algos, seeds, settings)
    ctx = mp.get_context("fork")
    _make_datasets(seeds, ds_given, cfg_path, args.set, jobs, ctx, bool(args.quiet))
    meta = _DATASETS[seeds[0]].meta
    results, failures = _run_tasks(_tasks(algos, seeds), settings, jobs, ctx, meta.n_epochs(), bool(args.quiet))

    truths = {s: truth_at_epochs(_DATASETS[s]) for s in seeds}
    ran = [a for a in algos if all((a, s) in results for s in seeds)]
    # the one report assembly, shared with the monitor (swarmnav.assembly)
    rep = assemble_report(mode="in-process", meta=meta, seeds=seeds, runs={a: [results[(a, s)] for s in seeds] for a in ran},
                          truths=[truths[s] for s in seeds], labels=[link_labels(_DATASETS[s]) for s in seeds],
                          settings=settings, provenance=provenance(cfg_sha), source="config" if args.config else "dataset",
                          failed=failures, ranges=[_DATASETS[s].table("ranges") for s in seeds])
    problems = validate_report(rep)
    if problems:
        log.error("report.json does not meet the contract: %s", problems)
    (out / "report.json").write_text(json.dumps(rep, indent=1, sort_keys=False) + "\n")
    (out / "report.md").write_text(render_markdown(rep))
    _write_views(out, rep, results, truths, seeds, ran, meta, rrd=not args.no_rrd)
    wall = time.perf_counter() - t_wall
    log.info("done in %.1f s", wall)
    print(summary_table(rep))
    print(f"wrote {out}/report.json, report.md, figures/, traj/, {'evaluate.rrd, ' if not args.no_rrd else ''}evaluate.log "
          f"({wall:.1f} s wall)")
    logging.getLogger("swarmnav").removeHandler(handler)
    handler.close()
    return 1 if failures or problems else 0


def _write_views(out: Path, rep: dict, results: dict, truths: dict, seeds: list[int], ran: list[str], meta, rrd: bool) -> None:
    """figures/*.png, traj/**.tum and (unless rrd is False) evaluate.rrd: the first seed is shown."""
    from services.figures import write_figures

    s0 = seeds[0]
    res0 = {a: results[(a, s0)] for a in ran}
    write_figures(out, res0, truths[s0], {a: [results[(a, s)] for s in seeds] for a in ran},
                  [truths[s] for s in seeds], meta.gnss_outages, _DATASETS[s0], meta, rep["thresholds"]["delta_l_m"])
    _write_tum(out, results, truths, seeds, ran)
    if rrd:
        _write_rrd(out / "evaluate.rrd", res0, truths[s0], meta.anchors())


# -- outputs ------------------------------------------------------------------------------------


def _tum_lines(t, pos, quat) -> str:
    import numpy as np

    rows = []
    for ti, p, q in zip(t, pos, quat):
        if not np.all(np.isfinite(p)):
            continue
        if not np.all(np.isfinite(q)):
            q = (1.0, 0.0, 0.0, 0.0)
        rows.append(f"{ti:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}")
    return "\n".join(rows) + "\n"


def _write_tum(out: Path, results: dict, truths: dict, seeds: list[int], algos: list[str]) -> None:
    """TUM: 'timestamp tx ty tz qx qy qz qw' (ENU m; q body FLU -> ENU; identity when the estimator
    has no attitude). First seed at traj/<algo>/uav<id>.tum, other seeds under traj/seed<N>/."""
    for i, s in enumerate(seeds):
        base = out / "traj" if i == 0 else out / "traj" / f"seed{s}"
        tr = truths[s]
        for name, get in [("truth", lambda j: (tr.pos[:, j], tr.quat[:, j]))] + \
                [(a, (lambda a: lambda j: (results[(a, s)].pos[:, j], results[(a, s)].quat[:, j]))(a)) for a in algos]:
            d = base / name
            d.mkdir(parents=True, exist_ok=True)
            for j, u in enumerate(tr.uavs):
                p, q = get(j)
                (d / f"uav{int(u)}.tum").write_text(_tum_lines(tr.t, p, q))


def _write_rrd(path: Path, res0: dict, truth, anchors: dict) -> None:
    """Every algorithm side by side (first seed): positions, link classes, error series."""
    import numpy as np

    from services import recording as R

    algos = list(res0)
    link_algos = [a for a in algos if len(res0[a].links)]
    rec = R.open_recording(path, blueprint=R.default_blueprint(algos, link_algos, bool(anchors)))
    try:
        t = truth.t
        k = np.arange(1, len(t) + 1)
        R.log_styles(algos, rec, link_algos)
        # point sizes scaled to the scene (km-scale swarm or an indoor flight), anchors drawn once
        radius = R.point_radius(truth.pos, list(anchors.values()))
        R.log_anchors(anchors, radius, rec)
        for j, u in enumerate(truth.uavs):
            R.send_positions("truth", int(u), t, k, truth.pos[:, j], rec, radius=0.75 * radius)
        uavs = list(truth.uavs)
        for a, r in res0.items():
            for j, u in enumerate(truth.uavs):
                R.send_positions(a, int(u), t, k, r.pos[:, j], rec, radius=radius)
            pe = np.linalg.norm(r.pos - truth.pos, axis=2)
            ve = np.linalg.norm(r.vel - truth.vel, axis=2)
            R.send_labels(a, t, k, r.pos, uavs, rec)
            tr3 = np.trace(r.pos_cov, axis1=2, axis2=3)  # K x N: the estimator's own 3-D position variance
            if 1 in uavs:
                R.send_series(R.error_path(a, "pos_3d", "uav1"), t, k, pe[:, uavs.index(1)], rec)
                R.send_series(R.error_path(a, "pos_3sigma", "uav1"), t, k, 3 * np.sqrt(tr3[:, uavs.index(1)]), rec)
            R.send_series(R.error_path(a, "pos_3d", "swarm"), t, k, np.sqrt(np.nanmean(pe**2, axis=1)), rec)
            R.send_series(R.error_path(a, "pos_3sigma", "swarm"), t, k, 3 * np.sqrt(np.nanmean(tr3, axis=1)), rec)
            R.send_series(R.error_path(a, "vel_3d", "swarm"), t, k, np.sqrt(np.nanmean(ve**2, axis=1)), rec)
            if len(r.links):
                R.send_links(a, t, k, *_link_segments(r, truth.uavs), rec=rec, radius=0.15 * radius)
        R.set_epoch(0, float(truth.t[0]) - (truth.t[1] - truth.t[0] if len(truth.t) > 1 else 1.0), rec)
        R.log_event("evaluate", 0, 0.0, text=f"in-process evaluation of {', '.join(algos)} (seed "
                    f"{next(iter(res0.values())).seed if res0 else '-'}); no kills in-process", rec=rec, level="INFO")
    finally:
        R.close_recording(rec)


def _link_segments(r, uavs):
    """Per epoch, one segment per unordered pair between the two estimated positions, with the
    worse of the two ends' classes. -> (segments (M,2,3), classes (M,), per-epoch counts (K,))."""
    import numpy as np

    K = len(r.t)
    lk = r.links
    o = lk["observer"].astype(np.int64)
    x = lk["other"].astype(np.int64)
    a, b = np.minimum(o, x), np.maximum(o, x)
    M = int(max(b.max(), max(int(u) for u in uavs))) + 1
    col = np.full(M, -1)
    col[np.asarray(uavs, int)] = np.arange(len(uavs))
    kk = lk["k"].astype(np.int64)
    key = (kk * M + a) * M + b
    order = np.lexsort((lk["cls"], key))  # by pair-epoch, then class: first of a group = worst
    ks = key[order]
    first = order[np.r_[True, ks[1:] != ks[:-1]]]
    kk, a, b, cls = kk[first], a[first], b[first], lk["cls"][first].astype(int)
    ok = (col[a] >= 0) & (col[b] >= 0)
    kk, a, b, cls = kk[ok], a[ok], b[ok], cls[ok]
    p1, p2 = r.pos[kk - 1, col[a]], r.pos[kk - 1, col[b]]
    fin = np.all(np.isfinite(p1), axis=1) & np.all(np.isfinite(p2), axis=1)
    segs = np.stack([p1[fin], p2[fin]], axis=1)
    return segs, cls[fin], np.bincount(kk[fin] - 1, minlength=K)[:K]
