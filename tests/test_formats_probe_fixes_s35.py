"""DEM formats, acceptance probe s35: GeoTIFFs as GDAL leaves them that the reader took for heights of
0 m or -3.4e38 m with STATUS_OK: a sparse file's unwritten blocks (SPARSE_OK) when tifffile could not
parse its GDAL_NODATA in the image's dtype, a nodata value kept in GDAL's PAM sidecar (.aux.xml), and
undeclared nodata sentinels; and a GDAL_NODATA with a decimal comma, which GDAL reads.

Every surface here is the plane h = 1000 + 200 (lat - 46) + 300 (lon - 8) m (lat, lon degrees), which
the bilinear surface reproduces exactly and the harmonic void fill too (a plane is harmonic), so the
reference at any point is the formula. Each test names what the code before the fix did instead."""

from __future__ import annotations

import logging
import struct

import numpy as np
import pytest
import tifffile

from client.terrain_client import TerrainClient
from server.terrain_service import create_server
from sortie.errors import DataFormatError
from terrain.dem import read_dem, read_geotiff
from terrain.mosaic import load_sources
from terrain.raster import STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE
from terrain.terrain import Terrain

LAT0, LON0, D = 46.0, 8.0, 0.01  # the south-west post and the spacing, degrees
F32_LOWEST = "-3.4028234663852886e+38"  # how GDAL prints float32's lowest value as GDAL_NODATA
# int16 posts are the plane rounded to the metre: 0.5 m; the fill is exact for a plane, to its 1 mm tolerance.
BOUND_INT_M = 0.5 + 1e-3
BOUND_FLOAT_M = 1e-3


def plane(lat, lon):
    return 1000.0 + 200.0 * (np.asarray(lat) - LAT0) + 300.0 * (np.asarray(lon) - LON0)


def _posts(n, dtype):
    """(n, n) posts of the plane, row 0 north, PixelIsPoint at (LAT0 + (n-1-r) D, LON0 + c D)."""
    r, c = np.mgrid[0:n, 0:n]
    h = plane(LAT0 + (n - 1 - r) * D, LON0 + c * D)
    return (np.round(h) if np.dtype(dtype).kind in "iu" else h).astype(dtype)


def _geotiff(path, data, nodata=None, **write):
    directory = [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 2, 2048, 0, 1, 4326]
    top = LAT0 + (data.shape[0] - 1) * D
    tags = [(34735, "H", len(directory), directory, True), (33550, "d", 3, (D, D, 0.0), True),
            (33922, "d", 6, (0, 0, 0, LON0, top, 0), True)]
    if nodata is not None:
        tags.append((42113, "s", 0, nodata, True))
    tifffile.imwrite(path, data, extratags=tags, **write)
    return path


def _leave_unwritten(path, segments):
    """Zero the offset and byte count of these strips or tiles, as GDAL's SPARSE_OK=TRUE leaves a
    block of nodata alone (GDAL GTiff driver documentation, "Sparse files")."""
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        where = []
        for name in (("TileOffsets", "TileByteCounts") if page.is_tiled else ("StripOffsets", "StripByteCounts")):
            tag = page.tags[name]
            size = {3: 2, 4: 4, 16: 8}[int(tag.dtype)]
            where += [(tag.valueoffset + k * size, tif.byteorder + {2: "H", 4: "I", 8: "Q"}[size]) for k in segments]
    with open(path, "r+b") as f:
        for at, fmt in where:
            f.seek(at)
            f.write(struct.pack(fmt, 0))


def _grid(n, step=0.25):
    """Query points strictly inside an n x n raster, (lat, lon) degrees."""
    lat, lon = np.meshgrid(LAT0 + np.arange(step, n - 1, step * 3.1) * D, LON0 + np.arange(step, n - 1, step * 2.9) * D)
    return lat.ravel(), lon.ravel()


# ------------------------------------------------------------------------------------------ sparse files

@pytest.mark.parametrize("dtype, nodata", [(np.float32, F32_LOWEST), (np.int16, "-9999.0"), (np.uint16, "nan")],
                         ids=["float32-lowest", "int16-9999.0", "uint16-nan"])
