"""Passive listening: ``uwb_passive.csv`` of every robot (a third tag overhearing a two-way ranging
transaction) -> range differences, the ``tdoa`` table.

A row is logged by several robots (identical values): deduplicated on (listener, initiator,
responder, transaction time). Dropped, and counted in the summary: rows outside the span, a
listener that is not a robot's tag or is one of the transaction's own tags, non-finite values, a
clock-rate ratio beyond 1 ± PASSIVE_MAX_SKEW, and range differences that break the triangle
inequality |d(R,L) − d(I,L)| <= d(I,R) by more than 3 σ. Time = the transaction's timestamp
(``timestamp_n``, the active range's, which the row overheard); σ = the row's ``std`` (the
recording's median range std where it is missing or not positive). Label NLOS_REAL where the
error against mocap exceeds 3 σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarmnav.dataset import FaultKind
from swarmnav.errors import DatasetError

from .constants import ANCHOR_NODE_OFFSET, PASSIVE_MAX_SKEW, PASSIVE_WRAP_NS, SPEED_OF_LIGHT_M_PER_NS
from .ranges import unknown_id
from .readers import read_csv
from .series import Span
from .truth import TagTruth

PASSIVE_COLS = ["my_id", "from_id", "to_id", "rx1", "rx2", "rx3", "rx1_n", "tx2_n", "tx3_n", "range_n", "std", "timestamp_n"]


def passive_rdiff(c: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Range difference d(resp, listener) − d(init, listener) [m] of passive-listening rows, and
    the listener/responder clock-rate ratio (for the sanity check).

    MILUV's two-way ranging (``*_n`` = the overheard active transaction): the initiator I sends a
    poll at tx1 (I's clock), the responder R receives it at rx1_n and sends two messages at tx2_n,
    tx3_n (R's clock). The listener L receives the three at rx1, rx2, rx3 (L's clock). In R's clock,
    rx2 − rx1 = (tx2_n − rx1_n) + ToF(I,R) + (d(R,L) − d(I,L))/c, with L's intervals converted to
    R's clock by the ratio (tx3_n − tx2_n)/(rx3 − rx2) (two messages from R on the same path), and
    c·ToF(I,R) = the transaction's calibrated range ``range_n``. Intervals modulo the counter wrap.
    """
    w = PASSIVE_WRAP_NS
    d_l12 = np.mod(c["rx2"] - c["rx1"], w)
    d_l23 = np.mod(c["rx3"] - c["rx2"], w)
    d_r = np.mod(c["tx3_n"] - c["tx2_n"], w)
    reply = np.mod(c["tx2_n"] - c["rx1_n"], w)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = d_r / d_l23
        rdiff = SPEED_OF_LIGHT_M_PER_NS * (d_l12 * ratio - reply) - c["range_n"]
    return rdiff, ratio


@dataclass
class PassiveLog:
    """Kept rows: (listener, initiator, responder tag, time) -> (rdiff, sigma)."""

    seen: dict[tuple[int, int, int, float], tuple[float, float]] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("outside_span", "not_a_listener", "invalid", "clock_ratio", "triangle", "no_ids", "robot_not_here"), 0))
    n_logged: int = 0
    n_dup: int = 0


