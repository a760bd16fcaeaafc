"""A command is kept only for the session that owns the agent when it is kept (acceptance
probe, pilot). A pilot streaming stick commands while it left: the service validated a command
(its session still held the agent), the Leave released the agent on another thread, and the
command was then kept after the release, journalled between the release and the next claim;
the released f16 flew on the departed pilot's stick instead of its scenario hold, and crashed
into the sea (3 of 160 leaves made mid-stream). World.command now checks the owner under the
world's lock, where release clears it."""

import pytest

from fdm.aircraft import FlatTerrain, InitialConditions
from server.aircraft_host import LocalAircraftHost
from server.world import World
from sortie.errors import PermissionDenied


class Journal:
    def __init__(self):
        self.inputs = []

    def on_input(self, tick, kind, entity_id, fields):
        self.inputs.append((kind, entity_id, fields.get("command")))

    def on_tick(self, snapshot, infos):
        pass

    def on_event(self, tick, ev):
        pass


@pytest.fixture()
def world():
    w = World(FlatTerrain(400.0), aircraft_host=LocalAircraftHost(FlatTerrain(400.0), 1.0 / 120.0))
    e = w.spawn_aircraft("held", "f16", InitialConditions(47.0, 9.0, 3000.0, heading_deg=0.0, speed_mps=200.0),
                         controllable=True, hold={"heading_deg": 0.0, "alt_msl_m": 3000.0, "speed_mps": 200.0})
    yield w, e.id
    w.close()


def test_a_command_of_a_session_that_no_longer_owns_the_agent_is_refused_and_not_journalled(world):
    w, agent = world
    journal = Journal()
    w.attach_recorder(journal)
    w.claim(agent, "pilot-a")
    w.command(agent, "stick", {"roll": 0.3}, owner="pilot-a")  # its own: kept
    w.tick()
    w.release(agent)  # its Leave, on another thread, between the service's check and the keep
    with pytest.raises(PermissionDenied) as e:
        w.command(agent, "stick", {"roll": 0.3}, owner="pilot-a")
    assert "held" in str(e.value)
    w.claim(agent, "pilot-b")  # the next pilot: the old session's command does not reach it either
    with pytest.raises(PermissionDenied):
        w.command(agent, "stick", {"roll": 0.3}, owner="pilot-a")
    w.command(agent, "stick", {"roll": -0.1}, owner="pilot-b")
    kinds = [(k, c) for k, i, c in journal.inputs if i == agent]
    release = kinds.index(("release", None))
    claim_b = len(kinds) - 1 - kinds[::-1].index(("claim", None))
    assert ("command", "stick") not in kinds[release:claim_b]  # nothing of pilot-a's after its release
    assert kinds[-1] == ("command", "stick")  # pilot-b's


def test_a_command_without_an_owner_is_the_callers_business(world):
    w, agent = world
    w.command(agent, "autopilot", {"heading_deg": 90.0})  # re-simulation and in-process use: unchanged
    w.tick()
