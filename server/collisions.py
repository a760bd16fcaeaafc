"""Collisions between agents: which pairs of entities came into contact during a world tick.

Every entity moving over a tick is a straight ECEF segment from its position in the
previous snapshot to its position in this one (the same path the terrain collision test
uses). Two entities collide in a tick when they were apart at its start and touch during
it; pairs already touching at the start are an ongoing contact, not a new collision, so a
collision is reported once however long the two stay together. On request the same pass
lists the ongoing contacts too (touching at the tick's start and at its end), which the
world uses to keep a vehicle from driving on through what it touches.

Shapes:

- **Ground vehicles** are boxes: length x width of their type (fdm.vehicle_types) on the
  local horizontal, along their heading. Two boxes touch when they overlap on the tangent
  plane (the separating-axis test on the four edge directions: Gottschalk, Lin and Manocha,
  "OBBTree", SIGGRAPH 1996, sec. 4, in two dimensions) and their centres are within the
  sum of their bounding radii vertically; the other's heading, which is from its own north,
  is carried onto the first's horizontal through ECEF (near a pole two vehicles a few metres
  apart have norths tens of degrees apart: two side by side 0.3 m apart 11 m from the pole
  were found touching, 0.17 m deep). Boxes are tested at the start of the tick and
  then at every half of the narrower one's width of relative travel up to its end (their
  headings the end's): at 30 Hz two vehicles close by at most about 2 m a tick, so the end
  alone is tested; at a low world rate (1 Hz: up to 60 m) more instants are, so two boxes
  cannot pass through each other between two tests unless one only grazes the other's
  corner by less than that.
- **Everything else** (aircraft, static entities, external entities, and a ground vehicle
  against any of them) is a sphere about its reference point, tested continuously: the
  least distance between two points moving linearly over the tick (r(t) = r0 + t dr,
  t in [0, 1], least at t = -r0.dr / |dr|^2 clamped; Ericson, *Real-Time Collision
  Detection*, 2005, sec. 5.9.2), so an aircraft closing at 600 m/s (20 m a tick at 30 Hz)
  cannot pass through another between snapshots.

Broad phase: sort and sweep (Baraff, *Dynamic Simulation of Non-Penetrating Rigid Bodies*,
1992, ch. 7) on the axis along which the entities spread most, with each entity's swept
box (its segment's bounding box, grown by its radius); only pairs whose boxes overlap on
all three axes reach the exact test. One compiled pass: ~2000 ground vehicles and a few
hundred aircraft take well under a millisecond.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# The most contacts one pass returns before it is run again with room for more.
INITIAL_CAPACITY_PER_ENTITY = 2


@numba.njit(cache=True, nogil=True)
def _forward_in(lat_deg, lon_deg, heading_rad, ex, ey, nx, ny, nz):
    """(east, north) unit components, on the horizontal whose east and north are the ECEF unit
    vectors ``ex, ey`` (0) and ``nx, ny, nz``, of the direction ``heading_rad`` from true north
    at (lat, lon) degrees: its ECEF vector sin(h) east + cos(h) north there, projected and
    renormalised. Where the two norths agree (anywhere but within kilometres of a pole) it is
    (sin h, cos h) to rounding; near a pole it turns by the meridians' convergence."""
    sp, cp = math.sin(math.radians(lat_deg)), math.cos(math.radians(lat_deg))
    sl, cl = math.sin(math.radians(lon_deg)), math.cos(math.radians(lon_deg))
    sh, ch = math.sin(heading_rad), math.cos(heading_rad)
    fx, fy, fz = -sh * sl - ch * sp * cl, sh * cl - ch * sp * sl, ch * cp
    fe, fn = fx * ex + fy * ey, fx * nx + fy * ny + fz * nz
    norm = math.sqrt(fe * fe + fn * fn)
    if norm < 1e-9:  # straight up the other's horizontal: only across the globe, never a neighbour
        return sh, ch
    return fe / norm, fn / norm


def forward_ecef(lat_deg, lon_deg, heading_deg) -> np.ndarray:
    """(..., 3) ECEF unit vectors of the directions ``heading_deg`` (degrees from true north)
    on the local horizontals at (lat, lon) degrees: sin(h) east + cos(h) north."""
    from terrain.geodesy import enu_basis

    east, north, _ = enu_basis(lat_deg, lon_deg)
    h = np.radians(np.asarray(heading_deg, np.float64))[..., None]
    return np.sin(h) * east + np.cos(h) * north


