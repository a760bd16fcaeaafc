"""Terrain fixes from the s30 acceptance probe.

1. Short segments scattered over the procedural world are answered: a group whose box holds far
   more posts than its segments' own boxes is split (terrain.terrain._sparse), so the per-call
   budget counts the rasters the rays need (200 segments under 1 km over 6 degrees were refused
   after 7 s: 40 M posts of rasters for 6,500 posts of their own boxes); every raster's fixed cost is
   counted too.
2. Fractal detail keeps the filled-void rule: DetailedRaster's dense ray rasters carry the
   source's filled mask, so rays meet the measured DEM behind a filled void (as heights do) and
   keep their FILLED status.
3. GeoTIFFs declaring ellipsoidal (or unknown) vertical systems are refused naming
   VerticalCSTypeGeoKey and the code; mean-sea-level ones are read and named.
4. GetMetadata's SHA-256 is of the DEM bytes the service read, hashed from start-up on; a file
   changed since it was read is named without a hash.
5. A point-like segment (no longer than 2 mm) lying under the surface is not visible, as a longer
   segment from a buried end is not.
"""

from __future__ import annotations

import hashlib
import os
import time

import numpy as np
import pytest
import tifffile

from server.terrain_service import TerrainServicer
from sortie.errors import DataFormatError, LimitExceeded
from sortie.v1 import terrain_pb2 as pb
from terrain.dem import read_dem
from terrain.detail import DetailedRaster
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef
from terrain.los import line_of_sight
from terrain.mosaic import load_sources
from terrain.procedural import ProceduralTerrain
from terrain.pyramid import build_pyramid, reduce_2x2, to_float32_outward
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef, Raster
from terrain.terrain import RAY_MAX_POSTS_PER_CALL, RayBudget, Terrain, ray_box

# --------------------------------------------------------------------------- 1: scattered rays


def _scattered(world_terrain, n, span_deg, seed=1, reach_deg=0.005):
    """The probe's batch: n segments under about 1 km, 20 m above the ground, spread over
    [0, span_deg]^2 degrees (t22_budget.py)."""
    rng = np.random.default_rng(seed)
    la, lo = rng.uniform(0, span_deg, n), rng.uniform(0, span_deg, n)
    lb, lob = la + rng.uniform(-reach_deg, reach_deg, n), lo + rng.uniform(-reach_deg, reach_deg, n)
    ha = world_terrain.heights(la, lo).height_msl_m + 20.0
    hb = world_terrain.heights(lb, lob).height_msl_m + 20.0
    return la, lo, ha, lb, lob, hb


def _grid(world_terrain, side, span_deg, seed=2):
    """side^2 short segments on a jittered grid over [0, span_deg]^2: every two at least about
    span_deg / side / 2 apart, so each is a group of its own."""
    rng = np.random.default_rng(seed)
    step = span_deg / side
    la0, lo0 = np.meshgrid(np.arange(side) * step, np.arange(side) * step, indexing="ij")
    la = la0.ravel() + rng.uniform(0, 0.25 * step, side * side)
    lo = lo0.ravel() + rng.uniform(0, 0.25 * step, side * side)
    lb, lob = la + rng.uniform(-0.005, 0.005, la.size), lo + rng.uniform(-0.005, 0.005, la.size)
    ha = world_terrain.heights(la, lo).height_msl_m + rng.uniform(-5.0, 30.0, la.size)
    hb = world_terrain.heights(lb, lob).height_msl_m + rng.uniform(-5.0, 30.0, la.size)
    return la, lo, ha, lb, lob, hb


def _answers(t, rays, budget=None):
    s = t.intersect(*rays, budget=budget)
    v = t.line_of_sight(*rays)
    return (s.hit, s.distance_m, s.lat_deg, s.lon_deg, s.height_msl_m, s.normal_enu, s.status, v.visible, v.status)


def test_scattered_short_segments_are_answered_within_a_small_budget():
    """The probe's 200 segments over 6 degrees (seed 11's world, as `sortie terrain serve
    --procedural 11`): before, both calls were refused (40,019,263 posts > 33,554,432) after
    about 7 s of work; now answered, the rasters made costing under 1/8 of the limit (their own
    boxes hold about 6,500 posts; a raster's fixed cost counted for each)."""
    t = Terrain([ProceduralTerrain(11)])
    rays = _scattered(t, 200, 6.0)
    budget = RayBudget()
    got = t.intersect(*rays, budget=budget)
    assert budget.posts < RAY_MAX_POSTS_PER_CALL // 8
    assert got.hit.any() and not got.hit.all()
    los = t.line_of_sight(*rays)
    assert np.all(los.status == STATUS_OK)
    assert not np.any(los.visible & got.hit)  # a segment meeting the surface is not clear


