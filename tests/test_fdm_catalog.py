"""Every aircraft of the jsbsim wheel's catalog, by name (issue #3): each one loads and
flies, or fails with a typed error that says why; never a process crash or a raw JSBSim
exception. Models that read properties nothing defines, models without tanks or with
degenerate contacts, and a model flown far outside its envelope are the hard cases.

Real JSBSim on a flat terrain (these are about the models, not the terrain).
"""

import math
import subprocess
import sys

import numpy as np
import pytest

from fdm import catalog
from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.events import CRASH, OUT_OF_FUEL
from fdm.fleet import Fleet
from sortie.errors import InvalidArgument, SortieError

GROUND_M = 400.0


def _airborne(name: str, speed_mps: float = 60.0, **ic) -> Aircraft:
    return Aircraft(name, FlatTerrain(GROUND_M), InitialConditions(
        47.5, 9.5, 3000.0, heading_deg=90.0, speed_mps=speed_mps, trim=False, **ic))


def test_every_catalog_aircraft_flies_or_is_refused_by_name():
    """One second of untrimmed flight at 60 m/s, 2600 m above the ground, for each model:
    a finite state every time (a model that diverges ends in a crash event, its state
    frozen where it last was finite), and nothing but SortieError otherwise."""
    flown, refused = [], []
    for name in catalog.list_aircraft():
        try:
            ac = _airborne(name)
            ac.run(1.0)
        except SortieError as exc:
            refused.append((name, str(exc)))
            continue
        row = np.array(ac.raw_values())
        assert np.isfinite(row).all(), name
        if ac.crashed:
            assert any(e.kind == CRASH for e in ac.events), name
        flown.append(name)
    assert not refused, refused  # an airborne start without trim asks nothing a model can lack
    assert len(flown) >= 50


def test_undefined_properties_are_created_and_flightgear_throttles_driven():
    """f104 reads systems/radar/range, which nothing defines (JSBSim raises on its first
    evaluation): it is created and the model flies. The fokker50's FCS takes its throttle
    commands from FlightGear's /controls/engines/engine[i]/throttle: Sortie's throttle
    drives those too, so the engines answer the control."""
    f104 = _airborne("f104", speed_mps=150.0)
    assert "systems/radar/range" in f104.undefined_properties
    f104.run(0.5)
    assert not f104.crashed

    fokker = _airborne("fokker50", speed_mps=80.0)
    fg = [p for p in fokker.undefined_properties if p.startswith("/controls/engines/engine")]
    assert len(fg) == 2
    for throttle in (0.9, 0.2):
        fokker.set_controls(throttle=throttle)
        fokker.run(0.2)
        assert all(fokker.fdm[p] == throttle for p in fg)
        cmd = fokker.fdm["fcs/throttle-cmd-norm[0]"]  # the model's own function of the FG throttle
        assert cmd == pytest.approx(throttle * fokker.fdm["fcs/eec-throttle-multiplier"], abs=1e-9)
    # A second aircraft of the model starts without rediscovering them.
    again = _airborne("fokker50", speed_mps=80.0)
    assert again.undefined_properties == fokker.undefined_properties
    assert len(fokker._set["throttle"]) == 4  # two engines: fcs/* and FlightGear's, one setter a node


def test_flightgear_inputs_a_model_declares_are_driven_too():
    """The p51d declares FlightGear's /controls/engines/engine/throttle itself (<property>) and
    reads it (its boost schedule's input): nothing is undefined, and Sortie's throttle still
    reaches it, once (one node, one setter)."""
    p51 = _airborne("p51d", speed_mps=80.0)
    assert not p51.undefined_properties and len(p51._set["throttle"]) == 2
    for throttle in (0.2, 0.9):
        p51.set_controls(throttle=throttle)
        p51.run(0.5)
        assert p51.fdm["/controls/engines/engine/throttle"] == throttle


