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
and be seen; a touch elsewhere (clearance exactly 0) blocks. A segment no
longer than twice that has no interior left: it is a point, visible unless it
lies more than ENDPOINT_TOLERANCE_M under the surface (as a longer segment from
a buried end is blocked).

Coverage
--------
Status OUTSIDE when the segment leaves the raster's posts, or enters a cell
with a NaN post, before any hit (a segment that starts outside is OUTSIDE at
once; :func:`line_of_sight` traces such a ray from its other end as well, so
a ray blocked on the raster before it leaves is blocked whichever end is
outside); FILLED when the walk passed over a block holding a filled-void post
(conservative: at whatever pyramid level it cleared that block); else OK.
A segment whose track runs along a line of posts (a vertical one, one in a
meridian plane, one on the equator over a row of posts) reads that line's
posts alone, as heights do at its points: along a hole's rim it meets the
raster, with the slope its points have there, and a filled post beside the
line does not make it FILLED.
A raster spanning a full turn of longitude or more (a whole number of cells a
turn) is walked periodically over its first turn's cells; any other
raster ends at its first and last column (an antimeridian-crossing raster is
one range of columns: longitudes are unwrapped along the ray). A geographic
raster whose first or last row lies on a pole keeps tracks over the pole.

Stacks of sources
-----------------
:func:`stack_trace` and :func:`stack_line_of_sight` meet the surface of an
ordered stack of rasters (a terrain.terrain.Terrain's sources): at each point
that of the first raster covering it, or, where that raster has only a filled
void, of the first later raster measuring the ground there. Each raster's covered intervals along a
segment (:func:`segment_coverage`) come from the same pieces, track and block
walk as the exact trace (the walk's stepping is shared: :func:`_walk_start`,
:func:`_enter`, :func:`_block`, :func:`_next_cell`); the stretches left to
each raster are traced in order by :func:`trace_segments` until the first
contact. Where a segment passes onto a raster whose surface is above it, the
contact is at that raster's edge (the step between the surfaces is a wall); a
stretch no raster covers (longer than STACK_GAP_TOLERANCE_M) before any
contact makes the segment OUTSIDE.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sortie.errors import InvalidArgument
from terrain.geodesy import (WGS84_A_M, WGS84_B_M, WGS84_E2, WGS84_EP2, WGS84_F, ecef_to_geodetic,
                             geodetic_to_ecef)
from terrain.raster import (CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, TWO_PI_A_M, Raster,
                            _gradient_value, fractional_index, metres_per_index)
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
    Deep inside (within about e2 * a = 43 km of the Earth's centre, which a
    segment end may be: lat 0, h = -a) the normal is kept pointing outwards
    (cos(lat) >= 0), as geodesy.ecef_to_geodetic keeps it, and on the
    equatorial plane latitude 0 is returned at once: the equator's normal
    passes through every point there, and the iteration would divide by zero
    at the centre itself.
    """
    p = math.sqrt(x * x + y * y)
    if z == 0.0:
        return 0.0, math.degrees(math.atan2(y, x)), p - WGS84_A_M
    sb, cb = z, (1.0 - WGS84_F) * p
    num, den = z, p
    for _ in range(3):
        norm = math.sqrt(sb * sb + cb * cb)
        sb, cb = sb / norm, cb / norm
        num = z + WGS84_EP2 * WGS84_B_M * sb * sb * sb
        den = p - WGS84_E2 * WGS84_A_M * cb * cb * cb
        if den < 0.0:  # nearer the axis than the centre of curvature: the same normal, outwards
            num, den = -num, -den
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


# The block walk over the min/max pyramid, shared by _walk (first contact) and _cover_walk (the
# covered stretches, for stack_trace): each step takes the block of level k holding cell (i, j)
# (_enter, _block), finds where the track leaves it, and either descends a level into the block or
# moves on to the cell the track enters next (_next_cell) and climbs one level. The track's pieces
# are shared likewise by _trace_kernel and _cover_kernel (_segment, _track_at, _next_piece,
# _fit_piece).
#
# Helpers marked inline="always" are inlined at numba IR level, so the hot kernels compile as if
# the helpers were written out in them; none takes an array, as an array argument of an inlined
# helper costs a reference count update per call. Those that take arrays (_segment, _fit_piece)
# are plain njit functions, which LLVM inlines.


@numba.njit(cache=True, nogil=True, inline="always")
def _walk_start(r0, r1, r2, c0, c1, c2, ua, ub, ncy, ncx):
    """(sr, sc, i, j) of the monotone stretch [ua, ub] of the track (row r0 + r1 u + r2 u**2, column
    c0 + c1 u + c2 u**2): the signs of its row and column steps and its first cell (the cell ahead on a
    boundary; _OUT_OF_RANGE for a coordinate that is not finite)."""
    dr = _quad(r0, r1, r2, ub) - _quad(r0, r1, r2, ua)
    dc = _quad(c0, c1, c2, ub) - _quad(c0, c1, c2, ua)
    sr = 1 if dr > 0.0 else (-1 if dr < 0.0 else 0)
    sc = 1 if dc > 0.0 else (-1 if dc < 0.0 else 0)
    return sr, sc, _cell_of(_quad(r0, r1, r2, ua), sr, ncy), _cell_of(_quad(c0, c1, c2, ua), sc, ncx)


@numba.njit(cache=True, nogil=True, inline="always")
def _enter(i, j, sr, periodic, poles, ncy, ncx):
    """(on, i, sr, jw) on entering cell (i, j): on is False when the cell is off the raster; a row
    past a pole row (poles as for :func:`_walk`) is held in the polar cells (no crossing out through
    a pole); jw is the column wrapped into the raster (periodic) or j itself."""
    if i < 0 and poles & 1 and i != _OUT_OF_RANGE:
        i, sr = 0, max(sr, 0)
    if i >= ncy and poles & 2:
        i, sr = ncy - 1, min(sr, 0)
    if i < 0 or i >= ncy:
        return False, i, sr, j
    if periodic:
        if j == _OUT_OF_RANGE:
            return False, i, sr, j
        return True, i, sr, j % ncx
    if j < 0 or j >= ncx:
        return False, i, sr, j
    return True, i, sr, j


@numba.njit(cache=True, nogil=True, inline="always")
def _block(r0, r1, r2, c0, c1, c2, i, j, jw, k, sr, sc, u, ub, ncy, ncx):
    """The level-k block holding cell (i, j) (jw: j wrapped), and where the track leaves it.

    Returns (bi, bj, rlo, rhi, clo, chi, u_r, u_c, u_e): the block's index in its level, the rows
    [rlo, rhi) and (unwrapped, as j) columns [clo, chi) it spans, the parameters in [u, ub] where the
    track crosses its last row or column boundary ahead (inf: none, or not moving that way) and
    u_e = min(u_r, u_c, ub), where the step ends.
    """
    bi, bj = i >> k, jw >> k
    rlo, rhi = bi << k, min((bi + 1) << k, ncy)
    clo, chi = (bj << k) + (j - jw), min((bj + 1) << k, ncx) + (j - jw)
    u_r = math.inf if sr == 0 else _cross(r0, r1, r2, float(rhi if sr > 0 else rlo), u, ub)
    u_c = math.inf if sc == 0 else _cross(c0, c1, c2, float(chi if sc > 0 else clo), u, ub)
    return bi, bj, rlo, rhi, clo, chi, u_r, u_c, min(u_r, u_c, ub)


@numba.njit(cache=True, nogil=True, inline="always")
def _next_cell(r0, r1, r2, c0, c1, c2, sr, sc, rlo, rhi, clo, chi, u_r, u_c, u_e, ncy, ncx):
    """(i, j): the cell the track enters at u_e on leaving the block (values of :func:`_block`):
    past the row or column boundary it crosses there, else (rounding) the cell of its position,
    kept within the block."""
    if u_r <= u_e:
        i = rhi if sr > 0 else rlo - 1
    else:
        i = min(max(_cell_of(_quad(r0, r1, r2, u_e), sr, ncy), rlo), rhi - 1)
    if u_c <= u_e:
        j = chi if sc > 0 else clo - 1
    else:
        j = min(max(_cell_of(_quad(c0, c1, c2, u_e), sc, ncx), clo), chi - 1)
    return i, j


@numba.njit(cache=True, nogil=True, inline="always")
def _track_posts(r0, r1, r2, c0, c1, c2, i, j, jw):
    """(i0, i1, j0, j1): the rows and (wrapped) columns of the posts of cell (i, j) (jw: j wrapped)
    that have weight somewhere on a stretch of the track (row r0 + r1 u + r2 u**2, column
    c0 + c1 u + c2 u**2, unwrapped as j). A track along a post line (its row or column a constant
    on it, as a vertical segment's both are and a segment in a meridian plane its column, snapped
    to the line by terrain.raster.fractional_index) reads that line's posts alone, a post of zero
    weight replaced by its neighbour on the line, as terrain.raster._weighted_corners does for a
    point: such a track is covered where the heights of its points are (a hole beside the line
    takes nothing from it); any other track reads the cell's four posts."""
    on_r = r1 == 0.0 and r2 == 0.0
    on_c = c1 == 0.0 and c2 == 0.0
    return ((i + 1 if on_r and r0 == i + 1 else i), (i if on_r and r0 == i else i + 1),
            (jw + 1 if on_c and c0 == j + 1 else jw), (jw if on_c and c0 == j else jw + 1))


@numba.njit(cache=True, nogil=True)
def _walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, ua, ub, stack, out):
    """Walk the cells of one monotone stretch [ua, ub] of a piece.

    periodic: the cells per turn when the columns wrap (the raster spans a full turn or more: only
    the first turn's cells are read), else 0. poles: bit 0
    set when row 0 lies on the south pole, bit 1 when the last row lies on the
    north pole; there no latitude lies beyond the raster, so a track that the
    quadratic carries a hair past the pole row stays in the polar cells.

    Returns _WALK_ON (no hit, continue), _WALK_HIT (out[0] = u of the hit,
    out[1], out[2] = surface slope d h / d col, d h / d row there, or, with out[5] set to 1, the
    hit's fractional row and column in the raster, on a post line beside a hole: its slope is
    :func:`_rim_slopes`') or _WALK_OUTSIDE. out[3] is set to 1 when a filled-void cell was used.
    """
    ny, nx = heights.shape
    ncy, ncx = ny - 1, (periodic if periodic else nx - 1)
    r0, r1, r2, c0, c1, c2, p0, p1, p2 = poly[0], poly[1], poly[2], poly[3], poly[4], poly[5], \
        poly[6], poly[7], poly[8]
    sr, sc, i, j = _walk_start(r0, r1, r2, c0, c1, c2, ua, ub, ncy, ncx)
    has_fill = pfill.shape[0] > 0
    top = pshape.shape[0] - 1
    k = min(int(out[4]) + 1, top)
    u = ua
    while True:
        on, i, sr, jw = _enter(i, j, sr, periodic, poles, ncy, ncx)
        if not on:
            return _WALK_OUTSIDE
        bi, bj, rlo, rhi, clo, chi, u_r, u_c, u_e = _block(r0, r1, r2, c0, c1, c2, i, j, jw, k, sr, sc, u, ub,
                                                           ncy, ncx)
        if k > 0:
            block = poff[k] + bi * pshape[k, 1] + bj
            if not (_min_quad(p0, p1, p2, u, u_e) > pmax[block]):
                k -= 1
                continue
            if has_fill and pfill[block]:
                out[3] = 1.0
        else:
            i0, i1, j0, j1 = _track_posts(r0, r1, r2, c0, c1, c2, i, j, jw)
            h00, h01 = np.float64(heights[i, jw]), np.float64(heights[i, jw + 1])
            h10, h11 = np.float64(heights[i + 1, jw]), np.float64(heights[i + 1, jw + 1])
            rim = (h00 + h01 + h10 + h11) != (h00 + h01 + h10 + h11)
            if rim:  # a hole's post: only a track along a line of the cell's finite posts stays on
                h00, h01 = np.float64(heights[i0, j0]), np.float64(heights[i0, j1])
                h10, h11 = np.float64(heights[i1, j0]), np.float64(heights[i1, j1])
                if (h00 + h01 + h10 + h11) != (h00 + h01 + h10 + h11):
                    return _WALK_OUTSIDE
            if filled.shape[0] > 0 and (filled[i0, j0] | filled[i0, j1] | filled[i1, j0] | filled[i1, j1]):
                out[3] = 1.0
            w = u_e - u
            v = _cell_root(h00, h01, h10, h11, poly, u, w, i, j, stack)
            if v >= 0.0:
                uh = u + v * w
                fx = _quad(c0, c1, c2, uh) - j
                fy = _quad(r0, r1, r2, uh) - i
                out[0] = uh
                if rim:  # the slope there is found by trace_segments (_rim_slopes), kept out of this loop
                    out[1], out[2], out[5] = i + fy, jw + fx, 1.0
                else:
                    out[1] = (h01 - h00) + (h00 - h01 - h10 + h11) * fy
                    out[2] = (h10 - h00) + (h00 - h01 - h10 + h11) * fx
                return _WALK_HIT
        if u_e >= ub:
            out[4] = k
            return _WALK_ON
        i, j = _next_cell(r0, r1, r2, c0, c1, c2, sr, sc, rlo, rhi, clo, chi, u_r, u_c, u_e, ncy, ncx)
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
def _segment(a_ecef, b_ecef, n):
    """(ax, ay, az, vx, vy, vz, length, ux, uy) of segment n: its start a, v = b - a, |v| and v's x and
    y over |v| (0 for a segment of zero length)."""
    ax, ay, az = a_ecef[n, 0], a_ecef[n, 1], a_ecef[n, 2]
    vx, vy, vz = b_ecef[n, 0] - ax, b_ecef[n, 1] - ay, b_ecef[n, 2] - az
    length = math.sqrt(vx * vx + vy * vy + vz * vz)
    ux, uy = (vx / length, vy / length) if length > 0.0 else (0.0, 0.0)
    return ax, ay, az, vx, vy, vz, length, ux, uy


