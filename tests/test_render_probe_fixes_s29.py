"""Acceptance-probe fixes of the render client (session 29).

1. Over a lossy terrain store (step s) the sea at 0 m decodes anywhere within s/2 of it; the
   renderer's water test (terrain_mesh TERRAIN_COLOUR_GLSL) and the clipmap's coastline rule
   (clipmap_layer.straddles_sea_level) take the store's quantisation bound as the water level,
   as ``sortie terrain texture`` does (client/render/shading.water_level_m); a DEM keeps h <= 0.
2. A camera less than the near plane above the ground saw through it: the renderer brings the
   near plane in with the height above the ground (camera.near_plane_m).
3. ``sortie render --out`` without an image extension, or a directory: one line naming --out,
   before rendering.
4. Where no terrain data covers the camera the sea is drawn at 0 m: a camera below it is refused.
5. ``sortie view --observe-radius-km``: errors name the option, the value as given, km.

Real parts: a synthetic coast written as an ESRI grid and imported into a store at the default
step (1 m), the Alps SRTM tile, EGL (llvmpipe), small frames, the simulation server on loopback.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from client.render.camera import NEAR_FLOOR_M, Camera, near_plane_m
from client.render.clipmap_layer import (BLOCK, clipmap_factory, coastline_shift_m, decimation_errors,
                                         straddles_sea_level)
from client.render.profiles import profile
from client.render.renderer import Renderer

ARCSEC = 1.0 / 3600.0
MAGENTA = (255, 0, 255)
SEA_LAT = 45.02  # the synthetic coast: sea at exactly 0 m south of this


def _write_asc(path: Path, lat0: float, lon0: float, spacing: float, rows: int, cols: int, heights_of) -> Path:
    lats = lat0 + np.arange(rows) * spacing
    lons = lon0 + np.arange(cols) * spacing
    h = heights_of(*np.meshgrid(lats, lons, indexing="ij"))
    lines = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}", f"cellsize {spacing!r}"]
    lines += [" ".join(f"{v:.3f}" for v in row) for row in h[::-1]]
    path.write_text("\n".join(lines) + "\n")
    return path


def _coast(lat, lon):
    """Sea at exactly 0 m; the shore rising 2 m a post from 2 m; skerries of 6 m off it."""
    h = np.where(lat >= SEA_LAT, 2.0 + (lat - SEA_LAT) / ARCSEC * 2.0, 0.0)
    skerry = ((np.round((lon - 10.0) / ARCSEC) % 40) < 4) & (np.abs(lat - (SEA_LAT - 0.004)) < 2.5 * ARCSEC)
    return np.where(skerry, 6.0, h)


@pytest.fixture(scope="module")
def coast(tmp_path_factory):
    """(the DEM as a Terrain, the store at the default step of 1 m as a Terrain)."""
    from terrain.dem import read_dem
    from terrain.store import StoreSource, TerrainStore
    from terrain.store_import import import_dems
    from terrain.terrain import Terrain

    d = tmp_path_factory.mktemp("coast")
    asc = _write_asc(d / "coast.asc", 45.0, 10.0, ARCSEC, 121, 181, _coast)
    import_dems([asc], d / "store", step_m=1.0)
    return Terrain([read_dem(asc)]), Terrain([StoreSource(TerrainStore(d / "store"))])


def _water(image: np.ndarray) -> np.ndarray:
    img = image.astype(int)
    return (img[..., 2] > img[..., 1] + 10) & ~np.all(img == MAGENTA, axis=-1)


def _frame(terrain, layer: str, camera: Camera, size=(160, 120)):
    factory = clipmap_factory(terrain, **profile("observer").layer_args()) if layer == "clipmap" else None
    with Renderer(terrain, *size, flat_sky_rgb=MAGENTA, terrain_layer_factory=factory, window_m=4000.0,
                  horizon_m=8000.0) as r:
        image = r.render(camera)
        return image, r.water_level_m, r.terrain_layer


# --------------------------------------------------------------------------- 1: a lossy store's sea


@pytest.mark.parametrize("layer", ["clipmap", "mesh"])
def test_a_lossy_stores_sea_is_drawn_as_water_as_over_the_dem(coast, layer):
    """Before: 3133 (clipmap) and 3329 (mesh) of 19,200 pixels of sea in the DEM's frame were land
    in the store's (the posts of the 0 m sea decode within +-0.5 m, about half of them above 0)."""
    dem, store = coast
    camera = Camera.from_geodetic(SEA_LAT, 10.025, 3000.0, 0.0, -90.0, fov_x_deg=60.0)
    by_dem, dem_level, _ = _frame(dem, layer, camera)
    by_store, store_level, drawn = _frame(store, layer, camera)
    assert dem_level == 0.0 and store_level == pytest.approx(0.5)  # a DEM keeps h <= 0
    if layer == "clipmap":
        assert drawn.clipmap.water_level_m == pytest.approx(0.5)  # its class map and coastline rule
    wd, ws = _water(by_dem), _water(by_store)
    assert 0.3 < wd.mean() < 0.7  # a coast in the frame
    assert np.count_nonzero(wd & ~ws) < 0.01 * wd.size, np.count_nonzero(wd & ~ws)
    # The price (docs/STORE.md): ground within s/2 of sea level is water too; here the shore starts
    # at 2 m, and the store's own lattice moves the skerries' outlines by a post or so.
    assert np.count_nonzero(ws != wd) < 0.02 * wd.size, np.count_nonzero(ws != wd)


