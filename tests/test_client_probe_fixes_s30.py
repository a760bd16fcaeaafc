"""Client library and bots (acceptance probe, round 30), against real in-process servers:

- `sortie bot` waits for a server still starting and exits 0, each bot's agent named, when
  the server ends the exercise (it ran on until a signal, then exited 1 with "agent None");
- a client stream the server has ended refuses a message (three were dropped silently);
- a bot counts its legs in world time: a leg begun while the clock is paused still ends, and
  a paused clock elapses none;
- aircraft bots fly their profile: a patrol box closes and a racetrack reverses (an f16 turns
  ~2.2 deg/s, so 90 degrees every 20 s never closed the box), at two altitudes only (the
  targets crept down by the overshoot, -20 m every two legs);
- a picture stops at its stream's end (it went on extrapolating), and a listener's exception
  ends it with that error (it read as the exercise's end, the call left open).
"""

from __future__ import annotations

import math
import subprocess
import threading
import time

import numpy as np
import pytest

from client import cli
from client.sim_client import SimClient
from fdm.aircraft import InitialConditions
from server.process import sortie_command
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from sortie.errors import SortieError
from terrain.geodesy import ecef_to_geodetic

BOT_PORT = 53040  # the subprocess test's server: the bot starts before it listens


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _tank_world(alps) -> World:
    """A world of one controllable m1a2 (entity 1): cheap to run, and it pivots on the spot."""
    w = World(alps)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, controllable=True)
    return w


def _logged_commands(world: World) -> list:
    """(world time, values) of every command the world takes, from now on."""
    log = []
    command = world.command

    def logged(entity_id, kind, values, **kw):  # (owner: the sending session)
        log.append((world.time_s, dict(values)))
        return command(entity_id, kind, values, **kw)

    world.command = logged
    return log


def _changes(values: list) -> list:
    """``values`` without repeats in a row (a bot sends its last command again every leg_s)."""
    return [v for k, v in enumerate(values) if k == 0 or v != values[k - 1]]


def _run_bot(address: str, profile: str, leg_s: float, duration_s: float = 0.0):
    """cli._bot on its own thread (as sortie bot runs each): (thread, results, stop event)."""
    results, stop = [], threading.Event()
    t = threading.Thread(target=cli._bot, args=(address, 0, profile, leg_s, duration_s, results, stop), daemon=True)
    t.start()
    return t, results, stop


# -- 1, 8: sortie bot and the server's start and end ------------------------------------------------