@numba.njit(cache=True, nogil=True)
def _box_overlap(dx, dy, ci, si, li, wi, cj, sj, lj, wj):
    """Whether two rectangles on a plane overlap: centres ``dx, dy`` apart (j - i, east and
    north metres), headings as cos/sin (``ci, si``: unit vector along the length, east and
    north components), half lengths ``l`` and half widths ``w`` (separating-axis test)."""
    # Each box's two axes: along (c, s) and across (s, -c) (the east/north plane's normal
    # to the heading). A separating axis among the four exists iff the boxes are apart.
    axes = ((ci, si), (si, -ci), (cj, sj), (sj, -cj))
    for k in range(4):
        ax, ay = axes[k]
        dist = abs(dx * ax + dy * ay)
        ri = li * abs(ci * ax + si * ay) + wi * abs(si * ax - ci * ay)
        rj = lj * abs(cj * ax + sj * ay) + wj * abs(sj * ax - cj * ay)
        if dist > ri + rj:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _contacts_kernel(p0, p1, radius, lat_deg, lon_deg, heading_rad, half_l, half_w, moves, ongoing, out_i, out_j,
                     out_t, out_d):
    """New contacts among n entities (see the module docstring), as rows (out_i, out_j,
    out_t, out_d): the two entities' indices (i < j), the fraction of the tick at which they
    first touch (spheres: the smaller root of |r(t)| = r_i + r_j; boxes: the first instant
    tested that overlaps) and their reference points' distance then (spheres: the least over
    the tick). With ``ongoing``, also the pairs touching at the tick's start and still at its
    end, with out_t -1 and their distance at the end. Returns the count, or minus the count
    needed when the outputs are too small. ``moves`` says which entities can move (pairs of
    two that cannot are skipped)."""
    n = p0.shape[0]
    # The sweep's axis: the one along which the paths' midpoints spread most.
    best, axis = -1.0, 0
    for ax in range(3):
        m = 0.0
        for i in range(n):
            m += p0[i, ax] + p1[i, ax]
        m /= 2.0 * n
        v = 0.0
        for i in range(n):
            c = 0.5 * (p0[i, ax] + p1[i, ax]) - m
            v += c * c
        if v > best:
            best, axis = v, ax
    lo = np.empty(n)
    hi = np.empty(n)
    for i in range(n):
        a, b = p0[i, axis], p1[i, axis]
        lo[i] = min(a, b) - radius[i]
        hi[i] = max(a, b) + radius[i]
    order = np.argsort(lo)
    count = 0
    cap = out_i.shape[0]
    for oi in range(n):
        i = order[oi]
        for oj in range(oi + 1, n):
            j = order[oj]
            if lo[j] > hi[i]:
                break
            if not (moves[i] or moves[j]):
                continue
            rs = radius[i] + radius[j]
            apart = False
            for ax in range(3):  # swept boxes on the other axes
                if (min(p0[i, ax], p1[i, ax]) - radius[i] > max(p0[j, ax], p1[j, ax]) + radius[j]
                        or min(p0[j, ax], p1[j, ax]) - radius[j] > max(p0[i, ax], p1[i, ax]) + radius[i]):
                    apart = True
                    break
            if apart:
                continue
            r0x, r0y, r0z = p0[j, 0] - p0[i, 0], p0[j, 1] - p0[i, 1], p0[j, 2] - p0[i, 2]
            r1x, r1y, r1z = p1[j, 0] - p1[i, 0], p1[j, 1] - p1[i, 1], p1[j, 2] - p1[i, 2]
            d0 = math.sqrt(r0x * r0x + r0y * r0y + r0z * r0z)
            drx, dry, drz = r1x - r0x, r1y - r0y, r1z - r0z
            dd = drx * drx + dry * dry + drz * drz
            b = r0x * drx + r0y * dry + r0z * drz
            if half_l[i] > 0.0 and half_l[j] > 0.0:  # two boxes: apart at the start, overlapping later
                tl = 0.0 if dd == 0.0 else min(max(-b / dd, 0.0), 1.0)
                mx, my, mz = r0x + tl * drx, r0y + tl * dry, r0z + tl * drz
                if mx * mx + my * my + mz * mz >= rs * rs:
                    continue  # their bounding circles never meet in the tick
                # i's local east, north and up (ECEF unit vectors at its geodetic position).
                sp, cp = math.sin(math.radians(lat_deg[i])), math.cos(math.radians(lat_deg[i]))
                sl, cl = math.sin(math.radians(lon_deg[i])), math.cos(math.radians(lon_deg[i]))
                ex, ey = -sl, cl
                nx, ny, nz = -sp * cl, -sp * sl, cp
                ux, uy, uz = cp * cl, cp * sl, sp
                ci, si = math.sin(heading_rad[i]), math.cos(heading_rad[i])  # heading from north, clockwise
                # j's heading is from j's north: carried onto i's horizontal (near a pole they differ).
                cj, sj = _forward_in(lat_deg[j], lon_deg[j], heading_rad[j], ex, ey, nx, ny, nz)
                # Sampled at the start, then every half of the narrower box's width of relative
                # travel to the end: at 30 Hz one sample (the end), at low world rates more, so
                # two boxes cannot pass through each other between samples.
                samples = max(1, int(math.ceil(math.sqrt(dd) / min(half_w[i], half_w[j]))))
                t = -1.0
                for k in range(samples + 1):
                    tk = k / samples
                    rx, ry, rz = r0x + tk * drx, r0y + tk * dry, r0z + tk * drz
                    if (abs(rx * ux + ry * uy + rz * uz) < rs
                            and _box_overlap(rx * ex + ry * ey, rx * nx + ry * ny + rz * nz, ci, si, half_l[i],
                                             half_w[i], cj, sj, half_l[j], half_w[j])):
                        t = tk
                        break
                if t < 0.0:
                    continue  # never touching
                if t == 0.0:  # touching already at the start: an ongoing contact, if still at the end
                    if not (ongoing and abs(r1x * ux + r1y * uy + r1z * uz) < rs
                            and _box_overlap(r1x * ex + r1y * ey, r1x * nx + r1y * ny + r1z * nz, ci, si, half_l[i],
                                             half_w[i], cj, sj, half_l[j], half_w[j])):
                        continue
                    t = -1.0
                    mx, my, mz = r1x, r1y, r1z
                else:
                    mx, my, mz = r0x + t * drx, r0y + t * dry, r0z + t * drz
                d = math.sqrt(mx * mx + my * my + mz * mz)
            else:  # spheres, continuously
                if d0 < rs:  # touching already: an ongoing contact, if still at the end
                    d = math.sqrt(r1x * r1x + r1y * r1y + r1z * r1z)
                    if not (ongoing and d < rs):
                        continue
                    t = -1.0
                else:
                    t = 0.0 if dd == 0.0 else min(max(-b / dd, 0.0), 1.0)
                    mx, my, mz = r0x + t * drx, r0y + t * dry, r0z + t * drz
                    d = math.sqrt(mx * mx + my * my + mz * mz)
                    if d >= rs:
                        continue
                    # When they first touch: the smaller root of |r0 + t dr| = rs (t <= the least's).
                    disc = b * b - dd * (d0 * d0 - rs * rs)
                    t = min(max((-b - math.sqrt(max(disc, 0.0))) / dd, 0.0), 1.0)
            if count < cap:
                out_i[count] = min(i, j)
                out_j[count] = max(i, j)
                out_t[count] = t
                out_d[count] = d
            count += 1
    return count if count <= cap else -count


