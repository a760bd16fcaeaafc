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
spacing in metres (positive): scalars for a grid with one spacing, or (rows,)
arrays, each row's own. A lat/lon grid takes each row's from
:func:`row_spacing` (its east-west spacing shrinks as cos(latitude), 2.5x from
30 to 75 N); slopes, normals, sky view and shadows use them row by row.
NaN heights mean "no data".

Water and quantised heights (:func:`water_mask`): water is where the height
is within a height tolerance of ClassParams.sea_level_m, the quantisation
bound of the grid's source (``water_tolerance_m`` of :func:`base_classes`,
:func:`class_map` and :func:`synthesize`), on any slope; lower than that,
only where it is flat (ClassParams.below_sea_flat_max_deg, 1 degree) or
at the sea's edge (within shore_width_m of the sea at sea level): a
lake's surface below sea level (the Dead Sea) is water, the land sloping
down to it (the Jordan valley) is land. A DEM, a lossless store and a
procedural world have bound 0: the sea is exactly ``h == sea_level_m``. A
lossy terrain store of step s (docs/STORE.md) decodes every post within s/2
of its imported value (closed-loop quantisation), so it cannot tell a sea at
0 m from ground at s/2: sea posts come back anywhere in [-s/2, s/2], and
bilinear samples between them too. Posts within s/2 of sea level are
therefore water; the price is that low shore ground within s/2 of sea level
is drawn as water as well. ``sortie terrain texture`` takes the bound from
its terrain's sources (terrain/texture_cli.py), locally or over the terrain
service's metadata.

Class noise (band jitter, woodlots) is placed by world position: 3-D noise
at the pixels' ECEF positions (:func:`noise_positions`), the same wherever
a box lies around a place and however its longitude is written.

Everything is a plain numpy array function; :func:`synthesize` strings them
together. Determinism: the same inputs and seed give bit-identical arrays
(noise comes from the SplitMix64 lattice hash of terrain/procedural.py, not
from a random-number generator's stream).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from terrain.geodesy import geodetic_to_ecef, radii_of_curvature, wrap_lon_exact_deg
from terrain.procedural import lattice_uniform, mix64, splitmix64
from terrain.pyramid import build_pyramid

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

    sea_level_m: float = 0.0  # height at this (within the source's quantisation bound) is water (SRTM: sea at 0 m)
    # Lower than sea level, water only where flatter than this (degrees): a lake's surface below sea
    # level is flat in a DEM (SRTM's edited water bodies are one height; a 1 m quantisation step
    # between 30 m posts reads atan(1 / 60) = 0.95 degrees by central differences), land below it slopes.
    below_sea_flat_max_deg: float = 1.0
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
    tan(phi) * 0.5 deg in relative terms from the centre value (1 % at 47 N):
    the texture itself takes each row's own spacing (:func:`row_spacing`);
    this is the box's size for choosing a grid.
    """
    phi = 0.5 * (lat_min_deg + lat_max_deg)
    m, n = radii_of_curvature(phi)
    dy = float(m * np.radians(dlat_deg))
    dx = float(n * np.cos(np.radians(phi)) * np.radians(dlon_deg))
    return dx, dy


def row_spacing(lat_deg, dlat_deg: float, dlon_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(dx_m, dy_m), each (rows,) float64 metres: the post spacings of each row of a lat/lon grid.

    lat_deg: (rows,) the rows' latitudes (pixel centres, :func:`grid_latlon`);
    dlat_deg, dlon_deg: the grid's steps. dx = N(phi) cos(phi) dlon and
    dy = M(phi) dlat (dlon, dlat in radians) at each row's own latitude, M and
    N WGS84's meridian and prime-vertical radii of curvature (NIMA TR8350.2,
    3rd ed., eqs. 4-18 and 4-20; terrain.geodesy.radii_of_curvature): the
    length of a parallel's arc is N cos(phi) dlon, of a meridian's M dphi.
    A row at 89.99 deg is some 27 m across for 0.14 deg of longitude, where the
    box's centre would say 1.4 km.
    """
    lat = np.asarray(lat_deg, dtype=np.float64)
    if lat.ndim != 1:
        raise ValueError(f"lat_deg must be (rows,), got shape {lat.shape}")
    m, n = radii_of_curvature(lat)
    dx = n * np.cos(np.radians(lat)) * np.radians(dlon_deg)
    dy = m * np.radians(dlat_deg)
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


def spacing_rows(dx_m, dy_m, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """dx_m and dy_m (scalars, one spacing for the grid, or (rows,) / (rows, 1), each row's own)
    as two (rows,) float64 arrays; ValueError naming the one that is not positive and finite or
    not shaped so."""
    out = []
    for name, v in (("dx_m", dx_m), ("dy_m", dy_m)):
        a = np.asarray(v, dtype=np.float64)
        if a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        if a.ndim > 1 or (a.ndim == 1 and a.shape[0] != rows):
            raise ValueError(f"{name} must be a scalar or one spacing per row ({rows},), got shape {a.shape}")
        if not (np.isfinite(a).all() and (a > 0.0).all()):
            raise ValueError(f"{name} must be positive finite metres, got {v!r}")
        out.append(np.broadcast_to(a, (rows,)).astype(np.float64))
    return out[0], out[1]


def gradient_en(heights, dx_m, dy_m) -> tuple[np.ndarray, np.ndarray]:
    """(dz/d_east, dz/d_north), dimensionless, by central differences.

    Interior posts: (z[c+1] - z[c-1]) / 2dx; edges: one-sided first
    differences (numpy.gradient, edge_order=1). Row 0 is north, so
    dz/d_north = -(dz/d_row) / dy. dx_m, dy_m: scalars or each row's own
    ((rows,), :func:`row_spacing`). NaN spreads to neighbours.
    """
    z = np.asarray(heights, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"heights must be 2-D with at least 2 rows and 2 columns, got shape {z.shape}")
    dx, dy = spacing_rows(dx_m, dy_m, z.shape[0])
    d_row, d_col = np.gradient(z)
    return d_col / dx[:, None], -d_row / dy[:, None]


def slope_deg(heights, dx_m, dy_m) -> np.ndarray:
    """Slope angle from horizontal, degrees (rows, cols) float64, from :func:`gradient_en`."""
    de, dn = gradient_en(heights, dx_m, dy_m)
    return np.degrees(np.arctan(np.hypot(de, dn)))


def normals_enu(heights, dx_m, dy_m) -> np.ndarray:
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


@numba.njit(cache=True, nogil=True)
def _lattice3(h_seed, ix, iy, iz) -> float:
    """:func:`terrain.procedural.lattice_hash` of (seed, ix, iy, iz), top 53 bits in [0, 1)."""
    h = mix64(h_seed ^ np.uint64(ix))
    h = mix64(h ^ np.uint64(iy))
    h = mix64(h ^ np.uint64(iz))
    return np.float64(h >> np.uint64(11)) * 2.0**-53


@numba.njit(cache=True, nogil=True)
def _fractal3_into(x, y, z, h_seeds, out):
    """Octave o of h_seeds at frequency 2^o, amplitude 2^-o, summed into out (flat arrays)."""
    for k in range(x.shape[0]):
        total = 0.0
        norm = 0.0
        for o in range(h_seeds.shape[0]):
            f = np.float64(1 << o)
            px, py, pz = x[k] * f, y[k] * f, z[k] * f
            fx, fy, fz = np.floor(px), np.floor(py), np.floor(pz)
            tx, ty, tz = px - fx, py - fy, pz - fz
            tx = tx * tx * (3.0 - 2.0 * tx)
            ty = ty * ty * (3.0 - 2.0 * ty)
            tz = tz * tz * (3.0 - 2.0 * tz)
            ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
            hs = h_seeds[o]
            v = 0.0
            for c in range(8):
                a, b, d = c & 1, (c >> 1) & 1, (c >> 2) & 1
                w = (tx if a else 1.0 - tx) * (ty if b else 1.0 - ty) * (tz if d else 1.0 - tz)
                v += w * _lattice3(hs, ix + a, iy + b, iz + d)
            total += v / f
            norm += 1.0 / f
        out[k] = total / norm


def fractal_noise3(x, y, z, seed: int, octaves: int = 3) -> np.ndarray:
    """3-D :func:`fractal_noise`: value noise on the integer lattice of (x, y, z) (broadcast
    arrays, lattice units), blended with the cubic smoothstep along each axis, octaves at
    frequency x2 and amplitude /2, rescaled to [0, 1]; float64 of the broadcast shape.

    Lattice values are :func:`terrain.procedural.lattice_hash` of (seed + 7919 o, ix, iy, iz).
    Given world positions (ECEF metres over a feature size), the noise is a function of the
    place alone: the same in every grid that holds it, whatever its box or the longitude's
    turn, and with no seam at the antimeridian or singularity at the poles.
    """
    x, y, z = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x, y, z)))
    h_seeds = np.array([splitmix64(np.uint64((int(seed) + 7919 * o) % (1 << 64))) for o in range(octaves)],
                       dtype=np.uint64)
    out = np.zeros(x.size)
    _fractal3_into(np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel(),
                   np.ascontiguousarray(z).ravel(), h_seeds, out)
    return out.reshape(x.shape)


