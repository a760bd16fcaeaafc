"""Fixes to the compressed terrain store found by an acceptance probe (docs/STORE.md).

1. A lossy store's sea (decoded within step/2 of 0 m) is water in the synthesized texture: the
   class map's water test takes the source's quantisation bound as its tolerance, from a local
   store and over the terrain service's metadata; DEM textures are unchanged.
2. Damaged level files raise DataFormatError naming the level file, the tile and what is wrong
   (never zstd's, the OS's or a bare ValueError), and the service answers FAILED_PRECONDITION.
3. A --step that is not a whole number of centimetres is refused, not rounded.
4. GetRegion's errors name the request's field (lat_min_deg ...), not lat[0].
5. Synthetic detail (fractal, cellular) leaves posts at or below sea level as the source has them.
6. Regions touching the South Pole store no tile beyond the quad tree's rows.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sortie.errors import DataFormatError, InvalidArgument
from terrain.store import StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import Terrain

ARCSEC = 1.0 / 3600.0


def _write_asc(path: Path, lat0: float, lon0: float, spacing: float, rows: int, cols: int, heights_of) -> Path:
    """An ESRI ASCII grid of rows x cols posts, the south-west one at (lat0, lon0), heights_of(lat, lon)."""
    lats = lat0 + np.arange(rows) * spacing
    lons = lon0 + np.arange(cols) * spacing
    h = heights_of(*np.meshgrid(lats, lons, indexing="ij"))
    lines = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}",
             f"cellsize {spacing!r}"]
    lines += [" ".join(f"{v:.3f}" for v in row) for row in h[::-1]]
    path.write_text("\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------- 1: sea in the texture

SEA_LAT = 45.02  # south of this: sea at 0 m, and at -12.5 m in the south-east corner


def _coast(lat, lon):
    h = np.full(lat.shape, 100.0) + 1500.0 * np.exp(-((lon - 10.05) / 0.004) ** 2)  # a ridge on a plain
    h = np.where(lat < SEA_LAT, 0.0, h)
    return np.where((lat < 45.015) & (lon > 10.07), -12.5, h)


@pytest.fixture(scope="module")
def coast(tmp_path_factory):
    """(the .asc, a store of it at step 1 m, one lossless)."""
    d = tmp_path_factory.mktemp("coast")
    asc = _write_asc(d / "coast.asc", 45.0, 10.0, ARCSEC, 181, 361, _coast)
    import_dems([asc], d / "step1", step_m=1.0)
    import_dems([asc], d / "lossless", lossless=True)
    return asc, d / "step1", d / "lossless"


def _coast_texture(terrain):
    from terrain.texture_cli import make_texture, texture_request

    req = texture_request([45.0, 10.0, 45.05, 10.1], "200x100", None, "2024-06-21T05:30:00Z")
    tex, summary = make_texture(terrain, req)
    lat = req.lat_max - (np.arange(req.rows) + 0.5) * (req.lat_max - req.lat_min) / req.rows
    sea = np.broadcast_to((lat < SEA_LAT - 0.0005)[:, None], tex.classes.shape)
    return tex, summary, sea


def test_a_lossy_stores_sea_is_water_locally_and_over_grpc(coast):
    """Store posts of the 0 m sea decode anywhere within +-0.5 m (step 1 m); every sea pixel is
    still water, and the service's metadata carries the bound to a thin client."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server
    from terrain.texture import WATER

    _, step1, _ = coast
    store = TerrainStore(step1)
    assert store.quantisation_bound_m == pytest.approx(0.5)
    sea_posts = store.raster(0, 45.0, 10.0, SEA_LAT - 0.001, 10.1).heights
    assert np.nanmax(sea_posts) > 0.0  # the bug's premise: the lossy sea is partly above 0 m
    terrain = Terrain([StoreSource(store)])
    tex, summary, sea = _coast_texture(terrain)
    assert summary["water_tolerance_m"] == pytest.approx(0.5)
    assert (tex.classes[sea] == WATER).all(), np.count_nonzero(tex.classes[sea] != WATER)
    assert (tex.classes[~sea] != WATER).any()  # the land is not drowned

    server, port = create_server(terrain, "127.0.0.1:0")
    server.start()
    try:
        client = TerrainClient(f"127.0.0.1:{port}")
        (meta,) = client.describe()
        assert float(meta["store_quantisation_m"]) == pytest.approx(0.5)
        remote, remote_summary, _ = _coast_texture(client)
        client.close()
    finally:
        server.stop(0)
    assert remote_summary["water_tolerance_m"] == pytest.approx(0.5)
    assert np.array_equal(remote.classes, tex.classes)


