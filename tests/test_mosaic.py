"""Mosaic: split real tiles and put them back; gaps, priority, antimeridian, limits.

Oracle: the unsplit tile. A correct mosaic of its pieces is the same post
array on the same grid, so every query must agree bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from terrain.dem import read_geotiff, read_hgt, read_raw16
from terrain.mosaic import load_sources, mosaic
from terrain.raster import (
    CRS_GEOGRAPHIC,
    STATUS_FILLED,
    STATUS_OK,
    STATUS_OUTSIDE,
    Georef,
    Raster,
)
from terrain.terrain import Terrain

SRTM3 = 1.0 / 1200.0  # degrees between SRTM3 posts


def query(sources, lat, lon):
    result = Terrain(sources if isinstance(sources, list) else [sources]).heights(
        np.asarray(lat, float), np.asarray(lon, float))
    return result.height_msl_m, result.status


def piece(raster: Raster, r0: int, r1: int, c0: int, c1: int, heights=None) -> Raster:
    """Posts rows r0..r1, cols c0..c1 (inclusive, row 0 south) of raster as a new Raster."""
    g = raster.georef
    h = raster.heights[r0:r1 + 1, c0:c1 + 1] if heights is None else heights
    return Raster(h, Georef(g.crs, g.x0 + c0 * g.dx, g.y0 + r0 * g.dy, g.dx, g.dy),
                  name=f"{raster.name}[{r0}:{r1},{c0}:{c1}]", vertical_datum=raster.vertical_datum)


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Raster:
    return read_hgt(hgt_alps)


@pytest.fixture(scope="module")
def alps_corner(alps) -> Raster:
    """The tile's south-west 241 x 241 posts (a 0.2 degree square)."""
    return piece(alps, 0, 240, 0, 240)


def test_split_tile_mosaics_back_exactly(tmp_path, alps, hgt_alps):
    """N47E009 cut into 4 raw16 files that share the cut row and column."""
    cut_r, cut_c = 437, 611  # uneven cuts: sub-tile origins are not binary fractions
    south_up = np.fromfile(hgt_alps, dtype=">i2").reshape(1201, 1201)[::-1]
    tiles = []
    for r0, r1 in ((0, cut_r), (cut_r, 1200)):
        for c0, c1 in ((0, cut_c), (cut_c, 1200)):
            path = tmp_path / f"alps_{r0}_{c0}.raw"
            south_up[r0:r1 + 1, c0:c1 + 1][::-1].tofile(path)  # north row first, big-endian
            tiles.append(read_raw16(path, r1 - r0 + 1, c1 - c0 + 1, 47.0 + r0 * SRTM3, 9.0 + c0 * SRTM3,
                                    SRTM3, SRTM3))
    rng = np.random.default_rng(9)
    order = rng.permutation(4)
    merged = mosaic([tiles[k] for k in order])
    assert len(merged) == 1
    m = merged[0]
    assert m.georef == alps.georef  # exact: the origin is the SW piece's own 47.0, 9.0
    np.testing.assert_array_equal(m.heights, alps.heights)
    assert m.filled is None
    assert m.meta["overlap_posts"] > 0 and m.meta["overlap_disagreeing_posts"] == 0
    assert m.meta["gap_posts_filled"] == m.meta["gap_posts_outside"] == 0

    seam_lat, seam_lon = 47.0 + cut_r * SRTM3, 9.0 + cut_c * SRTM3
    n = 3000
    lat = np.concatenate([47.0 + rng.random(n), np.full(n, seam_lat), 47.0 + rng.random(n),
                          [seam_lat, seam_lat + 1e-12, seam_lat - 1e-12]])
    lon = np.concatenate([9.0 + rng.random(n), 9.0 + rng.random(n), np.full(n, seam_lon),
                          [seam_lon, seam_lon - 1e-12, seam_lon + 1e-12]])
    h_mosaic, status = query(m, lat, lon)
    h_tile, _ = query(alps, lat, lon)
    np.testing.assert_array_equal(h_mosaic, h_tile)  # exact: same posts, same grid, same kernel
    assert np.all(status == STATUS_OK)


def test_web_mercator_pieces_mosaic_back_exactly(tif_grand_canyon):
    canyon = read_geotiff(tif_grand_canyon)
    pieces = [piece(canyon, 0, 300, 0, 511), piece(canyon, 300, 511, 0, 200),
              piece(canyon, 300, 511, 200, 511)]
    merged = mosaic(pieces[::-1])
    assert len(merged) == 1
    # Origins are canyon.x0 + c0 * dx: equal to the tile's to a few ulp of 1.3e7 m.
    assert merged[0].georef.x0 == canyon.georef.x0 and merged[0].georef.y0 == canyon.georef.y0
    np.testing.assert_array_equal(merged[0].heights, canyon.heights)


