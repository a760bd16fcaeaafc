"""Route following and convoy spacing for ground vehicles (:mod:`fdm.ground`).

A :class:`Route` is a polyline of (lat, lon) waypoints, degrees, (lat, lon)
order. Each leg is the shorter great-circle arc of the ellipsoid's unit normals
(n-vectors: Gade, "A Non-singular Horizontal Position Representation", J.
Navigation 63(3), 2010) between its waypoints, measured with the radii of
curvature at its midpoint (M north, N east): no longitude arithmetic, so a leg
crosses the antimeridian or a pole as it crosses anywhere else. Arc length along
a leg is the angle its normal turns times the metres per radian along it there
(exact on the leg); offsets across it are metres in the plane tangent at its
midpoint (the normals projected orthographically). A leg is then the geodesic
(GeographicLib, Karney 2013) to within 1e-7 of its length and 0.2 m sideways
for legs up to 50 km at any latitude, over a pole included (tests/
test_fdm_route_probe_fixes_s30.py); a leg straight in latitude and longitude,
as they were, went round a pole along its parallel (57 % long). A leg must span
less than LEG_MAX_ARC_DEG. ``seg_dn``/``seg_de`` are the legs laid flat in order
(the route's development): each turned from the one before by the route's turn
at their waypoint, measured in that waypoint's own tangent plane, the first
along its compass heading at its midpoint; the corners and the chords over short
legs are taken from them, so a corner near a pole is the corner it is, not that
plus the meridians' convergence between two legs' midpoints. Goal points and
their offsets from a vehicle are unit normals and metres in the plane tangent at
the vehicle, pole-safe as well.

Steering is pure pursuit (Coulter, "Implementation of the Pure Pursuit Path
Tracking Algorithm", CMU-RI-TR-92-01, 1992): the goal point lies a lookahead
distance Ld = clip(k |v|, Ld_min, Ld_max) further along the route than the
vehicle's projection on it; the arc through the goal point has curvature
kappa = 2 sin(alpha) / D (alpha the goal's bearing off the heading, D its
distance), and the heading-rate command is v kappa. A tracked vehicle whose
goal lies more than PIVOT_ALPHA_DEG off its heading stops and pivots.

Speed: a route follower cruises, slows for each corner ahead (pure pursuit
turns through a corner of angle theta over about one lookahead (theta the heading
change between the route's chords over LOOKAHEAD_MIN_M either side of the
waypoint: a jog of centimetres is no corner), so the corner
speed is v_c = sqrt(a_lat Ld / theta), reached by braking at a before the
turn starts: v <= sqrt(v_c^2 + 2 a d)) and brakes to stop at the route's end
(v <= sqrt(2 a (s_end - s))); a and a_lat are half the type's limits. A convoy's leader follows the route; each
follower keeps a constant along-route gap behind its predecessor with the
constant-spacing law v_i = v_(i-1) + k_p (gap_i - spacing) (predecessor speed
fed forward; Rajamani, *Vehicle Dynamics and Control*, 2nd ed. 2012, ch. 7),
so a gap error decays with time constant 1 / k_p while speeds are within the
vehicles' limits. The leader holds to the lowest corner ceiling of any
vehicle in the column, so the column takes a corner as one body; a follower may exceed the cruise speed by CATCH_UP_FRAC to
close up, and the leader eases off while the column is strung out (its speed
scaled by 1 - excess / WAIT_DISTANCE_M, excess the largest gap beyond the
spacing), which keeps the accordion after a corner short.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from fdm.ground import GroundVehicles
from fdm.vehicle_types import P_ALAT, P_BRAKE, P_KIND, P_VMAX, P_VREV, TRACKED
from sortie.errors import InvalidArgument
from terrain.geodesy import WGS84_A_M, WGS84_E2, enu_basis, radii_of_curvature
from terrain.validate import check_latlon

PIVOT_ALPHA_DEG = 60.0
# A route's end is reached within this distance (m, along the route; at it or past it counts):
# the goal point is then the end itself, under a vehicle stopping there (stopping_speed brings it
# to within millimetres), and its bearing is rounding: a tracked vehicle that had arrived facing
# along the route pivoted 120 degrees on the spot towards it, a wheeled one was left commanding
# its full yaw rate. A vehicle there, or with its goal as near, holds its heading (pursue).
GOAL_REACHED_M = 0.5
# Lookahead distance: k |v| clipped to [min, max] metres.
LOOKAHEAD_GAIN_S = 1.5
LOOKAHEAD_MIN_M = 12.0
LOOKAHEAD_MAX_M = 60.0
# Fractions of the type's limits a controller plans with (margin for the rest).
CURVE_LAT_ACCEL_FRAC = 0.5
STOP_BRAKE_FRAC = 0.5
# Constant-spacing gain (1/s): a gap error decays with a 1/k_p = 3.3 s time constant.
SPACING_GAIN_PER_S = 0.3
# How much faster than the cruise speed a follower may drive to close a gap.
CATCH_UP_FRAC = 0.3
# The leader slows by the column's largest gap excess over this distance, down to WAIT_MIN_FRAC
# of its speed ceiling, so stragglers close up.
WAIT_DISTANCE_M = 100.0
WAIT_MIN_FRAC = 0.3
# A driver stops this far (m, bumper to bumper) behind what is in its path (server/obstacles.py),
# braking at STOP_BRAKE_FRAC of its type's deceleration.
OBSTACLE_STANDOFF_M = 4.0
# A driver passing an obstacle (stopped, or coming the other way) steers its route's goal point
# sideways so the two pass this far apart (m, side to side), for as long as it takes to get past
# (its length, the obstacle's and PASS_AFTER_M); it does not leave its route by more than
# PASS_MAX_OFFSET_M for it (it waits instead).
PASS_CLEAR_M = 1.5
PASS_AFTER_M = 10.0
PASS_MAX_OFFSET_M = 25.0
# While it steers out to pass, a driver keeps rolling at up to this speed (m/s; a wheeled vehicle
# cannot turn standing) until within PASS_CRAWL_CLEAR_M of the obstacle.
PASS_CRAWL_MPS = 3.0
PASS_CRAWL_CLEAR_M = 1.0
# A driver that has stood for BACK_OFF_AFTER_S too close to what it would pass to steer round it
# (a wheeled vehicle cannot turn standing; two meeting nose to nose at a corner) backs straight off
# at BACK_OFF_MPS (its reverse limit if lower) for BACK_OFF_S, then steers round it.
BACK_OFF_AFTER_S = 2.0
BACK_OFF_S = 3.0
BACK_OFF_MPS = 2.0
# Segments searched before and after a vehicle's last segment when projecting.
SEARCH_BEHIND = 1
SEARCH_AHEAD = 3
# Candidate closest points within this distance (m) of the closest count as equally close:
# where legs overlap (an out-and-back A -> B -> A) the two legs' distances differ only by
# rounding, and the leg whose direction agrees with the vehicle's heading is taken.
PROJECT_TIE_M = 0.5


def stopping_speed(free_m, brake_mps2, step_s=None, speed_mps=None):
    """The speed (m/s) from which a driver stops within ``free_m`` metres, braking at
    STOP_BRAKE_FRAC of ``brake_mps2``: sqrt(2 a d).

    With ``step_s`` (the time the vehicle's next integration covers: the world tick times
    its level-of-detail divisor) and its ``speed_mps`` now, d is what is left after the
    step at that speed, as a driver who acts once a step looks that far ahead, and the
    speed is at most d / step_s, so that one long step does not carry it past the point.
    At a 1 Hz world a Humvee at 29 m/s stopped 4.4 m past its route's end without them;
    at 30 Hz they move its braking point by under a metre and its stop not at all."""
    free = np.asarray(free_m, np.float64)
    if step_s is not None:
        step = np.asarray(step_s, np.float64)
        ahead = free if speed_mps is None else free - np.abs(np.asarray(speed_mps, np.float64)) * step
        return np.minimum(np.sqrt(2.0 * STOP_BRAKE_FRAC * np.asarray(brake_mps2, np.float64)
                                  * np.maximum(ahead, 0.0)), np.maximum(free, 0.0) / step)
    return np.sqrt(2.0 * STOP_BRAKE_FRAC * np.asarray(brake_mps2, np.float64) * np.maximum(free, 0.0))


def obstacle_speed_ceiling(clearance_m, brake_mps2, step_s=None, speed_mps=None):
    """The speed (m/s) from which a driver stops OBSTACLE_STANDOFF_M short of an obstacle
    ``clearance_m`` ahead (free distance, front to its near side; inf: none), braking at
    STOP_BRAKE_FRAC of ``brake_mps2`` (:func:`stopping_speed`), 0 within the standoff."""
    return stopping_speed(np.asarray(clearance_m, np.float64) - OBSTACLE_STANDOFF_M, brake_mps2, step_s, speed_mps)


def pass_offset_m(across_m, need_m, oncoming):
    """The sideways shift (m, to the right; negative: left) of a driver's path that passes an
    obstacle ``across_m`` to its right (negative: left) with ``need_m`` between their centres
    side to side plus PASS_CLEAR_M: one coming the other way is kept on the left (both keep
    right), a stopped one on the side of the smaller shift (right on a tie). NaN where the
    shift would exceed PASS_MAX_OFFSET_M."""
    across, need = np.asarray(across_m, np.float64), np.asarray(need_m, np.float64) + PASS_CLEAR_M
    right, left = across + need, across - need
    shift = np.where(np.asarray(oncoming, bool) | (np.abs(right) <= np.abs(left)), right, left)
    return np.where(np.abs(shift) <= PASS_MAX_OFFSET_M, shift, np.nan)


def swing_room_m(shift_m, turn_radius_m):
    """How far behind an obstacle a driver waiting to pass it stops, to have room to swing
    out by ``shift_m`` from a standstill: the length of an S-bend of two arcs of its least
    turning radius R, 2 sqrt(R d - d^2 / 4) for a sideways step d <= 2R (each arc turns by
    theta, d = 2R(1 - cos theta), length 2R sin theta), and at least pure pursuit's least
    look-ahead, over which its path converges on the shifted one. A vehicle that pivots
    (R = 0) needs only the standoff. From the 4 m standoff a Humvee (R = 7.6 m) could not
    step 2.8 m aside and stopped against the corner of the truck it meant to pass."""
    d = np.minimum(np.abs(np.asarray(shift_m, np.float64)), 2.0 * np.asarray(turn_radius_m, np.float64))
    r = np.asarray(turn_radius_m, np.float64)
    bend = 2.0 * np.sqrt(np.maximum(r * d - 0.25 * d * d, 0.0))
    return np.where(r > 0.0, np.maximum(bend, LOOKAHEAD_MIN_M), OBSTACLE_STANDOFF_M)


def obstacle_reach_m(speed_mps, brake_mps2):
    """How far ahead (m of clearance) a driver at ``speed_mps`` looks for obstacles: its stopping
    distance at STOP_BRAKE_FRAC of ``brake_mps2``, the standoff, two seconds of travel and 10 m."""
    v = np.abs(np.asarray(speed_mps, np.float64))
    return v * v / (2.0 * STOP_BRAKE_FRAC * np.asarray(brake_mps2, np.float64)) + OBSTACLE_STANDOFF_M + 2.0 * v + 10.0


# A leg's geometry, per leg of a route (Route.seg_axes rows, Route.seg_arc columns).
AX_MID, AX_TANGENT, AX_ALONG, AX_RIGHT = 0, 1, 2, 3
ARC_RADIUS, ARC_START, ARC_LO, ARC_HI = 0, 1, 2, 3
# A leg spans at most this arc of the globe (degrees): its midpoint's plane holds the points within
# 90 degrees of that midpoint, and at 180 degrees which way round is not defined.
LEG_MAX_ARC_DEG = 90.0


@numba.njit(cache=True, nogil=True)
def _normal(lat_deg, lon_deg):
    """The ellipsoid's unit normal (n-vector, ECEF axes) at geodetic (lat, lon) degrees, and
    the sines and cosines it is made of: (x, y, z, sin lat, cos lat, sin lon, cos lon)."""
    phi, lam = math.radians(lat_deg), math.radians(lon_deg)
    sp, cp, sl, cl = math.sin(phi), math.cos(phi), math.sin(lam), math.cos(lam)
    return cp * cl, cp * sl, sp, sp, cp, sl, cl


@numba.njit(cache=True, nogil=True)
def _radii(sin_lat):
    """Meridian radius M and prime-vertical radius N (m) where sin(latitude) is ``sin_lat``."""
    w2 = 1.0 - WGS84_E2 * sin_lat * sin_lat
    w = math.sqrt(w2)
    return WGS84_A_M * (1.0 - WGS84_E2) / (w2 * w), WGS84_A_M / w


@numba.njit(cache=True, nogil=True)
def _latlon(x, y, z):
    """Geodetic (lat, lon) degrees of the unit normal (x, y, z); lon in [-180, 180)."""
    lat = math.degrees(math.atan2(z, math.hypot(x, y)))
    lon = math.degrees(math.atan2(y, x))
    return lat, (lon - 360.0 if lon >= 180.0 else lon)


@numba.njit(cache=True, nogil=True)
def _north_east_m(sp, cp, sl, cl, dx, dy, dz):
    """North and east metres of a small change (dx, dy, dz) of the unit normal at the point of
    latitude and longitude sines and cosines (sp, cp) and (sl, cl): to first order, its
    components on the local north and east axes times M and N there."""
    m, n = _radii(sp)
    return m * (-sp * cl * dx - sp * sl * dy + cp * dz), n * (-sl * dx + cl * dy)


@numba.njit(cache=True, nogil=True)
def _leg_d2(seg_axes, seg_arc, k, px, py, pz):
    """Squared distance (m^2) from the point of unit normal (px, py, pz) to leg k, in the
    leg's midpoint plane; a point on the far side of the globe from the leg's midpoint is
    farther than any on the near side."""
    ax = seg_axes[k]
    op = ax[AX_MID, 0] * px + ax[AX_MID, 1] * py + ax[AX_MID, 2] * pz
    r = seg_arc[k, ARC_RADIUS]
    if op <= 0.0:
        return (r * (2.0 - op)) ** 2
    a = ax[AX_ALONG, 0] * px + ax[AX_ALONG, 1] * py + ax[AX_ALONG, 2] * pz
    x = ax[AX_RIGHT, 0] * px + ax[AX_RIGHT, 1] * py + ax[AX_RIGHT, 2] * pz
    da = a - min(max(a, seg_arc[k, ARC_LO]), seg_arc[k, ARC_HI])
    return da * da + x * x


@numba.njit(cache=True, nogil=True)
def _project_kernel(seg_axes, seg_arc, seg_len, cum, lat, lon, hint, heading_deg, out_s, out_x, out_seg):
    """Closest point of the route for each (lat, lon): arc length, signed cross-track, segment.

    hint[j] < 0 searches every segment, else the window around hint[j]. Among points within
    PROJECT_TIE_M of the closest (overlapping legs), one on the hint's segment or later is
    taken before one on an earlier segment (a vehicle never goes back a leg it overlaps),
    then the one on the segment most aligned with heading_deg[j] (compass degrees; NaN: no
    preference, the first).
    Cross-track is positive to the right of the route's direction. The arc length of a point
    before the first waypoint is measured along the first leg extended backwards (negative),
    of one past the last waypoint along the last leg extended on (over the route's length):
    a column lined up behind its start keeps its order and gaps (clamped to 0, every member
    stood level at s = 0, the listed first led from the back and drove into the others).
    """
    nseg = seg_len.shape[0]
    for j in range(lat.shape[0]):
        if hint[j] < 0:
            k0, k1 = 0, nseg
        else:
            k0 = max(0, hint[j] - SEARCH_BEHIND)
            k1 = min(nseg, hint[j] + SEARCH_AHEAD + 1)
        px, py, pz, sp, cp, sl, cl = _normal(lat[j], lon[j])
        best = math.inf
        for k in range(k0, k1):  # the closest distance
            best = min(best, _leg_d2(seg_axes, seg_arc, k, px, py, pz))
        bound = (math.sqrt(best) + PROJECT_TIE_M) ** 2
        # The heading as a direction of the unit normal: cos(h) north + sin(h) east.
        ch, sh = math.cos(math.radians(heading_deg[j])), math.sin(math.radians(heading_deg[j]))
        hx, hy, hz = -ch * sp * cl - sh * sl, -ch * sp * sl + sh * cl, ch * cp
        align = -math.inf
        for k in range(k0, k1):  # the best aligned of the (nearly) closest
            if _leg_d2(seg_axes, seg_arc, k, px, py, pz) > bound:
                continue
            ax = seg_axes[k]
            op = ax[AX_MID, 0] * px + ax[AX_MID, 1] * py + ax[AX_MID, 2] * pz
            up = ax[AX_TANGENT, 0] * px + ax[AX_TANGENT, 1] * py + ax[AX_TANGENT, 2] * pz
            # The leg's direction at the point's foot on it: its tangent turned to that angle.
            tx = ax[AX_TANGENT, 0] * op - ax[AX_MID, 0] * up
            ty = ax[AX_TANGENT, 1] * op - ax[AX_MID, 1] * up
            tz = ax[AX_TANGENT, 2] * op - ax[AX_MID, 2] * up
            a = (hx * tx + hy * ty + hz * tz) / max(math.sqrt(op * op + up * up), 1e-300)
            if not a == a:  # no heading: the first candidate
                a = 0.0
            if hint[j] >= 0 and k >= hint[j]:  # never back onto an earlier leg it overlaps
                a += 10.0
            if a > align:
                align = a
                r = seg_arc[k, ARC_RADIUS]
                along = ax[AX_ALONG, 0] * px + ax[AX_ALONG, 1] * py + ax[AX_ALONG, 2] * pz
                angle = math.atan2(along / r, op)  # exact on the leg, its plane's foot beside it
                along_leg = r * (angle - seg_arc[k, ARC_START])
                if k > 0:
                    along_leg = max(along_leg, 0.0)
                if k < nseg - 1:
                    along_leg = min(along_leg, seg_len[k])
                out_s[j] = cum[k] + along_leg
                out_x[j] = ax[AX_RIGHT, 0] * px + ax[AX_RIGHT, 1] * py + ax[AX_RIGHT, 2] * pz
                out_seg[j] = k


@numba.njit(cache=True, nogil=True)
def _leg_point(seg_axes, seg_arc, k, along_m):
    """The unit normal of the point ``along_m`` metres along leg k from its start, and the
    leg's unit direction there: (px, py, pz, tx, ty, tz)."""
    ax = seg_axes[k]
    angle = seg_arc[k, ARC_START] + along_m / seg_arc[k, ARC_RADIUS]
    c, s = math.cos(angle), math.sin(angle)
    px = c * ax[AX_MID, 0] + s * ax[AX_TANGENT, 0]
    py = c * ax[AX_MID, 1] + s * ax[AX_TANGENT, 1]
    pz = c * ax[AX_MID, 2] + s * ax[AX_TANGENT, 2]
    tx = c * ax[AX_TANGENT, 0] - s * ax[AX_MID, 0]
    ty = c * ax[AX_TANGENT, 1] - s * ax[AX_MID, 1]
    tz = c * ax[AX_TANGENT, 2] - s * ax[AX_MID, 2]
    return px, py, pz, tx, ty, tz


@numba.njit(cache=True, nogil=True)
def _corner_ceiling_kernel(corner_at, corner_turn, s, lookahead_m, lat_accel, brake, out):
    """Route.corner_speed_ceiling for each vehicle: the least ceiling over the corners at or
    ahead of s. Corners come in order of distance, and a corner d metres beyond the turn's
    start gives at least sqrt(2 brake d): once that reaches the least so far, no corner
    further on can lower it, and the walk stops (the same least as over every corner)."""
    first = np.searchsorted(corner_at, s)  # the first corner with at >= s
    for j in range(s.shape[0]):
        best = math.inf
        for w in range(first[j], corner_at.shape[0]):
            d = max(corner_at[w] - lookahead_m[j] - s[j], 0.0)
            if math.sqrt(2.0 * brake[j] * d) >= best:
                break
            v_c = math.sqrt(lat_accel[j] * LOOKAHEAD_MIN_M / corner_turn[w])
            best = min(best, math.sqrt(v_c * v_c + 2.0 * brake[j] * d))
        out[j] = best


@numba.njit(cache=True, nogil=True)
def _chord_heading(seg_dn, seg_de, seg_len, k, step, length_m):
    """Heading (rad) of the chord over ``length_m`` of route from the waypoint at the near end
    of segment k, walking segments k, k + step, ... (step -1: backwards, the chord then taken
    towards the waypoint); NaN when segment k alone is that long (its own heading stands)."""
    if seg_len[k] >= length_m:
        return math.nan
    dn = 0.0
    de = 0.0
    left = length_m
    while 0 <= k < seg_len.shape[0]:
        f = min(left / seg_len[k], 1.0)
        dn += f * seg_dn[k]
        de += f * seg_de[k]
        left -= seg_len[k]
        if left <= 0.0:
            break
        k += step
    return math.atan2(de, dn)


@numba.njit(cache=True, nogil=True)
def _chord_headings(seg_dn, seg_de, seg_len, length_m, before, after):
    """For each inner waypoint i (1 .. n-2): the headings of the chords over ``length_m`` before
    it (into ``before[i - 1]``) and after it (``after[i - 1]``), each to the route's end where
    it is shorter; left as they are (the adjacent segments' headings) where a segment is
    itself that long."""
    for i in range(before.shape[0]):
        h = _chord_heading(seg_dn, seg_de, seg_len, i, -1, length_m)
        if not math.isnan(h):
            before[i] = h
        h = _chord_heading(seg_dn, seg_de, seg_len, i + 1, 1, length_m)
        if not math.isnan(h):
            after[i] = h


@numba.njit(cache=True, nogil=True)
def _goal_offsets(lat, lon, goal_nv, out_dn, out_de):
    """North and east metres of each goal (unit normal goal_nv[j]) from its vehicle at (lat,
    lon), in the plane tangent at the vehicle (pole-safe: the normals' difference on its north
    and east axes; a goal is a lookahead, at most LOOKAHEAD_MAX_M, away)."""
    for j in range(lat.shape[0]):
        px, py, pz, sp, cp, sl, cl = _normal(lat[j], lon[j])
        out_dn[j], out_de[j] = _north_east_m(sp, cp, sl, cl, goal_nv[j, 0] - px, goal_nv[j, 1] - py,
                                             goal_nv[j, 2] - pz)


def pursue(v: GroundVehicles, idx: np.ndarray, goal_nv: np.ndarray, speed_cmd, reached=None):
    """(speed_cmd, yaw_rate_cmd_dps) of pure pursuit (Coulter 1992: curvature 2 sin(alpha) / L
    towards the goal point at distance L) for vehicles ``idx`` of ``v`` towards goal points of
    unit normals ``goal_nv`` ((n, 3) float64, ECEF axes: :meth:`Route.normals_at`); a tracked
    vehicle whose goal lies more than PIVOT_ALPHA_DEG off its heading stops (speed 0) and
    pivots at its yaw-rate limit, a wheeled one whose goal lies behind it turns at its limit.
    One whose goal is within GOAL_REACHED_M, or that has ``reached`` (per vehicle, bool, or
    None) its route's end, holds its heading (yaw rate 0, no pivot): it stops facing the way
    its route goes, not the way a goal millimetres off (or just behind it) happens to lie."""
    speed = v.speed_mps[idx]
    dn, de = np.empty(idx.size), np.empty(idx.size)
    _goal_offsets(v.lat[idx], v.lon[idx], goal_nv, dn, de)
    dist = np.maximum(np.hypot(dn, de), 1e-6)
    alpha = (np.arctan2(de, dn) - np.radians(v.heading_deg[idx]) + np.pi) % (2 * np.pi) - np.pi
    kappa = 2.0 * np.sin(alpha) / dist
    yaw = np.degrees(speed * kappa)
    tracked = v.table[v.type_id[idx], P_KIND] == TRACKED
    lim = v.yaw_rate_limit_dps[idx]
    there = dist < GOAL_REACHED_M if reached is None else (dist < GOAL_REACHED_M) | reached
    pivot = tracked & (np.abs(alpha) > math.radians(PIVOT_ALPHA_DEG)) & ~there
    # A goal behind a wheeled vehicle (the far end of an out-and-back route): 2 sin(alpha) / L
    # falls to 0 as alpha nears 180 deg and it would drive on away; it turns at its limit
    # towards the goal's side instead (the model's lateral-acceleration limit sets the radius).
    behind = ~tracked & (np.abs(alpha) > 0.5 * np.pi) & ~there
    yaw = np.where(pivot | behind, np.where(alpha < 0.0, -lim, lim), np.where(there, 0.0, yaw))
    speed_cmd = np.where(pivot, 0.0, speed_cmd)
    return speed_cmd, np.clip(yaw, -lim, lim)


def _unit_normals(lat_deg, lon_deg) -> np.ndarray:
    """(n, 3) float64 unit normals of the ellipsoid (n-vectors, ECEF axes) at geodetic (lat, lon)
    degrees, (n,) each."""
    phi, lam = np.radians(lat_deg), np.radians(lon_deg)
    return np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)], axis=-1)


