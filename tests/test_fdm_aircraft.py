"""JSBSim aircraft on Sortie terrain: start, controls, coupling, events, determinism, hard cases.

Real JSBSim throughout; the terrains are the Alps DEM and small terrain
sources with the same ``heights(lat, lon)`` API (flat, a step that moves, a
plane slope). Simulated times are short so the file runs in seconds.
"""

import math

import numpy as np
import pytest

from fdm import catalog
from fdm.autopilot import Autopilot, Targets
from fdm.aircraft import (MAX_REFRESH_S, Aircraft, Controls, FlatTerrain, InitialConditions, TrimFailed,
                          validate_controls)
from fdm.events import CRASH, OUT_OF_FUEL, TAKEOFF, TOUCHDOWN
from fdm.state import FT_M, RAW_WIDTH, AircraftState, euler_to_quaternion
from sortie.errors import InvalidArgument, NotFound
from terrain.geodesy import geodetic_to_ecef
from terrain.terrain import HeightResult

LAKE = (47.60, 9.40)  # Lake Constance in N47E009: flat at 392 m


class MovableTerrain:
    """Flat terrain whose height the test changes between steps (the 100 m step case)."""

    def __init__(self, h):
        self.h = float(h)

    def heights(self, lat, lon):
        lat = np.asarray(lat, np.float64)
        return HeightResult(np.full(lat.shape, self.h), np.ones(lat.shape, np.uint8))


class SlopeTerrain:
    """A plane rising northwards: h = h0 + grade * (metres north of lat0)."""

    def __init__(self, lat0, h0, grade):
        self.lat0, self.h0, self.grade = lat0, h0, grade

    def heights(self, lat, lon):
        north_m = (np.asarray(lat, np.float64) - self.lat0) * 111_200.0
        return HeightResult(self.h0 + self.grade * north_m, np.ones(north_m.shape, np.uint8))


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def c172(terrain=None, **ic):
    base = dict(lat_deg=47.3, lon_deg=9.5, alt_m=1500.0, heading_deg=90.0, speed_mps=50.0)
    base.update(ic)
    return Aircraft("c172x", terrain or FlatTerrain(0.0), InitialConditions(**base))


# -- catalog --------------------------------------------------------------------------------------

def test_catalog_lists_the_wheels_aircraft():
    names = catalog.list_aircraft()
    for n in ("c172x", "f16", "A4", "737"):
        assert n in names
    assert catalog.resolve("F16") == "f16"
    with pytest.raises(NotFound, match="f16"):
        catalog.resolve("f61")


# -- start and trim -------------------------------------------------------------------------------

def test_airborne_start_is_trimmed_at_the_requested_state():
    ac = c172()
    s = ac.state()
    assert abs(s.alt_msl_m - 1500.0) < 1e-6 and abs(s.airspeed_true_mps - 50.0) < 1e-6
    assert abs(s.heading_deg - 90.0) < 1e-6 and abs(s.lat_deg - 47.3) < 1e-9
    ac.run(5.0)
    s = ac.state()
    # Trimmed: level within a few metres and the same speed after 5 s hands off.
    assert abs(s.alt_msl_m - 1500.0) < 5.0 and abs(s.airspeed_true_mps - 50.0) < 1.0
    assert ac.events == []


def test_agl_start_is_above_the_dem(alps):
    ac = Aircraft("f16", alps, InitialConditions(47.3, 9.5, 300.0, "agl", 45.0, 200.0))
    s = ac.state()
    h = alps.heights([47.3], [9.5]).height_msl_m[0]
    assert abs(s.terrain_msl_m - h) < 1e-9 and abs(s.agl_m - 300.0) < 1e-6


def test_trim_failure_is_a_typed_error():
    with pytest.raises(TrimFailed, match="trim failed"):
        c172(alt_m=18_000.0, speed_mps=15.0)


