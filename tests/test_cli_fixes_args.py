"""`sortie client` and `sortie bot` options: out-of-range and non-finite values are argparse
errors naming the option and the value; the observer's default radius fits the server's
limit; a bot's commands are paced in wall time however fast the clock runs."""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import pytest

from client import cli
from sortie.v1 import simulation_pb2 as pb


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sortie")
    cli.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser


BAD = [  # (command line after the command, option, value)
    (["bot", "--count", "0"], "--count", "0"),
    (["bot", "--count", "-3"], "--count", "-3"),
    (["bot", "--count", "257"], "--count", "257"),
    (["bot", "--count", "2.5"], "--count", "2.5"),
    (["bot", "--leg-s", "0"], "--leg-s", "0"),
    (["bot", "--leg-s", "nan"], "--leg-s", "nan"),
    (["bot", "--leg-s", "inf"], "--leg-s", "inf"),
    (["bot", "--duration", "-1"], "--duration", "-1"),
    (["bot", "--duration", "nan"], "--duration", "nan"),
    (["bot", "--duration", "1e9"], "--duration", "1e9"),
    (["client", "--every", "nan"], "--every", "nan"),
    (["client", "--every", "0"], "--every", "0"),
    (["client", "--every", "-2"], "--every", "-2"),
    (["client", "--duration", "nan"], "--duration", "nan"),
    (["client", "--duration", "-1"], "--duration", "-1"),
    (["client", "--duration", "inf"], "--duration", "inf"),
]


@pytest.mark.parametrize("argv, option, value", BAD)
def test_bad_values_are_argparse_errors_naming_option_and_value(capsys, argv, option, value):
    with pytest.raises(SystemExit) as info:
        _parser().parse_args([argv[0], "--server", "127.0.0.1:1", *argv[1:]])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}: " in err and repr(value) in err, err


