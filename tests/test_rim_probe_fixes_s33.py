"""Along the rim of a DEM's hole, slopes and rays come from the DEM that answers the height
(acceptance probe s33, rim finding).

A point on a cell edge or a post has its height from the posts of non-zero weight alone
(terrain.raster._bilinear_value), so a post line beside a hole is covered. Its slope took the
cell to the north-east whole and, where that cell had a NaN post, said "not found": a clipped
DEM's rim answered its height OK but its normal NaN/OUTSIDE, or the procedural world's (7-22
degrees where the DEM's plane is 0.01), and a vertical segment dropped there met the procedural
world at 643 m where heights said 115 m. Now slopes are found wherever heights are (each partial
derivative the north-east cell's with its zero-weight posts unread, else the cell's across the
line), and a ray along a post line (a vertical segment, one in a meridian plane, one on the
equator) reads that line's posts, so it meets the surface heights answer, with the normal
normals answer there.

Oracles: a plane's slope (any cell of it has the plane's derivative), Terrain.heights and
Terrain.normals, and dense sampling of each segment against Terrain.heights (the stack's surface
as heights answer it)."""

from __future__ import annotations

import numpy as np
import pytest

from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef
from terrain.procedural import ProceduralTerrain
from terrain.raster import (CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef, Raster,
                            metres_per_index)
from terrain.terrain import Terrain

D = 0.001  # degrees between posts (111 m): rays over the raster stay short
N = 21
A_COL, B_ROW = 1.5, -0.75  # the plane's rise per column and per row step (m)
# A hole touching each edge of the raster (rows, columns; a clipped DEM's nodata, left NaN): each
# leaves post lines with the hole on every side of them (north, south, east, west).
HOLES = ((slice(0, 4), slice(8, 13)), (slice(17, 21), slice(8, 13)), (slice(8, 13), slice(0, 4)),
         (slice(8, 13), slice(17, 21)))
# Points on the raster's lattice every quarter post: posts, edges, cell interiors.
QUARTERS = np.arange(0, 4 * (N - 1) + 1) / 4.0
SAMPLE_M = 0.5  # the dense oracle's step along a segment


def _plane(lat0, lon0, holes=HOLES, filled=None):
    rr, cc = np.mgrid[0:N, 0:N]
    h = 100.0 + A_COL * cc + B_ROW * rr
    for rows, cols in holes:
        h[rows, cols] = np.nan
    return Raster(h, Georef(CRS_GEOGRAPHIC, lon0, lat0, D, D), name="rim", filled=filled)


def _lattice(lat0, lon0):
    r, c = np.meshgrid(QUARTERS, QUARTERS, indexing="ij")
    return lat0 + r.ravel() * D, lon0 + c.ravel() * D


@pytest.fixture(scope="module")
def rim():
    return _plane(10.0, -60.0)


def test_slopes_are_found_wherever_heights_are_and_are_the_dems(rim):
    """Every lattice point: the slope's status is the height's, and a covered point's slope is the
    plane's (each side of any rim line is a cell of the plane). Old: the rim lines with the hole
    north or east of them (columns 7 and 16, rows 7 and 16) were OUTSIDE."""
    lat, lon = _lattice(10.0, -60.0)
    one = Terrain([rim])
    h = one.heights(lat, lon)
    de, dn, st = one.gradients(lat, lon)
    np.testing.assert_array_equal(st, h.status)
    assert (st == STATUS_OK).sum() > 4000 and (st == STATUS_OUTSIDE).sum() > 1000
    mx, my = metres_per_index(CRS_GEOGRAPHIC, D, D, lat)
    ok = st == STATUS_OK
    np.testing.assert_allclose(de[ok], (A_COL / mx)[ok], rtol=1e-12)
    np.testing.assert_allclose(dn[ok], (B_ROW / my)[ok], rtol=1e-12)
    n = one.normals(lat, lon)
    np.testing.assert_array_equal(n.status, h.status)
    assert np.isfinite(n.normal_enu[ok]).all() and np.isnan(n.normal_enu[~ok]).all()


