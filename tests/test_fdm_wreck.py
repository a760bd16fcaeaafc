"""A wreck falling (fdm.wreck): an aircraft that crashes clear of the surface comes down
ballistically and rests where it meets the surface, against references of our own (the
closed-form vertical fall with quadratic drag, scipy's ODE solution on a flat earth)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.wreck import FALL_MIN_AGL_M, G0_MPS2, TERMINAL_SPEED_MPS, fall, impact_fraction
from server.world import World
from terrain.geodesy import geodetic_to_ecef

DT = 1.0 / 120.0
VT = TERMINAL_SPEED_MPS


def _drop_time(h0, surface, v_ned, steps=1):
    """Seconds until a wreck dropped from h0 passes ``surface`` (whole calls of ``steps``)."""
    lat, lon, h, v, t = 47.0, 9.0, h0, v_ned, 0.0
    while h > surface:
        before = h
        lat, lon, h, v, _ = fall(lat, lon, h, v, DT, steps)
        t += steps * DT
    return t - (1.0 - float(impact_fraction(before - surface, h - surface))) * steps * DT, v


def test_a_vertical_drop_matches_the_closed_form_with_quadratic_drag():
    """From rest, d = (v_t^2 / g) ln cosh(g t / v_t): the time to fall 3000 m within 0.02 s
    (of 47 s), the speed then within 0.5 % of the closed form's v_t tanh(g t / v_t)."""
    d = 3000.0
    t_ref = VT / G0_MPS2 * math.acosh(math.exp(d * G0_MPS2 / VT ** 2))
    t, v = _drop_time(100.0 + d, 100.0, (0.0, 0.0, 0.0))
    assert abs(t - t_ref) < 0.02, (t, t_ref)
    assert abs(math.hypot(*v) - VT * math.tanh(G0_MPS2 * t / VT)) < 0.005 * VT
    assert abs(v[0]) < 1e-3 and abs(v[1]) < 1e-3  # straight down (the normal through the wreck, within 2e-5 rad)


def test_a_fall_with_forward_speed_matches_an_ode_reference():
    """200 m/s east and 20 m/s up at 2000 m: impact time within 0.05 s and the distance
    flown east within 0.5 % of scipy's solution of dv/dt = g - (g / v_t^2)|v| v on a flat
    earth (the ellipsoid's curvature moves the impact by well under that over a few km)."""
    k = G0_MPS2 / VT ** 2

    def rhs(_, s):  # s = (x east, z up, vx, vz)
        speed = math.hypot(s[2], s[3])
        return [s[2], s[3], -k * speed * s[2], -G0_MPS2 - k * speed * s[3]]

    ground = lambda _, s: s[1]  # noqa: E731 - scipy's event function
    ground.terminal, ground.direction = True, -1
    sol = solve_ivp(rhs, (0.0, 200.0), [0.0, 2000.0, 200.0, 20.0], events=ground, rtol=1e-10, atol=1e-9)
    t_ref, x_ref = float(sol.t_events[0][0]), float(sol.y_events[0][0][0])

    lat0, lon0 = -33.9, 151.2  # southern and eastern hemispheres
    lat, lon, h, v, t = lat0, lon0, 2000.0, (0.0, 200.0, -20.0), 0.0
    h_prev = h
    while h > 0.0:
        p0 = (lat, lon, h)
        h_prev = h
        lat, lon, h, v, _ = fall(lat, lon, h, v, DT, 4)
        t += 4 * DT
    f = float(impact_fraction(h_prev, h))
    a, b = geodetic_to_ecef(*p0), geodetic_to_ecef(lat, lon, h)
    t_hit = t - (1.0 - f) * 4 * DT
    hit = a + f * (b - a)
    east = float(np.linalg.norm(hit - geodetic_to_ecef(lat0, lon0, 0.0)))
    assert abs(t_hit - t_ref) < 0.05, (t_hit, t_ref)
    assert abs(east - x_ref) < 0.005 * x_ref, (east, x_ref)


@pytest.mark.parametrize("lat0, lon0, v", [
    (10.0, 179.9995, (0.0, 250.0, 0.0)),  # east across the antimeridian
    (89.9995, 30.0, (250.0, 0.0, 0.0)),  # north over the pole
    (-89.9995, -150.0, (-250.0, 0.0, 0.0)),  # south over the south pole
])
def test_the_path_is_continuous_across_the_antimeridian_and_the_poles(lat0, lon0, v):
    """Call by call the wreck moves as far in ECEF as its speed says (within 1 %), its
    longitude stays in [-180, 180] and its latitude in [-90, 90], whatever it crosses."""
    lat, lon, h = lat0, lon0, 5000.0
    p = geodetic_to_ecef(lat, lon, h)
    for _ in range(30):  # 1 s
        lat, lon, h, v_new, _ = fall(lat, lon, h, v, DT, 4)
        q = geodetic_to_ecef(lat, lon, h)
        mean_speed = 0.5 * (math.hypot(*v) + math.hypot(*v_new))
        assert abs(np.linalg.norm(q - p) - mean_speed * 4 * DT) < 0.01 * mean_speed * 4 * DT
        assert -180.0 <= lon <= 180.0 and -90.0 <= lat <= 90.0
        p, v = q, v_new


