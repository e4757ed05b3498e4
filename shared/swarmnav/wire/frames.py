"""Binary frames for the bulky per-epoch traffic: the sensor input of a UAV's epoch and the peer
state of a round. They are most of the traffic, so they travel as little-endian arrays, not JSON.

* ``uav/<id>/input`` (sensor-sim -> node): ONE message per UAV and epoch with the whole
  EpochInput. Frame: ``b"SNI"`` + version byte, uint32 LE length of a JSON header (an
  :class:`InputHeader`, pydantic-validated: ids, times, participants, GNSS fix, altitude and the
  array lengths), then the arrays as little-endian float64/int64 in :data:`_INPUT_F` /
  :data:`_INPUT_I` order. The arrays are validated with numpy after decoding (finite, ranges
  >= 0, sigmas > 0, ids >= 0, no self-ranging or self-observation).
* ``uav/<id>/state`` (node -> peers, every round; also the state queryable's history replies):
  ``b"SNS"`` + version byte, int32 LE uav, k, r, uint32 n (ranges), uint32 m (bearings), uint32 w
  (relink-window positions), float64 LE [t, pos(3), pos_cov(9, row-major), vel(3), delta_m,
  n_links, quat(4: w, x, y, z; all zero = no attitude), range values(n), bearings (az, el,
  sigma)(m), positions (3)(w)], int64 LE range peer ids(n), bearing target ids(m), position
  epochs(w). Decoded straight into the core's NodeState.

float64 bytes are copied, so values arrive bit-identical.
"""

from __future__ import annotations

import math
import struct
import sys
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..dataset import EpochInput
from ..estimators.base import NodeState
from . import _frames  # C: built by `make setup` (setup.py)
from .codec import (ENVELOPE_M, MAX_UWB_M, MAX_VAR_M2, SCHEMA_VERSION, Finite, Pos, UavId, UavMsg, Vec3, WireError,
                    check_position_cov, check_scope, decode)

_STATE_MAGIC = b"SNS"
_INPUT_MAGIC = b"SNI"
_STATE_HDR = struct.Struct("<3sBiiiIII")
_INPUT_HDR = struct.Struct("<3sBI")
_STATE_NF = 22  # t, pos 3, cov 9, vel 3, delta_m, n_links, quat 4, then n range values
_STATE_FIXED = struct.Struct("<22d")
_LITTLE = sys.byteorder == "little"  # the frame is little-endian: native arrays can view it


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
    quat = (0.0, 0.0, 0.0, 0.0) if s.quat is None else np.asarray(s.quat, np.float64).ravel().tolist()
    fixed = _STATE_FIXED.pack(float(s.t), *np.asarray(s.pos, np.float64).ravel().tolist(),
                              *np.asarray(s.pos_cov, np.float64).ravel().tolist(),
                              *np.asarray(s.vel, np.float64).ravel().tolist(), float(s.delta_m), float(s.n_links), *quat)
    f = np.empty(n + 3 * m + 3 * w, np.float64)
    f[:n] = [s.ranges[o] for o in ids]
    f[n:n + 3 * m] = np.asarray([s.bearings[o] for o in bids], np.float64).ravel()
    f[n + 3 * m:] = np.asarray([s.traj[k] for k in kids], np.float64).ravel()
    return (_STATE_HDR.pack(_STATE_MAGIC, SCHEMA_VERSION, int(s.uav), int(s.k), int(s.r), n, m, w) + fixed
            + f.astype("<f8", copy=False).tobytes() + np.asarray(ids + bids + kids, "<i8").tobytes())


def decode_state(payload: bytes, *, uav: int | None = None, min_k: int | None = None,
                 envelope_m: float = ENVELOPE_M) -> NodeState:
    """Binary state frame -> NodeState; WireError(malformed|version|invalid|envelope|covariance|wrong_uav|stale).

    The checks and the parse run in C (``_frames.state_frame``: ~3 µs of the ~11 µs a decoded state
    costs; a node of a 100-UAV swarm decodes ~100 peer states per epoch). A frame that fails any of
    them is decoded again by :func:`decode_state_py`, the reference, which names the error: the C
    code only says whether a frame is valid, and tests/test_frames_c.py holds it to the reference
    on real and mutated frames."""
    try:
        env = float(envelope_m)  # C compares with a double; an envelope no double equals (an int past 2**53) -> the reference
    except OverflowError:  # an int beyond the doubles: NaN equals nothing, so the reference too
        env = math.nan
    got = _frames.state_frame(payload, SCHEMA_VERSION, env, ENVELOPE_M, MAX_VAR_M2) if env == envelope_m else None
    if got is None:
        return decode_state_py(payload, uav=uav, min_k=min_k, envelope_m=envelope_m)
    check_scope(got[0], got[1], uav, min_k)
    return _node_state(payload, *got)


