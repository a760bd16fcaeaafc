"""Fixes to rays over the detail synthesis and the procedural world, and to the procedural
world's limits: a batch of rays over a DetailedRaster is answered as each ray alone, on every
detail level (the surface heights answer); a segment over or near a pole of the procedural world
is answered (traced in parts, each part with its own box); one call cannot make the procedural
world generate blocks without bound; its parameters are checked when it is made."""

from __future__ import annotations

import numpy as np
import pytest

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.dem import read_dem
from terrain.detail import DetailedRaster
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef
from terrain.procedural import ProceduralTerrain
from terrain.raster import STATUS_OK
from terrain.terrain import Terrain, ray_box


@pytest.fixture(scope="module")
def detailed_alps(hgt_alps):
    return Terrain([DetailedRaster(read_dem(hgt_alps), 0, 1.0)])


def _near_ground_rays(t, rng, n, lat_rng, lon_rng, reach_deg):
    """n segments with ends 1 m above the ground (a within the ranges, b up to reach_deg away)."""
    la, lo = rng.uniform(*lat_rng, n), rng.uniform(*lon_rng, n)
    lb, lob = la + rng.uniform(-reach_deg, reach_deg, n), lo + rng.uniform(-reach_deg, reach_deg, n)
    ga, gb = t.heights(la, lo).height_msl_m, t.heights(lb, lob).height_msl_m
    return la, lo, ga + 1.0, lb, lob, gb + 1.0


def _dense_clearance(t, rays, samples=4001):
    """(n,) smallest sampled (segment height - Terrain.heights) along each segment, metres."""
    out = []
    for k in range(rays[0].size):
        pa = geodetic_to_ecef(rays[0][k], rays[1][k], rays[2][k])
        pb = geodetic_to_ecef(rays[3][k], rays[4][k], rays[5][k])
        s = np.linspace(0.0, 1.0, samples)[1:-1]
        lat, lon, h = ecef_to_geodetic(pa[None] + s[:, None] * (pb - pa)[None])
        out.append(np.min(h - t.heights(lat, lon).height_msl_m))
    return np.array(out)


def test_detail_rays_in_a_batch_answer_as_alone_and_as_heights(detailed_alps):
    """Rays of a few hundred metres, ends 1 m above the detailed surface, spread over the tile:
    the batch's raster used to drop the finest detail levels (a box over the whole batch), so a
    fifth of the answers differed from the ray's alone and from heights. Now the detail source
    raises LimitExceeded for a box it cannot serve on every level (ray_raster_for), the batch is
    split and every ray meets the full surface: batch and alone agree, and agree with dense
    samples of heights wherever the clearance is not within 5 cm of 0."""
    t = detailed_alps
    rng = np.random.default_rng(1)
    rays = _near_ground_rays(t, rng, 40, (47.1, 47.9), (9.1, 9.9), 0.004)
    batch, batch_los = t.intersect(*rays), t.line_of_sight(*rays)
    alone = [t.intersect(*(x[k:k + 1] for x in rays)) for k in range(40)]
    alone_vis = np.array([t.line_of_sight(*(x[k:k + 1] for x in rays)).visible[0] for k in range(40)])
    np.testing.assert_array_equal(batch_los.visible, alone_vis)
    np.testing.assert_array_equal(batch.hit, [r.hit[0] for r in alone])
    np.testing.assert_allclose(batch.distance_m, [r.distance_m[0] for r in alone], rtol=0, atol=1e-6)
    clear = _dense_clearance(t, rays)
    sure = np.abs(clear) > 0.05
    assert sure.sum() >= 30 and batch_los.visible.any() and (~batch_los.visible).any()
    np.testing.assert_array_equal(batch_los.visible[sure], clear[sure] > 0.0)


def test_detail_ray_batches_far_apart_answer_bit_for_bit_as_alone(detailed_alps):
    """Two clusters of rays half a degree apart: each cluster's box fits one raster of every detail
    level, the box of both does not. The mixed batch is split into the two clusters and answers,
    bit for bit, what each cluster's batch answers alone (before: one raster with fewer levels)."""
    t = detailed_alps
    rng = np.random.default_rng(3)
    batches = [_near_ground_rays(t, rng, 15, (lat0, lat0 + 0.001), (lon0, lon0 + 0.001), 0.0015)
               for lat0, lon0 in ((47.3, 9.3), (47.7, 9.8))]
    both = [np.concatenate([x, y]) for x, y in zip(*batches)]
    mixed, mixed_los = t.intersect(*both), t.line_of_sight(*both)
    for j, rays in enumerate(batches):
        alone, alone_los = t.intersect(*rays), t.line_of_sight(*rays)
        sl = slice(15 * j, 15 * (j + 1))
        for g, w in zip((mixed.hit, mixed.distance_m, mixed.normal_enu, mixed.status, mixed_los.visible),
                        (alone.hit, alone.distance_m, alone.normal_enu, alone.status, alone_los.visible)):
            np.testing.assert_array_equal(g[sl], w)
    assert mixed.hit.any() and (~mixed.hit).any()


