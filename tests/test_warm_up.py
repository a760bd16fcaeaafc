"""Terrain.warm_up: after it, the queries a real-time caller makes compile nothing.

numba compiles a kernel on its first call in a process (or loads it from its cache): in a fresh
clone the world's first segment across a target area's inset edge compiled for 10-25 s inside a
tick (tests/test_insets_integration.py's view then saw nothing for its 15 s). Each check runs in a
process of its own, where nothing has been called yet, and counts the signatures the terrain
package's kernels hold (compiled, or loaded from numba's cache) before and after the queries.
"""

import json
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
