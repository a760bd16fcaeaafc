"""Where an aircraft's contact points are: one compiled kernel per coupling step.

Near the ground the host places every contact point (wheels and structure
points) each step and asks the terrain for the height under each. Doing that
with small numpy arrays cost ~100 us a step (array set-up dominates for a
dozen points); this kernel does the same arithmetic in one call.

Frames: JSBSim's structural frame (x aft, y right, z up; inches) ->
body axes from the CG (FGMassBalance::StructuralToBody) -> local NED through
the transpose of C_n2b = R1(phi) R2(theta) R3(psi) (Stevens & Lewis,
*Aircraft Control and Simulation*, 3rd ed., eq. 1.3-20) -> geodetic offsets on
the local tangent plane with the WGS84 radii of curvature M and N (metres
of offset: the plane's error is d^2 / 2R, below 1e-5 m for a 10 m wing).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from terrain.geodesy import WGS84_A_M, WGS84_E2

FT_M = 0.3048  # international foot, exact (NIST SP 811, B.8); = fdm.state.FT_M


@numba.njit(cache=True, nogil=True)
def place_contacts(lat_deg, lon_deg, alt_m, cg_x_in, cg_y_in, cg_z_in, phi, theta, psi, ahead_n_m, ahead_e_m,
                   locations_in, out_lat, out_lon, out_alt):
    """Fill out_lat/out_lon (k + 1: the CG now, then the k contacts shifted by
    ``ahead`` metres north/east) and out_alt (k: each contact's altitude, m).

    ``locations_in`` is (k, 3) structural inches. Latitude is clipped to
    [-90, 90], longitude wrapped into [-180, 180).
    """
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    # Rows of C_n2b (NED -> body); a body vector b maps to NED as b @ C_n2b.
    c00, c01, c02 = ct * cp, ct * sp, -st
    c10, c11, c12 = sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct
    c20, c21, c22 = cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct
    s = math.sin(math.radians(lat_deg))
    w2 = 1.0 - WGS84_E2 * s * s
    n_rad = WGS84_A_M / math.sqrt(w2)
    m_rad = WGS84_A_M * (1.0 - WGS84_E2) / (w2 * math.sqrt(w2))
    coslat = max(math.cos(math.radians(lat_deg)), 1e-9)
    k_lat = 180.0 / math.pi / (m_rad + alt_m)
    k_lon = 180.0 / math.pi / ((n_rad + alt_m) * coslat)
    out_lat[0] = lat_deg
    out_lon[0] = lon_deg
    scale = FT_M / 12.0
    for i in range(locations_in.shape[0]):
        bx = -(locations_in[i, 0] - cg_x_in) * scale
        by = (locations_in[i, 1] - cg_y_in) * scale
        bz = -(locations_in[i, 2] - cg_z_in) * scale
        north = bx * c00 + by * c10 + bz * c20
        east = bx * c01 + by * c11 + bz * c21
        down = bx * c02 + by * c12 + bz * c22
        la = lat_deg + (north + ahead_n_m) * k_lat
        out_lat[i + 1] = min(90.0, max(-90.0, la))
        lo = lon_deg + (east + ahead_e_m) * k_lon
        out_lon[i + 1] = (lo + 180.0) % 360.0 - 180.0
        out_alt[i] = alt_m - down


def contact_points(lat_deg, lon_deg, alt_m, cg_in, phi, theta, psi, ahead_ned_m, locations_in):
    """Array-returning form of :func:`place_contacts` (tests, one-off callers)."""
    locations_in = np.ascontiguousarray(locations_in, dtype=np.float64).reshape(-1, 3)
    k = locations_in.shape[0]
    out_lat, out_lon, out_alt = np.empty(k + 1), np.empty(k + 1), np.empty(k)
    place_contacts(float(lat_deg), float(lon_deg), float(alt_m), float(cg_in[0]), float(cg_in[1]),
                   float(cg_in[2]), float(phi), float(theta), float(psi), float(ahead_ned_m[0]),
                   float(ahead_ned_m[1]), locations_in, out_lat, out_lon, out_alt)
    return out_lat, out_lon, out_alt


@numba.njit(cache=True, nogil=True)
def ground_clearance(contact_alt, terrain, structure):
    """(c_min, elevation, structure_hit) of one coupling step.

    ``terrain[1:]`` is the terrain under each contact (``terrain[0]``, under the
    CG, is not used), ``contact_alt`` their altitudes, ``structure`` which are
    structure points. c_min is the smallest clearance h_i - T_i; elevation
    E = min_i h_i - c_min gives the most-penetrating contact its true clearance
    on JSBSim's level ground; structure_hit says whether any structure point is
    below its terrain.
    """
    c_min = np.inf
    h_min = np.inf
    hit = False
    for i in range(contact_alt.size):
        c = contact_alt[i] - terrain[i + 1]
        c_min = min(c_min, c)
        h_min = min(h_min, contact_alt[i])
        if structure[i] and c < 0.0:
            hit = True
    return c_min, h_min - c_min, hit