def test_the_coastline_rule_takes_the_water_level():
    """A block whose sea posts decoded a little above 0 m (0.3 m: water over a store of step 1 m)
    beside 20 m land straddles the water level: decimated only within the coastline's bound.
    Before, it straddled nothing (every post > 0) and a stride could move that coast freely."""
    n = 2 * BLOCK + 1
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    heights = np.where(j < BLOCK // 2, 0.3, 20.0)
    heights[0, 0] = -0.2  # (a block holding some posts <= 0 straddles either way)
    pos = np.stack([90.0 * j, 90.0 * i, heights], -1).astype(np.float64)
    texel = np.zeros((n, n, 4))
    texel[..., 3] = heights
    level = SimpleNamespace(pos_ecef=pos, texel=texel)
    blk = np.array([[0, BLOCK, BLOCK, 2 * BLOCK], [BLOCK, 0, 2 * BLOCK, BLOCK]], np.int32)
    assert straddles_sea_level(blk, level, n).tolist() == [False, False]  # dry land / sea "above 0"
    assert straddles_sea_level(blk, level, n, 0.5).tolist() == [False, True]
    assert straddles_sea_level(np.array([[0, 0, BLOCK, BLOCK]], np.int32), level, n).tolist() == [True]  # -0.2 m
    err0, err = decimation_errors(blk, level, n), decimation_errors(blk, level, n, 0.5)
    shift = coastline_shift_m(blk[1:], level, n)[0]
    assert np.all(err0[1] < shift) and np.all(err[1] >= shift - 1e-9)
    assert np.array_equal(err0[0], err[0])


def test_the_clipmap_over_a_store_decimates_with_its_water_level(coast):
    """The layer's cached decimation errors are those of the store's water level (0.5 m)."""
    _, store = coast
    camera = Camera.from_geodetic(SEA_LAT, 10.025, 3000.0, 0.0, -90.0, fov_x_deg=60.0)
    factory = clipmap_factory(store, **profile("observer").layer_args())
    with Renderer(store, 96, 72, flat_sky_rgb=MAGENTA, terrain_layer_factory=factory) as r:
        r.render(camera)
        layer = r.terrain_layer
        c = layer.clipmap
        assert layer._errors and c.water_level_m == pytest.approx(0.5)
        for k, (_, errors, _, blk) in layer._errors.items():
            assert np.array_equal(errors, decimation_errors(blk, c.levels[k], c.n, 0.5)), k


# --------------------------------------------------------------------------- 2: the near plane

@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


GROUND = (47.35, 9.62)  # 415.0 m MSL, nearly flat


@pytest.mark.parametrize("layer", ["clipmap", "mesh"])
@pytest.mark.parametrize("above_m", [0.5, 0.05])
def test_a_camera_just_above_the_ground_sees_the_ground(alps, layer, above_m):
    """Looking 45 degrees down from 0.5 m (before: 36k of 43k pixels sky through a 1 m near
    plane) and from 5 cm: no pixel of sky."""
    ground = float(alps.heights(np.array([GROUND[0]]), np.array([GROUND[1]])).height_msl_m[0])
    camera = Camera.from_geodetic(*GROUND, ground + above_m, 0.0, -45.0, fov_x_deg=60.0)
    image, _, _ = _frame(alps, layer, camera, size=(96, 72))
    sky = np.all(image == MAGENTA, axis=-1)
    assert not sky.any(), int(sky.sum())


def test_the_near_plane_follows_the_height_above_the_ground(alps):
    camera = Camera.from_geodetic(*GROUND, 1000.0, 0.0, -45.0, fov_x_deg=60.0)
    fx, fy = camera.focal(160, 90)
    cos_corner = 1.0 / math.sqrt(1.0 + fx ** -2 + fy ** -2)
    assert near_plane_m(camera, 160, 90, 585.0) == camera.near_m == 1.0  # high up: unchanged
    assert near_plane_m(camera, 160, 90, 0.5) == pytest.approx(0.25 * cos_corner)
    assert near_plane_m(camera, 160, 90, 0.0) == near_plane_m(camera, 160, 90, -3.0) == NEAR_FLOOR_M
    assert near_plane_m(camera, 160, 90, math.nan) == 1.0
    # The renderer measures the height above the highest post of the cell under the camera.
    low = Camera.from_geodetic(*GROUND, 415.5, 0.0, -45.0, fov_x_deg=60.0)
    with Renderer(alps, 32, 24, flat_sky_rgb=MAGENTA,
                  terrain_layer_factory=clipmap_factory(alps, **profile("observer").layer_args())) as r:
        r.render(low)
        h = r.height_above_ground_m(low)
        assert 0.0 <= h <= 0.5 and r._last_near == pytest.approx(near_plane_m(low, 32, 24, h))
        # A camera over no data (the sea at 0 m there)
        assert r.height_above_ground_m(Camera.from_geodetic(0.0, 0.0, 2.0)) == pytest.approx(2.0, abs=1e-6)


# --------------------------------------------------------------------------- 3-5: the CLI

def test_render_out_without_an_image_extension_or_a_directory_is_refused_before_rendering(tmp_path, capsys):
    from sortie.cli import main

    missing = str(tmp_path / "no.hgt")  # never opened: --out is checked first
    for out in (tmp_path / "frame_noext", tmp_path):
        rc = main(["render", "--dem", missing, "--camera", "47.25,9.34,3000,0,-10", "--size", "32x24",
                   "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and "sortie render: error: --out: " in err and repr(str(out)) in err, err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_camera_below_the_sea_where_no_terrain_covers_is_refused(hgt_alps, tmp_path, capsys):
    from sortie.cli import main

    out = tmp_path / "u.png"
    rc = main(["render", "--dem", str(hgt_alps), "--camera", "0,0,-1000000,0,-10", "--size", "32x24",
               "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "--camera: altitude -1e+06 m MSL is below sea level" in err and not out.exists(), err
    assert main(["render", "--dem", str(hgt_alps), "--camera", "0,0,10,0,-10", "--size", "32x24",
                 "--terrain-renderer", "mesh", "--out", str(out)]) == 0  # above the sea: a frame
    assert out.exists()


def test_view_observe_radius_errors_name_the_option_in_km(alps, hgt_alps, tmp_path, capsys):
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World
    from sortie.cli import main

    base = ["view", "--agent-type", "aircraft", "--frames", "1", "--fps", "1", "--out", str(tmp_path / "v"),
            "--role", "observer"]
    assert main([*base, "--server", "127.0.0.1:1", "--observe-radius-km", "-5"]) == 2  # before connecting
    err = capsys.readouterr().err
    assert "sortie view: error: --observe-radius-km: must be a finite number of km > 0 (got -5.0)" in err, err
    w = World(alps)
    srv = SimulationServer(w, ServerConfig(exercise_name="radius", terrain=f"dem:{hgt_alps}"))
    srv.start()
    try:
        assert main([*base, "--server", srv.address, "--observe-radius-km", "1e9"]) == 2
    finally:
        srv.stop(0.5)
        w.close()
    err = capsys.readouterr().err
    assert "sortie view: error: --observe-radius-km: must be in (0, " in err and "] km" in err, err
    assert "(got 1000000000.0)" in err and "observer_radius_m" not in err, err