def test_segments_far_apart_answer_bit_for_bit_as_alone():
    """36 short segments on a grid 1 degree apart over 6 degrees: each gets its own raster, on the
    box it has alone, so the batch's answers are the lone segment's, bit for bit (before: refused,
    over the posts limit, as the batch's box held about 76 M posts)."""
    t = Terrain([ProceduralTerrain(11)])
    rays = _grid(t, 6, 6.0)
    batch = _answers(t, rays)
    for k in range(rays[0].size):
        alone = _answers(t, tuple(x[k:k + 1] for x in rays))
        for got, want in zip(batch, alone):
            np.testing.assert_array_equal(got[k:k + 1], want)


def test_a_batch_over_one_area_keeps_one_raster():
    """A fan of 300 rays from one observer over 5 km: one raster (the budget holds exactly its
    posts and one fixed cost), as before the split rule."""
    from terrain.terrain import RAY_RASTER_OVERHEAD_POSTS

    world = ProceduralTerrain(3)
    t = Terrain([world])
    rng = np.random.default_rng(4)
    n = 300
    az = rng.uniform(0, 2 * np.pi, n)
    lat0, lon0 = 45.0, 7.0
    lb, lob = lat0 + 0.045 * np.cos(az), lon0 + 0.045 * np.sin(az) / np.cos(np.radians(lat0))
    h0 = t.heights([lat0], [lon0]).height_msl_m[0] + 10.0
    rays = (np.full(n, lat0), np.full(n, lon0), np.full(n, h0), lb, lob, t.heights(lb, lob).height_msl_m + 2.0)
    budget = RayBudget()
    t.intersect(*rays, budget=budget)
    a = geodetic_to_ecef(*rays[:3])
    b = geodetic_to_ecef(*rays[3:])
    posts, _ = world.box_cost(*ray_box(rays, a, b, np.arange(n)))
    assert budget.posts == posts + RAY_RASTER_OVERHEAD_POSTS


def test_every_raster_counts_its_fixed_cost():
    """Splitting cannot hide work from the budget: the 36 lone rasters of the grid batch (about
    200 posts each) pass a limit of 30 rasters' fixed cost, and the call is refused as they are made."""
    from terrain.terrain import RAY_RASTER_OVERHEAD_POSTS

    t = Terrain([ProceduralTerrain(11)])
    rays = _grid(t, 6, 6.0)
    with pytest.raises(LimitExceeded, match=r"segments \(procedural raster posts\).*made for the call's segments"):
        t.line_of_sight(*rays, budget=RayBudget(max_posts=30 * RAY_RASTER_OVERHEAD_POSTS))


def test_the_block_cap_is_per_call_over_every_raster():
    """The new-block cap holds over the call's rasters together, not per raster: boxes of a few
    blocks each pass a cap of 40 one by one and are refused together once past it. (The four rays
    at a 1.5-degree square's corners that tested this before now get a raster each, of a block or
    two, instead of one of some 80 blocks: answered, generating a handful.)"""
    world = ProceduralTerrain(1)
    budget = RayBudget(max_new_blocks=40)
    boxes = [(10.0 + 0.3 * k, 20.0, 10.2 + 0.3 * k, 20.3) for k in range(10)]  # 2 x 3 blocks or so, apart
    with pytest.raises(LimitExceeded, match=r"segments \(new procedural blocks\): \d+ exceeds the limit of 40 "
                                            r"\(made for the call's segments so far"):
        for box in boxes:
            budget.charge(world, box)
    assert world.blocks_generated == 0
    lat, lon = np.array([10.0, 10.0, 11.5, 11.5]), np.array([20.0, 21.5, 20.0, 21.5])
    h = np.full(4, 3000.0)
    Terrain([world]).line_of_sight(lat, lon, h, lat + 0.0009, lon, h, budget=RayBudget(max_new_blocks=40))
    assert world.blocks_generated <= 16


