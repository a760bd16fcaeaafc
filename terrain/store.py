"""The terrain store: a compressed multi-resolution height pyramid on disk,
tiled by the geographic quad tree.

Layout (version 2, documented in docs/STORE.md)::

    STORE/store.json              the manifest (written last: a store without it is unfinished)
    STORE/region-NNN/level-KK.tiles   one file per region and level

The store holds one global lattice (``global-terrain-flight-sim.txt`` §4):
level 0 has posts every ``90 / (2^D T)`` degrees of latitude and
``120 / (2^D T)`` of longitude, row 0 on the North Pole counting south and
column 0 on the 180th meridian counting east, so the T x T posts of tile
(row, col) of level k are exactly the quad-tree cell (D - k, row, col): the
cell owns its northern and western edge posts. Posts are square in metres near
latitude 41° (cos 41° = 3/4) and within 6 % of square at 45°.

Heights are integers of ``unit_m`` (1 cm), coded by :mod:`terrain.heightcodec`
with a quantisation step of ``step_units`` (1 = lossless): every decoded post
of every level is within ``step / 2`` of the imported value. A per-post class
(0 outside the data, 1 measured, 2 a filled void) rides along each tile.

Each level file::

    magic b"SRTL" | u16 version | u16 level | u32 tile count
    count x (i64 tile_row, i64 tile_col, u64 offset, u32 height_len, u32 class_len)
    blobs: height blob (heightcodec), then class blob (empty: every post measured;
           1 byte: every post that class; else zstd of the uint8 classes)
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import struct
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import zstandard

from sortie.errors import DataFormatError, InvalidArgument, LimitExceeded, NotFound, shown
from terrain import heightcodec
from terrain.heightcodec import LevelRect, PyramidReader, tile_overlap
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef, Raster

FORMAT_NAME = "sortie-terrain-store"
FORMAT_VERSION = 2  # 2: height blobs of heightcodec BLOB_VERSION 2
MANIFEST = "store.json"
LEVEL_MAGIC = b"SRTL"
_LEVEL_HEAD = struct.Struct("<4sHHI")
_INDEX_ENTRY = np.dtype([("row", "<i8"), ("col", "<i8"), ("offset", "<u8"), ("hlen", "<u4"), ("clen", "<u4")])

DEFAULT_TILE = 256
DEFAULT_UNIT_M = 0.01
MAX_DEPTH = 20  # level-0 posts of 90 / (2^20 * 256) deg ~ 4 cm: beyond any DEM
CLASS_OUTSIDE, CLASS_MEASURED, CLASS_FILLED = 0, 1, 2

# Decoded tiles cached per open store (every level together): 512 tiles of
# 256^2 int64 is 256 MiB at most.
DEFAULT_CACHE_TILES = 512
# Point queries read blocks of BLOCK_TILES^2 tiles as one raster (fewer, larger
# groups per batch); at most CACHE_BLOCKS of them are kept (4 MiB each at T = 256).
BLOCK_TILES = 4
CACHE_BLOCKS = 64
# The most posts StoreSource.raster_for merges from several regions for a batch of rays (16 M:
# 128 MiB of float64 while merging); beyond, the rays get the region holding most of their box.
RAY_RASTER_MAX_POSTS = 1 << 24


def lattice_spacing_deg(depth: int, tile: int = DEFAULT_TILE) -> tuple[float, float]:
    """(dlat, dlon) degrees between the posts of a lattice whose cells at ``depth`` hold tile^2 posts."""
    n = (1 << depth) * tile
    return 90.0 / n, 120.0 / n


def depth_for_spacing(dlat_deg: float, tile: int = DEFAULT_TILE) -> int:
    """The least depth whose latitude spacing is no coarser than dlat_deg."""
    if not (math.isfinite(dlat_deg) and dlat_deg > 0):
        raise InvalidArgument("resolution", "must be a positive number of arc-seconds", value=dlat_deg * 3600)
    d = max(0, math.ceil(math.log2(90.0 / (tile * dlat_deg)) - 1e-9))
    if d > MAX_DEPTH:
        raise InvalidArgument("resolution", f"is finer than the store's finest lattice (depth {MAX_DEPTH})",
                              value=dlat_deg * 3600)
    return d


@dataclass(frozen=True)
class Region:
    """One connected coded area: its pyramid's level rectangles (finest first)."""

    index: int
    rects: tuple[LevelRect, ...]
    bounds: tuple[float, float, float, float]  # lat_min, lon_min, lat_max, lon_max of level 0's data

    @property
    def directory(self) -> str:
        return f"region-{self.index:03d}"