def test_dems_and_lossless_stores_keep_the_exact_water_test(coast):
    """Bound 0: the DEM's texture is the one of the exact rule h <= 0, bit for bit, and a
    lossless store's sea is water too."""
    from terrain.dem import read_dem
    from terrain.texture import WATER, synthesize
    from terrain.texture_cli import water_tolerance_m

    asc, _, lossless = coast
    dem = Terrain([read_dem(asc)])
    assert water_tolerance_m(dem) == 0.0
    tex, summary, sea = _coast_texture(dem)
    assert summary["water_tolerance_m"] == 0.0
    assert (tex.classes[sea] == WATER).all()
    store = Terrain([StoreSource(TerrainStore(lossless))])
    assert water_tolerance_m(store) == 0.0
    assert (_coast_texture(store)[0].classes[sea] == WATER).all()
    # The default (no tolerance) and tolerance 0 are the same arrays.
    h = np.where(np.arange(64)[None, :] < 20, 0.0, 3.0) * np.ones((48, 1))
    a = synthesize(h, 30.0, 30.0, 120.0, 30.0)
    b = synthesize(h, 30.0, 30.0, 120.0, 30.0, water_tolerance_m=0.0)
    assert np.array_equal(a.classes, b.classes) and np.array_equal(a.image, b.image)
    with pytest.raises(ValueError, match="water_tolerance_m"):
        synthesize(h, 30.0, 30.0, 120.0, 30.0, water_tolerance_m=math.nan)


# --------------------------------------------------------------------------- 2: damaged level files

def _damaged_copy(src: Path, dst: Path, level: int, mutate) -> Path:
    """A copy of a store whose region-000 level file has been through ``mutate(bytearray)``;
    returns the level file's path."""
    import shutil

    shutil.copytree(src, dst)
    path = dst / "region-000" / f"level-{level:02d}.tiles"
    data = bytearray(path.read_bytes())
    mutate(data)
    path.write_bytes(bytes(data))
    return path


def _read_everything(store: TerrainStore) -> None:
    """Decode every level of every region whole (heights and classes)."""
    for region in store.regions:
        for k, r in enumerate(region.rects):
            store.decode(region, k, r.row0, r.row1, r.col0, r.col1)


def _largest_entry(data, field: str = "hlen"):
    """(offset, height blob length, class blob length) of the tile of a level file's index whose
    ``field`` (hlen or clen) is largest."""
    from terrain.store import _INDEX_ENTRY

    count = int.from_bytes(data[8:12], "little")
    index = np.frombuffer(bytes(data[12:12 + count * _INDEX_ENTRY.itemsize]), _INDEX_ENTRY)
    e = index[int(np.argmax(index[field]))]
    return int(e["offset"]), int(e["hlen"]), int(e["clen"])


