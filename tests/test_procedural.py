"""Procedural midpoint-displacement terrain: formula oracle, determinism, seams, cache, wrap, poles, water."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.procedural import (RASTER_FOR_MAX_POSTS, ProceduralTerrain, height_bounds_m, lattice_hash,
                                lattice_uniform, midpoint_displacement, mix64)
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, Georef, Raster, metres_per_index
from terrain.terrain import Terrain

U64 = (1 << 64) - 1

# A small world so that poles and the antimeridian are a few blocks away:
# 16-cell blocks, 64 blocks around, 32 from pole to pole.
SMALL = dict(block_cells=16, posts_per_turn=1024)


def _mix64_reference(x: int) -> int:
    """SplitMix64 in plain Python integers (Steele et al. 2014)."""
    z = (x + 0x9E3779B97F4A7C15) & U64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & U64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & U64
    return z ^ (z >> 31)


def test_hash_known_answers():
    # SplitMix64 seeded with 0 first outputs 0xE220A8397B1DCDAF (reference C implementation).
    assert int(mix64(np.uint64(0))) == 0xE220A8397B1DCDAF
    rows = np.array([0, 5, -3, 2**40], dtype=np.int64)
    got = lattice_hash(11, rows, np.int64(7))
    want = [_mix64_reference(_mix64_reference(_mix64_reference(11) ^ (r & U64)) ^ 7) for r in rows.tolist()]
    assert got.tolist() == want
    u = lattice_uniform(11, rows, np.int64(7))
    assert ((u >= 0.0) & (u < 1.0)).all()


def test_formula_oracle_one_block_by_hand():
    m, e, w = 800.0, 1.7, 0.35
    p = ProceduralTerrain(42, max_height_m=m, level_exponent=e, water=w, block_cells=4, posts_per_turn=64)
    b = p.generate_block(3, 5)
    rows = 3 * 4 + np.arange(5)
    cols = 5 * 4 + np.arange(5)
    r = lattice_uniform(42, rows[:, None], cols[None, :])

    def disp(a_m, r_val, level):  # the paper's H = A + (R - W)(1 + A)^2 M / L^E with A in units of M
        return a_m + (r_val - w) * (1.0 + a_m / m) ** 2 * m / level**e

    want = np.full((5, 5), np.nan)
    for i in (0, 4):
        for j in (0, 4):
            want[i, j] = (r[i, j] - w) * m  # level 0: A = 0, L = 1
    want[2, 2] = disp(0.25 * (want[0, 0] + want[0, 4] + want[4, 0] + want[4, 4]), r[2, 2], 1)
    for i in (0, 4):
        want[i, 2] = disp(0.5 * (want[i, 0] + want[i, 4]), r[i, 2], 1)
    for j in (0, 4):
        want[2, j] = disp(0.5 * (want[0, j] + want[4, j]), r[2, j], 1)
    # Level 2: one centre and one edge midpoint, by hand.
    want_c = disp(0.25 * (want[0, 0] + want[0, 2] + want[2, 0] + want[2, 2]), r[1, 1], 2)
    want_e = disp(0.5 * (want[2, 2] + want[2, 4]), r[2, 3], 2)
    lvl1 = ~np.isnan(want)
    # 1e-9 m: the same formula, only normalised by M, so only rounding differs (heights < 1e4 m).
    np.testing.assert_allclose(b.bed_msl_m[lvl1], want[lvl1], rtol=0, atol=1e-9)
    assert b.bed_msl_m[1, 1] == pytest.approx(want_c, abs=1e-9)
    assert b.bed_msl_m[2, 3] == pytest.approx(want_e, abs=1e-9)


def test_roughness_factor_is_clamped():
    # All R = 0.99, W = 0: corners a = 0.99; level-1 posts a = 0.99 + 0.99 * 1.99^2 > 1, so
    # level 2 uses the clamped factor 2^2 = 4 instead of (1 + a)^2 > 20.
    u = np.full((5, 5), 0.99)
    a = midpoint_displacement(u, level_exponent=2.0, water=0.0)
    a1 = 0.99 + 0.99 * 1.99**2
    assert a[2, 2] == pytest.approx(a1, rel=1e-15)  # 1e-15: a couple of float64 roundings
    mean = 0.25 * (0.99 + 3.0 * a1)  # level-2 centre: 1 corner and 3 level-1 posts
    assert a[1, 1] == pytest.approx(mean + 0.99 * 4.0 / 2.0**2, rel=1e-15)
    # Below a = -1 the paper's factor would grow again; clamped it is 0: no displacement.
    u = np.zeros((3, 3))
    u[1, 1] = 0.5
    a = midpoint_displacement(u, level_exponent=2.0, water=1.0)  # corners -1: factor 0
    assert a[1, 1] == -1.0 and a[0, 1] == -1.0


def test_unclamped_formula_diverges_where_the_clamped_one_is_bounded():
    # Why the guard: along the chain of centres with every R = 0.99, W = 0, E -> 1, the literal
    # a' = a + R (1 + a)^2 / L^E passes 1e50 within the 8 levels of a 256-cell block.
    e, a = 1.0001, 0.99
    for level in range(1, 9):
        a = a + 0.99 * (1.0 + a) ** 2 / level**e
    _, hi = height_bounds_m(1.0, e, 0.0, 256)
    assert a > 1e50 > hi
    clamped = midpoint_displacement(np.full((257, 257), 0.99), level_exponent=e, water=0.0)
    assert clamped.max() <= hi


@settings(max_examples=40, deadline=None)
@given(m=st.floats(1e-3, 1e4), e=st.floats(1.0001, 5.0), w=st.floats(0.0, 1.0),
       seed=st.integers(0, 2**64 - 1), cells=st.sampled_from([2, 16, 64]))
def test_heights_bounded_for_all_paper_parameters(m, e, w, seed, cells):
    p = ProceduralTerrain(seed, max_height_m=m, level_exponent=e, water=w, block_cells=cells, posts_per_turn=4096)
    lo, hi = height_bounds_m(m, e, w, cells)
    bed = p.generate_block(7, 9).bed_msl_m
    assert np.isfinite(bed).all()
    # 1e-12 * M: the bound is exact in real arithmetic; slack for float64 rounding only.
    assert bed.min() >= lo - 1e-12 * m and bed.max() <= hi + 1e-12 * m


def test_bound_covers_default_block_size_at_roughest_exponent():
    p = ProceduralTerrain(3, max_height_m=1000.0, level_exponent=1.0001, water=0.0)
    lo, hi = height_bounds_m(1000.0, 1.0001, 0.0, 256)
    bed = np.concatenate([p.generate_block(500, c).bed_msl_m.ravel() for c in range(4)])
    assert lo == 0.0 and bed.min() >= 0.0 and bed.max() <= hi


def test_deterministic_and_seed_sensitive():
    a, b, c = ProceduralTerrain(5), ProceduralTerrain(5), ProceduralTerrain(6)
    assert np.array_equal(a.generate_block(600, 1200).bed_msl_m, b.generate_block(600, 1200).bed_msl_m)
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(40.0, 40.5, 2000), rng.uniform(-3.0, -2.5, 2000)
    ha = Terrain([a]).heights(lat, lon).height_msl_m
    hb = Terrain([b]).heights(lat[::-1], lon[::-1]).height_msl_m[::-1]  # another order, same bits
    hc = Terrain([c]).heights(lat, lon).height_msl_m
    assert np.array_equal(ha, hb)
    assert np.mean(ha != hc) > 0.99  # a different seed changes nearly every point


@settings(max_examples=30, deadline=None)
@given(row=st.integers(0, 31), col=st.sampled_from([0, 1, 30, 62, 63]), order=st.permutations(range(9)))
def test_seamless_in_any_generation_order(row, col, order):
    p = ProceduralTerrain(77, water=0.4, cache_blocks=9, **SMALL)
    fresh = ProceduralTerrain(77, water=0.4, **SMALL)
    cells = [(row + dr, col + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
    got = {}
    for k in order:
        r, c = cells[k]
        if 0 <= r < p.block_rows:  # no blocks beyond the poles
            got[(r, c)] = p.block(r, c).bed_msl_m
            assert np.array_equal(got[(r, c)], fresh.generate_block(r, c).bed_msl_m)
    for (r, c), bed in got.items():
        east, north, ne = got.get((r, c + 1)), got.get((r + 1, c)), got.get((r + 1, c + 1))
        if east is not None:
            assert np.array_equal(bed[:, -1], east[:, 0])
        if north is not None:
            assert np.array_equal(bed[-1, :], north[0, :])
        if ne is not None:
            assert bed[-1, -1] == ne[0, 0]


def test_exact_at_posts_and_water_surface():
    p = ProceduralTerrain(8, water=0.5, **SMALL)
    b = p.block(20, 40)
    i, j = np.meshgrid(np.arange(17), np.arange(17), indexing="ij")
    lat = b.lat0_deg + i.ravel() * b.spacing_deg
    lon = b.lon0_deg + j.ravel() * b.spacing_deg
    res = Terrain([p]).heights(lat, lon)
    assert np.array_equal(res.height_msl_m, b.surface_msl_m.ravel())
    assert np.array_equal(b.surface_msl_m, np.maximum(b.bed_msl_m, 0.0))
    assert (b.bed_msl_m < 0).any() and (res.height_msl_m >= 0).all() and (res.status == STATUS_OK).all()


def test_cache_bounded_and_regeneration_identical():
    p = ProceduralTerrain(9, cache_blocks=4, **SMALL)
    first = p.block(10, 10).bed_msl_m.copy()
    rng = np.random.default_rng(1)
    for _ in range(20):
        lat, lon = rng.uniform(-80, 80, 50), rng.uniform(-180, 180, 50)
        Terrain([p]).heights(lat, lon)
        assert len(p.cached_blocks()) <= 4
    assert p.blocks_generated > 4
    assert p.blocks_evicted == p.blocks_generated - len(p.cached_blocks())
    assert np.array_equal(p.block(10, 10).bed_msl_m, first)


def test_retain_near_drops_far_blocks():
    p = ProceduralTerrain(9, cache_blocks=64)  # default 257-post blocks of ~19.6 km
    Terrain([p]).heights([10.0, 10.0, 10.3, -40.0], [20.0, 20.3, 20.0, 100.0])
    before = set(p.cached_blocks())
    near = set(p.block_index(np.array([10.0, 10.0, 10.3]), np.array([20.0, 20.3, 20.0])))
    far = set(p.block_index(np.array([-40.0]), np.array([100.0])))
    far_bed = p.block(*next(iter(far))).bed_msl_m.copy()
    evicted = p.blocks_evicted
    dropped = p.retain_near([10.1], [20.1], 50_000.0)
    assert set(p.cached_blocks()) == near and near | far == before
    assert dropped == len(far) and p.blocks_evicted == evicted + dropped
    assert p.retain_near([], [], 1.0) == len(near) and not p.cached_blocks()  # no viewer: drop all
    assert np.array_equal(p.block(*next(iter(far))).bed_msl_m, far_bed)


def test_antimeridian_wraps_seamlessly():
    p = ProceduralTerrain(12, **SMALL)
    t = Terrain([p])
    lat = np.linspace(-60.0, 60.0, 101)
    h_east = t.heights(lat, np.full(101, 180.0)).height_msl_m
    h_west = t.heights(lat, np.full(101, -180.0)).height_msl_m
    h_wrap = t.heights(lat, np.full(101, 540.0)).height_msl_m
    assert np.isfinite(h_east).all() and np.array_equal(h_east, h_west) and np.array_equal(h_east, h_wrap)
    # Continuity across the seam: 1e-7 deg steps change the height by at most the steepest
    # lattice slope, max |post difference| per post spacing, times the step in posts.
    b_w, b_e = p.block(20, 63), p.block(20, 0)
    slope = max(np.abs(np.diff(b.surface_msl_m, axis=ax)).max() for b in (b_w, b_e) for ax in (0, 1))
    lat_s = b_w.lat0_deg + 3.3 * p.spacing_deg
    near = t.heights([lat_s, lat_s], [180.0 - 1e-7, -180.0 + 1e-7]).height_msl_m
    assert abs(near[0] - near[1]) <= 2 * slope * 1e-7 / p.spacing_deg + 1e-9
    box = p.raster_for(lat_s - 0.5, 179.0, lat_s + 0.5, -179.0)
    lon = np.linspace(179.0, 181.0, 301)
    lon = np.where(lon > 180.0, lon - 360.0, lon)
    la = np.full(301, lat_s + 0.123)
    # 1e-6 m: the same posts and bilinear rule; only index rounding differs.
    np.testing.assert_allclose(Terrain([box]).heights(la, lon).height_msl_m, t.heights(la, lon).height_msl_m,
                               rtol=0, atol=1e-6)


def test_poles_are_single_finite_heights():
    p = ProceduralTerrain(13, **SMALL)
    t = Terrain([p])
    lon = np.linspace(-180.0, 180.0, 77)
    for pole in (-90.0, 90.0):
        h = t.heights(np.full(77, pole), lon).height_msl_m
        assert np.isfinite(h).all() and (h == h[0]).all()
        n = t.normals(np.full(77, pole), lon)
        assert np.isfinite(n.normal_enu).all() and np.isfinite(n.slope_deg).all()
    near_pole = t.heights(np.full(77, 90.0 - 1e-9), lon).height_msl_m
    top = t.heights([90.0], [0.0]).height_msl_m[0]
    # 1e-9 deg from the pole is 1e-6 posts: heights within 1e-6 of the steepest post difference.
    steep = np.abs(np.diff(p.block(31, 0).surface_msl_m, axis=0)).max()
    assert np.abs(near_pole - top).max() <= steep * 1e-6 + 1e-9


def test_water_parameter_raises_sea_fraction():
    fractions = []
    for w in (0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0):
        p = ProceduralTerrain(21, water=w, block_cells=64)
        beds = [p.generate_block(1000 + i, 3000 + j).bed_msl_m for i in range(8) for j in range(8)]
        fractions.append(float(np.mean([(b < 0).mean() for b in beds])))
    # Exact at the ends: W = 0 never displaces downwards, W = 1 never upwards (R in [0, 1)).
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    # 0.005 per step: the measured steps are 0.03 to 0.33 with a seed-to-seed spread below 0.03
    # (64 blocks of 65^2 posts), so every step rises by far more than the spread allows to invert.
    assert all(b - a >= 0.005 for a, b in zip(fractions, fractions[1:])), fractions


def test_gradient_matches_finite_differences():
    p = ProceduralTerrain(14, **SMALL)
    t = Terrain([p])
    rng = np.random.default_rng(2)
    b = p.block(18, 7)
    fi = rng.uniform(0.1, 0.9, 200) + rng.integers(0, 16, 200)
    fj = rng.uniform(0.1, 0.9, 200) + rng.integers(0, 16, 200)
    lat, lon = b.lat0_deg + fi * b.spacing_deg, b.lon0_deg + fj * b.spacing_deg
    n = t.normals(lat, lon).normal_enu
    de, dn = -n[:, 0] / n[:, 2], -n[:, 1] / n[:, 2]
    step = 1e-4 * b.spacing_deg  # stays inside the cell, where the surface is bilinear
    mx, my = metres_per_index(CRS_GEOGRAPHIC, step, step, lat)
    h = lambda la, lo: t.heights(la, lo).height_msl_m  # noqa: E731
    fd_e = (h(lat, lon + step) - h(lat, lon - step)) / (2 * mx)
    fd_n = (h(lat + step, lon) - h(lat - step, lon)) / (2 * my)
    # rtol 1e-6: central differences are exact along each axis of a bilinear cell; what is
    # left is rounding of ~1e-13 m in heights over steps of ~1e-2 m.
    np.testing.assert_allclose(de, fd_e, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(dn, fd_n, rtol=1e-6, atol=1e-9)


def test_fills_behind_real_data_and_raster_for_limits():
    dem = Raster(np.full((3, 3), 1234.0), Georef(CRS_GEOGRAPHIC, 10.0, 45.0, 0.01, 0.01))
    p = ProceduralTerrain(15)
    res = Terrain([dem, p]).heights([45.01, 50.0], [10.01, 10.0])
    assert res.height_msl_m[0] == 1234.0 and np.isfinite(res.height_msl_m[1])
    with pytest.raises(LimitExceeded):
        p.raster_for(-10.0, -10.0, 10.0, 10.0)
    r = p.raster_for(89.99, 0.0, 90.0, 0.01)
    assert r.bounds[2] == 90.0 and r.shape[0] >= 2 and r.heights.size <= RASTER_FOR_MAX_POSTS
    assert p.describe()["kind"] == "procedural"


@pytest.mark.parametrize("kwargs", [dict(max_height_m=0.0), dict(level_exponent=1.0), dict(water=1.5),
                                    dict(block_cells=48), dict(posts_per_turn=1000), dict(cache_blocks=0),
                                    dict(max_height_m=math.nan)])
def test_rejects_parameters_outside_the_papers_ranges(kwargs):
    with pytest.raises(InvalidArgument):
        ProceduralTerrain(1, **kwargs)


def test_slopes_stay_bounded_towards_the_poles():
    """The lattice's columns crowd together towards a pole while the paper's displacements do not:
    unfaded, p99 slopes (rise over run) were 1.1 at 40-45 degrees, 32 at 88-89 (seed 7, default
    parameters). Beyond POLAR_FADE_LAT_DEG displacements fade with cos(lat): no band nearer the
    pole is steeper at its p99 than the band just below the fade, and each pole is one height
    at sea level."""
    from terrain.procedural import POLAR_FADE_LAT_DEG, polar_fade

    t = Terrain([ProceduralTerrain(7)])
    rng = np.random.default_rng(0)

    def p99_slope(lat0, lat1):
        lat, lon = rng.uniform(lat0, lat1, 4000), rng.uniform(10.0, 10.4, 4000)
        return float(np.percentile(np.tan(np.radians(t.normals(lat, lon).slope_deg)), 99))

    at_fade = p99_slope(POLAR_FADE_LAT_DEG - 1.0, POLAR_FADE_LAT_DEG)
    for band in ((80.0, 81.0), (85.0, 86.0), (88.0, 89.0), (89.5, 89.9), (-89.9, -89.5)):
        assert p99_slope(*band) <= at_fade, band
    assert np.all(polar_fade(np.linspace(-POLAR_FADE_LAT_DEG, POLAR_FADE_LAT_DEG, 1001)) == 1.0)  # no change there
    for pole in (-90.0, 90.0):
        h = t.heights(np.full(5, pole), np.linspace(-180.0, 180.0, 5)).height_msl_m
        assert np.unique(h).size == 1 and abs(h[0]) < 1e-6
