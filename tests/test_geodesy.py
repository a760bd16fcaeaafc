"""Geodesy oracles: closed forms, round trips, and GeographicLib's geodesics."""

import numpy as np
from geographiclib.geodesic import Geodesic
from hypothesis import given, settings
from hypothesis import strategies as st

from terrain import geodesy as g


def test_ecef_closed_forms():
    # Equator/prime meridian: x = a + h; pole: z = b + h (WGS84 definition).
    p = g.geodetic_to_ecef([0.0, 90.0, -90.0], [0.0, 0.0, 0.0], [100.0, 50.0, 0.0])
    np.testing.assert_allclose(p[0], [g.WGS84_A_M + 100.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(p[1], [0.0, 0.0, g.WGS84_B_M + 50.0], atol=1e-6)
    np.testing.assert_allclose(p[2], [0.0, 0.0, -g.WGS84_B_M], atol=1e-6)


@settings(max_examples=300, deadline=None)
@given(lat=st.floats(-90, 90), lon=st.floats(-180, 180), h=st.floats(-1.1e4, 1.0e7))
def test_ecef_round_trip(lat, lon, h):
    # Bound: 1e-9 deg is ~0.1 mm on the ground; 1e-6 m in height, poles included.
    lat2, lon2, h2 = g.ecef_to_geodetic(g.geodetic_to_ecef(lat, lon, h))
    assert abs(lat2 - lat) < 1e-9
    if abs(lat) < 90.0 - 1e-9:  # longitude is undefined at the poles
        assert abs(((lon2 - lon) + 180.0) % 360.0 - 180.0) < 1e-9
    assert abs(h2 - h) < 1e-6


def test_enu_is_orthonormal_and_up_is_ellipsoid_normal():
    lat, lon = np.array([47.5, -33.0, 89.9]), np.array([9.5, 151.0, -120.0])
    e, n, u = g.enu_basis(lat, lon)
    basis = np.stack([e, n, u], axis=-2)
    np.testing.assert_allclose(basis @ np.swapaxes(basis, -1, -2), np.broadcast_to(np.eye(3), basis.shape), atol=1e-12)
    # Moving 1 m along "up" changes the geodetic height by 1 m and nothing else.
    p = g.geodetic_to_ecef(lat, lon, 0.0) + u
    lat2, lon2, h2 = g.ecef_to_geodetic(p)
    np.testing.assert_allclose(h2, 1.0, atol=1e-9)
    np.testing.assert_allclose(lat2, lat, atol=1e-12)


def test_radii_match_geodesic_small_steps():
    # A 1e-4 deg step along a meridian / parallel is M dlat / N cos(lat) dlon to ~1e-7 relative.
    geod = Geodesic.WGS84
    for lat in (0.0, 45.0, 80.0):
        m, n = g.radii_of_curvature(lat)
        d = 1e-4
        s_north = geod.Inverse(lat - d / 2, 10.0, lat + d / 2, 10.0)["s12"]
        s_east = geod.Inverse(lat, 10.0, lat, 10.0 + d)["s12"]
        assert abs(s_north - m * np.radians(d)) / s_north < 1e-7
        assert abs(s_east - n * np.cos(np.radians(lat)) * np.radians(d)) / s_east < 1e-7


def test_web_mercator_round_trip_and_known_value():
    # EPSG guidance note 7-2 example: lat 24.381787, lon -100.333333 -> x -11169055.58, y 2800000.00
    x, y = g.web_mercator_forward(24.38178696, -100.33333333)
    assert abs(x - -11169055.58) < 0.01 and abs(y - 2800000.00) < 0.01
    lat, lon = g.web_mercator_inverse(x, y)
    assert abs(lat - 24.38178696) < 1e-12 and abs(lon - -100.33333333) < 1e-12


def test_grid_to_ecef_equals_the_broadcast_conversion_bit_for_bit():
    """geodetic_to_ecef of a (rows, 1) by (1, cols) grid (sines, cosines and radii once a row and a
    column: the clipmap's posts) is that of the broadcast grid, bit for bit, poles and the
    antimeridian included."""
    rng = np.random.default_rng(3)
    lat = np.concatenate([[-90.0, 90.0, 0.0], rng.uniform(-90.0, 90.0, 40)])
    lon = np.concatenate([[-180.0, 180.0, 179.999999], rng.uniform(-180.0, 180.0, 50)])
    h = rng.uniform(-430.0, 8850.0, (lat.size, lon.size))
    la, lo = np.broadcast_arrays(lat[:, None], lon[None, :])
    assert np.array_equal(g.geodetic_to_ecef(lat[:, None], lon[None, :], h), g.geodetic_to_ecef(la, lo, h))
