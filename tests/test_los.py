"""Segment/surface intersection and line of sight: closed forms, brute force, hard cases.

Oracles never use terrain.los internals: surface heights come from
Raster.heights_into (the bilinear kernel), ray points from
terrain.geodesy (ECEF <-> geodetic), and dense walks sample the segment.
"""

import math

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic
from hypothesis import given, settings
from hypothesis import strategies as st

from sortie.errors import InvalidArgument
from terrain.geodesy import (ecef_to_geodetic, enu_basis, geodetic_to_ecef, radii_of_curvature,
                             web_mercator_inverse)
from terrain.los import (ENDPOINT_TOLERANCE_M, MODEL_ERROR_M, PIECE_RHO_COEF, _geodetic, dense_los_reference,
                         intersect_segments, line_of_sight, piece_length_m)
from terrain.raster import (CRS_GEOGRAPHIC, CRS_WEB_MERCATOR, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef,
                            Raster)

GEOD = Geodesic.WGS84
D = 1.0 / 1200.0  # 3 arc-second posts
# A hit's height equals the surface's at its (lat, lon) to within the model's
# horizontal error (1 um) times the slope (< 20 on every raster here), plus
# rounding: 1 mm leaves a wide margin.
ON_SURFACE_M = 1.0e-3
# A dense sample before the first hit may be below the surface by at most the
# same model error times slope: 20 um on these rasters.
BEFORE_HIT_M = 20 * MODEL_ERROR_M


@pytest.fixture(scope="module")
def alps(hgt_alps):
    """N47E009 read independently of terrain.dem: big-endian int16, north row first."""
    h = np.fromfile(hgt_alps, ">i2").reshape(1201, 1201)[::-1].astype(np.float32)
    return Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D), name="N47E009")


def surface(raster, lat, lon):
    h = np.full(np.size(lat), np.nan)
    status = np.full(np.size(lat), STATUS_OUTSIDE, np.uint8)
    raster.heights_into(np.atleast_1d(np.asarray(lat, float)), np.atleast_1d(np.asarray(lon, float)), h, status)
    return h


def random_rays(raster, n, rng, length_m=10_000.0, eye_m=2.0, margin_m=12_000.0):
    """n rays of length_m on random azimuths, both ends eye_m above the ground."""
    lat0, lon0, lat1, lon1 = raster.bounds
    m_lat = margin_m / 111_000.0
    m_lon = m_lat / np.cos(np.radians(0.5 * (lat0 + lat1)))
    a_lat = rng.uniform(lat0 + m_lat, lat1 - m_lat, n)
    a_lon = rng.uniform(lon0 + m_lon, lon1 - m_lon, n)
    az = rng.uniform(0.0, 360.0, n)
    b = [GEOD.Direct(la, lo, z, length_m) for la, lo, z in zip(a_lat, a_lon, az)]
    b_lat = np.array([d["lat2"] for d in b])
    b_lon = np.array([d["lon2"] for d in b])
    return (a_lat, a_lon, surface(raster, a_lat, a_lon) + eye_m,
            b_lat, b_lon, surface(raster, b_lat, b_lon) + eye_m)


def random_pairs(raster, n, rng, eye_m):
    """n rays between uniform random points of the raster, both ends eye_m above the ground."""
    lat0, lon0, lat1, lon1 = raster.bounds
    a_lat, b_lat = rng.uniform(lat0, lat1, (2, n))
    a_lon, b_lon = rng.uniform(lon0, lon1, (2, n))
    return (a_lat, a_lon, surface(raster, a_lat, a_lon) + eye_m,
            b_lat, b_lon, surface(raster, b_lat, b_lon) + eye_m)


def clearance(raster, a_ecef, b_ecef, s):
    """Ray height minus surface height (m) at parameters s in [0, 1] of the segment a -> b."""
    lat, lon, h = ecef_to_geodetic(a_ecef + np.asarray(s)[:, None] * (b_ecef - a_ecef))
    return h - surface(raster, lat, lon)