def read_passive(src: Path, robots: list[tuple[str, int]], tag_owner: dict[int, int], span: Span,
                 sigma_nominal: float, used_files: list[Path], absent_tags: dict[int, str] | None = None
                 ) -> PassiveLog | None:
    """Every robot's ``uwb_passive.csv``, checked and deduplicated; None if no robot has the file.
    Rows with a tag of a robot without a folder here (``absent_tags``) are counted and dropped."""
    log, any_file = PassiveLog(), False
    absent_tags = absent_tags or {}
    for name, _ in robots:
        p = src / name / "uwb_passive.csv"
        if not p.is_file():
            continue
        any_file = True
        used_files.append(p)
        c = read_csv(p, PASSIVE_COLS)
        rdiff, ratio = passive_rdiff(c)
        for i in range(len(c["timestamp_n"])):
            log.n_logged += 1
            ids = (c["my_id"][i], c["from_id"][i], c["to_id"][i])
            if not all(math.isfinite(x) for x in ids):
                log.dropped["no_ids"] += 1
                continue
            if not all(x == int(x) for x in ids):
                raise DatasetError(f"{p}: row {i + 2}: my_id/from_id/to_id not integers {ids}")
            key = (*(int(x) for x in ids), float(c["timestamp_n"][i]))
            if any(tg not in tag_owner and tg in absent_tags for tg in key[:3]):
                log.dropped["robot_not_here"] += 1
                continue
            for tg in key[:3]:
                if tg not in tag_owner:
                    raise unknown_id(p, i + 2, tg, tag_owner)
            z, sd = float(rdiff[i]), float(c["std"][i])
            why = _drop_reason(key, z, float(c["range_n"][i]), float(ratio[i]), sd, tag_owner, span, sigma_nominal)
            if why:
                log.dropped[why] += 1
                continue
            if key in log.seen:
                log.n_dup += 1
                if abs(log.seen[key][0] - z) > 1e-9:
                    raise DatasetError(f"{p}: row {i + 2}: passive row {key} also logged by another robot with a different value")
                continue
            log.seen[key] = (z, sd if math.isfinite(sd) and sd > 0 else sigma_nominal)
    return log if any_file else None


def _drop_reason(key: tuple[int, int, int, float], z: float, rng: float, ratio: float, sd: float,
                 tag_owner: dict[int, int], span: Span, sigma_nominal: float) -> str | None:
    """Why a passive row is not kept (a key of PassiveLog.dropped), None to keep it."""
    lt, it, rt, ts = key
    if not (math.isfinite(ts) and span.t_start < ts <= span.t_end):
        return "outside_span"
    if tag_owner[lt] >= ANCHOR_NODE_OFFSET or lt in (it, rt):
        return "not_a_listener"
    if not (math.isfinite(z) and math.isfinite(rng) and rng > 0):
        return "invalid"
    if abs(ratio - 1.0) > PASSIVE_MAX_SKEW:
        return "clock_ratio"
    sd = sd if math.isfinite(sd) and sd > 0 else sigma_nominal
    if abs(z) > rng + 3 * sd:
        return "triangle"
    return None


def tdoa_table(log: PassiveLog, tag_owner: dict[int, int], truth: TagTruth, summary: dict) -> dict[str, np.ndarray]:
    """The ``tdoa`` table of the kept rows, sorted, with their error against mocap as the label."""
    own = tag_owner
    keys = sorted(log.seen, key=lambda k: (k[3], own[k[0]], k[0], own[k[1]], k[1], own[k[2]], k[2]))
    lt, it, rt = (np.array([k[j] for k in keys], np.int64).reshape(-1) for j in range(3))
    ts = np.array([k[3] for k in keys], float)
    z = np.array([log.seen[k][0] for k in keys], float)
    sd = np.array([log.seen[k][1] for k in keys], float)
    owner = np.vectorize(tag_owner.__getitem__, otypes=[np.int64])
    nl, ni, nr = (owner(x) if len(x) else x for x in (lt, it, rt))
    pl, pi, pr = truth.positions(nl, lt, ts), truth.positions(ni, it, ts), truth.positions(nr, rt, ts)
    err = z - (np.linalg.norm(pr - pl, axis=1) - np.linalg.norm(pi - pl, axis=1))
    faulty = np.abs(err) > 3 * sd
    tab = {"t": ts, "node": nl, "tag": lt, "init": ni, "tag_init": it, "resp": nr, "tag_resp": rt, "rdiff": z, "sigma": sd,
           "fault_kind": np.where(faulty, int(FaultKind.NLOS_REAL), int(FaultKind.NONE)).astype(np.int64), "fault_err": err}
    summary["tdoa"] = {
        "logged_rows": log.n_logged, "duplicates_removed": log.n_dup, "kept": len(keys), "dropped": log.dropped,
        "with_anchor": int(((ni >= ANCHOR_NODE_OFFSET) | (nr >= ANCHOR_NODE_OFFSET)).sum()),
        "error_m": ({"median": round(float(np.median(err)), 4),
                     "robust_sigma": round(float(1.4826 * np.median(np.abs(err - np.median(err)))), 4)} if len(err) else None),
        "nlos_real_rows": int(faulty.sum()),
    }
    return tab
