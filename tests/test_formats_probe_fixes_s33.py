"""DEM formats, acceptance probe s33: an ESRI grid's .prj read whole (compound CRSs classified by their
horizontal part, their vertical unit and datum applied, ArcInfo's Units DS and Zunits), ESRI's NAD83
name, NODATA compared as GDAL does (float32, NaN), macOS zips, user-defined WGS 84 GeoTIFFs, and
mosaics that compare vertical datums, not their labels.

Each test names what the code before the fix did instead."""

from __future__ import annotations

import math
import zipfile

import numpy as np
import pytest
import tifffile
from pyproj import CRS

from sortie.errors import DataFormatError
from terrain.dem import (
    VERTICAL_DATUM_DEFAULT,
    VERTICAL_DATUM_SRTM,
    VERTICAL_DATUMS_EPSG,
    read_asc,
    read_dem,
)
from terrain.mosaic import load_sources
from terrain.raster import STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE
from terrain.terrain import Terrain

US_FOOT_M = 1200.0 / 3937.0  # EPSG:9003, the US survey foot
ROWS = [[1000, 1001, 1002, 1003], [1004, 1005, 1006, 1007], [1008, 1009, 1010, 1011]]
GEO = ('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],'
       'UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]]')
UTM = ('PROJCS["WGS 84 / UTM zone 19S",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
       'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
       'PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",-69],PARAMETER["scale_factor",0.9996],'
       'PARAMETER["false_easting",500000],PARAMETER["false_northing",10000000],UNIT["metre",1],'
       'AUTHORITY["EPSG","32719"]]')
VERT_FTUS = ('VERT_CS["NAVD88 height (ftUS)",VERT_DATUM["North American Vertical Datum 1988",2005],'
             'UNIT["US survey foot",0.304800609601219],AXIS["Up",UP]]')
VERT_M = 'VERT_CS["EGM96 height",VERT_DATUM["EGM96 geoid",2005],UNIT["metre",1],AXIS["Up",UP]]'


def _asc(path, prj, x0=-70.0, y0=-33.0, cellsize=0.01, rows=ROWS):
    body = "\n".join(" ".join(str(v) for v in row) for row in rows)
    path.write_text(f"ncols {len(rows[0])}\nnrows {len(rows)}\nxllcorner {x0}\nyllcorner {y0}\n"
                    f"cellsize {cellsize}\n{body}\n")
    if prj is not None:
        path.with_suffix(".prj").write_text(prj)
    return path


def _geotiff(path, data, keys, scale, tie, nodata=None):
    """A GeoTIFF of ``data`` (row 0 north) with GeoKeys ``keys`` [(id, location, count, value)]."""
    directory = [1, 1, 0, len(keys)] + [v for k in sorted(keys) for v in k]
    tags = [(34735, "H", len(directory), directory, False), (33550, "d", 3, list(scale), False),
            (33922, "d", 6, list(tie), False)]
    if nodata is not None:
        tags.append((42113, "s", 0, nodata, False))
    tifffile.imwrite(path, data, extratags=tags)
    return path


# --------------------------------------------------------------------------- 1. compound CRSs, units

@pytest.mark.parametrize("prj", [f'COMPD_CS["WGS 84 + NAVD88 height (ftUS)",{GEO},{VERT_FTUS}]',
                                 CRS("EPSG:4269+6360").to_wkt("WKT1_ESRI"),   # GEOGCS[...],VERTCS[...]
                                 CRS("EPSG:4326+6360").to_wkt("WKT2_2019")],
                         ids=["compd_cs", "esri", "wkt2"])
