"""DEM readers: SRTM .hgt, ESRI ASCII grid, GeoTIFF and raw 16-bit posts.

Every reader returns a :class:`terrain.raster.Raster` in its one layout:
heights (ny, nx), row 0 the southernmost row, column 0 the westernmost, posts
(point samples) at ``Georef(crs, x0, y0, dx, dy)`` with dx, dy > 0. Files with
north-up rows are flipped, cell-area grids are shifted half a cell so their
posts sit at cell centres, and enclosed voids are filled by :func:`fill_voids`.

Heights are stored as float32 where that is lossless (int16 sources, float32
sources) and float64 otherwise; filled voids are computed in float64 and
rounded once to that dtype.

Void rule. A void (nodata) post whose 4-connected void region touches the
raster's edge is where the data ends (a DEM clipped to a polygon, a tile's
missing corner): it stays NaN, which queries report as STATUS_OUTSIDE so a
lower-priority source answers there, as at a mosaic's outer gaps. A region
enclosed by valid posts is a hole in the data and is filled harmonically:
each void post equals the mean of its four neighbours, the valid posts
around the region fixed (Dirichlet). By the discrete maximum principle a
filled value never leaves the [min, max] range of the valid posts bordering
its region, so a fill never invents a peak or a pit; the solvers' last
rounding is clipped to that range, so the promise holds bit for bit. Filled
posts are marked in ``Raster.filled`` and queries touching them report
STATUS_FILLED; :mod:`terrain.mosaic` and :class:`terrain.terrain.Terrain`
let measured posts of a lower-priority source win over them.

Global rasters. A raster of nx columns spanning exactly a full turn (nx * dx
= 360 degrees: a cell-registered global grid such as ETOPO, GEBCO or GMTED,
whose posts run from -179.5 to 179.5 for 1-degree cells) gets its first
column repeated one turn east (meta["wrap_column_added"]), so heights and
rays cross the seam between its last and first columns (the line-of-sight
walk then treats it as periodic). Rows are not extended: above the last row
of cell centres (89.5 degrees for 1-degree cells) and below the first, the
raster is OUTSIDE, since its data says nothing about the pole itself. Voids
touching the first or last column count as touching the edge.

Cost of a fill, bounded per region: up to FILL_DIRECT_MAX_POSTS posts a
sparse direct solve (SuperLU); larger regions multigrid-preconditioned
conjugate gradients, linear in memory (about 130 bytes a post of the
region's box) and near-linear in time (measured: a 1000 x 1000-post hole
about 1 s and 0.3 GB, 18 iterations, where the direct solve took 8 s and
1.5 GB; a 3400 x 3400 one 15 s and 1.7 GB, 23 iterations), to within
FILL_TOLERANCE_M (1 mm) of the exact harmonic values. A region of
more than FILL_MAX_POSTS posts (the interior of an SRTM1 tile) is refused
with a DataFormatError naming the file.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import shutil
import tempfile
import zipfile
from pathlib import Path, PurePosixPath
from typing import NamedTuple

import numba
import numpy as np
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg
import tifffile

from sortie.errors import DataFormatError, InvalidArgument, LimitExceeded, NotFound
from terrain.raster import CRS_GEOGRAPHIC, CRS_WEB_MERCATOR, TWO_PI_A_M, Georef, Raster

log = logging.getLogger(__name__)


class _TifffileNodataNote(logging.Filter):
    """Drops tifffile's warning that it could not take a GDAL_NODATA in the image's dtype
    ("-9999.0" on int16 posts, float32's lowest printed in float64): :func:`read_geotiff`
    reads the tag itself (:func:`_gdal_nodata`) and finds the blocks tifffile then filled with
    0 (:func:`_unwritten_segments`), so the warning told a user of a problem there is not."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "parsing GDAL_NODATA tag raised" not in record.getMessage()


logging.getLogger("tifffile").addFilter(_TifffileNodataNote())

# SRTM marks a void post with the most negative int16 (SRTM Topography,
# NASA JPL 2005, "Data voids").
SRTM_VOID = -32768

# Name of an SRTM tile: hemisphere letters and the south-west corner in whole
# degrees, e.g. N47E009, S12W077 (then anything: N47E009.SRTMGL1.hgt).
HGT_NAME = re.compile(r"([NS])(\d{2})([EW])(\d{3})", re.IGNORECASE)

# Posts this far (degrees) beyond a pole are rounding, not data.
POLE_TOLERANCE_DEG = 1e-9
# Columns spanning a full turn of longitude to this relative tolerance wrap.
FULL_TURN_TOLERANCE = 1e-9

VERTICAL_DATUM_SRTM = "EGM96 geoid (SRTM)"
VERTICAL_DATUM_DEFAULT = "mean sea level (as supplied)"

# GeoTIFF tags (GeoTIFF 1.0 section 2.4 and 2.6.1; OGC GeoTIFF 1.1,
# OGC 19-008r4, sections 7.1.2 and 7.3) and GDAL's private nodata tag
# (GDAL GeoTIFF driver documentation, "Nodata value").
TAG_MODEL_PIXEL_SCALE = 33550
TAG_MODEL_TIEPOINT = 33922
TAG_MODEL_TRANSFORMATION = 34264
TAG_GEO_KEY_DIRECTORY = 34735
TAG_GEO_DOUBLE_PARAMS = 34736
TAG_GEO_ASCII_PARAMS = 34737
TAG_GDAL_NODATA = 42113
TAG_GDAL_METADATA = 42112

# GeoKey ids (GeoTIFF 1.0 section 6.2; OGC 19-008r4 sections 7.2 and 7.4).
KEY_GT_MODEL_TYPE = 1024
KEY_GT_RASTER_TYPE = 1025
KEY_GEOGRAPHIC_TYPE = 2048  # GeodeticCRSGeoKey in GeoTIFF 1.1
KEY_PROJECTED_CS_TYPE = 3072  # ProjectedCRSGeoKey in GeoTIFF 1.1
KEY_GEOG_ANGULAR_UNITS = 2054
KEY_PROJ_LINEAR_UNITS = 3076
KEY_VERTICAL_CS_TYPE = 4096
KEY_VERTICAL_UNITS = 4099
# VerticalUnitsGeoKey and ProjLinearUnitsGeoKey codes (EPSG units of measure, GeoTIFF 1.0 section
# 6.3.1.3; OGC 19-008r4 7.4.4 and Annex C): metre, international foot (0.3048 m exactly), US
# survey foot (1200/3937 m). Values: (name, metres per unit).
VERTICAL_UNITS_M = {9001: ("metre", 1.0), 9002: ("foot", 0.3048), 9003: ("US survey foot", 1200.0 / 3937.0)}
LINEAR_UNITS_M = VERTICAL_UNITS_M
# GeogAngularUnitsGeoKey codes (EPSG units of measure, GeoTIFF 1.0 section 6.3.1.4; OGC 19-008r4
# 7.4.3): radian, degree, arc-minute, arc-second, grad, gon, and 9122 "degree (supplier to
# define representation)", the unit of EPSG:4326 itself. Values: (name, degrees per unit).
ANGULAR_UNITS_DEG = {9101: ("radian", 180.0 / math.pi), 9102: ("degree", 1.0), 9103: ("arc-minute", 1.0 / 60.0),
                     9104: ("arc-second", 1.0 / 3600.0), 9105: ("grad", 0.9), 9106: ("gon", 0.9),
                     9122: ("degree", 1.0)}
# GDAL's band unit type (GDAL_METADATA <Item role="unittype">, GDALRasterBand::GetUnitType) for
# heights, lower-cased: the names GDAL and PROJ write for metre, foot and US survey foot. Values:
# (name, metres per unit).
GDAL_UNIT_TYPES_M = {**{u: ("metre", 1.0) for u in ("m", "metre", "meter", "metres", "meters")},
                     **{u: ("foot", 0.3048) for u in ("ft", "foot", "feet", "international foot")},
                     **{u: ("US survey foot", 1200.0 / 3937.0)
                        for u in ("us survey foot", "us-ft", "ftus", "us_survey_foot", "foot_us", "us-foot")}}

# GTModelTypeGeoKey codes (GeoTIFF 1.0 section 6.3.1.1).
MODEL_TYPE_PROJECTED = 1
MODEL_TYPE_GEOGRAPHIC = 2
# GTRasterTypeGeoKey codes (GeoTIFF 1.0 section 6.3.1.2; OGC 19-008r4 7.2.1).
RASTER_PIXEL_IS_AREA = 1
RASTER_PIXEL_IS_POINT = 2
# Geographic CRSs read as WGS 84, with the accuracy of the EPSG registry's null
# transformation to it (the datums differ by about that much in position):
# WGS 84 (geographic 3D, 4979: its heights are ellipsoidal unless VerticalCSTypeGeoKey says
# otherwise, see _vertical_datum) exactly; NAD83 (4269, USGS 3DEP DEMs) through
# EPSG:1188 "NAD83 to WGS 84 (1)", 4 m; ETRS89 (4258, European national DEMs)
# through EPSG:1149 "ETRS89 to WGS 84 (1)", 1 m; NAD83's realisations, which the
# newer USGS and NOAA rasters declare, through the registry's null transformations
# to WGS 84, each 2 m (PROJ's proj.db, helmert_transformation, all parameters 0):
# NAD83(HARN) 4152 EPSG:1580, NAD83(CSRS) 4617 EPSG:1842, NAD83(NSRS2007) 4759
# EPSG:15931, NAD83(2011) 6318 EPSG:9774 (the same four the .prj reader below takes
# by name). NAD83(CORS96) 6783 has no transformation to WGS 84 in the registry and is
# refused, as are other datums (ED50, Tokyo, ...), which differ by tens to hundreds
# of metres.
GEOGRAPHIC_AS_WGS84 = {4326: ("WGS 84", 0.0, None), 4979: ("WGS 84 (3D)", 0.0, None),
                       4269: ("NAD83", 4.0, 1188), 4258: ("ETRS89", 1.0, 1149),
                       4152: ("NAD83(HARN)", 2.0, 1580), 4617: ("NAD83(CSRS)", 2.0, 1842),
                       4759: ("NAD83(NSRS2007)", 2.0, 15931), 6318: ("NAD83(2011)", 2.0, 9774)}
# A user-defined geographic CRS (GeographicTypeGeoKey 32767, GeoTIFF 1.0 sections 6.2.2 and 6.3.2.1) given by
# its parts: GeogGeodeticDatumGeoKey (2050, codes 6.3.2.2) and GeogPrimeMeridianGeoKey (2051, codes 6.3.2.4;
# absent: Greenwich, as libgeotiff's GTIFGetDefn leaves a zero offset). On the EPSG datum of one of
# GEOGRAPHIC_AS_WGS84's 2-D CRSs (WGS 84 6326, NAD83 6269, ETRS89 6258, NAD83(HARN) 6152, NAD83(CSRS) 6140,
# NAD83(NSRS2007) 6759, NAD83(2011) 1116; PROJ's proj.db, geodetic_crs.datum_code) with the Greenwich
# meridian (8901) it is that CRS, as GDAL reads it; its angular unit is GeogAngularUnitsGeoKey's, as for
# any geographic raster.
KEY_GEOG_GEODETIC_DATUM = 2050
KEY_GEOG_PRIME_MERIDIAN = 2051
GEOGRAPHIC_USER_DEFINED = 32767
PRIME_MERIDIAN_GREENWICH = 8901
GEOGRAPHIC_OF_DATUM = {6326: 4326, 6269: 4269, 6258: 4258, 6152: 4152, 6140: 4617, 6759: 4759, 1116: 6318}
# EPSG:3857 and its deprecated alias EPSG:3785. The older unofficial code
# 900913 exceeds 65535, so it cannot appear in a SHORT GeoKey value.
EPSG_WEB_MERCATOR = (3857, 3785)
# VerticalCSTypeGeoKey (4096; VerticalGeoKey in OGC 19-008r4 7.4.5) codes read as heights above mean
# sea level: gravity-related heights, whose reference surface is the geoid or a tide-gauge mean sea
# level (within a metre or two of it). EPSG vertical CRSs with an up axis in metres (checked against
# the EPSG registry in PROJ's proj.db: CRS type "Vertical CRS", axis up, unit metre), and GeoTIFF
# 1.0's orthometric codes (section 6.3.4.1, VertCS_Newlyn .. VertCS_Baltic_Sea; their unit is
# VerticalUnitsGeoKey's). Not among them, so refused: ellipsoidal heights (GeoTIFF 1.0's
# VertCS_*_ellipsoid 5001-5033, geographic 3D CRSs such as EPSG:4979), which differ from sea
# level by the geoid undulation (-107 m to +86 m for EGM2008); depths (EPSG:5715 MSL depth, axis
# down); the Caspian Sea's level (GeoTIFF 5106, EPSG:5611; about 28 m below the ocean's); CRSs in
# feet (EPSG:5702, 6360, 8228: their unit would be read as metres without VerticalUnitsGeoKey).
# 32767 (user-defined) and no key at all stay "as supplied" (VERTICAL_DATUM_DEFAULT).
VERTICAL_DATUMS_EPSG = {5773: "EGM96 geoid (EPSG:5773)", 3855: "EGM2008 geoid (EPSG:3855)",
                        5798: "EGM84 geoid (EPSG:5798)", 5714: "mean sea level (EPSG:5714)",
                        5703: "NAVD88 (EPSG:5703)", 5701: "Ordnance Datum Newlyn (EPSG:5701)",
                        5711: "Australian Height Datum (EPSG:5711)", 5705: "Baltic 1977 (EPSG:5705)",
                        5709: "Normaal Amsterdams Peil (EPSG:5709)", 5783: "DHHN92 (EPSG:5783)",
                        7837: "DHHN2016 (EPSG:7837)", 5941: "NN2000 (EPSG:5941)",
                        5713: "CGVD28 (EPSG:5713)", 6647: "CGVD2013 (EPSG:6647)",
                        5101: "Newlyn (GeoTIFF VertCS 5101)", 5102: "NGVD 1929 (GeoTIFF VertCS 5102)",
                        5103: "NAVD 1988 (GeoTIFF VertCS 5103)", 5104: "Yellow Sea 1956 (GeoTIFF VertCS 5104)",
                        5105: "Baltic Sea (GeoTIFF VertCS 5105)"}
VERTICAL_CS_USER_DEFINED = 32767
# The EPSG vertical datum (reference surface) of each system above: PROJ's proj.db, table vertical_crs,
# column datum_code; GeoTIFF 1.0's VertCS 5101-5105 (section 6.3.4.1) are named after the EPSG vertical
# datums of the same codes (5101 Ordnance Datum Newlyn, ..., 5105 Baltic 1977). SRTM's heights are above
# the EGM96 geoid (SRTM Topography, NASA JPL 2005), EPSG datum 5171. Two labels on one datum are one
# system (vertical_datum_identity): "EGM96 geoid (SRTM)" and "EGM96 geoid (EPSG:5773)" merge in a mosaic.
VERTICAL_DATUM_CODES = {5773: 5171, 3855: 1027, 5798: 5203, 5714: 5100, 5703: 5103, 5701: 5101, 5711: 5111,
                        5705: 5105, 5709: 5109, 5783: 5181, 7837: 1170, 5941: 1096, 5713: 5114, 6647: 1127,
                        5101: 5101, 5102: 5102, 5103: 5103, 5104: 5104, 5105: 5105}
EPSG_DATUM_EGM96 = 5171
# GeoTIFF 1.0 section 6.3.4.1: VertCS_Airy_1830_ellipsoid (5001) .. VertCS_OSU91A_ellipsoid (5033).
VERTICAL_CS_ELLIPSOID_CODES = range(5001, 5034)
# Geographic 3D CRSs (EPSG, PROJ's proj.db type "Geographic 3D CRS") a file may give as its vertical
# system: WGS 84, ETRS89, NZGD2000, NAD83(2011), ITRF2014. Their third axis is the ellipsoidal height.
GEOGRAPHIC_3D_CODES = (4979, 4937, 4959, 6319, 7912)
# What the error refusing a vertical system goes on to say.
MSL_ADVICE = ("heights are read as metres above mean sea level: convert them with the geoid (e.g. EGM96/EGM2008), "
              f"or declare VerticalCSTypeGeoKey ({KEY_VERTICAL_CS_TYPE}) 32767 (user-defined) to take them as "
              "supplied; read are " + ", ".join(str(c) for c in VERTICAL_DATUMS_EPSG))
_DATUM_OF_LABEL = {VERTICAL_DATUM_SRTM: EPSG_DATUM_EGM96,
                   **{label: VERTICAL_DATUM_CODES[code] for code, label in VERTICAL_DATUMS_EPSG.items()}}


def vertical_datum_identity(label: str) -> str:
    """The vertical system behind a ``Raster.vertical_datum`` label, for comparing sources: the EPSG
    vertical datum of a label the readers give for one (VERTICAL_DATUM_CODES), else the label itself.
    "mean sea level (as supplied)" (no vertical key, 32767, an ASCII grid without a vertical CRS) is
    its own system: heights taken as supplied are not claimed to be on any named datum."""
    code = _DATUM_OF_LABEL.get(label)
    return label if code is None else f"EPSG vertical datum {code}"


def vertical_datum_label(datum_code: int) -> str | None:
    """The reader's label (VERTICAL_DATUMS_EPSG, an EPSG vertical CRS's before GeoTIFF 1.0's) for heights
    in metres on EPSG vertical datum ``datum_code``; None for a datum not among them."""
    return next((VERTICAL_DATUMS_EPSG[c] for c, d in VERTICAL_DATUM_CODES.items() if d == datum_code), None)


RAW_SUFFIXES = (".raw", ".r16")
# read_raw16's georeference: a raw file cannot be read without it.
RAW_GEOREFERENCE = ("rows", "cols", "lat0", "lon0", "dlat", "dlon")


# --------------------------------------------------------------------------- dispatch

def read_dem(path, **kwargs) -> Raster:
    """Read a DEM file, choosing the reader by suffix (case-insensitive).

    .hgt -> :func:`read_hgt`, .asc -> :func:`read_asc`, .tif/.tiff ->
    :func:`read_geotiff`, .raw/.r16 -> :func:`read_raw16` (which needs its
    georeference as keyword arguments); .zip -> the one DEM inside it, as
    SRTM tiles are distributed (``N47E009.SRTMGL1.hgt.zip``).
    """
    path = _existing(path)
    suffix = path.suffix.lower()
    if suffix == ".zip":
        return _read_zipped(path, **kwargs)
    if suffix == ".hgt":
        return read_hgt(path, **kwargs)
    if suffix == ".asc":
        return read_asc(path, **kwargs)
    if suffix in (".tif", ".tiff"):
        return read_geotiff(path, **kwargs)
    if suffix in RAW_SUFFIXES:
        missing = [k for k in RAW_GEOREFERENCE if k not in kwargs]
        if missing:
            raise DataFormatError(f"{path}: a {suffix} file is headerless 16-bit posts with no georeference; "
                                  f"it lacks {', '.join(missing)} (read_raw16's arguments: rows, cols, the "
                                  "south-west post's lat0, lon0 and the spacing dlat, dlon in degrees), which "
                                  "no DEM option supplies: convert it to a GeoTIFF, or name a square SRTM "
                                  "tile after its corner (N47E009.hgt)")
        return read_raw16(path, **kwargs)
    raise DataFormatError(f"{path}: unknown DEM suffix {path.suffix!r} "
                          f"(expected {', '.join(DEM_SUFFIXES)} or .zip of one of them)")


DEM_SUFFIXES = (".hgt", ".asc", ".tif", ".tiff", *RAW_SUFFIXES)


def file_identity(path) -> dict:
    """{"path": absolute path, "size_bytes": int, "sha256": hex} of a DEM file: what a
    recording keeps of its terrain, and a terrain service tells its clients, so the same
    bytes can be found and checked later."""
    p = _existing(path).resolve()
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return {"path": str(p), "size_bytes": p.stat().st_size, "sha256": h.hexdigest()}
# Largest DEM read out of a .zip (its declared size; a 1" SRTM tile is 26 MB).
MAX_ZIPPED_DEM_BYTES = 4 << 30


def _read_zipped(path: Path, **kwargs) -> Raster:
    """The one DEM file inside a zip archive, read by its own suffix and name."""
    try:
        with zipfile.ZipFile(path) as archive:
            members = [m for m in archive.infolist()
                       if not m.is_dir() and not _archive_metadata(m.filename)
                       and Path(m.filename).suffix.lower() in DEM_SUFFIXES]
            if len(members) != 1:
                names = ", ".join(m.filename for m in archive.infolist()) or "nothing"
                raise DataFormatError(f"{path}: a DEM archive must hold exactly one DEM file "
                                      f"({', '.join(DEM_SUFFIXES)}); it holds {names}")
            member = members[0]
            if member.file_size > MAX_ZIPPED_DEM_BYTES:
                raise DataFormatError(f"{path}: {member.filename} unpacks to {member.file_size} bytes, "
                                      f"over the {MAX_ZIPPED_DEM_BYTES} read from an archive")
            with tempfile.TemporaryDirectory(prefix="sortie-dem-") as tmp:
                inner = Path(tmp) / Path(member.filename).name
                with archive.open(member) as src, open(inner, "wb") as dst:
                    shutil.copyfileobj(src, dst, 1 << 20)
                sidecar = _zipped_prj(archive, member)
                if sidecar is not None:  # read_asc checks the grid's CRS from it, as beside a loose file
                    with archive.open(sidecar) as src, open(inner.with_suffix(".prj"), "wb") as dst:
                        shutil.copyfileobj(src, dst, 1 << 20)
                pam = _zipped_pam(archive, member)
                if pam is not None:  # read_geotiff takes a nodata from it, as beside a loose file
                    with archive.open(pam) as src, open(inner.with_name(inner.name + ".aux.xml"), "wb") as dst:
                        shutil.copyfileobj(src, dst, 1 << 20)
                try:
                    raster = read_dem(inner, **kwargs)
                except DataFormatError as e:  # named by the archive, not the scratch copy
                    raise DataFormatError(str(e).replace(str(inner), f"{path}!{member.filename}")) from None
    # zipfile raises NotImplementedError for a compression method it lacks (e.g. Deflate64).
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError) as e:
        raise DataFormatError(f"{path}: not a readable zip archive ({e})") from None
    raster.source = f"{path}!{member.filename}"
    return raster


