"""Wire messages (JSON models and binary frames): float64-exact round trips and rejection of bad input
with the reason the receivers count."""

import json
import logging

import numpy as np
import pytest

from swarmnav.dataset import EpochInput
from swarmnav.estimators.base import InitialState, LinkClass, LinkInfo, NodeEstimate, NodeState
from swarmnav.wire import messages as M


def _state(rng):
    return NodeState(3, 5, 2, 5.0, rng.normal(size=3) * 1e3, np.diag(rng.random(3)), rng.normal(size=3),
                     float("inf"), {1: 12.345678901234567, 7: float(rng.random() * 400)},
                     {1: (float(rng.uniform(-3, 3)), float(rng.uniform(-1.5, 1.5)), 0.017453292519943295),
                      9: (-np.pi, np.pi / 2, 1e-3)}, _unit_quat(rng), n_links=7,
                     traj={4: rng.normal(size=3) * 10, 2: rng.normal(size=3)})


def _unit_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _estimate(rng, uav=2, k=9):
    return NodeEstimate(uav, k, 9.0, rng.normal(size=3), rng.normal(size=3), np.eye(3) * 0.3, _unit_quat(rng),
                        [LinkInfo(4, LinkClass.H1_INTERFERED, 2.5, 0.3)], 3, 1.5, 4.0, 0.4)


def test_estimate_round_trip():
    e = _estimate(np.random.default_rng(2))
    e2 = M.msg_to_estimate(M.decode(M.EstimateMsg, M.estimate_to_msg(e).encode(), uav=2))
    assert np.array_equal(e.pos, e2.pos) and np.array_equal(e.vel, e2.vel) and np.array_equal(e.quat, e2.quat)
    assert e2.links[0].cls == LinkClass.H1_INTERFERED and e2.delta_h_m == 4.0 and e2.rounds == 3


def test_estimate_link_without_residual_round_trips():
    """fg (no detection) gives every link a NaN residual: it travels as null and comes back NaN
    (hold-out review: the NaN was refused, so every node of `launch --algo fg` died at epoch 1)."""
    e = _estimate(np.random.default_rng(2))
    e.links = [LinkInfo(4, LinkClass.H2_NORMAL, float("nan"), 1.0), LinkInfo(5, LinkClass.H2_NORMAL, 0.25, 1.0)]
    raw = M.estimate_to_msg(e).encode()
    assert b"NaN" not in raw
    e2 = M.msg_to_estimate(M.decode(M.EstimateMsg, raw, uav=2))
    assert np.isnan(e2.links[0].residual_m) and e2.links[1].residual_m == 0.25


