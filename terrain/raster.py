"""A georeferenced grid of height posts and its bilinear surface.

A :class:`Raster` is the unit every query works on: a (rows, cols) array of
heights whose row 0 is the southernmost row and column 0 the westernmost,
posts (not cell areas) at the coordinates its :class:`Georef` gives. Readers in
:mod:`terrain.dem` turn files into this one layout, flipping rows and shifting
PixelIsArea grids by half a cell, so no query has to know a file's quirks.

Kernels here are numba functions over plain arrays; the class only holds and
validates them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np

from terrain.geodesy import WGS84_A_M, WEB_MERCATOR_MAX_LAT_DEG, radii_of_curvature

CRS_GEOGRAPHIC = 0  # EPSG:4326: x = longitude (deg), y = latitude (deg)
CRS_WEB_MERCATOR = 1  # EPSG:3857: x, y in projected metres
CRS_NAMES = {CRS_GEOGRAPHIC: "EPSG:4326", CRS_WEB_MERCATOR: "EPSG:3857"}

# Per-point status codes; the values equal sortie.v1.PointStatus.
STATUS_OK = 1  # inside the data, from a source's own posts (measured, or generated for the procedural world)
STATUS_FILLED = 2  # inside, but a contributing post was a void filled by rule
STATUS_OUTSIDE = 3  # no terrain covers the point: height is NaN

# A fractional index this close to an integer is taken as that post, so that
# (lat, lon) computed as origin + k * spacing hit the post exactly despite
# rounding (1e-9 of a 90 m post is 0.1 micrometre).
POST_SNAP_TOLERANCE = 1e-9

TWO_PI_A_M = 2.0 * math.pi * WGS84_A_M


@dataclass(frozen=True)
class Georef:
    """Where the posts of a raster are.

    Post (row r, col c) lies at x = x0 + c * dx, y = y0 + r * dy with dx, dy > 0,
    x, y in the units of ``crs`` (degrees for EPSG:4326, metres for EPSG:3857).
    """

    crs: int
    x0: float
    y0: float
    dx: float
    dy: float

    def __post_init__(self):
        if self.crs not in CRS_NAMES:
            raise ValueError(f"crs must be one of {sorted(CRS_NAMES)}, got {self.crs!r}")
        for name in ("x0", "y0", "dx", "dy"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Georef.{name} must be finite, got {getattr(self, name)!r}")
        if not (self.dx > 0 and self.dy > 0):
            raise ValueError(f"Georef spacing must be positive, got dx={self.dx}, dy={self.dy}")

    @property
    def crs_name(self) -> str:
        return CRS_NAMES[self.crs]

    def post_xy(self, rows, cols):
        """Native (x, y) of posts at (rows, cols); arrays broadcast."""
        return (self.x0 + np.asarray(cols, np.float64) * self.dx,
                self.y0 + np.asarray(rows, np.float64) * self.dy)


@numba.njit(cache=True, nogil=True)
def normals_from_gradients(de, dn, normal_out, slope_out):
    """Unit (east, north, up) normals (n, 3) and slopes (degrees, (n,)) of a surface whose
    gradients are de = dh/d(east metre), dn = dh/d(north metre) (n,): the normal of the plane
    h = de e + dn n is (-de, -dn, 1) / |(-de, -dn, 1)|, the slope atan(hypot(de, dn)). NaN
    gradients give NaN. One pass: the numpy composition it replaces (stack, norm, divide,
    hypot, arctan, degrees) took 4.4 ms over 100k points, mostly temporaries."""
    for i in range(de.shape[0]):
        x, y = -de[i], -dn[i]
        norm = math.sqrt(x * x + y * y + 1.0)
        normal_out[i, 0] = x / norm
        normal_out[i, 1] = y / norm
        normal_out[i, 2] = 1.0 / norm
        slope_out[i] = math.degrees(math.atan(math.hypot(de[i], dn[i])))


@numba.njit(cache=True, nogil=True)
def _snap(v):
    r = math.floor(v + 0.5)
    if abs(v - r) < POST_SNAP_TOLERANCE:
        return r
    return v


@numba.njit(cache=True, nogil=True)
def fractional_index(lat, lon, crs, x0, y0, dx, dy):
    """(lat, lon) degrees -> (row, col) as floats in the raster's index space.

    Longitude wraps: x is taken east of x0 modulo a full turn, so a raster that
    crosses the antimeridian answers for both -179.9 and 180.1.
    """
    if crs == CRS_GEOGRAPHIC:
        return _index_of(lon, lat, 360.0, x0, y0, dx, dy)
    return _index_of(WGS84_A_M * math.radians(lon), _mercator_y(lat), TWO_PI_A_M, x0, y0, dx, dy)


@numba.njit(cache=True, nogil=True)
def _mercator_y(lat):
    """EPSG:3857 northing (m) of a latitude (degrees): y = a ln tan(pi/4 + lat/2) (IOGP
    Guidance Note 7-2, Popular Visualisation Pseudo-Mercator), NaN beyond
    WEB_MERCATOR_MAX_LAT_DEG."""
    clat = min(max(lat, -WEB_MERCATOR_MAX_LAT_DEG), WEB_MERCATOR_MAX_LAT_DEG)
    if clat != lat:
        return math.nan
    return WGS84_A_M * math.log(math.tan(math.pi / 4.0 + math.radians(clat) / 2.0))


@numba.njit(cache=True, nogil=True)
def fractional_index_tab(lat, lon, crs, x0, y0, dx, dy, ytab):
    """:func:`fractional_index` with a Web Mercator raster's row read from its table
    (:func:`mercator_row_table`; empty: computed) where the latitude lies in it: what the
    raster's own kernels use, about 3.6 ns a point against 23.5 for the logarithm and
    tangent, and as accurate (tests/test_raster.py)."""
    if crs == CRS_GEOGRAPHIC:
        return _index_of(lon, lat, 360.0, x0, y0, dx, dy)
    x = WGS84_A_M * math.radians(lon)
    if ytab.shape[0] >= 6:  # a table (two nodes at least)
        u = (lat - ytab[0]) * ytab[1]
        if u >= 0.0 and u < (ytab.shape[0] - 2) // 2 - 1.0:  # within it (not NaN)
            i = int(u)
            t = u - i
            t2 = t * t
            t3 = t2 * t
            k = 2 + 2 * i
            # The cubic Hermite basis (h00, h10, h01, h11) on the unit interval.
            row = ((2.0 * t3 - 3.0 * t2 + 1.0) * ytab[k] + (t3 - 2.0 * t2 + t) * ytab[k + 1]
                   + (3.0 * t2 - 2.0 * t3) * ytab[k + 2] + (t3 - t2) * ytab[k + 3])
            return _snap(row), _column_of(x, TWO_PI_A_M, x0, dx)
    return _index_of(x, _mercator_y(lat), TWO_PI_A_M, x0, y0, dx, dy)  # no table, or beyond it: computed


@numba.njit(cache=True, nogil=True)
def _index_of(x, y, turn, x0, y0, dx, dy):
    """(row, col) of a point at (x, y) in the raster's CRS, x wrapped modulo ``turn``."""
    return _snap((y - y0) / dy), _column_of(x, turn, x0, dx)