def _archive_metadata(name: str) -> bool:
    """Whether a zip member is macOS's AppleDouble metadata, not a file's data: the Finder's "Compress"
    stores each file's extended attributes as ``__MACOSX/<folder>/._<name>`` (Apple's AppleDouble
    format, RFC 1740), and copies to non-Apple volumes leave ``._<name>`` beside the file."""
    parts = PurePosixPath(name).parts
    return bool(parts) and (parts[0] == "__MACOSX" or parts[-1].startswith("._"))


# Largest .prj sidecar read out of a .zip (a WKT CRS is a few kilobytes).
MAX_ZIPPED_PRJ_BYTES = 1 << 20


def _zipped_prj(archive: zipfile.ZipFile, member: zipfile.ZipInfo):
    """The .prj beside an ESRI grid in the archive (same folder and stem, suffix in any
    case), or None: other DEMs carry their CRS inside."""
    if Path(member.filename).suffix.lower() != ".asc":
        return None
    stem = str(Path(member.filename).with_suffix("")).lower()
    for m in archive.infolist():
        if (not m.is_dir() and not _archive_metadata(m.filename) and Path(m.filename).suffix.lower() == ".prj"
                and str(Path(m.filename).with_suffix("")).lower() == stem and m.file_size <= MAX_ZIPPED_PRJ_BYTES):
            return m
    return None


