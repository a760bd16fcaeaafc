"""Terrain store fixes from the s35 acceptance probe (terrain/store_import.py).

1. DEMs on different vertical datums imported together: the store recorded the first source's datum
   alone (``store.json`` ``vertical_datum``) and stored the others' heights as if on it, silently
   (a NAVD88 GeoTIFF and an EGM2008 one made a store saying "NAVD88 (EPSG:5703)"; the datums differ
   by a metre or more). Two named datums that are not the same datum are refused naming ``files``,
   both files and both datums, before anything is written; two labels of one datum, and heights "as
   supplied" (no datum claimed), still import.
2. A store far coarser than its source sampled its anti-aliasing box (ky x kx bilinear samples a
   post, the spacing ratios) one offset at a time, a Terrain.heights call each: a 0.1" DEM (a
   lidar tile) at --resolution 120 made 834,000 calls for its few posts, 106 s (half an hour at
   600", most of a day at 3600"). The offsets are now sampled together, up to SAMPLE_CHUNK points a
   call: 2.4 s (600": 9 s; 3600": 94 s), the same level files byte for byte.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile

from sortie.cli import main
from sortie.errors import InvalidArgument
from terrain.dem import read_dem
from terrain.store import StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import Terrain

CS = 1.0 / 1200.0  # 3 arc-seconds


def _geotiff(path: Path, heights: np.ndarray, vertical_cs: int | None, lat_north: float, lon_west: float) -> Path:
    """A float32 GeoTIFF in EPSG:4326, PixelIsPoint, posts CS apart, row 0 north at ``lat_north``,
    column 0 at ``lon_west`` (degrees); VerticalCSTypeGeoKey (4096) ``vertical_cs`` if given."""
    keys = {1024: 2, 1025: 2, 2048: 4326}
    if vertical_cs is not None:
        keys[4096] = vertical_cs
    directory = [1, 1, 0, len(keys)] + [v for k in sorted(keys) for v in (k, 0, 1, keys[k])]
    tags = [(34735, "H", len(directory), directory, True), (33550, "d", 3, [CS, CS, 0.0], True),
            (33922, "d", 6, [0.0, 0.0, 0.0, lon_west, lat_north, 0.0], True)]
    tifffile.imwrite(path, heights.astype(np.float32), extratags=tags)
    return path


def _asc(path: Path, heights: np.ndarray, lat_south: float, lon_west: float) -> Path:
    """An ESRI ASCII grid (no .prj: heights as supplied), row 0 north, south-west post at
    (lat_south, lon_west), posts CS apart."""
    rows, cols = heights.shape
    head = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {lon_west!r}", f"yllcenter {lat_south!r}",
            f"cellsize {CS!r}"]
    path.write_text("\n".join(head + [" ".join(f"{v:.2f}" for v in row) for row in heights]) + "\n")
    return path


def _hill(n: int = 61, base_m: float = 1600.0) -> np.ndarray:
    y, x = np.mgrid[0:n, 0:n] / n
    return base_m + 40.0 * np.sin(5 * x) * np.cos(3 * y)


# --------------------------------------------------------------------------- 1: one vertical datum


@pytest.mark.parametrize("first, second", [(5703, 3855), (3855, 5703), (5773, 5703)],
                         ids=["navd88-egm2008", "egm2008-navd88", "egm96-navd88"])
def test_dems_on_different_vertical_datums_are_refused_naming_files_and_datums(tmp_path, first, second):
    """Overlapping GeoTIFFs near Boulder on two different datums: refused naming files, both files
    and both datums' labels, and the store directory is not even created. Before: a store saying
    the first's datum over both."""
    a = _geotiff(tmp_path / "a.tif", _hill(), first, 40.05, -105.05)
    b = _geotiff(tmp_path / "b.tif", _hill() - 1.5, second, 40.08, -105.02)
    la, lb = read_dem(a).vertical_datum, read_dem(b).vertical_datum
    out = tmp_path / "store"
    with pytest.raises(InvalidArgument, match=r"^files: ") as e:
        import_dems([a, b], out)
    msg = str(e.value)
    assert str(a) in msg and str(b) in msg and la in msg and lb in msg, msg
    assert not out.exists()
    # The command line says the same and exits 2.
    assert main(["terrain", "import", str(a), str(b), "-o", str(out), "--no-progress"]) == 2
    assert not out.exists()


