"""Aerial texture synthesis from a height grid, after Microsoft Flight Simulator X.

Source: A. Szofran, "Global Terrain Technology for Flight Simulation",
Microsoft ACES Game Studio, 2006, section 7 "Synthesis of aerial imagery"
(copy in ../shared/seeds/global-terrain-flight-sim.txt).

The steps of §7 without the land-class and vector data FSX had: a class map
from elevation bands and distance to water (§7.1), modulated by slope through
a lookup table (§7.1, figures 12-13); procedural tileable class textures
applied with the class map as a stencil (§7.2); a light map of sky-exposure
ambient light, N.L directional sun light and cast terrain shadows (§7.4);
the product of diffuse and light as the final image.

Grid convention for every function here: ``heights`` is (rows, cols) float64
metres above mean sea level, north up: row 0 is the NORTH edge, column 0 the
WEST edge; ``dx_m`` is the east-west and ``dy_m`` the north-south post
spacing in metres (both positive). NaN heights mean "no data". A lat/lon grid
gets its metre spacings from :func:`metre_spacing`.

Water and quantised heights: water is where the height is at or below
ClassParams.sea_level_m plus a height tolerance, the quantisation bound of the
grid's source (``water_tolerance_m`` of :func:`base_classes`, :func:`class_map`
and :func:`synthesize`). A DEM, a lossless store and a procedural world have
bound 0: water is exactly ``h <= sea_level_m``, as before. A lossy terrain
store of step s (docs/STORE.md) decodes every post within s/2 of its imported
value (closed-loop quantisation), so it cannot tell a sea at 0 m from ground
at s/2: sea posts come back anywhere in [-s/2, s/2], and bilinear samples
between them too. Posts within s/2 of sea level are therefore water
(``h <= sea_level_m + s/2``); the price is that low shore ground within s/2 of
sea level is drawn as water as well. ``sortie terrain texture`` takes the
bound from its terrain's sources (terrain/texture_cli.py), locally or over
the terrain service's metadata.

Everything is a plain numpy array function; :func:`synthesize` strings them
together. Determinism: the same inputs and seed give bit-identical arrays
(noise comes from the SplitMix64 lattice hash of terrain/procedural.py, not
from a random-number generator's stream).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from terrain.geodesy import radii_of_curvature
from terrain.procedural import lattice_uniform

# --------------------------------------------------------------------------- classes

NODATA, WATER, BEACH, FARMLAND, GRASS, FOREST, ALPINE, ROCK, SNOW = range(9)
CLASS_NAMES = ("nodata", "water", "beach", "farmland", "grass_shrub", "forest", "alpine_meadow", "rock", "snow")
N_CLASSES = len(CLASS_NAMES)

# Legend colours (sRGB, 0-255) for the class map image; the textures' mean colours are near these.
CLASS_COLOURS_RGB = np.array([
    (64, 64, 64),      # nodata
    (30, 70, 120),     # water
    (214, 196, 140),   # beach
    (170, 178, 90),    # farmland
    (112, 140, 62),    # grass and shrub
    (40, 80, 38),      # forest
    (150, 160, 100),   # alpine meadow
    (130, 126, 120),   # rock
    (245, 247, 252),   # snow
], dtype=np.uint8)

# Slope bins (index into the lookup table's columns): 0 flat, 1 moderate, 2 steep, 3 cliff.
SLOPE_BIN_NAMES = ("flat", "moderate", "steep", "cliff")

# The slope lookup table of §7.1: row = the class from elevation and water, column = slope bin,
# value = the class drawn. Steep ground loses its farmland (left to grass and scrub, then
# woods), trees give way to rock on cliffs ("the carpet of trees is often interrupted by the
# steepest parts of the terrain"), a steep shore is rock, snow does not lie on cliffs.
SLOPE_LUT = np.array([
    # flat      moderate  steep     cliff
    [NODATA,   NODATA,   NODATA,   NODATA],    # nodata
    [WATER,    WATER,    WATER,    WATER],     # water: decided by height alone
    [BEACH,    GRASS,    ROCK,     ROCK],      # beach
    [FARMLAND, GRASS,    FOREST,   ROCK],      # farmland
    [GRASS,    GRASS,    FOREST,   ROCK],      # grass and shrub
    [FOREST,   FOREST,   FOREST,   ROCK],      # forest
    [ALPINE,   ALPINE,   ROCK,     ROCK],      # alpine meadow
    [ROCK,     ROCK,     ROCK,     ROCK],      # rock
    [SNOW,     SNOW,     SNOW,     ROCK],      # snow
], dtype=np.uint8)


def _piecewise(table) -> tuple[tuple[float, float], ...]:
    return tuple((float(a), float(b)) for a, b in table)


@dataclass(frozen=True)
class ClassParams:
    """Every threshold of :func:`class_map`; override any with ``ClassParams(name=value)``.

    Heights are metres MSL, slopes degrees, lines are (abs latitude deg,
    height m) pairs interpolated linearly (constant beyond the ends).

    The snow and tree lines are hand-fitted to commonly quoted regional
    values (Alps at 46 N: tree line about 2000 m, climatic snow line about
    2900 m; southern Scandinavia at 62 N: about 900 m and 1500 m; Svalbard at
    78 N: no trees, snow line about 450 m; equatorial Andes and East Africa:
    about 3800 m and 4800 m). They are a visual rule, not climatology:
    aspect, continentality and precipitation move real lines by hundreds of metres.
    """

    sea_level_m: float = 0.0  # height <= this (plus the source's quantisation bound) is water (SRTM: sea at 0 m)
    shore_width_m: float = 90.0  # land this close to water (along rows and columns) is shore ...
    shore_max_height_m: float = 6.0  # ... when it is no higher than this
    forest_min_m: float = 800.0  # lowland farmland below, forest above (to the tree line)
    woodlot_fraction: float = 0.3  # share of the lowland drawn as forest patches
    woodlot_scale_m: float = 2500.0  # feature size of those patches
    alpine_band_m: float = 450.0  # meadow from the tree line up this far, then rock to the snow line
    band_jitter_m: float = 80.0  # noise amplitude added to every band edge, so they are not contour lines
    band_jitter_scale_m: float = 1200.0  # feature size of that noise
    # Slope bin edges (degrees): flat < 12 <= moderate < 25 <= steep < 38 <= cliff.
    slope_bins_deg: tuple[float, float, float] = (12.0, 25.0, 38.0)
    snow_line: tuple[tuple[float, float], ...] = field(default_factory=lambda: _piecewise(
        [(0, 4800), (30, 4800), (46, 2900), (62, 1500), (78, 450), (90, 0)]))
    tree_line: tuple[tuple[float, float], ...] = field(default_factory=lambda: _piecewise(
        [(0, 3800), (30, 3500), (46, 2000), (62, 900), (70, 400), (78, 0), (90, 0)]))
    slope_lut: tuple[tuple[int, ...], ...] = field(default_factory=lambda: tuple(map(tuple, SLOPE_LUT.tolist())))

    def __post_init__(self):
        lut = np.asarray(self.slope_lut)
        if lut.shape != (N_CLASSES, len(SLOPE_BIN_NAMES)) or lut.min() < 0 or lut.max() >= N_CLASSES:
            raise ValueError(f"slope_lut must be {N_CLASSES} x {len(SLOPE_BIN_NAMES)} class numbers, "
                             f"got shape {lut.shape}")
        if list(self.slope_bins_deg) != sorted(self.slope_bins_deg) or len(self.slope_bins_deg) != 3:
            raise ValueError(f"slope_bins_deg must be 3 ascending angles, got {self.slope_bins_deg}")


def line_height_m(table, lat_deg) -> np.ndarray:
    """A (abs latitude, height) line such as ClassParams.snow_line at latitudes (degrees)."""
    pts = np.asarray(table, dtype=np.float64)
    return np.interp(np.abs(np.asarray(lat_deg, dtype=np.float64)), pts[:, 0], pts[:, 1])


# --------------------------------------------------------------------------- grid geometry

def metre_spacing(lat_min_deg: float, lat_max_deg: float, dlat_deg: float, dlon_deg: float) -> tuple[float, float]:
    """(dx_m, dy_m) of a lat/lon grid at its centre latitude, WGS84.

    dy = M(phi) dlat and dx = N(phi) cos(phi) dlon in radians, M and N the
    meridian and prime-vertical radii of curvature (terrain.geodesy). Over a
    1-degree grid the true east-west spacing varies by about
    tan(phi) * 0.5 deg in relative terms from the centre value (1 % at 47 N).
    """
    phi = 0.5 * (lat_min_deg + lat_max_deg)
    m, n = radii_of_curvature(phi)
    dy = float(m * np.radians(dlat_deg))
    dx = float(n * np.cos(np.radians(phi)) * np.radians(dlon_deg))
    return dx, dy


def grid_latlon(lat_min: float, lon_min: float, lat_max: float, lon_max: float,
                rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre latitudes (rows,) north to south and longitudes (cols,) west to east.

    Pixel (i, j) covers [lat_max - (i+1) dlat, lat_max - i dlat] x
    [lon_min + j dlon, lon_min + (j+1) dlon], dlat = (lat_max - lat_min) / rows.
    """
    dlat = (lat_max - lat_min) / rows
    dlon = (lon_max - lon_min) / cols
    lat = lat_max - (np.arange(rows) + 0.5) * dlat
    lon = lon_min + (np.arange(cols) + 0.5) * dlon
    return lat, lon


