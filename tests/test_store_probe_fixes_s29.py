"""Fixes to the terrain store found by the s29 acceptance probe (docs/STORE.md).

1. A DEM whose longitudes start west of -180 (xllcorner -180.05) or turns east (1000) imports to a
   region whose first column lies in the lattice's first turn, and every reader wraps whole turns
   whatever turn a region's columns lie in, so stores written before (negative col0, col0 turns
   east) answer too: point heights, the texture's grid, GetRegion's raster, cells.
2. Where a DEM's NODATA runs to its edge, the store answers at the DEM's first valid posts (it used
   to lose that column: edge posts were taken only at the source's box, not at its voids' edges).
3. ``sortie terrain texture --spacing-m 1e-300`` is refused in a short message (it printed numbers
   thousands of digits long; 1e-320 raised OverflowError).
4. A DEM finer than the finest lattice is refused naming the file and its spacing, not
   ``resolution``, which the user did not give.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sortie.errors import InvalidArgument
from terrain import store as st
from terrain.dem import read_dem
from terrain.raster import STATUS_OK, STATUS_OUTSIDE
from terrain.store import StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import Terrain

CS = 1.0 / 1200.0  # 3 arc-seconds


def _write_asc(path: Path, x0: float, y0: float, h: np.ndarray, nodata: float | None = None) -> Path:
    """An ESRI ASCII grid (corner registration: xllcorner, yllcorner) of h (rows north to south)."""
    head = [f"ncols {h.shape[1]}", f"nrows {h.shape[0]}", f"xllcorner {x0!r}", f"yllcorner {y0!r}",
            f"cellsize {CS!r}"] + ([f"NODATA_value {nodata:g}"] if nodata is not None else [])
    path.write_text("\n".join(head + [" ".join(f"{v:.2f}" for v in row) for row in h]) + "\n")
    return path


def _sloped_asc(path: Path, x0: float) -> Path:
    """41 x 121 posts 3" apart from (x0, -10), a plane rising north and east (the probe's grid)."""
    lat = -10 + CS / 2 + CS * np.arange(41)[::-1]
    lon = x0 + CS / 2 + CS * np.arange(121)
    return _write_asc(path, x0, -10.0, 100 + np.add.outer(2 * (lat - lat[-1]) * 3600, 0.7 * (lon - lon[0]) * 3600))


def _dem_posts(asc: Path):
    """(lat, lon, height, DEM status) at every post of a DEM, longitudes wrapped to [-180, 180)."""
    r = read_dem(asc)
    ny, nx = r.heights.shape
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij"))
    x, y = r.georef.post_xy(rows, cols)
    x = (x + 180.0) % 360.0 - 180.0
    res = Terrain([r]).heights(y, x)
    return y, x, res.height_msl_m, res.status


# --------------------------------------------------------------------------- 1: columns in any turn

@pytest.fixture(scope="module")
def far_west(tmp_path_factory):
    """(the DEM across the antimeridian from -180.05, its store)."""
    d = tmp_path_factory.mktemp("amneg")
    asc = _sloped_asc(d / "amneg.asc", -180.05)
    import_dems([asc], d / "st", lossless=True)
    return asc, d / "st"


def _assert_answers_every_post(store: TerrainStore, asc: Path) -> None:
    lat, lon, want, dem_status = _dem_posts(asc)
    assert np.all(dem_status == STATUS_OK)
    for lo in (lon, lon + 360.0, lon - 360.0):  # any turn Terrain takes (within +-540)
        got = Terrain([StoreSource(store)]).heights(lat, lo)
        assert np.all(got.status == STATUS_OK), f"{np.sum(got.status != STATUS_OK)} posts outside"
        np.testing.assert_allclose(got.height_msl_m, want, atol=1.0)


@pytest.mark.parametrize("x0", [-180.05, 1000.0])
def test_a_dem_west_of_minus_180_or_turns_east_imports_in_the_first_turn(tmp_path, x0):
    asc = _sloped_asc(tmp_path / "dem.asc", x0)
    import_dems([asc], tmp_path / "st", lossless=True)
    store = TerrainStore(tmp_path / "st")
    rect = store.regions[0].rects[0]
    assert 0 <= rect.col0 < store.cols_per_turn(0)
    assert -180.0 <= store.regions[0].bounds[1] < 180.0
    _assert_answers_every_post(store, asc)