def test_a_compound_prj_in_us_survey_feet_is_read_in_metres(tmp_path, prj):
    """Before: 1011 ft read as 1011 m (3.28x too high). Now x 1200/3937 exactly, on NAVD88 as a GeoTIFF
    on 5703 is, and the same heights as the GeoTIFF reader gives for VerticalUnitsGeoKey 9003."""
    raster = read_asc(_asc(tmp_path / "g.asc", prj))
    expected = np.array(ROWS[::-1], float) * US_FOOT_M
    assert np.array_equal(raster.heights, expected)
    assert abs(float(raster.heights.max()) - 308.153) < 1e-3
    assert raster.meta["vertical_units"] == "US survey foot"
    assert raster.vertical_datum == VERTICAL_DATUMS_EPSG[5703]
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 1), (2048, 0, 1, 4326), (4096, 0, 1, 5703), (4099, 0, 1, 9003)]
    tif = read_dem(_geotiff(tmp_path / "g.tif", np.array(ROWS, np.float32), keys, (0.01, 0.01, 0),
                            (0, 0, 0, -70.0, -32.97, 0)))
    assert np.array_equal(tif.heights, raster.heights) and tif.vertical_datum == raster.vertical_datum


@pytest.mark.parametrize("zunits, to_m", [("FEET", US_FOOT_M), ("METERS", 1.0), ("NO", 1.0)])
def test_arcinfo_zunits_are_applied(tmp_path, zunits, to_m):
    """Before: Zunits ignored, feet read as metres. FEET is the US survey foot, as GDAL's importFromESRI
    reads FEET in this form."""
    prj = f"Projection    GEOGRAPHIC\nDatum         WGS84\nZunits        {zunits}\nUnits         DD\n"
    raster = read_asc(_asc(tmp_path / "g.asc", prj))
    assert np.array_equal(raster.heights, np.array(ROWS[::-1], float) * to_m)
    assert raster.vertical_datum == VERTICAL_DATUM_DEFAULT


@pytest.mark.parametrize("prj, message", [
    ("Projection GEOGRAPHIC\nDatum WGS84\nZunits INCHES\n", r"gives Zunits 'INCHES'; read are NO .*FEET"),
    ("Projection GEOGRAPHIC\nDatum WGS84\nUnits DMS\n", r"gives Units 'DMS' for a GEOGRAPHIC projection"),
    (f'COMPD_CS["x",{GEO},VERT_CS["h",VERT_DATUM["EGM96 geoid",2005],UNIT["furlong",201.168],AXIS["Up",UP]]]',
     r"vertical CRS \(h\) gives heights in 'furlong' \(201.168 m\)"),
    (f'COMPD_CS["x",{GEO},VERT_CS["d",VERT_DATUM["EGM96 geoid",2005],UNIT["metre",1],AXIS["Down",DOWN]]]',
     r"vertical CRS \(d\) has its axis down: depths"),
    (CRS("EPSG:4269+5703").to_wkt("WKT1_ESRI").replace('"Vertical_Shift",0.0', '"Vertical_Shift",1.5'),
     r"vertical CRS \(NAVD88 height\) has Vertical_Shift 1.5"),
], ids=["zunits-inches", "units-dms", "furlong", "depth", "esri-shift"])
def test_units_and_vertical_systems_it_cannot_read_are_refused_by_name(tmp_path, prj, message):
    """Before: all read silently, the values as metres above mean sea level and the coordinates as degrees."""
    with pytest.raises(DataFormatError, match=r"g\.asc: its g\.prj.* " + message):
        read_asc(_asc(tmp_path / "g.asc", prj))


def test_a_compound_prj_names_its_vertical_datum(tmp_path):
    """Before: "as supplied" whatever the .prj said. A vertical CRS on EGM96 (by name, no authority code)
    gives the GeoTIFF reader's EGM96 label, so the grid merges with SRTM and EPSG:5773 tiles."""
    raster = read_asc(_asc(tmp_path / "g.asc", f'COMPD_CS["WGS 84 + EGM96 height",{GEO},{VERT_M}]'))
    assert raster.vertical_datum == VERTICAL_DATUMS_EPSG[5773]
    assert np.array_equal(raster.heights, np.array(ROWS[::-1], float)) and "vertical_units" not in raster.meta