def _pyramid_reference(heights, filled):
    """The pyramid's flat arrays by numpy steps (cell bounds, then reduce_2x2 level by level)."""
    h = np.asarray(heights, np.float64)
    corners = (h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:])
    lo = np.minimum(np.minimum(corners[0], corners[1]), np.minimum(corners[2], corners[3]))
    hi = np.maximum(np.maximum(corners[0], corners[1]), np.maximum(corners[2], corners[3]))
    hole = np.isnan(lo)
    lo[hole], hi[hole] = -np.inf, np.inf
    mins, maxs = [to_float32_outward(lo, -np.inf)], [to_float32_outward(hi, np.inf)]
    fills = [] if filled is None else [filled[:-1, :-1] | filled[:-1, 1:] | filled[1:, :-1] | filled[1:, 1:]]
    while mins[-1].shape != (1, 1):
        mins.append(reduce_2x2(mins[-1], np.min, np.float32(np.inf)))
        maxs.append(reduce_2x2(maxs[-1], np.max, np.float32(-np.inf)))
        if fills:
            fills.append(reduce_2x2(fills[-1], np.max, 0))
    return [np.concatenate([a.ravel() for a in levels]) for levels in (mins, maxs, fills) if levels]


def test_the_compiled_pyramid_is_the_numpy_one_bit_for_bit():
    """The pyramid (built for every ray raster: a small one's numpy steps cost some 0.2 ms a level,
    which made many small rasters slow) is the same, bit for bit, as the level-by-level numpy
    reduction, odd sizes, holes, float32 and float64, filled flags included."""
    rng = np.random.default_rng(5)
    for trial in range(120):
        ny, nx = rng.integers(2, 60, 2)
        h = rng.normal(500.0, 300.0, (ny, nx)).astype(np.float32 if trial % 3 else np.float64)
        h[rng.random((ny, nx)) < 0.04] = np.nan
        filled = (rng.random((ny, nx)) < 0.1).astype(np.uint8) if trial % 2 else None
        pyr = build_pyramid(h, filled)
        want = _pyramid_reference(h, filled)
        got = [pyr.min_flat, pyr.max_flat] + ([pyr.filled_flat] if filled is not None and filled.any() else [])
        for g, w in zip(got, want):
            assert g.dtype == w.dtype
            np.testing.assert_array_equal(g, w)


# --------------------------------------------------------------------------- 2: detail over filled voids

DD = 1.0 / 1200.0


def _void_rasters():
    """The probe's pair (t18_detail_stack.py): a DEM whose 20 x 20 post void was filled with a
    guess (400 m), and a measured DEM of the same posts 60 m above the original heights."""
    rng = np.random.default_rng(1)
    y, x = np.arange(101), np.arange(101)
    h = (300 + 50 * np.sin(y[:, None] / 7.0) * np.cos(x[None, :] / 5.0) + rng.normal(0, 5, (101, 101)))
    filled = np.zeros((101, 101), bool)
    filled[40:60, 40:60] = True
    guess = h.astype(np.float32)
    guess[40:60, 40:60] = 400.0
    g = Georef(CRS_GEOGRAPHIC, -70.0, -33.0, DD, DD)
    return Raster(guess, g, name="filled", filled=filled), Raster((h + 60).astype(np.float32), g, name="measured")


def test_detail_rays_meet_the_measured_dem_behind_a_filled_void():
    """Over the filled void heights answer the measured DEM (332.01 m, OK); a vertical segment now
    meets that surface too (before: 400.95 m, the filled guess plus detail), and an oblique segment
    1 m above the heights' surface is clear of it (before: a hit at distance 0)."""
    filled, measured = _void_rasters()
    t = Terrain([DetailedRaster(filled, seed=5, finest_spacing_m=2.0), measured])
    lat, lon = -33.0 + 50.3 * DD, -70.0 + 50.6 * DD
    h = t.heights([lat], [lon])
    assert h.status[0] == STATUS_OK
    s = t.intersect([lat], [lon], [1000.0], [lat], [lon], [0.0])
    assert s.hit[0] and abs(s.height_msl_m[0] - h.height_msl_m[0]) < 1e-6
    la, lo, lb, lob = -33.0 + 45 * DD, -70.0 + 45.2 * DD, -33.0 + 55 * DD, -70.0 + 55.3 * DD
    ha = t.heights([la], [lo]).height_msl_m + 1.0
    hb = t.heights([lb], [lob]).height_msl_m + 1.0
    a, b = geodetic_to_ecef([la], [lo], ha), geodetic_to_ecef([lb], [lob], hb)
    p_lat, p_lon, p_h = ecef_to_geodetic(a + np.linspace(0, 1, 4001)[:, None] * (b - a))
    assert np.min(p_h - t.heights(p_lat, p_lon).height_msl_m) > 0.1  # the oracle: clear by dense samples
    s = t.intersect([la], [lo], ha, [lb], [lob], hb)
    assert not s.hit[0]
    assert t.line_of_sight([la], [lo], ha, [lb], [lob], hb).visible[0]