def test_labels_of_one_datum_and_heights_as_supplied_still_import(tmp_path):
    """EPSG:5701 (Ordnance Datum Newlyn) and GeoTIFF VertCS 5101 (Newlyn) are one datum (EPSG
    datum 5101): one store, recording the first's label, answering each file's own heights inside
    it, to 0.1 m: the lossless store's 0.005 m rounding, and its 1.2" x 1.6" posts' bilinear
    resampling of the file's surface, which bends at its 3" grid lines by up to 0.3 m a post per
    post on this hill (40 m x (5 / 61)^2), a quarter of that times the store's spacing in posts
    (0.55) between bends: 0.05 m. An ASCII grid (heights as supplied, no datum claimed) goes with
    a named datum too."""
    a = _geotiff(tmp_path / "a.tif", _hill(), 5701, 51.05, -1.05)
    b = _geotiff(tmp_path / "b.tif", _hill(base_m=100.0), 5101, 51.05, -0.95)
    out = tmp_path / "store"
    summary = import_dems([a, b], out, lossless=True)
    assert summary.regions == 1
    manifest = json.loads((out / "store.json").read_text())
    assert manifest["vertical_datum"] == read_dem(a).vertical_datum
    store = Terrain([StoreSource(TerrainStore(out))])
    for path in (a, b):
        r = read_dem(path)
        lat_s, lon_w, lat_n, lon_e = r.bounds
        lat, lon = np.meshgrid(np.linspace(lat_s + 0.005, lat_n - 0.005, 25),
                               np.linspace(lon_w + 0.005, lon_e - 0.005, 25), indexing="ij")
        got = store.heights(lat.ravel(), lon.ravel()).height_msl_m
        want = Terrain([r]).heights(lat.ravel(), lon.ravel()).height_msl_m
        assert np.max(np.abs(got - want)) < 0.1
    c = _asc(tmp_path / "c.asc", _hill(), 51.0, -0.85)
    assert import_dems([a, c], tmp_path / "mixed").posts > 0
    assert import_dems([c, b], tmp_path / "mixed2").posts > 0


# --------------------------------------------------------------------------- 2: coarse anti-aliasing


def test_a_store_far_coarser_than_its_source_is_averaged_in_seconds(tmp_path):
    """A 6" x 6" lidar-like grid (0.1" posts) with a 10 m ripple of 1.13" wavelength near Interlaken,
    centred on a post of the lattice of --resolution 240 (depth 3, 158" x 211" posts: 1582 x 2110
    samples a post). That post's box holds the whole grid, whose samples it averages over 5.3 ripple
    periods: within 10 m x 2 / (2 pi 5.3) = 0.6 m of the ripple's mean, 500 m, taken as 1 m (a point
    sample lies anywhere in 490..510). One offset a call (3.3 M calls), it took 150 s; now 3 s, and 40 s
    allows for a loaded 2-core machine and a cold numba cache."""
    n, sp = 60, 0.1 / 3600
    dlat, dlon = 90.0 / (256 * 8), 120.0 / (256 * 8)
    row, col = 988, 3206  # the depth-3 lattice post at (46.58203, 7.85156)
    lat_c, lon_c = 90.0 - row * dlat, col * dlon - 180.0
    lat0, lon0 = lat_c - (n - 1) / 2 * sp, lon_c - (n - 1) / 2 * sp
    lat = lat0 + sp * np.arange(n)[::-1, None] + np.zeros((1, n))
    heights = 500.0 + 10.0 * np.sin(lat * 2e4)  # 2 pi / 2e4 degrees = 1.13" a period
    path = tmp_path / "lidar.asc"
    head = [f"ncols {n}", f"nrows {n}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}", f"cellsize {sp!r}"]
    path.write_text("\n".join(head + [" ".join(f"{v:.3f}" for v in r) for r in heights]) + "\n")
    start = time.perf_counter()
    summary = import_dems([path], tmp_path / "store", resolution_arcsec=240.0, lossless=True)
    seconds = time.perf_counter() - start
    assert summary.depth == 3
    store = TerrainStore(tmp_path / "store")
    h, c = store.decode(store.regions[0], 0, row, row + 1, col, col + 1)
    assert c[0, 0] == 1 and abs(h[0, 0] - 500.0) < 1.0, h
    assert seconds < 40.0, seconds
