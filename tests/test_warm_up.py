"""Terrain.warm_up: after it, the queries a real-time caller makes compile nothing.

numba compiles a kernel on its first call in a process (or loads it from its cache): in a fresh
clone the world's first segment across a target area's inset edge compiled for 10-25 s inside a
tick (tests/test_insets_integration.py's view then saw nothing for its 15 s). Each check runs in a
process of its own, where nothing has been called yet, and counts the signatures the terrain
package's kernels hold (compiled, or loaded from numba's cache) before and after the queries.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from server.scenario import load_scenario
from server.sim_server import open_terrain_source, terrain_spec

REPO = Path(__file__).resolve().parents[1]

PROBE = r"""
import json, sys
import numpy as np
from server.scenario import load_scenario
from server.sim_server import open_terrain_source, terrain_spec
from terrain.procedural import ProceduralTerrain
from terrain.terrain import Terrain

which = sys.argv[1]
if which == "canyon":
    terrain = open_terrain_source(**terrain_spec(load_scenario("data/scenarios/grand_canyon.toml")))
    near = (36.28, -113.16)
else:
    terrain = Terrain([ProceduralTerrain(seed=7)])
    near = (46.5, 8.0)
warm_s = terrain.warm_up(near=near)

def overloads():  # every compiled kernel of the terrain package, and how many signatures it holds
    from numba.core.registry import CPUDispatcher
    return {f"{m}.{k}": len(v.overloads) for m, mod in list(sys.modules.items()) if m.startswith("terrain.")
            for k, v in vars(mod).items() if isinstance(v, CPUDispatcher)}

before = overloads()
rng = np.random.default_rng(int(sys.argv[2]))
n = 64
if which == "canyon":  # inside the inset, across its edge, across the DEM's edge, and outside it
    lat_a = rng.uniform(36.05, 36.30, n); lon_a = rng.uniform(-113.18, -112.9, n)
    lat_b = lat_a + rng.uniform(-0.05, 0.05, n); lon_b = lon_a + rng.uniform(-0.05, 0.05, n)
    lat_b[:8] = 36.35; lon_b[8:16] = -112.80  # beyond the DEM's north and east edges
else:
    lat_a = near[0] + rng.uniform(-0.03, 0.03, n); lon_a = near[1] + rng.uniform(-0.03, 0.03, n)
    lat_b = lat_a + rng.uniform(-0.01, 0.01, n); lon_b = lon_a + rng.uniform(-0.01, 0.01, n)
g_a = terrain.heights(lat_a, lon_a).height_msl_m
g_b = terrain.heights(lat_b, lon_b).height_msl_m
h_a = np.where(np.isfinite(g_a), g_a, 1000.0) + rng.uniform(-20, 60, n)
h_b = np.where(np.isfinite(g_b), g_b, 1000.0) + rng.uniform(-60, 20, n)
hit = terrain.intersect(lat_a, lon_a, h_a, lat_b, lon_b, h_b).hit
terrain.line_of_sight(lat_a, lon_a, h_a, lat_b, lon_b, h_b)
terrain.normals(lat_b, lon_b)
after = overloads()
print(json.dumps({"warm_s": warm_s, "compiled": sorted(k for k, v in after.items() if v > before.get(k, 0)),
                  "hits": int(np.count_nonzero(hit))}))
"""


def _probe(which: str, seed: int) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE, which, str(seed)], capture_output=True, text=True,
                          timeout=600, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("seed", [1, 2])
def test_after_warm_up_queries_over_an_inset_and_its_dem_compile_nothing(seed):
    got = _probe("canyon", seed)
    assert got["compiled"] == [], got["compiled"]
    assert got["hits"] > 0  # the segments reach the ground: the contact paths ran
    assert got["warm_s"] >= 0.0


def test_after_warm_up_queries_over_the_procedural_world_compile_nothing():
    got = _probe("procedural", 3)
    assert got["compiled"] == [], got["compiled"]


def test_warm_up_changes_no_answer():
    """The warm-up only queries: the answers after it are those of a terrain never warmed."""
    spec = terrain_spec(load_scenario("data/scenarios/grand_canyon.toml"))
    cold, warm = open_terrain_source(**spec), open_terrain_source(**spec)
    warm.warm_up(near=(36.28, -113.16))
    rng = np.random.default_rng(5)
    lat, lon = rng.uniform(36.05, 36.30, 500), rng.uniform(-113.18, -112.9, 500)
    a, b = cold.heights(lat, lon), warm.heights(lat, lon)
    assert np.array_equal(a.height_msl_m, b.height_msl_m, equal_nan=True) and np.array_equal(a.status, b.status)
    h = a.height_msl_m + 30.0
    sa = cold.intersect(lat, lon, h, lat + 0.01, lon + 0.01, h - 80.0)
    sb = warm.intersect(lat, lon, h, lat + 0.01, lon + 0.01, h - 80.0)
    assert np.array_equal(sa.distance_m, sb.distance_m, equal_nan=True)


# -- the world's own kernels (server.warm_up) --------------------------------------------------------

WORLD_PROBE = r"""
import json, sys
import numpy as np

