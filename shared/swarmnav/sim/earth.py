"""Earth model and unit conversions used by the simulator (numpy only).

- Normal gravity: Somigliana's closed formula on the WGS84 ellipsoid with the second-order
  free-air height correction (NIMA TR8350.2, eqs. 4-1 and 4-3), evaluated once at the geodetic
  origin and held constant over the local-level ENU frame.
- Earth rotation in ENU at latitude φ: Ω_ie = ω_ie · [0, cos φ, sin φ], ω_ie = 7.292115e-5 rad/s (WGS84).
- PSINS ``imuerrset`` units -> SI (PSINS ``glv``: g0 = 9.7803267714 m/s², µg = 1e-6 g0).
"""

from __future__ import annotations

import numpy as np

# WGS84
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_GM = 3.986004418e14
OMEGA_IE = 7.292115e-5  # rad/s
GAMMA_E = 9.7803253359  # normal gravity at the equator, m/s^2
SOMIGLIANA_K = 0.00193185265241  # (b γ_p − a γ_e) / (a γ_e)

# PSINS glv constants
PSINS_G0 = 9.7803267714
DEG = np.pi / 180.0
DPH = DEG / 3600.0  # deg/h -> rad/s
UG = 1e-6 * PSINS_G0  # micro-g -> m/s^2
DPSH = DEG / 60.0  # deg/sqrt(h) -> rad/sqrt(s)
UGPSHZ = UG  # micro-g/sqrt(Hz) -> m/s^2/sqrt(Hz)
DPHPSH = DPH / 60.0  # deg/h/sqrt(h) -> rad/s/sqrt(s)
UGPSSH = UG  # micro-g/sqrt(s) -> m/s^2/sqrt(s)


def normal_gravity(lat_deg: float, h_m: float = 0.0) -> float:
    """Magnitude of WGS84 normal gravity (m/s²) at geodetic latitude and ellipsoidal height."""
    s2 = np.sin(np.deg2rad(lat_deg)) ** 2
    g0 = GAMMA_E * (1.0 + SOMIGLIANA_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)
    m = OMEGA_IE**2 * WGS84_A**2 * WGS84_B / WGS84_GM
    corr = 1.0 - 2.0 / WGS84_A * (1.0 + WGS84_F + m - 2.0 * WGS84_F * s2) * h_m + 3.0 * h_m**2 / WGS84_A**2
    return float(g0 * corr)


def earth_rate_enu(lat_deg: float) -> np.ndarray:
    """Earth rotation vector Ω_ie expressed in the local ENU frame (rad/s)."""
    phi = np.deg2rad(lat_deg)
    return np.array([0.0, OMEGA_IE * np.cos(phi), OMEGA_IE * np.sin(phi)])
