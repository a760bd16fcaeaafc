"""The reference renderer (client/render/, ``sortie render``, ``sortie view``).

Real parts: an EGL OpenGL 4.5 context (Mesa llvmpipe without a GPU), the
Alps SRTM tile, the procedural world, a simulation server on a free port.
Every ``Renderer.render`` checks glGetError after its frame and raises on
any error, so every test that renders also asserts "no GL error".

How sky holes are found: a renderer in test mode draws the sky as one exact
colour (magenta) with fog off, so a sky pixel is recognisable bit for bit.
Which pixels *must* show terrain is decided by geometry alone: a ray that
meets the surface of geodetic height h_low (the lowest post of the mesh)
at a point inside the mesh's extent must have crossed the terrain before it
(the camera is above every post), so a magenta pixel there is a hole. Rays
above the camera's horizontal can meet no terrain when the camera is above
every post: they must all be sky.

Error bounds: the projected peak is checked against the point the depth
buffer puts under its pixel, within 2 pixel footprints (the pixel's centre
is up to half a pixel from the peak, and the surface there slopes away); an
entity's drawn pixels are centred within 3 px of its projected position (its
mesh is not symmetric about its reference point); float32 vertex positions
relative to the camera within 1 cm of float64 (camera.py's bound: ~1 mm).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from client.render.camera import Camera, LocalOrigin, heading_pitch_roll_deg, quat_to_matrix
from client.render.entities import KIND_AIRCRAFT, KIND_STATIC, EntitySet
from client.render.gl import check_gl_error
from client.render.renderer import Renderer
from client.render.terrain_mesh import build_mesh, grid_triangles, interleave, lattice_for, stitch_edges
from sortie.errors import InvalidArgument
from render_helpers import hits_height
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef

W, H = 320, 180
MAGENTA = (255, 0, 255)
SANTIS = (47.2494, 9.3433)  # the highest summit of the tile's north-west (2502 m)
WINDOW_M, HORIZON_M = 8000.0, 24000.0


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.fixture(scope="module")
def flat_sky(alps):
    """Test mode: magenta sky, no fog, no sea."""
    with Renderer(alps, W, H, window_m=WINDOW_M, horizon_m=HORIZON_M, flat_sky_rgb=MAGENTA, sea=False) as r:
        yield r


@pytest.fixture(scope="module")
def shaded(alps):
    with Renderer(alps, W, H, window_m=WINDOW_M, horizon_m=HORIZON_M) as r:
        yield r


def _is_sky(image) -> np.ndarray:
    return np.all(image == np.array(MAGENTA, np.uint8), axis=-1)


def _elevation(camera: Camera, rays: np.ndarray) -> np.ndarray:
    from terrain.geodesy import enu_basis

    lat, lon, _ = camera.geodetic()
    return np.arcsin(np.clip(rays @ enu_basis(lat, lon)[2], -1.0, 1.0))


# -- camera math -----------------------------------------------------------------------------------

def test_camera_orientation_matches_the_wire_convention():
    """Camera.from_geodetic's body axes equal those of fdm.state's Euler quaternion taken to ECEF
    (server.dead_reckoning), and heading/pitch/roll read back."""
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat

    lat, lon, hdg, pitch, roll = 47.3, 9.4, 123.0, -12.0, 31.0
    cam = Camera.from_geodetic(lat, lon, 1500.0, hdg, pitch, roll)
    q = ned_to_ecef_quat(euler_to_quaternion(math.radians(roll), math.radians(pitch), math.radians(hdg)), lat, lon)
    assert np.abs(quat_to_matrix(q) - cam.r_ecef_body).max() < 1e-12
    assert np.allclose(heading_pitch_roll_deg(cam.position_ecef, cam.r_ecef_body), (hdg, pitch, roll), atol=1e-9)
    cam2 = Camera.from_ecef_quat(cam.position_ecef, q)
    assert np.abs(cam2.r_ecef_body - cam.r_ecef_body).max() < 1e-12
    # The view matrix (float64) and to_view agree; the optical axis projects to the image centre.
    origin = LocalOrigin(geodetic_to_ecef(lat, lon + 0.01, 0.0))
    p = cam.position_ecef + 5000.0 * cam.r_ecef_body[:, 0] + 300.0 * cam.r_ecef_body[:, 1]
    v = cam.view_matrix(origin) @ np.append(origin.to_local(p), 1.0)
    assert np.abs(v[:3] - cam.to_view(p)).max() < 1e-6
    px, d = cam.project(cam.position_ecef + 1000.0 * cam.r_ecef_body[:, 0], W, H)
    assert np.allclose(px, (W / 2, H / 2)) and math.isclose(d, 1000.0)


def test_bad_input_names_the_field():
    from client.render_cli import parse_pose, parse_size

    with pytest.raises(InvalidArgument, match="--size"):
        parse_size("960by540")
    with pytest.raises(InvalidArgument, match="--camera"):
        parse_pose("47.1,9.2,3000")
    with pytest.raises(InvalidArgument, match="lat_deg"):
        Camera.from_geodetic(95.0, 9.0, 100.0)
    with pytest.raises(InvalidArgument, match="fov_x_deg"):
        Camera.from_geodetic(47.0, 9.0, 100.0, fov_x_deg=0.0)
    with pytest.raises(InvalidArgument, match="quat_wxyz"):
        Camera.from_ecef_quat(geodetic_to_ecef(47.0, 9.0, 0.0), (0.0, 0.0, 0.0, 0.0))
    with pytest.raises(InvalidArgument, match="width"):
        Renderer(None, 0, 100)


# -- mesh functions --------------------------------------------------------------------------------

def test_holes_drop_their_cells_and_edges_are_stitched():
    valid = np.ones((4, 5), bool)
    assert len(grid_triangles(valid)) == 2 * 3 * 4
    valid[1, 2] = False  # an interior NaN post: its four cells go
    tris = grid_triangles(valid)
    assert len(tris) == 2 * (12 - 4) and not np.isin(1 * 5 + 2, tris)
    # Stitching: boundary posts between every 4th lie on the chord between those two.
    rng = np.random.default_rng(3)
    p = rng.normal(size=(9, 9, 3)) * 100.0
    h = rng.normal(size=(9, 9))
    q, g = p.copy(), h.copy()
    stitch_edges(q, g, 4)
    assert np.array_equal(q[1:-1, 1:-1], p[1:-1, 1:-1]) and np.array_equal(q[0, ::4], p[0, ::4])
    assert np.allclose(q[0, 1], 0.75 * p[0, 0] + 0.25 * p[0, 4]) and np.allclose(q[6, -1], 0.5 * (p[4, -1] + p[8, -1]))


def test_mesh_posts_are_exact_dem_posts_and_the_ring_does_not_overlap(alps):
    lattice = lattice_for(alps.describe(), 47.4, 9.6)
    assert lattice.exact and math.isclose(lattice.dlat, 1.0 / 1200.0)
    m = build_mesh(alps, lattice, 47.4, 9.6, window_m=3000.0, horizon_m=9000.0, horizon_stride=4)
    lat, lon, h = ecef_to_geodetic(m.positions_ecef)
    # Interior window posts sit on the DEM's lattice at its exact heights.
    n_window = m.window_shape[0] * m.window_shape[1]
    inner = np.arange(n_window).reshape(m.window_shape)[1:-1, 1:-1].ravel()
    assert np.abs((lat[inner] - 47.0) * 1200.0 - np.round((lat[inner] - 47.0) * 1200.0)).max() < 1e-6
    ref = alps.heights(lat[inner], lon[inner]).height_msl_m
    assert np.abs(m.height_msl_m[inner] - ref).max() == 0.0 and np.abs(h[inner] - ref).max() < 1e-6
    # No triangle of the ring lies inside the window (cells are disjoint in lat/lon).
    ring = m.triangles[np.all(m.triangles >= n_window, axis=1)]
    c_lat, c_lon = lat[ring].mean(axis=1), lon[ring].mean(axis=1)
    w_lat, w_lon = lat[:n_window], lon[:n_window]
    inside = ((c_lat > w_lat.min()) & (c_lat < w_lat.max()) & (c_lon > w_lon.min()) & (c_lon < w_lon.max()))
    assert len(ring) > 0 and not inside.any()


def test_mesh_through_the_terrain_service_equals_in_process(alps):
    """TerrainClient (gRPC, loopback) and the in-process Terrain give the same mesh, bit for bit."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    server, port = create_server(alps, "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as remote:
            lattice = lattice_for(remote.describe(), 47.6, 9.2)
            a = build_mesh(remote, lattice, 47.6, 9.2, window_m=2000.0, horizon_m=6000.0)
    finally:
        server.stop(0)
    b = build_mesh(alps, lattice_for(alps.describe(), 47.6, 9.2), 47.6, 9.2, window_m=2000.0, horizon_m=6000.0)
    assert np.array_equal(a.positions_ecef, b.positions_ecef) and np.array_equal(a.triangles, b.triangles)