def overloads():  # every compiled kernel of the project's packages, and how many signatures it holds
    from numba.core.registry import CPUDispatcher
    return {f"{m}.{k}": len(v.overloads) for m, mod in list(sys.modules.items())
            if m.split(".")[0] in ("terrain", "server", "fdm")
            for k, v in vars(mod).items() if isinstance(v, CPUDispatcher)}

def main():
    from server.scenario import load_scenario
    from server.sim_server import SimulationServer, aircraft_host, build_world, open_terrain, server_config

    scenario = load_scenario(sys.argv[1])
    terrain, desc, factory = open_terrain(scenario, None, None)
    world = build_world(scenario, terrain, aircraft_host(scenario, terrain, factory, 0))
    config = server_config(scenario, desc)
    config.clock = "paused"  # the test ticks the world itself, after the start's warm-up
    server = SimulationServer(world, config, "127.0.0.1:0")
    entities, events = sorted(world.entities), world.events_since(0)[1]
    server.start()
    server.stop(0.5)
    untouched = {"time_s": world.time_s, "ticks": world.tick_count, "entities": sorted(world.entities) == entities,
                 "events": world.events_since(0)[1] == events}
    before = overloads()
    for _ in range(int(sys.argv[2])):
        world.tick()
    after = overloads()
    world.close()
    print(json.dumps({"compiled": sorted(k for k, v in after.items() if v > before.get(k, 0)),
                      "untouched": untouched, "ground": int(world.ground.n if world.ground is not None else 0)}))

if __name__ == "__main__":
    main()
"""


@pytest.mark.parametrize("scenario", ["alps", "grand_canyon"])
def test_after_the_start_a_worlds_ticks_compile_nothing(scenario, tmp_path):
    """The scenario's world (aircraft in process, a convoy on a route and vehicles off any:
    alps; one tank on a route over an inset: grand_canyon) started by its SimulationServer
    (which warms the terrain and then ticks a scratch world), then 40 ticks: no kernel of the
    terrain, server or fdm packages gains a signature in them; the start left the world
    itself with its own entities and events and the one tick a paused clock runs."""
    probe = tmp_path / "probe.py"
    probe.write_text(WORLD_PROBE)
    proc = subprocess.run([sys.executable, str(probe), f"data/scenarios/{scenario}.toml", "40"],
                          capture_output=True, text=True, timeout=600, cwd=REPO,
                          env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["compiled"] == [], got["compiled"]
    # the paused clock runs the world's first tick (a snapshot for whoever joins): the scratch
    # world's ticks are not the world's
    assert got["untouched"] == {"time_s": pytest.approx(1 / 30), "ticks": 1, "entities": True, "events": True}
    assert got["ground"] > 0


def test_warm_up_world_takes_the_first_place_with_ground_and_skips_the_sea():
    """The scratch world goes to the first place that takes ground vehicles: a place that is
    no place (NaN) or outside the data is passed over; none left, nothing is warmed and
    (seconds, None) says so. The world given lends only its terrain and rates."""
    from server.warm_up import warm_up_world
    from server.world import World

    spec = terrain_spec(load_scenario("data/scenarios/alps.toml"))
    terrain = open_terrain_source(**spec)
    world = World(terrain)
    try:
        seconds, place = warm_up_world(world, [(math.nan, 9.5), (10.0, 20.0), (47.35, 9.45)])
        assert place == (47.35, 9.45) and seconds > 0.0
        seconds, place = warm_up_world(world, [(10.0, 20.0)])
        assert place is None
        assert world.entities == {} and world.tick_count == 0
    finally:
        world.close()