def test_bad_initial_conditions_name_the_field(alps):
    with pytest.raises(InvalidArgument, match="lat_deg"):
        c172(lat_deg=float("nan"))
    with pytest.raises(InvalidArgument, match="alt_m"):
        Aircraft("c172x", alps, InitialConditions(47.3, 9.5, 500.0, speed_mps=50.0))  # below the Alps
    with pytest.raises(InvalidArgument, match="dt"):
        Aircraft("c172x", FlatTerrain(), InitialConditions(47.3, 9.5, 500.0, speed_mps=50.0), dt=0.0)


# -- controls -------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad, field", [
    ({"pitch": float("nan")}, "pitch"),
    ({"roll": float("inf")}, "roll"),
    ({"throttle": 1.5}, "throttle"),
    ({"brakes": -0.1}, "brakes"),
    ({"gear_down": 0.5}, "gear_down"),
    ({"elevator": 0.1}, "elevator"),
    ({"flaps": "full"}, "flaps"),
])
def test_bad_controls_are_rejected_and_nothing_is_applied(bad, field):
    ac = c172()
    before = ac.controls
    elevator = ac.fdm["fcs/elevator-cmd-norm"]
    with pytest.raises(InvalidArgument) as err:
        ac.set_controls(**{"pitch": 0.5, "yaw": 0.2, **bad})  # good values first
    assert err.value.field == field and field in str(err.value)
    assert ac.controls == before and ac.fdm["fcs/elevator-cmd-norm"] == elevator


def test_controls_move_the_aircraft_the_documented_way():
    ac = c172()
    ac.set_controls(pitch=0.3)
    ac.run(0.5)
    assert ac.state().body_rates_rps[1] > 0.02  # nose up
    ac = c172()
    ac.set_controls(roll=0.3)
    ac.run(0.5)
    assert ac.state().body_rates_rps[0] > 0.05  # right wing down
    ac.set_controls(Controls(throttle=0.5, gear_down=True))
    assert ac.controls == Controls(throttle=0.5, gear_down=True)


# -- determinism and state ------------------------------------------------------------------------

def _trajectory(seed):
    ac = c172()
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(240):
        if k % 10 == 0:
            ac.set_controls(pitch=float(rng.uniform(-0.2, 0.2)), roll=float(rng.uniform(-0.3, 0.3)),
                            throttle=float(rng.uniform(0.5, 1.0)))
        ac.step()
        rows.append(ac.raw_state())
    return np.array(rows)


def test_same_start_and_controls_give_a_bit_identical_trajectory():
    a, b = _trajectory(7), _trajectory(7)
    assert a.shape == (240, RAW_WIDTH)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, _trajectory(8))


