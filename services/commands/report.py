"""`swarmnav report RUN_DIR`: rebuild a distributed run's outputs from what is on disk.

Replays the monitor's journal (``RUN_DIR/journal/monitor.jnl``: every estimate, clock message and
event it accepted, flushed per record) through the same code the live monitor runs
(services/monitor/core.py) and writes report.json, report.md, estimates.npz and a fresh, valid
``swarm.rrd``. Use it after a monitor crash (SIGKILL, power loss), or to re-score a run. A run whose
journal ends before the clock's ``done`` is reported as incomplete, with a ``monitor_lost`` event.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

HELP = "rebuild report.json, report.md and a valid .rrd of a distributed run from its journal (after a crash)"
DESCRIPTION = HELP + """

example:
  swarmnav report runs/latest
"""

DERIVED = {"epochs_lost", "scheduled_kill", "scheduled_restart", "rebootstrap", "rejected_messages"}


def add_arguments(p):
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory written by `swarmnav launch` (holds journal/monitor.jnl)")


def rebuild(run_dir: Path) -> dict:
    from services import recording as R
    from services.monitor import journal as J
    from services.monitor.core import MonitorCore
    from swarmnav.errors import SwarmnavError
    from swarmnav.wire import messages as M

    jp = J.journal_path(run_dir)
    if not jp.is_file():
        raise SwarmnavError(f"{run_dir}: no monitor journal ({jp.relative_to(run_dir)}); is this a `swarmnav launch` run directory?")
    records = list(J.read_journal(jp))
    if not records or records[0][0] != J.HEADER:
        raise SwarmnavError(f"{jp}: no run header (the monitor died before it started): nothing to rebuild")
    h = json.loads(records[0][1])
    ds = Path(h["dataset"])
    if not ds.is_dir() and (run_dir / "dataset").is_dir():
        ds = run_dir / "dataset"
    if not ds.is_dir():
        raise SwarmnavError(f"the run's dataset {h['dataset']} is gone; put it back (or at {run_dir / 'dataset'}) and retry")
    tmp = run_dir / "swarm.rrd.rebuild"
    from services.monitor.core import LINK_ALGOS

    sink = R.FileRecording(tmp, recording_id=h["run"],
                           blueprint=R.default_blueprint([h["algo"]], [h["algo"]] if h["algo"] in LINK_ALGOS else [],
                                                         R.dataset_has_anchors(ds)))
    core = MonitorCore(run=h["run"], dataset=ds, seed=h["seed"], algo=h["algo"], out=run_dir, sink=sink,
                       kills=h.get("kills", []), restarts=h.get("restarts", []), security=h.get("security"),
                       config_sha256=h.get("config_sha256"))
    rejected: dict[str, int] = {}
    for kind, payload in records[1:]:
        try:
            if kind == J.ESTIMATE:
                core.on_estimate(M.decode(M.EstimateMsg, payload))
            elif kind == J.CLOCK:
                core.on_clock(M.decode(M.ClockMsg, payload))
            elif kind == J.EVENT:
                ev = json.loads(payload)
                if ev.get("kind") == "_rejected":
                    rejected = dict(ev.get("counts", {}))
                elif ev.get("kind") not in DERIVED:
                    extra = {k: v for k, v in ev.items() if k not in ("t", "kind", "uav")}
                    core.event(ev["kind"], ev.get("uav", 0), t=ev.get("t"), **extra)
                    if ev.get("kind") == "conflicting_estimates":  # the live monitor saw two senders: never complete
                        core.conflicts += 1
                        core.conflicting.add(int(ev.get("uav", 0)))
        except M.WireError:
            continue  # journalled only after validation: a record that fails now is corrupt, skip it
    for key in sorted(rejected):
        if key not in core.rejected and ":" in key and not key.startswith("uav"):
            core.event("rejected_messages", 0, detail=key)
    core.rejected.update(rejected)
    if not core.done:
        core.event("monitor_lost", 0, detail=f"the journal ends at epoch {core.k_now}: the monitor stopped before the run ended")
    rep = core.finish()
    os.replace(tmp, run_dir / "swarm.rrd")
    import shutil

    shutil.rmtree(run_dir / "recording", ignore_errors=True)  # the live segments: all in swarm.rrd now
    return rep


def run(args) -> int:
    from swarmnav.errors import SwarmnavError
    from swarmnav.report import completeness_text, summary_table

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise SwarmnavError(f"{run_dir}: not a directory; give a run directory, e.g. runs/latest")
    rep = rebuild(run_dir.resolve())
    print(summary_table(rep))
    print(completeness_text(rep).replace("**", ""))
    print(f"rebuilt {run_dir}/report.json, report.md, estimates.npz and swarm.rrd from the monitor's journal")
    return 0
