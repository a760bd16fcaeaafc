"""Terrain fixes from the s29 acceptance probe.

1. Segment calls over the procedural world keep to a per-call cost (terrain.terrain.RayBudget):
   refused before any work when their boxes hold too many posts or new blocks, and refused as the
   rasters are made when groups or parts would pass it (the new-block cap is per call, not per
   raster); over the service, LineOfSight / IntersectSegments stop once the caller's deadline has
   passed, so one client's abandoned batch no longer shuts the others out.
2. GeoTIFF unit declarations are read: GDAL's band unit type (feet), GeogAngularUnitsGeoKey
   (radian), ProjLinearUnitsGeoKey (US survey foot); unknown ones are refused naming the key.
3. GetTile / GetRegion serve every store of a service with several, not only the first.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile

from client.terrain_client import HeightGrid, ServiceError, TerrainClient
from server.terrain_service import TerrainServicer, create_server
from sortie.errors import DataFormatError, LimitExceeded, NotFound
from sortie.v1 import terrain_pb2 as pb
from terrain import quadtree
from terrain.dem import read_dem
from terrain.geodesy import geodetic_to_ecef
from terrain.procedural import MAX_NEW_BLOCKS_PER_CALL, ProceduralTerrain
from terrain.raster import STATUS_OK
from terrain.store import CLASS_OUTSIDE, StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import RAY_MAX_POSTS_PER_CALL, RayBudget, Terrain

# --------------------------------------------------------------------------- 1: ray cost and deadline

# The probe's batch: rays on a 3-degree diagonal at 3500 m over the procedural world (each traced
# in parts, about 10 M raster posts and 190 new blocks).
_RNG = np.random.default_rng(20)
DIAG_LAT = _RNG.uniform(-60, 60, 10)
DIAG_LON = _RNG.uniform(-170, 170, 10)


def _diagonals(n):
    h = np.full(n, 3500.0)
    return DIAG_LAT[:n], DIAG_LON[:n], h, DIAG_LAT[:n] + 3.0, DIAG_LON[:n] + 3.0, h


@pytest.mark.parametrize("call", ["line_of_sight", "intersect"])
def test_a_costly_batch_is_refused_before_any_work(call):
    """The probe's 10 long rays (about 100 M posts of rasters; 20-30 s of work, for each of six
    clients) are refused at once, naming what is over the limit; no block is generated."""
    world = ProceduralTerrain(1)
    t0 = time.perf_counter()
    with pytest.raises(LimitExceeded, match=r"segments \(procedural raster posts\): \d+ exceeds the limit of "
                                            f"{RAY_MAX_POSTS_PER_CALL}.*before any work") as info:
        getattr(Terrain([world]), call)(*_diagonals(10))
    assert info.value.size > RAY_MAX_POSTS_PER_CALL
    assert world.blocks_generated == 0
    assert time.perf_counter() - t0 < 5.0


def test_a_costly_batch_is_refused_over_the_service():
    """RESOURCE_EXHAUSTED over gRPC, with the field and the size (the client's LimitExceeded)."""
    server, port = create_server(Terrain([ProceduralTerrain(1)]), "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}", timeout_s=30.0) as client:
            with pytest.raises(LimitExceeded, match=r"segments \(procedural raster posts\)"):
                client.line_of_sight(*_diagonals(10))
    finally:
        server.stop(0)


def test_every_part_of_a_long_segment_is_counted():
    """A segment too long for one raster is traced in parts, each with its own raster: the budget
    counts every one (its new blocks are the blocks generated), and the estimate made before any
    work is of the same size as what the parts cost."""
    world = ProceduralTerrain(1)
    budget = RayBudget()
    Terrain([world]).intersect(*_diagonals(1), budget=budget)
    assert budget.new_blocks == world.blocks_generated > MAX_NEW_BLOCKS_PER_CALL // 40
    a = geodetic_to_ecef(*_diagonals(1)[:3])
    b = geodetic_to_ecef(*_diagonals(1)[3:])
    posts, _ = ProceduralTerrain(1).boxes_cost(*_piece_boxes(a, b))
    assert 0.5 * budget.posts < posts < 2.0 * budget.posts
    with pytest.raises(LimitExceeded, match="before any work"):
        RayBudget(max_posts=posts - 1).estimate([ProceduralTerrain(1)], a, b)


def _piece_boxes(a, b):
    """The boxes RayBudget.estimate makes for one 3-degree diagonal (two pieces)."""
    from terrain.geodesy import ecef_to_geodetic

    p = np.concatenate([a, a + 0.5 * (b - a), b])
    lat, lon, _ = ecef_to_geodetic(p)
    return (np.minimum(lat[:2], lat[1:]), np.minimum(lon[:2], lon[1:]), np.maximum(lat[:2], lat[1:]),
            np.maximum(lon[:2], lon[1:]))


def test_an_ordinary_batch_costs_no_budget_work():
    """Short rays over one area: the estimate is the sum of their boxes, far under the limits (no
    grid pass), and the answer is the one an unlimited budget gives."""
    world = ProceduralTerrain(3)
    rng = np.random.default_rng(1)
    n = 2000
    lat, lon = rng.uniform(45.0, 45.2, n), rng.uniform(7.0, 7.2, n)
    h = np.full(n, 2500.0)
    got = Terrain([world]).line_of_sight(lat, lon, h, lat + 0.05, lon + 0.05, h)
    free = Terrain([world]).line_of_sight(lat, lon, h, lat + 0.05, lon + 0.05, h,
                                          budget=RayBudget(max_posts=2**62, max_new_blocks=2**62))
    np.testing.assert_array_equal(got.visible, free.visible)
    posts, blocks = world.boxes_cost(lat, lon, lat + 0.05, lon + 0.05)
    assert posts < RAY_MAX_POSTS_PER_CALL // 4 and blocks < MAX_NEW_BLOCKS_PER_CALL


def test_an_abandoned_call_stops_and_the_service_serves_others():
    """One worker thread. A LineOfSight batch under the cost limit but seconds of work (three long
    rays, traced in parts) with a 0.3 s deadline: its work stops at the next raster after the
    deadline (far fewer blocks generated than the whole batch's 550 or so; before, the call ran to
    the end) and is counted as DEADLINE_EXCEEDED or CANCELLED; another client's height is answered."""
    world = ProceduralTerrain(1)
    server, port = create_server(Terrain([world]), "127.0.0.1:0", max_workers=1)
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}", timeout_s=0.3) as hasty:
            hasty.wait_ready(10.0)
            with pytest.raises(ServiceError, match="DEADLINE_EXCEEDED"):
                hasty.line_of_sight(*_diagonals(3))
        with TerrainClient(f"127.0.0.1:{port}", timeout_s=20.0) as other:
            assert other.heights([45.0], [7.0]).status[0] == STATUS_OK
        deadline = time.monotonic() + 20.0
        while "LineOfSight" not in server.stats.snapshot() and time.monotonic() < deadline:
            time.sleep(0.05)
        calls, _, codes = server.stats.snapshot()["LineOfSight"]
        assert calls == 1 and sum(codes.values()) == 1
        assert set(codes) <= {"DEADLINE_EXCEEDED", "CANCELLED"}
        assert world.blocks_generated < 300
    finally:
        server.stop(0)


