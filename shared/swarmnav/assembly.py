"""The one assembly of report.json: :func:`assemble_report`. Pure (arrays and dicts in, a dict out).

Both producers of a report call it with what they hold, so an in-process evaluation and a
distributed run of the same seed give the same keys and the same numbers:

- ``swarmnav evaluate`` (services/commands/evaluate.py): the :class:`RunResult` of every algorithm
  and seed it ran, mode ``"in-process"``;
- the monitor (services/monitor/core.py, also ``swarmnav report RUN_DIR``): the estimates the nodes
  published, gathered into one :class:`RunResult`, mode ``"distributed"``, plus what only a
  distributed run knows (events, rejected messages, scheduled kill windows, lost epochs).

Thresholds are the ones the estimators *used*: every estimate carries the Δl/Δh its node applied
(``NodeEstimate.delta_l_m``/``delta_h_m``, on the wire in ``EstimateMsg``), so the report never
quotes the settings file when the estimator fell back to another value (graph.py uses the trained
Δl only on data with the ranging σ it was trained at). ``thresholds.delta_l_m`` (the headline) =
``thresholds.delta_l_used_m`` = the median over UAV-epochs of what the headline algorithm
(``atvfg`` if it ran, else the first that reported a Δl) used; ``delta_l_used_by_uav_m`` per UAV;
``delta_l_configured_m`` what the settings held. Every algorithm that reported a Δl gets its own
``thresholds`` block and ``detection`` scores.

Adding a field: compute it here from ``runs``/``truths``/``labels`` (per-algorithm blocks come from
:func:`swarmnav.metrics.algorithm_metrics`, so a field added there reaches both reports), never in
one caller only. Keep it quick: a stopped distributed run must write its report inside the
launcher's SIGTERM grace (4 s for the monitor); the monitor runs it once on two epochs at start-up
(``MonitorCore._warm_report``) so lazy imports (e.g. scipy.stats) are paid before.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from . import metrics
from .scenario import evaluation_block
from .evaluation import FAULT_RULE, RunResult, Truth
from .report import build_report

HEADLINE_ALGO = "atvfg"  # the algorithm whose thresholds and single-threshold detection lead the report


def _used(values: np.ndarray) -> float | None:
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    return float(np.median(v)) if len(v) else None


def threshold_block(rs: Sequence[RunResult]) -> dict | None:
    """The Δl/Δh an algorithm's estimators reported over its runs (None if they reported no Δl):
    {"delta_l_used_m", "delta_l_used_by_uav_m": {"<id>": m}, "delta_h_m": {"p50", "p95"}}."""
    dl = np.concatenate([r.delta_l_m.ravel() for r in rs]) if rs else np.zeros(0)
    used = _used(dl)
    if used is None:
        return None
    by_uav = {}
    for j, u in enumerate(rs[0].uavs):
        v = _used(np.concatenate([r.delta_l_m[:, j] for r in rs]))
        if v is not None:
            by_uav[str(int(u))] = v
    dh = metrics.percentiles(np.concatenate([r.delta_h_m.ravel() for r in rs]), (50, 95))
    return {"delta_l_used_m": used, "delta_l_used_by_uav_m": by_uav, "delta_h_m": dh}


def completeness(runs: Mapping[str, Sequence[RunResult]], excused: Sequence[np.ndarray] | None = None,
                 done: bool = True, lost_epochs: Sequence[int] = (), conflicts: int = 0) -> dict:
    """The completeness fields (report.json top level), over every algorithm and seed: an estimate is expected
    from every UAV at every epoch except where ``excused[seed index]`` (K x N, scheduled kill windows)
    is true; ``complete`` only if every expected estimate is there, the run reached its end
    (``done``), no epoch was lost and no estimate conflicted with another."""
    exp_n = got_n = 0
    recorded = 0
    missing: dict[str, int] = {}
    for rs in runs.values():
        for i, r in enumerate(rs):
            got = np.isfinite(r.pos[..., 0])
            exp = ~np.asarray(excused[i], bool) if excused is not None else np.ones_like(got)
            miss = exp & ~got
            exp_n += int(exp.sum())
            got_n += int((got & exp).sum())
            recorded = max(recorded, int(got.any(axis=1).sum()))
            for j, u in enumerate(r.uavs):
                missing[str(int(u))] = missing.get(str(int(u)), 0) + int(miss[:, j].sum())
    K = max((len(r.t) for rs in runs.values() for r in rs), default=0)
    complete = bool(done and exp_n == got_n and not lost_epochs and not conflicts)
    return {"complete": complete, "epochs_expected": int(K), "epochs_recorded": recorded,
            "estimates_expected": exp_n, "estimates_received": got_n, "missing_by_uav": missing,
            "epochs_lost": sorted(int(k) for k in lost_epochs), "conflicting_estimates": int(conflicts)}


def _range_nis(meta, rs: Sequence[RunResult], ranges: Sequence) -> dict:
    """metrics.nis_summary of every seed's ranges against that seed's prior estimates."""
    tags = {int(n.id): {int(g): tuple(v) for g, v in n.tags.items()} for n in meta.nodes}
    anchors = meta.anchors()
    vals, labs = [np.zeros(0)], [np.zeros(0, int)]
    for r, rg in zip(rs, ranges):
        if len(rg["t"]) == 0:
            continue
        thr = meta.fault_threshold_for(np.asarray(rg["sigma"], float))
        v, lab = metrics.range_nis_values(r.t, r.uavs, r.pos, r.vel, r.pos_cov, r.quat, rg, tags, anchors, thr)
        vals.append(v)
        labs.append(lab)
    return metrics.nis_summary(np.concatenate(vals), np.concatenate(labs))


def assemble_report(*, mode: str, meta, seeds: Sequence[int], runs: Mapping[str, Sequence[RunResult]], truths: Sequence[Truth],
                    labels: Sequence[np.ndarray], settings: Mapping, provenance: dict, source: str,
                    events: Sequence[dict] = (), failed: Mapping[str, str] | None = None,
                    excused: Sequence[np.ndarray] | None = None, done: bool = True, lost_epochs: Sequence[int] = (),
                    conflicts: int = 0, rejected: Mapping[str, int] | None = None, extra: Mapping | None = None,
                    ranges: Sequence | None = None) -> dict:
    """report.json of a run (see the module docstring).

    ``runs[algo]``: one :class:`RunResult` per seed of ``seeds``, in the order of ``truths`` and ``labels``
    (:func:`swarmnav.evaluation.truth_at_epochs` / :func:`~swarmnav.evaluation.link_labels` of that
    seed's dataset), with ``links`` filled; ``meta`` the (first) dataset's metadata; ``settings`` the
    estimator settings the runs used (``delta_l_file``, a path, is left out); ``source`` "config" or
    "dataset"; ``failed`` {"algo/seedN": error} of runs that did not finish. Distributed runs add
    ``excused`` (per seed, K x N: scheduled kill windows), ``done``, ``lost_epochs``, ``conflicts``,
    ``rejected`` and ``extra`` (keys only they have, e.g. ``security``, ``distributed``; never
    overriding a key computed here). ``ranges``: each seed's ranges table; with it every algorithm
    gets ``range_nis`` (NIS of the ranges against the prior estimates, no truth needed: _range_nis).
    """
    for a, rs in runs.items():
        if [int(r.seed) for r in rs] != [int(s) for s in seeds]:
            raise ValueError(f"{a}: runs of seeds {[r.seed for r in rs]}, expected {list(seeds)}")
    windows = list(meta.gnss_outages or [])
    blocks: dict[str, dict] = {}
    thresholds: dict[str, dict] = {}
    detections: dict[str, tuple] = {}
    for a, rs in runs.items():
        rs = list(rs)
        if len(rs) != len(truths) or len(rs) != len(labels):
            raise ValueError(f"{a}: {len(rs)} runs for {len(truths)} truths and {len(labels)} label sets")
        blocks[a], th, dets = _algorithm_block(rs, truths, labels, meta, windows, ranges)
        if th is not None:
            thresholds[a], detections[a] = th, dets
    head = HEADLINE_ALGO if HEADLINE_ALGO in thresholds else next(iter(thresholds), None)
    det, single = detections.get(head, (None, None)) if head else (None, None)
    configured = settings.get("delta_l_m")
    th_head = thresholds.get(head) if head else None
    used = th_head["delta_l_used_m"] if th_head else None
    comp = completeness(runs, excused, done, lost_epochs, conflicts)
    if failed:  # a run that did not finish is missing from the tables: the report is not complete
        comp["complete"] = False
    ex = {**comp, "rejected": dict(rejected or {}), "source": source, "failed": dict(failed or {}),
          "gnss_outages": [w.model_dump() if hasattr(w, "model_dump") else dict(w) for w in windows],
          "fault_threshold_m": meta.fault_threshold_m, "fault_threshold_rule": FAULT_RULE,
          "settings": {k: v for k, v in settings.items() if k != "delta_l_file"},
          # the scenario's [evaluation] seeds and whether these are report or tuning seeds
          "evaluation": evaluation_block((getattr(meta, "config", None) or {}).get("evaluation"), seeds)}
    for k, v in (extra or {}).items():
        ex.setdefault(k, v)
    rep = build_report(mode=mode, scenario=meta.name, seeds=seeds, n_uavs=len(meta.uav_ids()),
                       duration_s=meta.duration_s, algorithms=blocks, detection=det, detection_single=single,
                       delta_l_m=used, delta_h_m=th_head["delta_h_m"] if th_head else {"p50": None, "p95": None},
                       provenance=provenance, events=sorted(events, key=lambda e: e["t"]), extra=ex)
    rep["thresholds"].update({
        "delta_l_used_m": used,
        "delta_l_used_by_uav_m": dict(th_head["delta_l_used_by_uav_m"]) if th_head else {},
        "delta_l_algorithm": head,
        "delta_l_configured_m": configured,
        "delta_l_source": _delta_l_source(used, configured),
    })
    return rep


def _algorithm_block(rs: list[RunResult], truths: Sequence[Truth], labels: Sequence[np.ndarray], meta, windows: list,
                     ranges: Sequence | None) -> tuple[dict, dict | None, tuple | None]:
    """One algorithm's report block over its seeds' runs, with its Δl/Δh thresholds and detection
    scores (None for an algorithm that classifies no links). -> (block, thresholds, detection_report)."""
    tr0 = truths[0]
    b = metrics.algorithm_metrics(tr0.uavs, tr0.t, [r.pos - t.pos for r, t in zip(rs, truths)],
                                  [r.vel - t.vel for r, t in zip(rs, truths)], [r.pos_cov for r in rs],
                                  [r.step_ms for r in rs], windows)
    got = np.concatenate([np.isfinite(r.pos[..., 0]).ravel() for r in rs])
    rounds = np.concatenate([np.asarray(r.rounds, float).ravel() for r in rs])[got]
    b["rounds_mean"] = float(np.mean(rounds)) if len(rounds) else None
    wall = float(sum(r.wall_s for r in rs))
    if wall > 0:
        b["wall_s"] = wall
    th = threshold_block(rs)
    dets = None
    if th is not None:
        b["thresholds"] = th
        lk, lb = [], []
        for i, (r, lab) in enumerate(zip(rs, labels)):  # epochs made unique across seeds
            off = i * (len(r.t) + 1)
            x, y = r.links.copy(), np.asarray(lab).copy()
            x["k"] += off
            y["k"] += off
            lk.append(x)
            lb.append(y)
        dets = metrics.detection_report(np.concatenate(lk), np.concatenate(lb), meta.fault_threshold_m)
        b["detection"] = dets[0]  # (build_report sets atvfg's to the same scores)
    if ranges is not None:
        b["range_nis"] = _range_nis(meta, rs, ranges)
    return b, th, dets


def _delta_l_source(used: float | None, configured) -> str:
    """Where the headline algorithm's Δl came from: the delta_l_file, the estimator's fallback, or nowhere."""
    if used is None:
        return "not used (no algorithm that ran reported a Δl)"
    if configured is not None and abs(used - float(configured)) <= 1e-12 * max(1.0, abs(used)):
        return "delta_l_file"
    return "estimator fallback: delta_l_fallback_sigmas x the data's ranging sigma"
