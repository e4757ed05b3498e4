"""Wire messages of the Zenoh deployment: pydantic models with a schema version, JSON-encoded.

Every message carries ``v`` (:data:`SCHEMA_VERSION`). Floats travel as JSON numbers written with
the shortest repr that round-trips, so float64 values arrive bit-identical (tests/test_messages.py);
``+inf`` is allowed only where the protocol needs it (``delta_m`` of round 0) and NaN never.

Receivers call :func:`decode` with what the key told them (the UAV id) and the oldest epoch they
still accept; anything malformed (not JSON, wrong shape, unknown field), of an unknown version,
out of range (NaN/inf, negative range or sigma, bad ids) or about the wrong UAV or a stale epoch
raises :class:`WireError`. Services count and log those with :class:`Rejects` and keep running.
This module is pure (no zenoh); converters map messages to/from the core's dataclasses.

On the wire since schema version 2 the two bulky kinds are binary frames (end of this module):
the sensor input of a UAV's epoch (one ``input`` frame: a pydantic-validated JSON header + float64
/int64 arrays checked with numpy) and the peer state of a round (a fixed struct + float64 array).
The per-part JSON models (ImuMsg, GnssMsg, UwbMsg, RelMsg, TdoaMsg, EpochMsg) and StateMsg remain for
tests and for the state queryable's JSON history replies.
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..dataset import EpochInput
from ..estimators.base import InitialState, LinkClass, LinkInfo, NodeEstimate, NodeState

SCHEMA_VERSION = 5  # 2: binary input/state frames (below); 3: states carry az/el bearings; 4: tdoa inputs;
#                    5: states carry the relink window's smoothed positions (traj)

# no UWB range or range difference is this long: larger (finite) values are hostile or corrupt
MAX_UWB_M = 1e5
# plausible envelope of a position (m, any ENU axis, local frame) and of a variance (m^2): a state or
# estimate outside it is rejected as corrupt or hostile. Receivers may pass a tighter envelope_m.
ENVELOPE_M = 1e6
MAX_VAR_M2 = 1e12


def check_position_cov(pos, cov, envelope_m: float = ENVELOPE_M) -> None:
    """WireError unless ``pos`` (3) lies inside the envelope and ``cov`` (3x3 or 9, row-major) is
    symmetric positive definite (Sylvester: leading minors > 0) with variances below MAX_VAR_M2.
    Plain float arithmetic: it runs on every received peer state."""
    p = [float(x) for x in np.asarray(pos, np.float64).ravel().tolist()]
    a, b, c, d, e, f, g, h, i = (float(x) for x in np.asarray(cov, np.float64).ravel().tolist())
    if not all(math.isfinite(x) for x in (*p, a, b, c, d, e, f, g, h, i)):
        raise WireError("invalid", "non-finite position or covariance")
    if max(abs(x) for x in p) > envelope_m:
        raise WireError("envelope", f"position {max(abs(x) for x in p):.3g} m from the origin, outside the {envelope_m:g} m envelope")
    tol = 1e-9 * max(abs(a), abs(e), abs(i), 1e-300)
    if abs(b - d) > tol or abs(c - g) > tol or abs(f - h) > tol:
        raise WireError("covariance", "position covariance not symmetric")
    if max(a, e, i) > MAX_VAR_M2:
        raise WireError("covariance", f"position variance {max(a, e, i):.3g} m^2 implausibly large")
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if not (a > 0 and a * e - b * d > 0 and det > 0):
        raise WireError("covariance", "position covariance not positive definite")


Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
UavId = Annotated[int, Field(ge=1)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Mat3 = Annotated[list[Finite], Field(min_length=9, max_length=9)]  # row-major 3x3


class WireError(ValueError):
    """A received message was rejected. ``reason`` is a short class for counting."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


class Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, ser_json_inf_nan="constants", strict=False)
    v: Literal[SCHEMA_VERSION] = SCHEMA_VERSION

    def encode(self) -> bytes:
        return self.model_dump_json().encode()


class UavMsg(Msg):
    uav: UavId
    k: int = Field(ge=0)


def _same_len(m: BaseModel, *names: str, per: dict[str, int] | None = None) -> None:
    per = per or {}
    n = None
    for name in names:
        ln = len(getattr(m, name)) // per.get(name, 1)
        if len(getattr(m, name)) % per.get(name, 1):
            raise ValueError(f"{name}: length not a multiple of {per[name]}")
        if n is None:
            n = ln
        elif ln != n:
            raise ValueError(f"{names}: lengths differ")


# -- sensor-sim -> node ------------------------------------------------------------------------


