"""Hostile requests against a real simulation server, generated: joins and control streams.

Any join (names of any text, any role number, observers anywhere with any radius)
and any control message (a real or forged token, any agent id, stick, autopilot
or drive values of any float, several in one stream) gets either success or a
client-error status with a message; never INTERNAL or UNKNOWN. Throughout, an
observer's Watch keeps receiving updates and the world keeps ticking, and a
valid command still reaches the aircraft after the run.
"""

from __future__ import annotations

import grpc
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client.sim_client import SimClient
from fdm.aircraft import InitialConditions
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc
from server_helpers import rpc_outcome

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

edges = st.sampled_from([0.0, -0.0, 1.0, -1.0, 0.5, 90.0, -90.0, 180.0, 360.0, 1e308, -1e308, 5e-324])
any_float = st.one_of(st.floats(allow_nan=True, allow_infinity=True), edges, st.floats(-1.0, 1.0))
maybe = st.one_of(st.none(), any_float)


@pytest.fixture(scope="module")
def running(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    w = World(Terrain([read_dem(hgt_alps)]))
    w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     controllable=True)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, controllable=True)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45)
    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=2.0, vanished_timeout_s=60.0))
    srv.start()
    obs = SimClient(srv.address)
    obs.join("watcher", "observer", observer=(47.35, 9.45, 100_000.0))
    picture = obs.watch()
    assert picture.snapshot_received.wait(20.0)
    pilot = SimClient(srv.address)
    agent = pilot.join("pilot", "pilot", agent_name="viper1")
    channel = grpc.insecure_channel(srv.address)
    yield srv, pb_grpc.SimulationServiceStub(channel), picture, pilot, agent
    channel.close()
    pilot.close()
    obs.close()
    srv.stop(0.5)


@FUZZ
@given(name=st.one_of(st.text(max_size=80), st.text("abcxyz-0", min_size=1, max_size=12)),
       role=st.one_of(st.integers(-2, 6), st.sampled_from([pb.ROLE_PILOT, pb.ROLE_DRIVER, pb.ROLE_OBSERVER])),
       agent=st.one_of(st.text(max_size=20), st.sampled_from(["", "viper1", "tank1", "sam1"])),
       where=st.one_of(st.tuples(any_float, any_float, any_float),
                       st.tuples(st.floats(-90, 90), st.floats(-180, 180), st.floats(1.0, 500_000.0))))
def test_joins(running, name, role, agent, where):
    srv, stub, _, _, _ = running
    r = rpc_outcome(lambda: stub.Join(pb.JoinRequest(client_name=name, role=role, agent_name=agent,
                                                  observer_lat_deg=where[0], observer_lon_deg=where[1],
                                                  observer_radius_m=where[2]), timeout=10))
    if isinstance(r, pb.JoinResponse):  # leave again: the fuzz must not use up the agents
        stub.Leave(pb.LeaveRequest(session_token=r.session_token), timeout=10)


@FUZZ
@given(data=st.data(), forged=st.booleans(), n=st.integers(1, 4))
def test_control_streams(running, data, forged, n):
    srv, stub, _, pilot, agent = running
    kinds = st.sampled_from(["stick", "autopilot", "drive"])
    msgs = []
    for _ in range(n):
        token = data.draw(st.text(max_size=40)) if forged else pilot.token
        agent_id = data.draw(st.one_of(st.just(agent), st.integers(0, 2**64 - 1)))
        kind = data.draw(kinds)
        if kind == "stick":
            values = {k: v for k in ("pitch", "roll", "yaw", "throttle", "mixture", "flaps", "brakes")
                      if (v := data.draw(maybe)) is not None}
            cmd = {"stick": pb.StickControls(**values)}
        elif kind == "autopilot":
            values = {k: v for k in ("heading_deg", "alt_msl_m", "speed_mps") if (v := data.draw(maybe)) is not None}
            cmd = {"autopilot": pb.AutopilotTargets(**values)}
        else:
            cmd = {"drive": pb.DriveControls(speed_mps=data.draw(any_float), yaw_rate_dps=data.draw(any_float))}
        msgs.append(pb.ControlInput(session_token=token, agent_id=agent_id, **cmd))
    rpc_outcome(lambda: stub.SendControls(iter(msgs), timeout=10))


def test_still_serving_after_the_fuzz(running):
    """Runs last in this file: the watcher kept getting updates, and a valid command lands."""
    srv, _, picture, pilot, agent = running
    before = picture.updates
    assert picture.alive and picture.error is None
    with pilot.controls() as c:
        c.stick(pitch=0.1, throttle=0.8)
    assert picture.wait_for(lambda p: p.updates > before + 3, 20.0)
    assert srv.world.aircraft_controls(agent).pitch == 0.1
