"""Segments follow the measured-over-filled rule of heights: over a cell one DEM has only as a filled
void (a guess) and a later DEM measures, a ray meets the later DEM's surface, as Terrain.heights
answers there; a synthetic source (the procedural world) never replaces a fill. Oracles are
Terrain.heights along the segment (tests/test_terrain_fixes_stack_rays.py's), never the trace."""

from __future__ import annotations

import numpy as np
import pytest

from terrain.los import trace_segments
from terrain.procedural import ProceduralTerrain
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, Georef, Raster
from terrain.terrain import Terrain
from tests.test_terrain_fixes_stack_rays import (WALL_DISTANCE_M, _assert_symmetric_and_consistent,
                                                 _check_first_contact, _ecef, _segments_across)

D1 = 1.0 / 1200.0  # 3" posts
D2 = 1.0 / 900.0  # 4" posts: not aligned with the first DEM's
N = 61


def _first(level=500.0, noise=0.0, seed=5):
    """A 3" DEM at about ``level`` m whose posts 20..29 x 20..29 are a filled void at that level."""
    rng = np.random.default_rng(seed)
    h = level + rng.normal(0.0, noise, (N, N)) if noise else np.full((N, N), level)
    filled = np.zeros((N, N), bool)
    filled[20:30, 20:30] = True
    h[filled] = level
    return Raster(h.astype(np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D1, D1), name="first", filled=filled)


def _plateau(level=800.0):
    """A 3" DEM over all of the first at ``level`` m: it measures ground where the first has a fill."""
    return Raster(np.full((N, N), level, np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D1, D1), name="plateau")


def _across_the_void(h_m=650.0):
    """A chord along post row 25 (through the void) from column 5 to column 55, ends h_m high."""
    lat = 47.0 + 25 * D1
    return ([lat], [9.0 + 5 * D1], [h_m]), ([lat], [9.0 + 55 * D1], [h_m])


def test_a_ray_over_a_filled_void_meets_the_dem_that_measured_it():
    """Over the fill (500 m) a later DEM measured a plateau (800 m): a chord at 650 m meets the
    plateau's wall where the first DEM's filled cells begin (cell 19 holds post 20), from either
    end, and cannot see across; before, it passed over the fill and saw."""
    t = Terrain([_first(), _plateau()])
    a, b = _across_the_void()
    for start, end, edge_col in ((a, b, 19), (b, a, 30)):
        res = t.intersect(*start, *end)
        assert res.hit[0] and res.status[0] == STATUS_OK
        wall = np.linalg.norm(_ecef([start[0][0]], [9.0 + edge_col * D1], [650.0])
                              - _ecef(start[0], start[1], start[2]))
        assert abs(res.distance_m[0] - wall) < 0.05  # the chord's sag off 650 m moves the wall's foot ~0 m
        _check_first_contact(t, start, end, res, 0)
    assert not t.line_of_sight(*a, *b).visible[0]
    # The first DEM alone passes over the fill (its heights say the same).
    one = Terrain([_first()])
    assert not one.intersect(*a, *b).hit[0] and one.line_of_sight(*a, *b).visible[0]


def test_the_distance_to_the_wall_is_exact():
    """The contact on the wall lies where the chord crosses the meridian plane of the filled cells'
    first column, to the stack's wall tolerance (the chord is not at constant height: compare with
    the chord's own point there)."""
    t = Terrain([_first(), _plateau()])
    a, b = _across_the_void()
    res = t.intersect(*a, *b)
    pa, pb = _ecef(*a)[0], _ecef(*b)[0]
    lon_wall = np.radians(9.0 + 19 * D1)
    n = np.array([-np.sin(lon_wall), np.cos(lon_wall), 0.0])  # the meridian plane's normal
    s = -(pa @ n) / ((pb - pa) @ n)
    assert abs(res.distance_m[0] - s * np.linalg.norm(pb - pa)) < WALL_DISTANCE_M


