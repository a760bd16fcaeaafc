"""Acceptance-probe fixes of the render client (session 30).

1. A camera a few metres over the terrain (the bilinear surface queries answer and vehicles
   sit on) could be under the drawn triangles, which stand above that surface by up to a quarter
   of a cell's twist (60 m in a cell of the Alps tile): the frame showed the world from below.
   The renderer raises the eye to 5 cm over the surface drawn under it (``eye_lift_m``), and the
   reference mesh's near plane takes its cell's highest post, as the clipmap's does.
2. Near a pole the clipmap's levels are strips a cos(latitude) wide: it draws the reference
   mesh there instead (ClipmapLayer.polar).
3. ``sortie view`` summary: frames are frames (not images), the rate is intervals over time.
4. ``--camera`` bounds ALT_MSL_M; the fog takes any height.
5. ``--out`` in a format Pillow registers but cannot write an RGB frame in: refused up front.
6. ``sortie view``: an --out that is a file is refused naming --out; an observer that does not
   see the agent says it may be outside the observed area.
7. The mesh's terrain limit names --window-km and --horizon-km.
8. ``sortie client`` refuses render options without --follow/--agent-type.

Real parts: the Alps SRTM tile, a synthetic south-polar GeoTIFF, EGL (llvmpipe), small frames,
the simulation server and a procedural terrain service on loopback (ports 52750-52799).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap_layer import clipmap_factory
from client.render.profiles import profile
from client.render.renderer import Renderer
from sortie.cli import main

MAGENTA = (255, 0, 255)
# A cell of the Alps tile (N47E009, 3") whose quarter-twist (h_SW + h_NE - h_SE - h_NW) / 4 is 60 m,
# and the probe's cell of 6 m under a camera 3 m over the terrain (a tank's eye).
TWISTED = (47.140417, 9.308750)
STEEP = (47.286250, 9.690417)


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _sky_below(image: np.ndarray) -> int:
    """Flat-sky pixels in the lower half of a frame pitched 10 degrees down: all below the horizon."""
    return int(np.all(image[image.shape[0] // 2:] == MAGENTA, axis=-1).sum())


def _drawn_triangle_height(hgt_alps, lat: float, lon: float) -> tuple[float, float]:
    """(the SW-NE-split triangle's height, the quarter-twist) at (lat, lon) from the raw .hgt posts:
    an independent reading of the tile (1201 x 1201 big-endian int16, north row first)."""
    raw = np.fromfile(hgt_alps, ">i2").reshape(1201, 1201).astype(float)[::-1]
    fi, fj = (lat - 47.0) * 1200.0, (lon - 9.0) * 1200.0
    i, j = int(fi), int(fj)
    fy, fx = fi - i, fj - j
    sw, se, nw, ne = raw[i, j], raw[i, j + 1], raw[i + 1, j], raw[i + 1, j + 1]
    tri = sw + fx * (se - sw) + fy * (ne - se) if fx >= fy else sw + fy * (nw - sw) + fx * (ne - nw)
    return tri, (sw + ne - se - nw) / 4.0


# --------------------------------------------------------------------------- 1: under the triangles


@pytest.mark.parametrize("layer", ["clipmap", "mesh"])
def test_a_low_camera_sees_the_ground_from_above(alps, hgt_alps, layer):
    """Before: 100 % of the lower half sky at 5 cm and 1 m over the 60 m-twist cell (clipmap), and
    over the 6 m cell at 3 m up looking south 7200 of 7200 (mesh: also its 1 m near plane cut the
    slope). Now 0 at every heading, the eye raised to 5 cm over the tile's own triangle there (the
    clipmap's finest level, not morphing at its centre, draws the DEM's posts as the mesh does)."""
    for (lat, lon), up in ((TWISTED, 0.05), (TWISTED, 1.0), (STEEP, 3.0)):
        ground = float(alps.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
        tri, quarter_twist = _drawn_triangle_height(hgt_alps, lat, lon)
        assert 0.0 < tri - ground <= abs(quarter_twist) + 1e-6  # the triangle's rise over the bilinear surface
        factory = clipmap_factory(alps, **profile("observer").layer_args()) if layer == "clipmap" else None
        with Renderer(alps, 160, 90, flat_sky_rgb=MAGENTA, terrain_layer_factory=factory, window_m=4000.0,
                      horizon_m=8000.0) as r:
            for heading in (0.0, 90.0, 180.0, 270.0):
                image = r.render(Camera.from_geodetic(lat, lon, ground + up, heading, -10.0))
                assert _sky_below(image) == 0, (lat, lon, up, heading)
                from client.render.renderer import EYE_CLEARANCE_M

                assert r.stats.eye_lift_m == pytest.approx(max(tri + EYE_CLEARANCE_M - ground - up, 0.0), abs=1e-3)


def test_sortie_render_says_when_it_raises_the_eye(hgt_alps, tmp_path, capsys):
    out = tmp_path / "low.png"
    rc = main(["render", "--dem", str(hgt_alps), "--camera", f"{STEEP[0]},{STEEP[1]},854,180,-10", "--size",
               "160x90", "--out", str(out), "--terrain-renderer", "mesh", "--window-km", "3", "--horizon-km", "0"])
    assert rc == 0 and out.exists()
    assert "eye raised 3.0" in capsys.readouterr().out


# --------------------------------------------------------------------------- 2: near a pole


@pytest.fixture(scope="module")
def south_pole(tmp_path_factory):
    """A flat 2800 m south-polar plateau: -90 .. -89 degrees, every longitude, as a GeoTIFF."""
    import tifffile

    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    rows, cols, dlat, dlon = 201, 7201, 0.005, 0.05
    path = tmp_path_factory.mktemp("pole") / "south_pole.tif"
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 2), (2048, 0, 1, 4326)]  # geographic, pixel is area, WGS 84
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tags = [(34735, "H", len(directory), directory, False), (33550, "d", 3, [dlon, dlat, 0.0], False),
            (33922, "d", 6, [0.0, 0.0, 0.0, -180.0 - dlon / 2, -89.0 + dlat / 2, 0.0], False)]
    tifffile.imwrite(path, np.full((rows, cols), 2800, np.int16), extratags=tags)
    return Terrain([read_dem(path)])


def test_the_clipmap_covers_the_view_near_a_pole(south_pole):
    """Before: at -89.99 the clipmap drew a strip metres wide and the rest of the lower half was
    sky (sea without the test's flat sky). Now it draws the reference mesh there: 0 pixels."""
    factory = clipmap_factory(south_pole, **profile("observer").layer_args())
    with Renderer(south_pole, 160, 90, flat_sky_rgb=MAGENTA, sea=False, terrain_layer_factory=factory) as r:
        for heading in (0.0, 120.0, 240.0):
            image = r.render(Camera.from_geodetic(-89.99, 0.0, 3300.0, heading, -10.0))
            assert _sky_below(image) == 0, heading
        assert r.terrain_layer.polar and r.stats.triangles > 1000
        assert r.terrain_layer.fog_range_m > 50_000.0  # was about 50 m: the fog hid nothing from 500 m up


def test_the_clipmap_is_the_clipmap_away_from_the_poles(alps):
    factory = clipmap_factory(alps, **profile("observer").layer_args())
    with Renderer(alps, 64, 48, terrain_layer_factory=factory) as r:
        r.render(Camera.from_geodetic(47.2, 9.3, 3000.0, 0.0, -10.0))
        assert not r.terrain_layer.polar and r.stats.levels_active > 0


# --------------------------------------------------------------------------- 3, 6: sortie view


@pytest.fixture()
def tank_server(alps, hgt_alps):
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World

    w = World(alps, geoid_undulation_m=48.0)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, coalition="red")
    srv = SimulationServer(w, ServerConfig(exercise_name="render probe s30", terrain=f"dem:{hgt_alps}"),
                           address="127.0.0.1:52760")
    srv.start()
    yield srv
    srv.stop(0.5)
    w.close()