def check_rays(raster, rays, samples_per_post=64):
    """Every hit is on the surface and on the segment; no dense sample before it is below."""
    hit, dist, lat, lon, h, normal, status = intersect_segments(raster, *rays)
    a = geodetic_to_ecef(rays[0], rays[1], rays[2])
    b = geodetic_to_ecef(rays[3], rays[4], rays[5])
    assert (status[hit] != STATUS_OUTSIDE).all()
    assert np.abs(h[hit] - surface(raster, lat[hit], lon[hit])).max(initial=0) < ON_SURFACE_M
    p = geodetic_to_ecef(lat[hit], lon[hit], h[hit])
    assert np.abs(np.linalg.norm(p - a[hit], axis=1) - dist[hit]).max(initial=0) < 1e-6
    u = (b - a)[hit] / np.linalg.norm((b - a)[hit], axis=1, keepdims=True)
    off_line = (p - a[hit]) - np.sum((p - a[hit]) * u, axis=1, keepdims=True) * u
    assert np.linalg.norm(off_line, axis=1).max(initial=0) < 1e-6
    assert np.allclose(np.linalg.norm(normal[hit], axis=1), 1.0)
    step = min(raster.post_spacing_m) / samples_per_post
    for k in np.flatnonzero(status != STATUS_OUTSIDE):
        length = np.linalg.norm(b[k] - a[k])
        end = dist[k] if hit[k] else length
        s = np.arange(0.0, end, step) / length
        if s.size:
            assert clearance(raster, a[k], b[k], s).min() >= -BEFORE_HIT_M, k
    return hit, dist, status


def flat_raster(height, lat0, lon0, ny, nx, d, crs=CRS_GEOGRAPHIC):
    return Raster(np.full((ny, nx), height, np.float32), Georef(crs, lon0, lat0, d, d))


def test_kernel_geodetic_matches_geodesy():
    """The kernel's trig-free Bowring agrees with geodesy.ecef_to_geodetic, poles included."""
    rng = np.random.default_rng(1)
    lat = np.r_[rng.uniform(-90, 90, 3000), 90.0, -90.0, 89.9999999, 0.0]
    lon = np.r_[rng.uniform(-180, 180, 3000), 0.0, 10.0, 20.0, -180.0]
    h = np.r_[rng.uniform(-500, 1e6, 3000), 0.0, 100.0, 5.0, -10.0]
    p = geodetic_to_ecef(lat, lon, h)
    got = np.array([_geodetic(*q) for q in p])
    want = np.stack(ecef_to_geodetic(p), axis=1)
    assert np.abs(got[:, 0] - want[:, 0]).max() < 1e-12  # degrees: 0.1 um
    dlon = np.abs(got[:, 1] - want[:, 1])
    assert np.minimum(dlon, 360 - dlon).max() < 1e-12
    assert np.abs(got[:, 2] - want[:, 2]).max() < 1e-8  # metres, at up to 1000 km up


def test_piecewise_quadratic_model_error_below_bound():
    """Quadratic through a piece's start/middle/end vs exact positions, equator to pole."""
    rng = np.random.default_rng(7)
    u = np.linspace(0.05, 0.95, 19)

    def fit(f):
        f0, fm, f1 = f
        return f0 + (4 * fm - 3 * f0 - f1) * u + (2 * f0 + 2 * f1 - 4 * fm) * u * u

    for lat_c in (0.0, 35.0, 47.0, 70.0, 85.0, 89.9, 89.9999):
        for _ in range(40):
            a = geodetic_to_ecef(lat_c, rng.uniform(-180, 180), rng.uniform(0, 9000))
            d = rng.normal(size=3)
            d -= rng.uniform(0.8, 1.0) * np.dot(d, a) / np.dot(a, a) * a  # mostly horizontal
            d /= np.linalg.norm(d)
            length = piece_length_m(a[0], a[1], d[0], d[1], PIECE_RHO_COEF)
            nodes = ecef_to_geodetic(a + np.array([0.0, 0.5, 1.0])[:, None] * length * d)
            lat_t, lon_t, h_t = ecef_to_geodetic(a + (u * length)[:, None] * d)
            lon_n = np.unwrap(np.radians(nodes[1]))
            lon_t = np.radians(lon_t)
            lon_t += 2 * np.pi * np.round((lon_n[0] - lon_t) / (2 * np.pi))
            m, n = radii_of_curvature(lat_t)
            e_north = np.radians(fit(nodes[0]) - lat_t) * m
            e_east = (fit(lon_n) - lon_t) * n * np.cos(np.radians(lat_t))
            assert np.hypot(e_north, e_east).max() < MODEL_ERROR_M
            assert np.abs(fit(nodes[2]) - h_t).max() < MODEL_ERROR_M
            if lat_c <= 85.0:  # Web Mercator rows: y = a ln tan(pi/4 + lat/2)
                y = np.log(np.tan(np.pi / 4 + np.radians(nodes[0]) / 2))
                y_t = np.log(np.tan(np.pi / 4 + np.radians(lat_t) / 2))
                assert (np.abs(fit(y) - y_t) * np.cos(np.radians(lat_t)) * m).max() < MODEL_ERROR_M


