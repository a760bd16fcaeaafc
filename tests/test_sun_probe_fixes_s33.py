"""Probe fix (session 33): the renderer's sun is the exercise's.

The finding: a scenario's ``start_time`` "fixes the sun" (server/scenario.py; alps.toml: "09:00
local (CEST): sun from the south-east"), yet every frame was lit from azimuth 315, elevation 45
degrees (client/render/shading.py's defaults), whatever the time and place: no client read
WorldInfo.start_time and ``sortie render``/``sortie view`` had no time option.

Now ``Renderer.sun_time`` lights the terrain with terrain/sun.py's apparent sun at that instant
in the camera's sky (recomputed once a world second), ``sortie view`` sets it to WorldInfo.start_time
plus the picture's world time, ``sortie render --time`` to the instant given (fixed light without
it), and with the sun below the camera's horizon only the ambient term lights the terrain.

Real parts: EGL rendering (llvmpipe without a GPU), a DEM file, a simulation server on a port.
The terrain is a north-south ridge at 47.4 N, 9.5 E (the probe's place) with 25 degree east and
west faces; a camera straight down over its crest, heading north, has the west face in the left of
the frame and the east face in the right, tinted alike (the tint is by height, symmetric). The
expected ratio of their brightness is Lambert's (shading.py: AMBIENT + SUN x max(n . l, 0)) with l
from terrain.sun.sun_position: the bounds below are within 10 % of it (the frames measured 1-3 %
off: 8-bit rounding, the mesh's normals at the crest and the foot). At 07:00Z on 15 June the sun
is at azimuth 90.8, elevation 33.2 degrees there (the probe's figures): the east face 2.0 times
as bright as the west; the old fixed light made the west face 1.4 times as bright as the east.
"""

from __future__ import annotations

import json
import math
from datetime import datetime, timezone

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.renderer import Renderer
from client.render.shading import AMBIENT, SUN
from terrain.geodesy import enu_basis
from terrain.sun import sun_direction_enu, sun_position

LAT0, LON0 = 47.4, 9.5
CELL_DEG = 0.0005  # 37.6 m east, 55.7 m north
POSTS = 161
SLOPE_DEG = 25.0  # below shading.ROCK_SLOPE_DEG: both faces tinted, not rock
CREST_M, FOOT_M = 2000.0, 100.0
MORNING = datetime(2026, 6, 15, 7, tzinfo=timezone.utc)  # the Alps scenario's start_time
AFTERNOON = datetime(2026, 6, 15, 16, tzinfo=timezone.utc)
DUSK = datetime(2026, 6, 15, 20, tzinfo=timezone.utc)  # sun 5.8 degrees below the horizon, in the north-west
MIDNIGHT = datetime(2026, 6, 15, 22, tzinfo=timezone.utc)
W, H = 160, 120
WEST, EAST = np.s_[:, : W // 2 - 10], np.s_[:, W // 2 + 10:]  # the faces, clear of the crest's pixels
RATIO_TOLERANCE = 0.10
PORT = 53650


@pytest.fixture(scope="module")
def ridge_dem(tmp_path_factory):
    """An ESRI ASCII grid: a ridge along the meridian LON0, faces SLOPE_DEG east and west."""
    path = tmp_path_factory.mktemp("sun") / "ridge.asc"
    x_m = (np.arange(POSTS) - (POSTS - 1) / 2) * CELL_DEG * 111_320.0 * math.cos(math.radians(LAT0))
    h = np.maximum(CREST_M - np.abs(x_m) * math.tan(math.radians(SLOPE_DEG)), FOOT_M)
    half = CELL_DEG * (POSTS - 1) / 2
    head = [f"ncols {POSTS}", f"nrows {POSTS}", f"xllcenter {LON0 - half}", f"yllcenter {LAT0 - half}",
            f"cellsize {CELL_DEG}", "NODATA_value -9999"]
    path.write_text("\n".join(head + [" ".join(f"{v:.3f}" for v in h)] * POSTS) + "\n")
    return path


@pytest.fixture(scope="module")
def ridge(ridge_dem):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(ridge_dem)])


