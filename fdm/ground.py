"""Vectorised ground vehicles on real terrain: every vehicle in one batch per step.

State is a struct of arrays (lat, lon, height, heading, speed, pitch, roll,
...), one entry per vehicle; each step runs two numba kernels over all the
vehicles due and makes **one** batched terrain query between them, so the
terrain source can be the in-process :class:`terrain.terrain.Terrain` or the
gRPC :class:`client.terrain_client.TerrainClient` alike (anything with
``heights(lat, lon) -> .height_msl_m, .status``). Argument order is always
(lat, lon), degrees WGS84; heights are metres above mean sea level, as the
terrain gives them (``height_msl_m``).

One sub-step of one vehicle
---------------------------
1. *Speed.* The commanded speed is capped by the type's maximum (forward or
   reverse) and, uphill, by the power the drivetrain delivers against grade
   and rolling resistance: v <= eta P / (m g (f_r cos(theta) + sin(theta)))
   (Wong, *Theory of Ground Vehicles*, 4th ed. 2008, sec. 3.1 and 3.3), theta
   the current pitch in the travel direction. Speed approaches the target at
   the type's acceleration, or its braking rate when slowing or reversing.
2. *Heading.* The commanded heading rate is capped at the type's limits at the
   sub-step's mean speed |v|: a wheeled vehicle turns no tighter than its
   minimum radius (|r| <= |v| / R_min, so it cannot turn standing still), a
   tracked one pivots at up to its pivot rate; both keep the lateral
   acceleration |r v| within the type's limit. Steering is instantaneous
   within those limits (no actuator lag).
3. *Move.* The vehicle moves s = v_mean h cos(pitch) metres of ground along
   the mid-step heading (second order in h). North/east metres become
   degrees with the radii of curvature, dlat = dn / M, dlon = de / (N cos lat),
   and the heading is transported by dlon sin(lat) (meridian convergence), so
   straight lines stay great-circle-like at any latitude. Longitudes wrap into
   [-180, 180): the antimeridian is seamless. Within POLAR_LAT_DEG of a pole
   the move is made in ECEF instead (tangent-plane step, back to geodetic,
   heading re-read in the new ENU frame), which is exact over the pole.
4. *Terrain under the wheel base.* Five points are sampled at the proposed
   pose in the one batched call: the centre, and front/rear at +-L/2 along the
   heading and left/right at +-W/2 across it (L, W: the type's contact length
   and width -- wheelbase and track, or track ground contact and gauge).
   Height is the terrain at the centre (so the reference point is on the
   surface exactly), pitch = atan((h_front - h_rear) / L) nose up positive,
   roll = atan2((h_left - h_right) / W, sqrt(1 + gp^2)) right side down
   positive (gp the front-to-rear gradient: the z-y-x Euler roll of a body
   lying on the plane, :func:`roll_rad`).
5. *Accept or stop.* The proposed pose is rejected -- the vehicle keeps its
   previous pose and its speed drops to 0 -- when any contact point is
   OUTSIDE the terrain or at or below WATER_LEVEL_MSL_M (a DEM carries no
   water mask: sea is height <= 0, as SRTM stores the sea and the procedural
   world's water is; inland lakes are not detected), when the gradient in the
   travel direction exceeds the type's maximum gradient up or down (a cliff is
   a gradient beyond any type's limit), or when the side slope exceeds its
   limit. Uphill beyond the maximum gradient is always stopped, whatever the
   gradient the vehicle stood on (a vehicle placed on a steep face does not
   climb it); downhill and side slope beyond their limits stop only a move that
   makes them worse, so a vehicle placed on a steep slope can still drive off
   it, down or across. "Worse" across is steeper than the gentlest side slope
   the vehicle has stood on since it was placed, by more than the heights'
   resolution can tell apart (:func:`side_slope_tolerances`): heights stored as
   float32 or whole metres (SRTM) make a plane's side gradient vary from pose to
   pose, and a vehicle driving along its contour was stopped every few steps.
   ``blocked`` says why.

No tunnelling at any step size
------------------------------
A step of length dt is split into sub-steps of at most SUBSTEP_MAX_LENGTH_FRAC
times the contact length L (and at most SUBSTEP_MAX_TURN_DEG of heading). The
leading contact therefore advances at most L/2 per sub-step: the ground it
passes over lies between the old and the new leading contact, within the
wheel base of the new pose, so any rise steeper than the type's gradient over
a width of L/2 or more -- every cliff a DEM with posts >= L/2 apart can hold --
is seen by one sub-step's front-to-rear gradient and stops the vehicle there.
A blocked vehicle stays where its last accepted sub-step put it: it stops at
a cliff foot, cliff edge or shore, never on the far side.

Model only what a scene needs: level of detail by distance
----------------------------------------------------------
With observers set (:meth:`GroundVehicles.set_observers`), each vehicle gets a
step divisor from the great-circle distance d to its nearest observer:
1 within ``near_m``, then 2, 4, ... doubling every doubling of d/near_m, up
to ``max_divisor``. Vehicle i is integrated only on ticks where
(tick + i) % divisor == 0 -- staggered, so the work per tick stays level --
and then over the whole time elapsed since its own last integration (at most
``max_divisor`` ticks), with the same sub-stepping, so a far vehicle still
never leaves the surface, it is only updated less often (its reported pose
lags by under divisor * dt; a renderer can dead-reckon it). Divisors are
recomputed from the current positions every DIVISOR_REFRESH_TICKS ticks and
whenever the observers change; :meth:`sync` brings every vehicle up to the
current time (e.g. before a recording snapshot). Because a long integration is
still cut into sub-steps of at most L/2, a divisor of 8 saves less than 8x:
measured 2.8x for 5,000 vehicles of which 90 % are at divisor 8 (bench fdm).

Limitations: steering is instantaneous within the limits; a blocked vehicle
stops at once (no deceleration, no damage model); water is "height <= 0 m
MSL" only; vertical obstacles narrower than the DEM's posts do not exist for
the model. The time of a stop depends on whether a sub-step lands beyond a
limit's crest, so near a limit runs with different dt may part ways.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from fdm.vehicle_types import (G_MPS2, P_ACCEL, P_ALAT, P_BRAKE, P_FR, P_GRAD, P_KIND, P_LEN,
                               P_PIVOT, P_POWER_PER_KG, P_RMIN, P_SIDE, P_VMAX, P_VREV, P_WID, P_YAWMAX,
                               TRACKED, VehicleType, get_type, type_table)
from sortie.errors import InvalidArgument, SortieError, bound_text
from terrain.geodesy import WGS84_A_M, WGS84_E2
from terrain.raster import STATUS_OUTSIDE
from terrain.validate import as_1d_f64, check_finite, check_latlon, first_bad

# Sea level: a contact point at or below this height (m MSL) is in the water.
WATER_LEVEL_MSL_M = 0.0
# How much steeper (rise per metre) a move down a slope the vehicle already stands beyond
# its limit on may find the ground before it counts as making it worse: the gradient
# under the wheel base varies by a few thousandths from one pose to the next over float32
# posts, and a vehicle driving off a steep face must not be stopped by that noise. A vehicle
# within its limits gets none: any move beyond them stops it.
SLOPE_WORSE_TOLERANCE = 0.02
# The side-slope "no worse" rule's tolerance: how much two poses' side gradients may differ
# with no change in the ground, from the resolution q of the stored heights (each post within
# q/2 of its value: IEEE 754 round to nearest for float32, whole metres for SRTM). The heights
# are bilinear over the posts, so each is within q/2 of the exact surface's and the error's
# slope within a cell is at most q/dx east and q/dy north (post spacings dx, dy): the side
# gradient, (h_left - h_right) / W over the track width W, is off by at most
#   e = q * min(1 / W, hypot(1 / dx, 1 / dy))   (the first: two errors of q/2; the second: the
# error's largest slope along the axle), and two poses' by up to 2 e. Steps coarser than float32's
# come from the terrain's description (height_steps, side_slope_tolerances); float32's own is
# taken at the contacts' height in the kernel, over W alone (it knows no post spacing there).
# Measured against the gentlest side gradient the vehicle has stood on (GroundVehicles.side_ref),
# not the last pose's: a margin taken from the last pose compounds (with 0.02 a vehicle on a 0.53
# side slope crept to 0.81 in 8 s at 20 Hz), this one never lets a vehicle stand more than 2 e
# (4 e on the exact surface) steeper across than it already has.
# float32 keeps 24 significant bits (IEEE 754 binary32): its spacing at x in [2^k, 2^(k+1)) is
# 2^(k - 23), i.e. 2^(e - 24) with frexp's exponent e. Taken at twice the contacts' height, and
# at least at 1024 m, it is that of every post up to that height around the wheel base (a cell
# rising further above the contacts than they stand above sea level is a cliff at any height over
# a few hundred metres); an overestimate costs nothing: 2 e is 1.6e-4 at 2 km on a 3 m track.
FLOAT32_SIGNIFICAND_BITS = 24
FLOAT32_SPACING_FLOOR_M = 1024.0
# SRTM .hgt posts are whole metres (signed 16-bit integers: SRTM Topography, NASA JPL 2005),
# however a reader stores them.
HGT_HEIGHT_STEP_M = 1.0
# A sub-step moves at most this fraction of the contact length (see module doc).
SUBSTEP_MAX_LENGTH_FRAC = 0.5
# ... and turns at most this far.
SUBSTEP_MAX_TURN_DEG = 10.0
# Poleward of this latitude moves are made in ECEF (about 11 km from a pole).
POLAR_LAT_DEG = 89.9
# Below this turn (rad) a sub-step rotates its heading's cosine and sine by Taylor
# terms (_rotate: truncation < 0.05^6 / 720 = 2e-11, nanometres at a wheel base).
SMALL_TURN_RAD = 0.05
# Contact points sampled per vehicle: centre, front, rear, right, left.
N_CONTACTS = 5
# Divisors are recomputed every this many ticks (and when the observers change):
# in 4 ticks at 20 Hz a vehicle moves a few metres of the km that separate bands.
DIVISOR_REFRESH_TICKS = 4
# Sphere radius for observer distances (IUGG mean radius): LOD only needs ~0.5 %.
MEAN_EARTH_RADIUS_M = 6_371_008.8

# Why a vehicle stopped (``blocked``); 0 while it moves freely.
FREE = 0
BLOCKED_SIDE_SLOPE = 1
BLOCKED_SLOPE = 2
BLOCKED_WATER = 3
BLOCKED_OUTSIDE = 4
BLOCKED_COLLISION = 5  # ran into another entity (set by the world: server/collisions.py)
BLOCKED_NAMES = {FREE: "free", BLOCKED_SIDE_SLOPE: "side_slope", BLOCKED_SLOPE: "slope",
                 BLOCKED_WATER: "water", BLOCKED_OUTSIDE: "outside", BLOCKED_COLLISION: "collision"}

# Largest step the model accepts: a long step is sub-stepped, but beyond this
# it is a unit mix-up (ms for s), not a simulation.
MAX_DT_S = 60.0


# -- geodesy kernels ----------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _radii(phi):
    """Meridian radius M and prime-vertical radius N (m) at latitude phi (rad)."""
    s = math.sin(phi)
    w2 = 1.0 - WGS84_E2 * s * s
    w = math.sqrt(w2)
    return WGS84_A_M * (1.0 - WGS84_E2) / (w2 * w), WGS84_A_M / w


@numba.njit(cache=True, nogil=True)
def _wrap_lon(lon):
    """Longitude (deg) into [-180, 180); values already there pass untouched."""
    if lon < -180.0 or lon >= 180.0:
        lon = (lon + 180.0) % 360.0 - 180.0
        if lon >= 180.0:
            lon -= 360.0
    return lon


@numba.njit(cache=True, nogil=True)
def _offset_local(lat, lon, dn, de):
    """:func:`_offset` away from the poles, with what a caller placing points around
    the new pose can reuse: (lat2, lon2, dpsi, M, N, cos of the mid-step latitude)."""
    phi = math.radians(lat)
    m, n = _radii(phi)
    dphi = dn / m
    phi_mid = phi + 0.5 * dphi
    cpm = math.cos(phi_mid)
    dlam = de / (n * cpm)
    return lat + math.degrees(dphi), _wrap_lon(lon + math.degrees(dlam)), dlam * math.sin(phi_mid), m, n, cpm


@numba.njit(cache=True, nogil=True)
def _offset(lat, lon, dn, de):
    """(lat, lon) degrees moved dn metres north and de east on the surface.

    Returns (lat2, lon2, dpsi): dpsi (rad) is the change of heading that
    carries the move's direction into the new point's north (meridian
    convergence). Near the poles the step is made in ECEF (see module doc).
    """
    if abs(lat) < POLAR_LAT_DEG:
        la, lo, dpsi, _, _, _ = _offset_local(lat, lon, dn, de)
        return la, lo, dpsi
    if dn == 0.0 and de == 0.0:
        return lat, lon, 0.0
    phi = math.radians(lat)
    lam = math.radians(lon)
    sp, cp = math.sin(phi), math.cos(phi)
    sl, cl = math.sin(lam), math.cos(lam)
    _, n = _radii(phi)
    # ECEF position and the step along the local east/north axes.
    x = n * cp * cl
    y = n * cp * sl
    z = n * (1.0 - WGS84_E2) * sp
    dx = -sl * de - sp * cl * dn
    dy = cl * de - sp * sl * dn
    dz = cp * dn
    x += dx
    y += dy
    z += dz
    p = math.hypot(x, y)
    phi2 = math.atan2(z, (1.0 - WGS84_E2) * p)  # exact on the ellipsoid; the step is ~um above it
    lam2 = math.atan2(y, x)
    sp2, cp2 = math.sin(phi2), math.cos(phi2)
    sl2, cl2 = math.sin(lam2), math.cos(lam2)
    e2 = -sl2 * dx + cl2 * dy
    n2 = -sp2 * cl2 * dx - sp2 * sl2 * dy + cp2 * dz
    dpsi = math.atan2(e2, n2) - math.atan2(de, dn)
    return math.degrees(phi2), _wrap_lon(math.degrees(lam2)), dpsi


@numba.njit(cache=True, nogil=True)
def _heading_deg(psi):
    """Heading (rad) -> compass degrees in [0, 360)."""
    h = math.degrees(psi) % 360.0
    if h >= 360.0:
        h -= 360.0
    return h


# -- dynamics kernels ---------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _contacts(k, lat, lon, psi, half_l, half_w, pts_lat, pts_lon):
    """Write the five contact points of a pose into slots 5k .. 5k + 4.

    The offsets (a few metres) use the radii at the pose, computed once: the
    latitude change across the wheel base moves them by parts in 1e7.
    """
    if abs(lat) >= POLAR_LAT_DEG:
        c = math.cos(psi)
        s = math.sin(psi)
        b = N_CONTACTS * k
        pts_lat[b] = lat
        pts_lon[b] = lon
        for q, (dn, de) in enumerate(((half_l * c, half_l * s), (-half_l * c, -half_l * s),
                                      (-half_w * s, half_w * c), (half_w * s, -half_w * c))):
            la, lo, _ = _offset(lat, lon, dn, de)
            pts_lat[b + 1 + q] = la
            pts_lon[b + 1 + q] = lo
        return
    phi = math.radians(lat)
    m, n = _radii(phi)
    _contacts_local(k, lat, lon, math.cos(psi), math.sin(psi), math.degrees(1.0) / m,
                    math.degrees(1.0) / (n * math.cos(phi)), half_l, half_w, pts_lat, pts_lon)


@numba.njit(cache=True, nogil=True)
def _contacts_local(k, lat, lon, c, s, to_lat, to_lon, half_l, half_w, pts_lat, pts_lon):
    """The five contact points away from the poles, from the heading's cosine and sine
    and the degrees per metre north (to_lat) and east (to_lon) at the pose."""
    b = N_CONTACTS * k
    pts_lat[b] = lat
    pts_lon[b] = lon
    fl, fo = half_l * c * to_lat, half_l * s * to_lon  # front
    rl, ro = -half_w * s * to_lat, half_w * c * to_lon  # right
    pts_lat[b + 1] = lat + fl
    pts_lon[b + 1] = _wrap_lon(lon + fo)
    pts_lat[b + 2] = lat - fl
    pts_lon[b + 2] = _wrap_lon(lon - fo)
    pts_lat[b + 3] = lat + rl
    pts_lon[b + 3] = _wrap_lon(lon + ro)
    pts_lat[b + 4] = lat - rl
    pts_lon[b + 4] = _wrap_lon(lon - ro)


@numba.njit(cache=True, nogil=True)
def _rotate(c, s, d):
    """(cos, sin) of a + d from those of a, for a small turn d (rad): Taylor terms to
    d^5 below SMALL_TURN_RAD (truncation < d^6 / 720 < 2e-11), exact above."""
    if abs(d) < SMALL_TURN_RAD:
        d2 = d * d
        cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0))
        sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)))
    else:
        cd = math.cos(d)
        sd = math.sin(d)
    return c * cd - s * sd, s * cd + c * sd


@numba.njit(cache=True, nogil=True)
def _place_kernel(lat, lon, heading_deg, type_id, table, pts_lat, pts_lon):
    """Contact points of the vehicles where they stand."""
    for j in range(lat.shape[0]):
        t = type_id[j]
        _contacts(j, lat[j], lon[j], math.radians(heading_deg[j]), 0.5 * table[t, P_LEN], 0.5 * table[t, P_WID],
                  pts_lat, pts_lon)


@numba.njit(cache=True, nogil=True)
def _schedule_kernel(tick, dt, world_t, last_tick, last_t, divisor, speed, type_id, table,
                     sub_dt, n_sub, due_only_lagging):
    """Pick the vehicles due this tick; their elapsed time, sub-step count and length.

    A vehicle is due when (tick + i) % divisor == 0 (or, with
    due_only_lagging, whenever it lags the world time). Returns how many are
    due; sub_dt/n_sub are set for due vehicles and n_sub = 0 for the rest.
    """
    count = 0
    for j in range(speed.shape[0]):
        if due_only_lagging:
            due = last_tick[j] != tick
        else:
            due = (tick + j) % divisor[j] == 0
        if not due:
            n_sub[j] = 0
            continue
        if last_tick[j] == tick - 1 and not due_only_lagging:
            elapsed = dt  # the common case, exactly
        else:
            elapsed = world_t - last_t[j]
        t = type_id[j]
        # Upper bound on the distance and turn of this step.
        vmax = max(table[t, P_VMAX], table[t, P_VREV])
        vbound = min(abs(speed[j]) + max(table[t, P_ACCEL], table[t, P_BRAKE]) * elapsed, vmax)
        dist = vbound * elapsed
        k = math.ceil(dist / (SUBSTEP_MAX_LENGTH_FRAC * table[t, P_LEN]))
        kt = math.ceil(math.degrees(table[t, P_YAWMAX] * elapsed) / SUBSTEP_MAX_TURN_DEG)
        k = max(1, k, kt)
        n_sub[j] = k
        sub_dt[j] = elapsed / k
        count += 1
    return count


@numba.njit(cache=True, nogil=True)
def _propose_kernel(idx, sub_dt, lat, lon, heading_deg, speed, pitch_grad, type_id, speed_cmd, yaw_cmd_dps,
                    table, p_lat, p_lon, p_psi, p_v, p_r, p_s, pts_lat, pts_lon):
    """One sub-step's proposed pose for each vehicle in idx, and its contact points."""
    for k in range(idx.shape[0]):
        j = idx[k]
        t = type_id[j]
        h = sub_dt[j]
        v = speed[j]
        tgt = speed_cmd[j]
        vlim = table[t, P_VMAX] if tgt >= 0.0 else table[t, P_VREV]
        if abs(tgt) > vlim:
            tgt = math.copysign(vlim, tgt)
        # Power-limited speed uphill (Wong sec. 3.1): eta P = m g (f_r cos + sin) v,
        # with cos, sin of the slope from its tangent g: (f_r + g) / sqrt(1 + g^2).
        gp = pitch_grad[j]
        sec = math.sqrt(1.0 + gp * gp)
        g = gp if tgt > 0.0 else (-gp if tgt < 0.0 else 0.0)
        if g > 0.0:
            vcap = table[t, P_POWER_PER_KG] * sec / (G_MPS2 * (table[t, P_FR] + g))
            if abs(tgt) > vcap:
                tgt = math.copysign(vcap, tgt)
        dv = tgt - v
        rate = table[t, P_ACCEL] if (tgt * v >= 0.0 and abs(tgt) > abs(v)) else table[t, P_BRAKE]
        step = rate * h
        v_new = tgt if abs(dv) <= step else v + math.copysign(step, dv)
        v_mid = 0.5 * (v + v_new)
        av = abs(v_mid)
        if table[t, P_KIND] == TRACKED:
            rlim = table[t, P_PIVOT]
        else:
            rlim = av / table[t, P_RMIN]
        if av > 0.0:
            rlim = min(rlim, table[t, P_ALAT] / av)
        r = min(max(math.radians(yaw_cmd_dps[j]), -rlim), rlim)
        psi = math.radians(heading_deg[j])
        psi_mid = psi + 0.5 * r * h
        s = v_mid * h / sec  # ground distance projected on the horizontal
        cm, sm = math.cos(psi_mid), math.sin(psi_mid)
        p_v[k] = v_new
        p_r[k] = math.degrees(r)
        p_s[k] = s
        half_l, half_w = 0.5 * table[t, P_LEN], 0.5 * table[t, P_WID]
        la0 = lat[j]
        if abs(la0) >= POLAR_LAT_DEG:
            la, lo, dpsi = _offset(la0, lon[j], s * cm, s * sm)
            psi2 = psi + r * h + dpsi
            _contacts(k, la, lo, psi2, half_l, half_w, pts_lat, pts_lon)
        else:
            # The move's radii and cos(phi_mid) serve the contacts too (at the new point they
            # differ by parts in 1e9 and 1e6 of a few metres: micrometres), and the new
            # heading's cosine and sine are psi_mid's rotated: four sines and cosines a
            # vehicle instead of nine.
            la, lo, dpsi, m, n, cpm = _offset_local(la0, lon[j], s * cm, s * sm)
            turn = 0.5 * r * h + dpsi
            psi2 = psi_mid + turn
            c2, s2 = _rotate(cm, sm, turn)
            _contacts_local(k, la, lo, c2, s2, math.degrees(1.0) / m, math.degrees(1.0) / (n * cpm),
                            half_l, half_w, pts_lat, pts_lon)
        p_lat[k] = la
        p_lon[k] = lo
        p_psi[k] = psi2


