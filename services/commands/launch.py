"""`swarmnav launch`: the swarm as real processes on Zenoh (router, sensor-sim, N UAV nodes, monitor).

The scenario is simulated once into ``<run>/dataset/`` (or ``--dataset DIR`` is played as is);
then deploy/launcher.py starts an embedded router on a free loopback port and one OS process per
service, each logging to ``<run>/logs/<name>.log``. Kills/restarts come from ``--kill/--restart
ID@T`` (simulation time) and the config's ``faults.process_kill``. Results: ``report.json``
("mode": "distributed"), ``report.md``, ``swarm.rrd``. Without ``--out`` the run goes to
``runs/<timestamp>-<scenario>/`` and ``runs/latest`` points at it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

HELP = "run the swarm as a real multi-process Zenoh deployment (router, sensor-sim, UAV nodes, monitor)"
DESCRIPTION = HELP + """.

Secure by default: the embedded router speaks mutual TLS only and enforces an ACL; every process has
its own identity (RUN_DIR/security/<principal>.json5). The run directory receives report.json,
report.md, swarm.rrd, estimates.npz, logs/ and the monitor's journal/. The exit status is 0 only
for a complete run (every expected estimate received).

examples:
  swarmnav launch --config configs/smoke.toml                       # 5 UAVs, 60 s, lockstep
  swarmnav launch --config configs/paper.toml --algo fg --seed 2    # the paper swarm with plain fg
  swarmnav launch --config configs/smoke.toml --kill 2@15 --restart 2@25 --out runs/dropout
  swarmnav launch --config configs/scale.toml --set swarm.n_uavs=100   # 100 UAV processes, 60 s
  swarmnav launch --config configs/smoke.toml --rate 1              # real time instead of lockstep
  swarmnav launch --dataset runs/miluv-dataset --seed 0             # replay a recorded dataset
  swarmnav launch --config configs/smoke.toml --rate 1 --live       # watch it live in a Rerun viewer
  swarmnav report runs/latest                                       # rebuild the outputs after a crash
"""


def default_run_dir(name: str) -> Path:
    """``runs/<timestamp>-<name>``, one directory level: a dataset name such as
    ``miluv/cirObstacles_3_random_0`` becomes ``miluv-cirObstacles_3_random_0`` (runs/latest
    points at it by its base name)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(name)).strip("-.") or "run"
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{safe}"


def claim_default_run_dir(name: str) -> Path:
    """Create ``default_run_dir(name)`` atomically and return it; when it exists already (another
    launch started in the same second) ``-2``, ``-3``, ... is appended, so two runs never share a
    directory (they overwrote each other's identities: one hung, the other failed)."""
    from swarmnav.errors import SwarmnavError

    base = default_run_dir(name)
    for i in range(1, 1000):
        p = base if i == 1 else base.with_name(f"{base.name}-{i}")
        try:
            p.mkdir(parents=True, exist_ok=False)
            return p
        except FileExistsError:
            continue
        except OSError as e:
            raise SwarmnavError(f"cannot create the run directory {p} ({e.strerror}); give one with --out") from None
    raise SwarmnavError(f"cannot find a new run directory beside {base}; give one with --out")


def point_latest(run_dir: Path) -> None:
    """runs/latest -> run_dir, replaced atomically (two launches may finish setting up together)."""
    tmp = run_dir.parent / f".latest-{os.getpid()}"
    try:
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(run_dir.name)
        os.replace(tmp, run_dir.parent / "latest")
    except OSError as e:  # e.g. runs/latest is a real directory: the run goes on without the link
        tmp.unlink(missing_ok=True)
        print(f"swarmnav launch: warning: cannot point {run_dir.parent / 'latest'} at this run ({e.strerror})",
              file=sys.stderr)