def test_json_floats_exact():
    """JSON messages carry the shortest repr that round-trips: float64 values arrive bit-identical."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2000, 3)) * 10.0 ** rng.integers(-300, 6, (2000, 3))  # inside the 1e6 m envelope
    for row in x:
        e = _estimate(rng)
        e.pos = row
        assert np.array_equal(M.msg_to_estimate(M.decode(M.EstimateMsg, M.estimate_to_msg(e).encode())).pos, row)
    s = InitialState(t=1.0, pos=x[0], vel=x[1], quat=_unit_quat(rng), pos_sigma=np.array([1e-300, 2.5, 3.0]),
                     vel_sigma=0.1, att_sigma=np.array([0.1, 0.2, 0.3]))
    s2 = M.msg_to_init(M.decode(M.InitMsg, M.init_to_msg(4, s).encode(), uav=4))
    assert all(np.array_equal(getattr(s, f), getattr(s2, f)) for f in ("pos", "vel", "quat", "pos_sigma", "att_sigma"))


@pytest.mark.parametrize("mutate,reason", [
    (lambda d: d.update(v=M.SCHEMA_VERSION + 1), "version"),
    (lambda d: d.pop("v"), "version"),
    (lambda d: d.update(step_ms=-1.0), "invalid"),
    (lambda d: d.update(t=float("nan")), "invalid"),
    (lambda d: d.update(vel=[float("inf"), 0.0, 0.0]), "invalid"),
    (lambda d: d.update(quat=[1.0, 0.0, 0.0]), "invalid"),
    (lambda d: d.update(links=[{"other": 4, "cls": 3, "residual_m": 0.0, "weight": 1.0}]), "invalid"),
    (lambda d: d.update(links=[{"other": 4, "cls": 2, "residual_m": float("nan"), "weight": 1.0}]), "invalid"),
    (lambda d: d.update(extra=1), "invalid"),
    (lambda d: d.update(uav=3), "wrong_uav"),
    (lambda d: d.update(k=1), "stale"),
])
def test_rejects(mutate, reason):
    d = json.loads(M.estimate_to_msg(_estimate(np.random.default_rng(3), k=4)).encode())
    mutate(d)
    payload = json.dumps(d).encode()  # json writes NaN as NaN: must still be rejected
    with pytest.raises(M.WireError) as e:
        M.decode(M.EstimateMsg, payload, uav=2, min_k=3)
    assert e.value.reason == reason


@pytest.mark.parametrize("payload", [b"", b"\xff\xfe", b"[1,2]", b"{", b"null", b"garbage"])
@pytest.mark.parametrize("cls", [M.ClockMsg, M.HistoryMsg, M.EstimateMsg])
def test_rejects_malformed(payload, cls):
    with pytest.raises(M.WireError) as e:
        M.decode(cls, payload)
    assert e.value.reason in ("malformed", "version")


def test_history_carries_the_state_frames():
    """The state queryable's reply carries the very frames published on ``state`` (one encoding)."""
    rng = np.random.default_rng(0)
    frames = [M.encode_state(_state(rng)) for _ in range(3)]
    ests = [M.estimate_to_msg(_estimate(rng, uav=3))]
    h = M.decode(M.HistoryMsg, M.HistoryMsg.of(3, frames, ests).encode(), uav=3)
    got = h.node_states()
    assert [M.encode_state(s) for s in got] == frames and h.estimates == ests
    assert M.decode(M.HistoryMsg, M.HistoryMsg.of(3, [], []).encode(), uav=3).node_states() == []


def test_history_states_checked_like_frames():
    rng = np.random.default_rng(1)
    good = M.encode_state(_state(rng))
    far = _state(rng)
    far.pos, far.traj = np.array([5e4, 0.0, 0.0]), {}
    for states, reason, kw in (([good[:-1]], "malformed", {}), ([M.encode_state(_state(rng))[:3] + b"\x00" + good[4:]], "version", {}),
                               ([good], "wrong_uav", {"uav": 4}), ([M.encode_state(far)], "envelope", {"envelope_m": 1e4})):
        h = M.HistoryMsg.of(3, states, [])
        if "uav" in kw:
            h = h.model_copy(update={"uav": kw.pop("uav")})
        with pytest.raises(M.WireError) as e:
            M.decode(M.HistoryMsg, h.encode()).node_states(**kw)
        assert e.value.reason == reason
    bad = {**json.loads(M.HistoryMsg.of(3, [good], []).encode()), "states": ["not base64!"]}
    with pytest.raises(M.WireError) as e:
        M.decode(M.HistoryMsg, json.dumps(bad), uav=3).node_states()
    assert e.value.reason == "malformed"


def test_rejects_counter(caplog):
    r = M.Rejects(logging.getLogger("t"))
    with caplog.at_level(logging.WARNING):
        r.add("imu", M.WireError("malformed", "x"))
        r.add("imu", M.WireError("malformed", "y"))
        r.add("state", M.WireError("stale", "z"))
    assert r.total == 3 and r.as_dict() == {"imu:malformed": 2, "state:stale": 1}
    assert "rejected message on imu" in caplog.text


# -- binary frames (uav/<id>/input, uav/<id>/state) ----------------------------------------------