def gradient_en(heights, dx_m: float, dy_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(dz/d_east, dz/d_north), dimensionless, by central differences.

    Interior posts: (z[c+1] - z[c-1]) / 2dx; edges: one-sided first
    differences (numpy.gradient, edge_order=1). Row 0 is north, so
    dz/d_north = -(dz/d_row) / dy. NaN spreads to neighbours.
    """
    z = np.asarray(heights, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"heights must be 2-D with at least 2 rows and 2 columns, got shape {z.shape}")
    d_row, d_col = np.gradient(z)
    return d_col / dx_m, -d_row / dy_m


def slope_deg(heights, dx_m: float, dy_m: float) -> np.ndarray:
    """Slope angle from horizontal, degrees (rows, cols) float64, from :func:`gradient_en`."""
    de, dn = gradient_en(heights, dx_m, dy_m)
    return np.degrees(np.arctan(np.hypot(de, dn)))


def normals_enu(heights, dx_m: float, dy_m: float) -> np.ndarray:
    """Unit surface normals (east, north, up), (rows, cols, 3) float64: (-dz/de, -dz/dn, 1) normalised."""
    de, dn = gradient_en(heights, dx_m, dy_m)
    n = np.stack([-de, -dn, np.ones_like(de)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n


# --------------------------------------------------------------------------- noise

def _smoothstep(t):
    return t * t * (3.0 - 2.0 * t)


def value_noise(x, y, seed: int, period: int | None = None) -> np.ndarray:
    """Smooth value noise in [0, 1) at lattice coordinates (x, y) (broadcast arrays).

    Lattice values are :func:`terrain.procedural.lattice_uniform` of the
    integer post (seed, row=y, col=x), blended with the cubic smoothstep
    (Perlin 1985's value-noise interpolation). period: wrap the lattice every
    ``period`` posts, which makes the noise tile with that period.
    """
    seed = int(seed) % (1 << 64)  # any integer seed, negative ones included
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    x0, y0 = np.floor(x), np.floor(y)
    tx, ty = _smoothstep(x - x0), _smoothstep(y - y0)
    ix, iy = x0.astype(np.int64), y0.astype(np.int64)
    if ix.size == 0 or iy.size == 0:
        return np.zeros(np.broadcast(ix, iy).shape)
    # Hash each lattice post once: a table over the posts' box, then gather (same values
    # as hashing per point; far fewer hashes when many points share a lattice cell).
    lo_x, lo_y = int(ix.min()), int(iy.min())
    nx, ny = int(ix.max()) - lo_x + 2, int(iy.max()) - lo_y + 2
    cols = np.arange(lo_x, lo_x + nx)[None, :]
    rows = np.arange(lo_y, lo_y + ny)[:, None]
    if period is not None:
        cols, rows = cols % period, rows % period
    if nx * ny <= np.broadcast(ix, iy).size:
        table = lattice_uniform(seed, rows, cols)
        jx, jy = ix - lo_x, iy - lo_y
        v00, v01 = table[jy, jx], table[jy, jx + 1]
        v10, v11 = table[jy + 1, jx], table[jy + 1, jx + 1]
    else:
        ix1, iy1 = ix + 1, iy + 1
        if period is not None:
            ix, ix1, iy, iy1 = ix % period, ix1 % period, iy % period, iy1 % period
        v00, v01 = lattice_uniform(seed, iy, ix), lattice_uniform(seed, iy, ix1)
        v10, v11 = lattice_uniform(seed, iy1, ix), lattice_uniform(seed, iy1, ix1)
    top = v00 + (v01 - v00) * tx
    bottom = v10 + (v11 - v10) * tx
    return top + (bottom - top) * ty


def fractal_noise(x, y, seed: int, octaves: int = 3, period: int | None = None) -> np.ndarray:
    """Sum of :func:`value_noise` octaves (frequency x2, amplitude /2), rescaled to [0, 1]."""
    total = 0.0
    norm = 0.0
    for o in range(octaves):
        f = 2**o
        total = total + value_noise(np.asarray(x) * f, np.asarray(y) * f, seed + 7919 * o,
                                    None if period is None else period * f) / f
        norm += 1.0 / f
    return total / norm


# --------------------------------------------------------------------------- class map

def _near(mask: np.ndarray, half_rows: int, half_cols: int) -> np.ndarray:
    """True where mask has a True within a (2 half_rows + 1) x (2 half_cols + 1) box (summed-area table)."""
    if half_rows == 0 and half_cols == 0:
        return mask.copy()
    rows, cols = mask.shape
    s = np.zeros((rows + 1, cols + 1), dtype=np.int64)
    np.cumsum(np.cumsum(mask, axis=0), axis=1, out=s[1:, 1:])
    r0 = np.clip(np.arange(rows) - half_rows, 0, rows)
    r1 = np.clip(np.arange(rows) + half_rows + 1, 0, rows)
    c0 = np.clip(np.arange(cols) - half_cols, 0, cols)
    c1 = np.clip(np.arange(cols) + half_cols + 1, 0, cols)
    box = s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]
    return box > 0


def slope_bins(slope, params: ClassParams = ClassParams()) -> np.ndarray:
    """Slope bin (0 flat .. 3 cliff) of each slope, uint8; NaN slopes count as flat."""
    s = np.asarray(slope, dtype=np.float64)
    out = np.zeros(s.shape, dtype=np.uint8)
    for edge in params.slope_bins_deg:
        out += s >= edge
    return out


def check_water_tolerance(water_tolerance_m) -> float:
    """A water tolerance (metres) as float: finite and 0 or more, else ValueError naming it."""
    tol = float(water_tolerance_m)
    if not (np.isfinite(tol) and tol >= 0.0):
        raise ValueError(f"water_tolerance_m must be a finite number of metres, 0 or more, got {water_tolerance_m!r}")
    return tol


def base_classes(heights, dx_m: float, dy_m: float, lat_deg=45.0, *, params: ClassParams = ClassParams(),
                 seed: int = 0, noise_en_m=None, water_tolerance_m: float = 0.0) -> np.ndarray:
    """The class of each post from height, latitude and water alone (before slope), uint8.

    Rules, first match wins (h: height m MSL, jitter: band noise of amplitude
    band_jitter_m added to every band edge):

    ==============  ==========================================================
    class           rule
    ==============  ==========================================================
    nodata (0)      h is NaN
    water (1)       h <= sea_level_m + water_tolerance_m (0 m: SRTM
                    writes the sea as 0; the tolerance is the source's
                    quantisation bound, see the module docstring)
    beach (2)       h <= shore_max_height_m and water within shore_width_m
                    along rows and columns (a box, not a disc)
    snow (8)        h >= snow line(lat) + jitter
    rock (7)        h >= tree line(lat) + alpine_band_m + jitter
    alpine (6)      h >= tree line(lat) + jitter, or tree line(lat) <= 0
                    (no trees at all: Svalbard and north of it, all land is
                    above the tree line whatever the jitter)
    forest (5)      h >= min(forest_min_m, tree line) + jitter, or a woodlot
                    (woodlot noise < woodlot_fraction) below that
    farmland (3)    everything else (lowland)
    ==============  ==========================================================

    grass and shrub (4) only comes from the slope table (farmland on
    moderate slopes). lat_deg: scalar or broadcastable to heights (e.g. a
    (rows, 1) column). noise_en_m: (east_m, north_m) arrays broadcastable to
    heights placing each post for the noise (give world positions so that
    neighbouring grids agree); default: the grid's own (col dx, -row dy).
    water_tolerance_m: the quantisation bound of the heights' source (0 for a
    DEM or a lossless store, half the step for a lossy store).
    """
    tol = check_water_tolerance(water_tolerance_m)
    z = np.asarray(heights, dtype=np.float64)
    rows, cols = z.shape
    if noise_en_m is None:
        east = (np.arange(cols) * dx_m)[None, :]
        north = (-np.arange(rows) * dy_m)[:, None]
    else:
        east, north = noise_en_m
    p = params
    jitter = p.band_jitter_m * (2.0 * fractal_noise(np.asarray(east) / p.band_jitter_scale_m,
                                                    np.asarray(north) / p.band_jitter_scale_m, seed + 1) - 1.0)
    jitter = np.broadcast_to(jitter, z.shape)
    woodlot = np.broadcast_to(fractal_noise(np.asarray(east) / p.woodlot_scale_m,
                                            np.asarray(north) / p.woodlot_scale_m, seed + 2), z.shape)
    snow_line = line_height_m(p.snow_line, lat_deg)
    tree_line = line_height_m(p.tree_line, lat_deg)
    forest_min = np.minimum(p.forest_min_m, tree_line)

    nodata = np.isnan(z)
    # False for NaN. A tolerance of 0.0 leaves sea_level_m as it is: a DEM's classes are unchanged.
    water = z <= p.sea_level_m + tol
    out = np.full(z.shape, FARMLAND, dtype=np.uint8)
    out[woodlot < stretch_fraction(p.woodlot_fraction)] = FOREST
    zj = z - jitter
    out[zj >= forest_min] = FOREST
    out[(zj >= tree_line) | (tree_line <= 0.0)] = ALPINE  # no woodlot or farmland where no tree grows
    out[zj >= tree_line + p.alpine_band_m] = ROCK
    out[zj >= snow_line] = SNOW
    if water.any() and p.shore_width_m > 0:
        shore = _near(water, int(round(p.shore_width_m / dy_m)), int(round(p.shore_width_m / dx_m)))
        out[shore & (z <= p.shore_max_height_m)] = BEACH
    out[water] = WATER
    out[nodata] = NODATA
    return out


def stretch_fraction(fraction: float) -> float:
    """The threshold t with P(fractal_noise < t) near fraction.

    Three-octave value noise bunches around 0.5 (a sum of smoothed uniforms),
    so a share of ``fraction`` lies below 0.5 + (fraction - 0.5) * 0.45: a
    linear fit to the noise's measured distribution over 10^6 samples (to
    within 0.03 in share for fractions 0.1 .. 0.9; 0.024 measured).
    Fractions 0 and 1 give 0 and 1: none and all.
    """
    if fraction <= 0.0 or fraction >= 1.0:
        return float(np.clip(fraction, 0.0, 1.0))
    return 0.5 + (fraction - 0.5) * 0.45


def class_map(heights, slope, dx_m: float, dy_m: float, lat_deg=45.0, *, params: ClassParams = ClassParams(),
              seed: int = 0, noise_en_m=None, water_tolerance_m: float = 0.0) -> np.ndarray:
    """uint8 land class of each post: :func:`base_classes`, then the slope lookup table (§7.1).

    slope: degrees, (rows, cols) (from :func:`slope_deg`). The table
    (ClassParams.slope_lut, default :data:`SLOPE_LUT`), base class by slope
    bin (flat < 12 <= moderate < 25 <= steep < 38 <= cliff, degrees):

    ==============  ========  ========  ========  ======
    base class      flat      moderate  steep     cliff
    ==============  ========  ========  ========  ======
    nodata          nodata    nodata    nodata    nodata
    water           water     water     water     water
    beach           beach     grass     rock      rock
    farmland        farmland  grass     forest    rock
    grass/shrub     grass     grass     forest    rock
    forest          forest    forest    forest    rock
    alpine meadow   alpine    alpine    rock      rock
    rock            rock      rock      rock      rock
    snow            snow      snow      snow      rock
    ==============  ========  ========  ========  ======

    So: water is exactly where height <= sea_level_m + water_tolerance_m (the
    source's quantisation bound, 0 for a DEM: see the module docstring); every
    land post at cliff slope or steeper is rock; farmland only on flat ground.
    """
    base = base_classes(heights, dx_m, dy_m, lat_deg, params=params, seed=seed, noise_en_m=noise_en_m,
                        water_tolerance_m=water_tolerance_m)
    lut = np.asarray(params.slope_lut, dtype=np.uint8)
    return lut[base, slope_bins(slope, params)]


def class_histogram(classes) -> dict[str, int]:
    """Posts per class name."""
    counts = np.bincount(np.asarray(classes, dtype=np.uint8).ravel(), minlength=N_CLASSES)
    return {name: int(n) for name, n in zip(CLASS_NAMES, counts)}


# --------------------------------------------------------------------------- class textures

TILE_PX = 256

# Per class: two colours the noise blends between (sRGB 0..1), the noise's lattice period
# across a 256-pixel tile (larger = finer grain), fine-grain amplitude. Hand-picked to
# resemble the FSX tiles of figure 15 at about 10-100 m per pixel.
_TILE_STYLE = {
    NODATA: ((0.24, 0.24, 0.26), (0.26, 0.26, 0.28), 8, 0.00),
    WATER: ((0.09, 0.21, 0.36), (0.13, 0.28, 0.42), 8, 0.02),
    BEACH: ((0.78, 0.71, 0.50), (0.88, 0.82, 0.63), 16, 0.05),
    FARMLAND: ((0.55, 0.58, 0.30), (0.72, 0.70, 0.42), 16, 0.05),
    GRASS: ((0.35, 0.46, 0.20), (0.52, 0.58, 0.30), 32, 0.08),
    FOREST: ((0.10, 0.22, 0.10), (0.22, 0.38, 0.18), 64, 0.10),
    ALPINE: ((0.50, 0.56, 0.33), (0.66, 0.66, 0.46), 32, 0.07),
    ROCK: ((0.40, 0.39, 0.37), (0.64, 0.62, 0.58), 64, 0.10),
    SNOW: ((0.86, 0.89, 0.95), (0.98, 0.98, 1.00), 8, 0.02),
}

# Farmland fields: a patchwork of square fields (8 pixels on a 256-pixel tile), each one of these crops.
_FIELD_COLOURS = np.array([(0.50, 0.60, 0.28), (0.74, 0.68, 0.40), (0.42, 0.52, 0.24),
                           (0.58, 0.48, 0.34), (0.64, 0.66, 0.36)])


def class_tile(cls: int, size: int = TILE_PX, seed: int = 0) -> np.ndarray:
    """The diffuse ("sun overhead") texture of one class: (size, size, 3) float32 in [0, 1], tileable.

    Periodic fractal value noise (lattice wrapped at the tile edge, so the
    tile repeats seamlessly) blends the class's two colours; a finer
    octave adds grain. Farmland adds a patchwork of 8-pixel fields with
    darker field edges. size: a multiple of 32.
    Deterministic in (cls, size, seed).
    """
    if size < 32 or size % 32:
        raise ValueError(f"size must be a positive multiple of 32, got {size}")
    c0, c1, period, grain = _TILE_STYLE[cls]
    period = max(2, period * size // TILE_PX)
    u = (np.arange(size) + 0.5) / size
    x, y = u[None, :], u[:, None]
    s = seed * 1009 + cls * 131
    n = fractal_noise(x * period, y * period, s, octaves=3, period=period)
    fine = value_noise(x * size / 2, y * size / 2, s + 17, period=size // 2) - 0.5
    t = np.clip((n - 0.5) * 2.2 + 0.5 + grain * 2.0 * fine, 0.0, 1.0)[..., None]
    rgb = np.asarray(c0) + (np.asarray(c1) - np.asarray(c0)) * t
    if cls == FARMLAND:
        field_px = 8
        f = np.arange(size) // field_px
        pick = (lattice_uniform((s + 3) % (1 << 64), f[:, None], f[None, :]) * len(_FIELD_COLOURS)).astype(np.int64)
        crop = _FIELD_COLOURS[pick]
        rgb = 0.35 * rgb + 0.65 * crop * (0.9 + 0.2 * t)
        edge = np.arange(size) % field_px == 0
        hedge = edge[:, None] | edge[None, :]
        rgb[hedge] *= 0.88
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def class_tiles(size: int = TILE_PX, seed: int = 0) -> np.ndarray:
    """Every class's tile: (N_CLASSES, size, size, 3) float32."""
    return np.stack([class_tile(k, size, seed) for k in range(N_CLASSES)])


def _box_blur(a: np.ndarray, r: int) -> np.ndarray:
    """Mean over a (2r + 1)^2 box, the box cut at the grid edges (summed-area table)."""
    rows, cols = a.shape
    s = np.zeros((rows + 1, cols + 1))
    np.cumsum(np.cumsum(a, axis=0), axis=1, out=s[1:, 1:])
    r0, r1 = np.clip(np.arange(rows) - r, 0, rows), np.clip(np.arange(rows) + r + 1, 0, rows)
    c0, c1 = np.clip(np.arange(cols) - r, 0, cols), np.clip(np.arange(cols) + r + 1, 0, cols)
    area = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    return (s[r1][:, c1] - s[r0][:, c1] - s[r1][:, c0] + s[r0][:, c0]) / area


def diffuse(classes, tiles: np.ndarray | None = None, *, soft_px: int = 0, seed: int = 0) -> np.ndarray:
    """Diffuse texture (rows, cols, 3) float32 in [0, 1] from a class map (§7.2).

    Each class's tile (``tiles``: (N_CLASSES, T, T, 3), default
    :func:`class_tiles`) repeats over the whole grid, pixel (i, j) reading
    texel (i mod T, j mod T), and is drawn where the class map holds that
    class: the class map is the stencil. soft_px > 0 blends instead: each
    class weighs by its share of a (2 soft_px + 1)^2 box around the pixel,
    which softens class edges over about soft_px pixels (water keeps a hard
    edge: it is stencilled over the blend, as FSX draws water bodies last).
    """
    cm = np.asarray(classes, dtype=np.uint8)
    if tiles is None:
        tiles = class_tiles(seed=seed)
    t = tiles.shape[1]
    ri = (np.arange(cm.shape[0]) % t)[:, None]
    ci = (np.arange(cm.shape[1]) % t)[None, :]
    hard = tiles[cm, ri, ci]  # one gather: the stencil of every class at once
    if soft_px <= 0:
        return hard
    out = np.zeros(cm.shape + (3,), dtype=np.float64)
    total = np.zeros(cm.shape)
    for k in np.unique(cm):
        w = _box_blur((cm == k).astype(np.float64), soft_px)
        out += w[..., None] * tiles[k][ri, ci]
        total += w
    out /= total[..., None]
    water = cm == WATER
    out[water] = hard[water]
    return out.astype(np.float32)


# --------------------------------------------------------------------------- light map

@dataclass(frozen=True)
class LightParams:
    """Light map weights and reach.

    ambient + sun = 1 makes a flat plane under an overhead sun exactly 1.
    night_ambient: the ambient weight once the sun is 6 degrees below the
    horizon (end of civil twilight); between -6 and 0 degrees it ramps
    linearly up to ``ambient``.
    """

    ambient: float = 0.35
    sun: float = 0.65
    night_ambient: float = 0.06
    twilight_deg: float = 6.0
    sky_azimuths: int = 16  # directions for the sky-view factor
    sky_radius_m: float = 2500.0  # how far each direction looks for its horizon
    shadow_max_m: float | None = None  # cap on cast-shadow length; None: the whole grid


@dataclass(frozen=True)
class LightResult:
    """light: (rows, cols) float32 in [0, 1]; shadow: bool, True where the sun is hidden
    (by terrain, or everywhere at night); sky: float32 sky-view factor in [0, 1];
    n_dot_l: float32 cosine of the sun's incidence (negative: facing away)."""

    light: np.ndarray
    shadow: np.ndarray
    sky: np.ndarray
    n_dot_l: np.ndarray


def _sky_steps(radius_lines: float) -> list[int]:
    """Line offsets for the horizon search: every line to 6, then x1.25 per step (rounded, distinct)."""
    steps = [1, 2, 3, 4, 5, 6]
    while True:
        nxt = int(round(steps[-1] * 1.25))
        if nxt > radius_lines:
            break
        steps.append(nxt)
    return [k for k in steps if k <= max(radius_lines, 1.0)]


def _shifted_views(rows: int, cols: int, dr: int, dc: int):
    """Slices (target, source) so that target[i, j] pairs with source pixel (i + dr, j + dc)."""
    if abs(dr) >= rows or abs(dc) >= cols:
        return None
    tr = slice(max(0, -dr), rows - max(0, dr))
    tc = slice(max(0, -dc), cols - max(0, dc))
    sr = slice(max(0, dr), rows + min(0, dr))
    sc = slice(max(0, dc), cols + min(0, dc))
    return (tr, tc), (sr, sc)


def sky_view(heights, dx_m: float, dy_m: float, *, azimuths: int = 16, radius_m: float = 2500.0) -> np.ndarray:
    """Sky-view factor of each post, float32 in [0, 1] (1: the whole sky dome is open).

    For each of ``azimuths`` directions (from north, evenly spaced), the
    horizon elevation angle h is the largest atan(dz / d) over sample points
    on the straight line out to radius_m: the line crosses the rows (or the
    columns, whichever it is closer to parallel with) at offsets 1..6 then
    x1.25 per step, and each sample is linearly interpolated between the two
    posts it falls between, so d is the true distance along the line. h is
    clamped at 0 (a pinnacle sees no less than a flat plane). The factor is
    the mean over directions of cos^2(h): the share of an isotropic sky's
    diffuse light a horizontal surface receives with that horizon (Dozier &
    Frew 1990, IEEE TGRS 28(5), eq. 7 without the surface tilt term). Points
    beyond the grid or with no data do not obstruct. A flat plane gives exactly 1.
    """
    z = np.asarray(heights, dtype=np.float32)  # float32: half the memory traffic, 1 mm at 9 km
    total = np.zeros(z.shape)
    for k in range(azimuths):
        az = 2.0 * np.pi * k / azimuths
        east, north = np.sin(az), np.cos(az)
        tan_h = np.zeros(z.shape, dtype=np.float32)  # horizon tangent, starts at the flat horizon
        if abs(north) / dy_m >= abs(east) / dx_m:
            # Step whole rows (north is row -1); the column offset per row is fractional.
            grid, out, line_m, along = z, tan_h, dy_m / abs(north), -np.sign(north)
            side = east * (dy_m / abs(north)) / dx_m
        else:
            # Step whole columns: work on the transposes (views), rows and columns swapped.
            grid, out, line_m, along = z.T, tan_h.T, dx_m / abs(east), np.sign(east)
            side = -north * (dx_m / abs(east)) / dy_m
        for step in _sky_steps(radius_m / line_m):
            got = _line_sample(grid, int(along * step), side * step)
            if got is None:
                break
            (tr, tc), sample = got
            rise = (sample - grid[tr, tc]) * np.float32(1.0 / (step * line_m))
            np.fmax(out[tr, tc], rise, out=out[tr, tc])  # fmax: NaN (no data) never wins
        total += 1.0 / (1.0 + tan_h.astype(np.float64) ** 2)  # cos^2(atan t)
    return (total / azimuths).astype(np.float32)


def _line_sample(grid: np.ndarray, dr: int, dc: float):
    """Heights at (i + dr, j + dc) for every post (i, j) whose sample lies inside the grid,
    linear between the two posts either side of the fractional column j + dc.

    Returns ((row slice, column slice) of the posts, the samples), or None when none lie inside.
    """
    rows, cols = grid.shape
    c0 = int(np.floor(dc))
    w = np.float32(dc - c0)
    if abs(dr) >= rows or c0 >= cols or c0 + 1 <= -cols:
        return None
    tr = slice(max(0, -dr), rows - max(0, dr))
    sr = slice(tr.start + dr, tr.stop + dr)
    # Posts j with both j + c0 and j + c0 + 1 inside (only j + c0 when w is 0).
    hi = c0 + (1 if w > 0 else 0)
    j0, j1 = max(0, -c0), cols - max(0, hi)
    if j1 <= j0:
        return None
    left = grid[sr, j0 + c0:j1 + c0]
    if w == 0:
        return (tr, slice(j0, j1)), left
    right = grid[sr, j0 + c0 + 1:j1 + c0 + 1]
    return (tr, slice(j0, j1)), left + (right - left) * w


def cast_shadow(heights, dx_m: float, dy_m: float, sun_az_deg, sun_el_deg,
                *, max_distance_m: float | None = None) -> np.ndarray:
    """True where terrain toward the sun rises above the sun's elevation (a cast shadow).

    A post p is in shadow when some point at distance d > 0 toward the sun
    is higher than z(p) + d tan(elevation). Swept in one pass instead of
    marched per post: with H(p) = max over d of [z(p + d u) - d tan e], the
    ray envelope, H(p) = max(z, H)(p') - delta tan e where p' is the
    neighbour one row (or column, whichever axis the sun's direction is
    closer to) toward the sun, at along-ray distance delta. p' is picked
    along digital lines (the accumulated sideways offset rounded, as
    Bresenham's algorithm), so every ray follows a chain of posts within
    half a pixel sideways of the true ray, and the envelope along it is
    exact. Shadow: H(p) > z(p). Earth curvature is ignored (it would lower a
    blocker d away by d^2 / 2R: 20 m at 16 km). NaN posts neither cast nor
    receive shadows. max_distance_m: forget blockers farther than this (None: any).
    Below or on the horizon everything is in shadow.

    sun_az_deg, sun_el_deg: scalars (one sun for the whole grid), or arrays
    broadcastable to the grid: each post's own sun (:func:`_cast_shadow_field`).
    """
    z = np.asarray(heights, dtype=np.float64)
    if np.ndim(sun_az_deg) or np.ndim(sun_el_deg):
        return _cast_shadow_field(z, dx_m, dy_m, sun_az_deg, sun_el_deg, max_distance_m)
    sun_az_deg, sun_el_deg = float(sun_az_deg), float(sun_el_deg)
    if sun_el_deg <= 0.0:
        return np.ones(z.shape, dtype=bool)
    az = np.radians(sun_az_deg)
    tan_e = np.tan(np.radians(sun_el_deg))
    se, cn = np.sin(az), np.cos(az)  # toward the sun: east, north components
    rows_rate, cols_rate = abs(cn) / dy_m, abs(se) / dx_m  # pixels per metre along the ray
    if rows_rate >= cols_rate:
        delta = dy_m / abs(cn)  # metres along the ray per row
        side = se * delta / dx_m  # columns toward the sun per row (|side| <= 1)
        # Canonical frame: line 0 is the sunward edge, line k+1 lies one step away from the sun.
        grid = z if cn > 0 else z[::-1]  # sun in the north: row 0 (north) first
        transpose, flip = False, cn <= 0
    else:
        delta = dx_m / abs(se)
        side = -cn * delta / dy_m  # rows toward the sun (row index grows southward) per column
        grid = z.T[::-1] if se > 0 else z.T  # sun in the east: the east column first
        transpose, flip = True, se > 0
    n_lines, width = grid.shape
    drop = delta * tan_e
    max_steps = n_lines if max_distance_m is None else max(1, int(max_distance_m / delta))
    env = np.full(grid.shape, -np.inf)
    lines = np.arange(n_lines)
    offs = np.floor(lines * side + 0.5).astype(np.int64)  # accumulated sideways offset, rounded
    if max_distance_m is None:
        for k in range(1, n_lines):
            shift = int(offs[k] - offs[k - 1])  # post j's ray crosses line k - 1 at post j + shift
            prev = np.fmax(grid[k - 1], env[k - 1])
            views = _shifted_views(1, width, 0, shift)
            if views is None:
                continue
            (_, tc), (_, sc) = views
            env[k, tc] = prev[sc] - drop
    else:
        # Bounded reach: march each line's rays back at most max_steps lines.
        for k in range(1, n_lines):
            for s in range(1, min(k, max_steps) + 1):
                shift = int(offs[k] - offs[k - s])
                views = _shifted_views(1, width, 0, shift)
                if views is None:
                    continue
                (_, tc), (_, sc) = views
                np.fmax(env[k, tc], grid[k - s, sc] - s * drop, out=env[k, tc])
    with np.errstate(invalid="ignore"):
        shadow = env > grid  # False where grid is NaN
    if flip:
        shadow = shadow[::-1]
    if transpose:
        shadow = shadow.T
    return np.ascontiguousarray(shadow)


def _cast_shadow_field(z: np.ndarray, dx_m: float, dy_m: float, sun_az_deg, sun_el_deg,
                       max_distance_m: float | None) -> np.ndarray:
    """:func:`cast_shadow` with each post's own sun: az and el arrays broadcastable to z.

    One sun everywhere (equal arrays) is cast_shadow's own sweep, exactly.
    Otherwise posts are sorted into four sweeps by the axis their sun is
    closer to and its side (north, south, east, west: the sunward edge
    first), and each sweep runs cast_shadow's recurrence with every post's
    own sun: H(p) = max(z, H) at the point one line toward p's sun (p's own
    sideways offset, linear between the two posts either side of it) minus
    p's own along-ray step times tan(p's elevation). Digital lines, exact for
    one sun, would step a post early or late wherever neighbouring posts'
    suns differ; the interpolation has no such jitter (it is exact on a
    plane) but blends the envelopes of neighbouring rays, as sky_view's
    samples do. Where the sun varies, the envelope p takes from its sunward
    neighbour was swept along that neighbour's sun, so a ray bends with the
    sun's direction along it: the error is the change of the sun's direction
    over the shadow's length (about 1 degree per degree of arc on the
    ground at mid-latitudes, 0.1 degree along a 10 km shadow; east-west,
    1/cos(latitude) times that toward the poles), not the change across the box.
    Within a sweep, posts whose sun lies on the far side of the sweep's axis
    pass on no envelope (only their height), and posts whose sun is nearer
    the other axis step diagonally (offset clamped to one post per line), so
    rays running from one sweep's posts into another's keep their blockers.
    """
    shape = z.shape
    az = np.broadcast_to(np.asarray(sun_az_deg, dtype=np.float64), shape)
    el = np.broadcast_to(np.asarray(sun_el_deg, dtype=np.float64), shape)
    if az.size and (az == az.flat[0]).all() and (el == el.flat[0]).all():
        return cast_shadow(z, dx_m, dy_m, float(az.flat[0]), float(el.flat[0]), max_distance_m=max_distance_m)
    up = el > 0.0  # False for NaN
    shadow = ~up  # below or on the horizon: in shadow
    rad = np.radians(az)
    se, cn = np.sin(rad), np.cos(rad)  # toward the sun: east, north components
    tan_e = np.tan(np.radians(np.where(up, el, 45.0)))
    rows_major = np.abs(cn) / dy_m >= np.abs(se) / dx_m
    # (members, view of a grid in the sweep's frame, forward and sideways components of the
    # direction to the sun, metres per line and per post across)
    sweeps = (
        (rows_major & (cn > 0), lambda a: a, cn, se, dy_m, dx_m),  # sun in the north: row 0 first
        (rows_major & (cn <= 0), lambda a: a[::-1], -cn, se, dy_m, dx_m),
        (~rows_major & (se > 0), lambda a: a.T[::-1], se, -cn, dx_m, dy_m),  # sun in the east: east column first
        (~rows_major & (se <= 0), lambda a: a.T, -se, -cn, dx_m, dy_m),
    )
    for members, frame, forward, sideways, line_m, across_m in sweeps:
        mine = members & up
        if not mine.any():
            continue
        grid = frame(z)
        fwd, sdw, tan_f = frame(forward), frame(sideways), frame(tan_e)
        toward = fwd > 0.0  # the sun on this sweep's side of the axis
        with np.errstate(divide="ignore", invalid="ignore"):
            side = np.where(toward, np.clip(sdw * (line_m / fwd) / across_m, -1.0, 1.0), 0.0)  # posts per line
        delta = np.hypot(line_m, side * across_m)  # metres along the (clamped) ray per line
        drop = np.where(toward & frame(up), delta * tan_f, np.inf)  # inf: passes on no envelope
        n_lines, width = grid.shape
        env = np.full(grid.shape, -np.inf)
        posts = np.arange(width)
        reach = None
        if max_distance_m is not None:
            reach = np.maximum(1, np.minimum(np.floor(max_distance_m / delta), n_lines)).astype(np.int64)
        for k in range(1, n_lines):
            if reach is None:
                steps = (1,)
            else:
                steps = range(1, min(k, int(reach[k].max())) + 1)
            for s in steps:
                src = grid[k - s] if reach is not None else np.fmax(grid[k - s], env[k - s])
                pos = posts + s * side[k]
                c0 = np.floor(pos).astype(np.int64)
                w = pos - c0
                left = np.where((c0 >= 0) & (c0 < width), src[np.clip(c0, 0, width - 1)], -np.inf)
                right = np.where((c0 + 1 >= 0) & (c0 + 1 < width), src[np.clip(c0 + 1, 0, width - 1)], -np.inf)
                both = np.isfinite(left) & np.isfinite(right)
                with np.errstate(invalid="ignore"):
                    val = np.where(both, left + (right - left) * w,
                                   np.where(w > 0.0, np.fmax(left, right), left)) - s * drop[k]
                if reach is not None:
                    val = np.where(s <= reach[k], val, -np.inf)
                np.fmax(env[k], val, out=env[k])
        with np.errstate(invalid="ignore"):
            cast = env > grid  # False where grid is NaN
        back = np.zeros(shape, dtype=bool)
        frame(back)[...] = cast  # the frame is a view: this writes back in the grid's own orientation
        shadow[mine] = back[mine]
    return np.ascontiguousarray(shadow)


def light_map(heights, dx_m: float, dy_m: float, sun_az_deg, sun_el_deg,
              *, params: LightParams = LightParams(), sky: np.ndarray | None = None) -> LightResult:
    """Light reaching each post (§7.4), float32 in [0, 1], and the shadow mask.

    light = ambient(e) * sky + sun * max(N.L, 0) * (not shadow), clipped to
    [0, 1]; sky from :func:`sky_view`, N from :func:`normals_enu`, L the unit
    vector toward the sun (terrain.sun.sun_direction_enu), shadow from
    :func:`cast_shadow`. With the sun at or below the horizon there is no
    directional term and shadow is all True; ambient(e) is params.ambient
    by day, falling linearly to params.night_ambient at -twilight_deg.
    No-data posts get light 0 and shadow False. ``sky``: a precomputed
    :func:`sky_view` (it does not depend on the sun).

    sun_az_deg, sun_el_deg: scalars, one sun for every post, or arrays
    broadcastable to the grid, each post's own sun (a box wide enough for
    the sun to differ across it: its ambient, N.L and day or night are each
    post's own, its shadows :func:`cast_shadow`'s per-post sweep).
    """
    from terrain.sun import sun_direction_enu

    z = np.asarray(heights, dtype=np.float64)
    p = params
    if sky is None:
        sky = sky_view(z, dx_m, dy_m, azimuths=p.sky_azimuths, radius_m=p.sky_radius_m)
    normal = normals_enu(z, dx_m, dy_m)
    per_post = bool(np.ndim(sun_az_deg) or np.ndim(sun_el_deg))
    if per_post:
        az = np.broadcast_to(np.asarray(sun_az_deg, dtype=np.float64), z.shape)
        el = np.broadcast_to(np.asarray(sun_el_deg, dtype=np.float64), z.shape)
        n_dot_l = np.einsum("ijk,ijk->ij", normal, sun_direction_enu(az, el))
    else:
        az, el = float(sun_az_deg), float(sun_el_deg)
        n_dot_l = normal @ sun_direction_enu(az, el)
    day = np.clip(1.0 + el / p.twilight_deg, 0.0, 1.0)
    ambient = p.night_ambient + (p.ambient - p.night_ambient) * day
    light = ambient * sky.astype(np.float64)
    if np.any(el > 0.0):
        shadow = cast_shadow(z, dx_m, dy_m, az, el, max_distance_m=p.shadow_max_m)  # True where el <= 0
        light = light + p.sun * np.where(shadow, 0.0, np.maximum(np.nan_to_num(n_dot_l), 0.0))
    else:
        shadow = np.ones(z.shape, dtype=bool)
    nodata = np.isnan(z)
    light[nodata] = 0.0
    shadow[nodata] = False
    return LightResult(np.clip(np.nan_to_num(light), 0.0, 1.0).astype(np.float32), shadow,
                       np.asarray(sky, dtype=np.float32), n_dot_l.astype(np.float32))


def compose(diffuse_rgb, light) -> np.ndarray:
    """The final image: diffuse x light per channel, rounded to uint8 RGB (rows, cols, 3)."""
    d = np.asarray(diffuse_rgb, dtype=np.float32)
    li = np.asarray(light, dtype=np.float32)
    return np.clip(np.rint(d * li[..., None] * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- all steps

@dataclass(frozen=True)
class Texture:
    """Every layer of one synthesized texture (see :func:`synthesize`)."""

    slope_deg: np.ndarray
    classes: np.ndarray
    diffuse: np.ndarray
    light: LightResult
    image: np.ndarray


def synthesize(heights, dx_m: float, dy_m: float, sun_az_deg, sun_el_deg, lat_deg=45.0, *,
               class_params: ClassParams = ClassParams(), light_params: LightParams = LightParams(),
               seed: int = 0, soft_px: int = 0, noise_en_m=None, water_tolerance_m: float = 0.0) -> Texture:
    """slope -> class map -> diffuse -> light map -> image, for one height grid.

    sun_az_deg, sun_el_deg: one sun (scalars) or each post's own (arrays broadcastable to
    the grid), as :func:`light_map` takes them. water_tolerance_m: the heights' source's
    quantisation bound (:func:`base_classes`; 0 for a DEM)."""
    slope = slope_deg(heights, dx_m, dy_m)
    classes = class_map(heights, slope, dx_m, dy_m, lat_deg, params=class_params, seed=seed,
                        noise_en_m=noise_en_m, water_tolerance_m=water_tolerance_m)
    rgb = diffuse(classes, soft_px=soft_px, seed=seed)
    light = light_map(heights, dx_m, dy_m, sun_az_deg, sun_el_deg, params=light_params)
    return Texture(slope, classes, rgb, light, compose(rgb, light.light))
