"""Terrain import fixes from the s33 acceptance probe (terrain/store_import.py).

1. Cellular detail (--add-detail cellular) had a seam at the antimeridian: its lattice was laid out
   in x = lon cos(lat) R / cell, which jumps at +-180 by 2 pi R cos(lat) / cell cells, not a whole
   number (the detail stepped 1.06 m between the two columns either side of 180, where adjacent
   columns elsewhere differ by at most 0.58 m). The feature points now form a 3-D lattice in ECEF
   (CellularDetail, _worley_f1): continuous everywhere, the poles and the antimeridian included.
2. The same layout sheared the bumps by lon sin(lat): their correlation at 40 m ranged 0.27-0.85
   with the bearing at 45 N 90 E, -0.05-0.93 at 179 E. In 3-D it is the same whatever the bearing
   and the longitude.
3. The detail was biased low: F1 - 0.5 averaged -0.0706 a unit of amplitude (one jittered point a
   cell does not give a mean F1 of 0.5). The measured mean of the 3-D field, CELLULAR_F1_MEAN, is
   removed.
4. A source round the globe (360 degrees: its reader adds a wrap column) gave a region of 49,408
   columns where a turn has 49,152: a tile of columns stored twice at every level, their posts
   counted twice in the summary and decoded up to 0.95 m apart. A region is at most one turn wide,
   the turn from the antimeridian; readers interpolate across its own wrap.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from terrain import store as st
from terrain.geodesy import geodetic_to_ecef
from terrain.procedural import lattice_hash
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, Georef, Raster
from terrain.store_import import CELLULAR_F1_MEAN, CellularDetail, _worley_f1_cells, import_dems

SP = 1 / 1200  # SRTM3 post spacing, degrees
FINEST_M = 38.1758  # the store's latitude spacing at depth 10 (1.236 arc-seconds), metres


def _write_asc(path: Path, lat0: float, lon0: float, dlat: float, dlon: float, heights: np.ndarray) -> Path:
    """An ESRI ASCII grid of ``heights`` ((rows, cols) metres, row 0 south), the south-west post at
    (lat0, lon0) degrees, posts dlat x dlon degrees apart."""
    rows, cols = heights.shape
    lines = [f"ncols {cols}", f"nrows {rows}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}", f"dx {dlon!r}",
             f"dy {dlat!r}"]
    lines += [" ".join(f"{v:.3f}" for v in row) for row in heights[::-1]]
    path.write_text("\n".join(lines) + "\n")
    return path


def _cellular(seed: int = 0) -> CellularDetail:
    """Cellular detail of amplitude 1 m on a store of depth 10 (cells of 4 x 38.18 m); its raster
    is not read by _f1."""
    raster = Raster(np.zeros((2, 2), np.float32), Georef(CRS_GEOGRAPHIC, 0.0, 0.0, 1.0, 1.0))
    return CellularDetail(raster, seed, FINEST_M, amplitude_m=1.0)


def _chord_cells(lat_a, lon_a, lat_b, lon_b, cell_m: float) -> np.ndarray:
    """(n,) straight-line distances between points on the ellipsoid, in cells."""
    return np.linalg.norm(geodetic_to_ecef(lat_a, lon_a, 0.0) - geodetic_to_ecef(lat_b, lon_b, 0.0), axis=-1) / cell_m


# --------------------------------------------------------------------------- 1: no seam

def test_cellular_detail_is_continuous_everywhere_the_antimeridian_and_poles_included():
    """F1 is 1-Lipschitz in 3-D (a distance to the nearest point): two points a chord c apart
    differ by at most c cells. Across the antimeridian the old field jumped by up to a whole cell."""
    detail = _cellular()
    rng = np.random.default_rng(1)
    n = 200_000
    # Either side of +-180, 1e-7 degrees (1 cm at the equator) from it.
    lat = np.degrees(np.arcsin(rng.uniform(-0.999, 0.999, n)))
    west, east = np.full(n, 180.0 - 1e-7), np.full(n, -180.0 + 1e-7)
    step = np.abs(detail._f1(lat, west) - detail._f1(lat, east))
    bound = _chord_cells(lat, west, lat, east, detail.cell_m)
    assert (step <= bound + 1e-9).all(), float(step.max())  # old code: up to 0.99
    # Anywhere: pairs 3 m apart in random directions over the globe.
    lat_a = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    lon_a = rng.uniform(-180.0, 180.0, n)
    bearing = rng.uniform(0.0, 2.0 * math.pi, n)
    lat_b = np.clip(lat_a + np.degrees(3.0 * np.cos(bearing) / 6.371e6), -90.0, 90.0)
    lon_b = (lon_a + np.degrees(3.0 * np.sin(bearing) / (6.371e6 * np.maximum(np.cos(np.radians(lat_a)), 1e-3)))
             + 180.0) % 360.0 - 180.0
    step = np.abs(detail._f1(lat_a, lon_a) - detail._f1(lat_b, lon_b))
    assert (step <= _chord_cells(lat_a, lon_a, lat_b, lon_b, detail.cell_m) + 1e-9).all()
    # A pole is one point: one value whatever the longitude (1e-9 cells: cos(90 deg) is 6e-17, not 0).
    lon = np.linspace(-180.0, 180.0, 97)
    for pole in (90.0, -90.0):
        f = detail._f1(np.full(lon.size, pole), lon)
        assert np.ptp(f) < 1e-9


def test_an_import_across_the_antimeridian_has_no_seam_in_its_cellular_detail(tmp_path):
    """The probe's import: a 3" grid either side of 180 with 3 m of noise, imported lossless with
    and without cellular detail. The detail (the difference) between adjacent level-0 columns is
    bounded by the amplitude times the posts' chord in cells (F1 is 1-Lipschitz), plus 2 cm of
    rounding, at the antimeridian as elsewhere: 0.57 m; it stepped 1.06 m there."""
    heights = 300.0 + np.random.default_rng(2).normal(0.0, 3.0, (40, 60))
    src = _write_asc(tmp_path / "am.asc", -17.2, 180.0 - 30 * SP, SP, SP, heights)
    import_dems([src], tmp_path / "cell", lossless=True, add_detail="cellular")
    import_dems([src], tmp_path / "plain", lossless=True)
    plain, cell = st.TerrainStore(tmp_path / "plain"), st.TerrainStore(tmp_path / "cell")
    r = plain.regions[0].rects[0]
    assert cell.regions[0].rects[0] == r
    h_plain, c_plain = plain.decode(plain.regions[0], 0, r.row0, r.row1, r.col0, r.col1)
    h_cell, _ = cell.decode(cell.regions[0], 0, r.row0, r.row1, r.col0, r.col1)
    amplitude = cell.manifest["sources"][0]["detail_amplitude_m"]
    assert amplitude > 1.0 and heights.min() > 3 * amplitude  # land: the detail at full weight
    both = (c_plain[:, 1:] != st.CLASS_OUTSIDE) & (c_plain[:, :-1] != st.CLASS_OUTSIDE)
    step = np.abs(np.diff(h_cell - h_plain, axis=1))
    dlat, dlon = plain.spacing_deg(0)
    lat = np.repeat(90.0 - (r.row0 + np.arange(r.rows)) * dlat, r.cols - 1).reshape(r.rows, r.cols - 1)
    lon = np.tile((r.col0 + np.arange(r.cols - 1)) * dlon - 180.0, (r.rows, 1))
    cell_m = 4.0 * cell.manifest["detail_finest_spacing_m"]  # 4 store posts
    bound = amplitude * _chord_cells(lat, lon, lat, lon + dlon, cell_m) + 0.02
    seam = plain.cols_per_turn(0) - r.col0 - 1  # the step from the last column before 180 to the first after
    assert both[:, seam].sum() > 50 and both.sum() > 5000
    assert (step[both] <= bound[both]).all(), float((step - bound)[both].max())
    assert step[both[:, seam], seam].max() <= bound[both[:, seam], seam].max()


# --------------------------------------------------------------------------- 2: isotropic

@pytest.mark.parametrize("lat0, lon0", [(45.0, 1.0), (45.0, 90.0), (45.0, 179.0), (70.0, -120.0),
                                        (-60.0, 179.99)])
def test_cellular_bumps_are_round_whatever_the_longitude(lat0, lon0):
    """The field's correlation between points 40 m apart, by bearing: one value (within 0.03, the
    sampling noise of 40,000 pairs being about 0.004) at every bearing, and the same at every
    place (0.715 +- 0.015). The old field's ranged 0.27-0.85 at 45 N 90 E, -0.05-0.93 at 179 E."""
    detail = _cellular()
    rng = np.random.default_rng(0)
    n = 40_000
    north, east = rng.uniform(-2e4, 2e4, n), rng.uniform(-2e4, 2e4, n)
    R = 6_371_000.0

    def at(e, nn):
        lat = lat0 + np.degrees(nn / R)
        lon = lon0 + np.degrees(e / (R * math.cos(math.radians(lat0))))
        return detail._f1(lat, (lon + 180.0) % 360.0 - 180.0)

    f0 = at(east, north)
    corr = []
    for bearing in np.radians(np.arange(0.0, 180.0, 22.5)):
        f1 = at(east + 40.0 * math.sin(bearing), north + 40.0 * math.cos(bearing))
        corr.append(np.corrcoef(f0, f1)[0, 1])
    assert np.ptp(corr) < 0.03, corr
    assert abs(np.mean(corr) - 0.715) < 0.015, corr