@numba.njit(cache=True, nogil=True)
def roll_rad(pitch_grad, roll_grad):
    """Roll (radians, right side down positive) of a body lying on the terrain's plane, whose
    height rises gp = ``pitch_grad`` per metre forward and falls gr = ``roll_grad`` per metre to
    the right (the contacts' gradients).

    With z-y-x Euler angles (heading psi, pitch theta, roll phi: the sequence of
    fdm.state.euler_to_quaternion and of _snapshot_kernel's quaternion, Stevens & Lewis,
    *Aircraft Control and Simulation*; the direction cosine matrix's first two rows are the
    body's x and y axes), in axes along the heading (forward f, right r, down d) the plane is
    d = -gp f + gr r, the body's x axis (cos theta, 0, -sin theta) and its y axis
    (sin phi sin theta, cos phi, sin phi cos theta). x on the plane: tan theta = gp. y on the
    plane: sin phi cos theta = -gp sin phi sin theta + gr cos phi, so
    tan phi cos theta (1 + gp tan theta) = gr; 1 + gp tan theta = 1 + gp^2 = 1 / cos^2 theta,
    hence tan phi = gr cos theta = gr / sqrt(1 + gp^2). atan(gr), the gradient alone, tilted the
    body off the terrain's normal by up to 0.9 degrees on a 25 degree slope, 5.9 on a 45 degree
    one (the worst heading across it)."""
    return math.atan2(roll_grad, math.sqrt(1.0 + pitch_grad * pitch_grad))


