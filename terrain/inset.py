"""Target-area insets: high-detail height data over a polygon, one source for server and renderer.

Issue #5 ("Geomipmap inset for target areas") and thesis §3.3.1: the clipmap
is used "in areas of low visual interest", the geomipmap (de Boer 2000) in
"important areas, for instance target areas", combined "by simply cutting out
an area in the height map used by the clipmap ... We smooth the borders of the
cut out area ... the clipmap method will still produce geometry in this area
of interest, but it will be below the geometry of the geomipmap method".
An :class:`InsetSource` is that area's height data. It is a height source of
:class:`terrain.terrain.Terrain` (answering inside the polygon, NaN outside so
the next source answers), so the terrain service, the world's collision checks
and the renderer read the same numbers: what is drawn and what collides agree.

The lattice
-----------
Posts lie on a regular lat/lon lattice that refines the lattice of the DEM
beneath (the first EPSG:4326 source covering the area: its rows and columns,
or the procedural world's global lattice) by a power of two per axis,
2^Ky rows and 2^Kx columns per DEM post, the least making the spacing at most
``detail_m`` (0.5 ``detail_m`` < spacing <= ``detail_m``; the Alps tile at
47.25 N, ``detail_m`` = 5: 2.89 m north, 3.94 m east). Being aligned, the
bilinear surface of the DEM sampled at these posts and interpolated again is
the DEM's bilinear surface itself (a bilinear patch is bilinear on any
aligned sub-grid), so without detail the inset *is* the DEM, not a resampled
approximation of it. It spans the polygon's bounding box plus
``INSET_MARGIN_CELLS``, rounded up so that rows - 1 and cols - 1 are
multiples of ``INSET_BLOCK_CELLS`` (64): geomipmap patches of 2^k + 1 posts,
k <= 6, tile it. A DEM in another CRS (Web Mercator) gets a lattice of its
spacing at the area's latitude, which is not aligned: the inset is then the
DEM resampled (bilinear of bilinear, off by at most the slope change across a
DEM post times a quarter of the inset spacing).

Heights
-------
h(post) = b(post) + w(s) d(post), where

* b is the terrain beneath at the post (its bilinear surface, exact there);
* d is fractal detail below the DEM's post spacing, thesis §3.1.9 as in
  :mod:`terrain.detail`: per sub-level k = 1..K (lattice spacing 2^-k DEM
  posts, K = min(Kx, Ky) so every level's lattice is a sub-lattice of the
  inset's) bilinear Gaussian noise of standard deviation sigma_k, fitted to the
  log-linear decay of the residual variances of the DEM's pyramid over the
  area and ``STATS_MARGIN_POSTS`` posts around it (over land: residuals whose
  posts are all above sea level, as terrain.detail counts them, since the sea
  gets no detail), drawn by a counter hash of (seed, level, global lattice
  row, column) and scaled by terrain.detail.polar_taper: deterministic per
  seed and equal to :class:`terrain.detail.DetailedRaster`'s values there for
  the same sigmas. d is 0 at the DEM's posts. A terrain whose covering source already
  synthesises detail (kind "dem+detail") gets none added (K = 0);
* the sign of b is kept (``keep_sea_level_sign``): where b <= 0 (the sea, as
  SRTM stores it) h = b, and land stays above 1 cm, since land and water are
  told apart by the height's sign (the renderer's colour, the ground vehicles'
  water rule): detail raised land blotches on half the sea posts of a coastal
  area before;
* w(s) = smoothstep(a0, a0 + B, s), s the signed distance (m) of the post
  from the polygon's boundary (positive inside), a0 = sqrt(2) x the DEM's
  larger post spacing (``detail_offset_m``; 131 m for 3" SRTM at 47 N),
  B = ``border_band_m``: no detail within a0 of the border, so there the
  inset is the terrain beneath exactly, then the detail fades in over B. Why
  a0: it is where the cut-out of a clipmap level as fine as the DEM starts
  (below), so the clipmap is already lowered wherever the detail can dig.

Bounds (tested): |d| <= A = max|g| sum(sigma_k) (``detail_bound_m``; g the
standard-normal table of :mod:`terrain.detail`, max|g| = 4.3), since each
level is a convex combination of table values; the inset's surface differs
from the DEM's bilinear surface by at most A (aligned lattice); within
a0 - c of the border (c the inset cell's diagonal, 4.9 m on the test area)
it is the DEM's surface, up to the rounding of the posts' coordinates
(1e-6 m): continuous with the terrain beneath. On the Alps test area
A = 68 m: the extrapolated sub-post sigmas are 8.6, 4.2, 2.0, 1.0 m (the
Säntis is the tile's most rugged corner; typical |d| is their root sum of
squares, 9.8 m).

Coverage is the closed polygon (s >= 0), tested exactly per point for points
in cells the border crosses and by a per-cell class elsewhere. Line of sight
and segment intersection trace the whole lattice (an InsetSource is a
:class:`terrain.raster.Raster`, so :class:`terrain.terrain.Terrain` traces each
ray on it and passes the rays that leave it on): outside the polygon, and
up to a0 - c inside it, the lattice's surface is the DEM's own (w = 0 there).
A ray that leaves the lattice goes on over the next sources from where it
leaves (terrain.los.stack_trace), so the inset's detail counts on its way in.

The clipmap's cut-out
---------------------
:meth:`InsetSource.cutout_depth_m` tells the clipmap how far to push its
terrain below the inset: c(s) = D smoothstep(a, a + B, s), with

* a = sqrt(2) x the clipmap level's post spacing g (``clip_spacing_m``): a
  clipmap triangle spans at most one cell diagonal, so a triangle with a
  lowered vertex lies wholly inside the polygon and the linear interpolation
  between posts never dents the terrain outside it (where no inset covers
  it);
* D = A + CUTOUT_MARGIN_M (``cutout_depth_max_m``) and the detail's band B:
  for a level at most as coarse as the DEM (a <= a0) c(s) >= A w(s) + 2 m
  w(s) everywhere, so the clipmap stays under the deepest trough the detail
  can dig; a coarser level (far from the viewer, or near it after a jump
  while the finer levels catch up) is cut less or not at all (level 3 of the
  Alps tile, 741 m posts, not over a 1.6 km wide area), so the cut alone
  would let it show through the troughs in the strip a0 < s < a + B. Deeper
  would buy nothing (the inset hides it all); shallower lets the clipmap show
  through the troughs.
  The ramp is a smoothstep (§3.3.1: "smooth the borders of the cut out area
  ... to prevent sharp edges"); its steepest slope is 1.5 D / B. B = 200 m
  spans two 3" posts, so a clipmap level as fine as the DEM resolves the
  ramp, and keeps that slope at 0.52 for the test area's D = 70 m.

What no cut of posts can do, the renderer does per fragment
(client/render/clipmap_layer.py "Insets"): :meth:`InsetSource.coverage_mask`
is the polygon as a texture of signed distances less a margin e (< a0); a
clipmap fragment where it is > 0 lies surely inside and is pushed far behind
the inset, at every level. Within e of the border, and outside where the
inset's last triangles reach, both are drawn and both are the same surface
(the DEM): the inset is drawn a hair nearer (client/render/geomipmap.py), so
a tie goes to it, and it is shaded as the clipmap, so whichever wins no seam
shows.

Limits: at most ``INSET_MAX_POSTS`` (4096^2, 128 MiB of float64 heights)
posts per inset; ``detail_m`` within [0.25, 100] m as in server/scenario.py.
Argument order is (lat, lon), degrees; heights metres in the datum of the
terrain beneath (MSL for SRTM).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.detail import (SEA_LEVEL_M, detail_noise, fit_sub_level_std, noise_table, pole_rows, polar_taper,
                            pyramid_residual_variance)
from terrain.geodesy import radii_of_curvature
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OUTSIDE, Georef, Raster
from terrain.validate import check_latlon

INSET_MAX_POSTS = 4096 * 4096
INSET_BLOCK_CELLS = 64  # rows - 1 and cols - 1 are multiples of this (patches of up to 65 posts)
INSET_MARGIN_CELLS = 2  # lattice cells beyond the polygon's bounding box, at least
DETAIL_M_RANGE = (0.25, 100.0)  # as server/scenario.py DETAIL_MIN_M, DETAIL_MAX_M
DEFAULT_BORDER_BAND_M = 200.0  # B: detail fade-in and cut-out ramp width
CUTOUT_MARGIN_M = 2.0  # D = detail bound + this
STATS_MARGIN_POSTS = 32  # DEM posts around the area's box whose pyramid residuals fit the detail
MAX_POLYGON_VERTICES = 1000  # as server/scenario.py
ALIGNMENT_TOLERANCE_POSTS = 1e-6  # as terrain/detail.py: an origin this close to a multiple is aligned
DETAIL_TABLE_MAX = float(np.abs(noise_table()).max())  # max |g| of the Gaussian table (4.3)
LAND_FLOOR_M = 0.01  # the lowest height detail leaves a land post at (keep_sea_level_sign)
COVERAGE_MASK_MAX_TEXELS = 512  # a side of InsetSource.coverage_mask's grid, at most
COVERAGE_MASK_MARGIN_TEXELS = math.sqrt(2.0) + 1.0 / 16.0  # e = this x the texel + COVERAGE_MASK_MARGIN_M
COVERAGE_MASK_MARGIN_M = 2.0


def keep_sea_level_sign(below_m, detailed_m) -> np.ndarray:
    """The detailed heights with the sign of the heights beneath: water (<= 0 m MSL, as SRTM
    stores the sea) keeps its own height, land stays above LAND_FLOOR_M (or its own height when
    lower). Land and water are told apart by the height's sign (the renderer's colour, the ground
    vehicles' water rule), so detail must not raise land in the sea nor sink land under it."""
    below_m = np.asarray(below_m, np.float64)
    land = below_m > 0.0
    return np.where(land, np.maximum(detailed_m, np.minimum(below_m, LAND_FLOOR_M)), below_m)