def test_sortie_bot_waits_for_the_server_and_exits_0_when_it_ends_the_exercise(alps):
    """Started 4 s before its server listens (it waits 10 s, as sortie client), with
    --duration 0 (until a signal): it joins, and exits 0 within 10 s of the exercise's end,
    each bot's line naming its agent and the end (it failed at once with UNAVAILABLE, and
    ran on past the end until SIGTERM)."""
    bot = subprocess.Popen([*sortie_command(), "bot", "--server", f"127.0.0.1:{BOT_PORT}", "--count", "1",
                            "--duration", "0", "--leg-s", "2"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    srv, w = None, _tank_world(alps)
    try:
        time.sleep(4.0)
        srv = SimulationServer(w, ServerConfig(clock="realtime"), address=f"127.0.0.1:{BOT_PORT}")
        srv.start()
        deadline = time.monotonic() + 20.0
        while w.entities[1].owner is None and time.monotonic() < deadline and bot.poll() is None:
            time.sleep(0.1)
        assert w.entities[1].owner is not None, "the bot never took its agent"
        time.sleep(1.0)
        srv.stop(0.5)
        ended = time.monotonic()
        out, _ = bot.communicate(timeout=30.0)
        took = time.monotonic() - ended
    finally:
        if bot.poll() is None:
            bot.kill()
        if srv is not None:
            srv.stop(0.1)
        w.close()
    assert bot.returncode == 0, out
    assert took < 10.0, took
    assert out.startswith("bot-0: agent 1: ") and "then the server ended the exercise at world time" in out, out


def _wait_for_a_driver(world, timeout_s: float = 10.0) -> None:
    """Until the bot has taken agent 1 (or the timeout)."""
    deadline = time.monotonic() + timeout_s
    while world.entities[1].owner is None and time.monotonic() < deadline:
        time.sleep(0.05)


def test_a_bot_ends_within_seconds_of_the_exercises_end(alps):
    """A bot with no --duration (until a signal) whose server ends the exercise: its thread
    ends within 5 s, its line naming its agent and the end, not a failure (it commanded on
    into a stream the server had ended, forever)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    t, results, stop = _run_bot(srv.address, "patrol", 2.0)
    try:
        _wait_for_a_driver(w)
        time.sleep(0.5)
        srv.stop(0.5)
        t.join(5.0)
        assert not t.is_alive(), "the bot ran on after the exercise's end"
    finally:
        stop.set()
        t.join(5.0)
        srv.stop(0.1)
        w.close()
    (k, agent, what), = results
    assert agent == 1 and "then the server ended the exercise at world time" in what, results
    assert not isinstance(what, cli.BotFailure)


def test_a_bot_whose_server_goes_away_names_its_agent_and_fails(alps):
    """A server gone without ending the exercise (its port closed under the bot): the bot's
    line names its agent and says so, and counts as a failure (sortie bot exits 1)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    t, results, stop = _run_bot(srv.address, "patrol", 2.0)
    try:
        _wait_for_a_driver(w)
        srv.grpc.stop(0).wait()  # no OK end of the streams: the connection drops
        t.join(15.0)
        assert not t.is_alive(), "the bot ran on after its server went away"
    finally:
        stop.set()
        srv.stop(0.1)
        w.close()
    (k, agent, what), = results
    assert agent == 1 and isinstance(what, cli.BotFailure), results


# -- 2: a client stream the server ended ---------------------------------------------------------------

def test_a_message_for_a_stream_the_server_ended_raises(alps):
    """After the server's end (srv.stop: the streams end OK) a command or an external
    entity's update raises naming the stream; none is dropped silently. A stream this
    client closed says so."""
    w, w2 = _tank_world(alps), _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    try:
        with SimClient(srv.address) as driver, SimClient(srv.address) as gateway:
            driver.join("d", "driver")
            gateway.join("g", "gateway")
            controls, external = driver.controls(), gateway.external()
            controls.autopilot(heading_deg=90.0, speed_mps=5.0)
            time.sleep(0.3)
            srv.stop(0.5)
            time.sleep(0.5)
            for k in range(3):
                with pytest.raises(SortieError, match=r"^SendControls: the stream has ended \(the server ended it"):
                    controls.autopilot(heading_deg=100.0 + k)
            with pytest.raises(SortieError, match=r"^PublishExternal: the stream has ended \(the server ended it"):
                external.remove("x")
            assert controls.close() == 1
        srv = SimulationServer(w2, ServerConfig(clock="realtime"))
        srv.start()
        with SimClient(srv.address) as driver:
            driver.join("d", "driver")
            controls = driver.controls()
            controls.drive(2.0)
            assert controls.close() == 1
            with pytest.raises(SortieError, match=r"^SendControls: the stream has ended \(this client closed it; "
                                                  r"1 messages accepted\)"):
                controls.drive(3.0)
    finally:
        srv.stop(0.1)
        w.close()
        w2.close()


# -- 3: legs in world time ---------------------------------------------------------------------------

def _wait_for_commands(commands: list, n: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while len(commands) < n and time.monotonic() < deadline:
        time.sleep(0.05)


def test_a_bot_begun_on_a_paused_clock_turns_once_it_runs(alps):
    """A bot whose first leg begins while the clock is paused turns once it runs, a leg of
    2 world s each (it waited leg_s / 1e-6 wall seconds: it never turned again)."""
    w = _tank_world(alps)
    commands = _logged_commands(w)
    srv = SimulationServer(w, ServerConfig(clock="paused", time_scale=10.0))
    srv.start()
    t, results, stop = _run_bot(srv.address, "patrol", 2.0)
    try:
        _wait_for_commands(commands, 1, 10.0)
        time.sleep(1.0)
        assert len(commands) == 1, commands  # the first leg's, on its heading: the paused world does not turn
        srv.set_clock("fast")  # x10: a 2-s leg and an m1a2's 90-degree pivot in about 1 wall second
        deadline = time.monotonic() + 8.0
        while len(_changes([round(v["heading_deg"]) for _, v in commands])) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        t.join(5.0)
        srv.stop(0.1)
        w.close()
    headings = _changes([round(v["heading_deg"]) % 360 for _, v in commands])
    assert headings[:4] == [45, 135, 225, 315], commands  # a right turn of 90 degrees a leg


def test_a_clock_paused_mid_leg_elapses_no_leg(alps):
    """A fast clock (x10, legs of 20 world s: 2 wall s) paused as a leg begins: no leg ends
    in 3 wall seconds of pause (legs were timed in wall seconds at the rate they began with,
    and this one ended during the pause)."""
    w = _tank_world(alps)
    commands = _logged_commands(w)
    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=10.0))
    srv.start()
    t, results, stop = _run_bot(srv.address, "patrol", 20.0)
    try:
        _wait_for_commands(commands, 2, 15.0)
        srv.set_clock("paused")
        before = len(commands)
        assert before == 2 and commands[1][1]["heading_deg"] != commands[0][1]["heading_deg"], commands
        time.sleep(3.0)
        assert len(commands) == before, commands[before:]
    finally:
        stop.set()
        t.join(5.0)
        srv.stop(0.1)
        w.close()


# -- 4, 5: aircraft fly their profile -------------------------------------------------------------------

LEG_S = 10.0
F16_SPEED_MPS = 200.0
F16_ALT_M = 3500.0


def _east_north(point_ecef):
    """The unit east and north vectors (3,) ECEF at a point (3,) ECEF m."""
    lat, lon, _ = ecef_to_geodetic(np.asarray(point_ecef, np.float64).reshape(1, 3))
    la, lo = math.radians(lat[0]), math.radians(lon[0])
    return (np.array([-math.sin(lo), math.cos(lo), 0.0]),
            np.array([-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)]))