@numba.njit(cache=True, nogil=True)
def _float32_spacing(h):
    """Spacing of float32 values (m) at max(``h``, FLOAT32_SPACING_FLOOR_M), ``h`` >= 0 metres."""
    _, e = math.frexp(max(h, FLOAT32_SPACING_FLOOR_M))
    return math.ldexp(1.0, e - FLOAT32_SIGNIFICAND_BITS)


@numba.njit(cache=True, nogil=True)
def _resolve_kernel(idx, type_id, table, step_grad, p_lat, p_lon, p_psi, p_v, p_r, p_s, pts_h, pts_status,
                    water_level, lat, lon, heading_deg, speed, yaw_rate_dps, height, pitch_grad, roll_grad, side_ref,
                    blocked):
    """Accept each proposal whose wheel base is on dry, drivable ground; stop the rest.
    ``step_grad``: (types,) the side-gradient error of the terrain's coarsest height step per
    type (:func:`side_slope_tolerances`); ``side_ref``: (n,) the gentlest side gradient each
    vehicle has stood on (magnitude), updated here."""
    for k in range(idx.shape[0]):
        j = idx[k]
        t = type_id[j]
        b = N_CONTACTS * k
        code = FREE
        for q in range(N_CONTACTS):
            if pts_status[b + q] == STATUS_OUTSIDE:
                code = BLOCKED_OUTSIDE
            elif pts_h[b + q] <= water_level and code < BLOCKED_WATER:
                code = BLOCKED_WATER
        gp = 0.0
        gr = 0.0
        if code == FREE:
            gp = (pts_h[b + 1] - pts_h[b + 2]) / table[t, P_LEN]
            gr = (pts_h[b + 4] - pts_h[b + 3]) / table[t, P_WID]
            sig = 1.0 if p_s[k] > 0.0 else (-1.0 if p_s[k] < 0.0 else 0.0)
            a = sig * gp
            a0 = sig * pitch_grad[j]
            gmax = table[t, P_GRAD]
            side = table[t, P_SIDE]
            if a > gmax or (a < -gmax and (a0 >= -gmax or a < a0 - SLOPE_WORSE_TOLERANCE)):
                code = BLOCKED_SLOPE
            elif abs(gr) > side:
                # Within its limit before: any move beyond stops it. Beyond it: one steeper
                # across than the gentlest it has stood on, by more than twice the side
                # gradient's error from the heights' resolution (see FLOAT32_SIGNIFICAND_BITS).
                top = 2.0 * max(abs(pts_h[b + 3]), abs(pts_h[b + 4]))
                tol = 2.0 * max(_float32_spacing(top) / table[t, P_WID], step_grad[t])
                if abs(roll_grad[j]) <= side or abs(gr) > side_ref[j] + tol:
                    code = BLOCKED_SIDE_SLOPE
        blocked[j] = code
        if code != FREE:
            speed[j] = 0.0
            yaw_rate_dps[j] = 0.0
            continue
        lat[j] = p_lat[k]
        lon[j] = p_lon[k]
        heading_deg[j] = _heading_deg(p_psi[k])
        speed[j] = p_v[k]
        yaw_rate_dps[j] = p_r[k]
        height[j] = pts_h[b]
        pitch_grad[j] = gp
        roll_grad[j] = gr
        side_ref[j] = min(side_ref[j], abs(gr))