@pytest.mark.parametrize("name", ["SGS", "minisgs"])
def test_ground_start_with_degenerate_contacts_does_not_crash_the_process(name):
    """SGS and minisgs put all six contacts at the origin; JSBSim 1.3.3's ground trim
    crashes the process on them (SIGSEGV). Sortie skips that trim where the contacts do not
    span a plane: run in a child process, so a regression fails here instead of killing
    the test run."""
    code = ("from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions\n"
            f"ac = Aircraft({name!r}, FlatTerrain(400.0), InitialConditions(47.5, 9.5, 0.0, on_ground=True))\n"
            "ac.run(2.0)\n"
            "print('ok', ac.crashed)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert r.stdout.strip().splitlines()[-1].startswith("ok")


def test_aircraft_without_tanks_never_runs_out_of_fuel():
    """A glider has no propulsion/total-fuel-lbs: it loads, reports 0 kg on board, never
    an out-of-fuel event, and refuses fuel by name."""
    glider = _airborne("sgs233", speed_mps=30.0)
    assert not glider.has_fuel and glider.fuel_kg() == 0.0
    glider.run(3.0)
    assert not any(e.kind == OUT_OF_FUEL for e in glider.events)
    with pytest.raises(InvalidArgument, match="fuel_kg"):
        glider.set_fuel_kg(10.0)
    glider.set_fuel_kg(0.0)  # nothing to do, nothing refused


def test_a_diverging_model_crashes_where_it_was_finite_and_the_fleet_flies_on():
    """The paraglider at 60 m/s (ten times its speed) makes JSBSim's state NaN within a
    fraction of a second. That is a crash event ("state diverged") at its last finite
    position, its state out frozen there (finite), and the fleet it flies in keeps
    stepping the others (their batched terrain query never sees the NaN)."""
    terrain = FlatTerrain(GROUND_M)
    fleet = Fleet(terrain)
    pg = fleet.add(Aircraft("paraglider", terrain, InitialConditions(47.5, 9.5, 3000.0, speed_mps=60.0, trim=False)))
    c172 = fleet.add(Aircraft("c172x", terrain, InitialConditions(47.5, 9.6, 3000.0, heading_deg=90.0,
                                                                  speed_mps=50.0)))
    events = [e for _ in range(60) for _, evs in fleet.advance(4) for e in evs]
    crash = [e for e in events if e.kind == CRASH]
    assert len(crash) == 1 and crash[0].detail["reason"] == "state diverged"
    assert pg.crashed and not c172.crashed and c172.time_s == pytest.approx(2.0, abs=1e-6)
    assert math.isfinite(crash[0].lat_deg) and abs(crash[0].lat_deg - 47.5) < 0.01
    assert abs(crash[0].alt_msl_m - 3000.0) < 100.0
    state = pg.state()
    assert np.isfinite(fleet.raw_values()).all()
    assert state.lat_deg == pytest.approx(crash[0].lat_deg) and state.alt_msl_m == pytest.approx(crash[0].alt_msl_m)


def test_a_piston_aircraft_that_cannot_trim_full_rich_high_up_is_leaned():
    """At 3000 m full rich leaves a c172p without the power for level flight at any speed
    (JSBSim's trim fails); the start tries again leaned to the air's density ratio, as a
    pilot leans, and it trims and holds level. A model that trims full rich keeps it (the
    c310 there, a c172x low down)."""
    c172p = Aircraft("c172p", FlatTerrain(0.0), InitialConditions(47.0, 9.0, 3000.0, speed_mps=50.0))
    sigma = c172p.fdm["atmosphere/sigma"]
    assert 0.7 < sigma < 0.8 and c172p.controls.mixture == pytest.approx(sigma, abs=0.01)
    start = c172p.state()
    c172p.run(10.0)
    assert abs(c172p.state().alt_msl_m - start.alt_msl_m) < 1.0 and not c172p.crashed
    assert Aircraft("c310", FlatTerrain(0.0), InitialConditions(47.0, 9.0, 3000.0, speed_mps=100.0)).controls.mixture == 1.0
    assert Aircraft("c172x", FlatTerrain(0.0), InitialConditions(47.0, 9.0, 300.0, speed_mps=50.0)).controls.mixture == 1.0


def test_the_trim_survey_covers_the_catalog_and_still_holds():
    """catalog.TRIM_SPEEDS_SURVEYED / TRIM_NEVER (what TrimFailed's message quotes) name every
    model once, on the survey's grid; a sample still trims where the table says (a powered
    model at its lowest and highest speed, a glider at its lowest) and a model the table
    says never trims fails there (so a JSBSim upgrade that moves them fails here)."""
    names = set(catalog.list_aircraft())
    surveyed, never = set(catalog.TRIM_SPEEDS_SURVEYED), set(catalog.TRIM_NEVER)
    assert surveyed | never == names and not surveyed & never
    assert all(v in catalog.TRIM_SURVEY_SPEEDS for s in catalog.TRIM_SPEEDS_SURVEYED.values() for v in s)
    alt = catalog.TRIM_SURVEY_ALT_M
    for name, v in (("c172x", min), ("c172x", max), ("sgs126", min)):
        ac = Aircraft(name, FlatTerrain(0.0), InitialConditions(47.0, 9.0, alt, speed_mps=float(
            v(catalog.TRIM_SPEEDS_SURVEYED[name]))))
        assert ac.trim_gamma_deg == 0.0 if name == "c172x" else ac.trim_gamma_deg < 0.0
    with pytest.raises(SortieError, match="trims at no speed"):
        Aircraft("weather-balloon", FlatTerrain(0.0), InitialConditions(47.0, 9.0, alt, speed_mps=20.0))
