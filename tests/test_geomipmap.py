"""Target-area insets (terrain/inset.py) and their geomipmap layer (client/render/geomipmap.py).

Real parts: the Alps SRTM tile (N47E009, 3" posts), a 3 x 3 km target area by
the Säntis (47.25 N, 9.35 E, the tile's most rugged corner) at detail_m = 5,
and an EGL OpenGL 4.5 context (Mesa llvmpipe without a GPU). Every
``Renderer.render`` checks glGetError after its frame and raises on any error.

Oracles:
- exactness at posts and the aligned-lattice identity: the inset's surface
  minus the DEM's equals the bilinear interpolation of (inset posts - DEM at
  the posts), within 1e-6 m (rounding of the posts' coordinates);
- error bound: |inset - DEM| <= A = 4.3 sum(sigma_k) (``detail_bound_m``),
  and at the polygon's border <= A smoothstep(0, B, cell diagonal);
- cut-out: an independent signed distance to the (rectangular) polygon;
- levels: the drawn triangles (the layer's index buffer, mapped back to
  lattice posts and checked against the uploaded vertex positions) are
  evaluated at every post of their patch by this file's own barycentric
  code; each drawn patch's error delta x K / d (d the least distance from
  the camera to the patch's posts, K = v_res / (2 tan(fov_y / 2))) must be
  <= tau, and every post's projected displacement <= tau / cos^2(theta_max)
  (first-order projection of a vertical displacement off the optical axis);
- holes: a magenta sky, no fog; a pixel must show terrain when its ray, at
  some sample point over the polygon (shrunk by 20 m), is more than 1 m below
  the lowest post of the patches around that point (the drawn surface there
  is no lower: every triangle belongs to one patch and interpolates its
  posts; the camera is over the convex polygon and above every post, so the
  ray crossed the surface before that point). Sample heights use the local
  osculating expansion h = u + e^2 / 2N + n^2 / 2M (< 1 cm off within 6 km:
  the 1 m margin covers it; horizontal error ~ m: the 20 m shrink and the
  3 x 3 patch neighbourhood cover it).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import minimum_filter

from client.render.camera import Camera
from client.render.geomipmap import GeomipmapInset, patch_template
from client.render.gl import check_gl_error
from client.render.renderer import Renderer
from sortie.errors import InvalidArgument, LimitExceeded
from terrain.geodesy import enu_basis, geodetic_to_ecef, radii_of_curvature
from terrain.inset import (DETAIL_TABLE_MAX, InsetSource, cutout_depth_m, insets_of, smoothstep, with_insets)
from terrain.raster import STATUS_OK, STATUS_OUTSIDE

W, H = 320, 180
MAGENTA = (255, 0, 255)
CENTRE = (47.25, 9.35)
HALF_M = 1500.0
SEED = 2024
DETAIL_M = 5.0
TAU_PX = 1.0


def _square(lat_c: float, lon_c: float, half_m: float):
    m, n = radii_of_curvature(lat_c)
    dlat = math.degrees(half_m / float(m))
    dlon = math.degrees(half_m / (float(n) * math.cos(math.radians(lat_c))))
    return [(lat_c - dlat, lon_c - dlon), (lat_c - dlat, lon_c + dlon), (lat_c + dlat, lon_c + dlon),
            (lat_c + dlat, lon_c - dlon)]


AREA = _square(*CENTRE, HALF_M)
LAT_S, LAT_N = AREA[0][0], AREA[2][0]
LON_W, LON_E = AREA[0][1], AREA[1][1]


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.fixture(scope="module")
def inset(alps):
    return InsetSource(alps, AREA, DETAIL_M, SEED, name="alpstein")


@pytest.fixture(scope="module")
def with_area(alps):
    return with_insets(alps, [("alpstein", AREA, DETAIL_M)], SEED)


def _posts(inset, rows, cols):
    g = inset.georef
    return g.y0 + np.asarray(rows) * g.dy, g.x0 + np.asarray(cols) * g.dx


def _rect_signed_distance_m(lat, lon):
    """Independent signed distance (m) to the rectangular AREA in the plane about its first vertex."""
    m, n = radii_of_curvature(AREA[0][0])
    ky, kx = math.radians(1.0) * float(m), math.radians(1.0) * float(n) * math.cos(math.radians(AREA[0][0]))
    x, y = (np.asarray(lon) - LON_W) * kx, (np.asarray(lat) - LAT_S) * ky
    x1, y1 = (LON_E - LON_W) * kx, (LAT_N - LAT_S) * ky
    inside = np.minimum.reduce([x, x1 - x, y, y1 - y])
    ox, oy = np.maximum(np.maximum(-x, x - x1), 0.0), np.maximum(np.maximum(-y, y - y1), 0.0)
    return np.where(inside >= 0, inside, -np.hypot(ox, oy))


# -- the inset's data ------------------------------------------------------------------------------

def test_the_lattice_refines_the_dem_and_posts_are_exact(inset, with_area):
    ky, kx = inset.refine
    g = inset.georef
    assert math.isclose(g.dy, 1 / 1200 / 2**ky) and math.isclose(g.dx, 1 / 1200 / 2**kx)
    assert all(DETAIL_M / 2 < s <= DETAIL_M for s in inset.spacing_m)
    for origin, spacing in ((g.y0 - 47.0, g.dy), (g.x0 - 9.0, g.dx)):  # aligned with the DEM's posts
        assert abs(origin / spacing - round(origin / spacing)) < 1e-6
    rows, cols = inset.shape
    assert (rows - 1) % 64 == 0 and (cols - 1) % 64 == 0
    r, c = np.meshgrid(np.arange(0, rows, 7), np.arange(0, cols, 5), indexing="ij")
    lat, lon = _posts(inset, r.ravel(), c.ravel())
    res = with_area.heights(lat, lon)
    inside = inset.covers(lat, lon)
    assert inside.mean() > 0.5 and (~inside).any()
    # Inside the polygon the terrain answers the inset's posts bit for bit.
    assert np.array_equal(res.height_msl_m[inside], inset.heights[r.ravel(), c.ravel()][inside])
    assert np.all(res.status[inside] == STATUS_OK)


def test_the_inset_is_the_dem_plus_bounded_faded_detail(alps, inset):
    """Between posts the inset's surface minus the DEM's is the bilinear interpolant of the
    posts' differences (the lattice is aligned: the DEM's bilinear surface is reproduced
    exactly), and never more than the detail bound A."""
    a_m = DETAIL_TABLE_MAX * float(np.sum(inset.level_std_m))
    assert inset.detail_levels == min(inset.refine) == 4 and math.isclose(inset.detail_bound_m, a_m)
    assert inset.cutout_depth_max_m > a_m
    rng = np.random.default_rng(5)
    lat = rng.uniform(LAT_S, LAT_N, 20_000)
    lon = rng.uniform(LON_W, LON_E, 20_000)
    from terrain.terrain import Terrain

    mine = Terrain([inset]).heights(lat, lon).height_msl_m
    dem = alps.heights(lat, lon).height_msl_m
    g = inset.georef
    rf, cf = (lat - g.y0) / g.dy, (lon - g.x0) / g.dx
    i, j = np.floor(rf).astype(int), np.floor(cf).astype(int)
    fy, fx = rf - i, cf - j
    plat, plon = _posts(inset, np.stack([i, i, i + 1, i + 1]), np.stack([j, j + 1, j, j + 1]))
    diff = inset.heights[np.stack([i, i, i + 1, i + 1]), np.stack([j, j + 1, j, j + 1])] \
        - alps.heights(plat.ravel(), plon.ravel()).height_msl_m.reshape(4, -1)
    expect = (diff[0] * (1 - fx) + diff[1] * fx) * (1 - fy) + (diff[2] * (1 - fx) + diff[3] * fx) * fy
    assert np.abs((mine - dem) - expect).max() < 1e-6
    assert np.abs(mine - dem).max() <= a_m + 1e-6
    # Deep inside (w = 1) the detail has about its stated spread: sqrt(sum sigma^2) averaged over
    # the cells (bilinear interpolation averages, so between 0.5 and 1.0 of it).
    deep = _rect_signed_distance_m(lat, lon) > inset.border_band_m
    spread = np.std((mine - dem)[deep]) / math.sqrt(float(np.sum(inset.level_std_m ** 2)))
    assert 0.5 < spread < 1.0, spread


def test_the_inset_meets_the_terrain_below_at_its_border(alps, inset, with_area):
    """On the border and up to a0 - c inside it the inset is the DEM's surface (no detail yet):
    continuous with the terrain beneath; deeper in, the detail is there."""
    a0, diag = inset.detail_offset_m, inset.cell_diagonal_m
    assert 120.0 < a0 < 140.0  # sqrt(2) x 92.6 m, the tile's 3" post spacing north
    t = np.linspace(0.0, 1.0, 4001)
    lat = np.concatenate([np.full_like(t, LAT_S), LAT_S + t * (LAT_N - LAT_S)])
    lon = np.concatenate([LON_W + t * (LON_E - LON_W), np.full_like(t, LON_E)])
    assert np.abs(_rect_signed_distance_m(lat, lon)).max() < 1e-6
    assert np.abs(with_area.heights(lat, lon).height_msl_m - alps.heights(lat, lon).height_msl_m).max() < 1e-6
    rng = np.random.default_rng(3)
    lat = rng.uniform(LAT_S, LAT_N, 50_000)
    lon = rng.uniform(LON_W, LON_E, 50_000)
    s = _rect_signed_distance_m(lat, lon)
    diff = np.abs(with_area.heights(lat, lon).height_msl_m - alps.heights(lat, lon).height_msl_m)
    assert diff[s < a0 - diag].max() < 1e-6 and (s < a0 - diag).sum() > 1000
    assert np.median(diff[s > a0 + inset.border_band_m]) > 1.0
    # A metre outside, the DEM answers: same bits.
    out_lat = np.full(4001, LAT_S - 1.0 / 111_000)
    out_lon = LON_W + t * (LON_E - LON_W)
    assert np.array_equal(with_area.heights(out_lat, out_lon).height_msl_m,
                          alps.heights(out_lat, out_lon).height_msl_m)


def test_with_insets_answers_inside_from_the_inset_and_collides_with_it(alps, inset, with_area):
    assert [d["kind"] for d in with_area.describe()] == ["inset", "dem"]
    assert insets_of(with_area)[0].area_name == "alpstein" and insets_of(alps) == []
    rng = np.random.default_rng(11)
    lat = rng.uniform(LAT_S - 0.01, LAT_N + 0.01, 5000)
    lon = rng.uniform(LON_W - 0.01, LON_E + 0.01, 5000)
    inside = _rect_signed_distance_m(lat, lon) > 1e-6
    got = with_area.heights(lat, lon)
    raw_h, raw_s = np.full(lat.size, np.nan), np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    from terrain.raster import Raster

    Raster.heights_into(inset, lat, lon, raw_h, raw_s)  # the lattice's own surface, no polygon
    assert np.array_equal(got.height_msl_m[inside], raw_h[inside])
    assert np.array_equal(got.height_msl_m[~inside], alps.heights(lat[~inside], lon[~inside]).height_msl_m)
    nrm = with_area.normals(lat, lon)
    assert np.isfinite(nrm.normal_enu).all() and np.all(nrm.status == STATUS_OK)
    # A vertical segment through a point inside hits the inset's surface there (LOS traces the
    # inset's lattice: what collides is what is answered and drawn).
    k = np.flatnonzero(inside)[:50]
    h = got.height_msl_m[k]
    hit = with_area.intersect(lat[k], lon[k], h + 300.0, lat[k], lon[k], h - 300.0)
    assert hit.hit.all() and np.abs(hit.height_msl_m - h).max() < 1e-3


def test_the_inset_is_deterministic_and_rebuilt_from_a_terrain_that_serves_it(alps, inset, with_area):
    again = InsetSource(alps, AREA, DETAIL_M, SEED, name="alpstein")
    assert again.heights.tobytes() == inset.heights.tobytes()
    other = InsetSource(alps, AREA, DETAIL_M, SEED + 1, name="alpstein")
    assert not np.array_equal(other.heights, inset.heights)
    # A client of a terrain service serving with_insets(...) rebuilds the very same inset.
    served = InsetSource.from_inset_terrain(with_area, AREA, DETAIL_M, SEED, name="alpstein")
    assert served.heights.tobytes() == inset.heights.tobytes()
    assert np.array_equal(served.level_std_m, inset.level_std_m)
    assert served.cutout_depth_max_m == inset.cutout_depth_max_m


def test_a_client_of_the_terrain_service_rebuilds_the_served_inset(inset, with_area):
    """The server's terrain is with_insets(...); a render client over gRPC rebuilds the inset
    from the service's answers, bit for bit (what it draws is what the server collides with)."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    server, port = create_server(with_area, "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as remote:
            assert remote.describe()[0]["kind"] == "inset"
            rebuilt = InsetSource.from_inset_terrain(remote, AREA, DETAIL_M, SEED, name="alpstein")
    finally:
        server.stop(0)
    assert rebuilt.heights.tobytes() == inset.heights.tobytes()
    assert rebuilt.signed_distance.tobytes() == inset.signed_distance.tobytes()
    assert rebuilt.cutout_depth_max_m == inset.cutout_depth_max_m


