"""Segments over a stack of sources meet the stack's surface: at every point the first source covering
it, as heights answer. intersect(a, b) and intersect(b, a) agree on whether they hit wherever the
segment crosses from one source onto another (a DEM's edge over the procedural world, a fine DEM over a
coarse one, across the antimeridian); line of sight stays symmetric and consistent with intersect,
also where part of a segment lies over no source at all.

Oracles never use the composite trace: surfaces come from Terrain.heights, ray points from
terrain.geodesy, the DEM edge crossing from the plane of a meridian."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef
from terrain.los import ENDPOINT_TOLERANCE_M, MODEL_ERROR_M, intersect_segments, line_of_sight
from terrain.procedural import ProceduralTerrain
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, STATUS_OUTSIDE, Georef, Raster
from terrain.terrain import Terrain

# A hit is on the surface of the source covering its point to within the track model's error times
# the slope (< 5 here) plus rounding; 1 mm is a wide margin (as tests/test_los.py).
ON_SURFACE_M = 1.0e-3
# Where a segment passes onto a source whose surface is above it, the contact is the step between the
# two surfaces (a wall) at the edge: its distance is exact to the track model's error, the nudge of
# the stretch's start (1e-9 m, doubled at most a few times) and rounding.
WALL_DISTANCE_M = 1.0e-5
# Dense samples before the first contact are above the surface to within the model's error times
# the slope.
BEFORE_HIT_M = 5.0e-5
SAMPLE_M = 2.0


def _rough(lat0, lon0, n, d, base, seed, amp=80.0):
    """A smooth random surface (sums of sines) of n x n posts d degrees apart."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:n, 0:n] * d
    h = np.full((n, n), base)
    for _ in range(6):
        k = rng.uniform(20.0, 300.0, 2)
        h += amp / 6 * np.sin(k[0] * rr + rng.uniform(0, 6)) * np.cos(k[1] * cc + rng.uniform(0, 6))
    return Raster(h.astype(np.float32), Georef(CRS_GEOGRAPHIC, lon0, lat0, d, d), name=f"rough{seed}")


@pytest.fixture(scope="module")
def fine_over_coarse():
    """A 1" DEM (0.1 degree, its surface some 60 m above the other's) over a 3" one (0.2 degree)."""
    fine = _rough(47.05, 9.05, 361, 1.0 / 3600.0, 560.0, 1)
    coarse = _rough(47.0, 9.0, 241, 1.0 / 1200.0, 500.0, 2)
    return Terrain([fine, coarse])


@pytest.fixture(scope="module")
def alps_over_procedural(hgt_alps):
    from terrain.dem import read_dem

    return Terrain([read_dem(hgt_alps), ProceduralTerrain(seed=3)])


def _ecef(lat, lon, h):
    return geodetic_to_ecef(np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float))


def _check_first_contact(t: Terrain, a, b, res, k):
    """Ray k's contact (if any) lies on the stack's surface, or on a wall where the stack's surface
    steps; no dense sample of the segment before it is below the stack's surface."""
    pa, pb = _ecef(a[0][k], a[1][k], a[2][k]), _ecef(b[0][k], b[1][k], b[2][k])
    length = float(np.linalg.norm(pb - pa))
    end = res.distance_m[k] if res.hit[k] else length
    s = np.arange(0.0, end, SAMPLE_M) / length
    if s.size:
        lat, lon, h = ecef_to_geodetic(pa + s[:, None] * (pb - pa))
        ground = t.heights(lat, lon).height_msl_m
        assert np.nanmin(h - ground) >= -BEFORE_HIT_M, k
    if res.hit[k]:
        on = t.heights([res.lat_deg[k]], [res.lon_deg[k]]).height_msl_m[0]
        if abs(res.height_msl_m[k] - on) >= ON_SURFACE_M:  # then a wall: just past it, the ray is underground
            s_past = (res.distance_m[k] + 1e-3) / length
            lat, lon, h = ecef_to_geodetic((pa + s_past * (pb - pa))[None])
            assert h[0] < t.heights(lat, lon).height_msl_m[0], k


# Dense samples 2 m apart on a bilinear surface of 90 m posts miss at most a few centimetres of it
# between them; clearances within half a metre of zero are left undecided.
DENSE_MARGIN_M = 0.5