# --------------------------------------------------------------------------- 2: GeoTIFF units

def _geotiff(path, data, *, crs=4326, tie, scale, raster_type=2, gdal_meta=None, extra_keys=()):
    """A one-band GeoTIFF: model type and CRS keys, raster type, any extra (key, 0, 1, value) keys."""
    geographic = crs == 4326
    keys = [(1024, 0, 1, 2 if geographic else 1), (1025, 0, 1, raster_type), (2048 if geographic else 3072, 0, 1, crs)]
    keys = sorted(keys + list(extra_keys))
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tags = [(34735, "H", len(directory), directory, False), (33550, "d", 3, list(scale), False),
            (33922, "d", 6, list(tie), False)]
    if gdal_meta is not None:
        tags.append((42112, "s", 0, gdal_meta, False))
    tifffile.imwrite(path, data, extratags=tags)
    return path


POSTS = np.array([[100, 200], [300, 400]], np.int16)


def _unittype(unit):
    return f'<GDALMetadata><Item name="UNITTYPE" sample="0" role="unittype">{unit}</Item></GDALMetadata>'


@pytest.mark.parametrize("unit, to_m", [("ft", 0.3048), ("foot", 0.3048), ("US survey foot", 1200.0 / 3937.0),
                                        ("ftUS", 1200.0 / 3937.0), ("m", 1.0), ("metre", 1.0), ("meter", 1.0)])
def test_gdal_band_unit_type_scales_heights(tmp_path, unit, to_m):
    path = _geotiff(tmp_path / "u.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0),
                    gdal_meta=_unittype(unit))
    np.testing.assert_allclose(read_dem(path).heights[::-1], POSTS * to_m, rtol=1e-6)