# -- frames ----------------------------------------------------------------------------------------

def test_frames_are_deterministic_and_error_free(shaded):
    cam = Camera.from_geodetic(47.25, 9.45, 2200.0, 300.0, -6.0)
    a = shaded.render(cam)
    check_gl_error(shaded.ctx, "test frame")
    b = shaded.render(cam)
    assert a.shape == (H, W, 3) and a.dtype == np.uint8
    assert a.tobytes() == b.tobytes()
    s = shaded.stats
    assert s.triangles > 100_000 and s.vertices > 50_000 and s.frame_ms > 0
    assert len(np.unique(a.reshape(-1, 3), axis=0)) > 500  # shaded terrain, fog and sky, not a flat fill


def test_a_known_peak_lands_on_its_pixel(alps, flat_sky):
    """Säntis' highest post, projected by the camera math, is where the depth buffer puts terrain.
    The camera looks steeply down on it, so the peak is seen against its own flanks, not on a
    silhouette (where the pixel centre may just miss it and see the valley behind)."""
    i0, j0 = round((SANTIS[0] - 47.0) * 1200), round((SANTIS[1] - 9.0) * 1200)
    ii, jj = np.meshgrid(np.arange(i0 - 12, i0 + 13), np.arange(j0 - 12, j0 + 13), indexing="ij")
    lat, lon = 47.0 + ii.ravel() / 1200.0, 9.0 + jj.ravel() / 1200.0
    h = alps.heights(lat, lon).height_msl_m
    k = int(np.argmax(h))
    peak = geodetic_to_ecef(lat[k], lon[k], h[k])
    assert 2400.0 < h[k] < 2600.0
    cam = Camera.from_geodetic(lat[k] - 0.02, lon[k] - 0.012, h[k] + 2500.0, 20.0, -45.0)
    image = flat_sky.render(cam)
    (px, py), dist = cam.project(peak, W, H)
    assert 10 < px < W - 10 and 10 < py < H - 10 and abs(px - W / 2) + abs(py - H / 2) > 5  # in view
    col, row = int(px), int(py)
    assert not _is_sky(image)[row, col]
    depth = flat_sky.depth_m()[row, col]
    ray = cam.pixel_rays(W, H)[row, col]
    seen = cam.position_ecef + ray * depth / float(ray @ cam.r_ecef_body[:, 0])
    footprint = dist * cam.pixel_footprint_rad(W)
    assert np.linalg.norm(seen - peak) < 2.0 * footprint, (np.linalg.norm(seen - peak), footprint)