def _interior_clearance(t: Terrain, a, b, k) -> float:
    """Ray k's least height above the stack's surface, over dense samples of the segment between
    ENDPOINT_TOLERANCE_M from either end (negative: below it somewhere)."""
    pa, pb = _ecef(a[0][k], a[1][k], a[2][k]), _ecef(b[0][k], b[1][k], b[2][k])
    length = float(np.linalg.norm(pb - pa))
    d = np.append(np.arange(ENDPOINT_TOLERANCE_M, length - ENDPOINT_TOLERANCE_M, SAMPLE_M),
                  length - ENDPOINT_TOLERANCE_M)
    lat, lon, h = ecef_to_geodetic(pa + (d / length)[:, None] * (pb - pa))
    return float(np.nanmin(h - t.heights(lat, lon).height_msl_m))


def _assert_symmetric_and_consistent(t: Terrain, a, b, gaps: bool):
    """intersect both ways, line of sight both ways, and the relations between them."""
    fwd = t.intersect(*a, *b)
    back = t.intersect(*b, *a)
    ab = t.line_of_sight(*a, *b)
    ba = t.line_of_sight(*b, *a)
    np.testing.assert_array_equal(ab.visible, ba.visible)
    np.testing.assert_array_equal(ab.status, ba.status)
    length = np.linalg.norm(_ecef(*b) - _ecef(*a), axis=1)

    def inner(r):  # a contact strictly between the ends, as line of sight counts them
        return r.hit & (r.distance_m > ENDPOINT_TOLERANCE_M) & (r.distance_m < length - ENDPOINT_TOLERANCE_M)

    def at_end(r):  # a first contact at an end hides from that side whatever comes after it
        return r.hit & ~inner(r)

    if not gaps:  # the stack covers every segment: both ways meet the same surface
        np.testing.assert_array_equal(fwd.hit, back.hit)
        assert (fwd.status != STATUS_OUTSIDE).all() and (ab.status != STATUS_OUTSIDE).all()
        # Blocked where either way's first contact lies strictly between the ends. Where both
        # ways' first contacts are at the ends (within ENDPOINT_TOLERANCE_M), intersect cannot
        # tell: a chord along lat 48.0 from the foot of the 456 m cliff where the Alps tile ends
        # under the procedural world runs into the cliff at once, and either comes out again
        # further on (9.125 -> 9.5 E) or stays in it to the other end's cliff (9.125 -> 9.625 E:
        # both first contacts at 0 m, blocked in between). Those are judged by dense samples.
        settled = ~(at_end(fwd) & at_end(back))
        np.testing.assert_array_equal(~ab.visible[settled], (inner(fwd) | inner(back))[settled])
        for k in np.flatnonzero(~settled):
            clearance = _interior_clearance(t, a, b, k)
            if abs(clearance) > DENSE_MARGIN_M:
                assert ab.visible[k] == (clearance > 0.0), (k, clearance)
    else:  # from either end up to the first stretch no source covers
        np.testing.assert_array_equal(~ab.visible & (ab.status != STATUS_OUTSIDE), inner(fwd) | inner(back))
        nothing = ~fwd.hit & ~back.hit & (fwd.status == STATUS_OUTSIDE)
        np.testing.assert_array_equal(ab.status == STATUS_OUTSIDE, nothing)
    return fwd, back, ab


def _segments_across(t, rng, n, lat_rng, lon_rng, reach_deg, up_m=(2.0, 150.0), within=None):
    """n segments from random points of a box to random points within reach_deg (and the box
    ``within``, (lat_min, lon_min, lat_max, lon_max), if given), both ends up_m above the stack's
    surface (points over no source: above 0 m)."""
    lat_a, lon_a = rng.uniform(*lat_rng, n), rng.uniform(*lon_rng, n)
    lat_b = lat_a + rng.uniform(-reach_deg, reach_deg, n)
    lon_b = lon_a + rng.uniform(-reach_deg, reach_deg, n) / math.cos(math.radians(lat_a.mean()))
    if within is not None:
        lat_b, lon_b = np.clip(lat_b, within[0], within[2]), np.clip(lon_b, within[1], within[3])
    ga = np.nan_to_num(t.heights(lat_a, lon_a).height_msl_m)
    gb = np.nan_to_num(t.heights(lat_b, lon_b).height_msl_m)
    return (lat_a, lon_a, ga + rng.uniform(*up_m, n)), (lat_b, lon_b, gb + rng.uniform(*up_m, n))


# ---------------------------------------------------------------------------------- closed form

