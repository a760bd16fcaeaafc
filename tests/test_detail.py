"""Fractal detail under a real DEM: exact posts, continuity, determinism, residual statistics."""

import math

import numpy as np
import pytest

from terrain.detail import (NOISE_TABLE_SIZE, DetailedRaster, detail_noise, fit_sub_level_std, level_residuals,
                            noise_table, pyramid_residual_variance)
from terrain.procedural import ProceduralTerrain, lattice_hash
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, STATUS_OUTSIDE, Georef, Raster, metres_per_index
from terrain.terrain import Terrain

SPACING_DEG = 1 / 1200  # SRTM3: 3 arc-seconds


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Raster:
    # Read independently of terrain.dem: big-endian int16, north row first; N47E009 has no voids.
    h = np.fromfile(hgt_alps, ">i2").reshape(1201, 1201)[::-1].astype(np.float32)
    return Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, SPACING_DEG, SPACING_DEG), name="N47E009")


@pytest.fixture(scope="module")
def detailed(alps) -> DetailedRaster:
    return DetailedRaster(alps, seed=2024, finest_spacing_m=1.0)


def test_noise_table_is_standard_normal():
    g = noise_table()
    assert g.shape == (NOISE_TABLE_SIZE,)
    # 1e-12: mean and variance are normalised exactly, up to summation rounding.
    assert abs(g.mean()) < 1e-12 and abs(g.var() - 1.0) < 1e-12
    assert np.all(np.diff(g) > 0)  # quantiles, so the hash picks each value equally often


def test_residuals_oracle_plane_and_white_noise():
    r, c = np.mgrid[0:65, 0:65].astype(np.float64)
    # A plane is reproduced by bilinear subdivision: residuals 0 up to rounding (1e-9 m at 1e3 m).
    assert np.abs(level_residuals(3.0 * r - 2.0 * c + 1000.0)).max() < 1e-9
    # White noise of variance s^2: an edge midpoint's residual has variance s^2 (1 + 2/4), a
    # centre's s^2 (1 + 4/16); the new posts are 2/3 edges and 1/3 centres -> 17/12 s^2.
    z = np.random.default_rng(0).normal(0.0, 2.0, (801, 801))
    v = pyramid_residual_variance(z)[0]
    # 2 %: about 480 000 residuals, partly correlated, give a relative spread near 0.3 %.
    assert v == pytest.approx(4.0 * 17 / 12, rel=0.02)


def test_residual_variance_ignores_voids():
    z = np.random.default_rng(1).normal(0.0, 1.0, (65, 65))
    z[10:20, 10:20] = np.nan
    v = pyramid_residual_variance(z)
    assert v.size >= 3 and np.isfinite(v).all()


def test_fit_extrapolates_log_linear_decay(alps, detailed):
    # Independent oracle of the fit: the DEM's own residual variances, a line through log2 of
    # the 4 finest, evaluated at levels -1..-K.
    var = []
    z = alps.heights.astype(np.float64)
    for _ in range(4):
        res = level_residuals(z)
        var.append(res.var())
        z = z[::2, ::2]
    slope, icpt = np.polyfit(np.arange(4.0), np.log2(var), 1)
    k = np.arange(1, detailed.sub_levels + 1)
    # 1e-9 relative: the same arithmetic up to rounding.
    np.testing.assert_allclose(detailed.level_std_m, np.sqrt(2.0 ** (icpt - slope * k)), rtol=1e-9)
    # 92.6 m north spacing down to 1 m takes ceil(log2(92.6)) = 7 halvings.
    assert detailed.sub_levels == 7
    assert np.all(np.diff(detailed.level_std_m) < 0)  # finer levels are quieter
    std, _, beta = fit_sub_level_std(np.array([4.0, 2.0, 1.0]), 2)
    assert beta == 0.0 and np.allclose(std, 2.0)  # variance growing toward finer levels is clamped


def test_exact_at_every_real_post(alps, detailed):
    rows, cols = np.meshgrid(np.arange(1201), np.arange(1201), indexing="ij")
    res = Terrain([detailed]).heights(47.0 + rows.ravel() * SPACING_DEG, 9.0 + cols.ravel() * SPACING_DEG)
    assert np.array_equal(res.height_msl_m, alps.heights.ravel().astype(np.float64))
    assert (res.status == STATUS_OK).all()


def test_detail_deterministic_and_seed_dependent(alps, detailed):
    rng = np.random.default_rng(3)
    lat, lon = rng.uniform(47.2, 47.8, 5000), rng.uniform(9.2, 9.8, 5000)
    a = Terrain([detailed]).heights(lat, lon).height_msl_m
    b = Terrain([DetailedRaster(alps, seed=2024)]).heights(lat, lon).height_msl_m
    c = Terrain([DetailedRaster(alps, seed=2025)]).heights(lat, lon).height_msl_m
    assert np.array_equal(a, b)
    assert np.mean(a != c) > 0.99


