"""Probe fixes, stop 32, datum: adaptive meshes in the frame their vertices are in, and
geographic 3D CRSs as ellipsoidal heights.

1. An adaptive terrain mesh (terrain/rtin.py through terrain/mesh.py) bounded the error of its
   MSL heights on the lat/lon grid while its vertices stand in a local ENU frame, where the
   ground drops with Earth's curvature: a plane of heights over 0.8 degree became 2 triangles
   255 m under the ground at the centre, the Kattegat's sea 15 m under its posts at
   --max-error-m 1, a debrief scene's parked aircraft 82 m above the drawn ground; and the
   reported error (``centre_error``) measured on the grid too, so it said "0.00 m".
   Oracles here are independent of Sortie's geodesy and point location: each post's true
   position from PROJ (pyproj, EPSG:4979 -> EPSG:4978, then the ENU rotation written out), the
   mesh's height at a point from matplotlib's triangle interpolator.
   Bounds: every post within ``max_error_m`` + 1e-6 m (rounding) of the mesh along the frame's
   up, where the mesh covers it (the box's edges are parallels, which bow out of the straight
   border edges: those posts have no mesh over them); a file's vertices are float32 offsets,
   within 2^-24 of |v| <= 60 km each, 2 x 4 mm with the axis swap: 0.01 m more. Between posts,
   the terrain bends away from a plane by at most (cell diagonal)^2 / (8R) more (1.8 km cells:
   0.07 m): 0.1 m allowed there.
2. A GeoTIFF whose GeographicTypeGeoKey (2048) is a geographic 3D CRS (4979: its third axis is
   the ellipsoidal height) and that has no VerticalCSTypeGeoKey (4096) was read as mean sea
   level; it is refused naming the key and the value, as 4096 = 4979 is. An ASCII grid's .prj
   that is a geographic 3D CRS likewise.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import matplotlib.tri as mtri
import numpy as np
import pytest
import tifffile
from pyproj import CRS, Transformer

from server.terrain_cli import build_terrain
from sortie.errors import DataFormatError
from terrain.dem import read_asc, read_dem
from terrain.mesh import build_adaptive_mesh, build_mesh, centre_error, read_glb, with_grid_faces
from terrain.rtin import rtin_faces

_TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
# The probe's plane of heights in central Chile: MSL = 500 + 100 (lat + 34) + 50 (lon + 71) m.
BOX = (-33.9, -70.9, -33.1, -70.1)  # lat, lon south-west, north-east: about 89 x 74 km
UNDULATION_M = 30.0


def _plane(lat, lon):
    return 500.0 + 100.0 * (np.asarray(lat) + 34.0) + 50.0 * (np.asarray(lon) + 71.0)


def _grid(n: int = 65):
    lat = np.linspace(BOX[2], BOX[0], n)  # row 0 north
    lon = np.linspace(BOX[1], BOX[3], n)
    return _plane(lat[:, None], lon[None, :]), lat, lon


def _enu(frame_lat, frame_lon, frame_h, lat, lon, h_ellipsoidal) -> np.ndarray:
    """(n, 3) ENU metres of points given by latitude, longitude and ellipsoidal height, by PROJ."""
    x, y, z = _TO_ECEF.transform(np.ravel(lon), np.ravel(lat), np.ravel(h_ellipsoidal))
    origin = np.array(_TO_ECEF.transform(frame_lon, frame_lat, frame_h))
    la, lo = np.radians(frame_lat), np.radians(frame_lon)
    rot = np.array([[-np.sin(lo), np.cos(lo), 0.0],
                    [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                    [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    return (np.stack([x, y, z], -1) - origin) @ rot.T


def _mesh_up(vertices_enu, faces, east_north) -> np.ndarray:
    """The mesh's up at each (east, north), NaN outside it (matplotlib's interpolator)."""
    tri = mtri.Triangulation(vertices_enu[:, 0], vertices_enu[:, 1], faces)
    z = mtri.LinearTriInterpolator(tri, vertices_enu[:, 2])(east_north[:, 0], east_north[:, 1])
    return np.asarray(np.ma.filled(z, np.nan), dtype=np.float64)


def _post_gaps(mesh, lat, lon, heights_msl) -> np.ndarray:
    """Mesh minus truth along the frame's up at every post's true east and north (NaN: no mesh
    over it)."""
    f = mesh.frame
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    truth = _enu(f.lat_deg, f.lon_deg, f.h_m, la, lo, np.asarray(heights_msl) + mesh.geoid_undulation_m)
    return _mesh_up(mesh.vertices, mesh.faces, truth[:, :2]) - truth[:, 2]


class _PlaneTerrain:
    """The plane of heights as a terrain (``heights(lat, lon).height_msl_m``), exact anywhere."""

    def heights(self, lat, lon):
        return SimpleNamespace(height_msl_m=_plane(lat, lon))


# --------------------------------------------------------------------------- 1: curvature

def test_an_adaptive_mesh_of_a_plane_of_heights_keeps_its_bound_on_the_curved_earth():
    """The probe's plane over 89 x 74 km at 0.5 m: before, 2 triangles, 255 m under the posts at
    the centre; now every post within 0.5 m of the mesh in its ENU frame."""
    h, lat, lon = _grid()
    mesh = build_adaptive_mesh(h, lat, lon, 0.5, geoid_undulation_m=UNDULATION_M)
    gaps = _post_gaps(mesh, lat, lon, h)
    covered = np.isfinite(gaps)
    assert covered.mean() > 0.95  # all but posts on the bowed-out parallels at the box's edges
    assert np.abs(gaps[covered]).max() <= 0.5 + 1e-6
    assert len(mesh.faces) > 2  # the curved ground takes triangles a plane of heights did not


def test_the_kattegat_at_one_metre(hgt_kattegat):
    """N57E011 (mostly sea, at 0 m) as 129 x 129 posts over the whole tile at 1 m: before, the
    sea's large triangles sagged 15 m under their posts (a 28 km edge: L^2 / (8R) = 15 m)."""
    terrain = build_terrain([hgt_kattegat])
    lat, lon = np.linspace(58.0, 57.0, 129), np.linspace(11.0, 12.0, 129)
    res = terrain.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size))
    h = np.where(res.status == 3, np.nan, res.height_msl_m).reshape(lat.size, lon.size)
    mesh = build_adaptive_mesh(h, lat, lon, 1.0, geoid_undulation_m=36.0)
    gaps = _post_gaps(mesh, lat, lon, h)
    covered = np.isfinite(gaps)
    assert covered.mean() > 0.95
    assert np.abs(gaps[covered]).max() <= 1.0 + 1e-6


