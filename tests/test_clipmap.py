"""The geometry clipmap (client/render/clipmap.py, clipmap_layer.py): regions and toroidal
storage against rebuilds, the sample budget, the GPU's copy against the CPU's, heights at
level posts against the terrain query, and no holes at a grazing view. Real DEM, real EGL."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from client.render.camera import Camera
from client.render.clipmap import (Clipmap, Rect, active_origin, blocks, clip_region, drawn_regions, ring_rects,
                                   toroidal_pieces, uncovered_rects)
from client.render.clipmap_layer import clipmap_factory, height_alpha
from client.render.renderer import Renderer
from client.render.terrain_mesh import lattice_for
from sortie.errors import InvalidArgument
from render_helpers import hits_height
from terrain.geodesy import ecef_to_geodetic, enu_basis

W, H = 320, 180
MAGENTA = (255, 0, 255)
N = 31


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def make_clipmap(alps, levels=4, n=N, budget=10 ** 9):
    return Clipmap(alps, lattice_for(alps.describe(), 47.5, 9.5), levels, n, budget)


def cells(rects) -> set:
    return {(i, j) for r in rects for i in range(r.i0, r.i1 + 1) for j in range(r.j0, r.j1 + 1)}


# -- pure region arithmetic ------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(st.integers(-100, 100), st.integers(-100, 100), st.integers(-40, 40), st.integers(-40, 40))
def test_uncovered_strips_are_exactly_the_new_posts(i0, j0, di, dj):
    old, new = clip_region(2 * i0, 2 * j0, N), clip_region(2 * i0 + 2 * di, 2 * j0 + 2 * dj, N)
    strips = uncovered_rects(old, new)
    assert len(strips) <= 4 and sum(r.size for r in strips) == len(cells(strips))  # disjoint
    assert cells(strips) == cells([new]) - cells([old])


@settings(max_examples=100, deadline=None)
@given(st.integers(-10_000, 10_000), st.integers(-10_000, 10_000), st.integers(1, N), st.integers(1, N))
def test_toroidal_pieces_cover_the_rect_at_their_texels(i0, j0, rows, cols):
    r = Rect(i0, j0, i0 + rows - 1, j0 + cols - 1)
    pieces = toroidal_pieces(r, N)
    assert cells([p for p, _, _ in pieces]) == cells([r]) and len(pieces) <= 4
    for p, t0, c0 in pieces:  # a piece is contiguous in storage, where i mod n puts it
        assert t0 == p.i0 % N and c0 == p.j0 % N and t0 + p.i1 - p.i0 < N and c0 + p.j1 - p.j0 < N


def test_active_region_is_even_and_centred():
    for fi, fj in [(0.0, 0.0), (100.3, -57.8), (-3.5, 2.49)]:
        i0, j0 = active_origin(fi, fj, N)
        assert i0 % 2 == 0 and j0 % 2 == 0
        assert abs(i0 + (N - 1) / 2 - fi) <= 1.0 and abs(j0 + (N - 1) / 2 - fj) <= 1.0


def test_ring_rects_and_blocks_tile_the_region_minus_the_hole():
    region, hole = clip_region(0, 0, N), Rect(8, 6, 20, 22)
    rects = ring_rects(region, hole)
    all_cells = cells([Rect(0, 0, N - 2, N - 2)])
    hole_cells = cells([Rect(8, 6, 19, 21)])
    assert cells(rects) == all_cells - hole_cells and sum(r.size for r in rects) == len(all_cells - hole_cells)
    b = blocks(rects, 8)
    covered = {(i, j) for i0, j0, i1, j1 in b for i in range(i0, i1) for j in range(j0, j1)}
    assert covered == all_cells - hole_cells


def test_bad_parameters_name_the_field(alps):
    lattice = lattice_for(alps.describe(), 47.5, 9.5)
    for kw, field in [({"n": 32}, "n"), ({"levels": 0}, "levels"), ({"budget": 0}, "budget")]:
        args = {"levels": 3, "n": N, "budget": 100, **kw}
        with pytest.raises(InvalidArgument, match=field):
            Clipmap(alps, lattice, args["levels"], args["n"], args["budget"])


# -- toroidal updates against a rebuild ------------------------------------------------------------

def test_toroidal_updates_equal_a_rebuild_bit_for_bit_after_any_motion(alps):
    moving = make_clipmap(alps)
    rng = np.random.default_rng(5)
    lat, lon = 47.4, 9.4
    steps = [0.0003, 0.002, 0.01, 0.05, 0.3]  # from under a post to a jump across every level
    for k in range(12):
        d = steps[k % len(steps)]
        lat, lon = lat + rng.uniform(-d, d), lon + rng.uniform(-d, d)
        moving.update(lat, lon)
        fresh = make_clipmap(alps)
        fresh.update(lat, lon)
        for a, b in zip(moving.levels, fresh.levels):
            assert a.region == b.region
            ta, pa, na = a.unrolled()
            tb, pb, nb = b.unrolled()
            assert np.array_equal(pa, pb) and np.array_equal(ta[..., 3], tb[..., 3]) and np.array_equal(na, nb)
            # The float32 offsets are the float64 positions less the level's own origin.
            assert np.array_equal(ta[..., :3], (pa - a.origin_ecef).astype(np.float32))
            assert np.abs(ta[..., :3]).max() <= 3 * moving.extent_m(a.k)


def test_the_budget_moves_coarse_levels_first_and_finer_ones_catch_up(alps):
    c = make_clipmap(alps, levels=5, budget=2 * N * (1 + 4) * 2)  # about two strips
    c.update(47.4, 9.4)  # the first update fills every level (each is the first of its frame... or over budget)
    while c.stats.levels_behind:
        c.update(47.4, 9.4)
    before = [lv.region for lv in c.levels]
    c.update(47.4 + 0.04, 9.4 + 0.04)  # every level must move; the budget allows only the coarsest
    assert c.stats.levels_moved >= 1 and c.stats.levels_behind >= 1
    assert c.levels[-1].region != before[-1] and c.levels[0].region == before[0]  # coarse moved, fine lags
    regions = drawn_regions(c, [lv.k for lv in c.levels])
    for k, r in regions.items():  # drawn regions nest, cropped on even posts
        if k + 1 in regions:
            outer = regions[k + 1]
            assert r.i0 % 2 == 0 and r.j1 % 2 == 0 and r.i0 // 2 > outer.i0 and r.j1 // 2 < outer.j1
    for _ in range(40):
        c.update(47.44, 9.44)
        if not c.stats.levels_behind and not c.stats.levels_moved:
            break
    fi, fj = c.focus_index(0, 47.44, 9.44)
    assert c.levels[0].region == clip_region(*active_origin(fi, fj, N), N)  # caught up


# -- the GPU's copy -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def flat_sky_clipmap(alps):
    with Renderer(alps, W, H, flat_sky_rgb=MAGENTA, sea=False,
                  terrain_layer_factory=clipmap_factory(alps, levels=5, n=63, budget=10 ** 9)) as r:
        yield r


def test_gpu_textures_hold_the_cpu_storage_and_the_terrain_heights(alps, flat_sky_clipmap):
    r = flat_sky_clipmap
    r.render(Camera.from_geodetic(47.45, 9.45, 2500.0, 30.0, -10.0))
    r.render(Camera.from_geodetic(47.46, 9.47, 2500.0, 30.0, -10.0))  # a move: strip uploads
    layer = r.terrain_layer
    c = layer.clipmap
    with r.ctx:
        for level, (tex, nmap) in zip(c.levels, layer._tex):
            gpu = np.frombuffer(tex.read(), np.float32).reshape(c.n, c.n, 4)
            assert np.array_equal(gpu, level.texel)
            gpu_n = np.frombuffer(nmap.read(), np.float16).reshape(2 * c.n, 2 * c.n, 4)
            assert np.array_equal(gpu_n, level.normal)
            # Heights at the level's posts are the terrain query's (float32 at the GPU boundary).
            reg = level.region
            ii, jj = np.meshgrid(np.arange(reg.i0, reg.i1 + 1), np.arange(reg.j0, reg.j1 + 1), indexing="ij")
            lat, lon = c.latlon(level.k, ii, jj)
            truth = alps.heights(lat.ravel(), lon.ravel()).height_msl_m.reshape(lat.shape)
            texel, _, _ = level.unrolled()
            assert np.array_equal(texel[..., 3], truth.astype(np.float32))


def test_no_holes_at_a_grazing_view_across_level_borders(flat_sky_clipmap):
    r = flat_sky_clipmap
    lat, lon = 47.5, 9.5
    r.render(Camera.from_geodetic(lat, lon, 3000.0, 200.0, -3.0))
    c = r.terrain_layer.clipmap
    h_max = max(float(lv.texel[..., 3].max()) for lv in c.levels)
    h_min = min(float(lv.texel[..., 3].min()) for lv in c.levels)
    cam = Camera.from_geodetic(lat, lon, h_max + 150.0, 200.0, -3.0)
    image = r.render(cam)
    assert len(r.terrain_layer.draws) >= 3  # several levels meet on screen
    sky = np.all(image == np.array(MAGENTA, np.uint8), axis=-1)
    rays = cam.pixel_rays(W, H)
    up = enu_basis(lat, lon)[2]
    above = rays @ up > 1e-3
    hit = hits_height(cam, rays, h_min)
    hlat, hlon, _ = ecef_to_geodetic(hit)
    lat_min, lat_max, lon_min, lon_max = r.terrain_layer.solid_bounds
    m = 0.05
    must_hit = (hlat > lat_min + m) & (hlat < lat_max - m) & (hlon > lon_min + m) & (hlon < lon_max - m)
    assert above.mean() > 0.2 and must_hit.mean() > 0.4
    assert np.all(sky[above]), "terrain or junk above the horizon"
    holes = int(np.count_nonzero(sky & must_hit))
    assert holes == 0, f"{holes} sky pixels where the clipmap must cover the ground"


def test_levels_fade_out_with_height_before_they_are_dropped(flat_sky_clipmap):
    assert height_alpha(0.0, 1000.0) == 0.0 and height_alpha(400.0, 1000.0) == 1.0
    assert 0.0 < height_alpha(300.0, 1000.0) < 1.0
    r = flat_sky_clipmap
    low = Camera.from_geodetic(47.45, 9.45, 1500.0, 0.0, -30.0)
    r.render(low)
    low_levels = {d.k for d in r.terrain_layer.draws}
    high = Camera.from_geodetic(47.45, 9.45, 40_000.0, 0.0, -60.0)
    r.render(high)
    high_levels = {d.k for d in r.terrain_layer.draws}
    assert 0 in low_levels and 0 not in high_levels and max(high_levels) == max(low_levels)


# -- profiles and views ---------------------------------------------------------------------------

def test_profiles_per_agent_type():
    from client.render.profiles import PROFILES, profile, profile_for

    assert profile_for("aircraft", "f16").name == "fast_jet"
    assert profile_for("aircraft", "UH60-heli").name == "helicopter"
    assert profile_for("ground", "m1a2").name == "ground_vehicle"
    assert profile_for("static").name == "observer"
    for p in PROFILES.values():  # every profile is a valid clipmap reaching past 80 km at 90 m posts
        assert (p.n + 1) & p.n == 0 and p.view_distance_m(90.0) > 80_000.0
        assert p.pixel_error is None or 0 < p.pixel_error <= 2  # decimation within a couple of pixels
    assert profile("fast_jet").view_distance_m(90.0) > 350_000.0  # the horizon from 10 km
    with pytest.raises(InvalidArgument, match="profile"):
        profile("submarine")


@pytest.fixture()
def tank_server(alps, hgt_alps):
    """A live exercise with one tank on the Alps tile, its terrain named by the server."""
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World

    w = World(alps, geoid_undulation_m=48.0)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, coalition="red")
    srv = SimulationServer(w, ServerConfig(exercise_name="render client", terrain=f"dem:{hgt_alps}"))
    srv.start()
    yield srv
    srv.stop(0.5)
    w.close()


def test_two_views_share_one_clipmap_centred_on_the_agent(tank_server, tmp_path):
    import json

    from sortie.cli import main

    rc = main(["view", "--server", tank_server.address, "--follow", "tank1", "--views", "cockpit,chase", "--frames",
               "2", "--fps", "10", "--out", str(tmp_path), "--size", "160x90", "--profile", "helicopter"])
    assert rc == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["terrain_renderer"] == "clipmap" and s["profile"] == "helicopter" and s["camera"] == "cockpit,chase"
    assert sorted(p.rsplit("/", 1)[-1] for p in s["pngs"]) == [
        "frame_0000_chase.png", "frame_0000_cockpit.png", "frame_0001_chase.png", "frame_0001_cockpit.png"]
    assert s["levels_active"]["max"] >= 3
    # The second view of a frame found the clipmap already updated by the first: one load for both.
    assert all(f["terrain_samples"] == 0 for f in s["per_frame"][1:])


def test_sortie_client_follow_headless_renders_like_sortie_view(tank_server, tmp_path):
    import json

    from sortie.cli import main

    rc = main(["client", "--server", tank_server.address, "--agent-type", "ground", "--headless", "--frames", "1",
               "--out", str(tmp_path)])
    s = json.loads((tmp_path / "summary.json").read_text())
    assert rc == 0 and s["frames"] == 1 and s["follow"] == "tank1" and s["profile"] == "ground_vehicle"


# -- land classes (terrain/texture.py) as the base colour -------------------------------------------

def test_land_classes_follow_height_and_slope(alps):
    """The clipmap's per-texel classes are terrain.texture.class_map's: rock where the normal
    is steep, none of the lowland classes above the snow line, water at or below sea level."""
    from terrain import texture

    c = make_clipmap(alps, levels=2)
    c.land_classes = True
    c.update(47.1, 9.6, unlimited=True)
    level = c.levels[0]
    classes = level.normal[..., 3].astype(np.int64)
    assert set(np.unique(classes)) <= set(range(texture.N_CLASSES))
    up_cos = []
    fi, fj = c.focus_index(0, 47.1, 9.6)
    reg = level.region
    h = np.repeat(np.repeat(level.unrolled()[0][..., 3], 2, 0), 2, 1)
    assert h.shape == classes.shape
    n = level.normal[..., :3].astype(np.float64)
    lat, lon = c.latlon(0, (reg.i0 + reg.i1) / 2, (reg.j0 + reg.j1) / 2)
    up = enu_basis(float(lat), float(lon))[2]
    # The normal texels are stored toroidally; compare in storage order (classes and normals share it).
    up_cos = n @ up
    steep = up_cos < np.cos(np.radians(45.0))
    assert steep.sum() > 20
    assert np.mean(classes[steep] == texture.CLASS_NAMES.index("rock")) > 0.6
    assert texture.CLASS_NAMES.index("forest") in set(np.unique(classes))
    del fi, fj


def test_land_classes_colour_the_terrain(alps):
    """--land-classes: the same frame, coloured by the classes' palette."""
    cam = Camera.from_geodetic(47.15, 9.5, 3500.0, 45.0, -10.0)
    frames = {}
    for flag in (False, True):
        with Renderer(alps, W, H, flat_sky_rgb=MAGENTA, sea=False,
                      terrain_layer_factory=clipmap_factory(alps, levels=5, n=63, budget=10 ** 9,
                                                            land_classes=flag)) as r:
            frames[flag] = r.render(cam).astype(np.int64)
    ground = ~np.all(frames[False] == MAGENTA, axis=-1)
    assert ground.mean() > 0.3
    assert np.abs(frames[True] - frames[False])[ground].mean() > 5.0  # coloured otherwise
    # Forest green (40, 80, 38) dominates lit forest pixels: green well above red and blue.
    g = frames[True][ground]
    assert np.mean((g[:, 1] > g[:, 0] + 15) & (g[:, 1] > g[:, 2] + 15)) > 0.2