def test_state_is_si_and_consistent():
    ac = c172(terrain=FlatTerrain(200.0))
    ac.run(1.0)
    s = ac.state()
    assert isinstance(s, AircraftState) and s.is_finite()
    np.testing.assert_array_equal(s.ecef_m, geodetic_to_ecef(s.lat_deg, s.lon_deg, s.alt_msl_m))
    assert abs(np.linalg.norm(s.vel_ecef_mps) - np.linalg.norm(s.vel_ned_mps)) < 1e-9
    assert abs(np.linalg.norm(s.quat_wxyz) - 1.0) < 1e-12 and s.quat_wxyz[0] >= 0
    assert abs(s.agl_m - (s.alt_msl_m - 200.0)) < 1e-9
    assert abs(s.airspeed_true_mps - ac.fdm["velocities/vt-fps"] * FT_M) < 1e-12
    # The quaternion of the identity attitude, and of a 90 degree yaw.
    np.testing.assert_allclose(euler_to_quaternion(0.0, 0.0, math.pi / 2),
                               [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-15)


# -- terrain coupling and events ------------------------------------------------------------------

def test_terrain_under_the_aircraft_is_fed_to_jsbsim(alps):
    ac = Aircraft("c172x", alps, InitialConditions(47.3, 9.5, 100.0, "agl", 90.0, 50.0))
    for _ in range(60):
        ac.step()
    s = ac.state()
    h = alps.heights([s.lat_deg], [s.lon_deg]).height_msl_m[0]
    assert abs(s.terrain_msl_m - h) < 1e-9
    # Near the ground every contact is checked; JSBSim's elevation is within the
    # aircraft's size of the terrain under the CG.
    assert abs(ac.fdm["position/terrain-elevation-asl-ft"] * FT_M - h) < 10.0


def test_ground_start_rest_and_take_off(alps):
    ac = Aircraft("c172x", alps, InitialConditions(*LAKE, heading_deg=250.0, on_ground=True))
    s = ac.state()
    assert s.on_ground and 0.5 < s.agl_m < 2.0
    ac.run(2.0)
    assert ac.events == [] and ac.state().ground_speed_mps < 0.2  # brakes on
    ac.set_controls(brakes=0.0, throttle=1.0)
    # Wings level and on heading by the autopilot (full power at low speed rolls a
    # c172 left); the pitch is the test's.
    ap = Autopilot(ac, Targets(heading_deg=250.0))
    ap.run(25.0)
    ac.set_controls(pitch=0.25)
    ap.run(15.0)
    kinds = [e.kind for e in ac.events]
    assert kinds == [TAKEOFF], ac.events
    assert ac.state().agl_m > 10.0


def test_gentle_landing_is_a_touchdown_and_a_dive_is_a_crash():
    ac = c172(terrain=FlatTerrain(392.0), alt_m=392.0 + 5.0, speed_mps=30.0)
    ac.set_controls(throttle=0.2)
    ac.run(20.0)
    assert [e.kind for e in ac.events][:1] == [TOUCHDOWN], ac.events
    assert ac.events[0].detail["sink_rate_mps"] < 3.05 and not ac.crashed

    ac = c172(terrain=FlatTerrain(392.0), alt_m=392.0 + 60.0, speed_mps=50.0)
    ac.set_controls(pitch=-1.0, throttle=1.0)
    ac.run(15.0)
    assert ac.crashed and ac.events[-1].kind == CRASH
    assert ac.state().is_finite()


def test_out_of_fuel_is_reported_once():
    ac = c172()
    ac.set_fuel_kg(0.0)
    ac.run(1.0)
    assert [e.kind for e in ac.events] == [OUT_OF_FUEL]


def test_terrain_steps_of_100_m_between_steps():
    terrain = MovableTerrain(1000.0)
    # Far above: a 100 m rise is just less height above ground, seen within the
    # far-field refresh period.
    ac = c172(terrain=terrain, alt_m=1500.0)
    ac.run(0.5)
    terrain.h = 1100.0
    ac.run(MAX_REFRESH_S + 0.1)
    s = ac.state()
    assert ac.events == [] and abs(s.agl_m - (s.alt_msl_m - 1100.0)) < 1e-9
    # Low: the ground jumping 100 m up through the aircraft is a crash, state finite.
    terrain.h = 1000.0
    ac = c172(terrain=terrain, alt_m=1050.0)
    ac.run(0.2)
    terrain.h = 1100.0
    ac.step()
    assert ac.crashed and ac.events[-1].detail["reason"] == "terrain penetration"
    assert ac.state().is_finite()
    # On the ground: the ground falling 100 m drops the aircraft; it lands hard.
    terrain.h = 1000.0
    ac = Aircraft("c172x", terrain, InitialConditions(47.3, 9.5, on_ground=True))
    ac.run(0.5)
    terrain.h = 900.0
    ac.run(6.0)
    kinds = [e.kind for e in ac.events]
    assert kinds[:3] == [TAKEOFF, TOUCHDOWN, CRASH], ac.events
    assert ac.state().is_finite()


def test_on_a_slope_the_uphill_wheel_sets_the_ground():
    # Facing east on a 4 % north-rising slope: the left (north) main wheel is uphill.
    terrain = SlopeTerrain(47.3, 500.0, 0.04)
    ac = Aircraft("c172x", terrain, InitialConditions(47.3, 9.5, heading_deg=90.0, on_ground=True))
    ac.run(1.0)
    s = ac.state()
    assert s.on_ground and ac.events == []
    e = ac.fdm["position/terrain-elevation-asl-ft"] * FT_M
    # The ground JSBSim sees is set by the most compressed wheel: between the terrain
    # under the CG and under the uphill (left main, 1.4 m north) wheel.
    assert s.terrain_msl_m - 0.01 < e < s.terrain_msl_m + 0.04 * 1.4 + 0.01
    assert s.ground_speed_mps < 0.5
    # A slope too steep to stand on is refused at the start.
    with pytest.raises(InvalidArgument, match="too steep"):
        Aircraft("c172x", SlopeTerrain(47.3, 500.0, 0.6), InitialConditions(47.3, 9.5, heading_deg=90.0,
                                                                            on_ground=True))


class CliffTerrain:
    """A straight cliff along a parallel: ``low`` m south of lat0, ``high`` m north of it."""

    def __init__(self, lat0, low, high):
        self.lat0, self.low, self.high = lat0, low, high

    def heights(self, lat, lon):
        lat = np.asarray(lat, np.float64)
        return HeightResult(np.where(lat >= self.lat0, self.high, self.low), np.ones(lat.shape, np.uint8))


M_PER_DEG_LAT = 111_200.0  # near 47 N, to place starts; the bounds below are much looser


def test_landing_just_past_a_cliff_edge():
    # A 100 m cliff facing south; the c172 glides in 5 m above the plateau from
    # 150 m south of the edge. The wheels cross a 100 m terrain step and the
    # touchdown is on the plateau, gentle, not a crash.
    cliff = CliffTerrain(47.3, 300.0, 400.0)
    ac = c172(terrain=cliff, lat_deg=47.3 - 150.0 / M_PER_DEG_LAT, alt_m=405.0, heading_deg=0.0, speed_mps=30.0)
    ac.set_controls(throttle=0.2)
    ac.run(20.0)
    touchdowns = [e for e in ac.events if e.kind == TOUCHDOWN]
    assert touchdowns and not ac.crashed, ac.events
    td = touchdowns[0]
    assert td.lat_deg > 47.3 and 400.0 < td.alt_msl_m < 403.0 and td.detail["sink_rate_mps"] < 3.05
    s = ac.state()
    assert s.on_ground and abs(s.terrain_msl_m - 400.0) < 1e-9 and 0.3 < s.agl_m < 2.0


def test_flying_into_a_cliff_face_stops_at_the_face():
    # 50 m below the plateau's top, heading for the face: a crash at the face
    # (the nose wheel, ~1 m ahead of the CG, penetrates first), the aircraft
    # frozen there, not lifted onto the plateau. Bound: the CG within 10 m south
    # of the cliff line (contact offset + one step of flight at 50 m/s: 0.4 m).
    cliff = CliffTerrain(47.3, 300.0, 400.0)
    ac = c172(terrain=cliff, lat_deg=47.3 - 300.0 / M_PER_DEG_LAT, alt_m=350.0, heading_deg=0.0)
    ac.run(15.0)
    assert ac.crashed and ac.events[-1].kind == CRASH, ac.events
    assert ac.events[-1].detail["reason"] in ("terrain penetration", "structure contact")
    s = ac.state()
    assert 47.3 - 10.0 / M_PER_DEG_LAT < s.lat_deg < 47.3 and s.alt_msl_m < 360.0 and s.is_finite()
    ac.run(1.0)
    assert ac.state().lat_deg == s.lat_deg  # frozen where it hit


# -- hard cases -----------------------------------------------------------------------------------

def test_spin_stall_and_inverted_stay_finite():
    ac = c172(alt_m=3000.0, speed_mps=30.0)
    ac.set_controls(throttle=0.0, pitch=1.0, yaw=1.0, roll=-1.0)  # stall, then spin entry
    alpha_max = 0.0
    for _ in range(15 * 120):
        ac.step()
        s = ac.state()
        assert s.is_finite()
        alpha_max = max(alpha_max, abs(s.alpha_rad))
    assert alpha_max > math.radians(15)  # past the stall (c172: about 16 degrees)
    ac = c172(alt_m=3000.0)
    ac.set_controls(roll=1.0)  # full aileron: rolls through inverted
    bank_max = 0.0
    for _ in range(4 * 120):
        ac.step()
        s = ac.state()
        assert s.is_finite()
        bank_max = max(bank_max, abs(s.euler_rad[0]))
    assert bank_max > math.radians(170)
    f16 = Aircraft("f16", FlatTerrain(), InitialConditions(0.0, 0.0, 6000.0, heading_deg=0.0, speed_mps=150.0))
    f16.set_controls(pitch=1.0, roll=0.6, throttle=0.0)  # high alpha, rolling
    f16.run(8.0)
    assert f16.state().is_finite()


def _continuity(ac, seconds):
    prev = ac.state()
    worst = 0.0
    for _ in range(int(seconds / ac.dt)):
        ac.step()
        s = ac.state()
        moved = np.linalg.norm(s.ecef_m - prev.ecef_m)
        worst = max(worst, moved / (np.linalg.norm(s.vel_ecef_mps) * ac.dt))
        prev = s
    return prev, worst


def test_crossing_the_antimeridian_is_continuous():
    ac = Aircraft("f16", FlatTerrain(), InitialConditions(10.0, 179.995, 3000.0, heading_deg=90.0,
                                                          speed_mps=250.0))
    s, worst = _continuity(ac, 4.0)
    assert s.lon_deg < -179.99  # crossed
    # No step moves further than speed * dt (+1 %: speed changes within a step).
    assert worst < 1.01


def test_passing_near_the_pole_is_continuous():
    ac = Aircraft("f16", FlatTerrain(), InitialConditions(89.995, 30.0, 3000.0, heading_deg=0.0,
                                                          speed_mps=250.0))
    s, worst = _continuity(ac, 6.0)
    assert s.lat_deg < 89.995 and abs(s.lon_deg - 30.0) > 170.0  # went over the pole
    assert worst < 1.01 and s.is_finite()


def test_dt_sweep_converges():
    end = {}
    for hz in (50, 60, 120, 240):  # 50 Hz: the longest step (fdm.catalog.DT_MAX_S)
        ac = Aircraft("c172x", FlatTerrain(), InitialConditions(47.3, 9.5, 1500.0, heading_deg=90.0,
                                                                speed_mps=50.0), dt=1.0 / hz)
        ac.set_controls(roll=0.2)
        ac.run(10.0)
        end[hz] = ac.state().ecef_m
    err = {hz: float(np.linalg.norm(end[hz] - end[240])) for hz in (50, 60, 120)}
    # Stated bound: within 25 m of the 240 Hz run after 10 s of a rolling turn at every rate,
    # and smaller at 120 Hz than at 50 Hz.
    assert max(err.values()) < 25.0 and err[120] < err[50], err


def test_cli_fly_summary():
    from fdm.cli import fly

    summary = fly("c172x", InitialConditions(47.3, 9.5, 1500.0, heading_deg=90.0, speed_mps=50.0), 5.0, hold=True)
    assert summary["aircraft"] == "c172x" and not summary["crashed"]
    assert 240.0 < summary["distance_m"] < 260.0 and abs(summary["end"]["alt_msl_m"] - 1500.0) < 5.0
    with pytest.raises(InvalidArgument, match="seconds"):
        fly("c172x", InitialConditions(47.3, 9.5, 1500.0, speed_mps=50.0), float("nan"))


# -- acceptance probing --------------------------------------------------------------------------

def test_a_model_declaring_a_network_input_opens_no_port():
    """The catalog's 737 declares <input port="5137"/>, JSBSim's telnet property server on every
    interface: anyone reaching it could set any property of a hosted aircraft. The host
    disables JSBSim's inputs, so after load, trim and steps nothing listens there."""
    import socket

    xml = (catalog.root_dir() / "aircraft" / "737" / "737.xml").read_text()
    assert 'port="5137"' in xml.replace("'", '"')  # the hazard is real in this catalog
    ac = Aircraft("737", FlatTerrain(), InitialConditions(47.5, 9.5, 3000.0, heading_deg=90.0, speed_mps=150.0))
    ac.advance(12)
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", 5137)) != 0


def test_hostile_control_values_are_invalid_arguments():
    for values, field in (({"pitch": 10 ** 400}, "pitch"), ({"gear_down": np.array([1, 0])}, "gear_down"),
                          ({"gear_down": 0.5}, "gear_down"), ({"gear_down": "yes"}, "gear_down")):
        with pytest.raises(InvalidArgument, match=f"^{field}"):
            validate_controls(values)
    assert validate_controls({"gear_down": np.True_, "pitch": np.float32(0.5)}) == {"gear_down": True, "pitch": 0.5}


def test_structure_contact_is_a_crash_at_speed_not_at_rest():
    """A glider parked on the ground settles on a wing tip (a STRUCTURE contact) and stays
    parked; the detector still calls a structure contact at speed, or sinking past the
    touchdown limit, a crash."""
    from fdm.events import LIMITS, STRUCTURE_REST_SPEED_MPS, EventDetector

    glider = Aircraft("sgs233", FlatTerrain(), InitialConditions(47.3, 9.6, 0.0, on_ground=True))
    glider.advance(int(15.0 / glider.dt))
    assert not glider.crashed and not [e for e in glider.events if e.kind == CRASH]
    for speed, sink, crash in ((1.0, 0.2, False), (STRUCTURE_REST_SPEED_MPS + 0.5, 0.2, True),
                               (0.5, LIMITS["light"].sink_rate_mps + 0.5, True)):
        d = EventDetector(LIMITS["light"], on_ground=True)
        events = d.update(1.0, 47.0, 9.0, 400.0, True, True, sink, 1.0, speed)
        assert bool([e for e in events if e.kind == CRASH]) == crash, (speed, sink)


class RampTerrain:
    """Flat at ``h0`` up to ``start_m`` north of lat0, then rising northwards at ``grade``."""

    def __init__(self, lat0, h0, start_m, grade):
        self.lat0, self.h0, self.start_m, self.grade = lat0, h0, start_m, grade

    def heights(self, lat, lon):
        north_m = (np.asarray(lat, np.float64) - self.lat0) * 111_200.0
        return HeightResult(self.h0 + self.grade * np.maximum(north_m - self.start_m, 0.0),
                            np.ones(north_m.shape, np.uint8))


@pytest.mark.parametrize("grade", [0.0, 0.03])
def test_landing_on_an_up_slope_rolls_out(grade):
    """A c172x descending at 3 m below its altitude, flaps down, lands where a 3 % up-slope
    begins (sink under 1.5 m/s), then idles with brakes: it rolls out and stops on the slope
    with no crash. Steeper slopes fail: JSBSim's strut damping takes the climb up the slope
    for strut extension (fdm/aircraft.py's docstring: at 5 % a c172x noses over)."""
    from fdm.autopilot import Autopilot

    terrain = RampTerrain(47.0, 500.0, 300.0, grade)
    ac = Aircraft("c172x", terrain, InitialConditions(47.0, 8.0, 15.0, alt_ref="agl", speed_mps=30.0,
                                                      heading_deg=0.0, gear_down=True))
    ac.set_controls(flaps=1.0, throttle=0.25)
    ap = Autopilot(ac)
    down = False
    for _ in range(120 * 40):
        if not down:
            ap.set_targets(0.0, ac.state().alt_msl_m - 3.0, None)
            ap.update()
            if ac.events:
                down = True
                ac.set_controls(pitch=0.0, roll=0.0, yaw=0.0, throttle=0.0, brakes=0.5)
        ac.step()
    kinds = [e.kind for e in ac.events]
    assert kinds == [TOUCHDOWN], ac.events
    assert ac.events[0].detail["sink_rate_mps"] < 1.5
    s = ac.state()
    assert not ac.crashed and s.on_ground and s.ground_speed_mps < 1.0
    assert (s.lat_deg - 47.0) * 111_200.0 > 300.0 + 50.0  # well up the slope
    assert abs(math.degrees(s.euler_rad[1])) < 10.0  # on its wheels (at 5 % it nosed over to -31 degrees)
