"""report.json (the report contract: README "Quick start" file table, docs/results.md; schema "swarmnav.report/1") and report.md. Pure: dicts and strings.

:func:`build_report` assembles the dict from per-algorithm metric blocks (see
:func:`swarmnav.metrics.algorithm_metrics`) and what the caller measured (thresholds, detection,
provenance, events); :func:`validate_report` checks the contract's required keys;
:func:`render_markdown` lays it out like the paper's Table 2 (position RMSE per algorithm, E/N/U)
and Table 3 (normal vs GNSS-denied), plus our extra columns.
"""

from __future__ import annotations

import math

SCHEMA = "swarmnav.report/1"
ENU3 = ("e", "n", "u", "3d")
IMPROVEMENT_PAIRS = (("atvfg", "fg"), ("atvfg", "fkf"), ("atvfg", "ins"), ("atvfg", "central"))
ALGO_ORDER = ("fkf", "fg", "atvfg", "atvfg_paper", "ins", "central")  # the paper's Table 2 order first


def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars -> python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "item") and not isinstance(x, (str, bytes)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def build_report(*, mode: str, scenario: str, seeds: list[int], n_uavs: int, duration_s: float,
                 algorithms: dict[str, dict], detection: dict | None, detection_single: dict | None,
                 delta_l_m: float | None, delta_h_m: dict, provenance: dict, events: list[dict],
                 extra: dict | None = None) -> dict:
    """The report.json dict. ``algorithms[name]`` are metric blocks; ``detection`` (double threshold)
    is attached to ``atvfg`` only; improvement keys exist only when both algorithms ran."""
    from .metrics import improvement_pct

    if mode not in ("in-process", "distributed"):
        raise ValueError(f"mode must be 'in-process' or 'distributed', not {mode!r}")
    from .metrics import monte_carlo

    algos = {}
    per_seed = {}
    for name in sorted(algorithms, key=lambda a: (ALGO_ORDER.index(a) if a in ALGO_ORDER else 99, a)):
        block = dict(algorithms[name])
        ps = block.pop("per_seed_pos_rmse_3d_m", None)
        if ps is not None:
            per_seed[name] = list(ps)
        if name == "atvfg":
            block["detection"] = detection
        algos[name] = block
    imp = {}
    for a, b in IMPROVEMENT_PAIRS:
        if a in algos and b in algos:
            imp[f"{a}_vs_{b}"] = improvement_pct(algos[a]["pos_rmse_m"]["3d"], algos[b]["pos_rmse_m"]["3d"])
    rep = {
        "schema": SCHEMA,
        "mode": mode,
        "scenario": scenario,
        "seeds": [int(s) for s in seeds],
        "n_uavs": int(n_uavs),
        "duration_s": float(duration_s),
        "algorithms": algos,
        "improvement_pct": imp,
        "detection_single_threshold": detection_single,
        "thresholds": {"delta_l_m": delta_l_m, "delta_h_m": dict(delta_h_m)},
        # mean over seeds of the per-seed 3-D RMSE, Student-t CI, paired differences (metrics.monte_carlo)
        "monte_carlo": monte_carlo(seeds, per_seed),
        "provenance": provenance,
        "events": [{**e, "t": float(e["t"]), "kind": str(e["kind"]), "uav": int(e["uav"])} for e in events],
    }
    if extra:
        for k, v in extra.items():
            rep.setdefault(k, v)
    return _clean(rep)


def validate_report(rep: dict) -> list[str]:
    """Problems with ``rep`` against the report contract (empty list = valid)."""
    errs: list[str] = []

    def need(d, key, where):
        if not isinstance(d, dict) or key not in d:
            errs.append(f"missing {where}{key}")
            return None
        return d[key]

    for k in ("schema", "mode", "scenario", "seeds", "n_uavs", "duration_s", "algorithms", "improvement_pct",
              "detection_single_threshold", "thresholds", "provenance", "events"):
        need(rep, k, "")
    if rep.get("schema") != SCHEMA:
        errs.append(f"schema is {rep.get('schema')!r}, expected {SCHEMA!r}")
    if rep.get("mode") not in ("in-process", "distributed"):
        errs.append(f"mode {rep.get('mode')!r} invalid")
    if not isinstance(rep.get("seeds"), list) or not all(isinstance(s, int) for s in rep.get("seeds") or [None]):
        errs.append("seeds must be a non-empty list of int")
    for name, a in (rep.get("algorithms") or {}).items():
        w = f"algorithms.{name}."
        for blk in ("pos_rmse_m", "vel_rmse_mps", "uav1_pos_rmse_m"):
            d = need(a, blk, w)
            for ax in ENU3:
                if d is not None:
                    need(d, ax, f"{w}{blk}.")
        need(a, "per_uav_pos_rmse_m", w)
        for k in ("nees", "nees_mean", "nees_in_band_share"):  # consistency, navlie-style (None without covariance)
            need(a, k, w)
        st = need(a, "step_ms", w)
        if st is not None:
            need(st, "p50", f"{w}step_ms.")
            need(st, "p99", f"{w}step_ms.")
        for blk in ("outage_pos_rmse_m", "nominal_pos_rmse_m"):
            if blk in a:
                for ax in ENU3:
                    need(a[blk], ax, f"{w}{blk}.")
        if name == "atvfg":
            det = need(a, "detection", w)
            if det is not None:
                for k in ("precision", "recall", "false_alarm_rate"):
                    need(det, k, f"{w}detection.")
    algos = rep.get("algorithms") or {}
    for a, b in (("atvfg", "fg"), ("atvfg", "fkf")):
        key = f"{a}_vs_{b}"
        if a in algos and b in algos:
            need(rep.get("improvement_pct"), key, "improvement_pct.")
        elif key in (rep.get("improvement_pct") or {}):
            errs.append(f"improvement_pct.{key} present although {a} or {b} did not run")
    dst = rep.get("detection_single_threshold")
    if dst is not None:
        for k in ("precision", "recall", "false_alarm_rate"):
            need(dst, k, "detection_single_threshold.")
    th = rep.get("thresholds") or {}
    need(th, "delta_l_m", "thresholds.")
    need(th, "delta_l_used_m", "thresholds.")  # what the nodes used (None when no algorithm reported one)
    dh = need(th, "delta_h_m", "thresholds.")
    if dh is not None:
        need(dh, "p50", "thresholds.delta_h_m.")
        need(dh, "p95", "thresholds.delta_h_m.")
    pv = rep.get("provenance") or {}
    for k in ("git", "config_sha256", "packages"):
        need(pv, k, "provenance.")
    for i, e in enumerate(rep.get("events") or []):
        for k in ("t", "kind", "uav"):
            need(e, k, f"events[{i}].")
    return errs


# -- markdown -----------------------------------------------------------------------------------


def _f(x, nd=2) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        return f"{x:.{nd}f}"
    return str(x)


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.1f} %"