def _input(rng, uav=2, k=4):
    x = rng.normal(size=100) * 10.0 ** rng.integers(-300, 300, 100)  # extreme magnitudes: bytes are copied
    return EpochInput(uav=uav, k=k, t=4.0, t_prev=3.0, imu_t=np.arange(3.0, 4.0, 0.01), gyro=rng.normal(size=(100, 3)),
                      accel=np.c_[x, x, x], gnss_pos=rng.normal(size=3), gnss_vel=rng.normal(size=3),
                      gnss_pos_sigma=np.array([5.0, 5, 8]), gnss_vel_sigma=0.2, range_t=np.array([3.5, 4.0]),
                      range_other=np.array([1, 3]), range_tag_self=np.array([0, 1]), range_tag_other=np.array([0, 0]),
                      range_m=np.array([50.1, 80.2]), range_sigma=np.array([0.1, 0.1]), rel_target=np.array([1]),
                      rel_az=np.array([0.3]), rel_el=np.array([-0.1]), rel_sigma=np.array([0.017]), altitude=12.5,
                      altitude_sigma=0.5)


def _same_input(inp, out):
    for f in inp.__dataclass_fields__:
        a, b = getattr(inp, f), getattr(out, f)
        if isinstance(a, np.ndarray):
            assert a.dtype.kind == b.dtype.kind and a.shape == b.shape and np.array_equal(a, b), f
        else:
            assert a == b, f


def test_input_frame_exact():
    rng = np.random.default_rng(5)
    inp = _input(rng)
    out, part = M.decode_input(M.encode_input(inp, [3, 1, 2]), uav=2, min_k=4)
    assert part == [1, 2, 3]
    _same_input(inp, out)
    # no GNSS, no ranges, no az/el: the defaults of EpochInput stay as they are
    bare = EpochInput(uav=2, k=5, t=5.0, t_prev=4.0, imu_t=inp.imu_t, gyro=inp.gyro, accel=inp.accel)
    _same_input(bare, M.decode_input(M.encode_input(bare, [2]))[0])


def _with_tdoa(inp):
    """A passive-listening epoch: tag 21 of UAV 2 heard 10 (UAV 1) ranging to anchor 3 (node 103)."""
    inp.tdoa_t, inp.tdoa_listener, inp.tdoa_tag = np.array([3.4, 3.9]), np.array([2, 2]), np.array([21, 20])
    inp.tdoa_init, inp.tdoa_tag_init = np.array([1, 3]), np.array([10, 30])
    inp.tdoa_resp, inp.tdoa_tag_resp = np.array([103, 1]), np.array([3, 11])
    inp.tdoa_m, inp.tdoa_sigma = np.array([-1.25, 0.5e-300]), np.array([0.19, 0.2])
    return inp


def test_tdoa_input_round_trips():
    inp = _with_tdoa(_input(np.random.default_rng(11)))
    _same_input(inp, M.decode_input(M.encode_input(inp, [1, 2, 3]), uav=2)[0])


@pytest.mark.parametrize("field, value", [("tdoa_sigma", np.array([0.19, 0.0])), ("tdoa_init", np.array([-1, 3])),
                                          ("tdoa_m", np.array([2e5, 0.0])),
                                          ("tdoa_listener", np.array([0, 2])),
                                          ("tdoa_m", np.array([np.inf, 0.0]))])
def test_tdoa_input_rejects_values(field, value):
    inp = _with_tdoa(_input(np.random.default_rng(12)))
    setattr(inp, field, value)
    with pytest.raises(M.WireError) as e:
        M.decode_input(M.encode_input(inp, [1, 2, 3]), uav=2)
    assert e.value.reason == "invalid"


@pytest.mark.parametrize("mutate, reason", [
    (lambda b: b"not json", "malformed"),
    (lambda b: b[:3] + bytes([M.SCHEMA_VERSION + 1]) + b[4:], "version"),
    (lambda b: b[:-8], "malformed"),
    (lambda b: b[:-8] + np.array([0], "<i8").tobytes(), "invalid"),  # az/el target id 0 (the last int64)
])
def test_input_frame_rejects(mutate, reason):
    b = M.encode_input(_input(np.random.default_rng(6)), [1, 2, 3])
    with pytest.raises(M.WireError) as e:
        M.decode_input(mutate(b), uav=2)
    assert e.value.reason == reason