@numba.njit(cache=True, nogil=True)
def _snapshot_kernel(idx, lat, lon, height, heading_deg, speed, yaw_rate_dps, pitch_grad, roll_grad, undulation,
                     ecef, vel, quat, rates):
    """The world snapshot's rows of vehicles idx in one pass: ECEF position (height MSL +
    undulation above the ellipsoid), ECEF velocity, the ECEF -> body quaternion and body
    rates. The numpy compositions they replace, formula for formula:
    terrain.geodesy.geodetic_to_ecef / enu_basis, fdm.state.euler_to_quaternion (w >= 0),
    server.dead_reckoning.ned_to_ecef_quat, :meth:`GroundVehicles.velocity_ned`."""
    for k in range(idx.shape[0]):
        j = idx[k]
        phi_g, lam = math.radians(lat[j]), math.radians(lon[j])
        sl, cl = math.sin(phi_g), math.cos(phi_g)
        so, co = math.sin(lam), math.cos(lam)
        h = height[j] + undulation
        n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sl * sl)
        ecef[k, 0] = (n + h) * cl * co
        ecef[k, 1] = (n + h) * cl * so
        ecef[k, 2] = (n * (1.0 - WGS84_E2) + h) * sl
        psi = math.radians(heading_deg[j])
        th = math.atan(pitch_grad[j])
        ph = roll_rad(pitch_grad[j], roll_grad[j])
        horiz = speed[j] * math.cos(th)
        vn, ve, vd = horiz * math.cos(psi), horiz * math.sin(psi), -speed[j] * math.sin(th)
        # v_n north + v_e east - v_d up, with east (-so, co, 0), north (-sl co, -sl so, cl), up (cl co, cl so, sl)
        vel[k, 0] = vn * (-sl * co) + ve * (-so) - vd * (cl * co)
        vel[k, 1] = vn * (-sl * so) + ve * co - vd * (cl * so)
        vel[k, 2] = vn * cl - vd * sl
        # NED -> body from z-y-x Euler angles (Stevens & Lewis eq. 1.8-17), w >= 0
        cr, sr = math.cos(0.5 * ph), math.sin(0.5 * ph)
        cp, sp = math.cos(0.5 * th), math.sin(0.5 * th)
        cy, sy = math.cos(0.5 * psi), math.sin(0.5 * psi)
        bw, bx = cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy
        by, bz = cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy
        if bw < 0.0:
            bw, bx, by, bz = -bw, -bx, -by, -bz
        # ECEF -> NED: about z by the longitude, then about the new y by -(lat + 90 deg)
        zw, zz = math.cos(0.5 * lam), math.sin(0.5 * lam)
        tilt = -0.5 * (phi_g + 0.5 * math.pi)
        yw, yy = math.cos(tilt), math.sin(tilt)
        aw, ax, ay, az = zw * yw, -zz * yy, zw * yy, zz * yw
        quat[k, 0] = aw * bw - ax * bx - ay * by - az * bz
        quat[k, 1] = aw * bx + ax * bw + ay * bz - az * by
        quat[k, 2] = aw * by - ax * bz + ay * bw + az * bx
        quat[k, 3] = aw * bz + ax * by - ay * bx + az * bw
        rates[k, 0] = 0.0
        rates[k, 1] = 0.0
        rates[k, 2] = math.radians(yaw_rate_dps[j])


