"""Regression tests of the author probe's ground-start finding (session 31): an L410 parked
on_ground at a field of 380 m or more rolled away at 10 m/s with its brakes set. Causes: the
L410's propeller file gives its diameter without a unit, which JSBSim reads as 99 ft
(fdm.catalog.propeller_diameter_fixes), and a ground start began at the full-throttle steady
state JSBSim's set-running leaves (fdm.aircraft.Aircraft._settle_engines). Real JSBSim."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest

from fdm import catalog
from fdm.aircraft import RUNNING_KINDS, Aircraft, FlatTerrain, InitialConditions

logging.getLogger("jsbsim").setLevel(logging.CRITICAL)

FIELDS_M = (100.0, 400.0, 1000.0, 2000.0)
PARKED_S = 5.0
PARKED_SPEED_MPS = 0.2  # the probe's bound: ground speed 5 s after a ground start, brakes set
FT_M = 0.3048

# Propeller types of the catalog left out, and why.
NOT_PARKED = {
    "paraglider": "not at rest even at 120 Hz (fdm.catalog, DT_MAX_S)",
    "Short_S23": "a flying boat without landing gear: a ground start on land is refused",
}
# Thrust below zero at idle that is the model's, not a start's: the ZLT-NT's variable-pitch
# propellers (-25 to 35 degrees, an airship's) sit in reverse at idle; it stays put all the same.
REVERSE_AT_IDLE = {"ZLT-NT"}


def _propeller_types() -> list:
    """The catalog's piston and turboprop types (whatever it holds: a new one is checked too)."""
    kinds = {"piston_engine", "turboprop_engine"}
    return [n for n in catalog.list_aircraft()
            if kinds & {e.kind for e in catalog.propulsion(n).engines} and n not in NOT_PARKED]


def _thrust_lbs(ac: Aircraft) -> list:
    return [ac.fdm[f"propulsion/engine[{i}]/thrust-lbs"] for i, k in enumerate(ac.engine_kinds) if k in RUNNING_KINDS]


def _parked(name: str, field_m: float) -> Aircraft:
    return Aircraft(name, FlatTerrain(field_m), InitialConditions(45.0, 10.0, heading_deg=100.0, on_ground=True))


@pytest.mark.parametrize("field_m", [100.0, 380.0, 1000.0, 2000.0])
def test_a_parked_l410_idles_on_its_brakes(field_m):
    # Old: 380 m: 9.84 m/s after 2 s, thrust -499 lbf each; 1000 m: 94 and 6112 lbf; 100 m: at
    # rest, but its propellers at 7 rpm and its thrust 0 (a 99 ft propeller the engines cannot turn).
    ac = _parked("L410", field_m)
    ac.run(PARKED_S)
    thrust = _thrust_lbs(ac)
    rpm = [ac.fdm[f"propulsion/engine[{i}]/propeller-rpm"] for i in range(2)]
    assert ac.fdm["velocities/vg-fps"] * FT_M < PARKED_SPEED_MPS and ac.on_ground and not ac.crashed
    assert all(200.0 < t < 600.0 for t in thrust) and max(thrust) - min(thrust) < 1.0, thrust
    # The M601's idle (N1 60 %) turns a 2.5 m propeller at its fine pitch at about 1150 rpm.
    assert all(900.0 < r < 1400.0 for r in rpm), rpm


def test_the_l410_propeller_is_99_inches():
    # Old: JSBSim read vrtule2.xml's bare "<diameter> 99 </diameter>" as 99 ft.
    fixes = catalog.propeller_diameter_fixes("L410")
    assert [(ref, Path(path).name, d) for ref, path, d in fixes] == [("vrtule2", "vrtule2.xml", 99.0)]
    assert not [n for n in catalog.list_aircraft() if n != "L410" and catalog.propeller_diameter_fixes(n)]
    # The diameter JSBSim flies with, from its tip speed at rest: helical tip Mach = pi D n / a.
    ac = _parked("L410", 100.0)
    f = ac.fdm
    d_ft = (f["propulsion/engine[0]/helical-tip-Mach"] * f["atmosphere/a-fps"]
            / (math.pi * f["propulsion/engine[0]/propeller-rpm"] / 60.0))
    assert d_ft * 12.0 == pytest.approx(99.0, rel=0.01)
    with catalog.model_paths("L410") as paths:
        copy = Path(paths[0]) / "L410" / "Engines" / "vrtule2.xml"
        assert '<diameter unit="IN">' in copy.read_text()
    assert not copy.exists()  # the corrected copy lives only while JSBSim loads it
    with catalog.model_paths("c172p") as paths:
        assert paths is None


@pytest.mark.parametrize("field_m", FIELDS_M)
def test_every_propeller_type_stays_parked_at_idle(field_m):
    # Old: the L410 (10 m/s at 400 m, 2 m/s and 94 / 6112 lbf at 1000 m), the Boeing314 at 1000 and
    # 2000 m (4 x 3600 lbf for a second on its unbraked hull: 0.9 m/s), the brakeless dr1 (6 m/s at
    # every field), the wrightFlyer1903 (crashed at 100 and 400 m).
    bad = []
    for name in _propeller_types():
        ac = _parked(name, field_m)
        ac.run(PARKED_S)
        speed = ac.fdm["velocities/vg-fps"] * FT_M
        thrust = _thrust_lbs(ac)
        finite = all(math.isfinite(t) for t in thrust)
        symmetric = finite and max(thrust) - min(thrust) <= 0.01 * max(abs(t) for t in thrust) + 1.0
        forward = finite and (name in REVERSE_AT_IDLE or min(thrust) >= -1.0)
        if ac.crashed or not speed < PARKED_SPEED_MPS or not (symmetric and forward):
            bad.append((name, round(speed, 3), [round(t, 1) for t in thrust], ac.crashed))
    assert not bad, f"at a {field_m:g} m field: {bad}"


@pytest.mark.parametrize("name, field_m", [("Boeing314", 1000.0), ("c172p", 400.0), ("dr1", 100.0)])
def test_a_ground_start_begins_at_its_idle(name, field_m):
    # Old: thrust at time 0 was set-running's full-throttle steady state: the Boeing314's 3567 lbf
    # an engine (290 lbf 5 s on), the c172p's 414 lbf (39), the dr1's 288 lbf (41).
    ac = _parked(name, field_m)
    start = _thrust_lbs(ac)
    assert ac.time_s == 0.0
    # The settling run burnt no fuel the start keeps: as much as a start with its engines off.
    off = Aircraft(name, FlatTerrain(field_m), InitialConditions(45.0, 10.0, heading_deg=100.0, on_ground=True,
                                                                engines_running=False))
    assert ac.fuel_kg() == off.fuel_kg()
    ac.run(PARKED_S)
    later = _thrust_lbs(ac)
    assert all(abs(a - b) <= 0.1 * abs(b) + 5.0 for a, b in zip(start, later)), (start, later)
