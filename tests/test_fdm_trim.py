"""Airborne trim: level flight for powered models (exactly JSBSim's own full trim), a steady
glide for models without engines (Aircraft._trim_glide), and a refusal that says what to try.

Real JSBSim on flat terrain, 1500 m MSL; short simulated times.
"""

import math

import numpy as np
import pytest

from fdm import aircraft as aircraft_mod
from fdm import catalog
from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions, TrimFailed, _jsbsim, trim_speeds
from fdm.state import FT_M

ALT_M = 1500.0


def _start(name, speed_mps, **ic):
    return Aircraft(name, FlatTerrain(0.0), InitialConditions(47.0, 9.0, ALT_M, speed_mps=speed_mps, **ic))


def _jsbsim_trim(name, speed_mps):
    """JSBSim's own full trim of the start Sortie makes (same IC, engines running, mixture
    full rich, throttle closed, gear up), without Sortie."""
    fdm = _jsbsim().FGFDMExec(catalog.root_dir().as_posix())
    fdm.set_debug_level(0)
    fdm.load_model(name)
    fdm.disable_output()
    fdm.set_dt(aircraft_mod.DEFAULT_DT_S)
    for prop, v in {"ic/lat-geod-deg": 47.0, "ic/long-gc-deg": 9.0, "ic/terrain-elevation-ft": 0.0,
                    "ic/h-agl-ft": ALT_M / FT_M, "ic/psi-true-deg": 0.0, "ic/vt-fps": speed_mps / FT_M}.items():
        fdm[prop] = v
    fdm.run_ic()
    fdm["propulsion/set-running"] = -1
    for i in range(fdm.get_propulsion().get_num_engines()):
        fdm[f"fcs/throttle-cmd-norm[{i}]"] = 0.0
        fdm[f"fcs/mixture-cmd-norm[{i}]"] = 1.0
    fdm["gear/gear-cmd-norm"] = 0.0
    fdm.do_trim(1)
    return fdm


@pytest.mark.parametrize("name, speed", [("c172x", 50.0), ("f16", 200.0)])
def test_a_powered_model_trims_level_exactly_as_jsbsim_does(name, speed):
    """The glide trim is for models without engines only: a powered model's trim is JSBSim's
    full trim, bit for bit (angle of attack, throttle, pitch trim, aileron), level flight
    (flight-path angle 0, no vertical speed)."""
    ac = _start(name, speed)
    ref = _jsbsim_trim(name, speed)
    for prop in ("aero/alpha-deg", "fcs/throttle-cmd-norm", "fcs/pitch-trim-cmd-norm", "fcs/aileron-cmd-norm"):
        assert ac.fdm[prop] == ref[prop], prop
    assert ac.trim_gamma_deg == 0.0
    assert abs(ac.fdm["flight-path/gamma-deg"]) < 1e-3  # JSBSim's tolerances, not exactly 0
    assert abs(ac.state().vel_ned_mps[2]) < 1e-3


def test_a_glider_starts_in_its_steady_glide():
    """sgs233 (no engines) at 35 m/s: JSBSim's trim alone fails (it zeroes udot with the
    throttle); Sortie trims the glide. The flight-path angle is the equilibrium glide's,
    tan(-gamma) = D/L (Anderson, Introduction to Flight, gliding flight), the vertical
    speed is v sin(-gamma) downwards, and 10 s untouched the speed and the path hold."""
    ac = _start("sgs233", 35.0)
    gamma = ac.trim_gamma_deg
    assert -15.0 < gamma < -1.0
    lod = ac.fdm["forces/lod-norm"]
    assert math.tan(math.radians(-gamma)) == pytest.approx(1.0 / lod, rel=1e-3)
    s0 = ac.state()
    assert s0.airspeed_true_mps == pytest.approx(35.0, abs=1e-6)
    assert s0.vel_ned_mps[2] == pytest.approx(35.0 * math.sin(math.radians(-gamma)), rel=1e-3)  # down
    assert ac.controls.pitch == 0.0  # the pitch trim holds it, stick centred
    ac.run(10.0)
    s1 = ac.state()
    assert np.isfinite(ac.raw_values()).all() and not ac.crashed
    assert abs(s1.airspeed_true_mps - 35.0) < 1.0
    assert abs(ac.fdm["flight-path/gamma-deg"] - gamma) < 0.5
    assert s1.alt_msl_m < s0.alt_msl_m - 10.0 * 35.0 * math.sin(math.radians(-gamma)) * 0.9


