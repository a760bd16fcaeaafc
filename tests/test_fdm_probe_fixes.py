"""Regressions found by acceptance probing of the fdm: ground starts on slopes (the CG read
before JSBSim set it), landings on slopes, JSBSim's output files and stdout, the take-off
event's position.

Real JSBSim; the terrains are analytic (a plane slope) so the expected values are exact.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.contacts import contact_points
from terrain.terrain import HeightResult

M_PER_DEG_LAT = 111_200.0  # near 47 N: places the slope's metres; the bounds below are much looser


class SlopeTerrain:
    """A plane rising northwards: h = h0 + grade * (metres north of lat0); with ``start_m``,
    flat at h0 up to ``start_m`` north of lat0 and rising from there."""

    def __init__(self, lat0, h0, grade, start_m=None):
        self.lat0, self.h0, self.grade, self.start_m = lat0, h0, grade, start_m

    def heights(self, lat, lon):
        north_m = (np.asarray(lat, np.float64) - self.lat0) * M_PER_DEG_LAT
        h = self.h0 + self.grade * (north_m if self.start_m is None else np.maximum(north_m - self.start_m, 0.0))
        return HeightResult(h, np.ones(north_m.shape, np.uint8))


def gear_clearances(ac, terrain):
    """Each gear contact's clearance (m) above ``terrain`` now, placed by the contact kernel
    from JSBSim's own CG, attitude and position."""
    s = ac.state()
    cg = [ac.fdm[f"inertia/cg-{a}-in"] for a in "xyz"]
    p_lat, p_lon, h = contact_points(s.lat_deg, s.lon_deg, s.alt_msl_m, cg, *s.euler_rad, (0.0, 0.0),
                                     ac._contact_locations_in)
    c = h - terrain.heights(p_lat[1:], p_lon[1:]).height_msl_m
    return c[[k.kind == "gear" for k in ac.contacts]]


# -- 1. the ground start reads JSBSim's CG ----------------------------------------------------------

@pytest.mark.parametrize("name", ["737", "A4"])
def test_ground_start_on_a_10_percent_slope_stands_still(name):
    """At rest, brakes on, facing up a plain 10 % slope. The start placed the contacts from
    the CG before JSBSim had computed it (0, 0, 0: a 737's contacts 15.5 m aft of where
    they are), so the nose wheel started 1.58 m inside the slope: a crash at 0.008 s."""
    slope = SlopeTerrain(47.0, 500.0, 0.10)
    ac = Aircraft(name, slope, InitialConditions(47.0, 8.0, on_ground=True, heading_deg=0.0))
    # Right after the start every wheel is on the ground, none buried.
    c = gear_clearances(ac, slope)
    assert c.min() > -0.5 and c.min() < 0.05, c
    s0 = ac.state()
    ac.set_controls(brakes=1.0)
    ac.run(3.0)
    s = ac.state()
    assert ac.events == [] and not ac.crashed and s.on_ground
    assert np.linalg.norm(s.ecef_m - s0.ecef_m) < 0.5
    assert gear_clearances(ac, slope).min() > -0.5



def test_ground_start_is_deterministic():
    """The CG is read after a first run_ic: the same start still gives the same flight, bit for bit."""
    slope = SlopeTerrain(47.0, 500.0, 0.10)
    rows = []
    for _ in range(2):
        ac = Aircraft("737", slope, InitialConditions(47.0, 8.0, on_ground=True, heading_deg=30.0))
        ac.set_controls(brakes=0.0, throttle=0.3)
        ac.run(2.0)
        rows.append(ac.raw_state())
    assert (rows[0] == rows[1]).all()


# -- 3. nothing written into the jsbsim package, nothing of JSBSim's on stdout ---------------------

def _package_outputs():
    """(name, size, mtime) of every CSV file in the jsbsim package's own directory."""
    from fdm import catalog

    return sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in catalog.root_dir().glob("*.csv"))


