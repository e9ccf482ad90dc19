"""WGS84 earth model in NED: radii, normal gravity, earth rate, transport rate.

Angles in radians, heights in metres, velocities NED in m/s. Vectorised over leading dimensions.
"""
from __future__ import annotations

import numpy as np

A_M = 6378137.0  # semi-major axis
F = 1.0 / 298.257223563  # flattening
B_M = A_M * (1.0 - F)
E2 = F * (2.0 - F)  # first eccentricity squared
OMEGA_IE_RAD_S = 7.292115e-5  # earth rotation rate
GM_M3_S2 = 3.986004418e14
# Somigliana normal gravity constants
GAMMA_E_M_S2 = 9.7803253359
GAMMA_P_M_S2 = 9.8321849378
_K_SOMIGLIANA = (B_M * GAMMA_P_M_S2) / (A_M * GAMMA_E_M_S2) - 1.0
_M_GRAV = OMEGA_IE_RAD_S**2 * A_M**2 * B_M / GM_M3_S2


def radii_m(lat_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Meridian radius R_M and prime-vertical (transverse) radius R_N at latitude."""
    s2 = np.sin(lat_rad) ** 2
    den = 1.0 - E2 * s2
    r_n = A_M / np.sqrt(den)
    r_m = A_M * (1.0 - E2) / den**1.5
    return r_m, r_n


def gravity_m_s2(lat_rad: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    """Magnitude of normal gravity (Somigliana + free-air second-order height correction)."""
    s2 = np.sin(lat_rad) ** 2
    g0 = GAMMA_E_M_S2 * (1.0 + _K_SOMIGLIANA * s2) / np.sqrt(1.0 - E2 * s2)
    h = np.asarray(alt_m, dtype=float)
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + _M_GRAV - 2.0 * F * s2) * h + 3.0 / A_M**2 * h**2)


def gravity_ned_m_s2(lat_rad: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    """Normal gravity vector in NED (down positive)."""
    g = np.asarray(gravity_m_s2(lat_rad, alt_m))
    z = np.zeros_like(g)
    return np.stack([z, z, g], axis=-1)


def earth_rate_ned(lat_rad: np.ndarray) -> np.ndarray:
    """omega_ie^n: earth rotation expressed in NED."""
    lat = np.asarray(lat_rad, dtype=float)
    return np.stack(
        [OMEGA_IE_RAD_S * np.cos(lat), np.zeros_like(lat), -OMEGA_IE_RAD_S * np.sin(lat)], axis=-1
    )


def transport_rate_ned(lat_rad: np.ndarray, alt_m: np.ndarray, vel_ned_m_s: np.ndarray) -> np.ndarray:
    """omega_en^n: rotation of NED relative to the earth due to motion over the ellipsoid."""
    r_m, r_n = radii_m(lat_rad)
    v = np.asarray(vel_ned_m_s, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    vn, ve = v[..., 0], v[..., 1]
    return np.stack(
        [ve / (r_n + h), -vn / (r_m + h), -ve * np.tan(lat_rad) / (r_n + h)], axis=-1
    )


def llh_rates(lat_rad: np.ndarray, alt_m: np.ndarray, vel_ned_m_s: np.ndarray) -> np.ndarray:
    """d/dt [lat, lon, alt] (rad/s, rad/s, m/s) from NED velocity."""
    r_m, r_n = radii_m(lat_rad)
    v = np.asarray(vel_ned_m_s, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    return np.stack(
        [v[..., 0] / (r_m + h), v[..., 1] / ((r_n + h) * np.cos(lat_rad)), -v[..., 2]], axis=-1
    )


def llh_to_ecef(lat_rad: np.ndarray, lon_rad: np.ndarray, alt_m: np.ndarray) -> np.ndarray:
    _, r_n = radii_m(lat_rad)
    cl, sl = np.cos(lat_rad), np.sin(lat_rad)
    return np.stack(
        [(r_n + alt_m) * cl * np.cos(lon_rad), (r_n + alt_m) * cl * np.sin(lon_rad),
         (r_n * (1 - E2) + alt_m) * sl], axis=-1)


def dcm_ecef_to_ned(lat_rad: np.ndarray, lon_rad: np.ndarray) -> np.ndarray:
    """mat_ne: rotates ECEF vectors into the local NED frame."""
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    so, co = np.sin(lon_rad), np.cos(lon_rad)
    m = np.empty(np.shape(lat_rad) + (3, 3))
    m[..., 0, :] = np.stack([-sl * co, -sl * so, cl], axis=-1)
    m[..., 1, :] = np.stack([-so, co, np.zeros_like(co)], axis=-1)
    m[..., 2, :] = np.stack([-cl * co, -cl * so, -sl], axis=-1)
    return m