def test_glide_trims_are_deterministic():
    """The same glider start twice: the same glide angle and a bit-identical trajectory."""
    def fly():
        ac = _start("sgs126", 25.0)
        rows = []
        for _ in range(60):
            ac.advance(4)
            rows.append(ac.raw_values())
        return ac.trim_gamma_deg, np.array(rows)

    (g1, a), (g2, b) = fly(), fly()
    assert g1 == g2 and g1 < 0.0
    assert np.array_equal(a, b)


def test_a_model_that_cannot_trim_is_refused_with_what_to_try():
    """A ball has no lift: no glide holds any speed. The refusal is TrimFailed (quickly:
    the glide search is a few dozen evaluations), naming the model, the conditions, why, and
    what to try. A powered model too slow to fly names the speeds the survey found."""
    with pytest.raises(TrimFailed) as exc:
        _start("ball", 60.0)
    msg = str(exc.value)
    assert "ball" in msg and "60.0 m/s" in msg and "1500 m" in msg and "glide" in msg
    assert "no lift" in msg and "trim=False" in msg

    with pytest.raises(TrimFailed, match="trim failed") as exc:
        _start("c172x", 15.0)
    msg = str(exc.value)
    assert "level flight" in msg and "c172x trims at" in msg and "trim_speeds" in msg


def test_trim_speeds_scans_on_request_and_caches():
    """trim_speeds (opt-in, not part of a failing start) lists the speeds that trim; a second
    call with the same model and altitude (to 100 m) is answered from the cache."""
    got = trim_speeds("sgs233", 1510.0, speeds=(20, 30, 40))
    assert got == (30, 40)
    assert trim_speeds("SGS233", 1490.0, speeds=(20, 30, 40)) is got


def test_sortie_fdm_trims_surveys_models_in_child_processes():
    """`sortie fdm trims` runs each model in its own process and reports the speeds that trim:
    the c172x at 50 m/s, not at 10; the ball at neither. Bad arguments are refused by name."""
    import json
    import subprocess
    import sys

    run = lambda *a: subprocess.run([sys.executable, "-m", "sortie.cli", "fdm", "trims", *a],  # noqa: E731
                                    capture_output=True, text=True, timeout=300)
    r = run("c172x", "ball", "--speeds", "10", "50", "--json", "--timeout-s", "120")
    assert r.returncode == 0, r.stderr[-2000:]
    got = {m["name"]: m for m in json.loads(r.stdout.strip().splitlines()[-1])["results"]}
    assert got["c172x"]["trims"] == [50.0] and got["ball"]["trims"] == []
    assert "error" in got["c172x"]["rows"][0] and not got["c172x"]["timed_out"]
    bad = run("c172x", "--speeds", "0")
    assert bad.returncode != 0 and "speeds" in bad.stderr


@pytest.mark.parametrize("name, speed", [("c172x", 40.0), ("A4", 120.0)])
def test_an_engine_out_start_is_trimmed_in_its_glide(name, speed):
    """Started airborne with its engines off (an engine-out exercise), a powered model cannot
    hold level flight: it starts in its steady glide (a piston and a jet), no thrust, and holds
    the speed; a model whose glide the pitch trim cannot hold (the f16's fly-by-wire) is
    refused saying its engines are off."""
    ac = _start(name, speed, engines_running=False)
    assert -15.0 < ac.trim_gamma_deg < -1.0
    s0 = ac.state()
    ac.run(10.0)
    assert abs(ac.state().airspeed_true_mps - s0.airspeed_true_mps) < 1.5 and not ac.crashed
    # (JSBSim's trim evaluation leaves a jet's spooled-down turbine about 120 lbf at first.)
    assert ac.fdm["propulsion/engine/thrust-lbs"] == pytest.approx(0.0, abs=1.0)
    assert ac.state().alt_msl_m < s0.alt_msl_m - 20.0
    with pytest.raises(TrimFailed, match="engines are off"):
        _start("f16", 150.0, engines_running=False)