def smoothstep(edge0: float, edge1: float, x) -> np.ndarray:
    """GLSL smoothstep: 0 for x <= edge0, 1 for x >= edge1, 3t^2 - 2t^3 between; float64."""
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


# -- the lattice of the terrain beneath ----------------------------------------------------------

@dataclass(frozen=True)
class BaseLattice:
    """Posts of the terrain beneath at (lat0 + i dlat, lon0 + j dlon), degrees.

    exact: the source's own posts (EPSG:4326); kind: its describe() kind; row_offset,
    col_offset: global lattice index of (lat0, lon0) when lat0, lon0 are multiples of the
    spacing (else 0); col_period: posts per turn of longitude (0: not whole).
    """

    lat0: float
    lon0: float
    dlat: float
    dlon: float
    exact: bool
    kind: str
    name: str
    vertical_datum: str
    row_offset: int = 0
    col_offset: int = 0
    col_period: int = 0


def _aligned(origin: float, spacing: float) -> int:
    q = origin / spacing
    return int(round(q)) if abs(q - round(q)) < ALIGNMENT_TOLERANCE_POSTS else 0


def _covers(s: dict, lat: float, lon: float) -> bool:
    try:
        lat0, lat1 = float(s["lat_min"]), float(s["lat_max"])
        lon0, lon1 = float(s["lon_min"]), float(s["lon_max"])
    except (KeyError, TypeError, ValueError):
        return False
    return lat0 <= lat <= lat1 and (lon - lon0) % 360.0 <= (lon1 - lon0) + 1e-9