@numba.njit(cache=True, nogil=True)
def _divisor_kernel(lat, lon, obs_xyz, near_m, max_divisor, out):
    """Step divisor per vehicle from the great-circle distance to its nearest observer.

    Distances on the mean sphere: the smallest squared chord to the observers'
    unit vectors (obs_xyz, (m, 3)), then one arcsine; a few trig calls per
    vehicle whatever the number of observers.
    """
    for j in range(lat.shape[0]):
        p = math.radians(lat[j])
        q = math.radians(lon[j])
        cp = math.cos(p)
        x = cp * math.cos(q)
        y = cp * math.sin(q)
        z = math.sin(p)
        best = 4.0  # the largest squared chord of the unit sphere
        for o in range(obs_xyz.shape[0]):
            dx = x - obs_xyz[o, 0]
            dy = y - obs_xyz[o, 1]
            dz = z - obs_xyz[o, 2]
            c2 = dx * dx + dy * dy + dz * dz
            if c2 < best:
                best = c2
        d = 2.0 * MEAN_EARTH_RADIUS_M * math.asin(min(0.5 * math.sqrt(best), 1.0))
        div = 1
        lim = near_m
        while d > lim and div < max_divisor:
            div *= 2
            lim *= 2.0
        out[j] = div


# -- the class over the kernels -------------------------------------------------

@dataclass(frozen=True)
class GroundState:
    """A copy of the vehicles' state; every array (n,). Angles in degrees:
    heading compass [0, 360), pitch nose up +, roll right side down +."""

    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_msl_m: np.ndarray
    heading_deg: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_dps: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    blocked: np.ndarray
    time_s: np.ndarray


# The per-vehicle arrays, kept in step by add() and remove() (type_id apart).
PER_VEHICLE = ("lat", "lon", "heading_deg", "speed_mps", "yaw_rate_dps", "height_msl_m", "pitch_grad", "roll_grad",
               "side_ref", "blocked", "speed_cmd_mps", "yaw_rate_cmd_dps", "last_tick", "last_time_s", "divisor", "ids")


def height_steps(terrain) -> list[tuple[float, float, float]]:
    """(height step q, post spacing east dx, north dy), metres, of each source of ``terrain``
    whose heights are held to a step coarser than float32's: SRTM .hgt files (whole metres,
    HGT_HEIGHT_STEP_M; any source a mosaic merged one into) and terrain stores (their
    quantisation step, ``store_step_m``). From ``terrain.describe()`` (Terrain, TerrainClient:
    a service's details come as text); [] for a terrain that cannot describe itself (FlatTerrain)."""
    describe = getattr(terrain, "describe", None)
    if describe is None:
        return []
    try:
        sources = describe()
    except SortieError:  # a service that does not answer: its heights will say so
        return []
    out = []
    for d in sources:
        if not isinstance(d, dict):
            continue
        if d.get("kind") == "store":
            q = d.get("store_step_m", 0.0)
        elif d.get("kind") == "dem" and any(
                m.strip().lower().endswith(".hgt") for m in str(d.get("source", "")).split(";")):
            q = HGT_HEIGHT_STEP_M
        else:
            continue
        try:
            q, dx, dy = float(q), float(d.get("spacing_east_m", 0.0)), float(d.get("spacing_north_m", 0.0))
        except (TypeError, ValueError):
            continue
        if q > 0.0 and dx > 0.0 and dy > 0.0:
            out.append((q, dx, dy))
    return out


def side_slope_tolerances(widths_m, steps) -> np.ndarray:
    """(types,) the largest error of a side gradient measured over each track width
    ``widths_m`` (m) on the sources ``steps`` (:func:`height_steps`): q min(1 / W,
    hypot(1 / dx, 1 / dy)) at the worst source (see FLOAT32_SIGNIFICAND_BITS); 0 where none.
    The float32 term is the kernel's (it depends on the height)."""
    w = np.asarray(widths_m, np.float64)
    out = np.zeros(w.size)
    for q, dx, dy in steps:
        out = np.maximum(out, q * np.minimum(1.0 / w, math.hypot(1.0 / dx, 1.0 / dy)))
    return out