def _fly_f16_bot(alps, profile: str, world_s: float):
    """An f16 at 200 m/s, 3500 m flown by a bot (legs of LEG_S) on a x16 clock until world
    time ``world_s``: (times (n,), east (n,), north (n,), track deg (n,), alt m MSL (n,), the
    commands, the bot's results), the server's truth at every tick sampled."""
    w = World(alps)
    w.spawn_aircraft("viper", "f16", InitialConditions(47.5, 9.5, F16_ALT_M, heading_deg=30.0,
                                                       speed_mps=F16_SPEED_MPS),
                     controllable=True, hold=dict(heading_deg=30.0, alt_msl_m=F16_ALT_M, speed_mps=F16_SPEED_MPS))
    commands = _logged_commands(w)
    truth = []
    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=16.0),
                           before_tick=lambda world: truth.append(world.snapshot))
    srv.start()
    t, results, stop = _run_bot(srv.address, profile, LEG_S)
    try:
        deadline = time.monotonic() + 120.0
        while w.time_s < world_s and time.monotonic() < deadline and t.is_alive():
            time.sleep(0.1)
        assert w.time_s >= world_s, (w.time_s, results)
    finally:
        stop.set()
        t.join(10.0)
        srv.stop(0.1)
        w.close()
    snaps = [s for s in truth if s is not None and len(s.ids)]
    times = np.array([s.time_s for s in snaps])
    ecef = np.array([s.ecef_m[0] for s in snaps])
    vel = np.array([s.vel_ecef_mps[0] for s in snaps])
    e, n = _east_north(ecef[0])  # one tangent plane: the track spans ~20 km, its frame turns < 0.2 deg
    east, north = (ecef - ecef[0]) @ e, (ecef - ecef[0]) @ n
    track = np.degrees(np.arctan2(vel @ e, vel @ n)) % 360.0
    alt = np.array([s.alt_msl_m[0] for s in snaps])
    return times, east, north, track, alt, commands, results