def _zipped_pam(archive: zipfile.ZipFile, member: zipfile.ZipInfo):
    """GDAL's PAM sidecar ``<name>.aux.xml`` beside a GeoTIFF in the archive (GDAL reads it through
    /vsizip/ as beside a loose file; see _pam_nodata), or None."""
    if Path(member.filename).suffix.lower() not in (".tif", ".tiff"):
        return None
    name = (member.filename + ".aux.xml").lower()
    return next((m for m in archive.infolist() if not m.is_dir() and m.filename.lower() == name
                 and m.file_size <= MAX_PAM_BYTES), None)


# --------------------------------------------------------------------------- SRTM .hgt

def hgt_southwest_corner(name: str) -> tuple[int, int]:
    """(lat, lon) whole degrees of an SRTM tile's south-west post from its file name."""
    m = HGT_NAME.match(name)
    if m is None:
        raise DataFormatError(f"{name}: an .hgt name must start with the tile's south-west corner, "
                              "like N47E009 or S12W077")
    lat = int(m.group(2)) * (1 if m.group(1).upper() == "N" else -1)
    lon = int(m.group(4)) * (1 if m.group(3).upper() == "E" else -1)
    if not (-90 <= lat <= 89 and -180 <= lon <= 179):
        raise DataFormatError(f"{name}: corner {m.group(0)} is not a 1-degree tile on the globe")
    return lat, lon