def _dot(a, b) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def leg_geometry(lat_deg, lon_deg):
    """Each leg of the polyline of waypoints (lat, lon) (n,) degrees, n >= 2, as the leg kernels
    take it (module doc): (axes (n-1, 4, 3) float64, arc (n-1, 4) float64, length_m (n-1,),
    heading_rad (n-1,): its compass heading at its midpoint).

    axes[k]: unit vectors, ECEF axes: AX_MID the normal at the leg's midpoint, AX_TANGENT the
    leg's direction there; AX_ALONG and AX_RIGHT the metres along it and to its right per unit
    change of a normal there (its north and east components times M and N, turned onto the leg).
    arc[k]: ARC_RADIUS metres per radian of the normal along the leg; ARC_START the angle (rad)
    from the midpoint to the start (negative); ARC_LO, ARC_HI the along-metres of its ends in
    the midpoint's plane. A leg of length 0 comes out NaN: the caller refuses those, and legs
    of LEG_MAX_ARC_DEG or more."""
    nv = _unit_normals(lat_deg, lon_deg)
    a, b = nv[:-1], nv[1:]
    mid = a + b
    o = mid / np.linalg.norm(mid, axis=1)[:, None]
    o_lat = np.degrees(np.arctan2(o[:, 2], np.hypot(o[:, 0], o[:, 1])))
    o_lon = np.degrees(np.arctan2(o[:, 1], o[:, 0]))
    east, north, _ = enu_basis(o_lat, o_lon)
    m, n = radii_of_curvature(o_lat)
    d = b - a  # tangent at the midpoint (|a| = |b|): the leg's chord
    en, ee = m * _dot(north, d), n * _dot(east, d)
    chord = np.hypot(en, ee)
    un, ue = (en / chord)[:, None], (ee / chord)[:, None]
    along = un * m[:, None] * north + ue * n[:, None] * east
    right = -ue * m[:, None] * north + un * n[:, None] * east
    u = d - _dot(o, d)[:, None] * o
    u /= np.linalg.norm(u, axis=1)[:, None]
    radius = _dot(along, u)
    start, end = np.arctan2(_dot(u, a), _dot(o, a)), np.arctan2(_dot(u, b), _dot(o, b))
    axes = np.stack([o, u, along, right], axis=1)
    arc = np.stack([radius, start, _dot(along, a), _dot(along, b)], axis=1)
    return axes, arc, radius * (end - start), np.arctan2(ee, en)