class ImuMsg(UavMsg):
    t: Finite
    t_prev: Finite
    imu_t: list[Finite]
    gyro: list[Finite]  # M*3 row-major, rad/s
    accel: list[Finite]  # M*3, m/s^2

    @model_validator(mode="after")
    def _shape(self):
        _same_len(self, "imu_t", "gyro", "accel", per={"gyro": 3, "accel": 3})
        return self


class GnssMsg(UavMsg):
    pos: Vec3
    vel: Vec3
    pos_sigma: Annotated[list[Pos], Field(min_length=3, max_length=3)]
    vel_sigma: Pos


class UwbMsg(UavMsg):
    range_t: list[Finite]
    other: list[Annotated[int, Field(ge=0)]]
    tag_self: list[Annotated[int, Field(ge=0)]]
    tag_other: list[Annotated[int, Field(ge=0)]]
    range_m: list[Annotated[float, Field(ge=0, le=MAX_UWB_M, allow_inf_nan=False)]]
    sigma: list[Pos]

    @model_validator(mode="after")
    def _shape(self):
        _same_len(self, "range_t", "other", "tag_self", "tag_other", "range_m", "sigma")
        if self.uav in self.other:
            raise ValueError("a UAV cannot range to itself")
        return self


class RelMsg(UavMsg):
    target: list[UavId]
    az: list[Finite]
    el: list[Finite]
    sigma: list[Pos]

    @model_validator(mode="after")
    def _shape(self):
        _same_len(self, "target", "az", "el", "sigma")
        if self.uav in self.target:
            raise ValueError("a UAV cannot observe itself")
        return self


class TdoaMsg(UavMsg):
    """Passive-listening range differences this UAV takes part in (dataset ``tdoa`` table)."""

    tdoa_t: list[Finite]
    listener: list[UavId]
    tag: list[Annotated[int, Field(ge=0)]]
    init: list[Annotated[int, Field(ge=0)]]
    tag_init: list[Annotated[int, Field(ge=0)]]
    resp: list[Annotated[int, Field(ge=0)]]
    tag_resp: list[Annotated[int, Field(ge=0)]]
    rdiff: list[Annotated[float, Field(ge=-MAX_UWB_M, le=MAX_UWB_M, allow_inf_nan=False)]]
    sigma: list[Pos]

    @model_validator(mode="after")
    def _shape(self):
        _same_len(self, "tdoa_t", "listener", "tag", "init", "tag_init", "resp", "tag_resp", "rdiff", "sigma")
        return self


class EpochMsg(UavMsg):
    """Closes epoch k's inputs for one UAV: which parts were sent, who takes part in the epoch."""

    t: Finite
    t_prev: Finite
    parts: list[Literal["imu", "gnss", "uwb", "rel", "tdoa"]]
    participants: list[UavId]
    altitude: Finite | None = None
    altitude_sigma: Pos | None = None


class InitMsg(Msg):
    uav: UavId
    t: Finite
    pos: Vec3
    vel: Vec3
    quat: Annotated[list[Finite], Field(min_length=4, max_length=4)]
    pos_sigma: Annotated[list[Pos], Field(min_length=3, max_length=3)]
    vel_sigma: NonNeg
    att_sigma: Annotated[list[NonNeg], Field(min_length=3, max_length=3)]


class MetaMsg(Msg):
    run: str
    seed: int
    meta: dict  # DatasetMeta as JSON (by alias)


class TruthLabel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    other: int
    fault_kind: int
    fault_err: float | None  # None = unknown


class TruthMsg(UavMsg):
    t: Finite
    pos: Vec3
    vel: Vec3
    quat: Annotated[list[Finite], Field(min_length=4, max_length=4)]


# -- node -> peers / monitor -----------------------------------------------------------------


class StateMsg(UavMsg):
    r: int = Field(ge=0)
    t: Finite
    pos: Vec3
    pos_cov: Mat3
    vel: Vec3
    delta_m: Annotated[float, Field(ge=0, allow_inf_nan=True)] = math.inf
    ranges: dict[int, NonNeg] = Field(default_factory=dict)
    # target id -> [azimuth rad, elevation rad, sigma rad] (round 0)
    bearings: dict[int, Annotated[list[Finite], Field(min_length=3, max_length=3)]] = Field(default_factory=dict)
    quat: Annotated[list[Finite], Field(min_length=4, max_length=4)] | None = None  # w, x, y, z body -> ENU
    n_links: int = Field(0, ge=0, le=1_000_000)
    # round 0: epoch -> smoothed ENU position of the sender's relink window (graph.py)
    traj: dict[int, Vec3] = Field(default_factory=dict)

    @field_validator("quat")
    @classmethod
    def _unit(cls, q):
        if q is not None and abs(math.sqrt(sum(x * x for x in q)) - 1.0) > 1e-6:
            raise ValueError("attitude quaternion not of unit norm")
        return q

    @model_validator(mode="after")
    def _traj_epochs(self):
        if any(e < 0 or e > self.k for e in self.traj):
            raise ValueError(f"traj epochs must lie in [0, k = {self.k}]")
        try:
            check_position_cov(self.pos, self.pos_cov)
        except WireError as e:
            raise ValueError(str(e)) from None
        return self

    @field_validator("bearings")
    @classmethod
    def _bearings(cls, b: dict) -> dict:
        for o, (az, el, sg) in b.items():
            if o < 0 or not (-math.pi <= az <= math.pi and -math.pi / 2 <= el <= math.pi / 2 and sg > 0):
                raise ValueError(f"bearing to {o}: azimuth in [-pi, pi], elevation in [-pi/2, pi/2], sigma > 0")
        return b

    @field_validator("delta_m")
    @classmethod
    def _no_nan(cls, x: float) -> float:
        if math.isnan(x):
            raise ValueError("delta_m is NaN")
        return x