def test_detail_ray_raster_is_strict_and_raster_for_still_degrades(hgt_alps):
    """ray_raster_for keeps every level or raises LimitExceeded naming the posts; raster_for (a
    viewer's overview) still answers a big box with fewer levels."""
    d = DetailedRaster(read_dem(hgt_alps), 0, 1.0)
    small = d.ray_raster_for(47.5, 9.5, 47.501, 9.501)
    assert small.meta["detail_levels"] == d.sub_levels
    with pytest.raises(LimitExceeded, match="detail box posts"):
        d.ray_raster_for(47.1, 9.1, 47.9, 9.9)
    assert 0 < d.raster_for(47.1, 9.1, 47.9, 9.9).meta["detail_levels"] < d.sub_levels


def _ends(lat_a, lon_a, h_a, lat_b, lon_b, h_b):
    return tuple(np.array([v], dtype=np.float64) for v in (lat_a, lon_a, h_a, lat_b, lon_b, h_b))


@pytest.mark.parametrize("lat", [89.95, 89.99, 89.999])
def test_a_segment_over_the_pole_of_the_procedural_world_is_answered(lat):
    """A segment from (lat, 0) to (lat, 180) at 9000 m passes over the north pole (11 km, 2.2 km,
    220 m). Its box spans every longitude near the pole: 23 M posts at 89.95 (LimitExceeded
    before); at 89.99 and 89.999 the box took the wrong side (the short way of exactly 180
    degrees is ambiguous: OUTSIDE before). Now the box turns the way the chord does (all the way
    round beside the axis) and a segment whose box is too big is traced in parts: clear, OK."""
    t = Terrain([ProceduralTerrain(seed=7)])
    rays = _ends(lat, 0.0, 9000.0, lat, 180.0, 9000.0)
    los, seg = t.line_of_sight(*rays), t.intersect(*rays)
    assert los.visible[0] and los.status[0] == STATUS_OK
    assert not seg.hit[0] and seg.status[0] == STATUS_OK


def test_a_segment_over_the_pole_near_the_ground_hits_where_heights_say():
    """11 km over the pole, ends 1 m above the ground, which rises 2.4 m above their chord
    between them (the sagitta d^2 / 8R; the procedural world fades to a sea-level pole): the
    contact is where dense samples of heights first go below the segment, to within the
    sampling step."""
    t = Terrain([ProceduralTerrain(seed=7)])
    g = t.heights([89.95, 89.95], [0.0, 180.0]).height_msl_m
    rays = _ends(89.95, 0.0, g[0] + 1.0, 89.95, 180.0, g[1] + 1.0)
    pa, pb = geodetic_to_ecef(*rays[:3])[0], geodetic_to_ecef(*rays[3:])[0]
    s = np.linspace(0.0, 1.0, 8001)
    lat, lon, h = ecef_to_geodetic(pa[None] + s[:, None] * (pb - pa)[None])
    below = np.flatnonzero(h - t.heights(lat, lon).height_msl_m < 0.0)
    assert below.size
    seg = t.intersect(*rays)
    step = np.linalg.norm(pb - pa) / 8000
    assert seg.hit[0] and seg.status[0] == STATUS_OK
    assert s[below[0]] * np.linalg.norm(pb - pa) - step <= seg.distance_m[0] <= s[below[0]] * np.linalg.norm(pb - pa)
    assert not t.line_of_sight(*rays).visible[0]


def test_a_polar_segment_in_a_batch_leaves_the_others_as_alone():
    """An ordinary segment and one over the pole in one batch: the batch used to fail whole
    (LimitExceeded); each is now answered as alone, bit for bit."""
    t = Terrain([ProceduralTerrain(seed=7)])
    both = [np.array(v) for v in ([10.0, 89.95], [10.0, 0.0], [3000.0, 9000.0], [10.01, 89.95], [10.01, 180.0],
                                  [3000.0, 9000.0])]
    mixed, mixed_los = t.intersect(*both), t.line_of_sight(*both)
    for k in range(2):
        one = [x[k:k + 1] for x in both]
        alone, alone_los = t.intersect(*one), t.line_of_sight(*one)
        for g, w in zip((mixed.hit, mixed.distance_m, mixed.status, mixed_los.visible, mixed_los.status),
                        (alone.hit, alone.distance_m, alone.status, alone_los.visible, alone_los.status)):
            np.testing.assert_array_equal(g[k:k + 1], w)
    assert mixed_los.visible.all() and (mixed.status == STATUS_OK).all()


