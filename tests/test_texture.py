"""Texture synthesis (terrain/texture.py), sun position (terrain/sun.py) and `sortie terrain texture`.

Sun: Meeus' worked examples, published equinox/solstice instants, noon and
sunrise geometry, and an independent path (sidereal time + ECEF rotation).
Texture: water exactly where height <= 0 on real coastal data, rock on
cliffs in the Alps, hand-computed shadow geometry of a ridge and a cone,
flat-plane and V-valley sky exposure, night, determinism, and the CLI end to end.
"""

from __future__ import annotations

import argparse
import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from PIL import Image

from sortie.errors import InvalidArgument
from terrain.dem import read_dem
from terrain.geodesy import enu_basis
from terrain.sun import (JD_J2000, julian_day, refraction_deg, solar_coordinates, sun_direction_enu,
                         sun_position)
from terrain.terrain import Terrain
from terrain.texture import (ALPINE, BEACH, FARMLAND, FOREST, GRASS, N_CLASSES, NODATA, ROCK, SNOW, WATER,
                             ClassParams, LightParams, base_classes, cast_shadow, class_map, class_tiles,
                             compose, diffuse, fractal_noise, grid_latlon, light_map, metre_spacing,
                             normals_enu, sky_view, slope_deg, synthesize)
from terrain.texture_cli import MAX_PIXELS, TextureRequest, add_texture_parser, sample_heights, texture_request

UTC = timezone.utc


# --------------------------------------------------------------------------- sun

def test_meeus_example_25a_and_28b():
    # Meeus, Astronomical Algorithms 2nd ed., example 25.a (1992 October 13.0 TD, JDE 2448908.5):
    # L0 = 201.80720, M = 278.99397, e = 0.016711668, apparent lambda = 199.90895,
    # corrected epsilon = 23.43999, alpha = 198.38083, delta = -7.78507 (degrees).
    c = solar_coordinates(2448908.5)
    assert float(c.mean_longitude_deg) == pytest.approx(201.80720, abs=2e-5)
    assert float(c.mean_anomaly_deg) == pytest.approx(278.99397, abs=2e-5)
    assert float(c.eccentricity) == pytest.approx(0.016711668, abs=1e-9)
    assert float(c.apparent_longitude_deg) == pytest.approx(199.90895, abs=2e-5)
    assert float(c.obliquity_deg) == pytest.approx(23.43999, abs=2e-5)
    assert float(c.right_ascension_deg) == pytest.approx(198.38083, abs=2e-5)
    assert float(c.declination_deg) == pytest.approx(-7.78507, abs=2e-5)
    # Example 28.b, same instant, formula 28.3: E = +3.42772 degrees = 13 min 42.7 s.
    assert float(c.equation_of_time_min) / 4.0 == pytest.approx(3.42772, abs=1e-4)


def test_julian_day():
    # J2000.0 is 2000-01-01T12:00 (the UTC/TT difference ignored, as the module says).
    assert float(julian_day(datetime(2000, 1, 1, 12, tzinfo=UTC))) == JD_J2000
    stamps = np.array(["2000-01-01T12:00:00", "2000-01-02T00:00:00"], dtype="datetime64[s]")
    assert julian_day(stamps).tolist() == [JD_J2000, JD_J2000 + 0.5]
    with pytest.raises(ValueError, match="naive"):
        julian_day(datetime(2000, 1, 1))


# Published instants (USNO / IMCCE): March equinox 2026-03-20 14:46 UTC, June solstice 2026-06-21 08:24 UTC.
EQUINOX = datetime(2026, 3, 20, 14, 46, tzinfo=UTC)
SOLSTICE = datetime(2026, 6, 21, 8, 24, tzinfo=UTC)


def test_declination_at_equinox_and_solstice():
    assert abs(float(solar_coordinates(julian_day(EQUINOX)).declination_deg)) < 0.01  # 0.39 deg/day: 1.5 min
    days = np.array([SOLSTICE.replace(tzinfo=None) + timedelta(hours=h) for h in range(-72, 73, 6)],
                    dtype="datetime64[s]")
    dec = solar_coordinates(julian_day(days)).declination_deg
    assert int(np.argmax(dec)) == 12  # the peak is at the published instant
    assert float(dec[12]) == pytest.approx(23.44, abs=0.01)  # the obliquity of 2026


