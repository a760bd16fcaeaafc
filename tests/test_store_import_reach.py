"""The importer samples only what can reach a source (terrain/store_import.py ``_reaching``).

A store post's height is the mean of ky x kx bilinear samples over its cell. Samples that fall
outside every source answer OUTSIDE and count for nothing, so the importer drops, before
sampling, the posts and offsets whose samples cannot fall inside a source's box. These tests
check that the dropped samples are exactly ones that would not have counted (the band's
heights and classes bit for bit those of sampling everything), across the antimeridian and at
the poles, and that a tiny source far finer than its store is no longer sampled over the whole
band (a 60 x 60-post, 0.1" grid at --resolution 3600: 12,650^2 offsets a post over 256 x 256
posts, 83 s; now about a second).
"""

from __future__ import annotations

import numpy as np
import pytest

from terrain import store as st
from terrain.dem import read_dem
from terrain.store_import import _reaching, _sample_band, import_dems
from terrain.terrain import Terrain


def _asc(path, heights, lat_south: float, lon_west: float, spacing_deg: float, nodata: float | None = None):
    """An ESRI ASCII grid, row 0 north, its south-west post at (lat_south, lon_west) degrees."""
    rows, cols = heights.shape
    head = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {lon_west!r}", f"yllcenter {lat_south!r}",
            f"cellsize {spacing_deg!r}"] + ([f"NODATA_value {nodata!r}"] if nodata is not None else [])
    path.write_text("\n".join(head + [" ".join(f"{v:.2f}" for v in r) for r in heights]) + "\n")
    return path


