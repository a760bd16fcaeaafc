"""Geometry clipmap data: nested levels of posts around a focus, stored toroidally.

The CPU side of the clipmap terrain layer (client/render/clipmap_layer.py draws
it); pure numpy, no GL, so the tests can compare it with a rebuild bit for bit.
Thesis: ../shared/seeds/clipmaps-jsbsim-thesis.txt §3.1 (after Losasso and
Hoppe, "Geometry clipmaps", SIGGRAPH 2004).

**Lattice.** Level k (0 the finest, L - 1 the coarsest) has posts at
``lat = lat0 + i dlat 2^k``, ``lon = lon0 + j dlon 2^k`` for integers i, j:
the terrain's own post lattice (its first source's; client/render/terrain_mesh
``lattice_for``) scaled by a power of two, so level k + 1's post (i, j) is level
k's post (2i, 2j) and the levels nest exactly (thesis §3.1.2, "power-of-two
spacing"). A profile may start finer than the DEM (the terrain's fractal
detail, or bilinear, answers there). Columns are not wrapped at a fixed
meridian: a longitude's column is taken on the turn of the globe nearest the
last update's focus (:meth:`Clipmap.unwrapped_dlon`), so the regions follow
the focus across every meridian by strips, their columns running on past a
turn; the terrain is asked, and normals are placed, at the longitude within
[-180, 180).

**Regions** (thesis §3.1.2). A level's *clip region* is the n x n posts
(n = 2^m - 1) it holds: rows i0 .. i0 + n - 1, columns j0 .. j0 + n - 1, with
i0 and j0 even so that its corners are posts of the coarser level. Its
*active region* is the n x n square centred on the focus (snapped to even
indices); an update moves the clip region onto it. What is drawn (its *render
region*) is the clip region, cropped to lie inside the coarser level's drawn
region (a level that fell behind), minus the finer level's drawn region (the
hole): :func:`drawn_regions`, :func:`ring_rects`.

**Toroidal storage** (thesis §3.1.3). Post (i, j) of a level lives at texel
(i mod n, j mod n) of that level's arrays, so moving the clip region writes
only the L-shaped strips it uncovered (:func:`uncovered_rects`), split at the
wrap (:func:`toroidal_pieces`); storage is allocated once.

**What a post stores.** Its ECEF position in float64 (``pos_ecef``) and, for
the GPU, its offset from the level's own float64 origin as float32 plus its
height MSL (``texel``, RGBA32F). A level's origin is set when the level is
filled and moved (offsets recomputed from the float64 copy, no terrain query)
once the clip region has drifted ORIGIN_DRIFT_EXTENTS of its extent from it,
so a float32 offset never exceeds a few level extents: the precision of the
geometry scales with the level's spacing (global-terrain-flight-sim §6). The
normal map holds 2 x 2 normals per post (thesis §3.1.7: "at least twice the
resolution of the geometry"), ECEF unit vectors at the half-lattice points,
stored toroidally the same way with period 2n.

**Sample budget** (thesis §3.1.4). :meth:`Clipmap.update` processes levels
coarse to fine, each moved whole onto its active region, until the frame's
budget of terrain samples (heights + normals) is spent; the finer levels then
keep their old regions (they fall behind and are cropped by the coarser at
draw time). A level that must move does so even over budget when it is the
first of the frame, so the coarsest always keeps up. The first load (and a
caller that asks, ``unlimited``) fills every level at once.

Posts the terrain does not cover (height NaN) are stored at MSL 0 with an up
normal: they draw as water at sea level, as the sea shell does around them.

**From a terrain store.** When the terrain reads first from a terrain store
(terrain/store.py) and the clipmap's lattice is the store's (``lattice_for``
gives it: posts from the North Pole and the 180th meridian), level k's posts
are the store's level k + f posts, so they are decoded straight from that
level of the pyramid (:meth:`Clipmap.sample_posts`): a coarse level over
hundreds of kilometres never decodes the fine data under it (thesis §3.1.8:
"region-of-interest queries at any power-of-two resolution"). The store's
per-level cache keeps the cells within STORE_CACHE_RADIUS_CELLS of the viewer
(global-terrain-flight-sim §5), trimmed at most once a second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from sortie.errors import InvalidArgument
from terrain.geodesy import geodetic_to_ecef

MAX_LEVELS = 16
MIN_N, MAX_N = 15, 1023
ORIGIN_DRIFT_EXTENTS = 1.0  # move a level's origin once its region centre is this many extents from it
NORMALS_PER_POST = 4  # the normal map is 2 x 2 per post
STORE_CACHE_RADIUS_CELLS = 3.5  # cells kept around the viewer at every store level (FSX: 2.5 - 4.5)
STORE_CACHE_TRIM_S = 1.0
WRITE_LOG_MOVES = 16  # moves a level remembers the written posts of (LevelStore.written_since)


@dataclass(frozen=True)
class Rect:
    """Lattice rows i0 .. i1 and columns j0 .. j1, inclusive (empty when i1 < i0 or j1 < j0)."""

    i0: int
    j0: int
    i1: int
    j1: int

    @property
    def empty(self) -> bool:
        return self.i1 < self.i0 or self.j1 < self.j0

    @property
    def size(self) -> int:
        return 0 if self.empty else (self.i1 - self.i0 + 1) * (self.j1 - self.j0 + 1)

    def intersect(self, other: Rect) -> Rect:
        return Rect(max(self.i0, other.i0), max(self.j0, other.j0), min(self.i1, other.i1), min(self.j1, other.j1))

    def contains(self, other: Rect) -> bool:
        return (not other.empty and self.i0 <= other.i0 and self.j0 <= other.j0 and other.i1 <= self.i1
                and other.j1 <= self.j1)


def clip_region(i0: int, j0: int, n: int) -> Rect:
    return Rect(i0, j0, i0 + n - 1, j0 + n - 1)


def active_origin(focus_i: float, focus_j: float, n: int) -> tuple[int, int]:
    """(i0, j0), both even, of the n x n region centred on the focus (level lattice units)."""
    half = (n - 1) / 2.0
    return 2 * math.floor((focus_i - half) / 2.0 + 0.5), 2 * math.floor((focus_j - half) / 2.0 + 0.5)


def uncovered_rects(old: Rect | None, new: Rect) -> list[Rect]:
    """The parts of ``new`` not in ``old`` (all of it when old is None or disjoint): at most two
    rectangles, the L-shaped strips a move uncovers."""
    if old is None or old.intersect(new).empty:
        return [new]
    out = []
    if new.i0 < old.i0:  # rows south of the old region
        out.append(Rect(new.i0, new.j0, old.i0 - 1, new.j1))
    if new.i1 > old.i1:
        out.append(Rect(old.i1 + 1, new.j0, new.i1, new.j1))
    i0, i1 = max(new.i0, old.i0), min(new.i1, old.i1)  # the rows both share
    if new.j0 < old.j0:
        out.append(Rect(i0, new.j0, i1, old.j0 - 1))
    if new.j1 > old.j1:
        out.append(Rect(i0, old.j1 + 1, i1, new.j1))
    return [r for r in out if not r.empty]


def toroidal_pieces(r: Rect, period: int) -> list[tuple[Rect, int, int]]:
    """``r`` (at most ``period`` posts a side) split where the toroidal storage wraps: a list of
    (piece in lattice indices, its first texel row, its first texel column)."""
    if r.i1 - r.i0 + 1 > period or r.j1 - r.j0 + 1 > period:
        raise InvalidArgument("rect", f"must fit the storage ({period} a side)", value=r)
    out = []
    for a0, a1 in _split(r.i0, r.i1, period):
        for b0, b1 in _split(r.j0, r.j1, period):
            out.append((Rect(a0, b0, a1, b1), a0 % period, b0 % period))
    return out


def _split(lo: int, hi: int, period: int) -> list[tuple[int, int]]:
    wrap = lo + (period - lo % period)  # the first index stored at texel 0 after lo
    return [(lo, hi)] if hi < wrap else [(lo, wrap - 1), (wrap, hi)]


def ring_rects(region: Rect, hole: Rect | None) -> list[Rect]:
    """Cells of ``region`` outside ``hole`` as at most four rectangles of *cells* (a cell (i, j)
    spans posts i..i+1, j..j+1; cell rectangles hold the cells' lower-left posts), the thesis'
    index regions: south and north strips across, west and east strips between them."""
    cells = Rect(region.i0, region.j0, region.i1 - 1, region.j1 - 1)
    if hole is None or hole.empty:
        return [] if cells.empty else [cells]
    h = Rect(hole.i0, hole.j0, hole.i1 - 1, hole.j1 - 1)  # the hole's cells
    out = [Rect(cells.i0, cells.j0, h.i0 - 1, cells.j1), Rect(h.i1 + 1, cells.j0, cells.i1, cells.j1),
           Rect(h.i0, cells.j0, h.i1, h.j0 - 1), Rect(h.i0, h.j1 + 1, h.i1, cells.j1)]
    return [r for r in out if not r.empty]


def blocks(cell_rects: list[Rect], size: int) -> np.ndarray:
    """(m, 4) int32 (i0, j0, i1, j1) post rectangles of blocks of at most size x size cells
    tiling ``cell_rects`` (block b covers cells i0..i1-1, j0..j1-1)."""
    out = []
    for r in cell_rects:
        ii = np.arange(r.i0, r.i1 + 1, size)
        jj = np.arange(r.j0, r.j1 + 1, size)
        gi, gj = np.meshgrid(ii, jj, indexing="ij")
        b = np.stack([gi, gj, np.minimum(gi + size, r.i1 + 1), np.minimum(gj + size, r.j1 + 1)], -1)
        out.append(b.reshape(-1, 4))
    return np.concatenate(out).astype(np.int32) if out else np.zeros((0, 4), np.int32)


@dataclass
class LevelStore:
    """One level's toroidal storage (CPU mirror of its textures)."""

    k: int
    n: int
    region: Rect | None = None
    origin_ecef: np.ndarray = field(default_factory=lambda: np.zeros(3))
    origin_generation: int = 0
    pos_ecef: np.ndarray = None  # (n, n, 3) float64 at texel (i mod n, j mod n)
    texel: np.ndarray = None  # (n, n, 4) float32: offset from origin_ecef (ECEF axes), height MSL
    normal: np.ndarray = None  # (2n, 2n, 4) float16: unit normal (ECEF axes), 0
    version: int = 0  # counts the writes to the storage (culling bounds are cached against it)
    _range: tuple = (-1, math.inf, -math.inf)  # (version, h_min, h_max), computed when asked
    # (version, Rect of posts written by the move to that version), the last WRITE_LOG_MOVES moves
    writes: list = field(default_factory=list)

    def __post_init__(self):
        self.pos_ecef = np.zeros((self.n, self.n, 3))
        self.texel = np.zeros((self.n, self.n, 4), np.float32)
        self.normal = np.zeros((2 * self.n, 2 * self.n, 4), np.float16)

    @property
    def valid(self) -> bool:
        return self.region is not None

    def written_since(self, version: int) -> list[Rect] | None:
        """The post rectangles written after ``version``; None when the log no longer reaches
        back that far (take every post as written). A post of the current region outside
        them holds the value it held at ``version``: a move writes only posts new to the
        region, and two posts of one region never share a storage slot."""
        if version == self.version:
            return []
        if not self.writes or self.writes[0][0] > version + 1:
            return None
        return [r for v, r in self.writes if v > version]

    def _log_writes(self, rects: list[Rect]) -> None:
        self.writes += [(self.version, r) for r in rects]
        first = self.version - WRITE_LOG_MOVES
        if self.writes and self.writes[0][0] <= first:
            self.writes = [(v, r) for v, r in self.writes if v > first]

    @property
    def h_min(self) -> float:
        """The lowest height (m MSL) in the storage (inf before the first fill)."""
        return self._height_range()[0]

    @property
    def h_max(self) -> float:
        return self._height_range()[1]

    def _height_range(self) -> tuple[float, float]:
        # Computed when asked, not at every move: the scan of the whole storage cost a tenth
        # of a move at n = 255, its 1 MB cold after a frame's rendering.
        if self.region is None:
            return math.inf, -math.inf
        if self._range[0] != self.version:
            self._range = (self.version, *_height_range(self.texel))
        return self._range[1], self._range[2]

    def unrolled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(texel (n, n, 4), pos_ecef (n, n, 3), normal (2n, 2n, 4)) in lattice order, row 0 = region.i0."""
        r = self.region
        ti = np.arange(r.i0, r.i0 + self.n) % self.n
        tj = np.arange(r.j0, r.j0 + self.n) % self.n
        ni = np.arange(2 * r.i0, 2 * r.i0 + 2 * self.n) % (2 * self.n)
        nj = np.arange(2 * r.j0, 2 * r.j0 + 2 * self.n) % (2 * self.n)
        return (self.texel[np.ix_(ti, tj)], self.pos_ecef[np.ix_(ti, tj)], self.normal[np.ix_(ni, nj)])


@dataclass(frozen=True)
class Upload:
    """A piece of a level's storage to send to its textures: ``what`` "texel" or "normal",
    texel rows/columns [r0, r0 + rows) x [c0, c0 + cols); ``all``: the whole level."""

    k: int
    what: str
    r0: int
    c0: int
    rows: int
    cols: int


@dataclass
class UpdateStats:
    samples: int = 0  # terrain samples taken this frame (heights + normals)
    levels_moved: int = 0
    levels_behind: int = 0  # levels that wanted to move but the budget was spent
    origins_moved: int = 0


def globe_levels(dlon_deg: float, n: int) -> int:
    """How many levels of n posts a lattice of ``dlon_deg`` spacing has before a level's n - 1
    cells span more than the globe's 360 degrees of longitude (at least 1): level k spans
    (n - 1) 2^k dlon."""
    span = (n - 1) * float(dlon_deg)
    if not (span > 0.0 and math.isfinite(span)):
        return 1
    return max(1, int(math.floor(math.log2(360.0 / span) + 1e-12)) + 1)


class Clipmap:
    """L levels of n x n posts on ``lattice`` (terrain_mesh.Lattice of the finest level's spacing
    over 2^finest_exponent... see the module docstring), filled from ``terrain`` (heights(lat, lon)
    and normals(lat, lon): Terrain or TerrainClient). geoid_undulation_m: ellipsoid height =
    MSL + N. budget: terrain samples per update (heights + 4 normals per post)."""

    def __init__(self, terrain, lattice, levels: int, n: int, budget: int, geoid_undulation_m: float = 0.0):
        if not (isinstance(levels, int) and 1 <= levels <= MAX_LEVELS):
            raise InvalidArgument("levels", f"must be an integer in [1, {MAX_LEVELS}]", value=levels)
        if not (isinstance(n, int) and MIN_N <= n <= MAX_N and (n + 1) & n == 0):
            raise InvalidArgument("n", f"must be 2^m - 1 in [{MIN_N}, {MAX_N}]", value=n)
        if not (isinstance(budget, int) and budget > 0):
            raise InvalidArgument("budget", "must be a positive number of samples", value=budget)
        self.terrain = terrain
        self.lattice = lattice
        self.n = n
        self.budget = budget
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.levels = [LevelStore(k, n) for k in range(levels)]
        self.stats = UpdateStats()
        # Optional cutout(lat, lon, spacing_m) -> metres to lower the surface (under geomipmap insets:
        # terrain/inset.cutout_depth_m, given the level's post spacing).
        self.cutout = None
        self.store, self.store_level0 = _store_on_lattice(terrain, lattice)
        if self.store is not None:  # views sharing the store keep each other's cells cached
            import weakref

            weakref.finalize(self, self.store.forget_viewer, id(self))
        self.remote_store_levels, self.remote_level0 = _remote_store_on_lattice(terrain, lattice)
        # Land classes (terrain/texture.py, global-terrain-flight-sim §7.1) in the normal map's
        # fourth channel, one per normal texel, when asked for: the base colour of the terrain.
        self.land_classes = False
        self._water_tolerance_m = None  # the water level (water_level_m): the terrain's quantisation bound
        self._trimmed_at = -math.inf
        self.store_blocks = 0  # level blocks read straight from the store
        # The last update's focus in degrees east of lon0, unwrapped (continuous from one update to
        # the next): lattice columns are taken on the turn nearest it (unwrapped_dlon).
        self._focus_dlon = 0.0

    # -- geometry of the lattice

    def spacing_deg(self, k: int) -> tuple[float, float]:
        return self.lattice.dlat * 2 ** k, self.lattice.dlon * 2 ** k

    def spacing_m(self, k: int) -> float:
        """Level k's north-south post spacing, metres (the mean Earth radius: for sizes, not geometry)."""
        return math.radians(self.lattice.dlat * 2 ** k) * 6_371_000.0

    def extent_m(self, k: int) -> float:
        return (self.n - 1) * self.spacing_m(k)

    def focus_index(self, k: int, lat, lon) -> tuple:
        """(i, j), fractional, of (lat, lon) (degrees, scalars or arrays) in level k's lattice, the
        column on the turn of the globe nearest the last update's focus (:meth:`unwrapped_dlon`)."""
        dlat, dlon = self.spacing_deg(k)
        return (lat - self.lattice.lat0) / dlat, self.unwrapped_dlon(lon) / dlon

    def unwrapped_dlon(self, lon):
        """Degrees east of the lattice's lon0 of ``lon`` (scalar or array), on the turn nearest the
        last update's focus: [-180, 180) plus whole turns. Columns so taken run on continuously
        past every meridian, lon0 + 180 and the antimeridian included: a level's region follows
        the focus across them by toroidal strips as anywhere else (thesis §3.1.3, §3.1.4), where
        a column wrapped at a fixed meridian jumped a whole turn and refilled every level."""
        dl = (lon - self.lattice.lon0 + 180.0) % 360.0 - 180.0
        turns = np.floor((self._focus_dlon - dl) / 360.0 + 0.5)
        return dl + 360.0 * turns

    def latlon(self, k: int, i, j) -> tuple[np.ndarray, np.ndarray]:
        dlat, dlon = self.spacing_deg(k)
        return (self.lattice.lat0 + np.asarray(i, np.float64) * dlat,
                self.lattice.lon0 + np.asarray(j, np.float64) * dlon)

    def heights_at(self, lat, lon) -> np.ndarray:
        """(n,) float64 heights MSL (m) of the levels' surfaces at points (lat, lon) ((n,)
        degrees), from the posts they hold (no terrain query): each from the finest valid level
        whose region holds the point's cell, bilinear between that cell's four posts; NaN where
        no level holds it."""
        lat = np.asarray(lat, np.float64).ravel()
        lon = np.asarray(lon, np.float64).ravel()
        out = np.full(lat.shape, np.nan)
        todo = np.isfinite(lat) & np.isfinite(lon)
        n = self.n
        for level in self.levels:
            if not level.valid or not todo.any():
                continue
            fi, fj = self.focus_index(level.k, lat, lon)
            r = level.region
            with np.errstate(invalid="ignore"):
                i, j = np.floor(np.where(todo, fi, r.i0)), np.floor(np.where(todo, fj, r.j0))
            inside = todo & (i >= r.i0) & (i + 1 <= r.i1) & (j >= r.j0) & (j + 1 <= r.j1)
            if not inside.any():
                continue
            ii, jj = i[inside].astype(np.int64), j[inside].astype(np.int64)
            fy, fx = fi[inside] - ii, fj[inside] - jj
            h = level.texel[..., 3]
            h00, h01 = h[ii % n, jj % n], h[ii % n, (jj + 1) % n]
            h10, h11 = h[(ii + 1) % n, jj % n], h[(ii + 1) % n, (jj + 1) % n]
            out[inside] = (h00 * (1.0 - fx) + h01 * fx) * (1.0 - fy) + (h10 * (1.0 - fx) + h11 * fx) * fy
            todo &= ~inside
        return out

    # -- sampling

    def sample_posts(self, k: int, r: Rect) -> tuple[np.ndarray, np.ndarray]:
        """(ECEF positions (rows, cols, 3) float64, heights MSL (rows, cols)) of a rectangle of posts."""
        lat_rows, lon_cols = self.latlon(k, np.arange(r.i0, r.i1 + 1), np.arange(r.j0, r.j1 + 1))
        lat_rows = np.clip(lat_rows, -90.0, 90.0)
        lon_cols = _wrapped_lon(lon_cols)
        lat, lon = np.broadcast_arrays(lat_rows[:, None], lon_cols[None, :])
        h = self._store_posts(k, r)
        if h is None and hasattr(self.terrain, "height_grid"):  # in process: one index a row and a column
            h = self.terrain.height_grid(lat_rows, lon_cols).height_msl_m
        elif h is None:
            h = np.asarray(self.terrain.heights(lat.ravel(), lon.ravel()).height_msl_m, np.float64).reshape(lat.shape)
        h = np.where(np.isfinite(h), h, 0.0)  # no data: water at sea level
        surface = h.copy()
        if self.cutout is not None:
            surface -= self.cutout(lat.ravel(), lon.ravel(), self.spacing_m(k)).reshape(lat.shape)
        # A row's and a column's trigonometry once each: geodetic_to_ecef broadcasts them.
        return geodetic_to_ecef(lat_rows[:, None], lon_cols[None, :], surface + self.geoid_undulation_m), h

    def _store_posts(self, k: int, r: Rect) -> np.ndarray | None:
        """Heights of a rectangle of level k's posts decoded from the store's own level (NaN
        outside its data), or None when the store's rectangles there do not hold all of it. The
        posts come from every region holding some of them (TerrainStore.level_posts): two nearby
        regions' coarser levels share tiles, each region holding part of their data."""
        if self.remote_store_levels and k + self.remote_level0 < self.remote_store_levels:
            return self._remote_store_posts(k, r)
        if self.store is None or k + self.store_level0 >= self.store.levels:
            return None
        # Clipmap row i is at latitude 90 + i dlat: store row -i (rows count south from the pole);
        # clipmap column j is lattice column j (from -180, any turn).
        posts = self.store.level_posts(k + self.store_level0, -r.i1, -r.i0 + 1, r.j0, r.j1 + 1)
        if posts is None:
            return None
        self.store_blocks += 1
        return posts[0][::-1]

    def _remote_store_posts(self, k: int, r: Rect) -> np.ndarray | None:
        """As :meth:`_store_posts` through a terrain service over a store (GetRegion of the
        store's level k + f): a thin client fetches each level's posts, not bilinear samples
        of level 0."""
        from sortie.errors import SortieError

        m = k + self.remote_level0
        dlat, dlon = self.spacing_deg(k)
        lat_s, lat_n = 90.0 + r.i0 * dlat, 90.0 + r.i1 * dlat
        lon_w, lon_e = -180.0 + r.j0 * dlon, -180.0 + r.j1 * dlon
        if lat_s < -90.0 or lat_n > 90.0:
            return None
        try:
            grid = self.terrain.get_region(m, lat_s, (lon_w + 180.0) % 360.0 - 180.0, lat_n,
                                           (lon_w + 180.0) % 360.0 - 180.0 + (lon_e - lon_w))
        except SortieError:
            return None
        a = round((grid.lat_north_deg - lat_n) / dlat)
        b = round(((lon_w - grid.lon_west_deg + 180.0) % 360.0 - 180.0) / dlon)
        rows, cols = r.i1 - r.i0 + 1, r.j1 - r.j0 + 1
        if a < 0 or b < 0 or a + rows > grid.heights.shape[0] or b + cols > grid.heights.shape[1]:
            return None
        h = np.asarray(grid.heights[a:a + rows, b:b + cols], np.float64)
        self.store_blocks += 1
        return h[::-1]

    def sample_normals(self, k: int, r: Rect) -> np.ndarray:
        """(2 rows, 2 cols, 3) ECEF unit normals at the half-lattice points of a rectangle of posts
        (half-lattice point (p, q) is at post coordinates (p / 2, q / 2)), from the terrain's
        gradients in one pass (:func:`_normals_ecef`: the ENU -> ECEF rotation is separable on
        the lattice, per-row and per-column sines and cosines)."""
        lat_rows, lon_cols = self.latlon(k, np.arange(2 * r.i0, 2 * r.i1 + 2) / 2.0,
                                         np.arange(2 * r.j0, 2 * r.j1 + 2) / 2.0)
        lat_rows, lon_cols = np.clip(lat_rows, -90.0, 90.0), _wrapped_lon(lon_cols)
        gradient_grid = getattr(self.terrain, "gradient_grid", None)
        if gradient_grid is not None:  # in process: one index a row and a column
            de, dn, _ = gradient_grid(lat_rows, lon_cols)
        else:  # a terrain service answers normals: their slopes are -n_e / n_u, -n_n / n_u (n_u > 0)
            n = np.asarray(self.terrain.normals(np.repeat(lat_rows, lon_cols.size),
                                                np.tile(lon_cols, lat_rows.size)).normal_enu, np.float64)
            de, dn = -n[:, 0] / n[:, 2], -n[:, 1] / n[:, 2]
        out = np.empty((lat_rows.size, lon_cols.size, 3))
        lam = np.radians(lon_cols)
        _normals_ecef(np.ascontiguousarray(de).ravel(), np.ascontiguousarray(dn).ravel(), np.radians(lat_rows),
                      np.sin(lam), np.cos(lam), out)
        return out

    def classes_of(self, k: int, r: Rect, h: np.ndarray, normals_ecef: np.ndarray) -> np.ndarray:
        """Land class (terrain.texture.class_map) of each normal texel of a rectangle: the height
        of its post, the slope of its normal, band noise placed by world position (so that
        neighbouring strips agree). (2 rows, 2 cols) float."""
        from terrain.texture import class_map, noise_positions

        lat_rows, lon_cols = self.latlon(k, np.arange(2 * r.i0, 2 * r.i1 + 2) / 2.0,
                                         np.arange(2 * r.j0, 2 * r.j1 + 2) / 2.0)
        lat_rows, lon_cols = np.clip(lat_rows, -90.0, 90.0), _wrapped_lon(lon_cols)
        sl, cl = np.sin(np.radians(lat_rows))[:, None], np.cos(np.radians(lat_rows))[:, None]
        so, co = np.sin(np.radians(lon_cols))[None, :], np.cos(np.radians(lon_cols))[None, :]
        up = np.stack(np.broadcast_arrays(cl * co, cl * so, sl), axis=-1)
        cos_slope = np.clip(np.sum(normals_ecef * up, axis=-1), -1.0, 1.0)
        slope = np.degrees(np.arccos(cos_slope))
        heights = np.repeat(np.repeat(h, 2, axis=0), 2, axis=1)
        dy = self.spacing_m(k) / 2.0
        dx = dy * self.lattice.dlon / self.lattice.dlat * max(float(np.cos(np.radians(lat_rows.mean()))), 1e-6)
        # The class noise at each sample's ECEF position, as `sortie terrain texture` places it: the
        # same classes at the same place as the CLI's texture, no seam at the antimeridian.
        return class_map(heights, slope, dx, dy, lat_rows[:, None],
                         noise_xyz_m=noise_positions(lat_rows[:, None], lon_cols[None, :]),
                         water_tolerance_m=self.water_level_m).astype(np.float64)

    @property
    def water_level_m(self) -> float:
        """Posts at or below this height MSL are water: 0, or over a lossy store half its step (its
        sea decodes within step/2 of 0 m; client/render/shading.water_level_m, terrain/texture.py).
        The class map's water test and the decimation's coastline rule take it."""
        if self._water_tolerance_m is None:
            from client.render.shading import water_level_m

            self._water_tolerance_m = water_level_m(self.terrain)
        return self._water_tolerance_m

    @staticmethod
    def cost(r: Rect) -> int:
        return r.size * (1 + NORMALS_PER_POST)

    # -- updates

    def update(self, focus_lat: float, focus_lon: float, unlimited: bool = False) -> list[Upload]:
        """Move levels onto their active regions around the focus, coarse to fine, within the
        budget (``unlimited``: every level, as a first load does); the storage pieces to upload."""
        self.stats = UpdateStats()
        self._focus_dlon = float(self.unwrapped_dlon(focus_lon))
        uploads: list[Upload] = []
        spent = 0
        behind = False
        for level in reversed(self.levels):
            fi, fj = self.focus_index(level.k, focus_lat, focus_lon)
            new = clip_region(*active_origin(fi, fj, self.n), self.n)
            if level.region == new:
                continue
            todo = uncovered_rects(level.region, new)
            cost = sum(self.cost(r) for r in todo)
            if not unlimited and (behind or (spent > 0 and spent + cost > self.budget)):
                behind = True
                self.stats.levels_behind += 1
                continue
            uploads += self._move(level, new, todo)
            spent += cost
        self.stats.samples = spent
        if self.store is not None and uploads:
            import time

            now = time.monotonic()
            self.store.set_viewer(id(self), focus_lat, focus_lon)
            if now - self._trimmed_at >= STORE_CACHE_TRIM_S:
                self._trimmed_at = now
                self.store.retain_near([], STORE_CACHE_RADIUS_CELLS)
        return uploads

    def _move(self, level: LevelStore, new: Rect, todo: list[Rect]) -> list[Upload]:
        n = self.n
        refill = level.region is None or todo == [new]
        c_lat, c_lon = self.latlon(level.k, (new.i0 + new.i1) / 2.0, (new.j0 + new.j1) / 2.0)
        centre = np.asarray(geodetic_to_ecef(float(np.clip(c_lat, -90.0, 90.0)), float(c_lon), 0.0), float).reshape(3)
        move_origin = refill or np.linalg.norm(centre - level.origin_ecef) > ORIGIN_DRIFT_EXTENTS * self.extent_m(
            level.k)
        if move_origin:
            level.origin_ecef = centre
            level.origin_generation += 1
            self.stats.origins_moved += 1
        uploads = []
        for r in todo:
            pos, h = self.sample_posts(level.k, r)
            normals = self.sample_normals(level.k, r)
            if self.land_classes:
                normals = np.concatenate([normals, self.classes_of(level.k, r, h, normals)[..., None]], axis=-1)
            for piece, t0, c0 in toroidal_pieces(r, n):
                a, b = piece.i0 - r.i0, piece.j0 - r.j0
                rows, cols = piece.i1 - piece.i0 + 1, piece.j1 - piece.j0 + 1
                level.pos_ecef[t0:t0 + rows, c0:c0 + cols] = pos[a:a + rows, b:b + cols]
                level.texel[t0:t0 + rows, c0:c0 + cols, 3] = h[a:a + rows, b:b + cols]
                if not move_origin:
                    level.texel[t0:t0 + rows, c0:c0 + cols, :3] = pos[a:a + rows, b:b + cols] - level.origin_ecef
                    uploads.append(Upload(level.k, "texel", t0, c0, rows, cols))
            for piece, t0, c0 in toroidal_pieces(Rect(2 * r.i0, 2 * r.j0, 2 * r.i1 + 1, 2 * r.j1 + 1), 2 * n):
                a, b = piece.i0 - 2 * r.i0, piece.j0 - 2 * r.j0
                rows, cols = piece.i1 - piece.i0 + 1, piece.j1 - piece.j0 + 1
                level.normal[t0:t0 + rows, c0:c0 + cols, :normals.shape[-1]] = normals[a:a + rows, b:b + cols]
                uploads.append(Upload(level.k, "normal", t0, c0, rows, cols))
        level.region = new
        if move_origin:  # every offset against the new origin (from the float64 copy)
            level.texel[..., :3] = level.pos_ecef - level.origin_ecef
            uploads.append(Upload(level.k, "texel", 0, 0, n, n))
        level.version += 1
        level._log_writes(todo)
        self.stats.levels_moved += 1
        return uploads


def _wrapped_lon(lon: np.ndarray) -> np.ndarray:
    """Longitudes (degrees) of a level's columns, any turn, within [-180, 180) (those already
    there bit for bit): what the terrain is asked (its queries stop at +-540, and a region's
    columns run on past a turn, Clipmap.unwrapped_dlon) and what the normals and land classes are
    placed by, so that a post's values do not depend on the turn its column was taken on."""
    return np.where((lon >= -180.0) & (lon < 180.0), lon, (lon + 180.0) % 360.0 - 180.0)


@numba.njit(cache=True, nogil=True)
def _height_range(texel):
    """(min, max) of the heights (channel 3) of a level's (n, n, 4) storage, in one pass (numpy's
    two reductions over the strided channel: 140-400 us at n = 255; this: about 40 us warm)."""
    lo, hi = np.float32(np.inf), np.float32(-np.inf)
    for i in range(texel.shape[0]):
        for j in range(texel.shape[1]):
            lo = min(lo, texel[i, j, 3])  # finite: no-data posts are stored at sea level
            hi = max(hi, texel[i, j, 3])
    return float(lo), float(hi)


@numba.njit(cache=True)
def _normals_ecef(de, dn, phi_rows, so_cols, co_cols, out):
    """out (rows, cols, 3): ECEF unit normals of the surface with gradients de, dn (rows x cols,
    row-major; per metre east and north) at latitudes phi_rows (rad) and longitudes whose sines
    and cosines are given; (0, 0, 1) ENU where a gradient is NaN (no data). The ENU axes are
    terrain.geodesy.enu_basis's: east (-so, co, 0), north (-sl co, -sl so, cl), up (cl co, cl so, sl)."""
    nc = so_cols.size
    for i in range(phi_rows.size):
        sl, cl = math.sin(phi_rows[i]), math.cos(phi_rows[i])
        for j in range(nc):
            a, b = de[i * nc + j], dn[i * nc + j]
            if math.isfinite(a) and math.isfinite(b):
                inv = 1.0 / math.sqrt(a * a + b * b + 1.0)
                ne, nn, nu = -a * inv, -b * inv, inv
            else:
                ne, nn, nu = 0.0, 0.0, 1.0
            so, co = so_cols[j], co_cols[j]
            out[i, j, 0] = -ne * so - nn * sl * co + nu * cl * co
            out[i, j, 1] = ne * co - nn * sl * so + nu * cl * so
            out[i, j, 2] = nn * cl + nu * sl


def _store_on_lattice(terrain, lattice):
    """(store, level offset f) when the terrain's first source is a terrain store whose level f
    posts are the lattice's, else (None, 0)."""
    from terrain.store import StoreSource

    sources = getattr(terrain, "sources", None)
    if not sources or not isinstance(sources[0], StoreSource) or sources[0].level != 0:
        return None, 0
    store = sources[0].store
    f = _level_offset(lattice, store.dlat, store.dlon)
    return (None, 0) if f is None else (store, f)


def _level_offset(lattice, dlat: float, dlon: float) -> int | None:
    """f when the lattice's posts are the level-f posts of a store lattice of level-0 spacing
    (dlat, dlon) (posts from the North Pole and the 180th meridian), else None."""
    if lattice.lat0 != 90.0 or lattice.lon0 != -180.0:
        return None
    ratio = lattice.dlat / dlat
    f = round(math.log2(ratio)) if ratio > 0 else -1
    if f < 0 or abs(ratio - 2.0 ** f) > 1e-9 * ratio or abs(lattice.dlon - dlon * 2.0 ** f) > 1e-9 * lattice.dlon:
        return None
    return f


def _remote_store_on_lattice(terrain, lattice):
    """(store levels, level offset f) when the terrain is a terrain service client whose first
    source is a store on this lattice, else (0, 0)."""
    if not hasattr(terrain, "get_region"):
        return 0, 0
    sources = terrain.describe()
    if not sources or sources[0].get("kind") != "store":
        return 0, 0
    s = sources[0]
    f = _level_offset(lattice, float(s["resolution_lat_deg"]), float(s["resolution_lon_deg"]))
    return (0, 0) if f is None else (int(s["store_levels"]), f)


def drawn_regions(clipmap: Clipmap, drawn_levels: list[int], margin_cells: int = 1) -> dict[int, Rect]:
    """Each drawn level's render extent (posts): the coarsest its clip region; a finer one its
    clip region cropped to lie at least ``margin_cells`` coarse cells inside the coarser level's
    drawn region (the layer asks for the morph width + 1, so a lagging level's border stays out
    of the coarser level's morph band), on even rows and columns (so its border runs through
    coarse posts). A level cropped to fewer than 4 cells a side is left out, and the finer
    ones with it."""
    out: dict[int, Rect] = {}
    coarser = None
    for k in sorted(drawn_levels, reverse=True):
        r = clipmap.levels[k].region
        if coarser is not None:
            c = out[coarser]
            m = margin_cells
            inner = Rect(2 * (c.i0 + m), 2 * (c.j0 + m), 2 * (c.i1 - m), 2 * (c.j1 - m))
            r = r.intersect(inner)
            r = Rect(r.i0 + (r.i0 & 1), r.j0 + (r.j0 & 1), r.i1 - (r.i1 & 1), r.j1 - (r.j1 & 1))
            if r.empty or r.i1 - r.i0 < 4 or r.j1 - r.j0 < 4 or coarser != k + 1:
                break
        out[k] = r
        coarser = k
    return out