@pytest.mark.parametrize("prj", [f'COMPD_CS["WGS 84 / UTM zone 19S + EGM96 height",{UTM},{VERT_M}]',
                                 CRS("EPSG:32719+5773").to_wkt("WKT2_2019"),
                                 CRS("EPSG:32719+5773").to_wkt("WKT1_ESRI")],  # PROJCS[...],VERTCS[...]
                         ids=["compd_cs", "wkt2", "esri"])
@pytest.mark.parametrize("x0, y0, cellsize", [(350000.0, 6300000.0, 30.0), (35.0, 10.0, 0.5)],
                         ids=["utm-metres", "small-coordinates"])
def test_a_projected_compound_prj_is_refused_by_name(tmp_path, prj, x0, y0, cellsize):
    """Before: "posts span latitudes 6300015.0..6300075.0, beyond the poles", and with small coordinates
    the UTM grid was read silently as degrees at 35 E, 10 N."""
    with pytest.raises(DataFormatError, match=r"g\.asc: its g\.prj is a projected CRS \(WGS 84 / UTM zone 19S, "
                                              r"the horizontal part of compound CRS"):
        read_asc(_asc(tmp_path / "g.asc", prj, x0, y0, cellsize))


def test_arcinfo_units_ds_are_arc_seconds(tmp_path):
    """Before: "beyond the poles". Units DS: the header's coordinates and cell size are arc-seconds, as
    GDAL's AAIGrid driver reads them (its geotransform divided by 3600): the same grid in degrees."""
    ds = read_asc(_asc(tmp_path / "ds.asc", "Projection GEOGRAPHIC\nDatum WGS84\nZunits NO\nUnits DS\n",
                       -252000.0, -118800.0, 3.0))
    dd = read_asc(_asc(tmp_path / "dd.asc", "Projection GEOGRAPHIC\nDatum WGS84\nUnits DD\n",
                       -70.0, -33.0, 3.0 / 3600.0))
    for a, b in zip((ds.georef.x0, ds.georef.y0, ds.georef.dx, ds.georef.dy),
                    (dd.georef.x0, dd.georef.y0, dd.georef.dx, dd.georef.dy)):
        assert math.isclose(a, b, rel_tol=1e-13)
    assert np.array_equal(ds.heights, dd.heights) and ds.meta["horizontal_units"] == "arc-second"


# --------------------------------------------------------------------------- 2. ESRI's NAD83

@pytest.mark.parametrize("prj", [
    'GEOGCS["GCS_North_American_1983",DATUM["D_North_American_1983",SPHEROID["GRS_1980",6378137.0,'
    '298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]]',  # GDAL's morphToESRI, USGS NED
    CRS(4152).to_wkt("WKT1_ESRI"), CRS(4617).to_wkt("WKT1_ESRI"), CRS(6318).to_wkt("WKT1_ESRI"),
], ids=["nad83", "nad83-harn", "nad83-csrs", "nad83-2011"])
def test_esri_nad83_prj_is_read(tmp_path, prj):
    """Before: "is on datum 'D_North_American_1983'; read are WGS 84, NAD83 and ETRS89"."""
    raster = read_asc(_asc(tmp_path / "g.asc", prj))
    assert raster.meta["crs_prj"].startswith(("GCS_North_American_1983", "GCS_NAD_1983"))
    assert (raster.georef.x0, raster.georef.y0) == (-69.995, -32.995)


@pytest.mark.parametrize("code, datum", [(4267, "D_North_American_1927"), (4230, "D_European_1950")])
def test_other_esri_datums_are_still_refused(tmp_path, code, datum):
    with pytest.raises(DataFormatError, match=f"g.prj is on datum '{datum}'"):
        read_asc(_asc(tmp_path / "g.asc", CRS(code).to_wkt("WKT1_ESRI")))