def test_sky_above_the_horizon_and_no_holes_below_at_a_grazing_view(flat_sky):
    cam0 = Camera.from_geodetic(47.5, 9.5, 3000.0, 200.0, -3.0)
    flat_sky.render(cam0)  # builds the mesh around the camera
    mesh = flat_sky.terrain_layer.mesh
    cam = Camera.from_geodetic(47.5, 9.5, float(np.nanmax(mesh.height_msl_m)) + 150.0, 200.0, -3.0)
    image = flat_sky.render(cam)
    assert flat_sky.stats.mesh_rebuilds >= 1 and np.isfinite(mesh.height_msl_m).all()  # inside the tile
    sky = _is_sky(image)
    rays = cam.pixel_rays(W, H)
    above = _elevation(cam, rays) > 1e-3
    hit = hits_height(cam, rays, float(np.nanmin(mesh.height_msl_m)))
    lat, lon, _ = ecef_to_geodetic(hit)
    lat_min, lat_max, lon_min, lon_max = mesh.bounds
    margin = 0.01  # one ring cell (8 posts of 1/1200 degree) and a little
    must_hit = ((lat > lat_min + margin) & (lat < lat_max - margin)
                & (lon > lon_min + margin) & (lon < lon_max - margin))
    holes_px = int(np.count_nonzero(sky & must_hit))
    assert above.mean() > 0.2 and must_hit.mean() > 0.4  # the test sees both
    assert np.all(sky[above]), "terrain or junk above the horizon"
    assert holes_px == 0, f"{holes_px} sky pixels where the terrain must be"


