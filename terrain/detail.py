"""Fractal detail synthesis under real elevation data.

Geometry-clipmap thesis §3.1.9 (after Losasso & Hoppe 2004): where the data
become too sparse, detail is made by "adding uncorrelated Gaussian noise to the
upsampled terrain at the sub sample level", the noise variance at each level
scaled "to equal that in actual terrain, i.e. the variance of the residuals"
of the compression pyramid (§3.1.8: finer levels predicted from coarser ones
by interpolatory subdivision).

Here, in a raster's index space (row, col; posts at integers):

* Pyramid residuals (:func:`pyramid_residual_variance`): level l + 1 keeps
  every other post of level l; level l is predicted from it by bilinear
  subdivision (edge midpoints: mean of 2, centres: mean of 4) and the residual
  variance is taken over the new posts only. With a sea level (below) only the
  residuals whose stencil posts (the new post and the 2 or 4 it is predicted
  from) all lie above it count: the detail is synthesised over land alone, so
  the sea's flat posts must not dilute the variance it is scaled to (a tile of
  86 % sea gave land 1/2.6 of its own residual std). Where land gives no fit
  (fewer than 2 levels of ``min_residuals``: an all-sea tile, a few islets)
  every residual counts, as without a sea level. Sources of one import pool
  their residuals (:func:`pooled_residual_variance`, per lattice spacing), so
  tiles kept apart get one fit and their detail meets at the seam.
* The variance decays about log-linearly with level; a least-squares line
  through log2 of the finest measured levels (:func:`fit_sub_level_std`) is
  extrapolated to the sub-sample levels l = -1, -2, ..., -K, whose lattices
  have spacing 2^-k posts, down to about ``finest_spacing_m``.
* Level k's noise lives on its lattice: zero at the posts of the coarser
  lattice (so the real posts keep their exact heights), sigma_k times a
  standard Gaussian at the new posts, interpolated bilinearly so the surface
  is continuous. Since a bilinear function sampled on a finer aligned grid
  and re-interpolated is unchanged, upsampling level by level and adding each
  level's noise equals base bilinear + the sum of the levels' bilinear noise
  (:func:`detail_noise`), which is what is evaluated.
* Gaussian values come from a table of standard normal quantiles (the
  thesis's precomputed table) indexed by a counter hash of (seed, level,
  global lattice row, column) modulo the table size: deterministic per seed,
  without the visible period of indexing by coordinates modulo the table.
  Lattice coordinates are global where the raster is aligned to its own
  spacing (SRTM tiles are), so neighbouring tiles draw the same values on
  their shared edge.
* Water stays water: the detail is scaled by a weight of the undetailed
  (bilinear) height h at the point, w = clip((h - sea_level_m) / taper_m, 0, 1),
  with taper_m = SEA_TAPER_STDS times the detail's total std. No detail where the
  source is at or below sea level (SRTM writes the sea as 0 m; terrain/texture.py
  draws h <= 0 as water), full detail from taper_m above it, and a linear ramp
  between, so the surface stays continuous at the coastline, and land goes
  below sea level only where the noise is below -taper_m (-3 sigma: 0.13 % of
  the points) instead of wherever it is below -h. The weight is our rule, not
  the thesis's (whose terrain has no sea). ``sea_level_m=None`` turns it off.
  Near the coast (0 < h - sea_level_m < taper_m) the densified rasters of
  :meth:`DetailedRaster.raster_for` interpolate the weighted posts, so rays
  there meet the surface to within the weight's curvature over a finest cell;
  elsewhere exactly.
* The detail's amplitude is one fit per raster (its whole pyramid's residual
  variance over land), so a flat plain beside mountains in the same raster gets the
  mountains' detail: the thesis's rule (noise variance "equal that in actual
  terrain", taken over the data the detail is synthesised for).
* Towards the poles a geographic lattice's cells narrow east-west (width/height
  = dx cos(lat) / dy), while the noise drawn at its posts does not: its
  east-west slopes grow as 1 / cos(lat), and at a pole, where a row is one point,
  the noise of that row's posts would give one point many heights and a
  horizontal normal (east slope d/dcol over 6e-17 m a column). So the noise of a
  lattice row on a pole (+-90 deg) is 0 (the surface there is the source's, its
  slope the source's), and the detail is scaled by the polar taper
  p(lat) = min(1, dx cos(lat) / (dy POLAR_ASPECT_MIN)) (:func:`polar_taper`): 1
  wherever cells are at least POLAR_ASPECT_MIN as wide as tall (every latitude
  to 60 deg for square posts, SRTM's whole range), then falling with the cells'
  width, so the detail's east-west slopes stay within 1 / POLAR_ASPECT_MIN of
  its north-south ones. It is a function of latitude and spacing alone, so
  tiles of one spacing agree on their seams; Web Mercator cells are square (1).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.special import ndtri

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.geodesy import WGS84_A_M
from terrain.procedural import lattice_hash, mix64
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OUTSIDE, Georef, Raster, fractional_index, metres_per_index

NOISE_TABLE_SIZE = 1 << 16  # Gaussian quantiles; a power of two so "modulo" is a mask
FIT_LEVELS = 4  # finest pyramid levels used in the log-linear variance fit
MAX_SUB_LEVELS = 24  # 90 m / 2^24 is 5 micrometres: deeper is never useful
# Largest densified raster raster_for builds (32 MiB of float64); bigger boxes
# get the finest detail level that fits (ray_raster_for raises LimitExceeded instead).
DETAIL_RASTER_MAX_POSTS = 1 << 22
# A raster origin within this many posts of a whole multiple of its spacing is
# taken as aligned to the global lattice of that spacing.
ALIGNMENT_TOLERANCE_POSTS = 1e-6
# Sea level (m, the source's datum): no detail at or below it (SRTM writes the sea as 0 m).
SEA_LEVEL_M = 0.0
# The detail ramps in over this many of its total standard deviations above sea level.
SEA_TAPER_STDS = 3.0
# Lattice cells narrower east-west than this fraction of their north-south height get their
# detail scaled down in proportion (polar_taper): 0.5 is cos 60 deg, SRTM's northern limit.
POLAR_ASPECT_MIN = 0.5
# A lattice row a raster does not hold at a pole (detail_noise's pole_rows).
NO_POLE_ROW = -(1 << 62)


def sea_taper(base_m, sea_level_m: float | None, taper_m: float):
    """(weight, d weight / d height) of synthetic detail over undetailed heights ``base_m``:
    clip((h - sea_level_m) / taper_m, 0, 1) and its slope (0 outside the ramp); (1, 0) when
    sea_level_m is None; a step (0 at or below sea level, 1 above) when taper_m is 0."""
    base = np.asarray(base_m, dtype=np.float64)
    if sea_level_m is None:
        return np.ones(base.shape), np.zeros(base.shape)
    above = base - sea_level_m
    if taper_m <= 0.0:
        return (above > 0.0).astype(np.float64), np.zeros(base.shape)
    t = above / taper_m
    with np.errstate(invalid="ignore"):
        slope = np.where((t > 0.0) & (t < 1.0), 1.0 / taper_m, 0.0)
    return np.clip(t, 0.0, 1.0), slope


def noise_table(size: int = NOISE_TABLE_SIZE) -> np.ndarray:
    """(size,) float64 standard normal quantiles at (t + 0.5) / size, exactly mean 0, variance 1."""
    g = ndtri((np.arange(size) + 0.5) / size)
    g -= g.mean()
    return g / np.sqrt(np.mean(g * g))


_TABLE = noise_table()
_TABLE.flags.writeable = False


def _level_parts(z: np.ndarray):
    """The three residual grids of one pyramid step (edge midpoints east, north, cell centres)
    with, for each, the posts of its stencil: (residuals, [new post, coarse posts...]) triples."""
    z = z[: z.shape[0] - 1 + z.shape[0] % 2, : z.shape[1] - 1 + z.shape[1] % 2]
    c = z[::2, ::2]
    east = (z[::2, 1::2], [c[:, :-1], c[:, 1:]])
    north = (z[1::2, ::2], [c[:-1], c[1:]])
    centre = (z[1::2, 1::2], [c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
    for new, coarse in (east, north, centre):
        predicted = coarse[0] + coarse[1] if len(coarse) == 2 else (coarse[0] + coarse[1]) + (coarse[2] + coarse[3])
        yield new - predicted / len(coarse), [new, *coarse]


def _kept_residuals(parts, above_m: float | None) -> np.ndarray:
    """(k,) float64 finite residuals of one step's parts (:func:`_level_parts`), with ``above_m``
    those whose stencil posts all lie above it."""
    out = []
    for res, stencil in parts:
        keep = np.isfinite(res)
        if above_m is not None:
            for post in stencil:
                keep &= post > above_m
        out.append(res[keep])
    return np.concatenate(out)


def level_residuals(z: np.ndarray, above_m: float | None = None) -> np.ndarray:
    """Residuals of predicting z from z[::2, ::2] by bilinear subdivision (thesis §3.1.8).

    z: (ny, nx) float heights, metres; an even trailing row/column is dropped
    so the coarse posts include the last ones. Returns (k,) float64 residuals
    (actual - predicted) at the new posts only, NaN ones removed; with
    ``above_m``, only those whose stencil posts all lie above it (m, land).
    """
    return _kept_residuals(list(_level_parts(np.asarray(z, dtype=np.float64))), above_m)


def residual_moments(heights: np.ndarray, above_m=(None,)) -> np.ndarray:
    """(T, L, 3) float64 for each threshold of ``above_m`` (None: every finite residual; a
    height, m: residuals whose stencil posts all lie above it), per pyramid level, finest
    (l = 0) first: count, mean (m) and sum of squared deviations from it (m^2) of the level's
    residuals (:func:`level_residuals`); levels while both sides hold at least 3 posts. Moments
    pool exactly over several rasters (:func:`pool_moments`)."""
    z = np.asarray(heights, dtype=np.float64)
    out = []
    while min(z.shape) >= 3:
        parts = list(_level_parts(z))
        level = []
        for threshold in above_m:
            res = _kept_residuals(parts, threshold)
            mean = float(res.mean()) if res.size else 0.0
            level.append((float(res.size), mean, float(np.sum((res - mean) ** 2))))
        out.append(level)
        z = z[: z.shape[0] - 1 + z.shape[0] % 2: 2, : z.shape[1] - 1 + z.shape[1] % 2: 2]
    return np.array(out, dtype=np.float64).reshape(-1, len(above_m), 3).transpose(1, 0, 2)


def pool_moments(moments) -> np.ndarray:
    """(L, 3) moments of the union of several rasters' residuals, level by level (L the most
    levels any has): counts add, means weigh by count, and each raster's squared deviations
    add with count x (its mean - the pooled mean)^2 (Chan, Golub & LeVeque 1979, the pairwise
    update of the sum of squares)."""
    moments = [np.asarray(m, dtype=np.float64).reshape(-1, 3) for m in moments]
    levels = max((m.shape[0] for m in moments), default=0)
    out = np.zeros((levels, 3))
    for lv in range(levels):
        rows = np.array([m[lv] for m in moments if m.shape[0] > lv and m[lv, 0] > 0]).reshape(-1, 3)
        n = rows[:, 0].sum()
        if n == 0:
            continue
        mean = float(np.sum(rows[:, 0] * rows[:, 1]) / n)
        out[lv] = (n, mean, float(np.sum(rows[:, 2] + rows[:, 0] * (rows[:, 1] - mean) ** 2)))
    return out


def moment_variances(moments: np.ndarray, min_residuals: int = 64) -> np.ndarray:
    """(L,) float64 residual variance (m^2) per level, finest first, up to the first level with
    fewer than min_residuals residuals."""
    out = []
    for n, _, m2 in np.asarray(moments, dtype=np.float64).reshape(-1, 3):
        if n < min_residuals:
            break
        out.append(m2 / n)
    return np.array(out, dtype=np.float64)


# Levels of land residuals that make a fit (a slope): with fewer, every residual counts.
LAND_FIT_MIN_LEVELS = 2


def pooled_residual_variance(height_grids, sea_level_m: float | None = None, min_residuals: int = 64) -> np.ndarray:
    """(L,) float64 residual variance (m^2) per pyramid level, finest (l = 0) first, of the
    residuals of every grid of ``height_grids`` ((ny, nx) float, metres, NaN for no data)
    together: each counts by its number of residuals (:func:`pool_moments`).

    With ``sea_level_m``, only residuals whose stencil posts all lie above it (land: the detail
    is added there alone, :func:`sea_taper`), unless land gives fewer than
    LAND_FIT_MIN_LEVELS levels of min_residuals while all residuals give more (an all-sea
    tile, a few islets): then every residual, as without a sea level. Levels stop at the first
    with fewer than min_residuals residuals."""
    moments = [residual_moments(h, (None,) if sea_level_m is None else (None, sea_level_m)) for h in height_grids]
    every = moment_variances(pool_moments([m[0] for m in moments]), min_residuals)
    if sea_level_m is None:
        return every
    land = moment_variances(pool_moments([m[1] for m in moments]), min_residuals)
    return land if land.size >= min(LAND_FIT_MIN_LEVELS, every.size) else every


def pyramid_residual_variance(heights: np.ndarray, min_residuals: int = 64,
                              sea_level_m: float | None = None) -> np.ndarray:
    """(L,) float64 residual variance (m^2) per pyramid level, finest (l = 0) first.

    heights: (ny, nx) float, metres, NaN for no data. Level l + 1 is every
    other post of level l; levels stop when fewer than min_residuals finite
    residuals remain. sea_level_m: count land alone (:func:`pooled_residual_variance`).
    """
    return pooled_residual_variance([heights], sea_level_m, min_residuals)


def fit_sub_level_std(variances: np.ndarray, sub_levels: int, fit_levels: int = FIT_LEVELS):
    """Noise std (m) for sub-sample levels k = 1..sub_levels, and the fit.

    variances: (L,) float64 m^2 from :func:`pyramid_residual_variance`. Fits
    log2 var = alpha + beta * l over the finest min(L, fit_levels) levels and
    evaluates it at l = -k. beta is clamped to >= 0 (finer levels never get
    more variance than coarser ones); with a single level, beta = 0.
    Returns (std: (sub_levels,) float64, alpha, beta).
    """
    v = np.asarray(variances, dtype=np.float64)[:fit_levels]
    lv = np.flatnonzero(v > 0).astype(np.float64)  # a flat level (variance 0) has no logarithm
    v = v[v > 0]
    if v.size == 0:
        return np.zeros(sub_levels), -math.inf, 0.0
    if v.size == 1:
        alpha, beta = float(np.log2(v[0])), 0.0
    else:
        beta, alpha = (float(x) for x in np.polyfit(lv, np.log2(v), 1))
        beta = max(beta, 0.0)
    k = np.arange(1, sub_levels + 1, dtype=np.float64)
    return np.sqrt(np.exp2(alpha - beta * k)), alpha, beta


@numba.njit(cache=True, nogil=True)
def _lattice_noise(seed_hash, level, gi, gj, std, table):
    """Noise of one level at global lattice post (gi, gj): 0 on the coarser lattice.

    The table index is lattice_hash(seed, level, gi, gj) modulo the table size.
    """
    if (gi | gj) & 1 == 0:
        return 0.0
    h = mix64(seed_hash ^ np.uint64(level))
    h = mix64(h ^ np.uint64(gi))
    h = mix64(h ^ np.uint64(gj))
    return std * table[h & np.uint64(table.shape[0] - 1)]


@numba.njit(cache=True, nogil=True)
def _on_pole(i, lv, pole_south, pole_north):
    """Whether local lattice row i of level lv lies on a pole row (level-0 rows pole_south,
    pole_north; NO_POLE_ROW for none)."""
    return ((pole_south != NO_POLE_ROW and i == pole_south << lv)
            or (pole_north != NO_POLE_ROW and i == pole_north << lv))


@numba.njit(cache=True, nogil=True)
def _detail_kernel(rows, cols, level_std_m, seed_hash, table, ny, nx, row_offset, col_offset, col_period,
                   pole_south, pole_north, out, d_row, d_col):
    for p in range(rows.shape[0]):
        acc = 0.0
        acc_r = 0.0
        acc_c = 0.0
        for lv in range(1, level_std_m.shape[0] + 1):
            scale = float(1 << lv)
            u = rows[p] * scale
            v = cols[p] * scale
            i = min(math.floor(u), (ny - 1) * scale - 1.0)
            j = min(math.floor(v), (nx - 1) * scale - 1.0)
            fy = u - i
            fx = v - j
            gi = np.int64(i) + (row_offset << lv)
            gj = np.int64(j) + (col_offset << lv)
            gj1 = gj + 1
            if col_period > 0:
                gj = gj % (col_period << lv)
                gj1 = gj1 % (col_period << lv)
            std = level_std_m[lv - 1]
            v00 = v01 = v10 = v11 = 0.0  # a row on a pole is one point: no noise there
            if not _on_pole(np.int64(i), lv, pole_south, pole_north):
                v00 = _lattice_noise(seed_hash, lv, gi, gj, std, table)
                v01 = _lattice_noise(seed_hash, lv, gi, gj1, std, table)
            if not _on_pole(np.int64(i) + 1, lv, pole_south, pole_north):
                v10 = _lattice_noise(seed_hash, lv, gi + 1, gj, std, table)
                v11 = _lattice_noise(seed_hash, lv, gi + 1, gj1, std, table)
            south = v00 * (1.0 - fx) + v01 * fx
            north = v10 * (1.0 - fx) + v11 * fx
            acc += south * (1.0 - fy) + north * fy
            acc_r += scale * (north - south)
            acc_c += scale * ((v01 - v00) * (1.0 - fy) + (v11 - v10) * fy)
        out[p] = acc
        d_row[p] = acc_r
        d_col[p] = acc_c


def detail_noise(rows, cols, level_std_m, seed: int, shape, row_offset: int = 0, col_offset: int = 0,
                 col_period: int = 0, pole_rows=(None, None)):
    """Synthesised detail at fractional raster indices: sum over sub-levels of bilinear noise.

    rows, cols: (n,) float64 fractional (row, col) in the raster's index
    space; level_std_m: (K,) float64 noise std (m) of levels k = 1..K
    (lattice spacing 2^-k posts); shape: the raster's (ny, nx), for the
    far-edge cell choice; row_offset, col_offset: global lattice index of the
    raster's post (0, 0); col_period: posts per turn of longitude (0: no
    wrap); pole_rows: (south, north) rows of the raster's index space on the
    poles (:func:`pole_rows`; None: not a row of its lattice), whose noise is 0
    at every level. Returns (detail, d/drow, d/dcol), each (n,) float64: metres,
    and metres per post index (the north-east cell on a lattice line).
    """
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    cols = np.ascontiguousarray(cols, dtype=np.float64)
    if rows.ndim != 1 or rows.shape != cols.shape:
        raise ValueError(f"rows and cols must be equal (n,) arrays, got shapes {rows.shape} and {cols.shape}")
    out, d_row, d_col = np.zeros(rows.shape), np.zeros(rows.shape), np.zeros(rows.shape)
    seed_hash = lattice_hash(seed)[()]
    south, north = (NO_POLE_ROW if r is None else int(r) for r in pole_rows)
    _detail_kernel(rows, cols, np.ascontiguousarray(level_std_m, dtype=np.float64), seed_hash, _TABLE,
                   shape[0], shape[1], row_offset, col_offset, col_period, south, north, out, d_row, d_col)
    return out, d_row, d_col


def pole_rows(crs: int, y0: float, dy: float) -> tuple[int | None, int | None]:
    """(south, north): the rows of a raster whose row r lies at y0 + r dy on the poles (-90, +90
    deg) where they are rows of its lattice (within ALIGNMENT_TOLERANCE_POSTS), else None; (None,
    None) for a projected raster (Web Mercator never reaches a pole)."""
    if crs != CRS_GEOGRAPHIC:
        return None, None
    out = []
    for lat in (-90.0, 90.0):
        q = (lat - y0) / dy
        out.append(int(round(q)) if abs(q - round(q)) < ALIGNMENT_TOLERANCE_POSTS else None)
    return out[0], out[1]


def polar_taper(lat_deg, crs: int, dx: float, dy: float):
    """(p, dp/dlat): the detail's scale p = clip(dx cos(lat) / (dy POLAR_ASPECT_MIN), 0, 1) of a
    geographic lattice of spacing dx, dy (degrees) at latitudes lat_deg ((n,) float64 degrees),
    and its slope per degree of latitude (0 where p is 1); (1, 0) for a projected lattice, whose
    cells are square (module docstring)."""
    lat = np.asarray(lat_deg, dtype=np.float64)
    if crs != CRS_GEOGRAPHIC:
        return np.ones(lat.shape), np.zeros(lat.shape)
    k = dx / (dy * POLAR_ASPECT_MIN)
    raw = k * np.cos(np.radians(lat))
    slope = np.where(raw < 1.0, -k * np.sin(np.radians(lat)) * (math.pi / 180.0), 0.0)
    return np.clip(raw, 0.0, 1.0), slope


@numba.njit(cache=True, nogil=True)
def _fractional_indices(lat, lon, crs, x0, y0, dx, dy):
    """(n,) float64 (row, col) of each (lat, lon) via terrain.raster.fractional_index."""
    rows = np.zeros(lat.shape[0])
    cols = np.zeros(lat.shape[0])
    for k in range(lat.shape[0]):
        rows[k], cols[k] = fractional_index(lat[k], lon[k], crs, x0, y0, dx, dy)
    return rows, cols


def _bilinear_at_index(heights, rows, cols):
    """Bilinear heights (m) at fractional indices inside the grid, float64, same cell rule as the raster."""
    ny, nx = heights.shape
    i = np.minimum(np.floor(rows), ny - 2).astype(np.intp)
    j = np.minimum(np.floor(cols), nx - 2).astype(np.intp)
    fy, fx = rows - i, cols - j
    h = heights.astype(np.float64, copy=False)
    south = h[i, j] * (1.0 - fx) + h[i, j + 1] * fx
    north = h[i + 1, j] * (1.0 - fx) + h[i + 1, j + 1] * fx
    return south * (1.0 - fy) + north * fy


def _filled_at_index(filled, rows, cols):
    """(n,) bool: whether the bilinear height at each fractional index (rows, cols: (n,) float64,
    inside the grid) of a raster whose filled-void posts are ``filled`` ((ny, nx) uint8) reads a
    filled post with non-zero weight: the status its heights give there is FILLED
    (terrain.raster._bilinear_value, same cell and corner rule). As the filled mask of a densified
    lattice (:meth:`DetailedRaster._dense`), it gives every point of a fine cell the status the
    source's heights give it: a fine cell lies in one coarse cell, its four corners together read
    every corner of that cell (as a point inside it does), and the fine posts on the coarse cell's
    edge read only that edge's two corners (as a point on it does)."""
    ny, nx = filled.shape
    i = np.minimum(np.floor(rows), ny - 2).astype(np.intp)
    j = np.minimum(np.floor(cols), nx - 2).astype(np.intp)
    fy, fx = rows - i, cols - j
    # terrain.raster._weighted_corners: a corner of zero weight is replaced by its neighbour.
    i0, i1 = np.where(fy == 1.0, i + 1, i), np.where(fy == 0.0, i, i + 1)
    j0, j1 = np.where(fx == 1.0, j + 1, j), np.where(fx == 0.0, j, j + 1)
    return (filled[i0, j0] | filled[i0, j1] | filled[i1, j0] | filled[i1, j1]).astype(bool)