@numba.njit(cache=True, nogil=True)
def _column_of(x, turn, x0, dx):
    """The fractional column of easting (or longitude) x, wrapped modulo ``turn``."""
    d = x - x0
    # Only wrapped longitudes pay for the modulo. A hair below a full turn is the
    # origin's column too, whether d got there by the modulo or by rounding alone
    # (x0 + 360 - x0 may round just below 360, and a * radians(lon + 360) - x0
    # below 2 pi a at every west-edge post of a Web Mercator raster).
    if d < 0.0 or turn - d < POST_SNAP_TOLERANCE * dx:
        d = d % turn
        if turn - d < POST_SNAP_TOLERANCE * dx:
            d -= turn
    return _snap(d / dx)


@numba.njit(cache=True, nogil=True)
def _cell(v, n):
    """Cell index and fraction for a fractional index v in [0, n - 1]."""
    i = int(math.floor(v))
    if i >= n - 1:
        i = n - 2
    return i, v - i


@numba.njit(cache=True, nogil=True, inline="always")
def _weighted_corners(i, fy, j, fx):
    """(i0, i1, j0, j1): the rows and columns of cell (i, j)'s corners at fractions (fy, fx),
    a corner of zero weight replaced by its neighbour across the cell (so it is not read)."""
    return (i + 1 if fy == 1.0 else i), (i if fy == 0.0 else i + 1), (j + 1 if fx == 1.0 else j), \
        (j if fx == 0.0 else j + 1)


@numba.njit(cache=True, nogil=True)
def _bilinear_value(heights, filled, has_filled, r, c):
    """(height, status) of one point at fractional index (r, c), the careful way: edges,
    holes, filled voids; (NaN, STATUS_OUTSIDE) where this raster has no answer."""
    ny, nx = heights.shape
    if not (r >= 0.0 and r <= ny - 1 and c >= 0.0 and c <= nx - 1):
        return np.nan, STATUS_OUTSIDE
    i, fy = _cell(r, ny)
    j, fx = _cell(c, nx)
    # Corners of zero weight are not read, so a post beside a hole or a
    # filled void keeps its own value and status.
    i0, i1, j0, j1 = _weighted_corners(i, fy, j, fx)
    h00 = np.float64(heights[i0, j0])
    h01 = np.float64(heights[i0, j1])
    h10 = np.float64(heights[i1, j0])
    h11 = np.float64(heights[i1, j1])
    south = h00 * (1.0 - fx) + h01 * fx
    north = h10 * (1.0 - fx) + h11 * fx
    h = south * (1.0 - fy) + north * fy
    if h != h:  # a NaN post is a hole in coverage: left to the next source
        return np.nan, STATUS_OUTSIDE
    if has_filled and (filled[i0, j0] | filled[i0, j1] | filled[i1, j0] | filled[i1, j1]):
        return h, STATUS_FILLED
    return h, STATUS_OK