class LinkMsg(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    other: int = Field(ge=0)
    cls: int = Field(ge=0, le=2)
    residual_m: Finite
    weight: NonNeg


class EstimateMsg(UavMsg):
    t: Finite
    pos: Vec3
    vel: Vec3
    pos_cov: Mat3
    quat: Annotated[list[Finite], Field(min_length=4, max_length=4)] | None = None
    links: list[LinkMsg] = Field(default_factory=list)
    rounds: int = Field(0, ge=0)
    step_ms: NonNeg = 0.0
    wait_ms: NonNeg = 0.0
    delta_h_m: Finite | None = None
    delta_l_m: Finite | None = None
    peers: list[UavId] = Field(default_factory=list)  # the peers whose states this epoch used
    bytes_out: int = Field(0, ge=0)  # bytes this node published for the epoch (state + estimate)
    inc: int = Field(0, ge=0)  # the sender's incarnation (bumped at every re-bootstrap)
    # messages the sender rejected so far, "topic:reason" -> count (hostile or corrupt input it saw)
    rejected: dict[Annotated[str, Field(max_length=64)], Annotated[int, Field(ge=0)]] = Field(default_factory=dict, max_length=64)

    @model_validator(mode="after")
    def _plausible(self):
        try:
            check_position_cov(self.pos, self.pos_cov)
            check_position_cov(self.vel, np.eye(3))
        except WireError as e:
            raise ValueError(str(e)) from None
        return self


class LinksMsg(UavMsg):
    links: list[LinkMsg]


class HistoryMsg(Msg):
    """Reply of the state queryable: the node's latest states (oldest first)."""

    uav: UavId
    states: list[StateMsg]
    estimates: list[EstimateMsg] = Field(default_factory=list)


class ClockMsg(Msg):
    """Sensor-sim clock: epoch k (time t) starts with these participants; ``done`` ends the run.
    ``hold`` names a scheduled fault the clock waits for before epoch k (the launcher acts on it)."""

    k: int = Field(ge=0)
    t: Finite
    n_epochs: int = Field(ge=0)
    participants: list[UavId] = Field(default_factory=list)
    done: bool = False
    hold: Literal["kill", "restart"] | None = None
    hold_uav: UavId | None = None
    lost: Annotated[list[Annotated[int, Field(ge=1)]], Field(min_length=2, max_length=2)] | None = None  # [first, last]
    #     epochs played into a bus outage in real-time mode (never delivered)


# -- decoding --------------------------------------------------------------------------------


def decode(cls: type[Msg], payload: bytes | str, *, uav: int | None = None, min_k: int | None = None) -> Msg:
    """Parse and validate; raise WireError(reason) on anything the receiver must not use."""
    try:
        raw = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as e:
        raise WireError("malformed", f"not JSON ({e})") from None
    if not isinstance(raw, dict):
        raise WireError("malformed", "not a JSON object")
    if raw.get("v") != SCHEMA_VERSION:
        raise WireError("version", f"schema version {raw.get('v')!r}, expected {SCHEMA_VERSION}")
    try:
        m = cls.model_validate(raw)
    except ValidationError as e:
        err = e.errors()[0]
        raise WireError("invalid", f"{'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    _check_scope(getattr(m, "uav", uav), getattr(m, "k", min_k), uav, min_k)
    return m


def _check_scope(u, k, uav: int | None, min_k: int | None) -> None:
    """WireError if a message about UAV ``u``, epoch ``k`` is not for ``uav`` or older than ``min_k``."""
    if uav is not None and u != uav:
        raise WireError("wrong_uav", f"message about UAV {u} on UAV {uav}'s key")
    if min_k is not None and k < min_k:
        raise WireError("stale", f"epoch {k} < {min_k}")


class Rejects:
    """Counts rejected messages by (topic, reason) and logs them (first few, then every 100th)."""

    def __init__(self, log: logging.Logger):
        self.log = log
        self.counts: Counter = Counter()

    def add(self, topic: str, err: Exception) -> None:
        reason = getattr(err, "reason", type(err).__name__)
        self.counts[(topic, reason)] += 1
        n = sum(self.counts.values())
        if n <= 20 or n % 100 == 0:
            self.log.warning("rejected message on %s (%s): %s [total rejected %d]", topic, reason, err, n)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def as_dict(self) -> dict[str, int]:
        return {f"{t}:{r}": n for (t, r), n in sorted(self.counts.items())}


# -- converters to/from the core's dataclasses ------------------------------------------------


def _f(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).ravel()]


def state_to_msg(s: NodeState) -> StateMsg:
    return StateMsg(uav=s.uav, k=s.k, r=s.r, t=float(s.t), pos=_f(s.pos), pos_cov=_f(s.pos_cov), vel=_f(s.vel),
                    delta_m=float(s.delta_m), ranges={int(o): float(d) for o, d in sorted(s.ranges.items())},
                    bearings={int(o): [float(x) for x in b] for o, b in sorted(s.bearings.items())},
                    quat=None if s.quat is None else _f(s.quat), n_links=int(s.n_links),
                    traj={int(k): _f(p) for k, p in sorted(s.traj.items())})


def msg_to_state(m: StateMsg) -> NodeState:
    return NodeState(uav=m.uav, k=m.k, r=m.r, t=m.t, pos=np.array(m.pos, np.float64),
                     pos_cov=np.array(m.pos_cov, np.float64).reshape(3, 3), vel=np.array(m.vel, np.float64),
                     delta_m=m.delta_m, ranges={int(o): float(d) for o, d in sorted(m.ranges.items())},
                     bearings={int(o): (float(b[0]), float(b[1]), float(b[2])) for o, b in sorted(m.bearings.items())},
                     quat=None if m.quat is None else np.array(m.quat, np.float64), n_links=m.n_links,
                     traj={int(k): np.array(p, np.float64) for k, p in sorted(m.traj.items())})


def estimate_to_msg(e: NodeEstimate, **extra) -> EstimateMsg:
    return EstimateMsg(uav=e.uav, k=e.k, t=float(e.t), pos=_f(e.pos), vel=_f(e.vel), pos_cov=_f(e.pos_cov),
                       quat=None if e.quat is None else _f(e.quat),
                       links=[LinkMsg(other=int(li.other), cls=int(li.cls), residual_m=float(li.residual_m),
                                      weight=float(li.weight)) for li in e.links],
                       rounds=int(e.rounds), step_ms=float(e.step_ms),
                       delta_h_m=None if e.delta_h_m is None else float(e.delta_h_m),
                       delta_l_m=None if e.delta_l_m is None else float(e.delta_l_m), **extra)


def msg_to_estimate(m: EstimateMsg) -> NodeEstimate:
    return NodeEstimate(uav=m.uav, k=m.k, t=m.t, pos=np.array(m.pos, np.float64), vel=np.array(m.vel, np.float64),
                        pos_cov=np.array(m.pos_cov, np.float64).reshape(3, 3),
                        quat=None if m.quat is None else np.array(m.quat, np.float64),
                        links=[LinkInfo(li.other, LinkClass(li.cls), li.residual_m, li.weight) for li in m.links],
                        rounds=m.rounds, step_ms=m.step_ms, delta_h_m=m.delta_h_m, delta_l_m=m.delta_l_m)


def init_to_msg(uav: int, s: InitialState) -> InitMsg:
    return InitMsg(uav=uav, t=float(s.t), pos=_f(s.pos), vel=_f(s.vel), quat=_f(s.quat), pos_sigma=_f(s.pos_sigma),
                   vel_sigma=float(s.vel_sigma), att_sigma=_f(s.att_sigma))


def msg_to_init(m: InitMsg) -> InitialState:
    a = lambda x: np.array(x, np.float64)  # noqa: E731
    return InitialState(t=m.t, pos=a(m.pos), vel=a(m.vel), quat=a(m.quat), pos_sigma=a(m.pos_sigma),
                        vel_sigma=m.vel_sigma, att_sigma=a(m.att_sigma))


def epoch_input_to_msgs(inp: EpochInput, participants: list[int]) -> dict[str, UavMsg]:
    """Split one EpochInput into the per-topic messages (``epoch`` last: it lists the parts)."""
    u, k = inp.uav, inp.k
    out: dict[str, UavMsg] = {
        "imu": ImuMsg(uav=u, k=k, t=inp.t, t_prev=inp.t_prev, imu_t=_f(inp.imu_t), gyro=_f(inp.gyro), accel=_f(inp.accel)),
        "uwb": UwbMsg(uav=u, k=k, range_t=_f(inp.range_t), other=[int(x) for x in inp.range_other],
                      tag_self=[int(x) for x in inp.range_tag_self], tag_other=[int(x) for x in inp.range_tag_other],
                      range_m=_f(inp.range_m), sigma=_f(inp.range_sigma)),
        "rel": RelMsg(uav=u, k=k, target=[int(x) for x in inp.rel_target], az=_f(inp.rel_az), el=_f(inp.rel_el),
                      sigma=_f(inp.rel_sigma)),
    }
    if len(inp.tdoa_m):
        ints = lambda x: [int(v) for v in x]  # noqa: E731
        out["tdoa"] = TdoaMsg(uav=u, k=k, tdoa_t=_f(inp.tdoa_t), listener=ints(inp.tdoa_listener), tag=ints(inp.tdoa_tag), init=ints(inp.tdoa_init),
                              tag_init=ints(inp.tdoa_tag_init), resp=ints(inp.tdoa_resp), tag_resp=ints(inp.tdoa_tag_resp),
                              rdiff=_f(inp.tdoa_m), sigma=_f(inp.tdoa_sigma))
    if inp.gnss_pos is not None:
        out["gnss"] = GnssMsg(uav=u, k=k, pos=_f(inp.gnss_pos), vel=_f(inp.gnss_vel), pos_sigma=_f(inp.gnss_pos_sigma),
                              vel_sigma=float(inp.gnss_vel_sigma))
    out["epoch"] = EpochMsg(uav=u, k=k, t=inp.t, t_prev=inp.t_prev, parts=[p for p in ("imu", "gnss", "uwb", "rel", "tdoa") if p in out],
                            participants=sorted(participants), altitude=inp.altitude, altitude_sigma=inp.altitude_sigma)
    return out


def msgs_to_epoch_input(parts: dict[str, UavMsg]) -> EpochInput:
    """Inverse of :func:`epoch_input_to_msgs` (needs 'epoch' and every part it lists)."""
    ep: EpochMsg = parts["epoch"]
    a = lambda x: np.array(x, np.float64)  # noqa: E731
    i = lambda x: np.array(x, np.int64)  # noqa: E731
    imu: ImuMsg = parts["imu"]
    inp = EpochInput(uav=ep.uav, k=ep.k, t=ep.t, t_prev=ep.t_prev, imu_t=a(imu.imu_t),
                     gyro=a(imu.gyro).reshape(-1, 3), accel=a(imu.accel).reshape(-1, 3),
                     altitude=ep.altitude, altitude_sigma=ep.altitude_sigma)
    g = parts.get("gnss")
    if g is not None:
        inp.gnss_pos, inp.gnss_vel, inp.gnss_pos_sigma, inp.gnss_vel_sigma = a(g.pos), a(g.vel), a(g.pos_sigma), g.vel_sigma
    w = parts.get("uwb")
    if w is not None and len(w.range_t):
        inp.range_t, inp.range_other, inp.range_tag_self, inp.range_tag_other = a(w.range_t), i(w.other), i(w.tag_self), i(w.tag_other)
        inp.range_m, inp.range_sigma = a(w.range_m), a(w.sigma)
    r = parts.get("rel")
    if r is not None and len(r.target):
        inp.rel_target, inp.rel_az, inp.rel_el, inp.rel_sigma = i(r.target), a(r.az), a(r.el), a(r.sigma)
    d = parts.get("tdoa")
    if d is not None and len(d.tdoa_t):
        inp.tdoa_t, inp.tdoa_listener, inp.tdoa_tag = a(d.tdoa_t), i(d.listener), i(d.tag)
        inp.tdoa_init, inp.tdoa_tag_init = i(d.init), i(d.tag_init)
        inp.tdoa_resp, inp.tdoa_tag_resp, inp.tdoa_m, inp.tdoa_sigma = i(d.resp), i(d.tag_resp), a(d.rdiff), a(d.sigma)
    return inp


SENSOR_MSG: dict[str, type[UavMsg]] = {"imu": ImuMsg, "gnss": GnssMsg, "uwb": UwbMsg, "rel": RelMsg, "tdoa": TdoaMsg,
                                        "epoch": EpochMsg}


# -- binary frames for the bulky per-epoch traffic ---------------------------------------------
#
# The two message kinds that dominate the traffic travel as binary frames instead of JSON:
#
# * ``uav/<id>/input`` (sensor-sim -> node): ONE message per UAV and epoch with the whole
#   EpochInput. Frame: ``b"SNI"`` + version byte, uint32 LE length of a JSON header (an
#   :class:`InputHeader`, pydantic-validated: ids, times, participants, GNSS fix, altitude and the
#   array lengths), then the arrays as little-endian float64/int64 in :data:`_INPUT_F` /
#   :data:`_INPUT_I` order. The arrays are validated with numpy after decoding (finite, ranges
#   >= 0, sigmas > 0, ids >= 0, no self-ranging or self-observation).
# * ``uav/<id>/state`` (node -> peers, every round): ``b"SNS"`` + version byte, int32 LE
#   uav, k, r, uint32 n (ranges), uint32 m (bearings), uint32 w (relink-window positions),
#   float64 LE [t, pos(3), pos_cov(9, row-major), vel(3), delta_m, n_links, quat(4: w, x, y, z;
#   all zero = no attitude), range values(n), bearings (az, el, sigma)(m), positions (3)(w)],
#   int64 LE range peer ids(n), bearing target ids(m), position epochs(w).
#   Decoded straight into the core's NodeState.
#
# float64 bytes are copied, so values arrive bit-identical (as with the JSON repr before).
# The state queryable's history replies stay JSON (:class:`HistoryMsg`, rare).

import struct  # noqa: E402

_STATE_MAGIC = b"SNS"
_INPUT_MAGIC = b"SNI"
_STATE_HDR = struct.Struct("<3sBiiiIII")
_INPUT_HDR = struct.Struct("<3sBI")
_STATE_NF = 22  # t, pos 3, cov 9, vel 3, delta_m, n_links, quat 4, then n range values


def _check_magic(payload: bytes, magic: bytes, min_len: int) -> None:
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) < min_len or payload[:3] != magic:
        raise WireError("malformed", f"not a {magic.decode()} frame")
    if payload[3] != SCHEMA_VERSION:
        raise WireError("version", f"schema version {payload[3]!r}, expected {SCHEMA_VERSION}")


