"""What lies ahead of a ground vehicle: the nearest entity in the strip it is about to drive over.

An autopilot driver (a route follower or a convoy, fdm.convoy) brakes for what is in its path:
another vehicle, a wreck, a static site, an aircraft on the ground. For each vehicle asked about,
every entity within its look-ahead is put in the vehicle's own frame (ahead along its heading,
across to its right, up) and is in the path when it is ahead, within the vehicle's half width
plus its own half extent across the heading (and a margin) to either side, and within their
heights of each other, with its centre in front of the vehicle's front (what is beside it is
not in its way: two vehicles parked side by side do not hold each other). The clearance is the
free distance along the heading from the vehicle's front to the entity's near side: ahead less
the vehicle's half length and the entity's half extent along the heading (boxes by their
footprint); negative when they already overlap. An entity's heading is from its own north, and
is carried onto the vehicle's horizontal through ECEF: near a pole two neighbours' norths differ
by tens of degrees (a convoy's vehicle just past the pole, heading "south", still goes its
follower's way; its follower braked for it as for one met head-on). A sphere (a site, an
aircraft, a wreck of one) meets a vehicle where server/collisions.py says they touch, within
the sum of their radii (the vehicle's the circle round its footprint): it reaches that much
less the vehicle's half width across the path and less its half length along it.

Broad phase: the entities sorted once on the ECEF axis along which they spread most; each
vehicle looks at those within its look-ahead on that axis (binary search), so a tick of 2000
vehicles costs a sort and a few neighbours each, not all pairs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from server.collisions import _forward_in

# Free space either side of the path (m): a vehicle brakes for what would pass closer than this.
PATH_MARGIN_M = 0.75
# Crossing traffic: a mover whose heading differs from the vehicle's by at least CROSSING_MIN_DEG
# (and at most 180 less it: head-on and same-way traffic is the path's) and whose closest approach,
# both going on as they go, comes within YIELD_HORIZON_S and closer than their radii and
# YIELD_MARGIN_M, is a conflict; the vehicle that has the other on its right yields (the
# right-hand rule: of two crossing, exactly one sees the other on its right), stopping short of
# where it would be at the closest approach. Movers are at least MOVING_MPS.
CROSSING_MIN_DEG = 25.0
YIELD_HORIZON_S = 6.0
YIELD_MARGIN_M = 1.5
MOVING_MPS = 0.5


@numba.njit(cache=True, nogil=True)
def _ahead_kernel(p, vel, lat_deg, lon_deg, heading_rad, radius, half_l, half_w, group, place, rows, reach, offset,
                  min_speed, out_clear, out_row, out_across, out_need, out_yield):
    n = p.shape[0]
    v_max = 0.0
    for i in range(n):
        v_max = max(v_max, math.sqrt(vel[i, 0] ** 2 + vel[i, 1] ** 2 + vel[i, 2] ** 2))
    cos_cross = math.cos(math.radians(CROSSING_MIN_DEG))
    best, axis = -1.0, 0
    for ax in range(3):  # the axis the entities spread most along
        m = 0.0
        for i in range(n):
            m += p[i, ax]
        m /= n
        v = 0.0
        for i in range(n):
            v += (p[i, ax] - m) ** 2
        if v > best:
            best, axis = v, ax
    fwd = np.empty((n, 3))  # each entity's heading as an ECEF unit vector (comparable anywhere)
    for i in range(n):
        sp, cp = math.sin(math.radians(lat_deg[i])), math.cos(math.radians(lat_deg[i]))
        sl, cl = math.sin(math.radians(lon_deg[i])), math.cos(math.radians(lon_deg[i]))
        sh, ch = math.sin(heading_rad[i]), math.cos(heading_rad[i])
        fwd[i, 0], fwd[i, 1], fwd[i, 2] = -sh * sl - ch * sp * cl, sh * cl - ch * sp * sl, ch * cp
    order = np.argsort(p[:, axis])
    keys = p[order, axis]
    r_max = 0.0
    for i in range(n):
        r_max = max(r_max, radius[i])
    for k in range(rows.shape[0]):
        i = rows[k]
        out_clear[k] = math.inf
        out_row[k] = -1
        out_yield[k] = math.inf
        if i < 0:
            continue
        sp, cp = math.sin(math.radians(lat_deg[i])), math.cos(math.radians(lat_deg[i]))
        sl, cl = math.sin(math.radians(lon_deg[i])), math.cos(math.radians(lon_deg[i]))
        ex, ey = -sl, cl
        nx, ny, nz = -sp * cl, -sp * sl, cp
        ux, uy, uz = cp * cl, cp * sl, sp
        fe, fn = math.sin(heading_rad[i]), math.cos(heading_rad[i])  # ahead, east and north parts
        vie = vel[i, 0] * ex + vel[i, 1] * ey
        vin = vel[i, 0] * nx + vel[i, 1] * ny + vel[i, 2] * nz
        window = reach[k] + radius[i] + r_max + v_max * YIELD_HORIZON_S
        lo = np.searchsorted(keys, p[i, axis] - window)
        hi = np.searchsorted(keys, p[i, axis] + window, side="right")
        for o in range(lo, hi):
            j = order[o]
            if j == i or (group[i] >= 0 and group[j] == group[i] and place[j] <= place[i]
                          and fwd[i, 0] * fwd[j, 0] + fwd[i, 1] * fwd[j, 1] + fwd[i, 2] * fwd[j, 2] > 0.0):
                continue  # ahead of it in its own column, going its way: the convoy's law spaces it
            dx, dy, dz = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
            up = dx * ux + dy * uy + dz * uz
            if abs(up) > radius[i] + radius[j]:
                continue  # above or below (an aircraft overhead, a bridge's traffic)
            de = dx * ex + dy * ey
            dn = dx * nx + dy * ny + dz * nz
            ahead = de * fe + dn * fn
            across = de * fn - dn * fe  # to the right
            vje = vel[j, 0] * ex + vel[j, 1] * ey
            vjn = vel[j, 0] * nx + vel[j, 1] * ny + vel[j, 2] * nz
            sj = math.sqrt(vje * vje + vjn * vjn)
            if across > 0.0 and sj >= MOVING_MPS and abs(vje * fe + vjn * fn) <= cos_cross * sj:
                # Crossing traffic on its right: yield when they would come too close.
                we, wn = vje - vie, vjn - vin
                ww = we * we + wn * wn
                t = -(de * we + dn * wn) / ww if ww > 0.0 else 0.0
                if 0.0 < t <= YIELD_HORIZON_S:
                    ce, cn = de + we * t, dn + wn * t
                    if ce * ce + cn * cn < (radius[i] + radius[j] + YIELD_MARGIN_M) ** 2:
                        # Stop short of its position then, by the two radii and the margin.
                        own = (vie * fe + vin * fn) * t - radius[i] - radius[j] - YIELD_MARGIN_M
                        out_yield[k] = min(out_yield[k], own)
            if sj < min_speed:
                continue  # only movers asked for (the lane a pass would take)
            if half_l[j] > 0.0:  # a box: its half extents along and across i's heading
                ge, gn = _forward_in(lat_deg[j], lon_deg[j], heading_rad[j], ex, ey, nx, ny, nz)
                c = abs(fe * ge + fn * gn)
                s = abs(fe * gn - fn * ge)
                ext_along = half_l[j] * c + half_w[j] * s
                ext_across = half_l[j] * s + half_w[j] * c
            else:  # a sphere touches i where the collision test says: within their two radii
                ext_along = radius[j] + radius[i] - half_l[i]
                ext_across = radius[j] + radius[i] - half_w[i]
            if abs(across - offset[k]) > half_w[i] + ext_across + PATH_MARGIN_M:
                continue
            clear = ahead - half_l[i] - ext_along
            if ahead < half_l[i] or clear > reach[k]:
                continue  # beside it (no further in front than its own front: not in its way), or far
            if clear < out_clear[k]:
                out_clear[k] = clear
                out_row[k] = j
                out_across[k] = across
                out_need[k] = half_w[i] + ext_across


def clearance_ahead(ecef_m, lat_deg, lon_deg, heading_deg, radius_m, half_length_m, half_width_m, group, rows,
                    reach_m, vel_ecef_mps=None, offset_m=None, min_speed_mps=0.0, place=None) -> tuple:
    """For each vehicle ``rows`` (indices into the entity arrays; -1: none) the free distance
    (m) from its front to the nearest entity in its path ahead (the module docstring), that
    entity's index, how far it is to the vehicle's right (m, negative: left) and how far apart
    sideways their centres must be for the two to pass clear (m: their half extents across
    the heading); inf, -1, NaN, NaN where nothing is within ``reach_m`` (per row, metres of
    clearance); and how far it may go on before yielding to crossing traffic (m, the module
    docstring's right-hand rule; inf: no conflict; ``vel_ecef_mps`` (n, 3): the entities'
    velocities, None: nobody moves). ``offset_m`` (per row; None: 0): the path searched runs
    that far to the vehicle's right of it, parallel (the lane a pass would take);
    ``min_speed_mps``: only entities moving at least this fast count for the path.

    Entity arrays (n,): ECEF positions (n, 3) m, geodetic lat/lon, heading (degrees from north;
    of boxes, and of the asking vehicles), bounding radius, half length (0: a sphere), half
    width; ``group`` (n,) int64: an entity of a group (>= 0) ignores one of its group going
    its way that is ahead of it in the group's column (``place`` (n,) int64, 0 the leader;
    None: all level, every one ignored): a convoy, whose spacing its own law keeps. One met
    head-on (on an out-and-back route the leader meets its own column) is traffic, and so is
    one behind it in the column that stands in its path: a column out of order does not drive
    into itself (a leader staged behind its column rammed it)."""
    rows = np.ascontiguousarray(rows, np.int64)
    clear, row = np.full(rows.size, np.inf), np.full(rows.size, -1, np.int64)
    across, need = np.full(rows.size, np.nan), np.full(rows.size, np.nan)
    yield_m = np.full(rows.size, np.inf)
    p = np.ascontiguousarray(ecef_m, np.float64).reshape(-1, 3)
    if rows.size == 0 or p.shape[0] < 2:
        return clear, row, across, need, yield_m
    vel = np.zeros_like(p) if vel_ecef_mps is None else np.nan_to_num(np.asarray(vel_ecef_mps, np.float64))
    finite = np.isfinite(p).all(axis=1)
    if not finite.all():  # an entity with no position is in nobody's path
        p = np.where(finite[:, None], p, 1.0e12)

    def column(values, dtype=np.float64):
        return np.ascontiguousarray(np.broadcast_to(np.asarray(values, dtype), (p.shape[0],)))

    _ahead_kernel(p, np.ascontiguousarray(vel.reshape(-1, 3)), column(lat_deg), column(lon_deg),
                  np.radians(column(heading_deg)), column(radius_m), column(half_length_m), column(half_width_m),
                  column(group, np.int64), column(0 if place is None else place, np.int64), rows,
                  np.ascontiguousarray(np.broadcast_to(np.asarray(reach_m, np.float64), rows.shape)),
                  np.ascontiguousarray(np.broadcast_to(np.asarray(0.0 if offset_m is None else offset_m, np.float64),
                                                       rows.shape)),
                  float(min_speed_mps), clear, row, across, need, yield_m)
    return clear, row, across, need, yield_m