@pytest.mark.parametrize("i0, j0, i1, j1", [(0, 0, 126, 126), (-37, 12, 89, 140), (3, -5, 60, 33), (2, 4, 63, 64)])
def test_border_segments_cover_every_border_cell_from_even_posts(i0, j0, i1, j1):
    """The zero-area border triangles (GPU Gems 2 ch. 2) span every cell of the region's outer
    rows and columns on even lattice lines (but at most one at an odd start), each segment
    starting at an even lattice post; borders on odd lines get none."""
    from client.render.clipmap_layer import BLOCK, border_segments

    region = Rect(i0, j0, i1, j1)
    rows, cols = border_segments(region)
    h, w = i1 - i0, j1 - j0
    for seg in rows:
        assert seg[0] == seg[2] and seg[0] in (0, h)
        assert (j0 + seg[1]) % 2 == 0 and seg[3] - seg[1] <= BLOCK
    for seg in cols:
        assert seg[1] == seg[3] and seg[1] in (0, w)
        assert (i0 + seg[0]) % 2 == 0 and seg[2] - seg[0] <= BLOCK
    covered = {(s[0], j) for s in rows for j in range(s[1], s[3])}
    for i in (0, h):
        line = {(i, j) for j in range(j0 % 2, w)}
        assert line <= covered if (i0 + i) % 2 == 0 else not (line & covered)
    covered = {(i, s[1]) for s in cols for i in range(s[0], s[2])}
    for j in (0, w):
        line = {(i, j) for i in range(i0 % 2, h)}
        assert line <= covered if (j0 + j) % 2 == 0 else not (line & covered)


