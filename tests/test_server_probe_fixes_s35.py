"""Simulation server, sessions and bots: findings of the acceptance probe (session 35).

1. ``sortie client --server``, ``sortie bot --server`` and the client library took any port
   number: gRPC keeps a port's low 16 bits, so a mistyped port beyond 65535 (a digit too many)
   joined whatever server listens on the port it wraps to, silently, as if it were the one
   meant. Now refused at once, naming --server (the library: ``address``) and the value.
2. ``sortie server --terrain`` (and ``sortie resim --take-over --terrain``) took any text: a
   port beyond 65535 reached another port's terrain service, and a name with no port waited
   10 s to say "no terrain service". Now refused at once as the scenario's [terrain] service
   is, naming --terrain and the value.
3. A landplane parked within a wheel base of the DEM's edge (a wheel beyond the last post,
   where no data reads as sea level) was refused as standing "on water" with the ground under it
   at 659 m; it is now refused as a wheel outside the terrain, naming the wheel's place. On the
   sea the refusal is still water's; a wheel base inside the edge it starts.

Real parts: a real simulation server on loopback gRPC, the real ``sortie`` command line (run in
this process, as the entry point runs it), the embedded SRTM tile.
"""

from __future__ import annotations

import re
import subprocess
import time

import numpy as np
import pytest

from conftest import REPO
from sortie.errors import InvalidArgument

SCENARIO = REPO / "data" / "scenarios" / "alps.toml"


def sortie(capsys, *args) -> subprocess.CompletedProcess:
    """A ``sortie`` command run in this process (sortie.cli.main, as the entry point runs it):
    its exit status (argparse's SystemExit included), stdout and stderr."""
    from sortie.cli import main

    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


@pytest.fixture(scope="module")
def empty_server(hgt_alps):
    """A running simulation server with no agents (what a wrapped port would reach)."""
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    srv = SimulationServer(World(Terrain([read_dem(hgt_alps)])), ServerConfig(exercise_name="the wrong one"))
    srv.start()
    yield srv
    srv.stop(0.5)


# -- 1. a port beyond 65535 joined another server ----------------------------------------------------

def test_the_client_library_refuses_a_port_beyond_65535_instead_of_joining_the_wrapped_one(empty_server):
    from client.sim_client import SimClient

    wrapped = f"127.0.0.1:{empty_server.port + 65536}"  # gRPC would dial empty_server's port
    with pytest.raises(InvalidArgument) as exc:
        with SimClient(wrapped) as sim:
            sim.join("obs", "observer", observer=(47.3, 9.5, 1000.0))
    assert exc.value.field == "address" and exc.value.value == wrapped
    assert "port 1..65535" in str(exc.value)
    with SimClient(empty_server.address) as sim:  # the right address still joins
        sim.join("obs", "observer", observer=(47.3, 9.5, 1000.0))
        assert sim.world_info.exercise_name == "the wrong one"


@pytest.mark.parametrize("command", ["client", "bot"])
def test_sortie_client_and_bot_refuse_a_port_beyond_65535_naming_server(empty_server, capsys, command):
    wrapped = f"127.0.0.1:{empty_server.port + 65536}"
    out = sortie(capsys, command, "--server", wrapped, "--duration", "0.5")
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert f"argument --server: must be HOST:PORT with a port 1..65535 (got '{wrapped}')" in out.stderr, out.stderr
    assert "observing" not in out.stdout and "bot-0" not in out.stdout  # nobody joined the wrapped server


@pytest.mark.parametrize("address", ["nonsense", "127.0.0.1", "127.0.0.1:0"])
def test_sortie_client_refuses_an_address_without_a_port_at_once(capsys, address):
    t0 = time.monotonic()
    out = sortie(capsys, "client", "--server", address, "--duration", "0.5")
    assert out.returncode == 2 and f"argument --server: must be HOST:PORT with a port 1..65535 (got '{address}')" \
        in out.stderr, out.stderr
    assert time.monotonic() - t0 < 5.0  # it waited 10 s for "no simulation server" before


# -- 2. sortie server --terrain ---------------------------------------------------------------------