def test_a_segment_onto_a_higher_source_hits_its_edge_either_way():
    """A flat DEM at 500 m (priority) over a flat world at 0 m. A horizontal-ish chord at 300 m from
    west of the DEM to east of it passes under its surface: coming from either side, the first
    contact is the DEM's edge on that side (the meridian plane of its first or last column), not
    nothing; at 600 m it clears both ways. The old code traced a segment that starts off the first
    source on the next source alone, and missed the DEM."""
    dem = Raster(np.full((61, 61), 500.0, np.float32), Georef(CRS_GEOGRAPHIC, 9.5, 47.5, 1 / 600, 1 / 600))
    world = Raster(np.zeros((121, 241), np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1 / 100, 1 / 100))
    t = Terrain([dem, world])
    lat = 47.55
    a, b = ([lat], [9.45], [300.0]), ([lat], [9.65], [300.0])
    pa, pb = _ecef(*a), _ecef(*b)
    for p, q, edge_lon in ((pa, pb, 9.5), (pb, pa, 9.6)):
        normal = np.array([-math.sin(math.radians(edge_lon)), math.cos(math.radians(edge_lon)), 0.0])
        s_edge = -(normal @ p[0]) / (normal @ (q[0] - p[0]))
        lat_p, lon_p, h_p = ecef_to_geodetic(p)
        lat_q, lon_q, h_q = ecef_to_geodetic(q)
        res = t.intersect(lat_p, lon_p, h_p, lat_q, lon_q, h_q)
        assert res.hit[0] and res.status[0] == STATUS_OK
        assert abs(res.distance_m[0] - s_edge * np.linalg.norm(q - p)) < WALL_DISTANCE_M
        assert abs(res.lon_deg[0] - edge_lon) < 1e-9 and 250.0 < res.height_msl_m[0] < 500.0
    assert not t.line_of_sight(*a, *b).visible[0]
    over = ([lat], [9.45], [600.0]), ([lat], [9.65], [600.0])
    for p, q in (over, over[::-1]):
        res = t.intersect(*p, *q)
        assert not res.hit[0] and res.status[0] == STATUS_OK
        assert t.line_of_sight(*p, *q).visible[0]


def test_one_source_and_segments_that_stay_on_the_first_are_answered_as_before(hgt_alps):
    """The first source traces every segment; only those that leave it meet the stack: answers of
    a one-DEM terrain are terrain.los's own, bit for bit, and so are those of a DEM over the
    procedural world for segments inside the DEM."""
    from terrain.dem import read_dem

    alps = read_dem(hgt_alps)
    rng = np.random.default_rng(7)
    a, b = _segments_across(Terrain([alps]), rng, 300, (47.2, 47.8), (9.2, 9.8), 0.1)
    want = intersect_segments(alps, *a, *b)
    for t in (Terrain([alps]), Terrain([alps, ProceduralTerrain(seed=3)])):
        got = t.intersect(*a, *b)
        for g, w in zip((got.hit, got.distance_m, got.lat_deg, got.lon_deg, got.height_msl_m, got.normal_enu,
                         got.status), want):
            np.testing.assert_array_equal(g, w)
        los = t.line_of_sight(*a, *b)
        ref = line_of_sight(alps, *a, *b)
        np.testing.assert_array_equal(los.visible, ref[0])
        np.testing.assert_array_equal(los.status, ref[1])
    assert want[0].any() and (~want[0]).any()


# ---------------------------------------------------------------------------------- batches

def test_fine_dem_over_a_coarse_one(fine_over_coarse):
    """Segments inside, outside and across the fine DEM's edge: both ways hit or both miss, every
    contact is on the stack's surface or its wall, no sample before it is underground; line of
    sight agrees with intersect."""
    t = fine_over_coarse
    a, b = _segments_across(t, np.random.default_rng(11), 400, (47.03, 47.17), (9.03, 9.17), 0.06,
                            within=(47.01, 9.01, 47.19, 9.19))
    fwd, back, _ = _assert_symmetric_and_consistent(t, a, b, gaps=False)
    assert 50 < fwd.hit.sum() < 350
    for res, p, q in ((fwd, a, b), (back, b, a)):
        for k in range(0, 400, 4):
            _check_first_contact(t, p, q, res, k)