@pytest.mark.parametrize("azimuth", [0.0, 45.0, 90.0, 150.0])
def test_flat_terrain_chord_sag_closed_form(azimuth):
    """Over constant-height terrain the chord between two points e metres up
    clears iff e exceeds its sag: (R + h) - sqrt((R + h)**2 - c**2 / 4) on the
    sphere of the normal section's radius (Euler); the ellipsoid differs from
    that sphere by < 1 mm of sag over 20 km (radius varies by 3e-5)."""
    ground = 100.0
    raster = flat_raster(ground, 46.75, 8.7, 61, 81, 1 / 120)
    lat_a, lon_a = 47.0, 9.0
    far = GEOD.Direct(lat_a, lon_a, azimuth, 20_000.0)
    m, n = radii_of_curvature(lat_a)
    alpha = np.radians(azimuth)
    radius = 1.0 / (np.cos(alpha) ** 2 / m + np.sin(alpha) ** 2 / n)
    eye = 8.0
    a = geodetic_to_ecef(lat_a, lon_a, ground + eye)
    b = geodetic_to_ecef(far["lat2"], far["lon2"], ground + eye)
    c = np.linalg.norm(b - a)
    sag = radius + ground + eye - np.sqrt((radius + ground + eye) ** 2 - c * c / 4)
    assert 7.7 < sag < 7.9  # d**2 / (8 R)
    lowest = ecef_to_geodetic(a + np.linspace(0, 1, 20001)[:, None] * (b - a))[2].min()
    assert abs((ground + eye - lowest) - sag) < 1e-3
    for e, visible in ((sag + 0.002, True), (sag - 0.002, False)):
        vis, status = line_of_sight(raster, [lat_a], [lon_a], [ground + e], [far["lat2"]], [far["lon2"]],
                                    [ground + e])
        assert vis[0] == visible and status[0] == STATUS_OK
    # Two points 2 m up and 20 km apart cannot see each other.
    vis, _ = line_of_sight(raster, [lat_a], [lon_a], [ground + 2], [far["lat2"]], [far["lon2"]], [ground + 2])
    assert not vis[0]
    hit, dist, _, _, h, _, _ = intersect_segments(raster, [lat_a], [lon_a], [ground + 2], [far["lat2"]],
                                                  [far["lon2"]], [ground + 2])
    # The chord reaches the ground where x (c - x) / (2 R) = 2 m.
    x = 0.5 * (c - np.sqrt(c * c - 16.0 * radius))
    assert hit[0] and abs(dist[0] - x) < 0.5 and abs(h[0] - ground) < ON_SURFACE_M


def test_hits_on_surface_and_first_on_real_dem(alps):
    rays = random_rays(alps, 150, np.random.default_rng(11))
    hit, _, status = check_rays(alps, rays)
    assert hit.sum() > 50 and (status == STATUS_OK).all()


def test_los_matches_dense_reference_on_2000_rays(alps):
    """Zero disagreements wherever the reference's clearance is more than 1 cm
    from zero, except where the reference stepped over an obstruction: each
    such ray is confirmed by sampling the gap it stepped over at 1 mm."""
    rays = random_rays(alps, 2000, np.random.default_rng(2026))
    visible, status = line_of_sight(alps, *rays)
    assert (status == STATUS_OK).all()
    ref_visible, ref_clear = dense_los_reference(alps, *rays, samples_per_post=16)
    sure = np.abs(ref_clear) > 0.01
    assert not np.any(visible & ~ref_visible & sure)  # the reference saw a sample below ground
    missed = np.flatnonzero(~visible & ref_visible & sure)
    assert missed.size <= 0.005 * visible.size
    hit, dist, *_ = intersect_segments(alps, *(r[missed] for r in rays))
    step = min(alps.post_spacing_m) / 16
    for k, d in zip(missed, dist):
        a = geodetic_to_ecef(rays[0][k], rays[1][k], rays[2][k])
        b = geodetic_to_ecef(rays[3][k], rays[4][k], rays[5][k])
        length = np.linalg.norm(b - a)
        s = np.arange(d, d + step, 1e-3) / length
        assert clearance(alps, a, b, s).min() < 0.0


@settings(max_examples=80, deadline=None)
@given(a=st.tuples(st.floats(47.01, 47.99), st.floats(9.01, 9.99), st.floats(0.5, 300)),
       b=st.tuples(st.floats(47.01, 47.99), st.floats(9.01, 9.99), st.floats(0.5, 300)))
