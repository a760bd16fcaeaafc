"""Fixes from the terrain acceptance probe: profiles near the +-540 degree longitude limit, segments
with an end at the Earth's centre or on the polar axis, west-edge posts queried a turn away, a
directory given as a DEM, and validation errors that name the first bad point."""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from server.terrain_service import create_server
from sortie.errors import DataFormatError, InvalidArgument
from terrain.dem import read_dem
from terrain.geodesy import WGS84_A_M, WGS84_B_M, web_mercator_inverse, wrap_lon_deg, wrap_lon_exact_deg
from terrain.los import trace_segments
from terrain.mosaic import load_sources
from terrain.procedural import ProceduralTerrain
from terrain.raster import CRS_GEOGRAPHIC, CRS_WEB_MERCATOR, STATUS_OK, STATUS_OUTSIDE, Georef, Raster
from terrain.terrain import Terrain
from terrain.validate import check_heights, check_latlon

# --- 1. profiles near the +-540 degree limit ----------------------------------------------------

# Each request's ends pass the profile's check (|lon| <= 540), but the unrolled samples of the
# first two run past 540 (530 -> 550) and of the third below -540 (-530 -> -550).
NEAR_LIMIT = [((0.0, 530.0, 0.0, 190.0), (0.0, 170.0, 0.0, -170.0)),
              ((0.0, 530.0, 0.0, -170.0), (0.0, 170.0, 0.0, -170.0)),
              ((0.0, -530.0, 0.0, 170.0), (0.0, -170.0, 0.0, 170.0))]


@pytest.fixture(scope="module")
def world(hgt_alps) -> Terrain:
    """A real DEM over the procedural world, which covers the antimeridian."""
    return Terrain([read_dem(hgt_alps), ProceduralTerrain(seed=5)])


@pytest.mark.parametrize("request_, same_line", NEAR_LIMIT)
def test_profile_near_the_540_limit_is_answered_with_unrolled_longitudes(world, request_, same_line):
    got = world.profile(*request_, 5)
    ref = world.profile(*same_line, 5)
    # Longitudes stay continuous along the line (the documented contract), from lon1 exactly.
    assert got.lon_deg[0] == request_[1]
    step = np.diff(got.lon_deg)
    assert np.allclose(step, step[0], atol=1e-9) and abs(step[0]) == pytest.approx(5.0, abs=1e-9)
    assert np.allclose(wrap_lon_deg(got.lon_deg), wrap_lon_deg(ref.lon_deg), rtol=0.0, atol=1e-9)
    # Heights are those at the samples, whichever turn they are written in.
    want = world.heights(got.lat_deg, wrap_lon_exact_deg(got.lon_deg))
    assert np.array_equal(got.height_msl_m, want.height_msl_m) and (got.status == STATUS_OK).all()
    assert np.allclose(got.height_msl_m, ref.height_msl_m, rtol=0.0, atol=1e-6)


@pytest.fixture(scope="module")
def world_client(world):
    server, port = create_server(world, "127.0.0.1:0", max_workers=2)
    server.start()
    with TerrainClient(f"127.0.0.1:{port}", timeout_s=20.0) as client:
        yield client
    server.stop(0).wait()


def _assert_same(got, want, names):
    for name in names:
        assert np.array_equal(getattr(got, name), getattr(want, name), equal_nan=True), name


def test_profile_near_the_540_limit_is_answered_over_grpc(world, world_client):
    for request_, _ in NEAR_LIMIT:
        _assert_same(world_client.profile(*request_, 9), world.profile(*request_, 9),
                     ("lat_deg", "lon_deg", "distance_m", "height_msl_m", "status"))


# --- 2. segment ends at the Earth's centre and on the polar axis ---------------------------------

CENTRE_EQ = (0.0, 0.0, -WGS84_A_M)  # (lat, lon, h): ECEF (0, 0, 0) exactly
CENTRE_POLE = (90.0, 0.0, -6356752.3142)  # about a micrometre from the centre, on the axis


def _global(level_m: float = 100.0) -> Raster:
    """A 1 degree global raster (poles and the antimeridian included) at level_m everywhere."""
    return Raster(np.full((181, 361), level_m, np.float32), Georef(CRS_GEOGRAPHIC, -180.0, -90.0, 1.0, 1.0),
                  name="global")


def _rays(*pairs):
    return [np.array(v, np.float64) for v in zip(*(a + b for a, b in pairs))]


