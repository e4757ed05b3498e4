"""The per-UAV graph's *own* factors of an epoch besides IMU: GNSS position/velocity and altitude
(``models/gnss.py``, ``models/altimeter.py``), known-anchor ranges, passive range differences whose tags are all the node's own or anchors', and the rotor-drag factor.

Sparse ranging without GNSS (docs/miluv.md, "Third pass"): an anchor range taken at t_r inside the
epoch is fused at the epoch time t with the anchor moved by v_pred·(t − t_r) (``anchor_time_shift``,
default on). Measurements to known anchors are not broadcast, so a robust kernel guards NLOS
(``anchor_kernel``: default Huber, k = ``anchor_kernel_k`` whitened; cauchy/tukey/gm were measured
worse on MILUV). Passive-listening rows (``EpochInput.tdoa_*``, docs/miluv.md "Fifth pass"): a row
whose tags are all the node's own or anchors' is an own factor here (``ins`` uses only these); one
that involves a neighbour's tag is a cooperative link (graph_links.py, rounds.py). Models:
``models/anchor_range.py``, ``models/tdoa.py``, ``models/rotor_drag.py``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..dataset import DatasetMeta, EpochInput
from ..models.altimeter import DEFAULT_SIGMA_M as DEFAULT_ALT_SIGMA
from ..models.gnss import position_sigma
from .factors import altitude_factor, rotor_drag_factor, rotor_drag_prior, rotor_drag_sigma, stacked_range_factor, tdoa_factor, tdoa_row
from .imu import mean_specific_force

DRAG_KEY = gtsam.symbol("m", 0)  # rotor-drag state [μ, c_x, c_y] of a multirotor (OwnFactors.add_drag)


def _unwrap_error(f: gtsam.CustomFactor):
    """Error callback of a unit-noise CustomFactor, to re-wrap it with another noise model."""
    def err(this, v, H):
        if H is None:
            return f.unwhitenedError(v)
        lin = f.linearize(v)
        A, b = lin.jacobian()
        H[0] = A
        return -b
    return err


_swarm_tags: tuple = (None, None)  # (meta, its swarm_tags): every node of a swarm asks, each O(N)


def swarm_tags(meta: DatasetMeta) -> tuple[dict[int, dict[int, np.ndarray]], frozenset[int]]:
    """(UAV id -> tag id -> lever arm (body m) for every UAV with a tag off its body origin, the UAV
    ids), computed once per ``meta`` (the last one asked): O(N) per swarm, not per node."""
    global _swarm_tags
    if _swarm_tags[0] is not meta:
        levers = {n.id: {int(k): np.asarray(v, float) for k, v in n.tags.items()}
                  for n in meta.nodes if n.kind == "uav" and any(any(v) for v in n.tags.values())}
        _swarm_tags = (meta, (levers, frozenset(meta.uav_ids())))
    return _swarm_tags[1]


class OwnFactors:
    """Builds one node's own anchor, passive-range and rotor-drag factors (tuning: ``t``, an
    ``EstimatorTuning``; ``drag`` whether the node is a multirotor with the drag model on)."""

    def __init__(self, uav: int, meta: DatasetMeta, t, uwb_sigma: float, tags: dict, params, drag: bool):
        self.uav, self.meta, self.uwb_sigma, self.tags, self.params = uav, meta, uwb_sigma, tags, params
        self.anchors = meta.anchors()
        self.uavs = swarm_tags(meta)[1]
        self.time_shift = t.anchor_time_shift
        me = gtsam.noiseModel.mEstimator
        self._kernel = {"huber": me.Huber, "cauchy": me.Cauchy, "tukey": me.Tukey, "gm": me.GemanMcClure}[t.anchor_kernel]
        self.kernel_k = t.anchor_kernel_k
        self.use_tdoa, self.tdoa_scale, self.tdoa_offset = t.use_tdoa, t.tdoa_sigma_scale, t.tdoa_offset_m
        self.drag, self.drag_mu0, self.drag_mu_sigma = drag, t.drag_mu_prior, t.drag_mu_prior_sigma
        self.drag_sigma_scale = t.drag_sigma_scale
        self.drag_new = drag  # the drag state is not in the smoother yet (inserted with its prior)
        node = meta.node(uav)
        self.gnss_extra_var = t.gnss_extra_var_m2
        # GNSS σ × gnss_sigma_scale where the dataset says the receiver has a time-correlated error
        # (node.gnss_correlated_sigma_m > 0) or does not say (None); a declared white-noise
        # receiver (0) at its stated σ; a per-role override wins
        self.gnss_scale = 1.0 if node.gnss_correlated_sigma_m == 0 else t.gnss_sigma_scale
        self.gnss_scale = float(t.gnss_sigma_scale_by_role.get(str(node.role), self.gnss_scale))

    def add_gnss_altitude(self, g, key, vel_key, inp: EpochInput):
        """The epoch's GNSS position (ENU m, on pose ``key``) and velocity (m/s, on ``vel_key``) and
        barometric altitude factors, where the epoch has them."""
        if inp.gnss_pos is not None:
            sig = position_sigma(inp.gnss_pos_sigma, self.gnss_extra_var, self.gnss_scale)
            g.add(gtsam.GPSFactor(key, np.asarray(inp.gnss_pos, float), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        if inp.gnss_vel is not None and inp.gnss_vel_sigma:
            g.add(gtsam.PriorFactorVector(vel_key, np.asarray(inp.gnss_vel, float),
                                          gtsam.noiseModel.Isotropic.Sigma(3, float(inp.gnss_vel_sigma))))
        if inp.altitude is not None:
            g.add(altitude_factor(key, inp.altitude, inp.altitude_sigma or DEFAULT_ALT_SIGMA))

    def robust(self, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        """``base`` under the anchor kernel."""
        return gtsam.noiseModel.Robust.Create(self._kernel.Create(self.kernel_k), base)

    def add_anchor_ranges(self, g, key, inp: EpochInput, v_pred: np.ndarray):
        """The epoch's ranges to known anchors as one robust stacked factor on pose ``key``."""
        if not self.anchors or len(inp.range_other) == 0:
            return
        m = np.isin(inp.range_other, list(self.anchors))
        if not m.any():
            return
        pts = np.array([self.anchors[int(o)] for o in inp.range_other[m]])
        if self.time_shift and len(inp.range_t) == len(inp.range_m):
            # a range taken at t_r < t: the tag was at p(t) − v·(t − t_r); equivalently the anchor
            # is moved by +v·(t − t_r) (v = the IMU prediction's velocity)
            pts = pts + np.outer(float(inp.t) - inp.range_t[m], v_pred)
        levers = np.array([self.tags.get(int(t), np.zeros(3)) for t in inp.range_tag_self[m]])
        sig = np.where(inp.range_sigma[m] > 0, inp.range_sigma[m], self.uwb_sigma)
        z = inp.range_m[m]
        f = stacked_range_factor(key, pts, z, sig, levers)
        g.add(gtsam.CustomFactor(self.robust(gtsam.noiseModel.Unit.Create(len(z))), [key], _unwrap_error(f)))

    def tdoa_rows(self, inp: EpochInput) -> tuple[list[int], list[int]]:
        """Indices of this epoch's tdoa rows: (own = every tag is this node's or an anchor's,
        cooperative = a neighbour UAV's tag is involved). Rows naming an unknown node are ignored."""
        own, coop = [], []
        if not self.use_tdoa or not len(inp.tdoa_m):
            return own, coop
        for i in range(len(inp.tdoa_m)):
            ends = (int(inp.tdoa_listener[i]), int(inp.tdoa_init[i]), int(inp.tdoa_resp[i]))
            if (not np.isfinite(inp.tdoa_m[i]) or self.uav not in ends
                    or not all(o in self.anchors or o in self.uavs for o in ends)):
                continue
            (own if all(o == self.uav or o in self.anchors for o in ends) else coop).append(i)
        return own, coop

    def tdoa_row(self, inp: EpochInput, i: int) -> tuple[float, float]:
        """(rdiff less the passive path's offset, σ) in m of tdoa row i (models.tdoa.tdoa_row)."""
        return tdoa_row(inp.tdoa_m[i], inp.tdoa_sigma[i], self.uwb_sigma, self.tdoa_scale, self.tdoa_offset)

    @staticmethod
    def tdoa_ends(inp: EpochInput, i: int) -> tuple[tuple[int, int], ...]:
        """(node, tag) of listener, initiator, responder of tdoa row i."""
        return ((int(inp.tdoa_listener[i]), int(inp.tdoa_tag[i])), (int(inp.tdoa_init[i]), int(inp.tdoa_tag_init[i])),
                (int(inp.tdoa_resp[i]), int(inp.tdoa_tag_resp[i])))

    def tdoa_end(self, node: int, tag: int, key: int | None = None):
        """(key, lever) of an own tag on pose ``key`` or (None, position) of an anchor's tag, for
        factors.tdoa_factor."""
        if node == self.uav:
            return key, self.tags.get(tag, np.zeros(3))
        return None, self.anchors[node] + np.asarray(self.meta.node(node).tags.get(tag, (0.0, 0.0, 0.0)), float)

    def add_own_tdoa(self, g, key, inp: EpochInput, rows: list[int], v_pred: np.ndarray):
        """Own tdoa rows ``rows`` as robust factors on pose ``key``."""
        for i in rows:
            ends = [self.tdoa_end(nd, tg, key) for nd, tg in self.tdoa_ends(inp, i)]
            if self.time_shift:
                # taken at t_r < t: the own tags were at p(t) − v·(t − t_r); equivalently every
                # anchor end moves by +v·(t − t_r) (as for anchor ranges)
                dt = float(inp.t) - float(inp.tdoa_t[i])
                ends = [(k, x) if k is not None else (k, x + dt * v_pred) for k, x in ends]
            z, sig = self.tdoa_row(inp, i)
            g.add(tdoa_factor(ends, z, self.robust(gtsam.noiseModel.Isotropic.Sigma(1, sig))))

    def add_drag(self, g, keys: tuple[int, int, int], inp: EpochInput, at_rest: bool):
        """Rotor-drag factor of a multirotor on (X, V, B) ``keys`` and the drag state M = [μ, c_x, c_y]
        (models/rotor_drag.py): residual μ(Rᵀv)_xy + (f̄ − b_a)_xy − c over the epoch's mean specific
        force f̄, σ = accel_noise_density/√Δt × ``drag_sigma_scale``. M is estimated online: μ prior
        ``drag_mu_prior`` ± ``drag_mu_prior_sigma`` (1/s, loose); c prior = the first epoch's f̄_xy
        ± 0.1 m/s² when the node starts at rest (standing on its landing gear the rotor axis is the
        floor normal), else 0 ± 0.5. Off during the initial rest phase (ground contact, not drag).
        Returns M's initial value on the first call (the caller inserts it), else None."""
        mf = mean_specific_force(inp)
        if mf is None:
            return None
        fbar, T = mf
        m0 = None
        if self.drag_new:
            self.drag_new = False
            prior, m0 = rotor_drag_prior(DRAG_KEY, self.drag_mu0, self.drag_mu_sigma, fbar[:2], at_rest)
            g.add(prior)
        if at_rest:
            return m0
        sig = rotor_drag_sigma(self.params, T, self.drag_sigma_scale)
        g.add(rotor_drag_factor(*keys, DRAG_KEY, fbar[:2], sig))
        return m0