# --------------------------------------------------------------------------- 3: zero mean

def test_cellular_detail_has_zero_mean():
    """Over 4 M points uniform on the globe the detail averages 0 (within 0.01 a unit of amplitude;
    the sampling error is 1e-4): it averaged -0.0706. Its least value is -CELLULAR_F1_MEAN (F1 >= 0),
    which keeps land above the sea (docs/STORE.md, Import step 3)."""
    detail = _cellular(seed=5)
    rng = np.random.default_rng(4)
    n = 4_000_000
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    f = detail._f1(lat, rng.uniform(-180.0, 180.0, n))
    assert abs(f.mean()) < 0.01, f.mean()
    assert f.min() >= -CELLULAR_F1_MEAN
    assert 0.15 < f.std() < 0.2  # 0.172 (the constant's comment)


def test_the_cellular_field_is_exact_worley_f1_and_deterministic():
    """The kernel's F1 is the distance to the nearest feature point of a brute-force search of
    7^3 cubes (its search of 27 cubes, then 125 where the nearest may lie further, is exact), each
    cube's point from terrain.procedural.lattice_hash(seed, i, j, k); the same seed gives the same
    bits, another seed another field."""
    rng = np.random.default_rng(9)
    n, seed = 20_000, 77
    p = rng.uniform(-4e4, 4e4, (3, n))  # cells: ECEF coordinates at depth 10 reach 4.2e4
    got = np.empty(n)
    _worley_f1_cells(p[0].copy(), p[1].copy(), p[2].copy(), np.uint64(seed), got)
    cube = np.floor(p).astype(np.int64)
    best = np.full(n, np.inf)
    mask = np.uint64((1 << 21) - 1)
    for a in range(-3, 4):
        for b in range(-3, 4):
            for c in range(-3, 4):
                h = lattice_hash(seed, cube[0] + a, cube[1] + b, cube[2] + c)
                jitter = [((h >> np.uint64(s)) & mask).astype(np.float64) / 2.0**21 for s in (0, 21, 42)]
                d2 = sum((cube[k] + o + jitter[k] - p[k]) ** 2 for k, o in enumerate((a, b, c)))
                best = np.minimum(best, d2)
    np.testing.assert_allclose(got, np.sqrt(best), rtol=0, atol=1e-9)
    lat, lon = rng.uniform(-90, 90, 1000), rng.uniform(-180, 180, 1000)
    assert np.array_equal(_cellular(3)._f1(lat, lon), _cellular(3)._f1(lat, lon))
    assert np.abs(_cellular(3)._f1(lat, lon) - _cellular(4)._f1(lat, lon)).max() > 0.3