def test_view_summary_counts_frames_and_their_rate(tank_server, tmp_path, capsys):
    """Before: "frames": 4 (the PNGs of 2 frames in 2 views) and achieved_fps 4 / the run's time
    (1.9 at --fps 0.5); the HUD said (k + 1) / elapsed. Now 2 frames, 1 interval of 2 s: 0.5."""
    rc = main(["view", "--server", tank_server.address, "--follow", "tank1", "--views", "cockpit,chase", "--frames",
               "2", "--fps", "0.5", "--out", str(tmp_path), "--size", "96x54", "--profile", "helicopter"])
    assert rc == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["frames"] == 2 and len(s["pngs"]) == 4 and len(s["per_frame"]) == 2
    assert 0.45 <= s["achieved_fps"] <= 0.51, s["achieved_fps"]
    hud = [line for line in capsys.readouterr().out.splitlines() if line.startswith("frame 0001")]
    assert len(hud) == 1 and " fps  0.5" in hud[0], hud


def test_an_observer_that_does_not_see_the_agent_says_why(tank_server, tmp_path, capsys, monkeypatch):
    """Before: "agent 'tank1' is not in the exercise"; it is, 5,000 km from the observed area."""
    import client.render_cli as render_cli

    monkeypatch.setattr(render_cli, "FOLLOW_WAIT_S", 1.0)  # (the wait for the agent to show, 15 s)
    rc = main(["view", "--server", tank_server.address, "--follow", "tank1", "--role", "observer",
               "--observe-radius-km", "1", "--frames", "1", "--fps", "1", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and "not within the observed area" in err and "--observe-radius-km" in err
    assert "--role gateway" in err and "not in the exercise (" not in err
    assert "the picture had" in err  # what it did see (here: the observed area's own entities, if any)


def test_a_gateway_that_does_not_see_the_agent_names_what_it_saw(tank_server, tmp_path, capsys, monkeypatch):
    """A misspelt name: the error lists the names the picture held, among them the right one."""
    import client.render_cli as render_cli

    monkeypatch.setattr(render_cli, "FOLLOW_WAIT_S", 1.0)
    rc = main(["view", "--server", tank_server.address, "--follow", "tank9", "--role", "gateway",
               "--frames", "1", "--fps", "1", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and "'tank9' is not in the exercise" in err, err
    assert "'tank1'" in err and "the picture had" in err, err


def test_view_out_that_is_a_file_is_refused_by_name(tmp_path, capsys):
    """Before: "[Errno 17] File exists", after trying the server."""
    target = tmp_path / "a_file"
    target.write_text("x")
    t0 = time.monotonic()
    rc = main(["view", "--server", "127.0.0.1:52799", "--follow", "x", "--frames", "1", "--fps", "1", "--out",
               str(target)])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "is a file" in err
    assert time.monotonic() - t0 < 5.0  # before any connection


# --------------------------------------------------------------------------- 4: altitude


def test_camera_altitude_is_bounded_by_name(hgt_alps, tmp_path, capsys):
    """Before: OverflowError in the fog's (h / range) ** 2, after loading the terrain."""
    rc = main(["render", "--dem", str(hgt_alps), "--camera", "47.2,9.3,1e200,0,-90", "--out",
               str(tmp_path / "a.png")])
    err = capsys.readouterr().err
    assert rc == 2 and "--camera" in err and "ALT_MSL_M" in err and "1e+08" in err


def test_the_fog_takes_any_height(alps):
    with Renderer(alps, 32, 24, window_m=2000.0, horizon_m=0.0) as r:
        r.render(Camera.from_geodetic(47.2, 9.3, 3000.0, 0.0, -10.0))
        frame = r._frame(Camera.from_geodetic(47.2, 9.3, 1e200, 0.0, -90.0))
        assert frame.fog_density == 0.0


# --------------------------------------------------------------------------- 5: --out formats


@pytest.mark.parametrize("ext", [".blp", ".xbm", ".msp", ".palm", ".h5", ".bufr", ".grib"])
def test_out_in_a_format_that_cannot_hold_a_frame_is_refused_first(tmp_path, capsys, ext):
    """Before: each failed after the render (.blp with a traceback). The DEM named does not exist,
    so an error about --out shows it came first."""
    rc = main(["render", "--dem", str(tmp_path / "missing.hgt"), "--camera", "47.2,9.3,3000,0,-10", "--out",
               str(tmp_path / f"frame{ext}")])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "Pillow cannot write an RGB frame" in err, err


def test_out_under_a_file_is_refused_first(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    rc = main(["render", "--dem", str(tmp_path / "missing.hgt"), "--camera", "47.2,9.3,3000,0,-10", "--out",
               str(tmp_path / "f" / "frame.png")])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "is a file, not a directory" in err, err


# --------------------------------------------------------------------------- 7: the mesh's limit


def test_the_mesh_limit_names_the_options_that_set_its_area(tmp_path, capsys):
    """A procedural world's new blocks a call (4096) near a pole with a 300 km ring: the error
    names --window-km and --horizon-km (before, only "ask over a smaller area")."""
    from server.terrain_service import create_server
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    server, port = create_server(Terrain([ProceduralTerrain(seed=7)]), "127.0.0.1:52761")
    server.start()
    try:
        rc = main(["render", "--terrain", f"127.0.0.1:{port}", "--terrain-renderer", "mesh", "--camera",
                   "88,20,3000,0,-10", "--size", "32x24", "--horizon-km", "300", "--out", str(tmp_path / "m.png")])
    finally:
        server.stop(0)
    err = capsys.readouterr().err
    assert rc == 2 and "new procedural blocks" in err and "--window-km 20" in err and "--horizon-km 300" in err, err


# --------------------------------------------------------------------------- 8: sortie client


def test_client_render_options_need_an_agent_to_follow(tmp_path):
    """Before: the text observer ran and ignored them (here: waited for a server that is not there)."""
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "client", "--server", "127.0.0.1:52799", "--headless",
                          "--frames", "2", "--out", str(tmp_path / "c2")], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    assert "--headless, --frames, --out are rendering options" in run.stderr and "--follow" in run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "c2").exists()


def test_client_still_renders_with_an_agent(tank_server, tmp_path):
    rc = main(["client", "--server", tank_server.address, "--agent-type", "ground", "--frames", "1", "--fps", "5",
               "--out", str(tmp_path)])
    assert rc == 0 and (tmp_path / "frame_0000.png").exists()
    assert json.loads((tmp_path / "summary.json").read_text())["frames"] == 1