def test_a_fill_is_kept_where_no_measured_source_has_the_ground():
    """Over the procedural world alone a fill stays the surface (status FILLED), as heights keep it:
    the same contact as the first DEM's own trace, bit for bit."""
    first = _first(level=500.0)
    t = Terrain([first, ProceduralTerrain(seed=3)])
    lat = 47.0 + 25 * D1
    a, b = ([lat], [9.0 + 5 * D1], [540.0]), ([lat], [9.0 + 25 * D1], [490.0])  # meets the fill at column 21
    res = t.intersect(*a, *b)
    pa, pb = _ecef(*a), _ecef(*b)
    s, _, _, st = trace_segments(first, pa, pb, np.zeros(1), np.ones(1))
    assert res.hit[0] and res.status[0] == STATUS_FILLED and st[0] == STATUS_FILLED
    assert res.distance_m[0] == s[0] * np.linalg.norm(pb - pa, axis=1)[0]
    assert 20 * D1 < res.lon_deg[0] - 9.0 < 22 * D1
    assert t.heights([res.lat_deg[0]], [res.lon_deg[0]]).status[0] == STATUS_FILLED


def test_a_measured_dem_behind_the_procedural_world_still_replaces_a_fill():
    """Sources [DEM with a fill, procedural, DEM measuring the ground]: heights take the third for
    the filled points, and so do rays; the procedural world between them answers nothing here."""
    t = Terrain([_first(), ProceduralTerrain(seed=3), _plateau()])
    a, b = _across_the_void()
    res = t.intersect(*a, *b)
    assert res.hit[0] and res.status[0] == STATUS_OK
    _check_first_contact(t, a, b, res, 0)
    lat, lon = [47.0 + 25 * D1], [9.0 + 25 * D1]
    assert t.heights(lat, lon).height_msl_m[0] == 800.0


@pytest.fixture(scope="module")
def rough_stack():
    """A rough 3" DEM with a filled void and a rough 4" DEM over all of it but its western columns
    (from 24): the void's west part keeps the fill, its east part is the second DEM's ground."""
    rng = np.random.default_rng(7)
    rr, cc = np.mgrid[0:N, 0:N]
    h1 = 500.0 + 3.0 * rr + 1.0 * cc + rng.normal(0.0, 2.0, (N, N))
    filled = np.zeros((N, N), bool)
    filled[20:30, 20:30] = True
    h1[filled] = 530.0 + 0.5 * cc[filled]
    first = Raster(h1.astype(np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D1, D1), name="first", filled=filled)
    m = 31
    rr, cc = np.mgrid[0:m, 0:m]
    h2 = 600.0 - 2.0 * rr + 5.0 * cc + rng.normal(0.0, 2.0, (m, m))
    second = Raster(h2.astype(np.float32), Georef(CRS_GEOGRAPHIC, 9.0 + 24 * D1, 47.0 + 10 * D1, D2, D2),
                    name="second")
    return Terrain([first, second])


@pytest.mark.parametrize("seed", range(4))
def test_random_segments_over_a_partly_measured_void(rough_stack, seed):
    """Segments around and over the void, ends 2-150 m above the stack's surface: every first
    contact is on the stack's surface (or a wall where it steps) with no sample before it below,
    both ways agree, line of sight is symmetric and consistent with intersect."""
    rng = np.random.default_rng(seed)
    box = (47.0 + 12 * D1, 9.0 + 12 * D1, 47.0 + 38 * D1, 9.0 + 38 * D1)
    a, b = _segments_across(rough_stack, rng, 150, (box[0], box[2]), (box[1], box[3]), 20 * D1, within=box)
    fwd, _, _ = _assert_symmetric_and_consistent(rough_stack, a, b, gaps=False)
    for k in range(fwd.hit.size):
        _check_first_contact(rough_stack, a, b, fwd, k)
    assert fwd.hit.any() and not fwd.hit.all()