def test_the_cutout_is_zero_outside_its_band_full_inside_and_smooth(inset):
    depth, band = inset.cutout_depth_max_m, inset.border_band_m
    lat = np.full(20_001, CENTRE[0] + 0.003)
    lon = LON_W + np.linspace(-0.005, 0.012, lat.size)  # 380 m outside to 900 m inside the west edge
    s = _rect_signed_distance_m(lat, lon)
    a0 = inset.detail_offset_m
    for spacing in (0.0, 90.0, 250.0):
        a = math.sqrt(2.0) * spacing
        c = inset.cutout_depth_m(lat, lon, clip_spacing_m=spacing)
        assert np.all(c[s <= a - 1e-6] == 0.0) and np.all(c[s >= a + band + 1e-6] == depth)
        assert (s > a + band).any() and (s < 0).any()
        assert np.all(np.diff(c) >= 0)  # walking inward it only deepens
        if a <= a0:  # a level as fine as the DEM: below the deepest trough the detail can dig
            assert np.all(c >= (inset.detail_bound_m + 2.0) * smoothstep(a0, a0 + band, s) - 1e-9)
        slope = np.abs(np.diff(c)) / np.maximum(np.abs(np.diff(s)), 1e-12)
        assert slope.max() <= 1.5 * depth / band * (1 + 1e-6)  # smoothstep's steepest
    assert np.array_equal(cutout_depth_m([inset], lat, lon), inset.cutout_depth_m(lat, lon))
    # A clipmap level of 90 m posts, interpolating its posts' cut linearly, never lowers a
    # point outside the polygon.
    g_lat, g_lon = 90.0 / 111_200, 90.0 / (111_320 * math.cos(math.radians(CENTRE[0])))
    pi, pj = np.meshgrid(np.arange(-30, 31), np.arange(-30, 31), indexing="ij")
    post_lat, post_lon = CENTRE[0] + 0.0007 + pi * g_lat, CENTRE[1] + 0.0011 + pj * g_lon
    cut = inset.cutout_depth_m(post_lat.ravel(), post_lon.ravel(), 90.0).reshape(pi.shape)
    u = np.linspace(0, 1, 7)[1:-1]
    mid = (cut[:-1, :-1, None, None] * (1 - u[:, None]) * (1 - u[None, :]) + cut[:-1, 1:, None, None]
           * (1 - u[:, None]) * u[None, :] + cut[1:, :-1, None, None] * u[:, None] * (1 - u[None, :])
           + cut[1:, 1:, None, None] * u[:, None] * u[None, :])
    m_lat = post_lat[:-1, :-1, None, None] + u[:, None] * g_lat + 0 * u[None, :]
    m_lon = post_lon[:-1, :-1, None, None] + u[None, :] * g_lon + 0 * u[:, None]
    outside = _rect_signed_distance_m(m_lat, m_lon) < 0
    assert outside.any() and np.all(mid[outside] == 0.0)


