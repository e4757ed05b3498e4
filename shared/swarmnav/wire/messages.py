"""The JSON wire messages of the Zenoh deployment (clock, meta, init, truth, estimate, links and the
state queryable's history replies) and their converters to/from the core's dataclasses.

Each message has exactly one encoding: these are pydantic models with a schema version ``v``,
JSON-encoded with the shortest float repr that round-trips (float64 values arrive bit-identical;
NaN and inf never travel). The two bulky kinds, a UAV's epoch input and a peer state, are binary
frames (:mod:`.frames`); a history reply carries the state frames themselves. The shared pieces
(:class:`WireError`, :func:`decode`, :class:`Rejects`, the limits) live in :mod:`.codec`; this
module re-exports them and the frame codec so services need one import. Pure: no zenoh.
"""

from __future__ import annotations

import base64
import binascii
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..estimators.base import InitialState, LinkClass, LinkInfo, NodeEstimate, NodeState
from .codec import (ENVELOPE_M, SCHEMA_VERSION, Finite, Mat3, Msg, NonNeg, Pos, Quat, Rejects, UavId, UavMsg, Vec3,
                    WireError, check_position_cov, decode)
from .frames import decode_input, decode_state, encode_input, encode_state

# what the services use, from one import (``from swarmnav.wire import messages as M``)
__all__ = ["SCHEMA_VERSION", "ENVELOPE_M", "WireError", "Rejects", "decode", "encode_input", "decode_input", "encode_state",
           "decode_state", "InitMsg", "MetaMsg", "TruthMsg", "LinkMsg", "EstimateMsg", "LinksMsg", "HistoryMsg", "ClockMsg",
           "estimate_to_msg", "msg_to_estimate", "init_to_msg", "msg_to_init"]

# -- sensor-sim -> node (the epoch input itself is a binary frame) ----------------------------


class InitMsg(Msg):
    uav: UavId
    t: Finite
    pos: Vec3
    vel: Vec3
    quat: Quat
    pos_sigma: Annotated[list[Pos], Field(min_length=3, max_length=3)]
    vel_sigma: NonNeg
    att_sigma: Annotated[list[NonNeg], Field(min_length=3, max_length=3)]


class MetaMsg(Msg):
    run: str
    seed: int
    meta: dict  # DatasetMeta as JSON (by alias)


class TruthMsg(UavMsg):
    t: Finite
    pos: Vec3
    vel: Vec3
    quat: Quat


# -- node -> peers / monitor (the state of a round is a binary frame) ---------------------------


class LinkMsg(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    other: int = Field(ge=0)
    cls: int = Field(ge=0, le=2)
    # None: not computed (an estimator without detection, e.g. fg, classifies every link H2 with no
    # residual; a NaN here was refused and killed every fg node at its first estimate)
    residual_m: Finite | None
    weight: NonNeg


class EstimateMsg(UavMsg):
    t: Finite
    pos: Vec3
    vel: Vec3
    pos_cov: Mat3
    quat: Quat | None = None
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
            # validated lists of floats: as tuples they take check_position_cov's plain-float path
            check_position_cov(tuple(self.pos), tuple(self.pos_cov))
            check_position_cov(tuple(self.vel), _EYE3)
        except WireError as e:
            raise ValueError(str(e)) from None
        return self


_EYE3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # row-major identity (a velocity's plausibility check)


class LinksMsg(UavMsg):
    links: list[LinkMsg]


EST_HISTORY = 64  # estimates a node keeps for its state queryable (what a HistoryMsg can carry back)


class HistoryMsg(Msg):
    """Reply of the state queryable: the node's latest state frames (oldest first, base64 of
    :func:`.frames.encode_state`, the bytes it published) and its recent estimates."""

    uav: UavId
    states: list[str] = Field(default_factory=list)
    estimates: list[EstimateMsg] = Field(default_factory=list)

    @classmethod
    def of(cls, uav: int, frames: list[bytes], estimates: list[EstimateMsg]) -> HistoryMsg:
        return cls(uav=uav, states=[base64.b64encode(f).decode("ascii") for f in frames], estimates=list(estimates))

    def node_states(self, *, envelope_m: float = ENVELOPE_M) -> list[NodeState]:
        """The states, each checked like a frame on the ``state`` key (about ``uav``); WireError."""
        out = []
        for s in self.states:
            try:
                frame = base64.b64decode(s, validate=True)
            except (binascii.Error, ValueError):
                raise WireError("malformed", "history state not base64") from None
            out.append(decode_state(frame, uav=self.uav, envelope_m=envelope_m))
        return out


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


# -- converters to/from the core's dataclasses ------------------------------------------------


def _f(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).ravel()]


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def residual_or_nan(x) -> float:
    return float("nan") if x is None else float(x)


def estimate_to_msg(e: NodeEstimate, **extra) -> EstimateMsg:
    return EstimateMsg(uav=e.uav, k=e.k, t=float(e.t), pos=_f(e.pos), vel=_f(e.vel), pos_cov=_f(e.pos_cov),
                       quat=None if e.quat is None else _f(e.quat),
                       links=[LinkMsg(other=int(li.other), cls=int(li.cls), residual_m=_finite_or_none(li.residual_m),
                                      weight=float(li.weight)) for li in e.links],
                       rounds=int(e.rounds), step_ms=float(e.step_ms),
                       delta_h_m=None if e.delta_h_m is None else float(e.delta_h_m),
                       delta_l_m=None if e.delta_l_m is None else float(e.delta_l_m), **extra)


def msg_to_estimate(m: EstimateMsg) -> NodeEstimate:
    return NodeEstimate(uav=m.uav, k=m.k, t=m.t, pos=np.array(m.pos, np.float64), vel=np.array(m.vel, np.float64),
                        pos_cov=np.array(m.pos_cov, np.float64).reshape(3, 3),
                        quat=None if m.quat is None else np.array(m.quat, np.float64),
                        links=[LinkInfo(li.other, LinkClass(li.cls), residual_or_nan(li.residual_m), li.weight)
                               for li in m.links],
                        rounds=m.rounds, step_ms=m.step_ms, delta_h_m=m.delta_h_m, delta_l_m=m.delta_l_m)


def init_to_msg(uav: int, s: InitialState) -> InitMsg:
    return InitMsg(uav=uav, t=float(s.t), pos=_f(s.pos), vel=_f(s.vel), quat=_f(s.quat), pos_sigma=_f(s.pos_sigma),
                   vel_sigma=float(s.vel_sigma), att_sigma=_f(s.att_sigma))


def msg_to_init(m: InitMsg) -> InitialState:
    a = lambda x: np.array(x, np.float64)  # noqa: E731
    return InitialState(t=m.t, pos=a(m.pos), vel=a(m.vel), quat=a(m.quat), pos_sigma=a(m.pos_sigma),
                        vel_sigma=m.vel_sigma, att_sigma=a(m.att_sigma))