@numba.njit(cache=True, nogil=True)
def _bilinear_point(heights, filled, has_filled, r, c, out_h, out_status, k):
    """:func:`_bilinear_value` into out_h[k], out_status[k], where it has an answer."""
    h, status = _bilinear_value(heights, filled, has_filled, r, c)
    if status != STATUS_OUTSIDE:
        out_h[k] = h
        out_status[k] = status


@numba.njit(cache=True, nogil=True)
def bilinear_one(heights, filled, lat, lon, crs, x0, y0, dx, dy, ytab):
    """The height of one point (lat, lon degrees) as :func:`bilinear_into` answers it (the
    same snap, wrap and careful path, so bit for bit), NaN where the raster has none. One
    call with scalars: what a host asking one point now and then pays for least, its
    caches cold after the rest of its work (an aircraft's refresh far from the ground)."""
    r, c = fractional_index_tab(lat, lon, crs, x0, y0, dx, dy, ytab)
    return _bilinear_value(heights, filled, filled.shape[0] > 0, r, c)[0]


# Points per chunk of the fast path: its scratch arrays stay in L1.
_CHUNK = 1024

# Raster.warm_cache: the largest raster (posts plus filled flags, bytes) worth
# streaming into the CPU caches; a larger one would not stay there.
WARM_MAX_BYTES = 16 * 1024 * 1024
CACHE_LINE_BYTES = 64


@numba.njit(cache=True, nogil=True)
def _touch_lines(raw, step):
    """Read one byte every ``step`` bytes of raw (uint8 (n,)): brings every cache
    line of the array into the caches at streaming speed. Returns a checksum,
    only so that the reads cannot be optimised away."""
    acc = 0
    for i in range(0, raw.shape[0], step):
        acc += raw[i]
    return acc


@numba.njit(cache=True, nogil=True)
def bilinear_into(heights, filled, lat, lon, crs, x0, y0, dx, dy, ytab, out_h, out_status):
    """Fill out_h/out_status for points whose status is still STATUS_OUTSIDE.

    heights: (ny, nx) float32/float64 posts, NaN where no data; filled: (ny, nx) uint8, 1 where a
    void was filled (or shape (0, 0) when none were). Points already answered
    by a higher-priority raster are left alone. Exact at posts: the lerp form
    returns the post value bit for bit when both fractions are 0 or 1.

    Two paths giving identical results: a branch-free chunked one for points
    strictly inside the grid (index arithmetic, then gathers; both loops
    vectorise), and :func:`_bilinear_point` for the rest -- wrapped longitudes,
    the last row and column, holes and filled voids. Measured on 1M uniform
    random points it runs in about 0.55x the time of the per-point loop alone.
    """
    ny, nx = heights.shape
    has_filled = filled.shape[0] > 0
    flat_h = heights.ravel()
    flat_f = filled.ravel()
    n = lat.shape[0]
    q_buf = np.empty(_CHUNK, np.int64)
    fy_buf = np.empty(_CHUNK)
    fx_buf = np.empty(_CHUNK)
    r_buf = np.empty(_CHUNK)
    c_buf = np.empty(_CHUNK)
    v_buf = np.empty(_CHUNK)
    fast = np.empty(_CHUNK, np.bool_)
    # Strictly inside, so that snapping up never reaches the last row/column.
    r_max = ny - 1.0 - 2.0 * POST_SNAP_TOLERANCE
    c_max = nx - 1.0 - 2.0 * POST_SNAP_TOLERANCE
    for s in range(0, n, _CHUNK):
        m = min(_CHUNK, n - s)
        if crs == CRS_GEOGRAPHIC:
            for t in range(m):
                r_buf[t] = (lat[s + t] - y0) / dy
                c_buf[t] = (lon[s + t] - x0) / dx
        else:
            for t in range(m):
                r_buf[t], c_buf[t] = fractional_index_tab(lat[s + t], lon[s + t], crs, x0, y0, dx, dy, ytab)
        for t in range(m):
            r = r_buf[t]
            c = c_buf[t]
            inside = (r >= 0.0) & (r <= r_max) & (c >= 0.0) & (c <= c_max)
            # The snap of fractional_index, as selects: within the tolerance of
            # a post the fraction is exactly 0.
            fi = math.floor(r)
            fy = r - fi
            up = fy > 1.0 - POST_SNAP_TOLERANCE
            fi = fi + 1.0 if up else fi
            fy = 0.0 if (up | (fy < POST_SNAP_TOLERANCE)) else fy
            fj = math.floor(c)
            fx = c - fj
            up = fx > 1.0 - POST_SNAP_TOLERANCE
            fj = fj + 1.0 if up else fj
            fx = 0.0 if (up | (fx < POST_SNAP_TOLERANCE)) else fx
            q_buf[t] = int(fi) * nx + int(fj) if inside else 0
            fy_buf[t] = fy
            fx_buf[t] = fx
            fast[t] = inside
        for t in range(m):
            q = q_buf[t]
            fx = fx_buf[t]
            fy = fy_buf[t]
            h00 = np.float64(flat_h[q])
            h01 = np.float64(flat_h[q + 1])
            h10 = np.float64(flat_h[q + nx])
            h11 = np.float64(flat_h[q + nx + 1])
            v_buf[t] = (h00 * (1.0 - fx) + h01 * fx) * (1.0 - fy) + (h10 * (1.0 - fx) + h11 * fx) * fy
        for t in range(m):
            k = s + t
            if out_status[k] != STATUS_OUTSIDE:
                continue
            v = v_buf[t]
            good = fast[t] and v == v
            if good and has_filled:
                q = q_buf[t]
                good = (flat_f[q] | flat_f[q + 1] | flat_f[q + nx] | flat_f[q + nx + 1]) == 0
            if good:
                out_h[k] = v
                out_status[k] = STATUS_OK
            else:
                r = r_buf[t]
                c = c_buf[t]
                if crs == CRS_GEOGRAPHIC:  # redo with the wrap and snap of fractional_index
                    r, c = fractional_index_tab(lat[k], lon[k], crs, x0, y0, dx, dy, ytab)
                _bilinear_point(heights, filled, has_filled, r, c, out_h, out_status, k)