def test_good_values_parse_and_help_states_the_bounds(capsys):
    p = _parser()
    a = p.parse_args(["bot", "--server", "h:1", "--count", "256", "--leg-s", "1", "--duration", "0"])
    assert (a.count, a.leg_s, a.duration) == (256, 1.0, 0.0)
    a = p.parse_args(["client", "--server", "h:1", "--every", "0.05", "--duration", "604800"])
    assert (a.every, a.duration) == (0.05, 604800.0)
    with pytest.raises(SystemExit):
        p.parse_args(["bot", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "[1, 256]" in text and "[1, 3600]" in text and "at most 604800" in text, text
    with pytest.raises(SystemExit):
        p.parse_args(["client", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "[0.05, 3600]" in text and "at most 604800" in text, text


def test_the_bot_count_limit_is_the_servers_session_limit():
    from server.sim_service import MAX_SESSIONS

    assert cli.MAX_BOTS == MAX_SESSIONS


# -- the observer's default area ------------------------------------------------------------------

class _Picture:
    alive = False
    error = None
    time_s = 0.0


class _Observer:
    """A SimClient stand-in for `sortie client`: records the join."""

    joined = []

    def __init__(self, address):
        self.world_info = pb.WorldInfo(exercise_name="x")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def wait_ready(self):
        pass

    def world(self):
        return pb.WorldInfo(exercise_name="x", observer_radius_max_m=50_000.0,
                            target_areas=[pb.TargetArea(name="a", lat_deg=[1.0, 3.0], lon_deg=[10.0, 12.0])])

    def join(self, name, role, observer=None):
        _Observer.joined.append((role, observer))

    def watch(self):
        return _Picture()


def test_the_observer_radius_defaults_to_the_servers_limit_when_smaller(monkeypatch, capsys):
    import client.sim_client

    monkeypatch.setattr(client.sim_client, "SimClient", _Observer)
    monkeypatch.setattr(cli, "_stop_on_signals", threading.Event)
    _Observer.joined.clear()
    args = _parser().parse_args(["client", "--server", "h:1", "--duration", "1"])
    assert cli.client_command(args) == 0
    assert _Observer.joined == [("observer", (2.0, 11.0, 50_000.0))]
    assert "50 km" in capsys.readouterr().out


def test_default_observe():
    assert cli.default_observe(pb.WorldInfo()) == (0.0, 0.0, 100_000.0)  # a server that does not say
    assert cli.default_observe(pb.WorldInfo(observer_radius_max_m=250_000.0)) == (0.0, 0.0, 100_000.0)
    assert cli.default_observe(pb.WorldInfo(observer_radius_max_m=20_000.0)) == (0.0, 0.0, 20_000.0)


def test_default_observe_centres_an_area_across_the_antimeridian_on_it():
    """An acceptance probe: an area from 179.97 to -179.97 was watched from longitude 0, the
    arithmetic mean of its longitudes, and the client saw nothing."""
    area = pb.TargetArea(name="am", lat_deg=[-16.7, -16.7, -16.5, -16.5], lon_deg=[179.97, -179.97, -179.97, 179.97])
    lat, lon, _ = cli.default_observe(pb.WorldInfo(target_areas=[area]))
    assert lat == pytest.approx(-16.6)
    assert abs(lon) == pytest.approx(180.0, abs=1e-9)  # on the antimeridian, not at 0
    area = pb.TargetArea(name="a", lat_deg=[1.0, 3.0], lon_deg=[10.0, 12.0])
    assert cli.default_observe(pb.WorldInfo(target_areas=[area]))[1] == pytest.approx(11.0)


# -- a bot's pace ----------------------------------------------------------------------------------

class _Controls:
    def __init__(self):
        self.sent = 0

    def autopilot(self, **targets):
        self.sent += 1

    def close(self):
        return self.sent


class _BotPicture:
    time_scale = 1000.0  # a fast clock: a 1-s leg is 1 ms of wall time
    updates = 0
    alive = True  # its stream runs

    def now_s(self):
        return time.monotonic() * self.time_scale

    def __init__(self, agent):
        self.infos = {agent: pb.EntityInfo(entity_id=agent, kind=pb.ENTITY_KIND_GROUND)}

    def wait_for(self, predicate, timeout_s):
        return True

    def state(self, ids=None):
        return np.array([7]), np.array([[4_300_000.0, 800_000.0, 4_650_000.0]]), np.array([[1.0, 0.0, 0.0, 0.0]])


class _Bot(_Observer):
    controls_made = []

    def join(self, name, role, observer=None):
        return 7

    def watch(self):
        return _BotPicture(7)

    def controls(self):
        c = _Controls()
        _Bot.controls_made.append(c)
        return c

    def leave(self):
        pass


def test_a_bot_commands_at_most_five_times_a_wall_second_on_a_fast_clock(monkeypatch):
    import client.sim_client

    monkeypatch.setattr(client.sim_client, "SimClient", _Bot)
    _Bot.controls_made.clear()
    results = []
    cli._fly_bot("h:1", 0, "patrol", 1.0, 1.0, results, threading.Event())
    assert results and results[0][1] == 7, results
    sent = _Bot.controls_made[0].sent
    assert 1 <= sent <= 1.0 / cli.MIN_LEG_WALL_S + 2, sent


# -- drive commands at the type's heading-rate limit ----------------------------------------------

@pytest.fixture(scope="module")
def alps_terrain():
    from pathlib import Path

    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(Path(__file__).resolve().parents[1] / "data" / "dem" / "N47E009.hgt")])


def test_a_heading_rate_of_exactly_the_limit_is_accepted(alps_terrain):
    """The bound is inclusive, as the message says: an M1A2's +-30 deg/s passes (its limit in
    radians read back in degrees is 29.999999999999996)."""
    from fdm.ground import GroundVehicles
    from sortie.errors import InvalidArgument

    g = GroundVehicles(alps_terrain, [47.29, 47.30], [9.59, 9.60], [45.0, 45.0], ["m1a2", "hmmwv"])
    assert g.yaw_rate_limit_dps[0] == 30.0
    for rate in (30.0, -30.0):
        g.check_controls(9.0, rate, index=[0])
        g.set_controls(0.0, rate, index=[0])
    g.set_controls([5.0, 5.0], g.yaw_rate_limit_dps)  # every type's own limit passes
    g.step(0.1)
    with pytest.raises(InvalidArgument, match=r"^yaw_rate_dps\[0\]: must be within \+-30 deg/s for vehicle 0 \(m1a2\)"):
        g.check_controls(9.0, 30.001, index=[0])
    with pytest.raises(InvalidArgument, match=r"^yaw_rate_dps\[0\]: must be within \+-30 deg/s for tank1 \(m1a2\) "
                                              r"\(got -31.0\)"):
        g.check_controls(9.0, -31.0, index=[0], names=["tank1"])
    with pytest.raises(InvalidArgument, match=r"^speed_mps\[0\]: must be within \[-\S+, \S+\] m/s for jeep \(hmmwv\)"):
        g.check_controls(99.0, None, index=[1], names=["jeep"])


# -- Tacview across the antimeridian ---------------------------------------------------------------

LONS = [179.998, 179.9995, -179.9995, -179.998]  # eastbound across 180, ~16 m a step at 16.5 S


def _pose_at(lon: float):
    from server.dead_reckoning import ned_to_ecef_quat
    from terrain.geodesy import geodetic_to_ecef

    lat = np.array([-16.5])
    pos = np.asarray(geodetic_to_ecef(lat, np.array([lon]), np.array([3000.0]))).reshape(1, 3)
    return pos, np.asarray(ned_to_ecef_quat(np.array([1.0, 0.0, 0.0, 0.0]), lat, np.array([lon]))).reshape(1, 4)


def test_live_tacview_longitudes_run_on_across_the_antimeridian():
    from server.tacview_live import FrameBuilder

    b = FrameBuilder(180, -16)
    infos = {1: pb.EntityInfo(entity_id=1, name="east1", kind=pb.ENTITY_KIND_AIRCRAFT, type="f16", coalition="blue")}
    written = []
    for k, lon in enumerate(LONS):
        text = b.frame(float(k), [1], *_pose_at(lon), infos).decode()
        written.append(float(text.split("T=")[1].split("|")[0]))
    assert written == [-0.002, -0.0005, 0.0005, 0.002], written


def test_acmi_export_longitudes_run_on_across_the_antimeridian(tmp_path):
    from server import acmi
    from server.recording import Recording

    from test_acmi import info, parse_acmi, write_synthetic

    path = tmp_path / "dateline.sortie"
    tracks = {1: (info(1, "east1", 1, "f16"), lambda tick: (-16.5, LONS[min(tick - 1, 3)], 3000.0, 0.0, 0.0, 90.0)),
              2: (info(2, "west1", 1, "c172x", "red"), lambda tick: (-16.5, -179.9, 3000.0, 0.0, 0.0, 270.0)),
              3: (info(3, "statE", 3, "radar", "red"), lambda tick: (-16.5, 179.9, 0.0, 0.0, 0.0, 0.0))}
    write_synthetic(path, tracks, ticks=4)
    out = tmp_path / "dateline.acmi"
    with Recording(path) as r:
        acmi.export_acmi(r, out)
    text = out.read_text(encoding="utf-8-sig")
    assert "0,ReferenceLongitude=180\n" in text
    series = parse_acmi(out).series
    lon1 = np.array([v for _, v in series["1"]["Longitude"]])
    assert np.allclose(lon1, [180 + d for d in (-0.002, -0.0005, 0.0005, 0.002)], atol=1e-7), lon1
    assert np.abs(np.diff(lon1)).max() < 0.002
    assert series["2"]["Longitude"][0][1] == pytest.approx(180.1) and series["3"]["Longitude"][0][1] == 179.9


def test_reference_point_and_offsets_across_the_antimeridian():
    from server.acmi import lon_offset_deg, pose_integers, reference_point

    assert reference_point([-16.5, -16.5], [179.9, -179.9]) == (180, -16)  # the plain median is 0
    assert reference_point([-16.5] * 3, [-179.6, -179.9, 179.2]) == (180, -16)  # median 180.1 in [0, 360)
    assert reference_point([47.0, 47.5], [9.2, 9.9]) == (10, 47)  # elsewhere as before
    assert lon_offset_deg([-179.75, 179.75, 0.0], 180).tolist() == [0.25, -0.25, 180.0]
    assert lon_offset_deg([179.75, -179.75], -180).tolist() == [-0.25, 0.25]
    v = pose_integers(np.array([[-179.75, -16.5, 0.0, 0.0, 0.0, 0.0]]), 180, -16)
    assert v[0, 0] == 2_500_000  # +0.25 degrees in units of the 7th decimal


class _AircraftPicture(_BotPicture):
    def __init__(self, agent):
        self.infos = {agent: pb.EntityInfo(entity_id=agent, kind=pb.ENTITY_KIND_AIRCRAFT)}

    def state(self, ids=None):
        from terrain.geodesy import geodetic_to_ecef

        return np.array([7]), geodetic_to_ecef([47.0], [9.0], [3048.0]), np.array([[1.0, 0.0, 0.0, 0.0]])


class _TargetsControls(_Controls):
    def __init__(self):
        super().__init__()
        self.targets = []

    def autopilot(self, **targets):
        super().autopilot(**targets)
        self.targets.append(targets)


class _AircraftBot(_Bot):
    def __init__(self, address):
        self.world_info = pb.WorldInfo(exercise_name="x", geoid_undulation_m=48.0)

    def watch(self):
        return _AircraftPicture(7)

    def controls(self):
        c = _TargetsControls()
        _Bot.controls_made.append(c)
        return c


def test_a_bot_aircrafts_legs_are_about_its_altitude_above_the_geoid(monkeypatch):
    """An acceptance probe: a bot took the state's height above the ellipsoid for its altitude
    above sea level, and climbed by the geoid's undulation (48 m there) every leg. At 3048 m
    above the ellipsoid, 3000 m MSL, its first leg is 3300 m MSL."""
    import client.sim_client

    monkeypatch.setattr(client.sim_client, "SimClient", _AircraftBot)
    _Bot.controls_made.clear()
    results = []
    cli._fly_bot("h:1", 0, "patrol", 1.0, 0.5, results, threading.Event())
    targets = _Bot.controls_made[0].targets
    assert targets[0]["alt_msl_m"] == pytest.approx(3300.0, abs=1e-6)