def _day_samples(day: datetime, step_s: int = 10) -> np.ndarray:
    start = np.datetime64(day.replace(hour=0, minute=0, second=0, tzinfo=None), "s")
    return start + np.arange(0, 86400, step_s).astype("timedelta64[s]")


def test_noon_elevations():
    # Equator, equinox day, at lon -40 where local noon (about 14:40 UTC) is within minutes of the
    # equinox: the highest sun is 90 - |delta| with |delta| < 0.005; 10 s samples are within
    # 0.021 deg of the peak (hour angle 0.042 deg a step).
    times = _day_samples(EQUINOX)
    el = sun_position(times, 0.0, -40.0).elevation_deg
    assert el.max() > 89.97
    # Solstice: highest elevation 90 - |phi - 23.44| (delta changes by < 0.001 deg that day).
    times = _day_samples(SOLSTICE)
    for lat in (-30.0, 0.0, 23.44, 47.5, 60.0):
        el = sun_position(times, lat, 8.0).elevation_deg
        assert el.max() == pytest.approx(90.0 - abs(lat - 23.44), abs=0.03), lat


def test_sunrise_and_sunset_azimuth_at_equinox():
    # delta ~ 0 rises due east and sets due west: cos(az) = sin(delta) / cos(phi), and on the
    # equinox day |delta| < 0.2 deg from sunrise to sunset, so |az - 90| < 0.2 / cos(phi).
    times = _day_samples(EQUINOX)
    for lat in (0.0, 45.0):
        pos = sun_position(times, lat, -40.0)
        el = pos.elevation_deg
        rise = int(np.flatnonzero((el[:-1] < 0.0) & (el[1:] >= 0.0))[0])
        sets = int(np.flatnonzero((el[:-1] >= 0.0) & (el[1:] < 0.0))[0])
        bound = 0.2 / math.cos(math.radians(lat))
        assert abs(pos.azimuth_deg[rise] - 90.0) < bound
        assert abs(pos.azimuth_deg[sets] - 270.0) < bound


def test_direction_agrees_with_sidereal_time_and_ecef():
    # An independent path: Greenwich mean sidereal time (Meeus 12.4), the sun's right ascension and
    # declination as an ECEF direction, rotated into the local frame by terrain.geodesy.enu_basis.
    # It skips the equation of time and the hour-angle formulas; the two agree to 0.02 deg
    # (nutation in right ascension, up to 0.005 deg, is ignored on this side).
    for k in range(60):
        when = datetime(2026, 1, 1, tzinfo=UTC) + timedelta(hours=k * 146.3)
        lat, lon = (k * 37) % 170 - 85, (k * 53) % 360 - 180
        jd = float(julian_day(when))
        t = (jd - JD_J2000) / 36525.0
        c = solar_coordinates(jd)
        gmst = 280.46061837 + 360.98564736629 * (jd - JD_J2000) + 0.000387933 * t * t - t**3 / 38710000.0
        lng, dec = np.radians(c.right_ascension_deg - gmst), np.radians(c.declination_deg)
        v = np.array([np.cos(dec) * np.cos(lng), np.cos(dec) * np.sin(lng), np.sin(dec)])
        east, north, up = enu_basis(lat, lon)
        want = np.array([east @ v, north @ v, up @ v])
        pos = sun_position(when, lat, lon)
        got = sun_direction_enu(pos.azimuth_deg, pos.elevation_deg)
        assert np.degrees(np.arccos(min(1.0, float(got @ want)))) < 0.02, (when, lat, lon)


def test_direction_vector_and_refraction():
    az = np.array([0.0, 90.0, 200.0, 315.0])
    el = np.array([10.0, 45.0, -5.0, 89.0])
    d = sun_direction_enu(az, el)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert np.allclose(np.degrees(np.arcsin(d[:, 2])), el)
    assert np.allclose(np.degrees(np.arctan2(d[:, 0], d[:, 1])) % 360.0, az)
    # Refraction: about 34' at the horizon, 0 near the zenith, shrinking with elevation.
    r = refraction_deg([0.0, 5.0, 10.0, 45.0, 86.0])
    assert 0.45 < r[0] < 0.6 and r[-1] == 0.0 and np.all(np.diff(r) < 0.0)
    when = datetime(2026, 6, 21, 5, tzinfo=UTC)
    geo = sun_position(when, 47.0, 9.0)
    app = sun_position(when, 47.0, 9.0, refraction=True)
    assert float(app.elevation_deg - geo.elevation_deg) == pytest.approx(float(refraction_deg(geo.elevation_deg)))
    assert float(app.azimuth_deg) == float(geo.azimuth_deg)