@numba.njit(cache=True, nogil=True, inline="always")
def _track_at(seg, s, crs, x0, y0, dx, dy):
    """(row, col, h): the raster's fractional index and the height of the point a + s v of
    seg = :func:`_segment`'s values (exact geodetic position)."""
    lat, lon, h = _geodetic(seg[0] + s * seg[3], seg[1] + s * seg[4], seg[2] + s * seg[5])
    r, c = fractional_index(lat, lon, crs, x0, y0, dx, dy)
    return r, c, h


@numba.njit(cache=True, nogil=True, inline="always")
def _next_piece(seg, sa, s_end, ca, crs, x0, y0, dx, dy, turn_cols, rho_coef):
    """The piece of the track from s = sa (column ca there) to sb, a piece_length_m on or s_end if
    nearer: (sb, rm, cm, hm, rb, cb, hb), the exact positions (:func:`_track_at`) at its middle and
    end, columns unwrapped along the ray; :func:`_fit_piece` fits them."""
    sb = s_end
    if seg[6] > 0.0:
        step = piece_length_m(seg[0] + sa * seg[3], seg[1] + sa * seg[4], seg[7], seg[8], rho_coef) / seg[6]
        sb = min(sa + step, sb)
    rm, cm, hm = _track_at(seg, 0.5 * (sa + sb), crs, x0, y0, dx, dy)
    rb, cb, hb = _track_at(seg, sb, crs, x0, y0, dx, dy)
    cm = _unwrap(cm, ca, turn_cols)
    cb = _unwrap(cb, cm, turn_cols)
    return sb, rm, cm, hm, rb, cb, hb