def test_the_probes_rim_over_the_procedural_world_keeps_the_dems_slope(rim):
    """Stacked over the procedural world, every point the DEM answers the height of has the DEM's
    slope, bit for bit, per point and in lattice form (the clipmap's normal maps); old: the
    procedural world's (7-22 degrees in the probe, the DEM's plane 0.01)."""
    lat, lon = _lattice(10.0, -60.0)
    stack = Terrain([rim, ProceduralTerrain(3)])
    alone = Terrain([rim])
    mine = alone.heights(lat, lon).status == STATUS_OK
    w_de, w_dn, _ = alone.gradients(lat, lon)
    rows, cols = 10.0 + QUARTERS * D, -60.0 + QUARTERS * D
    for de, dn, st in (stack.gradients(lat, lon), (x.ravel() for x in stack.gradient_grid(rows, cols))):
        np.testing.assert_array_equal(st, stack.heights(lat, lon).status)
        np.testing.assert_array_equal(de[mine], w_de[mine])
        np.testing.assert_array_equal(dn[mine], w_dn[mine])
    mx, my = metres_per_index(CRS_GEOGRAPHIC, D, D, lat[mine])
    plane_deg = np.degrees(np.arctan(np.hypot(A_COL / mx, B_ROW / my)))  # 0.87 degrees
    np.testing.assert_allclose(stack.normals(lat, lon).slope_deg[mine], plane_deg, rtol=1e-9)


@pytest.mark.parametrize("stacked", [False, True])
def test_lattice_slopes_are_the_points_slopes(rim, stacked):
    t = Terrain([rim, ProceduralTerrain(3)] if stacked else [rim])
    rows, cols = 10.0 + QUARTERS * D, -60.0 + QUARTERS * D
    de, dn, st = t.gradient_grid(rows, cols)
    lat, lon = np.repeat(rows, cols.size), np.tile(cols, rows.size)
    w_de, w_dn, w_st = t.gradients(lat, lon)
    np.testing.assert_array_equal(de.ravel(), w_de)
    np.testing.assert_array_equal(dn.ravel(), w_dn)
    np.testing.assert_array_equal(st.ravel(), w_st)
    np.testing.assert_array_equal(st, t.height_grid(rows, cols).status)


def test_a_line_or_a_post_alone_has_its_slope_along_it_and_none_across():
    """Where the raster holds only a post line (holes on both sides) or a lone post, heights answer
    from it; the slope along the line is the data's and across it 0 (nothing is known there)."""
    strip_and_post = ((slice(5, 16), slice(9, 10)), (slice(5, 16), slice(11, 12)), (slice(2, 5), slice(2, 5)))
    r = _plane(10.0, -60.0, holes=strip_and_post)
    h = np.array(r.heights)
    h[3, 3] = 123.0
    r = Raster(h, r.georef)
    lat = 10.0 + np.array([10.5, 10.0, 6.25, 3.0]) * D
    lon = -60.0 + np.array([10.0, 10.0, 10.0, 3.0]) * D
    t = Terrain([r])
    assert (t.heights(lat, lon).status == STATUS_OK).all()
    de, dn, st = t.gradients(lat, lon)
    assert (st == STATUS_OK).all()
    _, my = metres_per_index(CRS_GEOGRAPHIC, D, D, lat)
    np.testing.assert_array_equal(de, 0.0)
    np.testing.assert_allclose(dn[:3], B_ROW / my[:3], rtol=1e-12)
    assert dn[3] == 0.0


def test_the_column_west_of_column_0_of_a_raster_that_wraps():
    """A raster of every longitude: beside a hole east of column 0 the slope across column 0 is
    taken from column 359 (the same turn's column west of it), as heights wrap."""
    lon = -180.0 + np.arange(361)
    rows = np.arange(11)
    h = 100.0 + 20.0 * np.cos(np.radians(lon))[None, :] + 0.5 * rows[:, None]
    h[0:4, 1:6] = np.nan
    r = Raster(h, Georef(CRS_GEOGRAPHIC, -180.0, -5.0, 1.0, 1.0))
    de, dn, st = Terrain([r]).gradients(np.array([-4.0, -3.5]), np.array([-180.0, 180.0]))
    assert (st == STATUS_OK).all()
    mx, my = metres_per_index(CRS_GEOGRAPHIC, 1.0, 1.0, np.array([-4.0, -3.5]))
    np.testing.assert_allclose(de, (h[1, 0] - h[1, 359]) / mx, rtol=1e-12)
    np.testing.assert_allclose(dn, 0.5 / my, rtol=1e-12)


