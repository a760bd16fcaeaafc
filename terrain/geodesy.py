"""WGS84 geodesy as pure, vectorised array functions.

Geodesic lines (distances, azimuths, profiles) come from GeographicLib; this
module holds what GeographicLib's Python package does not vectorise: geodetic
<-> ECEF, local ENU frames, radii of curvature and the Web Mercator projection.

Argument order is always (lat, lon): degrees, WGS84 geodetic. Heights are
metres above the ellipsoid unless a name says ``_msl``.
"""

from __future__ import annotations

import numpy as np

# WGS84 defining constants (NIMA TR8350.2, 3rd ed., table 3.1).
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared

# EPSG:3857 projects WGS84 (lat, lon) on a sphere of radius a (EPSG Guidance
# Note 7-2, "Popular Visualisation Pseudo Mercator"). Its latitude limit keeps
# the square world extent.
WEB_MERCATOR_MAX_LAT_DEG = 85.05112877980659


def geodetic_to_ecef(lat_deg, lon_deg, h_m):
    """(lat, lon) degrees and height (m above ellipsoid) -> (n, 3) float64 ECEF metres.

    Inputs broadcast against each other; the result has shape (..., 3).
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    h = np.asarray(h_m, dtype=np.float64)
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    x = (n + h) * cos_lat * np.cos(lon)
    y = (n + h) * cos_lat * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(points_ecef):
    """(..., 3) float64 ECEF metres -> (lat_deg, lon_deg, h_m), each of shape (...).

    Bowring's iteration on the reduced latitude (Bowring 1976, Surv. Rev. 23),
    three rounds: below 1e-9 m and 1e-14 rad for any point within 10,000 km of
    the surface, poles included (tested against geodetic_to_ecef round trips).
    """
    p_ecef = np.asarray(points_ecef, dtype=np.float64)
    if p_ecef.shape[-1] != 3:
        raise ValueError(f"points_ecef must have shape (..., 3), got {p_ecef.shape}")
    x, y, z = p_ecef[..., 0], p_ecef[..., 1], p_ecef[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    beta = np.arctan2(z, (1.0 - WGS84_F) * p)
    # den < 0 only nearer the axis than e2 * a (43 km: deep inside, near the centre), nearer
    # than the centre of curvature: there the same normal is taken outwards (cos(lat) >= 0,
    # |lat| <= 90). Checked once, so the usual call pays nothing for it.
    deep = bool((p < WGS84_E2 * WGS84_A_M).any())
    for _ in range(3):
        sb, cb = np.sin(beta), np.cos(beta)
        num, den = z + WGS84_EP2 * WGS84_B_M * sb**3, p - WGS84_E2 * WGS84_A_M * cb**3
        if deep:
            lat = np.arctan2(np.where(den < 0.0, -num, num), np.abs(den)) + 0.0  # -0.0 into 0.0
        else:
            lat = np.arctan2(num, den)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    # Height without the 1/cos(lat) blow-up near the poles.
    h = p * cos_lat + z * sin_lat - WGS84_A_M * np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    return np.degrees(lat), np.degrees(lon), h


def radii_of_curvature(lat_deg):
    """Meridian radius M and prime-vertical radius N (metres) at geodetic latitude."""
    s = np.sin(np.radians(np.asarray(lat_deg, dtype=np.float64)))
    w2 = 1.0 - WGS84_E2 * s * s
    n = WGS84_A_M / np.sqrt(w2)
    m = WGS84_A_M * (1.0 - WGS84_E2) / (w2 * np.sqrt(w2))
    return m, n


def enu_basis(lat_deg, lon_deg):
    """Unit vectors (east, north, up), each (..., 3) float64, in ECEF at (lat, lon)."""
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl * so)
    east = np.stack(np.broadcast_arrays(-so, co, zero), axis=-1)
    north = np.stack(np.broadcast_arrays(-sl * co, -sl * so, cl), axis=-1)
    up = np.stack(np.broadcast_arrays(cl * co, cl * so, sl), axis=-1)
    return east, north, up


def web_mercator_forward(lat_deg, lon_deg):
    """WGS84 (lat, lon) degrees -> EPSG:3857 (x, y) metres."""
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    x = WGS84_A_M * lon
    y = WGS84_A_M * np.log(np.tan(np.pi / 4.0 + lat / 2.0))
    return x, y


def web_mercator_inverse(x_m, y_m):
    """EPSG:3857 (x, y) metres -> WGS84 (lat, lon) degrees."""
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    lat = 2.0 * np.arctan(np.exp(y / WGS84_A_M)) - np.pi / 2.0
    lon = x / WGS84_A_M
    return np.degrees(lat), np.degrees(lon)


def wrap_lon_deg(lon_deg):
    """Longitude wrapped into [-180, 180)."""
    lon = np.asarray(lon_deg, dtype=np.float64)
    return (lon + 180.0) % 360.0 - 180.0


def wrap_lon_exact_deg(lon):
    """Longitude reduced exactly into [-180, 180): one already there is returned as it is, bit
    for bit, and any other moved by an exact multiple of 360 (wrap_lon_deg rounds both)."""
    # fmod is exact in IEEE 754; the +-360 shifts are exact by Sterbenz's lemma
    # (the operands are within a factor of two of each other).
    x = np.fmod(lon, 360.0)
    x = np.where(x >= 180.0, x - 360.0, x)
    x = np.where(x < -180.0, x + 360.0, x)
    return x + 0.0  # turn -0.0 into 0.0