def test_dem_edge_over_the_procedural_world(alps_over_procedural):
    """Segments across the Alps tile's north and east edges (47-48 N, 9-10 E) over the procedural
    world."""
    t = alps_over_procedural
    rng = np.random.default_rng(12)
    north = _segments_across(t, rng, 200, (47.95, 48.05), (9.2, 9.8), 0.08)
    east = _segments_across(t, rng, 200, (47.2, 47.8), (9.95, 10.05), 0.08)
    for a, b in (north, east):
        fwd, back, _ = _assert_symmetric_and_consistent(t, a, b, gaps=False)
        assert fwd.hit.any() and (~fwd.hit).any()
        for k in range(0, 200, 5):
            _check_first_contact(t, a, b, fwd, k)
            _check_first_contact(t, b, a, back, k)


def test_dem_edge_over_no_source(hgt_alps):
    """The Alps tile alone: a segment's stretch beyond its edge is covered by nothing. intersect
    stops there (OUTSIDE) unless it hit first; line of sight is blocked when a contact is found
    from either end before that stretch, OUTSIDE when none is, and symmetric."""
    from terrain.dem import read_dem

    t = Terrain([read_dem(hgt_alps)])
    a, b = _segments_across(t, np.random.default_rng(13), 400, (47.95, 48.05), (9.2, 9.8), 0.08)
    fwd, back, ab = _assert_symmetric_and_consistent(t, a, b, gaps=True)
    assert (ab.status == STATUS_OUTSIDE).any() and (~ab.visible & (ab.status == STATUS_OK)).any()


def test_across_the_antimeridian_onto_the_procedural_world():
    """A DEM straddling 180 E (179.5 .. 180.5) over the procedural world: segments across its
    edges and across the antimeridian inside it."""
    dem = _rough(47.0, 179.5, 121, 1 / 120, 300.0, 3, amp=200.0)
    t = Terrain([dem, ProceduralTerrain(seed=5)])
    rng = np.random.default_rng(14)
    a, b = _segments_across(t, rng, 300, (47.1, 47.9), (179.3, 180.7), 0.1)
    a = (a[0], (a[1] + 180.0) % 360.0 - 180.0, a[2])
    b = (b[0], (b[1] + 180.0) % 360.0 - 180.0, b[2])
    assert (np.sign(a[1]) != np.sign(b[1])).sum() > 10
    fwd, back, _ = _assert_symmetric_and_consistent(t, a, b, gaps=False)
    assert fwd.hit.any() and (~fwd.hit).any()
    for k in range(0, 300, 6):
        _check_first_contact(t, a, b, fwd, k)


def test_holes_in_the_first_source_and_a_web_mercator_dem(tif_grand_canyon):
    """The fine DEM with a hole (NaN posts: a DEM clipped around a lake) over the coarse one: the
    coarse surface answers in the hole, for segments as for heights. And a Web Mercator GeoTIFF
    (its rows nonlinear in latitude) over the procedural world, segments across its edges."""
    from terrain.dem import read_dem

    fine = _rough(47.05, 9.05, 361, 1.0 / 3600.0, 560.0, 1)
    h = np.array(fine.heights)
    h[120:240, 150:200] = np.nan
    holed = Terrain([Raster(h, fine.georef, name="holed"), _rough(47.0, 9.0, 241, 1.0 / 1200.0, 500.0, 2)])
    a, b = _segments_across(holed, np.random.default_rng(15), 300, (47.07, 47.13), (9.07, 9.13), 0.04,
                            within=(47.01, 9.01, 47.19, 9.19))
    fwd, back, _ = _assert_symmetric_and_consistent(holed, a, b, gaps=False)
    for k in range(0, 300, 5):
        _check_first_contact(holed, a, b, fwd, k)
    canyon = read_dem(tif_grand_canyon)
    t = Terrain([canyon, ProceduralTerrain(seed=6)])
    lat0, lon0, lat1, lon1 = canyon.bounds
    a, b = _segments_across(t, np.random.default_rng(16), 200, (lat0 - 0.02, lat0 + 0.02), (lon0 + 0.05, lon1 - 0.05),
                            0.05, up_m=(2.0, 400.0))
    fwd, back, _ = _assert_symmetric_and_consistent(t, a, b, gaps=False)
    assert fwd.hit.any() and (~fwd.hit).any()
    for k in range(0, 200, 5):
        _check_first_contact(t, a, b, fwd, k)


# ---------------------------------------------------------------------------------- hypothesis