def test_centre_error_measures_in_the_vertices_frame():
    """A two-triangle mesh of the plane of heights (what the grid-space bound kept) is 255 m
    under the ground at the centre: ``centre_error`` now says so, to within 1 cm of the
    independent gap at the cells' centres; before, it said 0. The adaptive mesh's centre error
    stays within the bound plus a cell's bend (0.1 m)."""
    h, lat, lon = _grid()
    full = build_mesh(h, lat, lon, geoid_undulation_m=UNDULATION_M)
    two = with_grid_faces(full, rtin_faces(h, 0.5))  # the heights alone: one plane
    assert len(two.faces) == 2
    terrain = _PlaneTerrain()
    lat_c, lon_c = 0.5 * (lat[:-1] + lat[1:]), 0.5 * (lon[:-1] + lon[1:])
    f = two.frame
    la, lo = np.meshgrid(lat_c, lon_c, indexing="ij")
    truth = _enu(f.lat_deg, f.lon_deg, f.h_m, la, lo, _plane(la, lo) + UNDULATION_M)
    oracle = np.abs(_mesh_up(two.vertices, two.faces, truth[:, :2]) - truth[:, 2])
    err = centre_error(two, terrain)
    assert err.size == 64 * 64
    assert err.max() > 200.0 and abs(err.max() - np.nanmax(oracle)) < 0.01
    adaptive = build_adaptive_mesh(h, lat, lon, 0.5, geoid_undulation_m=UNDULATION_M)
    assert centre_error(adaptive, terrain).max() <= 0.5 + 0.1


def test_rtin_positions_are_checked_and_the_grid_default_unchanged():
    """``east_north`` is (n, n, 2), finite where a post has a height (InvalidArgument naming the
    post); given as the grid's own (column, row), it makes the same triangles as the default."""
    from sortie.errors import InvalidArgument

    h = np.cumsum(np.cumsum(np.random.default_rng(2).normal(size=(33, 33)), 0), 1)
    rows, cols = np.mgrid[0:33, 0:33].astype(float)
    grid = np.stack([cols, rows], -1)
    assert np.array_equal(rtin_faces(h, 2.0, grid), rtin_faces(h, 2.0))
    with pytest.raises(InvalidArgument, match="east_north") as err:
        rtin_faces(h, 2.0, grid[:, :, :1])
    assert err.value.field == "east_north"
    grid[3, 5] = np.nan
    with pytest.raises(InvalidArgument) as err:
        rtin_faces(h, 2.0, grid)
    assert err.value.field == "east_north[3, 5]"
    h[3, 5] = np.nan  # no height, no position needed
    assert np.isfinite(h.ravel()[rtin_faces(h, 2.0, grid)]).all()


