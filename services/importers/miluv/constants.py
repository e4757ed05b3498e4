"""Constants of the MILUV import: node numbering, sensor floors, priors, passive-listening timing."""

from __future__ import annotations

ANCHOR_NODE_OFFSET = 100  # anchor k -> node id 100 + k (UAVs are 1..9)
GRAVITY_MPS2 = 9.81
HEIGHT_MIN_VALID_M = 0.30  # the rangefinder reads a constant 0.29 m on the ground (below its minimum range)
HEIGHT_SIGMA_M = 0.10  # altitude sigma: in-flight (height - bias) vs mocap z spread 0.03-0.09 m per robot
TRUTH_SUBSTEPS = 10  # truth rows per epoch (epoch times themselves included exactly)
VEL_HALF_WINDOW_S = 0.05  # truth velocity = central difference over +-50 ms of interpolated mocap
MAX_TILT_DEG = 45.0  # mocap attitudes tilted more than this are marker-swap glitches (flight max ~11 deg)
GYRO_BIAS_SIGMA = 0.005  # rad/s, turn-on bias prior (not in config/imu; PX4 calibrates the gyro at boot)
ACCEL_BIAS_SIGMA = 0.3  # m/s^2, turn-on bias prior (not in config/imu; MEMS datasheet order ~30 mg)
INIT = {"vel_sigma_mps": 0.05, "roll_pitch_sigma_deg": 3.0, "yaw_sigma_deg": 3.0}
# Coarse alignment (initial.py ``init.level_window_s``): roll/pitch from each UAV's own accelerometer
# over the first LEVEL_WINDOW_S s, set only if every UAV is at rest then by its IMU alone (gyro-norm
# std and specific-force-norm std below these, mean |f| within LEVEL_MAX_G_DEV of g).
LEVEL_WINDOW_S = 1.0
LEVEL_MAX_GYRO_STD = 0.01  # rad/s
LEVEL_MAX_ACC_STD = 0.1  # m/s^2
LEVEL_MAX_G_DEV = 0.3  # m/s^2
# In-flight accelerometer white noise from the recording itself (no mocap): vibration = the signal
# minus its VIB_SMOOTH_S moving average, while the rangefinder says airborne; density = per-sample
# RMS std / sqrt(rate). Used when above the at-rest Allan value.
VIB_SMOOTH_S = 0.2
# Passive listening (uwb_passive.csv): timestamps in ns of the DW1000's 63.8976 GHz counter
# (15.65 ps ticks). The listener's logged rx timestamps wrap every 2**32 ticks = 67.216 ms (seen in
# the recording: ~15 % of the rows have rx2 - rx1 one wrap too long), so every interval is taken
# modulo PASSIVE_WRAP_NS. Clock-rate ratio sanity bound: DW1000 crystals are +-20 ppm.
SPEED_OF_LIGHT_M_PER_NS = 0.299792458
PASSIVE_WRAP_NS = 2.0**32 / (128 * 499.2e6) * 1e9
PASSIVE_MAX_SKEW = 1e-4