def test_the_sea_fills_where_the_terrain_has_no_data(alps):
    """At the tile's southern edge looking out: no post there (NaN), the sea shell shows, no sky."""
    with Renderer(alps, W, H, window_m=4000.0, horizon_m=0.0, flat_sky_rgb=MAGENTA, sea=True) as r:
        cam = Camera.from_geodetic(47.01, 9.5, 1500.0, 180.0, -4.0)
        image = r.render(cam)
        rays = cam.pixel_rays(W, H)
        hit = hits_height(cam, rays, 0.0)
        lat, _, _ = ecef_to_geodetic(hit)
        beyond = np.isfinite(lat) & (lat < 46.99) & (np.linalg.norm(hit - cam.position_ecef, axis=-1) < 100_000.0)
        assert beyond.mean() > 0.2
        assert not np.any(_is_sky(image)[beyond])
        water = image[beyond].astype(int)
        assert np.mean(water[:, 2] > water[:, 0]) > 0.95  # blue: water, not terrain


def test_poles_and_the_antimeridian_render_without_holes():
    """The procedural world (global lattice) at a pole and on both sides of the antimeridian,
    looking steeply down: every pixel of the lower half meets the ground within the window."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    world = Terrain([ProceduralTerrain(seed=5)])
    with Renderer(world, 160, 90, window_m=1500.0, horizon_m=0.0, flat_sky_rgb=MAGENTA, sea=False) as r:
        for lat, lon in ((89.999, 0.0), (10.0, 179.999), (10.0, -179.999)):
            ground = float(world.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
            image = r.render(Camera.from_geodetic(lat, lon, ground + 600.0, 90.0, -60.0))
            assert r.stats.triangles > 1000
            assert not _is_sky(image[45:]).any(), (lat, lon)


def test_entity_is_drawn_where_its_pose_says(flat_sky):
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat

    cam = Camera.from_geodetic(47.4, 9.7, 2500.0, 10.0, -2.0)
    target = cam.position_ecef + 400.0 * cam.r_ecef_body[:, 0] + 60.0 * cam.r_ecef_body[:, 1] \
        + 25.0 * cam.r_ecef_body[:, 2]
    lat, lon, _ = ecef_to_geodetic(target)
    quat = ned_to_ecef_quat(euler_to_quaternion(0.0, 0.0, math.radians(100.0)), float(lat), float(lon))
    one = EntitySet(np.array([7]), np.array([KIND_AIRCRAFT]), target[None], quat[None], ("blue",))
    bare = flat_sky.render(cam)
    drawn = flat_sky.render(cam, one)
    assert flat_sky.stats.entities_drawn == 1
    changed = np.any(bare != drawn, axis=-1)
    (px, py), _ = cam.project(target, W, H)
    rows, cols = np.nonzero(changed)
    assert changed[int(py), int(px)]
    assert abs(cols.mean() + 0.5 - px) < 3.0 and abs(rows.mean() + 0.5 - py) < 3.0
    assert 50 < changed.sum() < 5000


def test_depth_resolves_two_metres_at_400_km():
    """Reversed-Z float depth: of two markers 2 m apart ~400 km away, the nearer is drawn in
    either draw order (a 24-bit buffer with a 1 m near plane resolves ~10 km there)."""
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat

    cam = Camera.from_geodetic(47.5, 9.5, 1000.0, 0.0, 0.0)
    q = ned_to_ecef_quat(euler_to_quaternion(0.0, 0.0, 0.0), 47.5, 9.5)
    fwd = cam.r_ecef_body[:, 0]
    near, far = cam.position_ecef + 400_000.0 * fwd, cam.position_ecef + 400_002.0 * fwd
    with Renderer(None, W, H, sea=False, flat_sky_rgb=MAGENTA) as r:
        for order in ((far, near), (near, far)):
            colours = ("blue", "red") if order[0] is far else ("red", "blue")
            ents = EntitySet(np.array([1, 2]), np.array([KIND_STATIC, KIND_STATIC]), np.stack(order),
                             np.stack([q, q]), colours)
            image = r.render(cam, ents)
            drawn = ~_is_sky(image)
            assert 100 < drawn.sum() < 2000  # magnified to ~24 px
            assert np.all(image[drawn][:, 0] > image[drawn][:, 2]), "the far marker shows"  # near is red
        assert np.all(r.depth_m()[drawn] > 350_000.0)


def test_float32_offsets_with_rebasing_stay_within_a_centimetre():
    """A camera 1000 km from the first origin: after the rebase, vertex positions relative to the
    camera computed in float32 as uploaded (offsets, view matrix) are within 1 cm of float64;
    without the rebase they are not."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    world = Terrain([ProceduralTerrain(seed=11)])
    lat0, lon0, lat1, lon1 = 47.0, 9.0, 47.0, 22.2  # ~1000 km apart
    origin = LocalOrigin(geodetic_to_ecef(lat0, lon0, 0.0))
    cam = Camera.from_geodetic(lat1, lon1, 1200.0, 45.0, -10.0)
    assert np.linalg.norm(cam.position_ecef - origin.ecef) > 990_000.0
    mesh = build_mesh(world, lattice_for(world.describe(), lat1, lon1), lat1, lon1, window_m=5000.0, horizon_m=0.0)
    truth = cam.to_view(mesh.positions_ecef)

    def error_m() -> float:
        offsets = interleave(origin, mesh.positions_ecef, mesh.normals_ecef, mesh.height_msl_m, mesh.cos_slope)[:, :3]
        view = cam.view_matrix(origin).astype(np.float32)
        in_f32 = offsets @ view[:3, :3].T + view[:3, 3]  # what the vertex shader computes
        assert in_f32.dtype == np.float32
        return float(np.abs(in_f32.astype(np.float64) - truth).max())

    unrebased = error_m()
    assert origin.rebase_if_far(cam.position_ecef) and origin.generation == 1
    assert not origin.rebase_if_far(cam.position_ecef + 3000.0 * cam.r_ecef_body[:, 0])
    rebased = error_m()
    assert rebased < 0.01, rebased
    assert unrebased > 0.01, unrebased