def _plane_geotiff(path):
    """The plane of heights as a GeoTIFF, EPSG:4326, 0.01 degree posts over -34..-33, -71..-70."""
    lat = np.linspace(-33.0, -34.0, 101)[:, None]
    lon = np.linspace(-71.0, -70.0, 101)[None, :]
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 2), (2048, 0, 1, 4326)]
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tifffile.imwrite(path, _plane(lat, lon).astype(np.float64),
                     extratags=[(34735, "H", len(directory), directory, False),
                                (33550, "d", 3, [0.01, 0.01, 0.0], False),
                                (33922, "d", 6, [0, 0, 0, -71.0, -33.0, 0], False)])
    return path


def _glb_mesh(path):
    """(gltf JSON, binary, vertices ENU, faces) of the first mesh of a GLB file."""
    gltf, binary = read_glb(path.read_bytes())

    def accessor(i):
        a = gltf["accessors"][i]
        view = gltf["bufferViews"][a["bufferView"]]
        n = {"SCALAR": 1, "VEC3": 3}[a["type"]]
        dtype = {5126: "<f4", 5123: "<u2", 5125: "<u4"}[a["componentType"]]
        return np.frombuffer(binary, dtype, a["count"] * n, view.get("byteOffset", 0) + a.get("byteOffset", 0)
                             ).reshape(-1, n).astype(np.float64)

    prim = gltf["meshes"][0]["primitives"][0]
    p = accessor(prim["attributes"]["POSITION"])
    enu = np.stack([p[:, 0], -p[:, 2], p[:, 1]], -1)  # glTF (east, up, -north)
    return gltf, enu, accessor(prim["indices"]).reshape(-1, 3).astype(np.int64)