def test_earlier_source_wins_and_disagreement_is_recorded(alps_corner):
    west = piece(alps_corner, 0, 240, 0, 150)
    east_posts = alps_corner.heights[:, 100:241] + np.float32(5.0)  # 5 m off over 51 shared columns
    east = piece(alps_corner, 0, 240, 100, 240, heights=east_posts)
    (m,) = mosaic([west, east])
    np.testing.assert_array_equal(m.heights[:, :151], alps_corner.heights[:, :151])
    np.testing.assert_array_equal(m.heights[:, 151:], east_posts[:, 51:])
    assert m.meta["overlap_posts"] == 241 * 51
    assert m.meta["overlap_disagreeing_posts"] == 241 * 51
    assert m.meta["overlap_max_abs_diff_m"] == 5.0
    (m2,) = mosaic([east, west])
    np.testing.assert_array_equal(m2.heights[:, 100:], east_posts)


def test_enclosed_gap_is_filled(alps_corner):
    """3 x 3 pieces sharing edges, the centre one missing: its interior is enclosed."""
    tiles = [piece(alps_corner, 80 * a, 80 * a + 80, 80 * b, 80 * b + 80)
             for a in range(3) for b in range(3) if (a, b) != (1, 1)]
    (m,) = mosaic(tiles)
    gap = np.zeros(m.shape, bool)
    gap[81:160, 81:160] = True
    np.testing.assert_array_equal(m.filled.astype(bool), gap)
    assert m.meta["gap_posts_filled"] == 79 * 79 and m.meta["gap_posts_outside"] == 0
    np.testing.assert_array_equal(m.heights[~gap], alps_corner.heights[~gap])
    ring = np.zeros(m.shape, bool)
    ring[80:161, 80:161] = True
    ring &= ~gap
    h = m.heights
    # Maximum principle, exact: the fill stays within its boundary's range.
    assert h[ring].min() <= h[gap].min() and h[gap].max() <= h[ring].max()
    lat = 47.0 + np.array([120.5, 79.5, 30.0]) * SRTM3
    lon = 9.0 + np.array([120.5, 80.5, 200.0]) * SRTM3
    _, status = query(m, lat, lon)
    assert list(status) == [STATUS_FILLED, STATUS_OK, STATUS_OK]


def test_edge_gap_stays_outside_and_falls_through(alps_corner, alps):
    """2 x 2 pieces with the north-east one missing: that gap touches the edge."""
    tiles = [piece(alps_corner, r0, r0 + 120, c0, c0 + 120)
             for r0, c0 in ((0, 0), (0, 120), (120, 0))]
    (m,) = mosaic(tiles)
    assert m.shape == (241, 241)
    assert m.meta["gap_posts_outside"] == 120 * 120 and m.meta["gap_posts_filled"] == 0
    assert m.filled is None
    assert np.isnan(m.heights[121:, 121:]).all()
    # In the gap; in a cell with a gap corner; clear of it; on the last covered
    # row next to the gap (whichever source answers, the height is the post's).
    lat = 47.0 + np.array([200.0, 120.5, 60.0, 120.0]) * SRTM3
    lon = 9.0 + np.array([200.0, 200.0, 200.0, 200.0]) * SRTM3
    _, status = query(m, lat, lon)
    assert list(status[:3]) == [STATUS_OUTSIDE, STATUS_OUTSIDE, STATUS_OK]
    h_fallback, status_fallback = query([m, alps], lat, lon)
    h_truth, _ = query(alps, lat, lon)
    np.testing.assert_array_equal(h_fallback, h_truth)  # exact: the full tile answers the rest
    assert np.all(status_fallback == STATUS_OK)


