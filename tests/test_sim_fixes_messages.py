"""Scenario and request errors that name what the user can change (server probe, bugs 4-6):
an inset target area off the terrain names its scenario key and file, before any inset is
built; the world-build errors carry the scenario file's name and advice a scenario can
follow; INVALID_ARGUMENT names the request's own field (``stick.pitch``,
``state.dead_reckoning``). Real scenario files, real `sortie server` runs, real JSBSim, real
gRPC on loopback."""

from __future__ import annotations

import math
import subprocess

import grpc
import pytest

from client.sim_client import SimClient
from server.process import sortie_command
from server.scenario import ScenarioError, load_scenario
from server.sim_server import build_world, open_terrain
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc
from terrain.geodesy import geodetic_to_ecef

from test_sim_fixes_streams import alps, server  # noqa: F401 (fixtures)
from test_sim_hardening import AGENTS, scenario_file

# [terrain] insets = true (the line lands in scenario_file's [terrain] table), an area well on
# the N47E009 tile (its 1 m inset takes seconds to build) and one whose centre is past its north edge.
INSET_AREAS = "insets = true\n" + AGENTS + """
    [[target_areas]]
    name = "rc"
    polygon = [[47.274, 9.545], [47.274, 9.565], [47.284, 9.585], [47.290, 9.570], [47.286, 9.545]]
    detail_m = 1.0

    [[target_areas]]
    name = "edge"
    polygon = [[47.995, 9.9], [47.995, 10.05], [48.01, 10.05], [48.01, 9.9]]
    detail_m = 5.0
"""


def sortie_server(path: str) -> subprocess.CompletedProcess:
    return subprocess.run([*sortie_command(), "server", "--scenario", path, "--port", "0", "--no-record",
                           "--duration", "0.2", "--aircraft-workers", "0"], capture_output=True, text=True,
                          timeout=120)


# -- bug 4: an inset target area off the terrain -------------------------------------------------

def test_an_inset_target_area_off_the_terrain_names_its_key_and_file_before_any_inset_is_built(
        tmp_path, monkeypatch):
    import terrain.inset as inset

    path = scenario_file(tmp_path, INSET_AREAS)
    done = sortie_server(path)
    assert done.returncode == 2, done.stderr
    assert (f"error: {path}: target_areas[1].polygon: target area 'edge' is off the terrain" in done.stderr
            and "no terrain source covers (48.002500, 9.975000)" in done.stderr
            and "(got [[47.995, 9.9], [47.995, 10.05], [48.01, 10.05], [48.01, 9.9]])" in done.stderr), done.stderr
    assert "area_polygon_latlon" not in done.stderr and "Traceback" not in done.stderr

    built = []  # the refusal comes before the seconds of building the good area's inset

    class Spy(inset.InsetSource):
        def __init__(self, *args, **kwargs):
            built.append(kwargs.get("name"))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(inset, "InsetSource", Spy)
    with pytest.raises(ScenarioError) as info:
        open_terrain(load_scenario(path))
    assert info.value.field == "target_areas[1].polygon" and str(info.value).startswith(f"{path}: ")
    assert built == []


# -- bug 5: world-build errors: the file's name, advice the scenario can follow ------------------

def test_a_static_off_the_terrain_is_told_to_move_it_not_to_give_an_altitude(tmp_path):
    path = scenario_file(tmp_path, AGENTS + """
        [[agents]]
        name = "sam1"
        kind = "static"
        type = "sam_site"
        coalition = "red"
        lat_deg = 10.35
        lon_deg = 9.45
        """)
    done = sortie_server(path)
    assert done.returncode == 2, done.stderr
    assert (f"error: {path}: agents[4]: 'sam1' is placed on the ground outside the terrain: no terrain data at "
            "(10.35, 9.45); move it onto the terrain (a static stands on the ground: it takes no alt_m)\n"
            in done.stderr), done.stderr
    assert "altitude above mean sea level" not in done.stderr


@pytest.mark.parametrize("agent, message", [
    ('kind = "static"\ntype = "radar"\nlat_deg = 50.0\nlon_deg = 9.5',
     "agents[0]: 'lost' is placed on the ground outside the terrain"),
    ('kind = "ground"\ntype = "m1a2"\nlat_deg = 10.29\nlon_deg = 9.59',
     "agents[0]: 'lost' (m1a2) is placed outside the terrain at (10.29, 9.59); move it onto land within the "
     "terrain"),
    ('kind = "aircraft"\ntype = "c172x"\nlat_deg = 50.0\nlon_deg = 9.5\nalt_m = 500.0\nalt_ref = "agl"\n'
     'speed_mps = 50.0', "agents[0]: 'lost' is placed at an altitude above ground outside the terrain"),
    ('kind = "aircraft"\ntype = "f16"\nlat_deg = 47.30\nlon_deg = 9.30\nalt_m = 3000.0\nspeed_mps = 5.0',
     "agents[0]: 'lost' (f16) cannot start: f16: JSBSim trim failed"),
    ('kind = "aircraft"\ntype = "f16"\nlat_deg = 47.25\nlon_deg = 9.34\nalt_m = 100.0\nspeed_mps = 200.0',
     "agents[0]: 'lost' (f16) cannot start: alt_m: an airborne start must be above the terrain"),
], ids=["static", "ground", "aircraft-agl", "trim", "below-terrain"])
def test_world_build_errors_name_the_scenario_file(tmp_path, agent, message):
    path = scenario_file(tmp_path, f'[[agents]]\nname = "lost"\ncoalition = "red"\n{agent}\n')
    scenario = load_scenario(path)
    with pytest.raises(ScenarioError) as info:
        build_world(scenario, open_terrain(scenario)[0])
    assert str(info.value).startswith(f"{path}: {message}"), str(info.value)
    # Advice names what a scenario can say: no trim=False (not a scenario key); on_ground = true is.
    assert "trim=False" not in str(info.value)
    if "trim failed" in message:
        assert str(info.value).endswith("; in the scenario, give it a speed_mps or alt_m it trims at, or start "
                                        "it on the ground (on_ground = true)")


# -- bug 6: INVALID_ARGUMENT names the request's field ---------------------------------------------

def test_invalid_stick_and_dead_reckoning_values_name_the_requests_fields(server):  # noqa: F811
    pilot, gateway = SimClient(server.address), SimClient(server.address)
    pilot.join("p", "pilot", agent_name="viper1")
    gateway.join("g", "gateway")
    stub = pb_grpc.SimulationServiceStub(grpc.insecure_channel(server.address))

    def refusal(call, msg) -> str:
        with pytest.raises(grpc.RpcError) as info:
            call(iter([msg]), timeout=10.0)
        assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT, info.value.details()
        return info.value.details()

    assert refusal(stub.SendControls, pb.ControlInput(
        session_token=pilot.token, agent_id=pilot.agent_id, stick=pb.StickControls(pitch=math.nan))
    ) == "stick.pitch: must be finite (got nan)"
    x, y, z = (float(v) for v in geodetic_to_ecef([47.4], [9.5], [3000.0])[0])
    details = refusal(stub.PublishExternal, pb.ExternalEntityUpdate(
        session_token=gateway.token, external_id="dis:1.1.1", name="e", kind=1, coalition="red",
        state=pb.EntityState(ecef_x_m=x, ecef_y_m=y, ecef_z_m=z, velocity_ecef_mps=[0, 0, 0],
                             orientation_wxyz=[1, 0, 0, 0], dead_reckoning=10)))
    assert details.startswith("state.dead_reckoning: must be a DIS dead-reckoning code ") and "(got 10)" in details