def test_los_symmetric_and_consistent_with_intersect(alps, a, b):
    a_h = surface(alps, a[0], a[1]) + a[2]
    b_h = surface(alps, b[0], b[1]) + b[2]
    ab = line_of_sight(alps, [a[0]], [a[1]], a_h, [b[0]], [b[1]], b_h)
    ba = line_of_sight(alps, [b[0]], [b[1]], b_h, [a[0]], [a[1]], a_h)
    assert ab[0][0] == ba[0][0] and ab[1][0] == ba[1][0] == STATUS_OK
    fwd = intersect_segments(alps, [a[0]], [a[1]], a_h, [b[0]], [b[1]], b_h)
    back = intersect_segments(alps, [b[0]], [b[1]], b_h, [a[0]], [a[1]], a_h)
    assert fwd[0][0] == back[0][0] == (not ab[0][0])


def test_spike_tent_hit_exactly():
    """A single 100 m post on flat ground; along its column the surface is the
    tent 100 (1 - |dr|), so a ray at height h meets it at dr = -(1 - h/100)."""
    h = np.zeros((21, 21), np.float32)
    h[10, 10] = 100.0
    raster = Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    lat_p, lon_p = 47.0 + 10 * D, 9.0 + 10 * D
    hit, dist, lat, lon, hh, normal, status = intersect_segments(
        raster, [lat_p - 6 * D], [lon_p], [50.0], [lat_p + 6 * D], [lon_p], [50.0])
    assert hit[0] and status[0] == STATUS_OK and abs(lon[0] - lon_p) < 1e-12
    assert abs(hh[0] - 50.0) < 0.03  # the 1.1 km chord sags 2.4 cm in the middle
    want_lat = lat_p - (1.0 - hh[0] / 100.0) * D
    assert abs(lat[0] - want_lat) * 111_000 < 1e-6
    assert normal[0, 1] < -0.5 and normal[0, 2] > 0  # faces south, toward the ray
    rays = random_pairs(raster, 200, np.random.default_rng(3), eye_m=30.0)
    hit, _, _ = check_rays(raster, rays)
    assert hit.any()


@pytest.mark.parametrize("offset_m, blocked", [(1e-3, False), (-1e-3, True), (0.0, None)])
def test_grazing_the_top_of_a_post(offset_m, blocked):
    """A straight line tangent to the ellipsoid-parallel at a spike's tip rises
    away from it on both sides, so it touches the tip only: 1 mm above clears,
    1 mm below hits at the tip, exactly on it either outcome is allowed."""
    h = np.zeros((21, 21), np.float32)
    h[10, 10] = 100.0
    raster = Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    lat_p, lon_p = 47.0 + 10 * D, 9.0 + 10 * D
    tip = geodetic_to_ecef(lat_p, lon_p, 100.0)
    east, north, _ = enu_basis(lat_p, lon_p)
    t = east + 0.3 * north
    t /= np.linalg.norm(t)
    ends = ecef_to_geodetic(np.stack([tip - 300.0 * t, tip + 300.0 * t]))
    hit, dist, lat, lon, _, _, _ = intersect_segments(
        raster, ends[0][:1], ends[1][:1], ends[2][:1] + offset_m, ends[0][1:], ends[1][1:], ends[2][1:] + offset_m)
    if blocked is not None:
        assert hit[0] == blocked
    if hit[0]:
        assert abs(dist[0] - 300.0) < 0.01


def test_cliff_ramp_hit_exactly():
    """A 1000 m step between two post columns is a ramp one cell wide; a ray at
    height h meets it at fraction h / 1000 across that cell."""
    h = np.zeros((11, 21), np.float32)
    h[:, 10:] = 1000.0
    raster = Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    lat = 47.0 + 5 * D
    hit, dist, lat_h, lon_h, hh, normal, status = intersect_segments(
        raster, [lat], [9.0 + 3 * D], [500.0], [lat], [9.0 + 17 * D], [500.0])
    assert hit[0] and status[0] == STATUS_OK
    assert abs(hh[0] - 500.0) < 0.03  # the 0.8 km chord sags 1.5 cm there
    want_lon = 9.0 + (9.0 + hh[0] / 1000.0) * D
    assert abs(lon_h[0] - want_lon) * 75_000 < 1e-5  # metres east; the ramp is 16:1
    assert abs(hh[0] - surface(raster, lat_h, lon_h)[0]) < ON_SURFACE_M
    assert normal[0, 0] < -0.99  # the ramp faces west
    rays = random_pairs(raster, 200, np.random.default_rng(5), eye_m=5.0)
    check_rays(raster, rays)