@numba.njit(cache=True, nogil=True)
def _filled_status(filled, r, c):
    """STATUS_FILLED when a post of non-zero weight at fractional index (r, c) (inside the grid)
    is a filled void, else STATUS_OK: the status :func:`_bilinear_value` gives a point it covers,
    so a slope and a height at one point carry the same status."""
    if filled.shape[0] == 0:
        return STATUS_OK
    ny, nx = filled.shape
    i, fy = _cell(r, ny)
    j, fx = _cell(c, nx)
    i0, i1, j0, j1 = _weighted_corners(i, fy, j, fx)
    if filled[i0, j0] | filled[i0, j1] | filled[i1, j0] | filled[i1, j1]:
        return STATUS_FILLED
    return STATUS_OK


@numba.njit(cache=True, nogil=True)
def gradient_into(heights, filled, lat, lon, crs, x0, y0, dx, dy, ytab, periodic, out_dcol, out_drow, out_status):
    """Partial derivatives of the bilinear surface in index units (m per post).

    Found wherever :func:`bilinear_into` has a height (:func:`_gradient_value`: on a cell edge
    the cell to the north-east, the last cell at the far edges, unless a hole beside the edge
    leaves it a post the height does not read). periodic: the columns a turn holds when the
    raster's columns wrap (:attr:`Raster.columns_per_turn`), else 0. filled as for
    :func:`bilinear_into`; the status is the one bilinear_into gives the point (FILLED where a
    post of non-zero weight is a filled void), so :class:`terrain.terrain.Terrain` can answer a
    filled point's slope from a measured source, as it does its height.
    """
    for k in range(lat.shape[0]):
        if out_status[k] != STATUS_OUTSIDE:
            continue
        r, c = fractional_index_tab(lat[k], lon[k], crs, x0, y0, dx, dy, ytab)
        dcol, drow, found = _cell_gradient(heights, r, c)
        if not found:  # a hole's post in the cell; called apart, as inlined it slowed this loop by half
            dcol, drow, found = _rim_gradient(heights, r, c, periodic)
        if found:
            out_dcol[k] = dcol
            out_drow[k] = drow
            out_status[k] = _filled_status(filled, r, c)


@numba.njit(cache=True, nogil=True)
def _grid_indices(lat_rows, lon_cols, crs, x0, y0, dx, dy, ytab):
    """(row index of each latitude, column index of each longitude): fractional_index is
    separable (y from the latitude alone, x from the longitude alone), so a lattice of rows x
    columns needs rows + columns of them, each what the point's own call gives."""
    rr = np.empty(lat_rows.shape[0])
    cc = np.empty(lon_cols.shape[0])
    for i in range(lat_rows.shape[0]):
        rr[i] = fractional_index_tab(lat_rows[i], lon_cols[0], crs, x0, y0, dx, dy, ytab)[0]
    for j in range(lon_cols.shape[0]):
        cc[j] = fractional_index_tab(lat_rows[0], lon_cols[j], crs, x0, y0, dx, dy, ytab)[1]
    return rr, cc