def leg_turns(lat_deg, lon_deg, axes, arc, length_m) -> np.ndarray:
    """The signed turn (rad, right positive) at each inner waypoint 1 .. n-2 of the route whose
    legs are ``leg_geometry``'s: between the leg ending there and the one starting there, both
    taken in the waypoint's own tangent plane (north and east metres)."""
    east, north, _ = enu_basis(lat_deg[1:-1], lon_deg[1:-1])
    m, n = radii_of_curvature(lat_deg[1:-1])

    def direction(k, angle):  # the leg's direction at ``angle`` from its midpoint, north/east metres
        t = np.cos(angle)[:, None] * axes[k, AX_TANGENT] - np.sin(angle)[:, None] * axes[k, AX_MID]
        return m * _dot(north, t), n * _dot(east, t)

    k = np.arange(length_m.size - 1)
    in_n, in_e = direction(k, arc[k, ARC_START] + length_m[k] / arc[k, ARC_RADIUS])
    out_n, out_e = direction(k + 1, arc[k + 1, ARC_START])
    return np.arctan2(in_n * out_e - in_e * out_n, in_n * out_n + in_e * out_e)


class Route:
    """A polyline of at least two (lat, lon) waypoints, degrees; no leg under 1 mm or over
    LEG_MAX_ARC_DEG of arc (module doc).

    seg_axes (n-1, 4, 3), seg_arc (n-1, 4): each leg's geometry (:func:`leg_geometry`);
    seg_len (n-1,) its length (m); cum (n,) the arc length (m) at each waypoint; seg_dn,
    seg_de (n-1,) the legs in the route's development (m; module doc)."""

    def __init__(self, lat, lon):
        lat, lon = check_latlon(lat, lon, prefix="route_")
        if lat.size < 2:
            raise InvalidArgument("route_lat", f"a route needs at least 2 waypoints, got {lat.size}")
        self.lat = lat.copy()
        self.lon = lon.copy()
        nv = _unit_normals(lat, lon)
        arc_deg = np.degrees(np.arctan2(np.linalg.norm(np.cross(nv[:-1], nv[1:]), axis=1), _dot(nv[:-1], nv[1:])))
        bad = ~(arc_deg < LEG_MAX_ARC_DEG)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidArgument("route_lat", f"a leg must span less than {LEG_MAX_ARC_DEG:g} degrees of arc; the "
                                  f"one from waypoint {i} spans {float(arc_deg[i]):.6g}", index=i + 1,
                                  value=float(lat[i + 1]))
        with np.errstate(invalid="ignore", divide="ignore"):  # a leg of length 0 is NaN, refused below
            self.seg_axes, self.seg_arc, self.seg_len, heading = leg_geometry(lat, lon)
        bad = ~(self.seg_len > 1e-3)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidArgument("route_lat", "consecutive waypoints must be at least 1 mm apart", index=i + 1,
                                  value=float(lat[i + 1]))
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])
        # The development: the first leg along its heading, each next one turned by the turn
        # at its waypoint (in that waypoint's plane, so a corner near a pole is the corner it
        # is, not that plus the meridians' convergence between the legs' midpoints).
        turns = leg_turns(lat, lon, self.seg_axes, self.seg_arc, self.seg_len)
        laid = (heading[0] + np.concatenate([[0.0], np.cumsum(turns)]) + np.pi) % (2 * np.pi) - np.pi
        self.seg_dn = self.seg_len * np.cos(laid)
        self.seg_de = self.seg_len * np.sin(laid)
        # The corners (waypoints 1 .. n-2 where the route turns): where, and by how much. The turn
        # is the heading change between the chords over LOOKAHEAD_MIN_M before and after the
        # waypoint (the length the corner speed's curvature theta / Ld is taken over), so a jog
        # of a centimetre between long legs is no corner (it braked 25 m/s to 4 as at a right
        # angle), a finely digitised curve of radius R turns by about Ld / R, and where both
        # legs are at least that long the chords are the legs themselves (their headings).
        psi = np.arctan2(self.seg_de, self.seg_dn)
        before = psi[:-1].copy()
        after = psi[1:].copy()
        _chord_headings(self.seg_dn, self.seg_de, self.seg_len, LOOKAHEAD_MIN_M, before, after)
        turn = np.abs((after - before + np.pi) % (2 * np.pi) - np.pi)
        corner = np.flatnonzero(turn >= 1e-6)
        self.corner_at = self.cum[corner + 1]
        self.corner_turn = turn[corner]

    @property
    def length_m(self) -> float:
        return float(self.cum[-1])

    def point_at(self, s):
        """(lat, lon, heading_deg) at arc lengths s (m, clipped to the route), arrays of s's
        shape; heading_deg the route's compass heading there, in [0, 360)."""
        s = np.asarray(s, dtype=np.float64)
        nv, direction = self.normals_at(s.reshape(-1))
        lat, lon, heading = np.empty(nv.shape[0]), np.empty(nv.shape[0]), np.empty(nv.shape[0])
        _latlon_heading(nv, direction, lat, lon, heading)
        return lat.reshape(s.shape), lon.reshape(s.shape), heading.reshape(s.shape)

    def normals_at(self, s):
        """(unit normals (n, 3), unit directions (n, 3)), float64, ECEF axes: the route's points
        at arc lengths s ((n,) m, clipped to the route) as n-vectors, and its direction there."""
        s = np.ascontiguousarray(s, dtype=np.float64).reshape(-1)
        nv, direction = np.empty((s.size, 3)), np.empty((s.size, 3))
        _points_kernel(self.seg_axes, self.seg_arc, self.seg_len, self.cum, s, nv, direction)
        return nv, direction

    def project(self, lat, lon, hint=None, heading_deg=None):
        """(s, cross_track_m, segment) of each point's closest route point; s (m) runs on
        beyond the route's ends along its first and last legs extended (negative before the
        first waypoint, over :attr:`length_m` past the last), so points lined up there keep
        their order.

        hint: (n,) int64 segments from the last call (-1: search all); the
        search looks a few segments around it, which keeps a vehicle on its own
        leg where the route passes near itself. heading_deg: (n,) the vehicles'
        headings, which choose between legs that overlap (None: the first leg).
        """
        lat = np.ascontiguousarray(lat, dtype=np.float64)
        lon = np.ascontiguousarray(lon, dtype=np.float64)
        n = lat.size
        hint = np.full(n, -1, np.int64) if hint is None else np.ascontiguousarray(hint, dtype=np.int64)
        heading = np.full(n, np.nan) if heading_deg is None else np.ascontiguousarray(heading_deg, dtype=np.float64)
        s = np.zeros(n)
        x = np.zeros(n)
        seg = np.zeros(n, np.int64)
        _project_kernel(self.seg_axes, self.seg_arc, self.seg_len, self.cum, lat, lon, hint, heading, s, x, seg)
        return s, x, seg

    def corner_speed_ceiling(self, s, lookahead_m, lat_accel_mps2, brake_mps2):
        """Highest speed (m/s) at arc length s from which each corner ahead can be taken.

        Pure pursuit turns through a corner of angle theta over about one
        lookahead distance, at curvature theta / Ld; the corner speed keeps the
        lateral acceleration v^2 theta / Ld within lat_accel. The turn begins
        when the goal point reaches the corner (s = corner - Ld); before that
        the ceiling rises with the braking distance, sqrt(v_c^2 + 2 a d). All
        arguments broadcast over vehicles; corners behind (beyond s = corner)
        no longer count.
        """
        args = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (s, lookahead_m, lat_accel_mps2,
                                                                                 brake_mps2)))
        out = np.full(args[0].shape, np.inf)
        if self.corner_at.size:
            _corner_ceiling_kernel(self.corner_at, self.corner_turn, *(a.ravel() for a in args), out.reshape(-1))
        return out