def base_lattice(sources: list[dict], lat: float, lon: float) -> BaseLattice:
    """The post lattice of the first source of ``sources`` (``Terrain.describe()`` or a
    ``TerrainClient``'s, values possibly text) covering (lat, lon), insets skipped."""
    cands = [s for s in sources if s.get("kind") != "inset" and _covers(s, lat, lon)]
    if not cands:
        raise InvalidArgument("area_polygon_latlon", f"no terrain source covers ({lat:.6f}, {lon:.6f})")
    s = cands[0]
    lat0, lon0 = float(s["lat_min"]), float(s["lon_min"])
    kind, name = str(s.get("kind", "")), str(s.get("name", ""))
    datum = str(s.get("vertical_datum", "mean sea level"))
    if s.get("crs") == "EPSG:4326":
        if s.get("spacing_deg"):
            dlat = dlon = float(s["spacing_deg"])
        else:
            dlat = (float(s["lat_max"]) - lat0) / (int(s["rows"]) - 1)
            dlon = (float(s["lon_max"]) - lon0) / (int(s["cols"]) - 1)
        turn = 360.0 / dlon
        period = int(round(turn)) if abs(turn - round(turn)) < ALIGNMENT_TOLERANCE_POSTS else 0
        return BaseLattice(lat0, lon0, dlat, dlon, True, kind, name, datum, _aligned(lat0, dlat),
                           _aligned(lon0, dlon), period)
    m, n = radii_of_curvature(lat)
    dlat = math.degrees(float(s["spacing_north_m"]) / float(m))
    dlon = math.degrees(float(s["spacing_east_m"]) / (float(n) * math.cos(math.radians(lat))))
    return BaseLattice(lat0, lon0, dlat, dlon, False, kind, name, datum)


# -- the polygon in a local plane ----------------------------------------------------------------

@dataclass(frozen=True)
class PolygonPlane:
    """A polygon in the plane x = east, y = north metres about its first vertex (lat_ref, lon_ref):
    x = wrap(lon - lon_ref) k_x, y = (lat - lat_ref) k_y with the WGS84 radii of curvature there
    (server/scenario.py's plane). The map is linear in (lat, lon), so an edge straight in one is
    straight in the other. x, y: (n,) float64 vertices, no closing vertex."""

    lat_ref: float
    lon_ref: float
    k_x: float  # metres per degree of longitude
    k_y: float  # metres per degree of latitude
    x: np.ndarray
    y: np.ndarray

    @classmethod
    def of(cls, lat, lon) -> PolygonPlane:
        lat_ref, lon_ref = float(lat[0]), float(lon[0])
        m, n = radii_of_curvature(lat_ref)
        k_x = math.radians(1.0) * float(n) * math.cos(math.radians(lat_ref))
        k_y = math.radians(1.0) * float(m)
        p = cls(lat_ref, lon_ref, k_x, k_y, np.zeros(0), np.zeros(0))
        x, y = p.to_plane(lat, lon)
        x.flags.writeable = y.flags.writeable = False
        return cls(lat_ref, lon_ref, k_x, k_y, x, y)

    def to_plane(self, lat, lon):
        """(x, y) metres of (lat, lon) degrees, float64 arrays of their shape."""
        dlon = (np.asarray(lon, dtype=np.float64) - self.lon_ref + 180.0) % 360.0 - 180.0
        return dlon * self.k_x, (np.asarray(lat, dtype=np.float64) - self.lat_ref) * self.k_y

    def signed_distance_m(self, lat, lon) -> np.ndarray:
        """(n,) float64 metres from the boundary, positive inside, at (lat, lon) (n,) degrees.
        Exact (in the plane); O(points x vertices)."""
        x, y = self.to_plane(lat, lon)
        out = np.zeros(x.shape)
        _signed_distance_kernel(np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel(), self.x, self.y,
                                out.reshape(-1))
        return out


@numba.njit(cache=True, nogil=True)
def _segment_d2(px, py, ax, ay, bx, by):
    dx = bx - ax
    dy = by - ay
    l2 = dx * dx + dy * dy
    t = 0.0
    if l2 > 0.0:
        t = min(max(((px - ax) * dx + (py - ay) * dy) / l2, 0.0), 1.0)
    qx = ax + t * dx - px
    qy = ay + t * dy - py
    return qx * qx + qy * qy


