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

Runtime parameters (§3: M, E, W "can be changed by the user at runtime"; a
new square's "borders are fitted to the borders of already existing neighbor
squares", the rest filled "using the currently active parameters").
:meth:`ProceduralTerrain.set_parameters` starts a new *epoch* of (M, E, W);
the blocks cached at that moment are the paper's existing squares and keep
the epoch they were made in for good (a frozen block dropped from the cache
regenerates as it was). Every other block belongs to the current epoch. A
post's height is made by the oldest (lowest-epoch) block holding it, with
that block's parameters: a corner by the oldest of its 4 blocks, an edge by
the older of its 2, a pole by the oldest of its block row, the interior by
its own block. That is the paper's preset of corner and border posts from
existing neighbours, computed instead of looked up: an edge is displaced
from its two ends alone, so a younger block recomputes an older
neighbour's edge exactly (the same operations on the same values, bit for
bit) without needing that block in the cache, and the answer does not
depend on the order blocks are generated in. A preset post is taken in
metres; the younger block's own posts displace from it in units of its own
M. While the parameters never change this is the single-epoch world above,
bit for bit.

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

# The generation parameters' defaults (§3's M, E, W): hills up to about a kilometre, the
# paper's E = 2 ("reduction by half with every step"), about a third of the world under water.
DEFAULT_MAX_HEIGHT_M = 1000.0
DEFAULT_LEVEL_EXPONENT = 2.0
DEFAULT_WATER = 0.3
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
# Displacements fade towards the poles from this latitude (degrees): a post's (R - W) M / L^E is
# scaled by cos(lat) / cos(POLAR_FADE_LAT_DEG) beyond it. The lattice's columns crowd together
# there (a post's east-west neighbour is cos(lat) as far as at the equator) while the paper's
# displacements do not shrink with them, so slopes grew as 1 / cos(lat): p99 slope (rise over
# run) 1.1 at 40-45 degrees, 2.6 at 70-75, 9.1 at 85-86 and 32 at 88-89 (seed 7, the default
# parameters), a cliff field that stopped every ground vehicle near a pole. Faded, slopes beyond
# the fade stay those of its latitude, and each pole is a single height at sea level (its level-0
# value times a fade of ~1e-16). Below the fade nothing changes, bit for bit.
POLAR_FADE_LAT_DEG = 70.0
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


def polar_fade(lat_deg) -> np.ndarray:
    """The factor of a post's displacement at latitude ``lat_deg`` (degrees): 1 up to
    POLAR_FADE_LAT_DEG, cos(lat) / cos(POLAR_FADE_LAT_DEG) beyond it (0 at the poles, to rounding)."""
    fade = np.cos(np.radians(np.asarray(lat_deg, np.float64))) / math.cos(math.radians(POLAR_FADE_LAT_DEG))
    return np.clip(fade, 0.0, 1.0)