def noise_positions(lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, z) ECEF metres of points on the WGS84 ellipsoid (height 0), each of the broadcast
    shape of lat_deg and lon_deg (degrees; any turn of longitude): where :func:`base_classes`
    places its band and woodlot noise (``noise_xyz_m``), so that every box draws the same
    classes at the same place."""
    p = geodetic_to_ecef(lat_deg, wrap_lon_exact_deg(np.asarray(lon_deg, dtype=np.float64)), 0.0)
    return p[..., 0], p[..., 1], p[..., 2]


# --------------------------------------------------------------------------- class map

def _box_count(mask: np.ndarray, half_rows, half_cols) -> np.ndarray:
    """How many True values mask has within (2 half_rows + 1) x (2 half_cols + 1) posts around each
    post, the box cut at the grid's edges (summed-area table), int64. half_rows, half_cols: ints,
    or (rows,) ints, each row's own."""
    rows, cols = mask.shape
    hr = np.broadcast_to(np.asarray(half_rows, dtype=np.int64), (rows,))[:, None]
    hc = np.broadcast_to(np.asarray(half_cols, dtype=np.int64), (rows,))[:, None]
    s = np.zeros((rows + 1, cols + 1), dtype=np.int64)
    np.cumsum(np.cumsum(mask, axis=0), axis=1, out=s[1:, 1:])
    i, j = np.arange(rows)[:, None], np.arange(cols)[None, :]
    r0, r1 = np.clip(i - hr, 0, rows), np.clip(i + hr + 1, 0, rows)
    c0, c1 = np.clip(j - hc, 0, cols), np.clip(j + hc + 1, 0, cols)
    return s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0]


def _near(mask: np.ndarray, half_rows, half_cols) -> np.ndarray:
    """True where mask has a True within (2 half_rows + 1) x (2 half_cols + 1) posts around
    (:func:`_box_count`)."""
    return _box_count(mask, half_rows, half_cols) > 0


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


# A post at sea level is the sea (whose edge keeps its steps and dips below sea level as water) when
# at least this many of its 3 x 3 posts, itself included, are at sea level.
SEA_MIN_OF_9 = 4


def water_mask(heights, slope, dx_m, dy_m, *, params: ClassParams = ClassParams(),
               water_tolerance_m: float = 0.0) -> np.ndarray:
    """Where the class map draws water, bool (rows, cols).

    A post within water_tolerance_m of sea_level_m (at or above sea_level_m -
    tol, at or below sea_level_m + tol) is water, on any slope: the sea as a
    DEM writes it (SRTM: 0 m; the tolerance is the source's quantisation
    bound, see the module docstring). A post lower than that is water where
    its slope (degrees) is under params.below_sea_flat_max_deg (a NaN slope
    counts as flat), or where it lies within params.shore_width_m (along rows
    and columns) of the sea: posts at sea level with at least 3 more of their
    3 x 3 neighbours at sea level (a sea, not a speck of land that happens to
    read 0 m). A lake whose surface lies below sea level (the Dead Sea at
    -430 m) is flat in a DEM, land below sea level (the Jordan valley's
    flanks, Death Valley's fans) slopes, and the sea's own edge keeps its
    steps and dips (a DEM's sea floor stepping down from 0 m, a coastal pit of
    -2 m) as water. Limits: flat land below sea level (a polder, a salt pan)
    reads as water, a steep sea floor farther than shore_width_m from a 0 m
    sea (a DEM with bathymetry) as land, and a lake above sea level as land.
    dx_m, dy_m: post spacings in metres, scalars or each row's own.
    """
    tol = check_water_tolerance(water_tolerance_m)
    z = np.asarray(heights, dtype=np.float64)
    dx, dy = spacing_rows(dx_m, dy_m, z.shape[0])
    sl = np.broadcast_to(np.asarray(slope, dtype=np.float64), z.shape)
    p = params
    with np.errstate(invalid="ignore"):
        # False for NaN. A tolerance of 0.0 leaves sea_level_m as it is: the sea of a DEM at exactly 0 m.
        at_sea = (z <= p.sea_level_m + tol) & (z >= p.sea_level_m - tol)
        below = z < p.sea_level_m - tol
        flat = ~(sl >= p.below_sea_flat_max_deg)
    water = at_sea | (below & flat)
    if p.shore_width_m > 0 and at_sea.any() and (below & ~flat).any():
        sea = at_sea & (_box_count(at_sea, 1, 1) >= SEA_MIN_OF_9)
        water |= below & _near(sea, np.rint(p.shore_width_m / dy).astype(np.int64),
                               np.rint(p.shore_width_m / dx).astype(np.int64))
    return water