@numba.njit(cache=True, nogil=True)
def _fit_piece(ra, rm, rb, ca, cm, cb, ha, hm, hb, poly, cuts):
    """A piece's row, column and height quadratics in u in [0, 1], through its start, middle and end,
    into poly[0:9], and the ends of its stretches monotone in both row and column (split where
    either turns) into cuts[0:n_cuts + 1], in order, the last 1. Returns n_cuts."""
    _fit(ra, rm, rb, poly, 0)
    _fit(ca, cm, cb, poly, 3)
    _fit(ha, hm, hb, poly, 6)
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
    return n_cuts


@numba.njit(cache=True, nogil=True)
def _trace_kernel(heights, filled, pmax, pfill, poff, pshape, crs, x0, y0, dx, dy, periodic, poles, turn_cols,
                  a_ecef, b_ecef, s_lo, s_hi, rho_coef, out_s, out_dcol, out_drow, out_status, out_rim):
    """First contact parameter s in [s_lo, s_hi] (NaN: none) of each segment a + s (b - a).

    a_ecef, b_ecef: (n, 3) float64 ECEF metres; s_lo, s_hi: (n,) float64.
    Writes out_s (n,) float64, out_dcol/out_drow (n,) float64 surface slope at
    the hit in metres per index step, out_status (n,) uint8 STATUS_*; out_rim (n,) uint8 1 where
    the hit lies on a post line beside a hole, out_dcol/out_drow then its fractional row and
    column (:func:`_walk`).
    """
    poly = np.zeros(9)
    cuts = np.zeros(4)
    stack = np.zeros((_STACK_DEPTH, 7))
    out = np.zeros(6)
    for n in range(a_ecef.shape[0]):
        seg = _segment(a_ecef, b_ecef, n)
        out_s[n] = math.nan
        out[3] = 0.0
        out[5] = 0.0
        out[4] = pshape.shape[0] - 1
        sa = s_lo[n]
        ra, ca, ha = _track_at(seg, sa, crs, x0, y0, dx, dy)
        code = _WALK_ON
        while code == _WALK_ON:
            sb, rm, cm, hm, rb, cb, hb = _next_piece(seg, sa, s_hi[n], ca, crs, x0, y0, dx, dy, turn_cols, rho_coef)
            n_cuts = _fit_piece(ra, rm, rb, ca, cm, cb, ha, hm, hb, poly, cuts)
            u0 = 0.0
            for c in range(n_cuts + 1):
                code = _walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, u0, cuts[c],
                             stack, out)
                if code != _WALK_ON:
                    break
                u0 = cuts[c]
            if code == _WALK_HIT:
                out_s[n] = sa + out[0] * (sb - sa)
                out_dcol[n], out_drow[n], out_rim[n] = out[1], out[2], out[5] > 0.0
            if code == _WALK_ON and sb >= s_hi[n]:
                break
            sa, ra, ca, ha = sb, rb, cb, hb
        if code == _WALK_OUTSIDE:
            out_status[n] = STATUS_OUTSIDE
        else:
            out_status[n] = STATUS_FILLED if out[3] > 0.0 else STATUS_OK


@numba.njit(cache=True, nogil=True)
def _rim_slopes(heights, periodic, rows, cols):
    """(d h / d col, d h / d row) (m per index step) at fractional indices (rows, cols) (m,) of hits
    on a post line beside a hole: the raster's slope there as its points' (terrain.raster's
    _gradient_value, which Raster.gradient_into answers normals with), so a ray's contact normal is
    the one normals give its point. Kept out of the walk, whose hot loop it slowed by half."""
    dcol, drow = np.zeros(rows.shape[0]), np.zeros(rows.shape[0])
    for k in range(rows.shape[0]):
        dcol[k], drow[k], _ = _gradient_value(heights, rows[k], cols[k], periodic)
    return dcol, drow


def check_segments(a_lat, a_lon, a_h, b_lat, b_lon, b_h):
    """Validated segment end arrays, each (n,) float64; raises InvalidArgument naming the field."""
    a_lat, a_lon = check_latlon(a_lat, a_lon, prefix="a_")
    b_lat, b_lon = check_latlon(b_lat, b_lon, prefix="b_")
    if b_lat.size != a_lat.size:
        raise InvalidArgument("b_lat", f"must have as many values as a_lat ({a_lat.size}), got {b_lat.size}")
    a_h = check_heights("a_h", a_h, a_lat.size)
    b_h = check_heights("b_h", b_h, a_lat.size)
    return a_lat, a_lon, a_h, b_lat, b_lon, b_h


def _walk_params(raster: Raster) -> tuple[int, int, float]:
    """(periodic, poles, columns per turn) of a raster as :func:`trace_segments` walks it.

    periodic: the cells per turn when the raster's columns wrap, else 0. A raster wraps when a turn
    is a whole number of its cells (to 1e-9 of a turn) and it spans that turn or more: its cells
    past the first turn repeat the first ones, and like the heights kernel (terrain.raster, longitude
    modulo a turn east of x0) the walk reads only the first turn's cells (a GeoTIFF from -180.05 to
    180.05, or a store's all-longitude raster of a turn and two posts, was walked as a plain range
    and rays over the pole or across its seam left it: OUTSIDE).
    """
    g = raster.georef
    turn = 360.0 if g.crs == CRS_GEOGRAPHIC else TWO_PI_A_M
    periodic = raster.columns_per_turn
    poles = 0
    if g.crs == CRS_GEOGRAPHIC:
        lat_top = g.y0 + (raster.shape[0] - 1) * g.dy
        poles = int(abs(g.y0 + 90.0) <= 1.0e-9) | 2 * int(abs(lat_top - 90.0) <= 1.0e-9)
    return periodic, poles, turn / g.dx


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
    periodic, poles, turn_cols = _walk_params(raster)
    pyr = raster.pyramid
    s = np.zeros(n)
    dcol = np.full(n, np.nan)
    drow = np.full(n, np.nan)
    status = np.zeros(n, np.uint8)
    filled = raster.filled if raster.filled is not None else _NO_FILLED
    rim = np.zeros(n, np.uint8)
    _trace_kernel(raster.heights, filled, pyr.max_flat, pyr.filled_flat, pyr.offsets, pyr.shapes,
                  g.crs, g.x0, g.y0, g.dx, g.dy, periodic, poles, turn_cols, a_ecef, b_ecef, s_lo, s_hi,
                  PIECE_RHO_COEF, s, dcol, drow, status, rim)
    rim = np.flatnonzero(rim)
    if rim.size:
        dcol[rim], drow[rim] = _rim_slopes(raster.heights, periodic, dcol[rim], drow[rim])
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

    def trace(a, b, s_lo, s_hi):
        s, _, _, status = trace_segments(raster, a, b, s_lo, s_hi)
        return s, status

    return _both_ways(trace, a, b)