def midpoint_displacement(uniform: np.ndarray, level_exponent: float, water: float,
                          pinned_rows: np.ndarray | None = None, preset: np.ndarray | None = None,
                          row_scale: np.ndarray | None = None) -> np.ndarray:
    """Normalised heights a = H / M of one block by the paper's subdivision (§3).

    uniform: (n + 1, n + 1) float64, R of each post, n a power of two.
    pinned_rows: (n + 1,) bool, rows whose posts get no displacement (the
    poles), or None. preset: (n + 1, n + 1) float64, dimensionless, the posts
    already set (the paper's borders fitted to existing neighbours), NaN
    elsewhere, or None: a preset post keeps its value and later levels
    displace from it. row_scale: (n + 1,) float64, each row's factor of its
    posts' displacements, level 0's too (:func:`polar_fade`), or None (1).
    Returns (n + 1, n + 1) float64, dimensionless.

    Vectorised per level: all centres and edge midpoints of a level are set at
    once from the previous level's posts.
    """
    size = uniform.shape[0]
    n = size - 1
    if uniform.shape != (size, size) or n < 1 or n & (n - 1):
        raise ValueError(f"uniform must be (n + 1, n + 1) with n a power of two, got shape {uniform.shape}")
    if preset is not None and preset.shape != uniform.shape:
        raise ValueError(f"preset must be shaped like uniform {uniform.shape}, got shape {preset.shape}")
    moves = np.ones((size, 1)) if pinned_rows is None else (~pinned_rows).astype(np.float64)[:, None]
    if row_scale is not None:
        if np.shape(row_scale) != (size,):
            raise ValueError(f"row_scale must be ({size},), got shape {np.shape(row_scale)}")
        moves = moves * np.asarray(row_scale, np.float64)[:, None]
    free = None if preset is None else np.isnan(preset)
    a = np.zeros((size, size))
    a[::n, ::n] = uniform[::n, ::n] - water  # level 0: A = 0, L = 1 (a pole's corners too: not displaced later)
    if row_scale is not None:
        a[::n, ::n] *= np.asarray(row_scale, np.float64)[::n, None]
    if free is not None:
        a[::n, ::n] = np.where(free[::n, ::n], a[::n, ::n], preset[::n, ::n])
    s, level = n, 1
    while s > 1:
        h = s // 2
        lo, hi = slice(0, n, s), slice(s, None, s)
        centre = 0.25 * ((a[lo, lo] + a[lo, hi]) + (a[hi, lo] + a[hi, hi]))
        along_row = 0.5 * (a[::s, lo] + a[::s, hi])  # midpoints of east-west edges
        along_col = 0.5 * (a[lo, ::s] + a[hi, ::s])  # midpoints of north-south edges
        div = level**level_exponent
        for rows, cols, mean in ((slice(h, None, s), slice(h, None, s), centre),
                                 (slice(0, None, s), slice(h, None, s), along_row),
                                 (slice(h, None, s), slice(0, None, s), along_col)):
            made = _displaced(mean, uniform[rows, cols], water, div, moves[rows])
            a[rows, cols] = made if free is None else np.where(free[rows, cols], made, preset[rows, cols])
        s, level = h, level + 1
    return a


def line_displacement(uniform: np.ndarray, level_exponent: float, water: float, ends: np.ndarray,
                      scale: np.ndarray | None = None) -> np.ndarray:
    """Normalised heights of one block edge, displaced from its two ends alone.

    uniform: (n + 1,) float64, R of the edge's posts; ends: (2,) float64,
    dimensionless, its end posts; scale: (n + 1,) float64, each post's factor of
    its displacement (its row's :func:`polar_fade`), or None (1). Returns
    (n + 1,) float64. The same
    operations on the same values as :func:`midpoint_displacement` gives a
    block's border row or column (an edge's midpoints are means of that
    edge's posts only), so a block can recompute, bit for bit, the edge an
    older neighbour made with other parameters.
    """
    n = uniform.shape[0] - 1
    if uniform.ndim != 1 or n < 1 or n & (n - 1) or np.shape(ends) != (2,):
        raise ValueError(f"uniform must be (n + 1,) with n a power of two and ends (2,), got shapes "
                         f"{uniform.shape} and {np.shape(ends)}")
    a = np.zeros(n + 1)
    a[0], a[n] = ends
    s, level = n, 1
    while s > 1:
        h = s // 2
        mean = 0.5 * (a[0:n:s] + a[s::s])
        a[h::s] = _displaced(mean, uniform[h::s], water, level**level_exponent, 1.0 if scale is None else scale[h::s])
        s, level = h, level + 1
    return a


def _displaced(mean, uniform, water: float, div: float, moves):
    """The paper's H = A + (R - W)(1 + A)^2 M / L^E in units of M, factor clamped (module
    docstring), for posts whose mean of neighbours is ``mean``; div = L^E; moves 0 pins a post."""
    base = np.clip(1.0 + mean, 0.0, ROUGHNESS_BASE_MAX)
    return mean + (uniform - water) * (base * base) / div * moves


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


def mixed_height_bounds_m(parameters, block_cells: int) -> tuple[float, float]:
    """(lowest, highest) height in metres of a world whose blocks were made with any of
    ``parameters`` ((M, E, W) tuples, the epochs of :meth:`ProceduralTerrain.set_parameters`).

    A post is a level-0 corner of some epoch, or the mean of posts of earlier levels moved by one
    epoch's step at its level; so by induction over levels the bound is the largest corner plus
    the sum over levels of the largest step (and likewise down). One tuple gives
    :func:`height_bounds_m`.
    """
    parameters = list(parameters)
    if len(parameters) == 1:
        return height_bounds_m(*parameters[0], block_cells)
    levels = int(round(math.log2(block_cells)))
    down = max(w * m for m, _, w in parameters)
    up = max((1.0 - w) * m for m, _, w in parameters)
    for lv in range(1, levels + 1):
        down += max(4.0 * w * m * lv**-e for m, e, w in parameters)
        up += max(4.0 * (1.0 - w) * m * lv**-e for m, e, w in parameters)
    return -down, up


