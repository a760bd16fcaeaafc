"""Geodesic profiles: GeographicLib geometry, raster heights, argument checks."""

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.profile import PROFILE_MAX_SAMPLES, geodesic_profile
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, STATUS_OUTSIDE, Georef, Raster

GEOD = Geodesic.WGS84
D = 1.0 / 1200.0


@pytest.fixture(scope="module")
def alps(hgt_alps):
    h = np.fromfile(hgt_alps, ">i2").reshape(1201, 1201)[::-1].astype(np.float32)
    return Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D), name="N47E009")


def heights_of(raster):
    def query(lat, lon):
        h = np.full(lat.size, np.nan)
        status = np.full(lat.size, STATUS_OUTSIDE, np.uint8)
        raster.heights_into(lat, lon, h, status)
        return h, status
    return query


@pytest.mark.parametrize("p1, p2", [((47.1, 9.1), (47.9, 9.85)), ((47.5, 9.9), (47.5, 9.1)),
                                    ((47.02, 9.5), (47.98, 9.5))])
def test_geometry_matches_geographiclib(alps, p1, p2):
    n = 257
    lat, lon, dist, h, status = geodesic_profile(heights_of(alps), *p1, *p2, n)
    inv = GEOD.Inverse(*p1, *p2)
    assert (lat[0], lon[0], lat[-1], lon[-1]) == (*p1, *p2)
    # 1 nm: GeographicLib's own accuracy is ~15 nm; both use the same inverse solution.
    assert abs(dist[-1] - inv["s12"]) < 1e-9
    assert np.allclose(np.diff(dist), inv["s12"] / (n - 1), rtol=0, atol=1e-9)
    # Each sample lies at its distance from point 1 along the geodesic (1e-6 m).
    for k in (1, 100, 200, n - 2):
        back = GEOD.Inverse(*p1, lat[k], lon[k])
        assert abs(back["s12"] - dist[k]) < 1e-6
        assert abs(back["azi1"] - inv["azi1"]) < 1e-9
    # Heights are the raster's bilinear heights at the returned points, bit for bit.
    want, want_status = heights_of(alps)(lat, lon)
    assert np.array_equal(h, want) and (status == STATUS_OK).all()


def test_antimeridian_longitudes_are_continuous():
    flat = Raster(np.full((121, 121), 5.0, np.float32), Georef(CRS_GEOGRAPHIC, 179.5, -10.5, 1 / 120, 1 / 120))
    lat, lon, dist, h, status = geodesic_profile(heights_of(flat), -10.2, 179.8, -9.8, -179.7, 50)
    assert np.all(np.diff(lon) > 0) and lon[-1] == pytest.approx(180.3, abs=1e-12)
    assert abs(dist[-1] - GEOD.Inverse(-10.2, 179.8, -9.8, -179.7)["s12"]) < 1e-9
    assert (h == 5.0).all() and (status == STATUS_OK).all()


def test_outside_samples_carry_status(alps):
    lat, lon, dist, h, status = geodesic_profile(heights_of(alps), 47.5, 9.5, 47.5, 10.5, 12)
    inside = lon <= 10.0
    assert (status[inside] == STATUS_OK).all() and (status[~inside] == STATUS_OUTSIDE).all()
    assert np.isnan(h[~inside]).all()


def test_coincident_endpoints_give_a_point_profile(alps):
    lat, lon, dist, h, status = geodesic_profile(heights_of(alps), 47.3, 9.3, 47.3, 9.3, 4)
    assert (dist == 0).all() and (lat == 47.3).all() and (lon == 9.3).all()
    assert np.ptp(h) == 0


@pytest.mark.parametrize("n, error", [(1, InvalidArgument), (0, InvalidArgument), (-5, InvalidArgument),
                                      (2.5, InvalidArgument), (True, InvalidArgument), ("10", InvalidArgument),
                                      (PROFILE_MAX_SAMPLES + 1, LimitExceeded)])
def test_n_samples_is_validated(alps, n, error):
    with pytest.raises(error, match="n_samples"):
        geodesic_profile(heights_of(alps), 47.1, 9.1, 47.2, 9.2, n)


def test_limits_are_inclusive(alps):
    assert geodesic_profile(heights_of(alps), 47.1, 9.1, 47.2, 9.2, 2)[0].size == 2
    assert geodesic_profile(heights_of(alps), 47.1, 9.1, 47.2, 9.2, np.int64(300))[0].size == 300


@pytest.mark.parametrize("args, field", [((91.0, 9.0, 47.0, 9.0), "lat1"), ((47.0, np.nan, 47.0, 9.0), "lon1"),
                                         ((47.0, 9.0, -90.5, 9.0), "lat2"), ((47.0, 9.0, 47.0, 600.0), "lon2")])
def test_bad_coordinates_name_the_field(alps, args, field):
    with pytest.raises(InvalidArgument, match=field):
        geodesic_profile(heights_of(alps), *args, 10)
