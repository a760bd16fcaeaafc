"""Fixes to the terrain store found by the s30 acceptance probe (docs/STORE.md).

1. Two regions whose level-0 boxes lie more than a tile apart are coded apart, but their coarser
   rectangles are rounded out to whole tiles and can share tiles. Every reader now composes such a
   tile from each region holding it: GetTile (``cell_raster``), point queries of
   ``StoreSource(store, level)`` (block rasters) and the clipmap's store levels (``level_posts``)
   used to serve one region's half and call the other's posts outside (the probe: GetTile NaN where
   GetRegion gave 1409.87 m; StoreSource(store, 1) OUTSIDE at 3,400 posts).
2. A damaged ``store.json`` raises DataFormatError naming the file and the field (it raised
   ValueError, KeyError, TypeError, ZeroDivisionError, or opened a store of depth 80 / step 0).
3. A store's ``filled_posts`` (``terrain info``, GetMetadata) is the import's count (it was 0).
4. Sources a few posts apart across the antimeridian are one region, and a store's bounds take the
   shortest way round (they spanned 359.7 degrees).

The DEMs here lie on the store's lattice (ESRI ASCII with dx = the lattice's dlon, dy = its dlat,
post-registered), so the store's posts are the DEM's posts: a level-k post (r, c) is level 0's
(2^k r, 2^k c), and every answer there has an oracle, the DEM itself.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sortie.errors import DataFormatError
from terrain import quadtree
from terrain.dem import read_dem
from terrain.raster import STATUS_FILLED, STATUS_OK
from terrain import store as st
from terrain.store import MANIFEST, StoreSource, TerrainStore, lattice_spacing_deg
from terrain.store_import import import_dems
from terrain.terrain import Terrain

DEPTH = 10  # the lattice of the DEMs below: 1.236" x 1.648"
T = 256
PER_TURN = 3 * (1 << DEPTH) * T  # level-0 columns round the globe
# Lossless store answers at the DEM's posts within the store's bound (half a centimetre of rounding;
# TerrainStore.max_error_m) plus float32's rounding of a height near 2,000 m (1.2e-4 m).
HEIGHT_TOL_M = 0.005 + 2e-4


def _lattice_asc(path: Path, row_n: int, col_w: int, rows: int, cols: int, seed: int, void=None) -> Path:
    """An ESRI ASCII DEM whose posts are level-0 lattice posts rows [row_n, row_n + rows) x columns
    [col_w, col_w + cols) of a depth-DEPTH store (heights in whole centimetres, 800 to 1,800 m);
    void: (row slice, col slice) of NODATA posts (rows north to south)."""
    dlat, dlon = lattice_spacing_deg(DEPTH)
    y, x = np.mgrid[0:rows, 0:cols] / 9.0
    h = 1300.0 + 250.0 * np.sin(1.3 * x + seed) * np.cos(0.9 * y) + 150.0 * np.sin(0.7 * x + 1.9 * y)
    h = np.round(h, 2)
    text = [[f"{v:.2f}" for v in row] for row in h]
    if void is not None:
        for i in range(rows)[void[0]]:
            for j in range(cols)[void[1]]:
                text[i][j] = "-9999"
    head = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {-180.0 + col_w * dlon!r}",
            f"yllcenter {90.0 - (row_n + rows - 1) * dlat!r}", f"dx {dlon!r}", f"dy {dlat!r}",
            "NODATA_value -9999"]
    path.write_text("\n".join(head + [" ".join(row) for row in text]) + "\n")
    return path


def _expected(dems, level: int):
    """(lattice rows, lattice columns, heights m, statuses) of a level's posts on the DEMs: the
    DEMs' own posts (their voids as the DEM reader fills them)."""
    dlat, dlon = lattice_spacing_deg(DEPTH)
    s = 1 << level
    out = []
    for path, row_n, col_w, rows, cols in dems:
        r = np.arange(-(-row_n // s), (row_n + rows - 1) // s + 1)
        c = np.arange(-(-col_w // s), (col_w + cols - 1) // s + 1)
        R, C = (a.ravel() for a in np.meshgrid(r, c, indexing="ij"))
        res = Terrain([read_dem(path)]).heights(90.0 - R * s * dlat, (C * s * dlon) % 360.0 - 180.0)
        out.append((R, C, res.height_msl_m, res.status))
    return tuple(np.concatenate(parts) for parts in zip(*out))


# --------------------------------------------------------------------------- 1: regions sharing coarser tiles

# Two DEMs 276 level-0 posts apart (more than a tile: two regions). A's rectangle is level-0 tiles
# 2M + 1 and 2M + 2, rounded out at level 1 to tiles M and M + 1; B's is level-0 tiles 2M + 3 and
# 2M + 4, at level 1 tiles M + 1 and M + 2: tile M + 1 is shared, A's data in its first 45 columns,
# B's in its last 73 (and at level 2 they share a tile again).
M = 460  # near 72 W
ROW_N = 1479 * T + 20  # near 40 S
OVERLAP_DEMS = [("a.asc", ROW_N, (2 * M + 1) * T + 120, 40, 226, 0),
                ("b.asc", ROW_N, (2 * M + 3) * T + 110, 40, 226, 2)]


@pytest.fixture(scope="module")
def overlap(tmp_path_factory):
    """(store, [(dem path, row_n, col_w, rows, cols)]): the two DEMs, A with an enclosed void."""
    d = tmp_path_factory.mktemp("overlap")
    dems = []
    for name, row_n, col_w, rows, cols, seed in OVERLAP_DEMS:
        void = (slice(15, 21), slice(100, 108)) if name == "a.asc" else None
        dems.append((_lattice_asc(d / name, row_n, col_w, rows, cols, seed, void), row_n, col_w, rows, cols))
    import_dems([p for p, *_ in dems], d / "st", lossless=True)
    store = TerrainStore(d / "st")
    assert len(store.regions) == 2 and store.depth == DEPTH
    a, b = (r.rects[1] for r in store.regions)
    assert (a.col0, a.cols, b.col0, b.cols) == (M * T, 2 * T, (M + 1) * T, 2 * T)  # tile M + 1 shared
    return store, dems


def test_point_queries_at_a_coarser_level_answer_both_regions_sharing_a_tile(overlap):
    """StoreSource(store, 1) at every level-1 post on either DEM: OK, within HEIGHT_TOL_M of the DEM
    (old code: the later region's block won every point of the shared tile, so A's posts there
    were OUTSIDE). Gradients come from the same blocks: finite at every one of them."""
    store, dems = overlap
    dlat, dlon = store.spacing_deg(1)
    rows, cols, want, want_status = _expected(dems, 1)
    lat, lon = 90.0 - rows * dlat, cols * dlon - 180.0
    got = Terrain([StoreSource(store, 1)]).heights(lat, lon)
    assert np.all(got.status == want_status), f"{np.sum(got.status != want_status)} of {lat.size} posts differ"
    np.testing.assert_allclose(got.height_msl_m, want, atol=HEIGHT_TOL_M)
    assert np.any(got.status == STATUS_FILLED)  # A's void, filled
    # Between the posts (cell centres), heights and gradients come from the same blocks: as the
    # merged grid over both DEMs (GetRegion's) has them.
    lat_c, lon_c = lat - dlat / 2, lon + dlon / 2
    merged = Terrain([store.raster(1, lat.min() - dlat, lon.min(), lat.max(), lon.max() + dlon)])
    for query in ("heights", "normals"):
        got, want = (getattr(t, query)(lat_c, lon_c) for t in (Terrain([StoreSource(store, 1)]), merged))
        assert np.sum(want.status == STATUS_OK) > 0.8 * lat.size
        np.testing.assert_array_equal(got.status, want.status)
        for a, b in zip(got.__dict__.values(), want.__dict__.values()):
            np.testing.assert_allclose(a, b, atol=1e-9, equal_nan=True)


def test_get_tile_of_a_shared_cell_holds_both_regions_over_grpc(overlap):
    """GetTile of the level-1 cell both regions hold, through a real terrain service: every post of
    either DEM in it is there, within HEIGHT_TOL_M (old code: the first region's tile, B's posts
    NaN)."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    store, dems = overlap
    rows, cols, want, _ = _expected(dems, 1)
    shared = cols // T == M + 1
    rows, cols, want = rows[shared], cols[shared], want[shared]
    assert np.sum(cols < (M + 1) * T + 100) == 20 * 45 and np.sum(cols >= (M + 1) * T + 100) == 20 * 73  # A's, B's
    assert np.unique(rows // T).size == 1
    cell = quadtree.cell_id(DEPTH - 1, int(rows[0] // T), M + 1)
    server, port = create_server(Terrain([StoreSource(store)]), "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            grid = client.get_tile(cell)
    finally:
        server.stop(0)
    got = grid.heights[rows - rows // T * T, cols - (M + 1) * T]
    assert np.isfinite(got).all(), f"{np.sum(~np.isfinite(got))} of {got.size} posts NaN"
    np.testing.assert_allclose(got, want, atol=HEIGHT_TOL_M)


def test_the_clipmaps_store_level_holds_both_regions_sharing_a_tile(overlap):
    """A clipmap on the store's lattice reads its level 1 from the store's level 1, one block for
    the shared tile and one for a rectangle over both DEMs, and gets every post of either DEM there,
    within HEIGHT_TOL_M (old code: the shared tile from the region its centre fell in, the other's
    posts drawn as sea level; the rectangle over both from bilinear queries of level 0)."""
    from client.render.clipmap import Clipmap, Rect
    from client.render.terrain_mesh import lattice_for

    store, dems = overlap
    terrain = Terrain([StoreSource(store)])
    b = store.regions[0].bounds
    lattice = lattice_for(terrain.describe(), (b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
    clip = Clipmap(terrain, lattice, levels=2, n=63, budget=10 ** 9)
    assert clip.store is store
    rows, cols, want, _ = _expected(dems, 1)
    shared = cols // T == M + 1
    # Clipmap row i is lattice row -i (rows count south from the pole), column j lattice column j.
    for n, sel in enumerate((shared, np.ones_like(shared)), 1):
        r = Rect(-int(rows[sel].max()), int(cols[sel].min()), -int(rows[sel].min()), int(cols[sel].max()))
        _, h = clip.sample_posts(1, r)
        assert clip.store_blocks == n
        np.testing.assert_allclose(h[-rows[sel] - r.i0, cols[sel] - r.j0], want[sel], atol=HEIGHT_TOL_M)


def test_get_region_and_cells_agree_at_every_post_of_the_shared_tile(overlap):
    """The merged GetRegion grid (right before) and the composed tile agree at every post of the
    shared level-1 tile, NaN at the same posts (no data between the DEMs)."""
    store, _ = overlap
    rect = store.regions[1].rects[1]  # B's: the shared tile
    level, tile = store.cell_raster(quadtree.cell_id(DEPTH - 1, rect.row0 // T, rect.col0 // T))
    assert level == 1
    dlat, dlon = store.spacing_deg(1)
    lat_n, lon_w = 90.0 - rect.row0 * dlat, rect.col0 * dlon - 180.0
    region = store.raster(1, lat_n - (T - 1) * dlat, lon_w, lat_n, lon_w + (T - 1) * dlon)
    i = round((region.georef.y0 + (region.heights.shape[0] - 1) * dlat - lat_n) / dlat)  # rows from the north
    j = round((lon_w - region.georef.x0) / dlon)
    want = region.heights[::-1][i:i + T, j:j + T]
    got = tile.heights[::-1][:T, :T]
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, equal_nan=True, atol=0)


# --------------------------------------------------------------------------- 2: a damaged manifest


def _rects_not_nested(m):
    m["regions"][0]["rects"][1][1] += T


def _rects_one_level_more(m):
    m["regions"][0]["rects"].append(m["regions"][0]["rects"][-1])


DAMAGE = {
    "regions []": ("regions", lambda m: m.update(regions=[])),
    "regions null": ("regions", lambda m: m.update(regions=None)),
    "regions missing": ("regions", lambda m: m.pop("regions")),
    "tile missing": ("tile", lambda m: m.pop("tile")),
    "tile 'abc'": ("tile", lambda m: m.update(tile="abc")),
    "tile 0": ("tile", lambda m: m.update(tile=0)),
    "tile 255": ("tile", lambda m: m.update(tile=255)),
    "depth -3": ("depth", lambda m: m.update(depth=-3)),
    "depth 80": ("depth", lambda m: m.update(depth=80)),
    "step_units 0": ("step_units", lambda m: m.update(step_units=0)),
    "unit_m 0": ("unit_m", lambda m: m.update(unit_m=0)),
    "index 5": ("regions[0].index", lambda m: m["regions"][0].update(index=5)),
    "rects []": ("regions[0].rects", lambda m: m["regions"][0].update(rects=[])),
    "rects [[1, 2]]": ("regions[0].rects[0]", lambda m: m["regions"][0].update(rects=[[1, 2]])),
    "rects not tile-aligned": ("regions[0].rects[0]", lambda m: m["regions"][0]["rects"][0].__setitem__(0, 7)),
    "rects not nested": ("regions[0].rects[1]", _rects_not_nested),
    "rects one level more": ("regions[0].rects", _rects_one_level_more),
    "bounds missing": ("regions[0].bounds", lambda m: m["regions"][0].pop("bounds")),
    "bounds [1, 2]": ("regions[0].bounds", lambda m: m["regions"][0].update(bounds=[1, 2])),
    "bounds inverted": ("regions[0].bounds", lambda m: m["regions"][0]["bounds"].__setitem__(0, 89.0)),
    "summary a list": ("summary", lambda m: m.update(summary=[1])),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_manifest_raises_data_format_error_naming_the_file_and_field(overlap, tmp_path, case):
    """Each damage raises DataFormatError naming store.json and the field (old code: ValueError,
    KeyError, TypeError, ZeroDivisionError, or a store opened on a depth of 80, a step of 0, an odd
    tile, rectangles the level files do not have)."""
    store, _ = overlap
    field, damage = DAMAGE[case]
    m = json.loads((store.path / MANIFEST).read_text())
    damage(m)
    (tmp_path / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DataFormatError) as e:
        TerrainStore(tmp_path)
    assert str(tmp_path / MANIFEST) in str(e.value) and f"{field} " in str(e.value), str(e.value)


# --------------------------------------------------------------------------- 3: filled posts


def test_a_stores_filled_posts_are_the_imports_count_locally_and_over_grpc(overlap):
    """describe() and GetMetadata carry the import's filled_posts (A's void of 6 x 8 posts: 48 at
    level 0; old code: 0)."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    store, _ = overlap
    filled = json.loads((store.path / MANIFEST).read_text())["summary"]["filled_posts"]
    assert filled == 48
    terrain = Terrain([StoreSource(store)])
    assert terrain.describe()[0]["filled_posts"] == filled
    server, port = create_server(terrain, "127.0.0.1:0")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            assert int(client.describe()[0]["filled_posts"]) == filled
    finally:
        server.stop(0)


# --------------------------------------------------------------------------- 4: across the antimeridian


@pytest.fixture(scope="module")
def across(tmp_path_factory):
    """(store, dems): two DEMs 5 level-0 posts apart either side of the antimeridian near 16 S."""
    d = tmp_path_factory.mktemp("across")
    row_n = 1316 * T + 30
    dems = [(d / "east.asc", row_n, PER_TURN - 62, 40, 60), (d / "west.asc", row_n, 3, 40, 60)]
    for i, (path, row_n, col_w, rows, cols) in enumerate(dems):
        _lattice_asc(path, row_n, col_w, rows, cols, seed=i)
    import_dems([p for p, *_ in dems], d / "st", lossless=True)
    return TerrainStore(d / "st"), dems


def test_sources_a_few_posts_apart_across_the_antimeridian_are_one_region(across):
    """One region (old code: two), whose bounds and the store's run east across 180 and are under
    0.1 degree wide (old code: 359.7), answering every post of both DEMs within HEIGHT_TOL_M."""
    store, dems = across
    assert len(store.regions) == 1
    d = StoreSource(store).describe()
    assert 179.9 < d["lon_min"] < 180.0 < d["lon_max"] < 180.1, (d["lon_min"], d["lon_max"])
    rows, cols, want, want_status = _expected(dems, 0)
    dlat, dlon = store.spacing_deg(0)
    got = Terrain([StoreSource(store)]).heights(90.0 - rows * dlat, (cols * dlon) % 360.0 - 180.0)
    assert np.all(got.status == STATUS_OK) and np.all(want_status == STATUS_OK)
    np.testing.assert_allclose(got.height_msl_m, want, atol=HEIGHT_TOL_M)


@pytest.mark.parametrize("spans, cover", [
    ([(179.0, 179.9), (-179.8, -179.0)], (179.0, 181.0)),  # the probe's two regions of an older store
    ([(6.0, 10.0), (-110.0, -105.0)], (-110.0, 10.0)),  # far apart, not across
    ([(170.0, 190.0)], (170.0, 190.0)),  # one region across
    ([(-180.0, 180.0)], (-180.0, 180.0)),  # the globe
    ([(-100.0, 20.0), (10.0, 140.0), (130.0, 260.0)], (-180.0, 180.0)),  # round the globe in three
])
def test_a_stores_longitudes_take_the_shortest_way_round(spans, cover):
    assert st.lon_cover(spans) == pytest.approx(cover)


def test_a_stores_own_manifest_passes_the_checks_in_any_turn(overlap, tmp_path):
    """A store's own manifest passes the checks, moved whole turns too (older importers' col0)."""
    store, _ = overlap
    m = json.loads((store.path / MANIFEST).read_text())
    for r in m["regions"]:
        for k, rect in enumerate(r["rects"]):
            rect[1] -= PER_TURN >> k
    shutil.copytree(store.path, tmp_path / "st")
    (tmp_path / "st" / MANIFEST).write_text(json.dumps(m))
    assert TerrainStore(tmp_path / "st").regions[0].rects[0].col0 == (2 * M + 1) * T - PER_TURN