# -- rays -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("stacked", [False, True])
def test_vertical_segments_meet_the_height_and_normal_heights_and_normals_answer(rim, stacked):
    """Dropped at every lattice point the DEM covers (posts and edges along every rim included): the
    hit is at the height heights answer, with its status, and the normal normals answer. Old: on
    the rims with the hole north or east, OUTSIDE alone and the procedural world's 416-810 m over it
    (heights 114-115 m)."""
    t = Terrain([rim, ProceduralTerrain(3)] if stacked else [rim])
    lat, lon = _lattice(10.0, -60.0)
    h = Terrain([rim]).heights(lat, lon)
    on = h.status == STATUS_OK
    lat, lon, ground = lat[on], lon[on], h.height_msl_m[on]
    got = t.intersect(lat, lon, ground + 50.0, lat, lon, ground - 50.0)
    assert got.hit.all() and (got.status == STATUS_OK).all()
    assert np.abs(got.height_msl_m - ground).max() < 1e-6
    np.testing.assert_allclose(got.normal_enu, t.normals(lat, lon).normal_enu, rtol=0, atol=1e-9)
    vis = t.line_of_sight(lat, lon, ground + 50.0, lat, lon, ground + 0.5)
    assert vis.visible.all() and (vis.status == STATUS_OK).all()


def _dense_first_contact(terrain, a_lat, a_lon, a_h, b_lat, b_lon, b_h):
    """(distance of the first sample at or under the surface heights answer, None: none; step (m);
    whether every sample before it is covered), sampling the ECEF chord every SAMPLE_M."""
    a = geodetic_to_ecef(np.array([a_lat]), np.array([a_lon]), np.array([a_h]))[0]
    b = geodetic_to_ecef(np.array([b_lat]), np.array([b_lon]), np.array([b_h]))[0]
    length = float(np.linalg.norm(b - a))
    s = np.linspace(0.0, 1.0, int(np.ceil(length / SAMPLE_M)) + 1)
    lat, lon, h = ecef_to_geodetic(a[None, :] + s[:, None] * (b - a)[None, :])
    surf = terrain.heights(lat, lon)
    under = np.flatnonzero(h <= surf.height_msl_m)
    first = under[0] if under.size else s.size
    covered = bool((surf.status[:first] != STATUS_OUTSIDE).all())
    return (None if not under.size else s[first] * length), length / (s.size - 1), covered


def _line_segments(lat0, lon0, lines, specs):
    """Segments along post lines: ('col', k) the meridian of column k, ('row', k) the latitude of row
    k (the equator in these tests); specs (e0, e1, dh0, dh1): from row (column) e0 to e1, dh0 and
    dh1 metres above the plane (extended beyond the raster) at the ends."""
    out = []
    for kind, k in lines:
        for e0, e1, dh0, dh1 in specs:
            (r0, c0), (r1, c1) = ((e0, k), (e1, k)) if kind == "col" else ((k, e0), (k, e1))
            out.append((lat0 + r0 * D, lon0 + c0 * D, 100.0 + A_COL * c0 + B_ROW * r0 + dh0,
                        lat0 + r1 * D, lon0 + c1 * D, 100.0 + A_COL * c1 + B_ROW * r1 + dh1))
    return out


def _check_against_dense(terrain, segments):
    """Each segment's first contact is where dense samples of it first reach the surface heights
    answer (to a sample step: a contact at a wall, where the segment passes onto a higher source,
    is at the step's foot), unless a sample before it is uncovered (then OUTSIDE, no contact); one
    with no contact is clear where every sample is covered, else OUTSIDE. Line of sight is blocked
    where either end reaches a contact so (else clear or OUTSIDE as intersect). Returns how many
    segments hit."""
    arr = [np.array(x, float) for x in zip(*segments)]
    got = terrain.intersect(*arr)
    los = terrain.line_of_sight(*arr)
    for k, seg in enumerate(segments):
        want, step, covered = _dense_first_contact(terrain, *seg)
        back, _, back_covered = _dense_first_contact(terrain, *seg[3:], *seg[:3])
        if want is None or not covered:
            assert not got.hit[k], (k, seg, got.height_msl_m[k])
            assert got.status[k] == (STATUS_OK if covered else STATUS_OUTSIDE), (k, seg)
        else:
            assert got.hit[k] and got.status[k] == STATUS_OK, (k, seg, got.status[k])
            assert want - step - 1e-6 <= got.distance_m[k] <= want + 1e-6, (k, seg, got.distance_m[k], want)
        blocked = (want is not None and covered) or (back is not None and back_covered)
        assert los.visible[k] == (not blocked and covered), (k, seg)
        assert los.status[k] == (STATUS_OK if blocked or covered else STATUS_OUTSIDE), (k, seg)
    return int(got.hit.sum())


