"""Seeded swarm simulator (pure core): trajectories, IMU, GNSS, UWB with faults, relative az/el.

``simulate(scenario, seed) -> Dataset``; ``simulate_full`` also returns the full IMU-rate truth
and the ideal IMU; ``integrate_imu`` is the strapdown inverse of the simulator's discrete scheme.
"""

from .simulate import SimResult, simulate, simulate_full
from .trajectory import Truth, integrate_imu

__all__ = ["simulate", "simulate_full", "SimResult", "Truth", "integrate_imu"]