class GroundVehicles:
    """All ground vehicles of a scene, stepped together.

    terrain: anything with ``heights(lat, lon)`` answering ``height_msl_m``
    and ``status`` (Terrain, TerrainClient). lat, lon: (n,) degrees, (lat, lon)
    order; heading_deg: compass degrees; vehicle_type: one type (name or
    :class:`VehicleType`) for all, or a sequence of them, one per vehicle.
    Raises InvalidArgument naming the index of a vehicle placed in the water
    or outside the terrain.
    """

    def __init__(self, terrain, lat, lon, heading_deg, vehicle_type="m1a2", water_level_msl_m=WATER_LEVEL_MSL_M, *,
                 height_steps_of_terrain=None):
        lat, lon = check_latlon(lat, lon)
        n = lat.size
        heading = as_1d_f64("heading_deg", heading_deg)
        if heading.size == 1 and n != 1:
            heading = np.full(n, heading[0])
        if heading.size != n:
            raise InvalidArgument("heading_deg", f"must have {n} values, got {heading.size}")
        check_finite("heading_deg", heading)
        self.types, self.type_id = _resolve_types(vehicle_type, n)
        self.table = type_table(self.types)
        self.terrain = terrain
        # The terrain's coarse height steps (:func:`height_steps`; given by add(), which places
        # through a new instance, so a service is asked once).
        self.height_steps = height_steps(terrain) if height_steps_of_terrain is None else height_steps_of_terrain
        self._step_grad = side_slope_tolerances(self.table[:, P_WID], self.height_steps)
        self.water_level_msl_m = float(water_level_msl_m)
        self.n = n
        self.lat = lat.copy()
        self.lon = np.where((lon >= -180.0) & (lon < 180.0), lon, (lon + 180.0) % 360.0 - 180.0)
        self.heading_deg = heading % 360.0
        self.speed_mps = np.zeros(n)
        self.yaw_rate_dps = np.zeros(n)
        self.height_msl_m = np.zeros(n)
        # Pitch and roll are kept as gradients (tangents); pitch_deg/roll_deg convert.
        self.pitch_grad = np.zeros(n)
        self.roll_grad = np.zeros(n)
        # The gentlest side gradient (magnitude) each vehicle has stood on since it was placed:
        # the side-slope "no worse" rule's reference (_resolve_kernel).
        self.side_ref = np.zeros(n)
        self.blocked = np.zeros(n, np.uint8)
        self.speed_cmd_mps = np.zeros(n)
        self.yaw_rate_cmd_dps = np.zeros(n)
        # Time keeping: world tick/time and each vehicle's own.
        self.tick = 0
        self.time_s = 0.0
        self.last_tick = np.zeros(n, np.int64)
        self.last_time_s = np.zeros(n)
        self.divisor = np.ones(n, np.int64)
        self._observers = None
        self._divisors_stale = False
        self.near_m = 2000.0
        self.max_divisor = 8
        # Stable vehicle ids (indices shift when vehicles are removed; see index_of).
        self.ids = np.arange(n, dtype=np.int64)
        self._next_id = n
        self._size_scratch()
        self.vehicle_steps = 0  # integrations done (not sub-steps), for benchmarks
        self._place()

    def _size_scratch(self) -> None:
        """Scratch arrays sized to the vehicle count (allocated again only when it changes)."""
        n = self.n
        self._sub_dt = np.zeros(n)
        self._n_sub = np.zeros(n, np.int64)
        self._prop = [np.zeros(n) for _ in range(6)]
        self._pts_lat = np.zeros(N_CONTACTS * n)
        self._pts_lon = np.zeros(N_CONTACTS * n)
        self._all = np.arange(n, dtype=np.int64)

    # -- adding and removing vehicles -------------------------------------------

    def add(self, lat, lon, heading_deg, vehicle_type="m1a2") -> np.ndarray:
        """Place new vehicles (validated and placed on the terrain exactly as by the
        constructor; nothing is added if any is bad) at rest; their new ids."""
        new = GroundVehicles(self.terrain, lat, lon, heading_deg, vehicle_type, self.water_level_msl_m,
                             height_steps_of_terrain=self.height_steps)
        new.ids = np.arange(self._next_id, self._next_id + new.n, dtype=np.int64)
        new.last_tick[:] = self.tick
        new.last_time_s[:] = self.time_s
        types = list(self.types)
        for t in new.types:
            if not any(t is u for u in types):
                types.append(t)
        remap = np.array([next(k for k, u in enumerate(types) if u is t) for t in new.types], np.int64)
        for name in PER_VEHICLE:
            setattr(self, name, np.concatenate([getattr(self, name), getattr(new, name)]))
        self.type_id = np.concatenate([self.type_id, remap[new.type_id]])
        self.types, self.table = types, type_table(types)
        self._step_grad = side_slope_tolerances(self.table[:, P_WID], self.height_steps)
        self._next_id += new.n
        self._resized()
        return new.ids

    def remove(self, ids) -> None:
        """Remove vehicles by id; InvalidArgument (nothing removed) if any id is unknown."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        known = np.isin(ids, self.ids)
        if not known.all():
            i = first_bad(~known)
            raise InvalidArgument("ids", "no vehicle has this id", index=i, value=int(ids[i]))
        keep = ~np.isin(self.ids, ids)
        for name in PER_VEHICLE + ("type_id",):
            setattr(self, name, getattr(self, name)[keep])
        self._resized()

    def index_of(self, ids) -> np.ndarray:
        """Current indices (for ``set_controls(index=...)`` and the state arrays) of vehicle ids."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        # self.ids stays sorted: add() appends larger ids, remove() keeps the order.
        idx = np.minimum(np.searchsorted(self.ids, ids), max(self.n - 1, 0))
        bad = np.ones(ids.size, bool) if self.n == 0 else self.ids[idx] != ids
        if bad.any():
            i = first_bad(bad)
            raise InvalidArgument("ids", "no vehicle has this id", index=i, value=int(ids[i]))
        return idx

    def _resized(self) -> None:
        self.n = self.lat.size
        self._size_scratch()
        self._divisors_stale = self._observers is not None

    # -- placement and state --------------------------------------------------

    def _place(self) -> None:
        _place_kernel(self.lat, self.lon, self.heading_deg, self.type_id, self.table, self._pts_lat, self._pts_lon)
        res = self.terrain.heights(self._pts_lat, self._pts_lon)
        h = np.asarray(res.height_msl_m).reshape(self.n, N_CONTACTS)
        st = np.asarray(res.status).reshape(self.n, N_CONTACTS)
        bad = (st == STATUS_OUTSIDE).any(axis=1) | ~(h > self.water_level_msl_m).all(axis=1)
        if bad.any():
            i = first_bad(bad)
            where = "outside the terrain" if (st[i] == STATUS_OUTSIDE).any() else "in the water (height <= sea level)"
            raise InvalidArgument("lat", f"vehicle placed {where} at ({float(self.lat[i])!r}, "
                                         f"{float(self.lon[i])!r})", index=i)
        self._set_pose(self._all, h)

    def _set_pose(self, idx: np.ndarray, h: np.ndarray) -> None:
        """Height, pitch and roll of the vehicles idx from the heights (m, N_CONTACTS) of their
        contacts (centre, front, rear, left, right: _contacts)."""
        self.height_msl_m[idx] = h[:, 0]
        self.pitch_grad[idx] = (h[:, 1] - h[:, 2]) / self.table[self.type_id[idx], P_LEN]
        self.roll_grad[idx] = (h[:, 4] - h[:, 3]) / self.table[self.type_id[idx], P_WID]
        self.side_ref[idx] = np.abs(self.roll_grad[idx])  # placed: the no-worse rule starts here

    @property
    def pitch_deg(self) -> np.ndarray:
        """(n,) pitch, degrees, nose up positive: atan of the front-to-rear gradient."""
        return np.degrees(np.arctan(self.pitch_grad))

    @property
    def roll_deg(self) -> np.ndarray:
        """(n,) roll, degrees, right side down positive: the z-y-x Euler roll of the body lying on
        the terrain's plane, atan2(left-to-right gradient, sqrt(1 + front-to-rear gradient^2))
        (:func:`roll_rad`)."""
        return np.degrees(np.arctan2(self.roll_grad, np.sqrt(1.0 + self.pitch_grad * self.pitch_grad)))

    def state(self) -> GroundState:
        """A copy of the current state (see :class:`GroundState`)."""
        return GroundState(self.lat.copy(), self.lon.copy(), self.height_msl_m.copy(), self.heading_deg.copy(),
                           self.speed_mps.copy(), self.yaw_rate_dps.copy(), self.pitch_deg,
                           self.roll_deg, self.blocked.copy(), self.last_time_s.copy())

    def snapshot_rows(self, idx, undulation_m: float = 0.0) -> tuple:
        """(ECEF position, ECEF velocity, ECEF -> body quaternion (w, x, y, z), body rates,
        lat, lon, height MSL) of vehicles ``idx`` (rows), as a world snapshot holds them:
        positions at height MSL + ``undulation_m`` above the ellipsoid, the body turning
        only about its vertical (rates (0, 0, yaw rate)). One compiled pass."""
        idx = np.ascontiguousarray(idx, np.int64)
        m = idx.size
        ecef, vel, rates = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
        quat = np.empty((m, 4))
        _snapshot_kernel(idx, self.lat, self.lon, self.height_msl_m, self.heading_deg, self.speed_mps,
                         self.yaw_rate_dps, self.pitch_grad, self.roll_grad, float(undulation_m),
                         ecef, vel, quat, rates)
        return ecef, vel, quat, rates, self.lat[idx], self.lon[idx], self.height_msl_m[idx]

    def velocity_ned(self) -> np.ndarray:
        """(n, 3) velocity north, east, down in m/s along the ground (pitch included)."""
        psi = np.radians(self.heading_deg)
        th = np.radians(self.pitch_deg)
        horiz = self.speed_mps * np.cos(th)
        return np.stack([horiz * np.cos(psi), horiz * np.sin(psi), -self.speed_mps * np.sin(th)], axis=-1)

    @property
    def speed_limits_mps(self) -> tuple[np.ndarray, np.ndarray]:
        """(max reverse, max forward) speed per vehicle, m/s, both >= 0."""
        return self.table[self.type_id, P_VREV], self.table[self.type_id, P_VMAX]

    def top_speed_mps(self, index) -> np.ndarray:
        """Max forward speed (m/s) of the vehicles at rows ``index``: ``speed_limits_mps[1][index]``
        without building it for every vehicle (a route follower of a few, among 10,000)."""
        return self.table[self.type_id[np.asarray(index, np.int64)], P_VMAX]

    @property
    def yaw_rate_limit_dps(self) -> np.ndarray:
        """Largest heading-rate command accepted per vehicle, deg/s (inclusive)."""
        return self._type_yaw_limits_dps()[self.type_id]

    def _type_yaw_limits_dps(self) -> np.ndarray:
        """Each type's ``max_yaw_rate_dps`` as the type gives it: the table's radians back in
        degrees can land a hair under it (degrees(radians(30)) < 30), which refused exactly 30."""
        return np.array([t.max_yaw_rate_dps for t in self.types], dtype=np.float64)

    # -- controls ---------------------------------------------------------------

    def set_controls(self, speed_mps=None, yaw_rate_dps=None, index=None) -> None:
        """Commanded speed (m/s, negative reverses) and heading rate (deg/s,
        positive turns right/clockwise) for the vehicles in ``index`` (all when
        None). Every value is checked before any is applied: NaN/Inf, a speed
        beyond the type's forward/reverse maximum or a rate beyond its
        ``yaw_rate_limit_dps`` raise InvalidArgument naming the field and the
        index into the given array. The model still applies its dynamic
        limits (turn radius, lateral acceleration, slope) to valid commands.
        """
        idx, v, r = self.check_controls(speed_mps, yaw_rate_dps, index)
        if v is not None:
            self.speed_cmd_mps[idx] = v
        if r is not None:
            self.yaw_rate_cmd_dps[idx] = r

    def stop(self, index, reason: int = BLOCKED_COLLISION, lat=None, lon=None) -> None:
        """Stop the vehicles in ``index`` (speed 0, ``blocked`` = ``reason``), as a blocked move
        stops them; their commands stay, so they drive on from rest at the next step (a
        collision between vehicles: server/collisions.py). With ``lat``/``lon`` (degrees, one
        each), each is first put back there -- a point of the path it drove this step, where
        it hit something -- with height, pitch and roll from the terrain there; one the
        terrain does not hold there (or water) stays where it is."""
        idx = np.asarray(index, np.int64).reshape(-1)
        if lat is not None and idx.size:
            lat = np.asarray(lat, np.float64).reshape(-1).copy()
            lon = np.asarray(lon, np.float64).reshape(-1).copy()
            m = idx.size
            pts_lat, pts_lon = np.empty(m * N_CONTACTS), np.empty(m * N_CONTACTS)
            _place_kernel(lat, lon, self.heading_deg[idx].copy(), self.type_id[idx].copy(), self.table, pts_lat,
                          pts_lon)
            res = self.terrain.heights(pts_lat, pts_lon)
            h = np.asarray(res.height_msl_m).reshape(m, N_CONTACTS)
            st = np.asarray(res.status).reshape(m, N_CONTACTS)
            ok = ~(st == STATUS_OUTSIDE).any(axis=1) & (h > self.water_level_msl_m).all(axis=1)
            j = idx[ok]
            self.lat[j], self.lon[j] = lat[ok], lon[ok]
            self._set_pose(j, h[ok])
        self.speed_mps[idx] = 0.0
        self.blocked[idx] = reason

    def check_controls(self, speed_mps=None, yaw_rate_dps=None, index=None, names=None):
        """The checks of :meth:`set_controls`, applying nothing: (rows, speeds or None,
        rates or None) as it would apply them; InvalidArgument as it would raise. Both
        limits are inclusive. ``names`` (one per indexed vehicle, e.g. the world's agent
        names) label the vehicle in the message in place of ``vehicle <row>``."""
        if index is None:
            idx = self._all
        else:
            idx = np.asarray(index)
            if idx.ndim == 0:
                idx = idx.reshape(1)
            if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
                raise InvalidArgument("index", f"must be a 1-D integer array, got {idx.dtype} shape {idx.shape}")
            bad = (idx < 0) | (idx >= self.n)
            if bad.any():
                i = first_bad(bad)
                raise InvalidArgument("index", f"must be within [0, {self.n})", index=i, value=int(idx[i]))
            idx = idx.astype(np.int64)
        m = idx.size

        def which(i: int) -> str:
            label = f"vehicle {int(idx[i])}" if names is None else str(names[i])
            return f"{label} ({self.types[self.type_id[idx[i]]].name})"

        v = r = None
        if speed_mps is not None:
            v = _command("speed_mps", speed_mps, m)
            rev, fwd = self.table[self.type_id[idx], P_VREV], self.table[self.type_id[idx], P_VMAX]
            bad = (v > fwd) | (v < -rev)
            if bad.any():
                i = first_bad(bad)
                lo, hi = -float(rev[i]), float(fwd[i])
                raise InvalidArgument("speed_mps", f"must be within [{bound_text(lo, v[i])}, {bound_text(hi, v[i])}] "
                                      f"m/s for {which(i)}", index=i, value=float(v[i]))
        if yaw_rate_dps is not None:
            r = _command("yaw_rate_dps", yaw_rate_dps, m)
            lim = self._type_yaw_limits_dps()[self.type_id[idx]]
            bad = np.abs(r) > lim
            if bad.any():
                i = first_bad(bad)
                raise InvalidArgument("yaw_rate_dps", f"must be within +-{bound_text(float(lim[i]), abs(float(r[i])))} "
                                      f"deg/s for {which(i)}", index=i, value=float(r[i]))
        return idx, v, r

    # -- level of detail --------------------------------------------------------

    def set_observers(self, lat, lon, near_m: float = 2000.0, max_divisor: int = 8) -> None:
        """Observers (e.g. players' and sensors' positions), (m,) degrees: vehicles
        far from all of them step less often (see module doc). An empty set
        or None steps every vehicle every tick."""
        if lat is None or np.size(lat) == 0:
            self._observers = None
            self.divisor[:] = 1
            return
        lat, lon = check_latlon(lat, lon, prefix="observer_")
        if not (math.isfinite(near_m) and near_m > 0.0):
            raise InvalidArgument("near_m", "must be a finite distance > 0", value=near_m)
        if not (isinstance(max_divisor, (int, np.integer)) and 1 <= max_divisor <= 1024):
            raise InvalidArgument("max_divisor", "must be an integer in [1, 1024]", value=max_divisor)
        p, q = np.radians(lat), np.radians(lon)
        self._divisors_stale = True
        self._observers = np.ascontiguousarray(np.stack([np.cos(p) * np.cos(q), np.cos(p) * np.sin(q), np.sin(p)],
                                                        axis=-1))
        self.near_m = float(near_m)
        self.max_divisor = int(max_divisor)

    # -- stepping -----------------------------------------------------------------

    def step(self, dt_s: float) -> int:
        """Advance the world by dt_s seconds; returns how many vehicles were integrated."""
        dt = float(dt_s)
        if not (math.isfinite(dt) and 0.0 < dt <= MAX_DT_S):
            raise InvalidArgument("dt_s", f"must be in (0, {MAX_DT_S:g}] s", value=dt_s)
        self.tick += 1
        self.time_s += dt
        if self._observers is not None and (self._divisors_stale or self.tick % DIVISOR_REFRESH_TICKS == 0):
            self._divisors_stale = False
            _divisor_kernel(self.lat, self.lon, self._observers, self.near_m, self.max_divisor, self.divisor)
        return self._advance(dt, due_only_lagging=False)

    def sync(self) -> int:
        """Integrate every vehicle that lags the world time up to it."""
        return self._advance(0.0, due_only_lagging=True)

    def _advance(self, dt: float, due_only_lagging: bool) -> int:
        n_due = _schedule_kernel(self.tick, dt, self.time_s, self.last_tick, self.last_time_s, self.divisor,
                                 self.speed_mps, self.type_id, self.table, self._sub_dt, self._n_sub,
                                 due_only_lagging)
        if n_due == 0:
            return 0
        due = self._all if n_due == self.n else np.flatnonzero(self._n_sub > 0)
        n_max = int(self._n_sub[due].max())
        for s in range(n_max):
            idx = due if s == 0 else due[self._n_sub[due] > s]
            self._substep(idx)
        self.last_tick[due] = self.tick
        self.last_time_s[due] = self.time_s
        self.vehicle_steps += n_due
        return n_due

    def _substep(self, idx: np.ndarray) -> None:
        m = idx.size
        p = [a[:m] for a in self._prop]
        pts_lat = self._pts_lat[:N_CONTACTS * m]
        pts_lon = self._pts_lon[:N_CONTACTS * m]
        _propose_kernel(idx, self._sub_dt, self.lat, self.lon, self.heading_deg, self.speed_mps, self.pitch_grad,
                        self.type_id, self.speed_cmd_mps, self.yaw_rate_cmd_dps, self.table, *p, pts_lat, pts_lon)
        res = self.terrain.heights(pts_lat, pts_lon)
        _resolve_kernel(idx, self.type_id, self.table, self._step_grad, *p,
                        np.ascontiguousarray(res.height_msl_m, np.float64), np.ascontiguousarray(res.status, np.uint8),
                        self.water_level_msl_m, self.lat, self.lon, self.heading_deg, self.speed_mps,
                        self.yaw_rate_dps, self.height_msl_m, self.pitch_grad, self.roll_grad, self.side_ref,
                        self.blocked)