def sub_levels_for(raster: Raster, finest_spacing_m: float) -> int:
    """K: the detail levels a :class:`DetailedRaster` of ``raster`` adds, halving its larger post
    spacing (m, at its centre) until at or below finest_spacing_m (at most MAX_SUB_LEVELS)."""
    coarse_m = max(raster.post_spacing_m)
    return min(MAX_SUB_LEVELS, max(0, math.ceil(math.log2(coarse_m / finest_spacing_m))))


def detailed_rasters(rasters, seed: int, finest_spacing_m: float = 1.0,
                     sea_level_m: float | None = SEA_LEVEL_M) -> list[DetailedRaster]:
    """A :class:`DetailedRaster` of each raster, those of one lattice spacing (CRS, dx, dy)
    fitted to their residuals pooled (:func:`pooled_residual_variance`, over land): sources
    kept apart (tiles of an import) then draw the same noise on a shared edge from one global
    lattice with the same stds, so the detailed surface is as continuous across their seam as
    the sources are (each fitted alone, two halves of one tile stepped by up to 0.5 m)."""
    variance = variance_by_spacing(rasters, sea_level_m)
    return [DetailedRaster(r, seed, finest_spacing_m, sea_level_m=sea_level_m, residual_variance_m2=v)
            for r, v in zip(rasters, variance)]


