"""Autopilots on real JSBSim: heading, altitude and speed hold settle and stay within bounds."""

import math

import numpy as np
import pytest

from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.autopilot import Autopilot, WaypointFollower, wrap_pi
from sortie.errors import InvalidArgument


def _hold(name, speed, alt, seconds, settle):
    ac = Aircraft(name, FlatTerrain(0.0), InitialConditions(47.3, 9.5, alt, heading_deg=0.0, speed_mps=speed))
    ap = Autopilot(ac)
    # A 90 degree turn, a 100 m climb and 10 % more speed, all at once.
    ap.set_targets(heading_deg=90.0, alt_msl_m=alt + 100.0, speed_mps=speed * 1.1)
    ap.run(settle)
    worst_alt = worst_hdg = worst_spd = 0.0
    for _ in range(int((seconds - settle) / ac.dt)):
        ap.update()
        ac.step()
        r = ac.raw_state()
        s_alt = r[3] * 0.3048
        worst_alt = max(worst_alt, abs(s_alt - (alt + 100.0)))
        worst_hdg = max(worst_hdg, abs(math.degrees(wrap_pi(r[9] - math.radians(90.0)))))
        worst_spd = max(worst_spd, abs(r[17] * 0.3048 - speed * 1.1))
    assert ac.events == []
    return worst_alt, worst_hdg, worst_spd


@pytest.mark.parametrize("name, speed, alt", [("c172x", 50.0, 1000.0), ("f16", 200.0, 3000.0)])
def test_heading_altitude_speed_hold_settle_within_bounds(name, speed, alt):
    # Stated bounds after 60 s of settling, over the next 30 s: altitude +-30 m,
    # heading +-5 deg, speed +-3 m/s.
    worst_alt, worst_hdg, worst_spd = _hold(name, speed, alt, 90.0, 60.0)
    assert worst_alt < 30.0 and worst_hdg < 5.0 and worst_spd < 3.0, (worst_alt, worst_hdg, worst_spd)


def test_waypoints_are_passed_in_order():
    ac = Aircraft("c172x", FlatTerrain(0.0), InitialConditions(47.3, 9.5, 1000.0, heading_deg=0.0,
                                                                speed_mps=50.0))
    # 2 km north, then 2 km east of that.
    wps = [(47.318, 9.5, 1050.0), (47.318, 9.5265, 1050.0)]
    wf = WaypointFollower(ac, wps, speed_mps=50.0)
    wf.run(120.0)
    assert [p[0] for p in wf.passed] == [0, 1] and wf.done, wf.passed
    assert all(p[2] < wf.capture_radius_m for p in wf.passed)
    assert ac.events == []


def test_bad_targets_name_the_field():
    ac = Aircraft("c172x", FlatTerrain(0.0), InitialConditions(47.3, 9.5, 1000.0, speed_mps=50.0))
    ap = Autopilot(ac)
    with pytest.raises(InvalidArgument, match="alt_msl_m"):
        ap.set_targets(alt_msl_m=float("nan"))
    with pytest.raises(InvalidArgument, match="waypoints"):
        WaypointFollower(ac, [(91.0, 0.0, 100.0)], 50.0)
    assert np.isfinite(ac.state().alt_msl_m)
