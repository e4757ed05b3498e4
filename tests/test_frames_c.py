"""The peer-state frame's C checks (``swarmnav.wire._frames``) held to the Python reference decoder
(``frames.decode_state_py``): on valid frames and on frames mutated at random and at every
threshold, C accepts exactly the frames the reference accepts, and what it returns is the
reference's NodeState to the last bit. C decides only "valid or not": a frame it refuses is
decoded by the reference, which names the error."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from swarmnav.estimators.base import NodeState
from swarmnav.wire import _frames, frames
from swarmnav.wire.codec import ENVELOPE_M, MAX_VAR_M2, SCHEMA_VERSION, WireError

HDR, NF = frames._STATE_HDR.size, frames._STATE_NF


def _random_state(rng: np.random.Generator) -> NodeState:
    """A valid state with random sizes (none, few or many ranges, bearings and window epochs)."""
    k = int(rng.integers(0, 400))
    a = rng.normal(size=(3, 3))
    cov = a @ a.T + np.eye(3) * float(rng.uniform(1e-6, 10.0))
    n, m, w = (int(rng.choice([0, 1, 2, 7, 30])) for _ in range(3))
    peers = rng.choice(np.arange(1, 2000), n + m, replace=False)
    quat = None
    if rng.random() < 0.7:
        q = rng.normal(size=4)
        quat = q / np.linalg.norm(q)
    return NodeState(
        uav=int(rng.integers(1, 2000)), k=k, r=int(rng.integers(0, 11)), t=float(rng.uniform(-1e3, 1e5)),
        pos=rng.uniform(-5e3, 5e3, 3), pos_cov=cov, vel=rng.normal(0, 20, 3),
        delta_m=float("inf") if rng.random() < 0.3 else float(rng.uniform(0, 5)),
        ranges={int(p): float(rng.uniform(0, 500)) for p in peers[:n]},
        bearings={int(p): (float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(-1.5, 1.5)), float(rng.uniform(1e-4, 0.1)))
                  for p in peers[n:]},
        quat=quat, n_links=int(rng.integers(0, 40)),
        traj={int(e): rng.uniform(-5e3, 5e3, 3) for e in rng.choice(np.arange(0, k + 1), min(w, k + 1), replace=False)})


def _c(payload, envelope_m=ENVELOPE_M):
    return _frames.state_frame(payload, SCHEMA_VERSION, envelope_m, ENVELOPE_M, MAX_VAR_M2)


def _reference(payload, envelope_m=ENVELOPE_M):
    """The reference's verdict: its NodeState, or the WireError's text."""
    try:
        return frames.decode_state_py(payload, envelope_m=envelope_m)
    except WireError as e:
        return str(e)


def _bits(x) -> bytes:
    return np.asarray(x, np.float64).tobytes()


def _same_state(a: NodeState, b: NodeState) -> None:
    assert (a.uav, a.k, a.r, a.n_links) == (b.uav, b.k, b.r, b.n_links)
    assert type(a.n_links) is type(b.n_links) is int
    for x, y in ((a.t, b.t), (a.delta_m, b.delta_m), (a.pos, b.pos), (a.pos_cov, b.pos_cov), (a.vel, b.vel)):
        assert _bits(x) == _bits(y) and np.shape(x) == np.shape(y)
    assert (a.quat is None) == (b.quat is None) and (a.quat is None or _bits(a.quat) == _bits(b.quat))
    assert list(a.ranges) == list(b.ranges) and _bits(list(a.ranges.values())) == _bits(list(b.ranges.values()))
    assert list(a.bearings) == list(b.bearings)
    assert all(type(v) is tuple and _bits(v) == _bits(b.bearings[t]) for t, v in a.bearings.items())
    assert list(a.traj) == list(b.traj) and all(_bits(v) == _bits(b.traj[e]) and v.shape == (3,) for e, v in a.traj.items())
    assert all(type(j) is int for j in [*a.ranges, *a.bearings, *a.traj])
    assert type(a.t) is type(b.t) is float and type(a.delta_m) is type(b.delta_m) is float
    assert all(type(v) is float for v in [*a.ranges.values(), *(x for t in a.bearings.values() for x in t)])
    # whether the decoder set the frame's views: asked before reading the cached property, which
    # would otherwise put it in both __dict__s and make the comparison vacuous
    assert ("bearing_rows" in a.__dict__) == ("bearing_rows" in b.__dict__)
    for x, y in zip(a.bearing_rows, b.bearing_rows):
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
        assert x.flags.writeable == y.flags.writeable


def _agree(payload: bytes, envelope_m: float = ENVELOPE_M) -> bool:
    """C and the reference agree on ``payload``; True when it is valid."""
    ref = _reference(payload, envelope_m)
    got = _c(payload, envelope_m)
    assert (got is None) == isinstance(ref, str), (ref if isinstance(ref, str) else "valid", payload[:32])
    if got is None:
        return False
    _same_state(frames.decode_state(payload, envelope_m=envelope_m), ref)
    return True


def test_valid_frames_decode_to_the_reference_bit_for_bit():
    rng = np.random.default_rng(20261207)
    for _ in range(400):
        s = _random_state(rng)
        assert _agree(frames.encode_state(s))


def _f64_slots(payload: bytes) -> tuple[int, int, int, int, int]:
    n, m, w = frames._STATE_HDR.unpack_from(payload)[5:]
    return n, m, w, NF + n + 3 * m + 3 * w, n + m + w


# values at and around every threshold the checks use
_EDGES = [0.0, -0.0, 1.0, -1.0, math.nan, -math.nan, math.inf, -math.inf, 5e-324, -5e-324, 1e-300, 1e308, -1e308,
          math.pi, math.nextafter(math.pi, 4), -math.pi, math.nextafter(-math.pi, -4), math.pi / 2,
          math.nextafter(math.pi / 2, 2), -math.pi / 2, math.nextafter(-math.pi / 2, -2), ENVELOPE_M,
          math.nextafter(ENVELOPE_M, 2e6), -ENVELOPE_M, MAX_VAR_M2, math.nextafter(MAX_VAR_M2, 2e12), 1e6 - 1,
          2.5, 1e6 + 1, 1.0 + 1e-6, 1.0 + 2e-6, 1e-9, 1e154, 1e200]
_ID_EDGES = [0, -1, 1, 2**63 - 1, -2**63, 5, 400, 401]


def _mutate(rng: np.random.Generator, payload: bytes) -> bytes:
    b = bytearray(payload)
    n, m, w, nf, ni = _f64_slots(payload)
    kind = rng.integers(0, 9)
    if kind == 0:  # one float slot set to an edge value
        i = int(rng.integers(0, nf))
        struct.pack_into("<d", b, HDR + 8 * i, float(rng.choice(_EDGES)))
    elif kind == 1 and ni:  # one id set to an edge value or to another id of the frame (a repeat)
        i = int(rng.integers(0, ni))
        v = int(rng.choice(_ID_EDGES)) if rng.random() < 0.6 else struct.unpack_from("<q", b, HDR + 8 * (nf + int(rng.integers(0, ni))))[0]
        struct.pack_into("<q", b, HDR + 8 * (nf + i), v)
    elif kind == 2:  # header ints
        i = int(rng.integers(0, 6))
        v = int(rng.choice([0, -1, 1, 2, 7, 2**31 - 1, -2**31])) if i < 3 else int(rng.choice([0, 1, 3, 2**32 - 1]))
        struct.pack_into("<i" if i < 3 else "<I", b, 4 + 4 * i, v)
    elif kind == 3:  # random bytes flipped anywhere
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
    elif kind == 4:  # truncated or extended
        b = b[:int(rng.integers(0, len(b)))] if rng.random() < 0.5 else b + bytes(int(rng.integers(1, 17)))
    elif kind == 5:  # magic or version
        b[int(rng.integers(0, 4))] = int(rng.integers(0, 256))
    elif kind == 6:  # the covariance made asymmetric, indefinite or scaled by a little
        i = 4 + int(rng.integers(0, 9))
        x = struct.unpack_from("<d", b, HDR + 8 * i)[0]
        struct.pack_into("<d", b, HDR + 8 * i, x * float(rng.choice([1 + 1e-12, 1 + 1e-8, -1.0, 0.0, 1e6, 1e12])))
    elif kind == 7:  # a quaternion nudged around unit norm
        q = np.frombuffer(bytes(b[HDR + 8 * 18:HDR + 8 * 22]), "<f8") * float(rng.choice([1 + 5e-7, 1 + 2e-6, 0.0, -1.0]))
        b[HDR + 8 * 18:HDR + 8 * 22] = q.astype("<f8").tobytes()
    else:  # n_links or delta_m on their limits
        i, v = (17, float(rng.choice([0.0, 1e6, 1e6 + 1, 3.5, -0.0, -1.0, 1e300]))) if rng.random() < 0.5 else \
            (16, float(rng.choice([0.0, -0.0, math.inf, -math.inf, math.nan, -1e-300])))
        struct.pack_into("<d", b, HDR + 8 * i, v)
    return bytes(b)


def test_mutated_frames_get_the_references_verdict():
    """~14,000 frames mutated at random (single and repeated mutations): C's verdict is the
    reference's every time, and an accepted frame's values are the reference's bit for bit."""
    rng = np.random.default_rng(7)
    valid = invalid = 0
    for _ in range(4000):
        p = frames.encode_state(_random_state(rng))
        for _ in range(5):
            p = _mutate(rng, p)
            if _agree(p):
                valid += 1
            else:
                invalid += 1
            if len(p) < HDR or len(p) != HDR + 8 * sum(_f64_slots(p)[3:]):
                break  # the next mutation needs the frame's layout
    assert valid > 1000 and invalid > 5000  # both sides of the verdict were exercised