def render_markdown(rep: dict) -> str:
    """report.md: the human-readable view of report.json, one section per helper below."""
    algos = rep["algorithms"]
    L = _intro_md(rep)
    mc = rep.get("monte_carlo") or {}
    if (mc.get("n_seeds") or 0) >= 2:
        L.extend(monte_carlo_markdown(mc))
        L.append("")
    L.extend(_rmse_md(algos))
    if any("outage_pos_rmse_m" in a for a in algos.values()):
        L.extend(_outage_md(algos))
    if any(a.get("nees_mean") is not None for a in algos.values()):
        L.append("")
        L.extend(consistency_markdown(algos))
    if rep["improvement_pct"]:
        L.extend(_improvement_md(rep["improvement_pct"]))
    det = (algos.get("atvfg") or {}).get("detection")
    single = rep.get("detection_single_threshold")
    if det or single:
        L.extend(_detection_md(det, single))
    th = rep["thresholds"]
    L.append("")
    L.append(f"Thresholds: Δl = {_f(th['delta_l_m'], 3)} m; Δh p50 = {_f(th['delta_h_m'].get('p50'), 3)} m, "
             f"p95 = {_f(th['delta_h_m'].get('p95'), 3)} m." + _delta_l_note(th))
    L.append("")
    L.extend(_per_uav_md(algos))
    L.append("")
    L.extend(_run_md(rep))
    return "\n".join(L)