def test_input_frame_rejects_values():
    rng = np.random.default_rng(7)
    for field, value, reason in (("accel", np.full((100, 3), np.nan), "invalid"), ("range_m", np.array([-1.0, 2.0]), "invalid"),
                                 ("range_sigma", np.array([0.0, 1.0]), "invalid"),
                                 ("range_m", np.array([1e300, 2.0]), "invalid"), ("range_other", np.array([2, 3]), "invalid"),
                                 ("rel_target", np.array([2]), "invalid")):
        inp = _input(rng)
        setattr(inp, field, value)
        with pytest.raises(M.WireError) as e:
            M.decode_input(M.encode_input(inp, [1, 2, 3]), uav=2)
        assert e.value.reason == reason, field
    with pytest.raises(M.WireError) as e:
        M.decode_input(M.encode_input(_input(rng), [1, 2]), uav=3)
    assert e.value.reason == "wrong_uav"
    with pytest.raises(M.WireError) as e:
        M.decode_input(M.encode_input(_input(rng), [1, 2]), uav=2, min_k=5)
    assert e.value.reason == "stale"


def test_state_frame_exact():
    rng = np.random.default_rng(8)
    s = _state(rng)
    s2 = M.decode_state(M.encode_state(s), uav=3, min_k=5)
    assert np.array_equal(s.pos, s2.pos) and np.array_equal(s.pos_cov, s2.pos_cov) and np.array_equal(s.vel, s2.vel)
    assert s2.delta_m == float("inf") and s2.ranges == s.ranges and list(s2.ranges) == sorted(s.ranges)
    assert s2.bearings == s.bearings and list(s2.bearings) == sorted(s.bearings)
    assert np.array_equal(s2.quat, s.quat) and s2.n_links == 7
    assert list(s2.traj) == sorted(s.traj) and all(np.array_equal(s2.traj[k], s.traj[k]) for k in s.traj)
    s.quat = None  # no attitude (e.g. fkf) travels as zeros and comes back as None
    assert M.decode_state(M.encode_state(s)).quat is None
    assert (s2.uav, s2.k, s2.r, s2.t) == (3, 5, 2, 5.0)


def test_state_frame_bearing_rows_are_the_property():
    """decode_state gives NodeState.bearing_rows straight from the frame when its targets are in the
    encoder's order; the numbers equal what the cached property builds from ``bearings``, and a
    frame in another order (hand-made) or in a mutable buffer falls back to the property."""
    from swarmnav.estimators.base import NodeState
    from swarmnav.wire import frames

    rng = np.random.default_rng(12)
    s = _state(rng)
    s.bearings = {int(t): (float(rng.uniform(-3, 3)), float(rng.uniform(-1.5, 1.5)), 0.01 + float(rng.random()))
                  for t in rng.choice(np.arange(4, 90), 12, replace=False)}
    b = M.encode_state(s)
    fast = M.decode_state(b, uav=3)
    assert "bearing_rows" in fast.__dict__  # taken from the frame
    slow = NodeState.bearing_rows.func(fast)  # the property's own computation
    for x, y in zip(fast.bearing_rows, slow):
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
    assert not fast.bearing_rows[1].flags.writeable  # a view of the immutable frame
    assert "bearing_rows" not in M.decode_state(bytearray(b), uav=3).__dict__
    # the same frame with the bearing targets in descending order: decoded alike, rows sorted by the property
    n, m = len(s.ranges), len(s.bearings)
    hdr, nf = frames._STATE_HDR.size, 22 + n + 3 * m + 3 * len(s.traj)
    f = np.frombuffer(b, "<f8", nf, hdr).copy()
    ids = np.frombuffer(b, "<i8", n + m + len(s.traj), hdr + 8 * nf).copy()
    f[22 + n:22 + n + 3 * m] = f[22 + n:22 + n + 3 * m].reshape(m, 3)[::-1].ravel()
    ids[n:n + m] = ids[n:n + m][::-1]
    rev = M.decode_state(b[:hdr] + f.tobytes() + ids.tobytes(), uav=3)
    assert "bearing_rows" not in rev.__dict__ and rev.bearings == fast.bearings
    assert all(np.array_equal(x, y) for x, y in zip(rev.bearing_rows, fast.bearing_rows))


