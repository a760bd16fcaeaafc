"""Bilinear kernel oracles: exact at posts, scipy agreement, wrapping, coverage."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator

from sortie.errors import InvalidArgument
from terrain.raster import (CRS_GEOGRAPHIC, CRS_WEB_MERCATOR, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE,
                            Georef, Raster)
from terrain.terrain import Terrain


def _raster(ny=33, nx=45, seed=0, x0=9.0, y0=47.0, d=1 / 1200, dtype=np.float32):
    h = np.random.default_rng(seed).normal(500.0, 200.0, (ny, nx)).astype(dtype)
    return Raster(h, Georef(CRS_GEOGRAPHIC, x0, y0, d, d))


def test_exact_at_posts_bit_for_bit():
    r = _raster(dtype=np.float64)
    rows, cols = np.meshgrid(np.arange(33), np.arange(45), indexing="ij")
    lat = 47.0 + rows.ravel() / 1200
    lon = 9.0 + cols.ravel() / 1200
    res = Terrain([r]).heights(lat, lon)
    assert np.array_equal(res.height_msl_m, r.heights[rows.ravel(), cols.ravel()])
    assert (res.status == STATUS_OK).all()


def test_matches_scipy_linear():
    r = _raster()
    rng = np.random.default_rng(3)
    lat = rng.uniform(47.0, 47.0 + 32 / 1200, 5000)
    lon = rng.uniform(9.0, 9.0 + 44 / 1200, 5000)
    ref = RegularGridInterpolator((47.0 + np.arange(33) / 1200, 9.0 + np.arange(45) / 1200),
                                  r.heights.astype(np.float64))(np.c_[lat, lon])
    # 1e-6 m: both are float64 bilinear; the only difference is rounding order.
    np.testing.assert_allclose(Terrain([r]).heights(lat, lon).height_msl_m, ref, atol=1e-6, rtol=0)


@settings(max_examples=200, deadline=None)
@given(fr=st.floats(0, 32), fc=st.floats(0, 44))
def test_bilinear_bounded_by_cell_corners(fr, fc):
    r = _raster()
    h = Terrain([r]).heights(47.0 + fr / 1200, 9.0 + fc / 1200).height_msl_m[0]
    i, j = min(int(fr), 31), min(int(fc), 43)
    corners = r.heights[i:i + 2, j:j + 2]
    assert corners.min() - 1e-9 <= h <= corners.max() + 1e-9


def test_outside_nan_holes_and_priority():
    a = _raster(seed=1)
    hole = np.array(a.heights)
    hole[10, 10] = np.nan
    a_holed = Raster(hole, a.georef)
    b = _raster(seed=2)
    t = Terrain([a_holed, b])
    lat = np.array([47.0 + 10 / 1200, 47.0 + 20 / 1200, 10.0])
    lon = np.array([9.0 + 10 / 1200, 9.0 + 20 / 1200, 10.0])
    res = t.heights(lat, lon)
    assert res.height_msl_m[0] == b.heights[10, 10]  # hole answered by the next source
    assert res.height_msl_m[1] == a.heights[20, 20]  # first source wins where it has data
    assert res.status[2] == STATUS_OUTSIDE and np.isnan(res.height_msl_m[2])


def test_height_at_and_heights_of_are_heights():
    """The one-point and few-point paths answer what the batch path answers, bit for bit:
    inside, on a hole, outside (NaN), with several sources (priority), and refuse what
    heights() refuses."""
    a = _raster(seed=1)
    hole = np.array(a.heights)
    hole[10, 10] = np.nan
    one, two = Terrain([Raster(hole, a.georef)]), Terrain([Raster(hole, a.georef), _raster(seed=2)])
    rng = np.random.default_rng(3)
    lat = np.concatenate([rng.uniform(46.99, 47.03, 300), [47.0 + 10 / 1200, 10.0, 47.01]])
    lon = np.concatenate([rng.uniform(8.99, 9.04, 300), [9.0 + 10 / 1200, 10.0, 369.01]])
    for t in (one, two):
        want = t.heights(lat, lon).height_msl_m
        got = np.array([t.height_at(float(a_), float(b_)) for a_, b_ in zip(lat, lon)])
        assert np.array_equal(got, want, equal_nan=True)
        for k in range(0, lat.size, 11):  # heights_of, a few points at a time into the caller's array
            out = np.full(11, 7.0)[:lat[k:k + 11].size]
            assert t.heights_of(lat[k:k + 11], lon[k:k + 11], out) is out
            assert np.array_equal(out, want[k:k + 11], equal_nan=True)
    assert np.isnan(one.height_at(47.0 + 10 / 1200, 9.0 + 10 / 1200))
    assert not np.isnan(two.height_at(47.0 + 10 / 1200, 9.0 + 10 / 1200))
    for lat_, lon_, field in ((91.0, 9.0, "lat"), (47.0, float("nan"), "lon"), (float("inf"), 9.0, "lat")):
        with pytest.raises(InvalidArgument, match=field):
            one.height_at(lat_, lon_)
        with pytest.raises(InvalidArgument, match=field):
            one.heights_of(np.array([47.0, lat_]), np.array([9.0, lon_]), np.empty(2))


def test_height_at_scalar_path_is_the_batch_path_everywhere():
    """Raster.height_at (one compiled call with scalars, what Terrain.height_at takes for a
    single raster) against the batch kernel, bit for bit: on posts, on the last row and
    column, just inside and outside the edges, beside holes and filled voids, wrapped
    longitudes, and on a Web Mercator raster."""
    from terrain.geodesy import web_mercator_inverse

    base = _raster(ny=21, nx=27, seed=5, dtype=np.float64)
    h = np.array(base.heights)
    h[4, 6] = np.nan
    filled = np.zeros(h.shape, bool)
    filled[9, 9] = filled[20, 26] = True
    geo = Raster(h, base.georef, filled=filled)
    merc = Raster(h, Georef(CRS_WEB_MERCATOR, 1.0e6, 5.9e6, 90.0, 90.0))
    rng = np.random.default_rng(11)
    for r in (geo, merc):
        rows = np.concatenate([np.repeat(np.arange(21.0), 27), rng.uniform(-0.5, 20.5, 2000),
                               [0.0, 20.0, 20.0, 1e-12, 20.0 - 1e-12, 4.0, 4.5, 9.0, 19.9]])
        cols = np.concatenate([np.tile(np.arange(27.0), 21), rng.uniform(-0.5, 26.5, 2000),
                               [0.0, 26.0, 26.0 - 1e-12, 26.0, 1e-12, 6.0, 6.0, 9.5, 25.9]])
        x, y = r.georef.post_xy(rows, cols)
        lat, lon = (y, x) if r.georef.crs == CRS_GEOGRAPHIC else web_mercator_inverse(x, y)
        if r is geo:
            lat = np.concatenate([lat, [47.0 + 3 / 1200]])
            lon = np.concatenate([lon, [9.0 + 5 / 1200 + 360.0]])  # wraps onto the grid
        want = Terrain([r]).heights(lat, lon).height_msl_m
        got = np.array([r.height_at(float(a_), float(b_)) for a_, b_ in zip(lat, lon)])
        assert np.array_equal(got, want, equal_nan=True)
        assert np.isnan(got).any() and np.isfinite(got).sum() > 500
        one = Terrain([r])
        assert np.array_equal([one.height_at(float(a_), float(b_)) for a_, b_ in zip(lat, lon)], want,
                              equal_nan=True)


def test_filled_status():
    r = _raster()
    filled = np.zeros(r.shape, bool)
    filled[5, 5] = True
    t = Terrain([Raster(np.array(r.heights), r.georef, filled=filled)])
    res = t.heights([47.0 + 5.5 / 1200, 47.0 + 20 / 1200], [9.0 + 4.5 / 1200, 9.0 + 20 / 1200])
    assert list(res.status) == [STATUS_FILLED, STATUS_OK]


def test_antimeridian_wrap():
    # A raster from 179.5 E eastwards across 180 answers for -179.9 and 180.1 alike.
    r = _raster(ny=11, nx=13, x0=179.5, y0=0.0, d=0.1)
    t = Terrain([r])
    a = t.heights([0.5, 0.5], [-179.9, 180.1])
    assert a.height_msl_m[0] == pytest.approx(a.height_msl_m[1], abs=1e-9)
    assert (a.status == STATUS_OK).all()
    assert t.heights([0.5], [179.4]).status[0] == STATUS_OUTSIDE


def test_web_mercator_raster_posts():
    from terrain.geodesy import web_mercator_inverse

    h = np.arange(20, dtype=np.float32).reshape(4, 5)
    g = Georef(CRS_WEB_MERCATOR, -12601676.0, 4300000.0, 76.4, 76.4)
    lat, lon = web_mercator_inverse(-12601676.0 + 3 * 76.4, 4300000.0 + 2 * 76.4)
    assert Terrain([Raster(h, g)]).heights(lat, lon).height_msl_m[0] == pytest.approx(h[2, 3], abs=1e-6)


def test_normals_of_a_plane():
    # h = 0.01 * east metres: slope atan(0.01), normal (-0.01, 0, 1)/|.|.
    g = Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1 / 1200, 1 / 1200)
    r0 = Raster(np.zeros((3, 3)), g)
    ex, _ = r0.post_spacing_m
    cols = np.arange(50)
    h = np.tile(0.01 * cols * ex, (50, 1))
    t = Terrain([Raster(h, g)])
    res = t.normals([47.02], [9.02])
    # 1e-4 rel: the east spacing varies with latitude across the raster (cos lat).
    assert res.slope_deg[0] == pytest.approx(np.degrees(np.arctan(0.01)), rel=1e-3)
    np.testing.assert_allclose(res.normal_enu[0], np.array([-0.01, 0, 1]) / np.hypot(0.01, 1), atol=1e-4)


@pytest.mark.parametrize("lat,lon,field", [([np.nan], [0.0], "lat[0]"), ([0.0, 91.0], [0.0, 0.0], "lat[1]"),
                                           ([0.0], [np.inf], "lon[0]"), ([0.0, 1.0], [0.0], "lon")])
def test_bad_input_names_field_and_index(lat, lon, field):
    with pytest.raises(InvalidArgument, match=field.replace("[", r"\[").replace("]", r"\]")):
        Terrain([_raster()]).heights(lat, lon)


def test_post_beside_a_hole_keeps_its_value():
    # Zero-weight corners are not read: a post next to a NaN hole or a filled
    # void answers with its own value and status.
    r = _raster(dtype=np.float64)
    h = np.array(r.heights)
    h[5, 6] = np.nan
    h[6, 5] = np.nan
    res = Terrain([Raster(h, r.georef)]).heights([47.0 + 5 / 1200, 47.0 + 5.5 / 1200], [9.0 + 5 / 1200, 9.0 + 5 / 1200])
    assert res.height_msl_m[0] == h[5, 5] and res.status[0] == STATUS_OK
    assert res.status[1] == STATUS_OUTSIDE  # between a post and a hole: no data


@pytest.mark.parametrize("crs, table", [(CRS_GEOGRAPHIC, False), (CRS_WEB_MERCATOR, False),
                                        (CRS_WEB_MERCATOR, True)])
def test_chunked_fast_path_matches_the_careful_path(crs, table):
    """bilinear_into's vectorised path and its per-point path answer every point identically:
    posts, near-posts within the snap tolerance, edges, wrapped longitudes, holes, filled voids,
    points already answered, across chunk boundaries (a Web Mercator raster's northings
    computed, or read from its table as Raster's kernels read them)."""
    from terrain.raster import _bilinear_point, bilinear_into, fractional_index_tab, mercator_row_table

    rng = np.random.default_rng(7)
    ny, nx = 41, 57
    h = rng.normal(500.0, 200.0, (ny, nx)).astype(np.float32)
    h[rng.random((ny, nx)) < 0.03] = np.nan
    filled = (rng.random((ny, nx)) < 0.05).astype(np.uint8)
    g = (Georef(CRS_GEOGRAPHIC, 179.98, -10.0, 1 / 1200, 1 / 1200) if crs == CRS_GEOGRAPHIC
         else Georef(CRS_WEB_MERCATOR, 1.0e6, 5.0e6, 30.0, 30.0))
    n = 5000
    rows = np.concatenate([rng.uniform(-1, ny, n), rng.integers(0, ny, n).astype(float),
                           rng.integers(0, ny, n) + rng.choice([-1, 1], n) * rng.uniform(0, 3e-9, n)])
    cols = np.concatenate([rng.uniform(-1, nx, n), rng.integers(0, nx, n).astype(float),
                           rng.integers(0, nx, n) + rng.choice([-1, 1], n) * rng.uniform(0, 3e-9, n)])
    x, y = g.post_xy(rows, cols)
    if crs == CRS_GEOGRAPHIC:
        lat, lon = y, np.where(rng.random(x.size) < 0.3, x - 360.0, x)
    else:
        from terrain.geodesy import web_mercator_inverse
        lat, lon = web_mercator_inverse(x, y)
    lat, lon = np.ascontiguousarray(lat), np.ascontiguousarray(lon)
    answered = rng.random(lat.size) < 0.1
    for f in (None, filled):
        fa = np.zeros((0, 0), np.uint8) if f is None else f
        out = np.where(answered, -1.0, np.nan)
        status = np.where(answered, STATUS_OK, STATUS_OUTSIDE).astype(np.uint8)
        ytab = mercator_row_table(g, ny) if table else np.zeros(0)
        assert ytab.size > 0 or not table
        bilinear_into(h, fa, lat, lon, g.crs, g.x0, g.y0, g.dx, g.dy, ytab, out, status)
        ref = np.where(answered, -1.0, np.nan)
        ref_status = np.where(answered, STATUS_OK, STATUS_OUTSIDE).astype(np.uint8)
        for k in np.flatnonzero(~answered):
            r, c = fractional_index_tab(lat[k], lon[k], g.crs, g.x0, g.y0, g.dx, g.dy, ytab)
            _bilinear_point(h, fa, f is not None, r, c, ref, ref_status, k)
        np.testing.assert_array_equal(status, ref_status)
        np.testing.assert_array_equal(out, ref)
        assert (status == STATUS_OK).sum() > n and (status == STATUS_OUTSIDE).sum() > 100
        if f is not None:
            assert (status == STATUS_FILLED).sum() > 100


def test_warm_cache_only_when_the_batch_covers_the_raster_and_it_fits(monkeypatch):
    import terrain.raster as raster_module

    r = _raster()  # 33 x 45 float32: 93 cache lines
    lines = r.heights.nbytes // raster_module.CACHE_LINE_BYTES
    assert not r.warm_cache(lines // 2 - 1)  # too few points to touch most lines
    assert r.warm_cache(lines // 2 + 1)
    filled = np.zeros(r.shape, bool)
    filled[5, 5] = True
    assert Raster(np.array(r.heights), r.georef, filled=filled).warm_cache(lines)
    monkeypatch.setattr(raster_module, "WARM_MAX_BYTES", r.heights.nbytes - 1)
    assert not r.warm_cache(10 * lines)  # would not stay in the caches


def test_warm_terrain_answers_bit_for_bit_the_same(monkeypatch):
    """warm=True only brings posts into the caches: every source kind, holes,
    filled voids and points outside give the same answers as without it."""
    from terrain.detail import DetailedRaster
    from terrain.procedural import ProceduralTerrain

    warmed = []
    real_warm = Raster.warm_cache
    monkeypatch.setattr(Raster, "warm_cache", lambda self, n: warmed.append(real_warm(self, n)) or warmed[-1])

    base = _raster(ny=300, nx=400, seed=4)
    h = np.array(base.heights)
    h[100:103, 50:60] = np.nan
    filled = np.zeros(base.shape, bool)
    filled[200:210, 300:305] = True
    holed = Raster(h, base.georef, filled=filled)
    other = _raster(ny=300, nx=400, seed=5, x0=9.0 + 300 / 1200)
    t = Terrain([holed, DetailedRaster(other, seed=1), ProceduralTerrain(seed=3)])
    rng = np.random.default_rng(6)
    lat = rng.uniform(46.99, 47.0 + 310 / 1200, 200_000)
    lon = rng.uniform(8.99, 9.0 + 710 / 1200, 200_000)
    cold = t.heights(lat, lon)
    assert warmed == []
    warm = t.heights(lat, lon, warm=True)
    assert warmed == [True, True]  # the holed raster, then the detailed one under it
    assert np.array_equal(cold.height_msl_m, warm.height_msl_m, equal_nan=True)
    assert np.array_equal(cold.status, warm.status)
    assert {STATUS_OK, STATUS_FILLED} <= set(np.unique(cold.status).tolist())
    n_cold, n_warm = t.normals(lat, lon), t.normals(lat, lon, warm=True)
    assert np.array_equal(n_cold.normal_enu, n_warm.normal_enu, equal_nan=True)
    assert np.array_equal(n_cold.status, n_warm.status)


@pytest.mark.parametrize("dem", ["hgt_alps", "tif_grand_canyon", "asc_boulder"])
def test_lattice_queries_answer_as_the_points_queries(dem, request):
    """Terrain.height_grid / gradient_grid (a clipmap level's strips and normal maps: one index a
    row and a column) give the per-point answers bit for bit, on real DEMs (geographic and Web
    Mercator), at posts, between them and outside; with a second source behind a cropped first
    (the points the crop lacks go on to it), and with a first source that answers no lattice."""
    from types import SimpleNamespace

    from terrain.dem import read_dem

    r = read_dem(request.getfixturevalue(dem))
    g, b = r.georef, r.bounds
    crop = Raster(np.asarray(r.heights)[40:200, 30:300], Georef(g.crs, g.x0 + 30 * g.dx, g.y0 + 40 * g.dy, g.dx, g.dy))
    points_only = SimpleNamespace(heights_into=r.heights_into, gradient_into=r.gradient_into)
    rng = np.random.default_rng(4)
    for terrain in (Terrain([r]), Terrain([crop, r]), Terrain([points_only])):
        lat_rows = np.sort(np.r_[rng.uniform(b[0], b[2], 27), b[0] - 0.01, b[2] + 0.01])  # two rows outside
        lon_cols = np.r_[rng.uniform(b[1], b[3], 40), b[3] + 0.01]
        lat, lon = np.repeat(lat_rows, lon_cols.size), np.tile(lon_cols, lat_rows.size)
        grid, points = terrain.height_grid(lat_rows, lon_cols), terrain.heights(lat, lon)
        assert grid.height_msl_m.shape == (29, 41)
        assert np.array_equal(grid.height_msl_m.ravel(), points.height_msl_m, equal_nan=True)
        assert np.array_equal(grid.status.ravel(), points.status)
        assert (points.status == STATUS_OK).any() and (points.status == STATUS_OUTSIDE).any()
        for got, want in zip(terrain.gradient_grid(lat_rows, lon_cols), terrain.gradients(lat, lon)):
            assert np.array_equal(got.ravel(), want, equal_nan=True)
    # Exactly at posts, where the snap decides the cell.
    if g.crs == CRS_GEOGRAPHIC:
        rows, cols = g.y0 + np.arange(0, 200, 7) * g.dy, g.x0 + np.arange(0, 200, 5) * g.dx
        assert np.array_equal(Terrain([r]).height_grid(rows, cols).height_msl_m,
                              np.asarray(r.heights, np.float64)[0:200:7, 0:200:5])
    with pytest.raises(InvalidArgument, match="column lon"):
        Terrain([r]).height_grid([b[0]], [np.nan])
    with pytest.raises(InvalidArgument, match="row lat"):
        Terrain([r]).gradient_grid([91.0], [b[1]])


def test_normals_from_gradients_matches_the_plane_normal_and_slope():
    """The compiled pass against the numpy composition it replaced: unit (-de, -dn, 1)
    normals bit for bit, slopes to rounding, NaN where a gradient is NaN; flat ground is
    (0, 0, 1) at 0 degrees, a 45-degree ramp east is (-1, 0, 1)/sqrt(2) at 45."""
    from terrain.raster import normals_from_gradients

    rng = np.random.default_rng(8)
    de, dn = rng.normal(0, 0.7, 5000), rng.normal(0, 0.7, 5000)
    de[:3], dn[:3] = [0.0, 1.0, np.nan], [0.0, 0.0, 0.2]
    normal, slope = np.empty((5000, 3)), np.empty(5000)
    normals_from_gradients(de, dn, normal, slope)
    want = np.stack([-de, -dn, np.ones_like(de)], axis=-1)
    want /= np.linalg.norm(want, axis=-1, keepdims=True)
    np.testing.assert_array_equal(normal, want)
    np.testing.assert_allclose(slope, np.degrees(np.arctan(np.hypot(de, dn))), rtol=1e-14, atol=1e-13)
    np.testing.assert_array_equal(normal[0], [0.0, 0.0, 1.0])
    assert slope[0] == 0.0 and slope[1] == pytest.approx(45.0, abs=1e-12)
    np.testing.assert_allclose(normal[1], [-np.sqrt(0.5), 0.0, np.sqrt(0.5)], rtol=0, atol=1e-15)
    assert np.isnan(normal[2]).all() and np.isnan(slope[2])


# A Web Mercator raster's kernels read its rows from a cubic Hermite table (mercator_row_table):
# against the projection in long double, within MERCATOR_TABLE_TOLERANCE_ROWS (1e-10) plus rounding.
# The float64 formula itself errs up to 2.5e-8 of a 1 m row at 84.9 degrees (its logarithm of a
# rounded tangent), so the table snaps every post's latitude to its row where the formula does not.
TABLE_BOUND_ROWS = 2e-10


@pytest.mark.parametrize("lat_south, dy, rows", [(36.0, 76.437, 512), (-0.5, 30.0, 4000), (80.0, 10.0, 6000),
                                                 (84.9, 1.0, 2000), (-85.0, 30.0, 3000), (-60.0, 300.0, 9000)])
def test_the_mercator_table_gives_the_projections_rows(lat_south, dy, rows):
    from terrain.geodesy import WGS84_A_M, web_mercator_forward, web_mercator_inverse
    from terrain.raster import fractional_index, fractional_index_tab, mercator_row_table

    y0 = float(web_mercator_forward(lat_south, 0.0)[1])
    g = Georef(CRS_WEB_MERCATOR, -2.0e6, y0, 25.0, dy)
    ytab = mercator_row_table(g, rows)
    assert ytab.size >= 6
    rng = np.random.default_rng(3)
    r = np.concatenate([rng.uniform(-1.5, rows + 0.5, 20000), np.arange(rows, dtype=float)])
    lat, lon = web_mercator_inverse(np.full(r.size, -1.9e6), y0 + r * dy)
    ld = np.longdouble
    truth = (ld(WGS84_A_M) * np.log(np.tan(ld(np.pi) / 4 + np.radians(lat.astype(ld)) / 2)) - ld(y0)) / ld(dy)
    exact = np.array([fractional_index(a, b, g.crs, g.x0, g.y0, g.dx, g.dy) for a, b in zip(lat, lon)])
    tab = np.array([fractional_index_tab(a, b, g.crs, g.x0, g.y0, g.dx, g.dy, ytab) for a, b in zip(lat, lon)])
    np.testing.assert_array_equal(tab[:, 1], exact[:, 1])
    assert float(np.max(np.abs(tab[:20000, 0] - truth[:20000]))) <= TABLE_BOUND_ROWS
    # A post's latitude snaps to its row, where float64 latitudes can say the post to 5e-10 rows
    # (not at 84.9 degrees with 1 m rows: an ulp of the latitude is 1.8e-8 of a row there).
    post = np.abs(truth[20000:] - np.arange(rows)) < 5e-10
    assert post.any() or lat_south == 84.9
    np.testing.assert_array_equal(tab[20000:, 0][post], np.arange(rows)[post])


def test_the_mercator_table_is_empty_where_it_would_not_pay():
    from terrain.raster import MERCATOR_TABLE_MAX_NODES, fractional_index, fractional_index_tab, mercator_row_table

    assert mercator_row_table(Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1 / 1200, 1 / 1200), 1201).size == 0
    # The whole Web Mercator square at 1 mm posts would need more than MERCATOR_TABLE_MAX_NODES.
    whole = Georef(CRS_WEB_MERCATOR, -20037508.34, -20037508.34, 0.001, 0.001)
    assert mercator_row_table(whole, 40_075_016_686).size == 0
    assert 0 < mercator_row_table(Georef(CRS_WEB_MERCATOR, -20037508.34, -20037508.34, 30.0, 30.0),
                                  1_335_835).size <= 2 + 2 * MERCATOR_TABLE_MAX_NODES
    assert MERCATOR_TABLE_MAX_NODES >= 1 << 16
    # Without a table, and beyond the projection's latitude, the exact answer (NaN beyond it).
    for lat in (40.0, 85.06, -89.0, float("nan")):
        a = fractional_index(lat, 3.0, whole.crs, whole.x0, whole.y0, whole.dx, whole.dy)
        b = fractional_index_tab(lat, 3.0, whole.crs, whole.x0, whole.y0, whole.dx, whole.dy, np.zeros(0))
        np.testing.assert_array_equal(np.array(a), np.array(b))


def test_mercator_heights_read_through_the_table_match_the_projection():
    """Raster.heights_into over a Web Mercator raster (its table) against the same bilinear surface
    at the float64 formula's index: within what 1e-9 rows move a height."""
    from terrain.geodesy import web_mercator_forward
    from terrain.raster import _bilinear_point, fractional_index

    rng = np.random.default_rng(11)
    ny, nx = 300, 200
    h = rng.normal(1500.0, 400.0, (ny, nx))
    g = Georef(CRS_WEB_MERCATOR, -1.26e7, float(web_mercator_forward(36.0, 0.0)[1]), 76.4, 76.4)
    raster = Raster(h, g)
    lat0, lon0, lat1, lon1 = raster.bounds
    lat = rng.uniform(lat0, lat1, 5000)
    lon = rng.uniform(lon0, lon1, 5000)
    out, status = np.full(lat.size, np.nan), np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    raster.heights_into(lat, lon, out, status)
    ref, ref_status = np.full(lat.size, np.nan), np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    for k in range(lat.size):
        r, c = fractional_index(lat[k], lon[k], g.crs, g.x0, g.y0, g.dx, g.dy)
        _bilinear_point(h, np.zeros((0, 0), np.uint8), False, r, c, ref, ref_status, k)
    np.testing.assert_array_equal(status, ref_status)
    steepest = np.max(np.abs(np.diff(h, axis=0)))
    assert np.max(np.abs(out - ref)) <= 1e-9 * steepest + 1e-9  # rows within 1e-9 of the formula's
    for k in range(0, lat.size, 97):  # one point alone, as height_at answers it: bit for bit
        assert raster.height_at(lat[k], lon[k]) == out[k]