def column_order(route: Route, lat, lon, heading_deg) -> np.ndarray:
    """The order of a column on ``route``: indices of the vehicles at (lat, lon) heading
    heading_deg, farthest along the route first (it leads), the rest in their order along it
    (before the first waypoint, along the first leg extended back: a column staged behind its
    start forms up front first); a stable sort, so vehicles level with each other keep the
    order they were given in."""
    lat, lon, heading = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (lat, lon, heading_deg))
    s, _, _ = route.project(lat, lon, heading_deg=np.broadcast_to(heading, lat.shape))
    return np.argsort(-s, kind="stable")


@numba.njit(cache=True, nogil=True)
def _follow_kernel(members, gaps, spacing, gain, speed, speed_cmd, cap):
    """The convoy speed law, in place, for rows ``members`` (ascending; each follows row - 1):
    speed_cmd = the one ahead's speed + gain (gap - spacing), in [0, cap]. The one ahead's speed
    is the lower of its speed and its command this tick, worked out just before (rows ascend):
    a follower reacts to the one ahead braking in the same tick, not a tick later (at a 1 Hz
    world, trucks following at 21 m/s a leader slowing to 6 m/s for a corner ran into it).
    ``gaps[p]``: the gap behind row p."""
    for i in range(members.size):
        m = members[i]
        p = m - 1
        ahead = min(max(speed[p], 0.0), speed_cmd[p])
        follow = ahead + gain[m] * (gaps[p] - spacing[m])
        speed_cmd[m] = min(max(follow, 0.0), cap[i])