def base_classes(heights, dx_m, dy_m, lat_deg=45.0, *, params: ClassParams = ClassParams(),
                 seed: int = 0, noise_en_m=None, noise_xyz_m=None, water_tolerance_m: float = 0.0,
                 slope=None) -> np.ndarray:
    """The class of each post from height, latitude and water alone (before slope), uint8.

    Rules, first match wins (h: height m MSL, jitter: band noise of amplitude
    band_jitter_m added to every band edge):

    ==============  ==========================================================
    class           rule
    ==============  ==========================================================
    nodata (0)      h is NaN
    water (1)       :func:`water_mask`: h within water_tolerance_m of
                    sea_level_m (0 m: SRTM writes the sea as 0; the tolerance
                    is the source's quantisation bound, see the module
                    docstring), or lower and flatter than
                    below_sea_flat_max_deg (a lake below sea level) or
                    within shore_width_m of the sea at sea level
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
    moderate slopes). dx_m, dy_m: scalars or each row's own ((rows,),
    :func:`row_spacing`). lat_deg: scalar or broadcastable to heights (e.g. a
    (rows, 1) column). Where the noise lies: noise_xyz_m, (x, y, z) metres
    broadcastable to heights, world positions (:func:`noise_positions`:
    ECEF on the ellipsoid), 3-D noise (:func:`fractal_noise3`) that is the
    same at the same place in every grid; or noise_en_m, (east_m, north_m)
    broadcastable to heights, 2-D noise on those coordinates (the caller
    keeps them consistent between grids); neither: the grid's own
    (col dx, -row dy). water_tolerance_m: the quantisation bound of the
    heights' source (0 for a DEM or a lossless store, half the step for a
    lossy store). slope: degrees (rows, cols) for the water test, default
    :func:`slope_deg` of the heights.
    """
    z = np.asarray(heights, dtype=np.float64)
    rows, cols = z.shape
    dx, dy = spacing_rows(dx_m, dy_m, rows)
    if noise_en_m is not None and noise_xyz_m is not None:
        raise ValueError("give noise_en_m or noise_xyz_m, not both")
    p = params
    if noise_xyz_m is not None:
        x, y, w = (np.asarray(a, dtype=np.float64) for a in noise_xyz_m)

        def noise(scale_m, salt):
            return fractal_noise3(x / scale_m, y / scale_m, w / scale_m, seed + salt)
        dims = 3
    else:
        if noise_en_m is None:
            east = np.arange(cols)[None, :] * dx[:, None]
            north = (-np.arange(rows) * dy)[:, None]
        else:
            east, north = (np.asarray(a) for a in noise_en_m)

        def noise(scale_m, salt):
            return fractal_noise(east / scale_m, north / scale_m, seed + salt)
        dims = 2
    jitter = np.broadcast_to(p.band_jitter_m * (2.0 * noise(p.band_jitter_scale_m, 1) - 1.0), z.shape)
    woodlot = np.broadcast_to(noise(p.woodlot_scale_m, 2), z.shape)
    snow_line = line_height_m(p.snow_line, lat_deg)
    tree_line = line_height_m(p.tree_line, lat_deg)
    forest_min = np.minimum(p.forest_min_m, tree_line)

    nodata = np.isnan(z)
    water = water_mask(z, slope_deg(z, dx, dy) if slope is None else slope, dx, dy, params=p,
                       water_tolerance_m=water_tolerance_m)
    out = np.full(z.shape, FARMLAND, dtype=np.uint8)
    out[woodlot < stretch_fraction(p.woodlot_fraction, dims)] = FOREST
    zj = z - jitter
    out[zj >= forest_min] = FOREST
    out[(zj >= tree_line) | (tree_line <= 0.0)] = ALPINE  # no woodlot or farmland where no tree grows
    out[zj >= tree_line + p.alpine_band_m] = ROCK
    out[zj >= snow_line] = SNOW
    if water.any() and p.shore_width_m > 0:
        shore = _near(water, np.rint(p.shore_width_m / dy).astype(np.int64),
                      np.rint(p.shore_width_m / dx).astype(np.int64))
        out[shore & (z <= p.shore_max_height_m)] = BEACH
    out[water] = WATER
    out[nodata] = NODATA
    return out


# Slope of the share-to-threshold line of :func:`stretch_fraction`, by the noise's dimensions.
_STRETCH_SLOPE = {2: 0.45, 3: 0.37}


def stretch_fraction(fraction: float, dims: int = 2) -> float:
    """The threshold t with P(fractal noise < t) near fraction.

    Three-octave value noise bunches around 0.5 (a sum of smoothed uniforms),
    so a share of ``fraction`` lies below 0.5 + (fraction - 0.5) * k: a
    linear fit to the noise's measured distribution over 10^6 samples (to
    within 0.03 in share for fractions 0.1 .. 0.9). k = 0.45 for
    :func:`fractal_noise` (0.024 measured), 0.37 for :func:`fractal_noise3`
    on the Earth's surface, which bunches more (a 2-D slice of 3-D noise
    averages more lattice values; 0.019 measured at 1.2 and 2.5 km scales).
    Fractions 0 and 1 give 0 and 1: none and all.
    """
    if fraction <= 0.0 or fraction >= 1.0:
        return float(np.clip(fraction, 0.0, 1.0))
    return 0.5 + (fraction - 0.5) * _STRETCH_SLOPE[dims]