# --------------------------------------------------------------------------- 4, 5. NODATA

def test_asc_nodata_is_compared_in_float32_as_gdal_does(tmp_path):
    """Header nodata at full double precision, cells at float32 precision: both are float32's lowest
    value. Before: the enclosed void read as h = -3.4028235e+38 status OK, the edge void too."""
    ny, nx = 8, 10
    values = np.round(np.random.default_rng(15).uniform(100, 900, (ny, nx)), 3).astype(object)
    values[3:5, 4:6] = "-3.4028235e+38"  # enclosed
    values[0, :3] = "-3.4028235e+38"    # at the north edge
    body = "\n".join(" ".join(str(v) for v in row) for row in values)
    path = tmp_path / "g.asc"
    path.write_text(f"ncols {nx}\nnrows {ny}\nxllcorner -70.0\nyllcorner -33.0\ncellsize 0.01\n"
                    f"NODATA_value -3.4028234663852886e+38\n{body}\n")
    raster = read_asc(path)
    assert raster.meta["void_posts"] == 7 and raster.meta["void_posts_filled"] == 4
    ring = np.array([v for v in values[2:6, 3:7].ravel() if isinstance(v, float)])
    h = Terrain([raster]).heights([-33.0 + 0.005 + 3.5 * 0.01, -33.0 + 0.005 + 7 * 0.01],
                                  [-70.0 + 0.005 + 4.5 * 0.01, -70.0 + 0.005 + 1 * 0.01])
    assert h.status[0] == STATUS_FILLED and ring.min() <= h.height_msl_m[0] <= ring.max()
    assert h.status[1] == STATUS_OUTSIDE


def test_asc_nodata_nan_is_read(tmp_path):
    """GDAL's AAIGrid writer prints a NaN nodata as "nan". Before: "header nodata_value must be finite"."""
    path = tmp_path / "g.asc"
    path.write_text("ncols 4\nnrows 4\nxllcorner -70.0\nyllcorner -33.0\ncellsize 0.01\nNODATA_value nan\n"
                    "10 11 12 13\n14 nan 16 17\n18 19 20 21\n22 23 24 25\n")
    raster = read_asc(path)
    assert math.isnan(raster.meta["nodata_value"])
    assert raster.meta["void_posts"] == 1 and raster.meta["void_posts_filled"] == 1
    assert 11.0 <= float(raster.heights[2, 1]) <= 19.0


def test_a_nodata_that_is_not_a_number_is_still_refused(tmp_path):
    path = tmp_path / "g.asc"
    path.write_text("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\nNODATA_value none\n1 2\n3 4\n")
    with pytest.raises(DataFormatError, match="header nodata_value must be a number, got 'none'"):
        read_asc(path)


# --------------------------------------------------------------------------- 6. macOS zips

