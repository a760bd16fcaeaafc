"""Regression tests of the fdm acceptance probe's findings on aircraft start-up (session 30):
engines JSBSim's set-running leaves dead are started on their starter (or the start is refused),
the Concorde's collector tanks are kept fed, a ground start at a high field is leaned, and
`sortie fdm fly`'s trim-failure advice names what the command line can do. Real JSBSim."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

import fdm.aircraft as aircraft_module
from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions, TrimFailed
from sortie.errors import InvalidArgument

logging.getLogger("jsbsim").setLevel(logging.CRITICAL)

DEM = Path(__file__).resolve().parents[1] / "data" / "dem" / "N47E009.hgt"


def _running(ac) -> list:
    return [ac.fdm[f"propulsion/engine[{i}]/set-running"] > 0.5 for i in range(ac.n_engines)]


def _thrust_lbs(ac) -> float:
    return sum(ac.fdm[f"propulsion/engine[{i}]/thrust-lbs"] for i in range(ac.n_engines))


# -- finding 1: engines dead after a ground start ----------------------------------------------

@pytest.mark.parametrize("name", ["c310", "c182", "Boeing314", "p51d"])
def test_ground_start_runs_every_engine(name):
    # Old: c310 0/2, c182 0/1, Boeing314 0/4, p51d 0/1 engines running, 0 lbf, ground speed 0
    # after 5 s at full throttle with the brakes off. Stated bounds: the start is the requested
    # one (time 0, at rest, the model's own fuel: cranking is undone), every engine runs, and 5 s
    # at full throttle make thrust and roll the aircraft at least 2 m/s (measured 6.2-9.0).
    ic = InitialConditions(-33.9, 18.6, heading_deg=45.0, on_ground=True)
    ac = Aircraft(name, FlatTerrain(0.0), ic)
    fuel_kg = Aircraft(name, FlatTerrain(0.0), InitialConditions(-33.9, 18.6, on_ground=True,
                                                                 engines_running=False)).fuel_kg()
    s0 = ac.state()
    assert ac.time_s == 0.0 and s0.ground_speed_mps < 1e-3 and abs(s0.lat_deg + 33.9) < 1e-9
    assert ac.fuel_kg() == pytest.approx(fuel_kg, rel=1e-12)
    assert all(_running(ac)), _running(ac)
    ac.set_controls(throttle=1.0, brakes=0.0)
    ac.run(5.0)
    assert all(_running(ac)) and not ac.crashed, (_running(ac), ac.events)
    assert _thrust_lbs(ac) > 100.0 and ac.state().ground_speed_mps > 2.0, (_thrust_lbs(ac), ac.state())


def test_engine_that_will_not_start_refuses_the_start(monkeypatch):
    # JSBSim fires a piston engine once its starter has turned it for 175 frames (FGPiston): on
    # the starter for only 0.5 s (60 frames) the c182, dead after set-running, never runs. Old:
    # the start went ahead with a dead engine (a scenario's aircraft sat still forever). Now
    # InvalidArgument names the field, the aircraft and the engine.
    monkeypatch.setattr(aircraft_module, "CRANK_S", 0.5, raising=False)
    with pytest.raises(InvalidArgument) as e:
        Aircraft("c182", FlatTerrain(0.0), InitialConditions(-33.9, 18.6, on_ground=True))
    assert e.value.field == "engines_running" and "c182" in str(e.value) and "engine 0" in str(e.value)
    # With its engines off it starts (an engine-out exercise), nothing cranked.
    ac = Aircraft("c182", FlatTerrain(0.0), InitialConditions(-33.9, 18.6, on_ground=True, engines_running=False))
    assert not any(_running(ac))


def test_airborne_start_whose_engine_will_not_start_glides_and_says_so(caplog):
    # The p51d at 3000 m and 60 m/s: its manifold-pressure throttle loop holds the throttle shut
    # while the engine is stopped, and its starter cannot fire it in that air. In the air the
    # aircraft still flies (an engine-out glide, as every untrimmed airborne start of the catalog
    # does): not refused, but a warning names the aircraft and the engine (old: silent).
    with caplog.at_level(logging.WARNING, logger="fdm.aircraft"):
        ac = Aircraft("p51d", FlatTerrain(400.0), InitialConditions(47.5, 9.5, 3000.0, heading_deg=90.0,
                                                                    speed_mps=60.0, trim=False))
    assert ac.time_s == 0.0 and not any(_running(ac))
    assert any("p51d" in r.getMessage() and "engine 0" in r.getMessage() and "gliding" in r.getMessage()
               for r in caplog.records), caplog.text


def test_scenario_with_an_aircraft_whose_engine_will_not_start_is_refused(monkeypatch):
    # The refusal reaches a scenario's load as a ScenarioError naming the agent (the server exits 2).
    from server.scenario import ScenarioError, parse_scenario
    from server.sim_server import build_world, open_terrain

    monkeypatch.setattr(aircraft_module, "CRANK_S", 0.5, raising=False)
    doc = {"exercise": {"name": "t", "start_time": "2026-06-15T07:00:00Z", "fdm_rate_hz": 60, "world_rate_hz": 10},
           "terrain": {"dem": [str(DEM)]},
           "agents": [{"name": "skylane", "kind": "aircraft", "type": "c182", "coalition": "blue",
                       "lat_deg": 47.485, "lon_deg": 9.56, "heading_deg": 100.0, "on_ground": True}]}
    scenario = parse_scenario(doc, DEM.parent)
    terrain, _, _ = open_terrain(scenario)
    with pytest.raises(ScenarioError) as e:
        build_world(scenario, terrain)
    assert "agents[0]" in str(e.value) and "engines_running" in str(e.value) and "c182" in str(e.value)


def test_concorde_engines_keep_running_at_full_power():
    # Old: its engines feed from four 46 lb collector tanks that FlightGear's Nasal refills; all four
    # starved 5 s into a full-reheat take-off roll. Stated bounds after 12 s at full throttle: all
    # four run with over 100,000 lbf, each collector holds at least half its 46 lb, and the fuel
    # on board only went down (the transfer moves fuel, it makes none).
    ac = Aircraft("Concorde", FlatTerrain(0.0), InitialConditions(-33.9, 18.6, on_ground=True))
    total0 = ac.fdm["propulsion/total-fuel-lbs"]
    ac.set_controls(throttle=1.0, brakes=1.0)
    ac.run(12.0)
    assert all(_running(ac)) and _thrust_lbs(ac) > 100_000.0, (_running(ac), _thrust_lbs(ac))
    collectors = [ac.fdm[f"propulsion/tank[{i}]/contents-lbs"] for i in (13, 14, 15, 16)]
    assert min(collectors) >= 23.0, collectors
    total = ac.fdm["propulsion/total-fuel-lbs"]
    burnt = sum(ac.fdm[f"propulsion/engine[{i}]/fuel-used-lbs"] for i in range(4))
    assert total < total0 and total == pytest.approx(total0 - burnt, abs=1.0), (total0, total, burnt)


def test_feed_tank_transfer_leaves_other_models_alone():
    # Models whose engines feed from every fuel tank have nothing to transfer; one with its own
    # fuel system (the Short_S23's external flows) is left to it.
    for name in ("c172p", "737", "Short_S23"):
        ac = Aircraft(name, FlatTerrain(0.0), InitialConditions(10.0, 20.0, 1500.0, speed_mps=60.0, trim=False))
        assert not ac._feed_tanks, name


# -- finding 2: a ground start at a high field kept full-rich mixture ---------------------------

def _static_power_hp(name: str, field_m: float):
    ac = Aircraft(name, FlatTerrain(field_m), InitialConditions(-33.9, 18.6, on_ground=True))
    ac.set_controls(throttle=1.0)  # brakes on: a static run-up
    ac.run(4.0)
    return ac, ac.fdm["propulsion/engine[0]/power-hp"]


def test_high_field_ground_start_is_leaned():
    # Old: the c172p full rich at a 3000 m field made -1.5 hp of its 206 at sea level. Reference:
    # Gagg and Farrar's P/P0 = 1.132 sigma - 0.132 (normally aspirated piston engine at constant
    # rpm and a best-power mixture; sigma 0.742 at 3000 m ISA) gives 0.708. Stated bound: within
    # [0.6, 0.85] of the sea-level power (measured 0.731), the mixture leaned to sigma.
    _, p0 = _static_power_hp("c172p", 0.0)
    ac, p = _static_power_hp("c172p", 3000.0)
    sigma = ac.fdm["atmosphere/sigma"]
    assert ac.controls.mixture == pytest.approx(sigma, abs=0.01) and 0.70 < sigma < 0.75
    assert 0.6 < p / p0 < 0.85, (p, p0, 1.132 * sigma - 0.132)


def test_self_leaning_model_is_not_leaned_twice():
    # The c310's automatic mixture control sets its mixture's position to about sigma at full rich:
    # its command stays 1 at a 3000 m field, and its power keeps within [0.6, 0.85] of sea level
    # (leaned again to sigma it made 76 of 180 hp, 0.42).
    _, p0 = _static_power_hp("c310", 0.0)
    ac, p = _static_power_hp("c310", 3000.0)
    assert ac.controls.mixture == 1.0
    assert 0.6 < p / p0 < 0.85, (p, p0)


def test_low_field_ground_start_stays_full_rich():
    ac, _ = _static_power_hp("c172p", 300.0)
    assert ac.controls.mixture == 1.0


# -- finding 3: `sortie fdm fly`'s trim advice named an API argument ---------------------------

def test_fly_trim_failure_advice_names_the_command_line(capsys):
    # Old: "... or start with trim=False", which fdm fly has no option for.
    from sortie.cli import main

    code = main(["fdm", "fly", "c172x", "--lat", "-10", "--lon", "-50", "--speed-mps", "150", "--seconds", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "trim failed" in err
    assert "trim=False" not in err and "--speed-mps" in err and "--ground" in err, err
    with pytest.raises(TrimFailed, match="trim=False"):  # the API's own advice is unchanged
        Aircraft("c172x", FlatTerrain(0.0), InitialConditions(-10.0, -50.0, 1000.0, speed_mps=150.0))