def check_parameters(max_height_m, level_exponent, water,
                     names=("max_height_m", "level_exponent", "water")) -> tuple[float, float, float]:
    """(M, E, W) as floats, checked against the paper's ranges and this module's bounds:
    0 < M <= MAX_HEIGHT_MAX_M, 1 < E <= LEVEL_EXPONENT_MAX, 0 <= W <= 1; else InvalidArgument
    naming the field by ``names`` (a command line names its options) and the value."""
    _check_real(names[0], max_height_m, lambda v: 0 < v <= MAX_HEIGHT_MAX_M, f"within (0, {MAX_HEIGHT_MAX_M:g}]")
    _check_real(names[1], level_exponent, lambda v: 1 < v <= LEVEL_EXPONENT_MAX,
                f"within (1, {LEVEL_EXPONENT_MAX:g}]")
    _check_real(names[2], water, lambda v: 0 <= v <= 1, "within [0, 1]")
    return float(max_height_m), float(level_exponent), float(water)


def check_seed(seed, name: str = "seed") -> int:
    """The seed as an int when it is an integer within [0, 2^64) (the lattice hash takes it as a
    uint64); else InvalidArgument naming the field by ``name`` (a command line: its option,
    --procedural) and the value."""
    _check_int(name, seed, 0, 2**64 - 1)
    return int(seed)


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
    ``cache_blocks`` blocks; :meth:`retain_near` drops those no viewer is near
    and keeps the viewers' blocks out of the LRU's reach until its next call.
    A dropped block regenerates bit for bit. Thread-safe.

    Parameters are checked when it is made (InvalidArgument naming the field):
    0 < max_height_m <= MAX_HEIGHT_MAX_M, 1 < level_exponent <=
    LEVEL_EXPONENT_MAX, 0 <= water <= 1, block_cells a power of two in
    [2, BLOCK_CELLS_MAX], posts_per_turn a multiple of 2 block_cells up to
    2^40, cache_blocks at least 1 and holding at most CACHE_MAX_BYTES. They
    are read-only: M, E and W change through :meth:`set_parameters`, which
    keeps the seams (module docstring), the others not at all.
    """

    def __init__(self, seed: int, max_height_m: float = DEFAULT_MAX_HEIGHT_M,
                 level_exponent: float = DEFAULT_LEVEL_EXPONENT, water: float = DEFAULT_WATER,
                 block_cells: int = DEFAULT_BLOCK_CELLS, posts_per_turn: int = DEFAULT_POSTS_PER_TURN,
                 cache_blocks: int = DEFAULT_CACHE_BLOCKS, name: str = "procedural"):
        check_seed(seed)
        params = check_parameters(max_height_m, level_exponent, water)
        _check_int("block_cells", block_cells, 2, BLOCK_CELLS_MAX)
        if block_cells & (block_cells - 1):
            raise InvalidArgument("block_cells", "must be a power of two", value=block_cells)
        _check_int("posts_per_turn", posts_per_turn, 2 * block_cells, 2**40)
        if posts_per_turn % (2 * block_cells):
            raise InvalidArgument("posts_per_turn", f"must be a multiple of 2 * block_cells = {2 * block_cells}",
                                  value=posts_per_turn)
        block_bytes = 2 * 8 * (block_cells + 1) ** 2
        _check_int("cache_blocks", cache_blocks, 1, max(1, min(2**20, CACHE_MAX_BYTES // block_bytes)))
        self._seed = int(seed)
        self._block_cells = int(block_cells)
        self._posts_per_turn = int(posts_per_turn)
        self._cache_blocks = int(cache_blocks)
        self.name = name
        self.spacing_deg = 360.0 / self.posts_per_turn
        self.pole_row = self.posts_per_turn // 2  # global row of the north pole
        self.block_rows = self.pole_row // self.block_cells
        self.block_cols = self.posts_per_turn // self.block_cells
        self.blocks_generated = 0
        self.blocks_evicted = 0
        self._cache: OrderedDict[tuple[int, int], ProceduralBlock] = OrderedDict()
        self._lock = threading.Lock()
        self._epochs: list[tuple[float, float, float]] = [params]  # (M, E, W) of each epoch, oldest first
        self._frozen: dict[tuple[int, int], int] = {}  # block -> its epoch, for blocks cached at a change
        self._pole_epoch: dict[int, int] = {}  # block row holding a pole -> the oldest epoch frozen in it
        self._viewers: tuple[np.ndarray, np.ndarray, float] | None = None  # retain_near's (lat, lon, radius_m)
        self._near: set[tuple[int, int]] = set()  # cached blocks near a viewer: evicted last

    seed = property(lambda self: self._seed, doc="The lattice hash's seed (read-only).")
    block_cells = property(lambda self: self._block_cells, doc="Cells a block side, a power of two (read-only).")
    posts_per_turn = property(lambda self: self._posts_per_turn, doc="Lattice posts a turn of longitude (read-only).")
    cache_blocks = property(lambda self: self._cache_blocks, doc="The LRU's capacity in blocks (read-only).")
    max_height_m = property(lambda self: self._epochs[-1][0], doc="M now, metres (read-only: set_parameters).")
    level_exponent = property(lambda self: self._epochs[-1][1], doc="E now (read-only: set_parameters).")
    water = property(lambda self: self._epochs[-1][2], doc="W now (read-only: set_parameters).")

    @property
    def parameter_changes(self) -> int:
        """How many times :meth:`set_parameters` changed M, E or W (the current epoch's number)."""
        return len(self._epochs) - 1

    def set_parameters(self, max_height_m: float | None = None, level_exponent: float | None = None,
                       water: float | None = None) -> bool:
        """Change M, E and W at runtime (§3; None keeps one); whether anything changed.

        Blocks made from now on use the new values; the blocks cached now keep theirs for
        good, and a new block's corners and borders shared with them are theirs (module
        docstring), so every seam stays bit for bit whatever is generated when. Checked as
        the constructor checks them (InvalidArgument naming the field and value). Each change
        remembers the blocks cached then (a dictionary entry each, at most cache_blocks).
        """
        with self._lock:
            m, e, w = self._epochs[-1]
            params = check_parameters(m if max_height_m is None else max_height_m,
                                      e if level_exponent is None else level_exponent,
                                      w if water is None else water)
            if params == self._epochs[-1]:
                return False
            now = len(self._epochs) - 1
            for key in self._cache:
                epoch = self._frozen.setdefault(key, now)
                if key[0] in (0, self.block_rows - 1):
                    self._pole_epoch[key[0]] = min(self._pole_epoch.get(key[0], epoch), epoch)
            self._epochs.append(params)
            return True

    # -- blocks ---------------------------------------------------------------

    def generate_block(self, row: int, col: int) -> ProceduralBlock:
        """Block (row, col) computed afresh, bypassing the cache.

        row in [0, block_rows) counts from the south pole; col wraps modulo
        block_cols, counted east from longitude -180.
        """
        if not 0 <= row < self.block_rows:
            raise InvalidArgument("row", f"must be within [0, {self.block_rows})", value=row)
        col %= self.block_cols
        with self._lock:
            plan = self._plan(row, col)
        return self._make(row, col, plan)

    def _plan(self, row: int, col: int):
        """(own epoch, corner epochs (2, 2) [south/north, west/east], edge epochs {side: epoch})
        of block (row, col): whose parameters make each of its shared posts (module
        docstring). Called under the lock."""
        current = len(self._epochs) - 1

        def epoch(r, c):
            return self._frozen.get((r, c % self.block_cols), current) if 0 <= r < self.block_rows else None

        grid = [[epoch(row + dr, col + dc) for dc in (-1, 0, 1)] for dr in (-1, 0, 1)]
        own = grid[1][1]
        pole = {0: self._pole_epoch.get(row, own) if row == 0 else None,
                1: self._pole_epoch.get(row, own) if row == self.block_rows - 1 else None}
        pole = {k: None if v is None else min(v, own) for k, v in pole.items()}
        corners = [[pole[i] if pole[i] is not None else
                    min(grid[i + di][j + dj] for di in (0, 1) for dj in (0, 1)) for j in (0, 1)] for i in (0, 1)]
        edges = {"south": pole[0] if pole[0] is not None else min(own, grid[0][1]),
                 "north": pole[1] if pole[1] is not None else min(own, grid[2][1]),
                 "west": min(own, grid[1][0]), "east": min(own, grid[1][2])}
        return own, corners, edges, list(self._epochs)

    def _make(self, row: int, col: int, plan) -> ProceduralBlock:
        """Block (row, col) generated by ``plan`` (:meth:`_plan`)."""
        own, corners, edges, epochs = plan
        n = self.block_cells
        g_rows = row * n + np.arange(n + 1, dtype=np.int64)
        g_cols = (col * n + np.arange(n + 1, dtype=np.int64)) % self.posts_per_turn
        pinned = (g_rows == 0) | (g_rows == self.pole_row)
        uniform = lattice_uniform(self.seed, g_rows[:, None], np.where(pinned[:, None], 0, g_cols[None, :]))
        fade = self.row_fade(g_rows)
        m, e, w = epochs[own]
        preset = self._preset(uniform, own, corners, edges, epochs, (bool(pinned[0]), bool(pinned[n])), fade)
        if preset is None:
            bed = m * midpoint_displacement(uniform, e, w, pinned, row_scale=fade)
        else:
            bed = m * midpoint_displacement(uniform, e, w, pinned, preset / m, row_scale=fade)
            bed = np.where(np.isnan(preset), bed, preset)  # older posts as they made them, in metres
        surface = np.maximum(bed, 0.0)
        bed.flags.writeable = False
        surface.flags.writeable = False
        return ProceduralBlock(row, col, -90.0 + row * n * self.spacing_deg, -180.0 + col * n * self.spacing_deg,
                               self.spacing_deg, bed, surface)

    def row_fade(self, g_rows) -> np.ndarray:
        """:func:`polar_fade` of global lattice rows (row 0 the south pole): each row's factor of
        its posts' displacements, the same in every block that holds the row."""
        return polar_fade(-90.0 + np.asarray(g_rows, np.int64) * self.spacing_deg)

    def _preset(self, uniform, own, corners, edges, epochs, pole_rows, fade):
        """(n + 1, n + 1) float64 metres: the posts older blocks make (their corners and
        edges, with their parameters), NaN elsewhere; None when there are none. pole_rows:
        (south, north) bool, whether the block's first or last row is a pole; fade: (n + 1,)
        the rows' :meth:`row_fade`."""
        if min(min(corners[0]), min(corners[1]), *edges.values()) >= own:
            return None
        n = self.block_cells
        out = np.full(uniform.shape, np.nan)
        # Level 0 of the epoch making it, as midpoint_displacement computes it (M (R - W) fade would differ in
        # the last bit where fade is not 1).
        corner_m = [[epochs[c][0] * ((uniform[i * n, j * n] - epochs[c][2]) * fade[i * n]) for j, c in enumerate(pair)]
                    for i, pair in enumerate(corners)]
        for i in (0, 1):
            for j in (0, 1):
                if corners[i][j] < own:
                    out[i * n, j * n] = corner_m[i][j]
        sides = {"south": (np.s_[0, :], (0, 0), (0, 1)), "north": (np.s_[n, :], (1, 0), (1, 1)),
                 "west": (np.s_[:, 0], (0, 0), (1, 0)), "east": (np.s_[:, n], (0, 1), (1, 1))}
        for side, (line, c0, c1) in sides.items():
            epoch = edges[side]
            if epoch >= own:
                continue
            if side in ("south", "north") and pole_rows[c0[0]]:  # a pole: one height (pinned rows are not displaced)
                out[line] = corner_m[c0[0]][0]
                continue
            m, e, w = epochs[epoch]
            ends = [corner_m[i][j] / m if corners[i][j] < epoch else (uniform[i * n, j * n] - w) * fade[i * n]
                    for i, j in (c0, c1)]
            scale = np.broadcast_to(fade[:, None], uniform.shape)[line]  # each post's row's fade
            made = m * line_displacement(uniform[line], e, w, np.array(ends), scale)
            for k, (i, j) in ((0, c0), (n, c1)):
                if corners[i][j] < epoch:
                    made[k] = corner_m[i][j]
            out[line] = made
        return out

    def block(self, row: int, col: int) -> ProceduralBlock:
        """Block (row, col) from the cache, generated (and one evicted) if absent: the least
        recently used of those no viewer of :meth:`retain_near` is near, else of all."""
        key = (int(row), int(col) % self.block_cols)
        with self._lock:
            found = self._cache.get(key)
            if found is not None:
                self._cache.move_to_end(key)
                return found
            if not 0 <= key[0] < self.block_rows:
                raise InvalidArgument("row", f"must be within [0, {self.block_rows})", value=row)
            made = self._make(*key, self._plan(*key))
            self.blocks_generated += 1
            self._cache[key] = made
            if self._viewers is not None and self._near_mask([key])[0]:
                self._near.add(key)
            while len(self._cache) > self.cache_blocks:
                victim = next((k for k in self._cache if k not in self._near), None)
                if victim is None:  # the viewers' blocks alone fill the cache
                    victim = next(iter(self._cache))
                del self._cache[victim]
                self._near.discard(victim)
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
        """The viewers are now at (lat, lon): drop the cached blocks farther than radius_m from
        every one of them (§2: "squares dropping out of view have to be removed"); return how
        many. A caller with views (a simulation's agents and observers) calls it as they move.

        lat, lon: (k,) float64 degrees, the viewers; radius_m: metres, how far a view
        reaches (the paper's far edge of the view, hidden in fog). A block is near a viewer
        within radius_m plus the block's circumradius of its centre (spherical distance), so
        every block a viewer's disc touches stays. Until the next call the blocks near these
        viewers, cached now or made later, are the last the LRU evicts: a large query (a
        coarse clipmap level over a thousand blocks) cycles through the other slots and
        leaves the viewers' blocks, unless they alone fill the cache. No viewer (k = 0)
        drops every block and ends that protection.
        """
        lat = np.atleast_1d(np.asarray(lat, dtype=np.float64))
        lon = np.atleast_1d(np.asarray(lon, dtype=np.float64))
        if lat.shape != lon.shape or lat.ndim != 1:
            raise InvalidArgument("lon", f"must be a (k,) array like lat {lat.shape}, got shape {lon.shape}")
        for name, v in (("lat", lat), ("lon", lon)):
            bad = np.flatnonzero(~np.isfinite(v))
            if bad.size:
                raise InvalidArgument(name, "must be finite", index=int(bad[0]), value=float(v[bad[0]]))
        if not (math.isfinite(radius_m) and radius_m >= 0):
            raise InvalidArgument("radius_m", "must be finite and >= 0", value=radius_m)
        with self._lock:
            self._viewers = (lat.copy(), lon.copy(), float(radius_m)) if lat.size else None
            keys = list(self._cache)
            near = self._near_mask(keys) if keys else np.zeros(0, bool)
            dropped = [k for k, kept in zip(keys, near) if not kept]
            for key in dropped:
                del self._cache[key]
            self._near = {k for k, kept in zip(keys, near) if kept}
            self.blocks_evicted += len(dropped)
            return len(dropped)

    def _near_mask(self, keys) -> np.ndarray:
        """(k,) bool: which blocks ((row, col) pairs) a viewer of :meth:`retain_near` is near;
        all False without viewers. Called under the lock."""
        if self._viewers is None:
            return np.zeros(len(keys), bool)
        lat, lon, radius_m = self._viewers
        rows, cols = np.array(keys, dtype=np.float64).reshape(-1, 2).T
        half = 0.5 * self.block_cells * self.spacing_deg
        c_lat = -90.0 + (2.0 * rows + 1.0) * half
        c_lon = -180.0 + (2.0 * cols + 1.0) * half
        reach = radius_m + np.maximum(_sphere_distance_m(c_lat, c_lon, c_lat + half, c_lon + half),
                                      _sphere_distance_m(c_lat, c_lon, c_lat - half, c_lon + half))
        dist = _sphere_distance_m(c_lat[:, None], c_lon[:, None], lat[None, :], lon[None, :])
        return (dist <= reach[:, None]).any(axis=1)

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
        """(lowest, highest) height the generator can make, metres: :func:`height_bounds_m`, or
        after :meth:`set_parameters` :func:`mixed_height_bounds_m` of the epochs any block may
        still be made in (the frozen blocks' and the current one)."""
        with self._lock:
            used = sorted(set(self._frozen.values()) | {len(self._epochs) - 1})
            params = [self._epochs[k] for k in used]
        return mixed_height_bounds_m(params, self.block_cells)

    def describe(self) -> dict:
        """Metadata: bounds (the whole globe), spacing, datum and generation parameters (M, E
        and W now; parameter_changes: how many times :meth:`set_parameters` changed them)."""
        mx, my = metres_per_index(CRS_GEOGRAPHIC, self.spacing_deg, self.spacing_deg, 0.0)
        lo, hi = self.height_range_m
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
            "parameter_changes": self.parameter_changes,
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