def test_a_zip_made_on_macos_is_read(tmp_path):
    """The Finder adds __MACOSX/._NAME (AppleDouble) members. Before: "a DEM archive must hold exactly
    one DEM file"."""
    hgt = tmp_path / "S33W071.hgt"
    posts = np.random.default_rng(5).integers(0, 3000, (121, 121)).astype(">i2")
    posts.tofile(hgt)
    archive = tmp_path / "S33W071.SRTMGL3.hgt.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.write(hgt, "S33W071.hgt")
        z.writestr("__MACOSX/._S33W071.hgt", b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        " + bytes(58))
        z.writestr("._S33W071.hgt", b"\x00\x05\x16\x07")
    raster = read_dem(archive)
    assert raster.source.endswith("!S33W071.hgt")
    assert np.array_equal(raster.heights, posts[::-1].astype(np.float32))


def test_a_macos_zip_of_a_grid_reads_its_own_prj(tmp_path):
    _asc(tmp_path / "g.asc", None)
    archive = tmp_path / "g.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.write(tmp_path / "g.asc", "grid/g.asc")
        z.writestr("grid/g.prj", CRS("EPSG:4326+6360").to_wkt("WKT1_ESRI"))
        for name in ("__MACOSX/grid/._g.asc", "__MACOSX/grid/._g.prj", "grid/._g.asc", "grid/._g.prj"):
            z.writestr(name, b"\x00\x05\x16\x07")
    raster = read_dem(archive)
    assert raster.meta["vertical_units"] == "US survey foot"
    assert np.array_equal(raster.heights, np.array(ROWS[::-1], float) * US_FOOT_M)


# --------------------------------------------------------------------------- 7. user-defined geographic GeoTIFF

def _userdefined(path, datum, meridian=8901, extra=()):
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 1), (2048, 0, 1, 32767), (2054, 0, 1, 9102), (2056, 0, 1, 7030)]
    keys += [(2050, 0, 1, datum)] if datum is not None else []
    keys += [(2051, 0, 1, meridian)] if meridian is not None else []
    return _geotiff(path, np.arange(12, dtype=np.float32).reshape(3, 4) + 100, keys + list(extra),
                    (0.01, 0.01, 0), (0, 0, 0, 150.0, -35.0, 0))


@pytest.mark.parametrize("datum, meridian, name", [(6326, 8901, "WGS 84"), (6326, None, "WGS 84"),
                                                   (6269, 8901, "NAD83"), (6258, 8901, "ETRS89"),
                                                   (1116, 8901, "NAD83(2011)"), (6152, None, "NAD83(HARN)")])
def test_a_user_defined_geographic_crs_on_a_read_datum_is_read(tmp_path, datum, meridian, name):
    """GeographicTypeGeoKey 32767 with GeogGeodeticDatumGeoKey 6326 (GeoTIFF 1.0, as GDAL reads it).
    Before: "unsupported geographic CRS: GeographicTypeGeoKey (2048) = 32767"."""
    raster = read_dem(_userdefined(tmp_path / "u.tif", datum, meridian))
    code = {6326: 4326, 6269: 4269, 6258: 4258, 1116: 6318, 6152: 4152}[datum]
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 1), (2048, 0, 1, code)]
    same = read_dem(_geotiff(tmp_path / "e.tif", np.arange(12, dtype=np.float32).reshape(3, 4) + 100, keys,
                             (0.01, 0.01, 0), (0, 0, 0, 150.0, -35.0, 0)))
    assert raster.georef == same.georef and np.array_equal(raster.heights, same.heights)
    assert raster.meta["horizontal_datum"].startswith(name)
    assert raster.meta["horizontal_datum"] == same.meta["horizontal_datum"]


@pytest.mark.parametrize("datum, meridian", [(6230, 8901), (None, 8901), (6326, 8903), (1133, 8901)],
                         ids=["ed50", "no-datum", "paris", "nad83-cors96"])
def test_a_user_defined_geographic_crs_on_another_datum_is_refused_naming_the_keys(tmp_path, datum, meridian):
    with pytest.raises(DataFormatError, match=rf"GeographicTypeGeoKey \(2048\) = 32767 \(user-defined\) with "
                                              rf"GeogGeodeticDatumGeoKey \(2050\) = {datum} and "
                                              rf"GeogPrimeMeridianGeoKey \(2051\) = {meridian}"):
        read_dem(_userdefined(tmp_path / "u.tif", datum, meridian))


# --------------------------------------------------------------------------- 3. mosaics by vertical datum

def _surface(lat, lon):
    return np.round(800 + 300 * np.sin(5 * lat) * np.cos(4 * lon) + 100 * lon)


N = 121  # posts a side of the test tile: 30" posts


def _tile(path):
    lat = -33 + np.arange(N) / (N - 1)
    lon = -71 + np.arange(N) / (N - 1)
    _surface(*np.meshgrid(lat, lon, indexing="ij")).astype(">i2")[::-1].tofile(path)
    return path


