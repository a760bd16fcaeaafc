"""Target-area insets end to end: the server's terrain, a terrain service started with
--insets and a render client all answer inside the area from the same inset (what is drawn
and what collides agree), the clipmap is lowered beneath it, and the client draws it."""

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from server.process import ServiceProcess
from server.scenario import load_scenario
from server.sim_server import open_terrain_source, terrain_spec

SCENARIO = "data/scenarios/grand_canyon.toml"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def canyon():
    scenario = load_scenario(SCENARIO)
    spec = terrain_spec(scenario)
    return scenario, spec, open_terrain_source(**spec)


def area_points(scenario, n=400, seed=3):
    a = scenario.target_areas[0]
    lat = np.array([p[0] for p in a.polygon])
    lon = np.array([p[1] for p in a.polygon])
    rng = np.random.default_rng(seed)
    return (rng.uniform(lat.min() + 0.002, lat.max() - 0.002, n), rng.uniform(lon.min() + 0.002, lon.max() - 0.002, n))


def test_the_server_terrain_answers_inside_the_area_from_its_inset(canyon):
    scenario, spec, terrain = canyon
    assert scenario.terrain.insets and spec["target_areas"][0][0] == "rim-overlook"
    assert [s["kind"] for s in terrain.describe()][0] == "inset"
    from server.sim_server import server_config

    assert server_config(scenario).insets
    lat, lon = area_points(scenario)
    plain = open_terrain_source(dem=spec["dem"])
    d = terrain.heights(lat, lon).height_msl_m - plain.heights(lat, lon).height_msl_m
    assert np.abs(d).max() > 0.5  # detail inside the area
    far_lat, far_lon = np.array([36.10, 36.20]), np.array([-113.0, -112.95])
    assert np.array_equal(terrain.heights(far_lat, far_lon).height_msl_m, plain.heights(far_lat, far_lon).height_msl_m)


def test_a_terrain_service_with_insets_answers_as_the_server_does(canyon):
    from client.terrain_client import TerrainClient

    scenario, spec, terrain = canyon
    lat, lon = area_points(scenario)
    with ServiceProcess(["terrain", "serve", "--dem", *spec["dem"], "--insets", SCENARIO]) as svc:
        with TerrainClient(svc.address) as client:
            assert client.metadata()["sources"][0]["kind"] == "inset"
            assert np.array_equal(client.heights(lat, lon).height_msl_m, terrain.heights(lat, lon).height_msl_m)


def test_the_clipmap_is_lowered_beneath_the_inset_and_the_client_draws_it(canyon, tmp_path):
    from client.render.camera import Camera
    from client.render.clipmap_layer import clipmap_factory
    from client.render.renderer import Renderer
    from terrain.inset import cutout_depth_m, insets_of

    scenario, spec, terrain = canyon
    insets = insets_of(terrain)
    assert len(insets) == 1
    cam = Camera.from_geodetic(36.281, -113.166, 2400.0, 90.0, -20.0, geoid_undulation_m=-27.0)
    with Renderer(terrain, 160, 90, geoid_undulation_m=-27.0, insets=insets,
                  terrain_layer_factory=clipmap_factory(terrain, levels=4, n=31, budget=10 ** 9,
                                                        geoid_undulation_m=-27.0, insets=insets)) as r:
        r.render(cam)
        assert r.inset_layers[0].triangles > 0
        c = r.terrain_layer.clipmap
        level = c.levels[0]
        texel, pos, _ = level.unrolled()
        reg = level.region
        ii, jj = np.meshgrid(np.arange(reg.i0, reg.i1 + 1), np.arange(reg.j0, reg.j1 + 1), indexing="ij")
        lat, lon = c.latlon(0, ii, jj)
        cut = cutout_depth_m(insets, lat.ravel(), lon.ravel(), c.spacing_m(0)).reshape(lat.shape)
        assert cut.max() > 10.0  # part of the finest level lies under the inset
        from terrain.geodesy import ecef_to_geodetic

        _, _, h = ecef_to_geodetic(pos)
        surface = terrain.heights(lat.ravel(), lon.ravel()).height_msl_m.reshape(lat.shape)
        assert np.allclose(h, surface - cut - 27.0, atol=1e-6)  # the drawn surface is cut, the heights are not
        assert np.array_equal(texel[..., 3], surface.astype(np.float32))


# In clean-clone CI runs this test's view waited its 15 s for tank1 in vain: with numba's cache
# cold, the world's second tick compiled the segment-intersection kernels for a path across the
# inset's edge (los.stack_partitions, 10-25 s), stalling the clock and every stream. When the
# test ran alone, the view's own start took longer than that stall. The server now compiles
# them before its clock starts (SimulationServer._warm_up, Terrain.warm_up).
def test_sortie_view_draws_the_servers_insets(canyon, tmp_path):
    from server.sim_server import build_world, server_config, SimulationServer

    scenario, spec, terrain = canyon
    world = build_world(scenario, terrain)
    srv = SimulationServer(world, server_config(scenario, "dem:" + ",".join(spec["dem"])))
    srv.start()
    try:
        # The world has ticked before the view joins (its first tick may compile the ground
        # vehicles' kernels in a fresh clone).
        deadline = time.monotonic() + 120.0
        while world.tick_count < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert world.tick_count >= 1, "the world never ticked"
        # The render client in a process of its own, as it runs beside a server.
        proc = subprocess.run([sys.executable, "-m", "sortie.cli", "view", "--server", srv.address, "--follow", "tank1",
                               "--frames", "1", "--fps", "5", "--out", str(tmp_path), "--size", "160x90",
                               "--profile", "helicopter"], capture_output=True, text=True, timeout=300, cwd=REPO)
        rc = proc.returncode
        in_world = sorted((e.name, e.destroyed) for e in list(world.entities.values()))
    finally:
        srv.stop(0.5)
        world.close()
    assert rc == 0, f"{proc.stderr[-3000:]}\nthe world's entities (name, destroyed): {in_world}; ticks {world.tick_count}"
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["insets"] == ["rim-overlook"] and s["frames"] == 1