# Along a line: 1 m over it both ways (clear: the chords sag 0.1 m), descending into it, starting under it.
ALONG = [(0.0, 20.0, 1.0, 1.0), (20.0, 0.0, 1.5, 1.5), (1.0, 19.0, 20.0, -20.0), (19.0, 1.0, 20.0, -20.0),
         (2.0, 18.0, -5.0, 30.0)]
# Off the DEM onto the procedural world (300-460 m here): high over it, and low; from over it
# steeply down onto the DEM, meeting it 3 posts in (on the rims of the holes at its south and
# north edges, in stack_trace's stretch of the DEM from its edge).
OFF = [(6.0, -4.0, 1.0, 2900.0), (14.0, 26.0, 1.0, 300.0), (-0.5, 3.5, 500.0, -20.0), (20.5, 16.5, 500.0, -20.0)]
# Rim lines of HOLES: columns 7 (hole east), 13 (west), 4 (west), 16 (east), the raster's edges 0 and 20.
COLUMN_LINES = [("col", k) for k in (7, 13, 4, 16, 0, 20)]


@pytest.mark.parametrize("stacked", [False, True])
def test_meridian_segments_along_rims_meet_the_surface_heights_answer(rim, stacked):
    """Segments in the meridian plane of a rim's column (their track runs along the post line):
    just over the rim (under the procedural world), descending into it, and reaching off the DEM
    over the procedural world. Old: OUTSIDE along the hole-east rims, or the procedural world's
    surface there."""
    t = Terrain([rim, ProceduralTerrain(3)] if stacked else [rim])
    segs = _line_segments(10.0, -60.0, COLUMN_LINES, ALONG + (OFF if stacked else []))
    if not stacked:  # along a column line into a hole (rows 0-3 of column 10): OUTSIDE, as heights there
        into_hole = [np.array([x]) for x in (10.0 + 6 * D, -60.0 + 10 * D, 150.0, 10.0 + 1 * D, -60.0 + 10 * D, 150.0)]
        assert t.intersect(*into_hole).status[0] == STATUS_OUTSIDE
        assert t.line_of_sight(*into_hole).status[0] == STATUS_OUTSIDE
    assert 0 < _check_against_dense(t, segs) < len(segs)


@pytest.mark.parametrize("stacked", [False, True])
def test_equatorial_segments_along_a_rim_row_meet_the_surface_heights_answer(stacked):
    """Segments on the equator run along its row of posts: with a hole north of the row (the
    north-east cell rule's blind side) and south of it. Old: OUTSIDE, or the procedural world's."""
    lat0 = -10 * D  # row 10 on the equator
    r = _plane(lat0, 20.0, holes=((slice(11, 15), slice(3, 9)), (slice(6, 10), slice(12, 17))))
    t = Terrain([r, ProceduralTerrain(3)] if stacked else [r])
    assert t.heights(np.array([0.0]), np.array([20.0 + 5 * D])).status[0] == STATUS_OK
    segs = _line_segments(lat0, 20.0, [("row", 10)], ALONG + (OFF if stacked else []))
    assert 0 < _check_against_dense(t, segs) < len(segs)


def test_a_ray_along_a_line_beside_filled_posts_reports_the_heights_status():
    """A vertical segment on a post line whose cell holds a filled post of zero weight there: OK, as
    its height (old: FILLED, and over a second measured DEM its stretch went to that DEM)."""
    filled = np.zeros((N, N), bool)
    filled[:, 8] = True  # column 8: the posts east of the line c = 7
    r = _plane(10.0, -60.0, holes=(), filled=filled)
    lat = 10.0 + np.array([2.5, 3.0, 12.25]) * D
    lon = np.full(3, -60.0 + 7 * D)
    under = Raster(np.full((N, N), 500.0), r.georef, name="under")
    for t in (Terrain([r]), Terrain([r, under])):
        h = t.heights(lat, lon)
        assert (h.status == STATUS_OK).all() and (h.height_msl_m < 200.0).all()
        got = t.intersect(lat, lon, h.height_msl_m + 20.0, lat, lon, h.height_msl_m - 20.0)
        assert (got.status == STATUS_OK).all()
        assert np.abs(got.height_msl_m - h.height_msl_m).max() < 1e-6
    inside = Terrain([r]).heights(lat, lon + 0.5 * D)
    assert (inside.status == STATUS_FILLED).all()  # off the line the filled posts count