@pytest.mark.parametrize("terrain", ["127.0.0.1:99999", "nonsense"])
def test_sortie_server_refuses_a_terrain_option_that_is_no_address_naming_it(capsys, terrain):
    t0 = time.monotonic()
    out = sortie(capsys, "server", "--scenario", SCENARIO, "--terrain", terrain, "--port", "0", "--no-record",
                 "--aircraft-workers", "0")
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert (f'--terrain: must be "host:port" with a port in [1, 65535] ("[::1]:50051" for IPv6), or a comma list '
            f"of them (replicas) (got '{terrain}')") in out.stderr, out.stderr
    assert "listening" not in out.stdout
    assert time.monotonic() - t0 < 5.0  # refused before any terrain service is dialled (10 s)


# -- 3. a landplane parked at the DEM's edge ----------------------------------------------------------

@pytest.fixture(scope="module")
def alps_terrain(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.mark.parametrize("lat, lon, heading", [(47.99999, 9.3, 0.0), (47.5, 9.99999, 90.0)])
def test_a_landplane_parked_with_a_wheel_off_the_dem_is_refused_as_off_the_terrain_not_on_water(
        alps_terrain, lat, lon, heading):
    # The tile ends at 48 N and 10 E; 1.1 m (0.7 m) inside it the ground is 659 m (and dry), but
    # a c172p's nose wheel, about 1.2 m ahead of its CG, stands beyond the last post.
    from fdm.aircraft import Aircraft, InitialConditions

    assert alps_terrain.heights(np.array([lat]), np.array([lon])).height_msl_m[0] > 300.0
    with pytest.raises(InvalidArgument) as exc:
        Aircraft("c172p", alps_terrain, InitialConditions(lat, lon, 0.0, heading_deg=heading, on_ground=True))
    assert exc.value.field == "lat_deg" and exc.value.value == lat
    assert "stands outside the terrain: no terrain data at (" in str(exc.value), exc.value
    assert "water" not in str(exc.value), exc.value
    # The wheel it names is off the tile, within a wheel base (3 m) of the CG.
    m = re.search(r"no terrain data at \((-?[\d.]+), (-?[\d.]+)\)", str(exc.value))
    wheel = (float(m[1]), float(m[2]))
    assert wheel[0] > 48.0 or wheel[1] > 10.0
    assert abs(wheel[0] - lat) * 111_200.0 < 3.0 and abs(wheel[1] - lon) * 75_000.0 < 3.0


def test_a_landplane_parked_a_wheel_base_inside_the_edge_starts_and_on_the_sea_is_still_water(
        alps_terrain, hgt_kattegat):
    from fdm.aircraft import Aircraft, InitialConditions
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    a = Aircraft("c172p", alps_terrain, InitialConditions(47.9999, 9.3, 0.0, heading_deg=0.0, on_ground=True))
    for _ in range(60):
        a.step()
    assert not a.crashed
    sea = Terrain([read_dem(hgt_kattegat)])  # the Kattegat at (57.5, 11.3): sea, 0 m
    with pytest.raises(InvalidArgument, match=r"is water \(height <= sea level, 0 m\): c172p is a landplane"):
        Aircraft("c172p", sea, InitialConditions(57.5, 11.3, 0.0, on_ground=True))


def test_a_scenario_aircraft_parked_at_the_dems_edge_names_the_agent_and_the_wheel(tmp_path, alps_terrain):
    from server.scenario import ScenarioError, load_scenario
    from server.sim_server import build_world

    path = tmp_path / "edge.toml"
    path.write_text(f"""
[exercise]
name = "edge"
start_time = "2026-06-15T08:00:00Z"
[terrain]
dem = ["{REPO / 'data' / 'dem' / 'N47E009.hgt'}"]
[[agents]]
name = "parked"
kind = "aircraft"
type = "c172p"
coalition = "blue"
lat_deg = 47.99999
lon_deg = 9.3
on_ground = true
""", encoding="utf-8")
    with pytest.raises(ScenarioError) as exc:
        build_world(load_scenario(path), alps_terrain)
    assert str(exc.value).startswith(f"{path}: agents[0]: 'parked' (c172p) cannot start: lat_deg: a wheel of c172p "
                                     "at (47.99999, 9.3) stands outside the terrain: no terrain data at (48.0000"), \
        exc.value