# -- the commands ----------------------------------------------------------------------------------

def test_sortie_render_writes_a_png_of_the_right_size(hgt_alps, tmp_path):
    from PIL import Image

    out = tmp_path / "frame.png"
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "render", "--dem", str(hgt_alps), "--camera",
                          "47.15,9.25,2600,45,-8", "--out", str(out), "--size", "200x120", "--window-km", "4",
                          "--horizon-km", "0"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "triangles" in run.stdout
    with Image.open(out) as img:
        assert img.size == (200, 120) and img.mode == "RGB"


def test_sortie_render_takes_a_negative_latitude_without_equals(tmp_path):
    """--camera -33.9,151.2,... (a southern latitude, written as the help shows it) is the
    option's value, not taken for an option."""
    from PIL import Image

    lines = ["ncols 41", "nrows 41", "xllcenter 151.0", "yllcenter -34.0", "cellsize 0.005", "NODATA_value -9999"]
    lines += [" ".join(str(200 + 10 * ((i + j) % 7)) for j in range(41)) for i in range(41)]
    dem = tmp_path / "sydney.asc"
    dem.write_text("\n".join(lines) + "\n")
    out = tmp_path / "south.png"
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "render", "--dem", str(dem), "--camera",
                          "-33.95,151.1,1500,0,-10", "--out", str(out), "--size", "160x90", "--window-km", "3",
                          "--horizon-km", "0"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    with Image.open(out) as img:
        assert img.size == (160, 90)