def test_dense_detail_rasters_carry_the_filled_status_heights_give():
    """At random points over and around the void, the dense ray raster's status is what the
    detailed source's heights say (FILLED where a filled post weighs in); before, the dense
    raster had no filled mask and said OK everywhere."""
    filled, _ = _void_rasters()
    detailed = DetailedRaster(filled, seed=5, finest_spacing_m=2.0)
    box = (-33.0 + 34 * DD, -70.0 + 35 * DD, -33.0 + 46 * DD, -70.0 + 45 * DD)  # across a corner of the void
    dense = detailed.ray_raster_for(*box)
    rng = np.random.default_rng(3)
    posts = np.arange(35, 46)  # the posts themselves, and points on the lines between them
    lat = np.concatenate([rng.uniform(box[0], box[2], 3000), -33.0 + posts * DD, -33.0 + posts * DD,
                          rng.uniform(box[0], box[2], posts.size)])
    lon = np.concatenate([rng.uniform(box[1], box[3], 3000), -70.0 + posts * DD,
                          rng.uniform(box[1], box[3], posts.size), -70.0 + posts * DD])
    want_h, want_st = np.full(lat.size, np.nan), np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    detailed.heights_into(lat, lon, want_h, want_st)
    got_h, got_st = np.full(lat.size, np.nan), np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    dense.heights_into(lat, lon, got_h, got_st)
    assert (want_st == STATUS_FILLED).sum() > 300 and (want_st == STATUS_OK).sum() > 300
    np.testing.assert_array_equal(got_st, want_st)


def test_detail_segments_over_a_void_keep_their_filled_status():
    """Segments across the void above every surface (500 m), on the detailed source alone: they
    passed over filled posts, so their status is FILLED, as over the plain raster (before: OK,
    the dense rasters having no filled posts)."""
    filled, _ = _void_rasters()
    rng = np.random.default_rng(1)
    n = 20
    la, lo = -33.0 + rng.uniform(36, 39, n) * DD, -70.0 + rng.uniform(36, 39, n) * DD
    lb, lob = -33.0 + rng.uniform(44, 47, n) * DD, -70.0 + rng.uniform(44, 47, n) * DD
    h = np.full(n, 500.0)
    for source in (filled, DetailedRaster(filled, seed=5, finest_spacing_m=10.0)):
        t = Terrain([source])
        s = t.intersect(la, lo, h, lb, lob, h)
        assert not s.hit.any()
        assert np.all(s.status == STATUS_FILLED), source.name
        los = t.line_of_sight(la, lo, h, lb, lob, h)
        assert los.visible.all() and np.all(los.status == STATUS_FILLED), source.name


# --------------------------------------------------------------------------- 3: vertical datums


def _geotiff(path, vertical_cs=None):
    """A 4 x 4 GeoTIFF of 100 m posts, EPSG:4326, with VerticalCSTypeGeoKey (4096) if given."""
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 2), (2048, 0, 1, 4326)]
    if vertical_cs is not None:
        keys.append((4096, 0, 1, vertical_cs))
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tifffile.imwrite(path, np.full((4, 4), 100, np.int16),
                     extratags=[(34735, "H", len(directory), directory, False),
                                (33550, "d", 3, [0.1, 0.1, 0.0], False),
                                (33922, "d", 6, [0, 0, 0, 10.0, 50.0, 0], False)])
    return path


@pytest.mark.parametrize("code, what", [(5030, "ellipsoidal heights"), (5019, "ellipsoidal heights"),
                                        (4979, "ellipsoidal heights"), (5715, "not a mean-sea-level"),
                                        (6360, "not a mean-sea-level"), (1234, "not a mean-sea-level")])
def test_ellipsoidal_and_unknown_vertical_systems_are_refused(tmp_path, code, what):
    """Before, any code read as mean sea level ("as supplied"): WGS 84 ellipsoidal heights are
    off sea level by the geoid undulation (-107 m to +86 m)."""
    with pytest.raises(DataFormatError, match=rf"VerticalCSTypeGeoKey \(4096\) = {code}: {what}"):
        read_dem(_geotiff(tmp_path / f"v{code}.tif", code))