def test_unaligned_rasters_stay_separate_in_priority_order(alps_corner):
    a = piece(alps_corner, 0, 120, 0, 120)
    g = a.georef
    half_post = Raster(a.heights, Georef(g.crs, g.x0 + 0.5 * g.dx, g.y0, g.dx, g.dy), name="shifted",
                       vertical_datum=a.vertical_datum)
    # 1.5 posts: no whole multiple (2 or 3 would be refined to a's spacing and merged:
    # tests/test_mosaic_resolutions.py)
    other_spacing = Raster(a.heights, Georef(g.crs, g.x0, g.y0, 1.5 * g.dx, g.dy), name="coarse",
                           vertical_datum=a.vertical_datum)
    other_datum = Raster(a.heights, Georef(g.crs, g.x0 + 120 * g.dx, g.y0, g.dx, g.dy), name="datum",
                         vertical_datum="some other datum")
    out = mosaic([half_post, a, other_spacing, other_datum])
    assert [r.name for r in out] == ["shifted", a.name, "coarse", "datum"]
    assert all(x is y for x, y in zip(out, [half_post, a, other_spacing, other_datum]))


def test_distant_aligned_tiles_stay_separate(hgt_alps, hgt_kattegat):
    out = load_sources([hgt_kattegat, hgt_alps])
    assert [r.name for r in out] == ["N57E011", "N47E009"]
    h, status = query(out, [57.7, 47.0], [11.9, 9.0])
    assert h[0] == 13.0 and np.all(status == STATUS_OK)


def test_merge_never_overrides_an_earlier_source(alps_corner):
    west = piece(alps_corner, 0, 240, 0, 120)
    east = piece(alps_corner, 0, 240, 120, 240)
    g = east.georef
    over_east = Raster(np.full((11, 11), 1.0, np.float32),
                       Georef(g.crs, g.x0 + 50.5 * g.dx, g.y0 + 50.5 * g.dy, g.dx, g.dy), name="patch",
                       vertical_datum=east.vertical_datum)
    # patch ranks above east and lies on it: merging east into west would bury it.
    out = mosaic([west, over_east, east])
    assert [r.name for r in out] == [west.name, "patch", east.name]
    # Ranked below both, the patch no longer blocks the merge.
    out = mosaic([west, east, over_east])
    assert len(out) == 2 and out[1].name == "patch"
    np.testing.assert_array_equal(out[0].heights, alps_corner.heights)


def test_a_later_tile_bridges_two_groups(alps_corner):
    west = piece(alps_corner, 0, 240, 0, 80)
    east = piece(alps_corner, 0, 240, 160, 240)
    middle = piece(alps_corner, 0, 240, 80, 160)
    assert len(mosaic([west, east])) == 2  # a 79-post gap apart: not touching
    (m,) = mosaic([west, east, middle])
    np.testing.assert_array_equal(m.heights, alps_corner.heights)


def test_abutting_cell_centred_tiles_merge(alps_corner):
    """Tiles one post apart (no shared post), as cell-centred grids abut: the cell between them is kept."""
    west = piece(alps_corner, 0, 240, 0, 99)
    east = piece(alps_corner, 0, 240, 100, 240)
    (m,) = mosaic([west, east])
    np.testing.assert_array_equal(m.heights, alps_corner.heights)
    assert m.meta["overlap_posts"] == 0


def test_member_voids_stay_marked_filled(alps_corner):
    west = piece(alps_corner, 0, 240, 0, 120)
    mask = np.zeros(west.shape, bool)
    mask[10, 10] = True
    west = Raster(west.heights, west.georef, name="w", vertical_datum=west.vertical_datum, filled=mask)
    east = piece(alps_corner, 0, 240, 120, 240)
    (m,) = mosaic([west, east])
    assert m.filled[10, 10] and m.filled.sum() == 1


def test_mixed_dtypes_store_float64(alps_corner):
    west = piece(alps_corner, 0, 240, 0, 120)
    east = piece(alps_corner, 0, 240, 120, 240, heights=alps_corner.heights[:, 120:].astype(np.float64))
    (m,) = mosaic([west, east])
    assert m.heights.dtype == np.float64
    np.testing.assert_array_equal(m.heights, alps_corner.heights)


def _write_hgt(path, lat0, lon0, n, height_of):
    """An n x n .hgt tile of int16 heights height_of(lat, lon) (lon unwrapped, degrees)."""
    lat = lat0 + np.arange(n)[::-1, None] / (n - 1)  # file row 0 = north
    lon = lon0 + np.arange(n)[None, :] / (n - 1)
    np.round(height_of(lat, lon)).astype(">i2").tofile(path)
    return path