def _intro_md(rep: dict) -> list[str]:
    """Title, what was run, which seeds these are (report or tuning) and the oracle note."""
    L = [f"# swarmnav report — {rep['scenario']} ({rep['mode']})", "",
         f"Seeds {rep['seeds']}, {rep['n_uavs']} UAVs, {rep['duration_s']:g} s. "
         "RMSE pooled over UAVs, epochs and seeds (paper eq. 28; NEES and detection scoring: docs/estimators.md)."]
    ev = rep.get("evaluation")
    if ev:
        role = {"report": "the scenario's report seeds", "tuning": "**tuning seeds**: numbers not to report",
                "mixed": "**partly tuning seeds**: numbers not to report"}.get(ev.get("seeds_role"), "seeds the scenario names neither for tuning nor for reporting")
        L.append(f"These are {role} (settings tuned on seeds {_seed_text(ev.get('tuning_seeds') or [])}"
                 + (f" and on {', '.join(ev['tuning_scenarios'])}" if ev.get("tuning_scenarios") else "") + ").")
    if "central" in rep["algorithms"]:
        L.append("`central` is an **oracle**: one joint graph with the truly faulty links removed using the labels.")
    for run, why in sorted((rep.get("failed") or {}).items()):
        L.append(f"**FAILED, not in the tables: {run}** — {why}")
    L.append("")
    return L