def test_bad_terminal_speed_is_refused():
    with pytest.raises(ValueError, match="terminal_speed_mps"):
        fall(0.0, 0.0, 100.0, (0.0, 0.0, 0.0), DT, 1, terminal_speed_mps=0.0)


def _airborne_f16(terrain_m=200.0, alt_m=1500.0, lat=47.0, lon=9.0):
    ac = Aircraft("f16", FlatTerrain(terrain_m), InitialConditions(lat, lon, alt_m, heading_deg=90.0,
                                                                    speed_mps=150.0))
    ac.run(0.5)
    return ac


def test_an_aircraft_crashing_in_the_air_falls_and_rests_on_the_ground():
    """A mid-air crash at 1500 m over ground at 200 m: the wreck falls (descending, its attitude
    kept, no rotation), then one wreck_impact event where it meets the ground, 1300 m down, at
    about the terminal speed; from then on it is at rest at 200 m and does not move."""
    ac = _airborne_f16()
    s = ac.state()
    [crash] = ac.crash(s.time_s, s.lat_deg, s.lon_deg, s.alt_msl_m, "collision with bandit")
    assert crash.kind == "crash" and ac.crashed and ac.falling
    euler = s.euler_rad.copy()
    events, alts = [], []
    for _ in range(30 * 120):
        events += ac.advance(4)
        st = ac.state()
        alts.append(st.alt_msl_m)
        assert np.all(st.body_rates_rps == 0.0) and np.allclose(st.euler_rad, euler)
        if not ac.falling:
            break
    assert not ac.falling
    assert np.all(np.diff(alts[30:]) <= 0.0)  # down once the climb it had is spent
    [impact] = events
    assert impact.kind == "wreck_impact" and impact.alt_msl_m == 200.0
    assert abs(impact.detail["fell_m"] - (s.alt_msl_m - 200.0)) < 1e-3  # rounded to the mm
    assert 0.9 * VT < impact.detail["speed_mps"] < 1.1 * VT
    rest = ac.state()
    assert rest.alt_msl_m == 200.0 and np.all(rest.vel_ned_mps == 0.0) and rest.load_factor_g == 1.0
    assert abs(rest.lat_deg - impact.lat_deg) < 1e-12 and abs(rest.lon_deg - impact.lon_deg) < 1e-12
    assert ac.advance(4) == [] and ac.step() == []
    assert ac.state().alt_msl_m == 200.0 and ac.state().lon_deg == rest.lon_deg


@pytest.mark.parametrize("reason", ["terrain penetration", "structure contact", "sink rate at touchdown"])
def test_a_surface_crash_leaves_the_wreck_where_it_crashed(reason):
    """A crash of a surface contact (whatever its height: the CG of a cliff-face impact can be
    high above the foot of the cliff) does not fall."""
    ac = _airborne_f16()
    s = ac.state()
    ac.crash(s.time_s, s.lat_deg, s.lon_deg, s.alt_msl_m, reason)
    assert ac.crashed and not ac.falling
    ac.advance(120)
    assert ac.state().alt_msl_m == s.alt_msl_m


def test_a_crash_just_above_the_ground_does_not_fall():
    """Within FALL_MIN_AGL_M of the surface where it crashed, the wreck stays there."""
    ac = _airborne_f16()
    s = ac.state()
    ac.crash(s.time_s, s.lat_deg, s.lon_deg, 200.0 + 0.5 * FALL_MIN_AGL_M, "collision with bandit")
    assert ac.crashed and not ac.falling


def test_mid_air_wrecks_fall_in_the_world_and_the_world_reports_their_impact():
    """Two f16s head-on at 2000 m over ground at 400 m collide; both wrecks fall (no further
    collision between them), each world reports one wreck_impact at 400 m, and two worlds
    run alike give the same wreck states bit for bit (re-simulation stays exact)."""
    def run():
        world = World(FlatTerrain(400.0))
        try:
            lat0, lon0 = 47.0, 9.0
            east_deg = 500.0 / (111_200.0 * math.cos(math.radians(lat0)))
            a = world.spawn_aircraft("a", "f16", InitialConditions(lat0, lon0 - east_deg, 2000.0, heading_deg=90.0,
                                                                    speed_mps=250.0))
            b = world.spawn_aircraft("b", "f16", InitialConditions(lat0, lon0 + east_deg, 2000.0, heading_deg=270.0,
                                                                    speed_mps=250.0))
            events = []
            for _ in range(30 * 60):
                events += world.tick()
                if sum(e.kind == "wreck_impact" for e in events) == 2:
                    break
            return a, b, events, world.snapshot.ecef_m.copy()
        finally:
            world.close()

    a, b, events, ecef = run()
    for e in (a, b):
        assert [ev.detail["reason"] for ev in events if ev.kind == "crash" and ev.entity_id == e.id] == [
            f"collision with {'b' if e is a else 'a'}"]
        [impact] = [ev for ev in events if ev.kind == "wreck_impact" and ev.entity_id == e.id]
        assert impact.alt_msl_m == 400.0
    assert sum(ev.kind == "collision" for ev in events) == 2
    assert np.array_equal(run()[3], ecef)