def test_vertical_segment_hits_at_bilinear_height(alps):
    rng = np.random.default_rng(9)
    lat = rng.uniform(47.05, 47.95, 200)
    lon = rng.uniform(9.05, 9.95, 200)
    ground = surface(alps, lat, lon)
    hit, dist, lat_h, lon_h, h, normal, status = intersect_segments(alps, lat, lon, ground + 50.0, lat, lon,
                                                                    ground - 50.0)
    assert hit.all() and (status == STATUS_OK).all()
    assert np.abs(h - ground).max() < 1e-6
    assert np.abs(dist - 50.0).max() < 1e-6
    assert np.abs(lat_h - lat).max() < 1e-12 and np.abs(lon_h - lon).max() < 1e-12
    de, dn = np.zeros(200), np.zeros(200)
    st_ = np.full(200, STATUS_OUTSIDE, np.uint8)
    alps.gradient_into(lat, lon, de, dn, st_)
    want = np.stack([-de, -dn, np.ones(200)], axis=1)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert np.abs(normal - want).max() < 1e-9
    # Upward from below the ground: a is under the surface, so the hit is a itself.
    hit, dist, *_ = intersect_segments(alps, lat, lon, ground - 1.0, lat, lon, ground + 1.0)
    assert hit.all() and (dist == 0.0).all()


def test_segments_along_a_post_column_and_row(alps):
    rng = np.random.default_rng(21)
    rows = rng.integers(100, 1100, 60)
    cols = rng.integers(100, 1100, 60)
    lat0, lon0 = 47.0 + rows * D, 9.0 + cols * D
    span = rng.integers(5, 80, 60) * D
    eye = surface(alps, lat0, lon0) + 5.0
    column = (lat0, lon0, eye, lat0 + span, lon0, surface(alps, lat0 + span, lon0) + 5.0)
    row = (lat0, lon0, eye, lat0, lon0 + span, surface(alps, lat0, lon0 + span) + 5.0)
    for rays in (column, row):
        hit, _, status = check_rays(alps, rays)
        assert (status == STATUS_OK).all()
        vis, _ = line_of_sight(alps, *rays)
        assert np.array_equal(vis, ~hit)


def test_ground_observer_sees_and_is_blocked_by_its_own_hill():
    """On a slope rising east at 10 m per post: a point on the ground sees a
    point 50 m above the slope uphill, and cannot see one below the slope."""
    cols = np.arange(41, dtype=np.float32)
    h = np.tile(10.0 * cols, (21, 1))
    raster = Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    lat = 47.0 + 10 * D
    a_lon, b_lon = 9.0 + 5.3 * D, 9.0 + 30.0 * D
    a_h = surface(raster, lat, a_lon)
    b_h = surface(raster, lat, b_lon)
    vis, status = line_of_sight(raster, [lat, lat], [a_lon, a_lon], np.r_[a_h, a_h],
                                [lat, lat], [b_lon, b_lon], np.r_[b_h + 50.0, b_h - 50.0])
    assert list(vis) == [True, False] and (status == STATUS_OK).all()
    # Both ends on the ground 1 mm apart: nothing is left between them to block.
    b2 = GEOD.Direct(lat, a_lon, 90.0, 0.9 * ENDPOINT_TOLERANCE_M)
    b2_h = surface(raster, b2["lat2"], b2["lon2"])
    assert line_of_sight(raster, [lat], [a_lon], a_h, [b2["lat2"]], [b2["lon2"]], b2_h)[0][0]


def test_coverage_edges_holes_and_filled_posts():
    h = np.full((41, 41), 100.0, np.float32)
    h[20, 30] = np.nan
    filled = np.zeros((41, 41), bool)
    filled[5, 5] = True
    raster = Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D), filled=filled)
    lat = 47.0 + 20 * D

    def one(a_lat, a_lon, a_h, b_lat, b_lon, b_h):
        hit, _, _, _, _, _, status = intersect_segments(raster, [a_lat], [a_lon], [a_h], [b_lat], [b_lon], [b_h])
        vis, vstatus = line_of_sight(raster, [a_lat], [a_lon], [a_h], [b_lat], [b_lon], [b_h])
        assert vstatus[0] == status[0] and (vis[0] == (not hit[0] and status[0] != STATUS_OUTSIDE))
        return hit[0], status[0]

    assert one(lat, 9.0 + 10 * D, 150, lat, 9.0 + 50 * D, 150) == (False, STATUS_OUTSIDE)  # leaves
    assert one(lat, 8.99, 150, lat, 9.0 + 10 * D, 150) == (False, STATUS_OUTSIDE)  # starts outside
    assert one(lat, 9.0 + 20 * D, 150, lat, 9.0 + 35 * D, 150) == (False, STATUS_OUTSIDE)  # crosses the hole
    assert one(lat, 9.0 + 20 * D, 150, lat, 9.0 + 35 * D, 50) == (True, STATUS_OK)  # lands before it
    assert one(lat, 9.0 + 20 * D, 150, lat, 9.0 + 28 * D, 150) == (False, STATUS_OK)
    south = 47.0 + 5 * D
    assert one(south, 9.0 + 1 * D, 150, south, 9.0 + 12 * D, 150) == (False, STATUS_FILLED)  # over a filled post
    assert one(south, 9.0 + 20 * D, 150, south, 9.0 + 30 * D, 150) == (False, STATUS_OK)


