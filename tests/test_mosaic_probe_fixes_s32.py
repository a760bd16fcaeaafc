"""Session 32 mosaic probe fixes: wide periodic rasters in the ray walk, the import's error summary,
Web Mercator tiles across the antimeridian, and a DEM listed between two abutting tiles."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from terrain.los import intersect_segments, line_of_sight
from terrain.geodesy import web_mercator_inverse
from terrain.mosaic import mosaic
from terrain.raster import CRS_GEOGRAPHIC, CRS_WEB_MERCATOR, STATUS_OK, TWO_PI_A_M, Georef, Raster
from terrain.store import StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import Terrain

# Rays over the North Pole and across the antimeridian (the probe's p13/p14 rays, lifted onto the
# test surfaces below): each clears the ground, so the answer is visible, status OK.
POLAR_RAYS = np.array([[89.6085, -99.623, 1420.5, 89.8206, 81.564, 1612.8],
                       [89.7639, 3.649, 1497.9, 89.7987, -178.548, 1464.3]])


def _polar_surface(lat, lon):
    """Smooth on the sphere (a function of the unit vector), so one value at the pole."""
    c = np.cos(np.radians(lat))
    x, y = c * np.cos(np.radians(lon)), c * np.sin(np.radians(lon))
    return 1000.0 + 300.0 * np.sin(8.0 * x) + 200.0 * np.cos(6.0 * y)


def _rays(columns):
    return [columns[:, k] for k in range(6)]


def test_a_raster_wider_than_a_turn_is_walked_periodically_as_its_first_turn():
    """A geographic cap 89..90 N from -180.05 to 180.05 at 0.05 deg (7203 columns, a turn and two
    posts; its posts repeat a turn on) answers rays over the pole and across its seam as the
    exact-turn raster of the same posts does: the same hits to 1 mm and status OK (the walk took it
    as a plain range of columns: every such ray left it, OUTSIDE)."""
    d = 0.05
    rng = np.random.default_rng(32)
    turn = np.round(rng.normal(300.0, 60.0, (21, 7200)), 2)
    turn[-1, :] = 300.0  # the pole row is one point
    wide = Raster(turn[:, np.arange(-1, 7202) % 7200].astype(np.float32), Georef(CRS_GEOGRAPHIC, -180.05, 89.0, d, d))
    exact = Raster(turn[:, np.arange(7201) % 7200].astype(np.float32), Georef(CRS_GEOGRAPHIC, -180.0, 89.0, d, d))
    n = 200
    a_lat, b_lat = rng.uniform(89.6, 89.99, n), rng.uniform(89.6, 89.99, n)
    a_lon = rng.uniform(-180.0, 180.0, n)
    b_lon = np.where(np.arange(n) < n // 2, a_lon + 180.0 + rng.uniform(-20, 20, n),  # over the pole
                     rng.uniform(179.5, 180.5, n))  # across the seam at -180.05 / 179.95
    b_lon = (b_lon + 180.0) % 360.0 - 180.0
    a_h, b_h = rng.uniform(350.0, 700.0, n), rng.uniform(350.0, 700.0, n)
    want = intersect_segments(exact, a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    got = intersect_segments(wide, a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    assert np.all(want[-1] == STATUS_OK) and want[0].any() and (~want[0]).any()
    assert np.all(got[-1] == STATUS_OK)
    assert np.array_equal(got[0], want[0])
    assert np.nanmax(np.abs(got[1] - want[1])) <= 1e-3
    vis, status = line_of_sight(wide, a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    assert np.all(status == STATUS_OK) and np.array_equal(vis, ~want[0])


def test_polar_rays_batched_on_a_store_are_answered_as_alone(tmp_path):
    """On a store of a full-turn polar cap two rays over the pole share one all-longitude raster
    (a turn and two posts wide): each is answered visible, status OK, alone and together (together
    both were OUTSIDE)."""
    sp = 0.1
    lat = 89.0 + sp * np.arange(11)
    lon = -180.0 + sp * np.arange(3601)
    h = _polar_surface(*np.meshgrid(lat, lon, indexing="ij"))
    src = tmp_path / "cap.asc"
    head = [f"ncols {lon.size}", f"nrows {lat.size}", "xllcenter -180.0", "yllcenter 89.0", f"cellsize {sp!r}",
            "NODATA_value -32768"]
    src.write_text("\n".join(head + [" ".join(f"{v:.2f}" for v in row) for row in h[::-1]]) + "\n")
    import_dems([src], tmp_path / "store", resolution_arcsec=120.0)
    terrain = Terrain([StoreSource(TerrainStore(tmp_path / "store"))])
    for rows in ([0], [1], [0, 1]):
        got = terrain.line_of_sight(*_rays(POLAR_RAYS[rows]))
        assert np.all(got.visible) and np.all(got.status == STATUS_OK), (rows, got)


def _asc(path: Path, f, lat0: float, lon0: float, posts: int, spacing_deg: float) -> Path:
    """An ESRI ASCII grid of f(lat, lon) on posts x posts posts from (lat0, lon0) south-west."""
    lat = lat0 + spacing_deg * np.arange(posts)
    lon = lon0 + spacing_deg * np.arange(posts)
    h = f(*np.meshgrid(lat, lon, indexing="ij"))
    head = [f"ncols {posts}", f"nrows {posts}", f"xllcenter {lon0!r}", f"yllcenter {lat0!r}",
            f"cellsize {spacing_deg!r}", "NODATA_value -32768"]
    path.write_text("\n".join(head + [" ".join(f"{v:.3f}" for v in row) for row in h[::-1]]) + "\n")
    return path


def test_the_import_error_vs_sources_counts_only_posts_each_source_answers(tmp_path):
    """A 3" DEM A listed before a 1" DEM B that overlaps a quarter of it and reads 7 m higher: the
    store holds A where A answers, and B's posts under A are not B's error. The RMS error against
    the sources stays under 0.5 m (it was 5.2 m: every B post under A counted as 7 m of error)."""
    def hills(lat, lon):
        return 800.0 + 300.0 * np.sin(lat * 50.0) * np.cos(lon * 45.0)

    a = _asc(tmp_path / "a.asc", hills, -45.05, -70.05, 61, 1.0 / 1200.0)
    b = _asc(tmp_path / "b.asc", lambda la, lo: hills(la, lo) + 7.0, -45.025, -70.025, 181, 1.0 / 3600.0)
    summary = import_dems([a, b], tmp_path / "store", step_m=0.1)
    assert summary.rms_error_vs_source_m <= 0.5, summary


def test_web_mercator_tiles_cut_at_the_antimeridian_merge_across_it():
    """EPSG:3857 cell-centred tiles of 100.19 m cells (400,000 a turn) with cell edges on x = +-pi a
    merge into one raster running on past the antimeridian, which answers OK across it (a cell-wide
    strip at 179.9999..-179.9999 was OUTSIDE: the tiles did not merge)."""
    n, dx = 200, TWO_PI_A_M / 400_000
    y0 = -1.9e6
    half = 0.5 * TWO_PI_A_M
    east = Raster(np.full((n, n), 300.0, np.float32), Georef(CRS_WEB_MERCATOR, half - (n - 0.5) * dx, y0, dx, dx))
    west = Raster(np.full((n, n), 310.0, np.float32), Georef(CRS_WEB_MERCATOR, -half + 0.5 * dx, y0, dx, dx))
    merged = mosaic([east, west])
    assert len(merged) == 1 and merged[0].shape == (n, 2 * n)
    lat, _ = web_mercator_inverse(0.0, y0 + 50 * dx)
    lon = np.array([179.9995, 179.9999, 180.0, -180.0, -179.9999, -179.9995])
    got = Terrain(merged).heights(np.full(lon.size, lat), lon)
    assert np.all(got.status == STATUS_OK)
    assert np.all((got.height_msl_m >= 300.0) & (got.height_msl_m <= 310.0))
