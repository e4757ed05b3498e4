"""UWB two-way ranges: ``uwb_range.csv`` of every robot -> the ``ranges`` table.

An inter-UAV transaction is logged by both robots: rows are deduplicated on (timestamp, unordered
tag pair). sigma = the row's ``std`` (the recording's median std where missing); fault label
NLOS_REAL where |bias| > 3 sigma."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarmnav.dataset import FaultKind, epoch_of
from swarmnav.errors import DatasetError

from .constants import ANCHOR_NODE_OFFSET
from .readers import read_csv, warn
from .series import Span
from .truth import TagTruth

RANGE_COLS = ["timestamp", "from_id", "to_id", "range", "gt_range", "bias", "std"]
SIGMA_FALLBACK_M = 0.19  # only if no row of the recording has a usable std


@dataclass
class RangeLog:
    """Transactions of all robots' logs: (t, min tag, max tag) -> ((from, to), (range, gt, bias, std))."""

    seen: dict[tuple[float, int, int], tuple] = field(default_factory=dict)
    n_logged: int = 0
    n_dup: int = 0
    n_bad_ids: int = 0  # rows without a timestamp or ids (empty/NaN): dropped
    absent: dict[str, int] = field(default_factory=dict)  # robot without a folder -> rows with one of its tags


def unknown_id(p: Path, line: int, tg: int, tag_owner: dict[int, int]) -> DatasetError:
    anchors = sorted(t for t, n in tag_owner.items() if n >= ANCHOR_NODE_OFFSET)
    tags = sorted(t for t, n in tag_owner.items() if n < ANCHOR_NODE_OFFSET)
    return DatasetError(f"{p}: row {line}: UWB id {tg} is neither an anchor of the experiment's constellation "
                        f"({anchors}, config/uwb/anchors.yaml + anchor_constellation in config/experiments.csv) nor a tag "
                        f"of a robot ({tags}, config/uwb/tags.yaml): is the config/ folder the one of this MILUV release?")


def read_ranges(src: Path, robots: list[tuple[str, int]], tag_owner: dict[int, int], used_files: list[Path],
                absent_tags: dict[int, str] | None = None) -> RangeLog:
    """Every robot's ``uwb_range.csv``, deduplicated (a copy must carry the same values). Rows with a
    tag of a robot listed in tags.yaml but without a folder here (``absent_tags``) are counted and dropped."""
    log = RangeLog()
    absent_tags = absent_tags or {}
    for name, _ in robots:
        p = src / name / "uwb_range.csv"
        if not p.is_file():
            continue
        used_files.append(p)
        c = read_csv(p, RANGE_COLS)
        for i in range(len(c["timestamp"])):
            log.n_logged += 1
            ts, fr, to = float(c["timestamp"][i]), c["from_id"][i], c["to_id"][i]
            if not (math.isfinite(fr) and math.isfinite(to) and math.isfinite(ts)):
                log.n_bad_ids += 1
                continue
            if fr != int(fr) or to != int(to):
                raise DatasetError(f"{p}: row {i + 2}: from_id/to_id not integers ({fr}, {to})")
            fr, to = int(fr), int(to)
            gone = [absent_tags[tg] for tg in (fr, to) if tg not in tag_owner and tg in absent_tags]
            if gone:
                log.absent[gone[0]] = log.absent.get(gone[0], 0) + 1
                continue
            for tg in (fr, to):
                if tg not in tag_owner:
                    raise unknown_id(p, i + 2, tg, tag_owner)
            key = (ts, min(fr, to), max(fr, to))
            vals = (c["range"][i], c["gt_range"][i], c["bias"][i], c["std"][i])
            if key in log.seen:
                log.n_dup += 1
                old = log.seen[key][1]
                if not np.allclose(old, vals, rtol=0, atol=1e-9, equal_nan=True):
                    raise DatasetError(f"{p}: row {i + 2}: transaction at t={ts} between {fr} and {to} also logged "
                                       f"by another robot with different values {old} vs {vals}")
                continue
            log.seen[key] = ((fr, to), vals, name)
    return log