def test_antimeridian_raster_equals_its_rotated_copy():
    """Rotating the world about the polar axis is an exact symmetry: a raster
    straddling 180 E answers like the same posts at 9.5 E, to rounding."""
    rng = np.random.default_rng(17)
    h = rng.normal(300.0, 80.0, (121, 121)).astype(np.float32)
    dateline = Raster(h, Georef(CRS_GEOGRAPHIC, 179.5, 47.0, 1 / 120, 1 / 120))
    home = Raster(h, Georef(CRS_GEOGRAPHIC, 9.5, 47.0, 1 / 120, 1 / 120))
    rays = random_rays(home, 300, rng, length_m=5000.0, eye_m=20.0, margin_m=6000.0)
    shifted = list(rays)
    shifted[1] = (rays[1] + 170.0 + 180.0) % 360.0 - 180.0
    shifted[4] = (rays[4] + 170.0 + 180.0) % 360.0 - 180.0
    crossing = np.sign(shifted[1]) != np.sign(shifted[4])
    assert crossing.sum() > 10
    hit_h, dist_h, status_h = check_rays(home, rays, samples_per_post=16)
    hit_d, dist_d, status_d = check_rays(dateline, tuple(shifted), samples_per_post=16)
    assert np.array_equal(hit_h, hit_d) and np.array_equal(status_h, status_d)
    assert np.nanmax(np.abs(dist_h - dist_d)) < 1e-4
    assert np.array_equal(line_of_sight(home, *rays)[0], line_of_sight(dateline, *shifted)[0])


def test_web_mercator_raster_far_from_origin():
    """EPSG:3857 posts near 153 E, 44 S (x ~ 1.7e7 m): rows are nonlinear in latitude."""
    rng = np.random.default_rng(23)
    ny, nx = 160, 200
    yy, xx = np.mgrid[0:ny, 0:nx]
    h = (400 + 300 * np.sin(xx / 9.0) * np.cos(yy / 13.0) + rng.normal(0, 20, (ny, nx))).astype(np.float32)
    raster = Raster(h, Georef(CRS_WEB_MERCATOR, 1.7e7, -5.5e6, 90.0, 90.0))
    lat0, lon0 = web_mercator_inverse(1.7e7, -5.5e6)
    assert lon0 > 150 and lat0 < -40
    rays = random_rays(raster, 200, rng, length_m=4000.0, eye_m=10.0, margin_m=4500.0)
    hit, _, status = check_rays(raster, rays)
    assert hit.any() and (~hit).any() and (status == STATUS_OK).all()


def test_poles_periodic_cap():
    """A cap raster from 89 N to the pole, a full turn wide (columns wrap).

    A chord between (89.5, 0) and (89.5, 180) passes through the polar axis,
    where longitude is singular; by symmetry its lowest point is its midpoint,
    so it clears flat ground iff the ground is below that point's height.
    """
    d = 0.05
    ny, nx = 21, 7201
    a = geodetic_to_ecef(89.5, 0.0, 1000.0)
    b = geodetic_to_ecef(89.5, 180.0, 1000.0)
    lowest = ecef_to_geodetic(0.5 * (a + b))[2]
    assert 700 < lowest < 800  # (111.7 km)**2 / (8 R) ~ 245 m of sag
    for ground, visible in ((lowest - 0.01, True), (lowest + 0.01, False)):
        raster = Raster(np.full((ny, nx), ground, np.float32), Georef(CRS_GEOGRAPHIC, -180.0, 89.0, d, d))
        vis, status = line_of_sight(raster, [89.5], [0.0], [1000.0], [89.5], [180.0], [1000.0])
        assert vis[0] == visible and status[0] == STATUS_OK
        if not visible:
            hit, dist, lat, _, h, _, _ = intersect_segments(raster, [89.5], [0.0], [1000.0], [89.5], [180.0],
                                                            [1000.0])
            assert hit[0] and lat[0] > 89.99 and abs(h[0] - ground) < ON_SURFACE_M
    # Rough polar terrain: the pole row is one point, the seam column repeats.
    rng = np.random.default_rng(29)
    h = rng.normal(300.0, 60.0, (ny, nx)).astype(np.float32)
    h[-1, :] = 300.0
    h[:, -1] = h[:, 0]
    cap = Raster(h, Georef(CRS_GEOGRAPHIC, -180.0, 89.0, d, d))
    n = 120
    a_lat = rng.uniform(89.7, 89.99, n)
    a_lon = rng.uniform(-180, 180, n)
    b_lat = rng.uniform(89.7, 89.99, n)
    b_lon = np.where(np.arange(n) < 20, a_lon + 180.0, rng.uniform(-180, 180, n))  # 20 through the axis
    rays = (a_lat, a_lon, surface(cap, a_lat, a_lon) + 200.0, b_lat, b_lon,
            surface(cap, b_lat, b_lon) + 200.0)
    hit, _, status = check_rays(cap, rays, samples_per_post=16)
    assert (status == STATUS_OK).all() and hit.any() and (~hit).any()