def test_unwritten_tiles_of_a_sparse_geotiff_are_voids(tmp_path, dtype, nodata):
    """3 x 3 tiles of 32 x 32 posts; the north-west one (at the raster's edge: where the data ends) and
    the centre one (enclosed: a hole) unwritten. tifffile fills them with the GDAL_NODATA it parses in the
    image's dtype, and with 0 when it cannot (float32's lowest printed in double precision, an integer
    written "-9999.0", NaN for integers). Before: both tiles read as 0 m, STATUS_OK."""
    n = 96
    path = _geotiff(tmp_path / "sparse.tif", _posts(n, dtype), nodata, tile=(32, 32), compression="zlib")
    _leave_unwritten(path, [0, 4])
    terrain = Terrain(load_sources([path]))
    lat, lon = _grid(n)
    r = terrain.heights(lat, lon)
    row_from_north = (n - 1) - (lat - LAT0) / D
    col = (lon - LON0) / D
    nw = (row_from_north < 32) & (col < 32)  # the bilinear cells touching the NW tile's posts
    nw_near = (row_from_north < 33) & (col < 33)
    centre = (row_from_north >= 32) & (row_from_north <= 63) & (col >= 32) & (col <= 63)
    assert np.all(r.status[nw] == STATUS_OUTSIDE) and np.all(np.isnan(r.height_msl_m[nw]))
    assert np.all(r.status[centre] == STATUS_FILLED)
    answered = ~nw_near
    assert np.all(r.status[answered] != STATUS_OUTSIDE)
    bound = BOUND_INT_M if np.dtype(dtype).kind in "iu" else BOUND_FLOAT_M
    assert np.max(np.abs(r.height_msl_m[answered] - plane(lat[answered], lon[answered]))) <= bound


def test_an_unwritten_strip_is_void_over_the_service(tmp_path):
    """A stripped float32 file (4 rows a strip) with its first strip unwritten, served over gRPC. Before:
    that strip answered 0 m with STATUS_OK, here and in-process alike."""
    n = 40
    path = _geotiff(tmp_path / "strips.tif", _posts(n, np.float32), F32_LOWEST, rowsperstrip=4,
                    compression="zlib", predictor=3)
    _leave_unwritten(path, [0])
    terrain = Terrain(load_sources([path]))
    server, port = create_server(terrain, "127.0.0.1:0", max_workers=2)
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            lat = np.array([LAT0 + (n - 1.5) * D, LAT0 + (n - 6.5) * D, LAT0 + 10.25 * D])
            lon = np.array([LON0 + 5.5 * D, LON0 + 5.5 * D, LON0 + 20.75 * D])
            r = client.heights(lat, lon)
            n_ = client.normals(lat, lon)
    finally:
        server.stop(0)
    assert list(r.status) == [STATUS_OUTSIDE, STATUS_OK, STATUS_OK]
    assert np.isnan(r.height_msl_m[0]) and np.isnan(n_.slope_deg[0])
    assert np.max(np.abs(r.height_msl_m[1:] - plane(lat[1:], lon[1:]))) <= BOUND_FLOAT_M


def test_a_sparse_file_without_nodata_reads_its_unwritten_blocks_as_0_as_gdal_does(tmp_path):
    """GDAL reads an unwritten block as 0 when the file declares no nodata: that stays (and it is not
    what the fix turns into a void)."""
    path = _geotiff(tmp_path / "zero.tif", _posts(64, np.int16), None, tile=(32, 32))
    _leave_unwritten(path, [3])  # the south-east tile
    raster = read_geotiff(path)
    assert raster.meta["void_posts"] == 0
    assert np.all(raster.heights[:32, 32:] == 0.0)


# ------------------------------------------------------------------------------------------ GDAL's PAM sidecar

def _with_sentinel_corner(n=30):
    data = _posts(n, np.float32)
    data[:4, :4] = np.float32(F32_LOWEST)  # the north-west corner, at the edge: where the data ends
    data[15, 15] = np.float32(F32_LOWEST)  # an enclosed hole
    return data


def test_nodata_in_the_gdal_pam_sidecar_is_read(tmp_path):
    """gdal_edit.py -a_nodata on a read-only file, or ArcGIS, keep the nodata in <file>.aux.xml, which GDAL
    reads when the TIFF has no GDAL_NODATA tag. Before: those posts read as -3.4e38 m, STATUS_OK (and a
    segment over them went on as if they were a chasm)."""
    path = _geotiff(tmp_path / "pam.tif", _with_sentinel_corner())
    (tmp_path / "pam.tif.aux.xml").write_text(
        '<PAMDataset>\n  <PAMRasterBand band="1">\n    <NoDataValue le_hex_equiv="000000E0FFFFEFC7">'
        f"{F32_LOWEST}</NoDataValue>\n  </PAMRasterBand>\n</PAMDataset>\n")
    raster = read_dem(path)
    assert raster.meta["nodata"] == float(F32_LOWEST)
    assert raster.meta["void_posts_outside"] == 16 and raster.meta["void_posts_filled"] == 1
    terrain = Terrain([raster])
    lat = np.array([LAT0 + 27.5 * D, LAT0 + 14.0 * D, LAT0 + 5.5 * D])
    lon = np.array([LON0 + 1.5 * D, LON0 + 15.0 * D, LON0 + 20.5 * D])
    r = terrain.heights(lat, lon)
    assert list(r.status) == [STATUS_OUTSIDE, STATUS_FILLED, STATUS_OK]
    assert np.max(np.abs(r.height_msl_m[1:] - plane(lat[1:], lon[1:]))) <= BOUND_FLOAT_M