def _longest_on(times, track, heading_deg: float, within_deg: float = 6.0, after_s: float = -1.0) -> float:
    """The longest stretch of world seconds after ``after_s`` with the track within
    ``within_deg`` of ``heading_deg``."""
    on = (np.abs((track - heading_deg + 180.0) % 360.0 - 180.0) <= within_deg) & (times > after_s)
    best, start = 0.0, None
    for k, flag in enumerate(on):
        if flag and start is None:
            start = times[k]
        if start is not None and (not flag or k == len(on) - 1):
            best, start = max(best, times[k] - start), None
    return best


def _altitude_targets(commands) -> list:
    return _changes([v["alt_msl_m"] for _, v in commands if "alt_msl_m" in v])


@pytest.mark.slow  # ~15 s: some 250 s of an f16's flight at x16
def test_an_aircraft_bots_patrol_is_a_closed_box_at_two_altitudes(alps):
    """Four legs of LEG_S world seconds each on headings 90 degrees apart, turning right, and
    the track back within 1 km of where the first began (the box's sides are ~2 km of leg
    and a 5 km turn radius; it drifted 27 km in eight legs, its 90-degree turns cut short
    every 20 s). Its altitude targets are 3500 m +- 300 m and nothing else (they crept down
    by the overshoot), and it flies within 60 m of them. (Every check is made and the ones
    that fail are listed together: the box and the altitudes were separate findings.)"""
    times, east, north, track, alt, commands, results = _fly_f16_bot(alps, "patrol", 275.0)
    h0, t0 = commands[0][1]["heading_deg"], commands[0][0]
    failed = []
    on = [_longest_on(times, track, h0 + 90.0 * k) for k in range(4)]
    if min(on) < LEG_S - 4.0:
        failed.append(f"world seconds on each leg's heading {on}")
    start = np.searchsorted(times, t0)
    back = times > t0 + 200.0  # after the three turns, on the fourth
    miss = np.hypot(east[back] - east[start], north[back] - north[start]).min()
    if miss > 1000.0:
        failed.append(f"the box misses its start by {miss:.0f} m")
    targets = _altitude_targets(commands)
    alternating = [targets[0] - 600.0 * (k % 2) for k in range(len(targets))]  # up, down, up, ...
    if not np.allclose(targets, alternating, rtol=0.0, atol=1e-6) or abs(targets[0] - F16_ALT_M - 300.0) > 1.0:
        failed.append(f"altitude targets {targets}")
    if alt.min() < F16_ALT_M - 300.0 - 60.0 or alt.max() > F16_ALT_M + 300.0 + 60.0:
        failed.append(f"altitudes flown {alt.min():.0f}..{alt.max():.0f} m")
    assert abs(h0 - 30.0) < 3.0 and not failed, (failed, commands)
    (_, agent, what), = results
    assert agent == 1 and not isinstance(what, cli.BotFailure), results