class RouteFollower:
    """Pure-pursuit steering and a cruise/stop speed law for vehicles on one route.

    vehicles: the GroundVehicles; index: which of them follow this route.
    :meth:`update` computes and applies their commands.
    """

    def __init__(self, vehicles: GroundVehicles, route: Route, index, cruise_mps: float, stop_at_end: bool = True):
        self.vehicles = vehicles
        self.route = route
        self.index = np.asarray(index, dtype=np.int64).reshape(-1)
        if self.index.size == 0:
            raise InvalidArgument("index", "must name at least one vehicle")
        bad = (self.index < 0) | (self.index >= vehicles.n)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidArgument("index", f"must be within [0, {vehicles.n})", index=i, value=int(self.index[i]))
        top = float(vehicles.top_speed_mps(self.index).min())
        if not (math.isfinite(cruise_mps) and 0.0 < cruise_mps <= top):
            raise InvalidArgument("cruise_mps", f"must be in (0, {top:.3g}] m/s", value=cruise_mps)
        self.cruise_mps = float(cruise_mps)
        self.stop_at_end = stop_at_end
        self._hint = np.full(self.index.size, -1, np.int64)
        self.s = np.zeros(self.index.size)
        self.cross_track_m = np.zeros(self.index.size)
        self.locate()

    def locate(self) -> None:
        """Project the vehicles onto the route (arc length s and cross-track)."""
        v = self.vehicles
        self.s, self.cross_track_m, self._hint = self.route.project(v.lat[self.index], v.lon[self.index], self._hint,
                                                                    v.heading_deg[self.index])

    def _lookahead(self) -> np.ndarray:
        return np.clip(LOOKAHEAD_GAIN_S * np.abs(self.vehicles.speed_mps[self.index]), LOOKAHEAD_MIN_M,
                       LOOKAHEAD_MAX_M)

    def _corner_ceiling(self, lookahead=None) -> np.ndarray:
        """Speed each vehicle may have for the route's corners ahead (m/s); ``lookahead``:
        :meth:`_lookahead`'s, when the caller has it."""
        v = self.vehicles
        t = v.table[v.type_id[self.index]]
        return self.route.corner_speed_ceiling(self.s, self._lookahead() if lookahead is None else lookahead,
                                               CURVE_LAT_ACCEL_FRAC * t[:, P_ALAT], STOP_BRAKE_FRAC * t[:, P_BRAKE])

    def _end_ceiling(self) -> np.ndarray:
        """Speed from which each vehicle stops at the route's end, braking gently (m/s)."""
        v = self.vehicles
        t = v.table[v.type_id[self.index]]
        return stopping_speed(self.route.length_m - self.s, t[:, P_BRAKE])

    def _speed_ceiling(self, corner=None) -> np.ndarray:
        """The cruise speed within the corners' ceiling (``corner``, when the caller has it)
        and, stopping at the end, the end's."""
        ceiling = np.minimum(self._corner_ceiling() if corner is None else corner, self.cruise_mps)
        if self.stop_at_end:
            ceiling = np.minimum(ceiling, self._end_ceiling())
        return ceiling

    def steer(self, speed_cmd: np.ndarray, lookahead=None):
        """(speed_cmd, yaw_rate_cmd_dps) after pure pursuit for the vehicles' current poses
        (``lookahead``: :meth:`_lookahead`'s, when the caller has it)."""
        goal, _ = self.route.normals_at(self.s + (self._lookahead() if lookahead is None else lookahead))
        reached = self.s >= self.route.length_m - GOAL_REACHED_M if self.stop_at_end else None
        return pursue(self.vehicles, self.index, goal, speed_cmd, reached)

    def commands(self):
        """(speed_cmd, yaw_rate_cmd_dps) for the follower's vehicles, not applied."""
        self.locate()
        lookahead = self._lookahead()
        return self.steer(self._speed_ceiling(self._corner_ceiling(lookahead)), lookahead)

    def update(self) -> None:
        """Compute and apply this step's commands."""
        speed, yaw = self.commands()
        self.vehicles.set_controls(speed, yaw, index=self.index)