def test_state_frame_rejects():
    rng = np.random.default_rng(9)
    s = _state(rng)
    b = M.encode_state(s)
    cases = [(b"{}", "malformed"), (b[:-1], "malformed"), (b[:3] + bytes([M.SCHEMA_VERSION + 1]) + b[4:], "version")]
    for field, value in (("pos", np.array([np.nan, 0, 0])), ("delta_m", float("nan")), ("delta_m", -1.0)):
        bad = _state(np.random.default_rng(9))
        setattr(bad, field, value)
        cases.append((M.encode_state(bad), "invalid"))
    bad = _state(np.random.default_rng(9))
    bad.ranges = {1: -3.0}
    cases.append((M.encode_state(bad), "invalid"))
    for n_links in (-1, 2.5):
        bad = _state(np.random.default_rng(9))
        bad.n_links = n_links
        cases.append((M.encode_state(bad), "invalid"))
    for quat in (np.array([1.0, 0.1, 0.0, 0.0]), np.array([np.nan, 0.0, 0.0, 0.0])):
        bad = _state(np.random.default_rng(9))
        bad.quat = quat
        cases.append((M.encode_state(bad), "invalid"))
    for bearing in ((0.0, 1.6, 0.01), (3.2, 0.0, 0.01), (0.0, 0.0, 0.0), (0.0, float("nan"), 0.01)):
        bad = _state(np.random.default_rng(9))
        bad.bearings = {4: bearing}
        cases.append((M.encode_state(bad), "invalid"))
    for traj in ({3: np.array([np.inf, 0.0, 0.0])}, {-1: np.zeros(3)}, {6: np.zeros(3)}):  # epoch 6 > k 5
        bad = _state(np.random.default_rng(9))
        bad.traj = traj
        cases.append((M.encode_state(bad), "invalid"))
    for payload, reason in cases:
        with pytest.raises(M.WireError) as e:
            M.decode_state(payload, uav=3)
        assert e.value.reason == reason, (payload[:8], reason)
    with pytest.raises(M.WireError) as e:
        M.decode_state(b, uav=4)
    assert e.value.reason == "wrong_uav"
    with pytest.raises(M.WireError) as e:
        M.decode_state(b, uav=3, min_k=6)
    assert e.value.reason == "stale"


# -- plausibility: hostile or corrupt values in states and estimates (issue "No silent corruption") --


@pytest.mark.parametrize("pos, cov, reason", [
    ([1e300, 0.0, 0.0], np.eye(3), "envelope"),
    ([0.0, 0.0, 2e6], np.eye(3), "envelope"),
    ([1.0, 2.0, 3.0], np.zeros((3, 3)), "covariance"),
    ([1.0, 2.0, 3.0], -np.eye(3), "covariance"),
    ([1.0, 2.0, 3.0], np.diag([1.0, 1.0, -1e-6]), "covariance"),
    ([1.0, 2.0, 3.0], np.array([[1.0, 0.5, 0], [0.0, 1, 0], [0, 0, 1]]), "covariance"),  # not symmetric
    ([1.0, 2.0, 3.0], np.eye(3) * 1e13, "covariance"),  # variance implausibly large
])
def test_state_and_estimate_values_checked(pos, cov, reason):
    rng = np.random.default_rng(3)
    s = _state(rng)
    s.pos, s.pos_cov = np.array(pos, float), np.array(cov, float)
    with pytest.raises(M.WireError) as e:
        M.decode_state(M.encode_state(s), uav=3)
    assert e.value.reason == reason
    good = M.estimate_to_msg(NodeEstimate(2, 9, 9.0, np.zeros(3), np.zeros(3), np.eye(3), None, [], 3, 1.5, None, None))
    bad = {**good.model_dump(mode="json"), "pos": list(map(float, pos)), "pos_cov": list(map(float, np.ravel(cov)))}
    with pytest.raises(M.WireError) as e2:
        M.decode(M.EstimateMsg, json.dumps(bad).encode(), uav=2)
    assert e2.value.reason == "invalid" and reason in str(e2.value)


def test_state_envelope_set_by_the_receiver():
    s = _state(np.random.default_rng(4))
    s.pos = np.array([5e4, 0.0, 0.0])
    s.traj = {}
    assert M.decode_state(M.encode_state(s), uav=3).pos[0] == 5e4  # default envelope 1e6 m
    with pytest.raises(M.WireError, match="envelope"):
        M.decode_state(M.encode_state(s), uav=3, envelope_m=1e4)