def test_starts_write_no_output_file_into_the_jsbsim_package():
    """The c172x declares a CSV output (JSBout172B.csv). disable_output() stops the writing but
    each run_ic opened (truncated) the file again, in the installed package's directory; a
    second run_ic (ground start, lean retry) then printed 'ERROR: unable to open the file'."""
    from fdm.aircraft import TrimFailed

    before = _package_outputs()
    ac = Aircraft("c172x", FlatTerrain(0.0), InitialConditions(0.0, 0.0, 1000.0, speed_mps=50.0))
    assert ac.fdm.get_output_filename(0) == os.devnull
    ac.run(1.0)
    Aircraft("c172x", FlatTerrain(0.0), InitialConditions(0.0, 0.0, on_ground=True)).run(0.5)
    with pytest.raises(TrimFailed):  # full rich, then leaned: two run_ic
        Aircraft("c172x", FlatTerrain(0.0), InitialConditions(0.0, 0.0, 2000.0, speed_mps=200.0))
    Aircraft("B17", FlatTerrain(0.0), InitialConditions(0.0, 0.0, 1000.0, speed_mps=80.0, trim=False)).run(0.2)
    assert _package_outputs() == before


def test_jsbsim_messages_go_to_the_jsbsim_logger(caplog):
    import logging

    with caplog.at_level(logging.DEBUG, logger="jsbsim"):
        # Full rich at 3000 m the c172p's trim fails ("udot doesn't appear to be trimmable"), leaned it holds.
        ac = Aircraft("c172p", FlatTerrain(0.0), InitialConditions(0.0, 0.0, 3000.0, speed_mps=45.0))
    assert ac.controls.mixture < 1.0
    assert any("trimmable" in r.getMessage() for r in caplog.records if r.name == "jsbsim")


def test_cli_json_stdout_is_one_json_document():
    """JSBSim's 'Sorry, udot doesn't appear to be trimmable' (the c172p's full-rich trim at
    3000 m) was printed on stdout, before the JSON: `sortie fdm fly ... --json` did not parse."""
    r = subprocess.run([sys.executable, "-m", "sortie.cli", "fdm", "fly", "c172p", "--lat", "0", "--lon", "0",
                        "--alt-m", "3000", "--speed-mps", "45", "--seconds", "2", "--json"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["aircraft"] == "c172p" and not summary["crashed"]
    assert "trimmable" in r.stderr  # JSBSim's message is not lost: on stderr


# -- 4. the take-off event says where the wheels left ----------------------------------------------

def test_takeoff_event_has_the_time_and_place_the_wheels_left():
    """The event is reported takeoff_clear_s (0.5 s) after the wheels leave; its time was
    that instant but its position the one 0.5 s later (15 m further at 30 m/s)."""
    from fdm.events import LIMITS, TAKEOFF, EventDetector

    d = EventDetector(LIMITS["light"], on_ground=True)
    assert d.update(0.0, 47.0, 8.0, 500.0, True, False, 0.0, 1.0) == []
    events = []
    for k in range(1, 80):  # 1/120 s steps from t = 1 s, climbing away north
        t = 1.0 + (k - 1) / 120.0
        events += d.update(t, 47.0 + 1e-5 * k, 8.0, 500.0 + 0.01 * k, False, False, -1.0, 1.0)
    (ev,) = events
    assert ev.kind == TAKEOFF and ev.time_s == 1.0
    assert (ev.lat_deg, ev.lon_deg, ev.alt_msl_m) == (47.0 + 1e-5, 8.0, 500.01)


def test_takeoff_event_of_an_aircraft_is_where_it_was_at_that_time():
    ac = Aircraft("c172x", FlatTerrain(500.0), InitialConditions(47.0, 8.0, on_ground=True))
    ac.set_controls(throttle=1.0, brakes=0.0)
    where = {}
    for _ in range(120 * 40):
        s = ac.state()
        where[round(s.time_s * 120)] = (s.lat_deg, s.lon_deg, s.alt_msl_m)
        if s.airspeed_true_mps > 28.0:
            ac.set_controls(pitch=0.3)
        if [e for e in ac.step() if e.kind == "takeoff"]:
            break
    (ev,) = ac.events
    assert ev.kind == "takeoff" and ac.time_s - ev.time_s > 0.49
    # The state at the step that ended at the event's time.
    assert (ev.lat_deg, ev.lon_deg, ev.alt_msl_m) == pytest.approx(where[round(ev.time_s * 120)], abs=1e-9)