def _rmse_md(algos: dict) -> list[str]:
    """Table 2 (position RMSE, NEES, step times) and the velocity RMSE table."""
    L = ["## Table 2 — position RMSE of each algorithm (m)", "",
         "| Algorithm | E | N | U | 3-D | UAV 1 E | UAV 1 N | UAV 1 U | UAV 1 3-D | vel 3-D (m/s) | NEES (3) | step p50 (ms) | step p99 (ms) |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, a in algos.items():
        p, u1, v = a["pos_rmse_m"], a["uav1_pos_rmse_m"], a["vel_rmse_mps"]
        L.append(f"| {name} | {_f(p['e'])} | {_f(p['n'])} | {_f(p['u'])} | **{_f(p['3d'])}** | {_f(u1['e'])} | "
                 f"{_f(u1['n'])} | {_f(u1['u'])} | {_f(u1['3d'])} | {_f(v['3d'], 3)} | {_f(a['nees'])} | "
                 f"{_f(a['step_ms']['p50'])} | {_f(a['step_ms']['p99'])} |")
    L += ["", "### Velocity RMSE (m/s)", "", "| Algorithm | E | N | U | 3-D |", "|---|---:|---:|---:|---:|"]
    for name, a in algos.items():
        v = a["vel_rmse_mps"]
        L.append(f"| {name} | {_f(v['e'], 3)} | {_f(v['n'], 3)} | {_f(v['u'], 3)} | {_f(v['3d'], 3)} |")
    return L


def _outage_md(algos: dict) -> list[str]:
    """Table 3: UAVs that lose GNSS, inside vs outside the outage windows."""
    L = ["", "## Table 3 — normal vs GNSS-denied (UAVs that lose GNSS; inside vs outside the outage windows)", "",
         "| Algorithm | pos normal E | N | U | 3-D | pos denied E | N | U | 3-D | denied/normal | vel normal 3-D | vel denied 3-D |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, a in algos.items():
        if "outage_pos_rmse_m" not in a:
            continue
        nm, ou = a["nominal_pos_rmse_m"], a["outage_pos_rmse_m"]
        ratio = (ou["3d"] / nm["3d"]) if (ou["3d"] is not None and nm["3d"]) else None
        vn = (a.get("nominal_vel_rmse_mps") or {}).get("3d")
        vo = (a.get("outage_vel_rmse_mps") or {}).get("3d")
        L.append(f"| {name} | {_f(nm['e'])} | {_f(nm['n'])} | {_f(nm['u'])} | {_f(nm['3d'])} | {_f(ou['e'])} | "
                 f"{_f(ou['n'])} | {_f(ou['u'])} | {_f(ou['3d'])} | {_f(ratio)} | {_f(vn, 3)} | {_f(vo, 3)} |")
    return L


def _improvement_md(improvement: dict) -> list[str]:
    L = ["", "## Improvement of atvfg (swarm 3-D position RMSE)", "", "| Comparison | Improvement | Paper |", "|---|---:|---:|"]
    paper = {"atvfg_vs_fg": "47.4 %", "atvfg_vs_fkf": "52.6 %"}
    for k, v in improvement.items():
        L.append(f"| {k.replace('_', ' ')} | {_f(v, 1)} % | {paper.get(k, '—')} |")
    return L


def _detection_md(det: dict | None, single: dict | None) -> list[str]:
    L = ["", "## Fault detection (atvfg), per link classification vs labels", "",
         "| Test | Precision | Recall | False-alarm rate | TP | FP | FN | TN |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, d in (("double threshold (H0 or H1)", det), ("single threshold at Δh (H0)", single)):
        if d:
            L.append(f"| {label} | {_pct(d['precision'])} | {_pct(d['recall'])} | {_pct(d['false_alarm_rate'])} | "
                     f"{d.get('tp', '—')} | {d.get('fp', '—')} | {d.get('fn', '—')} | {d.get('tn', '—')} |")
    return L


def _per_uav_md(algos: dict) -> list[str]:
    names = list(algos)
    ids = sorted({int(i) for a in algos.values() for i in a["per_uav_pos_rmse_m"]})
    L = ["## Per-UAV 3-D position RMSE (m)", "", "| UAV | " + " | ".join(names) + " |", "|---:|" + "---:|" * len(names)]
    for i in ids:
        L.append(f"| {i} | " + " | ".join(_f(algos[n]["per_uav_pos_rmse_m"].get(str(i))) for n in names) + " |")
    return L


def _run_md(rep: dict) -> list[str]:
    """Completeness (distributed runs), events and provenance."""
    L = []
    if "complete" in rep:
        L += ["## Completeness", "", completeness_text(rep), ""]
    L += ["## Events", ""]
    if rep["events"]:
        L += [f"- {event_line(e)}" for e in rep["events"]]
    else:
        L.append("none" + (" (process kills and restarts happen only in distributed runs)" if rep["mode"] == "in-process" else ""))
    pv = rep["provenance"]
    L += ["", "## Provenance", "", f"git `{pv.get('git')}`, config sha256 `{pv.get('config_sha256')}`", "",
          ", ".join(f"{k} {v}" for k, v in sorted((pv.get("packages") or {}).items())), ""]
    return L


def _ci(d: dict | None, nd: int = 3) -> str:
    if not d or d.get("mean") is None:
        return "—"
    if not d.get("ci95"):
        return _f(d["mean"], nd)
    lo, hi = d["ci95"]
    return f"{d['mean']:.{nd}f} [{lo:.{nd}f}, {hi:.{nd}f}]"


def monte_carlo_markdown(mc: dict) -> list[str]:
    """The Monte-Carlo headline as markdown lines: per algorithm the mean of the per-seed 3-D
    position RMSE with its 95 % CI, then the paired per-seed differences."""
    L = [f"## Monte Carlo over {mc['n_seeds']} seeds — 3-D position RMSE (m)", "",
         f"Seeds {_seed_text(mc.get('seeds') or [])}. Mean of the per-seed swarm 3-D RMSE with its 95 % "
         "confidence interval (Student t over seeds); paired = the difference of two algorithms on the same "
         "seed (negative: the first is better), its mean, 95 % CI and two-sided paired t-test p value.", "",
         "| Algorithm | n | mean [95 % CI] | std | min | max |", "|---|---:|---:|---:|---:|---:|"]
    for a, d in mc.get("per_algorithm", {}).items():
        v = [x for x in d.get("per_seed", {}).values() if x is not None]
        L.append(f"| {a} | {d['n']} | {_ci(d)} | {_f(d.get('std'), 3)} | {_f(min(v), 3) if v else '—'} | "
                 f"{_f(max(v), 3) if v else '—'} |")
    if mc.get("paired"):
        L += ["", "| Paired difference | n | mean [95 % CI] (m) | ratio mean [95 % CI] | first better | p |",
              "|---|---:|---:|---:|---:|---:|"]
        for k, d in mc["paired"].items():
            pv = "—" if d.get("p_value") is None else f"{d['p_value']:.2g}"
            L.append(f"| {k.replace('-', ' − ')} | {d['n']} | {_ci(d)} | {_ci(d.get('ratio'))} | "
                     f"{d.get('a_better_seeds', '—')}/{d['n']} | {pv} |")
    return L


def _seed_text(seeds: list[int]) -> str:
    if seeds and seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(str(s) for s in seeds)


def consistency_markdown(algos: dict) -> list[str]:
    """NEES consistency per algorithm (metrics.nees_consistency) as markdown lines."""
    band = next((a.get("nees_band") for a in algos.values() if a.get("nees_band")), None) or [0.216, 9.35]
    L = ["## Consistency — 3-D position NEES (expected 3)", "",
         f"In band: share of UAV-epochs whose NEES lies in the two-sided χ²(3) 95 % band [{band[0]:.3f}, {band[1]:.2f}] "
         "(expected 95 %); below = covariance too large (conservative), above = too small (overconfident). "
         "Mean bounds: the two-sided 95 % interval of the mean of M independent χ²(3) samples (optimistic: "
         "errors are correlated in time). Epochs in bounds: the NEES averaged over seeds × UAVs at each epoch "
         "against its own bounds (expected 95 %).", "",
         "| Algorithm | NEES mean | mean bounds | verdict | in band | below | above | epochs in bounds | samples |",
         "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    for name, a in algos.items():
        if a.get("nees_mean") is None:
            continue
        b = a.get("nees_mean_bounds") or [None, None]
        L.append(f"| {name} | {_f(a['nees_mean'], 2)} | [{_f(b[0], 2)}, {_f(b[1], 2)}] | {a.get('nees_verdict') or '—'} | "
                 f"{_pct(a.get('nees_in_band_share'))} | {_pct(a.get('nees_below_band_frac'))} | "
                 f"{_pct(a.get('nees_above_band_frac'))} | {_pct(a.get('nees_epochs_in_bounds_frac'))} | "
                 f"{a.get('nees_n', '—')} |")
    nis = {n: a["range_nis"] for n, a in algos.items() if (a.get("range_nis") or {}).get("nis_mean") is not None}
    if nis:
        lo, hi = next(iter(nis.values()))["nis_band"]
        L += ["", "Range NIS (needs no truth): each two-way range against the estimates of both ends at the epoch "
              f"before it (ν²/S, S = σ² + uᵀ(P_a + P_b)u; expected mean 1, median 0.455, 95 % in the χ²(1) band "
              f"[{lo:.4f}, {hi:.2f}]). Approximate: the two ends' cross-covariance is neglected (errors common to "
              "neighbours, e.g. a formation-wide shift, make S too large: NIS low) and so are the motion and "
              "process noise over the epoch (S too small: NIS high).", "",
              "| Algorithm | NIS mean | median | in band | below | above | ranges | rows |", "|---|---:|---:|---:|---:|---:|---:|---|"]
        for name, d in nis.items():
            L.append(f"| {name} | {_f(d['nis_mean'], 2)} | {_f(d['nis_median'], 3)} | {_pct(d['nis_in_band_share'])} | "
                     f"{_pct(d['nis_below_band_frac'])} | {_pct(d['nis_above_band_frac'])} | {d['nis_n']} | {d['nis_rows']} |")
    return L


def _delta_l_note(th: dict) -> str:
    """Where Δl came from (swarmnav.assembly: the value the estimators reported using)."""
    if "delta_l_used_m" not in th:
        return ""
    if th.get("delta_l_used_m") is None:
        return f" No algorithm that ran uses Δl (configured {_f(th.get('delta_l_configured_m'), 3)} m)."
    txt = f" Δl is the value the {th.get('delta_l_algorithm') or ''} estimators used"
    src = th.get("delta_l_source") or ""
    if src != "delta_l_file" and th.get("delta_l_configured_m") is not None:
        txt += f" ({src}; the settings' Δl, {_f(th['delta_l_configured_m'], 3)} m, did not apply)"
    by = sorted({round(v, 9) for v in (th.get("delta_l_used_by_uav_m") or {}).values()})
    if len(by) > 1:
        txt += f"; per UAV {_f(by[0], 3)}–{_f(by[-1], 3)} m"
    return txt + "."


def summary_table(rep: dict) -> str:
    """A compact fixed-width table for stdout."""
    hdr = f"{'algo':<11} {'pos3d[m]':>9} {'vel3d[m/s]':>10} {'uav1[m]':>8} {'NEES':>7} {'p50[ms]':>8} {'p99[ms]':>8}  detection P/R/FA"
    rows = [hdr, "-" * len(hdr)]
    for name, a in rep["algorithms"].items():
        det = a.get("detection")
        dtxt = "" if not det else f"{_pct(det['precision'])} / {_pct(det['recall'])} / {_pct(det['false_alarm_rate'])}"
        rows.append(f"{name:<11} {_f(a['pos_rmse_m']['3d']):>9} {_f(a['vel_rmse_mps']['3d'], 3):>10} "
                    f"{_f(a['uav1_pos_rmse_m']['3d']):>8} {_f(a['nees']):>7} {_f(a['step_ms']['p50']):>8} "
                    f"{_f(a['step_ms']['p99']):>8}  {dtxt}")
    s = rep.get("detection_single_threshold")
    if s:
        rows.append(f"single threshold at Δh: P/R/FA {_pct(s['precision'])} / {_pct(s['recall'])} / {_pct(s['false_alarm_rate'])}")
    for k, v in rep["improvement_pct"].items():
        rows.append(f"improvement {k}: {_f(v, 1)} %")
    mc = rep.get("monte_carlo") or {}
    if (mc.get("n_seeds") or 0) >= 2:
        rows.append(f"Monte Carlo over {mc['n_seeds']} seeds, mean per-seed 3-D RMSE [95 % CI] (m): "
                    + "; ".join(f"{a} {_ci(d)}" for a, d in mc["per_algorithm"].items()))
        for k, d in mc.get("paired", {}).items():
            rows.append(f"  paired {k}: {_ci(d)} m")
    return "\n".join(rows)


def event_line(e: dict) -> str:
    """One event in words: ``t = 15 s: dropout of UAV 2 (liveliness lost)``."""
    who = f" of UAV {e['uav']}" if int(e.get("uav", 0) or 0) > 0 else ""
    detail = f" ({e['detail']})" if e.get("detail") else ""
    return f"t = {float(e['t']):g} s: {e['kind'].replace('_', ' ')}{who}{detail}"


def events_text(events: list[dict]) -> str:
    if not events:
        return "events: none"
    return "events:\n" + "\n".join(f"  {event_line(e)}" for e in events)


def completeness_text(rep: dict) -> str:
    """The completeness fields of a distributed run's report in one sentence."""
    miss = {u: n for u, n in (rep.get("missing_by_uav") or {}).items() if n}
    rej = sum((rep.get("rejected") or {}).values())
    head = "**complete**" if rep.get("complete") else "**INCOMPLETE**"
    txt = (f"{head}: {rep.get('estimates_received')} of {rep.get('estimates_expected')} expected estimates, "
           f"{rep.get('epochs_recorded')} of {rep.get('epochs_expected')} epochs recorded")
    if miss:
        txt += "; missing " + ", ".join(f"UAV {u}: {n}" for u, n in sorted(miss.items(), key=lambda x: int(x[0])))
    if rep.get("conflicting_estimates"):
        txt += f"; {rep['conflicting_estimates']} CONFLICTING estimates (a second sender with a UAV's identity)"
    if rej:
        txt += f"; {rej} hostile or malformed messages rejected"
    sec = rep.get("security")
    if sec:
        txt += f"; security {sec.get('mode')}, ACL {'on' if sec.get('acl') else 'off'}"
    return txt + "."