class TerrainStore:
    """An open store: manifest, level indexes, and the shared decoded-tile cache.

    Use :func:`open_store` so every view and client of one process shares one
    instance (and its cache) per store.
    """

    def __init__(self, path, cache_tiles: int = DEFAULT_CACHE_TILES, manifest: dict | None = None):
        """manifest: the importer's own, of the regions written so far (read while it runs);
        otherwise ``store.json``, refused while its import is unfinished."""
        self.path = Path(path)
        self._lock = threading.RLock()
        self._index: dict[tuple[int, int], tuple[np.ndarray, dict, int]] = {}  # entries, lookup, file size
        self._files: dict[tuple[int, int], object] = {}
        if manifest is not None:
            _check_format(manifest, self.path / MANIFEST)
            m, self._manifest_id = manifest, None
            self._open_level_files(m)
        else:
            m, self._manifest_id = self._open_snapshot()
        self.manifest = m
        self.tile = int(m["tile"])
        self.depth = int(m["depth"])
        self.unit_m = float(m["unit_m"])
        self.step_units = int(m["step_units"])
        self.dlat, self.dlon = lattice_spacing_deg(self.depth, self.tile)
        self.regions = [Region(r["index"], tuple(LevelRect(*x) for x in r["rects"]), _wrapped_bounds(r["bounds"]))
                        for r in m["regions"]]
        self.name = m.get("name", self.path.name)
        self._composing: dict[tuple[int, int], list[Region]] = {}  # (region, level) -> regions its tiles read
        self._readers = [PyramidReader(list(r.rects), self.tile, self.step_units,
                                       self._blob_getter(r.index), cache_tiles=cache_tiles,
                                       describe_tile=self._tile_namer(r.index))
                         for r in self.regions]
        self._class_cache: OrderedDict = OrderedDict()
        self._uniform_classes: dict[int, np.ndarray] = {}  # class -> a read-only tile of it
        self._block_cache: OrderedDict = OrderedDict()
        self._viewers: dict = {}  # key -> (lat, lon) of every view reading this store
        self._cache_tiles = cache_tiles
        self._dctx = zstandard.ZstdDecompressor()

    def _open_snapshot(self) -> tuple[dict, tuple]:
        """(manifest, its file's identity) read from ``store.json``, with the level files it lists
        opened (up to EAGER_LEVEL_FILES) while that same manifest was in place: an import replaces
        level files only while the store has no manifest (it removes the earlier one first), so
        files opened between reading a manifest and finding it unchanged are that manifest's. The
        open files keep their contents (their inodes) when a later import replaces them, so a
        process reading a store goes on reading the store it opened. Tried SNAPSHOT_ATTEMPTS
        times when the manifest changes meanwhile (an import finishing)."""
        manifest_path = self.path / MANIFEST
        for _ in range(SNAPSHOT_ATTEMPTS):
            m, identity = _read_manifest_file(self.path)
            _check_format(m, manifest_path)
            self._open_level_files(m)
            if _file_identity(manifest_path) == identity:
                return m, identity
            self.close()
        raise DataFormatError(f"terrain store {self.path}: its {MANIFEST} was replaced {SNAPSHOT_ATTEMPTS} times "
                              "while the store was being opened (an import writing it?); open it again once the "
                              "import has finished")

    def _open_level_files(self, m: dict) -> None:
        """Open the level files a manifest lists, the first EAGER_LEVEL_FILES of them (the rest open
        when first read, :meth:`_open_level`). One that cannot be opened is left to that too, where
        reading it raises the error naming it."""
        for r in m["regions"]:
            for level in range(len(r["rects"])):
                if len(self._files) >= EAGER_LEVEL_FILES:
                    return
                try:
                    self._files[(r["index"], level)] = open(self._level_path(r["index"], level), "rb")
                except OSError:
                    pass

    def is_current(self) -> bool:
        """False when ``store.json`` is no longer the one this store was opened with (a re-import
        finished since); True while an import is writing the store (it has no manifest then) and
        for an importer's own view (given its manifest)."""
        if self._manifest_id is None:
            return True
        now = _file_identity(self.path / MANIFEST)
        return now is None or now == self._manifest_id

    def _check_not_reimported(self, path: Path) -> None:
        """DataFormatError naming the store and ``path`` (a level file about to be read) unless the
        manifest is still the one the store was opened with: a level file opened after a re-import
        (or during one) is another pyramid's, and mixed with this store's tiles it decodes to wrong
        heights or fails as damage."""
        if self._manifest_id is not None and _file_identity(self.path / MANIFEST) != self._manifest_id:
            raise DataFormatError(f"terrain store {self.path}: re-imported since it was opened ({MANIFEST} replaced, "
                                  f"or removed by an import under way), so {path} is no longer this store's; "
                                  "reopen it")

    # ------------------------------------------------------------------ geometry

    @property
    def levels(self) -> int:
        return max(len(r.rects) for r in self.regions)

    @property
    def max_error_m(self) -> float:
        """Bound on |decoded - resampled source| at every post of every level: half a
        step of quantisation plus half a unit of rounding to the unit."""
        return (self.step_units // 2 + 0.5) * self.unit_m

    @property
    def quantisation_bound_m(self) -> float:
        """Bound on |decoded - imported| at every post from quantisation alone: half a step
        (floor(step_units / 2) units; 0 for a lossless store). The store cannot tell heights
        this close apart, e.g. a sea at 0 m from ground at step / 2 (terrain/texture.py's water)."""
        return (self.step_units // 2) * self.unit_m

    def spacing_deg(self, level: int) -> tuple[float, float]:
        return self.dlat * (1 << level), self.dlon * (1 << level)

    def cell_depth(self, level: int) -> int:
        """Quad-tree depth of the cells whose tiles make up a level."""
        return self.depth - level

    def post_latlon(self, level: int, rows, cols):
        """(lat, lon) degrees of lattice posts of a level; longitudes wrapped to [-180, 180)."""
        dlat, dlon = self.spacing_deg(level)
        lat = 90.0 - np.asarray(rows, np.float64) * dlat
        lon = (np.asarray(cols, np.float64) * dlon) % 360.0 - 180.0
        return lat, lon

    def fractional_post(self, level: int, lat, lon):
        """(row, col) as floats in a level's lattice for (lat, lon) degrees."""
        dlat, dlon = self.spacing_deg(level)
        return (90.0 - np.asarray(lat, np.float64)) / dlat, ((np.asarray(lon, np.float64) + 180.0) % 360.0) / dlon

    def region_of(self, level: int, row: float, col: float) -> Region | None:
        """The region whose level rectangle holds a post (None outside every region)."""
        for region in self.regions:
            if level >= len(region.rects):
                continue
            r = region.rects[level]
            per_turn = self.cols_per_turn(level)
            c = _unwrap_col(col, r, per_turn)
            if r.row0 <= row <= r.row1 - 1 and r.col0 <= c <= _east_col(r.col0, r.col1, per_turn):
                return region
        return None

    def cols_per_turn(self, level: int) -> int:
        """Lattice columns of a level round the globe (columns wrap at this)."""
        return (3 << self.depth) * self.tile >> level

    # ------------------------------------------------------------------ decoding

    def decode(self, region: Region, level: int, row_a: int, row_b: int, col_a: int, col_b: int):
        """(heights_m float64, classes uint8) of a block of a level's lattice, inside the
        region's rectangle for that level (rows north to south)."""
        with self._lock:
            heights = self._readers[region.index].decode_region(level, row_a, row_b, col_a, col_b,
                                                                scale=self.unit_m)
            classes = self._classes(region, level, row_a, row_b, col_a, col_b)
        return heights, classes

    def raster(self, level: int, lat_min: float, lon_min: float, lat_max: float, lon_max: float,
               region: Region | None = None, max_posts: int | None = None, strict: bool = False) -> Raster | None:
        """The posts of a level covering a box as a :class:`Raster` (row 0 south), merged from
        every region whose rectangle at this level overlaps the box (only ``region``'s when
        given): posts no region holds are NaN, outside, so a box over two regions reads both
        (GetRegion, rays through a :class:`StoreSource`). The grid is the box's posts cropped
        to the part of the box the rectangles reach; None when no rectangle overlaps it.
        A box with lon_max above 180 runs east across the antimeridian. With ``max_posts``, a
        merged grid larger than that (regions far apart, or a box wider than a turn) gives way to
        the one overlapping rectangle that shares most posts with the box, as large as it is; with
        ``strict`` too, it raises LimitExceeded instead (the caller splits its box)."""
        r_top, c_left = self.fractional_post(level, lat_max, lon_min)
        r_bot, _ = self.fractional_post(level, lat_min, lon_min)
        span = (lon_max - lon_min) / self.spacing_deg(level)[1]
        # The posts of the cells holding the box: rows from the north, columns unwrapped east of c_left's.
        row_a, row_b = int(math.floor(r_top)), int(math.floor(r_bot)) + 2
        col_a, col_b = int(math.floor(c_left)), int(math.floor(c_left + span)) + 2
        parts = self._parts(level, row_a, row_b, col_a, col_b, self.regions if region is None else [region])
        if not parts:
            return None
        merged = (max(p[2] for p in parts) - min(p[1] for p in parts)) * (
            max(p[4] for p in parts) - min(p[3] for p in parts))
        if max_posts is not None and merged > max_posts and len(parts) > 1:
            if strict:
                raise LimitExceeded("box posts", merged, max_posts, "regions far apart in one box")
            biggest = max(parts, key=lambda p: (p[2] - p[1]) * (p[4] - p[3]))
            # That rectangle's posts, with whatever other regions hold inside it (coarser levels
            # of nearby regions share tiles).
            parts = self._parts(level, *biggest[1:5], self.regions if region is None else [region])
        ga, gb = min(p[1] for p in parts), max(p[2] for p in parts)
        gc, gd = min(p[3] for p in parts), max(p[4] for p in parts)
        if gb - ga < 2 or gd - gc < 2:
            return None
        heights, classes = self._merge(parts, level, ga, gb, gc, gd)
        regions = tuple(dict.fromkeys(p[0].index for p in parts))
        return self._grid_raster(heights, classes, level, gb, gc,
                                 {"region": regions[0] if len(regions) == 1 else None, "regions": regions})

    def level_posts(self, level: int, row_a: int, row_b: int, col_a: int, col_b: int):
        """(heights_m float64, NaN outside the data; classes uint8) of a level's lattice rows
        [row_a, row_b) x columns [col_a, col_b) (rows north to south; columns in any turn), composed
        from every region whose rectangle at the level holds some of them; None unless the
        rectangles hold every one (the clipmap then asks the terrain's other sources)."""
        parts = self._parts(level, row_a, row_b, col_a, col_b, self.regions)
        covered = np.zeros((row_b - row_a, col_b - col_a), bool)
        for _, ra, rb, ca, cb, _ in parts:
            covered[ra - row_a:rb - row_a, ca - col_a:cb - col_a] = True
        if not parts or not covered.all():
            return None
        heights, classes = self._merge(parts, level, row_a, row_b, col_a, col_b)
        heights[classes == CLASS_OUTSIDE] = np.nan
        return heights, classes

    def _parts(self, level: int, row_a: int, row_b: int, col_a: int, col_b: int, regions) -> list:
        """Where each of ``regions``' rectangles at a level meets lattice rows [row_a, row_b) x
        columns [col_a, col_b) (columns unwrapped: any turn): (region, rows [ra, rb), columns [ca,
        cb), shift), the region's own columns being these less shift. A rectangle meets the range
        in each copy of it whole turns apart that overlaps it (one, unless the range spans more than
        a turn less the rectangle's width); a region whose pyramid stops below the level has none."""
        per_turn = self.cols_per_turn(level)
        parts = []
        for reg in regions:
            if level >= len(reg.rects):
                continue
            rect = reg.rects[level]
            ra, rb = max(row_a, rect.row0), min(row_b, rect.row1)
            if rb <= ra:
                continue
            for m in range((col_a - rect.col1) // per_turn + 1, -(-(col_b - rect.col0) // per_turn)):
                ca, cb = max(col_a, rect.col0 + m * per_turn), min(col_b, rect.col1 + m * per_turn)
                if cb > ca:
                    parts.append((reg, ra, rb, ca, cb, m * per_turn))
        return parts

    def _merge(self, parts, level: int, ga: int, gb: int, gc: int, gd: int):
        """(heights_m, classes) of rows [ga, gb) x columns [gc, gd) decoded from ``parts``
        (:meth:`_parts`): each post from the first part whose class there is not outside; class
        outside where none has data, the height there NaN or a region's fill (callers take NaN
        by the class, as :meth:`_grid_raster` does).

        Regions share no data posts (their level-0 boxes lie more than a tile apart; a store
        imported before sources across the antimeridian were grouped may have two, and the first
        region's wins), but their coarser rectangles are rounded out to whole tiles and so may
        share tiles: such a tile is coded in each region, every post outside the region's own
        data marked outside, and each post's data is in the one region that has it."""
        heights = np.full((gb - ga, gd - gc), np.nan)
        classes = np.zeros(heights.shape, np.uint8)
        for n, (reg, ra, rb, ca, cb, shift) in enumerate(parts):
            h, cl = self.decode(reg, level, ra, rb, ca - shift, cb - shift)
            window = (slice(ra - ga, rb - ga), slice(ca - gc, cb - gc))
            if n == 0:  # nothing there yet (the common case: one region)
                heights[window], classes[window] = h, cl
                continue
            dst_h, dst_c = heights[window], classes[window]
            take = (dst_c == CLASS_OUTSIDE) & (cl != CLASS_OUTSIDE)
            dst_h[take] = h[take]
            dst_c[take] = cl[take]
        return heights, classes

    def _composing_regions(self, region: Region, level: int) -> list[Region]:
        """The regions a tile or block of ``region`` at a level is composed from: the region, then
        every other whose rectangle there meets the region's grown by its tiles' east and south
        edge posts (one post; whole turns apart too). Empty but for the region itself unless
        coarser rectangles of nearby regions share tiles (or touch)."""
        key = (region.index, level)
        hit = self._composing.get(key)
        if hit is None:
            rect = region.rects[level]
            hit = [region] + [other for other in self.regions if other is not region and self._parts(
                level, rect.row0, rect.row1 + 1, rect.col0, rect.col1 + 1, [other])]
            self._composing[key] = hit
        return hit

    def _block_raster(self, region: Region, level: int, row_a, row_b, col_a, col_b,
                      pad_to: tuple[int, int] | None = None) -> Raster:
        """Posts [row_a, row_b) x [col_a, col_b) of a level as a Raster (row 0 south), in the
        region's columns; with pad_to (rows, cols), the grid is that size from (row_a, col_a).
        Each post comes from whichever region has data there (:meth:`_composing_regions`: a tile of
        a coarser level that two nearby regions share holds the data of both); NaN, outside, where
        none has, past every rectangle too."""
        r1, c1 = (row_b, col_b) if pad_to is None else (row_a + pad_to[0], col_a + pad_to[1])
        parts = self._parts(level, row_a, r1, col_a, c1, self._composing_regions(region, level))
        heights, classes = self._merge(parts, level, row_a, r1, col_a, c1)
        return self._grid_raster(heights, classes, level, r1, col_a, {"region": region.index})

    def _grid_raster(self, heights, classes, level: int, row_b: int, col_a: int, meta: dict) -> Raster:
        """Decoded posts (rows north to south, the last at lattice row row_b - 1, columns from
        col_a) as a Raster (row 0 south): NaN where the class is outside, filled flags."""
        heights = heights[::-1].copy()
        classes = classes[::-1]
        heights[classes == CLASS_OUTSIDE] = np.nan
        filled = classes == CLASS_FILLED
        dlat, dlon = self.spacing_deg(level)
        lat_south = 90.0 - (row_b - 1) * dlat
        lon_west = col_a * dlon - 180.0  # unwrapped: a raster may run past +180
        georef = Georef(CRS_GEOGRAPHIC, lon_west, lat_south, dlon, dlat)
        return Raster(heights.astype(np.float32), georef, name=f"{self.name}:L{level}",
                      vertical_datum=self.manifest.get("vertical_datum", "EGM96"),
                      filled=filled if filled.any() else None, source=str(self.path),
                      meta={"store_level": level, **meta})

    def cell_raster(self, cell_id: int) -> tuple[int, Raster]:
        """(level, tile raster) of a quad-tree cell: the cell at depth d is the tile of level
        depth - d, from every region holding it (:meth:`tile_raster`; two nearby regions' coarser
        rectangles may share a tile, each holding part of its data). NotFound, naming cell_id,
        when no level or region holds it."""
        from terrain import quadtree

        depth, row, col = quadtree.unpack(int(cell_id))
        level = self.depth - depth
        if not 0 <= level < self.levels:
            raise NotFound(f"cell_id: depth {depth} is not a level of the store (depths "
                           f"{self.depth - self.levels + 1}..{self.depth})")
        T = self.tile
        region = self.region_of(level, row * T, col * T)
        if region is None:
            raise NotFound(f"cell_id: no region of the store holds cell ({depth}, {row}, {col})")
        col_in_region = int(_unwrap_col(col * T, region.rects[level], self.cols_per_turn(level))) // T
        return level, self.tile_raster(region, level, row, col_in_region)

    def tile_raster(self, region: Region, level: int, tile_row: int, tile_col: int) -> Raster:
        """One tile of a region's rectangle (tile_row, tile_col in the region's columns) with its
        east and south edge posts (T + 1)^2, as a Raster: every point of the cell interpolates
        inside it. Each post is from whichever region has data there (:meth:`_block_raster`); edge
        posts past every rectangle are NaN, outside. Cached with the tiles."""
        T = self.tile
        key = ("raster", region.index, level, tile_row, tile_col)
        with self._lock:
            hit = self._class_cache.get(key)
            if hit is not None:
                self._class_cache.move_to_end(key)
                return hit
            r0, c0 = tile_row * T, tile_col * T
            raster = self._block_raster(region, level, r0, r0 + T + 1, c0, c0 + T + 1, pad_to=(T + 1, T + 1))
            self._remember(key, raster)
            return raster

    def block_raster(self, region: Region, level: int, block_row: int, block_col: int) -> Raster:
        """BLOCK_TILES^2 tiles with their east and south edge posts as one Raster
        (what point queries read); the last CACHE_BLOCKS are kept. Blocks count from the
        region's rectangle's first post (block (0, 0) starts at (row0, col0), tile-aligned), so
        their indices are small and never negative, whatever turn the rectangle's columns lie in."""
        key = (region.index, level, block_row, block_col)
        with self._lock:
            hit = self._block_cache.get(key)
            if hit is not None:
                self._block_cache.move_to_end(key)
                return hit
            n = BLOCK_TILES * self.tile
            rect = region.rects[level]
            r0, c0 = rect.row0 + block_row * n, rect.col0 + block_col * n
            # A rectangle a whole turn wide wraps onto itself: its last block takes the turn's
            # first column as its east edge (_parts reads it from the region's first columns).
            east = _east_col(rect.col0, rect.col1, self.cols_per_turn(level)) + 1
            raster = self._block_raster(region, level, r0, min(r0 + n + 1, rect.row1),
                                        c0, min(c0 + n + 1, east))
            self._block_cache[key] = raster
            while len(self._block_cache) > CACHE_BLOCKS:
                self._block_cache.popitem(last=False)
            return raster

    def _remember(self, key, value) -> None:
        self._class_cache[key] = value
        while len(self._class_cache) > self._cache_tiles:
            self._class_cache.popitem(last=False)

    def _classes(self, region: Region, level: int, row_a, row_b, col_a, col_b) -> np.ndarray:
        T = self.tile
        out = np.empty((row_b - row_a, col_b - col_a), np.uint8)
        for ti in range(row_a // T, -(-row_b // T)):
            for tj in range(col_a // T, -(-col_b // T)):
                key = ("class", region.index, level, ti, tj)
                cls = self._class_cache.get(key)
                if cls is None:
                    cls = self._decode_classes(region.index, level, ti, tj)
                    self._remember(key, cls)
                dst, src = tile_overlap(ti, tj, T, row_a, row_b, col_a, col_b)
                out[dst] = cls[src]
        return out

    def _decode_classes(self, region: int, level: int, ti: int, tj: int) -> np.ndarray:
        blob = self._read_tile(region, level, ti, tj, classes=True)
        if len(blob) <= 1:  # every post of one class: one shared read-only tile per class
            value = CLASS_MEASURED if len(blob) == 0 else blob[0]
            if value > CLASS_FILLED:
                raise self._tile_error(region, level, ti, tj, f"class blob: class {value} (classes are 0, 1 and 2)")
            tile = self._uniform_classes.get(value)
            if tile is None:
                tile = self._uniform_classes[value] = np.full((self.tile, self.tile), value, np.uint8)
                tile.setflags(write=False)
            return tile
        n = self.tile * self.tile
        try:
            size = zstandard.get_frame_parameters(blob).content_size
            if size != n:  # checked before decompressing: a damaged size is not allocated
                raise self._tile_error(region, level, ti, tj, f"class blob: its zstd frame holds {size} bytes, "
                                                              f"not {n}")
            classes = np.frombuffer(self._dctx.decompress(blob), np.uint8).reshape(self.tile, self.tile)
        except (zstandard.ZstdError, ValueError) as e:  # ValueError: a frame longer than its header says
            raise self._tile_error(region, level, ti, tj, f"class blob: damaged zstd frame ({e})") from None
        if classes.max() > CLASS_FILLED:
            raise self._tile_error(region, level, ti, tj, f"class blob: class {int(classes.max())} (classes are "
                                                          "0, 1 and 2)")
        return classes

    # ------------------------------------------------------------------ files

    def _level_path(self, region: int, level: int) -> Path:
        return level_file(self.path, region, level)

    def _tile_name(self, region: int, level: int, ti: int, tj: int) -> str:
        """How errors name a tile: its level file and the tile's (row, col) in the level's lattice."""
        return f"{self._level_path(region, level)}: tile ({ti}, {tj})"

    def _tile_error(self, region: int, level: int, ti: int, tj: int, what: str) -> DataFormatError:
        return DataFormatError(f"{self._tile_name(region, level, ti, tj)}: {what}")

    def _tile_namer(self, region: int):
        """:meth:`_tile_name` of one region: (level, tile row, tile col) -> name (the reader's describe_tile)."""
        return lambda level, ti, tj: self._tile_name(region, level, ti, tj)

    def _blob_getter(self, region: int):
        def get(level, ti, tj):
            return self._read_tile(region, level, ti, tj, classes=False)
        return get

    def _level_index(self, region: int, level: int):
        """(index entries, (tile row, col) -> entry, file size) of a level file, read once and
        checked: DataFormatError naming the file when its header or index is damaged."""
        key = (region, level)
        hit = self._index.get(key)
        if hit is None:
            path = self._level_path(region, level)
            f = self._files.get(key)
            if f is None:
                f = self._files[key] = self._open_level(path)
            try:
                hit = self._read_index(f, path, level)
            except OSError as e:
                raise DataFormatError(f"{path}: cannot be read: {e.strerror or e}") from None
            self._index[key] = hit
        return hit

    def _open_level(self, path: Path):
        """A level file the store did not open with the manifest (beyond EAGER_LEVEL_FILES, or after
        :meth:`close`), checked to be the manifest's after it is opened (:meth:`_check_not_reimported`)."""
        try:
            f = open(path, "rb")
        except OSError as e:
            self._check_not_reimported(path)  # gone because a re-import removed it: say so
            raise DataFormatError(f"terrain store {self.path}: cannot open {path}: {e.strerror or e}") from None
        try:
            self._check_not_reimported(path)
        except BaseException:
            f.close()
            raise
        return f

    @staticmethod
    def _read_index(f, path: Path, level: int):
        size = os.fstat(f.fileno()).st_size
        head = f.read(_LEVEL_HEAD.size)
        if len(head) < _LEVEL_HEAD.size:
            raise DataFormatError(f"{path}: truncated header ({len(head)} of {_LEVEL_HEAD.size} bytes)")
        magic, version, lvl, count = _LEVEL_HEAD.unpack(head)
        if magic != LEVEL_MAGIC or version != FORMAT_VERSION or lvl != level:
            raise DataFormatError(f"{path}: not a level-{level} tile file of version {FORMAT_VERSION} (magic "
                                  f"{magic!r}, version {version}, level {lvl})")
        n_bytes = count * _INDEX_ENTRY.itemsize
        if _LEVEL_HEAD.size + n_bytes > size:  # checked before reading: a damaged count is not allocated
            raise DataFormatError(f"{path}: truncated index ({size - _LEVEL_HEAD.size} bytes after the header, "
                                  f"{count:,} tiles need {n_bytes:,})")
        entries = np.frombuffer(f.read(n_bytes), _INDEX_ENTRY)
        lookup = {(int(e["row"]), int(e["col"])): i for i, e in enumerate(entries)}
        return entries, lookup, size

    def _read_tile(self, region: int, level: int, ti: int, tj: int, classes: bool) -> bytes:
        """One tile's height blob, or its class blob when ``classes``; DataFormatError naming the
        level file and the tile when the index lacks it or points outside the file's blobs."""
        with self._lock:
            entries, lookup, file_size = self._level_index(region, level)
            i = lookup.get((ti, tj))
            if i is None:
                raise self._tile_error(region, level, ti, tj, f"missing from the file's index (region {region} "
                                                              "needs it)")
            e = entries[i]
            f = self._files[(region, level)]
            start, hlen, clen = int(e["offset"]), int(e["hlen"]), int(e["clen"])
            blobs_start = _LEVEL_HEAD.size + entries.nbytes
            if not blobs_start <= start <= file_size or start + hlen + clen > file_size:
                raise self._tile_error(region, level, ti, tj, f"its index entry (offset {start:,}, {hlen:,} + "
                                       f"{clen:,} bytes) points outside the file's blobs (bytes {blobs_start:,} to "
                                       f"{file_size:,}; truncated or damaged)")
            offset, size = (start + hlen, clen) if classes else (start, hlen)
            try:
                f.seek(offset)
                data = f.read(size)
            except OSError as exc:
                raise self._tile_error(region, level, ti, tj, f"cannot be read: {exc.strerror or exc}") from None
            if len(data) != size:
                raise self._tile_error(region, level, ti, tj, f"truncated ({len(data)} of {size} bytes)")
            return data

    def stored_bytes(self) -> int:
        """Bytes of the level files the manifest lists (not of other files in the directory)."""
        return sum(p.stat().st_size for p in level_files(self.path, self.manifest["regions"]))

    def cache_tiles_held(self) -> int:
        return sum(len(r.cached()) for r in self._readers)

    def set_viewer(self, key, lat: float, lon: float) -> None:
        """Where one view (a clipmap, a bot's camera) now is; ``retain_near`` keeps the cells
        around every view registered, so views sharing the store never evict each other."""
        with self._lock:
            self._viewers[key] = (float(lat), float(lon))

    def forget_viewer(self, key) -> None:
        with self._lock:
            self._viewers.pop(key, None)

    def retain_near(self, viewers, radius_cells: float) -> int:
        """Keep only the decoded tiles of cells within ``radius_cells`` of any viewer
        (lat, lon), and of any view registered with :meth:`set_viewer`, at their own
        level (the per-level scene-graph radius of ``global-terrain-flight-sim.txt``
        §5); returns how many were evicted."""
        from terrain import quadtree

        with self._lock:
            viewers = list(viewers) + list(self._viewers.values())
        keep = set()
        for lat, lon in viewers:
            for level in range(self.levels):
                for cid in quadtree.cells_within(lat, lon, self.cell_depth(level), radius_cells):
                    _, row, col = quadtree.unpack(int(cid))
                    keep.add((level, row, col))
        evicted = 0
        with self._lock:
            for reader in self._readers:
                evicted += reader.evict([(level, ti, tj) for level, ti, tj in reader.cached()
                                         if (level, ti, tj % (self.cols_per_turn(level) // self.tile)) not in keep])
        return evicted

    def clear_cache(self) -> None:
        """Forget every decoded tile, class tile and block (benchmarks; memory pressure)."""
        with self._lock:
            for reader in self._readers:
                reader.evict()
            self._class_cache.clear()
            self._block_cache.clear()

    def close(self) -> None:
        """Close the level files; a later read opens them again, checked to be still this store's
        (:meth:`_open_level`)."""
        with self._lock:
            for f in self._files.values():
                f.close()
            self._files.clear()
            self._index.clear()


def read_manifest(path) -> dict:
    """A store's ``store.json``: NotFound without one; DataFormatError when it is not JSON, or
    when its import did not finish (no summary: manifests of an interrupted import of before
    the manifest was written once, at the end)."""
    return _read_manifest_file(path)[0]


def _read_manifest_file(path) -> tuple[dict, tuple]:
    """(:func:`read_manifest`, the identity of the file it was read from: :func:`_file_identity`)."""
    manifest_path = Path(path) / MANIFEST
    if not manifest_path.is_file():
        raise NotFound(f"terrain store {path}: no {MANIFEST} (not a store, or its import did not finish: "
                       f"run the same sortie terrain import again to resume it)")
    try:
        with open(manifest_path, "rb") as f:
            identity = _identity(os.fstat(f.fileno()))
            m = json.loads(f.read())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataFormatError(f"{manifest_path}: {e}") from None
    if not isinstance(m, dict):
        raise DataFormatError(f"{manifest_path}: not a JSON object")
    if m.get("format") == FORMAT_NAME and m.get("summary") is None:
        raise DataFormatError(f"{manifest_path}: unfinished import (the manifest has no summary); run the same "
                              f"sortie terrain import again to resume it")
    return m, identity


def _identity(stat: os.stat_result) -> tuple:
    """What tells one manifest file from its replacement: device, inode, size and modification
    time (an importer writes a new file and renames it over the old one)."""
    return stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns


def _file_identity(path: Path) -> tuple | None:
    """:func:`_identity` of the file now at ``path``; None when there is none."""
    try:
        return _identity(os.stat(path))
    except OSError:
        return None


def _check_format(m: dict, manifest_path: Path) -> None:
    """DataFormatError naming ``store.json`` unless the manifest is of this format and version and
    usable (:func:`check_manifest`)."""
    if m.get("format") != FORMAT_NAME:
        raise DataFormatError(f"{manifest_path}: format {m.get('format')!r} is not {FORMAT_NAME!r}")
    if m.get("version") != FORMAT_VERSION:
        raise DataFormatError(f"{manifest_path}: version {m.get('version')!r}, this build reads {FORMAT_VERSION}")
    check_manifest(m, manifest_path)


# Level files a store opens with its manifest (the rest when first read, checked against the manifest):
# a store of many regions would otherwise hold a descriptor per region and level.
EAGER_LEVEL_FILES = 256
# How often opening a store reads its manifest again when an import replaced it meanwhile.
SNAPSHOT_ATTEMPTS = 3
# The largest tile side a manifest may give: a decoded tile of 4096^2 int32 posts is 64 MiB (the
# importer writes DEFAULT_TILE; the codec needs an even side of at least 4, heightcodec.pyramid_rects).
MAX_TILE = 4096
# How many whole turns from the lattice's first a rectangle's first column may lie: importers before
# col0 was normalised kept a source's own turn (longitude 1000 is 3 turns east; queries stop at +-540).
MAX_COL0_TURNS = 64


def vertical_datums() -> frozenset[str]:
    """The vertical datums an import writes into ``store.json`` (a source's
    ``Raster.vertical_datum``): those terrain.dem's readers give, all heights above mean sea level."""
    from terrain import dem

    return frozenset((dem.VERTICAL_DATUM_SRTM, dem.VERTICAL_DATUM_DEFAULT, *dem.VERTICAL_DATUMS_EPSG.values()))


def check_manifest(m: dict, manifest_path) -> None:
    """DataFormatError naming ``store.json``, the field and its value for a manifest a reader cannot
    use (a damaged or hand-edited file): a missing key, a value of the wrong type, a lattice beyond
    the store's (tile, depth), a unit other than 1 cm, a step outside the codec's range, ``lossless``
    not saying whether the step is 1, a vertical datum no import writes, a region list that is empty or
    not numbered in order, a region's rectangles that are not its pyramid's (tile-aligned, inside
    the lattice, each level the tile-aligned box of the finer one's even posts, up to one tile or
    depth + 1 levels: what heightcodec.encode_pyramid coded), or bounds that are not a box."""

    def bad(field: str, what: str, value) -> DataFormatError:
        return DataFormatError(f"{manifest_path}: {field} {shown(value)} {what}")

    def get(obj: dict, key: str, field: str):
        if key not in obj:
            raise DataFormatError(f"{manifest_path}: {field} is missing")
        return obj[key]

    def integer(value, field: str, lo: int, hi: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise bad(field, f"is not an integer from {lo:,} to {hi:,}", value)
        return value

    def number(value, field: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad(field, "is not a finite number", value)
        return float(value)

    tile = integer(get(m, "tile", "tile"), "tile", 4, MAX_TILE)
    if tile % 2:
        raise bad("tile", "is not even (the codec's pyramid halves tiles)", tile)
    depth = integer(get(m, "depth", "depth"), "depth", 0, MAX_DEPTH)
    unit_m = number(get(m, "unit_m", "unit_m"), "unit_m")
    if unit_m != DEFAULT_UNIT_M:
        raise bad("unit_m", f"is not {DEFAULT_UNIT_M} m: the store's height unit is 1 cm (the codec's range of "
                  "2^29 units and GetRegion's HEIGHT_ENCODING_ZSTD_CM assume it; docs/STORE.md)", unit_m)
    step_units = integer(get(m, "step_units", "step_units"), "step_units", 1, heightcodec.MAX_ABS_UNITS)
    lossless = get(m, "lossless", "lossless")
    if not isinstance(lossless, bool) or lossless != (step_units == 1):
        raise bad("lossless", f"does not go with step_units {step_units} (lossless is a step of 1 unit: "
                  f"{str(step_units == 1).lower()} here)", lossless)
    for key in ("name", "vertical_datum"):
        if key in m and not isinstance(m[key], str):
            raise bad(key, "is not a string", m[key])
    if "vertical_datum" in m and m["vertical_datum"] not in vertical_datums():
        raise bad("vertical_datum", "is not a vertical datum an import writes (those of terrain.dem's readers: "
                  + ", ".join(sorted(vertical_datums())) + ")", m["vertical_datum"])
    _check_detail(m, bad, integer, number)
    summary = m.get("summary")
    if summary is not None and not isinstance(summary, dict):
        raise bad("summary", "is not a JSON object", summary)
    if summary is not None and "filled_posts" in summary:
        integer(summary["filled_posts"], "summary.filled_posts", 0, 2**62)
    regions = get(m, "regions", "regions")
    if not isinstance(regions, list) or not regions:
        raise bad("regions", "is not a list of at least one region", regions)
    rows_0 = 2 * (1 << depth) * tile  # lattice rows of level 0, North Pole to South Pole
    turn_0 = 3 * (1 << depth) * tile  # lattice columns of level 0 round the globe
    for i, r in enumerate(regions):
        where = f"regions[{i}]"
        if not isinstance(r, dict):
            raise bad(where, "is not a JSON object", r)
        index = get(r, "index", f"{where}.index")
        if isinstance(index, bool) or not isinstance(index, int) or index != i:
            raise bad(f"{where}.index", f"is not {i} (regions are listed in order of their index)", index)
        rects = get(r, "rects", f"{where}.rects")
        if not isinstance(rects, list) or not rects:
            raise bad(f"{where}.rects", "is not a list of at least one level's rectangle", rects)
        for k, rect in enumerate(rects):
            if (not isinstance(rect, list) or len(rect) != 4
                    or any(isinstance(v, bool) or not isinstance(v, int) for v in rect)):
                raise bad(f"{where}.rects[{k}]", "is not [row0, col0, rows, cols] of integers", rect)
        row0, col0, rows, cols = rects[0]
        if (row0 % tile or col0 % tile or rows % tile or cols % tile or rows <= 0 or cols <= 0 or row0 < 0
                or row0 + rows > rows_0 or abs(col0) > MAX_COL0_TURNS * turn_0 or cols > 2 * turn_0):
            raise bad(f"{where}.rects[0]", f"is not a rectangle of whole {tile}-post tiles inside level 0's "
                      f"lattice ({rows_0:,} rows, {turn_0:,} columns a turn; col0 within {MAX_COL0_TURNS} turns, "
                      f"at most 2 turns wide)", rects[0])
        want = heightcodec.pyramid_rects(row0, col0, rows, cols, tile, depth + 1)
        for k, (rect, w) in enumerate(zip(rects, want)):
            if rect != [w.row0, w.col0, w.rows, w.cols]:
                raise bad(f"{where}.rects[{k}]", f"is not level {k} of the pyramid over rects[0] "
                          f"([{w.row0}, {w.col0}, {w.rows}, {w.cols}]: the finer level's even posts "
                          f"in whole tiles)", rect)
        if len(rects) != len(want):
            raise bad(f"{where}.rects", f"has {len(rects)} levels, the pyramid over rects[0] {len(want)} "
                      f"(it stops where one tile holds it, or at depth + 1 levels)", len(rects))
        bounds = get(r, "bounds", f"{where}.bounds")
        if not isinstance(bounds, list) or len(bounds) != 4:
            raise bad(f"{where}.bounds", "is not [lat_min, lon_min, lat_max, lon_max]", bounds)
        lat_min, lon_min, lat_max, lon_max = (number(v, f"{where}.bounds") for v in bounds)
        if not (-90.0 <= lat_min <= lat_max <= 90.0 and lon_min <= lon_max):
            raise bad(f"{where}.bounds", "is not a box [lat_min, lon_min, lat_max, lon_max] (latitudes within "
                      "+-90, the minima at most the maxima)", bounds)


DETAIL_KINDS = ("fractal", "cellular")  # store.json's add_detail (sortie terrain import --add-detail)


def _check_detail(m: dict, bad, integer, number) -> None:
    """check_manifest's part for the synthetic detail (add_detail, detail_seed,
    detail_finest_spacing_m, each source's detail_level_std_m / detail_amplitude_m); a manifest
    without them (an import without detail, or from before they were recorded) passes."""
    kind = m.get("add_detail")
    if kind is None:
        return
    if kind not in DETAIL_KINDS:
        raise bad("add_detail", f"is not one of {', '.join(DETAIL_KINDS)} (or null)", kind)
    integer(m.get("detail_seed"), "detail_seed", 0, 2**64 - 1)
    if "detail_finest_spacing_m" in m and not number(m["detail_finest_spacing_m"], "detail_finest_spacing_m") > 0:
        raise bad("detail_finest_spacing_m", "is not > 0", m["detail_finest_spacing_m"])
    sources = m.get("sources", [])
    for i, src in enumerate(sources if isinstance(sources, list) else []):
        if not isinstance(src, dict):
            continue
        stds = src.get("detail_level_std_m", [])
        if not isinstance(stds, list) or any(number(v, f"sources[{i}].detail_level_std_m") < 0 for v in stds):
            raise bad(f"sources[{i}].detail_level_std_m", "is not a list of numbers >= 0 (m)", stds)
        if "detail_amplitude_m" in src and number(src["detail_amplitude_m"], f"sources[{i}].detail_amplitude_m") < 0:
            raise bad(f"sources[{i}].detail_amplitude_m", "is not >= 0 (m)", src["detail_amplitude_m"])


def detail_description(m: dict) -> dict:
    """A store's synthetic detail as describe() (GetMetadata's source details) says it:
    ``detail`` (its kind), ``detail_seed``, ``detail_finest_spacing_m``, and for fractal detail
    ``detail_levels`` and ``detail_level_std_m``, for cellular ``detail_amplitude_m`` (one value,
    or one per source in store.json's order where the sources' fits differ); {} for a store
    without detail, or imported before store.json recorded it."""
    kind = m.get("add_detail")
    if kind is None:
        return {}
    out = {"detail": kind, "detail_seed": m.get("detail_seed"),
           "detail_finest_spacing_m": m.get("detail_finest_spacing_m")}
    key = "detail_level_std_m" if kind == "fractal" else "detail_amplitude_m"
    values = [src[key] for src in m.get("sources", []) if isinstance(src, dict) and key in src]
    if values:
        out[key] = values[0] if all(v == values[0] for v in values) else values
    if kind == "fractal":
        out["detail_levels"] = max((len(v) for v in values), default=0)
    return out


def _wrapped_bounds(bounds) -> tuple[float, float, float, float]:
    """A region's bounds with lon_min moved by whole turns into [-180, 180) (lon_max with it, so
    it passes 180 for a region across the antimeridian), as importers now write them: stores
    imported before col0 was normalised may have lon_min below -180 or turns east."""
    lat_min, lon_min, lat_max, lon_max = (float(v) for v in bounds)
    shift = 360.0 * math.floor((lon_min + 180.0) / 360.0)
    return lat_min, lon_min - shift, lat_max, lon_max - shift


def _unwrap_col(col: float, rect: LevelRect, per_turn: int) -> float:
    """A column index moved by whole turns into [rect.col0, rect.col0 + per_turn): the copy of a
    lattice column that the rectangle's own columns count. Whatever turn the rectangle's col0 lies
    in: stores imported before col0 was normalised have negative ones (a source west of -180) and
    ones turns east (a source at longitude 1000); :func:`_block_keys` does the same arithmetic."""
    return _unwrap(float(col), rect.col0, per_turn)


@numba.njit(cache=True, nogil=True)
def _east_col(col0, col1, per_turn):
    """The easternmost column a rectangle's posts answer up to: its last, col1 - 1, or for a
    rectangle a whole turn wide (a region round the globe, docs/STORE.md) col1, the first column a
    turn on: the cells between its last column and the antimeridian interpolate across the wrap."""
    return col1 if col1 - col0 >= per_turn else col1 - 1


@numba.njit(cache=True, nogil=True)
def _unwrap(col, col0, per_turn):
    """:func:`_unwrap_col` on numbers (compiled, shared with :func:`_block_keys`)."""
    if col < col0:
        col += per_turn * math.ceil((col0 - col) / per_turn)
    elif col >= col0 + per_turn:
        col -= per_turn * math.floor((col - col0) / per_turn)
    return col


_open_stores: dict[str, TerrainStore] = {}
_open_lock = threading.Lock()


def open_store(path) -> TerrainStore:
    """The process-wide instance of a store (shared cache for every view and client); a new one
    once the store was re-imported since that instance was opened (:meth:`TerrainStore.is_current`:
    whoever holds the old one goes on reading the old files)."""
    key = os.path.realpath(path)
    with _open_lock:
        store = _open_stores.get(key)
        if store is None or not store.is_current():
            store = _open_stores[key] = TerrainStore(path)
        return store


# Block keys of StoreSource._groups: (region, block row, block column) packed in one int64; blocks
# count from the rectangle's first post, so a rectangle a turn wide at depth 20 has < 2^20 of them.
KEY_STRIDE = 1 << 21


@numba.njit(cache=True, nogil=True)
def _block_keys(lat, lon, dlat, dlon, per_turn, rects, n, out_key):
    """Each point's block key ((region * KEY_STRIDE + block row) * KEY_STRIDE + block
    column, or -1 outside every region) at one level; True when all keys are equal.
    Blocks count from the region's rectangle's first post (TerrainStore.block_raster).

    rects: (regions, 4) int64 rows of (row0, row1, col0, col1) of the level's
    rectangles; n: posts a block side. The later region holding a point wins,
    as the group order of StoreSource.heights_into always had it: which one does
    not change the answer, a block holding the data of every region that has
    some inside it (TerrainStore._block_raster). The same arithmetic as
    TerrainStore.fractional_post and _unwrap_col, one pass."""
    same = True
    for i in range(lat.shape[0]):
        row = (90.0 - lat[i]) / dlat
        col = ((lon[i] + 180.0) % 360.0) / dlon
        key = -1
        for r in range(rects.shape[0] - 1, -1, -1):
            row0, row1, col0, col1 = rects[r, 0], rects[r, 1], rects[r, 2], rects[r, 3]
            c = _unwrap(col, col0, per_turn)
            if row >= row0 and row <= row1 - 1 and c >= col0 and c <= _east_col(col0, col1, per_turn):
                bi = (min(int(math.floor(row)), row1 - 2) - row0) // n
                bj = (min(int(math.floor(c)), col1 - 2) - col0) // n
                key = (r * KEY_STRIDE + bi) * KEY_STRIDE + bj
                break
        out_key[i] = key
        if key != out_key[0]:
            same = False
    return same


# Most distinct blocks one batch is grouped into by the compiled counting sort (more: argsort).
MAX_GROUPS = 256


@numba.njit(cache=True, nogil=True)
def _group_by_key(keys, out_order, out_keys, out_starts):
    """Counting sort of the points by key, stable: out_order lists the point indices group
    by group, group g being out_order[out_starts[g]:out_starts[g + 1]] with key out_keys[g]
    (in order of first appearance). Returns the number of groups, or -1 past MAX_GROUPS."""
    n_groups = 0
    group = np.empty(keys.shape[0], np.int64)
    counts = np.zeros(out_keys.shape[0], np.int64)
    last = 0
    for i in range(keys.shape[0]):
        k = keys[i]
        if n_groups > 0 and out_keys[last] == k:
            g = last  # runs of one key are the common case (nearby points)
        else:
            g = -1
            for j in range(n_groups):
                if out_keys[j] == k:
                    g = j
                    break
            if g < 0:
                if n_groups == out_keys.shape[0]:
                    return -1
                g = n_groups
                out_keys[g] = k
                n_groups += 1
            last = g
        group[i] = g
        counts[g] += 1
    out_starts[0] = 0
    for g in range(n_groups):
        out_starts[g + 1] = out_starts[g] + counts[g]
    fill = out_starts[:n_groups].copy()
    for i in range(keys.shape[0]):
        g = group[i]
        out_order[fill[g]] = i
        fill[g] += 1
    return n_groups


class StoreSource:
    """A :class:`terrain.terrain.Terrain` source answering from a store's finest level.

    Points are grouped by the block (BLOCK_TILES^2 tiles) they fall in, in one
    compiled pass (:func:`_block_keys`); a batch inside one block, like an
    aircraft's contact points, goes to that block's raster without any
    grouping or copies."""

    def __init__(self, store: TerrainStore, level: int = 0):
        """level: any of the store's levels; regions whose pyramid stops below it (small
        regions have fewer levels) answer OUTSIDE (an empty rectangle)."""
        if not 0 <= level < store.levels:
            raise InvalidArgument("level", f"must be a level of the store (0..{store.levels - 1})", value=level)
        self.store = store
        self.level = level
        self._rects = np.array([[r.rects[level].row0, r.rects[level].row1, r.rects[level].col0,
                                 r.rects[level].col1] if level < len(r.rects) else [0, 0, 0, 0]
                                for r in store.regions], np.int64).reshape(-1, 4)

    def _groups(self, lat, lon):
        """(block raster, point indices or None for all of them) for the points inside
        some region, one group per block of BLOCK_TILES^2 tiles."""
        if lat.size == 0:
            return
        keys = np.empty(lat.size, np.int64)
        dlat, dlon = self.store.spacing_deg(self.level)
        same = _block_keys(lat, lon, dlat, dlon, self.store.cols_per_turn(self.level), self._rects,
                           BLOCK_TILES * self.store.tile, keys)
        if same:
            if keys[0] >= 0:
                yield self._block(int(keys[0])), None
            return
        order = np.empty(lat.size, np.int64)
        group_keys = np.empty(MAX_GROUPS, np.int64)
        starts = np.empty(MAX_GROUPS + 1, np.int64)
        n_groups = _group_by_key(keys, order, group_keys, starts)
        if n_groups < 0:  # points over very many blocks
            order = np.argsort(keys, kind="stable")
            cuts = np.flatnonzero(np.diff(keys[order])) + 1
            parts = np.split(order, cuts)
            group_keys = [int(keys[part[0]]) for part in parts]
        else:
            parts = [order[starts[g]:starts[g + 1]] for g in range(n_groups)]
        for key, part in zip(group_keys, parts):
            if key >= 0:
                yield self._block(int(key)), part

    def _block(self, key: int) -> Raster:
        region, rest = divmod(key, KEY_STRIDE * KEY_STRIDE)
        bi, bj = divmod(rest, KEY_STRIDE)
        return self.store.block_raster(self.store.regions[region], self.level, bi, bj)

    def _by_block(self, lat, lon, outs, answer) -> None:
        """``answer(raster, lat, lon, *outs)`` (a Raster method filling NaN / OUTSIDE
        outputs) block by block: on the batch itself when one block holds it, else on
        each block's points, gathered and scattered back."""
        for raster, sel in self._groups(lat, lon):
            if sel is None:
                answer(raster, lat, lon, *outs)
                continue
            part = [np.full(sel.size, np.nan) for _ in outs[:-1]] + [np.full(sel.size, STATUS_OUTSIDE, np.uint8)]
            answer(raster, lat[sel], lon[sel], *part)
            for out, values in zip(outs, part):
                out[sel] = values

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        self._by_block(lat, lon, (out_h, out_status), Raster.heights_into)

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        self._by_block(lat, lon, (out_de, out_dn, out_status), Raster.gradient_into)

    def raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float) -> Raster | None:
        """The store's posts over a box of rays (terrain.terrain.Terrain), merged from every region
        holding part of it up to RAY_RASTER_MAX_POSTS, else from the one holding most of it."""
        return self.store.raster(self.level, lat_min, lon_min, lat_max, lon_max, max_posts=RAY_RASTER_MAX_POSTS)

    def ray_raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float) -> Raster | None:
        """:meth:`raster_for` for a group of rays (terrain.terrain.Terrain splits a batch by it): a
        box whose regions merge into more than RAY_RASTER_MAX_POSTS posts raises LimitExceeded
        rather than keeping one region, so that rays over each region are answered from it."""
        return self.store.raster(self.level, lat_min, lon_min, lat_max, lon_max, max_posts=RAY_RASTER_MAX_POSTS,
                                 strict=True)

    def describe(self) -> dict:
        """Metadata (Terrain.describe, GetMetadata): the bounds hold every region's (longitudes
        the shortest way round: lon_max passes 180 for regions across the antimeridian);
        filled_posts is the import's count of level-0 posts in filled voids; a store imported with
        synthetic detail says so (:func:`detail_description`: detail, detail_seed, ...)."""
        s = self.store
        lat_min = min(r.bounds[0] for r in s.regions)
        lat_max = max(r.bounds[2] for r in s.regions)
        lon_min, lon_max = lon_cover([(r.bounds[1], r.bounds[3]) for r in s.regions])
        dlat, dlon = s.spacing_deg(self.level)
        # Ground spacing at the first region's centre latitude (the regions may lie anywhere).
        lat_c = math.radians((s.regions[0].bounds[0] + s.regions[0].bounds[2]) / 2)
        metres_per_deg = math.pi / 180.0 * 6371008.8
        return {"name": s.name, "kind": "store", "crs": "EPSG:4326",
                "spacing_east_m": dlon * metres_per_deg * math.cos(lat_c), "spacing_north_m": dlat * metres_per_deg,
                "store_regions": len(s.regions), "store_step_m": s.step_units * s.unit_m,
                "filled_posts": int((s.manifest.get("summary") or {}).get("filled_posts", 0)),
                "lat_min": lat_min, "lon_min": lon_min, "lat_max": lat_max, "lon_max": lon_max,
                "resolution_lat_deg": dlat, "resolution_lon_deg": dlon,
                "vertical_datum": s.manifest.get("vertical_datum", "EGM96"),
                "source": str(s.path), "store_levels": s.levels, "store_depth": s.depth,
                "max_error_m": s.max_error_m,
                # Half the step, 0 when lossless (GetMetadata: TerrainSource.details, as text).
                "store_quantisation_m": s.quantisation_bound_m,
                # Synthetic detail baked in at import (sortie terrain import --add-detail), if any.
                **detail_description(s.manifest)}


def lon_cover(spans) -> tuple[float, float]:
    """(lon_min, lon_max) degrees of the shortest eastward arc holding every (west, east) span
    (east >= west, any turn): lon_min in [-180, 180), lon_max up to a turn east of it (past 180
    for an arc across the antimeridian); (-180, 180) when the spans go round the globe. Plain
    minima and maxima make regions a few posts apart across the antimeridian span the globe."""
    spans = [((w + 180.0) % 360.0 - 180.0, e - w) for w, e in spans]
    best = None
    for west, _ in spans:  # the arc starts at some span's west end
        east = max(west + (w - west) % 360.0 + width for w, width in spans)
        if best is None or east - west < best[1] - best[0]:
            best = (west, east)
    if best[1] - best[0] >= 360.0:
        return -180.0, 180.0
    return best


# Point statuses of the classes (tests and the service map through this).
CLASS_STATUS = {CLASS_OUTSIDE: STATUS_OUTSIDE, CLASS_MEASURED: STATUS_OK, CLASS_FILLED: STATUS_FILLED}


def level_file(path, region: int, level: int) -> Path:
    """A region's level file in the store directory ``path`` (docs/STORE.md, Files)."""
    return Path(path) / f"region-{region:03d}" / f"level-{level:02d}.tiles"


def level_files(path, regions) -> list[Path]:
    """The level files a manifest's ``regions`` list: one per region and level of its ``rects``."""
    return [level_file(path, r["index"], k) for r in regions for k in range(len(r["rects"]))]


def write_level_file(path: Path, level: int, tiles: dict[tuple[int, int], tuple[bytes, bytes]]) -> None:
    """Write one level's tiles atomically (temporary file, then rename); the OSError of a write that
    fails propagates, its temporary file removed."""
    keys = sorted(tiles)
    index = np.zeros(len(keys), _INDEX_ENTRY)
    offset = _LEVEL_HEAD.size + index.nbytes
    for i, key in enumerate(keys):
        h, c = tiles[key]
        index[i] = (key[0], key[1], offset, len(h), len(c))
        offset += len(h) + len(c)
    tmp = path.with_suffix(".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(_LEVEL_HEAD.pack(LEVEL_MAGIC, FORMAT_VERSION, level, len(keys)))
            f.write(index.tobytes())
            for key in keys:
                f.write(tiles[key][0])
                f.write(tiles[key][1])
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # a write that failed (a full disk) leaves no partial file
            tmp.unlink(missing_ok=True)
        raise


def code_classes(classes: np.ndarray) -> bytes:
    """A tile's class blob: empty when all measured, one byte when uniform, else a zstd frame with
    its content checksum (XXH64, RFC 8878 section 3.1.1), so that damage inside it that still
    decodes is refused (classes of stores imported before are read as before, unchecked)."""
    first = int(classes.flat[0])
    if np.all(classes == first):
        return b"" if first == CLASS_MEASURED else bytes([first])
    return zstandard.ZstdCompressor(level=9, write_checksum=True).compress(
        np.ascontiguousarray(classes, np.uint8).tobytes())


__all__ = ["TerrainStore", "StoreSource", "open_store", "lattice_spacing_deg", "depth_for_spacing",
           "heightcodec"]