class Convoy(RouteFollower):
    """Vehicles in column on one route: index[0] leads, each follower keeps
    ``spacing_m`` of route behind the one ahead of it (see module doc)."""

    def __init__(self, vehicles: GroundVehicles, route: Route, index, cruise_mps: float, spacing_m: float,
                 gain_per_s: float = SPACING_GAIN_PER_S, stop_at_end: bool = True):
        if not (math.isfinite(spacing_m) and spacing_m > 0.0):
            raise InvalidArgument("spacing_m", "must be a finite distance > 0", value=spacing_m)
        if not (math.isfinite(gain_per_s) and gain_per_s > 0.0):
            raise InvalidArgument("gain_per_s", "must be finite and > 0", value=gain_per_s)
        super().__init__(vehicles, route, index, cruise_mps, stop_at_end)
        self.spacing_m = float(spacing_m)
        self.gain_per_s = float(gain_per_s)

    @property
    def gaps_m(self) -> np.ndarray:
        """Along-route gap of each follower to its predecessor, (n - 1,) metres."""
        return self.s[:-1] - self.s[1:]

    def commands(self):
        self.locate()
        v = self.vehicles
        lookahead = self._lookahead()
        corner = self._corner_ceiling(lookahead)
        speed_cmd = self._speed_ceiling(corner)
        # The column moves at the speed its slowest corner allows: the leader holds to the lowest
        # corner ceiling of any vehicle, so the column takes a corner as one body.
        speed_cmd[0] = min(speed_cmd[0], float(corner.min()))
        # The leader eases off while the column is strung out (after a corner or a climb).
        excess = max(float((self.gaps_m - self.spacing_m).max()), 0.0)
        speed_cmd[0] *= min(max(1.0 - excess / WAIT_DISTANCE_M, WAIT_MIN_FRAC), 1.0)
        # A follower may exceed the cruise speed by CATCH_UP_FRAC to close a gap, within its own
        # limits and the corners'; when the leader stops, its predecessor's speed 0 brings it to
        # rest spacing_m behind (_follow_kernel: each follows the one ahead's speed or command).
        cap = np.minimum(np.minimum(v.top_speed_mps(self.index[1:]), (1.0 + CATCH_UP_FRAC) * self.cruise_mps),
                         corner[1:])
        n = self.index.size
        _follow_kernel(np.arange(1, n), np.append(self.gaps_m, -np.inf), np.full(n, self.spacing_m),
                       np.full(n, self.gain_per_s), np.ascontiguousarray(v.speed_mps[self.index]), speed_cmd,
                       np.ascontiguousarray(cap))
        return self.steer(speed_cmd, lookahead)



