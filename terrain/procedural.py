"""Unbounded procedural terrain by midpoint displacement on a global lattice.

Ammeter & Mikhailyuk, "Generation and Rendering of Virtual Terrain", §3: the
world is made of square blocks of (n + 1) x (n + 1) height posts, n a power of
two. A block's corners are set first (level 0); at each level L = 1, 2, ...
every square's centre takes the mean A of its 4 corners and every edge
midpoint the mean of its 2 endpoints (the paper's scheme, not diamond-square),
and each new post is displaced:

    H = A + (R - W) (1 + A)^2 M / L^E                                  (§3)

R uniform in [0, 1), M > 0 the maximum height, E > 1 the level exponent
(roughness), 0 <= W <= 1 the water parameter. (The paper's prose says E = 2
"halves" the displacement per step; its formula divides by L^E, which is what
is implemented.)

Interpretation choices, each needed to make the formula well defined:

* **Normalised heights.** (1 + A)^2 only makes sense with A dimensionless, so
  the recursion runs on a = H / M: ``a' = a + (R - W) (1 + a)^2 / L^E`` and
  H = M a. This is the formula as written with A measured in units of M.
* **Bounded growth.** Unclamped, (1 + a)^2 feeds on itself (a = 1 gives
  a' = 5, then 23, ...: heights blow up for E near 1), and below a = -1 it
  grows again, roughening the deepest water, the opposite of the paper's
  intent. The factor is therefore (clip(1 + a, 0, 2))^2, in [0, 4], equal to
  the paper's on the design range -1 <= a <= 1. By induction over levels
  every height then lies in
  ``[-W M (1 + 4 S), (1 - W) M (1 + 4 S)]`` with S = sum_{L=1}^{log2 n} L^-E
  (:func:`height_bounds_m`), for every M > 0, E > 1, 0 <= W <= 1.
* **Level 0.** The formula is undefined at L = 0; block corners take
  H = (R - W) M, the formula with A = 0 and L = 1.
* **Water.** H < 0 is lake or sea bed under water at sea level (§3: "points
  below sea level are covered with water at height 0"). Queries
  (``heights_into``, ``gradient_into``, ``raster_for``) answer the surface a
  vehicle meets: posts max(H, 0), interpolated bilinearly. The raw bed H stays
  available per block (:meth:`ProceduralTerrain.block`) for renderers that
  draw the water plane themselves.

Seamless by construction, in any generation order: blocks sit on one global
lattice of posts (row 0 at latitude -90, column 0 at longitude -180, spacing
360 / ``posts_per_turn`` degrees, a whole number of blocks per turn of
longitude and per half turn of latitude), R of each post is a counter-based
hash of (seed, global row, global column) (:func:`lattice_uniform`), and a
post's level is fixed by its global position. A post on a shared edge is
computed from that edge alone (endpoints and edge midpoints), so both blocks
compute it with the same operations on the same values: bit for bit equal,
without the paper's look-up of existing neighbours. Columns wrap modulo the
turn, so the antimeridian is an ordinary seam. The pole rows (global rows 0
and ``posts_per_turn / 2``) hash column 0 for every column and get no
displacement, so each pole is a single height.

Heights are metres above mean sea level; argument order is always (lat, lon)
in degrees.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numba
import numpy as np

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.raster import (CRS_GEOGRAPHIC, POST_SNAP_TOLERANCE, STATUS_OK, STATUS_OUTSIDE, Georef, Raster,
                            metres_per_index)

DEFAULT_POSTS_PER_TURN = 2**19  # 360 / 2^19 deg = 0.000687 deg: 76.4 m north-south
DEFAULT_BLOCK_CELLS = 256  # 257 x 257 posts, 19.6 km north-south per block
# LRU capacity in blocks. A block holds bed and surface, 2 x 257^2 float64 =
# 1.06 MB at the default size, so the default cache stays under 70 MB.
DEFAULT_CACHE_BLOCKS = 64
# Largest raster_for box, in posts (64 MiB of float64): a box of about
# 220 km x 220 km at the default spacing near the equator.
RASTER_FOR_MAX_POSTS = 1 << 23
# Most blocks one query (heights_into, gradient_into, raster_for) may generate anew, beyond those
# cached: a new block costs about 1.5 ms (257^2 posts, measured), so 4096 is about 6 s of work,
# where 1,000,000 scattered points would take 25-45 minutes. A legitimate call stays far below:
# an aircraft's contacts touch 1-4 blocks, a profile across a continent (5000 km) about 400, a
# renderer's region of 1250 km x 1250 km 4096, a ray batch over one area its box's blocks. A
# query over one full ring of block columns (rays over a pole: every longitude, a few rows) is
# always allowed: the cap is max(MAX_NEW_BLOCKS_PER_CALL, block columns per turn).
MAX_NEW_BLOCKS_PER_CALL = 4096
# ProceduralTerrain.boxes_cost: boxes whose posts sum to more than this are counted once where they
# overlap, on a grid of at most COST_GRID_CELLS cells a turn of longitude (1024 x 512 cells over the
# globe at most: a few milliseconds a pass).
COST_UNION_POSTS = 1 << 22
COST_GRID_CELLS = 1024
# Upper bound of level_exponent: L^-E for L >= 2 is then at most 2^-64 (heights change by less than
# a part in 1e19 beyond it), and L**E stays finite (2^20 levels at most: 20^64 ~ 1e83).
LEVEL_EXPONENT_MAX = 64.0
# Upper bound of max_height_m (m): about eleven times Mount Everest (8849 m). Heights stay finite
# and slopes meaningful: height_bounds_m is then below 1e5 (1 + 4 H_12) m, about 1.4e6 m, for any
# E > 1 and the largest block (H_12 the 12th harmonic number, log2(BLOCK_CELLS_MAX) levels).
MAX_HEIGHT_MAX_M = 1.0e5
# Largest block (cells a side): 4097^2 posts are 134 MB of float64 per array (bed, surface and
# the generation's temporaries, about 0.7 GB at once), the most one block may take.
BLOCK_CELLS_MAX = 4096
# Most memory the block cache may hold (bed and surface of cache_blocks blocks): 4 GiB.
CACHE_MAX_BYTES = 4 << 30
# Upper clamp of the roughness factor's base (1 + a): see the module docstring.
ROUGHNESS_BASE_MAX = 2.0
# Spherical radius used only to decide which blocks are near a viewer (IUGG mean
# radius R1); the 0.5 % spherical error is far below a block's size.
MEAN_EARTH_RADIUS_M = 6371008.8

_GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_MIX_1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX_2 = np.uint64(0x94D049BB133111EB)
_SHIFT_27, _SHIFT_30, _SHIFT_31 = np.uint64(27), np.uint64(30), np.uint64(31)
_UNIT_53 = 2.0**-53


@numba.njit(cache=True, nogil=True)
def mix64(x):
    """SplitMix64 (Steele, Lea & Flood, OOPSLA 2014) of one uint64: x + gamma, then the finaliser.

    Arithmetic wraps modulo 2^64. Callable from numba kernels; the one
    definition of the hash every lattice in terrain/ uses.
    """
    z = x + _GOLDEN_GAMMA
    z = (z ^ (z >> _SHIFT_30)) * _MIX_1
    z = (z ^ (z >> _SHIFT_27)) * _MIX_2
    return z ^ (z >> _SHIFT_31)


@numba.njit(cache=True, nogil=True)
def _mix64_flat(x):
    out = np.zeros(x.shape[0], dtype=np.uint64)
    for k in range(x.shape[0]):
        out[k] = mix64(x[k])
    return out


def splitmix64(x) -> np.ndarray:
    """:func:`mix64` over a uint64 array of any shape; returns the same shape."""
    x = np.asarray(x, dtype=np.uint64)
    return _mix64_flat(np.ascontiguousarray(x).reshape(-1)).reshape(x.shape)


def lattice_hash(seed: int, *coords) -> np.ndarray:
    """Counter-based hash of (seed, coords...): uint64, shape of the broadcast coords.

    coords: integer arrays (int64 or uint64; negative values are taken modulo
    2^64). h = mix64(seed), then h = mix64(h ^ c) for each coordinate c, so
    equal inputs give equal bits on every machine and in any evaluation order.
    """
    h = splitmix64(np.uint64(seed))
    for c in coords:
        c = np.asarray(c)
        c = c.astype(np.int64).view(np.uint64) if c.dtype.kind == "i" else c.astype(np.uint64)
        h = splitmix64(h ^ c)
    return h


def lattice_uniform(seed: int, rows, cols) -> np.ndarray:
    """R in [0, 1) for global lattice posts: float64, shape of broadcast(rows, cols).

    The top 53 bits of :func:`lattice_hash` scaled by 2^-53.
    """
    return (lattice_hash(seed, rows, cols) >> np.uint64(11)).astype(np.float64) * _UNIT_53


def midpoint_displacement(uniform: np.ndarray, level_exponent: float, water: float,
                          pinned_rows: np.ndarray | None = None) -> np.ndarray:
    """Normalised heights a = H / M of one block by the paper's subdivision (§3).

    uniform: (n + 1, n + 1) float64, R of each post, n a power of two.
    pinned_rows: (n + 1,) bool, rows whose posts get no displacement (the
    poles), or None. Returns (n + 1, n + 1) float64, dimensionless.

    Vectorised per level: all centres and edge midpoints of a level are set at
    once from the previous level's posts.
    """
    size = uniform.shape[0]
    n = size - 1
    if uniform.shape != (size, size) or n < 1 or n & (n - 1):
        raise ValueError(f"uniform must be (n + 1, n + 1) with n a power of two, got shape {uniform.shape}")
    moves = np.ones((size, 1)) if pinned_rows is None else (~pinned_rows).astype(np.float64)[:, None]
    a = np.zeros((size, size))
    a[::n, ::n] = uniform[::n, ::n] - water  # level 0: A = 0, L = 1
    s, level = n, 1
    while s > 1:
        h = s // 2
        lo, hi = slice(0, n, s), slice(s, None, s)
        centre = 0.25 * ((a[lo, lo] + a[lo, hi]) + (a[hi, lo] + a[hi, hi]))
        along_row = 0.5 * (a[::s, lo] + a[::s, hi])  # midpoints of east-west edges
        along_col = 0.5 * (a[lo, ::s] + a[hi, ::s])  # midpoints of north-south edges
        for rows, cols, mean in ((slice(h, None, s), slice(h, None, s), centre),
                                 (slice(0, None, s), slice(h, None, s), along_row),
                                 (slice(h, None, s), slice(0, None, s), along_col)):
            base = np.clip(1.0 + mean, 0.0, ROUGHNESS_BASE_MAX)
            step = (uniform[rows, cols] - water) * (base * base) / level**level_exponent
            a[rows, cols] = mean + step * moves[rows]
        s, level = h, level + 1
    return a


def height_bounds_m(max_height_m: float, level_exponent: float, water: float,
                    block_cells: int) -> tuple[float, float]:
    """(lowest, highest) height in metres any post of any block can take.

    Each level moves a post from the mean of earlier posts by at most
    4 (1 - W) / L^E up or 4 W / L^E down (factor clamped to [0, 4]); summing
    over the log2(n) levels after the corners' [-W, 1 - W) gives the bound.
    """
    levels = int(round(math.log2(block_cells)))
    growth = 1.0 + 4.0 * sum(lv**-level_exponent for lv in range(1, levels + 1))
    return -water * max_height_m * growth, (1.0 - water) * max_height_m * growth


@dataclass(frozen=True, eq=False)
class ProceduralBlock:
    """One generated block.

    bed_msl_m, surface_msl_m: (n + 1, n + 1) float64, read-only, metres above
    MSL; row 0 south, column 0 west; surface = max(bed, 0) (water at sea
    level). Post (i, j) lies at lat = lat0_deg + i * spacing_deg, lon =
    lon0_deg + j * spacing_deg.
    """

    row: int
    col: int
    lat0_deg: float
    lon0_deg: float
    spacing_deg: float
    bed_msl_m: np.ndarray
    surface_msl_m: np.ndarray


class ProceduralTerrain:
    """Endless midpoint-displacement terrain, generated in blocks as queries reach them.

    A height source for :class:`terrain.terrain.Terrain` (same methods as
    :class:`terrain.raster.Raster`). Blocks are kept in an LRU cache of at most
    ``cache_blocks`` blocks; :meth:`retain_near` drops those no viewer is near.
    A dropped block regenerates bit for bit. Thread-safe.

    Parameters are checked when it is made (InvalidArgument naming the field):
    0 < max_height_m <= MAX_HEIGHT_MAX_M, 1 < level_exponent <=
    LEVEL_EXPONENT_MAX, 0 <= water <= 1, block_cells a power of two in
    [2, BLOCK_CELLS_MAX], posts_per_turn a multiple of 2 block_cells up to
    2^40, cache_blocks at least 1 and holding at most CACHE_MAX_BYTES.
    """

    def __init__(self, seed: int, max_height_m: float = 1000.0, level_exponent: float = 2.0,
                 water: float = 0.3, block_cells: int = DEFAULT_BLOCK_CELLS,
                 posts_per_turn: int = DEFAULT_POSTS_PER_TURN, cache_blocks: int = DEFAULT_CACHE_BLOCKS,
                 name: str = "procedural"):
        _check_int("seed", seed, 0, 2**64 - 1)
        _check_real("max_height_m", max_height_m, lambda v: 0 < v <= MAX_HEIGHT_MAX_M,
                    f"within (0, {MAX_HEIGHT_MAX_M:g}]")
        _check_real("level_exponent", level_exponent, lambda v: 1 < v <= LEVEL_EXPONENT_MAX,
                    f"within (1, {LEVEL_EXPONENT_MAX:g}]")
        _check_real("water", water, lambda v: 0 <= v <= 1, "within [0, 1]")
        _check_int("block_cells", block_cells, 2, BLOCK_CELLS_MAX)
        if block_cells & (block_cells - 1):
            raise InvalidArgument("block_cells", "must be a power of two", value=block_cells)
        _check_int("posts_per_turn", posts_per_turn, 2 * block_cells, 2**40)
        if posts_per_turn % (2 * block_cells):
            raise InvalidArgument("posts_per_turn", f"must be a multiple of 2 * block_cells = {2 * block_cells}",
                                  value=posts_per_turn)
        block_bytes = 2 * 8 * (block_cells + 1) ** 2
        _check_int("cache_blocks", cache_blocks, 1, max(1, min(2**20, CACHE_MAX_BYTES // block_bytes)))
        self.seed = int(seed)
        self.max_height_m = float(max_height_m)
        self.level_exponent = float(level_exponent)
        self.water = float(water)
        self.block_cells = int(block_cells)
        self.posts_per_turn = int(posts_per_turn)
        self.cache_blocks = int(cache_blocks)
        self.name = name
        self.spacing_deg = 360.0 / self.posts_per_turn
        self.pole_row = self.posts_per_turn // 2  # global row of the north pole
        self.block_rows = self.pole_row // self.block_cells
        self.block_cols = self.posts_per_turn // self.block_cells
        self.blocks_generated = 0
        self.blocks_evicted = 0
        self._cache: OrderedDict[tuple[int, int], ProceduralBlock] = OrderedDict()
        self._lock = threading.Lock()

    # -- blocks ---------------------------------------------------------------

    def generate_block(self, row: int, col: int) -> ProceduralBlock:
        """Block (row, col) computed afresh, bypassing the cache.

        row in [0, block_rows) counts from the south pole; col wraps modulo
        block_cols, counted east from longitude -180.
        """
        if not 0 <= row < self.block_rows:
            raise InvalidArgument("row", f"must be within [0, {self.block_rows})", value=row)
        col %= self.block_cols
        n = self.block_cells
        g_rows = row * n + np.arange(n + 1, dtype=np.int64)
        g_cols = (col * n + np.arange(n + 1, dtype=np.int64)) % self.posts_per_turn
        pinned = (g_rows == 0) | (g_rows == self.pole_row)
        uniform = lattice_uniform(self.seed, g_rows[:, None], np.where(pinned[:, None], 0, g_cols[None, :]))
        bed = self.max_height_m * midpoint_displacement(uniform, self.level_exponent, self.water, pinned)
        surface = np.maximum(bed, 0.0)
        bed.flags.writeable = False
        surface.flags.writeable = False
        return ProceduralBlock(row, col, -90.0 + row * n * self.spacing_deg, -180.0 + col * n * self.spacing_deg,
                               self.spacing_deg, bed, surface)

    def block(self, row: int, col: int) -> ProceduralBlock:
        """Block (row, col) from the cache, generated (and the LRU one evicted) if absent."""
        key = (int(row), int(col) % self.block_cols)
        with self._lock:
            found = self._cache.get(key)
            if found is not None:
                self._cache.move_to_end(key)
                return found
            made = self.generate_block(*key)
            self.blocks_generated += 1
            self._cache[key] = made
            while len(self._cache) > self.cache_blocks:
                self._cache.popitem(last=False)
                self.blocks_evicted += 1
            return made

    def block_index(self, lat, lon) -> list[tuple[int, int]]:
        """Distinct (row, col) of the blocks holding the points (lat, lon), (n,) degrees.

        A point on a block edge belongs to the block north-east of it, as in the queries.
        """
        r, c = lattice_index(lat, lon, self.spacing_deg, self.posts_per_turn)
        i = np.minimum(np.floor(r), self.pole_row - 1).astype(np.int64) // self.block_cells
        j = np.floor(c).astype(np.int64) // self.block_cells
        return sorted(set(zip(i.tolist(), j.tolist())))

    def cached_blocks(self) -> list[tuple[int, int]]:
        """(row, col) of the cached blocks, least recently used first."""
        with self._lock:
            return list(self._cache)

    def retain_near(self, lat, lon, radius_m: float) -> int:
        """Drop cached blocks farther than radius_m from every viewer; return how many.

        lat, lon: (k,) float64 degrees, the viewers. A block is kept when some
        viewer is within radius_m plus the block's circumradius of its centre
        (spherical distance), so every block a viewer's disc touches stays.
        """
        lat = np.atleast_1d(np.asarray(lat, dtype=np.float64))
        lon = np.atleast_1d(np.asarray(lon, dtype=np.float64))
        if lat.shape != lon.shape or lat.ndim != 1:
            raise InvalidArgument("lon", f"must be a (k,) array like lat {lat.shape}, got shape {lon.shape}")
        if not (math.isfinite(radius_m) and radius_m >= 0):
            raise InvalidArgument("radius_m", "must be finite and >= 0", value=radius_m)
        with self._lock:
            keys = list(self._cache)
            if not keys or lat.size == 0:
                dropped = keys
            else:
                rows, cols = np.array(keys, dtype=np.float64).T
                half = 0.5 * self.block_cells * self.spacing_deg
                c_lat = -90.0 + (2.0 * rows + 1.0) * half
                c_lon = -180.0 + (2.0 * cols + 1.0) * half
                reach = radius_m + _sphere_distance_m(c_lat, c_lon, c_lat + half, c_lon + half)
                reach = np.maximum(reach, radius_m + _sphere_distance_m(c_lat, c_lon, c_lat - half, c_lon + half))
                dist = _sphere_distance_m(c_lat[:, None], c_lon[:, None], lat[None, :], lon[None, :])
                far = ~(dist <= reach[:, None]).any(axis=1)
                dropped = [k for k, f in zip(keys, far) if f]
            for key in dropped:
                del self._cache[key]
            self.blocks_evicted += len(dropped)
            return len(dropped)

    # -- height-source interface ----------------------------------------------

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        """Surface heights (m, MSL; water at 0) for the points still OUTSIDE.

        lat, lon: (n,) float64 degrees, (lat, lon) order; out_h: (n,) float64;
        out_status: (n,) uint8. Bilinear over the surface posts max(H, 0),
        exact at posts. The world is unbounded: every point is answered. Raises
        LimitExceeded, before generating any, when the points lie in more than
        MAX_NEW_BLOCKS_PER_CALL blocks not cached.
        """
        for sel, s, fy, fx, i, j in self._cells(lat, lon, out_status):
            out_h[sel] = _lerp2(s[i, j], s[i, j + 1], s[i + 1, j], s[i + 1, j + 1], fy, fx)
            out_status[sel] = STATUS_OK

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        """dh/d(east metre), dh/d(north metre) of the surface for points still OUTSIDE.

        Derivatives of the bilinear cell (the north-east cell on a post line,
        as in :func:`terrain.raster.gradient_into`); at the poles the pole row
        is constant, so the east derivative is 0. LimitExceeded as :meth:`heights_into`.
        """
        for sel, s, fy, fx, i, j in self._cells(lat, lon, out_status):
            dcol = (s[i, j + 1] - s[i, j]) * (1.0 - fy) + (s[i + 1, j + 1] - s[i + 1, j]) * fy
            drow = (s[i + 1, j] - s[i, j]) * (1.0 - fx) + (s[i + 1, j + 1] - s[i, j + 1]) * fx
            mx, my = metres_per_index(CRS_GEOGRAPHIC, self.spacing_deg, self.spacing_deg, lat[sel])
            out_de[sel] = dcol / mx
            out_dn[sel] = drow / my
            out_status[sel] = STATUS_OK

    def raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float) -> Raster:
        """A Raster of surface posts covering the box (degrees); never None.

        lon_max < lon_min means the box crosses the antimeridian. The raster's
        posts are lattice posts, so its bilinear surface is this terrain's.
        Raises LimitExceeded beyond RASTER_FOR_MAX_POSTS posts, or when it would generate more
        than MAX_NEW_BLOCKS_PER_CALL new blocks (a box of every longitude: a full ring of block
        columns, if more: rays over a pole).
        """
        r0, r1, c0, c1, posts, keys, limit = self._box(lat_min, lon_min, lat_max, lon_max)
        if posts > RASTER_FOR_MAX_POSTS:
            raise LimitExceeded("box posts", posts, RASTER_FOR_MAX_POSTS)
        self._check_new_blocks(keys, limit)
        sp, n = self.spacing_deg, self.block_cells
        out = np.zeros((r1 - r0 + 1, c1 - c0 + 1))
        for br in range(r0 // n, (r1 - 1) // n + 1):
            for bc in range(c0 // n, (c1 - 1) // n + 1):
                rs, re = max(r0, br * n), min(r1, br * n + n)
                cs, ce = max(c0, bc * n), min(c1, bc * n + n)
                surf = self.block(br, bc).surface_msl_m
                out[rs - r0:re - r0 + 1, cs - c0:ce - c0 + 1] = surf[rs - br * n:re - br * n + 1,
                                                                     cs - bc * n:ce - bc * n + 1]
        return Raster(out, Georef(CRS_GEOGRAPHIC, -180.0 + c0 * sp, -90.0 + r0 * sp, sp, sp), name=self.name,
                      vertical_datum="mean sea level (procedural)", source="procedural",
                      meta={"seed": self.seed, "first_post_row": r0, "first_post_col": c0})

    def box_cost(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float) -> tuple[int, int] | None:
        """(posts, blocks not cached) of the raster :meth:`raster_for` would make for the box,
        before making it; None where it would refuse the box (LimitExceeded)."""
        _, _, _, _, posts, keys, limit = self._box(lat_min, lon_min, lat_max, lon_max)
        if posts > RASTER_FOR_MAX_POSTS:
            return None
        new = self._new_count(keys)
        return None if new > limit else (posts, new)

    def boxes_cost(self, lat_min, lon_min, lat_max, lon_max) -> tuple[int, int]:
        """(posts, blocks not cached) under a set of boxes ((k,) degrees each, lon_min in [-180,
        180), lon_max above it, possibly past 180), without generating any: a work estimate for
        :class:`terrain.terrain.RayBudget`. Posts are the boxes' posts summed, or, when that sum
        passes COST_UNION_POSTS, the posts of the union of the boxes on a grid of COST_GRID_CELLS
        cells a turn (whole blocks or more), if fewer; blocks likewise (the blocks each box
        touches, summed, or those of the union's cells less the cached ones). Constant work
        beyond the sums: one pass over a grid of the boxes' rows."""
        sp, n = self.spacing_deg, self.block_cells
        lat_min, lat_max = np.clip(lat_min, -90.0, 90.0), np.clip(lat_max, -90.0, 90.0)
        span = np.minimum(np.maximum(lon_max - lon_min, 0.0), 360.0)
        r0 = np.floor((lat_min + 90.0) / sp).astype(np.int64)
        r1 = np.maximum(np.minimum(np.ceil((lat_max + 90.0) / sp).astype(np.int64), self.pole_row - 1), r0)
        c0 = np.floor((lon_min + 180.0) / sp).astype(np.int64)
        c1 = np.minimum(np.maximum(np.ceil((lon_min + 180.0 + span) / sp).astype(np.int64), c0),
                        c0 + self.posts_per_turn - 1)
        posts = int(((r1 - r0 + 1) * (c1 - c0 + 1)).sum())
        blocks = int(((r1 // n - r0 // n + 1) * (c1 // n - c0 // n + 1)).sum())
        if posts <= COST_UNION_POSTS and blocks <= COST_UNION_POSTS // (n * n):
            return posts, blocks
        g = max(n, self.posts_per_turn // COST_GRID_CELLS)  # posts a grid cell side: whole blocks
        cols = self.posts_per_turn // g
        g0, g1 = int(r0.min() // g), int(r1.max() // g)
        diff = np.zeros((g1 - g0 + 2, 2 * cols + 1), np.int32)  # a difference array of the boxes
        for rr, cc, sign in ((r0 // g - g0, c0 // g, 1), (r0 // g - g0, c1 // g + 1, -1),
                             (r1 // g - g0 + 1, c0 // g, -1), (r1 // g - g0 + 1, c1 // g + 1, 1)):
            np.add.at(diff, (rr, cc), sign)
        cover = np.cumsum(np.cumsum(diff, axis=0, dtype=np.int32), axis=1, dtype=np.int32)[:-1, :2 * cols] > 0
        cover = cover[:, :cols] | cover[:, cols:]  # columns past the turn wrap
        cells = int(cover.sum())
        per_cell = (g // n) ** 2
        with self._lock:
            cached = list(self._cache)
        held = sum(1 for br, bc in cached if 0 <= br * n // g - g0 < cover.shape[0] and cover[br * n // g - g0, bc * n // g])
        return min(posts, cells * g * g), min(blocks, cells * per_cell - held)

    covers_globe = True  # every (lat, lon) has a height: nothing is OUTSIDE

    @property
    def height_range_m(self) -> tuple[float, float]:
        """(lowest, highest) height the generator can make (:func:`height_bounds_m`), metres."""
        return height_bounds_m(self.max_height_m, self.level_exponent, self.water, self.block_cells)

    def describe(self) -> dict:
        """Metadata: bounds (the whole globe), spacing, datum and generation parameters."""
        mx, my = metres_per_index(CRS_GEOGRAPHIC, self.spacing_deg, self.spacing_deg, 0.0)
        lo, hi = height_bounds_m(self.max_height_m, self.level_exponent, self.water, self.block_cells)
        return {
            "name": self.name,
            "kind": "procedural",
            "source": "midpoint displacement (Ammeter & Mikhailyuk)",
            "crs": "EPSG:4326",
            "lat_min": -90.0, "lon_min": -180.0, "lat_max": 90.0, "lon_max": 180.0,
            "spacing_deg": self.spacing_deg,
            "spacing_east_m": float(mx), "spacing_north_m": float(my),  # at the equator
            "vertical_datum": "mean sea level (procedural); water surface at 0",
            "seed": self.seed,
            "max_height_m": self.max_height_m,
            "level_exponent": self.level_exponent,
            "water": self.water,
            "block_cells": self.block_cells,
            "posts_per_turn": self.posts_per_turn,
            "cache_blocks": self.cache_blocks,
            "height_min_m": lo, "height_max_m": hi,
        }

    # -- internals ------------------------------------------------------------

    def _box(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float):
        """(r0, r1, c0, c1, posts, block keys, new-block limit) of :meth:`raster_for`'s box: its
        global post rows [r0, r1] and columns [c0, c1] (unwrapped), their count, the distinct
        blocks (row * block_cols + col) holding them, and how many of those it may generate."""
        for nm, v in (("lat_min", lat_min), ("lon_min", lon_min), ("lat_max", lat_max), ("lon_max", lon_max)):
            _check_real(nm, v, lambda x: abs(x) <= 540.0, "within +-540 degrees")
        if not -90.0 <= lat_min <= lat_max <= 90.0:
            raise InvalidArgument("lat_min", f"must satisfy -90 <= lat_min <= lat_max={lat_max} <= 90",
                                  value=lat_min)
        span = lon_max - lon_min if lon_max >= lon_min else lon_max - lon_min + 360.0
        sp = self.spacing_deg
        r0 = max(0, math.floor((lat_min + 90.0) / sp))
        r1 = min(self.pole_row, math.ceil((lat_max + 90.0) / sp))
        if r1 == r0:
            r0, r1 = (r0, r0 + 1) if r0 < self.pole_row else (r0 - 1, r0)
        c0 = math.floor((lon_min + 180.0) / sp)
        c1 = max(c0 + 1, math.ceil((lon_min + 180.0 + span) / sp))
        posts = (r1 - r0 + 1) * (c1 - c0 + 1)
        n = self.block_cells
        rows, cols = np.arange(r0 // n, (r1 - 1) // n + 1), np.arange(c0 // n, (c1 - 1) // n + 1)
        if posts > RASTER_FOR_MAX_POSTS:
            keys = np.zeros(0, np.int64)  # refused on its posts: no need to list them
        else:
            keys = np.unique(np.repeat(rows, cols.size) * self.block_cols + np.tile(cols % self.block_cols, rows.size))
        limit = max(MAX_NEW_BLOCKS_PER_CALL, self.block_cols) if span >= 360.0 else MAX_NEW_BLOCKS_PER_CALL
        return r0, r1, c0, c1, posts, keys, limit

    def _new_count(self, keys) -> int:
        """How many of the distinct blocks ``keys`` ((k,) int64, row * block_cols + col) are not cached."""
        if keys.size == 0:
            return 0
        with self._lock:
            cached = np.array([r * self.block_cols + c for r, c in self._cache], np.int64)
        return int(keys.size - np.isin(keys, cached).sum())

    def _check_new_blocks(self, keys, limit: int) -> None:
        """Raise LimitExceeded when more of the distinct blocks ``keys`` ((k,) int64, row *
        block_cols + col) than ``limit`` are not cached: before any is generated."""
        if keys.size <= limit:
            return
        new = self._new_count(keys)
        if new > limit:
            raise LimitExceeded("points (new procedural blocks)", new, limit,
                                f"each new block of {self.block_cells + 1}^2 posts is generated, about 1.5-4 ms; "
                                "ask over a smaller area or in several calls")

    def _cells(self, lat, lon, out_status):
        """Yield (sel, surface, fy, fx, i, j) per block for the points still OUTSIDE.

        sel: (k,) int64 point indices; surface: the block's surface posts;
        fy, fx: (k,) float64 cell fractions; i, j: (k,) int64 the cell's south-west
        post within the block.
        """
        todo = np.flatnonzero(out_status == STATUS_OUTSIDE)
        if todo.size == 0:
            return
        r, c = lattice_index(lat[todo], lon[todo], self.spacing_deg, self.posts_per_turn)
        i = np.minimum(np.floor(r), self.pole_row - 1).astype(np.int64)
        j = np.floor(c).astype(np.int64)
        fy, fx = r - i, c - j
        n = self.block_cells
        key = (i // n) * self.block_cols + j // n
        order = np.argsort(key, kind="stable")
        starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
        self._check_new_blocks(key[order][starts], MAX_NEW_BLOCKS_PER_CALL)
        for part in np.split(order, starts[1:]):
            br, bc = divmod(int(key[part[0]]), self.block_cols)
            yield todo[part], self.block(br, bc).surface_msl_m, fy[part], fx[part], i[part] - br * n, j[part] - bc * n


def lattice_index(lat, lon, spacing_deg: float, posts_per_turn: int):
    """(lat, lon) degrees -> fractional global (row, col), float64 (n,) each.

    Row 0 at latitude -90, column 0 at longitude -180; columns wrap into
    [0, posts_per_turn). Values within POST_SNAP_TOLERANCE of an integer snap
    to it so posts are hit exactly.
    """
    r = (np.asarray(lat, dtype=np.float64) + 90.0) / spacing_deg
    c = ((np.asarray(lon, dtype=np.float64) + 180.0) % 360.0) / spacing_deg
    r, c = _snap(r), _snap(c)
    return r, np.where(c >= posts_per_turn, c - posts_per_turn, c)


def _snap(v: np.ndarray) -> np.ndarray:
    near = np.floor(v + 0.5)
    return np.where(np.abs(v - near) < POST_SNAP_TOLERANCE, near, v)


def _lerp2(h00, h01, h10, h11, fy, fx):
    """Bilinear blend, exact at the cell's south-west post and along rows of equal posts.

    The a + (b - a) t form returns a at t = 0 and a for a == b, so a pole row
    (all posts equal) answers its one height for every longitude; fy == 1
    occurs only on the north-pole row and takes that row as is.
    """
    south = h00 + (h01 - h00) * fx
    north = h10 + (h11 - h10) * fx
    return np.where(fy == 1.0, north, south + (north - south) * fy)


def _sphere_distance_m(lat1, lon1, lat2, lon2):
    """Great-circle distance (m) on the mean-radius sphere (haversine); arrays broadcast."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dp, dl = p2 - p1, np.radians(np.asarray(lon2) - np.asarray(lon1))
    s = np.sin(0.5 * dp) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(0.5 * dl) ** 2
    return 2.0 * MEAN_EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(s, 0.0, 1.0)))


def _check_int(name: str, value, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InvalidArgument(name, f"must be an integer within [{lo}, {hi}]", value=value)


def _check_real(name: str, value, ok, what: str) -> None:
    """Raise InvalidArgument unless value is a finite real number with ok(value) true."""
    if (isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating))
            or not math.isfinite(value) or not ok(value)):
        raise InvalidArgument(name, f"must be a finite number {what}", value=value)
