"""Regression tests of the fdm acceptance probes' findings (session 29): wheels' penetration
limits from their struts, the sea's surface over bathymetry, take-off from a ground start on a
route, the step bound where the catalog's gear is stable. Real JSBSim, real DEM files."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from fdm import catalog
from fdm.aircraft import DT_MAX_S, Aircraft, FlatTerrain, InitialConditions, static_compressions_m
from fdm.autopilot import WaypointFollower
from server.scenario import ScenarioError, parse_scenario
from server.terrain_cli import build_terrain
from sortie.errors import InvalidArgument

logging.getLogger("jsbsim").setLevel(logging.CRITICAL)

XLL, YLL, CELL, N = -70.02, -33.02, 0.0002, 200
DEM = Path(__file__).resolve().parents[1] / "data" / "dem" / "N47E009.hgt"


def _write_asc(path, heights) -> str:
    with open(path, "w") as f:
        f.write(f"ncols {N}\nnrows {N}\nxllcorner {XLL!r}\nyllcorner {YLL!r}\ncellsize {CELL!r}\n"
                "NODATA_value -9999\n")
        for row in heights:
            f.write(" ".join(f"{v:.3f}" for v in row) + "\n")
    return str(path)


def _grid():
    lat = YLL + (N - 0.5 - np.arange(N)) * CELL  # row 0 north
    lon = XLL + (np.arange(N) + 0.5) * CELL
    return np.meshgrid(lat, lon, indexing="ij")


@pytest.fixture(scope="module")
def deep_sea(tmp_path_factory):
    """Land (50 m) west of lon -69.99, sea with its floor at -200 m east of it."""
    la, lo = _grid()
    return build_terrain([_write_asc(tmp_path_factory.mktemp("dem") / "deep.asc", np.where(lo < -69.99, 50.0, -200.0))])


# -- finding 1: a wheel's penetration limit is its strut's --------------------------------------

def test_b747_ground_start_stays_parked():
    # Old: "terrain penetration 1.55 m" in the first step (its nose strut rests 1.56 m compressed).
    ac = Aircraft("B747", FlatTerrain(100.0), InitialConditions(45.0, 10.0, on_ground=True))
    events = ac.run(2.0)
    assert not ac.crashed, events
    nose = ac.fdm["gear/unit[0]/compression-ft"] * 0.3048
    assert nose > 1.0 and ac.penetration_limits_m[0] > nose * 3.0


def test_l410_stands_on_its_gear():
    # Old: its gear read FlightGear's /controls/gear/gear-down-cond (0: retracted) and it sank
    # through the runway, "terrain penetration" at 0.44 s.
    ac = Aircraft("L410", FlatTerrain(100.0), InitialConditions(45.0, 10.0, on_ground=True))
    events = ac.run(2.0)
    assert not ac.crashed and ac.on_ground, events
    assert ac.fdm["gear/gear-pos-norm"] == 1.0


def test_static_compressions_balance_the_weight():
    # A tricycle: nose 100 in ahead of the CG, mains 20 in behind, all at one height.
    loc = np.array([[-100.0, 0.0, -50.0], [20.0, -60.0, -50.0], [20.0, 60.0, -50.0]])
    d = static_compressions_m(loc, [1000.0, 5000.0, 5000.0], [0.0, 0.0, 0.0], 1200.0) / 0.3048  # ft
    k = np.array([1000.0, 5000.0, 5000.0])
    force = k * d
    assert force.sum() == pytest.approx(1200.0)
    assert (force * loc[:, 0]).sum() == pytest.approx(0.0, abs=1e-6)  # pitch moment about the CG
    assert force[0] == pytest.approx(1200.0 * 20.0 / 120.0)  # the lever rule
    # A light aircraft's struts stay within the 1 m floor; structure points are at the floor.
    c172 = Aircraft("c172x", FlatTerrain(100.0), InitialConditions(45.0, 10.0, on_ground=True))
    assert (c172.penetration_limits_m == c172.max_penetration_m).all()


def test_gear_into_a_cliff_still_crashes(tmp_path):
    # A wall 60 m high across the path: the wheels' limits do not let an aircraft through it.
    la, lo = _grid()
    terrain = build_terrain([_write_asc(tmp_path / "wall.asc", np.where(lo < -70.0, 100.0, 160.0))])
    ac = Aircraft("c172x", terrain, InitialConditions(-33.01, -70.0015, 130.0, "msl", 90.0, 50.0))
    events = ac.run(5.0)
    assert ac.crashed and events[-1].detail["reason"] in ("terrain penetration", "structure contact")


# -- finding 2: over water the surface is the sea's ---------------------------------------------

def test_airborne_start_under_the_sea_surface_is_refused(deep_sea):
    # Old: accepted at -100 m MSL (above the -200 m sea floor), and flew under water.
    with pytest.raises(InvalidArgument) as e:
        Aircraft("c172x", deep_sea, InitialConditions(-33.01, -69.985, -100.0, "msl", 90.0, 50.0))
    assert e.value.field == "alt_m" and "sea surface" in str(e.value)


def test_agl_over_the_sea_is_above_its_surface(deep_sea):
    # Old: 100 m AGL was 100 m above the sea floor, 100 m under water.
    ac = Aircraft("c172x", deep_sea, InitialConditions(-33.01, -69.985, 100.0, "agl", 90.0, 50.0))
    s = ac.state()
    assert s.alt_msl_m == pytest.approx(100.0, abs=0.01) and s.terrain_msl_m == 0.0


def test_a_dive_into_the_sea_ends_at_its_surface(deep_sea):
    # Old: the c172x dived 200 m under water and crashed only on the sea floor.
    ac = Aircraft("c172x", deep_sea, InitialConditions(-33.01, -69.985, 60.0, "agl", 90.0, 50.0))
    events = []
    for _ in range(120 * 20):
        ac.set_controls(pitch=-0.3, throttle=0.5)
        events += ac.step()
        if ac.crashed:
            break
    assert ac.crashed and events[-1].alt_msl_m > -3.0, events


def test_flying_boat_floats_on_the_sea(deep_sea):
    ac = Aircraft("Boeing314", deep_sea, InitialConditions(-33.01, -69.985, on_ground=True))
    events = ac.run(2.0)
    assert not ac.crashed and ac.state().terrain_msl_m == 0.0, events


# -- finding 3: a route from a ground start takes off -------------------------------------------

def test_route_from_a_ground_start_takes_off():
    # Old: full throttle with the ground start's brakes on for good: it never moved.
    ac = Aircraft("c172x", FlatTerrain(400.0), InitialConditions(47.485, 9.56, heading_deg=100.0, on_ground=True))
    wf = WaypointFollower(ac, [(47.50, 9.60, 1000.0)], 50.0)
    events = wf.run(30.0)
    assert not ac.crashed, events
    assert any(e.kind == "takeoff" for e in events)
    assert ac.controls.brakes == 0.0 and ac.state().agl_m > 10.0


# -- finding 4: the step where the catalog's gear is stable -------------------------------------

def test_longest_step_keeps_a_parked_aircraft_parked():
    # Old: 0.1 s was accepted, and a c172x parked at it took off by itself and crashed.
    with pytest.raises(InvalidArgument) as e:
        Aircraft("c172x", FlatTerrain(400.0), InitialConditions(47.485, 9.56, on_ground=True), dt=0.1)
    assert e.value.field == "dt"
    for name in ("c172x", "B747"):
        ac = Aircraft(name, FlatTerrain(400.0), InitialConditions(47.485, 9.56, on_ground=True), dt=DT_MAX_S)
        s0 = ac.state()
        events = ac.run(10.0)
        s = ac.state()
        assert not events and s.on_ground and abs(s.alt_msl_m - s0.alt_msl_m) < 0.2, (name, events)


@pytest.mark.parametrize("rate, ok", [(30, False), (10, False), (50, True), (60, True)])
def test_scenario_fdm_rate_is_the_aircraft_step_bound(rate, ok):
    # Old: [1, 1000] documented, below 10 Hz a dt error at start, 10..49 Hz accepted.
    doc = {"exercise": {"name": "t", "start_time": "2026-06-15T07:00:00Z", "fdm_rate_hz": rate,
                        "world_rate_hz": 10},
           "terrain": {"dem": [str(DEM)]},
           "agents": [{"name": "c1", "kind": "aircraft", "type": "c172x", "coalition": "blue", "lat_deg": 47.485,
                       "lon_deg": 9.56, "heading_deg": 100.0, "on_ground": True}]}
    if ok:
        assert parse_scenario(doc, DEM.parent).exercise.fdm_rate_hz == rate and 1.0 / rate <= DT_MAX_S
        return
    with pytest.raises(ScenarioError) as e:
        parse_scenario(doc, DEM.parent)
    assert "exercise.fdm_rate_hz" in str(e.value) and f"[{math.ceil(1.0 / catalog.DT_MAX_S)}, " in str(e.value)