@numba.njit(cache=True, nogil=True)
def bilinear_grid_into(heights, filled, lat_rows, lon_cols, crs, x0, y0, dx, dy, ytab, out_h, out_status):
    """:func:`bilinear_into` over the lattice lat_rows x lon_cols (out_h, out_status (rows,
    cols)): the same answer at each point, bit for bit, with one index per row and column."""
    rr, cc = _grid_indices(lat_rows, lon_cols, crs, x0, y0, dx, dy, ytab)
    has_filled = filled.shape[0] > 0
    for i in range(rr.shape[0]):
        for j in range(cc.shape[0]):
            if out_status[i, j] == STATUS_OUTSIDE:
                h, status = _bilinear_value(heights, filled, has_filled, rr[i], cc[j])
                if status != STATUS_OUTSIDE:
                    out_h[i, j] = h
                    out_status[i, j] = status


@numba.njit(cache=True, nogil=True, inline="always")
def _side_slope(a0, b0, a1, b1, w):
    """(b0 - a0) (1 - w) + (b1 - a1) w: a cell's derivative across one axis from its posts a (before)
    and b (after) on its two lines along the other axis, the second line at weight w."""
    return (b0 - a0) * (1.0 - w) + (b1 - a1) * w


@numba.njit(cache=True, nogil=True)
def _cell_gradient(heights, r, c):
    """(d/dcol, d/drow, found) at fractional index (r, c) from its cell as :func:`gradient_into`
    takes it (the north-east one on an edge, the last cell at the far edges) when that cell's four
    posts are finite; else not found (:func:`_rim_gradient` answers there)."""
    ny, nx = heights.shape
    if not (r >= 0.0 and r <= ny - 1 and c >= 0.0 and c <= nx - 1):
        return 0.0, 0.0, False
    i, fy = _cell(r, ny)
    j, fx = _cell(c, nx)
    h00 = np.float64(heights[i, j])
    h01 = np.float64(heights[i, j + 1])
    h10 = np.float64(heights[i + 1, j])
    h11 = np.float64(heights[i + 1, j + 1])
    if (h00 + h01 + h10 + h11) != (h00 + h01 + h10 + h11):
        return 0.0, 0.0, False
    return (h01 - h00) * (1.0 - fy) + (h11 - h10) * fy, (h10 - h00) * (1.0 - fx) + (h11 - h01) * fx, True


@numba.njit(cache=True, nogil=True)
def _rim_gradient(heights, r, c, periodic):
    """(d/dcol, d/drow, found) at fractional index (r, c) whose cell has a NaN post: found where
    :func:`_bilinear_value` has a height (every post of non-zero weight finite), so a point on an
    edge or a post beside a hole gets this raster's slope, as it gets its height.

    Each partial derivative is the cell's with its posts of zero weight unread (so on a post
    line, the line's own posts along it); across a line the point lies on (fx or fy 0), where
    the cell lacks a post that derivative reads, the cell's on the other side of the line
    (west, south; the columns wrap where ``periodic``, as for :func:`gradient_into`); where
    neither side has them the raster holds only the line or the post there, and the slope
    across it is 0 (the data say nothing of it)."""
    ny, nx = heights.shape
    if not (r >= 0.0 and r <= ny - 1 and c >= 0.0 and c <= nx - 1):
        return 0.0, 0.0, False
    i, fy = _cell(r, ny)
    j, fx = _cell(c, nx)
    i0, i1, j0, j1 = _weighted_corners(i, fy, j, fx)
    weighted = (np.float64(heights[i0, j0]) + np.float64(heights[i0, j1]) + np.float64(heights[i1, j0])
                + np.float64(heights[i1, j1]))
    if weighted != weighted:
        return 0.0, 0.0, False
    dcol = _side_slope(np.float64(heights[i0, j]), np.float64(heights[i0, j + 1]), np.float64(heights[i1, j]),
                       np.float64(heights[i1, j + 1]), fy)
    west = j - 1 if j > 0 else (periodic - 1 if periodic else -1)
    if dcol != dcol and fx == 0.0 and west >= 0:
        dcol = _side_slope(np.float64(heights[i0, west]), np.float64(heights[i0, j]), np.float64(heights[i1, west]),
                           np.float64(heights[i1, j]), fy)
    drow = _side_slope(np.float64(heights[i, j0]), np.float64(heights[i + 1, j0]), np.float64(heights[i, j1]),
                       np.float64(heights[i + 1, j1]), fx)
    if drow != drow and fy == 0.0 and i > 0:
        drow = _side_slope(np.float64(heights[i - 1, j0]), np.float64(heights[i, j0]), np.float64(heights[i - 1, j1]),
                           np.float64(heights[i, j1]), fx)
    return (dcol if dcol == dcol else 0.0), (drow if drow == drow else 0.0), True