def test_bad_areas_are_named(alps):
    with pytest.raises(InvalidArgument, match="target area 'x' polygon"):
        InsetSource(alps, AREA[:2], DETAIL_M, SEED, name="x")
    with pytest.raises(InvalidArgument, match="target area 'x' detail_m"):
        InsetSource(alps, AREA, 0.1, SEED, name="x")
    with pytest.raises(InvalidArgument, match="seed"):
        InsetSource(alps, AREA, DETAIL_M, -1, name="x")
    with pytest.raises(LimitExceeded, match="target area 'big'"):
        InsetSource(alps, _square(47.5, 9.5, 20_000.0), 0.25, SEED, name="big")


# -- geomipmap patches -----------------------------------------------------------------------------

def _area2(tri, n):
    r, c = np.divmod(tri, n + 1)
    return (c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0]) - (c[:, 2] - c[:, 0]) * (r[:, 1] - r[:, 0])


def test_patch_templates_tile_the_patch_and_share_edge_posts():
    n = 16
    for level in range(5):
        for edges in [(level,) * 4, (4, level, 3 if level <= 3 else 4, level), (4, 4, 4, 4)]:
            tri = patch_template(n, level, edges)
            a = _area2(tri, n)
            assert np.all(a > 0) and a.sum() == 2 * n * n  # counter-clockwise, covering the square
            r, c = np.divmod(np.unique(tri), n + 1)
            for side, on in ((0, r == n), (1, c == n), (2, r == 0), (3, c == 0)):
                along = np.sort(c[on] if side in (0, 2) else r[on])
                assert np.array_equal(along, np.arange(0, n + 1, 1 << edges[side])), (level, edges, side)
            # Every post of the patch lies in exactly the triangles' union (no gap): each unit
            # cell's centre is inside some triangle.
            cr, cc = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5, indexing="ij")
            vr, vc = np.divmod(tri, n + 1)
            inside = np.zeros(cr.shape, bool)
            for t in range(len(tri)):
                ys, xs = vr[t], vc[t]
                d = [(xs[(k + 1) % 3] - xs[k]) * (cr - ys[k]) - (ys[(k + 1) % 3] - ys[k]) * (cc - xs[k])
                     for k in range(3)]
                inside |= (d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0)
            assert inside.all()