def _both_ways(trace, a, b):
    """(visible, status) of the ECEF segments a -> b ((n, 3), both changed) for a first-contact
    trace(a, b, s_lo, s_hi) -> (s (NaN: none), status): as :func:`line_of_sight` answers. Each pair
    is traced from the endpoint whose ECEF (x, y, z) sorts first (a and b are swapped in place to
    that order), and a ray that leaves the covered surface from the other end as well."""
    d = b - a
    first_diff = np.argmax(d != 0.0, axis=1)
    swap = d[np.arange(d.shape[0]), first_diff] < 0.0
    a[swap], b[swap] = b[swap], a[swap]
    length = np.linalg.norm(d, axis=1)
    with np.errstate(divide="ignore"):
        s_lo = np.minimum(ENDPOINT_TOLERANCE_M / length, 0.5)
    s, status = trace(a, b, s_lo, 1.0 - s_lo)
    # A ray that leaves the surface may be blocked on its covered part behind the endpoint it
    # was traced from (that endpoint outside, or a hole between): trace those from the other
    # end too. A contact found before leaving is a definite answer, as intersect_segments
    # reports it; the rest stay OUTSIDE (for the next source, on one raster).
    out = np.flatnonzero(status == STATUS_OUTSIDE)
    if out.size:
        s_back, status_back = trace(b[out], a[out], s_lo[out], 1.0 - s_lo[out])
        blocked = ~np.isnan(s_back)
        s[out[blocked]] = 1.0 - s_back[blocked]
        status[out[blocked]] = status_back[blocked]
    # A segment no longer than twice the tolerance has no interior left to block it: it is a point,
    # which sees unless it lies more than the tolerance under the surface (as a longer segment
    # from it is blocked within the tolerance of that end; one on the ground, rounding either way,
    # still sees). Its middle raised by the tolerance, traced as a point, meets the surface iff so.
    short = length <= 2.0 * ENDPOINT_TOLERANCE_M
    visible = (np.isnan(s) | short) & (status != STATUS_OUTSIDE)
    idx = np.flatnonzero(short & visible)
    if idx.size:
        q = _raised(0.5 * (a[idx] + b[idx]), ENDPOINT_TOLERANCE_M)
        s_q, _ = trace(q, q.copy(), np.zeros(idx.size), np.zeros(idx.size))
        visible[idx[~np.isnan(s_q)]] = False
    return visible, status


def _raised(p_ecef: np.ndarray, up_m: float) -> np.ndarray:
    """(n, 3) ECEF points p_ecef ((n, 3) metres) moved up_m metres along their ellipsoid normal
    (geodetic up: (cos lat cos lon, cos lat sin lon, sin lat)), so their height grows by up_m."""
    lat, lon, _ = ecef_to_geodetic(p_ecef)
    phi, lam = np.radians(lat), np.radians(lon)
    up = np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)], axis=-1)
    return p_ecef + up_m * up


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


# --------------------------------------------------------------------------- segments over a stack of sources
#
# The stack's surface along a segment is, at each point, the surface of the first source covering
# it (over its filled void, the first later one measuring the ground), as
# terrain.terrain.Terrain.heights answers. stack_trace finds the first contact with it: every
# source's raster gives the parameter intervals of the segment it covers (the cells of four finite
# posts the segment's track crosses, walked as _walk walks them: the same pieces and quadratic track,
# _next_piece and _fit_piece, and the same block walk over the same cells, _walk_start, _enter,
# _block, _next_cell); a sweep keeps each stretch for the first source covering it; the stretches
# are traced in order along the segment by trace_segments, each on its source's raster, until a
# contact.

# A stretch no source covers shorter than this (m) is no gap: where two rasters meet, the ends of
# their coverage come from two quadratic models of the track (each within MODEL_ERROR_M, 1 um, of
# it) and may leave a sliver between them.
STACK_GAP_TOLERANCE_M = 1.0e-4
# First step (m) by which a stretch's ends are moved inwards until its raster covers them exactly
# (trace_segments starts and ends a trace at the exact position; the interval came from the model).
STACK_NUDGE_M = 1.0e-9
# Parameter distance within which a covered interval continues the previous one (pieces meet at
# the same parameter; the product u (sb - sa) only rounds).
_TOUCH = 1.0e-12


@numba.njit(cache=True, nogil=True)
def _clip_monotone(p0, p1, p2, ua, ub, lo, hi):
    """[u0, u1] within [ua, ub] where lo <= p(u) <= hi, p = p0 + p1 u + p2 u^2 monotone on
    [ua, ub] (a stretch of the piecewise-quadratic track); u0 > u1 when empty."""
    pa, pb = _quad(p0, p1, p2, ua), _quad(p0, p1, p2, ub)
    if pa <= pb:
        if pb < lo or pa > hi:
            return 1.0, 0.0
        u0 = ua if pa >= lo else _cross(p0, p1, p2, lo, ua, ub)
        u1 = ub if pb <= hi else _cross(p0, p1, p2, hi, ua, ub)
    else:
        if pa < lo or pb > hi:
            return 1.0, 0.0
        u0 = ua if pa <= hi else _cross(p0, p1, p2, hi, ua, ub)
        u1 = ub if pb >= lo else _cross(p0, p1, p2, lo, ua, ub)
    return u0, u1


@numba.njit(cache=True, nogil=True)
def _emit(s0, s1, fill, ray, first, count, out_ray, out_s0, out_s1, out_fill):
    """Add [s0, s1] (fill: 1 over filled-void cells, else 0) to the ray's intervals
    out_*[first:count], merged into the last one when it continues it with the same fill; the new
    count, or -1 when the arrays are full."""
    if count > first and s0 <= out_s1[count - 1] + _TOUCH and out_fill[count - 1] == fill:
        if s1 > out_s1[count - 1]:
            out_s1[count - 1] = s1
        return count
    if count >= out_ray.shape[0]:
        return -1
    out_ray[count], out_s0[count], out_s1[count], out_fill[count] = ray, s0, s1, fill
    return count + 1


@numba.njit(cache=True, nogil=True)
def _cover_walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, shift, u0, u1, sa, sb, ray, first,
                count, out_ray, out_s0, out_s1, out_fill):
    """Emit (as parameters s = sa + u (sb - sa)) the parts of [u0, u1] over cells of four finite
    posts, each marked 1 in out_fill over cells with a filled-void post (pfill: the pyramid's
    filled flags, empty when the raster has none), else 0; along a post line, over cells whose
    posts on the line are finite, marked by those posts (:func:`_track_posts`, as :func:`_walk`
    reads them; heights, filled: the raster's). [u0, u1] is a monotone stretch of a
    piece clipped to the raster's rows and (columns less ``shift``, a whole number of turns) its
    columns. The walk is :func:`_walk`'s (the same block steps on the min/max pyramid): a block
    whose maximum is finite holds no hole and is passed whole (a cell with a NaN post has maximum
    +inf, terrain.pyramid), unless it holds a filled post (then its cells are told apart)."""
    ncy, ncx = pshape[0, 0], (periodic if periodic else pshape[0, 1])
    has_fill = pfill.shape[0] > 0
    r0, r1, r2 = poly[0], poly[1], poly[2]
    c0, c1, c2 = poly[3] - shift, poly[4], poly[5]
    on_line = (r1 == 0.0 and r2 == 0.0) or (c1 == 0.0 and c2 == 0.0)
    sr, sc, i, j = _walk_start(r0, r1, r2, c0, c1, c2, u0, u1, ncy, ncx)
    if i == _OUT_OF_RANGE or j == _OUT_OF_RANGE:
        return count
    i = min(max(i, 0), ncy - 1)  # clipped already: only rounding puts the start a cell out
    if not periodic:
        j = min(max(j, 0), ncx - 1)
    top = pshape.shape[0] - 1
    k = top
    u = u0
    while True:
        on, i, sr, jw = _enter(i, j, sr, periodic, poles, ncy, ncx)
        if not on:
            return count
        bi, bj, rlo, rhi, clo, chi, u_r, u_c, u_e = _block(r0, r1, r2, c0, c1, c2, i, j, jw, k, sr, sc, u, u1,
                                                           ncy, ncx)
        block = poff[k] + bi * pshape[k, 1] + bj
        covered = pmax[block] < math.inf
        fill = pfill[block] if has_fill else 0
        if (not covered or fill) and k > 0:
            k -= 1
            continue
        if (not covered or fill) and on_line:
            i0, i1, j0, j1 = _track_posts(r0, r1, r2, c0, c1, c2, i, j, jw)
            h = (np.float64(heights[i0, j0]) + np.float64(heights[i0, j1]) + np.float64(heights[i1, j0])
                 + np.float64(heights[i1, j1]))
            covered = h == h
            if has_fill:
                fill = filled[i0, j0] | filled[i0, j1] | filled[i1, j0] | filled[i1, j1]
        if covered:
            count = _emit(sa + u * (sb - sa), sa + u_e * (sb - sa), fill, ray, first, count, out_ray, out_s0, out_s1,
                          out_fill)
            if count < 0:
                return count
        if u_e >= u1:
            return count
        i, j = _next_cell(r0, r1, r2, c0, c1, c2, sr, sc, rlo, rhi, clo, chi, u_r, u_c, u_e, ncy, ncx)
        u = u_e
        k = min(k + 1, top)