# --------------------------------------------------------------------------- real data

def _sample(path, lat_min, lon_min, lat_max, lon_max, cols, rows):
    terrain = Terrain([read_dem(path)])
    req = TextureRequest(lat_min, lon_min, lat_max, lon_max, cols, rows, datetime(2026, 6, 21, 12, tzinfo=UTC))
    heights, lat, lon = sample_heights(terrain, req)
    dx, dy = metre_spacing(lat_min, lat_max, (lat_max - lat_min) / rows, (lon_max - lon_min) / cols)
    return heights, lat, lon, dx, dy


def test_water_exactly_at_or_below_sea_level_near_gothenburg(hgt_kattegat):
    # The box runs past the tile's east edge (12 E): those pixels have no data.
    h, lat, lon, dx, dy = _sample(hgt_kattegat, 57.55, 11.55, 57.75, 12.05, 200, 160)
    cm = class_map(h, slope_deg(h, dx, dy), dx, dy, lat[:, None])
    water = h <= 0.0
    assert 0.1 < water.mean() < 0.9  # both sea and land in the box
    assert np.array_equal(cm == WATER, water)
    assert np.array_equal(cm == NODATA, np.isnan(h))
    assert np.isnan(h[:, lon > 12.0 + 1e-9]).all() and (cm[:, lon > 12.0 + 1e-9] == NODATA).all()
    # Beach: low land next to the sea, never far from it.
    assert (cm == BEACH).any()
    assert (h[cm == BEACH] <= ClassParams().shore_max_height_m).all()


def test_slope_table_on_the_alps(hgt_alps):
    h, lat, lon, dx, dy = _sample(hgt_alps, 47.2, 9.25, 47.3, 9.45, 200, 140)
    slope = slope_deg(h, dx, dy)
    cm = class_map(h, slope, dx, dy, lat[:, None])
    land = np.isfinite(h) & (h > 0.0)
    cliff = land & (slope >= ClassParams().slope_bins_deg[2])
    assert cliff.sum() > 20  # the Alpstein (Saentis) has cliffs even at 90 m posts
    assert (cm[cliff] == ROCK).all()
    assert (slope[cm == FARMLAND] < ClassParams().slope_bins_deg[0]).all()  # farmland only on flat ground
    hist = np.bincount(cm.ravel(), minlength=N_CLASSES)
    assert hist[FOREST] and hist[ROCK] and hist[ALPINE] and hist[FARMLAND]


# --------------------------------------------------------------------------- class map rules

def test_base_classes_follow_the_table():
    p = ClassParams(band_jitter_m=0.0, woodlot_fraction=0.0, shore_width_m=0.0)
    h = np.array([[np.nan, -3.0, 0.0, 100.0, 1000.0, 2100.0, 2500.0, 3000.0]])
    # Latitude 46: tree line 2000 m, rock from 2450 m, snow line 2900 m.
    got = base_classes(np.repeat(h, 2, axis=0), 100.0, 100.0, 46.0, params=p)[0]
    assert got.tolist() == [NODATA, WATER, WATER, FARMLAND, FOREST, ALPINE, ROCK, SNOW]
    # Farther north the lines come down: at 62 N the snow line is 1500 m.
    north = base_classes(np.full((2, 2), 1600.0), 100.0, 100.0, 62.0, params=p)
    assert (north == SNOW).all()
    assert (base_classes(np.full((2, 2), 1600.0), 100.0, 100.0, 46.0, params=p) == FOREST).all()