@numba.njit(cache=True, nogil=True)
def _gradient_value(heights, r, c, periodic):
    """(d/dcol, d/drow, found) of the bilinear surface at fractional index (r, c), found wherever
    :func:`_bilinear_value` has a height: :func:`_cell_gradient`, else :func:`_rim_gradient`."""
    dcol, drow, found = _cell_gradient(heights, r, c)
    if found:
        return dcol, drow, found
    return _rim_gradient(heights, r, c, periodic)


@numba.njit(cache=True, nogil=True)
def gradient_grid_into(heights, filled, lat_rows, lon_cols, crs, x0, y0, dx, dy, ytab, periodic, mx_rows, my_rows,
                       out_de, out_dn, out_status):
    """Raster.gradient_into over the lattice lat_rows x lon_cols, with each row's metres per
    column and per row step (mx_rows, my_rows: :func:`metres_per_index` of lat_rows) given:
    the same slopes and statuses, bit for bit, for the points still OUTSIDE."""
    rr, cc = _grid_indices(lat_rows, lon_cols, crs, x0, y0, dx, dy, ytab)
    for i in range(rr.shape[0]):
        for j in range(cc.shape[0]):
            if out_status[i, j] == STATUS_OUTSIDE:
                dcol, drow, found = _cell_gradient(heights, rr[i], cc[j])
                if not found:
                    dcol, drow, found = _rim_gradient(heights, rr[i], cc[j], periodic)
                if found:
                    out_de[i, j] = dcol / mx_rows[i]
                    out_dn[i, j] = drow / my_rows[i]
                    out_status[i, j] = _filled_status(filled, rr[i], cc[j])