def test_detail_matches_hash_oracle_at_half_posts(detailed):
    # At the level-1 lattice post (2 i + 1, 2 j) only level 1 is non-zero: std_1 times the
    # table value the counter hash picks (global indices: 47 deg * 1200 * 2, 9 deg * 1200 * 2).
    i, j = np.array([100, 500, 900]), np.array([17, 333, 1000])
    gi, gj = 2 * (56400 + i) + 1, 2 * (10800 + j)
    want = detailed.level_std_m[0] * noise_table()[
        (lattice_hash(2024, np.int64(1), gi, gj) & np.uint64(NOISE_TABLE_SIZE - 1)).astype(np.intp)]
    got = detailed.detail_at_index(i + 0.5, j.astype(np.float64))[0]
    # 1e-12 m: a sum of exact zeros and one product.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("level", range(1, 8))
def test_synthesised_residuals_match_target_std(detailed, level):
    # Sample the surface on the level-k lattice (201 x 201 posts, 100 level-(k-1) cells a side)
    # and predict it from the level-(k-1) posts: base and coarser noise are bilinear there and
    # finer noise is 0 at these posts, so the residuals are exactly level k's noise values.
    scale = 2**level
    i, j = np.meshgrid(np.arange(201), np.arange(201), indexing="ij")
    r0, c0 = 300.0, 700.0
    lat = 47.0 + (r0 + i.ravel() / scale) * SPACING_DEG
    lon = 9.0 + (c0 + j.ravel() / scale) * SPACING_DEG
    z = Terrain([detailed]).heights(lat, lon).height_msl_m.reshape(201, 201)
    res = level_residuals(z)
    target = detailed.level_std_m[level - 1]
    n = res.size  # 30 000 independent Gaussian draws
    # 3 %: the sample std of n = 30 000 normals has relative spread 1/sqrt(2n) = 0.4 %.
    assert res.std() == pytest.approx(target, rel=0.03)
    # Zero mean: within 5 standard errors (5 / sqrt(n) = 3 % of the std).
    assert abs(res.mean()) < 5.0 * target / math.sqrt(n)


def test_detail_is_zero_mean_over_the_tile(alps, detailed):
    rng = np.random.default_rng(4)
    lat, lon = rng.uniform(47.01, 47.99, 200_000), rng.uniform(9.01, 9.99, 200_000)
    d = Terrain([detailed]).heights(lat, lon).height_msl_m - Terrain([alps]).heights(lat, lon).height_msl_m
    # 0.05 m: the mean of 2e5 samples of detail with std ~2.4 m (5 standard errors), noise being
    # independent between the ~4e6 level-1 posts they sample.
    assert abs(d.mean()) < 0.05 and 1.0 < d.std() < detailed.level_std_m[0]


def test_continuous_across_every_lattice_line(alps, detailed):
    # Points on level-k lattice lines (k = 0..7), stepped 1e-9 posts to either side.
    rng = np.random.default_rng(5)
    k = rng.integers(0, 8, 3000)
    r = rng.integers(10, 1190 * 2**k) / 2.0**k
    c = rng.uniform(10, 1190, 3000)
    r, c = np.where(k % 2 == 0, r, c), np.where(k % 2 == 0, c, r)  # lines of both directions
    eps = 1e-9
    t = Terrain([detailed])
    lo = t.heights(47.0 + (r - eps) * SPACING_DEG, 9.0 + (c - eps) * SPACING_DEG).height_msl_m
    hi = t.heights(47.0 + (r + eps) * SPACING_DEG, 9.0 + (c + eps) * SPACING_DEG).height_msl_m
    # Lipschitz bound per post: the steepest base post difference plus, for each level k,
    # 2^k * 2 * max|table| * std_k (a bilinear cell's slope is at most its corner spread).
    base = max(np.abs(np.diff(alps.heights.astype(np.float64), axis=ax)).max() for ax in (0, 1))
    lips = base + sum(2.0**lv * 2 * np.abs(noise_table()).max() * s
                      for lv, s in enumerate(detailed.level_std_m, start=1))
    # The step moves each index by 2 eps; plus 1e-9 m of rounding in the degree <-> index maps.
    assert np.abs(hi - lo).max() <= lips * 2 * (2 * eps) + 1e-9 * lips + 1e-9