@numba.njit(cache=True, nogil=True)
def _signed_distance_kernel(x, y, ex, ey, out):
    """Signed distance of points (x, y) to the closed polygon (ex, ey): crossing number with
    half-open edges in y (a point on the boundary has distance 0 either way)."""
    n_e = ex.shape[0]
    for k in range(x.shape[0]):
        px = x[k]
        py = y[k]
        best = math.inf
        inside = False
        for e in range(n_e):
            ax = ex[e]
            ay = ey[e]
            bx = ex[(e + 1) % n_e]
            by = ey[(e + 1) % n_e]
            if (ay > py) != (by > py):
                if ax + (py - ay) * (bx - ax) / (by - ay) > px:
                    inside = not inside
            best = min(best, _segment_d2(px, py, ax, ay, bx, by))
        d = math.sqrt(best)
        out[k] = d if inside else -d


@numba.njit(cache=True, nogil=True)
def _signed_distance_grid_kernel(x0, dx, nx, y0, dy, ny, ex, ey, clamp, out):
    """out[r, c] = signed distance of (x0 + c dx, y0 + r dy), clamped to [-clamp, clamp].

    Inside: scanline parity per row (the same crossing rule as the point kernel: a post is
    inside when an odd number of crossings lie strictly east of it). Distance: each edge
    updates only the posts within ``clamp`` of its bounding box.
    """
    n_e = ex.shape[0]
    xs = np.zeros(n_e)
    for r in range(ny):
        py = y0 + r * dy
        m = 0
        for e in range(n_e):
            ay = ey[e]
            by = ey[(e + 1) % n_e]
            if (ay > py) != (by > py):
                ax = ex[e]
                bx = ex[(e + 1) % n_e]
                xs[m] = ax + (py - ay) * (bx - ax) / (by - ay)
                m += 1
        crossings = np.sort(xs[:m])
        k = 0
        for c in range(nx):
            px = x0 + c * dx
            while k < m and crossings[k] <= px:
                k += 1
            # crossings east of px: m - k; m is even, so its parity is k's
            out[r, c] = clamp if (m - k) % 2 == 1 else -clamp
    for e in range(n_e):
        ax = ex[e]
        ay = ey[e]
        bx = ex[(e + 1) % n_e]
        by = ey[(e + 1) % n_e]
        c0 = max(0, int(math.ceil((min(ax, bx) - clamp - x0) / dx)))
        c1 = min(nx - 1, int(math.floor((max(ax, bx) + clamp - x0) / dx)))
        r0 = max(0, int(math.ceil((min(ay, by) - clamp - y0) / dy)))
        r1 = min(ny - 1, int(math.floor((max(ay, by) + clamp - y0) / dy)))
        for r in range(r0, r1 + 1):
            py = y0 + r * dy
            for c in range(c0, c1 + 1):
                d = math.sqrt(_segment_d2(x0 + c * dx, py, ax, ay, bx, by))
                if d < abs(out[r, c]):
                    out[r, c] = d if out[r, c] > 0 else -d