def test_antimeridian_tiles_merge_across_180(tmp_path):
    n = 121  # 30 arc-second posts

    def height_of(lat, lon_east):
        return 500.0 + 300.0 * np.sin(np.radians(40.0 * (lon_east - 179.0))) + 20.0 * (lat - 10.0)

    east = read_hgt(_write_hgt(tmp_path / "N10E179.hgt", 10, 179, n, height_of))
    west = read_hgt(_write_hgt(tmp_path / "N10W180.hgt", 10, -180, n, lambda la, lo: height_of(la, lo + 360.0)))
    for order in ([east, west], [west, east]):
        (m,) = mosaic(order)
        assert m.georef.x0 == 179.0
        assert m.shape == (n, 2 * n - 1)
        assert m.bounds == (10.0, 179.0, 11.0, 181.0)
        assert m.meta["overlap_disagreeing_posts"] == 0

    (m,) = mosaic([west, east])
    lat = np.linspace(10.0, 11.0, 37)
    h_pos, s_pos = query(m, lat, np.full(lat.shape, 180.0))
    h_neg, s_neg = query(m, lat, np.full(lat.shape, -180.0))
    np.testing.assert_array_equal(h_pos, h_neg)  # exact: both are the shared column
    assert np.all(s_pos == STATUS_OK) and np.all(s_neg == STATUS_OK)
    h_e, _ = query(m, lat, np.full(lat.shape, 179.99))
    h_w, _ = query(m, lat, np.full(lat.shape, -179.99))
    h_e_tile, _ = query(east, lat, np.full(lat.shape, 179.99))
    h_w_tile, _ = query(west, lat, np.full(lat.shape, -179.99))
    np.testing.assert_array_equal(h_e, h_e_tile)  # exact: same posts on either side
    np.testing.assert_array_equal(h_w, h_w_tile)
    # Continuity across 180: the bilinear slope is at most max |post step| per
    # post, so heights 2e apart in longitude differ by <= slope * 2e * 120 posts/deg.
    step = np.abs(np.diff(m.heights.astype(np.float64), axis=1)).max()
    for e in (1e-3, 1e-6, 1e-9):
        h_a, _ = query(m, lat, np.full(lat.shape, 180.0 - e))
        h_b, _ = query(m, lat, np.full(lat.shape, -180.0 + e))
        assert np.all(np.abs(h_a - h_b) <= step * 2 * e * (n - 1) + 1e-9)  # 1e-9 m: rounding


def test_merge_over_the_post_limit_keeps_rasters_separate():
    """Two thin strips that touch would span 70000 x 70000 posts: kept apart, nothing allocated."""
    dx = 1e-3
    strip_ew = Raster(np.zeros((2, 70_000), np.float32), Georef(CRS_GEOGRAPHIC, 0.0, 0.0, dx, dx), name="ew")
    strip_ns = Raster(np.zeros((70_000, 2), np.float32), Georef(CRS_GEOGRAPHIC, 0.0, 0.0, dx, dx), name="ns")
    out = mosaic([strip_ew, strip_ns])
    assert len(out) == 2 and out[0] is strip_ew and out[1] is strip_ns
    h, status = query(out, [0.0005, 69.0], [69.0, 0.0005])
    assert list(status) == [STATUS_OK, STATUS_OK] and list(h) == [0.0, 0.0]


def test_tiles_touching_at_a_corner_stay_separate(tmp_path):
    """Four SRTM1 tiles on a diagonal (the report's repro: 207 M posts of bounding box) load as
    four rasters; each answers its own posts exactly."""
    n = 3601
    paths = []
    for k in range(4):
        path = tmp_path / f"N{40 + k:02d}E{10 + k:03d}.hgt"
        np.full((n, n), 300 + k, ">i2").tofile(path)
        paths.append(path)
    sources = load_sources(paths)
    assert [s.shape for s in sources] == [(n, n)] * 4
    h, status = query(sources, [40.5, 41.5, 42.5, 43.5, 41.0], [10.5, 11.5, 12.5, 13.5, 11.0])
    assert list(h) == [300.0, 301.0, 302.0, 303.0, 300.0]  # the shared corner: the first tile wins
    assert np.all(status == STATUS_OK)


def test_edge_sharing_tiles_merge_but_a_corner_neighbour_does_not(alps_corner):
    """A and B share an edge, C touches B only at a corner: A+B merge, C stays apart."""
    a = piece(alps_corner, 0, 80, 0, 80)
    b = piece(alps_corner, 0, 80, 80, 160)
    c = piece(alps_corner, 80, 160, 160, 240)
    out = mosaic([a, b, c])
    assert len(out) == 2 and out[1] is c
    np.testing.assert_array_equal(out[0].heights, alps_corner.heights[0:81, 0:161])


def _write_south_up_hgt(path, south_up):
    south_up[::-1].astype(">i2").tofile(path)
    return path