def _camera(inset, north: bool = False) -> Camera:
    """A grazing view from inside the area, 100 m above its highest post: from the south edge
    looking north-north-east, or from the north edge looking south-south-west."""
    alt = float(np.nanmax(inset.heights)) + 100.0
    if north:
        return Camera.from_geodetic(LAT_N - 0.001, CENTRE[1] + 0.006, alt, 200.0, -9.0)
    return Camera.from_geodetic(LAT_S + 0.001, CENTRE[1] - 0.004, alt, 20.0, -8.0)


@pytest.fixture(scope="module")
def renderers(inset):
    """(stitched, unstitched) renderers drawing the inset alone, flat magenta sky, no sea."""
    out = []
    for stitch in (True, False):
        r = Renderer(None, W, H, sea=False, flat_sky_rgb=MAGENTA, rebase_distance_m=1000.0,
                     terrain_layer_factory=lambda ctx, origin, s=stitch: GeomipmapInset(
                         ctx, inset, origin, tau_px=TAU_PX, stitch=s))
        out.append(r)
    yield out
    for r in out:
        r.release()


def _drawn_surface_check(layer, inset, camera):
    """Per drawn patch (slot): the largest |drawn - post| (m) over its posts, evaluated here from
    the layer's triangles; and per covered post its projected displacement (px)."""
    n = layer.n
    tri = layer.indices.astype(np.int64)
    rc = layer.vertex_lattice_index(tri)  # (m, 3, 2)
    # The mapping is the truth of the uploaded vertices: positions are those posts' ECEF.
    v = np.unique(tri)
    vr, vc = layer.vertex_lattice_index(v).T
    lat, lon = _posts(inset, vr, vc)
    assert np.allclose(layer.positions_ecef[v], geodetic_to_ecef(lat, lon, inset.heights[vr, vc]), atol=1e-6)
    r, c = rc[..., 0], rc[..., 1]
    r0, c0 = r.min(1), c.min(1)
    width = c.max(1) - c0 + 1
    size = (r.max(1) - r0 + 1) * width
    t_id = np.repeat(np.arange(len(tri)), size)
    k = np.arange(size.sum()) - np.repeat(np.cumsum(size) - size, size)
    pr, pc = r0[t_id] + k // width[t_id], c0[t_id] + k % width[t_id]
    ys, xs = r[t_id].astype(float), c[t_id].astype(float)
    den = (ys[:, 1] - ys[:, 2]) * (xs[:, 0] - xs[:, 2]) + (xs[:, 2] - xs[:, 1]) * (ys[:, 0] - ys[:, 2])
    l0 = ((ys[:, 1] - ys[:, 2]) * (pc - xs[:, 2]) + (xs[:, 2] - xs[:, 1]) * (pr - ys[:, 2])) / den
    l1 = ((ys[:, 2] - ys[:, 0]) * (pc - xs[:, 2]) + (xs[:, 0] - xs[:, 2]) * (pr - ys[:, 2])) / den
    l2 = 1.0 - l0 - l1
    ok = (l0 >= -1e-12) & (l1 >= -1e-12) & (l2 >= -1e-12)
    hv = inset.heights[r[t_id], c[t_id]]
    drawn = l0 * hv[:, 0] + l1 * hv[:, 1] + l2 * hv[:, 2]
    truth = inset.heights[pr, pc]
    slot = tri[t_id, 0] // (n + 1) ** 2
    err = np.zeros(layer.active.size)
    np.maximum.at(err, slot[ok], np.abs(drawn - truth)[ok])
    plat, plon = _posts(inset, pr[ok], pc[ok])
    p_true = geodetic_to_ecef(plat, plon, truth[ok])
    p_drawn = geodetic_to_ecef(plat, plon, drawn[ok])
    px_true, depth = camera.project(p_true, W, H)
    px_drawn, _ = camera.project(p_drawn, W, H)
    in_view = (depth > 0) & np.all((px_true >= 0) & (px_true <= (W, H)), axis=1)
    disp = np.linalg.norm(px_true - px_drawn, axis=1)[in_view]
    return err, disp


