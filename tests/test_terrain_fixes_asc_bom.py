"""ESRI ASCII grids and their .prj written with a UTF-8 byte order mark (Notepad and other
Windows tools put one at the start of text files): the mark is skipped, nothing else changes."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from sortie.errors import DataFormatError
from terrain.dem import read_asc, read_dem

BOM = b"\xef\xbb\xbf"
HEADER = ["ncols 4", "nrows 3", "xllcorner 9.0", "yllcorner 47.0", "cellsize 0.01", "NODATA_value -9999"]
ROWS = [[1.5, 2, 3, 10], [4, -9999, 6, 10], [7, 8, 9, 10]]
WKT_WGS84 = ('GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",6378137.0,298.257223563]],'
             'PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]]')
WKT_UTM = ('PROJCS["WGS_1984_UTM_Zone_13N",GEOGCS["GCS_WGS_1984",DATUM["D_WGS_1984",SPHEROID["WGS_1984",'
           '6378137.0,298.257223563]]],PROJECTION["Transverse_Mercator"],UNIT["Meter",1.0]]')


def _grid_bytes(newline: str = "\n") -> bytes:
    lines = HEADER + [" ".join(str(v) for v in row) for row in ROWS]
    return (newline.join(lines) + newline).encode("ascii")


def _same_raster(a, b) -> None:
    assert a.georef == b.georef and a.shape == b.shape
    assert np.array_equal(np.asarray(a.heights), np.asarray(b.heights))  # bit for bit, fill included
    assert np.array_equal(a.filled, b.filled)


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_asc_with_a_utf8_bom_reads_as_without_it(tmp_path, newline):
    plain = tmp_path / "plain.asc"
    plain.write_bytes(_grid_bytes(newline))
    marked = tmp_path / "marked.asc"
    marked.write_bytes(BOM + _grid_bytes(newline))
    _same_raster(read_asc(marked), read_asc(plain))
    _same_raster(read_dem(marked), read_asc(plain))


def test_asc_with_a_bom_inside_a_zip_with_a_bom_prj(tmp_path):
    plain = tmp_path / "plain.asc"
    plain.write_bytes(_grid_bytes())
    archive = tmp_path / "g.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("g.asc", BOM + _grid_bytes("\r\n"))
        z.writestr("g.prj", BOM + WKT_WGS84.encode())
    raster = read_dem(archive)
    _same_raster(raster, read_asc(plain))
    assert raster.meta["crs_prj"] == "GCS_WGS_1984"


@pytest.mark.parametrize("prj, outcome", [(WKT_WGS84, "GCS_WGS_1984"), (WKT_UTM, "projected"),
                                          ("Projection    GEOGRAPHIC\r\nDatum         WGS84\r\n", "GEOGRAPHIC")])
def test_prj_with_a_utf8_bom_is_read_as_without_it(tmp_path, prj, outcome):
    """A BOM before the WKT once hid its keyword: the sidecar then read as no CRS at all, and
    a projected grid was silently taken as degrees."""
    path = tmp_path / "g.asc"
    path.write_bytes(_grid_bytes())
    (tmp_path / "g.prj").write_bytes(BOM + prj.encode())
    if outcome == "projected":
        with pytest.raises(DataFormatError, match="g.asc: its g.prj is a projected CRS"):
            read_asc(path)
    else:
        assert read_asc(path).meta["crs_prj"] == outcome


def test_other_non_ascii_bytes_are_still_refused(tmp_path):
    """Only a leading mark is skipped: one elsewhere, or any other non-ASCII byte, is still no grid."""
    for name, data in (("twice.asc", BOM + BOM + _grid_bytes()), ("late.asc", _grid_bytes() + BOM),
                       ("latin.asc", "ncols\u00a04\n".encode("latin-1") + _grid_bytes())):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(DataFormatError, match=f"{name}: not an ASCII grid"):
            read_asc(path)