def test_segment_from_the_earths_centre_is_answered_per_segment(hgt_alps):
    """The centre (lat 0, lon 0, h -a) passes validation; its segment is answered like any other
    (lat 0, lon 0 is outside the tile: OUTSIDE at once, as a start outside is documented), and
    the other segment of the batch keeps its own answer."""
    t = Terrain(load_sources([hgt_alps]))
    good = ((47.5, 9.2, 3000.0), (47.5, 9.8, 3000.0))
    rays = _rays((CENTRE_EQ, (47.5, 9.5, 5000.0)), good, (CENTRE_EQ, CENTRE_EQ))
    got = t.intersect(*rays)
    alone = t.intersect(*_rays(good))
    for name in ("hit", "distance_m", "lat_deg", "lon_deg", "height_msl_m", "status"):
        assert np.array_equal(getattr(got, name)[1], getattr(alone, name)[0], equal_nan=name != "hit"), name
    assert list(got.status[[0, 2]]) == [STATUS_OUTSIDE, STATUS_OUTSIDE] and not got.hit[[0, 2]].any()
    los = t.line_of_sight(*rays)
    assert not (got.hit & los.visible).any()


def test_segment_from_the_earths_centre_is_answered_over_grpc(world, world_client):
    """IntersectSegments answered INTERNAL (ZeroDivisionError) for the whole batch; over the
    procedural world a start within about 43 km of the centre then failed its box (latitudes
    past 90, then a box of every latitude and longitude). A start below every surface is the
    first contact (distance 0), and LineOfSight is blocked."""
    rays = _rays((CENTRE_EQ, (47.5, 9.5, 5000.0)), ((47.5, 9.2, 3000.0), (47.5, 9.8, 3000.0)),
                 (CENTRE_POLE, (0.0, 0.0, 9000.0)), ((0.001, 0.0, -WGS84_A_M), (47.5, 9.5, 5000.0)))
    got = world_client.intersect(*rays)
    _assert_same(got, world.intersect(*rays), ("hit", "distance_m", "lat_deg", "lon_deg", "height_msl_m",
                                               "status"))
    assert got.hit[[0, 2, 3]].all() and list(got.distance_m[[0, 2, 3]]) == [0.0, 0.0, 0.0]
    assert (np.abs(got.lat_deg[got.hit]) <= 90.0).all()
    los = world_client.line_of_sight(*rays)
    assert not los.visible[[0, 2, 3]].any() and (los.status == STATUS_OK).all()


def test_segment_from_the_earths_centre_hits_from_below_where_covered():
    """On a global raster the centre is below the ground: the hit is at distance 0 (a start below
    the ground), at the centre itself as (lat 0, lon 0, h -a), and LineOfSight is blocked."""
    t = Terrain([_global()])
    rays = _rays((CENTRE_EQ, (45.0, 0.0, 9000.0)), (CENTRE_EQ, (0.0, 0.0, 9000.0)),
                 ((47.5, 9.5, 5000.0), CENTRE_EQ))
    got = t.intersect(*rays)
    assert got.hit.all() and (got.status == STATUS_OK).all()
    assert list(got.distance_m[:2]) == [0.0, 0.0]
    assert list(got.lat_deg[:2]) == [0.0, 0.0] and list(got.lon_deg[:2]) == [0.0, 0.0]
    assert list(got.height_msl_m[:2]) == [-WGS84_A_M, -WGS84_A_M]
    # From above down to the centre: the ground, 100 m up, about 4900 m along the segment (which
    # leans from the local vertical by the angle between geodetic and geocentric latitude).
    assert got.distance_m[2] == pytest.approx(4900.0, abs=0.1)
    assert got.height_msl_m[2] == pytest.approx(100.0, abs=1e-6)
    los = t.line_of_sight(*rays)
    assert not los.visible.any() and (los.status == STATUS_OK).all()


def test_segments_on_the_polar_axis_do_not_divide_by_zero():
    g = _global()
    t = Terrain([g])
    rays = _rays((CENTRE_POLE, (90.0, 0.0, 9000.0)), ((90.0, 0.0, 1100.0), (-90.0, 0.0, 1100.0)),
                 ((-90.0, 0.0, 300.0), (47.5, 9.5, 5000.0)), (CENTRE_POLE, (47.5, 9.5, 5000.0)),
                 (CENTRE_POLE, CENTRE_EQ))
    got = t.intersect(*rays)
    assert got.hit.all() and (got.status == STATUS_OK).all()
    assert list(got.distance_m[[0, 3, 4]]) == [0.0, 0.0, 0.0]
    assert got.distance_m[1] == pytest.approx(1000.0, abs=1e-3)
    los = t.line_of_sight(*rays)
    assert not los.visible[:4].any()  # the last, 45 micrometres long, has no interior to block
    # Exactly on the axis in ECEF (x = y = 0, which no (lat, lon) gives in floating point): the
    # centre itself, and points above and below the pole.
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, WGS84_B_M + 300.0], [0.0, 0.0, -WGS84_B_M - 300.0]])
    b = np.array([[0.0, 0.0, WGS84_B_M + 9000.0], [0.0, 0.0, WGS84_B_M + 50.0], [0.0, 0.0, 0.0]])
    s, _, _, status = trace_segments(g, a, b, np.zeros(3), np.ones(3))
    assert (status == STATUS_OK).all()
    assert s[0] == 0.0
    assert s[1] * 250.0 == pytest.approx(200.0, abs=1e-3)
    assert s[2] * (WGS84_B_M + 300.0) == pytest.approx(200.0, abs=1e-3)


