"""Ground truth from mocap: the truth table on a grid of the epochs, and the true position of any
UWB tag at any time (for the range and range-difference error labels)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Slerp

from .constants import ANCHOR_NODE_OFFSET, TRUTH_SUBSTEPS, VEL_HALF_WINDOW_S
from .nodes import Layout
from .series import Mocap, Span
from .tables import sorted_table


class TagTruth:
    """True tag positions from mocap (position linear, attitude slerped, clamped to the recording's
    ends) plus the body-frame lever arm; anchors at their surveyed positions."""

    def __init__(self, mocap: dict[int, Mocap], layout: Layout):
        self._mocap = mocap
        self._slerp = {uid: Slerp(m.t, m.att) for uid, m in mocap.items()}
        self._levers = layout.levers()
        self._anchors = layout.anchors

    def positions(self, node: np.ndarray, tag: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(n, 3) positions of tags ``tag`` of nodes ``node`` at times ``t`` (arrays of length n)."""
        node, tag, t = np.asarray(node, np.int64), np.asarray(tag, np.int64), np.asarray(t, float)
        out = np.empty((len(t), 3))
        for nd, tg in set(zip(node.tolist(), tag.tolist())):
            m = (node == nd) & (tag == tg)
            out[m] = self._one(nd, tg, t[m])
        return out

    def _one(self, node: int, tag: int, t: np.ndarray) -> np.ndarray:
        if node >= ANCHOR_NODE_OFFSET:
            return np.broadcast_to(np.asarray(self._anchors[node - ANCHOR_NODE_OFFSET], float), (len(t), 3))
        mc = self._mocap[node]
        p = np.column_stack([np.interp(t, mc.t, mc.pos[:, j]) for j in range(3)])
        C = self._slerp[node](np.clip(t, mc.t[0], mc.t[-1])).as_matrix()
        return p + C @ np.asarray(self._levers[node][tag], float)

    def distance(self, node_a, tag_a, node_b, tag_b, t) -> np.ndarray:
        """True tag-to-tag distances [m]."""
        return np.linalg.norm(self.positions(node_a, tag_a, t) - self.positions(node_b, tag_b, t), axis=1)


def truth_table(mocap: dict[int, Mocap], span: Span, epoch_dt: float, summary: dict) -> dict[str, np.ndarray]:
    """Mocap resampled to TRUTH_SUBSTEPS rows per epoch (the epoch times themselves bitwise
    ``meta.epoch_time(k)``): position linear, velocity by central differences over
    ±VEL_HALF_WINDOW_S, attitude slerped (w >= 0)."""
    n = span.n_epochs
    ks = np.repeat(np.arange(n + 1), TRUTH_SUBSTEPS)[: n * TRUTH_SUBSTEPS + 1]
    ms = np.tile(np.arange(TRUTH_SUBSTEPS), n + 1)[: n * TRUTH_SUBSTEPS + 1]
    grid = span.t_start + ks * epoch_dt + ms * (epoch_dt / TRUTH_SUBSTEPS)  # m == 0: bitwise meta.epoch_time(k)
    tt, tu, rows = [], [], []
    for uid, mc in sorted(mocap.items()):
        t, pos = mc.t, mc.pos
        gap = np.diff(t).max()
        if gap > 0.5:
            summary.setdefault("warnings", []).append(f"ifo{uid:03d} mocap gap {gap:.2f} s (interpolated)")
        P = np.column_stack([np.interp(grid, t, pos[:, j]) for j in range(3)])
        lo_t = np.maximum(grid - VEL_HALF_WINDOW_S, t[0])
        hi_t = np.minimum(grid + VEL_HALF_WINDOW_S, t[-1])
        Plo = np.column_stack([np.interp(lo_t, t, pos[:, j]) for j in range(3)])
        Phi = np.column_stack([np.interp(hi_t, t, pos[:, j]) for j in range(3)])
        V = (Phi - Plo) / (hi_t - lo_t)[:, None]
        Q = Slerp(t, mc.att)(np.clip(grid, t[0], t[-1])).as_quat(canonical=True)  # x,y,z,w body -> local ENU
        tt.append(grid)
        tu.append(np.full(len(grid), uid))
        rows.append(np.column_stack([P, V, Q[:, 3], Q[:, 0], Q[:, 1], Q[:, 2]]))
        sp = np.linalg.norm(V, axis=1)
        summary.setdefault("speed_mps", {})[uid] = {"p50": round(float(np.median(sp)), 3), "p99": round(float(np.percentile(sp, 99)), 3),
                                                    "max": round(float(sp.max()), 3)}
    return sorted_table("truth", np.concatenate(tt), np.concatenate(tu), np.vstack(rows))