def test_levels_keep_every_drawn_patch_within_tau(renderers, inset):
    r = renderers[0]
    cam = _camera(inset)
    r.render(cam)
    check_gl_error(r.ctx, "geomipmap frame")
    layer = r.terrain_layer
    sel = layer.selection
    drawn = np.flatnonzero(sel.visible)
    assert np.count_nonzero(layer.stats.patches_per_lod) >= 4, layer.stats  # a mix of levels
    err, disp = _drawn_surface_check(layer, inset, cam)
    assert np.all(err[drawn] <= sel.error_m[drawn] + 1e-9)  # the tables bound what is drawn
    assert err[drawn].max() > 1.0  # coarse levels do drop metres of detail
    # Independent distance: the least over the patch's posts; independent K.
    n = layer.n
    k_px = 0.5 * H / (math.tan(math.radians(cam.fov_x_deg) / 2) * H / W)
    for slot in drawn:
        pr, pc = layer.patch_rc[slot]
        rows, cols = np.meshgrid(pr * n + np.arange(n + 1), pc * n + np.arange(n + 1), indexing="ij")
        lat, lon = _posts(inset, rows, cols)
        d = np.linalg.norm(geodetic_to_ecef(lat, lon, inset.heights[rows, cols]) - cam.position_ecef, axis=-1).min()
        assert err[slot] * k_px / d <= TAU_PX * (1 + 1e-9), (slot, err[slot], d)
    tx = math.tan(math.radians(cam.fov_x_deg) / 2)
    ty = tx * H / W
    assert disp.size > 100_000 and disp.max() <= TAU_PX * (1 + tx * tx + ty * ty) * 1.01, disp.max()