def test_dense_reference_reports_clearance_and_coverage():
    raster = flat_raster(100.0, 47.0, 9.0, 41, 41, D)
    lat = 47.0 + 20 * D
    vis, clear = dense_los_reference(raster, [lat, lat], [9.0 + 5 * D, 9.0 + 5 * D], [105.0, 105.0],
                                     [lat, lat], [9.0 + 10 * D, 9.0 + 60 * D], [105.0, 105.0])
    assert vis[0] and 4.9 < clear[0] < 5.0
    assert not vis[1] and np.isnan(clear[1])


def test_bad_input_names_the_field(alps):
    with pytest.raises(InvalidArgument, match="b_lat"):
        line_of_sight(alps, [47.5, 47.6], [9.5, 9.5], [1000, 1000], [47.5], [9.6], [1000])
    with pytest.raises(InvalidArgument, match=r"a_lat\[1\]"):
        intersect_segments(alps, [47.5, np.nan], [9.5, 9.5], [1000, 1000], [47.5, 47.5], [9.6, 9.6], [1, 1])
    with pytest.raises(InvalidArgument, match="b_h"):
        line_of_sight(alps, [47.5], [9.5], [1000], [47.5], [9.6], [np.inf])


# ----------------------------------------------------------------------------- DEM over procedural

@pytest.fixture(scope="module")
def alps_over_procedural(alps):
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    return Terrain([alps, ProceduralTerrain(seed=3)])


def test_los_blocked_inside_the_dem_before_the_ray_leaves_it(alps_over_procedural):
    """The acceptance report's repro: from inside N47E009 to 4 km north of it, the ray passes
    ~84 m below the DEM surface 7 km from a. Blocked, as intersect says (a DEM hit 42 m from
    a), whichever endpoint is given first."""
    t = alps_over_procedural
    a = (47.91228, 9.42954, 654.4)
    b = (48.03527, 9.40888, 532.3)
    for p, q in ((a, b), (b, a)):
        res = t.line_of_sight(*[[v] for v in p + q])
        assert not res.visible[0] and res.status[0] == STATUS_OK
    hit = t.intersect(*[[v] for v in a + b])
    assert hit.hit[0] and 40.0 < hit.distance_m[0] < 45.0  # the report's 42.07 m, in the DEM
    assert t.heights([47.9725], [9.4194]).height_msl_m[0] > 640.0  # the ridge the ray passes under


@settings(max_examples=80, deadline=None)
@given(lat_a=st.floats(47.90, 47.999), lon_a=st.floats(9.05, 9.95), north_km=st.floats(0.2, 12.0),
       east_km=st.floats(-6.0, 6.0), up_a=st.floats(2.0, 300.0), up_b=st.floats(2.0, 300.0))
def test_los_agrees_with_intersect_across_the_dem_edge(alps_over_procedural, lat_a, lon_a, north_km, east_km,
                                                       up_a, up_b):
    """Rays from inside the DEM to points north of it (inside or beyond its north edge at 48N),
    both endpoints above the terrain the stack answers there: line of sight is blocked exactly
    when intersect's first contact comes before the last ENDPOINT_TOLERANCE_M of the segment,
    whichever endpoint is given first; never OUTSIDE (the procedural world covers the rest)."""
    t = alps_over_procedural
    lat_b = lat_a + north_km / 111.2
    lon_b = lon_a + east_km / (111.2 * math.cos(math.radians(lat_a)))
    ground = t.heights([lat_a, lat_b], [lon_a, lon_b]).height_msl_m
    a = (lat_a, lon_a, ground[0] + up_a)
    b = (lat_b, lon_b, ground[1] + up_b)
    hit = t.intersect(*[[v] for v in a + b])
    length = np.linalg.norm(geodetic_to_ecef([b[0]], [b[1]], [b[2]]) - geodetic_to_ecef([a[0]], [a[1]], [a[2]]))
    blocked = bool(hit.hit[0] and hit.distance_m[0] < length - ENDPOINT_TOLERANCE_M)
    for p, q in ((a, b), (b, a)):
        res = t.line_of_sight(*[[v] for v in p + q])
        assert res.status[0] != STATUS_OUTSIDE
        assert (not res.visible[0]) == blocked, (p, q, hit.distance_m[0], length)