def decode_state_py(payload: bytes, *, uav: int | None = None, min_k: int | None = None,
                    envelope_m: float = ENVELOPE_M) -> NodeState:
    """The reference decoder of a state frame (what :func:`decode_state` does in C, and the error it
    raises): read with ``struct`` into Python floats and ints and checked in plain arithmetic."""
    _check_magic(payload, _STATE_MAGIC, _STATE_HDR.size)
    _, _, u, k, r, n, m, w = _STATE_HDR.unpack_from(payload)
    nf = _STATE_NF + n + 3 * m + 3 * w
    if len(payload) != _STATE_HDR.size + 8 * nf + 8 * (n + m + w):
        raise WireError("malformed", f"state frame of {len(payload)} bytes for {n} ranges, {m} bearings, {w} positions")
    fx = struct.unpack_from(f"<{nf}d", payload, _STATE_HDR.size)  # the fixed 22, then the variable part
    ids = struct.unpack_from(f"<{n + m + w}q", payload, _STATE_HDR.size + 8 * nf)
    if u < 1 or k < 0 or r < 0:
        raise WireError("invalid", f"ids uav {u} k {k} r {r}")
    if not (all(map(math.isfinite, fx[:16])) and all(map(math.isfinite, fx[18:]))):
        raise WireError("invalid", "non-finite value")
    check_position_cov(fx[1:4], fx[4:13], envelope_m)
    o_b, o_w = _STATE_NF + n, _STATE_NF + n + 3 * m  # offsets of the bearings and the window in fx
    if max(map(abs, fx[13:16])) > ENVELOPE_M or (w and max(map(abs, fx[o_w:])) > envelope_m):
        raise WireError("envelope", "velocity or window position outside the envelope")
    q = fx[18:22]
    q0, q1, q2, q3 = q
    if any(q) and abs(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3) - 1.0) > 1e-6:  # = sqrt(sum(x * x for x in q))
        raise WireError("invalid", "attitude quaternion not of unit norm")
    rng, kids = fx[_STATE_NF:o_b], ids[n + m:]
    if w and (min(kids) < 0 or max(kids) > k or len(set(kids)) != w):
        raise WireError("invalid", "relink-window epochs not distinct, negative or after the state's epoch")
    if (math.isnan(fx[16]) or fx[16] < 0 or (n + m and min(ids[:n + m]) < 0) or (n and min(rng) < 0)
            or not (0 <= fx[17] <= 1e6 and fx[17] == int(fx[17]))):
        raise WireError("invalid", "negative range/delta/link count or id")
    az, el, sg = fx[o_b:o_w:3], fx[o_b + 1:o_w:3], fx[o_b + 2:o_w:3]
    if m and not (max(map(abs, az)) <= math.pi and max(map(abs, el)) <= math.pi / 2 and min(sg) > 0):
        raise WireError("invalid", "bearing out of range (|az| <= pi, |el| <= pi/2, sigma > 0)")
    check_scope(u, k, uav, min_k)
    bid = ids[n:n + m]
    return _node_state(payload, u, k, r, fx[0], fx[1:4], fx[4:13], fx[13:16], fx[16], int(fx[17]),
                       q if any(q) else None, dict(zip(ids[:n], rng)), dict(zip(bid, zip(az, el, sg))), kids, fx[o_w:],
                       all(a < b for a, b in zip(bid, bid[1:])))


def _node_state(payload, u, k, r, t, pos, cov, vel, delta_m, n_links, quat, ranges, bearings, kids, window,
                ascending) -> NodeState:
    """The NodeState of a valid frame from its values (both decoders): pos, vel (3), cov (9, row-major),
    quat (4) or None, window (3 per epoch of kids) as float sequences. ``ascending``: the bearings are
    in the encoder's order (by target, no repeats), so ``bearing_rows`` are the frame's bytes as they
    lie (read-only views; the same numbers its cached property would build)."""
    st = NodeState(uav=u, k=k, r=r, t=t, pos=np.array(pos), pos_cov=np.array(cov).reshape(3, 3), vel=np.array(vel),
                   delta_m=delta_m, ranges=ranges, quat=None if quat is None else np.array(quat), n_links=n_links,
                   traj=dict(zip(kids, np.array(window).reshape(-1, 3))) if kids else {}, bearings=bearings)
    if bearings and ascending and type(payload) is bytes and _LITTLE:
        _bearing_views(st, payload)
    return st


def _bearing_views(st: NodeState, payload: bytes) -> None:
    """``st.bearing_rows`` as views of the frame's bytes (see :func:`_node_state`)."""
    n, m, w = _STATE_HDR.unpack_from(payload)[5:]
    nf = _STATE_NF + n + 3 * m + 3 * w
    st.__dict__["bearing_rows"] = (np.frombuffer(payload, np.int64, m, _STATE_HDR.size + 8 * (nf + n)),
                                   np.frombuffer(payload, np.float64, 3 * m, _STATE_HDR.size + 8 * (_STATE_NF + n)).reshape(m, 3))


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


def _f(a) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).ravel()]


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