def _must_be_terrain(cam: Camera, inset, n: int, shrink_m: float = 20.0, margin_m: float = 1.0,
                     samples: int = 160) -> np.ndarray:
    """(H, W) bool: pixels whose ray surely meets the drawn inset (module docstring)."""
    g = inset.georef
    rows, cols = inset.shape
    k = np.arange(n + 1)
    ri = (np.arange((rows - 1) // n) * n)[:, None, None, None] + k[None, None, :, None]
    ci = (np.arange((cols - 1) // n) * n)[None, :, None, None] + k[None, None, None, :]
    patch_min = inset.heights[ri, ci].min(axis=(2, 3))  # every post of each patch, its edges included
    low = minimum_filter(patch_min, size=3, mode="nearest") - margin_m
    lat_c, lon_c = CENTRE
    m, nn = (float(x) for x in radii_of_curvature(lat_c))
    basis = np.stack(enu_basis(lat_c, lon_c))
    centre = geodetic_to_ecef(lat_c, lon_c, 0.0)
    rays = cam.pixel_rays(W, H).reshape(-1, 3) @ basis.T
    eye = (cam.position_ecef - centre) @ basis.T
    dist = np.geomspace(2.0, 6000.0, samples)
    shrink_lat = math.degrees(shrink_m / m)
    shrink_lon = math.degrees(shrink_m / (nn * math.cos(math.radians(lat_c))))
    out = np.zeros(rays.shape[0], bool)
    for lo in range(0, rays.shape[0], 4096):
        p = eye + rays[lo:lo + 4096, None, :] * dist[None, :, None]
        e, no, u = p[..., 0], p[..., 1], p[..., 2]
        h = u + e * e / (2 * nn) + no * no / (2 * m)
        lat = lat_c + np.degrees(no / m)
        lon = lon_c + np.degrees(e / (nn * math.cos(math.radians(lat_c))))
        inside = ((lat > LAT_S + shrink_lat) & (lat < LAT_N - shrink_lat) & (lon > LON_W + shrink_lon)
                  & (lon < LON_E - shrink_lon))
        pr = np.clip(((lat - g.y0) / g.dy // n).astype(int), 0, low.shape[0] - 1)
        pc = np.clip(((lon - g.x0) / g.dx // n).astype(int), 0, low.shape[1] - 1)
        out[lo:lo + 4096] = (inside & (h < low[pr, pc])).any(axis=1)
    return out.reshape(H, W)


def test_no_cracks_between_levels_at_grazing_views_and_cracks_without_stitching(renderers, inset):
    """Two grazing views over the area (the second after a rebase of the local origin): no sky
    pixel where the terrain must be. The same views without stitching show sky through cracks."""
    views = [_camera(inset), _camera(inset, north=True)]
    holes = {}
    for r in renderers:
        stitched = r.terrain_layer.stitch
        holes[stitched] = []
        for cam in views:
            image = r.render(cam)
            layer = r.terrain_layer
            assert layer._generation == r.origin.generation  # uploaded for the current origin
            must = _must_be_terrain(cam, inset, layer.n)
            assert must.mean() > 0.3, must.mean()
            assert np.count_nonzero(layer.stats.patches_per_lod) >= 4
            sky = np.all(image == np.array(MAGENTA, np.uint8), axis=-1)
            holes[stitched].append(int(np.count_nonzero(sky & must)))
        assert r.stats.rebased  # the second view is 3 km from the first: the origin moved
    assert holes[True] == [0, 0], holes
    assert sum(holes[False]) > 0, holes


def test_frames_are_shaded_deterministic_and_release_cleanly(inset):
    cam = _camera(inset)
    layers = []

    def factory(ctx, origin):
        layers.append(GeomipmapInset(ctx, inset, origin))
        return layers[-1]

    with Renderer(None, W, H, sea=False, terrain_layer_factory=factory) as r:
        a = r.render(cam)
        b = r.render(cam)
        assert a.tobytes() == b.tobytes()
        assert len(np.unique(a.reshape(-1, 3), axis=0)) > 300  # lit, tinted terrain and a sky
        s = layers[0].stats
        assert s.triangles == r.stats.triangles - 1 and s.index_ms == 0.0  # the second frame reused the indices
        assert s.patches_drawn + s.patches_culled == s.patches
    assert layers[0].program is None and layers[0]._vbo is None