def test_shore_and_slope_lookup():
    p = ClassParams(band_jitter_m=0.0, woodlot_fraction=0.0, shore_width_m=100.0, shore_max_height_m=5.0)
    h = np.full((5, 8), 3.0)
    h[:, :2] = -1.0  # sea in the west
    h[:, 5:] = 50.0  # higher ground: not a beach even if near
    cm = class_map(h, np.zeros_like(h), 50.0, 50.0, 46.0, params=p)
    assert (cm[:, :2] == WATER).all() and (cm[:, 2:4] == BEACH).all()  # within 100 m = 2 posts
    assert (cm[:, 4] == FARMLAND).all() and (cm[:, 5:] == FARMLAND).all()
    # The lookup table: same base, rising slope.
    flat = np.full((1, 4), 100.0)
    slopes = np.array([[5.0, 15.0, 30.0, 45.0]])
    assert class_map(flat, slopes, 50.0, 50.0, 46.0, params=p)[0].tolist() == [FARMLAND, GRASS, FOREST, ROCK]
    forest = np.full((1, 4), 1000.0)
    assert class_map(forest, slopes, 50.0, 50.0, 46.0, params=p)[0].tolist() == [FOREST, FOREST, FOREST, ROCK]
    snow = np.full((1, 4), 3500.0)
    assert class_map(snow, slopes, 50.0, 50.0, 46.0, params=p)[0].tolist() == [SNOW, SNOW, SNOW, ROCK]
    with pytest.raises(ValueError):
        ClassParams(slope_bins_deg=(30.0, 20.0, 40.0))


# --------------------------------------------------------------------------- geometry and light

def _plane(rows, cols, dx, dy, east_slope, north_slope, z0=500.0):
    x = np.arange(cols) * dx
    y = -np.arange(rows) * dy  # row 0 north: northing falls with the row
    return z0 + east_slope * x[None, :] + north_slope * y[:, None]


def test_slope_and_normals_of_planes():
    z = _plane(20, 30, 25.0, 40.0, 0.3, -0.4)
    assert np.allclose(slope_deg(z, 25.0, 40.0), math.degrees(math.atan(0.5)))
    n = normals_enu(z, 25.0, 40.0)
    want = np.array([-0.3, 0.4, 1.0]) / math.sqrt(1.25)
    assert np.allclose(n, want)


def test_flat_plane_light():
    z = np.full((60, 80), 321.0)
    for az, el in ((0.0, 5.0), (135.0, 30.0), (250.0, 60.0), (90.0, 89.0)):
        res = light_map(z, 30.0, 20.0, az, el)
        assert np.abs(res.sky - 1.0).max() <= 1e-6
        assert np.abs(res.n_dot_l - math.sin(math.radians(el))).max() <= 1e-6
        assert not res.shadow.any()
        p = LightParams()
        assert np.allclose(res.light, p.ambient + p.sun * math.sin(math.radians(el)), atol=1e-6)


def test_night_has_no_directional_light():
    z = _plane(40, 40, 30.0, 30.0, 0.5, 0.2)
    p = LightParams()
    for el in (-0.5, -3.0, -10.0):
        res = light_map(z, 30.0, 30.0, 100.0, el)
        assert res.shadow.all()
        ramp = p.night_ambient + (p.ambient - p.night_ambient) * max(0.0, 1.0 + el / p.twilight_deg)
        assert np.allclose(res.light, ramp * res.sky, atol=1e-6)  # ambient only
    assert np.allclose(light_map(z, 30.0, 30.0, 100.0, -10.0).light, p.night_ambient * res.sky, atol=1e-6)
    day = light_map(z, 30.0, 30.0, 100.0, 20.0)
    assert day.light.mean() > 2.0 * res.light.mean()


def test_ridge_shadow_geometry():
    # A north-south ridge 1000 m high, 45-degree flanks (1000 m wide each side), on a plain at 0 m;
    # posts every 50 m. Sun from the east (azimuth 90), 10 degrees up: the crest shades the plain to
    # the west out to 1000 / tan(10) = 5671 m from the crest; the whole lee flank is shaded too
    # (its crest is 45 degrees up from it). The sampled crest and posts put the edge within one post.
    dx = 50.0
    cols, rows = 301, 41
    x = (np.arange(cols) - 200) * dx  # crest at column 200, 10 km of plain to its west
    z = np.repeat(np.maximum(0.0, 1000.0 - np.abs(x))[None, :], rows, axis=0)
    shadow = cast_shadow(z, dx, dx, 90.0, 10.0)
    reach = 1000.0 / math.tan(math.radians(10.0))
    west = x < 0.0
    assert shadow[:, west & (x > -reach + dx)].all()
    assert not shadow[:, west & (x < -reach - dx)].any()
    assert not shadow[:, x >= 0.0].any()  # the sunward flank and the crest are lit
    res = light_map(z, dx, dx, 90.0, 10.0)
    assert (res.n_dot_l[:, (x > 100.0) & (x < 900.0)] > math.sin(math.radians(10.0))).all()
    assert (res.light[:, west & (x > -reach + dx)] <= LightParams().ambient + 1e-6).all()