# --- 3. west-edge posts a turn away ---------------------------------------------------------------

def _shifts(lon0: float):
    """lon0 and lon0 moved by whole turns within the accepted +-540 degrees."""
    return [lon0 + 360.0 * k for k in (-2, -1, 1, 2) if abs(lon0 + 360.0 * k) <= 540.0]


def test_web_mercator_west_edge_posts_answer_a_turn_away(tif_grand_canyon):
    r = read_dem(tif_grand_canyon)
    g = r.georef
    assert g.crs == CRS_WEB_MERCATOR
    rows = np.arange(r.shape[0])
    lat, lon = web_mercator_inverse(np.full(rows.size, g.x0), g.y0 + rows * g.dy)
    t = Terrain([r])
    at_edge = t.heights(lat, lon)
    assert np.array_equal(at_edge.height_msl_m, r.heights[:, 0].astype(np.float64))
    shifts = _shifts(float(lon[0]))
    assert any(s > lon[0] for s in shifts) and any(s < lon[0] for s in shifts)
    for shift in (s - lon[0] for s in shifts):
        got = t.heights(lat, lon + shift)
        assert np.array_equal(got.height_msl_m, at_edge.height_msl_m), shift
        assert np.array_equal(got.status, at_edge.status), shift


@pytest.mark.parametrize("x0", [167.04527082787132, -180.0, -192.95472917212868, 12.345678901234567])
def test_geographic_west_edge_posts_answer_a_turn_away(x0):
    h = np.arange(100, dtype=np.float32).reshape(10, 10)
    r = Raster(h, Georef(CRS_GEOGRAPHIC, x0, 9.91, 0.01, 0.01), name="edge")
    t = Terrain([r])
    lat = 9.91 + 0.01 * np.arange(10)
    at_edge = t.heights(lat, np.full(10, x0))
    assert np.array_equal(at_edge.height_msl_m, h[:, 0].astype(np.float64))
    for lon in _shifts(x0):
        got = t.heights(lat, np.full(10, lon))
        assert np.array_equal(got.height_msl_m, at_edge.height_msl_m), lon
        assert (got.status == STATUS_OK).all(), lon


# --- 4. a directory given as a DEM --------------------------------------------------------------

def test_a_directory_given_as_a_dem_is_named_as_one(tmp_path):
    d = tmp_path / "N47E009.hgt"
    d.mkdir()
    with pytest.raises(DataFormatError, match=r"N47E009\.hgt.* is a directory, not a DEM file"):
        read_dem(d)


def test_a_directory_given_as_a_dem_on_the_command_line_exits_2(tmp_path, capsys):
    from sortie import cli

    d = tmp_path / "dir.hgt"
    d.mkdir()
    assert cli.main(["terrain", "info", "--dem", str(d)]) == 2  # as for a missing or unreadable file
    err = capsys.readouterr().err
    assert "is a directory, not a DEM file" in err and "does not exist" not in err
    assert "Traceback" not in err


# --- 5. the first offending index ---------------------------------------------------------------

@pytest.mark.parametrize("lat, lon, message", [
    ([47.5, 91.0, 47.0], [9.5, 0.0, math.nan], r"^lat\[1\]: must be within \[-90, 90\] degrees"),
    ([47.5, 0.0, math.nan], [9.5, 541.0, 0.0], r"^lon\[1\]: must be within \[-540, 540\] degrees"),
    ([47.5, math.inf, 95.0], [9.5, 0.0, 0.0], r"^lat\[1\]: must be finite"),
    ([47.5, 10.0, -95.0], [9.5, math.nan, 0.0], r"^lon\[1\]: must be finite"),
    # Both bad at one point: the checks' own order there (finiteness first), as before.
    ([47.5, 95.0, 0.0], [9.5, math.nan, 0.0], r"^lon\[1\]: must be finite"),
])
def test_check_latlon_names_the_first_bad_point(lat, lon, message):
    with pytest.raises(InvalidArgument, match=message):
        check_latlon(lat, lon)


def test_check_heights_names_the_first_bad_height():
    with pytest.raises(InvalidArgument, match=r"^h\[1\]: must be within \+-1e8 m"):
        check_heights("h", [0.0, 2.0e8, math.nan], 3)