@pytest.mark.parametrize("seed", range(4))
def test_random_holes_and_fills_slopes_and_rays_cover_what_heights_cover(seed):
    """Rasters with random holes (a third of the posts) and filled posts: at every point of the
    quarter-post lattice the slope's status is the height's, and a vertical segment dropped there
    meets the height with that status (the cells' posts of zero weight count for neither)."""
    rng = np.random.default_rng(seed)
    n = 9
    h = rng.uniform(50.0, 150.0, (n, n))
    h[rng.random((n, n)) < 0.33] = np.nan
    filled = rng.random((n, n)) < 0.15
    r = Raster(h, Georef(CRS_GEOGRAPHIC, 7.0, 45.0, D, D), filled=filled)
    q = np.arange(0, 4 * (n - 1) + 1) / 4.0
    lat, lon = 45.0 + np.repeat(q, q.size) * D, 7.0 + np.tile(q, q.size) * D
    t = Terrain([r])
    got = t.heights(lat, lon)
    de, dn, st = t.gradients(lat, lon)
    np.testing.assert_array_equal(st, got.status)
    assert np.isfinite(de[st != STATUS_OUTSIDE]).all() and np.isfinite(dn[st != STATUS_OUTSIDE]).all()
    on = got.status != STATUS_OUTSIDE
    assert {STATUS_OK, STATUS_FILLED} <= set(got.status[on].tolist())
    ground = got.height_msl_m[on]
    seg = t.intersect(lat[on], lon[on], ground + 10.0, lat[on], lon[on], ground - 10.0)
    assert seg.hit.all()
    np.testing.assert_array_equal(seg.status, got.status[on])
    assert np.abs(seg.height_msl_m - ground).max() < 1e-6
    np.testing.assert_allclose(seg.normal_enu, t.normals(lat[on], lon[on]).normal_enu, rtol=0, atol=1e-9)


def test_the_probes_clipped_asc_over_the_procedural_world(tmp_path):
    """The probe's case end to end: an ESRI ASCII grid (posts every 0.05 deg over lat 10..11, lon
    -60..-59, a plane) with nodata touching its south-east edge (rows 0-2, columns 15-20: left
    OUTSIDE, as documented) over ProceduralTerrain(3). On column 14 (lon -59.30), just west of the
    hole: heights 114-115.35 m OK; normals were the procedural world's (7.4-21.9 deg, the plane
    0.0117) and vertical segments met it at 416-810 m."""
    from terrain.mosaic import load_sources

    la, lo = 10 + np.arange(21) * 0.05, -60 + np.arange(21) * 0.05
    h = 100 + 10 * (la[:, None] - 10) + 20 * (lo[None, :] + 60)
    h[0:3, 15:21] = -9999
    path = tmp_path / "voids.asc"
    rows = "\n".join(" ".join(repr(float(v)) for v in row) for row in h[::-1])
    path.write_text(f"ncols 21\nnrows 21\nxllcenter -60.0\nyllcenter 10.0\ncellsize 0.05\nNODATA_value -9999\n{rows}\n")
    t = Terrain(load_sources([path]) + [ProceduralTerrain(3)])
    lat, lon = np.array([10.1, 10.05, 10.135, 10.15, 10.0]), np.full(5, -59.3)
    got = t.heights(lat, lon)
    assert (got.status == STATUS_OK).all()
    np.testing.assert_allclose(got.height_msl_m, [115.0, 114.5, 115.35, 115.5, 114.0], atol=1e-9)
    n = t.normals(lat, lon)
    assert (n.status == STATUS_OK).all()
    mx, my = metres_per_index(CRS_GEOGRAPHIC, 0.05, 0.05, lat)  # the plane: 1 m a column, 0.5 m a row
    np.testing.assert_allclose(n.slope_deg, np.degrees(np.arctan(np.hypot(1.0 / mx, 0.5 / my))), rtol=1e-6)
    assert n.slope_deg.max() < 0.012
    seg = t.intersect(lat, lon, np.full(5, 3000.0), lat, lon, np.full(5, -100.0))
    assert seg.hit.all() and (seg.status == STATUS_OK).all()
    assert np.abs(seg.height_msl_m - got.height_msl_m).max() < 1e-6
    np.testing.assert_allclose(seg.normal_enu, n.normal_enu, rtol=0, atol=1e-9)