_END = st.tuples(st.floats(47.90, 48.10), st.floats(9.05, 9.95), st.floats(2.0, 300.0))


@settings(max_examples=60, deadline=None)
@given(a=_END, b=_END)
@example(a=(48.0, 9.125, 2.0), b=(48.0, 9.5, 2.0))  # found by clean-clone CI runs (above)
@example(a=(48.0, 9.125, 2.0), b=(48.0, 9.625, 2.0))
def test_edge_over_procedural_symmetric(alps_over_procedural, a, b):
    """Both ends anywhere near the Alps tile's north edge (either side of it), above the stack."""
    t = alps_over_procedural
    ground = t.heights([a[0], b[0]], [a[1], b[1]]).height_msl_m
    pa, pb = ([a[0]], [a[1]], [ground[0] + a[2]]), ([b[0]], [b[1]], [ground[1] + b[2]])
    fwd, back, _ = _assert_symmetric_and_consistent(t, pa, pb, gaps=False)
    _check_first_contact(t, pa, pb, fwd, 0)
    _check_first_contact(t, pb, pa, back, 0)


@settings(max_examples=60, deadline=None)
@given(a=_END, b=_END)
def test_edge_over_nothing_consistent(hgt_alps, a, b):
    """The same ends over the Alps tile alone (nothing beyond 48 N)."""
    from terrain.dem import read_dem

    t = _alone(hgt_alps, read_dem)
    ground = np.nan_to_num(t.heights([a[0], b[0]], [a[1], b[1]]).height_msl_m)
    pa, pb = ([a[0]], [a[1]], [ground[0] + a[2]]), ([b[0]], [b[1]], [ground[1] + b[2]])
    _assert_symmetric_and_consistent(t, pa, pb, gaps=True)


_ALONE = {}


def _alone(path, read):
    if path not in _ALONE:
        _ALONE[path] = Terrain([read(path)])
    return _ALONE[path]


def test_model_error_bound_is_what_the_wall_tolerance_assumes():
    assert MODEL_ERROR_M <= 1.0e-6 < WALL_DISTANCE_M


# ---------------------------------------------------------------------------------- acceptance probe fixes

def _flat_or_rough(lat0, lon0, n, d, base, seed, rough):
    if rough:
        return _rough(lat0, lon0, n, d, base, seed)
    return Raster(np.full((n, n), base, np.float32), Georef(CRS_GEOGRAPHIC, lon0, lat0, d, d), name=f"flat{seed}")


@pytest.mark.parametrize("rough", [False, True])
def test_two_dems_meeting_over_a_third_source_leave_no_sliver(rough):
    """Tiles A (9.0-9.5 E, 500 m) and B (9.5-10.0 E, 700 m) over the procedural world, whose surface
    at the seam is above this ray: the two tiles' coverage ends come from two track models and
    differed by ~1e-10 m, and that nanometre of procedural surface between them was a "wall" 362 m
    above the stack's surface (b -> a hit, a -> b missed), or blocked line of sight (flat tiles).
    The ray is > 100 m above the stack's surface everywhere: no contact, either way."""
    d = 1 / 1200
    t = Terrain([_flat_or_rough(47.0, 9.0, 601, d, 500.0, 1, rough), _flat_or_rough(47.0, 9.5, 601, d, 700.0, 2, rough),
                 ProceduralTerrain(seed=3)])
    a = ([47.08005108815477], [9.464564220974992], [786.3540593428844])
    b = ([47.060288417121654], [9.518221304950789], [904.7765147286078])
    pa, pb = _ecef(*a), _ecef(*b)
    s = np.linspace(0.0, 1.0, 4001)
    lat, lon, h = ecef_to_geodetic(pa + s[:, None] * (pb - pa))
    assert (h - t.heights(lat, lon).height_msl_m).min() > 50.0  # the oracle: well clear of the stack
    for p, q in ((a, b), (b, a)):
        res = t.intersect(*p, *q)
        assert not res.hit[0] and res.status[0] == STATUS_OK
        assert t.line_of_sight(*p, *q).visible[0]