# -- a coarse global lattice -------------------------------------------------------------------------

def _global_quarter_degree():
    """A global grid of 0.25-degree posts (1441 x 721) rising gently eastwards, as a Terrain."""
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
    from terrain.terrain import Terrain

    lon = -180.0 + 0.25 * np.arange(1441)
    h = np.broadcast_to(100.0 + 10.0 * np.cos(np.radians(lon))[None, :], (721, 1441)).astype(np.float32)
    return Terrain([Raster(np.ascontiguousarray(h), Georef(CRS_GEOGRAPHIC, -180.0, -90.0, 0.25, 0.25),
                           name="global")])


def test_globe_levels_stop_before_a_level_spans_the_globe():
    from client.render.clipmap import globe_levels

    assert globe_levels(0.25, 255) == 3  # 63.5, 127, 254 degrees; the next would be 508
    assert globe_levels(1.0 / 1200.0, 255) == 11  # 1700 x a level-0 span of 0.21 degrees: 2^10 < 1700 < 2^11
    assert globe_levels(2.0, 255) == 1  # 508 degrees already: one level
    for dlon, n in ((0.25, 255), (0.01, 63), (1.0 / 3600.0, 511)):
        k = globe_levels(dlon, n)
        assert (n - 1) * dlon * 2 ** (k - 1) <= 360.0 < (n - 1) * dlon * 2 ** k


def test_a_global_quarter_degree_grid_renders_near_the_antimeridian():
    """An acceptance probe: the default clipmap failed on a global 0.25-degree grid ("lon[0]: must
    be within [-540, 540] (got -1364)"): its coarse levels spanned the globe several times. The
    levels stop at the globe's span, and posts are asked within [-180, 180)."""
    terrain = _global_quarter_degree()
    for lon in (9.0, 179.9, -179.9):
        cam = Camera.from_geodetic(47.0, lon, 3000.0, 90.0, -10.0)
        with Renderer(terrain, W, H, flat_sky_rgb=MAGENTA, sea=False,
                      terrain_layer_factory=clipmap_factory(terrain, levels=10, n=255, budget=10 ** 9)) as r:
            frame = r.render(cam)
            assert len(r.terrain_layer.clipmap.levels) == 3
        ground = ~np.all(frame == MAGENTA, axis=-1)
        assert ground[H // 2 + 10:].mean() > 0.99  # ground below the horizon, no hole
