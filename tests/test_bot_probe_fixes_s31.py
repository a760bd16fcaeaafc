"""Bots and the autopilot on the ground (docs probe, round 31): `sortie bot --profile racetrack` on
the alps scenario wrecked the parked c172p at Altenrhein and commanded altitudes under the ground.

- The bot took the runway's height (401 m) for its base and sent legs of base +- 300 m (101 m MSL,
  300 m under the runway) and heading steps of 90 degrees on the take-off roll: now an aircraft
  below its floor (FLOOR_AGL_M over the highest terrain within reach) first climbs out on its
  heading at a speed it flies, and no leg is lower than that floor.
- The autopilot steered a heading step on the take-off roll with full pedal (G_STEER * error):
  at 20-26 m/s the c172p ground-looped onto a wing tip. The heading the pedals steer to now
  follows the target at a turn of ROLL_LATERAL_ACCEL_MPS2, and after lift-off the wings stay
  within 5 degrees of level up to 20 m (a 787-8 turning as it lifted off struck the runway).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from client import cli
from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.autopilot import Autopilot
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from sortie.errors import InvalidArgument

PILOT_PIECE = 4  # FDM steps per autopilot update: 120 Hz / server.aircraft_host.PILOT_HZ


def _ground_start(name: str, heading_deg: float = 100.0) -> Aircraft:
    return Aircraft(name, FlatTerrain(0.0), InitialConditions(-16.5, -68.2, 0.0, "msl", heading_deg, 0.0,
                                                               on_ground=True))


def _fly(ac: Aircraft, ap: Autopilot, until_s: float, each=None) -> None:
    """Fly as a host does (the pilot updated every PILOT_PIECE steps, for their time) until world
    time ``until_s`` or a crash; ``each(ac)`` after every piece."""
    while ac.time_s < until_s and not ac.crashed:
        ap.update(None, PILOT_PIECE * ac.dt)
        for _ in range(PILOT_PIECE):
            ac.step()
        if each is not None:
            each(ac)


# -- the autopilot on the ground ------------------------------------------------------------------------

@pytest.mark.parametrize("name, speed_mps, at_mps, step_deg", [
    ("c172p", 45.0, 26.0, 90.0),   # old: structure contact 1 s after the step
    ("c172p", 45.0, 24.0, -90.0),  # old: crashed
    ("c172p", 45.0, 20.0, 180.0),  # old: crashed at 28 m/s
    ("c172x", 30.0, 20.0, 90.0),   # old: crashed
    ("J3Cub", 30.0, 10.0, 180.0),  # a tail wheel; old: crashed
    ("787-8", 130.0, 40.0, 90.0),  # old: lifted off turning, structure contact 2 s later
])
def test_a_heading_step_on_the_take_off_roll_crashes_nothing(name, speed_mps, at_mps, step_deg):
    """Stated bounds: from a ground start (targets +300 m and a speed), a heading step commanded on
    the roll at ``at_mps`` crashes nothing in 90 s, the aircraft lifts off, and it ends within 10
    degrees of the new heading (it still turns)."""
    ac = _ground_start(name)
    ap = Autopilot(ac)
    ap.set_targets(100.0, 300.0, speed_mps)
    stepped = []

    def step_once(a):
        if not stepped and a.on_ground and a.state().ground_speed_mps >= at_mps:
            ap.set_targets((100.0 + step_deg) % 360.0, 300.0, speed_mps)
            stepped.append(a.time_s)

    _fly(ac, ap, 90.0, step_once)
    assert stepped, "the roll never reached the step's speed"
    assert not ac.crashed, [(e.kind, round(e.time_s, 2), e.detail) for e in ac.events]
    assert "takeoff" in [e.kind for e in ac.events]
    off = abs((ac.state().heading_deg - (100.0 + step_deg) + 180.0) % 360.0 - 180.0)
    assert off < 10.0, off


def test_a_taxi_still_turns_and_a_take_off_roll_still_holds_the_runway():
    """Guards of what the limit must leave alone. A c172p taxiing at 4 m/s (its altitude held: no
    take-off) turns 90 degrees within 12 s; a c172p's take-off roll holds its runway's heading
    within 2 degrees (the pedals' full authority against the propeller: a pedal limit of
    (5 m/s / v)^2 let it swing 4.9 degrees, the c172x's 32)."""
    ac = _ground_start("c172p")
    ap = Autopilot(ac)
    ap.set_targets(100.0, ac.state().alt_msl_m, 4.0)
    _fly(ac, ap, 15.0)
    assert ac.on_ground and 3.0 < ac.state().ground_speed_mps < 5.0, ac.state().ground_speed_mps
    ap.set_targets(190.0, ac.state().alt_msl_m, 4.0)
    turned_at = []
    _fly(ac, ap, 30.0, lambda a: turned_at.append(a.time_s) if not turned_at and abs(
        (a.state().heading_deg - 190.0 + 180.0) % 360.0 - 180.0) < 5.0 else None)
    assert not ac.crashed and ac.on_ground
    assert turned_at and turned_at[0] < 15.0 + 12.0, turned_at

    ac = _ground_start("c172p")
    ap = Autopilot(ac)
    ap.set_targets(100.0, 300.0, 45.0)
    worst = []
    _fly(ac, ap, 30.0, lambda a: worst.append(abs((a.state().heading_deg - 100.0 + 180.0) % 360.0 - 180.0))
         if a.on_ground else None)
    assert max(worst) < 2.0, max(worst)


# -- the bot's pilot ------------------------------------------------------------------------------------

RUNWAY_M = 401.0  # the parked c172p's altitude at Altenrhein, m MSL
HIGHEST_M = 430.0  # the highest terrain a fake reach holds


def _climb(pilot, ground):
    """Feed ``pilot`` a parked aircraft at RUNWAY_M on heading 100 that rolls, then climbs at
    3 m/s and takes every heading sent at once: (every command with the altitude at the time,
    the time the profile began)."""
    sent, began, t = [], None, 0.0
    alt, hdg = RUNWAY_M, 100.0
    while t < 400.0:
        speed = 0.0 if t < 1.0 else min(39.0, 2.0 * t)
        c = pilot.command(t, hdg, alt, speed, ground)
        if c is not None:
            sent.append((t, alt, c))
            hdg = c["heading_deg"]
            if began is None and pilot.goal_deg is not None:
                began = t
        if t > 20.0:
            alt += 3.0 * 0.5
        t += 0.5
    return sent, began


def test_a_parked_bots_aircraft_climbs_out_before_its_profile():
    """A parked aircraft's first command holds its heading and climbs to at least 600 m over the
    highest terrain in reach at 1.3 times its slowest trim speed (the c172p's 30 m/s: 39); no turn
    before it is FLOOR_AGL_M above that terrain; every altitude sent at least that (old: the
    first leg at the runway's height + 300 m, the next at 101 m MSL, turns on the roll)."""
    pilot = cli.BotPilot("racetrack", 5.0, aircraft=True, climb_speed_mps=cli.climb_speed_mps("c172p"))
    reaches = []

    def ground(reach_m):
        reaches.append(reach_m)
        return HIGHEST_M

    sent, began = _climb(pilot, ground)
    floor = HIGHEST_M + cli.FLOOR_AGL_M
    first = sent[0][2]
    assert first == {"heading_deg": 100.0, "alt_msl_m": floor + 2 * cli.ALT_STEP_M, "speed_mps": 39.0}, first
    assert began is not None
    for t, alt, c in sent:
        if t < began:
            assert c["heading_deg"] == 100.0, (t, c)
        assert c.get("alt_msl_m", math.inf) >= floor, (t, c)
    assert [alt for t, alt, c in sent if t == began][0] >= floor
    legs = [c["alt_msl_m"] for t, alt, c in sent if t >= began and "alt_msl_m" in c]
    assert legs[:2] == [floor + 2 * cli.ALT_STEP_M, floor], legs  # up, down: never below the floor
    assert min(reaches) >= cli.bot_reach_m(39.0, 5.0), min(reaches)


def test_without_terrain_a_standing_aircraft_takes_its_own_height_for_the_ground():
    """No terrain (a server that names none, DEMs not here): a parked aircraft's floor is its own
    height + FLOOR_AGL_M, and nothing below it is sent."""
    pilot = cli.BotPilot("patrol", 5.0, aircraft=True, climb_speed_mps=cli.climb_speed_mps("c172p"))
    sent, began = _climb(pilot, None)
    floor = RUNWAY_M + cli.FLOOR_AGL_M
    assert sent[0][2]["alt_msl_m"] >= floor + cli.ALT_STEP_M and began is not None
    assert all(c.get("alt_msl_m", math.inf) >= floor for t, alt, c in sent), sent


def test_a_standing_aircraft_of_a_type_with_no_known_speed_is_not_taken_off():
    pilot = cli.BotPilot("patrol", 5.0, aircraft=True, climb_speed_mps=cli.climb_speed_mps("B17"), name="fortress")
    assert cli.climb_speed_mps("B17") is None and cli.climb_speed_mps("c172p") == pytest.approx(39.0)
    with pytest.raises(InvalidArgument, match="agent: fortress stands on the ground"):
        pilot.command(0.0, 100.0, RUNWAY_M, 0.0, lambda reach_m: HIGHEST_M)


def test_the_highest_ground_in_reach_finds_a_peak_between_the_posts():
    """A cone 200 m high and 2 km wide at its foot, 600 m north-east of the centre of a 1 km
    reach: found within its slope over a post's spacing (1.2 * 2 * 1000 / 32 m * 0.2 = 15 m)."""
    lat0, lon0 = 47.48, 9.56
    peak_n, peak_e = 420.0, 420.0

    def heights(lat, lon):
        n = np.radians(lat - lat0) * cli.EARTH_RADIUS_M
        e = np.radians(lon - lon0) * cli.EARTH_RADIUS_M * math.cos(math.radians(lat0))
        return 400.0 + np.maximum(200.0 - 0.2 * np.hypot(n - peak_n, e - peak_e), 0.0)

    assert 600.0 - 15.0 <= cli.highest_ground_msl_m(heights, lat0, lon0, 1000.0) <= 600.0
    assert cli.highest_ground_msl_m(lambda lat, lon: np.full(len(lat), np.nan), lat0, lon0, 1000.0) is None


# -- a racetrack bot on a parked c172p, live --------------------------------------------------------------

@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.mark.slow  # ~25 s: 190 world s of a c172p's take-off and climb at x10
def test_a_racetrack_bot_takes_a_parked_c172p_off_and_flies_above_the_floor(alps, hgt_alps):
    """The alps scenario's altenrhein1 (a c172p parked on runway 10 at 401 m) flown by a racetrack
    bot that can open the server's terrain: it crashes nothing; every heading sent while it is on
    the ground is the runway's (old: 100 -> 190 -> 280 on the roll, a crash at 41 s); every
    altitude sent is at least FLOOR_AGL_M over the highest terrain under its whole flight (old:
    101 m MSL); it leaves the ground and begins its racetrack (two legs) above that floor."""
    w = World(alps)
    e = w.spawn_aircraft("altenrhein1", "c172p", InitialConditions(47.4850, 9.5600, 0.0, heading_deg=100.0,
                                                                   on_ground=True), controllable=True)
    commands, truth = [], []
    command = w.command

    def logged(entity_id, kind, values, **kw):  # (owner: the sending session)
        commands.append((w.time_s, dict(values)))
        return command(entity_id, kind, values, **kw)

    w.command = logged

    def record(world):
        ac = world.air._get(e.id)
        s = ac.state()
        truth.append((world.time_s, ac.on_ground, s.lat_deg, s.lon_deg, s.alt_msl_m))

    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=10.0, terrain=f"dem:{hgt_alps}"),
                           before_tick=record)
    srv.start()
    results, stop = [], threading.Event()
    t = threading.Thread(target=cli._bot, args=(srv.address, 0, "racetrack", 5.0, 0.0, results, stop), daemon=True)
    t.start()
    try:
        deadline = time.monotonic() + 90.0
        while w.time_s < 190.0 and time.monotonic() < deadline and t.is_alive():
            time.sleep(0.1)
        assert w.time_s >= 190.0, (w.time_s, results)
    finally:
        stop.set()
        t.join(10.0)
        srv.stop(0.1)
        crashed = w.is_wreck(w.entities[e.id])
        w.close()
    assert not crashed, commands
    times = np.array([r[0] for r in truth])
    on_ground = np.array([r[1] for r in truth])
    lat, lon, alt = (np.array([r[k] for r in truth]) for k in (2, 3, 4))
    assert not on_ground[-1] and alt[-1] > 401.0 + cli.FLOOR_AGL_M - 50.0, alt[-1]
    highest = float(np.nanmax(alps.heights(lat, lon).height_msl_m))
    for when, values in commands:
        k = max(int(np.searchsorted(times, when)) - 1, 0)
        if on_ground[k]:
            assert abs((values["heading_deg"] - 100.0 + 180.0) % 360.0 - 180.0) < 1.0, (when, values)
        assert values.get("alt_msl_m", math.inf) >= highest + cli.FLOOR_AGL_M, (when, values, highest)
    headings = {round(v["heading_deg"]) % 360 for _, v in commands}
    assert {100, 190, 280} <= headings, headings  # the racetrack began: its first half turn, in steps
    (_, agent, what), = results
    assert agent == e.id and not isinstance(what, cli.BotFailure), results
