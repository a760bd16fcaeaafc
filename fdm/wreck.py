"""A wreck falling: an aircraft that broke up in the air comes down ballistically.

An aircraft that crashes in the air (a mid-air collision, a structural failure from an
over-g, a state gone non-finite is not one: its last good place is all there is) no longer
flies: JSBSim is no longer stepped, and what is left falls under gravity and air drag from
the velocity it had, keeping the attitude it had (no tumbling is modelled), until it meets
the surface (terrain, or the sea's surface over water), where it comes to rest. Debriefs
(Tacview, a replay) show the wreck coming down to where it lies, not hanging in the sky.

The model is a point mass with quadratic drag, the drag set by a terminal speed:
dv/dt = g - (g / v_t^2) |v| v, so a wreck falling long enough falls at v_t. The terminal
speed is an assumption (no model of the catalog's airframes breaking up exists here): 70 m/s,
between a skydiver's belly-to-earth 55 m/s and a streamlined body's hundreds. It is a
parameter of :func:`fall`.

Integration is in ECEF (float64), so a wreck falling across the antimeridian or over a pole
is continuous; gravity is standard gravity (9.80665 m/s^2, the CGPM 1901 conventional value)
along the ellipsoid's downward normal at the wreck's place. Each step is semi-implicit in the
drag, v' = (v + g dt) / (1 + k |v + g dt| dt), which stays stable for any step (the drag can
slow the wreck to rest along a direction, never reverse it). The height coordinate is the
caller's (metres MSL for fdm.aircraft): over a fall of a few kilometres the difference
between the geoid and the ellipsoid changes too little to matter to where the wreck lands.

Pure functions of one wreck's numbers (a few wrecks fall at once: floats, not arrays).
"""

from __future__ import annotations

import math

import numpy as np

from terrain.geodesy import WGS84_E2, ecef_to_geodetic, enu_basis, geodetic_to_ecef

G0_MPS2 = 9.80665  # standard gravity (3rd CGPM, 1901)
# Assumed terminal speed of a falling airframe's wreck (see the module docstring).
TERMINAL_SPEED_MPS = 70.0
# An aircraft that crashes more than this above the surface under it falls as a wreck;
# nearer, it comes to rest where it crashed (a crash on or at the ground: it is there).
FALL_MIN_AGL_M = 10.0


def fall(lat_deg: float, lon_deg: float, h_m: float, v_ned_mps, dt_s: float, steps: int,
         terminal_speed_mps: float = TERMINAL_SPEED_MPS):
    """``steps`` steps of ``dt_s`` of one falling wreck from (lat, lon) degrees, height ``h_m``,
    with velocity ``v_ned_mps`` (north, east, down, m/s).

    Returns (lat_deg, lon_deg, h_m, v_ned_mps, a_ned_mps2) as floats and 3-tuples: the place
    and velocity after the steps, and the acceleration (gravity plus drag) of the last step, in
    the local frame of the place reached. Each step takes "down" as the ellipsoid's normal
    through the wreck, (x, y, z / (1 - e^2)) normalised: exact on the ellipsoid, within
    e^2 h / a (2e-5 rad at 20 km) above it, far less than the plumb line's own deflection
    from the normal."""
    if not terminal_speed_mps > 0.0 or not math.isfinite(terminal_speed_mps):
        raise ValueError(f"terminal_speed_mps must be finite and > 0, got {terminal_speed_mps!r}")
    k = G0_MPS2 / (terminal_speed_mps * terminal_speed_mps)
    x, y, z = (float(c) for c in geodetic_to_ecef(lat_deg, lon_deg, h_m))
    east, north, up = (tuple(float(c) for c in b) for b in enu_basis(lat_deg, lon_deg))
    vn, ve, vd = (float(c) for c in v_ned_mps)
    vx, vy, vz = (vn * north[i] + ve * east[i] - vd * up[i] for i in range(3))
    ax = ay = az = 0.0
    flat = 1.0 / (1.0 - WGS84_E2)
    for _ in range(int(steps)):
        ux, uy, uz = x, y, z * flat
        r = math.sqrt(ux * ux + uy * uy + uz * uz)
        g = G0_MPS2 / r
        wx, wy, wz = vx - g * ux * dt_s, vy - g * uy * dt_s, vz - g * uz * dt_s
        d = 1.0 + k * dt_s * math.sqrt(wx * wx + wy * wy + wz * wz)
        wx, wy, wz = wx / d, wy / d, wz / d
        ax, ay, az = (wx - vx) / dt_s, (wy - vy) / dt_s, (wz - vz) / dt_s
        vx, vy, vz = wx, wy, wz
        x, y, z = x + vx * dt_s, y + vy * dt_s, z + vz * dt_s
    lat, lon, h = (float(c) for c in ecef_to_geodetic(np.array([x, y, z])))
    east, north, up = (tuple(float(c) for c in b) for b in enu_basis(lat, lon))

    def to_ned(a, b, c):
        return (a * north[0] + b * north[1] + c * north[2], a * east[0] + b * east[1] + c * east[2],
                -(a * up[0] + b * up[1] + c * up[2]))

    return lat, lon, h, to_ned(vx, vy, vz), to_ned(ax, ay, az)


def impact_fraction(agl_before_m, agl_after_m):
    """Where along a step's straight path a wreck meets the surface: the fraction of the step
    at which the height above the surface, linear between its values before (> 0) and after
    (<= 0) the step, reaches 0 (in [0, 1])."""
    before, after = np.asarray(agl_before_m, np.float64), np.asarray(agl_after_m, np.float64)
    span = before - after
    return np.clip(np.where(span > 0.0, before / np.where(span > 0.0, span, 1.0), 1.0), 0.0, 1.0)


def ned_to_body_matrix(phi: float, theta: float, psi: float) -> list:
    """The rotation (3 x 3, nested lists) taking local (north, east, down) vectors into body
    axes for Euler angles roll ``phi``, pitch ``theta``, yaw ``psi`` (radians; the aerospace
    z-y-x sequence: the direction cosine matrix of Stevens & Lewis, "Aircraft Control and
    Simulation", 2nd ed., section 1.3)."""
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    sp, cp = math.sin(psi), math.cos(psi)
    return [[ct * cp, ct * sp, -st],
            [sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct],
            [cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct]]