def test_the_mesh_command_writes_and_reports_the_curved_bound(tmp_path, capsys):
    """`sortie terrain mesh --max-error-m 0.5` of the probe's box: the file's mesh within 0.5 m
    (+ 0.01 m float32) of the terrain at the grid's posts, and the error it prints at the cells'
    centres within 0.6 m; before: 2 triangles, 255 m off, and "0.00 m at most"."""
    from test_mesh import _run

    out = tmp_path / "plane.glb"
    assert _run(["terrain", "mesh", "--dem", str(_plane_geotiff(tmp_path / "plane.tif")), "--bbox",
                 *map(str, BOX), "--size", "64x64", "--no-texture", "--geoid-undulation-m", str(UNDULATION_M),
                 "--max-error-m", "0.5", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    at_most = float(printed.split(" m at most")[0].rsplit(" ", 1)[1])
    assert "of a 65x65 grid" in printed and 0.0 < at_most <= 0.6
    gltf, enu, faces = _glb_mesh(out)
    frame = gltf["scenes"][0]["extras"]["sortie"]["frame"]
    h, lat, lon = _grid()  # 65 x 65 points over the box (the command's posts are its pixel centres: 0.1 m more)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    truth = _enu(frame["lat_deg"], frame["lon_deg"], frame["h_m"], la, lo, _plane(la, lo) + UNDULATION_M)
    gaps = _mesh_up(enu, faces, truth[:, :2]) - truth[:, 2]
    assert np.isfinite(gaps).mean() > 0.9
    assert np.nanmax(np.abs(gaps)) <= 0.5 + 0.01 + 0.1  # posts or not, where the grid is the command's


def test_a_debrief_scene_draws_its_ground_under_the_parked(tmp_path):
    """`sortie export gltf --max-error-m 1`: entities standing on the plane of heights across
    the box, the scene's terrain under each within 1 m + 0.1 m (between posts) + 0.01 m
    (float32); before, 4 vertices and the centre's entity 100 m and more above the drawn ground."""
    from server.gltf import export_gltf
    from server.recording import Recording
    from sortie.v1 import simulation_pb2 as pb
    from test_acmi import info, write_synthetic

    places = {1: (-33.8, -70.8), 2: (-33.2, -70.2), 3: (-33.5, -70.5), 4: (-33.8, -70.2)}
    tracks = {i: (info(i, f"parked{i}", pb.ENTITY_KIND_GROUND, "jeep"),
                  lambda tick, p=p: (p[0], p[1], float(_plane(*p)), 0.0, 0.0, 0.0)) for i, p in places.items()}
    rec = tmp_path / "plane.sortie"
    write_synthetic(rec, tracks, ticks=2)
    terrain = build_terrain([_plane_geotiff(tmp_path / "plane.tif")])
    with Recording(rec) as r:
        stats = export_gltf(r, tmp_path / "scene.glb", terrain, size="64x64", texture=False, max_error_m=1.0)
    assert stats.terrain_centre_error_m_max <= 1.0 + 0.1
    gltf, enu, faces = _glb_mesh(tmp_path / "scene.glb")
    markers = [n for n in gltf["nodes"] if n.get("name", "").endswith(" marker") and "translation" in n]
    assert len(markers) == len(places)
    at = np.array([m["translation"] for m in markers])
    ground = _mesh_up(enu, faces, np.stack([at[:, 0], -at[:, 2]], -1))
    assert np.isfinite(ground).all()
    assert np.abs(at[:, 1] - ground).max() <= 1.0 + 0.1 + 0.01, json.dumps([m["name"] for m in markers])


# --------------------------------------------------------------------------- 2: geographic 3D

def _geotiff(path, geographic: int, vertical: int | None):
    keys = [(1024, 0, 1, 2), (1025, 0, 1, 2), (2048, 0, 1, geographic)]
    if vertical is not None:
        keys.append((4096, 0, 1, vertical))
    directory = [1, 1, 0, len(keys)] + [v for k in keys for v in k]
    tifffile.imwrite(path, np.full((11, 11), 600.0, np.float32),
                     extratags=[(34735, "H", len(directory), directory, False),
                                (33550, "d", 3, [0.01, 0.01, 0.0], False),
                                (33922, "d", 6, [0, 0, 0, -71.0, -33.0, 0], False)])
    return path


def test_a_geographic_3d_crs_without_a_vertical_key_is_ellipsoidal(tmp_path):
    """2048 = 4979 alone: refused naming the key and the code (before: read as mean sea level,
    "as supplied"), as 2048 = 4326 with 4096 = 4979 is."""
    with pytest.raises(DataFormatError, match=r"g\.tif: GeographicTypeGeoKey \(2048\) = 4979 without a "
                                              r"VerticalCSTypeGeoKey \(4096\): ellipsoidal heights"):
        read_dem(_geotiff(tmp_path / "g.tif", 4979, None))
    with pytest.raises(DataFormatError, match=r"VerticalCSTypeGeoKey \(4096\) = 4979: ellipsoidal heights"):
        read_dem(_geotiff(tmp_path / "v.tif", 4326, 4979))


@pytest.mark.parametrize("geographic, vertical, datum", [
    (4979, 5773, "EGM96 geoid (EPSG:5773)"),       # the vertical key says what the heights are
    (4979, 32767, "mean sea level (as supplied)"),  # user-defined: as supplied, as for any CRS
    (4326, None, "mean sea level (as supplied)"),   # a 2-D CRS alone: as before
])
def test_a_vertical_key_still_decides(tmp_path, geographic, vertical, datum):
    raster = read_dem(_geotiff(tmp_path / "g.tif", geographic, vertical))
    assert raster.vertical_datum == datum and np.all(raster.heights == 600.0)


def _asc(path):
    path.write_text("ncols 3\nnrows 3\nxllcenter -71\nyllcenter -33\ncellsize 0.1\n" + "600 600 600\n" * 3)
    return path


@pytest.mark.parametrize("wkt", [
    CRS(4979).to_wkt("WKT1_ESRI"),  # GEOGCS["WGS_1984_3D", ..., LINUNIT["Meter",1.0]]
    CRS(4979).to_wkt("WKT2_2019"),  # GEOGCRS["WGS 84", ..., CS[ellipsoidal,3], ...]
    CRS(4937).to_wkt("WKT1_ESRI"),  # ETRS89 3D
], ids=["esri-4979", "wkt2-4979", "esri-4937"])
def test_an_ascii_grid_with_a_geographic_3d_prj_is_refused(tmp_path, wkt):
    (tmp_path / "g.prj").write_text(wkt)
    with pytest.raises(DataFormatError, match=r"g\.asc: its g\.prj is a geographic 3D CRS .*ellipsoidal heights"):
        read_asc(_asc(tmp_path / "g.asc"))


@pytest.mark.parametrize("wkt", [CRS(4326).to_wkt("WKT1_ESRI"), CRS(4326).to_wkt("WKT2_2019"),
                                 CRS(4326).to_wkt("WKT1_GDAL")], ids=["esri", "wkt2", "gdal"])
def test_an_ascii_grid_with_a_2d_prj_is_read(tmp_path, wkt):
    (tmp_path / "g.prj").write_text(wkt)
    raster = read_asc(_asc(tmp_path / "g.asc"))
    assert raster.meta["crs_prj"] and np.all(raster.heights == 600.0)