@pytest.mark.parametrize("az", [120.0, 200.0, 315.0, 30.0])
def test_cone_shadow_geometry(az):
    # A cone 1000 m high, base radius 2000 m, on a plain; posts every 50 m; sun 10 degrees up.
    # Its shadow on the plain is the hull of the base circle and the apex's shadow point, 5671 m
    # from the centre away from the sun. Half-width of that hull at 3000 m out: the tangents from
    # the tip touch the circle at asin(2000 / 5671) = 20.65 degrees, so (5671 - 3000) tan(20.65) =
    # 1007 m. Points checked are at least 2 posts from every edge (digital rays stray <= 0.5 post).
    dx = 50.0
    n = 281
    c = (n - 1) // 2
    u = (np.arange(n) - c) * dx
    east, north = u[None, :], -u[:, None]
    z = np.maximum(0.0, 1000.0 - np.hypot(east, north) / 2.0)
    shadow = cast_shadow(z, dx, dx, az, 10.0)
    a = math.radians(az)
    toward = np.array([math.sin(a), math.cos(a)])  # east, north
    side = np.array([math.cos(a), -math.sin(a)])

    def at(along_away, across):
        e, nn = -along_away * toward + across * side
        return shadow[c - int(round(nn / dx)), c + int(round(e / dx))]

    for d in (2500.0, 3000.0, 4000.0, 5500.0):
        assert at(d, 0.0), d
    for d in (5800.0, 6500.0):
        assert not at(d, 0.0), d
    assert at(3000.0, 500.0) and at(3000.0, -500.0)
    assert not at(3000.0, 1200.0) and not at(3000.0, -1200.0)
    assert not at(-1500.0, 0.0) and not at(0.0, 0.0)  # sunward flank and apex lit
    # A cap on blocker distance keeps near shadows and drops far ones.
    capped = cast_shadow(z, dx, dx, az, 10.0, max_distance_m=1e7)
    assert np.array_equal(capped, shadow)
    short = cast_shadow(z, dx, dx, az, 10.0, max_distance_m=500.0)
    assert not short[c - int(round(-5000.0 * toward[1] / dx)), c + int(round(-5000.0 * toward[0] / dx))]


def test_sky_view_of_a_valley_and_a_pinnacle():
    # A straight V valley running north-south, walls rising 1 m per m: from its floor, the horizon
    # toward azimuth a (from the axis) rises at tan h = |sin a|, so the exposure is the mean of
    # 1 / (1 + sin^2 a) over the 16 azimuths; the walls reach past the search radius.
    dx = 25.0
    n = 201
    u = (np.arange(n) - 100) * dx
    z = np.repeat(np.abs(u)[None, :], n, axis=0)
    # Samples interpolate linearly along the walls' planes, so the search finds the exact slope.
    a = 2.0 * np.pi * np.arange(16) / 16
    want = np.mean(1.0 / (1.0 + np.sin(a) ** 2))
    for dy in (dx, 31.0):  # square and oblong posts
        sky = sky_view(z, dx, dy, azimuths=16, radius_m=2000.0)
        assert sky[100, 100] == pytest.approx(want, abs=1e-5)
        assert (sky[:, 100] <= sky[:, 99]).all()  # the floor sees less sky than the wall
    cone = -np.hypot(u[None, :], u[:, None])  # a pinnacle: open sky
    assert sky_view(cone, dx, dx)[100, 100] == 1.0


# --------------------------------------------------------------------------- diffuse, compose, determinism