def _seam_batches():
    d = 1 / 1200
    A, B = _rough(47.0, 9.0, 601, d, 500.0, 1), _rough(47.0, 9.5, 601, d, 700.0, 2)
    E, W = _rough(-17.0, 179.5, 601, d, 300.0, 4, amp=200.0), _rough(-17.0, -180.0, 601, d, 600.0, 5, amp=200.0)
    P = ProceduralTerrain(seed=3)
    return {"seam_proc": (Terrain([A, B, P]), (47.05, 47.45), (9.4, 9.6)),
            "anti_proc": (Terrain([E, W, P]), (-16.9, -16.6), (179.7, 180.3)),
            "anti_W_first_proc": (Terrain([W, E, P]), (-16.9, -16.6), (179.7, 180.3))}


@pytest.mark.parametrize("case", ["seam_proc", "anti_proc", "anti_W_first_proc"])
def test_seams_over_a_third_source_random(case):
    """The probe's batches (smaller): segments across the seam of two tiles over the procedural
    world (9.5 E; and E179/W180 tiles across the antimeridian, either first). Before: 4-15 of 600
    hit one way only, 4-13 had line of sight disagree with intersect, hits up to 435 m above the
    stack's surface. Now none: both ways agree, line of sight agrees with intersect, every contact
    on the stack's surface or its wall, no sample before it underground."""
    t, lat_rng, lon_rng = _seam_batches()[case]
    a, b = _segments_across(t, np.random.default_rng(5), 240, lat_rng, lon_rng, 0.12, up_m=(2.0, 400.0))
    a = (a[0], (a[1] + 180.0) % 360.0 - 180.0, a[2])
    b = (b[0], (b[1] + 180.0) % 360.0 - 180.0, b[2])
    fwd, back, _ = _assert_symmetric_and_consistent(t, a, b, gaps=False)
    assert fwd.hit.any() and (~fwd.hit).any()
    for k in np.flatnonzero(fwd.hit)[:40]:
        _check_first_contact(t, a, b, fwd, k)
        _check_first_contact(t, b, a, back, k)


def test_endpoints_on_the_ground_at_a_dem_edge_agree_both_ways(alps_over_procedural):
    """Both endpoints on the stack's surface exactly on the Alps tile's north edge (48 N) over the
    procedural world: a 2.5e-7 m sliver of the DEM at b made a -> b hit at b, b -> a not (116 of
    1000). A stretch shorter than STACK_GAP_TOLERANCE_M at an end now goes to its neighbour."""
    t = alps_over_procedural
    rng = np.random.default_rng(99)
    n = 300
    lo = rng.uniform(9.1, 9.9, n)
    lob = lo + rng.uniform(-0.05, 0.05, n)
    lat = np.full(n, 48.0)
    a = (lat, lo, t.heights(lat, lo).height_msl_m)
    b = (lat, lob, t.heights(lat, lob).height_msl_m)
    fwd, back = t.intersect(*a, *b), t.intersect(*b, *a)
    np.testing.assert_array_equal(fwd.hit, back.hit)


def _tiles_3x3():
    """3 x 3 one-degree tiles (30", flat, 500..1300 m) over the procedural world."""
    d = 1 / 120
    return [Raster(np.full((121, 121), 500.0 + 100.0 * (3 * i + j), np.float32),
                   Georef(CRS_GEOGRAPHIC, 9.0 + j, 47.0 + i, d, d), name=f"t{i}{j}")
            for i in range(3) for j in range(3)]


