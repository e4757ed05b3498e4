"""What every wire encoding shares: the schema version, the plausibility limits, :class:`WireError`
and the checks that raise it, the pydantic base of the JSON messages with :func:`decode`, and the
:class:`Rejects` counter the services keep.

Receivers decode with what the key told them (the UAV id) and the oldest epoch they still accept;
anything malformed, of an unknown version, out of range (NaN/inf, negative range or sigma, bad
ids), about the wrong UAV or a stale epoch raises :class:`WireError`, whose ``reason`` the
services count per topic (:class:`Rejects`) before dropping the message and carrying on.
Pure: no zenoh.
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

SCHEMA_VERSION = 6  # 2: binary input/state frames; 3: states carry az/el bearings; 4: tdoa inputs;
#                    5: states carry the relink window's smoothed positions (traj);
#                    6: history replies carry the state frames (one encoding of a state)

# no UWB range or range difference is this long: larger (finite) values are hostile or corrupt
MAX_UWB_M = 1e5
# plausible envelope of a position (m, any ENU axis, local frame) and of a variance (m^2): a state or
# estimate outside it is rejected as corrupt or hostile. Receivers may pass a tighter envelope_m.
ENVELOPE_M = 1e6
MAX_VAR_M2 = 1e12


class WireError(ValueError):
    """A received message was rejected. ``reason`` is a short class for counting."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def check_position_cov(pos, cov, envelope_m: float = ENVELOPE_M) -> None:
    """WireError unless ``pos`` (3) lies inside the envelope and ``cov`` (3x3 or 9, row-major) is
    symmetric positive definite (Sylvester: leading minors > 0) with variances below MAX_VAR_M2.
    Plain float arithmetic: it runs on every received peer state."""
    if isinstance(pos, tuple) and isinstance(cov, tuple):  # a decoded frame's floats (frames.decode_state)
        p, (a, b, c, d, e, f, g, h, i) = pos, cov
    else:
        p = [float(x) for x in np.asarray(pos, np.float64).ravel().tolist()]
        a, b, c, d, e, f, g, h, i = (float(x) for x in np.asarray(cov, np.float64).ravel().tolist())
    if not all(map(math.isfinite, (*p, a, b, c, d, e, f, g, h, i))):
        raise WireError("invalid", "non-finite position or covariance")
    if max(map(abs, p)) > envelope_m:
        raise WireError("envelope", f"position {max(abs(x) for x in p):.3g} m from the origin, outside the {envelope_m:g} m envelope")
    tol = 1e-9 * max(abs(a), abs(e), abs(i), 1e-300)
    if abs(b - d) > tol or abs(c - g) > tol or abs(f - h) > tol:
        raise WireError("covariance", "position covariance not symmetric")
    if max(a, e, i) > MAX_VAR_M2:
        raise WireError("covariance", f"position variance {max(a, e, i):.3g} m^2 implausibly large")
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if not (a > 0 and a * e - b * d > 0 and det > 0):
        raise WireError("covariance", "position covariance not positive definite")


def check_scope(u, k, uav: int | None, min_k: int | None) -> None:
    """WireError if a message about UAV ``u``, epoch ``k`` is not for ``uav`` or older than ``min_k``."""
    if uav is not None and u != uav:
        raise WireError("wrong_uav", f"message about UAV {u} on UAV {uav}'s key")
    if min_k is not None and k < min_k:
        raise WireError("stale", f"epoch {k} < {min_k}")


# -- JSON messages: pydantic models with ``v``, floats as the shortest repr that round-trips ------

Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
UavId = Annotated[int, Field(ge=1)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Mat3 = Annotated[list[Finite], Field(min_length=9, max_length=9)]  # row-major 3x3
Quat = Annotated[list[Finite], Field(min_length=4, max_length=4)]  # w, x, y, z body -> ENU


class Msg(BaseModel):
    """A JSON wire message: every one carries ``v`` (:data:`SCHEMA_VERSION`); NaN and inf never travel."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, ser_json_inf_nan="constants", strict=False)
    v: Literal[SCHEMA_VERSION] = SCHEMA_VERSION

    def encode(self) -> bytes:
        return self.model_dump_json().encode()


class UavMsg(Msg):
    """A message about one UAV's epoch ``k``: receivers check both against the key and their clock."""

    uav: UavId
    k: int = Field(ge=0)


def decode(cls: type[Msg], payload: bytes | str, *, uav: int | None = None, min_k: int | None = None) -> Msg:
    """Parse and validate; raise WireError(reason) on anything the receiver must not use.

    Fast path: pydantic's own JSON parser (``model_validate_json``, ~2.5x cheaper than ``json.loads``
    + ``model_validate`` for an estimate: the monitor and the sensor-sim decode every one). Anything
    it does not accept (or that lacks ``v``) goes through the original two-step path below, which then
    accepts or rejects it exactly as before, with the same reason (``malformed`` / ``version`` /
    ``invalid``)."""
    try:
        m = cls.model_validate_json(payload)
    except (ValidationError, ValueError, TypeError):
        return _decode_slow(cls, payload, uav=uav, min_k=min_k)
    if "v" not in m.model_fields_set:  # ``v`` has a default, but a message without one is rejected
        return _decode_slow(cls, payload, uav=uav, min_k=min_k)
    check_scope(getattr(m, "uav", uav), getattr(m, "k", min_k), uav, min_k)
    return m


def _decode_slow(cls: type[Msg], payload: bytes | str, *, uav: int | None = None, min_k: int | None = None) -> Msg:
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
    check_scope(getattr(m, "uav", uav), getattr(m, "k", min_k), uav, min_k)
    return m


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