# --------------------------------------------------------------------------- 4: a turn, once

def _round_the_globe(tmp_path: Path, split: bool) -> list[Path]:
    """A grid at 1 degree of longitude round the globe (89.8-90 N), 500 + 20 sin(3 lon) m: one
    360-degree file, or three overlapping ones chained round it (the last across 180)."""
    lat = 89.80 + 0.05 * np.arange(5)
    if not split:
        lon = -179.5 + np.arange(360.0)
        return [_write_asc(tmp_path / "globe.asc", 89.8, -179.5, 0.05, 1.0,
                           500.0 + 20.0 * np.sin(np.radians(3.0 * lon))[None, :] + 0.0 * lat[:, None])]
    paths = []
    for k, (west, cols) in enumerate([(-179.5, 130), (-60.5, 131), (60.5, 125)]):
        lon = west + np.arange(float(cols))
        paths.append(_write_asc(tmp_path / f"part{k}.asc", 89.8, west, 0.05, 1.0,
                                500.0 + 20.0 * np.sin(np.radians(3.0 * lon))[None, :] + 0.0 * lat[:, None]))
    return paths


@pytest.mark.parametrize("split", [False, True])
def test_a_region_round_the_globe_is_one_turn_of_columns(tmp_path, split):
    """Every level's rectangle is one turn from the antimeridian (tile-aligned: a turn is 3 2^D T
    columns), so each lattice post is stored once and the summary counts it once. The old region
    of a 360-degree source was a tile wider than a turn (6,400 columns where a turn has 6,144)."""
    summary = import_dems(_round_the_globe(tmp_path, split), tmp_path / "st")
    store = st.TerrainStore(tmp_path / "st")
    assert len(store.regions) == 1
    region = store.regions[0]
    for level, rect in enumerate(region.rects):
        assert (rect.col0, rect.cols) == (0, store.cols_per_turn(level)), (level, rect)
    r = region.rects[0]
    _, classes = store.decode(region, 0, r.row0, r.row1, r.col0, r.col1)
    rows_with_data = int((classes != st.CLASS_OUTSIDE).any(axis=1).sum())
    assert (classes[(classes != st.CLASS_OUTSIDE).any(axis=1)] != st.CLASS_OUTSIDE).all()  # every column
    assert summary.posts == rows_with_data * store.cols_per_turn(0)
    assert summary.bounds[0][1] == -180.0 and summary.bounds[0][3] == pytest.approx(180.0 - store.dlon, abs=1e-9)