def test_tiles_tile_and_diffuse_is_a_stencil():
    tiles = class_tiles(size=64, seed=3)
    assert tiles.shape == (N_CLASSES, 64, 64, 3) and tiles.dtype == np.float32
    assert 0.0 <= tiles.min() and tiles.max() <= 1.0
    x = np.linspace(0.0, 8.0, 50)
    assert np.allclose(fractal_noise(x, 0.3, 9, period=8), fractal_noise(x + 8.0, 0.3 + 16.0, 9, period=8),
                       rtol=0.0, atol=1e-12)
    rng_classes = (np.arange(90 * 130).reshape(90, 130) * 7919 % N_CLASSES).astype(np.uint8)
    d = diffuse(rng_classes, tiles)
    i, j = np.meshgrid(np.arange(90), np.arange(130), indexing="ij")
    assert np.array_equal(d, tiles[rng_classes, i % 64, j % 64])
    soft = diffuse(rng_classes, tiles, soft_px=2)
    assert np.array_equal(soft[rng_classes == WATER], d[rng_classes == WATER])
    uniform = np.full((40, 40), FOREST, dtype=np.uint8)
    assert np.allclose(diffuse(uniform, tiles, soft_px=3), diffuse(uniform, tiles), atol=1e-6)


def test_compose():
    rgb = np.full((2, 3, 3), 1.0, dtype=np.float32)
    img = compose(rgb, np.array([[1.0, 0.5, 0.0], [0.25, 1.0, 0.0]], dtype=np.float32))
    assert img.dtype == np.uint8 and img.shape == (2, 3, 3)
    assert img[0, 0].tolist() == [255] * 3 and img[0, 2].tolist() == [0] * 3 and img[0, 1, 0] == 128