# ----------------------------------------------------------------------------- the shell of every surface

def test_a_ray_through_the_earth_is_answered_from_its_stretch_in_the_shell():
    """The acceptance probe's ray over a procedural world, from 10,000 km over (0, 0) to
    10,000 km over (0, 179): its chord passes 143 km from the Earth's centre. Only its stretch
    between the shell every surface lies in (Terrain._shell) and the point where it dives
    below it is traced (8 s before, for the rasters along 19,000 km of ground track): the same
    first contact as tracing all of it, and blocked either way round."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    t = Terrain([ProceduralTerrain(seed=42)])
    a, b = (0.0, 0.0, 1e7), (0.0, 179.0, 1e7)
    hit = t.intersect(*[[v] for v in a + b])
    assert hit.hit[0] and hit.status[0] == STATUS_OK
    assert 0.5 < hit.lon_deg[0] < 1.0  # where it comes down, near the start's side
    ground = t.heights(hit.lat_deg, hit.lon_deg).height_msl_m[0]
    assert hit.height_msl_m[0] == pytest.approx(ground, abs=0.01)
    for p, q in ((a, b), (b, a)):
        res = t.line_of_sight(*[[v] for v in p + q])
        assert not res.visible[0] and res.status[0] == STATUS_OK


def test_cut_segments_answer_as_traced_whole(monkeypatch):
    """Segments from 30-500 km up to points 0-2 km over a procedural world (each cut to its
    stretch in the shell) or wholly above it (clear): intersect and line of sight as with the
    shell turned off, to rounding (and 30 times faster: 0.5 s against 14 s for 40 such segments
    from up to 3,000 km)."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    rng = np.random.default_rng(5)
    n = 24
    lat_a, lon_a = rng.uniform(-60, 60, n), rng.uniform(-179, 179, n)
    lat_b = np.clip(lat_a + rng.uniform(-1, 1, n), -89, 89)
    lon_b = lon_a + rng.uniform(-1, 1, n)
    h_a = rng.uniform(3e4, 5e5, n)
    h_b = np.where(np.arange(n) % 4 == 0, rng.uniform(6e4, 9e4, n), rng.uniform(0.0, 2000.0, n))
    t = Terrain([ProceduralTerrain(seed=7, max_height_m=800.0)])
    got = t.intersect(lat_a, lon_a, h_a, lat_b, lon_b, h_b)
    seen = [t.line_of_sight(lat_a, lon_a, h_a, lat_b, lon_b, h_b),
            t.line_of_sight(lat_b, lon_b, h_b, lat_a, lon_a, h_a)]
    assert t._shell_cut(*_ends(lat_a, lon_a, h_a, lat_b, lon_b, h_b)) is not None  # the cut is taken
    monkeypatch.setattr(Terrain, "_shell", lambda self: None)
    whole = t.intersect(lat_a, lon_a, h_a, lat_b, lon_b, h_b)
    np.testing.assert_array_equal(got.hit, whole.hit)
    np.testing.assert_array_equal(got.status, whole.status)
    np.testing.assert_allclose(got.distance_m, whole.distance_m, rtol=1e-9, atol=1e-6)
    assert got.hit.any() and not got.hit.all()
    for res in seen:
        ref = t.line_of_sight(lat_a, lon_a, h_a, lat_b, lon_b, h_b)
        np.testing.assert_array_equal(res.visible, ref.visible)
        np.testing.assert_array_equal(res.status, ref.status)


def _ends(lat_a, lon_a, h_a, lat_b, lon_b, h_b):
    """(rays, a, b) as Terrain's ray methods make them."""
    from terrain.los import check_segments

    rays = check_segments(lat_a, lon_a, h_a, lat_b, lon_b, h_b)
    return rays, geodetic_to_ecef(rays[0], rays[1], rays[2]), geodetic_to_ecef(rays[3], rays[4], rays[5])