def new_contacts(p0, p1, radius, *, heading_deg=None, half_length_m=None, half_width_m=None, moves=None,
                 lat_deg=None, lon_deg=None, ongoing=False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of entities that came into contact over one tick (the module docstring's rules).

    ``p0``, ``p1``: (n, 3) ECEF positions at the tick's start and end, metres; ``radius``
    (n,): bounding radii, metres. Boxes (ground vehicles): ``half_length_m`` > 0 with
    ``half_width_m`` and ``heading_deg`` (degrees from true north), and the entities'
    ``lat_deg``/``lon_deg`` at the end (their local horizontal); ``half_length_m`` 0 for a
    sphere. ``moves`` (n,) bool: entities that can move (default all; two that cannot are
    never tested). Returns (i, j, t, distance): index pairs with i < j, sorted; the fraction
    of the tick at which they first touched; their reference points' distance (see the
    kernel). ``ongoing``: also the pairs touching at the tick's start and its end, with t -1
    (their distance at the end)."""
    p0 = np.ascontiguousarray(p0, np.float64).reshape(-1, 3)
    p1 = np.ascontiguousarray(p1, np.float64).reshape(-1, 3)
    n = p0.shape[0]
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0)

    def column(values, dtype=np.float64):
        return np.zeros(n, dtype) if values is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(values, dtype), (n,)))

    half_l = column(half_length_m)
    if np.any(half_l > 0) and (lat_deg is None or lon_deg is None):
        raise ValueError("boxes need lat_deg and lon_deg (their local horizontal)")
    moves = np.ones(n, bool) if moves is None else column(moves, bool)
    cap = max(16, INITIAL_CAPACITY_PER_ENTITY * n)
    args = [p0, p1, column(radius), column(lat_deg), column(lon_deg), np.radians(column(heading_deg)), half_l,
            column(half_width_m), moves]
    finite = np.isfinite(p0).all(axis=1) & np.isfinite(p1).all(axis=1) & np.isfinite(args[2])
    if not finite.all():  # an entity with no position is in no contact (it would compare false)
        keep = np.flatnonzero(finite)
        i, j, t, d = new_contacts(p0[keep], p1[keep], args[2][keep], heading_deg=np.degrees(args[5][keep]),
                                  half_length_m=half_l[keep], half_width_m=args[7][keep], moves=moves[keep],
                                  lat_deg=args[3][keep], lon_deg=args[4][keep], ongoing=ongoing)
        return keep[i], keep[j], t, d
    while True:
        out_i, out_j = np.empty(cap, np.int64), np.empty(cap, np.int64)
        out_t, out_d = np.empty(cap), np.empty(cap)
        k = _contacts_kernel(*args, bool(ongoing), out_i, out_j, out_t, out_d)
        if k >= 0:
            break
        cap = -k
    key = np.lexsort((out_j[:k], out_i[:k]))
    return out_i[:k][key], out_j[:k][key], out_t[:k][key], out_d[:k][key]


def overlap_depth(r, lat_deg, lon_deg, heading_i_deg, heading_j_deg, half_l_i, half_w_i, half_l_j, half_w_j,
                  radius_i, radius_j, lat_j_deg=None, lon_j_deg=None) -> np.ndarray:
    """(m,) how deep entity j (at ECEF offset ``r`` (m, 3) from i, metres) overlaps i, by the
    shapes of :func:`new_contacts`: two boxes (both half lengths > 0) by the separating-axis
    test on i's local horizontal (``lat_deg``/``lon_deg``: i's position), the least of the
    four axes' overlaps; otherwise spheres, the sum of the radii less the distance. Positive
    when they overlap. Headings are degrees from true north, each at its own entity's
    position: ``lat_j_deg``/``lon_j_deg`` j's (None: i's; near a pole the two norths differ,
    and j's heading is carried onto i's horizontal through ECEF, as :func:`new_contacts` does)."""
    from terrain.geodesy import enu_basis

    r = np.asarray(r, np.float64).reshape(-1, 3)
    depth = np.asarray(radius_i, np.float64) + np.asarray(radius_j, np.float64) - np.linalg.norm(r, axis=1)
    boxes = (np.asarray(half_l_i) > 0.0) & (np.asarray(half_l_j) > 0.0)
    if not boxes.any():
        return depth
    east, north, _ = enu_basis(lat_deg, lon_deg)
    east, north = np.broadcast_to(east, r.shape), np.broadcast_to(north, r.shape)
    dx, dy = np.einsum("ij,ij->i", r, east), np.einsum("ij,ij->i", r, north)
    hi = np.radians(heading_i_deg)
    ci, si = np.sin(hi), np.cos(hi)  # along each length: (east, north)
    if lat_j_deg is None:
        hj = np.radians(heading_j_deg)
        cj, sj = np.sin(hj), np.cos(hj)
    else:
        f = forward_ecef(lat_j_deg, lon_j_deg, heading_j_deg)
        cj, sj = np.einsum("ij,ij->i", f, east), np.einsum("ij,ij->i", f, north)
        norm = np.hypot(cj, sj)
        cj, sj = cj / norm, sj / norm
    box_depth = np.full(dx.shape, np.inf)
    for ax, ay in ((ci, si), (si, -ci), (cj, sj), (sj, -cj)):
        reach = (half_l_i * np.abs(ci * ax + si * ay) + half_w_i * np.abs(si * ax - ci * ay)
                 + half_l_j * np.abs(cj * ax + sj * ay) + half_w_j * np.abs(sj * ax - cj * ay))
        box_depth = np.minimum(box_depth, reach - np.abs(dx * ax + dy * ay))
    return np.where(boxes, box_depth, depth)