def read_hgt(path) -> Raster:
    """SRTM .hgt tile: big-endian int16, n x n posts, file row 0 = north edge.

    n comes from the file length (1201 for SRTM3, 3601 for SRTM1, any n >= 2);
    the tile spans one degree from the south-west corner in its name, so posts
    are 1/(n-1) degrees apart and neighbouring tiles share their edge posts.
    Voids (-32768) are filled by the harmonic rule. Heights float32, metres
    above the EGM96 geoid.
    """
    path = _existing(path)
    lat0, lon0 = hgt_southwest_corner(path.name)
    nbytes = path.stat().st_size
    n = math.isqrt(nbytes // 2)
    if n < 2 or 2 * n * n != nbytes:
        raise DataFormatError(f"{path}: {nbytes} bytes is not a square grid of 16-bit posts "
                              "(2*n*n bytes: 2884802 for SRTM3 1201x1201, 25934402 for SRTM1 3601x3601)")
    posts = np.fromfile(path, dtype=">i2").reshape(n, n)[::-1]
    spacing = 1.0 / (n - 1)
    meta = {"format": "SRTM HGT", "posts_per_side": n, "spacing_arcsec": 3600.0 / (n - 1)}
    return _finish(path, posts, posts == SRTM_VOID, Georef(CRS_GEOGRAPHIC, float(lon0), float(lat0),
                                                          spacing, spacing),
                   VERTICAL_DATUM_SRTM, meta)


# --------------------------------------------------------------------------- ESRI ASCII grid

def read_asc(path) -> Raster:
    """ESRI ASCII grid (Arc/Info ASCII GRID), in geographic degrees (EPSG:4326).

    The format carries no CRS, so x, y are taken as longitude, latitude in
    degrees, which is what SRTM-derived grids like the shared Boulder file
    hold. Header keys, case-insensitive: ncols, nrows, xllcorner | xllcenter,
    yllcorner | yllcenter, cellsize (or dx and dy), optional NODATA_value.
    ``*corner`` is the outer corner of the south-west cell (cell-area
    registration): posts are put at cell centres, half a cell inwards.
    ``*center`` is the centre of that cell, i.e. the post itself. File row 0 is
    the north row. NODATA posts are voids, filled by the harmonic rule (see
    :func:`_asc_voids`; ``NODATA_value nan``, as GDAL writes it, leaves the
    non-finite cells the voids they always are). A sidecar ``.prj`` (the WKT
    GDAL and ArcGIS write beside the grid, or the older ArcInfo keyword form) is
    read when present (:func:`_asc_sidecar_crs`): a projected CRS, alone or as
    the horizontal part of a compound CRS, or a geographic one on another datum
    than WGS 84 (or those read as it, see GEOGRAPHIC_AS_WGS84), is refused by
    name instead of read as degrees, and a geographic 3D one (its third axis,
    the grid's values, is the ellipsoidal height) instead of read as mean sea
    level. Its units are applied: coordinates in another angular unit (ArcInfo's
    ``Units DS``, arc-seconds) are converted to degrees, heights in feet (the
    unit of a compound CRS's vertical part, ArcInfo's ``Zunits FEET``) to metres
    as the GeoTIFF reader converts them (meta["vertical_units"]), and a vertical
    CRS on a datum the GeoTIFF reader names gives the grid that vertical datum.
    A leading UTF-8 byte order mark (what Windows tools such as Notepad write)
    is skipped, in the grid and in its ``.prj``.
    """
    path = _existing(path)
    crs = _asc_sidecar_crs(path)
    data = path.read_bytes()
    try:
        text = data[len(UTF8_BOM):].decode("ascii") if data.startswith(UTF8_BOM) else data.decode("ascii")
    except UnicodeDecodeError as e:
        raise DataFormatError(f"{path}: not an ASCII grid ({e})") from None
    header, body = _split_asc(path, text)
    ncols = _asc_int(path, header, "ncols")
    nrows = _asc_int(path, header, "nrows")
    dx, dy = _asc_spacing(path, header)
    x0, x_reg = _asc_origin(path, header, "x", dx)
    y0, y_reg = _asc_origin(path, header, "y", dy)
    try:
        values = np.array(body, dtype=np.float64)
    except ValueError as e:
        raise DataFormatError(f"{path}: grid values must be numbers ({e})") from None
    if values.size != nrows * ncols:
        raise DataFormatError(f"{path}: header says {nrows} x {ncols} = {nrows * ncols} values, "
                              f"file has {values.size}")
    grid = values.reshape(nrows, ncols)[::-1]
    nodata = _asc_nodata(path, header)
    voids = _asc_voids(grid, nodata)
    meta = {"format": "ESRI ASCII grid", "registration_x": x_reg, "registration_y": y_reg,
            "nodata_value": nodata, "crs_assumed": "EPSG:4326"}
    datum = VERTICAL_DATUM_DEFAULT
    if crs is not None:
        meta["crs_prj"] = crs.name
        datum = crs.vertical_datum
        unit_name, degrees = crs.horizontal_units
        if degrees != 1.0:  # the header's coordinates and spacing -> degrees
            x0, y0, dx, dy = (v * degrees for v in (x0, y0, dx, dy))
            meta["horizontal_units"] = unit_name
        unit_name, to_m = crs.vertical_units
        if to_m != 1.0:  # values -> metres, voids found on the values as written
            grid = grid * to_m
            meta["vertical_units"] = unit_name
    return _finish(path, grid, voids, _make_georef(path, CRS_GEOGRAPHIC, x0, y0, dx, dy), datum, meta)


def _asc_nodata(path: Path, header: dict) -> float | None:
    """NODATA_value, or None without one. Unlike the other header values it may be non-finite:
    GDAL's AAIGrid writer prints a NaN nodata as ``nan``."""
    if "nodata_value" not in header:
        return None
    try:
        return float(header["nodata_value"])
    except ValueError:
        raise DataFormatError(f"{path}: header nodata_value must be a number, got {header['nodata_value']!r}") from None


def _asc_voids(grid: np.ndarray, nodata: float | None) -> np.ndarray:
    """(ny, nx) bool: the void cells of a grid ((ny, nx) float64, as written): non-finite ones, and
    those equal to a finite NODATA_value in float64 or once both are rounded to float32. GDAL's
    AAIGrid driver reads a grid with floating point values as Float32 and compares there (GDAL's
    AAIGrid driver documentation, AAIGRID_DATATYPE: "set to Float32 for grid with floating point
    values"), and writers print the header and the cells at different precisions: a header of
    -3.4028234663852886e+38 over cells of -3.4028235e+38 is float32's lowest value both times. A
    nodata beyond float32's range is compared in float64 only."""
    voids = ~np.isfinite(grid)
    if nodata is None or not math.isfinite(nodata):
        return voids
    voids |= grid == nodata
    with np.errstate(over="ignore"):  # cells beyond float32's range round to +-inf: never a finite nodata
        nodata32 = np.float32(nodata)
        if np.isfinite(nodata32):
            voids |= grid.astype(np.float32) == nodata32
    return voids


# Datum names in WKT that are WGS 84 or read as it (GEOGRAPHIC_AS_WGS84's NAD83, ETRS89), matched in
# the .prj's own datum name (a leading "D_" dropped) and in PROJ's name for it. ESRI writes NAD83 as
# "D_North_American_1983" (GDAL's morphToESRI too, as USGS NED grids ship), and its realisations
# with a suffix (_HARN, _CSRS, _2011, _NSRS2007): all are read as NAD83, since the EPSG registry's
# transformations from each to WGS 84 are as accurate as NAD83's own or better (NAD83(HARN) EPSG:1580
# 2 m, NAD83(CSRS) EPSG:1842 2 m, NAD83(NSRS2007) EPSG:15931 2 m, NAD83(2011) EPSG:9774 2 m, against
# NAD83 EPSG:1188 4 m), and GDAL's names for them ("NAD83_High_Accuracy_Reference_Network", ...) were
# read as NAD83 already.
WKT_WGS84_DATUMS = ("WGS_1984", "WGS84", "WGS 84", "WORLD GEODETIC SYSTEM 1984", "NORTH_AMERICAN_DATUM_1983",
                    "NORTH AMERICAN DATUM 1983", "NORTH_AMERICAN_1983", "EUROPEAN_TERRESTRIAL_REFERENCE_SYSTEM_1989",
                    "EUROPEAN TERRESTRIAL REFERENCE SYSTEM 1989", "ETRS89", "ETRS_1989", "NAD83", "NAD_1983")
# ESRI's VERTCS carries a shift added to the heights (PARAMETER["Vertical_Shift", ...]), which PROJ drops.
WKT_ESRI_VERTICAL_SHIFT = re.compile(r'PARAMETER\s*\[\s*"Vertical_Shift"\s*,\s*([^\],\s]+)', re.IGNORECASE)
# Units are the same unit when their factors agree this closely (WKT prints them to 15 or 16 digits).
UNIT_FACTOR_RTOL = 1e-9
# The older ArcInfo .prj keywords (GDAL's OGRSpatialReference::importFromESRI reads this form): "Units" of a
# GEOGRAPHIC projection, DD decimal degrees or DS arc-seconds (GDAL's AAIGrid and AIG drivers divide the
# georeference by 3600 for DS); "Zunits" of the values, NO (none said: as supplied, in metres), METERS or
# FEET, read as the US survey foot, as importFromESRI reads "Units FEET" of the same form. Values:
# (name, degrees or metres per unit).
ARCINFO_UNITS_DEG = {"DD": ANGULAR_UNITS_DEG[9102], "DS": ANGULAR_UNITS_DEG[9104]}
ARCINFO_ZUNITS_M = {"NO": VERTICAL_UNITS_M[9001], "METERS": VERTICAL_UNITS_M[9001], "FEET": VERTICAL_UNITS_M[9003]}


class AscCrs(NamedTuple):
    """What an ESRI grid's .prj says: its name (meta["crs_prj"]); the header coordinates' unit
    (name, degrees per unit); the values' unit (name, metres per unit); their vertical datum
    (a Raster.vertical_datum label)."""

    name: str
    horizontal_units: tuple[str, float]
    vertical_units: tuple[str, float]
    vertical_datum: str


def _asc_sidecar_crs(path: Path) -> AscCrs | None:
    """What the grid's .prj sidecar says (None without one, or one that is no CRS); a CRS the grid
    cannot be read in is a DataFormatError naming it: a projected CRS (alone or as a compound CRS's
    horizontal part), another datum, a geographic 3D CRS (ellipsoidal heights), a unit it does not
    know (coordinates or heights), depths or ellipsoidal heights as a vertical CRS."""
    prj = path.with_suffix(".prj")
    if not prj.is_file():
        prj = path.with_suffix(".PRJ")
        if not prj.is_file():
            return None
    # utf-8-sig: a leading byte order mark would otherwise hide the WKT keyword from the match
    # below, and a projected CRS would then be read as degrees.
    text = prj.read_text(encoding="utf-8-sig", errors="replace").strip()
    head = re.match(r"\s*(\w+)\s*\[\s*\"([^\"]*)\"", text)
    if head is not None:  # WKT (GDAL, ArcGIS)
        return _wkt_prj(path, prj, text, head.group(2))
    # The older ArcInfo form: "Projection GEOGRAPHIC", "Datum WGS84", "Units DD", "Zunits NO", ...
    fields = dict((line.split(None, 1) + [""])[:2] for line in text.splitlines() if line.strip())
    fields = {k.upper(): v.strip() for k, v in fields.items()}
    if "PROJECTION" not in fields:
        return None  # not a CRS we can read: the grid is taken as degrees, as without one
    name = fields["PROJECTION"]
    if name.upper() != "GEOGRAPHIC":
        raise _projected_prj(path, prj, name)
    _check_prj_datum(path, prj, fields.get("DATUM", "WGS84"))
    units = (fields.get("UNITS") or "DD").upper()
    zunits = (fields.get("ZUNITS") or "NO").upper()
    if units not in ARCINFO_UNITS_DEG:
        raise DataFormatError(f"{path}: its {prj.name} gives Units {fields['UNITS']!r} for a GEOGRAPHIC projection; "
                              "read are " + ", ".join(f"{k} ({n})" for k, (n, _) in ARCINFO_UNITS_DEG.items()))
    if zunits not in ARCINFO_ZUNITS_M:
        raise DataFormatError(f"{path}: its {prj.name} gives Zunits {fields['ZUNITS']!r}; read are "
                              + ", ".join(f"{k} ({n})" for k, (n, _) in ARCINFO_ZUNITS_M.items()))
    return AscCrs(name, ARCINFO_UNITS_DEG[units], ARCINFO_ZUNITS_M[zunits], VERTICAL_DATUM_DEFAULT)


def _wkt_prj(path: Path, prj: Path, text: str, name: str) -> AscCrs:
    """A WKT .prj (WKT1 as GDAL or ESRI write it, WKT2; a compound CRS as COMPD_CS, COMPOUNDCRS or
    ESRI's horizontal CRS followed by a VERTCS) read by PROJ, which also maps ESRI's names to EPSG's."""
    import pyproj

    try:
        crs = pyproj.CRS.from_wkt(text)
    except pyproj.exceptions.CRSError as e:
        raise DataFormatError(f"{path}: its {prj.name} is not a WKT CRS PROJ can read ({e})") from None
    horizontal, vertical = (crs.sub_crs_list[0], crs.sub_crs_list[1]) if crs.is_compound else (crs, None)
    while horizontal.is_bound:  # WKT1's TOWGS84 makes a bound CRS around the one the grid is in
        horizontal = horizontal.source_crs
    if horizontal.is_projected:
        raise _projected_prj(path, prj, name if vertical is None else
                             f"{horizontal.name}, the horizontal part of compound CRS {name!r}")
    if not horizontal.is_geographic:
        raise DataFormatError(f"{path}: its {prj.name} is {horizontal.type_name!r} ({horizontal.name}), not a "
                              "geographic CRS; ESRI ASCII grids are read in geographic degrees only")
    raw_datum = re.search(r"\bDATUM\s*\[\s*\"([^\"]*)\"", text, re.IGNORECASE)
    _check_prj_datum(path, prj, raw_datum.group(1) if raw_datum else horizontal.datum.name, horizontal.datum.name)
    meridian = horizontal.prime_meridian
    if meridian.longitude != 0.0:
        raise DataFormatError(f"{path}: its {prj.name} has prime meridian {meridian.name!r} at {meridian.longitude:g} "
                              f"{meridian.unit_name} from Greenwich; read is Greenwich")
    if len(horizontal.axis_info) > 2:  # PROJ makes one of a compound CRS on an ellipsoidal VERT_DATUM (2002) too
        raise DataFormatError(f"{path}: its {prj.name} is a geographic 3D CRS ({name}): the grid's values are "
                              "ellipsoidal heights, not mean sea level; convert them with the geoid (e.g. "
                              "EGM96/EGM2008), or give the grid a 2-D geographic .prj to take them as supplied")
    axis = horizontal.axis_info[0]
    degrees = _known_unit(axis.unit_conversion_factor * 180.0 / math.pi, ANGULAR_UNITS_DEG.values())
    if degrees is None:
        raise DataFormatError(f"{path}: its {prj.name} gives coordinates in {axis.unit_name!r} "
                              f"({axis.unit_conversion_factor!r} rad); read are "
                              + ", ".join(sorted({n for n, _ in ANGULAR_UNITS_DEG.values()})))
    vertical_units, datum = VERTICAL_UNITS_M[9001], VERTICAL_DATUM_DEFAULT
    if vertical is not None:
        vertical_units, datum = _prj_vertical(path, prj, text, vertical)
    return AscCrs(name, degrees, vertical_units, datum)


def _prj_vertical(path: Path, prj: Path, text: str, vertical) -> tuple[tuple[str, float], str]:
    """((unit name, metres per unit), Raster.vertical_datum label) of a compound .prj's vertical CRS
    (a pyproj CRS): heights up, in a unit of VERTICAL_UNITS_M (the GeoTIFF reader's), labelled by
    their EPSG vertical datum where the GeoTIFF reader names it, else "as supplied"."""
    import pyproj

    while vertical.is_bound:
        vertical = vertical.source_crs
    what = f"{path}: its {prj.name}'s vertical CRS ({vertical.name})"
    axis = vertical.axis_info[0]
    if axis.direction.lower() != "up":
        raise DataFormatError(f"{what} has its axis {axis.direction}: depths, not heights above mean sea level")
    shift = WKT_ESRI_VERTICAL_SHIFT.search(text)
    if shift is not None and _float_or_nan(shift.group(1)) != 0.0:
        raise DataFormatError(f"{what} has Vertical_Shift {shift.group(1)}; read are heights without a shift (0)")
    unit = _known_unit(axis.unit_conversion_factor, VERTICAL_UNITS_M.values())
    if unit is None:
        raise DataFormatError(f"{what} gives heights in {axis.unit_name!r} ({axis.unit_conversion_factor!r} m); "
                              "read are " + ", ".join(n for n, _ in VERTICAL_UNITS_M.values()))
    ident = vertical.datum.to_json_dict().get("id") or {}
    if ident.get("authority") != "EPSG":
        try:  # PROJ's datum of that name (EPSG's names, ESRI's and their aliases: "EGM96_Geoid", "NAVD88")
            ident = pyproj.crs.Datum.from_name(vertical.datum.name, auth_name="EPSG",
                                               datum_type="VERTICAL_REFERENCE_FRAME").to_json_dict().get("id") or {}
        except pyproj.exceptions.CRSError:
            ident = {}
    label = vertical_datum_label(int(ident["code"])) if ident.get("authority") == "EPSG" else None
    return unit, label or VERTICAL_DATUM_DEFAULT


def _float_or_nan(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def _known_unit(factor: float, units) -> tuple[str, float] | None:
    """The (name, factor) of ``units`` whose factor is ``factor`` to UNIT_FACTOR_RTOL, or None."""
    return next(((n, f) for n, f in units if abs(factor - f) <= UNIT_FACTOR_RTOL * f), None)


def _projected_prj(path: Path, prj: Path, name: str) -> DataFormatError:
    return DataFormatError(f"{path}: its {prj.name} is a projected CRS ({name}); ESRI ASCII grids are read in "
                           "geographic degrees only (convert it to EPSG:4326, or to a GeoTIFF in EPSG:4326 or 3857)")


def _check_prj_datum(path: Path, prj: Path, datum_name: str, proj_name: str | None = None) -> None:
    """DataFormatError naming the datum unless it (the .prj's name, or PROJ's for it) is one of
    WKT_WGS84_DATUMS."""
    names = (datum_name.upper().replace("D_", "", 1), (proj_name or "").upper())
    if not any(d in n for d in WKT_WGS84_DATUMS for n in names):
        raise DataFormatError(f"{path}: its {prj.name} is on datum {datum_name!r}; read are WGS 84, NAD83 "
                              "and ETRS89")


# The UTF-8 byte order mark (U+FEFF encoded), which Windows editors put at the start of text files.
UTF8_BOM = b"\xef\xbb\xbf"

ASC_HEADER_KEYS = ("ncols", "nrows", "xllcorner", "xllcenter", "yllcorner", "yllcenter",
                   "cellsize", "dx", "dy", "nodata_value")


def _split_asc(path: Path, text: str) -> tuple[dict[str, str], list[str]]:
    """Header {lower-case key: value} and the whitespace-split value tokens.

    The header ends at the first line that starts with a number (``nan``
    included, which some writers use for voids).
    """
    lines = text.splitlines()
    header: dict[str, str] = {}
    k = 0
    for k, line in enumerate(lines):
        parts = line.split()
        if not parts:
            continue
        key = parts[0].lower()
        if key not in ASC_HEADER_KEYS:
            try:
                float(parts[0])
                break
            except ValueError:
                raise DataFormatError(f"{path}: unknown header key {parts[0]!r} on line {k + 1}; "
                                      f"expected {', '.join(ASC_HEADER_KEYS)}") from None
        if len(parts) != 2:
            raise DataFormatError(f"{path}: header line {k + 1} must be 'key value', got {line!r}")
        if key in header:
            raise DataFormatError(f"{path}: header key {parts[0]!r} appears twice")
        header[key] = parts[1]
    else:
        k = len(lines)
    return header, " ".join(lines[k:]).split()


def _asc_float(path: Path, header: dict, key: str) -> float:
    try:
        value = float(header[key])
    except KeyError:
        raise DataFormatError(f"{path}: header lacks {key}") from None
    except ValueError:
        raise DataFormatError(f"{path}: header {key} must be a number, got {header[key]!r}") from None
    if not math.isfinite(value):
        raise DataFormatError(f"{path}: header {key} must be finite, got {header[key]!r}")
    return value


def _asc_int(path: Path, header: dict, key: str) -> int:
    value = _asc_float(path, header, key)
    if value != int(value) or value < 2:
        raise DataFormatError(f"{path}: header {key} must be a whole number >= 2, got {header[key]!r}")
    return int(value)


def _asc_spacing(path: Path, header: dict) -> tuple[float, float]:
    if "cellsize" in header:
        if "dx" in header or "dy" in header:
            raise DataFormatError(f"{path}: header has both cellsize and dx/dy")
        dx = dy = _asc_float(path, header, "cellsize")
    else:
        dx, dy = _asc_float(path, header, "dx"), _asc_float(path, header, "dy")
    if dx <= 0 or dy <= 0:
        raise DataFormatError(f"{path}: cell size must be positive, got dx={dx}, dy={dy}")
    return dx, dy


def _asc_origin(path: Path, header: dict, axis: str, spacing: float) -> tuple[float, str]:
    """Post coordinate of the south-west post along one axis, and its registration."""
    corner, center = f"{axis}llcorner", f"{axis}llcenter"
    if (corner in header) == (center in header):
        raise DataFormatError(f"{path}: header needs exactly one of {corner}, {center}")
    if corner in header:
        return _asc_float(path, header, corner) + 0.5 * spacing, "corner"
    return _asc_float(path, header, center), "center"


# --------------------------------------------------------------------------- GeoTIFF

def read_geotiff(path) -> Raster:
    """Single-band GeoTIFF in EPSG:4326 or EPSG:3857 (Web Mercator); NAD83 and ETRS89
    geographic rasters are read as WGS 84 within the EPSG registry's stated accuracy
    (GEOGRAPHIC_AS_WGS84; the raster's meta["horizontal_datum"] says so), and so is a
    user-defined geographic CRS (32767) on one of their datums with the Greenwich meridian.

    Georeference from ModelPixelScale + one ModelTiepoint, or from a
    ModelTransformation without rotation. GTRasterTypeGeoKey decides where
    the posts are: PixelIsArea (1, also the reading when the key is absent, as
    GDAL does) puts the tie point on the outer corner of pixel (0, 0), so posts
    sit half a pixel inwards; PixelIsPoint (2) puts it on the post. Rows may
    run north->south (usual, positive ModelPixelScale y) or south->north; both
    come out row 0 = south. GDAL_NODATA (else the NoDataValue of GDAL's
    ``<file>.aux.xml`` sidecar), non-finite values and, with a nodata value,
    a sparse file's unwritten strips or tiles are voids, filled by the
    harmonic rule; a post beyond +-HEIGHT_ABS_MAX_M is refused. Georef x, y are in the CRS's native units.
    Strips or tiles, classic TIFF or BigTIFF, uncompressed or compressed as
    GDAL writes DEMs (LZW, DEFLATE, ZSTD, PackBits; horizontal or
    floating-point predictor): tifffile decodes them with imagecodecs. Heights
    stored scaled (GDAL_METADATA's band scale and offset, e.g. decimetres in
    int16) or in feet (VerticalUnitsGeoKey 9002, 9003, or GDAL_METADATA's band unit
    type "ft", "US survey foot", ...) come out in metres. Coordinates in other units than
    the CRS's own (GeogAngularUnitsGeoKey radian, grad, ...; ProjLinearUnitsGeoKey foot, US
    survey foot) are converted to degrees / metres; a unit it does not know is refused.
    """
    path = _existing(path)
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}
            data = page.asarray()
            unwritten = _unwritten_segments(page) if data.ndim == 2 else None
    # imagecodecs reports corrupt compressed data (DeflateError, ZstdError, LzwError, ...) as
    # RuntimeError subclasses.
    except (tifffile.TiffFileError, ValueError, OSError, KeyError, IndexError, RuntimeError) as e:
        raise DataFormatError(f"{path}: not a readable TIFF ({type(e).__name__}: {e})") from None
    if data.ndim != 2:
        raise DataFormatError(f"{path}: expected one band of heights, got an image of shape {data.shape}")
    if data.dtype.kind not in "iuf":
        raise DataFormatError(f"{path}: heights must be integers or floats, got {data.dtype}")
    if TAG_GEO_KEY_DIRECTORY not in tags:
        raise DataFormatError(f"{path}: no GeoKeyDirectoryTag ({TAG_GEO_KEY_DIRECTORY}); not a GeoTIFF")
    keys = parse_geokeys(path, tags[TAG_GEO_KEY_DIRECTORY], tags.get(TAG_GEO_DOUBLE_PARAMS, ()),
                         tags.get(TAG_GEO_ASCII_PARAMS, ""))
    crs = _geotiff_crs(path, keys)
    raster_type = keys.get(KEY_GT_RASTER_TYPE, RASTER_PIXEL_IS_AREA)
    if raster_type not in (RASTER_PIXEL_IS_AREA, RASTER_PIXEL_IS_POINT):
        raise DataFormatError(f"{path}: GTRasterTypeGeoKey ({KEY_GT_RASTER_TYPE}) = {raster_type!r} "
                              "is neither 1 (PixelIsArea) nor 2 (PixelIsPoint)")
    ax, sx, ay, sy = (v * _model_units(path, crs, keys) for v in _raster_to_model(path, tags))
    # Raster space puts pixel (0, 0)'s outer corner at (0, 0) and its centre at
    # (0.5, 0.5) (GeoTIFF 1.0 section 2.5.2.2; OGC 19-008r4 Annex B).
    half = 0.5 if raster_type == RASTER_PIXEL_IS_AREA else 0.0
    if sx < 0:
        data, unwritten = data[:, ::-1], unwritten[:, ::-1]
    if sy < 0:
        data, unwritten = data[::-1], unwritten[::-1]
    ny, nx = data.shape
    x0 = ax + sx * ((nx - 1 if sx < 0 else 0) + half)
    y0 = ay + sy * ((ny - 1 if sy < 0 else 0) + half)
    nodata = _gdal_nodata(path, tags.get(TAG_GDAL_NODATA))
    if nodata is None:
        nodata = _pam_nodata(path)
    voids = ~np.isfinite(data) if data.dtype.kind == "f" else np.zeros(data.shape, bool)
    if nodata is not None and math.isfinite(nodata):
        voids |= data == (data.dtype.type(nodata) if data.dtype.kind == "f" else nodata)
    if nodata is not None:  # GDAL reads a sparse file's unwritten blocks as the nodata value
        voids |= unwritten
    meta = {"format": "GeoTIFF", "dtype": str(data.dtype),
            "raster_type": "PixelIsArea" if half else "PixelIsPoint",
            "nodata": nodata, "rows_south_to_north": bool(sy > 0)}
    if crs == CRS_GEOGRAPHIC:
        code = _geographic_code(path, keys)
        name, accuracy_m, transformation = GEOGRAPHIC_AS_WGS84[code]
        meta["horizontal_datum"] = name if transformation is None else (
            f"{name} (EPSG:{code}) read as WGS 84: EPSG:{transformation} null "
            f"transformation, accurate to {accuracy_m:g} m")
        if keys.get(KEY_GEOGRAPHIC_TYPE) == GEOGRAPHIC_USER_DEFINED:
            meta["geographic_crs"] = (f"user-defined on EPSG datum {keys[KEY_GEOG_GEODETIC_DATUM]}, "
                                      f"read as EPSG:{code}")
    scale, offset, unit_type = _gdal_band_metadata(path, tags.get(TAG_GDAL_METADATA))
    unit_name, to_m = _vertical_units(path, keys, unit_type)
    if (scale, offset, to_m) != (1.0, 0.0, 1.0):  # stored values -> metres (GDAL's unscaling, then units)
        data = (data.astype(np.float64) * scale + offset) * to_m
        meta.update(scale=scale, offset=offset, vertical_units=unit_name)
    datum = _vertical_datum(path, keys)
    return _finish(path, data, voids, _make_georef(path, crs, x0, y0, abs(sx), abs(sy)), datum, meta)


def _unwritten_segments(page) -> np.ndarray:
    """(rows, cols) bool over a one-band page's pixels as stored (row 0 the file's first): those of
    the strips or tiles a sparse TIFF leaves unwritten, offset or byte count 0 (GDAL's GTiff
    driver, "Sparse files": with SPARSE_OK=TRUE blocks of nodata alone are not written, and are
    read back as the nodata value, or 0 without one). tifffile fills them with the GDAL_NODATA it
    could parse in the image's dtype, else 0 (an integer raster's "-9999.0", a float32 one's
    "-3.4028234663852886e+38"), so they are found here, by their segments."""
    rows, cols = page.shape[-2:]
    unwritten = np.zeros((rows, cols), bool)
    (seg_rows, seg_cols), per_row = page.chunks[:2], page.chunked[-1]
    for k, (offset, count) in enumerate(zip(page.dataoffsets, page.databytecounts)):
        if offset == 0 or count == 0:
            r, c = divmod(k, per_row)
            unwritten[r * seg_rows:(r + 1) * seg_rows, c * seg_cols:(c + 1) * seg_cols] = True
    return unwritten


def _vertical_datum(path: Path, keys: dict) -> str:
    """The heights' vertical datum from VerticalCSTypeGeoKey (4096): a mean-sea-level type one of
    VERTICAL_DATUMS_EPSG by name; 32767 (user-defined), or none with a 2-D geographic or projected
    CRS, "as supplied". Any other code is refused naming the key and the code: ellipsoidal heights
    (5001-5033, a geographic 3D CRS such as 4979) are tens of metres off sea level, and an unknown
    system cannot be read as it. Without the key, a geographic 3D CRS as GeographicTypeGeoKey (2048)
    says the third coordinate, the heights, is its ellipsoidal height (EPSG: the CRS's third axis,
    "ellipsoidal height (h)"), refused the same way naming that key."""
    code = keys.get(KEY_VERTICAL_CS_TYPE)
    if code is None and keys.get(KEY_GEOGRAPHIC_TYPE) in GEOGRAPHIC_3D_CODES:
        raise DataFormatError(f"{path}: GeographicTypeGeoKey ({KEY_GEOGRAPHIC_TYPE}) = "
                              f"{keys[KEY_GEOGRAPHIC_TYPE]!r} without a VerticalCSTypeGeoKey "
                              f"({KEY_VERTICAL_CS_TYPE}): ellipsoidal heights (a geographic 3D CRS), not mean "
                              "sea level; " + MSL_ADVICE)
    if code is None or code == VERTICAL_CS_USER_DEFINED:
        return VERTICAL_DATUM_DEFAULT
    if code in VERTICAL_DATUMS_EPSG:
        return VERTICAL_DATUMS_EPSG[code]
    what = ("ellipsoidal heights (GeoTIFF VertCS_*_ellipsoid), not mean sea level"
            if isinstance(code, int) and code in VERTICAL_CS_ELLIPSOID_CODES else
            "ellipsoidal heights (a geographic 3D CRS), not mean sea level" if code in GEOGRAPHIC_3D_CODES
            else "not a mean-sea-level vertical CRS this reader knows")
    raise DataFormatError(f"{path}: VerticalCSTypeGeoKey ({KEY_VERTICAL_CS_TYPE}) = {code!r}: {what}; "
                          + MSL_ADVICE)


def _model_units(path: Path, crs: int, keys: dict) -> float:
    """Factor from the file's model coordinates to the Georef's (degrees, or metres of Web
    Mercator): GeogAngularUnitsGeoKey (2054, default degree) of a geographic raster,
    ProjLinearUnitsGeoKey (3076, default metre) of a projected one. A unit not in
    ANGULAR_UNITS_DEG / LINEAR_UNITS_M (a user-defined 32767 among them) is refused, naming
    the key and its value."""
    if crs == CRS_GEOGRAPHIC:
        key, units, what = KEY_GEOG_ANGULAR_UNITS, ANGULAR_UNITS_DEG, "GeogAngularUnitsGeoKey"
        code = keys.get(key, 9102)
    else:
        key, units, what = KEY_PROJ_LINEAR_UNITS, LINEAR_UNITS_M, "ProjLinearUnitsGeoKey"
        code = keys.get(key, 9001)
    if code not in units:
        raise DataFormatError(f"{path}: {what} ({key}) = {code!r}; read are "
                              + ", ".join(f"{c} ({name})" for c, (name, _) in units.items()))
    return units[code][1]


def _vertical_units(path: Path, keys: dict, unit_type: str | None) -> tuple[str, float]:
    """(name, metres per unit) of the heights: VerticalUnitsGeoKey (4099) and GDAL's band unit
    type (GDAL_METADATA role "unittype", GDAL_UNIT_TYPES_M), metre when neither is given. An
    unknown unit, or the two naming different units, is refused."""
    unit_code = keys.get(KEY_VERTICAL_UNITS)
    if unit_code is not None and unit_code not in VERTICAL_UNITS_M:
        raise DataFormatError(f"{path}: VerticalUnitsGeoKey ({KEY_VERTICAL_UNITS}) = {unit_code!r}; read are "
                              + ", ".join(f"{c} ({name})" for c, (name, _) in VERTICAL_UNITS_M.items()))
    by_key = VERTICAL_UNITS_M[unit_code] if unit_code is not None else None
    by_type = None
    if unit_type:
        by_type = GDAL_UNIT_TYPES_M.get(unit_type.strip().lower())
        if by_type is None:
            raise DataFormatError(f"{path}: GDAL_METADATA ({TAG_GDAL_METADATA}) unittype = {unit_type!r}; read are "
                                  + ", ".join(repr(u) for u in GDAL_UNIT_TYPES_M))
    if by_key is not None and by_type is not None and by_key[1] != by_type[1]:
        raise DataFormatError(f"{path}: VerticalUnitsGeoKey ({KEY_VERTICAL_UNITS}) = {unit_code} ({by_key[0]}) "
                              f"and GDAL_METADATA unittype = {unit_type!r} ({by_type[0]}) disagree")
    return by_key or by_type or VERTICAL_UNITS_M[9001]


def _gdal_scale_offset(path: Path, text) -> tuple[float, float]:
    """(scale, offset) of band 1 from the GDAL_METADATA tag's XML (``<Item name="SCALE"
    sample="0" role="scale">``); (1, 0) without them. Heights are value * scale + offset."""
    return _gdal_band_metadata(path, text)[:2]


def _gdal_band_metadata(path: Path, text) -> tuple[float, float, str | None]:
    """(scale, offset, unit type) of band 1 from the GDAL_METADATA tag's XML (``<Item
    name="SCALE" sample="0" role="scale">``, ``role="offset"``, ``role="unittype"``: GDAL's
    GDALRasterBand::GetScale/GetOffset/GetUnitType); (1, 0, None) without them. Heights are
    (value * scale + offset) in the unit type."""
    if not text:
        return 1.0, 0.0, None
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(str(text).strip().rstrip("\x00"))
    except ET.ParseError as e:
        raise DataFormatError(f"{path}: GDAL_METADATA ({TAG_GDAL_METADATA}) is not XML ({e})") from None
    found = {"scale": 1.0, "offset": 0.0}
    unit_type = None
    for item in root.iter("Item"):
        role = (item.get("role") or "").lower()
        if role == "unittype" and item.get("sample", "0") == "0":
            unit_type = (item.text or "").strip() or None
        elif role in found and item.get("sample", "0") == "0":
            try:
                found[role] = float((item.text or "").strip())
            except ValueError:
                raise DataFormatError(f"{path}: GDAL_METADATA {role} must be a number, got {item.text!r}") from None
            if not math.isfinite(found[role]) or (role == "scale" and found[role] == 0.0):
                raise DataFormatError(f"{path}: GDAL_METADATA {role} = {found[role]!r} cannot scale heights")
    return found["scale"], found["offset"], unit_type


def parse_geokeys(path, directory, doubles=(), ascii_params: str = "") -> dict[int, object]:
    """GeoKeyDirectoryTag -> {key id: value} (GeoTIFF 1.0 section 2.4; OGC 19-008r4 7.1.2).

    directory: the tag's SHORTs: header (KeyDirectoryVersion, KeyRevision,
    MinorRevision, NumberOfKeys) then one (KeyID, TIFFTagLocation, Count,
    ValueOffset) entry per key. Location 0 means the SHORT value is
    ValueOffset itself; 34736 and 34737 index GeoDoubleParams / GeoAsciiParams.
    """
    d = [int(v) for v in directory]
    if len(d) < 4 or len(d) < 4 + 4 * d[3]:
        raise DataFormatError(f"{path}: GeoKeyDirectoryTag of {len(d)} values is shorter than "
                              f"its header says ({4 + 4 * d[3] if len(d) >= 4 else 4})")
    keys: dict[int, object] = {}
    for k in range(d[3]):
        key, location, count, offset = d[4 + 4 * k: 8 + 4 * k]
        if location == 0:
            keys[key] = offset
        elif location == TAG_GEO_DOUBLE_PARAMS:
            values = tuple(doubles[offset:offset + count])
            keys[key] = values[0] if count == 1 and values else values
        elif location == TAG_GEO_ASCII_PARAMS:
            keys[key] = ascii_params[offset:offset + count].rstrip("|\x00")
        elif location == TAG_GEO_KEY_DIRECTORY:
            keys[key] = tuple(d[offset:offset + count])
        else:
            raise DataFormatError(f"{path}: GeoKey {key} points into unknown tag {location}")
    return keys


def _geotiff_crs(path: Path, keys: dict) -> int:
    model = keys.get(KEY_GT_MODEL_TYPE)
    if model == MODEL_TYPE_GEOGRAPHIC:
        _geographic_code(path, keys)
        return CRS_GEOGRAPHIC
    if model == MODEL_TYPE_PROJECTED:
        code = keys.get(KEY_PROJECTED_CS_TYPE)
        if code not in EPSG_WEB_MERCATOR:
            raise DataFormatError(f"{path}: unsupported projected CRS: ProjectedCSTypeGeoKey "
                                  f"({KEY_PROJECTED_CS_TYPE}) = {code!r}; only Web Mercator "
                                  f"{EPSG_WEB_MERCATOR} is read")
        return CRS_WEB_MERCATOR
    raise DataFormatError(f"{path}: unsupported model type: GTModelTypeGeoKey ({KEY_GT_MODEL_TYPE}) = "
                          f"{model!r}; expected {MODEL_TYPE_PROJECTED} (projected) or "
                          f"{MODEL_TYPE_GEOGRAPHIC} (geographic)")


def _geographic_code(path: Path, keys: dict) -> int:
    """The GEOGRAPHIC_AS_WGS84 code a geographic GeoTIFF is read as: its GeographicTypeGeoKey (2048), or
    for a user-defined one (32767) the CRS on its GeogGeodeticDatumGeoKey (2050) with the Greenwich
    meridian (GEOGRAPHIC_OF_DATUM). Anything else is refused naming the keys and their values."""
    code = keys.get(KEY_GEOGRAPHIC_TYPE)
    if code == GEOGRAPHIC_USER_DEFINED:
        datum = keys.get(KEY_GEOG_GEODETIC_DATUM)
        meridian = keys.get(KEY_GEOG_PRIME_MERIDIAN, PRIME_MERIDIAN_GREENWICH)
        if datum in GEOGRAPHIC_OF_DATUM and meridian == PRIME_MERIDIAN_GREENWICH:
            return GEOGRAPHIC_OF_DATUM[datum]
        known = ", ".join(f"{d} ({GEOGRAPHIC_AS_WGS84[c][0]})" for d, c in GEOGRAPHIC_OF_DATUM.items())
        raise DataFormatError(f"{path}: unsupported geographic CRS: GeographicTypeGeoKey ({KEY_GEOGRAPHIC_TYPE}) = "
                              f"{code} (user-defined) with GeogGeodeticDatumGeoKey ({KEY_GEOG_GEODETIC_DATUM}) = "
                              f"{datum!r} and GeogPrimeMeridianGeoKey ({KEY_GEOG_PRIME_MERIDIAN}) = {meridian!r}; "
                              f"read are the datums {known} on the prime meridian {PRIME_MERIDIAN_GREENWICH} "
                              "(Greenwich)")
    if code not in GEOGRAPHIC_AS_WGS84:
        known = ", ".join(f"{c} ({name})" for c, (name, _, _) in GEOGRAPHIC_AS_WGS84.items())
        raise DataFormatError(f"{path}: unsupported geographic CRS: GeographicTypeGeoKey "
                              f"({KEY_GEOGRAPHIC_TYPE}) = {code!r}; read are {known} (or "
                              f"{GEOGRAPHIC_USER_DEFINED} on one of their datums)")
    return code


def _raster_to_model(path: Path, tags: dict) -> tuple[float, float, float, float]:
    """(ax, sx, ay, sy) with model x = ax + sx * I, y = ay + sy * J for raster (I, J).

    Raster I runs along a row (columns), J down the rows. GeoTIFF 1.0 section
    2.6.1 / OGC 19-008r4 7.3: with one tie point (I, J, K, X, Y, Z) and pixel
    scale (Sx, Sy, Sz), x = X + (i - I) Sx and y = Y - (j - J) Sy (a positive
    Sy is the usual north-up image). A ModelTransformation is a row-major 4x4
    matrix whose [0][1] and [1][0] must be zero here (no rotation or shear).
    """
    if TAG_MODEL_TRANSFORMATION in tags:
        m = [float(v) for v in tags[TAG_MODEL_TRANSFORMATION]]
        if len(m) != 16:
            raise DataFormatError(f"{path}: ModelTransformationTag must hold 16 values, got {len(m)}")
        if m[1] != 0.0 or m[4] != 0.0:
            raise DataFormatError(f"{path}: ModelTransformationTag has rotation/shear terms "
                                  f"({m[1]}, {m[4]}); only axis-aligned rasters are read")
        ax, sx, ay, sy = m[3], m[0], m[7], m[5]
    else:
        if TAG_MODEL_PIXEL_SCALE not in tags or TAG_MODEL_TIEPOINT not in tags:
            raise DataFormatError(f"{path}: needs ModelPixelScaleTag ({TAG_MODEL_PIXEL_SCALE}) and "
                                  f"ModelTiepointTag ({TAG_MODEL_TIEPOINT}), or "
                                  f"ModelTransformationTag ({TAG_MODEL_TRANSFORMATION})")
        scale = [float(v) for v in tags[TAG_MODEL_PIXEL_SCALE]]
        tie = [float(v) for v in tags[TAG_MODEL_TIEPOINT]]
        if len(scale) != 3 or len(tie) != 6:
            raise DataFormatError(f"{path}: expected 3 pixel scales and one tie point (6 values), got "
                                  f"{len(scale)} and {len(tie)} values")
        sx, sy = scale[0], -scale[1]
        ax, ay = tie[3] - tie[0] * sx, tie[4] - tie[1] * sy
    if not all(math.isfinite(v) for v in (ax, sx, ay, sy)) or sx == 0.0 or sy == 0.0:
        raise DataFormatError(f"{path}: degenerate georeference: origin ({ax}, {ay}), step ({sx}, {sy})")
    return ax, sx, ay, sy


def _gdal_nodata(path: Path, text, where: str = f"GDAL_NODATA ({TAG_GDAL_NODATA})") -> float | None:
    """The nodata value written as text, or None without one. A decimal comma is read as a point,
    as GDAL reads the tag (CPLAtofM: "either a comma or a period for the decimal delimiter")."""
    if text is None:
        return None
    try:
        return float(str(text).strip().rstrip("\x00").replace(",", "."))
    except ValueError:
        raise DataFormatError(f"{path}: {where} must be a number, got {text!r}") from None


# Largest GDAL PAM sidecar (<file>.aux.xml) read: its statistics and histograms are a few kilobytes.
MAX_PAM_BYTES = 1 << 20


def _pam_nodata(path: Path) -> float | None:
    """Band 1's NoDataValue from GDAL's PAM sidecar ``<file>.aux.xml`` (``<PAMDataset><PAMRasterBand
    band="1"><NoDataValue>``), or None without one. GDAL puts a GeoTIFF's nodata there when it cannot
    write the tag (a read-only file, gdal_edit.py -a_nodata on some files, ArcGIS), and reads it from
    there when the file has no GDAL_NODATA tag (GDAL's GTiff driver, then GDALPamRasterBand)."""
    pam = path.with_name(path.name + ".aux.xml")
    if not pam.is_file() or pam.stat().st_size > MAX_PAM_BYTES:
        return None
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(pam.read_bytes())
    except ET.ParseError as e:
        raise DataFormatError(f"{path}: its GDAL sidecar {pam.name} is not XML ({e})") from None
    for band in root.iter("PAMRasterBand"):
        item = band.find("NoDataValue")
        if band.get("band", "1") == "1" and item is not None:
            return _gdal_nodata(path, item.text or "", f"{pam.name}'s NoDataValue")
    return None


# --------------------------------------------------------------------------- raw 16-bit

def read_raw16(path, rows: int, cols: int, lat0: float, lon0: float, dlat: float, dlon: float,
               big_endian: bool = True, signed: bool = True, north_up: bool = True,
               nodata: int | None = None) -> Raster:
    """Headerless 16-bit posts with an explicit georeference (EPSG:4326).

    rows x cols posts; (lat0, lon0) degrees is the south-west post; dlat, dlon
    degrees between posts. north_up: file row 0 is the north row (as in .hgt).
    Posts equal to ``nodata`` are voids, filled by the harmonic rule.
    Heights float32, metres above mean sea level as supplied.
    """
    path = _existing(path)
    for name, value in (("rows", rows), ("cols", cols)):
        if int(value) != value or value < 2:
            raise InvalidArgument(name, "must be a whole number >= 2", value=value)
    for name, value in (("lat0", lat0), ("lon0", lon0), ("dlat", dlat), ("dlon", dlon)):
        if not math.isfinite(value):
            raise InvalidArgument(name, "must be finite", value=value)
    for name, value in (("dlat", dlat), ("dlon", dlon)):
        if value <= 0:
            raise InvalidArgument(name, "must be positive (degrees between posts)", value=value)
    rows, cols = int(rows), int(cols)
    nbytes = path.stat().st_size
    if nbytes != 2 * rows * cols:
        raise DataFormatError(f"{path}: {nbytes} bytes, but {rows} x {cols} 16-bit posts need "
                              f"{2 * rows * cols}")
    dtype = np.dtype(("i2" if signed else "u2")).newbyteorder(">" if big_endian else "<")
    posts = np.fromfile(path, dtype=dtype).reshape(rows, cols)
    if north_up:
        posts = posts[::-1]
    voids = np.zeros(posts.shape, bool) if nodata is None else posts == nodata
    meta = {"format": "raw 16-bit", "byte_order": "big" if big_endian else "little",
            "signed": signed, "north_up": north_up, "nodata": nodata}
    return _finish(path, posts, voids, _make_georef(path, CRS_GEOGRAPHIC, lon0, lat0, dlon, dlat),
                   VERTICAL_DATUM_DEFAULT, meta)


# --------------------------------------------------------------------------- voids

# Void regions up to this many posts are solved directly (sparse LU, SuperLU);
# larger ones by multigrid-preconditioned conjugate gradients (_fill_iterative).
FILL_DIRECT_MAX_POSTS = 40_000
# Small regions are solved together, in batches of at least this many posts (each region's
# equations are independent: the batch bounds the direct solver's memory, whatever the count).
FILL_DIRECT_BATCH_POSTS = 200_000
# Largest void region filled: the interior of a 3601 x 3601 SRTM1 tile
# (3599**2 posts; the iterative solve needs about 130 bytes a post of the
# region's box, 1.7 GB here). A larger one is refused by name, not swapped.
FILL_MAX_POSTS = 3599 * 3599
# Iterations of _mgcg before it gives up (each reduces the residual about
# threefold; measured 18 for a 1000 x 1000-post region, 23 for 3400 x 3400).
MGCG_MAX_ITERATIONS = 200
# Target error (m) of an iteratively filled post against the exact harmonic
# value, reached through the residual bound in _fill_iterative.
FILL_TOLERANCE_M = 1.0e-3


def enclosed_voids(voids: np.ndarray) -> np.ndarray:
    """(ny, nx) bool: the void posts whose 4-connected void region does not touch the grid's edge.

    voids: (ny, nx) bool. A region touching the edge is where the data ends (a
    clipped DEM's outside, a mosaic's gap at its border), not a hole in it.
    """
    voids = np.asarray(voids, dtype=bool)
    labels, n = scipy.ndimage.label(voids)
    if n == 0:
        return np.zeros(voids.shape, bool)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return voids & ~np.isin(labels, edge)


def fill_voids(heights: np.ndarray, voids: np.ndarray) -> np.ndarray:
    """Harmonic values for the void posts of a grid (the module's void rule).

    heights: (ny, nx) float, metres; values at void posts are ignored.
    voids: (ny, nx) bool, the posts to fill. Non-void posts that are NaN, and
    the grid's edge, are natural boundaries (no neighbour there). Returns (m,)
    float64, the filled values of the m void posts in row-major order (as
    ``heights[voids]`` orders them), each within the [min, max] of the valid
    posts bordering its region. Every 4-connected void region must border at
    least one finite non-void post (ValueError) and hold at most
    FILL_MAX_POSTS posts (LimitExceeded).
    """
    heights = np.asarray(heights)
    voids = np.asarray(voids, dtype=bool)
    if heights.ndim != 2 or voids.shape != heights.shape:
        raise ValueError(f"heights and voids must be (ny, nx) of one shape, got {heights.shape}, {voids.shape}")
    out = np.full(heights.shape, np.nan)
    labels, n_regions = scipy.ndimage.label(voids)  # 4-connected by default
    sizes = np.bincount(labels.ravel(), minlength=n_regions + 1)
    small = np.zeros(voids.shape, bool)
    small_posts = 0
    h_all = None
    for k, box in enumerate(scipy.ndimage.find_objects(labels), start=1):
        if sizes[k] > FILL_MAX_POSTS:
            raise LimitExceeded("void region (posts)", int(sizes[k]), FILL_MAX_POSTS)
        if sizes[k] <= FILL_DIRECT_MAX_POSTS:
            small[box] |= labels[box] == k
            small_posts += int(sizes[k])
            if small_posts >= FILL_DIRECT_BATCH_POSTS:  # many small holes: solved in batches, memory bounded
                h_all = np.where(voids, np.nan, heights).astype(np.float64) if h_all is None else h_all
                out[small] = _fill_direct(h_all, small)
                small[:] = False
                small_posts = 0
            continue
        grown = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
        region = labels[grown] == k
        h = np.where(voids[grown], np.nan, heights[grown]).astype(np.float64)
        out[grown][region] = _fill_iterative(h, region)
    if small.any():
        h_all = np.where(voids, np.nan, heights).astype(np.float64) if h_all is None else h_all
        out[small] = _fill_direct(h_all, small)
    return out[voids]


def _fill_direct(h: np.ndarray, void: np.ndarray) -> np.ndarray:
    """Harmonic values (m,) float64 of the void posts of h ((ny, nx) float64, metres, NaN
    at voids and at posts that are no neighbour), in row-major order, by one sparse direct
    solve: for regions of up to FILL_DIRECT_MAX_POSTS posts each."""
    if not void.any():
        return np.zeros(0)
    r = np.flatnonzero(void.any(axis=1))
    c = np.flatnonzero(void.any(axis=0))
    box = (slice(max(r[0] - 1, 0), r[-1] + 2), slice(max(c[0] - 1, 0), c[-1] + 2))
    h = h[box]
    void = void[box]
    known = ~void & np.isfinite(h)
    labels, n_regions = scipy.ndimage.label(void)
    m = int(void.sum())
    index = np.full(void.shape, -1, np.int64)
    index[void] = np.arange(m)
    diag = np.zeros(m)
    rhs = np.zeros(m)
    off_rows, off_cols = [], []
    lo = np.full(n_regions + 1, np.inf)
    hi = np.full(n_regions + 1, -np.inf)
    for p, q in _neighbour_pairs(void.shape):
        both = void[p] & void[q]
        off_rows.append(index[p][both])
        off_cols.append(index[q][both])
        edge = void[p] & known[q]
        value = h[q][edge]
        diag += np.bincount(index[p][both], minlength=m)
        diag += np.bincount(index[p][edge], minlength=m)
        rhs += np.bincount(index[p][edge], weights=value, minlength=m)
        np.minimum.at(lo, labels[p][edge], value)
        np.maximum.at(hi, labels[p][edge], value)
    region = labels[void]
    if not np.all(np.isfinite(lo[1:])):
        raise ValueError("a void region borders no valid post; its harmonic fill is undefined")
    rows = np.concatenate(off_rows)
    cols = np.concatenate(off_cols)
    a = scipy.sparse.csc_matrix((np.full(rows.size, -1.0), (rows, cols)), shape=(m, m))
    a = a + scipy.sparse.diags(diag, format="csc")
    # The matrix is symmetric: a symmetric fill-reducing ordering (measured 3x
    # faster than the default COLAMD on a 1000 x 1000-post void).
    values = np.atleast_1d(scipy.sparse.linalg.spsolve(a, rhs, permc_spec="MMD_AT_PLUS_A"))
    # The exact solution obeys the maximum principle; clipping removes only the
    # solver's rounding (~1e-12 m), so that promise holds bit for bit.
    return np.clip(values, lo[region], hi[region])


def _fill_iterative(h: np.ndarray, void: np.ndarray) -> np.ndarray:
    """Harmonic values (m,) float64 of the void posts of h (as :func:`_fill_direct`) by
    conjugate gradients preconditioned with one multigrid V-cycle (MGCG: Tatebe 1993,
    "The multigrid preconditioned conjugate gradient method"; V-cycle after Briggs,
    Henson & McCormick 2000, "A Multigrid Tutorial", ch. 3 and 7: red-black Gauss-Seidel,
    full weighting as the transpose of bilinear interpolation, the coarse operator the
    5-point stencil rediscretised). The sweeps are symmetric (red then black
    before, black then red after) so the preconditioner is symmetric positive definite.

    Memory is linear in the region's box: about 130 bytes a post. The iteration
    stops when the largest residual r (metres, of the unscaled 5-point equations)
    is at most FILL_TOLERANCE_M * 4 / R**2, R being half the diagonal of the box in
    posts: for a region whose posts all have four neighbours (void or valid: every
    region read_dem and the mosaic fill), the error e solves A e = r, and by the
    discrete maximum principle with the comparison function (R**2 - |x|**2) / 4,
    which A maps to 1, |e| <= max|r| R**2 / 4 <= FILL_TOLERANCE_M.
    """
    hp = np.pad(h, 1, constant_values=np.nan)
    vp = np.pad(void, 1)
    known = ~vp & np.isfinite(hp)
    deg = np.zeros(vp.shape)
    b = np.zeros(vp.shape)
    lo, hi = np.inf, -np.inf
    for p, q in _neighbour_pairs(vp.shape):
        deg[p] += vp[q] | known[q]
        border = vp[p] & known[q]
        b[p] += np.where(border, hp[q], 0.0)
        if border.any():
            lo, hi = min(lo, float(hp[q][border].min())), max(hi, float(hp[q][border].max()))
    if not math.isfinite(lo):
        raise ValueError("a void region borders no valid post; its harmonic fill is undefined")
    deg[~vp] = 1.0  # off the unknowns: any non-zero, never used
    masks = [vp.astype(np.uint8)]
    while min(masks[-1].shape) > 3 and masks[-1].any():
        masks.append(_coarse_mask(masks[-1]))
    radius = 0.5 * math.hypot(*void.shape)
    tol = FILL_TOLERANCE_M * 4.0 / max(radius * radius, 1.0)
    x, iters, residual = _mgcg(masks, deg, b, tol, MGCG_MAX_ITERATIONS)
    if residual > tol:
        log.warning("void fill: %d posts stopped after %d iterations at residual %.3g m (target %.3g m)",
                    int(void.sum()), iters, residual, tol)
    # Clipping keeps the maximum principle exact whatever the iteration left.
    return np.clip(x[vp], lo, hi)


def _mgcg(masks, deg, b, tol, max_iter):
    """x ((ny, nx) float64, zero off masks[0]) solving A x = b on masks[0]; (x, iterations,
    largest residual). A: deg x - the four neighbours' x (zero off the mask)."""
    x = np.zeros(b.shape)
    r = b.copy()
    z = _v_cycle(masks, deg, r)
    d = z.copy()
    rz = float(np.vdot(r, z))
    ad = np.zeros(b.shape)
    for it in range(max_iter + 1):
        rmax = float(np.abs(r).max())
        if rmax <= tol or it == max_iter or rz == 0.0:
            return x, it, rmax
        _apply(masks[0], deg, d, ad)
        alpha = rz / float(np.vdot(d, ad))
        x += alpha * d
        r -= alpha * ad
        z = _v_cycle(masks, deg, r)
        rz_new = float(np.vdot(r, z))
        d *= rz_new / rz
        d += z
        rz = rz_new
    return x, max_iter, rmax


def _coarse_mask(fine: np.ndarray) -> np.ndarray:
    """Coarse unknowns: coarse post (I, J) sits on fine post (2I, 2J) and is an unknown
    when a fine unknown lies in its 3 x 3 neighbourhood (its interpolation support)."""
    ny, nx = fine.shape
    grown = scipy.ndimage.binary_dilation(fine.astype(bool), np.ones((3, 3), bool))
    coarse = np.zeros((ny // 2 + 1, nx // 2 + 1), np.uint8)
    coarse[: (ny + 1) // 2, : (nx + 1) // 2] = grown[::2, ::2]
    coarse[0, :] = coarse[-1, :] = coarse[:, 0] = coarse[:, -1] = 0  # Dirichlet ring
    return coarse


def _v_cycle(masks, deg, r):
    """One V(2, 2)-cycle for A e = r from e = 0: the preconditioner's e ((ny, nx) float64)."""
    rhs = [r]
    es = []
    for level, mask in enumerate(masks):
        e = np.zeros(mask.shape)
        dg = deg if level == 0 else np.full(mask.shape, 4.0)
        last = level == len(masks) - 1
        if last:  # the coarsest level: a palindrome of sweeps keeps the cycle symmetric
            _smooth(mask, dg, rhs[level], e, 10, False)
            _smooth(mask, dg, rhs[level], e, 10, True)
        else:
            _smooth(mask, dg, rhs[level], e, 2, False)
        es.append((e, dg))
        if not last:
            res = np.zeros(mask.shape)
            _residual(mask, dg, rhs[level], e, res)
            rc = np.zeros(masks[level + 1].shape)
            _restrict(masks[level + 1], res, rc)
            rhs.append(rc)
    for level in range(len(masks) - 2, -1, -1):
        e, dg = es[level]
        _prolong_add(masks[level], es[level + 1][0], e)
        _smooth(masks[level], dg, rhs[level], e, 2, True)
    return es[0][0]


@numba.njit(cache=True, nogil=True)
def _apply(mask, deg, x, out):
    """out = A x on the mask (zero elsewhere)."""
    ny, nx = mask.shape
    for i in range(1, ny - 1):
        for j in range(1, nx - 1):
            if mask[i, j]:
                out[i, j] = deg[i, j] * x[i, j] - x[i - 1, j] - x[i + 1, j] - x[i, j - 1] - x[i, j + 1]


@numba.njit(cache=True, nogil=True)
def _residual(mask, deg, b, x, out):
    ny, nx = mask.shape
    for i in range(1, ny - 1):
        for j in range(1, nx - 1):
            if mask[i, j]:
                out[i, j] = b[i, j] - (deg[i, j] * x[i, j] - x[i - 1, j] - x[i + 1, j] - x[i, j - 1]
                                       - x[i, j + 1])


@numba.njit(cache=True, nogil=True)
def _smooth(mask, deg, b, x, sweeps, black_first):
    """Red-black Gauss-Seidel sweeps (red: i + j even), in place on the mask."""
    ny, nx = mask.shape
    for _ in range(sweeps):
        for half in range(2):
            colour = (half + (1 if black_first else 0)) % 2
            for i in range(1, ny - 1):
                for j in range(1 + (i + 1 + colour) % 2, nx - 1, 2):
                    if mask[i, j]:
                        x[i, j] = (b[i, j] + x[i - 1, j] + x[i + 1, j] + x[i, j - 1] + x[i, j + 1]) / deg[i, j]


@numba.njit(cache=True, nogil=True)
def _restrict(cmask, r, rc):
    """Full weighting (the transpose of bilinear interpolation): rc = P^T r on the coarse mask."""
    ny, nx = r.shape
    for ci in range(1, cmask.shape[0] - 1):
        for cj in range(1, cmask.shape[1] - 1):
            if cmask[ci, cj]:
                s = 0.0
                for di in range(-1, 2):
                    i = 2 * ci + di
                    if 0 <= i < ny:
                        for dj in range(-1, 2):
                            j = 2 * cj + dj
                            if 0 <= j < nx:
                                s += r[i, j] * (1.0 if di == 0 else 0.5) * (1.0 if dj == 0 else 0.5)
                rc[ci, cj] = s


@numba.njit(cache=True, nogil=True)
def _prolong_add(mask, ec, e):
    """e += P ec (bilinear interpolation of the coarse correction) on the fine mask."""
    ny, nx = mask.shape
    for i in range(1, ny - 1):
        i0, i1 = i // 2, (i + 1) // 2
        for j in range(1, nx - 1):
            if mask[i, j]:
                j0, j1 = j // 2, (j + 1) // 2
                e[i, j] += 0.25 * (ec[i0, j0] + ec[i0, j1] + ec[i1, j0] + ec[i1, j1])

def _neighbour_pairs(shape):
    """(p, q) slice pairs: q is the post north, south, east, west of post p."""
    ny, nx = shape
    full = slice(None)
    return (((slice(0, ny - 1), full), (slice(1, ny), full)),
            ((slice(1, ny), full), (slice(0, ny - 1), full)),
            ((full, slice(0, nx - 1)), (full, slice(1, nx))),
            ((full, slice(1, nx)), (full, slice(0, nx - 1))))


# --------------------------------------------------------------------------- shared finishing

def _storage_dtype(values: np.ndarray) -> np.dtype:
    """float32 if every finite value survives float32 exactly, else float64."""
    if values.dtype in (np.int8, np.uint8, np.int16, np.uint16, np.float32):
        return np.dtype(np.float32)
    v = values[np.isfinite(values)] if values.dtype.kind == "f" else values
    return np.dtype(np.float32 if np.array_equal(v.astype(np.float32), v) else np.float64)


def _existing(path) -> Path:
    path = Path(path)
    if path.is_dir():  # it exists: "does not exist" would send the user looking for a typo
        raise DataFormatError(f"{path}: is a directory, not a DEM file")
    if not path.is_file():
        raise NotFound(f"DEM file {path} does not exist")
    return path


# Largest |height| (m) a DEM post is read with: about eleven times Mount Everest (8849 m) and nine times
# the Challenger Deep (about -10,935 m), the bound of terrain.procedural.MAX_HEIGHT_MAX_M. A post beyond
# it is no terrain on Earth but a nodata value the file does not declare (float32's lowest,
# -3.4028235e+38, -1e30, ...) or heights in a unit it does not say (millimetres), which read as metres
# would be answered with STATUS_OK.
HEIGHT_ABS_MAX_M = 1.0e5


def _check_height_range(path: Path, posts: np.ndarray, voids: np.ndarray) -> None:
    """DataFormatError naming the file, the first post (row 0 south) and its value when a non-void
    post (metres) lies beyond +-HEIGHT_ABS_MAX_M."""
    if posts.dtype.kind in "iu" and posts.dtype.itemsize <= 2:  # within +-65535 m: no pass over an SRTM tile
        return
    flat = posts.reshape(-1)
    if flat.size == 0:
        return
    # fmax/fmin skip NaN (a float file's voids) without a temporary the size of the grid.
    if not (np.fmax.reduce(flat) > HEIGHT_ABS_MAX_M or np.fmin.reduce(flat) < -HEIGHT_ABS_MAX_M):
        return
    with np.errstate(invalid="ignore"):
        beyond = ((posts > HEIGHT_ABS_MAX_M) | (posts < -HEIGHT_ABS_MAX_M)) & ~voids
    if beyond.any():
        r, c = (int(i) for i in np.argwhere(beyond)[0])
        raise DataFormatError(f"{path}: {int(beyond.sum())} posts lie beyond +-{HEIGHT_ABS_MAX_M:g} m, the first "
                              f"(row {r} from the south, column {c} from the west) at {float(posts[r, c])!r} m: "
                              "a nodata value the file does not declare (GDAL_NODATA, or NODATA_value of an "
                              "ASCII grid), or heights in a unit it does not say")


def _make_georef(path: Path, crs: int, x0: float, y0: float, dx: float, dy: float) -> Georef:
    try:
        return Georef(crs, float(x0), float(y0), float(dx), float(dy))
    except ValueError as e:
        raise DataFormatError(f"{path}: bad georeference: {e}") from None


def _finish(path: Path, posts: np.ndarray, voids: np.ndarray, georef: Georef, datum: str,
            meta: dict) -> Raster:
    """Raster from file posts (row 0 south) and their void mask: checks, fills, stores."""
    ny, nx = posts.shape
    if ny < 2 or nx < 2:
        raise DataFormatError(f"{path}: needs at least 2 x 2 posts, got {ny} x {nx}")
    if voids.all():
        raise DataFormatError(f"{path}: every one of the {posts.size} posts is void")
    if georef.crs == CRS_GEOGRAPHIC:
        lat_top = georef.y0 + (ny - 1) * georef.dy
        if georef.y0 < -90.0 - POLE_TOLERANCE_DEG or lat_top > 90.0 + POLE_TOLERANCE_DEG:
            raise DataFormatError(f"{path}: posts span latitudes {georef.y0}..{lat_top}, beyond the poles")
    _check_height_range(path, posts, voids)
    dtype = _storage_dtype(posts[~voids])
    heights = posts.astype(np.float64)
    heights[voids] = np.nan
    holes = enclosed_voids(voids)
    if holes.any():
        try:
            heights[holes] = fill_voids(heights, holes)
        except LimitExceeded as e:
            raise DataFormatError(f"{path}: {e}; fill it before reading, or clip it from the raster's edge "
                                  "so that it is left outside") from None
    meta = {**meta, "void_posts": int(voids.sum()), "void_posts_filled": int(holes.sum()),
            "void_posts_outside": int(voids.sum() - holes.sum())}
    turn = 360.0 if georef.crs == CRS_GEOGRAPHIC else TWO_PI_A_M
    if abs(nx * georef.dx - turn) <= FULL_TURN_TOLERANCE * turn:
        # A full turn of cell-registered columns: repeat the first column one turn east, so
        # the cells between the last and the first column are read like any other.
        heights = np.concatenate([heights, heights[:, :1]], axis=1)
        holes = np.concatenate([holes, holes[:, :1]], axis=1)
        meta["wrap_column_added"] = True
    return Raster(heights.astype(dtype), georef, name=path.stem, vertical_datum=datum,
                  filled=holes if holes.any() else None, source=str(path), meta=meta)