@numba.njit(cache=True, nogil=True)
def _cover_stretch(heights, filled, pmax, pfill, poff, pshape, periodic, poles, turn_cols, poly, ua, ub, sa, sb, ray,
                   first, count, out_ray, out_s0, out_s1, out_fill):
    """:func:`_cover_walk` over the parts of the monotone stretch [ua, ub] inside the raster's rows
    (beyond a pole row too, when the raster reaches the pole) and columns: every copy of the
    column range a whole turn apart that the stretch meets, in order along it (a raster not
    spanning the globe ends at its first and last column, as in :func:`_walk`)."""
    ncy, ncx = pshape[0, 0], pshape[0, 1]
    u0, u1 = _clip_monotone(poly[0], poly[1], poly[2], ua, ub, -math.inf if poles & 1 else 0.0,
                            math.inf if poles & 2 else float(ncy))
    if not u0 <= u1:
        return count
    if periodic:
        return _cover_walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, 0.0, u0, u1, sa, sb, ray,
                           first, count, out_ray, out_s0, out_s1, out_fill)
    c_a, c_b = _quad(poly[3], poly[4], poly[5], ua), _quad(poly[3], poly[4], poly[5], ub)
    lo, hi = min(c_a, c_b), max(c_a, c_b)
    if not (abs(lo) < 1.0e12 and abs(hi) < 1.0e12):
        return count
    m_lo, m_hi = math.ceil((lo - ncx) / turn_cols), math.floor(hi / turn_cols)
    for t in range(int(m_hi - m_lo) + 1):
        m = m_lo + t if c_b >= c_a else m_hi - t
        shift = m * turn_cols
        v0, v1 = _clip_monotone(poly[3] - shift, poly[4], poly[5], ua, ub, 0.0, float(ncx))
        v0, v1 = max(v0, u0), min(v1, u1)
        if v0 <= v1:
            count = _cover_walk(heights, filled, pmax, pfill, poff, pshape, periodic, poles, poly, shift, v0, v1, sa,
                                sb, ray, first, count, out_ray, out_s0, out_s1, out_fill)
            if count < 0:
                return count
    return count


@numba.njit(cache=True, nogil=True)
def _cover_kernel(heights, filled, pmax, pfill, poff, pshape, crs, x0, y0, dx, dy, periodic, poles, turn_cols, a_ecef,
                  b_ecef, s_lo, s_hi, rho_coef, first_ray, out_ray, out_s0, out_s1, out_fill):
    """The parameter intervals of each segment a + s (b - a), s in [s_lo, s_hi], over the raster's
    covered cells (out_fill: 1 over filled-void cells), in order, from segment first_ray on:
    (count written, next segment). The
    track is :func:`_trace_kernel`'s (the pieces and monotone stretches of :func:`_next_piece` and
    :func:`_fit_piece`). When the arrays fill up the next segment is below n and none of its
    intervals are written: call again from it with larger ones."""
    poly = np.zeros(9)
    cuts = np.zeros(4)
    count = 0
    for n in range(first_ray, a_ecef.shape[0]):
        first = count
        seg = _segment(a_ecef, b_ecef, n)
        sa = s_lo[n]
        ra, ca, ha = _track_at(seg, sa, crs, x0, y0, dx, dy)
        while True:
            sb, rm, cm, hm, rb, cb, hb = _next_piece(seg, sa, s_hi[n], ca, crs, x0, y0, dx, dy, turn_cols, rho_coef)
            n_cuts = _fit_piece(ra, rm, rb, ca, cm, cb, ha, hm, hb, poly, cuts)
            u0 = 0.0
            for c in range(n_cuts + 1):
                count = _cover_stretch(heights, filled, pmax, pfill, poff, pshape, periodic, poles, turn_cols, poly, u0,
                                       cuts[c], sa, sb, n, first, count, out_ray, out_s0, out_s1, out_fill)
                if count < 0:
                    return first, n
                u0 = cuts[c]
            if sb >= s_hi[n]:
                break
            sa, ra, ca, ha = sb, rb, cb, hb
    return count, a_ecef.shape[0]


@numba.njit(cache=True, nogil=True, inline="always")
def _post_span(v, along):
    """(first, last) posts beside fractional index v whichever way a walk leaves it: the two of its
    cell, the three of both cells beside a post line it lies on, or that line's alone when the
    track runs along it (``along``)."""
    k = int(math.floor(v))
    if v != k:
        return k, k + 1
    return (k, k) if along else (k - 1, k + 1)


@numba.njit(cache=True, nogil=True)
def _covered_at(heights, crs, x0, y0, dx, dy, periodic, x, y, z, on_row, on_col):
    """Whether the ECEF point lies in a cell of four finite posts whichever way a walk leaves it
    (:func:`_walk` takes the cell ahead on a boundary): on a row or column line both cells beside
    it that the raster has must be covered, and one at least; a track along that line (on_row,
    on_col: its row, its column constant, :func:`_along_lines`) reads the line's posts alone, as
    :func:`_walk` does (:func:`_track_posts`)."""
    lat, lon, _ = _geodetic(x, y, z)
    r, c = fractional_index(lat, lon, crs, x0, y0, dx, dy)
    if not (abs(r) < 1.0e12 and abs(c) < 1.0e12):
        return False
    ny, nx = heights.shape
    if not (0.0 <= r <= ny - 1) or not (periodic or 0.0 <= c <= nx - 1):
        return False
    ra, rb = _post_span(r, on_row)
    ca, cb = _post_span(c, on_col)
    ra, rb = max(ra, 0), min(rb, ny - 1)
    if not periodic:
        ca, cb = max(ca, 0), min(cb, nx - 1)
    for p in range(ra, rb + 1):
        for q in range(ca, cb + 1):
            v = heights[p, q % periodic if periodic else q]
            if v != v:
                return False
    return True


@numba.njit(cache=True, nogil=True)
def _along_lines(crs, x0, y0, dx, dy, ax, ay, az, vx, vy, vz, lo, hi):
    """(on_row, on_col): whether the stretch [lo, hi] of segment a + s v runs along a row line, a
    column line of posts: its fractional row (column) the same whole number at its ends and middle
    (a straight chord lies on a line of constant latitude or longitude all along or crosses it;
    vertical segments and those in a meridian plane run along one, snapped to it as every point of
    their track is by terrain.raster.fractional_index)."""
    ra, ca = 0.0, 0.0
    on_row, on_col = True, True
    for t in range(3):
        s = lo + 0.5 * t * (hi - lo)
        lat, lon, _ = _geodetic(ax + s * vx, ay + s * vy, az + s * vz)
        r, c = fractional_index(lat, lon, crs, x0, y0, dx, dy)
        if t == 0:
            ra, ca = r, c
        on_row = on_row and r == ra and r == math.floor(r)
        on_col = on_col and c == ca and c == math.floor(c)
    return on_row, on_col