def grid_bounds(georef: Georef, shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """(lat_min, lon_min, lat_max, lon_max) degrees of the outermost posts of a grid.

    lon_max may exceed 180 for a grid that crosses the antimeridian.
    """
    from terrain.geodesy import web_mercator_inverse

    ny, nx = shape
    x1, y1 = georef.post_xy(ny - 1, nx - 1)
    if georef.crs == CRS_GEOGRAPHIC:
        return (georef.y0, georef.x0, float(y1), float(x1))
    lat0, lon0 = web_mercator_inverse(georef.x0, georef.y0)
    lat1, lon1 = web_mercator_inverse(x1, y1)
    return (float(lat0), float(lon0), float(lat1), float(lon1))


def metres_per_index(crs: int, dx: float, dy: float, lat_deg):
    """Ground metres per column step (east) and per row step (north) at lat."""
    m, n = radii_of_curvature(lat_deg)
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    if crs == CRS_GEOGRAPHIC:
        return np.radians(dx) * n * np.cos(lat), np.radians(dy) * m
    # EPSG:3857: x = a*lon, y = a*ln tan(pi/4 + lat/2) => dlon = dx/a, dlat = cos(lat) dy/a.
    return dx / WGS84_A_M * n * np.cos(lat), dy / WGS84_A_M * np.cos(lat) * m


# The row table's interpolation error bound, in rows (a tenth of POST_SNAP_TOLERANCE, so that a
# post's latitude still snaps to its row), and the most nodes a table may have (a raster that
# would need more is projected point by point).
MERCATOR_TABLE_TOLERANCE_ROWS = 1e-10
MERCATOR_TABLE_MAX_NODES = 1 << 20


def mercator_row_table(georef: Georef, rows: int) -> np.ndarray:
    """The table :func:`fractional_index_tab` reads a Web Mercator raster's fractional rows
    from, over its rows' latitudes and two nodes beyond (clipped to WEB_MERCATOR_MAX_LAT_DEG):
    [lat0, 1 / h, r_0, h r'_0, r_1, h r'_1, ...], nodes every h degrees from lat0, r = (y -
    y0) / dy the row of latitude lat0 + i h and r' its derivative in rows per degree. Empty for
    a geographic raster, or one that would need more than MERCATOR_TABLE_MAX_NODES.

    y(phi) = a gd^-1(phi) = a ln tan(pi/4 + phi/2) (IOGP Guidance Note 7-2, Popular
    Visualisation Pseudo-Mercator); cubic Hermite interpolation between nodes h radians apart
    errs by at most h^4 / 384 max|y^(4)| (de Boor, A Practical Guide to Splines, ch. IV), with
    gd^-1 (4) = sec tan (tan^2 + 5 sec^2), largest at the table's highest |latitude|: h is
    chosen so that this bound is MERCATOR_TABLE_TOLERANCE_ROWS. The nodes are computed in long
    double and kept as rows (hundreds, not the 1e7 m of a northing), so the table's rounding is
    far below the float64 formula's own (its logarithm of a rounded tangent)."""
    if georef.crs != CRS_WEB_MERCATOR:
        return np.zeros(0)
    from terrain.geodesy import web_mercator_inverse

    lat_a = float(web_mercator_inverse(0.0, georef.y0)[0])
    lat_b = float(web_mercator_inverse(0.0, georef.y0 + (rows - 1) * georef.dy)[0])
    top = min(max(abs(lat_a), abs(lat_b)) + 1e-3, WEB_MERCATOR_MAX_LAT_DEG)
    phi = math.radians(top)
    sec, tan = 1.0 / math.cos(phi), math.tan(phi)
    d4 = WGS84_A_M * max(sec * tan * (tan * tan + 5.0 * sec * sec), 1.0)
    h = math.degrees((384.0 * MERCATOR_TABLE_TOLERANCE_ROWS * georef.dy / d4) ** 0.25)
    lo = max(lat_a - 2.0 * h, -WEB_MERCATOR_MAX_LAT_DEG)
    hi = min(lat_b + 2.0 * h, WEB_MERCATOR_MAX_LAT_DEG)
    nodes = int(math.ceil((hi - lo) / h)) + 1
    if not 2 <= nodes <= MERCATOR_TABLE_MAX_NODES:
        return np.zeros(0)
    ld = np.longdouble
    rad = np.radians(ld(lo) + ld(h) * np.arange(nodes, dtype=ld))
    a = ld(WGS84_A_M)
    out = np.empty(2 + 2 * nodes)
    out[0], out[1] = lo, 1.0 / h
    out[2::2] = (a * np.log(np.tan(np.pi / ld(4) + rad / 2)) - ld(georef.y0)) / ld(georef.dy)
    out[3::2] = ld(h) * a * np.radians(ld(1)) / np.cos(rad) / ld(georef.dy)
    return out


@dataclass(eq=False)
class Raster:
    """Height posts on a georeferenced grid; row 0 south, column 0 west.

    heights: (ny, nx) float32 or float64, metres above ``vertical_datum``; NaN
    only where a void could not be filled. filled: (ny, nx) bool, True where
    the post is a filled void, or None when the source had none.
    """

    heights: np.ndarray
    georef: Georef
    name: str = "raster"
    vertical_datum: str = "EGM96 geoid (mean sea level)"
    filled: np.ndarray | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        h = np.asarray(self.heights)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"heights must be (ny>=2, nx>=2), got shape {h.shape}")
        if h.dtype not in (np.float32, np.float64):
            raise ValueError(f"heights must be float32 or float64, got {h.dtype}")
        h = np.ascontiguousarray(h)
        h.flags.writeable = False
        self.heights = h
        if self.filled is not None:
            f = np.ascontiguousarray(self.filled, dtype=np.uint8)
            if f.shape != h.shape:
                raise ValueError(f"filled must have shape {h.shape}, got {f.shape}")
            f.flags.writeable = False
            self.filled = f if f.any() else None

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    @cached_property
    def _filled_arg(self) -> np.ndarray:
        return self.filled if self.filled is not None else np.zeros((0, 0), np.uint8)

    @cached_property
    def _ytab(self) -> np.ndarray:
        """The row table of a Web Mercator raster's kernels (:func:`mercator_row_table`)."""
        return mercator_row_table(self.georef, self.shape[0])

    @cached_property
    def pyramid(self):
        """Min/max pyramid of the bilinear surface (:mod:`terrain.pyramid`), built on first use."""
        from terrain.pyramid import build_pyramid

        return build_pyramid(self.heights, self.filled)

    @cached_property
    def columns_per_turn(self) -> int:
        """The columns a full turn of longitude holds when this raster's columns wrap, else 0.

        They wrap when a turn is a whole number of cells (to 1e-9 of a turn) and the raster spans
        that turn or more: its columns past the first turn repeat the first ones (a GeoTIFF from
        -180.05 to 180.05, a store's all-longitude raster of a turn and two posts), so the column
        west of column 0 is column columns_per_turn - 1 (the slope on column 0, the ray walk)."""
        g = self.georef
        period = (360.0 if g.crs == CRS_GEOGRAPHIC else TWO_PI_A_M) / g.dx
        whole = round(period)
        return whole if abs(period - whole) <= 1.0e-9 * period and self.shape[1] - 1 >= whole else 0

    @cached_property
    def height_range_m(self) -> tuple[float, float] | None:
        """(lowest, highest) post height in metres (the bilinear surface stays between them;
        None when no post has data)."""
        if not np.isfinite(self.heights).any():
            return None
        return float(np.nanmin(self.heights)), float(np.nanmax(self.heights))

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(lat_min, lon_min, lat_max, lon_max) in degrees of the outermost posts."""
        return grid_bounds(self.georef, self.shape)

    @cached_property
    def post_spacing_m(self) -> tuple[float, float]:
        """Ground spacing (east, north) in metres at the raster's centre latitude."""
        lat_c = 0.5 * (self.bounds[0] + self.bounds[2])
        ex, ny_ = metres_per_index(self.georef.crs, self.georef.dx, self.georef.dy, lat_c)
        return float(ex), float(ny_)

    def warm_cache(self, n_points: int) -> bool:
        """Stream the posts into the CPU caches ahead of a batch of n_points, when worth it.

        A batch of uniformly spread points reads two rows per point at random:
        on a cold cache (as in a service, whose caches the transfer of the
        request and the time between calls have flushed) each of those reads
        is a miss waiting on memory, while one sequential pass brings the whole
        raster in at streaming speed. The pass is made when the batch touches
        about as many cache lines as the raster has (2 * n_points >= lines)
        and the raster fits WARM_MAX_BYTES; for a 1201² float32 tile it takes
        about 0.2 ms, what some 15,000 points cost warm. Results never depend
        on it. Returns whether it was made.
        """
        arrays = [self.heights] if self.filled is None else [self.heights, self.filled]
        nbytes = sum(a.nbytes for a in arrays)
        if nbytes > WARM_MAX_BYTES or 2 * n_points < self.heights.nbytes // CACHE_LINE_BYTES:
            return False
        for a in arrays:
            _touch_lines(a.reshape(-1).view(np.uint8), CACHE_LINE_BYTES)
        return True

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        """Answer the points of lat/lon (float64 (n,)) still marked OUTSIDE."""
        g = self.georef
        bilinear_into(self.heights, self._filled_arg, lat, lon, g.crs, g.x0, g.y0, g.dx, g.dy, self._ytab,
                      out_h, out_status)

    def height_at(self, lat: float, lon: float) -> float:
        """The height at one valid point (lat, lon degrees), NaN where this raster has none:
        what :meth:`heights_into` answers for it, bit for bit (:func:`bilinear_one`)."""
        g = self.georef
        return bilinear_one(self.heights, self._filled_arg, lat, lon, g.crs, g.x0, g.y0, g.dx, g.dy, self._ytab)

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        """Surface slope dh/d(east metre), dh/d(north metre) for points still OUTSIDE; status
        as :meth:`heights_into` gives it (FILLED on a filled void)."""
        g = self.georef
        todo = out_status == STATUS_OUTSIDE
        dcol = np.zeros(lat.shape[0])
        drow = np.zeros(lat.shape[0])
        st = out_status.copy()
        gradient_into(self.heights, self._filled_arg, lat, lon, g.crs, g.x0, g.y0, g.dx, g.dy, self._ytab,
                      self.columns_per_turn,
                      dcol, drow, st)
        hit = todo & (st != STATUS_OUTSIDE)
        if hit.any():
            mx, my = metres_per_index(g.crs, g.dx, g.dy, lat[hit])
            out_de[hit] = dcol[hit] / mx
            out_dn[hit] = drow[hit] / my
            out_status[hit] = st[hit]

    def grid_heights_into(self, lat_rows, lon_cols, out_h, out_status) -> None:
        """:meth:`heights_into` over the lattice lat_rows x lon_cols (float64 (rows,), (cols,);
        out_h, out_status (rows, cols)): the same answers, one index per row and column."""
        g = self.georef
        bilinear_grid_into(self.heights, self._filled_arg, lat_rows, lon_cols, g.crs, g.x0, g.y0, g.dx, g.dy,
                           self._ytab,
                           out_h, out_status)

    def grid_gradient_into(self, lat_rows, lon_cols, out_de, out_dn, out_status) -> None:
        """:meth:`gradient_into` over the lattice lat_rows x lon_cols (outputs (rows, cols))."""
        g = self.georef
        mx, my = metres_per_index(g.crs, g.dx, g.dy, lat_rows)
        gradient_grid_into(self.heights, self._filled_arg, lat_rows, lon_cols, g.crs, g.x0, g.y0, g.dx, g.dy,
                           self._ytab,
                           self.columns_per_turn, np.ascontiguousarray(mx, np.float64),
                           np.ascontiguousarray(my, np.float64), out_de, out_dn, out_status)

    def raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float):
        """This raster if it covers the box (degrees) entirely, else None."""
        lat0, lon0, lat1, lon1 = self.bounds
        lon_span = lon1 - lon0
        west = (lon_min - lon0) % 360.0
        east = west + (lon_max - lon_min)
        if lat_min >= lat0 and lat_max <= lat1 and east <= lon_span:
            return self
        return None

    def describe(self) -> dict:
        """Metadata for services and tools (bounds in degrees, spacing in metres)."""
        lat0, lon0, lat1, lon1 = self.bounds
        sx, sy = self.post_spacing_m
        return {
            "name": self.name,
            "kind": "dem",
            "source": self.source,
            "crs": self.georef.crs_name,
            "lat_min": lat0, "lon_min": lon0, "lat_max": lat1, "lon_max": lon1,
            "rows": self.shape[0], "cols": self.shape[1],
            "spacing_east_m": sx, "spacing_north_m": sy,
            "vertical_datum": self.vertical_datum,
            "filled_posts": int(self.filled.sum()) if self.filled is not None else 0,
        }