def class_map(heights, slope, dx_m, dy_m, lat_deg=45.0, *, params: ClassParams = ClassParams(),
              seed: int = 0, noise_en_m=None, noise_xyz_m=None, water_tolerance_m: float = 0.0) -> np.ndarray:
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

    So: water is :func:`water_mask` (height within water_tolerance_m of
    sea_level_m, the source's quantisation bound, 0 for a DEM: see the module
    docstring; or below that and flatter than below_sea_flat_max_deg, or near
    the sea at sea level); every
    land post at cliff slope or steeper is rock; farmland only on flat ground.
    """
    base = base_classes(heights, dx_m, dy_m, lat_deg, params=params, seed=seed, noise_en_m=noise_en_m,
                        noise_xyz_m=noise_xyz_m, water_tolerance_m=water_tolerance_m, slope=slope)
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


# Sky view: every line of posts out to this many lines from a post is sampled (exact on planes);
# beyond, windows of 2^p + 1 lines of a max-filtered grid (p grows by one as the distance doubles),
# so a sample's distance is within 1 / SKY_FINE_LINES of its highest post's. A window costs what a
# line costs; the default 2.5 km radius needs none down to 20 m posts.
SKY_FINE_LINES = 128


def _dilated_levels(z: np.ndarray, fine_lines: int, reach_lines: float) -> np.ndarray:
    """Max-filtered copies of z for :func:`sky_view`: level p (p = 1, 2, ..) holds at each post the
    largest height within 2^(p-1) posts along rows and columns (a (2^p + 1)^2 window, cut at the
    grid's edges; NaN ignored, all NaN: NaN), as long as fine_lines * 2^(p-1) < reach_lines.
    (levels, rows, cols) float32, rounded up; (0, rows, cols) when none is needed."""
    levels = []
    half = 1
    while fine_lines * half < reach_lines and half < 2 * max(z.shape):
        # Level 1: the posts either side and the post itself; level p: two level p - 1 windows
        # half a window either side. Edge posts repeat outward: a window cut at the edge keeps
        # every post it holds inside.
        prev, shifts = (z, (-1, 0, 1)) if half == 1 else (levels[-1], (-half // 2, half // 2))
        grown = prev
        for axis in (0, 1):
            pad = max(abs(t) for t in shifts)
            widths = [(0, 0), (0, 0)]
            widths[axis] = (pad, pad)
            padded = np.pad(grown, widths, mode="edge")
            n = grown.shape[axis]
            parts = [np.take(padded, np.arange(pad + t, pad + t + n), axis=axis) for t in shifts]
            with np.errstate(invalid="ignore"):
                grown = parts[0]
                for part in parts[1:]:
                    grown = np.fmax(grown, part)
        levels.append(grown)
        half *= 2
    out = np.zeros((len(levels),) + z.shape, dtype=np.float32)
    for p, level in enumerate(levels):
        f32 = level.astype(np.float32)
        low = f32 < level  # round up: a window never reads lower than its highest post
        f32[low] = np.nextafter(f32[low], np.float32(np.inf))
        out[p] = f32
    return out


@numba.njit(cache=True, nogil=True)
def _lerp_nan(a, b, w):
    """a + (b - a) w, with w == 0 giving a exactly (b may be outside or NaN)."""
    return a if w == 0.0 else a + (b - a) * w


@numba.njit(cache=True, nogil=True)
def _horizon_up(tan_h, near, far, w, base, inv_d):
    """tan_h[j] = max(tan_h[j], (near[j] + (far[j] - near[j]) w - base[j]) inv_d) for every j;
    near, far, base: row slices aligned with tan_h. A NaN sample never wins."""
    if w == 0.0:
        for j in range(tan_h.shape[0]):
            v = (near[j] - base[j]) * inv_d
            tan_h[j] = v if v > tan_h[j] else tan_h[j]
    else:
        for j in range(tan_h.shape[0]):
            v = (near[j] + (far[j] - near[j]) * w - base[j]) * inv_d
            tan_h[j] = v if v > tan_h[j] else tan_h[j]


@numba.njit(cache=True, nogil=True)
def _sky_rows_at(grid, tan_h, base, r, off, inv_d):
    """Samples on row r at fractional column j + off for every post j of the row whose sample lies
    inside, linear between the two columns around it: into tan_h."""
    cols = grid.shape[1]
    c0 = int(np.floor(off))
    w = off - c0
    c1 = c0 + (1 if w > 0.0 else 0)
    j_lo, j_hi = max(0, -c0), min(cols, cols - c1)
    if j_lo < j_hi:
        _horizon_up(tan_h[j_lo:j_hi], grid[r, j_lo + c0:j_hi + c0], grid[r, j_lo + c1:j_hi + c1], w,
                    base[j_lo:j_hi], inv_d)


@numba.njit(cache=True, nogil=True)
def _sky_cols_at(grid, tan_h, base, rr, shift, inv_d):
    """Samples at column j + shift on fractional row rr for every post j whose column lies inside,
    linear between the two rows around it: into tan_h."""
    rows, cols = grid.shape
    r0 = int(np.floor(rr))
    w = rr - r0
    r1 = min(r0 + 1, rows - 1)
    j_lo, j_hi = max(0, -shift), min(cols, cols - shift)
    if j_lo < j_hi:
        _horizon_up(tan_h[j_lo:j_hi], grid[r0, j_lo + shift:j_hi + shift], grid[r1, j_lo + shift:j_hi + shift], w,
                    base[j_lo:j_hi], inv_d)


@numba.njit(cache=True, nogil=True)
def _sky_along_rows(z, i0, e, n, dx, dy, radius_m, fine_lines, dilated, tan_h):
    """Horizon tangents of row i0 toward (e, n) (unit east, north), stepping whole rows."""
    rows, cols = z.shape
    sr = -1 if n > 0.0 else 1  # row 0 is north
    line_m = dy / abs(n)
    side = e * line_m / dx  # columns toward (e, n) per row, |side| <= 1
    reach = radius_m / line_m
    base = z[i0]
    off_prev = 0.0
    for k in range(1, fine_lines + 1):
        r = i0 + sr * k
        if (k > 1 and k > reach) or r < 0 or r >= rows:
            break
        off = _snap(side * k)
        # Where the line crosses a column between rows r - sr and r: linear between those rows.
        ci = int(np.floor(max(off, off_prev)))
        if min(off, off_prev) < ci < max(off, off_prev):
            tau = (ci - off_prev) / (off - off_prev)
            j_lo, j_hi = max(0, -ci), min(cols, cols - ci)
            if j_lo < j_hi:
                _horizon_up(tan_h[j_lo:j_hi], z[r - sr, j_lo + ci:j_hi + ci], z[r, j_lo + ci:j_hi + ci], tau,
                            base[j_lo:j_hi], 1.0 / ((k - 1 + tau) * line_m))
        off_prev = off
        _sky_rows_at(z, tan_h, base, r, off, 1.0 / (k * line_m))
    # Windows of 2^p + 1 rows centred on line k, one every 2^p lines, from line lo + 1 to hi.
    for p in range(1, dilated.shape[0] + 1):
        lo = fine_lines << (p - 1)
        hi = min(fine_lines << p, int(np.floor(reach)))
        half = 1 << (p - 1)
        k = lo + 1 + half
        while k - half <= hi:
            r = min(max(i0 + sr * k, 0), rows - 1)  # a window past the edge: its part inside
            if sr * (r - i0) < k - half:
                break
            _sky_rows_at(dilated[p - 1], tan_h, base, r, side * k, 1.0 / (k * line_m))
            k += 2 * half


@numba.njit(cache=True, nogil=True)
def _sky_along_cols(z, i0, e, n, dx, dy, radius_m, fine_lines, dilated, tan_h):
    """Horizon tangents of row i0 toward (e, n), stepping whole columns."""
    rows, cols = z.shape
    sc = 1 if e > 0.0 else -1
    line_m = dx / abs(e)
    side = -n * line_m / dy  # rows per column (north is row - 1), |side| <= 1
    reach = radius_m / line_m
    base = z[i0]
    rr_prev = float(i0)
    for k in range(1, min(fine_lines, cols - 1) + 1):
        rr = _snap(i0 + side * k)
        if (k > 1 and k > reach) or rr < 0.0 or rr > rows - 1:
            break
        shift = sc * k
        # Where the line crosses a row between columns shift - sc and shift: linear between them.
        ri = int(np.floor(max(rr, rr_prev)))
        if min(rr, rr_prev) < ri < max(rr, rr_prev):
            tau = (ri - rr_prev) / (rr - rr_prev)
            j_lo, j_hi = max(0, -shift, -(shift - sc)), min(cols, cols - shift, cols - (shift - sc))
            if j_lo < j_hi:
                _horizon_up(tan_h[j_lo:j_hi], z[ri, j_lo + shift - sc:j_hi + shift - sc],
                            z[ri, j_lo + shift:j_hi + shift], tau, base[j_lo:j_hi], 1.0 / ((k - 1 + tau) * line_m))
        rr_prev = rr
        _sky_cols_at(z, tan_h, base, rr, shift, 1.0 / (k * line_m))
    for p in range(1, dilated.shape[0] + 1):
        lo = fine_lines << (p - 1)
        hi = min(fine_lines << p, int(np.floor(reach)))
        half = 1 << (p - 1)
        k = lo + 1 + half
        while k - half <= hi and k - half < cols:
            rr = min(max(i0 + side * k, 0.0), rows - 1.0)  # a window past the edge: its part inside
            if abs(rr - i0) < abs(side) * (k - half) - 1e-9:
                break  # the window lies past the grid's north or south edge
            _sky_cols_at(dilated[p - 1], tan_h, base, rr, sc * k, 1.0 / (k * line_m))
            k += 2 * half


@numba.njit(cache=True, nogil=True)
def _sky_view_into(z, dx_rows, dy_rows, azimuths, radius_m, fine_lines, dilated, out):
    """:func:`sky_view` into out, row by row: each direction's horizon tangents, then cos^2 summed."""
    rows, cols = z.shape
    tan_h = np.zeros(cols)
    total = np.zeros(cols)
    for i0 in range(rows):
        total[:] = 0.0
        for k in range(azimuths):
            az = 2.0 * np.pi * k / azimuths
            e, n = np.sin(az), np.cos(az)
            tan_h[:] = 0.0  # the flat horizon
            if abs(n) / dy_rows[i0] >= abs(e) / dx_rows[i0]:
                _sky_along_rows(z, i0, e, n, dx_rows[i0], dy_rows[i0], radius_m, fine_lines, dilated, tan_h)
            else:
                _sky_along_cols(z, i0, e, n, dx_rows[i0], dy_rows[i0], radius_m, fine_lines, dilated, tan_h)
            for j in range(cols):
                total[j] += 1.0 / (1.0 + tan_h[j] * tan_h[j])  # cos^2(atan t)
        for j in range(cols):
            out[i0, j] = total[j] / azimuths


def sky_view(heights, dx_m, dy_m, *, azimuths: int = 16, radius_m: float = 2500.0,
             fine_lines: int = SKY_FINE_LINES) -> np.ndarray:
    """Sky-view factor of each post, float32 in [0, 1] (1: the whole sky dome is open).

    For each of ``azimuths`` directions (from north, evenly spaced), the
    horizon elevation angle h is the largest atan(dz / d) over the straight
    line out to radius_m. The line crosses the rows (or the columns, whichever
    it is closer to parallel with); out to ``fine_lines`` lines
    (SKY_FINE_LINES) every crossing is a sample, linear between the two posts
    either side of it, and so is every crossing of the other axis between
    them, at its true distance d along the line: the bilinear surface's
    profile, no post stepped over (the old geometric steps stepped over wall
    tops). Beyond, line k's sample is the crossing of a max-filtered grid
    (each post the highest within 2^(p-1) posts either way; p grows by one as
    the distance doubles), one every 2^p lines, so that the windows cover
    every line and the line's drift sideways within them: still no post
    missed, and a sample's distance within 1 / fine_lines of its highest
    post's. Cost: at most about fine_lines * (1 + log2(radius / fine_lines
    posts) / 2) samples a direction, whatever the radius. h is clamped at 0 (a
    pinnacle sees no less than a flat plane). The factor is the mean over
    directions of cos^2(h): the share of an isotropic sky's diffuse light a
    horizontal surface receives with that horizon (Dozier & Frew 1990, IEEE
    TGRS 28(5), eq. 7 without the surface tilt term). Points beyond the grid
    or with no data do not obstruct. A flat plane gives exactly 1.

    dx_m, dy_m: scalars, or each row's own ((rows,), :func:`row_spacing`): a
    row's lines run with its own spacings out to the radius (the east-west
    spacing changes by tan(phi) * d / R over d: 0.04 % over 2.5 km at 47 deg).
    """
    z = np.ascontiguousarray(heights, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"heights must be 2-D with at least 2 rows and 2 columns, got shape {z.shape}")
    dx, dy = spacing_rows(dx_m, dy_m, z.shape[0])
    if int(fine_lines) < 2:
        raise ValueError(f"fine_lines must be 2 or more, got {fine_lines!r}")
    dilated = _dilated_levels(z, int(fine_lines), radius_m / min(dx.min(), dy.min()))
    out = np.zeros(z.shape)
    _sky_view_into(z, dx, dy, int(azimuths), float(radius_m), int(fine_lines), dilated, out)
    return out.astype(np.float32)


def _row_lines(dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(north_m, north_cols), each (rows,): the rows' northings in metres from row 0 and in
    columns, the integral of dN / dx (trapezoids between rows): a line of constant azimuth a
    (a rhumb line) runs e/n (north_cols[r] - north_cols[r0]) columns east between rows r0 and r
    (e, n: sin a, cos a), whatever each row's east-west spacing."""
    north_m = np.concatenate([[0.0], -np.cumsum(0.5 * (dy[1:] + dy[:-1]))])
    ratio = dy / dx
    north_cols = np.concatenate([[0.0], -np.cumsum(0.5 * (ratio[1:] + ratio[:-1]))])
    return north_m, north_cols


@numba.njit(cache=True, nogil=True)
def _snap(x):
    """x, or the whole number within 1e-9 of it (a ray along a row or column stays on it)."""
    r = np.floor(x + 0.5)
    return r if abs(x - r) < 1e-9 else x


@numba.njit(cache=True, nogil=True)
def _row_at(north_cols, q, hint):
    """The fractional row where north_cols (decreasing) is q, linear between rows, and beyond the
    first or last row linear on with its neighbour's step. hint: a row near the answer."""
    n = north_cols.shape[0]
    r = min(max(hint, 0), n - 2)
    while r > 0 and north_cols[r] < q:
        r -= 1
    while r < n - 2 and north_cols[r + 1] > q:
        r += 1
    return _snap(r + (north_cols[r] - q) / (north_cols[r] - north_cols[r + 1]))


@numba.njit(cache=True, nogil=True)
def _block_max(mx, offsets, shapes, level, r_lo, r_hi, c_lo, c_hi):
    """The largest height over the posts rows r_lo..r_hi, cols c_lo..c_hi (clamped to the grid):
    the maximum of the level's blocks of cells holding them (terrain/pyramid.py's layout)."""
    ncr, ncc = shapes[0, 0], shapes[0, 1]
    cr0, cr1 = min(max(r_lo, 0), ncr - 1) >> level, min(max(r_hi, 0), ncr - 1) >> level
    cc0, cc1 = min(max(c_lo, 0), ncc - 1) >> level, min(max(c_hi, 0), ncc - 1) >> level
    nx = shapes[level, 1]
    base = offsets[level]
    best = -np.inf
    for bi in range(cr0, cr1 + 1):
        row = base + bi * nx
        for bj in range(cc0, cc1 + 1):
            best = max(best, mx[row + bj])
    return best


@numba.njit(cache=True, nogil=True)
def _march_rows(z, i0, j0, z0, e, n, t, north_m, north_cols, max_d, mx, offsets, shapes, top):
    """True when the ray from post (i0, j0) toward (e, n), rising at t, passes below a sample:
    where it crosses each row (the column on the rhumb line), linear between the row's two posts
    around it, and where it crosses a column between two rows, linear between those rows."""
    rows, cols = z.shape
    sr = -1 if n > 0.0 else 1
    edge = 0 if sr < 0 else rows - 1
    ratio, inv_n = e / n, 1.0 / n
    y0, q0 = north_m[i0], north_cols[i0]
    lmax = shapes.shape[0] - 1
    r, c, d, level = i0, float(j0), 0.0, 1
    while True:
        ray = z0 + d * t
        if ray >= top or d > max_d or r == edge:
            return False
        if level > 0:  # skip rows when every post they sample lies below the ray here
            rb = r + sr * min(1 << level, abs(edge - r))
            cb = j0 + ratio * (north_cols[rb] - q0)
            c_lo, c_hi = int(np.floor(min(c, cb))), int(np.floor(max(c, cb))) + 1
            if c_hi < 0 or c_lo > cols - 1:
                return False  # the ray has left the grid
            if _block_max(mx, offsets, shapes, level, min(r, rb), max(r, rb), c_lo, c_hi) > ray:
                level -= 1
                continue
            r, c = rb, cb
            d = (north_m[r] - y0) * inv_n
            level = min(level + 1, lmax)
            continue
        rn = r + sr
        dn = (north_m[rn] - y0) * inv_n
        cn = _snap(j0 + ratio * (north_cols[rn] - q0))
        ci = int(np.floor(max(c, cn)))
        if min(c, cn) < ci < max(c, cn) and 0 <= ci <= cols - 1:  # a column crossed between the rows
            tau = (ci - c) / (cn - c)
            dc = d + (dn - d) * tau
            if dc <= max_d and z[r, ci] + (z[rn, ci] - z[r, ci]) * tau > z0 + dc * t:
                return True
        r, c, d = rn, cn, dn
        c0 = int(np.floor(c))
        w = c - c0
        if c0 < 0 or c0 > cols - 1 or (c0 == cols - 1 and w > 0.0):
            return False
        if d <= max_d and _lerp_nan(z[r, c0], z[r, min(c0 + 1, cols - 1)], w) > z0 + d * t:
            return True
        level = 1


@numba.njit(cache=True, nogil=True)
def _march_cols(z, i0, j0, z0, e, n, t, dx_rows, north_cols, max_d, mx, offsets, shapes, top):
    """:func:`_march_rows` stepping whole columns (the row of each column on the rhumb line; the
    distance grows by dE / |e|, dE the columns' east-west spacing at the ray's row)."""
    rows, cols = z.shape
    sc = 1 if e > 0.0 else -1
    edge = 0 if sc < 0 else cols - 1
    ratio, inv_e = n / e, 1.0 / abs(e)  # north_cols per column
    q0 = north_cols[i0]
    lmax = shapes.shape[0] - 1
    c, r, d, level, hint = j0, float(i0), 0.0, 1, i0
    while True:
        ray = z0 + d * t
        if ray >= top or d > max_d or c == edge:
            return False
        k = min(1 << level, abs(edge - c)) if level > 0 else 1
        cb = c + sc * k
        rb = _row_at(north_cols, q0 + ratio * (cb - j0), hint)
        if level > 0:  # skip columns when every post they sample lies below the ray here
            rb_in = min(max(rb, 0.0), rows - 1.0)
            r_lo, r_hi = int(np.floor(min(r, rb_in))), int(np.floor(max(r, rb_in))) + 1
            if _block_max(mx, offsets, shapes, level, r_lo, r_hi, min(c, cb), max(c, cb)) > ray:
                level -= 1
                continue
        r_mid = min(max(0.5 * (r + rb), 0.0), rows - 1.0)
        i_mid = min(int(r_mid), rows - 2)
        db = d + k * (dx_rows[i_mid] + (dx_rows[i_mid + 1] - dx_rows[i_mid]) * (r_mid - i_mid)) * inv_e
        if level > 0:
            if rb < 0.0 or rb > rows - 1:
                return False  # the ray has left the grid, every post it passed below it
            c, r, d, hint = cb, rb, db, int(rb)
            level = min(level + 1, lmax)
            continue
        ri = int(np.floor(max(r, rb)))
        if min(r, rb) < ri < max(r, rb) and 0 <= ri <= rows - 1:  # a row crossed between the columns
            tau = (ri - r) / (rb - r)
            dc = d + (db - d) * tau
            if dc <= max_d and z[ri, c] + (z[ri, cb] - z[ri, c]) * tau > z0 + dc * t:
                return True
        if rb < 0.0 or rb > rows - 1:
            return False  # the ray has left the grid
        c, r, d, hint = cb, rb, db, int(rb)
        if d > max_d:
            return False
        r0 = int(np.floor(r))
        if _lerp_nan(z[r0, c], z[min(r0 + 1, rows - 1), c], r - r0) > z0 + d * t:
            return True
        level = 1


@numba.njit(cache=True, nogil=True)
def _cast_shadow_into(z, toward_e, toward_n, tan_e, dx_rows, dy_rows, north_m, north_cols, max_d, mx, offsets,
                      shapes, out):
    """:func:`cast_shadow` of each post's own sun into out: each post marches its own ray."""
    rows, cols = z.shape
    top = mx[offsets[shapes.shape[0] - 1]]  # the grid's highest post
    for i0 in range(rows):
        for j0 in range(cols):
            t = tan_e[i0, j0]
            if not t > 0.0:  # the sun on or below the horizon (or unknown)
                out[i0, j0] = True
                continue
            z0 = z[i0, j0]
            if z0 != z0:  # no data: receives no shadow
                continue
            e, n = toward_e[i0, j0], toward_n[i0, j0]
            if abs(n) / dy_rows[i0] >= abs(e) / dx_rows[i0]:
                out[i0, j0] = _march_rows(z, i0, j0, z0, e, n, t, north_m, north_cols, max_d, mx, offsets, shapes, top)
            else:
                out[i0, j0] = _march_cols(z, i0, j0, z0, e, n, t, dx_rows, north_cols, max_d, mx, offsets, shapes, top)


# One sun: rays a 1/SHADOW_RAYS_PER_POST of a post apart carry their envelopes line by line, and a
# post takes the ray passing nearest to it: at most half that (1/32 of a post) aside.
SHADOW_RAYS_PER_POST = 16


@numba.njit(cache=True, nogil=True)
def _bracket(u, pos, ip, uniform):
    """The post before pos along a line (posts at u, increasing; pos inside [u[0], u[-1]]) and pos's
    weight toward the next, walking on from ip where u is not uniform."""
    m = u.shape[0]
    if uniform:
        ip = min(int(pos - u[0]), m - 2)
    else:
        while ip < m - 2 and u[ip + 1] <= pos:
            ip += 1
    return ip, (pos - u[ip]) / (u[ip + 1] - u[ip])


@numba.njit(cache=True, nogil=True)
def _on_line(u, pos, delta):
    """pos, moved onto the line's first or last post when within 1e-9 of a ray spacing outside it (a
    ray along the grid's edge stays on it); NaN when it lies outside."""
    m = u.shape[0]
    if pos < u[0]:
        return u[0] if pos > u[0] - 1e-9 * delta else np.nan
    if pos > u[m - 1]:
        return u[m - 1] if pos < u[m - 1] + 1e-9 * delta else np.nan
    return pos


@numba.njit(cache=True, nogil=True)
def _sweep_shadow_into(lines, u, uniform, shift, drop_line, drop_post, delta, out):
    """Cast shadows of one sun by sweeping parallel rays across the grid, away from the sun.

    lines: (L, m) heights, line 0 the sunward edge, each line's posts at positions u (m,),
    increasing (uniform: u = 0, 1, ..); rays at u_0 - delta + g delta + phase on every line,
    phase in [0, delta), moving by shift[k] from line k - 1 to line k (the same for every ray:
    a rhumb line's shift; less than a post apart). A ray's envelope is the max over its samples
    of (sample - drop from there): where it crosses each line, linear between the two posts
    around it, and where it crosses a post's position between two lines, linear between the
    lines; the drop from line k - 1 to k is drop_line[k] + drop_post at the ray's place on line
    k - 1 (linear between posts), a share of it from a crossing between. A post's own ray runs
    exactly to line k - 1 (its sample there; no post's position lies between, a shift being less
    than a post apart) and on from there as the ray nearest to it: a post is in shadow when that
    envelope, dropped to it, is above it. out: (L, m) bool."""
    n_lines, m = lines.shape
    u0 = u[0] - delta
    n_rays = int(np.ceil((u[m - 1] - u0) / delta)) + 2
    env = np.full(n_rays, -np.inf)
    nxt = np.empty(n_rays)
    phase = 0.0
    for k in range(1, n_lines):
        total = phase + shift[k]
        carry = int(np.floor(total / delta))
        new_phase = min(max(total - carry * delta, 0.0), delta)
        src, dst = lines[k - 1], lines[k]
        ip = 0
        for i in range(m):  # each post's own ray, back to line k - 1, then the nearest ray's envelope
            pos = _on_line(u, u[i] - shift[k], delta)
            if pos != pos:
                continue  # it leaves the grid at once
            ip, w = _bracket(u, pos, ip, uniform)
            a = src[ip]
            sample = a if w == 0.0 else a + (src[ip + 1] - a) * w
            g = int(np.floor((pos - u0 - phase) / delta + 0.5))
            prev = env[g] if 0 <= g < n_rays else -np.inf
            drop = drop_line[k] + drop_post[ip] + (drop_post[ip + 1] - drop_post[ip]) * w
            if (sample if sample > prev else prev) - drop > dst[i]:  # False for NaN posts and samples
                out[k, i] = True
        ip = 0
        ic = 0  # the first post past the lower end of a ray's step
        for g in range(n_rays):
            gs = g - carry  # a ray beyond the array (outside the grid on line k - 1) may cross the edge post
            pos = _on_line(u, u0 + gs * delta + phase, delta)
            drop = drop_line[k]
            if pos != pos:
                sample = -np.inf
                pos = u0 + gs * delta + phase
            else:
                ip, w = _bracket(u, pos, ip, uniform)
                a = src[ip]
                sample = a if w == 0.0 else a + (src[ip + 1] - a) * w
                drop += drop_post[ip] + (drop_post[ip + 1] - drop_post[ip]) * w
            prev = env[gs] if 0 <= gs < n_rays else -np.inf
            best = (sample if sample > prev else prev) - drop  # a NaN sample never wins
            end = pos + shift[k]
            lo, hi = min(pos, end), max(pos, end)
            if uniform:
                ic = int(np.floor(lo - u[0])) + 1
            else:
                while ic < m and u[ic] <= lo:
                    ic += 1
            if 0 <= ic < m and u[ic] < hi:  # a post's position crossed between the lines
                tau = (u[ic] - pos) / (end - pos)
                cross = src[ic] + (dst[ic] - src[ic]) * tau - (1.0 - tau) * drop
                best = cross if cross > best else best
            nxt[g] = best
        env, nxt = nxt, env
        phase = new_phase


def _one_sun_sweep(z, dx, dy, az_deg, el_deg):
    """:func:`cast_shadow` of one sun by :func:`_sweep_shadow_into`, or None where the grid's rows
    do not all step the same way (some along rows, some along columns: a grid whose east-west
    spacing changes a lot) or, stepping columns, their north-south steps in columns differ by
    more than 2x (too many rays)."""
    a = np.radians(az_deg)
    e, n = float(np.sin(a)), float(np.cos(a))
    tan_e = float(np.tan(np.radians(min(el_deg, 90.0))))
    north_m, north_cols = _row_lines(dx, dy)
    rows_major = np.abs(n) / dy >= np.abs(e) / dx
    rows, cols = z.shape
    if rows_major.all():
        forward = n > 0.0  # the sun in the north: row 0 first
        order = np.arange(rows) if forward else np.arange(rows)[::-1]
        lines = z[order]
        shift = np.zeros(rows)
        shift[1:] = (e / n) * np.diff(north_cols[order])  # columns moved away from the sun
        drop = np.zeros(rows)
        drop[1:] = np.abs(np.diff(north_m[order])) / abs(n) * tan_e
        u, uniform, drop_post = np.arange(cols, dtype=np.float64), True, np.zeros(cols)
    elif not rows_major.any():
        u = -north_cols  # the rows' places along a column, in columns, increasing southward
        steps = np.diff(u)
        if steps.max() > 2.0 * steps.min():
            return None
        order = np.arange(cols)[::-1] if e > 0.0 else np.arange(cols)  # the sun in the east: east column first
        lines = z.T[order]
        shift = np.full(cols, n / abs(e))
        shift[0] = 0.0
        drop = np.zeros(cols)
        u, uniform, drop_post = u, False, dx / abs(e) * tan_e
    else:
        return None
    delta = float((1.0 if uniform else np.diff(u).min()) / SHADOW_RAYS_PER_POST)
    out = np.zeros(lines.shape, dtype=np.bool_)
    _sweep_shadow_into(np.ascontiguousarray(lines), u, uniform, shift, drop, drop_post, delta, out)
    back = np.zeros(z.shape, dtype=np.bool_)
    if rows_major.all():
        back[order] = out
    else:
        back[:, order] = out.T
    return back


def cast_shadow(heights, dx_m, dy_m, sun_az_deg, sun_el_deg, *, max_distance_m: float | None = None) -> np.ndarray:
    """True where terrain toward the sun rises above the sun's elevation (a cast shadow).

    A post p is in shadow when some point at distance d > 0 along its ray
    toward the sun is higher than z(p) + d tan(elevation). A ray is a line of
    constant azimuth (a rhumb line: with each row's own east-west spacing its
    column moves by e/n times the integral of dN/dx, so it runs straight on
    the ground whatever the rows' spacings), sampled where it crosses each row
    (or column, whichever it is closer to parallel with), linear between the
    two posts either side: the true ray, not a digital line (which strayed up
    to half a post aside and, on a slope steeper than the sun, gave metres of
    false height), and no envelope blended between neighbouring rays (which
    shortened the shadows of narrow peaks by up to half). Between crossings
    the bilinear surface can bulge above the line through the samples by up
    to a quarter of a cell's twist |z00 - z01 - z10 + z11|: the grazing
    tolerance (a ray clearing the samples but not that bulge is lit; 1.6 m
    seen on a 1000 m cone of 50 m posts, whose apex cells twist 15.5 m).

    One sun for the whole grid (scalars, or equal arrays): rays 1/16 of a
    post apart sweep across the grid away from the sun, each carrying its
    envelope max(z - d tan e) line by line exactly; a post's own ray runs
    exactly to the next line toward the sun and on from there as the ray
    passing nearest to it (at most 1/32 of a post aside); a grid whose rows
    do not all step the same way marches instead. Each post's own sun
    (arrays): each post marches its own ray, skipping the blocks of rows the
    ray passes above with the maximum mipmap of terrain/pyramid.py (Tevs,
    Ihrke & Seidel 2008), about log(grid) steps a post over open ground. Both
    take the ray's true distance and never step over a post that could rise
    above it.

    Earth curvature is ignored (it would lower a blocker d away by d^2 / 2R:
    20 m at 16 km). NaN posts neither cast nor receive shadows.
    max_distance_m: forget blockers farther than this (None: any; marched).
    Below or on the horizon everything is in shadow.

    dx_m, dy_m: scalars or each row's own ((rows,), :func:`row_spacing`).
    sun_az_deg, sun_el_deg: scalars (one sun for the whole grid), or arrays
    broadcastable to the grid: each post's own sun, its ray straight toward
    it (one sun given as arrays is the one-sun computation, bit for bit).
    """
    z = np.ascontiguousarray(heights, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"heights must be 2-D with at least 2 rows and 2 columns, got shape {z.shape}")
    dx, dy = spacing_rows(dx_m, dy_m, z.shape[0])
    az_deg = np.broadcast_to(np.asarray(sun_az_deg, dtype=np.float64), z.shape)
    el = np.broadcast_to(np.asarray(sun_el_deg, dtype=np.float64), z.shape)
    with np.errstate(invalid="ignore"):
        tan_e = np.where(el > 0.0, np.tan(np.radians(np.minimum(el, 90.0))), 0.0)
    out = np.zeros(z.shape, dtype=np.bool_)
    if not (tan_e > 0.0).any():
        out[...] = True
        return out
    north_m, north_cols = _row_lines(dx, dy)
    if max_distance_m is not None and max_distance_m >= np.hypot(north_m[0] - north_m[-1], dx.max() * z.shape[1]):
        max_distance_m = None  # no ray in the grid is that long
    one_sun = bool((az_deg == az_deg.flat[0]).all() and (el == el.flat[0]).all())
    if one_sun and max_distance_m is None:
        swept = _one_sun_sweep(z, dx, dy, float(az_deg.flat[0]), float(el.flat[0]))
        if swept is not None:
            return swept
    az = np.radians(az_deg)
    pyramid = build_pyramid(np.where(np.isnan(z), -np.inf, z))  # no data casts nothing: skip it
    max_d = np.inf if max_distance_m is None else float(max_distance_m)
    _cast_shadow_into(z, np.ascontiguousarray(np.sin(az)), np.ascontiguousarray(np.cos(az)), tan_e, dx, dy,
                      north_m, north_cols, max_d, pyramid.max_flat, pyramid.offsets, pyramid.shapes, out)
    return out


def light_map(heights, dx_m, dy_m, sun_az_deg, sun_el_deg,
              *, params: LightParams = LightParams(), sky: np.ndarray | None = None) -> LightResult:
    """Light reaching each post (§7.4), float32 in [0, 1], and the shadow mask.

    light = ambient(e) * sky + sun * max(N.L, 0) * (not shadow), clipped to
    [0, 1]; sky from :func:`sky_view`, N from :func:`normals_enu`, L the unit
    vector toward the sun (terrain.sun.sun_direction_enu), shadow from
    :func:`cast_shadow`. With the sun at or below the horizon there is no
    directional term and shadow is all True; ambient(e) is params.ambient
    by day, falling linearly to params.night_ambient at -twilight_deg.
    No-data posts get light 0 and shadow False. ``sky``: a precomputed
    :func:`sky_view` (it does not depend on the sun). dx_m, dy_m: scalars
    or each row's own ((rows,), :func:`row_spacing`).

    sun_az_deg, sun_el_deg: scalars, one sun for every post, or arrays
    broadcastable to the grid, each post's own sun (a box wide enough for
    the sun to differ across it: its ambient, N.L and day or night are each
    post's own, and each post's shadow ray runs toward its own sun).
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


def synthesize(heights, dx_m, dy_m, sun_az_deg, sun_el_deg, lat_deg=45.0, *,
               class_params: ClassParams = ClassParams(), light_params: LightParams = LightParams(),
               seed: int = 0, soft_px: int = 0, noise_en_m=None, noise_xyz_m=None,
               water_tolerance_m: float = 0.0) -> Texture:
    """slope -> class map -> diffuse -> light map -> image, for one height grid.

    dx_m, dy_m: scalars or each row's own ((rows,), :func:`row_spacing`). sun_az_deg,
    sun_el_deg: one sun (scalars) or each post's own (arrays broadcastable to the grid), as
    :func:`light_map` takes them. noise_xyz_m / noise_en_m: where the class noise lies
    (:func:`base_classes`). water_tolerance_m: the heights' source's quantisation bound
    (:func:`base_classes`; 0 for a DEM)."""
    slope = slope_deg(heights, dx_m, dy_m)
    classes = class_map(heights, slope, dx_m, dy_m, lat_deg, params=class_params, seed=seed,
                        noise_en_m=noise_en_m, noise_xyz_m=noise_xyz_m, water_tolerance_m=water_tolerance_m)
    rgb = diffuse(classes, soft_px=soft_px, seed=seed)
    light = light_map(heights, dx_m, dy_m, sun_az_deg, sun_el_deg, params=light_params)
    return Texture(slope, classes, rgb, light, compose(rgb, light.light))