def variance_by_spacing(rasters, sea_level_m: float | None = SEA_LEVEL_M) -> list[np.ndarray]:
    """Per raster, the (L,) residual variances (m^2) pooled over every raster of its lattice
    spacing (CRS, dx, dy): :func:`pooled_residual_variance`, over land with ``sea_level_m``.
    Levels are counted in posts, so only rasters of one spacing share a fit."""
    groups: dict[tuple, list[int]] = {}
    for k, r in enumerate(rasters):
        groups.setdefault((r.georef.crs, r.georef.dx, r.georef.dy), []).append(k)
    variance = [np.zeros(0)] * len(rasters)
    for members in groups.values():
        v = pooled_residual_variance([rasters[k].heights for k in members], sea_level_m)
        for k in members:
            variance[k] = v
    return variance


def _aligned_offset(origin: float, spacing: float) -> int:
    q = origin / spacing
    return int(round(q)) if abs(q - round(q)) < ALIGNMENT_TOLERANCE_POSTS else 0


class DetailedRaster:
    """A Raster with deterministic fractal detail below its post spacing.

    A height source for :class:`terrain.terrain.Terrain`. Heights at the
    raster's posts are exact; between them, sub-levels k = 1..K (lattice
    spacing 2^-k posts, the finest at or below ``finest_spacing_m``) add
    Gaussian noise whose std per level comes from pyramid residual variances:
    the raster's own over land (``sea_level_m``), or ``residual_variance_m2``
    when given (:func:`pooled_residual_variance` of several sources, so that
    tiles kept apart share one fit: :func:`detailed_rasters`); or the stds
    themselves, ``level_std_m``. Heights at or below ``sea_level_m`` get no
    detail, and it ramps in above (:func:`sea_taper`, the module docstring);
    None: detail everywhere, residuals of every post. Near the poles the detail
    is scaled by :func:`polar_taper`, and it is 0 on a pole's row.
    """

    def __init__(self, raster: Raster, seed: int, finest_spacing_m: float = 1.0, fit_levels: int = FIT_LEVELS,
                 level_std_m=None, name: str | None = None, sea_level_m: float | None = SEA_LEVEL_M,
                 residual_variance_m2=None):
        if not isinstance(raster, Raster):
            raise TypeError(f"raster must be a terrain.raster.Raster, got {type(raster).__name__}")
        if not (math.isfinite(finest_spacing_m) and finest_spacing_m > 0):
            raise InvalidArgument("finest_spacing_m", "must be finite and > 0", value=finest_spacing_m)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
            raise InvalidArgument("seed", "must be an integer within [0, 2^64)", value=seed)
        if sea_level_m is not None and not math.isfinite(sea_level_m):
            raise InvalidArgument("sea_level_m", "must be a finite height (m) or None", value=sea_level_m)
        self.raster = raster
        self.seed = int(seed)
        self.name = name or f"{raster.name}+detail"
        self.finest_spacing_m = float(finest_spacing_m)
        self.sea_level_m = None if sea_level_m is None else float(sea_level_m)
        self.sub_levels = sub_levels_for(raster, finest_spacing_m)
        if residual_variance_m2 is None:
            variance = pyramid_residual_variance(raster.heights, sea_level_m=self.sea_level_m)
        else:
            variance = np.array(residual_variance_m2, dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(variance) & (variance >= 0)):
                raise InvalidArgument("residual_variance_m2", "must be finite values >= 0 (m^2)", value=variance)
        variance.flags.writeable = False
        self.residual_variance_m2 = variance
        if level_std_m is None:
            std, self.fit_alpha, self.fit_beta = fit_sub_level_std(variance, self.sub_levels, fit_levels)
        else:
            std = np.array(level_std_m, dtype=np.float64)
            if std.shape != (self.sub_levels,) or not np.all(np.isfinite(std) & (std >= 0)):
                raise InvalidArgument("level_std_m", f"must be ({self.sub_levels},) finite values >= 0", value=std)
            self.fit_alpha, self.fit_beta = math.nan, math.nan
        std.flags.writeable = False
        self.level_std_m = std
        self.sea_taper_m = SEA_TAPER_STDS * float(np.sqrt(np.sum(std ** 2)))
        g = raster.georef
        self.row_offset = _aligned_offset(g.y0, g.dy)
        self.col_offset = _aligned_offset(g.x0, g.dx)
        turn = 360.0 / g.dx if g.crs == CRS_GEOGRAPHIC else 0.0
        self.col_period = int(round(turn)) if turn and abs(turn - round(turn)) < ALIGNMENT_TOLERANCE_POSTS else 0
        self.pole_rows = pole_rows(g.crs, g.y0, g.dy)

    def detail_at_index(self, rows, cols, levels: int | None = None):
        """(detail, d/drow, d/dcol) at fractional raster indices (n,) float64: :func:`detail_noise`
        times :func:`polar_taper` at the rows' latitudes (its slope in d/drow).

        levels: use only sub-levels 1..levels (default all).
        """
        std = self.level_std_m if levels is None else self.level_std_m[:levels]
        noise, d_row, d_col = detail_noise(rows, cols, std, self.seed, self.raster.shape, self.row_offset,
                                           self.col_offset, self.col_period, self.pole_rows)
        g = self.raster.georef
        if g.crs != CRS_GEOGRAPHIC:
            return noise, d_row, d_col
        taper, slope = polar_taper(g.y0 + np.asarray(rows, dtype=np.float64) * g.dy, g.crs, g.dx, g.dy)
        return taper * noise, taper * d_row + noise * slope * g.dy, taper * d_col

    def warm_cache(self, n_points: int) -> bool:
        """The underlying raster's :meth:`terrain.raster.Raster.warm_cache`."""
        return self.raster.warm_cache(n_points)

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        """Heights (m, the raster's datum) with detail for the points still OUTSIDE.

        lat, lon: (n,) float64 degrees, (lat, lon) order. Exact at the raster's
        posts; status as the raster reports it.
        """
        todo = out_status == STATUS_OUTSIDE
        self.raster.heights_into(lat, lon, out_h, out_status)
        hit = np.flatnonzero(todo & (out_status != STATUS_OUTSIDE))
        if hit.size and self.sub_levels:
            weight, _ = sea_taper(out_h[hit], self.sea_level_m, self.sea_taper_m)
            keep = weight > 0.0  # at or below sea level: the source's own height
            hit, weight = hit[keep], weight[keep]
            rows, cols = self._indices(lat[hit], lon[hit])
            out_h[hit] += weight * self.detail_at_index(rows, cols)[0]

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        """dh/d(east metre), dh/d(north metre) of the detailed surface for points still OUTSIDE."""
        todo = out_status == STATUS_OUTSIDE
        self.raster.gradient_into(lat, lon, out_de, out_dn, out_status)
        hit = np.flatnonzero(todo & (out_status != STATUS_OUTSIDE))
        if hit.size and self.sub_levels:
            weight, slope = np.ones(hit.size), np.zeros(hit.size)
            if self.sea_level_m is not None:
                base = np.full(hit.size, np.nan)
                self.raster.heights_into(lat[hit], lon[hit], base, np.full(hit.size, STATUS_OUTSIDE, np.uint8))
                weight, slope = sea_taper(base, self.sea_level_m, self.sea_taper_m)
                keep = weight > 0.0
                hit, weight, slope = hit[keep], weight[keep], slope[keep]
            rows, cols = self._indices(lat[hit], lon[hit])
            detail, d_row, d_col = self.detail_at_index(rows, cols)
            g = self.raster.georef
            mx, my = metres_per_index(g.crs, g.dx, g.dy, lat[hit])
            # d(w detail) = w d(detail) + detail dw/dh d(base): the product rule over the ramp.
            de, dn = out_de[hit], out_dn[hit]
            out_de[hit] = de + weight * d_col / mx + detail * slope * de
            out_dn[hit] = dn + weight * d_row / my + detail * slope * dn

    def raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float):
        """A densified Raster of the detailed surface over the box, or None if not covered.

        Posts on the finest sub-level lattice whose posts in the box number at
        most DETAIL_RASTER_MAX_POSTS; its bilinear surface then equals this
        source's wherever that is the finest level (coarser levels for big
        boxes: the omitted detail is in ``meta["omitted_detail_std_m"]``; a
        viewer's overview). lon_max < lon_min means the box crosses the
        antimeridian. Rays use :meth:`ray_raster_for`, which never omits detail.
        """
        window = self._window(lat_min, lon_min, lat_max, lon_max)
        if window is None or window[0] is None:
            return None if window is None else window[1]
        base, (r_lo, r_hi, c_lo, c_hi) = window
        level = self.sub_levels
        while level > 0 and _window_posts(_lattice_window(r_lo, r_hi, c_lo, c_hi, level, self.raster.shape)) \
                > DETAIL_RASTER_MAX_POSTS:
            level -= 1
        if level == 0:
            return base
        return self._dense(_lattice_window(r_lo, r_hi, c_lo, c_hi, level, self.raster.shape), level)

    def ray_raster_for(self, lat_min: float, lon_min: float, lat_max: float, lon_max: float):
        """:meth:`raster_for` for a group of rays (terrain.terrain.Terrain): always every detail
        level, so a ray meets the surface :meth:`heights_into` answers; a box whose finest lattice
        holds more than DETAIL_RASTER_MAX_POSTS posts raises LimitExceeded (the Terrain then splits
        the group, and traces a lone segment in parts)."""
        window = self._window(lat_min, lon_min, lat_max, lon_max)
        if window is None or window[0] is None:
            return None if window is None else window[1]
        lattice = _lattice_window(*window[1], self.sub_levels, self.raster.shape)
        posts = _window_posts(lattice)
        if posts > DETAIL_RASTER_MAX_POSTS:
            raise LimitExceeded("detail box posts", posts, DETAIL_RASTER_MAX_POSTS)
        return self._dense(lattice, self.sub_levels)

    def _window(self, lat_min, lon_min, lat_max, lon_max):
        """None when the raster does not cover the box; (None, raster) when it has no sub-levels;
        else (the raster, (r_lo, r_hi, c_lo, c_hi)): the box's fractional index ranges."""
        span = lon_max - lon_min if lon_max >= lon_min else lon_max - lon_min + 360.0
        base = self.raster.raster_for(lat_min, lon_min, lat_max, lon_min + span)
        if base is None:
            return None
        if self.sub_levels == 0:
            return None, base
        g = self.raster.georef
        (r_lo, r_hi), (c_lo, _) = _fractional_indices(np.array([lat_min, lat_max]), np.array([lon_min, lon_min]),
                                                      g.crs, g.x0, g.y0, g.dx, g.dy)
        c_hi = c_lo + (span if g.crs == CRS_GEOGRAPHIC else math.radians(span) * WGS84_A_M) / g.dx
        return base, (r_lo, r_hi, c_lo, c_hi)

    def _dense(self, lattice, level: int) -> Raster:
        """The Raster of the detailed surface (sub-levels 1..level) on the level's lattice posts
        i0..i1, j0..j1 (``lattice``, :func:`_lattice_window`)."""
        i0, i1, j0, j1 = lattice
        g = self.raster.georef
        scale = float(1 << level)
        rows, cols = np.meshgrid(np.arange(i0, i1 + 1) / scale, np.arange(j0, j1 + 1) / scale, indexing="ij")
        rows, cols = rows.ravel(), cols.ravel()
        base = _bilinear_at_index(self.raster.heights, rows, cols)
        weight, _ = sea_taper(base, self.sea_level_m, self.sea_taper_m)
        dense = base + weight * self.detail_at_index(rows, cols, level)[0]
        omitted = float(np.sqrt(np.sum(self.level_std_m[level:] ** 2)))
        shape = (i1 - i0 + 1, j1 - j0 + 1)
        filled = None if self.raster.filled is None else _filled_at_index(self.raster.filled, rows, cols).reshape(shape)
        return Raster(dense.reshape(shape),
                      Georef(g.crs, g.x0 + j0 * g.dx / scale, g.y0 + i0 * g.dy / scale, g.dx / scale, g.dy / scale),
                      name=self.name, vertical_datum=self.raster.vertical_datum, filled=filled,
                      source=self.raster.source, meta={"detail_levels": level, "omitted_detail_std_m": omitted})

    def describe(self) -> dict:
        """The raster's description with kind "dem+detail" and the synthesis parameters."""
        d = self.raster.describe()
        d.update({
            "name": self.name,
            "kind": "dem+detail",
            "detail_seed": self.seed,
            "detail_levels": self.sub_levels,
            "detail_finest_spacing_m": self.finest_spacing_m,
            "detail_level_std_m": [float(s) for s in self.level_std_m],
            "detail_sea_level_m": self.sea_level_m,
            "detail_sea_taper_m": self.sea_taper_m,
            "residual_variance_m2": [float(v) for v in self.residual_variance_m2],
            "fit_log2_variance_alpha": self.fit_alpha,
            "fit_log2_variance_beta": self.fit_beta,
        })
        return d

    def _indices(self, lat, lon):
        g = self.raster.georef
        return _fractional_indices(np.ascontiguousarray(lat), np.ascontiguousarray(lon), g.crs, g.x0, g.y0, g.dx,
                                   g.dy)


def _lattice_window(r_lo, r_hi, c_lo, c_hi, level, shape):
    """(i0, i1, j0, j1): the first and last post rows and columns, on the lattice of sub-level
    ``level`` (spacing 2^-level posts), of the cells holding fractional indices [r_lo, r_hi] x
    [c_lo, c_hi], within the raster of ``shape`` (ny, nx), at least one cell."""
    ny, nx = shape
    scale = float(1 << level)
    i0 = int(math.floor(r_lo * scale))
    i1 = max(i0 + 1, min(int(math.ceil(r_hi * scale)), int((ny - 1) * scale)))
    i0 = min(i0, i1 - 1)
    j0 = int(math.floor(c_lo * scale))
    j1 = max(j0 + 1, min(int(math.ceil(c_hi * scale)), int((nx - 1) * scale)))
    j0 = min(j0, j1 - 1)
    return i0, i1, j0, j1


def _window_posts(lattice) -> int:
    """Posts of a :func:`_lattice_window`."""
    i0, i1, j0, j1 = lattice
    return (i1 - i0 + 1) * (j1 - j0 + 1)