def test_gdal_unit_type_with_scale_and_offset(tmp_path):
    """GDAL unscales first (value * scale + offset), in the band's unit, then to metres."""
    meta = ('<GDALMetadata><Item name="SCALE" sample="0" role="scale">0.5</Item>'
            '<Item name="OFFSET" sample="0" role="offset">10</Item>'
            '<Item name="UNITTYPE" sample="0" role="unittype">ft</Item></GDALMetadata>')
    path = _geotiff(tmp_path / "s.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0), gdal_meta=meta)
    np.testing.assert_allclose(read_dem(path).heights[::-1], (POSTS * 0.5 + 10) * 0.3048, rtol=1e-6)


def test_unknown_or_conflicting_unit_type_is_refused(tmp_path):
    path = _geotiff(tmp_path / "x.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0),
                    gdal_meta=_unittype("fathom"))
    with pytest.raises(DataFormatError, match=r"GDAL_METADATA \(42112\) unittype = 'fathom'"):
        read_dem(path)
    path = _geotiff(tmp_path / "c.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0),
                    gdal_meta=_unittype("ft"), extra_keys=[(4099, 0, 1, 9001)])
    with pytest.raises(DataFormatError, match=r"VerticalUnitsGeoKey \(4099\) = 9001 \(metre\).*disagree"):
        read_dem(path)


def test_radian_coordinates_are_converted_to_degrees(tmp_path):
    path = _geotiff(tmp_path / "r.tif", POSTS, tie=(0, 0, 0, -2.0, 0.8, 0), scale=(0.001, 0.001, 0),
                    extra_keys=[(2054, 0, 1, 9101)])
    g = read_dem(path).georef
    assert g.x0 == pytest.approx(math.degrees(-2.0)) and g.dx == pytest.approx(math.degrees(0.001))
    assert g.y0 + g.dy == pytest.approx(math.degrees(0.8))  # the top row's post (PixelIsPoint)
    for code in (9102, 9122):  # degree
        path = _geotiff(tmp_path / f"d{code}.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0),
                        extra_keys=[(2054, 0, 1, code)])
        assert read_dem(path).georef.x0 == pytest.approx(-120.0)


def test_us_survey_feet_of_web_mercator_are_converted_to_metres(tmp_path):
    path = _geotiff(tmp_path / "f.tif", POSTS, crs=3857, tie=(0, 0, 0, -1e6, 5e6, 0), scale=(100, 100, 0),
                    extra_keys=[(3076, 0, 1, 9003)])
    g = read_dem(path).georef
    assert g.x0 == pytest.approx(-1e6 * 1200.0 / 3937.0) and g.dx == pytest.approx(100 * 1200.0 / 3937.0)
    path = _geotiff(tmp_path / "ft.tif", POSTS, crs=3857, tie=(0, 0, 0, -1e6, 5e6, 0), scale=(100, 100, 0),
                    extra_keys=[(3076, 0, 1, 9002)])
    assert read_dem(path).georef.dx == pytest.approx(30.48)


def test_unknown_coordinate_units_are_refused(tmp_path):
    path = _geotiff(tmp_path / "a.tif", POSTS, tie=(0, 0, 0, -120, 45, 0), scale=(0.1, 0.1, 0),
                    extra_keys=[(2054, 0, 1, 32767)])
    with pytest.raises(DataFormatError, match=r"GeogAngularUnitsGeoKey \(2054\) = 32767; read are 9101 \(radian\)"):
        read_dem(path)
    path = _geotiff(tmp_path / "b.tif", POSTS, crs=3857, tie=(0, 0, 0, -1e6, 5e6, 0), scale=(100, 100, 0),
                    extra_keys=[(3076, 0, 1, 9036)])  # kilometre
    with pytest.raises(DataFormatError, match=r"ProjLinearUnitsGeoKey \(3076\) = 9036"):
        read_dem(path)


# --------------------------------------------------------------------------- 3: several stores

def _asc(path: Path, lat0: float, lon0: float, base: float, posts: int = 31, spacing: float = 1.0 / 60.0) -> Path:
    k = np.arange(posts) * spacing
    lat, lon = lat0 + k, lon0 + k
    h = base + 300.0 * np.sin(np.radians(lat * 70.0))[:, None] * np.cos(np.radians(lon * 50.0))[None, :]
    lines = [f"ncols {posts}", f"nrows {posts}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}",
             f"cellsize {spacing!r}", "NODATA_value -32768"]
    path.write_text("\n".join(lines + [" ".join(str(int(round(v))) for v in row) for row in h[::-1]]) + "\n")
    return path


@pytest.fixture(scope="module")
def two_stores(tmp_path_factory):
    """Two stores on one lattice: a half-degree DEM near (10 N, 20 E) each, 0.6 degrees apart."""
    tmp = tmp_path_factory.mktemp("stores")
    import_dems([_asc(tmp / "a.asc", 10.0, 20.0, 900.0)], tmp / "a", resolution_arcsec=30.0)
    import_dems([_asc(tmp / "b.asc", 10.0, 20.6, 1500.0)], tmp / "b", resolution_arcsec=30.0)
    return TerrainStore(tmp / "a"), TerrainStore(tmp / "b")


def test_get_tile_serves_every_store(two_stores):
    a, b = two_stores
    servicer = TerrainServicer(Terrain([StoreSource(a), StoreSource(b)]))
    depth = a.cell_depth(0)
    for store, lat, lon in ((a, 10.2, 20.2), (b, 10.2, 20.8)):
        cell = quadtree.cell_at(lat, lon, depth)
        grid = HeightGrid.from_message(servicer.GetTile(pb.GetTileRequest(cell_id=cell)))
        _, want = store.cell_raster(cell)
        np.testing.assert_array_equal(grid.heights, np.asarray(want.heights[::-1], np.float32))
        assert (grid.classes != CLASS_OUTSIDE).sum() > 100
    with pytest.raises(NotFound, match="no store holds cell"):
        servicer.GetTile(pb.GetTileRequest(cell_id=quadtree.cell_at(-40.0, 100.0, depth)))


def test_get_region_merges_every_store(two_stores):
    """A box over both stores' data: one grid with each store's posts (as the terrain's heights
    answer them there), outside between them; a box over the second store alone is its data."""
    a, b = two_stores
    terrain = Terrain([StoreSource(a), StoreSource(b)])
    servicer = TerrainServicer(terrain)
    for box in ((10.1, 20.1, 10.4, 21.0), (10.1, 20.7, 10.4, 21.0)):
        grid = HeightGrid.from_message(servicer.GetRegion(pb.GetRegionRequest(
            level=0, lat_min_deg=box[0], lon_min_deg=box[1], lat_max_deg=box[2], lon_max_deg=box[3])))
        rows, cols = grid.heights.shape
        lat = grid.lat_north_deg - np.arange(rows) * grid.dlat_deg
        lon = grid.lon_west_deg + np.arange(cols) * grid.dlon_deg
        assert lat[-1] <= box[0] and lat[0] >= box[2] and lon[0] <= box[1] and lon[-1] >= box[3]
        want = terrain.heights(np.repeat(lat, cols), np.tile(lon, rows))
        has = (want.status == STATUS_OK).reshape(rows, cols)
        np.testing.assert_array_equal(grid.classes != CLASS_OUTSIDE, has)
        np.testing.assert_array_equal(grid.heights[has], want.height_msl_m.reshape(rows, cols)[has].astype(np.float32))
        lon2 = np.broadcast_to(lon, (rows, cols))
        assert has[lon2 > 20.65].sum() > 100  # the second store's posts
        if box[1] < 20.5:
            assert has[lon2 < 20.45].sum() > 100  # and the first's
    with pytest.raises(NotFound, match="2 stores"):
        servicer.GetRegion(pb.GetRegionRequest(level=0, lat_min_deg=-40.0, lon_min_deg=100.0, lat_max_deg=-39.9,
                                               lon_max_deg=100.1))


def test_segments_a_dem_holds_are_not_counted_for_the_world_behind_it():
    """A DEM before the procedural world: the probe's long rays inside the DEM's bounds cost the
    world nothing (estimated or made); the same rays beyond the DEM are refused before any work."""
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster

    lat, lon, h, lat2, lon2, h2 = _diagonals(10)
    dem = Raster(np.full((121, 121), 100.0), Georef(CRS_GEOGRAPHIC, 10.0, 10.0, 0.05, 0.05))
    world = ProceduralTerrain(1)
    terrain = Terrain([dem, world])
    inside = (11.0 + (lat - lat.min()) / 120.0, 11.0 + (lon - lon.min()) / 340.0)  # ends within 11..15 degrees
    high = np.full(10, 8000.0)  # the chord sags 4.3 km below its ends at mid-way
    got = terrain.line_of_sight(inside[0], inside[1], high, inside[0] + 3.0, inside[1] + 3.0, high)
    assert got.visible.all() and (got.status == STATUS_OK).all() and world.blocks_generated == 0
    with pytest.raises(LimitExceeded, match="before any work"):
        terrain.line_of_sight(lat, lon, h, lat2, lon2, h2)
    assert world.blocks_generated == 0