def encode_state(s: NodeState) -> bytes:
    ids = sorted(int(o) for o in s.ranges)
    bids = sorted(int(o) for o in s.bearings)
    kids = sorted(int(k) for k in s.traj)
    n, m, w = len(ids), len(bids), len(kids)
    f = np.empty(_STATE_NF + n + 3 * m + 3 * w, np.float64)
    f[0] = s.t
    f[1:4] = np.asarray(s.pos, np.float64).ravel()
    f[4:13] = np.asarray(s.pos_cov, np.float64).ravel()
    f[13:16] = np.asarray(s.vel, np.float64).ravel()
    f[16] = s.delta_m
    f[17] = float(s.n_links)
    f[18:22] = 0.0 if s.quat is None else np.asarray(s.quat, np.float64).ravel()
    f[_STATE_NF:_STATE_NF + n] = [s.ranges[o] for o in ids]
    f[_STATE_NF + n:_STATE_NF + n + 3 * m] = np.asarray([s.bearings[o] for o in bids], np.float64).ravel()
    f[_STATE_NF + n + 3 * m:] = np.asarray([s.traj[k] for k in kids], np.float64).ravel()
    return (_STATE_HDR.pack(_STATE_MAGIC, SCHEMA_VERSION, int(s.uav), int(s.k), int(s.r), n, m, w)
            + f.astype("<f8", copy=False).tobytes() + np.asarray(ids + bids + kids, "<i8").tobytes())