@pytest.mark.slow  # ~15 s: some 250 s of an f16's flight at x16
def test_an_aircraft_bots_racetrack_is_two_parallel_legs_joined_by_right_half_turns(alps):
    """Out on the first heading, a right half turn, back on the reciprocal ~2 turn radii to
    the right, a right half turn, out again on the first leg's line (within 800 m): it
    never reversed (180 degrees commanded every 20 s, the f16 taking ~80 s to turn them)."""
    times, east, north, track, alt, commands, results = _fly_f16_bot(alps, "racetrack", 215.0)
    h0 = commands[0][1]["heading_deg"]
    assert _longest_on(times, track, h0 + 180.0) >= LEG_S - 4.0, commands
    back = times[np.argmax(np.abs((track - h0 - 180.0 + 180.0) % 360.0 - 180.0) <= 6.0)]
    assert _longest_on(times, track, h0, after_s=back + LEG_S) >= 0.5 * LEG_S, commands
    # Cross-track, metres right of the first leg's line (through where it began, on h0).
    t0 = commands[0][0]
    start = np.searchsorted(times, t0)
    h = math.radians(h0)
    right = (east - east[start]) * math.cos(h) - (north - north[start]) * math.sin(h)
    on_back = np.abs((track - h0 - 180.0 + 180.0) % 360.0 - 180.0) <= 6.0
    radius = F16_SPEED_MPS / math.radians(2.2)  # ~5.2 km at the f16's ~2.2 deg/s
    assert np.all(right[on_back] > radius), right[on_back].min()  # the reciprocal leg: to the right
    out_again = (np.abs((track - h0 + 180.0) % 360.0 - 180.0) <= 6.0) & (times > back + LEG_S)
    assert out_again.any() and np.abs(right[out_again]).max() < 800.0, right[out_again]
    turned = np.degrees(np.unwrap(np.radians(track)))
    # Two right half turns by the time it is out on the first leg's line again (to its last
    # sample there: the bot's legs run on wall time, so on a loaded host the next turn may have
    # begun by the end of the run).
    last_out = np.flatnonzero(out_again)[-1]
    assert 340.0 < turned[last_out] - turned[start] < 380.0, turned[last_out] - turned[start]
    assert turned[-1] - turned[start] > 340.0  # and never back the other way
    targets = _altitude_targets(commands)
    assert np.allclose(targets, [targets[0] - 600.0 * (k % 2) for k in range(len(targets))], rtol=0.0, atol=1e-6)
    (_, agent, what), = results
    assert agent == 1 and not isinstance(what, cli.BotFailure), results


# -- 6, 7: a picture's end ----------------------------------------------------------------------------

def test_a_picture_is_not_extrapolated_past_its_streams_end(alps):
    """The exercise ends (srv.stop: the Watch ends OK): now_s() stays at the last update's
    world time and the entities where they were then (they moved on 440 m in 3 s)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    try:
        with SimClient(srv.address) as c:
            c.join("d", "driver")
            with c.controls() as controls:
                controls.drive(10.0)
            picture = c.watch()
            time.sleep(1.5)
            srv.stop(0.5)
            assert picture.wait_for(lambda p: not p.alive, 5.0)
            assert picture.error is None
            t1, (_, pos1, _) = picture.now_s(), picture.state()
            time.sleep(0.5)
            t2, (_, pos2, _) = picture.now_s(), picture.state()
            assert t1 == t2 == picture.time_s
            assert np.linalg.norm(pos2 - pos1) == 0.0
    finally:
        srv.stop(0.1)
        w.close()


def test_a_listeners_exception_ends_the_picture_with_that_error(alps):
    """A listener that raises: the picture ends with the error (a SortieError saying what was
    raised), the Watch is cancelled (the server no longer streams to it), and sortie
    client's end says this client failed, exit 1 (it read as the exercise's end, 0)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()

    def listener(picture, update):
        raise ValueError("listener bug")

    try:
        with SimClient(srv.address) as c:
            c.join("o", "observer", observer=(47.29, 9.59, 10_000.0))
            picture = c.watch(listener)
            picture.wait_for(lambda p: not p.alive, 5.0)
            assert not picture.alive
            assert isinstance(picture.error, SortieError) and "ValueError: listener bug" in str(picture.error)
            deadline = time.monotonic() + 5.0
            while srv.sessions.watching() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert srv.sessions.watching() == []
            assert cli.stream_end(c, picture) == 1
    finally:
        srv.stop(0.1)
        w.close()