def test_the_texture_grid_over_a_far_west_store_has_no_holes(far_west):
    from terrain.texture_cli import sample_heights, texture_request

    _, path = far_west
    req = texture_request([-9.99, 179.96, -9.97, 180.04], "64x16", None, "2026-06-21T12:00:00Z")
    heights, _, _ = sample_heights(Terrain([StoreSource(TerrainStore(path))]), req)
    assert np.isfinite(heights).all(), f"{np.sum(~np.isfinite(heights))} nodata pixels"


def _shift_turns(src: Path, dst: Path, turns: int) -> Path:
    """A copy of a store with every region's columns ``turns`` whole turns away at every level (the
    manifest's rects and bounds, the level files' tile columns): what importers wrote before col0
    was normalised (a negative col0 for a DEM from -180.05, turns east for one at 1000)."""
    store = TerrainStore(src)
    manifest = dict(store.manifest)
    regions = []
    dst.mkdir()
    for region in store.regions:
        rects = []
        for level, rect in enumerate(region.rects):
            shift = turns * store.cols_per_turn(level)
            assert shift % store.tile == 0
            rects.append([rect.row0, rect.col0 + shift, rect.rows, rect.cols])
            entries, _, _ = store._level_index(region.index, level)
            tiles = {(int(e["row"]), int(e["col"]) + shift // store.tile):
                     (store._read_tile(region.index, level, int(e["row"]), int(e["col"]), classes=False),
                      store._read_tile(region.index, level, int(e["row"]), int(e["col"]), classes=True))
                     for e in entries}
            (dst / region.directory).mkdir(exist_ok=True)
            st.write_level_file(st.level_file(dst, region.index, level), level, tiles)
        lat_min, lon_min, lat_max, lon_max = region.bounds
        regions.append({**store.manifest["regions"][region.index], "rects": rects,
                        "bounds": [lat_min, lon_min + 360.0 * turns, lat_max, lon_max + 360.0 * turns]})
    manifest["regions"] = regions
    (dst / st.MANIFEST).write_text(json.dumps(manifest))
    store.close()
    return dst


@pytest.mark.parametrize("turns", [-1, 2])
def test_a_store_written_with_columns_in_another_turn_still_reads(far_west, tmp_path, turns):
    """Old stores on users' disks: a region of negative columns (the probe's amneg store had col0
    -256) or of columns turns east answers as the store written today does (to float rounding: its
    rasters' west edges lie turns away)."""
    asc, path = far_west
    new = TerrainStore(path)
    old = TerrainStore(_shift_turns(path, tmp_path / "old", turns))
    assert old.regions[0].rects[0].col0 == new.regions[0].rects[0].col0 + turns * new.cols_per_turn(0)
    assert old.regions[0].bounds == pytest.approx(new.regions[0].bounds)  # read into [-180, 180)
    _assert_answers_every_post(old, asc)
    lat, lon, _, _ = _dem_posts(asc)
    a = Terrain([StoreSource(old)]).heights(lat, lon)
    b = Terrain([StoreSource(new)]).heights(lat, lon)
    np.testing.assert_allclose(a.height_msl_m, b.height_msl_m, rtol=0, atol=1e-6)
    for level in range(new.levels):  # every level, through the block keys
        a = Terrain([StoreSource(old, level)]).heights(lat, lon)
        b = Terrain([StoreSource(new, level)]).heights(lat, lon)
        np.testing.assert_array_equal(a.status, b.status)
        np.testing.assert_allclose(a.height_msl_m, b.height_msl_m, rtol=0, atol=1e-6)
    # GetRegion's raster and GetTile's cells.
    box = (-9.99, 179.96, -9.97, 180.04)
    ra, rb = old.raster(0, *box), new.raster(0, *box)
    np.testing.assert_array_equal(ra.heights, rb.heights)
    assert ra.georef.x0 == pytest.approx(rb.georef.x0, abs=1e-9)
    from terrain import quadtree

    for lo in (179.99, -179.99):
        cell = quadtree.cell_at(-9.98, lo, old.depth)
        la_, ta = old.cell_raster(int(cell))
        lb_, tb = new.cell_raster(int(cell))
        assert la_ == lb_
        np.testing.assert_array_equal(ta.heights, tb.heights)
        assert np.isfinite(ta.heights).any()


# --------------------------------------------------------------------------- 2: voids at the edge

def _void_edge_cases(tmp_path):
    n = 61
    west = np.full((n, n), 500.0) + np.arange(n)[None, :] * 3.0
    west[:, :12] = -9999  # the probe's grid: 12 columns of NODATA along the west edge
    corner = np.full((n, n), 500.0) + np.add.outer(np.arange(n)[::-1] * 2.0, np.arange(n) * 3.0)
    corner[-15:, :20] = -9999  # a NODATA block in the south-west corner
    return [_write_asc(tmp_path / "west.asc", -45.0, -20.0, west, nodata=-9999),
            _write_asc(tmp_path / "corner.asc", -45.0, -20.0, corner, nodata=-9999)]


@pytest.mark.parametrize("case", [0, 1])
def test_the_store_answers_at_the_first_valid_posts_beside_edge_voids(tmp_path, case):
    asc = _void_edge_cases(tmp_path)[case]
    import_dems([asc], tmp_path / "st", lossless=True)
    store = TerrainStore(tmp_path / "st")
    lat, lon, want, dem_status = _dem_posts(asc)
    valid = dem_status == STATUS_OK
    assert 0 < valid.sum() < valid.size
    got = Terrain([StoreSource(store)]).heights(lat, lon)
    assert np.all(got.status[valid] == STATUS_OK), f"{np.sum(got.status[valid] != STATUS_OK)} valid posts outside"
    # Within the resampling error of a 3 m-a-post slope (the edge posts take the source's edge value).
    np.testing.assert_allclose(got.height_msl_m[valid], want[valid], atol=1.0)
    # No further than one store spacing into the void: posts two source spacings in stay outside.
    r = read_dem(asc)
    void = ~np.isfinite(r.heights)
    deep = void.copy()
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            deep &= np.roll(np.roll(np.pad(void, 2, constant_values=True), dy, 0), dx, 1)[2:-2, 2:-2]
    assert deep.any()
    assert np.all(got.status[deep.ravel()] == STATUS_OUTSIDE)


# --------------------------------------------------------------------------- 3: --spacing-m

@pytest.mark.parametrize("spacing", [1e-300, 1e-320, 0.5])
def test_a_tiny_spacing_is_refused_in_a_short_message(spacing):
    from terrain.texture_cli import texture_request

    with pytest.raises(InvalidArgument) as e:
        texture_request([0.0, 0.0, 1.0, 1.0], None, spacing, "2026-06-21T12:00:00Z")
    text = str(e.value)
    assert e.value.field == "--spacing-m"
    assert len(text) < 250, text
    assert "16,777,216" in text and f"{spacing:g}"[:3] in text


# --------------------------------------------------------------------------- 4: a DEM finer than the lattice

def test_a_dem_finer_than_the_finest_lattice_is_blamed_not_resolution(tmp_path):
    asc = tmp_path / "tiny_cell.asc"
    asc.write_text("ncols 3\nnrows 3\nxllcorner 1\nyllcorner 1\ncellsize 1e-9\n1 2 3\n4 5 6\n7 8 9\n")
    with pytest.raises(InvalidArgument) as e:
        import_dems([asc], tmp_path / "st")
    assert e.value.field == "files"
    assert str(asc) in str(e.value) and "arc-seconds apart" in str(e.value) and "--resolution" in str(e.value)
    # Given, --resolution is what is refused.
    with pytest.raises(InvalidArgument) as e:
        import_dems([asc], tmp_path / "st", resolution_arcsec=1e-6)
    assert e.value.field == "resolution"