def test_synthesize_is_deterministic(hgt_alps):
    h, lat, lon, dx, dy = _sample(hgt_alps, 47.1, 9.3, 47.2, 9.45, 120, 100)
    a = synthesize(h, dx, dy, 140.0, 25.0, lat[:, None], seed=5)
    b = synthesize(h.copy(), dx, dy, 140.0, 25.0, lat[:, None], seed=5)
    for name in ("slope_deg", "classes", "diffuse", "image"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    assert a.light.light.tobytes() == b.light.light.tobytes()
    assert a.light.shadow.tobytes() == b.light.shadow.tobytes()
    assert a.image.dtype == np.uint8 and a.image.shape == (100, 120, 3)
    c = synthesize(h, dx, dy, 140.0, 25.0, lat[:, None], seed=6)
    assert c.diffuse.tobytes() != a.diffuse.tobytes()  # the seed matters


def test_grid_and_spacing():
    lat, lon = grid_latlon(47.0, 9.0, 48.0, 10.0, 4, 5)
    assert lat.tolist() == [47.875, 47.625, 47.375, 47.125]  # north first, pixel centres
    assert lon[0] == pytest.approx(9.1) and lon[-1] == pytest.approx(9.9)
    dx, dy = metre_spacing(47.0, 48.0, 1.0 / 1200, 1.0 / 1200)
    assert dy == pytest.approx(92.7, abs=0.2) and dx == pytest.approx(62.8, abs=0.2)


# --------------------------------------------------------------------------- CLI

def _parser():
    parser = argparse.ArgumentParser(prog="sortie")
    sub = parser.add_subparsers(dest="command", required=True)
    terrain = sub.add_parser("terrain")
    add_texture_parser(terrain.add_subparsers(dest="terrain_command", required=True))
    return parser


def _run(argv):
    args = _parser().parse_args(argv)
    return args.func(args)


def test_cli_end_to_end(tmp_path, hgt_kattegat, capsys):
    argv = ["terrain", "texture", "--dem", str(hgt_kattegat), "--bbox", "57.6", "11.7", "57.7", "11.9",
            "--size", "96x64", "--time", "2026-06-21T12:00:00Z"]
    assert _run(argv + ["-o", str(tmp_path / "a")]) == 0
    assert "96x64 texture" in capsys.readouterr().out
    for name in ("classes.png", "slope.png", "diffuse.png", "lightmap.png", "shadow.png", "composite.png"):
        with Image.open(tmp_path / "a" / name) as im:
            assert im.size == (96, 64), name
            assert im.mode == {"classes.png": "P", "diffuse.png": "RGB", "composite.png": "RGB"}.get(name, "L")
    summary = json.loads((tmp_path / "a" / "texture.json").read_text())
    assert summary["size"] == {"cols": 96, "rows": 64}
    assert sum(summary["class_histogram"].values()) == 96 * 64
    assert summary["class_histogram"]["water"] > 0
    # 12:00 UTC at 11.8 E is 12:47 local mean time: a little under the noon 90 - (57.65 - 23.44) = 55.8.
    assert 50.0 < summary["sun"]["elevation_deg"] < 55.8
    with Image.open(tmp_path / "a" / "classes.png") as im:
        classes = np.asarray(im)
    assert summary["class_histogram"]["water"] == int((classes == WATER).sum())
    # The same command writes the same bytes.
    assert _run(argv + ["-o", str(tmp_path / "b")]) == 0
    for name in summary["files"] + ["texture.json"]:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


@pytest.mark.parametrize("extra, field, text", [
    (["--bbox", "57.7", "11.7", "57.6", "11.9"], "--bbox", "inverted"),
    (["--bbox", "57.6", "11.9", "57.7", "11.7"], "--bbox", "inverted"),
    (["--bbox", "57.6", "11.7", "95", "11.9"], "--bbox", "[-90, 90]"),
    (["--time", "noon"], "--time", "ISO 8601"),
    (["--time", "2026-06-21T12:00:00"], "--time", "zone"),
    (["--size", "5000x4000"], "--size", "16 Mpixel"),
    (["--size", "big"], "--size", "COLSxROWS"),
    (["--spacing-m", "-5"], "--spacing-m", "positive"),
])
def test_cli_rejects_bad_input(tmp_path, hgt_kattegat, extra, field, text):
    base = {"--bbox": ["57.6", "11.7", "57.7", "11.9"], "--time": ["2026-06-21T12:00:00Z"], "--size": ["64x48"]}
    opts = dict(base)
    key = extra[0]
    if key == "--spacing-m":
        del opts["--size"]
    opts[key] = extra[1:]
    argv = ["terrain", "texture", "--dem", str(hgt_kattegat), "-o", str(tmp_path / "out")]
    for k, v in opts.items():
        argv += [k, *v]
    with pytest.raises(InvalidArgument) as err:
        _run(argv)
    assert err.value.field == field
    assert text in str(err.value)
    assert not (tmp_path / "out").exists()


def test_request_limits():
    req = texture_request([47.0, 9.0, 48.0, 10.0], None, None, "2026-06-21T14:00:00+02:00")
    assert req.when == datetime(2026, 6, 21, 12, tzinfo=UTC)
    assert max(req.cols, req.rows) == 1024 and req.cols < req.rows  # square pixels: 1 deg lon is shorter
    assert texture_request([47.0, 9.0, 48.0, 10.0], "4096x4096", None, "2026-06-21T12:00:00Z").cols == 4096
    assert 4096 * 4096 == MAX_PIXELS
    with pytest.raises(InvalidArgument, match="16 Mpixel"):
        texture_request([47.0, 9.0, 48.0, 10.0], None, 1.0, "2026-06-21T12:00:00Z")


def test_cli_texture_of_one_quadtree_cell(tmp_path, hgt_kattegat):
    """--cell: the texture of one quad-tree cell (a store tile's footprint)."""
    from terrain import quadtree

    cell = int(quadtree.cell_at(57.65, 11.8, 9))
    argv = ["terrain", "texture", "--dem", str(hgt_kattegat), "--cell", str(cell), "--size", "64x48",
            "--time", "2026-06-21T12:00:00Z", "-o", str(tmp_path / "c")]
    assert _run(argv) == 0
    box = json.loads((tmp_path / "c" / "texture.json").read_text())["bbox"]
    lat_min, lon_min, lat_max, lon_max = quadtree.bounds(cell)
    assert (box["lat_min"], box["lon_min"], box["lat_max"], box["lon_max"]) == (lat_min, lon_min, lat_max, lon_max)
    with pytest.raises(InvalidArgument) as err:
        _run(argv[:4] + ["--cell", str(-5)] + argv[6:])
    assert err.value.field == "--cell"
    assert str(err.value).count("(got -5)") == 1  # the value named once (it was twice: the quadtree's error inside)