def _rows_in_span(log: RangeLog, tag_owner: dict[int, int], span: Span) -> tuple[np.ndarray, dict]:
    """(n, 9) rows t, a, b, tag_a, tag_b, range, std, bias, gt_range (node a < node b), sorted; drop counts."""
    rows = []
    dropped = {"outside_span": 0, "invalid_range": 0, "no_std": 0}
    for (ts, _, _), ((fr, to), (rng, gt, bias, std), _) in log.seen.items():
        if not (span.t_start < ts <= span.t_end) or not math.isfinite(ts):
            dropped["outside_span"] += 1
            continue
        if not math.isfinite(rng) or rng <= 0:
            dropped["invalid_range"] += 1
            continue
        na, nb = tag_owner[fr], tag_owner[to]
        if na == nb:
            raise DatasetError(f"range between two tags ({fr}, {to}) of the same robot at t={ts}")
        ta, tb = (fr, to) if na < nb else (to, fr)
        rows.append((ts, min(na, nb), max(na, nb), ta, tb, rng, std, bias, gt))
    rows.sort(key=lambda r: (r[0], r[1], r[2], r[3], r[4]))
    return np.array(rows, float).reshape(-1, 9), dropped


def ranges_table(log: RangeLog, tag_owner: dict[int, int], span: Span, summary: dict
                 ) -> tuple[dict[str, np.ndarray], np.ndarray, float]:
    """The ``ranges`` table, the rows' ``gt_range`` and the recording's nominal sigma (median std) [m]."""
    R, dropped = _rows_in_span(log, tag_owner, span)
    std, bias = R[:, 6], R[:, 7]
    std_ok = np.isfinite(std) & (std > 0)
    sigma_nominal = float(np.median(std[std_ok])) if std_ok.any() else SIGMA_FALLBACK_M
    dropped["no_std"] = int((~std_ok).sum())  # kept, sigma = the median std
    sigma = np.where(std_ok, std, sigma_nominal)
    faulty = np.isfinite(bias) & (np.abs(bias) > 3 * sigma)
    threshold = 3 * sigma_nominal
    tab = {
        "t": R[:, 0], "a": R[:, 1].astype(np.int64), "b": R[:, 2].astype(np.int64),
        "tag_a": R[:, 3].astype(np.int64), "tag_b": R[:, 4].astype(np.int64),
        "range": R[:, 5], "sigma": sigma,
        "fault_kind": np.where(faulty, int(FaultKind.NLOS_REAL), int(FaultKind.NONE)).astype(np.int64),
        "fault_err": bias,
    }
    inter = tab["b"] < ANCHOR_NODE_OFFSET
    summary["ranges"] = {
        "logged_rows": log.n_logged, "duplicates_removed": log.n_dup, "transactions": len(log.seen), "kept": int(len(R)),
        "rows_without_ids": log.n_bad_ids, "rows_with_robots_not_here": dict(log.absent),
        "inter_uav": int(inter.sum()), "to_anchor": int((~inter).sum()), "dropped": dropped,
        "sigma_median_m": round(sigma_nominal, 4),
        "nlos_real_rows": int(faulty.sum()), "nlos_real_inter_uav": int((faulty & inter).sum()),
        "fault_threshold_m": round(threshold, 4),
        "rows_where_threshold_disagrees_with_per_row_rule": int(((np.abs(bias) > threshold) != faulty).sum()),
        "max_gap_s": round(float(np.diff(R[:, 0]).max()), 3) if len(R) > 1 else None,
    }
    return tab, R[:, 8], sigma_nominal