def _garbage_in_blob(data):
    off, hlen, _ = _largest_entry(data)
    data[off + hlen // 2:off + hlen // 2 + 40] = bytes((37 * k + 11) % 256 for k in range(40))


def _huge_offset(data):
    import struct

    struct.pack_into("<Q", data, 12 + 16, 1 << 62)


def _bad_part_size(data):
    off, _, _ = _largest_entry(data)
    data[off + 2] ^= 0x40


def _huge_tile_count(data):
    import struct

    struct.pack_into("<I", data, 8, 0xFFFFFFF0)


def _bad_class_blob(data):
    """A tile's class blob (zstd of its classes) with its middle garbled."""
    off, hlen, clen = _largest_entry(data, "clen")
    assert clen > 1, "the fixture has tiles with outside posts: their classes are zstd"
    a = off + hlen + clen // 2
    data[a:a + 8] = b"\xa5" * 8


@pytest.mark.parametrize("mutate, what", [
    (_garbage_in_blob, "zstd frame is damaged"),
    (_huge_offset, "points outside the file"),
    (_bad_part_size, "part sizes"),
    (_huge_tile_count, "truncated index"),
    (_bad_class_blob, "class blob"),
])
def test_damaged_level_files_raise_data_format_errors_naming_the_file_and_tile(coast, tmp_path, mutate, what):
    """The probe's cases: zstd garbage (was zstandard.ZstdError), a huge index offset (OSError
    EINVAL), a damaged part size (a bare ValueError), and a tile count, a class blob."""
    _, step1, _ = coast
    path = _damaged_copy(step1, tmp_path / "store", 0, mutate)
    store = TerrainStore(tmp_path / "store")
    with pytest.raises(DataFormatError) as info:
        _read_everything(store)
    message = str(info.value)
    assert str(path) in message and what in message, message
    if mutate is not _huge_tile_count:  # the index itself is unreadable: no tile to name
        assert ": tile (" in message, message
    # The store keeps answering where it can: the coarser levels are intact.
    region = store.regions[0]
    top = len(region.rects) - 1
    r = region.rects[top]
    h, _ = store.decode(region, top, r.row0, r.row1, r.col0, r.col1)
    assert np.isfinite(h).any()


@pytest.mark.parametrize("seed", range(3))
def test_random_damage_raises_nothing_but_data_format_error(coast, tmp_path, seed):
    """damage.py's mutations (truncation, flipped bits, a zeroed index entry, a truncated header,
    garbage in a blob), 20 per seed over every level file: reading the whole store either
    succeeds (a flip zstd cannot see) or raises DataFormatError naming a level file."""
    import random
    import shutil

    _, step1, _ = coast
    rng = random.Random(seed)
    files = sorted(p.name for p in (step1 / "region-000").glob("*.tiles"))
    for trial in range(20):
        name = rng.choice(files)
        kind = rng.choice(["truncate", "flip", "zero_index", "trunc_header", "garbage_blob", "flip_index"])

        def mutate(data, kind=kind):
            if kind == "truncate":
                del data[rng.randrange(len(data)):]
            elif kind == "flip":
                for _ in range(rng.randint(1, 20)):
                    data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            elif kind == "zero_index":
                data[12:44] = bytes(32)
            elif kind == "trunc_header":
                del data[rng.randrange(12):]
            elif kind == "flip_index":
                for _ in range(rng.randint(1, 3)):
                    data[rng.randrange(12, min(len(data), 12 + 32 * 4))] ^= 1 << rng.randrange(8)
            else:
                i = rng.randrange(44, len(data))
                data[i:i + 64] = bytes(rng.randrange(256) for _ in range(len(data[i:i + 64])))

        copy = tmp_path / f"t{trial}"
        _damaged_copy(step1, copy, int(name[6:8]), mutate)
        try:
            _read_everything(TerrainStore(copy))
        except DataFormatError as e:
            assert str(copy / "region-000") in str(e) and ".tiles" in str(e), (kind, str(e))
        shutil.rmtree(copy)


def test_the_service_answers_a_damaged_tile_failed_precondition_and_keeps_serving(coast, tmp_path):
    import grpc

    from server.terrain_service import create_server
    from sortie.v1 import terrain_pb2 as pb
    from sortie.v1 import terrain_pb2_grpc

    _, step1, _ = coast
    path = _damaged_copy(step1, tmp_path / "store", 0, _garbage_in_blob)
    store = TerrainStore(tmp_path / "store")
    server, port = create_server(Terrain([StoreSource(store)]), "127.0.0.1:0")
    server.start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
            stub = terrain_pb2_grpc.TerrainServiceStub(channel)
            box = dict(lat_min_deg=45.0, lon_min_deg=10.0, lat_max_deg=45.05, lon_max_deg=10.1)
            with pytest.raises(grpc.RpcError) as info:
                stub.GetRegion(pb.GetRegionRequest(level=0, **box))
            assert info.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            assert str(path) in info.value.details() and "tile (" in info.value.details()
            grid = stub.GetRegion(pb.GetRegionRequest(level=len(store.regions[0].rects) - 1, **box))
            assert grid.rows > 0
    finally:
        server.stop(0)


# --------------------------------------------------------------------------- 3: --step in whole centimetres

def test_a_step_that_is_not_whole_centimetres_is_refused_naming_the_nearest_steps(tmp_path, coast):
    import subprocess
    import sys

    from terrain.store_import import _step_units

    asc, _, _ = coast
    with pytest.raises(InvalidArgument, match=r"--step .*0\.015 m is not: take --step 0\.01 or --step 0\.02"):
        import_dems([asc], tmp_path / "x", step_m=0.015)
    with pytest.raises(InvalidArgument, match=r"take --step 1\.23 or --step 1\.24"):
        import_dems([asc], tmp_path / "x", step_m=1.234)
    assert not (tmp_path / "x").exists()  # refused before any work
    # Whole centimetres, however the decimal lands in binary, are taken as they are.
    assert [_step_units(s, False, 0.01) for s in (0.01, 0.07, 0.25, 0.29, 1.0, 3.0, 1234.56)] == \
        [1, 7, 25, 29, 100, 300, 123456]
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "terrain", "import", str(asc), "-o",
                          str(tmp_path / "y"), "--step", "0.015", "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert "--step" in run.stderr and "0.015" in run.stderr and "--step 0.02" in run.stderr


# --------------------------------------------------------------------------- 4: GetRegion's field names

@pytest.mark.parametrize("field, value", [
    ("lat_min_deg", -91.0), ("lat_min_deg", math.nan), ("lat_max_deg", 91.0), ("lat_max_deg", math.inf),
    ("lon_min_deg", -541.0), ("lon_min_deg", math.nan), ("lon_max_deg", 541.0), ("lon_max_deg", -math.inf),
])
def test_get_region_names_the_request_field_it_refuses(coast, field, value):
    from server.terrain_service import TerrainServicer
    from sortie.v1 import terrain_pb2 as pb

    _, step1, _ = coast
    servicer = TerrainServicer(Terrain([StoreSource(TerrainStore(step1))]))
    box = dict(lat_min_deg=45.0, lon_min_deg=10.0, lat_max_deg=45.05, lon_max_deg=10.1)
    box[field] = value
    with pytest.raises(InvalidArgument) as info:
        servicer.GetRegion(pb.GetRegionRequest(level=0, **box))
    assert info.value.field == field and str(info.value).startswith(f"{field}: "), str(info.value)
    assert "lat[" not in str(info.value) and "lon[" not in str(info.value)


def test_get_region_over_grpc_says_which_field(coast):
    import grpc

    from server.terrain_service import create_server
    from sortie.v1 import terrain_pb2 as pb
    from sortie.v1 import terrain_pb2_grpc

    _, step1, _ = coast
    server, port = create_server(Terrain([StoreSource(TerrainStore(step1))]), "127.0.0.1:0")
    server.start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
            stub = terrain_pb2_grpc.TerrainServiceStub(channel)
            for field, box in (("lat_min_deg", (-91.0, 10.0, 45.05, 10.1)),
                               ("lat_min_deg", (math.nan, 10.0, 45.05, 10.1)),
                               ("lon_max_deg", (45.0, 10.0, 45.05, math.nan))):
                request = pb.GetRegionRequest(level=0, lat_min_deg=box[0], lon_min_deg=box[1], lat_max_deg=box[2],
                                              lon_max_deg=box[3])
                with pytest.raises(grpc.RpcError) as info:
                    stub.GetRegion(request)
                assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
                assert field in info.value.details() and "lat[" not in info.value.details()
            assert stub.GetRegion(pb.GetRegionRequest(level=0, lat_min_deg=45.0, lon_min_deg=10.0, lat_max_deg=45.05,
                                                      lon_max_deg=10.1)).rows > 0
    finally:
        server.stop(0)


# --------------------------------------------------------------------------- 5: detail leaves the sea alone

def _coast_raster():
    """The coast (sea at 0 m and -12.5 m, a plain with a ridge) as a 1" Raster, with its heights."""
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster

    lats = 45.0 + np.arange(181) * ARCSEC
    lons = 10.0 + np.arange(361) * ARCSEC
    h = _coast(*np.meshgrid(lats, lons, indexing="ij"))
    return Raster(h, Georef(CRS_GEOGRAPHIC, 10.0, 45.0, ARCSEC, ARCSEC))


COAST_LEVEL_STD_M = (9.4, 5.8, 3.6)  # detail of the coast's 3 sub-levels at 4 m (m)


def _rough_coast(lat, lon):
    """The coast with +-3 m of post-to-post roughness on its land, so that its land has pyramid
    residuals for the detail's fit (the sea, 0 m and -12.5 m, as _coast)."""
    h = _coast(lat, lon)
    return np.where(h > 0.0, h + 3.0 * np.sin(lat * 2.0e5) * np.sin(lon * 3.0e5), h)


def _detail_sources(raster):
    from terrain.detail import DetailedRaster
    from terrain.store_import import CellularDetail

    # The detail the coast's fit gave when it counted the sea (9.4 m at level 1): its land, a flat
    # plain and a smooth ridge, has almost no residuals of its own, and the fit now counts land alone.
    return {"fractal": DetailedRaster(raster, 7, finest_spacing_m=4.0, level_std_m=COAST_LEVEL_STD_M),
            "cellular": CellularDetail(raster, 7, 4.0, amplitude_m=2.0)}


@pytest.mark.parametrize("kind", ["fractal", "cellular"])
def test_detail_adds_nothing_at_or_below_sea_level(kind):
    """Points whose source height is at or below 0 m keep it exactly (they used to get bumps of up to
    +20 m, land in the sea); points well above it still get their detail."""
    raster = _coast_raster()
    source = _detail_sources(raster)[kind]
    rng = np.random.default_rng(3)
    lat = rng.uniform(45.0, 45.0 + 180 * ARCSEC, 200_000)
    lon = rng.uniform(10.0, 10.0 + 360 * ARCSEC, 200_000)
    base = Terrain([raster]).heights(lat, lon).height_msl_m
    got = Terrain([source]).heights(lat, lon).height_msl_m
    sea = base <= 0.0
    assert sea.sum() > 10_000 and (base < -1.0).sum() > 1_000
    assert np.array_equal(got[sea], base[sea])
    high = base > 90.0
    assert np.abs(got[high] - base[high]).max() > 0.5  # the detail is there on land
    taper = source.sea_taper_m if kind == "fractal" else source.amplitude_m
    ramp = (base > 0.0) & (base < taper)
    assert ramp.any() and (np.abs(got - base)[ramp] <= np.abs(got - base).max()).all()


def test_fractal_detail_gradient_includes_the_ramp_and_the_switch_restores_it_everywhere():
    """The ramp's slope enters the gradient (product rule; checked against central differences
    on the coast's slope), and sea_level_m=None is the old detail, sea included."""
    from terrain.detail import DetailedRaster

    raster = _coast_raster()
    d = DetailedRaster(raster, 7, finest_spacing_m=4.0, level_std_m=COAST_LEVEL_STD_M)
    t = Terrain([d])
    # Points on the shore's slope (between the 0 m sea row and the 100 m plain), off the lattice lines.
    rng = np.random.default_rng(5)
    lat = SEA_LAT - ARCSEC + rng.uniform(0.05, 0.95, 400) * ARCSEC
    lon = 10.01 + (np.floor(rng.uniform(0, 300, 400)) + rng.uniform(0.05, 0.95, 400)) * ARCSEC
    base = Terrain([raster]).heights(lat, lon).height_msl_m
    ramp = (base > 0.0) & (base < d.sea_taper_m)
    assert ramp.sum() > 20
    de, dn, _ = t.gradients(lat[ramp], lon[ramp])
    eps = 1e-4 * ARCSEC / 4096  # well inside the finest detail cell
    m_lat = math.radians(eps) * 6_367_000.0
    up = t.heights(lat[ramp] + eps, lon[ramp]).height_msl_m
    down = t.heights(lat[ramp] - eps, lon[ramp]).height_msl_m
    np.testing.assert_allclose(dn, (up - down) / (2 * m_lat), rtol=0.02, atol=0.02)
    everywhere = DetailedRaster(raster, 7, finest_spacing_m=4.0, sea_level_m=None)
    sea_lat = np.full(1000, 45.01)
    sea_lon = 10.0 + rng.uniform(0.001, 0.06, 1000)
    assert np.abs(Terrain([everywhere]).heights(sea_lat, sea_lon).height_msl_m).max() > 0.5
    assert np.abs(t.heights(sea_lat, sea_lon).height_msl_m).max() == 0.0


@pytest.mark.parametrize("kind", ["fractal", "cellular"])
def test_an_import_with_detail_keeps_the_sea_as_the_source_has_it(tmp_path, kind):
    """`sortie terrain import --add-detail`: store posts over the 0 m sea decode to 0 m (lossless);
    they used to get up to +20 m (fractal) and +4 m (cellular)."""
    small = _write_asc(tmp_path / "coast.asc", 45.0, 10.0, ARCSEC, 121, 91, _rough_coast)
    import_dems([small], tmp_path / "st", lossless=True, add_detail=kind, resolution_arcsec=0.3)
    import_dems([small], tmp_path / "plain", lossless=True, resolution_arcsec=0.3)
    store = TerrainStore(tmp_path / "st")
    sea = store.raster(0, 45.0, 10.0, SEA_LAT - 2 * ARCSEC, 10.0 + 90 * ARCSEC).heights
    box = (SEA_LAT + 2 * ARCSEC, 10.0, 45.0 + 120 * ARCSEC, 10.0 + 90 * ARCSEC)
    land = store.raster(0, *box).heights
    plain = TerrainStore(tmp_path / "plain").raster(0, *box).heights
    assert np.isfinite(sea).sum() > 1000
    assert np.nanmax(np.abs(sea)) == 0.0  # (the -12.5 m corner lies east of this small grid)
    assert np.nanmax(np.abs(land - plain)) > 0.3  # the land has its detail


# --------------------------------------------------------------------------- 6: the South Pole

def test_a_region_at_the_south_pole_stores_only_addressable_tiles_and_a_short_pyramid(tmp_path):
    """A DEM whose bottom row is the South Pole: its rectangles used to take a tile row past the
    quad tree's last (rows 0 .. 2 2^d - 1) at every level, so the pyramid never shrank to one
    tile (11 levels at depth 10). Now every tile is a cell GetTile serves, the pyramid stops
    where one tile holds the region, and heights down to the lattice's last row (one spacing
    north of the pole) are the DEM's."""
    from terrain import quadtree
    from terrain.dem import read_dem
    from terrain.raster import STATUS_OK, STATUS_OUTSIDE

    src = _write_asc(tmp_path / "spole.asc", -90.0, -60.0, 1.0 / 120.0, 25, 37,
                     lambda lat, lon: 2000.0 + 50.0 * np.cos(np.radians(lon * 30.0)) * (lat + 90.0))
    import_dems([src], tmp_path / "st", resolution_arcsec=30.0, step_m=0.5)
    store = TerrainStore(tmp_path / "st")
    (region,) = store.regions
    T = store.tile
    for k, rect in enumerate(region.rects):
        assert rect.row1 // T <= 2 << store.cell_depth(k), (k, rect)
    assert region.rects[-1].rows == T and region.rects[-1].cols <= 2 * T
    assert len(region.rects) < store.depth  # it was depth + 1
    for k, rect in enumerate(region.rects):  # every stored tile is a quad-tree cell the store serves
        for ti in range(rect.row0 // T, rect.row1 // T):
            for tj in range(rect.col0 // T, rect.col1 // T):
                level, raster = store.cell_raster(quadtree.cell_id(store.cell_depth(k), ti, tj))
                assert level == k and raster.shape == (T + 1, T + 1)
    last_lat = 90.0 - (2 * (1 << store.depth) * T - 1) * store.dlat
    assert region.bounds[0] == pytest.approx(last_lat)
    rng = np.random.default_rng(2)
    lat = rng.uniform(last_lat, -89.8, 500)
    lon = rng.uniform(-59.99, -59.71, 500)
    got = Terrain([StoreSource(store)]).heights(lat, lon)
    want = Terrain([read_dem(src)]).heights(lat, lon)
    assert (got.status == STATUS_OK).all()
    assert np.abs(got.height_msl_m - want.height_msl_m).max() <= 0.5 + store.max_error_m
    # South of the last row (the pole's own row, which no cell owns): outside.
    assert Terrain([StoreSource(store)]).heights([-90.0], [-59.9]).status[0] == STATUS_OUTSIDE


def test_the_clipmaps_land_classes_over_a_lossy_store_keep_the_sea_water(coast):
    """`--land-classes` over a lossy store: the clipmap's texels over the 0 m sea are water
    (the class map takes the store's quantisation bound, as `sortie terrain texture` does)."""
    from client.render.clipmap import Clipmap
    from client.render.terrain_mesh import lattice_for
    from terrain.texture import WATER

    _, step1, _ = coast
    terrain = Terrain([StoreSource(TerrainStore(step1))])
    c = Clipmap(terrain, lattice_for(terrain.describe(), 45.01, 10.05), 2, 31, 10 ** 9)
    c.land_classes = True
    c.update(45.01, 10.03, unlimited=True)
    level = c.levels[0]
    classes = level.normal[..., 3].astype(np.int64)
    h = np.repeat(np.repeat(level.unrolled()[0][..., 3], 2, 0), 2, 1)
    sea = np.abs(h) <= 0.5  # the 0 m sea as the store decodes it (the -12.5 m bay is water anyway)
    assert sea.sum() > 100 and np.nanmax(h[sea]) > 0.0  # decoded sea partly above 0 m
    assert np.all(classes[sea] == WATER)