def decode_state(payload: bytes, *, uav: int | None = None, min_k: int | None = None,
                 envelope_m: float = ENVELOPE_M) -> NodeState:
    """Binary state frame -> NodeState; WireError(malformed|version|invalid|wrong_uav|stale)."""
    _check_magic(payload, _STATE_MAGIC, _STATE_HDR.size)
    _, _, u, k, r, n, m, w = _STATE_HDR.unpack_from(payload)
    nf = _STATE_NF + n + 3 * m + 3 * w
    if len(payload) != _STATE_HDR.size + 8 * nf + 8 * (n + m + w):
        raise WireError("malformed", f"state frame of {len(payload)} bytes for {n} ranges, {m} bearings, {w} positions")
    f = np.frombuffer(payload, "<f8", nf, _STATE_HDR.size).astype(np.float64)
    ids = np.frombuffer(payload, "<i8", n + m + w, _STATE_HDR.size + 8 * nf)
    if u < 1 or k < 0 or r < 0:
        raise WireError("invalid", f"ids uav {u} k {k} r {r}")
    if not (np.isfinite(f[:16]).all() and np.isfinite(f[18:]).all()):
        raise WireError("invalid", "non-finite value")
    check_position_cov(f[1:4], f[4:13], envelope_m)
    if np.abs(f[13:16]).max() > ENVELOPE_M or (w and np.abs(f[-3 * w:]).max() > envelope_m):
        raise WireError("envelope", "velocity or window position outside the envelope")
    q = f[18:22]
    if q.any() and abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
        raise WireError("invalid", "attitude quaternion not of unit norm")
    rng, bear = f[_STATE_NF:_STATE_NF + n], f[_STATE_NF + n:_STATE_NF + n + 3 * m].reshape(m, 3)
    traj = f[_STATE_NF + n + 3 * m:].reshape(w, 3)
    kids = ids[n + m:]
    if w and (kids.min() < 0 or kids.max() > k or len(set(kids.tolist())) != w):
        raise WireError("invalid", "relink-window epochs not distinct, negative or after the state's epoch")
    if (np.isnan(f[16]) or f[16] < 0 or (n + m and ids[:n + m].min() < 0) or (n and rng.min() < 0)
            or not (0 <= f[17] <= 1e6 and f[17] == int(f[17]))):
        raise WireError("invalid", "negative range/delta/link count or id")
    if m and not ((np.abs(bear[:, 0]) <= np.pi).all() and (np.abs(bear[:, 1]) <= np.pi / 2).all()
                  and (bear[:, 2] > 0).all()):
        raise WireError("invalid", "bearing out of range (|az| <= pi, |el| <= pi/2, sigma > 0)")
    _check_scope(u, k, uav, min_k)
    return NodeState(uav=u, k=k, r=r, t=float(f[0]), pos=f[1:4].copy(), pos_cov=f[4:13].reshape(3, 3).copy(),
                     vel=f[13:16].copy(), delta_m=float(f[16]), ranges=dict(zip(ids[:n].tolist(), rng.tolist())),
                     quat=q.copy() if q.any() else None, n_links=int(f[17]),
                     traj={int(e): p.copy() for e, p in zip(kids.tolist(), traj)},
                     bearings={int(o): (float(b[0]), float(b[1]), float(b[2])) for o, b in zip(ids[n:n + m].tolist(), bear)})