def test_a_batch_over_many_tiles_asks_the_procedural_world_only_where_needed():
    """Segments each inside its own tile of 3 x 3 one-degree tiles over the procedural world: none
    reaches the procedural world, so it is asked for nothing (before: a raster over the box of all
    segments off the first tile, 17.8 M posts > 8.4 M, LimitExceeded for the batch). Answers are
    each tile's own (a Terrain of that tile alone; distances to 1e-6 m, the trace's nudged
    stretch ends)."""
    tiles = _tiles_3x3()
    t = Terrain(tiles + [ProceduralTerrain(seed=3)])
    rng = np.random.default_rng(1)
    n = 300
    la, lo = rng.uniform(47.1, 49.9, n), rng.uniform(9.1, 11.9, n)
    lb = np.clip(la + rng.uniform(-0.05, 0.05, n), np.floor(la) + 0.01, np.floor(la) + 0.99)
    lob = np.clip(lo + rng.uniform(-0.07, 0.07, n), np.floor(lo) + 0.01, np.floor(lo) + 0.99)
    ga, gb = t.heights(la, lo).height_msl_m, t.heights(lb, lob).height_msl_m
    a, b = (la, lo, ga + rng.uniform(-20.0, 20.0, n)), (lb, lob, gb + rng.uniform(-20.0, 20.0, n))
    got, los = t.intersect(*a, *b), t.line_of_sight(*a, *b)
    assert (got.status == STATUS_OK).all() and got.hit.any() and (~got.hit).any()
    tile = ((np.floor(la) - 47) * 3 + np.floor(lo) - 9).astype(int)
    for k in range(9):
        sel = np.flatnonzero(tile == k)
        alone = Terrain([tiles[k]])
        want = alone.intersect(*(x[sel] for x in a), *(x[sel] for x in b))
        np.testing.assert_array_equal(got.hit[sel], want.hit)
        np.testing.assert_allclose(got.distance_m[sel], want.distance_m, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(los.visible[sel], alone.line_of_sight(*(x[sel] for x in a),
                                                                             *(x[sel] for x in b)).visible)


def test_a_batch_too_wide_for_one_procedural_raster_is_split():
    """Segments leaving a DEM onto the procedural world in two places 20 degrees apart (one box:
    about 20 M posts, beyond RASTER_FOR_MAX_POSTS, 8.4 M: LimitExceeded before): each group gets
    its own raster, and every answer equals that of its place's batch alone, bit for bit."""
    d = 1 / 120
    dems = [Raster(np.full((61, 61), 300.0, np.float32), Georef(CRS_GEOGRAPHIC, lon0, 47.0, d, d),
                   name=f"d{lon0}") for lon0 in (9.0, 29.0)]
    t = Terrain(dems + [ProceduralTerrain(seed=3)])
    rng = np.random.default_rng(2)
    batches = []
    for lon0 in (9.0, 29.0):
        a, b = _segments_across(t, rng, 100, (47.1, 47.4), (lon0 + 0.4, lon0 + 0.6), 0.1)
        batches.append((a, b))
    both = [tuple(np.concatenate([x, y]) for x, y in zip(p, q)) for p, q in zip(*batches)]
    mixed, mixed_los = t.intersect(*both[0], *both[1]), t.line_of_sight(*both[0], *both[1])
    for j, (a, b) in enumerate(batches):
        alone, alone_los = t.intersect(*a, *b), t.line_of_sight(*a, *b)
        sl = slice(100 * j, 100 * (j + 1))
        for g, w in zip((mixed.hit, mixed.distance_m, mixed.lat_deg, mixed.lon_deg, mixed.height_msl_m,
                         mixed.normal_enu, mixed.status, mixed_los.visible, mixed_los.status),
                        (alone.hit, alone.distance_m, alone.lat_deg, alone.lon_deg, alone.height_msl_m,
                         alone.normal_enu, alone.status, alone_los.visible, alone_los.status)):
            np.testing.assert_array_equal(g[sl], w)
    assert (mixed.status == STATUS_OK).all() and mixed.hit.any()


@pytest.mark.parametrize("seg", [((89.95, -5.0), (89.95, 5.0)), ((89.99, 0.0), (89.99, 170.0)),
                                 ((89.999, 30.0), (89.998, -100.0))])
def test_segments_near_a_pole_over_the_procedural_world(seg):
    """Short segments near the north pole (10 km, 2.2 km, passing within a few hundred metres of it;
    those right over it: tests/test_terrain_fixes_procedural_rays.py): the box pad used to be degrees of
    longitude times tan(lat), hundreds to thousands of degrees (InvalidArgument naming lon_max, a
    field the caller never sent, or LimitExceeded). The box is now the chord's real latitude
    reach: answered. Oracle: dense samples of the segment against Terrain.heights."""
    t = Terrain([ProceduralTerrain(seed=3)])
    (la, lo), (lb, lob) = seg
    ground = t.heights([la, lb], [lo, lob]).height_msl_m
    for up, want_hit in ((3000.0, False), (-50.0, True)):
        a, b = ([la], [lo], [ground[0] + up]), ([lb], [lob], [ground[1] + up])
        pa, pb = _ecef(*a), _ecef(*b)
        s = np.linspace(0.0, 1.0, 2001)
        lat, lon, h = ecef_to_geodetic(pa + s[:, None] * (pb - pa))
        clear = (h - t.heights(lat, lon).height_msl_m).min()
        assert (clear < 0.0) == want_hit
        res = t.intersect(*a, *b)
        assert res.hit[0] == want_hit and res.status[0] == STATUS_OK
        assert t.line_of_sight(*a, *b).visible[0] == (not want_hit)