def _rough(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 500.0 + np.cumsum(np.cumsum(rng.normal(0.0, 2.0, (n, n)), 0), 1) * 0.1


CASES = {
    # name: (south-west post lat, lon, spacing deg, posts a side, store depth)
    "alps": (47.5, 9.5, 0.002, 40, 6),
    "across the antimeridian": (-20.0, 179.9, 0.005, 40, 6),
    "west of -180": (10.0, -180.05, 0.004, 30, 7),
    "at the north pole": (89.9, 20.0, 0.004, 25, 6),
    "at the south pole": (-90.0, -60.0, 0.004, 25, 6),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_dropped_samples_are_only_those_that_could_not_count(tmp_path, name):
    """Bands of lattice posts around each source (a void in it, so FILLED and edge posts occur)
    at three anti-aliasing factors: the heights and classes with the reach filter equal, bit for
    bit, those of sampling every post at every offset."""
    lat0, lon0, spacing, n, depth = CASES[name]
    heights = _rough(n, 3)
    heights[4:7, 4:7] = -9999.0
    raster = read_dem(_asc(tmp_path / "src.asc", heights, lat0, lon0, spacing, nodata=-9999.0))
    terrain = Terrain([raster])
    dlat, dlon = st.lattice_spacing_deg(depth, 256)
    lat_min, lon_min, lat_max, lon_max = raster.bounds
    r_a = max(0, int(np.floor((90.0 - lat_max) / dlat)) - 3)
    r_b = min(int(round(180.0 / dlat)), int(np.ceil((90.0 - lat_min) / dlat)) + 4)
    col0 = int(np.floor((lon_min + 180.0) / dlon)) - 3
    cols = int(np.ceil((lon_max - lon_min) / dlon)) + 7
    edges = [(raster, raster)]
    for factors in ((1, 1), (3, 2), (7, 9)):
        full = _sample_band(terrain, r_a, r_b, col0, cols, dlat, dlon, factors, edges, boxes=None)
        reach = _sample_band(terrain, r_a, r_b, col0, cols, dlat, dlon, factors, edges, boxes=[raster.bounds])
        assert (full[1] != st.CLASS_OUTSIDE).any(), (name, factors)  # the band does hold the source
        np.testing.assert_array_equal(reach[0], full[0])
        np.testing.assert_array_equal(reach[1], full[1])


def test_reaching_keeps_every_sample_inside_a_box():
    """Random boxes (some across the antimeridian, lon_max past 180) and random bands: every
    (row, column, offset) whose sample (the importer's own formula) lies inside a box is kept."""
    rng = np.random.default_rng(11)
    dlat, dlon = 0.5, 2.0 / 3.0
    for _ in range(200):
        boxes = []
        for _ in range(rng.integers(1, 3)):
            la = np.sort(rng.uniform(-90.0, 90.0, 2) * rng.choice([1.0, 0.05]))
            lo = rng.uniform(-180.0, 180.0)
            boxes.append((la[0], lo, la[1], lo + rng.uniform(0.0, 20.0)))
        r_a = int(rng.integers(0, 300))
        rows = np.arange(r_a, r_a + rng.integers(1, 60), dtype=np.float64)
        c0 = int(rng.integers(-50, 600))
        cs = np.arange(c0, c0 + rng.integers(1, 60), dtype=np.float64)
        ky, kx = (int(k) for k in rng.integers(1, 12, 2))
        oy = (np.arange(ky) - (ky - 1) / 2.0) / ky
        ox = (np.arange(kx) - (kx - 1) / 2.0) / kx
        ri, ci, ky_kept, kx_kept = _reaching(rows, cs, oy, ox, dlat, dlon, boxes)
        lat = np.clip(90.0 - (rows[:, None] + oy[None, :]) * dlat, -90.0, 90.0)  # (rows, oy)
        lon = ((cs[:, None] + ox[None, :]) * dlon) % 360.0 - 180.0  # (cols, ox)
        for lat_min, lon_min, lat_max, lon_max in boxes:
            in_lat = (lat >= lat_min) & (lat <= lat_max)
            in_lon = (lon - lon_min) % 360.0 <= lon_max - lon_min
            for i, a in zip(*np.nonzero(in_lat)):
                if in_lon.any():
                    assert i in ri and oy[a] in ky_kept
            for j, b in zip(*np.nonzero(in_lon)):
                if in_lat.any():
                    assert j in ci and ox[b] in kx_kept


def test_a_tiny_source_in_a_far_coarser_store_samples_only_its_own_cell(tmp_path, monkeypatch):
    """A 60 x 60-post grid 0.1" apart (6" across) imported at --resolution 3600 (depth 0, posts
    1265" x 1687" apart: 12,650 x 16,870 samples a post): the points sampled are those of the few
    posts whose cells hold the grid, not those of the whole 256 x 256-post band (before: 4.4e10
    samples, 83 s). The store's post there holds the mean of the grid's heights to within the
    grid's spread."""
    n, sp = 60, 0.1 / 3600
    heights = 700.0 + 5.0 * np.sin(np.arange(n)[:, None] * 0.3) + np.zeros((1, n))
    path = _asc(tmp_path / "tiny.asc", heights, 47.6, 9.6, sp)
    sampled = []
    original = Terrain.heights

    def counting(self, lat, lon, **kwargs):  # the real query, counted
        sampled.append(np.size(lat))
        return original(self, lat, lon, **kwargs)

    monkeypatch.setattr(Terrain, "heights", counting)
    summary = import_dems([path], tmp_path / "store", resolution_arcsec=3600.0, lossless=True)
    assert summary.depth == 0
    # The grid lies in at most 2 x 2 posts' cells, each sampled at the offsets reaching it: at
    # most (60 + 2)^2 of its spacings' worth of offsets each, counted generously.
    assert 0 < sum(sampled) <= 4 * (n + 3) ** 2 * 2, sum(sampled)
    monkeypatch.undo()
    terrain = Terrain([st.StoreSource(st.TerrainStore(tmp_path / "store"))])
    h = terrain.heights(np.array([47.6 + (n - 1) * sp / 2]), np.array([9.6 + (n - 1) * sp / 2])).height_msl_m
    assert heights.min() - 0.01 <= h[0] <= heights.max() + 0.01, h
