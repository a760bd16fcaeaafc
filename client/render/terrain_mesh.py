"""The reference terrain layer: every DEM post in a window around the camera as one mesh.

What it draws (and what a geometry clipmap, issue #5, will replace behind the
same ``update(camera)`` / ``draw(frame)`` interface):

- **Full resolution**: the posts of the terrain's own lattice (the first
  source covering the camera: an EPSG:4326 DEM's rows and columns, the
  procedural world's global lattice) within ``window_m`` of the camera, at
  ``stride`` 1 unless a spacing is stated or the window would exceed
  MAX_POSTS_PER_AXIS. Posts are exact DEM values (no resampling).
- **Horizon ring** (optional): every ``horizon_stride``-th post of the same
  lattice out to ``horizon_m``, with the full-resolution window cut out. The
  window's bounds are multiples of the ring's spacing, so the ring's inner
  edge runs through posts the window also has (bit-identical: same lattice
  indices, same query). The window's boundary posts between them are moved
  onto the ring's edge (linear interpolation in ECEF between the two ring
  posts, as a clipmap's border blends to the coarser level, thesis §3.1.5 at
  alpha = 1), so the two meshes meet without cracks; only T-junction rounding
  remains (sub-pixel).
- **Earth curvature** is exact: posts are placed in ECEF from (lat, lon,
  height MSL + N), N the constant geoid undulation (``server.world``'s
  convention; the terrain service answers MSL heights).
- **Holes**: a post whose height is NaN (no source covers it) drops every
  cell it touches; nothing is invented there (the renderer's sea shell shows
  through). The no-data posts next to data (:func:`shore_posts`) are drawn at
  MSL 0, as the clipmap stores every no-data post (client/render/clipmap.py),
  so a DEM's edge or void is a wall down to the sea: without it a view from
  beside the edge looked under the terrain's last row at the sea shell.
- **Normals**: central differences of the ECEF post grid (one-sided at the
  edges), (P[c+1] - P[c-1]) x (P[r+1] - P[r-1]): exact on the ellipsoid, no
  local flat-earth approximation.

The mesh is rebuilt, centred on the camera, when the camera has moved more
than ``REBUILD_FRACTION`` of the window from its centre (so the full-resolution
radius is always at least 3/4 of the window), and re-uploaded when the local
origin is rebased. A rebuild is synchronous (the clipmap's incremental,
budgeted updates are issue #5's), unless the layer is made with ``background``
(the clipmap's polar mesh): then, while the camera is still inside the current
window, the next mesh is built on a helper thread and the current one drawn
until it is ready ("terrain work never disturbs the frame rate",
global-terrain-flight-sim), and only the GPU upload is the frame's.

The posts are asked for in as few calls as the terrain takes (:func:`grid_heights`):
one, split by rows where the terrain refuses it as over a per-call limit (a
procedural world generates at most MAX_NEW_BLOCKS_PER_CALL new blocks a call,
and near a pole every row of the window touches a whole ring of them), in at
most LIMIT_SPLIT_MAX_PARTS parts.
Shapes and frames are in each docstring; (lat, lon) order, degrees; heights
metres MSL.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from client.render.camera import Camera, LocalOrigin
from client.render.gl import check_gl_error
from client.render.shading import (GLSL_COMMON, ROCK_RGB, ROCK_SLOPE_DEG, TINT_HIGH_M, TINT_HIGH_RGB, TINT_LOW_RGB,
                                   TINT_MID_M, TINT_MID_RGB, WATER_RGB, WATER_SHININESS, WATER_SPECULAR, Frame, rgb)
from sortie.errors import InvalidArgument, LimitExceeded, SortieError
from terrain.geodesy import enu_basis, geodetic_to_ecef, radii_of_curvature

log = logging.getLogger(__name__)

DEFAULT_WINDOW_M = 20_000.0  # half-width of the full-resolution window
DEFAULT_HORIZON_M = 80_000.0  # half-width of the horizon ring (0: none)
DEFAULT_HORIZON_STRIDE = 8  # ring posts per full-resolution post, per axis
MAX_POSTS_PER_AXIS = 2049  # beyond this the window takes every k-th post (the stride)
REBUILD_FRACTION = 0.25  # recentre when the camera is this fraction of the window off centre
# A call the terrain refuses as over a per-call limit is asked again in this many times as many
# parts as its size over the limit (LimitExceeded.size / .limit): a little slack, as a part's
# count of what the limit counts (new procedural blocks) need not split evenly with its rows.
LIMIT_SPLIT_SLACK = 1.25
# ... in at most this many parts in all: the limit bounds the work one request may start (a
# procedural world's 4096 new blocks, about 6-16 s), and splitting is not a way round it. The
# default window and ring at a pole over the default procedural world need 1.2-1.6 times it
# (4864 and 6663 blocks: 90 N, 89.5 N), 2 or 3 parts; a 300 km ring at 88 N 5.8 times (23,679
# blocks, a minute or more), refused as the single call was, naming the options that set the
# area (client/render_cli.mesh_area_named).
LIMIT_SPLIT_MAX_PARTS = 4
_VERTEX_FLOATS = 8  # position (3), normal (3), height MSL, cos(slope)


# -- the post lattice ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Lattice:
    """Posts at (lat0 + i dlat, lon0 + j dlon), degrees, integer i, j. ``exact``: these are
    the source's own posts (False: a stated spacing, or a projected raster's approximation)."""

    lat0: float
    lon0: float
    dlat: float
    dlon: float
    exact: bool

    def lat(self, i) -> np.ndarray:
        return self.lat0 + np.asarray(i, dtype=np.float64) * self.dlat

    def lon(self, j) -> np.ndarray:
        return self.lon0 + np.asarray(j, dtype=np.float64) * self.dlon


def _covers(s: dict, lat: float, lon: float) -> bool:
    width = float(s["lon_max"]) - float(s["lon_min"])
    return (float(s["lat_min"]) <= lat <= float(s["lat_max"])
            and (lon - float(s["lon_min"])) % 360.0 <= width + 1e-9)


def lattice_for(sources: list[dict], lat: float, lon: float) -> Lattice:
    """The post lattice of the first source (``Terrain.describe()`` order) covering (lat, lon),
    or of the first source when none does.

    EPSG:4326 sources give their exact lattice; others (Web Mercator GeoTIFFs) a lattice of
    their post spacing in metres at ``lat``, anchored at their south-west corner.
    """
    sources = [s for s in sources if s.get("kind") != "inset"] or sources  # insets are drawn by their own layer
    if not sources:
        raise InvalidArgument("sources", "the terrain describes no source; give spacing_m")
    s = next((s for s in sources if _covers(s, lat, lon)), sources[0])
    if s.get("kind") == "store":  # the store's global lattice: posts from the North Pole and the 180th meridian
        return Lattice(90.0, -180.0, float(s["resolution_lat_deg"]), float(s["resolution_lon_deg"]), True)
    lat0, lon0 = float(s["lat_min"]), float(s["lon_min"])
    if s.get("crs") == "EPSG:4326":
        if s.get("spacing_deg"):
            d = float(s["spacing_deg"])
            return Lattice(lat0, lon0, d, d, True)
        rows, cols = int(s["rows"]), int(s["cols"])
        if rows > 1 and cols > 1:
            return Lattice(lat0, lon0, (float(s["lat_max"]) - lat0) / (rows - 1),
                           (float(s["lon_max"]) - lon0) / (cols - 1), True)
    return metric_lattice(float(s["spacing_north_m"]), float(s["spacing_east_m"]), lat, lat0, lon0)


def metric_lattice(spacing_north_m: float, spacing_east_m: float, lat: float, lat0: float = 0.0,
                   lon0: float = 0.0) -> Lattice:
    """A lattice of the given spacings (metres) at latitude ``lat``, anchored at (lat0, lon0)."""
    for name, v in (("spacing_north_m", spacing_north_m), ("spacing_east_m", spacing_east_m)):
        if not (v > 0 and math.isfinite(v)):
            raise InvalidArgument(name, "must be > 0", value=v)
    m, n = radii_of_curvature(lat)
    coslat = max(math.cos(math.radians(lat)), 1e-6)
    return Lattice(lat0, lon0, math.degrees(spacing_north_m / float(m)),
                   min(math.degrees(spacing_east_m / (float(n) * coslat)), 1.0), False)


def window_indices(lattice: Lattice, lat: float, lon: float, half_m: float, step_i: int, step_j: int) -> tuple:
    """Lattice index ranges (i0, i1, j0, j1), inclusive, rows multiples of ``step_i`` and columns
    of ``step_j``, covering at least ``half_m`` metres north, south, east and west of (lat, lon);
    rows stay within [-90, 90] and the columns within one turn."""
    m, n = radii_of_curvature(lat)
    half_lat = math.degrees(half_m / float(m))
    half_lon = min(math.degrees(half_m / (float(n) * max(math.cos(math.radians(lat)), 1e-9))), 180.0)
    i0 = math.floor((lat - half_lat - lattice.lat0) / lattice.dlat / step_i) * step_i
    i1 = math.ceil((lat + half_lat - lattice.lat0) / lattice.dlat / step_i) * step_i
    lo = math.ceil((-90.0 - lattice.lat0) / lattice.dlat / step_i) * step_i
    hi = math.floor((90.0 - lattice.lat0) / lattice.dlat / step_i) * step_i
    i0, i1 = max(i0, lo), min(i1, hi)
    j0 = math.floor((lon - half_lon - lattice.lon0) / lattice.dlon / step_j) * step_j
    j1 = math.ceil((lon + half_lon - lattice.lon0) / lattice.dlon / step_j) * step_j
    turn = math.floor(360.0 / lattice.dlon / step_j) * step_j
    if j1 - j0 > turn:
        j1 = j0 + turn
    return i0, i1, j0, j1


# -- pure grid functions -------------------------------------------------------------------------

def grid_normals(points_ecef: np.ndarray) -> np.ndarray:
    """(ny, nx, 3) ECEF post grid (row 0 south, column 0 west) -> (ny, nx, 3) float64 unit normals,
    ECEF, pointing up; NaN where a needed neighbour is NaN. Central differences, one-sided at edges."""
    if points_ecef.ndim != 3 or points_ecef.shape[2] != 3:
        raise ValueError(f"points_ecef must have shape (ny, nx, 3), got {points_ecef.shape}")
    ny, nx, _ = points_ecef.shape
    if ny < 2 or nx < 2:
        return np.full(points_ecef.shape, np.nan)
    d_east = np.gradient(points_ecef, axis=1)
    d_north = np.gradient(points_ecef, axis=0)
    n = np.cross(d_east, d_north)
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def shore_posts(heights_m: np.ndarray) -> np.ndarray:
    """(ny, nx) heights (NaN: no data) -> (ny, nx) bool: the no-data posts with a post of data
    among their 8 neighbours, so every cell that touches data has its four corners."""
    data = np.pad(np.isfinite(heights_m), 1)
    near = np.zeros(heights_m.shape, bool)
    ny, nx = heights_m.shape
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            near |= data[di:di + ny, dj:dj + nx]
    return near & ~np.isfinite(heights_m)


def grid_triangles(valid: np.ndarray, skip_cells: np.ndarray | None = None) -> np.ndarray:
    """(ny, nx) bool posts that exist -> (m, 3) uint32 vertex indices (row-major, r * nx + c).

    Each cell whose four corners exist, and that ``skip_cells`` ((ny - 1, nx - 1) bool) does not
    mark, makes two triangles SW-SE-NE and SW-NE-NW: counter-clockwise seen from above.
    """
    ny, nx = valid.shape
    if ny < 2 or nx < 2:
        return np.zeros((0, 3), np.uint32)
    cell = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    if skip_cells is not None:
        cell &= ~skip_cells
    r, c = np.nonzero(cell)
    sw = (r * nx + c).astype(np.uint32)
    se, nw = sw + 1, sw + nx
    ne = nw + 1
    return np.concatenate([np.stack([sw, se, ne], axis=-1), np.stack([sw, ne, nw], axis=-1)])


def cell_corner_weights(fy: float, fx: float) -> tuple[float, float, float, float]:
    """Weights of a cell's corners (SW, SE, NE, NW) at the point a fraction fy north and fx east
    across it, on the triangles the cell is drawn as: SW-SE-NE where fx >= fy, else SW-NE-NW
    (:func:`grid_triangles`, and the clipmap's block_grid, split every cell along that diagonal).
    Not the bilinear surface: the triangles part from it by up to a quarter of the cell's twist,
    |h_SW + h_NE - h_SE - h_NW| / 4, at its centre, above it where the twist is positive."""
    if fx >= fy:
        return 1.0 - fx, fx - fy, fy, 0.0
    return 1.0 - fy, 0.0, fx, fy - fx


def grid_surface_height(heights_m: np.ndarray, fi: float, fj: float, top: bool = False) -> float:
    """The height of the surface :func:`grid_triangles` draws over a grid of post heights
    ((ny, nx), metres, rows northwards) at the fractional grid index (fi row, fj column): its
    cell's triangle there (:func:`cell_corner_weights`); with ``top``, the cell's highest
    corner, which no point drawn in the cell rises above. NaN outside the grid or on a hole."""
    ny, nx = heights_m.shape
    i, j = min(math.floor(fi), ny - 2), min(math.floor(fj), nx - 2)
    if not (0 <= i and 0 <= j and fi <= ny - 1 and fj <= nx - 1):
        return math.nan
    corners = heights_m[(i, i, i + 1, i + 1), (j, j + 1, j + 1, j)]  # SW, SE, NE, NW
    if top:
        return float(corners.max())
    return float(np.dot(cell_corner_weights(fi - i, fj - j), corners))


def grid_surface_heights(heights_m: np.ndarray, fi: np.ndarray, fj: np.ndarray) -> np.ndarray:
    """(n,) float64 :func:`grid_surface_height` at (n,) fractional grid indices fi (rows), fj
    (columns) at once: the height of the triangle drawn there; NaN outside the grid or on a hole."""
    ny, nx = heights_m.shape
    fi, fj = np.asarray(fi, np.float64), np.asarray(fj, np.float64)
    inside = (fi >= 0.0) & (fj >= 0.0) & (fi <= ny - 1) & (fj <= nx - 1)
    i = np.clip(np.floor(np.where(inside, fi, 0.0)).astype(np.int64), 0, ny - 2)
    j = np.clip(np.floor(np.where(inside, fj, 0.0)).astype(np.int64), 0, nx - 2)
    y, x = fi - i, fj - j
    sw, se, ne, nw = heights_m[i, j], heights_m[i, j + 1], heights_m[i + 1, j + 1], heights_m[i + 1, j]
    lower = x >= y  # cell_corner_weights: SW-SE-NE, else SW-NE-NW
    h = np.where(lower, (1.0 - x) * sw + (x - y) * se + y * ne, (1.0 - y) * sw + x * ne + (y - x) * nw)
    return np.where(inside, h, np.nan)


def stitch_edges(points_ecef: np.ndarray, heights_m: np.ndarray, every: int) -> None:
    """Move the boundary posts of a (ny, nx, 3) grid that fall between every ``every``-th post
    onto the straight line (ECEF) between those two, in place; heights (ny, nx) likewise. The
    grid's shape must be 1 + a multiple of ``every`` along both axes."""
    ny, nx, _ = points_ecef.shape
    for edge in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
        p, h = points_ecef[edge], heights_m[edge]  # views
        k = np.arange(p.shape[0])
        a = (k // every) * every
        b = np.minimum(a + every, p.shape[0] - 1)
        t = ((k - a) / every)[:, None]
        between = (k % every) != 0
        p[between] = ((1.0 - t) * p[a] + t * p[b])[between]
        h[between] = ((1.0 - t[:, 0]) * h[a] + t[:, 0] * h[b])[between]


@dataclass
class MeshData:
    """A terrain mesh in float64, before upload.

    positions_ecef: (n, 3) metres ECEF; normals_ecef: (n, 3) unit; height_msl_m: (n,);
    cos_slope: (n,) cosine of the angle between the normal and the ellipsoid's vertical;
    triangles: (m, 3) uint32. centre: (lat, lon) degrees of the window's centre;
    window_shape / ring_shape: posts (rows, cols) of each grid; stride: (rows, cols) lattice
    posts per full-resolution post; bounds: (lat_min, lat_max, lon_min, lon_max) of the outer grid;
    solid_bounds: the same for the largest centred box where every cell is drawn (no hole
    in or next to it), None if there is none.
    """

    positions_ecef: np.ndarray
    normals_ecef: np.ndarray
    height_msl_m: np.ndarray
    cos_slope: np.ndarray
    triangles: np.ndarray
    centre: tuple
    window_shape: tuple
    ring_shape: tuple
    stride: tuple
    bounds: tuple
    solid_bounds: tuple | None
    window_corner: tuple = (math.nan, math.nan)  # (lat, lon) degrees of the window's first post (row 0, column 0)
    window_spacing_deg: tuple = (math.nan, math.nan)  # (dlat, dlon) between the window's posts


def posts_across(lattice: Lattice, lat: float, half_m: float) -> tuple[float, float]:
    """(rows, cols): lattice posts across a window of half-width half_m metres at latitude lat."""
    m, n = radii_of_curvature(lat)
    rows = 2.0 * half_m / (math.radians(lattice.dlat) * float(m))
    cols = 2.0 * half_m / (math.radians(lattice.dlon) * float(n) * max(math.cos(math.radians(lat)), 1e-9))
    return rows, min(cols, 360.0 / lattice.dlon)


class MeshBuildCancelled(SortieError):
    """A background mesh build stopped because its layer no longer wants it."""


def grid_heights(terrain, lat_rows: list, lon_cols: list, cancelled=None) -> np.ndarray:
    """Heights MSL (metres, NaN where no source answers) of grids of posts: grid g is every
    (lat_rows[g][r], lon_cols[g][c]) ((rows,), (cols,) float64 degrees), row-major, the grids one
    after another: one flat (sum of rows x cols,) float64 array.

    Asked of ``terrain.heights`` in one call, as the mesh always was. A call the terrain refuses
    as over a per-call limit (LimitExceeded: a procedural world's new blocks, which near a pole
    every row of the window touches a whole ring of) is asked again in bands of whole rows of
    every grid, in order of latitude (a band of rows is a band of the ground, so what serves it,
    a procedural block, is mostly needed by that band alone), size / limit x LIMIT_SPLIT_SLACK
    bands, each split the same way if refused in turn, in LIMIT_SPLIT_MAX_PARTS bands at most (a
    request that needs more, or a row refused alone, is refused: the LimitExceeded is raised).
    ``cancelled()`` (optional) is asked before every call: true raises MeshBuildCancelled."""
    sizes = [r.size * c.size for r, c in zip(lat_rows, lon_cols)]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    out = np.empty(int(offsets[-1]))
    rows = sorted((float(la), g, r) for g, lat_r in enumerate(lat_rows) for r, la in enumerate(lat_r))
    todo = [(0, len(rows))] if rows else []
    done = 0
    while todo:
        if cancelled is not None and cancelled():
            raise MeshBuildCancelled("the mesh is no longer wanted")
        a, b = todo.pop()
        band = rows[a:b]
        lat = np.concatenate([np.full(lon_cols[g].size, la) for la, g, _ in band])
        lon = np.concatenate([lon_cols[g] for _, g, _ in band])
        try:
            h = np.asarray(terrain.heights(lat, lon).height_msl_m, np.float64)
        except LimitExceeded as exc:
            k = min(b - a, max(2, math.ceil(LIMIT_SPLIT_SLACK * exc.size / max(exc.limit, 1))))
            if b - a == 1 or done + len(todo) + k > LIMIT_SPLIT_MAX_PARTS:
                raise
            cuts = np.linspace(a, b, k + 1).round().astype(int)
            todo += [(int(x), int(y)) for x, y in zip(cuts[:-1], cuts[1:]) if y > x][::-1]
            continue
        done += 1
        at = 0
        for _, g, r in band:
            cols = lon_cols[g].size
            start = int(offsets[g]) + r * cols
            out[start:start + cols] = h[at:at + cols]
            at += cols
    return out


def build_mesh(terrain, lattice: Lattice, lat: float, lon: float, *, window_m: float = DEFAULT_WINDOW_M,
               horizon_m: float = DEFAULT_HORIZON_M, horizon_stride: int = DEFAULT_HORIZON_STRIDE,
               stride: int = 1, geoid_undulation_m: float = 0.0, cancelled=None) -> MeshData:
    """Fetch the posts around (lat, lon) from ``terrain`` (anything with ``heights(lat, lon)``
    returning ``.height_msl_m``; :func:`grid_heights`: one call, split where the terrain refuses
    it as too large) and build the mesh: the full-resolution window
    (every ``stride``-th lattice post within ``window_m``) and, when ``horizon_m > window_m``,
    the ring of every ``stride * horizon_stride``-th post out to ``horizon_m``. Strides grow,
    per axis, when a grid would exceed MAX_POSTS_PER_AXIS. ``cancelled``: as grid_heights'."""
    rows, cols = posts_across(lattice, lat, window_m)
    si = max(stride, math.ceil(rows / MAX_POSTS_PER_AXIS))  # near a pole the columns thin out first
    sj = max(stride, math.ceil(cols / MAX_POSTS_PER_AXIS))
    ring = horizon_m > window_m
    if ring:
        rows, cols = posts_across(lattice, lat, horizon_m)
        horizon_stride = max(horizon_stride, math.ceil(max(rows / si, cols / sj) / MAX_POSTS_PER_AXIS))
    hs = horizon_stride if ring else 1  # the window's bounds are multiples of the ring's spacing
    fi0, fi1, fj0, fj1 = window_indices(lattice, lat, lon, window_m, si * hs, sj * hs)
    grids = [(np.arange(fi0, fi1 + 1, si), np.arange(fj0, fj1 + 1, sj))]
    if ring:
        ri0, ri1, rj0, rj1 = window_indices(lattice, lat, lon, horizon_m, si * hs, sj * hs)
        grids.append((np.arange(ri0, ri1 + 1, si * hs), np.arange(rj0, rj1 + 1, sj * hs)))
    lats = [np.broadcast_to(lattice.lat(i)[:, None], (i.size, j.size)) for i, j in grids]
    lons = [np.broadcast_to(lattice.lon(j)[None, :], (i.size, j.size)) for i, j in grids]
    all_h = grid_heights(terrain, [lattice.lat(i) for i, _ in grids], [lattice.lon(j) for _, j in grids],
                         cancelled)

    parts, offset, start, hole_i, hole_j = [], 0, 0, [], []
    for g, ((i, j), la, lo) in enumerate(zip(grids, lats, lons)):
        shape = (i.size, j.size)
        h = all_h[start:start + la.size].reshape(shape).copy()
        start += la.size
        nodata = ~np.isfinite(h)
        h[shore_posts(h)] = 0.0  # a wall down to the sea where the data ends (the module docstring)
        p = geodetic_to_ecef(la, lo, h + geoid_undulation_m)
        normals = grid_normals(p)
        skip = None
        if g == 0 and ring:
            stitch_edges(p, h, horizon_stride)
        if g == 1:  # the ring's cells inside the window are the window's
            ci = (i[:-1] >= fi0) & (i[1:] <= fi1)
            cj = (j[:-1] >= fj0) & (j[1:] <= fj1)
            skip = ci[:, None] & cj[None, :]
        valid = np.isfinite(h)
        hole_i.append(np.broadcast_to(i[:, None], shape)[nodata])  # the sea shell's too: shore posts are water
        hole_j.append(np.broadcast_to(j[None, :], shape)[nodata])
        up = enu_basis(la, lo)[2]
        cos_slope = np.einsum("...k,...k->...", normals, up)
        bad = ~np.isfinite(cos_slope)
        normals[bad], cos_slope[bad] = up[bad], 1.0  # posts whose neighbours are holes: level
        parts.append((p.reshape(-1, 3), normals.reshape(-1, 3), h.ravel(), cos_slope.ravel(),
                      grid_triangles(valid, skip) + np.uint32(offset)))
        offset += la.size
    pos, nrm, hgt, cos_s, tri = (np.concatenate(x) for x in zip(*parts))
    outer_i, outer_j = grids[-1]
    return MeshData(pos, nrm, hgt, cos_s, tri.astype(np.uint32), (lat, lon), lats[0].shape,
                    lats[1].shape if ring else (0, 0), (si, sj),
                    (float(lattice.lat(outer_i[0])), float(lattice.lat(outer_i[-1])),
                     float(lattice.lon(outer_j[0])), float(lattice.lon(outer_j[-1]))),
                    _solid_bounds(lattice, outer_i, outer_j, np.concatenate(hole_i), np.concatenate(hole_j)),
                    (float(lattice.lat(fi0)), float(lattice.lon(fj0))), (lattice.dlat * si, lattice.dlon * sj))


def _solid_bounds(lattice: Lattice, outer_i: np.ndarray, outer_j: np.ndarray, hole_i: np.ndarray,
                  hole_j: np.ndarray) -> tuple | None:
    """(lat_min, lat_max, lon_min, lon_max) of the largest box centred on the outer grid, one
    outer cell clear of its edge and of every hole post (lattice indices hole_i, hole_j); None
    when there is no such box."""
    step_i = int(outer_i[1] - outer_i[0]) if outer_i.size > 1 else 1
    step_j = int(outer_j[1] - outer_j[0]) if outer_j.size > 1 else 1
    ic, jc = 0.5 * (outer_i[0] + outer_i[-1]), 0.5 * (outer_j[0] + outer_j[-1])
    half_i, half_j = 0.5 * (outer_i[-1] - outer_i[0]), 0.5 * (outer_j[-1] - outer_j[0])
    if half_i <= 0 or half_j <= 0:
        return None
    frac = 1.0
    if hole_i.size:
        frac = float(np.min(np.maximum(np.abs(hole_i - ic) / half_i, np.abs(hole_j - jc) / half_j)))
    di, dj = frac * half_i - step_i, frac * half_j - step_j
    if di <= 0 or dj <= 0:
        return None
    return (float(lattice.lat(ic - di)), float(lattice.lat(ic + di)), float(lattice.lon(jc - dj)),
            float(lattice.lon(jc + dj)))


# -- the GL layer --------------------------------------------------------------------------------

TERRAIN_VERTEX_SHADER = "#version 330 core\n" + GLSL_COMMON + """
in vec3 in_position;   // local ENU metres (float32 offsets from the origin)
in vec3 in_normal;     // local ENU unit vector
in float in_height;    // metres MSL
in float in_cos_slope;
out vec3 v_world;
out vec3 v_normal;
out float v_height;
out float v_cos_slope;
void main() {
    v_world = in_position;
    v_normal = in_normal;
    v_height = in_height;
    v_cos_slope = in_cos_slope;
    gl_Position = u_projection * (u_view * vec4(in_position, 1.0));
}
"""

# The terrain's colour and lighting at a point (local ENU world position, unit normal, height
# MSL, cosine of the slope), shared by every terrain layer (this mesh, the clipmap).
TERRAIN_COLOUR_GLSL = f"""
const vec3 TINT_LOW = vec3{rgb(TINT_LOW_RGB)};
const vec3 TINT_MID = vec3{rgb(TINT_MID_RGB)};
const vec3 TINT_HIGH = vec3{rgb(TINT_HIGH_RGB)};
const vec3 ROCK = vec3{rgb(ROCK_RGB)};
const vec3 WATER = vec3{rgb(WATER_RGB)};
const float MID_M = {TINT_MID_M};
const float HIGH_M = {TINT_HIGH_M};
const float ROCK_COS_START = {math.cos(math.radians(ROCK_SLOPE_DEG[0]))};
const float ROCK_COS_FULL = {math.cos(math.radians(ROCK_SLOPE_DEG[1]))};
uniform float u_water_level;  // m MSL: 0, or a lossy store's quantisation bound (shading.water_level_m)
vec3 terrain_colour(vec3 world, vec3 n, float height, float cos_slope) {{
    vec3 colour;
    if (height <= u_water_level) {{  // water at sea level
        vec3 to_eye = normalize(u_camera - world);
        float spec = pow(max(dot(n, normalize(u_sun + to_eye)), 0.0), {WATER_SHININESS});
        colour = lambert(WATER, n) + {WATER_SPECULAR} * u_sun_light * spec;  // no glint of a set sun
    }} else {{
        vec3 tint = height < MID_M ? mix(TINT_LOW, TINT_MID, height / MID_M)
                                   : mix(TINT_MID, TINT_HIGH, clamp((height - MID_M) / (HIGH_M - MID_M), 0.0, 1.0));
        float rock = smoothstep(ROCK_COS_START, ROCK_COS_FULL, cos_slope);
        colour = lambert(mix(tint, ROCK, rock), n);
    }}
    return fogged(colour, world);
}}
"""

TERRAIN_FRAGMENT_SHADER = "#version 330 core\n" + GLSL_COMMON + TERRAIN_COLOUR_GLSL + """
in vec3 v_world;
in vec3 v_normal;
in float v_height;
in float v_cos_slope;
out vec4 out_colour;
void main() {
    out_colour = vec4(terrain_colour(v_world, normalize(v_normal), v_height, v_cos_slope), 1.0);
}
"""


def interleave(origin: LocalOrigin, positions_ecef, normals_ecef, height_msl_m, cos_slope) -> np.ndarray:
    """(n, 8) float32 vertex records: local position, local normal, height, cos(slope) - the GPU boundary."""
    out = np.empty((len(positions_ecef), _VERTEX_FLOATS), dtype="f4")
    out[:, 0:3] = origin.to_local(positions_ecef)
    out[:, 3:6] = origin.vectors_to_local(normals_ecef)
    out[:, 6] = height_msl_m
    out[:, 7] = cos_slope
    return out


class TerrainMeshLayer:
    """Full-resolution terrain mesh around the camera (the reference for issue #5's clipmap).

    terrain: ``Terrain`` or ``TerrainClient`` (``heights(lat, lon)``, and ``describe()`` unless
    ``spacing_m`` is given). window_m / horizon_m: half-widths of the full-resolution window and
    of the horizon ring (0: none). spacing_m: draw every k-th post, k = round(spacing_m / post
    spacing) (or, for a terrain that describes no source, a lattice of that spacing).
    background: rebuild on a helper thread while the camera is still inside the current window,
    drawing the current mesh until the next is ready (the first build, and one for a camera that
    has left the window, are the frame's own); the terrain must answer from two threads at once
    (Terrain and TerrainClient do).

    Counters: ``rebuilds`` (meshes built so far), ``samples`` (posts the mesh installed by the
    last update fetched: 0 unless it installed one), ``building`` (a background build running).
    """

    def __init__(self, ctx, terrain, origin: LocalOrigin, *, window_m: float = DEFAULT_WINDOW_M,
                 horizon_m: float = DEFAULT_HORIZON_M, horizon_stride: int = DEFAULT_HORIZON_STRIDE,
                 spacing_m: float | None = None, geoid_undulation_m: float = 0.0, background: bool = False):
        if not (0 < window_m <= 1_000_000):
            raise InvalidArgument("window_m", "must be in (0, 1000 km]", value=window_m)
        if not (horizon_m == 0 or window_m < horizon_m <= 2_000_000):
            raise InvalidArgument("horizon_m", "must be 0 or in (window_m, 2000 km]", value=horizon_m)
        if not (isinstance(horizon_stride, int) and horizon_stride >= 2):
            raise InvalidArgument("horizon_stride", "must be an integer >= 2", value=horizon_stride)
        if spacing_m is not None and not (spacing_m > 0 and math.isfinite(spacing_m)):
            raise InvalidArgument("spacing_m", "must be > 0", value=spacing_m)
        self.ctx = ctx
        self.terrain = terrain
        self.origin = origin
        self.window_m = float(window_m)
        self.horizon_m = float(horizon_m)
        self.horizon_stride = horizon_stride
        self.spacing_m = spacing_m
        self.geoid_undulation_m = float(geoid_undulation_m)
        describe = getattr(terrain, "describe", None)
        self._sources = describe() if describe is not None else []
        if not self._sources and spacing_m is None:
            raise InvalidArgument("spacing_m", "required for a terrain without describe()")
        self.program = ctx.program(vertex_shader=TERRAIN_VERTEX_SHADER, fragment_shader=TERRAIN_FRAGMENT_SHADER)
        self.mesh: MeshData | None = None
        self._vbo = self._ibo = self._vao = None
        self._uploaded_generation = None
        self.rebuilds = 0
        self.samples = 0
        self.last_build_ms = 0.0
        self.background = bool(background)
        self._job: _MeshJob | None = None

    @property
    def outer_half_m(self) -> float:
        return self.horizon_m if self.horizon_m > 0 else self.window_m

    @property
    def fog_range_m(self) -> float:
        """Least horizontal distance from the camera to the mesh's outer edge: the fog hides it."""
        return self.outer_half_m - REBUILD_FRACTION * self.window_m

    def _lattice_and_stride(self, lat: float, lon: float) -> tuple[Lattice, int]:
        if not self._sources:
            return metric_lattice(self.spacing_m, self.spacing_m, lat), 1
        lattice = lattice_for(self._sources, lat, lon)
        if self.spacing_m is None:
            return lattice, 1
        m, _ = radii_of_curvature(lat)
        post_m = math.radians(lattice.dlat) * float(m)
        return lattice, max(1, round(self.spacing_m / post_m))

    def _off_centre_m(self, lat: float, lon: float) -> float:
        clat, clon = self.mesh.centre
        m, n = radii_of_curvature(lat)
        dn = math.radians(lat - clat) * float(m)
        de = math.radians((lon - clon + 180.0) % 360.0 - 180.0) * float(n) * math.cos(math.radians(lat))
        return max(abs(dn), abs(de))

    def update(self, camera: Camera) -> None:
        """Rebuild around the camera when it has left the window's central part (on a helper thread
        with ``background`` while the camera is inside the current window: a finished build is
        installed by the next update); re-upload after a rebase of the local origin."""
        lat, lon, _ = camera.geodetic()
        self.samples = 0
        self._collect()
        off = math.inf if self.mesh is None else self._off_centre_m(lat, lon)
        if off > REBUILD_FRACTION * self.window_m:
            if self.background and off <= self.window_m:  # the current mesh still holds the camera
                if self._job is None:
                    self._job = _MeshJob(self._build_args(lat, lon), self._build)
            else:
                self.cancel_build()
                t0 = time.perf_counter()
                mesh = build_mesh(self.terrain, **self._build_args(lat, lon))
                self._install(mesh, (time.perf_counter() - t0) * 1e3)
        if self._uploaded_generation != self.origin.generation:
            self._upload()

    @property
    def building(self) -> bool:
        """Whether a background build is under way."""
        return self._job is not None

    def _build_args(self, lat: float, lon: float) -> dict:
        lattice, stride = self._lattice_and_stride(lat, lon)
        return dict(lattice=lattice, lat=lat, lon=lon, window_m=self.window_m, horizon_m=self.horizon_m,
                    horizon_stride=self.horizon_stride, stride=stride, geoid_undulation_m=self.geoid_undulation_m)

    def _build(self, args: dict, cancelled) -> MeshData:
        return build_mesh(self.terrain, cancelled=cancelled, **args)

    def _collect(self) -> None:
        """Install a finished background build (raise what stopped it)."""
        job = self._job
        if job is None or not job.done.is_set():
            return
        self._job = None
        if job.error is not None:
            raise job.error
        self._install(job.mesh, job.build_ms)

    def cancel_build(self) -> None:
        """Drop a background build, if any: it stops before its next terrain call, its result unused."""
        if self._job is not None:
            self._job.cancel.set()
            self._job = None

    def _install(self, mesh: MeshData, build_ms: float) -> None:
        self.mesh = mesh
        self._uploaded_generation = None
        self.rebuilds += 1
        self.samples = len(mesh.positions_ecef)
        self.last_build_ms = build_ms
        lat, lon = mesh.centre
        log.info("terrain mesh around (%.5f, %.5f): %s + %s posts, %d triangles, %.0f ms", lat, lon,
                 mesh.window_shape, mesh.ring_shape, len(mesh.triangles), build_ms)

    def _upload(self) -> None:
        m = self.mesh
        self._release_buffers()
        self._uploaded_generation = self.origin.generation
        if len(m.triangles) == 0:  # nothing to draw here (all holes)
            return
        data = interleave(self.origin, m.positions_ecef, m.normals_ecef, m.height_msl_m, m.cos_slope)
        self._vbo = self.ctx.buffer(data.tobytes())
        self._ibo = self.ctx.buffer(m.triangles.astype("u4").tobytes())
        self._vao = self.ctx.vertex_array(
            self.program, [(self._vbo, "3f 3f 1f 1f", "in_position", "in_normal", "in_height", "in_cos_slope")],
            index_buffer=self._ibo, index_element_size=4)
        check_gl_error(self.ctx, "terrain upload")

    @property
    def solid_bounds(self) -> tuple | None:
        """(lat_min, lat_max, lon_min, lon_max) where the mesh surely covers the ground, or None."""
        return None if self.mesh is None else self.mesh.solid_bounds

    def surface_height_msl(self, lat: float, lon: float, top: bool = False) -> float:
        """The height MSL of the surface the mesh draws at (lat, lon): the window's triangle there
        (:func:`grid_surface_height`), which is not the terrain's bilinear surface (the renderer
        keeps the camera above this one); with ``top``, the highest corner of its cell. NaN
        outside the window (the camera never is: the mesh is rebuilt round it first) or on a hole."""
        m = self.mesh
        if m is None:
            return math.nan
        (lat0, lon0), (dlat, dlon) = m.window_corner, m.window_spacing_deg
        rows, cols = m.window_shape
        heights = m.height_msl_m[:rows * cols].reshape(rows, cols)
        return grid_surface_height(heights, (lat - lat0) / dlat, ((lon - lon0) % 360.0) / dlon, top)

    def surface_heights_msl(self, lats: np.ndarray, lons: np.ndarray) -> np.ndarray:
        """(n,) float64 :meth:`surface_height_msl` at (n,) degrees at once (the renderer lifts
        entities onto it: entities.ground_lifts)."""
        m = self.mesh
        lats, lons = np.asarray(lats, np.float64), np.asarray(lons, np.float64)
        if m is None:
            return np.full(lats.shape, math.nan)
        (lat0, lon0), (dlat, dlon) = m.window_corner, m.window_spacing_deg
        rows, cols = m.window_shape
        heights = m.height_msl_m[:rows * cols].reshape(rows, cols)
        return grid_surface_heights(heights, (lats - lat0) / dlat, ((lons - lon0) % 360.0) / dlon)

    def ground_height_msl(self, lat: float, lon: float) -> float:
        """At least the height MSL of the surface drawn at (lat, lon), for the renderer's near plane:
        the highest corner of the window's cell holding it (every point drawn in the cell is a
        convex combination of its corners). NaN where :meth:`surface_height_msl` is."""
        return self.surface_height_msl(lat, lon, top=True)

    @property
    def triangles(self) -> int:
        return 0 if self.mesh is None else len(self.mesh.triangles)

    @property
    def vertices(self) -> int:
        return 0 if self.mesh is None else len(self.mesh.positions_ecef)

    def draw(self, frame: Frame) -> None:
        if self._vao is None or self.triangles == 0:
            return
        import moderngl

        frame.write_common(self.program)
        self.ctx.enable(moderngl.CULL_FACE)
        self._vao.render(moderngl.TRIANGLES)
        self.ctx.disable(moderngl.CULL_FACE)

    def _release_buffers(self) -> None:
        for obj in (self._vao, self._vbo, self._ibo):
            if obj is not None:
                obj.release()
        self._vbo = self._ibo = self._vao = None

    def release(self) -> None:
        self.cancel_build()
        self._release_buffers()
        self.program.release()


class _MeshJob:
    """A mesh built on a daemon helper thread: ``build(args, cancelled)`` -> MeshData into
    ``mesh`` (or the exception into ``error``), ``done`` set at the end, ``build_ms`` its wall
    time. Setting ``cancel`` stops it before its next terrain call (no GL here: the layer uploads
    on the render thread). A daemon, so that a build still running does not hold up the exit of
    a process that has released its layer."""

    def __init__(self, args: dict, build):
        self.cancel = threading.Event()
        self.done = threading.Event()
        self.mesh: MeshData | None = None
        self.error: BaseException | None = None
        self.build_ms = 0.0
        self._thread = threading.Thread(target=self._run, args=(args, build), name="terrain-mesh-build",
                                        daemon=True)
        self._thread.start()

    def _run(self, args: dict, build) -> None:
        t0 = time.perf_counter()
        try:
            self.mesh = build(args, self.cancel.is_set)
        except BaseException as exc:  # noqa: BLE001 - handed to the render thread, which raises it
            self.error = exc
        finally:
            self.build_ms = (time.perf_counter() - t0) * 1e3
            self.done.set()

