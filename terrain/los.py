"""Exact intersection of straight ECEF segments with a raster's bilinear surface.

The segment a -> b is straight in ECEF, so Earth curvature is exact: over flat
terrain the chord between two points sags below their height by about
d**2 / (8 R). The surface is the raster's bilinear interpolant, cell by cell.

Method
------
1. **Piecewise-quadratic ray.** The segment is cut into pieces (at most
   ``PIECE_MAX_M`` long, shorter near the polar axis, see
   :func:`piece_length_m`). At each piece's start, middle and end the exact
   geodetic position (Bowring 1976 iteration) gives the raster's fractional
   (row, col) and the height above the ellipsoid; row(u), col(u) and h(u) are
   the quadratics through those three values, u in [0, 1] along the piece.
   The cubic remainder of quadratic interpolation at 0, 1/2, 1 is at most
   (sqrt(3) / 216) L**3 max|f'''|; with the piece lengths used it stays below
   ``MODEL_ERROR_M`` (1 micrometre) horizontally and vertically, from the
   equator to the poles and for both CRSs (derivation at
   :func:`piece_length_m`; measured in tests/test_los.py), except within
   about 1 cm of the polar axis, where longitude itself is singular and the
   horizontal error grows to the 1 mm minimum piece length. This is the only
   approximation: everything below is exact for this model, up to rounding.
2. **Cell walk.** Each piece is split where row(u) or col(u) turns, so both
   are monotone; on a monotone stretch the cells are walked in order
   (Amanatides & Woo 1987, "A fast voxel traversal algorithm for ray
   tracing", with each boundary crossing solved from the quadratic).
3. **Empty-space skipping.** The walk runs on the min/max pyramid
   (:mod:`terrain.pyramid`; maximum mipmaps, Tevs et al. 2008): a block is
   skipped when the ray's lowest point over the block (the quadratic's minimum
   on that stretch) is above the block's maximum; otherwise it descends a
   level, and after each step forward it climbs one.
4. **Exact cell test.** In a cell, ray height minus the bilinear surface along
   the (quadratic) track is a quartic in the local parameter. Its Bernstein
   coefficients bound it (convex hull), so a cell whose coefficients are all
   positive is cleared at once; otherwise the smallest root is isolated by de
   Casteljau subdivision (Lane & Riesenfeld 1981, "Bounds on a polynomial",
   BIT 21) and polished by bisection.

Heights and datum
-----------------
Endpoint heights are taken as metres above the WGS84 ellipsoid to build the
ECEF segment and are compared with the raster's heights as they are (MSL for
SRTM): the geoid undulation is taken as constant along a ray. Returned heights
are in the same datum as the inputs.

Endpoints
---------
:func:`intersect_segments` reports the first point of the segment at or below
the surface, from a itself (a below the ground hits at distance 0).
:func:`line_of_sight` ignores contacts within ``ENDPOINT_TOLERANCE_M`` (1 mm,
straight-line distance) of either endpoint, so a point on the ground can see
and be seen; a touch elsewhere (clearance exactly 0) blocks.

Coverage
--------
Status OUTSIDE when the segment leaves the raster's posts, or enters a cell
with a NaN post, before any hit (a segment that starts outside is OUTSIDE at
once; :func:`line_of_sight` traces such a ray from its other end as well, so
a ray blocked on the raster before it leaves is blocked whichever end is
outside); FILLED when the walk passed over a block holding a filled-void post
(conservative: at whatever pyramid level it cleared that block); else OK.
A raster spanning a full turn of longitude is walked periodically; any other
raster ends at its first and last column (an antimeridian-crossing raster is
one range of columns: longitudes are unwrapped along the ray). A geographic
raster whose first or last row lies on a pole keeps tracks over the pole.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sortie.errors import InvalidArgument
from terrain.geodesy import (WGS84_A_M, WGS84_B_M, WGS84_E2, WGS84_EP2, WGS84_F, ecef_to_geodetic,
                             geodetic_to_ecef)
from terrain.raster import (CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, TWO_PI_A_M, Raster,
                            fractional_index, metres_per_index)
from terrain.validate import check_heights, check_latlon

# Longest piece of the piecewise-quadratic ray (m). Keeps the vertical cubic
# remainder below 2e-7 m: (sqrt(3)/216) * 0.86 / (6.3e6 m)**2 * (1000 m)**3.
PIECE_MAX_M = 1000.0
# Shortest piece (m): reached only within ~1 cm of the polar axis, where
# longitude itself is singular.
PIECE_MIN_M = 1.0e-3
# Bound on the model's horizontal and vertical error (m) the piece lengths keep.
MODEL_ERROR_M = 1.0e-6
# L**3 <= PIECE_RHO_COEF * rho**2 keeps the horizontal remainder below
# MODEL_ERROR_M at distance rho from the polar axis; see piece_length_m.
PIECE_RHO_COEF = MODEL_ERROR_M / 0.08
# line_of_sight ignores contacts closer than this (m) to either endpoint.
ENDPOINT_TOLERANCE_M = 1.0e-3

_WALK_ON, _WALK_HIT, _WALK_OUTSIDE = 0, 1, 2
# Stand-in for a raster without filled posts; read-only like Raster.filled, so
# both compile to one kernel signature.
_NO_FILLED = np.zeros((0, 0), np.uint8)
_NO_FILLED.flags.writeable = False
_OUT_OF_RANGE = -(1 << 40)
_STACK_DEPTH = 64
_ROOT_WIDTH = 2.0 ** -40  # subdivision stops on cell-parameter intervals this narrow


@numba.njit(cache=True, nogil=True)
def _geodetic(x, y, z):
    """Scalar ECEF metres -> (lat deg, lon deg, h m).

    Bowring's iteration on the reduced latitude, three rounds, as
    geodesy.ecef_to_geodetic, but carrying each angle as an unnormalised
    (sin, cos) pair: square roots instead of six trigonometric calls a round
    (4x faster; agreement with geodesy.ecef_to_geodetic is tested).
    """
    p = math.sqrt(x * x + y * y)
    sb, cb = z, (1.0 - WGS84_F) * p
    num, den = z, p
    for _ in range(3):
        norm = math.sqrt(sb * sb + cb * cb)
        sb, cb = sb / norm, cb / norm
        num = z + WGS84_EP2 * WGS84_B_M * sb * sb * sb
        den = p - WGS84_E2 * WGS84_A_M * cb * cb * cb
        sb, cb = (1.0 - WGS84_F) * num, den
    norm = math.sqrt(num * num + den * den)
    sin_lat, cos_lat = num / norm, den / norm
    h = p * cos_lat + z * sin_lat - WGS84_A_M * math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    return math.degrees(math.atan2(num, den)), math.degrees(math.atan2(y, x)), h


@numba.njit(cache=True, nogil=True)
def piece_length_m(px, py, ux, uy, rho_coef):
    """Length (m) of the next piece from ECEF point (px, py, .) along unit direction (ux, uy, .).

    Quadratic interpolation at u = 0, 1/2, 1 errs by at most
    (sqrt(3)/216) L**3 max|f'''| (f''' per metre cubed). Along a straight line
    at distance rho from the polar axis, longitude is atan(s / rho) with
    |lambda'''| <= 2 / rho**3 (a position error of rho * lambda); latitude and
    the Web Mercator row add terms of the same 1/rho**2 form. Their sum, with
    margin, is below 0.08 L**3 / rho**2 metres, so L**3 <= rho_coef * rho**2
    with rho_coef = MODEL_ERROR_M / 0.08 meets MODEL_ERROR_M. rho is taken as
    its minimum over the candidate piece, which only shortens it.
    """
    rho = math.hypot(px, py)
    length = min(PIECE_MAX_M, (rho_coef * rho * rho) ** (1.0 / 3.0))
    uu = ux * ux + uy * uy
    if uu > 0.0:
        t = min(max(-(px * ux + py * uy) / uu, 0.0), length)
        rho_min = math.hypot(px + t * ux, py + t * uy)
        length = min(length, (rho_coef * rho_min * rho_min) ** (1.0 / 3.0))
    return max(length, PIECE_MIN_M)


@numba.njit(cache=True, nogil=True)
def _quad(p0, p1, p2, u):
    return p0 + u * (p1 + u * p2)


@numba.njit(cache=True, nogil=True)
def _cross(p0, p1, p2, target, u_from, u_to):
    """First u in [u_from, u_to] with p(u) == target for p monotone there, else inf."""
    f0 = _quad(p0, p1, p2, u_from) - target
    f1 = _quad(p0, p1, p2, u_to) - target
    if f0 == 0.0:
        return u_from
    if (f0 > 0.0) == (f1 > 0.0) and f1 != 0.0:
        return math.inf
    c = p0 - target
    if p2 == 0.0:
        u = -c / p1
    else:
        # Stable quadratic roots (Press et al., Numerical Recipes, 5.6); the one
        # nearer the interval is the crossing, the other lies past a turn.
        q = -0.5 * (p1 + math.copysign(math.sqrt(max(p1 * p1 - 4.0 * p2 * c, 0.0)), p1))
        u = q / p2
        if q != 0.0:
            u2 = c / q
            mid = 0.5 * (u_from + u_to)
            if abs(u2 - mid) < abs(u - mid):
                u = u2
    return min(max(u, u_from), u_to)


@numba.njit(cache=True, nogil=True)
def _cell_of(v, step, n_cells):
    """Cell holding fractional index v when moving by sign ``step``; on a boundary
    the cell ahead. A non-moving coordinate on the far edge belongs to the last cell."""
    if not (abs(v) < 1.0e12):
        return _OUT_OF_RANGE
    k = int(math.ceil(v)) - 1 if step < 0 else int(math.floor(v))
    if step == 0 and k == n_cells and v == n_cells:
        k = n_cells - 1
    return k


@numba.njit(cache=True, nogil=True)
def _min_quad(p0, p1, p2, u0, u1):
    """Minimum of p(u) on [u0, u1]."""
    m = min(_quad(p0, p1, p2, u0), _quad(p0, p1, p2, u1))
    if p2 > 0.0:
        v = -p1 / (2.0 * p2)
        if u0 < v < u1:
            m = min(m, _quad(p0, p1, p2, v))
    return m


@numba.njit(cache=True, nogil=True)
def _first_root(g0, g1, g2, g3, g4, stack):
    """Smallest v in [0, 1] with g(v) <= 0 for the quartic sum(g_k v**k), or -1.

    Bernstein coefficients bound g on an interval (convex hull property);
    intervals are subdivided left first, so the first root found is the
    smallest. One sign change in the coefficients means one root (variation
    diminishing), which bisection polishes to rounding.
    """
    b0 = g0
    b1 = g0 + 0.25 * g1
    b2 = g0 + 0.5 * g1 + g2 / 6.0
    b3 = g0 + 0.75 * g1 + 0.5 * g2 + 0.25 * g3
    b4 = g0 + g1 + g2 + g3 + g4
    if min(b0, b1, b2, b3, b4) > 0.0:
        return -1.0
    if b0 <= 0.0:
        return 0.0
    stack[0, 0], stack[0, 1] = 0.0, 1.0
    stack[0, 2], stack[0, 3], stack[0, 4], stack[0, 5], stack[0, 6] = b0, b1, b2, b3, b4
    n = 1
    while n > 0:
        n -= 1
        lo, hi = stack[n, 0], stack[n, 1]
        b0, b1, b2, b3, b4 = stack[n, 2], stack[n, 3], stack[n, 4], stack[n, 5], stack[n, 6]
        if min(b0, b1, b2, b3, b4) > 0.0:
            continue
        if b0 <= 0.0:
            return lo
        changes = (int((b0 > 0.0) != (b1 > 0.0)) + int((b1 > 0.0) != (b2 > 0.0))
                   + int((b2 > 0.0) != (b3 > 0.0)) + int((b3 > 0.0) != (b4 > 0.0)))
        if changes == 1:
            for _ in range(64):
                mid = 0.5 * (lo + hi)
                if mid <= lo or mid >= hi:
                    break
                if g0 + mid * (g1 + mid * (g2 + mid * (g3 + mid * g4))) > 0.0:
                    lo = mid
                else:
                    hi = mid
            return hi
        if hi - lo < _ROOT_WIDTH or n + 2 > stack.shape[0]:
            return lo  # a touch: the hull dips to <= 0 on an interval of ~1e-12
        # de Casteljau at the midpoint.
        a0, a1, a2, a3 = 0.5 * (b0 + b1), 0.5 * (b1 + b2), 0.5 * (b2 + b3), 0.5 * (b3 + b4)
        c0, c1, c2 = 0.5 * (a0 + a1), 0.5 * (a1 + a2), 0.5 * (a2 + a3)
        d0, d1 = 0.5 * (c0 + c1), 0.5 * (c1 + c2)
        e0 = 0.5 * (d0 + d1)
        mid = 0.5 * (lo + hi)
        stack[n, 0], stack[n, 1] = mid, hi
        stack[n, 2], stack[n, 3], stack[n, 4], stack[n, 5], stack[n, 6] = e0, d1, c2, a3, b4
        stack[n + 1, 0], stack[n + 1, 1] = lo, mid
        stack[n + 1, 2], stack[n + 1, 3], stack[n + 1, 4], stack[n + 1, 5], stack[n + 1, 6] = b0, a0, c0, d0, e0
        n += 2
    return -1.0


@numba.njit(cache=True, nogil=True)
def _cell_root(h00, h01, h10, h11, poly, u, w, i, j, stack):
    """First v in [0, 1] where the ray meets cell (i, j)'s bilinear patch on
    u + v * w, or -1. j is the unwrapped column of the track."""
    r0, r1, r2, c0, c1, c2, p0, p1, p2 = poly[0], poly[1], poly[2], poly[3], poly[4], poly[5], \
        poly[6], poly[7], poly[8]
    x0 = _quad(c0, c1, c2, u) - j
    x1 = (c1 + 2.0 * c2 * u) * w
    x2 = c2 * w * w
    y0 = _quad(r0, r1, r2, u) - i
    y1 = (r1 + 2.0 * r2 * u) * w
    y2 = r2 * w * w
    t0 = _quad(p0, p1, p2, u)
    t1 = (p1 + 2.0 * p2 * u) * w
    t2 = p2 * w * w
    a = h01 - h00
    b = h10 - h00
    d = h00 - h01 - h10 + h11
    g0 = t0 - (h00 + a * x0 + b * y0 + d * x0 * y0)
    g1 = t1 - (a * x1 + b * y1 + d * (x0 * y1 + x1 * y0))
    g2 = t2 - (a * x2 + b * y2 + d * (x0 * y2 + x1 * y1 + x2 * y0))
    g3 = -d * (x1 * y2 + x2 * y1)
    g4 = -d * x2 * y2
    return _first_root(g0, g1, g2, g3, g4, stack)


@numba.njit(cache=True, nogil=True)
def _walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, ua, ub, stack, out):
    """Walk the cells of one monotone stretch [ua, ub] of a piece.

    periodic: the columns wrap (the raster spans a full turn). poles: bit 0
    set when row 0 lies on the south pole, bit 1 when the last row lies on the
    north pole; there no latitude lies beyond the raster, so a track that the
    quadratic carries a hair past the pole row stays in the polar cells.

    Returns _WALK_ON (no hit, continue), _WALK_HIT (out[0] = u of the hit,
    out[1], out[2] = surface slope d h / d col, d h / d row there) or
    _WALK_OUTSIDE. out[3] is set to 1 when a filled-void cell was used.
    """
    ny, nx = heights.shape
    ncy, ncx = ny - 1, nx - 1
    r0, r1, r2, c0, c1, c2, p0, p1, p2 = poly[0], poly[1], poly[2], poly[3], poly[4], poly[5], \
        poly[6], poly[7], poly[8]
    dr = _quad(r0, r1, r2, ub) - _quad(r0, r1, r2, ua)
    dc = _quad(c0, c1, c2, ub) - _quad(c0, c1, c2, ua)
    sr = 1 if dr > 0.0 else (-1 if dr < 0.0 else 0)
    sc = 1 if dc > 0.0 else (-1 if dc < 0.0 else 0)
    i = _cell_of(_quad(r0, r1, r2, ua), sr, ncy)
    j = _cell_of(_quad(c0, c1, c2, ua), sc, ncx)
    has_fill = pfill.shape[0] > 0
    top = pshape.shape[0] - 1
    k = min(int(out[4]) + 1, top)
    u = ua
    while True:
        if i < 0 and poles & 1 and i != _OUT_OF_RANGE:
            i, sr = 0, max(sr, 0)  # no crossing out through a pole
        if i >= ncy and poles & 2:
            i, sr = ncy - 1, min(sr, 0)
        if i < 0 or i >= ncy:
            return _WALK_OUTSIDE
        if periodic:
            if j == _OUT_OF_RANGE:
                return _WALK_OUTSIDE
            jw = j % ncx
        else:
            if j < 0 or j >= ncx:
                return _WALK_OUTSIDE
            jw = j
        bi, bj = i >> k, jw >> k
        rlo, rhi = bi << k, min((bi + 1) << k, ncy)
        clo, chi = (bj << k) + (j - jw), min((bj + 1) << k, ncx) + (j - jw)
        u_r = math.inf if sr == 0 else _cross(r0, r1, r2, float(rhi if sr > 0 else rlo), u, ub)
        u_c = math.inf if sc == 0 else _cross(c0, c1, c2, float(chi if sc > 0 else clo), u, ub)
        u_e = min(u_r, u_c, ub)
        if k > 0:
            block = poff[k] + bi * pshape[k, 1] + bj
            if not (_min_quad(p0, p1, p2, u, u_e) > pmax[block]):
                k -= 1
                continue
            if has_fill and pfill[block]:
                out[3] = 1.0
        else:
            h00, h01 = np.float64(heights[i, jw]), np.float64(heights[i, jw + 1])
            h10, h11 = np.float64(heights[i + 1, jw]), np.float64(heights[i + 1, jw + 1])
            if (h00 + h01 + h10 + h11) != (h00 + h01 + h10 + h11):
                return _WALK_OUTSIDE
            if filled.shape[0] > 0 and (filled[i, jw] | filled[i, jw + 1] | filled[i + 1, jw]
                                        | filled[i + 1, jw + 1]):
                out[3] = 1.0
            w = u_e - u
            v = _cell_root(h00, h01, h10, h11, poly, u, w, i, j, stack)
            if v >= 0.0:
                uh = u + v * w
                fx = _quad(c0, c1, c2, uh) - j
                fy = _quad(r0, r1, r2, uh) - i
                out[0] = uh
                out[1] = (h01 - h00) + (h00 - h01 - h10 + h11) * fy
                out[2] = (h10 - h00) + (h00 - h01 - h10 + h11) * fx
                return _WALK_HIT
        if u_e >= ub:
            out[4] = k
            return _WALK_ON
        if u_r <= u_e:
            i = rhi if sr > 0 else rlo - 1
        else:
            i = min(max(_cell_of(_quad(r0, r1, r2, u_e), sr, ncy), rlo), rhi - 1)
        if u_c <= u_e:
            j = chi if sc > 0 else clo - 1
        else:
            j = min(max(_cell_of(_quad(c0, c1, c2, u_e), sc, ncx), clo), chi - 1)
        u = u_e
        k = min(k + 1, top)


@numba.njit(cache=True, nogil=True)
def _fit(f0, fm, f1, poly, at):
    """Quadratic through (0, f0), (1/2, fm), (1, f1) into poly[at:at + 3]."""
    poly[at] = f0
    poly[at + 1] = 4.0 * fm - 3.0 * f0 - f1
    poly[at + 2] = 2.0 * f0 + 2.0 * f1 - 4.0 * fm


@numba.njit(cache=True, nogil=True)
def _unwrap(c, ref, turn_cols):
    return c + turn_cols * math.floor((ref - c) / turn_cols + 0.5)


@numba.njit(cache=True, nogil=True)
def _trace_kernel(heights, filled, pmax, pfill, poff, pshape, crs, x0, y0, dx, dy, periodic, poles, turn_cols,
                  a_ecef, b_ecef, s_lo, s_hi, rho_coef, out_s, out_dcol, out_drow, out_status):
    """First contact parameter s in [s_lo, s_hi] (NaN: none) of each segment a + s (b - a).

    a_ecef, b_ecef: (n, 3) float64 ECEF metres; s_lo, s_hi: (n,) float64.
    Writes out_s (n,) float64, out_dcol/out_drow (n,) float64 surface slope at
    the hit in metres per index step, out_status (n,) uint8 STATUS_*.
    """
    poly = np.zeros(9)
    cuts = np.zeros(4)
    stack = np.zeros((_STACK_DEPTH, 7))
    out = np.zeros(5)
    for n in range(a_ecef.shape[0]):
        ax, ay, az = a_ecef[n, 0], a_ecef[n, 1], a_ecef[n, 2]
        vx, vy, vz = b_ecef[n, 0] - ax, b_ecef[n, 1] - ay, b_ecef[n, 2] - az
        length = math.sqrt(vx * vx + vy * vy + vz * vz)
        ux, uy = (vx / length, vy / length) if length > 0.0 else (0.0, 0.0)
        out_s[n] = math.nan
        out[3] = 0.0
        out[4] = pshape.shape[0] - 1
        sa = s_lo[n]
        lat, lon, ha = _geodetic(ax + sa * vx, ay + sa * vy, az + sa * vz)
        ra, ca = fractional_index(lat, lon, crs, x0, y0, dx, dy)
        code = _WALK_ON
        while code == _WALK_ON:
            sb = s_hi[n]
            if length > 0.0:
                step = piece_length_m(ax + sa * vx, ay + sa * vy, ux, uy, rho_coef) / length
                sb = min(sa + step, sb)
            sm = 0.5 * (sa + sb)
            lat, lon, hm = _geodetic(ax + sm * vx, ay + sm * vy, az + sm * vz)
            rm, cm = fractional_index(lat, lon, crs, x0, y0, dx, dy)
            lat, lon, hb = _geodetic(ax + sb * vx, ay + sb * vy, az + sb * vz)
            rb, cb = fractional_index(lat, lon, crs, x0, y0, dx, dy)
            cm = _unwrap(cm, ca, turn_cols)
            cb = _unwrap(cb, cm, turn_cols)
            _fit(ra, rm, rb, poly, 0)
            _fit(ca, cm, cb, poly, 3)
            _fit(ha, hm, hb, poly, 6)
            # Split where row or column turns, so each stretch is monotone in both.
            n_cuts = 0
            for at in (0, 3):
                if poly[at + 2] != 0.0:
                    turn = -poly[at + 1] / (2.0 * poly[at + 2])
                    if 0.0 < turn < 1.0:
                        cuts[n_cuts] = turn
                        n_cuts += 1
            if n_cuts == 2 and cuts[1] < cuts[0]:
                cuts[0], cuts[1] = cuts[1], cuts[0]
            cuts[n_cuts] = 1.0
            u0 = 0.0
            for c in range(n_cuts + 1):
                code = _walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, u0, cuts[c],
                             stack, out)
                if code != _WALK_ON:
                    break
                u0 = cuts[c]
            if code == _WALK_HIT:
                out_s[n] = sa + out[0] * (sb - sa)
                out_dcol[n], out_drow[n] = out[1], out[2]
            if code == _WALK_ON and sb >= s_hi[n]:
                break
            sa, ra, ca, ha = sb, rb, cb, hb
        if code == _WALK_OUTSIDE:
            out_status[n] = STATUS_OUTSIDE
        else:
            out_status[n] = STATUS_FILLED if out[3] > 0.0 else STATUS_OK


def check_segments(a_lat, a_lon, a_h, b_lat, b_lon, b_h):
    """Validated segment end arrays, each (n,) float64; raises InvalidArgument naming the field."""
    a_lat, a_lon = check_latlon(a_lat, a_lon, prefix="a_")
    b_lat, b_lon = check_latlon(b_lat, b_lon, prefix="b_")
    if b_lat.size != a_lat.size:
        raise InvalidArgument("b_lat", f"must have as many values as a_lat ({a_lat.size}), got {b_lat.size}")
    a_h = check_heights("a_h", a_h, a_lat.size)
    b_h = check_heights("b_h", b_h, a_lat.size)
    return a_lat, a_lon, a_h, b_lat, b_lon, b_h


def trace_segments(raster: Raster, a_ecef: np.ndarray, b_ecef: np.ndarray, s_lo: np.ndarray, s_hi: np.ndarray):
    """First contact of each ECEF segment a + s (b - a), s in [s_lo, s_hi], with the surface.

    a_ecef, b_ecef: (n, 3) float64 ECEF metres (heights in the raster's datum,
    see the module docstring); s_lo, s_hi: (n,) float64, 0 <= s_lo <= s_hi <= 1.
    Returns s (n,) float64 (NaN: no contact), slope_col and slope_row (n,)
    float64 d h / d index of the hit cell at the hit (m per post step), status
    (n,) uint8 STATUS_*.
    """
    a_ecef = np.ascontiguousarray(a_ecef, dtype=np.float64)
    b_ecef = np.ascontiguousarray(b_ecef, dtype=np.float64)
    if a_ecef.ndim != 2 or a_ecef.shape[1] != 3 or b_ecef.shape != a_ecef.shape:
        raise ValueError(f"a_ecef, b_ecef must both be (n, 3), got {a_ecef.shape} and {b_ecef.shape}")
    n = a_ecef.shape[0]
    s_lo = np.ascontiguousarray(np.broadcast_to(s_lo, (n,)), dtype=np.float64)
    s_hi = np.ascontiguousarray(np.broadcast_to(s_hi, (n,)), dtype=np.float64)
    g = raster.georef
    turn = 360.0 if g.crs == CRS_GEOGRAPHIC else TWO_PI_A_M
    nx = raster.shape[1]
    periodic = abs((nx - 1) * g.dx - turn) <= 1.0e-9 * turn
    poles = 0
    if g.crs == CRS_GEOGRAPHIC:
        lat_top = g.y0 + (raster.shape[0] - 1) * g.dy
        poles = int(abs(g.y0 + 90.0) <= 1.0e-9) | 2 * int(abs(lat_top - 90.0) <= 1.0e-9)
    pyr = raster.pyramid
    s = np.zeros(n)
    dcol = np.full(n, np.nan)
    drow = np.full(n, np.nan)
    status = np.zeros(n, np.uint8)
    filled = raster.filled if raster.filled is not None else _NO_FILLED
    _trace_kernel(raster.heights, filled, pyr.max_flat, pyr.filled_flat, pyr.offsets, pyr.shapes,
                  g.crs, g.x0, g.y0, g.dx, g.dy, periodic, poles, turn / g.dx, a_ecef, b_ecef, s_lo, s_hi,
                  PIECE_RHO_COEF, s, dcol, drow, status)
    return s, dcol, drow, status


def intersect_segments(raster: Raster, a_lat, a_lon, a_h, b_lat, b_lon, b_h):
    """First intersection of each straight (ECEF) segment a -> b with the bilinear surface.

    a_lat, a_lon, b_lat, b_lon: (n,) float64 degrees, (lat, lon) order;
    a_h, b_h: (n,) float64 metres in the raster's vertical datum.
    Returns, in the field order of terrain.terrain.SegmentResult:
    hit (n,) bool; distance_m (n,) float64 straight-line metres from a to the
    hit; lat_deg, lon_deg, height_m (n,) float64 the hit point (on the
    segment; its height is the surface's to within MODEL_ERROR_M times the
    local slope); normal_enu (n, 3) float64 unit (east, north, up) normal of
    the hit cell's patch; status (n,) uint8 STATUS_*. Non-hits are NaN.
    """
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = check_segments(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    a = geodetic_to_ecef(a_lat, a_lon, a_h)
    b = geodetic_to_ecef(b_lat, b_lon, b_h)
    n = a_lat.size
    s, dcol, drow, status = trace_segments(raster, a, b, np.zeros(n), np.ones(n))
    hit = ~np.isnan(s)
    p = a + s[:, None] * (b - a)
    lat, lon, h = ecef_to_geodetic(p)
    distance = s * np.linalg.norm(b - a, axis=1)
    g = raster.georef
    m_col, m_row = metres_per_index(g.crs, g.dx, g.dy, np.where(hit, lat, 0.0))
    normal = np.stack([-dcol / m_col, -drow / m_row, np.ones(n)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return hit, distance, lat, lon, h, normal, status


def line_of_sight(raster: Raster, a_lat, a_lon, a_h, b_lat, b_lon, b_h):
    """Whether the straight (ECEF) segment a -> b clears the bilinear surface.

    Arguments as :func:`intersect_segments`. Contacts within
    ENDPOINT_TOLERANCE_M of either endpoint are ignored. Returns, in the
    field order of terrain.terrain.LosResult: visible (n,) bool (False when
    OUTSIDE) and status (n,) uint8 STATUS_*. A ray that leaves the raster is
    blocked (status OK or FILLED, not OUTSIDE) when it meets the surface on a
    covered part that either endpoint reaches before leaving. Symmetric by
    construction: each pair is traced from the endpoint whose ECEF (x, y, z)
    sorts first, and a ray that leaves from the other one as well.
    """
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = check_segments(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    a = geodetic_to_ecef(a_lat, a_lon, a_h)
    b = geodetic_to_ecef(b_lat, b_lon, b_h)
    d = b - a
    first_diff = np.argmax(d != 0.0, axis=1)
    swap = d[np.arange(d.shape[0]), first_diff] < 0.0
    a[swap], b[swap] = b[swap], a[swap]
    length = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore"):
        s_lo = np.minimum(ENDPOINT_TOLERANCE_M / length, 0.5)
    s, _, _, status = trace_segments(raster, a, b, s_lo, 1.0 - s_lo)
    # A ray that leaves the raster may be blocked on its covered part behind the endpoint it
    # was traced from (that endpoint outside, or a hole between): trace those from the other
    # end too. A contact found before leaving is a definite answer, as intersect_segments
    # reports it; the rest stay OUTSIDE for the next source.
    out = np.flatnonzero(status == STATUS_OUTSIDE)
    if out.size:
        s_back, _, _, status_back = trace_segments(raster, b[out], a[out], s_lo[out], 1.0 - s_lo[out])
        blocked = ~np.isnan(s_back)
        s[out[blocked]] = 1.0 - s_back[blocked]
        status[out[blocked]] = status_back[blocked]
    # A segment no longer than twice the tolerance has no interior left to block it.
    visible = (np.isnan(s) | (length <= 2.0 * ENDPOINT_TOLERANCE_M)) & (status != STATUS_OUTSIDE)
    return visible, status


def dense_los_reference(raster: Raster, a_lat, a_lon, a_h, b_lat, b_lon, b_h, samples_per_post: int = 16):
    """Brute-force line of sight by dense sampling, independent of the exact walk.

    Samples the straight ECEF segment every (smaller post spacing) /
    samples_per_post metres (endpoints excluded), converts each sample to
    geodetic and compares its height with Raster.heights_into. Arguments as
    :func:`intersect_segments`. Returns visible (n,) bool (every sample clears
    the surface and is covered) and min_clearance_m (n,) float64, the smallest
    sampled ray-minus-terrain height (NaN where a sample is outside coverage,
    +inf for segments too short to hold a sample). Sampling steps over dips
    narrower than the step: near a ridge it can miss an obstruction up to about
    slope * step / 2 deep (centimetres at 16 samples per 90 m post).
    """
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = check_segments(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    a = geodetic_to_ecef(a_lat, a_lon, a_h)
    b = geodetic_to_ecef(b_lat, b_lon, b_h)
    if not samples_per_post >= 1:
        raise ValueError(f"samples_per_post must be >= 1, got {samples_per_post!r}")
    step_m = min(raster.post_spacing_m) / samples_per_post
    n_steps = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step_m).astype(np.int64), 1)
    clearance = np.full(a_lat.size, np.inf)
    rays_per_chunk = max(1, (1 << 20) // int(n_steps.max(initial=1)))  # ~1M samples in memory at once
    for start in range(0, a_lat.size, rays_per_chunk):
        counts = n_steps[start:start + rays_per_chunk] - 1
        ray = np.repeat(np.arange(start, start + counts.size), counts)
        k = np.arange(ray.size) - np.repeat(np.cumsum(counts) - counts, counts) + 1
        s = k / n_steps[ray]
        lat, lon, h = ecef_to_geodetic(a[ray] + s[:, None] * (b[ray] - a[ray]))
        terrain_h = np.full(ray.size, np.nan)
        status = np.full(ray.size, STATUS_OUTSIDE, dtype=np.uint8)
        raster.heights_into(lat, lon, terrain_h, status)
        with np.errstate(invalid="ignore"):
            np.minimum.at(clearance, ray, h - terrain_h)  # NaN (outside) propagates
    return clearance > 0.0, clearance