@pytest.mark.parametrize("envelope_m", [2e3, 4.5e3])
def test_receiver_envelope_is_applied_alike(envelope_m):
    rng = np.random.default_rng(int(envelope_m))
    verdicts = set()
    for _ in range(300):
        verdicts.add(_agree(frames.encode_state(_random_state(rng)), envelope_m))
    assert verdicts == {True, False}


def test_not_bytes_or_short_goes_to_the_reference():
    p = frames.encode_state(_random_state(np.random.default_rng(1)))
    assert _c(bytearray(p)) is None and _c(memoryview(p)) is None and _c(b"") is None and _c(p[:HDR - 1]) is None
    assert frames.decode_state(bytearray(p)).uav == frames.decode_state(p).uav  # the reference decodes them
    with pytest.raises(WireError) as e:
        frames.decode_state(b"SNS")
    assert e.value.reason == "malformed"


def test_scope_checked_after_the_c_path():
    s = _random_state(np.random.default_rng(2))
    p = frames.encode_state(s)
    with pytest.raises(WireError) as e:
        frames.decode_state(p, uav=s.uav + 1)
    assert e.value.reason == "wrong_uav"
    with pytest.raises(WireError) as e:
        frames.decode_state(p, min_k=s.k + 1)
    assert e.value.reason == "stale"
    assert frames.decode_state(p, uav=s.uav, min_k=s.k).k == s.k


def test_envelope_that_is_not_a_double_gets_the_references_verdict():
    """The C checks see the receiver's envelope as a double; the reference compares with the value
    itself (an int exactly). An envelope no double equals goes to the reference."""
    p = bytearray(frames.encode_state(_random_state(np.random.default_rng(3))))
    struct.pack_into("<3d", p, HDR + 8, float(2**53 + 4), 0.0, 0.0)  # pos: just past an int envelope of 2**53 + 3
    p = bytes(p)
    assert isinstance(_reference(p, 2**53 + 3), str)
    with pytest.raises(WireError) as e:
        frames.decode_state(p, envelope_m=2**53 + 3)
    assert e.value.reason == "envelope"
    assert frames.decode_state(p, envelope_m=2**53 + 4).uav == frames.decode_state_py(p, envelope_m=2**53 + 4).uav


def test_envelope_beyond_the_doubles_gets_the_references_verdict():
    """An int envelope too large for a double (float() raises OverflowError) also goes to the
    reference, which compares with the int itself, instead of failing the decode."""
    p = frames.encode_state(_random_state(np.random.default_rng(4)))
    assert frames.decode_state(p, envelope_m=10**400).uav == frames.decode_state_py(p, envelope_m=10**400).uav