# -- every follower of a world at once ---------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _project_all(seg_axes, seg_arc, seg_len, cum, p0, g0, v0, lat, lon, hint, heading_deg, out_s, out_x, out_seg):
    """Route.project of each follower's vehicles (rows v0[f]:v0[f + 1]) on its route (points
    from p0[f], segments from g0[f] of the concatenated arrays): the same kernel on slices."""
    for f in range(v0.shape[0] - 1):
        a, b, p, q, g, h = v0[f], v0[f + 1], p0[f], p0[f + 1], g0[f], g0[f + 1]
        _project_kernel(seg_axes[g:h], seg_arc[g:h], seg_len[g:h], cum[p:q], lat[a:b], lon[a:b], hint[a:b],
                        heading_deg[a:b], out_s[a:b], out_x[a:b], out_seg[a:b])


@numba.njit(cache=True, nogil=True)
def _corners_all(corner_at, corner_turn, c0, v0, s, lookahead_m, lat_accel, brake, out):
    """Route.corner_speed_ceiling of each follower's vehicles on its route's corners (c0[f]:c0[f + 1])."""
    for f in range(v0.shape[0] - 1):
        a, b, c, d = v0[f], v0[f + 1], c0[f], c0[f + 1]
        _corner_ceiling_kernel(corner_at[c:d], corner_turn[c:d], s[a:b], lookahead_m[a:b], lat_accel[a:b],
                               brake[a:b], out[a:b])


@numba.njit(cache=True, nogil=True)
def _points_kernel(seg_axes, seg_arc, seg_len, cum, s, out_nv, out_dir):
    """Route.normals_at: the unit normal (out_nv[j], ECEF axes) of the route's point at arc
    length s[j] (m, clipped to the route) and the route's unit direction there (out_dir[j])."""
    nseg = seg_len.shape[0]
    length = cum[nseg]
    for j in range(s.shape[0]):
        sj = s[j]
        sj = sj if sj > 0.0 else 0.0
        sj = sj if sj < length else length
        k = np.searchsorted(cum, sj, side="right") - 1
        k = min(max(k, 0), nseg - 1)
        px, py, pz, tx, ty, tz = _leg_point(seg_axes, seg_arc, k, sj - cum[k])
        out_nv[j, 0], out_nv[j, 1], out_nv[j, 2] = px, py, pz
        out_dir[j, 0], out_dir[j, 1], out_dir[j, 2] = tx, ty, tz


@numba.njit(cache=True, nogil=True)
def _points_all(seg_axes, seg_arc, seg_len, cum, p0, g0, v0, s, out_nv, out_dir):
    """Route.normals_at for each follower's vehicles at arc lengths s, on its route: the same
    kernel on slices."""
    for f in range(v0.shape[0] - 1):
        a, b, p, q, g, h = v0[f], v0[f + 1], p0[f], p0[f + 1], g0[f], g0[f + 1]
        _points_kernel(seg_axes[g:h], seg_arc[g:h], seg_len[g:h], cum[p:q], s[a:b], out_nv[a:b], out_dir[a:b])


@numba.njit(cache=True, nogil=True)
def _latlon_heading(nv, direction, out_lat, out_lon, out_heading):
    """Geodetic (lat, lon) degrees of each unit normal nv[j], and the compass heading (degrees,
    [0, 360)) there of the unit tangent direction[j]."""
    for j in range(nv.shape[0]):
        lat, lon = _latlon(nv[j, 0], nv[j, 1], nv[j, 2])
        _, _, _, sp, cp, sl, cl = _normal(lat, lon)
        dn, de = _north_east_m(sp, cp, sl, cl, direction[j, 0], direction[j, 1], direction[j, 2])
        h = math.degrees(math.atan2(de, dn)) % 360.0
        out_lat[j], out_lon[j], out_heading[j] = lat, lon, (h if h < 360.0 else 0.0)


@numba.njit(cache=True, nogil=True)
def _shift_kernel(offset, goal_nv, direction):
    """Move each goal point (unit normal goal_nv[j], in place) ``offset[j]`` metres (0: left as
    it is) to the right of the route's direction there (``direction[j]``, a unit tangent), in
    the plane tangent at the goal: pole-safe, on the normal itself."""
    for j in range(goal_nv.shape[0]):
        if offset[j] == 0.0:
            continue
        gx, gy, gz = goal_nv[j, 0], goal_nv[j, 1], goal_nv[j, 2]
        cp = math.hypot(gx, gy)
        sp, cl, sl = gz, (gx / cp if cp > 0.0 else 1.0), (gy / cp if cp > 0.0 else 0.0)
        dn, de = _north_east_m(sp, cp, sl, cl, direction[j, 0], direction[j, 1], direction[j, 2])
        norm = max(math.hypot(dn, de), 1e-300)
        m, n = _radii(sp)
        qn, qe = offset[j] * (-de / norm) / m, offset[j] * (dn / norm) / n  # radians north and east
        x, y, z = gx - qn * sp * cl - qe * sl, gy - qn * sp * sl + qe * cl, gz + qn * cp
        r = math.sqrt(x * x + y * y + z * z)
        goal_nv[j, 0], goal_nv[j, 1], goal_nv[j, 2] = x / r, y / r, z / r


