"""Acceptance-probe fixes (low findings): ``sortie fdm trims`` option bounds; a route's corner
measured over a length, not between adjacent segments however short."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from fdm import trim_survey
from fdm.convoy import LOOKAHEAD_MIN_M, Route
from sortie.errors import InvalidArgument


def _trims_args(*argv):
    parser = argparse.ArgumentParser()
    trim_survey.add_parser(parser.add_subparsers())
    return parser.parse_args(["trims", "c172x", "--speeds", "50", *argv])


@pytest.mark.parametrize("argv, field", [
    (("--timeout-s", "inf"), "timeout_s"), (("--timeout-s", "1e12"), "timeout_s"),
    (("--alt-m", "inf"), "alt_m"), (("--alt-m", "2e5"), "alt_m"), (("--alt-m", "nan"), "alt_m"),
    (("--timeout-s", "-1"), "timeout_s")])
def test_trims_refuses_infinite_and_huge_options_by_name(argv, field):
    """--timeout-s inf / 1e12 ended in OverflowError from subprocess's wait and --alt-m inf was
    surveyed ("0/1 models trim at some speed at inf m MSL"): each is refused before any child
    runs, naming the option, the value and the finite bound."""
    args = _trims_args(*argv)
    with pytest.raises(InvalidArgument) as e:
        args.func(args)
    assert e.value.field == field and "within [0, " in str(e.value) and f"(got {float(argv[1])})" in str(e.value)


def _route(points):
    return Route([p[0] for p in points], [p[1] for p in points])


def _old_turns(r: Route):
    """The corner turns as they were taken before: between adjacent segments' headings."""
    psi = np.arctan2(r.seg_de, r.seg_dn)
    return np.abs((np.diff(psi) + np.pi) % (2 * np.pi) - np.pi)


def test_a_centimetre_jog_is_no_corner():
    """A 1 cm jog between two 450 m legs braked a vehicle from 25 m/s to about 4 as at a right
    angle; now the route's ceiling at the jog is far above any cruise speed, and that of the
    same route without the jog is the same kind (no corner at all)."""
    r = _route([[-33.015, -70.015], [-33.015, -70.010], [-33.0149999, -70.010], [-33.015, -70.000]])
    ceiling = r.corner_speed_ceiling(np.array([0.0, 300.0, 466.0]), 37.5, 4.0, 3.0)
    assert (ceiling > 100.0).all(), ceiling
    assert (r.corner_turn < 2e-3).all(), r.corner_turn


def test_corners_between_long_legs_are_unchanged_bit_for_bit():
    """Where every leg is at least LOOKAHEAD_MIN_M long, each corner's turn is the heading
    change between its legs exactly as before (right angles, a hairpin, shallow bends)."""
    rng = np.random.default_rng(7)
    lat = -33.0 + np.cumsum(rng.uniform(-1e-3, 1e-3, 40))
    lon = -70.0 + np.cumsum(rng.uniform(-1e-3, 1e-3, 40))
    pts = [[-33.0, -70.0], [-33.0, -69.99], [-32.99, -69.99], [-33.0, -69.99], [-33.0, -69.98]] + \
        [[a, b] for a, b in zip(lat, lon)]
    r = _route(pts)
    assert r.seg_len.min() >= LOOKAHEAD_MIN_M
    old = _old_turns(r)
    corner = np.flatnonzero(old >= 1e-6)
    assert np.array_equal(r.corner_turn, old[corner]) and np.array_equal(r.corner_at, r.cum[corner + 1])
    assert math.pi in r.corner_turn  # the hairpin


def test_a_short_legged_hairpin_and_a_finely_digitised_curve_keep_their_turn():
    """A U-turn through a 5 m leg (two 90 degree vertices) is taken as the near U-turn it is
    (more than 90 degrees at each); a circle of radius 40 m digitised every 2 m (2.9 degrees a
    vertex, which allowed 3.5 times the speed) turns by about LOOKAHEAD_MIN_M / R at each vertex,
    so its ceiling is about sqrt(a_lat R)."""
    d = 5.0 / 111_000.0
    r = _route([[0.0, 0.0], [0.0, 0.01], [d, 0.01], [d, 0.0]])
    assert (r.corner_turn > math.radians(120.0)).all() and r.corner_turn.size == 2
    radius, step = 40.0, 2.0
    a = np.arange(0.0, 0.5 * math.pi, step / radius)
    m_per_deg = 111_320.0
    r = _route(np.stack([radius * np.sin(a) / m_per_deg, radius * (1 - np.cos(a)) / m_per_deg], 1))
    inner = r.corner_turn[8:-8]
    assert inner == pytest.approx(LOOKAHEAD_MIN_M / radius, rel=0.03)
    v = r.corner_speed_ceiling(r.cum[20], 12.0, 4.0, 3.0)
    assert v == pytest.approx(math.sqrt(4.0 * radius), rel=0.03)


@pytest.fixture(scope="module")
def slope35(tmp_path_factory):
    """A plane rising 0.35 m a metre to the north (the acceptance probe's slope35.asc)."""
    from server.terrain_cli import build_terrain

    xll, yll, cs, n = -70.02, -33.02, 0.0002, 200
    lat = yll + (n - 0.5 - np.arange(n)) * cs
    h = np.repeat((100.0 + 0.35 * (lat - yll) * math.pi / 180.0 * 6_356_000.0)[:, None], n, axis=1)
    path = tmp_path_factory.mktemp("dem") / "slope35.asc"
    with open(path, "w") as f:
        f.write(f"ncols {n}\nnrows {n}\nxllcorner {xll}\nyllcorner {yll}\ncellsize {cs}\nNODATA_value -9999\n")
        f.writelines(" ".join(f"{v:.3f}" for v in row) + "\n" for row in h)
    return build_terrain([str(path)])


@pytest.mark.parametrize("heading", [90.0, 270.0, 85.0])
def test_a_vehicle_beyond_its_side_slope_limit_drives_along_the_contour(slope35, heading):
    """An M1083 (side-slope limit under 0.35) standing across a 0.35 plane drove along the
    contour at 0.05 m/s (stopped every other step: the side gradient's last bits, 3e-14, read as
    a worse slope); now it reaches its commanded speed and keeps its roll. Turning to face
    further across a steeper slope is still refused (the no-worse rule itself stands)."""
    from fdm.ground import BLOCKED_SIDE_SLOPE, FREE, GroundVehicles
    from fdm.vehicle_types import P_SIDE

    v = GroundVehicles(slope35, [-33.01], [-70.01], [heading], "m1083")
    assert abs(v.roll_grad[0]) > v.table[v.type_id[0], P_SIDE]
    g0 = abs(v.roll_grad[0])
    v.set_controls(np.array([10.0]), np.zeros(1))
    for _ in range(300):
        v.step(0.05)
    assert v.blocked[0] == FREE and v.speed_mps[0] == pytest.approx(10.0)
    assert abs(v.roll_grad[0]) == pytest.approx(g0, abs=1e-6)
    v = GroundVehicles(slope35, [-33.01], [-70.01], [heading - 20.0 if heading < 180 else heading + 20.0], "m1083")
    v.set_controls(np.array([5.0]), np.array([20.0 if heading < 180 else -20.0]))  # towards 90 / 270: steeper
    for _ in range(40):
        v.step(0.05)
    assert v.blocked[0] == BLOCKED_SIDE_SLOPE