@numba.njit(cache=True, nogil=True)
def _inner_bounds(heights, crs, x0, y0, dx, dy, periodic, a_ecef, b_ecef, p0, p1, nudge_m, out0, out1):
    """Each stretch [p0, p1] of a segment a + s (b - a) with its ends moved inwards, by nudge_m
    doubling, until the raster covers them exactly (:func:`_covered_at`, for a stretch along a
    post line that line's posts, :func:`_along_lines`), so that
    :func:`trace_segments` starts and ends the stretch on the raster; NaN when no point up to the
    stretch's middle is covered (a sliver along a hole's rim)."""
    for n in range(p0.shape[0]):
        ax, ay, az, vx, vy, vz, length, _, _ = _segment(a_ecef, b_ecef, n)
        step = nudge_m / length if length > 0.0 else 0.0
        lo, hi = p0[n], p1[n]
        mid = 0.5 * (lo + hi)
        on_row, on_col = _along_lines(crs, x0, y0, dx, dy, ax, ay, az, vx, vy, vz, lo, hi)
        out0[n] = math.nan
        out1[n] = math.nan
        s, d = lo, step
        while True:
            if _covered_at(heights, crs, x0, y0, dx, dy, periodic, ax + s * vx, ay + s * vy, az + s * vz, on_row,
                           on_col):
                out0[n] = s
                break
            if s >= mid or d == 0.0:
                break
            s, d = min(lo + d, mid), 2.0 * d
        s, d = hi, step
        while True:
            if _covered_at(heights, crs, x0, y0, dx, dy, periodic, ax + s * vx, ay + s * vy, az + s * vz, on_row,
                           on_col):
                out1[n] = s
                break
            if s <= mid or d == 0.0:
                break
            s, d = max(hi - d, mid), 2.0 * d


@numba.njit(cache=True, nogil=True)
def _top_at(iv_src, iv_s0, iv_s1, iv_fill, measured, start, stop, x):
    """The source of the stack's surface at parameter x, among intervals [start, stop): the first
    (lowest index) source holding x, unless it holds x only over filled-void cells and a measured
    source (measured[source] set) holds x over cells of its own data: then the first of those,
    as terrain.terrain.Terrain.heights answers a filled point. Returns (source, 1 when the
    source holds x over filled-void cells only, else 0); source -1: none."""
    top, top_fill, alt = -1, 0, -1
    for t in range(start, stop):
        if not iv_s0[t] <= x <= iv_s1[t]:
            continue
        src = iv_src[t]
        if top < 0 or src < top:
            top, top_fill = src, iv_fill[t]
        elif src == top:
            top_fill &= iv_fill[t]
        if iv_fill[t] == 0 and measured[src] and (alt < 0 or src < alt):
            alt = src
    if top_fill and alt >= 0:
        return alt, 0
    return top, top_fill


@numba.njit(cache=True, nogil=True, inline="always")
def _takes_the_run(left, left_fill, right, right_fill, measured):
    """Whether the stretch of source ``left`` (its fill flag left_fill, as :func:`_top_at` gives
    them) takes a run between it and that of ``right``: the one heights would answer where both
    cover (a source's own data over another's filled void, else the first; -1: no source)."""
    if left < 0 or right < 0:
        return left >= 0
    if left_fill != right_fill:
        return measured[right] == 0 if left_fill else measured[left] == 1
    return left < right


@numba.njit(cache=True, nogil=True)
def _stack_parts(iv_ray, iv_src, iv_s0, iv_s1, iv_fill, measured, s_lo, s_hi, length, gap_m, out_ray, out_src,
                 out_p0, out_p1, out_fill):
    """Cut each segment's [s_lo, s_hi] into stretches of one source: the first (lowest index)
    source whose interval holds the stretch, or the first measured one for a stretch the first
    holds over filled voids only (:func:`_top_at`), -1 where none does. iv_*: every source's
    covered intervals, grouped by segment in segment order; measured: per source, 1 unless its
    data is synthetic. out_fill: 1 for a stretch its source holds over filled voids only. Returns
    the count written (in order along each segment); a segment of zero extent gets one stretch,
    the source holding its point.

    No stretch is shorter than gap_m metres (but that of a segment shorter than it): the ends of
    the intervals (and the segment's own) are taken in runs each within gap_m of the next, and a
    run is one boundary. Where two rasters meet, their ends come from two quadratic models of the
    track (each within MODEL_ERROR_M of it) and differ by nanometres: the run holds both, and the
    sliver between them (of a source below both, or of none) is no stretch. The stretches meet
    at the run's end nearer the lower-priority neighbour (the higher-priority neighbour takes the
    run: the stack's surface where both are within the models' error of covering; a source over
    no source, -1, comes after every source), the same whichever way the segment runs; a run
    holding the segment's start or end ends the stretches there. The source of each stretch is
    read between two runs, where no interval ends, so it holds over the whole stretch but the
    runs' sub-gap_m ends."""
    count = 0
    g = 0
    for ray in range(s_lo.shape[0]):
        start = g
        while g < iv_ray.shape[0] and iv_ray[g] == ray:
            g += 1
        lo, hi = s_lo[ray], s_hi[ray]
        if not hi > lo:
            top, fill = _top_at(iv_src, iv_s0, iv_s1, iv_fill, measured, start, g, lo)
            out_ray[count], out_src[count], out_p0[count], out_p1[count], out_fill[count] = ray, top, lo, lo, fill
            count += 1
            continue
        npt = 2 * (g - start) + 2
        pts = np.empty(npt)
        pts[0], pts[1] = lo, hi
        for t in range(start, g):
            pts[2 + 2 * (t - start)] = min(max(iv_s0[t], lo), hi)
            pts[3 + 2 * (t - start)] = min(max(iv_s1[t], lo), hi)
        pts.sort()
        tol = gap_m / length[ray] if length[ray] > 0.0 else math.inf
        run_lo, run_hi = np.empty(npt), np.empty(npt)
        nr = 0
        for q in range(npt):
            if nr > 0 and pts[q] - run_hi[nr - 1] < tol:
                run_hi[nr - 1] = pts[q]
            else:
                run_lo[nr], run_hi[nr] = pts[q], pts[q]
                nr += 1
        if nr == 1:  # the segment is shorter than gap_m: one stretch, the source at its middle
            top, fill = _top_at(iv_src, iv_s0, iv_s1, iv_fill, measured, start, g, 0.5 * (lo + hi))
            out_ray[count], out_src[count], out_p0[count], out_p1[count], out_fill[count] = ray, top, lo, hi, fill
            count += 1
            continue
        tops, fills = np.empty(nr - 1, np.int64), np.empty(nr - 1, np.uint8)
        for q in range(nr - 1):
            tops[q], fills[q] = _top_at(iv_src, iv_s0, iv_s1, iv_fill, measured, start, g,
                                        0.5 * (run_hi[q] + run_lo[q + 1]))
        first = count
        x0 = lo
        for q in range(nr - 1):
            if q == nr - 2:
                x1 = hi
            elif _takes_the_run(tops[q], fills[q], tops[q + 1], fills[q + 1], measured):
                x1 = run_hi[q + 1]
            else:
                x1 = run_lo[q + 1]
            if count > first and out_src[count - 1] == tops[q] and out_fill[count - 1] == fills[q]:
                out_p1[count - 1] = x1
            else:
                out_ray[count], out_src[count], out_p0[count], out_p1[count] = ray, tops[q], x0, x1
                out_fill[count] = fills[q]
                count += 1
            x0 = x1
    return count