def test_negative_values_bind_to_their_long_option():
    from sortie.cli import bind_negative_values

    assert bind_negative_values(["render", "--camera", "-33.9,151.2,2000,0,-10", "--size", "9x9"]) == \
        ["render", "--camera=-33.9,151.2,2000,0,-10", "--size", "9x9"]
    unchanged = [["render", "--camera", "47,9,2000,0,-10"], ["x", "--", "--camera", "-1,2"], ["x", "-n", "-1,2"],
                 ["x", "--a", "-1"], ["x", "--a=b", "-1,2"]]
    for argv in unchanged:
        assert bind_negative_values(argv) == argv


def test_sortie_render_pixel_error_sets_the_decimation(hgt_alps, tmp_path):
    """--pixel-error overrides the profile's decimation: 0 draws every post, a larger bound fewer
    triangles; a negative one is refused naming the flag."""
    import re

    def triangles(*extra):
        run = subprocess.run([sys.executable, "-m", "sortie.cli", "render", "--dem", str(hgt_alps), "--camera",
                              "47.15,9.25,4000,45,-10", "--out", str(tmp_path / "f.png"), "--size", "320x180",
                              "--profile", "observer", *extra], capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        return int(re.search(r"([\d,]+) triangles", run.stdout).group(1).replace(",", ""))

    every, bounded = triangles("--pixel-error", "0"), triangles("--pixel-error", "4")
    assert bounded < 0.8 * every
    bad = subprocess.run([sys.executable, "-m", "sortie.cli", "render", "--dem", str(hgt_alps), "--camera",
                          "47.15,9.25,4000,45,-10", "--out", str(tmp_path / "g.png"), "--pixel-error", "-1"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "--pixel-error" in bad.stderr


def test_sortie_view_follows_a_ground_vehicle(alps, hgt_alps, tmp_path):
    from PIL import Image

    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World
    from sortie.cli import main

    w = World(alps, geoid_undulation_m=48.0)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, coalition="red")
    w.spawn_static("sam1", "sam_site", 47.2905, 9.5905, coalition="blue")
    srv = SimulationServer(w, ServerConfig(exercise_name="render test", terrain=f"dem:{hgt_alps}"))
    srv.start()
    try:
        rc = main(["view", "--server", srv.address, "--agent-type", "ground", "--chase", "--frames", "2",
                   "--fps", "10", "--out", str(tmp_path), "--size", "160x90", "--window-km", "3",
                   "--horizon-km", "0"])
    finally:
        srv.stop(0.5)
        w.close()
    assert rc == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["follow"] == "tank1" and summary["kind"] == "ground"
    assert summary["entities_drawn"]["max"] == 2  # the followed tank (chase view) and the site
    assert summary["terrain"] == f"dem:{hgt_alps}"  # the server's own terrain
    assert summary["geoid_undulation_m"] == 48.0  # from WorldInfo
    with Image.open(tmp_path / "frame_0001.png") as img:
        frame = np.asarray(img.convert("RGB")).astype(int)
    r, g, b = frame[40, 80]  # the chase camera looks at the tank's reference point: the hull is just above
    assert r > 2 * max(g, b), frame[40, 80]


def test_a_camera_below_the_terrain_is_refused_by_name(hgt_alps, tmp_path):
    """The Säntis massif (~2,300 m) under a camera at 100 m MSL: a clear error, no frame."""
    out = tmp_path / "below.png"
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "render", "--dem", str(hgt_alps), "--camera",
                          "47.25,9.34,100,0,0", "--out", str(out), "--size", "64x48"], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2 and "--camera: altitude 100 m MSL is below the terrain there" in run.stderr
    assert not out.exists()


def test_the_catalogs_helicopter_gets_the_helicopter_profile():
    """The ah1s flies on JSBSim rotors; its name holds none of the helicopter words."""
    from client.render.profiles import profile_for
    from fdm.catalog import is_rotorcraft, list_aircraft

    assert "ah1s" in [n for n in list_aircraft() if is_rotorcraft(n)] and not is_rotorcraft("f16")
    assert profile_for("aircraft", "ah1s").name == "helicopter"
    assert profile_for("aircraft", "f16").name == "fast_jet" and profile_for("aircraft", "uh60").name == "helicopter"


def test_fog_leaves_the_earth_visible_from_high_above(alps):
    """An acceptance probe: from 10,000 km up (and 150 km) the fog, set to hide where the
    terrain ends, hid the whole Earth: 3 colours in the frame. Fog now goes by horizontal
    distance and thins with the camera's height over the terrain's range."""
    from client.render.camera import Camera
    from client.render.clipmap_layer import clipmap_factory
    from client.render.renderer import Renderer

    for alt in (1e7, 1.5e5):
        with Renderer(alps, 160, 90, terrain_layer_factory=clipmap_factory(alps, levels=8, n=127, budget=10 ** 9)) as r:
            frame = r.render(Camera.from_geodetic(47.15, 9.25, alt, 45.0, -90.0))
        colours = np.unique(frame.reshape(-1, 3), axis=0)
        assert len(colours) > 200, (alt, len(colours))


def test_render_options_are_checked_naming_the_option():
    """An acceptance probe: a NaN geoid undulation came back as 'position_ecef: must be finite',
    --window-km 0 as 'window_m', and a NaN in --camera did not say which field."""
    import argparse

    from client.render_cli import check_render_options, parse_pose
    from sortie.errors import InvalidArgument

    def options(**kw):
        base = dict(geoid_undulation_m=None, window_km=20.0, horizon_km=80.0)
        base.update(kw)
        return argparse.Namespace(**base)

    check_render_options(options())
    check_render_options(options(geoid_undulation_m=-50.0, horizon_km=0.0))
    for kw, name in ((dict(geoid_undulation_m=float("nan")), "--geoid-undulation-m"),
                     (dict(geoid_undulation_m=500.0), "--geoid-undulation-m"),
                     (dict(window_km=0.0), "--window-km"), (dict(window_km=float("inf")), "--window-km"),
                     (dict(horizon_km=10.0), "--horizon-km"), (dict(horizon_km=float("nan")), "--horizon-km")):
        with pytest.raises(InvalidArgument, match=name):
            check_render_options(options(**kw))
    with pytest.raises(InvalidArgument, match="LON must be a finite number"):
        parse_pose("47.2,nan,3000,0,-5")
    assert parse_pose("47.2,9.5,3000,0,-5") == (47.2, 9.5, 3000.0, 0.0, -5.0, 0.0)
    # Heading and roll within a turn either way (a later probe: 1e300 was taken as an angle).
    for text, what in (("47.2,9.5,3000,1e300,-5", "HEADING_DEG 1e\\+300"), ("47.2,9.5,3000,0,-5,-361", "ROLL_DEG -361")):
        with pytest.raises(InvalidArgument, match=f"{what} must be within \\[-360, 360\\] degrees"):
            parse_pose(text)
    assert parse_pose("47.2,9.5,3000,-360,-5,360") == (47.2, 9.5, 3000.0, -360.0, -5.0, 360.0)