def _fault(s: str) -> tuple[int, float]:
    try:
        u, t = s.split("@")
        return int(u), float(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID@T with T in simulation seconds (e.g. 2@15), got {s!r}") from None


def add_arguments(p):
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", help="scenario TOML (simulated once for the run)")
    src.add_argument("--dataset", help="dataset directory to replay")
    p.add_argument("--algo", default="atvfg", help="estimator hosted by every node: atvfg (default), atvfg_paper, fg, fkf or ins")
    p.add_argument("--seed", type=int, default=None, help="run seed (default: the config's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set",
                   help="override a config field before validation (repeatable), e.g. --set swarm.n_uavs=100 "
                        "--set scenario.duration_s=60 (configs/scale.toml is made for this)")
    p.add_argument("--kill", type=_fault, action="append", default=[], metavar="ID@T", help="SIGKILL UAV ID's process at sim time T")
    p.add_argument("--restart", type=_fault, action="append", default=[], metavar="ID@T", help="restart UAV ID's process at sim time T")
    p.add_argument("--rate", type=float, default=None, help="real-time factor instead of lockstep")
    p.add_argument("--out", default=None, help="run directory (default runs/<timestamp>-<scenario>/ + runs/latest); "
                   "refused if it already holds files (see --force)")
    p.add_argument("--force", action="store_true", help="clear an existing run directory given with --out first")
    p.add_argument("--insecure", action="store_true",
                   help="debugging only: plain TCP router, no authentication, no access control (default: mutual TLS + ACL)")
    p.add_argument("--live", action="store_true",
                   help="follow the run in a Rerun viewer while it records: the monitor serves the recording "
                        "over gRPC (--live-bind/--live-port); a viewer opens when there is a display, else a web "
                        "viewer is served on --web-port for a browser (swarm.rrd is written as always)")
    p.add_argument("--live-bind", default="127.0.0.1", metavar="ADDR",
                   help="address the live recording is served on (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--live-port", type=int, default=9876, metavar="PORT", help="gRPC port of the live recording (default 9876)")
    p.add_argument("--web-port", type=int, default=9090, metavar="PORT", help="port of the web viewer with --live (default 9090)")
    p.add_argument("--timeout", type=float, default=7200.0, help="wall-clock limit of the whole run (s)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--garbage-at", type=int, default=None, help=argparse.SUPPRESS)  # test hook


RUN_ARTEFACTS = {"report.json", "report.md", "swarm.rrd", "estimates.npz", "logs", "dataset", "security", "journal",
                 "figures", "recording", "swarm.rrd.partial"}


def prepare_run_dir(path: Path, force: bool) -> None:
    """Refuse a run directory that already holds files (a new run must never mix with an old one);
    ``force`` clears it first, but only when everything in it is a swarmnav run artefact."""
    from swarmnav.errors import SwarmnavError

    if path.exists() and not path.is_dir():
        raise SwarmnavError(f"--out {path}: exists and is not a directory; choose another --out")
    held = sorted(x.name for x in path.iterdir()) if path.is_dir() else []
    if not held:
        return
    if not force:
        raise SwarmnavError(f"--out {path} already holds a run ({', '.join(held[:6])}{', ...' if len(held) > 6 else ''}); "
                            "choose a new directory, or add --force to clear this one first")
    foreign = [h for h in held if h not in RUN_ARTEFACTS and not h.endswith((".rrd", ".log", ".png"))]
    if foreign:
        raise SwarmnavError(f"--out {path} holds files that are not a swarmnav run's ({', '.join(foreign[:6])}); "
                            "--force clears only run directories: choose another --out")
    import shutil

    for h in held:
        x = path / h
        shutil.rmtree(x) if x.is_dir() and not x.is_symlink() else x.unlink()


def check_algo(algo: str) -> None:
    """A launch hosts one per-UAV estimator in every node process: refuse anything else up front."""
    from swarmnav.errors import SwarmnavError
    from swarmnav.estimators import registry

    nodes = [a for a in registry.known() if registry.kind(a) == "node"]
    if algo not in nodes:
        why = (" is the whole-swarm oracle: it runs in-process only (swarmnav evaluate --algos central)"
               if algo in registry.known() else " is not an estimator")
        raise SwarmnavError(f"--algo {algo!r}{why}; launch runs one of: {', '.join(nodes)}")


def check_schedule(kills, restarts, uavs: list[int], t_start: float, duration_s: float) -> None:
    """--kill/--restart: existing UAVs, times inside the scenario, a restart only after a kill."""
    from swarmnav.errors import SwarmnavError

    t_end = t_start + duration_s
    for flag, items in (("--kill", kills), ("--restart", restarts)):
        for u, t in items:
            if u not in uavs:
                raise SwarmnavError(f"{flag} {u}@{t:g}: UAV {u} does not exist (UAVs {uavs[0]}..{uavs[-1]})")
            if not t_start < t < t_end:
                raise SwarmnavError(f"{flag} {u}@{t:g}: T is simulation time and must lie inside the scenario "
                                    f"({t_start:g} < T < {t_end:g} s)")
    for u, t in restarts:
        if not any(ku == u and kt < t for ku, kt in kills):
            raise SwarmnavError(f"--restart {u}@{t:g}: UAV {u} is not killed before {t:g} s; add --kill {u}@T with T < {t:g}")


def check_live_ports(bind: str, live_port: int, web_port: int) -> None:
    """--live: ports in range, distinct and free on the bind address, before any work starts."""
    import socket

    from swarmnav.errors import SwarmnavError

    for flag, port in (("--live-port", live_port), ("--web-port", web_port)):
        if not 1 <= port <= 65535:
            raise SwarmnavError(f"{flag} {port}: a TCP port is 1..65535")
    if live_port == web_port:
        raise SwarmnavError(f"--live-port and --web-port are both {live_port}: choose two different ports")
    for flag, port in (("--live-port", live_port), ("--web-port", web_port)):
        with socket.socket(socket.AF_INET6 if ":" in bind else socket.AF_INET) as s:
            try:
                s.bind((bind, port))
            except OSError as e:
                raise SwarmnavError(f"{flag} {port}: cannot serve on {bind}:{port} ({e.strerror}; another viewer "
                                    f"or run?): choose a free port with {flag}, or --live-bind") from None


def run(args) -> int:
    from deploy.launcher import LaunchSpec, launch
    from swarmnav.dataset import Dataset
    from swarmnav.errors import SwarmnavError

    if args.rate is not None and not args.rate > 0:
        raise SwarmnavError(f"--rate {args.rate:g}: must be a real-time factor > 0 (e.g. --rate 1), or leave it out for lockstep")
    check_algo(args.algo)
    if not args.timeout > 0:
        raise SwarmnavError(f"--timeout {args.timeout:g}: the run's wall-clock limit must be > 0 s (default 7200)")
    if args.live:
        check_live_ports(args.live_bind, args.live_port, args.web_port)
    kills, restarts = list(args.kill), list(args.restart)
    sha = None
    if args.config:
        from swarmnav.sim import simulate

        sc = _checked_scenario(args, kills, restarts)
        seed = sc.scenario.seed if args.seed is None else args.seed
        name = sc.scenario.name
        sha = sc.sha256()
    else:
        if args.set:
            raise SwarmnavError("--set overrides a config's fields: use it with --config, not --dataset")
        ds = Dataset.read(args.dataset)
        name = ds.meta.name
        seed = args.seed if args.seed is not None else (ds.meta.seed or 0)
        check_schedule(kills, restarts, ds.meta.uav_ids(), ds.meta.t_start, ds.meta.duration_s)
    if seed < 0:
        raise SwarmnavError(f"--seed {seed}: seed must be >= 0")
    from ._checks import check_out_dir, make_out_dir

    if args.out:
        run_dir = Path(args.out)
        prepare_run_dir(check_out_dir(run_dir), args.force)
        make_out_dir(run_dir)
    else:
        run_dir = claim_default_run_dir(name)
    run_dir = run_dir.resolve()
    if args.config:
        t0 = time.perf_counter()
        ds = simulate(sc, seed)
        ds.write(run_dir / "dataset")
        dataset = run_dir / "dataset"
        print(f"simulated {name} seed {seed} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    else:
        dataset = Path(args.dataset).resolve()
    uavs = ds.meta.uav_ids()
    if not args.out:
        point_latest(run_dir)
    spec = LaunchSpec(run_dir=run_dir, dataset=dataset, seed=seed, algo=args.algo, uavs=uavs,
                      n_epochs=ds.meta.n_epochs(), kills=sorted(kills, key=lambda x: x[1]),
                      restarts=sorted(restarts, key=lambda x: x[1]), config_sha256=sha, rate=args.rate,
                      progress=not args.no_progress, timeout_s=args.timeout, secure=not args.insecure,
                      live=(args.live_bind, args.live_port) if args.live else None, web_port=args.web_port,
                      sim_extra=["--garbage-at", str(args.garbage_at)] if args.garbage_at else [])
    t0 = time.perf_counter()
    res = _launch_with_lookup_dirs(launch, spec, args.config)
    return finish_report(run_dir, res, time.perf_counter() - t0, ds.meta.duration_s)


def _checked_scenario(args, kills: list, restarts: list):
    """The config with ``--set`` applied, its process kills appended to ``kills`` / ``restarts``
    and the whole schedule checked; warns of a missing Δl file and of faults after the end."""
    from swarmnav.config import load_config
    from swarmnav.errors import SwarmnavError

    from services.settings import lookup_dirs, warn_missing_delta_l

    from ._checks import note_faults_after_end

    sc = load_config(args.config, args.set)
    for i, pk in enumerate(sc.faults.process_kill):
        for what, t in (("at_s", pk.at_s), ("restart_s", pk.restart_s)):
            if t is not None and not 0.0 < t < sc.scenario.duration_s:  # named as the config's, not as --kill
                raise SwarmnavError(f"faults.process_kill[{i}].{what} = {t:g} s (UAV {pk.uav}) lies outside the scenario "
                                    f"(0 < T < {sc.scenario.duration_s:g} s): move it, or run a longer scenario")
        kills.append((pk.uav, pk.at_s))
        if pk.restart_s is not None:
            restarts.append((pk.uav, pk.restart_s))
    check_schedule(kills, restarts, sc.uav_ids(), 0.0, sc.scenario.duration_s)
    warn_missing_delta_l(sc.estimation, "launch", lookup_dirs(args.config)[-2:])
    note_faults_after_end(sc, "launch")
    return sc


def _launch_with_lookup_dirs(launch, spec, config):
    """``launch(spec)`` with LOOKUP_DIRS_ENV set for its processes: the nodes and the monitor run in
    the repository and look a relative delta_l_file up where this command (and `evaluate`) does,
    so the two give the same Δl and the same numbers."""
    from services.settings import LOOKUP_DIRS_ENV, lookup_dirs

    old_dirs = os.environ.get(LOOKUP_DIRS_ENV)
    os.environ[LOOKUP_DIRS_ENV] = os.pathsep.join(str(d) for d in lookup_dirs(config))
    try:
        return launch(spec)
    finally:
        if old_dirs is None:
            os.environ.pop(LOOKUP_DIRS_ENV, None)
        else:
            os.environ[LOOKUP_DIRS_ENV] = old_dirs


def finish_report(run_dir: Path, res, wall: float, duration_s: float) -> int:
    """Add the launcher's figures to report.json, print the summary and say in words whether the run
    is complete; the exit status is non-zero for any run that lost data or was stopped."""
    status = res.status
    print(f"\n{'process':<12} {'exit':>18}  note")
    from deploy.launcher import describe_exit

    for n, s in res.processes.items():
        note = ("stopped with the run" if n == "web_viewer" else "killed by schedule" if s["killed_by_schedule"]
                else "restarted" if s["earlier"] else "")
        print(f"{n:<12} {describe_exit(s['exit']):>18}  {note}")
    rp = run_dir / "report.json"
    covered_s = duration_s if not res.stop_reason else None  # simulated seconds the run got through
    if rp.is_file():
        from swarmnav.report import events_text, summary_table

        rep = json.loads(rp.read_text())
        if res.stop_reason and rep.get("epochs_expected"):
            covered_s = duration_s * (rep.get("epochs_recorded") or 0) / rep["epochs_expected"]
        rep.setdefault("distributed", {})["wall_s"] = wall
        rep["distributed"]["realtime_factor"] = covered_s / wall if wall > 0 and covered_s is not None else None
        rep["distributed"]["processes"] = res.processes
        rep["distributed"]["stop_reason"] = res.stop_reason
        rep.setdefault("security", res.security)
        if res.events:
            rep["events"] = sorted(rep.get("events", []) + res.events, key=lambda e: (e.get("t", 0), e.get("kind", "")))
        if res.stop_reason:
            rep["complete"] = False
        rp.write_text(json.dumps(rep, indent=1) + "\n")
        print(summary_table(rep))
        print(events_text(rep.get("events", [])))
        if rep.get("complete") is not True:
            status = status or 1
            miss = rep.get("missing_by_uav") or {}
            lost = ", ".join(f"UAV {u}: {n}" for u, n in sorted(miss.items(), key=lambda x: int(x[0])) if n)
            print(f"INCOMPLETE RUN: {rep.get('estimates_received')} of {rep.get('estimates_expected')} expected estimates "
                  f"received over {rep.get('epochs_recorded')} of {rep.get('epochs_expected')} epochs"
                  + (f"; missing {lost}" if lost else "") + (f"; {res.stop_reason}" if res.stop_reason else "")
                  + ". The figures above cover only what was received.", file=sys.stderr)
        else:
            print("complete: every expected estimate of every epoch was received")
    else:
        print("no report.json was written (see the logs)" + (f"; {res.stop_reason}" if res.stop_reason else ""), file=sys.stderr)
        status = status or 1
    speed = (f"{covered_s / wall:.1f}x real time" + (f" over the {covered_s:g} s it got through" if res.stop_reason else "")
             if covered_s is not None and wall > 0 else "stopped early")
    print(f"run directory: {run_dir} ({wall:.1f} s wall, {speed})")
    return status