def test_heights_are_continuous_across_a_round_the_globe_regions_own_wrap(tmp_path):
    """The posts either side of the region's wrap (its last column, and its first a turn on) are
    read together: points between them answer, and interpolate the source (within the store's
    half step and the cell's bilinear error, 0.02 m), through StoreSource as through the raster
    of a box across 180."""
    from terrain.mosaic import load_sources
    from terrain.terrain import Terrain

    paths = _round_the_globe(tmp_path, split=False)
    import_dems(paths, tmp_path / "st", lossless=True)
    store = st.TerrainStore(tmp_path / "st")
    dlon = store.dlon
    lon = np.concatenate([180.0 - dlon * np.linspace(1.5, 0.0, 13), -180.0 + dlon * np.linspace(0.0, 1.5, 13)])
    lat = np.full(lon.size, 89.87)
    got = Terrain([st.StoreSource(store)]).heights(lat, lon)
    want = Terrain(load_sources(paths)).heights(lat, lon).height_msl_m
    assert (got.status == STATUS_OK).all(), got.status
    np.testing.assert_allclose(got.height_msl_m, want, rtol=0, atol=0.02)
    raster = store.raster(0, 89.85, 179.9, 89.9, 180.1)
    assert raster is not None and not np.isnan(raster.heights).any()