class GnssPart(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    pos: Vec3
    vel: Vec3
    pos_sigma: Annotated[list[Pos], Field(min_length=3, max_length=3)]
    vel_sigma: Pos


class InputHeader(UavMsg):
    """JSON header of the binary ``input`` frame (one per UAV and epoch)."""

    t: Finite
    t_prev: Finite
    participants: list[UavId]
    altitude: Finite | None = None
    altitude_sigma: Pos | None = None
    gnss: GnssPart | None = None
    n_imu: int = Field(ge=0)
    n_range: int = Field(ge=0)
    n_rel: int = Field(ge=0)
    n_tdoa: int = Field(0, ge=0)


# (name, columns) of the float64 and int64 blocks; lengths: n_imu, n_range, n_rel or n_tdoa rows
_INPUT_F = (("imu_t", "n_imu", 1), ("gyro", "n_imu", 3), ("accel", "n_imu", 3), ("range_t", "n_range", 1),
            ("range_m", "n_range", 1), ("range_sigma", "n_range", 1), ("rel_az", "n_rel", 1), ("rel_el", "n_rel", 1),
            ("rel_sigma", "n_rel", 1), ("tdoa_t", "n_tdoa", 1), ("tdoa_m", "n_tdoa", 1), ("tdoa_sigma", "n_tdoa", 1))
_INPUT_I = (("range_other", "n_range"), ("range_tag_self", "n_range"), ("range_tag_other", "n_range"), ("rel_target", "n_rel"),
            ("tdoa_listener", "n_tdoa"), ("tdoa_tag", "n_tdoa"), ("tdoa_init", "n_tdoa"), ("tdoa_tag_init", "n_tdoa"), ("tdoa_resp", "n_tdoa"),
            ("tdoa_tag_resp", "n_tdoa"))


def encode_input(inp: EpochInput, participants: list[int]) -> bytes:
    g = None
    if inp.gnss_pos is not None:
        g = GnssPart(pos=_f(inp.gnss_pos), vel=_f(inp.gnss_vel), pos_sigma=_f(inp.gnss_pos_sigma), vel_sigma=float(inp.gnss_vel_sigma))
    h = InputHeader(uav=inp.uav, k=inp.k, t=inp.t, t_prev=inp.t_prev, participants=sorted(int(p) for p in participants),
                    altitude=inp.altitude, altitude_sigma=inp.altitude_sigma, gnss=g, n_imu=len(inp.imu_t),
                    n_range=len(inp.range_t), n_rel=len(inp.rel_target), n_tdoa=len(inp.tdoa_m)).encode()
    body = [np.ascontiguousarray(getattr(inp, name), "<f8").tobytes() for name, _, _ in _INPUT_F]
    body += [np.ascontiguousarray(getattr(inp, name), "<i8").tobytes() for name, _ in _INPUT_I]
    return _INPUT_HDR.pack(_INPUT_MAGIC, SCHEMA_VERSION, len(h)) + h + b"".join(body)


def decode_input(payload: bytes, *, uav: int | None = None, min_k: int | None = None) -> tuple[EpochInput, list[int]]:
    """Binary input frame -> (EpochInput, participants); WireError on anything malformed or out of range."""
    _check_magic(payload, _INPUT_MAGIC, _INPUT_HDR.size)
    _, _, hl = _INPUT_HDR.unpack_from(payload)
    o = _INPUT_HDR.size + hl
    h: InputHeader = decode(InputHeader, bytes(payload[_INPUT_HDR.size:o]), uav=uav, min_k=min_k)
    n = {"n_imu": h.n_imu, "n_range": h.n_range, "n_rel": h.n_rel, "n_tdoa": h.n_tdoa}
    nf = sum(n[c] * w for _, c, w in _INPUT_F)
    ni = sum(n[c] for _, c in _INPUT_I)
    if len(payload) != o + 8 * (nf + ni):
        raise WireError("malformed", f"input frame of {len(payload)} bytes, header says {o + 8 * (nf + ni)}")
    f = np.frombuffer(payload, "<f8", nf, o).astype(np.float64)
    i = np.frombuffer(payload, "<i8", ni, o + 8 * nf).astype(np.int64)
    if not np.isfinite(f).all():
        raise WireError("invalid", "non-finite value in the input arrays")
    a: dict[str, np.ndarray] = {}
    p = 0
    for name, c, w in _INPUT_F:
        m = n[c] * w
        a[name] = f[p:p + m].reshape(-1, 3) if w == 3 else f[p:p + m]
        p += m
    p = 0
    for name, c in _INPUT_I:
        a[name] = i[p:p + n[c]]
        p += n[c]
    if h.n_range and (a["range_m"].min() < 0 or a["range_m"].max() > MAX_UWB_M or a["range_sigma"].min() <= 0
                      or a["range_other"].min() < 0
                      or a["range_tag_self"].min() < 0 or a["range_tag_other"].min() < 0):
        raise WireError("invalid", f"negative or > {MAX_UWB_M:g} m range, sigma <= 0 or negative id")
    if h.n_rel and (a["rel_sigma"].min() <= 0 or a["rel_target"].min() < 1):
        raise WireError("invalid", "non-positive sigma or bad target id")
    if h.n_tdoa and (a["tdoa_sigma"].min() <= 0 or a["tdoa_listener"].min() < 1 or np.abs(a["tdoa_m"]).max() > MAX_UWB_M
                     or min(a[c].min() for c in ("tdoa_tag", "tdoa_init", "tdoa_tag_init", "tdoa_resp", "tdoa_tag_resp")) < 0):
        raise WireError("invalid", f"tdoa: |rdiff| > {MAX_UWB_M:g} m, sigma <= 0 or bad id")
    if (a["range_other"] == h.uav).any() or (a["rel_target"] == h.uav).any():
        raise WireError("invalid", "a UAV cannot range to or observe itself")
    inp = EpochInput(uav=h.uav, k=h.k, t=h.t, t_prev=h.t_prev, imu_t=a["imu_t"], gyro=a["gyro"], accel=a["accel"],
                     altitude=h.altitude, altitude_sigma=h.altitude_sigma)
    if h.gnss is not None:
        g = h.gnss
        inp.gnss_pos, inp.gnss_vel = np.array(g.pos, np.float64), np.array(g.vel, np.float64)
        inp.gnss_pos_sigma, inp.gnss_vel_sigma = np.array(g.pos_sigma, np.float64), g.vel_sigma
    if h.n_range:
        inp.range_t, inp.range_other, inp.range_tag_self, inp.range_tag_other = (a["range_t"], a["range_other"],
                                                                                 a["range_tag_self"], a["range_tag_other"])
        inp.range_m, inp.range_sigma = a["range_m"], a["range_sigma"]
    if h.n_rel:
        inp.rel_target, inp.rel_az, inp.rel_el, inp.rel_sigma = a["rel_target"], a["rel_az"], a["rel_el"], a["rel_sigma"]
    if h.n_tdoa:
        for name in ("tdoa_t", "tdoa_m", "tdoa_sigma", "tdoa_listener", "tdoa_tag", "tdoa_init", "tdoa_tag_init", "tdoa_resp", "tdoa_tag_resp"):
            setattr(inp, name, a[name])
    return inp, list(h.participants)