def test_a_damaged_pam_sidecar_is_named(tmp_path):
    path = _geotiff(tmp_path / "bad.tif", _posts(8, np.float32))
    (tmp_path / "bad.tif.aux.xml").write_text('<PAMDataset><PAMRasterBand band="1"><NoDataValue>none'
                                              "</NoDataValue></PAMRasterBand></PAMDataset>")
    with pytest.raises(DataFormatError, match=r"bad\.tif: bad\.tif\.aux\.xml's NoDataValue must be a number, got 'none'"):
        read_dem(path)


# ------------------------------------------------------------------------------------------ nodata text

def test_a_gdal_nodata_with_a_decimal_comma_is_read(tmp_path):
    """GDAL reads the tag with CPLAtofM, which takes a comma or a point as the decimal delimiter (tifffile
    too). Before: DataFormatError "GDAL_NODATA (42113) must be a number, got '-9999,0'"."""
    data = _posts(10, np.int16)
    data[5, 5] = -9999
    raster = read_geotiff(_geotiff(tmp_path / "comma.tif", data, "-9999,0"))
    assert raster.meta["nodata"] == -9999.0 and raster.meta["void_posts_filled"] == 1
    lat, lon = LAT0 + 4.0 * D, LON0 + 5.0 * D  # the filled post (row 5 from the north of 10)
    h = Terrain([raster]).heights([lat], [lon])
    assert h.status[0] == STATUS_FILLED and abs(h.height_msl_m[0] - plane(lat, lon)) <= BOUND_INT_M


# ------------------------------------------------------------------------------------------ undeclared sentinels

def test_an_undeclared_nodata_sentinel_is_refused_by_name(tmp_path):
    """Before: the posts read as heights of -3.4e38 m (or -1e30 m), STATUS_OK."""
    tif = _geotiff(tmp_path / "sentinel.tif", _with_sentinel_corner())
    with pytest.raises(DataFormatError, match=r"sentinel\.tif: 17 posts lie beyond \+-100000 m, the first \(row 14 "
                                              r"from the south, column 15 from the west\) at -3\.40282\d*e\+38 m"):
        read_dem(tif)
    asc = tmp_path / "sentinel.asc"
    asc.write_text("ncols 3\nnrows 3\nxllcenter 8\nyllcenter 46\ncellsize 0.01\n1 2 3\n4 -1e30 6\n7 8 9\n")
    with pytest.raises(DataFormatError, match=r"sentinel\.asc: 1 posts lie beyond .* at -1e\+30 m: a nodata value"):
        read_dem(asc)


def test_the_highest_and_deepest_terrain_is_read(tmp_path):
    """The bound leaves every height on Earth: Mount Everest (8849 m), the Challenger Deep (about -10,935 m)."""
    asc = tmp_path / "extremes.asc"
    asc.write_text("ncols 2\nnrows 2\nxllcenter 86.9\nyllcenter 27.9\ncellsize 0.01\n8849 -10935\n0 0\n")
    assert sorted(read_dem(asc).heights.ravel()) == [-10935.0, 0.0, 0.0, 8849.0]


def test_a_zipped_geotiff_reads_the_pam_sidecar_beside_it(tmp_path):
    """GDAL reads <name>.aux.xml beside a GeoTIFF inside a zip (/vsizip/) too. Before: the sidecar was
    left in the archive and the posts read as -3.4e38 m."""
    import zipfile

    tif = _geotiff(tmp_path / "pam.tif", _with_sentinel_corner())
    pam = ('<PAMDataset><PAMRasterBand band="1"><NoDataValue>' + F32_LOWEST
           + "</NoDataValue></PAMRasterBand></PAMDataset>")
    with zipfile.ZipFile(tmp_path / "pam.zip", "w") as z:
        z.write(tif, "dem/pam.tif")
        z.writestr("dem/pam.tif.aux.xml", pam)
    raster = read_dem(tmp_path / "pam.zip")
    assert raster.meta["void_posts_outside"] == 16 and raster.meta["void_posts_filled"] == 1


@pytest.mark.parametrize("dtype, nodata", [(np.float32, F32_LOWEST), (np.int16, "-9999.0")],
                         ids=["float32-lowest", "int16-9999.0"])
def test_no_warning_about_a_nodata_the_reader_takes_itself(tmp_path, caplog, dtype, nodata):
    """tifffile warned "parsing GDAL_NODATA tag raised ..." on every such file (a value it could not
    take in the image's dtype); read_geotiff reads the tag itself, so nothing is logged, and the
    nodata posts are still voids."""
    posts = _posts(64, dtype)
    posts[20:24, 20:24] = np.float32(F32_LOWEST) if dtype == np.float32 else -9999
    path = _geotiff(tmp_path / "nodata.tif", posts, nodata)
    with caplog.at_level(logging.DEBUG):
        raster = read_geotiff(path)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert raster.filled is not None and raster.filled.sum() == 16
