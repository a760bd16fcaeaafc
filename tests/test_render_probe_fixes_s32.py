"""Acceptance-probe fixes of the entity layer (session 32, precision).

1. A ground vehicle on the terrain could vanish under the drawn ground: fdm.ground puts its
   reference point on the bilinear surface, the terrain layer draws each cell as two flat
   triangles that stand above that surface by up to a quarter of the cell's twist
   (terrain_mesh.cell_corner_weights), and only the eye was lifted onto them (a tank at bilinear
   + 0.5 m in an Alps cell drawn 6.25 m higher: 0 of its 1310 pixels drawn). Entities are now
   lifted onto the drawn surface (entities.ground_lifts, Renderer.drawn_ground_m).
2. A far aircraft's marker, magnified about its reference point, sank its lower part into the
   ground (x 11.5 at 6 km: its bottom 7.2 m under, a third of it hidden). An aircraft is now
   lifted until its lowest point, at its drawn scale and attitude, is on the drawn ground.

Real parts: in-memory rasters as Terrain, EGL (llvmpipe), small frames.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap_layer import clipmap_factory
from client.render.entities import (KIND_AIRCRAFT, KIND_GROUND, KIND_STATIC, EntitySet, apparent_scales,
                                    ground_lifts)
from client.render.profiles import profile
from client.render.renderer import Renderer
from server.dead_reckoning import ned_to_ecef_quat
from terrain.geodesy import enu_basis, geodetic_to_ecef
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

MAGENTA = (255, 0, 255)
SPACING_DEG = 1.0 / 1200.0  # 3 arc-seconds, about 90 m north-south
POSTS = 161  # a 13 km square
LAT0, LON0 = 47.0, 10.0
TWIST_AMPLITUDE_M = 5.0  # posts at 500 +- 5 m in a checkerboard: every cell's twist is +-4 x 5 m
TANK_HEIGHT_M = 2.7  # entities.ground_vehicle_mesh: hull and turret
AIRCRAFT_DEPTH_M = 0.8  # entities.aircraft_mesh: the fuselage's underside below its reference point
SEEN_FRACTION = 0.9  # of an entity's pixels drawn alone that must be drawn over the terrain


def _terrain(heights: np.ndarray) -> Terrain:
    """(POSTS, POSTS) heights MSL, rows northwards from LAT0, as a Terrain."""
    georef = Georef(CRS_GEOGRAPHIC, LON0, LAT0, SPACING_DEG, SPACING_DEG)
    return Terrain([Raster(np.ascontiguousarray(heights, np.float32), georef, name="probe")])


@pytest.fixture(scope="module")
def twisted():
    """A checkerboard of posts: in every cell whose SW and NE corners are high (i + j even) the
    triangles (split SW-NE) stand TWIST_AMPLITUDE_M over the bilinear surface at its centre."""
    i, j = np.indices((POSTS, POSTS))
    return _terrain(500.0 + TWIST_AMPLITUDE_M * np.where((i + j) % 2 == 0, 1.0, -1.0))


@pytest.fixture(scope="module")
def flat():
    return _terrain(np.full((POSTS, POSTS), 500.0))


def _level(kind: int, lat: float, lon: float, h: float, heading_deg: float = 0.0) -> EntitySet:
    """One level entity at (lat, lon, h ellipsoid), heading heading_deg."""
    half = math.radians(heading_deg) / 2.0
    quat = ned_to_ecef_quat(np.array([math.cos(half), 0.0, 0.0, math.sin(half)]), lat, lon)
    return EntitySet(np.array([1]), np.array([kind]), geodetic_to_ecef(lat, lon, h).reshape(1, 3),
                     np.asarray(quat).reshape(1, 4), ("red",))


def _pixels(terrain, camera: Camera, entities: EntitySet, width: int, height: int, factory=None):
    """(pixels of the entity drawn over the terrain, drawn alone, the renderer's lifts m)."""
    with Renderer(terrain, width, height, flat_sky_rgb=MAGENTA, terrain_layer_factory=factory) as r:
        with_entity = r.render(camera, entities)
        lifts = r.entity_layer.lifts_m.copy()
        without = r.render(camera)
    with Renderer(None, width, height, flat_sky_rgb=MAGENTA, sea=False) as r:
        alone = r.render(camera, entities)
    drawn = int((np.abs(with_entity.astype(int) - without.astype(int)).sum(-1) > 0).sum())
    return drawn, int((np.abs(alone.astype(int) - np.array(MAGENTA)).sum(-1) > 0).sum()), lifts


# -- 1. ground vehicles on the drawn triangles ----------------------------------------------------

@pytest.mark.parametrize("layer", ["mesh", "fast_jet"])
def test_a_tank_on_the_bilinear_surface_is_drawn_over_triangles_above_it(twisted, layer):
    # Cell (80, 80): SW and NE high, its centre drawn TWIST_AMPLITUDE_M over the bilinear 500 m.
    lat, lon = LAT0 + 80.5 * SPACING_DEG, LON0 + 80.5 * SPACING_DEG
    bilinear = float(twisted.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
    assert bilinear == pytest.approx(500.0, abs=1e-3)
    tank = _level(KIND_GROUND, lat, lon, bilinear + 0.5)  # under the drawn surface, turret top above it
    e, n, u = enu_basis(lat, lon)
    eye = tank.positions_ecef[0] - 60.0 * n + 25.0 * u
    camera = Camera.look_at(eye, tank.positions_ecef[0], fov_x_deg=30.0)
    factory = None if layer == "mesh" else clipmap_factory(twisted, **profile(layer).layer_args())
    drawn, alone, lifts = _pixels(twisted, camera, tank, 200, 150, factory)
    # Old code: the whole tank under the triangles seen from 25 m up, none of it drawn (0 of 508).
    assert alone > 300
    assert drawn >= SEEN_FRACTION * alone, (drawn, alone)
    # Lifted by what the drawn surface stands over its reference point: 5 - 0.5 m at the centre.
    assert lifts[0] == pytest.approx(TWIST_AMPLITUDE_M - 0.5, abs=0.05)


def test_entities_over_the_drawn_ground_are_not_moved(twisted):
    # Cell (80, 81): SW and NE low, the triangles 5 m under the bilinear surface at its centre.
    lat, lon = LAT0 + 80.5 * SPACING_DEG, LON0 + 81.5 * SPACING_DEG
    site = _level(KIND_STATIC, lat, lon, 500.0 + 0.1)
    e, n, u = enu_basis(lat, lon)
    camera = Camera.look_at(site.positions_ecef[0] - 80.0 * n + 30.0 * u, site.positions_ecef[0], fov_x_deg=40.0)
    with Renderer(twisted, 64, 48, flat_sky_rgb=MAGENTA) as r:
        r.render(camera, site)
        assert r.entity_layer.lifts_m.tolist() == [0.0]


def test_many_ground_entities_are_lifted_onto_the_drawn_surface_in_one_pass(twisted):
    # 400 vehicles at bilinear + 0.5 m across 20 x 20 cell centres: each lifted by exactly what the
    # layer draws over it (5 - 0.5 m where the cell's twist is positive, else not at all).
    rows, cols = np.meshgrid(np.arange(70, 90), np.arange(70, 90), indexing="ij")
    lat, lon = LAT0 + (rows.ravel() + 0.5) * SPACING_DEG, LON0 + (cols.ravel() + 0.5) * SPACING_DEG
    n = lat.size
    quats = ned_to_ecef_quat(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), lat, lon)
    tanks = EntitySet(np.arange(n), np.full(n, KIND_GROUND), geodetic_to_ecef(lat, lon, np.full(n, 500.5)),
                      quats, ("blue",) * n)
    camera = Camera.from_geodetic(LAT0 + 60 * SPACING_DEG, LON0 + 80 * SPACING_DEG, 2000.0, 0.0, -30.0)
    with Renderer(twisted, 64, 48, flat_sky_rgb=MAGENTA) as r:
        r.render(camera, tanks)
        lifts = r.entity_layer.lifts_m
    want = np.where((rows.ravel() + cols.ravel()) % 2 == 0, TWIST_AMPLITUDE_M - 0.5, 0.0)
    np.testing.assert_allclose(lifts, want, atol=0.05)


# -- 2. far aircraft markers stay on the ground ---------------------------------------------------

def test_a_far_aircraft_marker_is_lifted_so_its_underside_stays_on_the_ground(flat):
    # A parked jet, its reference point 2 m over flat ground, 2 km away in a 320-pixel, 60 degree
    # view: drawn 10.5 times its size, its underside 6.4 m under the ground about its reference point.
    lat, lon = LAT0 + 80 * SPACING_DEG, LON0 + 80 * SPACING_DEG
    jet = _level(KIND_AIRCRAFT, lat, lon, 502.0, heading_deg=90.0)
    e, n, u = enu_basis(lat, lon)
    camera = Camera.look_at(jet.positions_ecef[0] - 2000.0 * n + 20.0 * u, jet.positions_ecef[0], fov_x_deg=60.0)
    scale = float(apparent_scales(jet, np.array([15.0]), camera.position_ecef, camera.pixel_footprint_rad(320))[0])
    assert scale > 10.0
    drawn, alone, lifts = _pixels(flat, camera, jet, 320, 180)
    # Old code: two thirds of its pixels drawn (41 of 62; the lower part under the ground).
    assert drawn >= SEEN_FRACTION * alone, (drawn, alone)
    assert lifts[0] == pytest.approx(scale * AIRCRAFT_DEPTH_M - 2.0, abs=1e-3)


def test_a_near_aircraft_clear_of_the_ground_is_not_moved(flat):
    lat, lon = LAT0 + 80 * SPACING_DEG, LON0 + 80 * SPACING_DEG
    jet = _level(KIND_AIRCRAFT, lat, lon, 502.0, heading_deg=90.0)
    e, n, u = enu_basis(lat, lon)
    # 30 m away in a 64-pixel view: drawn true to scale (24 px x 16 mrad x 30 m < 15 m), its
    # underside 1.2 m over the ground.
    camera = Camera.look_at(jet.positions_ecef[0] - 30.0 * n + 10.0 * u, jet.positions_ecef[0], fov_x_deg=60.0)
    assert apparent_scales(jet, np.array([15.0]), camera.position_ecef, camera.pixel_footprint_rad(64))[0] == 1.0
    with Renderer(flat, 64, 48, flat_sky_rgb=MAGENTA) as r:
        r.render(camera, jet)
        assert r.entity_layer.lifts_m.tolist() == [0.0]


def test_ground_lifts_by_kind():
    kinds = np.array([KIND_GROUND, KIND_STATIC, KIND_AIRCRAFT, KIND_AIRCRAFT, KIND_GROUND, KIND_AIRCRAFT])
    heights = np.array([100.0, 100.0, 102.0, 102.0, 100.0, 5000.0])
    depths = np.array([0.0, 0.0, 0.8, 0.8, 0.0, 0.8])
    scales = np.array([5.0, 5.0, 1.0, 11.5, 1.0, 30.0])
    ground = np.array([103.0, 99.0, 100.0, 100.0, np.nan, 100.0])
    # Ground and statics onto the ground at their reference point whatever their scale; aircraft
    # by their lowest point, scale x depth under it; nothing where no ground is drawn or it clears.
    np.testing.assert_allclose(ground_lifts(kinds, heights, depths, scales, ground),
                               [3.0, 0.0, 0.0, 11.5 * 0.8 - 2.0, 0.0, 0.0], atol=1e-12)