def test_filled_void_yields_to_a_lower_priority_measured_post(tmp_path):
    """The report's repro: an SRTM tile with a hole listed before a complete DEM of the same area.
    The merged raster takes the second file's measured posts in the hole (status OK, exact), and
    the overlap statistics count only measured posts."""
    n = 121
    i, j = np.mgrid[0:n, 0:n]
    real = (1000 + 50 * np.sin(i / 5) * np.cos(j / 7) + 3 * i).astype(np.int16)  # row 0 south
    holed = real.copy()
    holed[40:80, 40:80] = -32768
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = _write_south_up_hgt(tmp_path / "a" / "N47E009.hgt", holed)
    b = _write_south_up_hgt(tmp_path / "b" / "N47E009.hgt", real)
    (m,) = load_sources([a, b])
    np.testing.assert_array_equal(m.heights, real)  # exact: int16 posts in float32
    assert m.filled is None
    assert m.meta["overlap_posts"] == n * n - 40 * 40 and m.meta["overlap_disagreeing_posts"] == 0
    h, status = query(m, [47.5], [9.5])
    assert h[0] == real[60, 60] and status[0] == STATUS_OK


def test_hole_no_member_measured_is_filled_from_all_members(tmp_path):
    """Both members hold the same hole; the merged raster fills it once from the measured posts
    around it: within their range (maximum principle) and marked filled."""
    n = 121
    i, j = np.mgrid[0:n, 0:n]
    real = (800 + 2 * i + j).astype(np.int16)
    holed = real.copy()
    holed[50:60, 50:60] = -32768
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = _write_south_up_hgt(tmp_path / "a" / "N47E009.hgt", holed)
    b_posts = holed.copy()
    b_posts[:, 100:] += 7  # disagrees away from the hole: a wins there
    b = _write_south_up_hgt(tmp_path / "b" / "N47E009.hgt", b_posts)
    (m,) = load_sources([a, b])
    hole = np.zeros((n, n), bool)
    hole[50:60, 50:60] = True
    np.testing.assert_array_equal(m.filled.astype(bool), hole)
    ring = real[49:61, 49:61]
    assert ring.min() <= m.heights[hole].min() and m.heights[hole].max() <= ring.max()


def test_terrain_answers_a_filled_point_from_a_lower_source_that_measured_it(tmp_path):
    """A tile with a hole, then a finer DEM (not mergeable: another grid) over part of the hole,
    then the procedural world. In the hole the finer DEM answers where it has data (OK, its own
    bilinear value exactly); elsewhere in the hole the tile's fill answers (FILLED), not the
    procedural world, which measures nothing; outside the hole the tile (OK). The lattice query
    agrees bit for bit."""
    from terrain.procedural import ProceduralTerrain

    n = 121
    i, j = np.mgrid[0:n, 0:n]
    real = (1000 + 50 * np.sin(i / 5) * np.cos(j / 7) + 3 * i).astype(np.int16)
    holed = real.copy()
    holed[40:80, 40:80] = -32768
    tile = read_hgt(_write_south_up_hgt(tmp_path / "N47E009.hgt", holed))
    fine_h = np.full((41, 41), 1234.5, np.float32)
    fine = Raster(fine_h, Georef(CRS_GEOGRAPHIC, 9.45, 47.45, 0.1 / 40, 0.1 / 40), name="fine")  # 9.45..9.55
    t = Terrain([tile, fine, ProceduralTerrain(seed=3)])
    lat = np.array([47.5, 47.5, 47.62, 47.2])
    lon = np.array([9.5, 9.6, 9.45, 9.2])  # hole & fine; hole only; hole only; outside the hole
    res = t.heights(lat, lon)
    assert list(res.status) == [STATUS_OK, STATUS_FILLED, STATUS_FILLED, STATUS_OK]
    assert res.height_msl_m[0] == 1234.5
    alone = Terrain([tile]).heights(lat, lon).height_msl_m
    np.testing.assert_array_equal(res.height_msl_m[1:], alone[1:])
    grid = t.height_grid(np.array([47.5, 47.2]), np.array([9.5, 9.6]))
    by_points = t.heights(np.repeat([47.5, 47.2], 2), np.tile([9.5, 9.6], 2))
    np.testing.assert_array_equal(grid.height_msl_m.ravel(), by_points.height_msl_m)
    np.testing.assert_array_equal(grid.status.ravel(), by_points.status)
    assert grid.status[0, 0] == STATUS_OK