def _check_polygon(polygon, name: str) -> tuple[np.ndarray, np.ndarray]:
    field = f"target area {name!r} polygon"
    try:
        p = np.asarray(polygon, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgument(field, "must be a sequence of (lat, lon) pairs") from None
    if p.ndim != 2 or p.shape[1] != 2:
        raise InvalidArgument(field, f"must have shape (n, 2) (lat, lon), got {p.shape}")
    if len(p) > 1 and np.array_equal(p[0], p[-1]):
        p = p[:-1]  # the closing vertex
    if not 3 <= len(p) <= MAX_POLYGON_VERTICES:
        raise InvalidArgument(field, f"must have 3..{MAX_POLYGON_VERTICES} vertices", value=len(p))
    lat, lon = check_latlon(p[:, 0], p[:, 1], prefix=f"{field} ")
    plane = PolygonPlane.of(lat, lon)
    area2 = float(np.sum(plane.x * np.roll(plane.y, -1) - np.roll(plane.x, -1) * plane.y))
    if not abs(area2) > 1e-6:
        raise InvalidArgument(field, "encloses no area")
    return lat, lon


# -- the source ----------------------------------------------------------------------------------

def _fetch(terrain, lat: np.ndarray, lon: np.ndarray):
    """Heights (float64, NaN outside) and FILLED mask of ``terrain`` at (lat, lon) of any shape."""
    res = terrain.heights(lat.ravel(), lon.ravel())
    h = np.asarray(res.height_msl_m, dtype=np.float64).reshape(lat.shape)
    return h, (np.asarray(res.status) == STATUS_FILLED).reshape(lat.shape)


def _centre_lattice(sources, plane: PolygonPlane, lat_v):
    """(base lattice, lat_c, lon_c, lon_un): the lattice of the source of ``sources`` under the
    centre (lat_c, lon_c) of the polygon's box, the one its inset refines (base_lattice), with
    lon_c and the vertex longitudes lon_un unwrapped about the first vertex."""
    lon_un = plane.lon_ref + plane.x / plane.k_x
    lat_c, lon_c = 0.5 * (lat_v.min() + lat_v.max()), 0.5 * (lon_un.min() + lon_un.max())
    return base_lattice(sources, lat_c, (lon_c + 180.0) % 360.0 - 180.0), lat_c, lon_c, lon_un


def check_covered(sources, area) -> None:
    """What InsetSource refuses first, checked without building the inset: InvalidArgument
    unless a source of ``sources`` (the terrain's ``describe()``) lies under the centre of target
    area ``area`` (a TargetArea or a (name, polygon, detail_m) tuple)."""
    name, polygon, _ = _area_fields(area)
    lat_v, lon_v = _check_polygon(polygon, name)
    _centre_lattice(sources, PolygonPlane.of(lat_v, lon_v), lat_v)


class InsetSource(Raster):
    """A target area's high-detail heights: a :class:`Terrain` source covering the polygon.

    terrain_below: ``Terrain`` or ``TerrainClient`` (``heights``, ``describe``) without this
    inset; area_polygon_latlon: (n, 2) (lat, lon) degrees, a simple polygon (server/scenario.py
    checks simplicity), closing vertex optional; detail_m: the post spacing asked for, metres
    (the lattice's is at most this, module docstring); seed: detail noise, integer in
    [0, 2^64); border_band_m: B. The lattice is the Raster's (``heights`` (rows, cols)
    float64, row 0 south); ``signed_distance`` (rows, cols) float64 metres from the border at
    each post, clamped to +-``distance_clamp_m``; detail_offset_m: a0 (module docstring).
    """

    def __init__(self, terrain_below, area_polygon_latlon, detail_m: float, seed: int, *, name: str = "inset",
                 border_band_m: float = DEFAULT_BORDER_BAND_M, _below_answers_inset: bool = False):
        lat_v, lon_v = _check_polygon(area_polygon_latlon, name)
        lo, hi = DETAIL_M_RANGE
        if not (isinstance(detail_m, (int, float, np.floating)) and lo <= detail_m <= hi):
            raise InvalidArgument(f"target area {name!r} detail_m", f"must be within [{lo}, {hi}] m", value=detail_m)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
            raise InvalidArgument("seed", "must be an integer within [0, 2^64)", value=seed)
        if not (math.isfinite(border_band_m) and border_band_m > 0):
            raise InvalidArgument("border_band_m", "must be finite and > 0", value=border_band_m)
        self.area_name = name
        self.plane = PolygonPlane.of(lat_v, lon_v)
        self.polygon = np.stack([lat_v, lon_v], axis=1)
        self.polygon.flags.writeable = False
        self.detail_m = float(detail_m)
        self.seed = int(seed)
        self.border_band_m = float(border_band_m)

        base, lat_c, lon_c, lon_un = _centre_lattice(terrain_below.describe(), self.plane, lat_v)
        self.base = base
        m, n = radii_of_curvature(lat_c)
        post_n_m = math.radians(base.dlat) * float(m)
        post_e_m = math.radians(base.dlon) * float(n) * math.cos(math.radians(lat_c))
        self.refine = (max(0, math.ceil(math.log2(post_n_m / detail_m) - 1e-9)),
                       max(0, math.ceil(math.log2(post_e_m / detail_m) - 1e-9)))  # (Ky, Kx)
        ky, kx = self.refine
        dlat, dlon = base.dlat / (1 << ky), base.dlon / (1 << kx)
        # Sub-lattice index ranges (relative to the base origin) of the box plus the margin.
        lon_base = base.lon0 + ((lon_c - base.lon0) // 360.0) * 360.0  # the base origin's turn nearest the area
        i0 = math.floor((lat_v.min() - base.lat0) / dlat) - INSET_MARGIN_CELLS
        i1 = math.ceil((lat_v.max() - base.lat0) / dlat) + INSET_MARGIN_CELLS
        j0 = math.floor((lon_un.min() - lon_base) / dlon) - INSET_MARGIN_CELLS
        j1 = math.ceil((lon_un.max() - lon_base) / dlon) + INSET_MARGIN_CELLS
        rows = -(-(i1 - i0) // INSET_BLOCK_CELLS) * INSET_BLOCK_CELLS + 1
        cols = -(-(j1 - j0) // INSET_BLOCK_CELLS) * INSET_BLOCK_CELLS + 1
        if rows * cols > INSET_MAX_POSTS:
            raise LimitExceeded(f"target area {name!r} inset posts ({rows} x {cols} at {detail_m} m)", rows * cols,
                                INSET_MAX_POSTS)
        lat0, lon0 = base.lat0 + i0 * dlat, lon_base + j0 * dlon
        if lat0 < -90.0 or lat0 + (rows - 1) * dlat > 90.0:
            raise InvalidArgument(f"target area {name!r} polygon", "lies too close to a pole for an inset")
        lat = lat0 + np.arange(rows, dtype=np.float64) * dlat
        lon = lon0 + np.arange(cols, dtype=np.float64) * dlon
        lat_g, lon_g = np.meshgrid(lat, lon, indexing="ij")
        below_h, filled = _fetch(terrain_below, lat_g, lon_g)

        cell_diag_m = math.hypot(post_n_m / (1 << ky), post_e_m / (1 << kx))
        self.spacing_m = (post_e_m / (1 << kx), post_n_m / (1 << ky))  # (east, north) at the area's centre
        self.cell_diagonal_m = cell_diag_m
        self.detail_offset_m = math.sqrt(2.0) * max(post_n_m, post_e_m)  # a0
        self.distance_clamp_m = self.detail_offset_m + self.border_band_m + INSET_BLOCK_CELLS * cell_diag_m
        sd = np.zeros((rows, cols))
        x0, y0 = self.plane.to_plane(lat0, lon0)
        _signed_distance_grid_kernel(float(x0), dlon * self.plane.k_x, cols, float(y0), dlat * self.plane.k_y, rows,
                                     self.plane.x, self.plane.y, self.distance_clamp_m, sd)
        sd.flags.writeable = False
        self.signed_distance = sd

        levels = min(ky, kx) if base.kind != "dem+detail" else 0
        self.detail_levels = levels
        self.residual_variance_m2 = self._residual_variance(terrain_below, base, lat_v.min(), lat_v.max(),
                                                            lon_un.min() - lon_base + base.lon0,
                                                            lon_un.max() - lon_base + base.lon0)
        std, self.fit_alpha, self.fit_beta = fit_sub_level_std(self.residual_variance_m2, levels)
        std.flags.writeable = False
        self.level_std_m = std
        self.detail_bound_m = DETAIL_TABLE_MAX * float(np.sum(std))
        self.cutout_depth_max_m = self.detail_bound_m + CUTOUT_MARGIN_M
        if _below_answers_inset or levels == 0:
            heights = below_h
        else:
            detail = self._detail(i0, j0, rows, cols)
            a0 = self.detail_offset_m
            heights = keep_sea_level_sign(below_h, below_h + smoothstep(a0, a0 + self.border_band_m, sd) * detail)
        super().__init__(heights=heights, georef=Georef(CRS_GEOGRAPHIC, lon0, lat0, dlon, dlat), name=name,
                         vertical_datum=base.vertical_datum, filled=filled if filled.any() else None,
                         source=f"inset over {base.name}", meta={"detail_levels": levels})
        self._cell_class = _cell_classes(sd, cell_diag_m)
        self._box = (self.plane.x.min(), self.plane.x.max(), self.plane.y.min(), self.plane.y.max())

    @classmethod
    def from_inset_terrain(cls, terrain, area_polygon_latlon, detail_m: float, seed: int, *, name: str = "inset",
                           border_band_m: float = DEFAULT_BORDER_BAND_M) -> InsetSource:
        """The same inset rebuilt from a terrain that already answers with it (a client of a
        terrain service serving ``with_insets(...)``): heights are the terrain's answers at the
        posts, which are the inset's posts bit for bit (exact at posts; outside the polygon
        w = 0, so the post is the terrain beneath's value), and the detail statistics come from
        the DEM's posts, where the detail is 0 — so every attribute equals the server's."""
        return cls(terrain, area_polygon_latlon, detail_m, seed, name=name, border_band_m=border_band_m,
                   _below_answers_inset=True)

    # -- construction helpers

    @staticmethod
    def _residual_variance(terrain_below, base: BaseLattice, lat_min, lat_max, lon_min, lon_max) -> np.ndarray:
        """Pyramid residual variances (m^2) of the DEM posts over the box and STATS_MARGIN_POSTS around,
        over land (terrain.detail.pyramid_residual_variance with the sea level: no detail is added
        to the sea, keep_sea_level_sign)."""
        i0 = math.floor((lat_min - base.lat0) / base.dlat) - STATS_MARGIN_POSTS
        i1 = math.ceil((lat_max - base.lat0) / base.dlat) + STATS_MARGIN_POSTS
        j0 = math.floor((lon_min - base.lon0) / base.dlon) - STATS_MARGIN_POSTS
        j1 = math.ceil((lon_max - base.lon0) / base.dlon) + STATS_MARGIN_POSTS
        i0 = max(i0, math.ceil((-90.0 - base.lat0) / base.dlat))
        i1 = min(i1, math.floor((90.0 - base.lat0) / base.dlat))
        lat = base.lat0 + np.arange(i0, i1 + 1, dtype=np.float64) * base.dlat
        lon = base.lon0 + np.arange(j0, j1 + 1, dtype=np.float64) * base.dlon
        lat_g, lon_g = np.meshgrid(lat, lon, indexing="ij")
        h, _ = _fetch(terrain_below, lat_g, lon_g)
        return pyramid_residual_variance(h, sea_level_m=SEA_LEVEL_M)

    def _detail(self, i0: int, j0: int, rows: int, cols: int) -> np.ndarray:
        """(rows, cols) detail (m) at the posts, in the DEM's index space (terrain/detail.py)."""
        ky, kx = self.refine
        b = self.base
        wi0, wj0 = i0 >> ky, j0 >> kx  # the DEM post at or south-west of the lattice's origin
        r = ((i0 + np.arange(rows)) / float(1 << ky)) - wi0  # exact: dyadic fractions
        c = ((j0 + np.arange(cols)) / float(1 << kx)) - wj0
        rr, cc = np.meshgrid(r, c, indexing="ij")
        shape = (int(math.ceil(r[-1])) + 2, int(math.ceil(c[-1])) + 2)
        lat_w = b.lat0 + wi0 * b.dlat  # the latitude of index row 0
        d, _, _ = detail_noise(rr.ravel(), cc.ravel(), self.level_std_m, self.seed, shape,
                               b.row_offset + wi0, b.col_offset + wj0, b.col_period,
                               pole_rows(CRS_GEOGRAPHIC, lat_w, b.dlat))
        taper, _ = polar_taper(lat_w + r * b.dlat, CRS_GEOGRAPHIC, b.dlon, b.dlat)
        return d.reshape(rows, cols) * taper[:, None]

    # -- coverage

    def covers(self, lat, lon) -> np.ndarray:
        """(n,) bool: (lat, lon) (n,) degrees lie in the closed polygon."""
        lat = np.asarray(lat, dtype=np.float64)
        lon = np.asarray(lon, dtype=np.float64)
        x, y = self.plane.to_plane(lat, lon)
        x_min, x_max, y_min, y_max = self._box
        out = np.zeros(lat.shape, bool)
        cand = np.flatnonzero((x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max))
        if cand.size == 0:
            return out
        g = self.georef
        ny, nx = self.shape
        r = np.clip(np.floor((lat[cand] - g.y0) / g.dy), 0, ny - 2).astype(np.intp)
        c = np.clip(np.floor(((lon[cand] - g.x0 + 180.0) % 360.0 - 180.0) / g.dx), 0, nx - 2).astype(np.intp)
        cls = self._cell_class[r, c]
        out[cand[cls == CELL_INSIDE]] = True
        border = cand[cls == CELL_BORDER]
        if border.size:
            out[border] = self.plane.signed_distance_m(lat[border], lon[border]) >= 0.0
        return out

    def _todo(self, lat, lon, out_status) -> np.ndarray:
        todo = np.flatnonzero(out_status == STATUS_OUTSIDE)
        if todo.size == 0:
            return todo
        return todo[self.covers(lat[todo], lon[todo])]

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        """Heights (m) of the inset's bilinear surface for the points still OUTSIDE inside the polygon."""
        idx = self._todo(lat, lon, out_status)
        if idx.size:
            h, st = np.full(idx.size, np.nan), np.full(idx.size, STATUS_OUTSIDE, np.uint8)
            super().heights_into(lat[idx], lon[idx], h, st)
            out_h[idx], out_status[idx] = h, st

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        """dh/d(east metre), dh/d(north metre) for the points still OUTSIDE inside the polygon."""
        idx = self._todo(lat, lon, out_status)
        if idx.size:
            de, dn = np.full(idx.size, np.nan), np.full(idx.size, np.nan)
            st = np.full(idx.size, STATUS_OUTSIDE, np.uint8)
            super().gradient_into(lat[idx], lon[idx], de, dn, st)
            out_de[idx], out_dn[idx], out_status[idx] = de, dn, st

    # -- the clipmap's cut-out

    def cutout_depth_m(self, lat, lon, clip_spacing_m: float = 0.0) -> np.ndarray:
        """(n,) float64 metres the clipmap's terrain goes down at (lat, lon) (n,) degrees.

        D smoothstep(a, a + B, s): 0 outside the polygon and within a = sqrt(2) clip_spacing_m of
        its border, D (``cutout_depth_max_m``) from a + B inward (module docstring: why).
        clip_spacing_m: the largest post spacing (m) of the clipmap level asking, so its linear
        interpolation between posts never lowers a point outside the polygon.
        """
        lat, lon = check_latlon(lat, lon)
        if not (math.isfinite(clip_spacing_m) and clip_spacing_m >= 0):
            raise InvalidArgument("clip_spacing_m", "must be finite and >= 0", value=clip_spacing_m)
        out = np.zeros(lat.shape)
        x, y = self.plane.to_plane(lat, lon)
        x_min, x_max, y_min, y_max = self._box
        cand = np.flatnonzero((x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max))
        if cand.size:
            a = math.sqrt(2.0) * clip_spacing_m
            s = self.plane.signed_distance_m(lat[cand], lon[cand])
            out[cand] = self.cutout_depth_max_m * smoothstep(a, a + self.border_band_m, s)
        return out

    def coverage_mask(self, max_texels: int = COVERAGE_MASK_MAX_TEXELS) -> CoverageMask:
        """The polygon as a grid a renderer tests fragments against (:class:`CoverageMask`):
        s - e at texel centres, s the signed distance (m, positive inside), e the margin that
        makes a bilinear sample > 0 only where the point is surely inside. Square texels of
        at least the inset's post spacing, at most ``max_texels`` a side, 4 texels of margin
        around the polygon's box (so clamping to the edge reads "outside")."""
        if not (isinstance(max_texels, int) and max_texels >= 16):
            raise InvalidArgument("max_texels", "must be an integer >= 16", value=max_texels)
        x_min, x_max, y_min, y_max = self._box
        pad = 4
        texel = max(min(self.spacing_m), (x_max - x_min) / (max_texels - 2 * pad - 1),
                    (y_max - y_min) / (max_texels - 2 * pad - 1))
        nx = min(max_texels, int(math.ceil((x_max - x_min) / texel)) + 2 * pad + 1)
        ny = min(max_texels, int(math.ceil((y_max - y_min) / texel)) + 2 * pad + 1)
        x0, y0 = x_min - pad * texel, y_min - pad * texel
        margin = texel * COVERAGE_MASK_MARGIN_TEXELS + COVERAGE_MASK_MARGIN_M
        clamp = margin + 2.0 * texel  # beyond this only the sign matters (CoverageMask)
        sd = np.zeros((ny, nx))
        _signed_distance_grid_kernel(x0, texel, nx, y0, texel, ny, self.plane.x, self.plane.y, clamp, sd)
        values = (sd - margin).astype(np.float32)
        values.flags.writeable = False
        return CoverageMask(values, x0, y0, texel, margin)

    def describe(self) -> dict:
        """The Raster's description with kind "inset" and the inset's parameters."""
        d = super().describe()
        d.update({
            "kind": "inset",
            "area": self.area_name,
            "polygon": [[float(a), float(b)] for a, b in self.polygon],
            "detail_m": self.detail_m,
            "detail_seed": self.seed,
            "detail_levels": self.detail_levels,
            "detail_level_std_m": [float(s) for s in self.level_std_m],
            "detail_bound_m": self.detail_bound_m,
            "border_band_m": self.border_band_m,
            "detail_offset_m": self.detail_offset_m,
            "cutout_depth_max_m": self.cutout_depth_max_m,
            "refine_rows_cols": list(self.refine),
        })
        return d


@dataclass(frozen=True)
class CoverageMask:
    """An inset's polygon as a texture (InsetSource.coverage_mask): ``values`` (ny, nx) float32
    metres at texel centres (x0 + c texel, y0 + r texel) of the polygon's plane
    (:class:`PolygonPlane`), each the signed distance to the border less ``margin_m``, clamped
    to +-(margin + 2 texels) beyond the border's neighbourhood.

    Why a bilinear sample v > 0 means the point is inside (s > 0): s is 1-Lipschitz, so s at
    each of the sample's four texel centres is within a texel diagonal t sqrt(2) of s at the
    point, and so is their convex combination; the margin e = t (sqrt(2) + 1/16) + 2 m
    (``COVERAGE_MASK_MARGIN_*``) covers that, 8-bit filter weights (1/256 texel) and where a
    renderer's fragment lies (its lattice position interpolated across a flat triangle: about
    2 m off the point's own on a 6 km clipmap cell at 47 N, from the second derivatives of
    (lat, lon) -> ECEF). Clamping keeps it: from above, a lowered corner only lowers the
    sample; from below, a corner raised to -(e + 2t) is still < e. So v > 0 only where s > 0,
    and v > 0 wherever s > e + t sqrt(2).
    """

    values: np.ndarray
    x0: float
    y0: float
    texel_m: float
    margin_m: float


CELL_OUTSIDE, CELL_BORDER, CELL_INSIDE = 0, 1, 2


def _cell_classes(sd: np.ndarray, cell_diag_m: float) -> np.ndarray:
    """(rows - 1, cols - 1) uint8 per lattice cell: INSIDE when every corner is more than a
    cell diagonal inside (no boundary point can be in the cell), OUTSIDE likewise outside,
    else BORDER (points there are tested exactly)."""
    corners = np.stack([sd[:-1, :-1], sd[:-1, 1:], sd[1:, :-1], sd[1:, 1:]])
    out = np.full(corners.shape[1:], CELL_BORDER, np.uint8)
    out[corners.min(axis=0) > cell_diag_m] = CELL_INSIDE
    out[corners.max(axis=0) < -cell_diag_m] = CELL_OUTSIDE
    out.flags.writeable = False
    return out


def _area_fields(area) -> tuple[str, object, float]:
    if hasattr(area, "polygon"):
        return str(area.name), area.polygon, float(area.detail_m)
    name, polygon, detail_m = area
    return str(name), polygon, float(detail_m)


# The seed of every exercise's inset detail: server, terrain service and clients build the same
# insets from the target areas alone (WorldInfo carries the areas, not a seed).
INSET_SEED = 0


def with_insets(terrain, target_areas, seed: int):
    """A new Terrain answering inside each target area from its InsetSource, elsewhere as
    ``terrain`` does (its sources follow, in order).

    terrain: a :class:`terrain.terrain.Terrain`; target_areas: ``server.scenario.TargetArea``
    objects or (name, polygon, detail_m) tuples (``ServerConfig.target_areas``); where areas
    overlap the first answers. Every inset is built over ``terrain`` itself.
    """
    from terrain.terrain import Terrain

    insets = []
    for area in target_areas:
        name, polygon, detail_m = _area_fields(area)
        insets.append(InsetSource(terrain, polygon, detail_m, seed, name=name))
    return Terrain(insets + list(terrain.sources))


def insets_of(terrain) -> list[InsetSource]:
    """The InsetSources of a Terrain's stack, in order (what a renderer draws with geomipmaps)."""
    return [s for s in getattr(terrain, "sources", ()) if isinstance(s, InsetSource)]


def cutout_depth_m(insets, lat, lon, clip_spacing_m: float = 0.0) -> np.ndarray:
    """(n,) float64: the deepest cut-out of any of ``insets`` at (lat, lon) (n,) degrees, metres."""
    lat, lon = check_latlon(lat, lon)
    out = np.zeros(lat.shape)
    for inset in insets:
        np.maximum(out, inset.cutout_depth_m(lat, lon, clip_spacing_m), out=out)
    return out
