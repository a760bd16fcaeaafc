"""The scenario acceptance probe's ground-vehicle finding, round 33 (/tmp/probes33/scenario/p_slope.py):
an M1A2 (side-slope limit 0.40) standing across a 30 degree plane stored as float32 drove along the
contour in fits and starts, 5 m in 8 s at a commanded 5 m/s, with a "blocked side_slope" every ~2 s;
the same plane in float64 it drove at 5 m/s. The "no worse" rule compared each pose's side gradient
with the last one's to 1e-9, and float32 heights (or SRTM's whole metres) make a plane's side gradient
vary by 1e-5 (or 1e-2) from pose to pose.

Real parts: GeoTIFF (float32, float64) and SRTM .hgt (int16) files written here and read by the
terrain readers, stepped by fdm.ground.GroundVehicles.

Bounds: along the contour, no step is blocked and the distance driven is the float64 plane's within
1 %, and both the free run's (from rest at the type's acceleration); wherever a vehicle stands beyond
its side-slope limit, its side gradient never exceeds the gentlest it has stood on by more than the
stated tolerance (fdm.ground.side_slope_tolerances and the float32 term: 2 q / W, q float32's
spacing at twice the height, at least at 1024 m); a climb beyond the gradient limit, and a turn onto
a steeper side slope, are still stopped.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdm.ground import BLOCKED_SIDE_SLOPE, BLOCKED_SLOPE, FREE, GroundVehicles
from fdm.vehicle_types import P_GRAD, P_SIDE, P_WID

WORLD_DT_S = 1.0 / 30.0
SPEED_MPS = 5.0
POST_DEG = 0.0001  # about 11 m
M_PER_DEG = 111_319.49  # WGS84 equatorial degree, as the probe's DEM used for the east metres
DISTANCE_REL = 0.01


def _geotiff(path, heights: np.ndarray, west: float, north: float, dtype) -> str:
    """A GeoTIFF in EPSG:4326 (PixelIsArea), POST_DEG posts, row 0 north."""
    import tifffile

    keys = [(1024, 0, 1, 2), (1025, 0, 1, 1), (2048, 0, 1, 4326)]
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tags = [(34735, "H", len(directory), directory, False), (33550, "d", 3, [POST_DEG, POST_DEG, 0.0], False),
            (33922, "d", 6, [0, 0, 0, west, north, 0], False)]
    tifffile.imwrite(path, heights.astype(dtype), extratags=tags)
    return str(path)


def _terrain(paths):
    from server.terrain_cli import build_terrain

    return build_terrain([str(p) for p in paths])


def _plane(tmp_path, slope: float, dtype, name: str, azimuth_deg: float = 90.0):
    """A plane rising ``slope`` m a metre towards ``azimuth_deg``, 1000 m at (10.01 N, 20.01 E),
    over 10.00-10.02 N, 20.00-20.02 E."""
    n = 200
    north_m = (n - 1 - np.arange(n))[:, None] * POST_DEG * 110_600.0 - 0.01 * 110_600.0
    east_m = np.arange(n)[None, :] * POST_DEG * M_PER_DEG * math.cos(math.radians(10.0)) - 0.01 * 109_630.0
    a = math.radians(azimuth_deg)
    heights = 1000.0 + slope * (east_m * math.sin(a) + north_m * math.cos(a))
    return _terrain([_geotiff(tmp_path / f"{name}.tif", heights, 20.0, 10.02, dtype)])


def _tolerance(v: GroundVehicles, height_m: float) -> float:
    """The side-slope rule's tolerance for vehicle 0 standing at ``height_m`` on a GeoTIFF of this
    file (fdm/ground.py: 2 q / W, q float32's spacing at twice the height, at least at 1024 m; these
    files declare no coarser step)."""
    f32 = float(np.spacing(np.float32(max(2.0 * height_m, 1024.0))))
    return 2.0 * f32 / v.table[v.type_id[0], P_WID]


def _drive(v: GroundVehicles, steps: int, yaw_dps: float = 0.0) -> dict:
    """Step ``v`` (one vehicle) at SPEED_MPS; what each step left: blocked codes, side gradients
    (magnitudes) and pitch gradients."""
    v.set_controls(np.array([SPEED_MPS]), np.array([yaw_dps]))
    out = {"blocked": [], "side": [], "pitch": []}
    for _ in range(steps):
        v.step(WORLD_DT_S)
        out["blocked"].append(int(v.blocked[0]))
        out["side"].append(abs(float(v.roll_grad[0])))
        out["pitch"].append(float(v.pitch_grad[0]))
    return out


def _metres_north(v: GroundVehicles, lat0: float) -> float:
    return (float(v.lat[0]) - lat0) * 110_600.0  # the meridian degree at 10 N


def _metres_from(v: GroundVehicles, lat0: float, lon0: float) -> float:
    """Ground metres from (lat0, lon0) to vehicle 0 (the degrees' lengths near 10 N: ample here)."""
    return math.hypot((float(v.lat[0]) - lat0) * 110_600.0,
                      (float(v.lon[0]) - lon0) * M_PER_DEG * math.cos(math.radians(lat0)))


def _free_run_m(v: GroundVehicles, seconds: float) -> float:
    """Metres an unhindered vehicle 0 covers from rest to SPEED_MPS at its acceleration."""
    a = v.types[v.type_id[0]].accel_mps2
    return SPEED_MPS * seconds - SPEED_MPS ** 2 / (2.0 * a)


@pytest.fixture(scope="module")
def planes(tmp_path_factory):
    """The probe's 30 degree plane rising east, and one rising towards 70 degrees (its posts'
    rounding then differs along every contour), in float32 and float64."""
    d = tmp_path_factory.mktemp("planes")
    slope = math.tan(math.radians(30.0))
    return {(az, kind): _plane(d, slope, dtype, f"p30-{az:g}-{kind}", az)
            for az in (90.0, 70.0) for kind, dtype in (("f32", np.float32), ("f64", np.float64))}


@pytest.mark.parametrize("azimuth", [90.0, 70.0])
def test_a_vehicle_beyond_its_side_slope_limit_drives_the_contour_of_a_float32_plane(planes, azimuth):
    """The probe's case: an M1A2 along the contour of a 0.577 plane (side-slope limit 0.40). Old:
    on float32 posts it crept about 5 m in 8 s with a side-slope stop every ~2 s. Now no step is
    blocked, and it covers the float64 plane's distance within 1 %, the free run's."""
    lat0, lon0 = 10.01, 20.01
    moved = {}
    for kind in ("f32", "f64"):
        v = GroundVehicles(planes[azimuth, kind], [lat0], [lon0], [azimuth - 90.0], "m1a2")
        assert abs(v.roll_grad[0]) > v.table[v.type_id[0], P_SIDE]  # beyond its limit from the start
        run = _drive(v, 240)  # 8 s
        assert run["blocked"] == [FREE] * 240, (kind, [i for i, b in enumerate(run["blocked"]) if b])
        moved[kind] = _metres_from(v, lat0, lon0)
    assert moved["f64"] == pytest.approx(_free_run_m(v, 8.0), rel=DISTANCE_REL)
    assert moved["f32"] == pytest.approx(moved["f64"], rel=DISTANCE_REL)


def test_a_vehicle_beyond_its_side_slope_limit_drives_the_contour_of_an_srtm_plane(tmp_path):
    """SRTM holds whole metres (int16): across a 0.45 plane rising towards 70 degrees, rounded to
    metres at 3" posts, an M1A2's side gradient varies by up to 2 q hypot(1/dx, 1/dy) = 0.03 from
    pose to pose. Old: stopped on such a step again and again. Now it drives the contour at its
    commanded speed."""
    n = 1201  # N10E020, 3" posts, row 0 at 11 N
    lat = (11.0 - np.arange(n) / (n - 1))[:, None]
    lon = (20.0 + np.arange(n) / (n - 1))[None, :]
    a = math.radians(70.0)
    rise = 0.45 * ((lon - 20.5) * M_PER_DEG * math.cos(math.radians(10.5)) * math.sin(a)
                   + (lat - 10.5) * 110_600.0 * math.cos(a))
    path = tmp_path / "N10E020.hgt"
    path.write_bytes(np.clip(np.rint(2000.0 + rise), 100, 32000).astype(">i2").tobytes())
    terrain = _terrain([path])
    lat0, lon0 = 10.5, 20.5
    v = GroundVehicles(terrain, [lat0], [lon0], [340.0], "m1a2")
    assert abs(v.roll_grad[0]) > v.table[v.type_id[0], P_SIDE]
    run = _drive(v, 240)
    assert run["blocked"] == [FREE] * 240, [i for i, b in enumerate(run["blocked"]) if b]
    assert _metres_from(v, lat0, lon0) == pytest.approx(_free_run_m(v, 8.0), rel=DISTANCE_REL)
    from fdm.ground import height_steps

    assert height_steps(terrain) == [pytest.approx((1.0, 91.2, 92.6), rel=0.01)]  # whole metres, 3" posts


def test_the_tolerance_does_not_compound_onto_a_steepening_side_slope(tmp_path):
    """A float32 surface whose side slope steepens along the contour by 2e-4 a metre (3.3e-5 a
    step at 5 m/s and 30 Hz, under the tolerance of 1.6e-4 at 1500 m): a margin taken from each
    last pose would let the vehicle drive on up it for ever; measured from the gentlest pose, it
    stops within a few metres, its side gradient never more than the tolerance above the
    gentlest it has stood on."""
    n = 400
    y = (n - 1 - np.arange(n))[:, None] * POST_DEG * 110_600.0  # metres north of the south row
    x = (np.arange(n)[None, :] - n // 2) * POST_DEG * M_PER_DEG * math.cos(math.radians(10.0))
    heights = 1500.0 + (0.45 + 2e-4 * y) * x
    terrain = _terrain([_geotiff(tmp_path / "steepening.tif", heights, 20.0, 10.04, np.float32)])
    lat0, lon0 = 10.02, 20.0 + (n // 2 + 0.5) * POST_DEG
    v = GroundVehicles(terrain, [lat0], [lon0], [0.0], "m1a2")
    g0 = abs(float(v.roll_grad[0]))
    tol = _tolerance(v, 1500.0)
    assert g0 > v.table[v.type_id[0], P_SIDE] and 2e-4 * SPEED_MPS * WORLD_DT_S < tol
    run = _drive(v, 240)
    assert BLOCKED_SIDE_SLOPE in run["blocked"]
    assert _metres_north(v, lat0) < 5.0
    assert max(run["side"]) <= g0 + tol
    gentlest = np.minimum.accumulate([g0] + run["side"][:-1])  # before each step
    assert all(s <= ref + tol for s, ref in zip(run["side"], gentlest))


def test_a_climb_beyond_the_gradient_limit_and_a_turn_onto_a_steeper_side_slope_are_still_stopped(tmp_path):
    """On a float32 0.70 plane (beyond the M1A2's 0.60 gradient and 0.40 side-slope limits):
    turning from the contour up the slope stops at the gradient limit (never accepted beyond it);
    facing up it, it does not move; turning from 30 degrees up the slope back towards the contour
    (steeper across) stops within the tolerance of where it stood."""
    terrain = _plane(tmp_path, 0.70, np.float32, "p70f32")
    lat0, lon0 = 10.01, 20.01
    v = GroundVehicles(terrain, [lat0], [lon0], [0.0], "m1a2")
    gmax = v.table[v.type_id[0], P_GRAD]
    run = _drive(v, 240, yaw_dps=10.0)  # towards east: up the slope
    assert run["blocked"][-1] == BLOCKED_SLOPE and max(run["pitch"]) <= gmax

    v = GroundVehicles(terrain, [lat0], [lon0], [90.0], "m1a2")
    run = _drive(v, 60)
    assert set(run["blocked"]) == {BLOCKED_SLOPE} and _metres_north(v, lat0) == 0.0 and float(v.lon[0]) == lon0

    v = GroundVehicles(terrain, [lat0], [lon0], [30.0], "m1a2")
    g0 = abs(float(v.roll_grad[0]))
    tol = _tolerance(v, float(v.height_msl_m[0]))
    run = _drive(v, 60, yaw_dps=-10.0)  # back towards north: the full 0.70 across
    assert BLOCKED_SIDE_SLOPE in run["blocked"]
    assert max(run["side"]) <= g0 + tol < 0.70 - 0.01