def sun_in_sky_deg(v_ecef, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(azimuth, elevation) degrees of an ECEF direction in the sky of (lat, lon)."""
    e, n, u = (float(b @ v_ecef) for b in enu_basis(lat_deg, lon_deg))
    return math.degrees(math.atan2(e, n)) % 360.0, math.degrees(math.atan2(u, math.hypot(e, n)))


def _overhead() -> Camera:
    return Camera.from_geodetic(LAT0, LON0, 4500.0, 0.0, -90.0, 0.0)  # sees the faces only, not the foot


def _faces(image) -> tuple[float, float]:
    img = np.asarray(image, np.float64)
    return float(img[WEST].mean()), float(img[EAST].mean())


def _lambert(when, face_east: bool) -> float:
    """Lambert's weight (shading.py) of a face under terrain.sun's sun at the ridge."""
    s = sun_position(when, LAT0, LON0, refraction=True)
    slope = math.radians(SLOPE_DEG)
    n = np.array([math.sin(slope) * (1.0 if face_east else -1.0), 0.0, math.cos(slope)])
    lit = float(s.elevation_deg) > 0.0
    return AMBIENT + SUN * lit * max(float(n @ sun_direction_enu(s.azimuth_deg, s.elevation_deg)), 0.0)


def _render(terrain, sun_time, camera=None, sea=False):
    """(image, the light vector its shader got (ECEF), its light weight, stats): the terrain's
    shader's, or with ``sea`` the sea shell's (a camera beyond the terrain)."""
    with Renderer(terrain, W, H, window_m=3000.0, horizon_m=0.0, fog=False, sea=sea, sun_time=sun_time) as r:
        image = r.render(camera or _overhead())
        program = (r.sea_layer if sea else r.terrain_layer).program
        with r.ctx:
            sun_local = np.array(program["u_sun"].value)
            light = program["u_sun_light"].value
        sun_ecef = sun_local @ r.origin.basis  # the shader's light vector, back in ECEF
        return image, sun_ecef, light, r.stats


def test_the_shading_light_vector_is_sun_position_at_the_camera(ridge):
    """The u_sun the terrain's shader was given, read back from GL, points where
    terrain.sun.sun_position puts the sun in the camera's sky: within 0.001 degree (float32);
    the probe's figures (azimuth 90.8, elevation 33.2 at 07:00Z) within 0.05. From a camera
    three degrees east (over the sea shell: no terrain there), the sun of that camera's sky (the
    origin rebased; not the first sky)."""
    for camera, sea in ((_overhead(), False), (Camera.from_geodetic(LAT0, LON0 + 3.0, 6000.0, 0.0, -90.0, 0.0), True)):
        lat, lon, _ = camera.geodetic()
        _, sun_ecef, light, stats = _render(ridge, MORNING, camera, sea)
        want = sun_position(MORNING, lat, lon, refraction=True)
        az, el = sun_in_sky_deg(sun_ecef / np.linalg.norm(sun_ecef), lat, lon)
        assert az == pytest.approx(float(want.azimuth_deg), abs=1e-3)
        assert el == pytest.approx(float(want.elevation_deg), abs=1e-3)
        assert light == 1.0
        assert (stats.sun_azimuth_deg, stats.sun_elevation_deg) == pytest.approx(
            (float(want.azimuth_deg), float(want.elevation_deg)), abs=1e-9)
    assert sun_in_sky_deg(sun_ecef, LAT0, LON0) != pytest.approx((az, el), abs=0.5)  # a different sky
    _, first, _, _ = _render(ridge, MORNING)
    assert sun_in_sky_deg(first, LAT0, LON0) == pytest.approx((90.8, 33.2), abs=0.05)


def test_the_slope_facing_the_sun_is_the_brighter(ridge):
    """07:00Z: the east face (towards the sun) brighter than the west, by Lambert's ratio (2.0)
    within 10 %; 16:00Z the other way round. Without a time, today's fixed light from the
    north-west: the west face the brighter (Lambert's 1.43)."""
    for when in (MORNING, AFTERNOON, None):
        image, _, _, _ = _render(ridge, when)
        west, east = _faces(image)
        if when is None:
            measured = west / east
            slope = math.radians(SLOPE_DEG)
            l_fixed = sun_direction_enu(315.0, 45.0)
            lit = [AMBIENT + SUN * max(float(np.array([s * math.sin(slope), 0.0, math.cos(slope)]) @ l_fixed), 0.0)
                   for s in (-1.0, 1.0)]
            expected = lit[0] / lit[1]
        else:
            towards_east = float(sun_position(when, LAT0, LON0).azimuth_deg) < 180.0
            bright, dim = (east, west) if towards_east else (west, east)
            measured = bright / dim
            expected = _lambert(when, towards_east) / _lambert(when, not towards_east)
        assert expected > 1.3
        assert measured == pytest.approx(expected, rel=RATIO_TOLERANCE), (when, west, east)


def test_night_is_ambient_only(ridge):
    """The sun below the horizon lights nothing: at dusk (5.8 degrees down in the north-west,
    where max(n . l, 0) alone lit the west face from below, n . l = 0.21) and at midnight both
    faces are alike (within half a level) and as bright as the ambient term alone makes them,
    not black: to the morning's east face as AMBIENT to that face's Lambert weight (0.39), within
    10 %. The light weight the shader got is 0."""
    morning_east = _faces(_render(ridge, MORNING)[0])[1]
    for when in (DUSK, MIDNIGHT):
        image, _, light, stats = _render(ridge, when)
        west, east = _faces(image)
        assert stats.sun_elevation_deg < 0.0 and light == 0.0
        assert abs(west - east) <= 0.5, (when, west, east)
        assert east / morning_east == pytest.approx(AMBIENT / _lambert(MORNING, True), rel=RATIO_TOLERANCE)


def test_a_fixed_sun_below_the_horizon_lights_from_nowhere(ridge):
    """Renderer's fixed sun given below the horizon (the dusk sun's azimuth and elevation) is
    ambient only too: the faces within half a level (the old shading lit the west face, which
    faces that sun, 1.4 times as bright as the east)."""
    dusk = sun_position(DUSK, LAT0, LON0, refraction=True)
    with Renderer(ridge, W, H, window_m=3000.0, horizon_m=0.0, fog=False, sea=False,
                  sun_azimuth_deg=float(dusk.azimuth_deg), sun_elevation_deg=float(dusk.elevation_deg)) as r:
        west, east = _faces(r.render(_overhead()))
    assert abs(west - east) <= 0.5, (west, east)


def test_the_sun_is_recomputed_once_a_world_second(ridge):
    """Frames 0.25 s apart: the ephemeris is evaluated at 0 s and 1 s only; a seek back by 2 s
    (a replay) evaluates it again; the sun of a numpy datetime64 is that of the same datetime."""
    from client.render.shading import SUN_UPDATE_S

    start = np.datetime64("2026-06-15T07:00:00", "us")
    with Renderer(ridge, 32, 24, window_m=3000.0, horizon_m=0.0, fog=False, sea=False) as r:
        for k in range(5):
            r.sun_time = start + np.timedelta64(250_000 * k, "us")
            r.render(_overhead())
        assert r.ephemeris.computed == 2
        assert SUN_UPDATE_S == 1.0
        r.sun_time = start - np.timedelta64(1, "s")
        r.render(_overhead())
        assert r.ephemeris.computed == 3
        want = sun_position(MORNING, LAT0, LON0, refraction=True)
        r.sun_time = start
        r.render(_overhead())
        assert (r.stats.sun_azimuth_deg, r.stats.sun_elevation_deg) == pytest.approx(
            (float(want.azimuth_deg), float(want.elevation_deg)), abs=1e-9)


def test_a_naive_or_bad_sun_time_is_refused_naming_it(ridge):
    from sortie.errors import InvalidArgument

    for bad in (datetime(2026, 6, 15, 7), "2026-06-15T07:00:00Z"):
        with pytest.raises(InvalidArgument, match="^sun_time: "):
            Renderer(ridge, 8, 8, window_m=3000.0, horizon_m=0.0, sun_time=bad)


def test_sortie_render_takes_time(ridge_dem, capsys):
    """--time lights by the sun of that instant (an offset is read as UTC: 09:00+02:00 is
    07:00Z); without it the fixed light (the west face the brighter), said on the output line;
    a time without a zone is refused as sortie terrain texture --time refuses it."""
    from PIL import Image

    from sortie.cli import main
    from sortie.errors import InvalidArgument
    from terrain.texture_cli import parse_time

    def render(out, *extra):
        rc = main(["render", "--dem", str(ridge_dem), "--camera", f"{LAT0},{LON0},4500,0,-90", "--out", str(out),
                   "--size", f"{W}x{H}", "--window-km", "3", "--horizon-km", "0", "--no-fog", *extra])
        return rc, capsys.readouterr()

    out = ridge_dem.parent / "frame.png"
    rc, cap = render(out, "--time", "2026-06-15T09:00:00+02:00")
    assert rc == 0, cap.err
    assert "sun at 2026-06-15T07:00:00Z, azimuth 90.8 elevation 33.2 degrees" in cap.out
    with Image.open(out) as img:
        west, east = _faces(img.convert("RGB"))
    assert east / west == pytest.approx(_lambert(MORNING, True) / _lambert(MORNING, False), rel=RATIO_TOLERANCE)

    rc, cap = render(out)
    assert rc == 0 and "fixed light (no --time), azimuth 315.0 elevation 45.0 degrees" in cap.out
    with Image.open(out) as img:
        west, east = _faces(img.convert("RGB"))
    assert west > 1.3 * east

    bad = "2026-06-15T07:00:00"
    with pytest.raises(InvalidArgument) as refused:
        parse_time(bad)
    rc, cap = render(ridge_dem.parent / "never.png", "--time", bad)
    assert rc == 2 and str(refused.value) in cap.err and "--time" in cap.err
    assert not (ridge_dem.parent / "never.png").exists()


def test_sortie_view_lights_with_the_exercise_clock(ridge, ridge_dem, tmp_path):
    """A live exercise starting 2026-06-15T07:00:00Z, its clock 10 x real time: every frame's
    sun is terrain.sun's at start_time + the frame's world time where the agent is (within
    0.01 degree: the sun moves 0.0042 degree in the SUN_UPDATE_S it may be old, the eye is 3 m
    from the agent's reference point), and the summary says whose it is."""
    from datetime import timedelta

    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World
    from sortie.cli import main

    w = World(ridge)
    w.spawn_ground(["tank1"], "m1a2", [LAT0 + 0.01], [LON0 + 0.01], 90.0, coalition="red")
    srv = SimulationServer(w, ServerConfig(exercise_name="sun test", start_time="2026-06-15T07:00:00Z",
                                           time_scale=10.0, terrain=f"dem:{ridge_dem}"),
                           address=f"127.0.0.1:{PORT}")
    srv.start()
    try:
        rc = main(["view", "--server", srv.address, "--agent-type", "ground", "--frames", "3", "--fps", "2",
                   "--out", str(tmp_path), "--size", "64x48", "--window-km", "2", "--horizon-km", "0"])
    finally:
        srv.stop(0.5)
        w.close()
    assert rc == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["start_time"] == "2026-06-15T07:00:00Z" and summary["sun"] == "exercise clock"
    frames = summary["per_frame"]
    assert len(frames) == 3 and frames[-1]["world_time_s"] > frames[0]["world_time_s"] + 5.0
    for f in frames:
        want = sun_position(MORNING + timedelta(seconds=f["world_time_s"]), f["lat_deg"], f["lon_deg"],
                            refraction=True)
        assert f["sun_azimuth_deg"] == pytest.approx(float(want.azimuth_deg), abs=0.01)
        assert f["sun_elevation_deg"] == pytest.approx(float(want.elevation_deg), abs=0.01)
    assert frames[0]["sun_azimuth_deg"] == pytest.approx(90.8, abs=0.1)


def test_an_unreadable_start_time_keeps_the_fixed_light(caplog):
    from client.render_cli import exercise_instant, exercise_start

    assert exercise_start("") is None and exercise_start("2026-06-15T07:00:00") is None
    assert "start_time" in caplog.text
    start = exercise_start("2026-06-15T09:00:00+02:00")
    assert start == np.datetime64("2026-06-15T07:00:00", "us")
    assert exercise_instant(start, 90.5) == np.datetime64("2026-06-15T07:01:30.5", "us")
    late = exercise_start("9999-12-31T23:59:59Z")  # world seconds carry it past datetime's year 9999
    assert exercise_instant(late, 3600.0) == np.datetime64("10000-01-01T00:59:59", "us")