class FollowerSet:
    """Every route follower (and convoy) of one GroundVehicles, updated in one pass: the
    same commands as each follower's :meth:`RouteFollower.update`, bit for bit, applied
    at once. A world tick updates its followers through one (server/world.py): each
    follower's own update is a few dozen numpy calls over its few vehicles, about 0.1 ms,
    so a hundred convoys took 10 ms a tick; here the routes' arrays are concatenated once,
    the projection, the corners and the goal points are compiled passes over every
    vehicle, and the speed law and the steering numpy over all of them together."""

    def __init__(self, followers):
        self.followers = list(followers)
        if not self.followers:
            return
        v = self.vehicles = self.followers[0].vehicles
        if any(f.vehicles is not v for f in self.followers):
            raise InvalidArgument("followers", "must all drive the same GroundVehicles")
        routes = [f.route for f in self.followers]
        sizes = np.array([f.index.size for f in self.followers], np.int64)
        self.index = np.concatenate([f.index for f in self.followers])
        self._v0 = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self._p0 = np.concatenate([[0], np.cumsum([r.lat.size for r in routes])]).astype(np.int64)
        self._g0 = np.concatenate([[0], np.cumsum([r.seg_len.size for r in routes])]).astype(np.int64)
        self._c0 = np.concatenate([[0], np.cumsum([r.corner_at.size for r in routes])]).astype(np.int64)
        self._route = {name: np.concatenate([getattr(r, name) for r in routes])
                       for name in ("seg_axes", "seg_arc", "seg_len", "cum", "corner_at", "corner_turn")}

        def each(values):
            return np.repeat(np.asarray(values, np.float64), sizes)

        self._length = each([r.length_m for r in routes])
        self._cruise = each([f.cruise_mps for f in self.followers])
        self._stops = np.repeat([f.stop_at_end for f in self.followers], sizes)
        convoy = np.array([isinstance(f, Convoy) for f in self.followers])
        self._starts = self._v0[:-1]
        self._leaders = self._starts[convoy]  # rows of the convoys' leaders
        member = np.repeat(convoy, sizes)
        member[self._starts] = False
        self._members = np.flatnonzero(member)  # rows of the convoys' other vehicles
        self._spacing = each([getattr(f, "spacing_m", np.nan) for f in self.followers])
        self._gain = each([getattr(f, "gain_per_s", np.nan) for f in self.followers])
        self._convoy = convoy
        # Per vehicle, its convoy's number (vehicles of one convoy keep their spacing by the
        # convoy's law, not by braking for each other), -1 for a route follower's.
        self.convoy_of = np.repeat(np.where(convoy, np.arange(convoy.size), -1), sizes).astype(np.int64)
        # and its place in the column (0: the leader), by which it brakes for a member behind it in
        # the column that stands in its path (server/obstacles.py).
        self.place = np.arange(self.index.size, dtype=np.int64) - np.repeat(self._starts, sizes)
        self._pass_offset = self._pass_until = None  # passes in progress (see update), made on the first
        self._s = None  # each vehicle's arc length along its route at the last update
        self._x = None  # and its cross-track (m, right of the route)

    def remaining_m(self) -> np.ndarray:
        """Per vehicle of :attr:`index`, the route still ahead of it (m) as of the last update, for
        those that stop at their route's end; inf for the others and before the first update."""
        if self._s is None:
            return np.full(self.index.size, np.inf)
        return np.where(self._stops, np.maximum(self._length - self._s, 0.0), np.inf)

    def cross_track_m(self) -> np.ndarray:
        """Per vehicle of :attr:`index`, how far it is right of its route (m, negative: left) as
        of the last update, where it is not passing (0 where it is, and before the first
        update): off its route by a corner it cut, not by a pass it is making."""
        if self._x is None:
            return np.zeros(self.index.size)
        if self._pass_offset is None:
            return self._x.copy()
        return np.where(self._s < self._pass_until, 0.0, self._x)

    def update(self, ceiling_mps=None, pass_offset=None, pass_length=None, backing=None, step_s=None) -> None:
        """Every follower's update (locate, speed law, pure pursuit), applied at once;
        ``ceiling_mps`` (per vehicle of :attr:`index`, or None): a further speed ceiling (an
        obstacle ahead, :func:`obstacle_speed_ceiling`). ``pass_offset``/``pass_length`` (per
        vehicle, NaN: none): pass an obstacle with the path shifted ``pass_offset`` metres to
        the right (:func:`pass_offset_m`) for the next ``pass_length`` metres of route; a
        pass in progress on the same side keeps the larger shift and the farther end.
        ``backing`` (per vehicle, bool, or None): back straight off at BACK_OFF_MPS.
        ``step_s`` (per vehicle, or None): the time each vehicle's next integration covers,
        which caps its speed near its route's end (:func:`stopping_speed`)."""
        if not self.followers:
            return
        v, idx, fs, r = self.vehicles, self.index, self.followers, self._route
        n = idx.size
        hint = np.concatenate([f._hint for f in fs])
        s, x, seg = np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
        _project_all(r["seg_axes"], r["seg_arc"], r["seg_len"], r["cum"], self._p0, self._g0, self._v0, v.lat[idx],
                     v.lon[idx], hint, v.heading_deg[idx], s, x, seg)
        for f, a, b in zip(fs, self._v0[:-1].tolist(), self._v0[1:].tolist()):
            f.s, f.cross_track_m, f._hint = s[a:b], x[a:b], seg[a:b]
        self._s, self._x = s, x
        speed = v.speed_mps[idx]
        lookahead = np.clip(LOOKAHEAD_GAIN_S * np.abs(speed), LOOKAHEAD_MIN_M, LOOKAHEAD_MAX_M)
        t = v.table[v.type_id[idx]]
        corner = np.full(n, np.inf)
        _corners_all(r["corner_at"], r["corner_turn"], self._c0, self._v0, s, lookahead,
                     CURVE_LAT_ACCEL_FRAC * t[:, P_ALAT], STOP_BRAKE_FRAC * t[:, P_BRAKE], corner)
        speed_cmd = np.minimum(corner, self._cruise)
        end = stopping_speed(self._length - s, t[:, P_BRAKE], step_s, speed)
        speed_cmd = np.where(self._stops, np.minimum(speed_cmd, end), speed_cmd)
        if self._leaders.size:
            self._convoy_law(speed_cmd, corner, s, speed, t)
        if ceiling_mps is not None:
            speed_cmd = np.minimum(speed_cmd, ceiling_mps)
        goal, direction = np.empty((n, 3)), np.empty((n, 3))
        _points_all(r["seg_axes"], r["seg_arc"], r["seg_len"], r["cum"], self._p0, self._g0, self._v0, s + lookahead,
                    goal, direction)
        offset = self._passing(s, pass_offset, pass_length)
        if offset is not None:
            self._shift_goals(offset, goal, direction)
        speed_cmd, yaw_cmd = pursue(v, idx, goal, speed_cmd, self._stops & (s >= self._length - GOAL_REACHED_M))
        if backing is not None and backing.any():
            rev = v.table[v.type_id[idx[backing]], P_VREV]
            speed_cmd = np.where(backing, 0.0, speed_cmd)
            speed_cmd[backing] = -np.minimum(BACK_OFF_MPS, rev)
            yaw_cmd = np.where(backing, 0.0, yaw_cmd)
        v.set_controls(speed_cmd, yaw_cmd, index=idx)

    def _passing(self, s, pass_offset, pass_length):
        """The passes in progress after this update's requests (see :meth:`update`): per
        vehicle its path's shift to the right (m), or None when no vehicle is passing."""
        n = s.size
        if self._pass_offset is None:
            if pass_offset is None or np.isnan(pass_offset).all():
                return None
            self._pass_offset, self._pass_until = np.zeros(n), np.full(n, -np.inf)
        if pass_offset is not None:
            new = ~np.isnan(pass_offset)
            active = s < self._pass_until
            same_side = np.sign(self._pass_offset) == np.sign(pass_offset)
            keep = new & active & same_side & (np.abs(self._pass_offset) >= np.abs(pass_offset))
            self._pass_offset = np.where(new & ~keep, pass_offset, self._pass_offset)
            until = s + np.where(new, pass_length, -np.inf)
            self._pass_until = np.where(new & ~(active & same_side), until, np.maximum(self._pass_until, until))
        offset = np.where(s < self._pass_until, self._pass_offset, 0.0)
        return offset if offset.any() else None

    @staticmethod
    def _shift_goals(offset, goal_nv, direction) -> None:
        """Move the goal points (unit normals goal_nv, in place) ``offset`` metres to the right
        of the route's direction there (``direction``: :meth:`Route.normals_at`'s)."""
        _shift_kernel(np.ascontiguousarray(offset, np.float64), goal_nv, direction)

    def _convoy_law(self, speed_cmd, corner, s, speed, t) -> None:
        """Convoy.commands' speed law for every convoy, into speed_cmd."""
        gaps = np.append(s[:-1] - s[1:], -np.inf)  # row j: the gap behind vehicle j
        excess_of = np.append(gaps[:-1] - self._spacing[1:], -np.inf)
        excess_of[self._starts[1:] - 1] = -np.inf  # pairs across two followers
        lead = self._leaders
        k = np.flatnonzero(self._convoy)
        corner_min = np.minimum.reduceat(corner, self._starts)[k]
        excess = np.maximum(np.maximum.reduceat(excess_of, self._starts)[k], 0.0)
        speed_cmd[lead] = np.minimum(speed_cmd[lead], corner_min)
        speed_cmd[lead] *= np.minimum(np.maximum(1.0 - excess / WAIT_DISTANCE_M, WAIT_MIN_FRAC), 1.0)
        m = self._members
        cap = np.minimum(np.minimum(t[m, P_VMAX], (1.0 + CATCH_UP_FRAC) * self._cruise[m]), corner[m])
        _follow_kernel(m, gaps, self._spacing, self._gain, np.ascontiguousarray(speed), speed_cmd, cap)