@numba.njit(cache=True, nogil=True)
def _covered_whole(iv_ray, iv_s0, iv_s1, s_lo, s_hi, length, gap_m, out):
    """out[ray] = whether the intervals (sorted by segment, then by start) cover the segment's
    [s_lo, s_hi] but for gaps (inside it or at its ends) shorter than gap_m metres, which
    :func:`_stack_parts` gives to the stretches beside them. A segment no longer than gap_m counts
    as not covered (the sources below are asked: _stack_parts reads its source at its middle)."""
    g = 0
    n_iv = iv_ray.shape[0]
    for ray in range(s_lo.shape[0]):
        tol = gap_m / length[ray] if length[ray] > 0.0 else math.inf
        reach = s_lo[ray]
        while g < n_iv and iv_ray[g] == ray:
            if iv_s0[g] < reach + tol:
                reach = max(reach, iv_s1[g])
            g += 1
        out[ray] = (s_hi[ray] - s_lo[ray]) * length[ray] > gap_m and reach > s_hi[ray] - tol


def segment_coverage(raster: Raster, a_ecef, b_ecef, s_lo, s_hi):
    """Where segments run over a raster: (segment index, s0, s1, fill) (m,) arrays of the parameter
    intervals of each a + s (b - a), s in [s_lo, s_hi], over cells of four finite posts, grouped
    by segment in order and along each segment; fill (uint8) is 1 for an interval over cells with
    a filled-void post (such cells make intervals of their own), else 0. The track and the cells are those of
    :func:`trace_segments`: a trace started inside an interval leaves the raster at its end, to
    within the track model's error (MODEL_ERROR_M)."""
    g = raster.georef
    periodic, poles, turn_cols = _walk_params(raster)
    pyr = raster.pyramid
    filled = raster.filled if raster.filled is not None else _NO_FILLED
    whole = _whole_segments(raster, a_ecef, b_ecef)
    walk = np.flatnonzero(~whole)
    a_walk, b_walk = np.ascontiguousarray(a_ecef[walk]), np.ascontiguousarray(b_ecef[walk])
    n = walk.size
    cap = max(64, 4 * n)
    parts, first = [], 0
    while first < n:
        out = np.empty(cap, np.int64), np.empty(cap), np.empty(cap), np.empty(cap, np.uint8)
        count, first = _cover_kernel(raster.heights, filled, pyr.max_flat, pyr.filled_flat, pyr.offsets, pyr.shapes,
                                     g.crs, g.x0, g.y0, g.dx, g.dy, periodic, poles, turn_cols, a_walk, b_walk,
                                     s_lo[walk], s_hi[walk], PIECE_RHO_COEF, first, *out)
        parts.append((walk[out[0][:count]], out[1][:count], out[2][:count], out[3][:count]))
        cap *= 2
    inside = np.flatnonzero(whole)
    parts.append((inside, s_lo[inside], s_hi[inside], np.zeros(inside.size, np.uint8)))
    ray, s0, s1, fill = (np.concatenate(p) for p in zip(*parts))
    order = np.argsort(ray, kind="stable")  # each segment's intervals stay in order along it
    return ray[order], s0[order], s1[order], fill[order]


def _whole_segments(raster: Raster, a_ecef, b_ecef) -> np.ndarray:
    """(n,) bool: segments a raster without holes or filled voids covers whole, no walk needed (the procedural
    world's raster for the segments' box). A geographic raster covers a segment whose endpoints
    lie inside its bounds by more than the chord's poleward bulge (per segment: d^2 tan(phi) / 8
    radians for an angular span d, the small-angle expansion of the great-circle vertex latitude,
    with d taken generously as the endpoints' degree spans, longitude unscaled): the track's
    longitude is monotone between the endpoints' (the chord's projection on the equatorial plane
    is a straight line), its latitude within the endpoints' and the bulge."""
    n = a_ecef.shape[0]
    if (raster.georef.crs != CRS_GEOGRAPHIC or not np.isfinite(raster.pyramid.max_flat[-1]) or n == 0
            or raster.pyramid.filled_flat.size > 0):
        return np.zeros(n, bool)
    lat_a, lon_a, _ = ecef_to_geodetic(a_ecef)
    lat_b, lon_b, _ = ecef_to_geodetic(b_ecef)
    lat0, lon0, lat1, lon1 = raster.bounds
    d_rad = np.radians(np.hypot(lat_b - lat_a, (lon_b - lon_a + 180.0) % 360.0 - 180.0))
    tan_phi = np.tan(np.radians(np.minimum(np.maximum(np.abs(lat_a), np.abs(lat_b)), 89.0)))
    margin = np.degrees(d_rad * d_rad * tan_phi / 8.0) + 1.0e-9
    wa = (lon_a - lon0) % 360.0
    wb = wa + (lon_b - lon_a + 180.0) % 360.0 - 180.0
    return ((np.minimum(lat_a, lat_b) - margin > lat0) & (np.maximum(lat_a, lat_b) + margin < lat1)
            & (np.minimum(wa, wb) > 1.0e-9) & (np.maximum(wa, wb) < lon1 - lon0 - 1.0e-9))


def stack_partitions(sources, a_ecef, b_ecef, s_lo, s_hi, measured=None):
    """Split a batch of segments a + s (b - a), s in [s_lo, s_hi], over a stack of sources into
    parts each traced on one raster per source. ``sources``: per source, in priority order, a
    callable groups(idx) -> iterable of (raster or None, indices), the indices (a partition of
    the segments idx) that each raster serves (a Raster source serves all; a procedural or
    store source one raster per group whose box it can serve). A source is asked only for the
    segments that the sources before it do not cover whole (:func:`_covered_whole`, with
    STACK_GAP_TOLERANCE_M), counting neither filled voids nor, on a segment over a filled void,
    synthetic sources (``measured`` as :func:`stack_trace` takes it): a later source may have
    measured the void's ground. A segment inside a DEM needs no procedural raster, and
    its box does not widen the procedural box of the others. Yields (indices, rasters (one per
    source, None where that source is not needed or has nothing), coverage (ray (local to the
    indices), source, s0, s1, fill), for :func:`stack_trace`), lazily: a group's rasters are
    dropped once its parts have been traced."""
    n = a_ecef.shape[0]
    length = np.linalg.norm(b_ecef - a_ecef, axis=1)
    n_src = len(sources)
    flags = np.ones(n_src, bool) if measured is None else np.asarray(measured, bool)

    def restrict(cov, idx):
        keep = np.zeros(n, bool)
        keep[idx] = True
        keep = keep[cov[0]]
        return tuple(x[keep] for x in cov)

    def local(cov, idx):
        pos = np.empty(n, np.int64)
        pos[idx] = np.arange(idx.size)
        return (pos[cov[0]],) + cov[1:]

    def walk(k, idx, rasters, cov):
        if k > 0 and k < n_src:
            whole = np.zeros(n, bool)
            own = cov if not cov[4].any() else tuple(x[_final(cov, flags, n)] for x in cov)
            if k == 1 and (own[0][1:] >= own[0][:-1]).all():  # one source's: in order along each segment
                _covered_whole(own[0], own[2], own[3], s_lo, s_hi, length, STACK_GAP_TOLERANCE_M, whole)
            else:
                order = np.lexsort((own[2], own[0]))
                _covered_whole(own[0][order], own[2][order], own[3][order], s_lo, s_hi, length,
                               STACK_GAP_TOLERANCE_M, whole)
            whole = whole[idx]
            if whole.any():
                done = idx[whole]
                yield done, rasters + [None] * (n_src - k), local(restrict(cov, done), done)
                idx = idx[~whole]
                if idx.size == 0:
                    return
                cov = restrict(cov, idx)
        if k == n_src:
            yield idx, rasters, local(cov, idx)
            return
        for raster, sub in sources[k](idx):
            c = cov if sub.size == idx.size else restrict(cov, sub)
            if raster is not None:
                ray, s0, s1, fill = segment_coverage(raster, a_ecef[sub], b_ecef[sub], s_lo[sub], s_hi[sub])
                c = tuple(np.concatenate(x) for x in zip(c, (sub[ray], np.full(ray.size, k, np.int64), s0, s1, fill)))
            yield from walk(k + 1, sub, rasters + [raster], c)

    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.uint8))
    yield from walk(0, np.arange(n), [], empty)