def test_ray_box_takes_the_way_the_chord_turns_and_every_longitude_through_the_axis():
    """Ends 180 degrees apart: beside the pole (the chord's (a x b)_z not 0) the box spans the
    half the track passes over; through the axis every longitude; a box is a few centimetres
    wider than a short segment's track, not 0.01 degree."""
    def box(*ends):
        rays = _ends(*ends)
        return ray_box(rays, geodetic_to_ecef(*rays[:3]), geodetic_to_ecef(*rays[3:]), np.array([0]))

    lat_lo, west, lat_hi, east = box(89.99, 0.0, 100.0, 89.99, 180.0, 100.0)
    assert (west, east) == (-180.0, 180.0) and lat_hi == 90.0
    lat_lo, west, lat_hi, east = box(89.99, -10.0, 100.0, 89.99, 170.0, 100.0)  # beside the axis
    assert (west, east) == (-180.0, 180.0) or west <= -10.0 and east >= 170.0
    lat_lo, west, lat_hi, east = box(89.99, 10.0, 100.0, 89.99, 179.0, 100.0)  # east, the short way
    assert -180.0 <= west < 10.0 and 179.0 < east < 180.0 and lat_hi < 90.0
    lat_lo, west, lat_hi, east = box(47.5, 9.5, 1000.0, 47.5, 9.501, 1000.0)
    assert 0 < 9.5 - west < 1e-5 and 0 < east - 9.501 < 1e-5 and 0 < 47.5 - lat_lo < 1e-5


def test_one_query_over_too_many_new_blocks_is_refused_before_any_is_made(monkeypatch):
    """Points scattered over the globe, one new block each: 20,000 used to take about a minute
    (1,000,000, the service's batch limit, 25-45 minutes). Beyond MAX_NEW_BLOCKS_PER_CALL
    (lowered here to 50 to keep the test short) the call raises LimitExceeded naming the numbers,
    and generates nothing; a call over cached blocks, or fewer new ones, is answered."""
    import terrain.procedural as proc

    monkeypatch.setattr(proc, "MAX_NEW_BLOCKS_PER_CALL", 50)
    p = ProceduralTerrain(seed=1)
    t = Terrain([p])
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-89.0, 89.0, 200), rng.uniform(-180.0, 180.0, 200)
    with pytest.raises(LimitExceeded, match=r"new procedural blocks\): 200 exceeds the limit of 50"):
        t.heights(lat, lon)
    with pytest.raises(LimitExceeded):
        t.normals(lat, lon)
    assert p.blocks_generated == 0
    assert (t.heights(lat[:40], lon[:40]).status == STATUS_OK).all()
    assert (t.heights(np.r_[lat[:40], lat[40:80]], np.r_[lon[:40], lon[40:80]]).status == STATUS_OK).all()
    with pytest.raises(LimitExceeded):
        p.raster_for(10.0, 0.0, 10.001, 100.0)  # a thin box over 500 blocks


def test_the_default_cap_leaves_legitimate_calls_alone():
    """At the default cap: a profile across 5000 km and a batch of 100,000 points over one
    200 km area are answered; 20,000 scattered points are refused at once."""
    import time

    from terrain.procedural import MAX_NEW_BLOCKS_PER_CALL

    p = ProceduralTerrain(seed=1, cache_blocks=8)
    t = Terrain([p])
    assert (t.profile(40.0, -10.0, 45.0, 50.0, 5000).status == STATUS_OK).all()
    rng = np.random.default_rng(0)
    assert (t.heights(rng.uniform(47.0, 49.0, 100_000), rng.uniform(9.0, 11.0, 100_000)).status
            == STATUS_OK).all()
    made = p.blocks_generated
    start = time.perf_counter()
    with pytest.raises(LimitExceeded, match=f"limit of {MAX_NEW_BLOCKS_PER_CALL}"):
        t.heights(rng.uniform(-89.0, 89.0, 20_000), rng.uniform(-180.0, 180.0, 20_000))
    assert p.blocks_generated == made and time.perf_counter() - start < 1.0


@pytest.mark.parametrize("field, value", [("max_height_m", 1e308), ("max_height_m", 1.0e6),
                                          ("level_exponent", 1e300), ("level_exponent", 65.0),
                                          ("block_cells", 2**15), ("block_cells", 2**16)])
def test_parameters_that_crashed_at_query_time_are_refused_when_made(field, value):
    """level_exponent 1e300 (OverflowError at the first query), max_height_m 1e308 (infinite
    bounds, 90 degree slopes), block_cells 2^15 and 2^16 (MemoryError): InvalidArgument naming
    the field, at construction."""
    with pytest.raises(InvalidArgument, match=field):
        ProceduralTerrain(3, **{field: value})


def test_a_cache_too_big_for_its_blocks_is_refused_and_the_bounds_still_work():
    """block_cells 4096 with the default 64 cached blocks would hold 17 GB: refused, naming
    cache_blocks; the largest parameters allowed give finite heights and bounds."""
    with pytest.raises(InvalidArgument, match="cache_blocks"):
        ProceduralTerrain(3, block_cells=4096, posts_per_turn=2**20)
    p = ProceduralTerrain(3, max_height_m=1.0e5, level_exponent=64.0, block_cells=16, posts_per_turn=2**12)
    t = Terrain([p])
    h = t.heights(np.array([10.0, 10.0001]), np.array([20.0, 20.0001])).height_msl_m
    d = p.describe()
    assert np.isfinite(h).all() and np.isfinite([d["height_min_m"], d["height_max_m"]]).all()
    assert np.isfinite(t.normals(np.array([10.0]), np.array([20.0])).slope_deg).all()