def _command(name: str, values, m: int) -> np.ndarray:
    arr = as_1d_f64(name, values)
    if arr.size == 1 and m != 1:
        arr = np.full(m, arr[0])
    if arr.size != m:
        raise InvalidArgument(name, f"must have {m} values (one per indexed vehicle), got {arr.size}")
    check_finite(name, arr)
    return arr


def _resolve_types(vehicle_type, n: int):
    """(list of distinct VehicleType, (n,) int64 index into it)."""
    def one(v, i=None):
        if isinstance(v, VehicleType):
            return v
        if isinstance(v, str):
            try:
                return get_type(v)
            except Exception as e:
                raise InvalidArgument("vehicle_type", str(e), index=i, value=v) from None
        raise InvalidArgument("vehicle_type", "must be a type name or a VehicleType", index=i, value=repr(v))

    if isinstance(vehicle_type, (str, VehicleType)):
        return [one(vehicle_type)], np.zeros(n, np.int64)
    seq = list(vehicle_type)
    if len(seq) != n:
        raise InvalidArgument("vehicle_type", f"must have {n} values (one per vehicle), got {len(seq)}")
    types: list[VehicleType] = []
    ids = np.zeros(n, np.int64)
    pos: dict = {}
    for i, v in enumerate(seq):
        t = one(v, i)
        key = id(t)
        if key not in pos:
            pos[key] = len(types)
            types.append(t)
        ids[i] = pos[key]
    return types, ids