def test_gradient_matches_finite_differences(detailed):
    rng = np.random.default_rng(6)
    fine = 2.0**-detailed.sub_levels
    # Points inside finest-level cells (away from their edges), where the surface is bilinear.
    r = (rng.integers(20 * 128, 1180 * 128, 500) + rng.uniform(0.2, 0.8, 500)) * fine
    c = (rng.integers(20 * 128, 1180 * 128, 500) + rng.uniform(0.2, 0.8, 500)) * fine
    lat, lon = 47.0 + r * SPACING_DEG, 9.0 + c * SPACING_DEG
    t = Terrain([detailed])
    n = t.normals(lat, lon).normal_enu
    de, dn = -n[:, 0] / n[:, 2], -n[:, 1] / n[:, 2]
    step = 1e-3 * fine * SPACING_DEG
    mx, my = metres_per_index(CRS_GEOGRAPHIC, step, step, lat)
    h = lambda la, lo: t.heights(la, lo).height_msl_m  # noqa: E731
    fd_e = (h(lat, lon + step) - h(lat, lon - step)) / (2 * mx)
    fd_n = (h(lat + step, lon) - h(lat - step, lon)) / (2 * my)
    # rtol 1e-4: exact for a bilinear cell along each axis; heights of ~1e3 m carry 1e-13 m of
    # rounding over steps of ~5e-4 m, and slopes are ~0.01 to 10.
    np.testing.assert_allclose(de, fd_e, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(dn, fd_n, rtol=1e-4, atol=1e-6)


def test_densified_raster_for_matches_queries(detailed):
    box = (47.5, 9.5, 47.505, 9.506)
    dense = detailed.raster_for(*box)
    assert dense.meta["detail_levels"] == detailed.sub_levels
    assert dense.georef.dx == pytest.approx(SPACING_DEG / 2**detailed.sub_levels, rel=1e-15)
    rng = np.random.default_rng(7)
    lat, lon = rng.uniform(box[0], box[2], 20_000), rng.uniform(box[1], box[3], 20_000)
    # 1e-6 m: the densified posts carry the exact detailed surface; index rounding only.
    np.testing.assert_allclose(Terrain([dense]).heights(lat, lon).height_msl_m,
                               Terrain([detailed]).heights(lat, lon).height_msl_m, rtol=0, atol=1e-6)
    big = detailed.raster_for(47.1, 9.1, 47.9, 9.9)
    assert 0 < big.meta["detail_levels"] < detailed.sub_levels and big.meta["omitted_detail_std_m"] > 0
    assert big.heights.size <= 1 << 22
    assert detailed.raster_for(46.0, 9.1, 46.1, 9.2) is None
    assert detailed.describe()["kind"] == "dem+detail"


def test_neighbouring_tiles_agree_on_their_shared_edge(alps):
    # Split the tile at column 600 into two rasters sharing that column; with one shared fit
    # the detail along the seam comes from the same global lattice on both sides.
    h = alps.heights
    west = Raster(h[:, :601], Georef(CRS_GEOGRAPHIC, 9.0, 47.0, SPACING_DEG, SPACING_DEG))
    east = Raster(h[:, 600:], Georef(CRS_GEOGRAPHIC, 9.5, 47.0, SPACING_DEG, SPACING_DEG))
    dw = DetailedRaster(west, seed=1)
    de = DetailedRaster(east, seed=1, level_std_m=dw.level_std_m)
    lat = 47.0 + np.random.default_rng(8).uniform(1, 1199, 5000) * SPACING_DEG
    lon = np.full(5000, 9.5)
    a = Terrain([dw]).heights(lat, lon).height_msl_m
    b = Terrain([de]).heights(lat, lon).height_msl_m
    # 1e-9 m: identical lattice values; the row index is computed from the same y0.
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert np.abs(a - Terrain([west]).heights(lat, lon).height_msl_m).max() > 0.1  # detail is there


def test_antimeridian_raster_and_fallback_to_procedural():
    z = np.random.default_rng(9).normal(100.0, 30.0, (121, 121))
    r = Raster(z, Georef(CRS_GEOGRAPHIC, 179.95, -0.05, SPACING_DEG, SPACING_DEG))
    d = DetailedRaster(r, seed=3)
    t = Terrain([d, ProceduralTerrain(3)])
    res = t.heights([0.0123, 0.0123, 10.0], [180.0123, -179.9877, 10.0])
    # 1e-6 m: the same point written two ways; the raster wraps longitude.
    assert res.height_msl_m[0] == pytest.approx(res.height_msl_m[1], abs=1e-6)
    assert (res.status != STATUS_OUTSIDE).all()
    assert d.col_period == 432_000  # 360 deg / 3 arc-seconds


def test_voids_stay_holes(alps):
    h = np.array(alps.heights[:65, :65])
    h[30, 30] = np.nan
    d = DetailedRaster(Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, SPACING_DEG, SPACING_DEG)), seed=1)
    res = Terrain([d]).heights([47.0 + 30.25 * SPACING_DEG, 47.0 + 10.25 * SPACING_DEG],
                               [9.0 + 30.5 * SPACING_DEG, 9.0 + 10.5 * SPACING_DEG])
    assert res.status.tolist() == [STATUS_OUTSIDE, STATUS_OK] and np.isnan(res.height_msl_m[0])


def test_detail_noise_checks_shapes():
    with pytest.raises(ValueError, match=r"\(3,\).*\(2,\)"):
        detail_noise(np.zeros(3), np.zeros(2), [1.0], 0, (4, 4))