def _final(cov, measured, n):
    """(m,) bool over covered intervals (ray, source, s0, s1, fill): those no later source can
    replace, the intervals of a source's own data, and a synthetic source's only on segments with
    no filled-void interval."""
    over_fill = np.zeros(n, bool)
    over_fill[cov[0][cov[4] > 0]] = True
    return (cov[4] == 0) & (measured[cov[1]] | ~over_fill[cov[0]])


def stack_trace(rasters, a_ecef, b_ecef, s_lo, s_hi, coverage=None, measured=None):
    """First contact of each segment a + s (b - a), s in [s_lo, s_hi], with the surface of a stack
    of rasters (priority order; None: a source with nothing here): at each point the first
    raster covering it, but where that raster has only a filled void and a measured raster
    (``measured``: per raster, False for synthetic data such as the procedural world's; None: all
    measured) has its own data, the first such (terrain.terrain.Terrain.heights's rule). Returns
    (s (NaN: none), d h / d col and d h / d row at the contact (its raster's index units), status,
    index of the contact's raster). ``coverage``: the rasters' covered intervals (ray, source, s0,
    s1, fill) when known (:func:`stack_partitions`), else found.

    Each raster's covered intervals (:func:`segment_coverage`) are cut into stretches of one
    source each (:func:`_stack_parts`; none shorter than STACK_GAP_TOLERANCE_M), which are traced
    in order along the segment by :func:`trace_segments` (exact against each bilinear surface)
    until the first contact: where a segment passes from a source onto a higher one under its
    surface, that is the stretch's start (the step between the two surfaces is a wall). Status
    OUTSIDE when a stretch no source covers comes first, else FILLED when a traced stretch passed
    over a filled void, else OK. Each stretch is traced from and to points its raster covers
    exactly (:func:`_inner_bounds`): the parts are exact to within about a micrometre of the
    sources' edges, and to within STACK_GAP_TOLERANCE_M where two sources' edges meet.
    """
    n = a_ecef.shape[0]
    length = np.linalg.norm(b_ecef - a_ecef, axis=1)
    if coverage is None:
        ivs = []
        for k, raster in enumerate(rasters):
            if raster is not None:
                ray, s0, s1, fill = segment_coverage(raster, a_ecef, b_ecef, s_lo, s_hi)
                ivs.append((ray, np.full(ray.size, k, np.int64), s0, s1, fill))
        iv = ([np.concatenate(x) for x in zip(*ivs)] if ivs
              else [np.zeros(0, np.int64)] * 2 + [np.zeros(0)] * 2 + [np.zeros(0, np.uint8)])
    else:
        iv = list(coverage)
    measured = np.ones(len(rasters), np.uint8) if measured is None else np.asarray(measured, np.uint8)
    order = np.argsort(iv[0], kind="stable")
    cap = 2 * iv[0].size + 2 * n
    parts = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap), np.empty(cap), np.empty(cap, np.uint8)
    m = _stack_parts(*(x[order] for x in iv), measured, s_lo, s_hi, length, STACK_GAP_TOLERANCE_M, *parts)
    p_ray, p_src, p_0, p_1, p_fill = (x[:m] for x in parts)
    rank = np.arange(m) - np.searchsorted(p_ray, p_ray)  # parts come in order along each segment
    s, dcol, drow = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    status = np.full(n, STATUS_OUTSIDE, np.uint8)
    which = np.full(n, -1, np.int64)
    done, filled = np.zeros(n, bool), np.zeros(n, bool)
    for j in range(int(rank.max(initial=-1)) + 1):
        sel = np.flatnonzero(rank == j)
        sel = sel[~done[p_ray[sel]]]
        done[p_ray[sel[p_src[sel] < 0]]] = True  # a gap before any contact: OUTSIDE
        for k in np.unique(p_src[sel]):
            if k < 0:
                continue
            part = sel[p_src[sel] == k]
            ray = p_ray[part]
            raster = rasters[k]
            g = raster.georef
            lo, hi = np.empty(part.size), np.empty(part.size)
            _inner_bounds(raster.heights, g.crs, g.x0, g.y0, g.dx, g.dy, _walk_params(raster)[0], a_ecef[ray],
                          b_ecef[ray], p_0[part], p_1[part], STACK_NUDGE_M, lo, hi)
            ok = ~np.isnan(lo) & ~np.isnan(hi) & (lo <= hi)
            ray = ray[ok]
            got_s, got_dc, got_dr, _ = trace_segments(raster, a_ecef[ray], b_ecef[ray], lo[ok], hi[ok])
            # The stretch's own flag, not the walk's (which flags every block it clears holding a
            # filled post, also beyond the stretch's ends).
            filled[ray[p_fill[part][ok] > 0]] = True
            hit = ~np.isnan(got_s)
            r = ray[hit]
            s[r], dcol[r], drow[r], which[r] = got_s[hit], got_dc[hit], got_dr[hit], k
            done[r] = True
            status[r] = np.where(filled[r], STATUS_FILLED, STATUS_OK)
    gap = done & np.isnan(s)
    through = ~done
    status[through] = np.where(filled[through], STATUS_FILLED, STATUS_OK)
    status[gap] = STATUS_OUTSIDE
    return s, dcol, drow, status, which


def stack_line_of_sight(sources, a_ecef, b_ecef, measured=None):
    """Whether each ECEF segment a -> b ((n, 3) float64 metres; swapped in place, per segment, to the
    order traced) clears the surface of a stack of sources (as :func:`stack_trace`; ``sources`` as
    :func:`stack_partitions` takes them, ``measured`` as :func:`stack_trace` does): (visible,
    status) as :func:`line_of_sight` gives them on one raster, contacts within
    ENDPOINT_TOLERANCE_M of either endpoint ignored; OUTSIDE (not visible) when a stretch no
    raster covers comes before any contact from either end."""
    n = a_ecef.shape[0]
    d = b_ecef - a_ecef
    swap = d[np.arange(n), np.argmax(d != 0.0, axis=1)] < 0.0  # _both_ways's order, so its swap is none
    a_ecef[swap], b_ecef[swap] = b_ecef[swap], a_ecef[swap]
    with np.errstate(divide="ignore"):
        s_lo = np.minimum(ENDPOINT_TOLERANCE_M / np.linalg.norm(d, axis=1), 0.5)
    visible, status = np.zeros(n, bool), np.full(n, STATUS_OUTSIDE, np.uint8)
    for idx, rasters, cov in stack_partitions(sources, a_ecef, b_ecef, s_lo, 1.0 - s_lo, measured):
        known = [cov]  # the first trace is over [s_lo, 1 - s_lo] of these segments, as partitioned

        def trace(a, b, lo, hi):
            s, _, _, st, _ = stack_trace(rasters, a, b, lo, hi, known.pop() if known else None, measured)
            return s, st

        visible[idx], status[idx] = _both_ways(trace, a_ecef[idx], b_ecef[idx])
    return visible, status