def _cells(path, first_lon, vertical, m=60):
    """m x m cell-area posts on the tile's 30" lattice, the first column's centre at first_lon."""
    step = 1.0 / (N - 1)
    top = -32.0 - 10 * step
    lat = top - np.arange(m) * step
    lon = first_lon + np.arange(m) * step
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 1), (2048, 0, 1, 4326)]
    keys += [(4096, 0, 1, vertical)] if vertical is not None else []
    data = _surface(*np.meshgrid(lat, lon, indexing="ij")).astype(np.int16)
    return _geotiff(path, data, keys, (step, step, 0), (0, 0, 0, first_lon - step / 2, top + step / 2, 0))


def _strip_statuses(files, lon):
    lat = np.linspace(-32.5, -32.1, 200)
    sources = load_sources(files)
    return sources, Terrain(sources).heights(lat, np.full_like(lat, lon))


def test_srtm_and_an_egm96_geotiff_merge_across_the_cell_between_them(tmp_path):
    """An SRTM tile and a GeoTIFF declaring EGM96 (5773) abutting one post apart on the same lattice.
    Before: two sources (labels 'EGM96 geoid (SRTM)', 'EGM96 geoid (EPSG:5773)') and every sample of the
    one-post strip between them OUTSIDE. Now one mosaic, the strip answered from both sides' posts."""
    step = 1.0 / (N - 1)
    files = [_tile(tmp_path / "S33W071.hgt"), _cells(tmp_path / "east.tif", -70.0 + step, 5773)]
    sources, h = _strip_statuses(files, -70.0 + step / 2)
    assert len(sources) == 1 and sources[0].vertical_datum == VERTICAL_DATUM_SRTM
    assert np.all(h.status == STATUS_OK)
    lat = np.linspace(-32.5, -32.1, 200)
    west, east = _surface(lat, -70.0), _surface(lat, -70.0 + step)  # bounds of the bilinear surface
    assert np.all(h.height_msl_m >= np.minimum(west, east).min() - 1e-3)
    assert np.all(h.height_msl_m <= np.maximum(west, east).max() + 1e-3)


@pytest.mark.parametrize("west, east, merged", [
    (5703, 5103, True),     # NAVD88 by EPSG and by GeoTIFF 1.0's VertCS code: one datum
    (5701, 5101, True),     # Ordnance Datum Newlyn likewise
    (5773, 3855, False),    # EGM96 and EGM2008: different datums still do not merge
    (None, 5773, False),    # no vertical key: "as supplied", not claimed to be EGM96 (ARCHITECTURE.md)
    (None, None, True),     # as before
])
def test_geotiffs_merge_when_their_vertical_datum_is_one(tmp_path, west, east, merged):
    step = 1.0 / (N - 1)
    files = [_cells(tmp_path / "w.tif", -70.5 - 59 * step, west), _cells(tmp_path / "e.tif", -70.5 + step, east)]
    sources, h = _strip_statuses(files, -70.5 + step / 2)
    assert len(sources) == (1 if merged else 2)
    assert np.all(h.status == (STATUS_OK if merged else STATUS_OUTSIDE))


def test_vertical_datum_identity():
    from terrain.dem import vertical_datum_identity

    assert vertical_datum_identity(VERTICAL_DATUM_SRTM) == vertical_datum_identity(VERTICAL_DATUMS_EPSG[5773])
    assert vertical_datum_identity(VERTICAL_DATUMS_EPSG[5703]) == vertical_datum_identity(VERTICAL_DATUMS_EPSG[5103])
    assert vertical_datum_identity(VERTICAL_DATUMS_EPSG[3855]) != vertical_datum_identity(VERTICAL_DATUMS_EPSG[5773])
    assert vertical_datum_identity(VERTICAL_DATUM_DEFAULT) == VERTICAL_DATUM_DEFAULT
    assert vertical_datum_identity("some other datum") == "some other datum"