@pytest.mark.parametrize("code, datum", [(5773, "EGM96 geoid (EPSG:5773)"), (3855, "EGM2008 geoid (EPSG:3855)"),
                                         (5703, "NAVD88 (EPSG:5703)"), (5714, "mean sea level (EPSG:5714)"),
                                         (5103, "NAVD 1988 (GeoTIFF VertCS 5103)"),
                                         (32767, "mean sea level (as supplied)"),
                                         (None, "mean sea level (as supplied)")])
def test_mean_sea_level_vertical_systems_are_read_and_named(tmp_path, code, datum):
    raster = read_dem(_geotiff(tmp_path / f"v{code}.tif", code))
    assert raster.vertical_datum == datum
    assert np.all(raster.heights == 100.0)


# --------------------------------------------------------------------------- 4: DEM hashes


def _asc(path, value):
    path.write_text("ncols 3\nnrows 3\nxllcenter 10\nyllcenter 50\ncellsize 0.1\n"
                    + "\n".join(" ".join([str(value)] * 3) for _ in range(3)) + "\n")
    return path


def test_metadata_hashes_the_file_served_not_the_file_later(tmp_path):
    """The service read one DEM; the file was rewritten after start-up, before the first
    GetMetadata. Before, the hash was taken at that first call: that of the new bytes, which the
    service never served. Now it is taken from start-up on: the served bytes' hash."""
    dem = _asc(tmp_path / "a.asc", 100)
    served = hashlib.sha256(dem.read_bytes()).hexdigest()
    servicer = TerrainServicer(Terrain(load_sources([dem])), [dem])
    time.sleep(0.5)  # the background hash of 100 bytes: microseconds
    _asc(dem, 555)
    os.utime(dem, ns=(time.time_ns(), time.time_ns() + 10**9))
    files = servicer.GetMetadata(pb.GetMetadataRequest()).dem_files
    assert [f.sha256 for f in files] == [served]


def test_a_file_changed_before_it_was_hashed_is_named_without_a_hash(tmp_path, caplog):
    """Its stat as read no longer matches: no hash (the bytes now are not those served), its size
    as read, and a warning naming the file."""
    from server.terrain_service import DemIdentities, file_stat

    dem = _asc(tmp_path / "b.asc", 100)
    as_read = file_stat(dem)
    _asc(dem, 5555)
    files = DemIdentities([dem], [as_read]).get()
    assert files == [{"path": str(dem.resolve()), "size_bytes": as_read[0]}]
    assert "changed since the service read it" in caplog.text
    same = DemIdentities([dem]).get()  # unchanged since its stat: hashed
    assert same[0]["sha256"] == hashlib.sha256(dem.read_bytes()).hexdigest()


# --------------------------------------------------------------------------- 5: point-like segments


@pytest.mark.parametrize("depth_m, visible", [(0.5, False), (0.002, False), (0.0005, True), (0.0, True),
                                              (-1.0, True)])
def test_a_point_under_the_ground_is_not_visible(depth_m, visible):
    """A zero-length segment 0.5 m under the ground was visible (one 10 cm long is not); a point
    more than 1 mm (ENDPOINT_TOLERANCE_M) under the surface is now hidden, one on it or above it
    sees, over one raster, a stack of a DEM and the procedural world, and the procedural world."""
    rng = np.random.default_rng(7)
    h = 200.0 + rng.normal(0.0, 20.0, (50, 50))
    dem = Raster(h, Georef(CRS_GEOGRAPHIC, 7.0, 45.0, DD, DD), name="dem")
    lat, lon = 45.0 + 20.3 * DD, 7.0 + 30.7 * DD
    for t in (Terrain([dem]), Terrain([dem, ProceduralTerrain(2)]), Terrain([ProceduralTerrain(2)])):
        ground = t.heights([lat], [lon]).height_msl_m
        p = (np.array([lat]), np.array([lon]), ground - depth_m)
        got = t.line_of_sight(*p, *p)
        assert got.visible[0] == visible and got.status[0] == STATUS_OK
        if len(t.sources) == 1 and t.sources[0] is dem:
            assert line_of_sight(dem, *p, *p)[0][0] == visible
    if depth_m >= 0.5:  # as a longer segment from that point: blocked
        t = Terrain([dem])
        ground = t.heights([lat], [lon]).height_msl_m
        assert not t.line_of_sight([lat], [lon], ground - depth_m, [lat + 1e-6], [lon], ground - depth_m).visible[0]