def range_truth_summary(tab: dict[str, np.ndarray], gt_range: np.ndarray, truth: TagTruth, span: Span,
                        epoch_dt: float, summary: dict) -> None:
    """Motion inside the epoch (change of the true range from the range's time to its epoch's
    time) and our mocap truth vs the recording's ``gt_range``, into ``summary["ranges"]``."""
    t = tab["t"]
    if not len(t):
        return
    t_ep = span.t_start + epoch_of(t, span.t_start, epoch_dt) * epoch_dt
    d_now = truth.distance(tab["a"], tab["tag_a"], tab["b"], tab["tag_b"], t)
    d_ep = truth.distance(tab["a"], tab["tag_a"], tab["b"], tab["tag_b"], t_ep)
    dd = np.abs(d_ep - d_now)
    summary["ranges"]["range_change_to_epoch_end_m"] = {"p50": round(float(np.median(dd)), 4),
                                                        "p95": round(float(np.percentile(dd, 95)), 4),
                                                        "max": round(float(dd.max()), 4)}
    ok = np.isfinite(gt_range)
    summary["ranges"]["our_truth_minus_gt_range_m"] = {"max_abs": round(float(np.abs(d_now[ok] - gt_range[ok]).max()), 4)}


GT_RANGE_TOL_M = 0.10  # median |our truth distance - the recording's gt_range| above which the config is wrong
GT_RANGE_WARN_M = 0.02


def check_config_against_gt_range(tab: dict[str, np.ndarray], gt_range: np.ndarray, truth: TagTruth, cfg: Path,
                                  exp: dict[str, str], summary: dict) -> None:
    """The config against the recording itself: MILUV computed each range's ``gt_range`` from mocap
    with the experiment's true anchor positions and lever arms, so the same distance from our mocap
    truth and config/ must agree (it does to 0.0 m on cirObstacles_3_random_0). A wrong
    anchor_constellation, anchors.yaml, tags.yaml or a time base shifted between uwb_range.csv and
    mocap.csv shows up here and would otherwise give quietly wrong anchors/labels: refused,
    naming the files."""
    ok = np.isfinite(gt_range)
    if not ok.any():
        summary["ranges"]["config_check"] = "skipped: no gt_range in uwb_range.csv"
        return
    d = np.abs(truth.distance(tab["a"], tab["tag_a"], tab["b"], tab["tag_b"], tab["t"]) - gt_range)
    groups = {f"anchor {int(b) - ANCHOR_NODE_OFFSET}": ok & (tab["b"] == b)
              for b in np.unique(tab["b"][tab["b"] >= ANCHOR_NODE_OFFSET])}
    groups["inter-UAV"] = ok & (tab["b"] < ANCHOR_NODE_OFFSET)
    med = {g: (round(float(np.median(d[m])), 4), int(m.sum())) for g, m in groups.items() if m.sum() >= 3}
    summary["ranges"]["config_check"] = {g: {"median_abs_m": v, "rows": n} for g, (v, n) in med.items()}
    bad = {g: v for g, v in med.items() if v[0] > GT_RANGE_TOL_M}
    if bad:
        which = "; ".join(f"{g}: median {v:.2f} m over {n} ranges" for g, (v, n) in bad.items())
        raise DatasetError(
            f"the config does not match the recording: the tag-to-tag/anchor distance from mocap and {cfg} differs from "
            f"uwb_range.csv's gt_range (which MILUV computed with the right geometry) — {which}. Check the experiment's "
            f"anchor_constellation ({exp.get('anchor_constellation')!r}) in {cfg / 'experiments.csv'}, the constellation in "
            f"{cfg / 'uwb' / 'anchors.yaml'}, the lever arms in {cfg / 'uwb' / 'tags.yaml'}, and that every file has the "
            "same time base")
    overall = float(np.median(d[ok]))
    if overall > GT_RANGE_WARN_M:
        warn(summary, f"distances from mocap + config differ from uwb_range.csv's gt_range by median {overall:.3f} m "
                      f"(usually 0): check {cfg}")
