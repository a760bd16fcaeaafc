"""Terrain meshes (terrain/mesh.py) and `sortie terrain mesh` (terrain/mesh_cli.py).

Bounds, and why they hold:

- *At the posts.* A grid whose points are the Alps tile's posts gets the file's heights
  (big-endian int16 read here with numpy, not through Sortie's reader) to 1e-6 m: bilinear
  interpolation at a post returns the post, up to the rounding of the grid's latitudes
  (1e-15 degrees, times a slope below 2: nanometres).
- *Round trip.* ENU -> ECEF -> geodetic (Bowring, 3 rounds: terrain/geodesy.py) recovers each
  vertex's latitude and longitude within 1e-9 degrees and its height within 1 mm.
- *The files.* glTF stores float32 positions: within 2^-24 of |v| per coordinate, times 2
  for the write and the axis swap (|v| <= 15 km here: under 2 mm).
- *Cell centres.* On the posts' own grid the cut diagonal puts the mesh at (h_NW + h_SE) / 2
  and the bilinear surface at the mean of the four corners: their difference is |d| / 4,
  d = h_NW - h_NE - h_SW + h_SE, exactly (module docstring). ``centre_error`` measures in the
  mesh's ENU frame, where the diagonal's chord also sags below the curved Earth by
  (diagonal)^2 / (8R) (0.25 mm for these 112 m cells) and the frame's up leans from a cell's
  plumb line by its distance from the origin over R (under 6e-4 rad within 3.7 km), moving the
  compared points apart by that times their height difference: it must equal |d| / 4 within
  5 mm (1.3 mm measured).
"""

from __future__ import annotations

import argparse
import json
import struct

import numpy as np
import pytest
import trimesh

from server.terrain_cli import build_terrain
from sortie.errors import InvalidArgument
from terrain.mesh import (LocalFrame, build_mesh, centre_error, enu_to_gltf, gltf_to_enu, grid_faces,
                          mesh_geodetic, output_format, write_mesh)
from terrain.mesh_cli import add_mesh_parser, local_noon


POSTS = 1201  # N47E009.hgt: 3 arc-second posts, 47-48 N, 9-10 E, row 0 north


def _hgt_posts(path) -> np.ndarray:
    return np.fromfile(path, dtype=">i2").reshape(POSTS, POSTS).astype(np.float64)


def _post_grid(row0: int, col0: int, rows: int, cols: int):
    """Latitudes (north to south) and longitudes of a window of the tile's posts."""
    lat = 48.0 - (row0 + np.arange(rows)) / (POSTS - 1)
    lon = 9.0 + (col0 + np.arange(cols)) / (POSTS - 1)
    return lat, lon


@pytest.fixture(scope="module")
def alps(hgt_alps):
    return build_terrain([hgt_alps])


def test_grid_faces_wind_counter_clockwise_and_skip_cells_without_data():
    valid = np.ones((3, 4), bool)
    f = grid_faces(valid)
    assert f.shape == (2 * 2 * 3, 3)
    x, y = np.meshgrid(np.arange(4.0), -np.arange(3.0))  # column east, row 0 north
    p = np.stack([x.ravel(), y.ravel()], -1)
    a, b, c = p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]
    area2 = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    assert np.all(area2 == 1.0)  # counter-clockwise seen from above, half a unit cell each
    valid[1, 1] = False  # touches 4 cells: 2 remain
    assert grid_faces(valid).shape == (2 * 2, 3)
    assert not np.isin(1 * 4 + 1, grid_faces(valid))
    assert grid_faces(np.ones((1, 5), bool)).shape == (0, 3)


def test_axes_round_trip_and_handedness():
    enu = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]])
    assert np.array_equal(gltf_to_enu(enu_to_gltf(enu)), enu)
    e, n, u = enu_to_gltf(np.eye(3))
    assert np.array_equal(e, [1, 0, 0]) and np.array_equal(u, [0, 1, 0]) and np.array_equal(n, [0, 0, -1])
    assert np.linalg.det(np.stack([e, n, u])) == 1.0  # east x north = up stays right-handed


def test_heights_at_the_posts_and_the_round_trip(hgt_alps, alps):
    posts = _hgt_posts(hgt_alps)
    row0, col0, rows, cols = 700, 400, 60, 80  # the Alpstein (Saentis), 47.2-47.3 N
    lat, lon = _post_grid(row0, col0, rows, cols)
    res = alps.heights(np.repeat(lat, cols), np.tile(lon, rows))
    heights = res.height_msl_m.reshape(rows, cols)
    truth = posts[row0:row0 + rows, col0:col0 + cols]
    assert np.abs(heights - truth).max() <= 1e-6
    mesh = build_mesh(heights, lat, lon, geoid_undulation_m=48.0)
    assert mesh.faces.shape == (2 * (rows - 1) * (cols - 1), 3)
    la, lo, h = mesh_geodetic(mesh)
    assert np.abs(la - np.repeat(lat, cols)).max() < 1e-9
    assert np.abs(lo - np.tile(lon, rows)).max() < 1e-9
    assert np.abs(h - truth.ravel()).max() < 1e-3
    # The vertices' normals point up: a height field has no overhangs.
    v = mesh.vertices
    normals = np.cross(v[mesh.faces[:, 1]] - v[mesh.faces[:, 0]], v[mesh.faces[:, 2]] - v[mesh.faces[:, 0]])
    assert np.all(normals[:, 2] > 0)
    # At the cells' centres: |d| / 4, the mesh's distance from the bilinear surface, within the
    # curved Earth's 5 mm in the mesh's frame (module docstring).
    err = centre_error(mesh, alps)
    d = np.abs(truth[:-1, :-1] - truth[:-1, 1:] - truth[1:, :-1] + truth[1:, 1:]).ravel() / 4.0
    assert np.abs(err - d).max() < 5e-3
    assert mesh.max_twist_m() == pytest.approx(d.max())
    assert d.max() > 10.0  # rugged: the check has something to see


def test_cells_without_data_make_no_triangles(alps):
    lat = np.linspace(47.05, 46.95, 11)  # the tile's southern edge at 47 N: half the rows have no data
    lon = np.linspace(9.3, 9.4, 12)
    res = alps.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size))
    h = np.where(res.status == 3, np.nan, res.height_msl_m).reshape(lat.size, lon.size)
    mesh = build_mesh(h, lat, lon)
    covered = int(np.isfinite(h).all(axis=1).sum())
    assert 0 < covered < lat.size
    assert mesh.faces.shape == (2 * (covered - 1) * (lon.size - 1), 3)
    assert np.isfinite(h.ravel()[mesh.faces]).all()


def test_bad_input_names_the_field():
    lat, lon = np.array([47.0, 46.9]), np.array([9.0, 9.1, 9.2])
    with pytest.raises(InvalidArgument, match="heights_msl_m"):
        build_mesh(np.zeros((3, 2)), lat, lon)
    with pytest.raises(InvalidArgument, match=r"lat\[1\]"):
        build_mesh(np.zeros((2, 3)), np.array([47.0, np.nan]), lon)
    with pytest.raises(InvalidArgument, match=r"lon\[2\]"):
        build_mesh(np.zeros((2, 3)), lat, np.array([9.0, 9.1, 600.0]))
    with pytest.raises(InvalidArgument, match="geoid_undulation_m"):
        build_mesh(np.zeros((2, 3)), lat, lon, geoid_undulation_m=np.inf)
    with pytest.raises(InvalidArgument, match="geoid_undulation_m"):
        build_mesh(np.zeros((2, 3)), lat, lon, geoid_undulation_m=1e300)  # finite, and no geoid's
    with pytest.raises(InvalidArgument, match="no triangles"):
        write_mesh(build_mesh(np.full((2, 3), np.nan), lat, lon), "x.glb")
    with pytest.raises(InvalidArgument, match="lat_deg"):
        LocalFrame.at(91.0, 0.0)
    with pytest.raises(InvalidArgument, match="output"):
        output_format("terrain.xyz")
    assert output_format("A.GLB") == "glb"


def _glb_json(data: bytes) -> dict:
    """The JSON chunk of a GLB container (glTF 2.0 specification, "Binary glTF Layout"), parsed
    strictly (NaN is not JSON: RFC 8259 §6)."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    chunk_length, chunk_type = struct.unpack_from("<II", data, 12)
    assert chunk_type == 0x4E4F534A  # "JSON"

    def no_constants(name):
        raise ValueError(f"{name} in glTF JSON")

    return json.loads(data[20:20 + chunk_length], parse_constant=no_constants)


def test_glb_file(tmp_path, alps):
    lat = np.linspace(47.30, 47.20, 41)
    lon = np.linspace(9.25, 9.40, 53)
    res = alps.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size))
    h = res.height_msl_m.reshape(lat.size, lon.size)
    mesh = build_mesh(h, lat, lon)
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (lat.size, lon.size, 3), dtype=np.uint8)
    path = write_mesh(mesh, tmp_path / "t.glb", image, extras={"note": "test"})
    data = path.read_bytes()
    gltf = _glb_json(data)
    assert gltf["asset"]["version"] == "2.0"
    frame = gltf["scenes"][0]["extras"]["sortie"]["frame"]
    assert frame["lat_deg"] == pytest.approx(47.25) and frame["lon_deg"] == pytest.approx(9.325)
    assert gltf["scenes"][0]["extras"]["sortie"]["note"] == "test"
    prim = gltf["meshes"][0]["primitives"][0]
    pos = gltf["accessors"][prim["attributes"]["POSITION"]]
    assert pos["count"] == lat.size * lon.size
    # glTF's Y is up: the accessor's bounds hold the heights (float32) in y.
    v_gltf = enu_to_gltf(mesh.vertices)
    assert np.allclose(pos["min"], v_gltf.min(axis=0), atol=1e-2) and np.allclose(pos["max"], v_gltf.max(axis=0),
                                                                                  atol=1e-2)
    # Read back through trimesh (its own glTF reader): positions within float32 rounding.
    scene = trimesh.load(tmp_path / "t.glb", force="scene")
    tm = scene.geometry["terrain"]
    back = gltf_to_enu(tm.vertices)
    bound = 2.0 * 2.0 ** -24 * np.abs(mesh.vertices).max()
    assert np.abs(back - mesh.vertices).max() <= bound
    assert np.array_equal(tm.faces, mesh.faces)
    # Each vertex samples its own pixel of the texture.
    uv = tm.visual.uv
    col = np.floor(uv[:, 0] * lon.size).astype(int)
    row = np.floor((1.0 - uv[:, 1]) * lat.size).astype(int)
    assert np.array_equal(row * lon.size + col, np.arange(lat.size * lon.size))
    assert np.array_equal(np.asarray(tm.visual.material.baseColorTexture.convert("RGB")), image)


def test_ply_obj_stl_files(tmp_path, alps):
    lat = np.linspace(47.30, 47.25, 9)
    lon = np.linspace(9.30, 9.36, 10)
    h = alps.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size)).height_msl_m.reshape(lat.size, lon.size)
    mesh = build_mesh(h, lat, lon)
    image = np.random.default_rng(1).integers(0, 256, (lat.size, lon.size, 3), dtype=np.uint8)
    ply = trimesh.load(write_mesh(mesh, tmp_path / "t.ply", image), process=False)
    assert np.abs(ply.vertices - mesh.vertices).max() <= 2.0 * 2.0 ** -24 * np.abs(mesh.vertices).max()
    assert np.array_equal(ply.visual.vertex_colors[:, :3], image.reshape(-1, 3))
    stl = trimesh.load(write_mesh(mesh, tmp_path / "t.stl"), process=False)
    assert len(stl.faces) == len(mesh.faces)
    write_mesh(mesh, tmp_path / "o" / "t.obj", image)
    write_mesh(mesh, tmp_path / "o" / "u.obj", image[::-1].copy())  # beside it: its own material and texture
    obj = trimesh.load(tmp_path / "o" / "t.obj", process=False)
    assert len(obj.faces) == len(mesh.faces)
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["t.mtl", "t.obj", "t.png", "u.mtl", "u.obj", "u.png"]
    from PIL import Image

    with Image.open(tmp_path / "o" / "t.png") as im:
        assert np.array_equal(np.asarray(im.convert("RGB")), image)
    # ENU as it is in these formats: z is up, so the heights are the z range.
    assert np.abs(stl.vertices[:, 2].max() - mesh.vertices[:, 2].max()) < 1e-2


# --------------------------------------------------------------------------- CLI

def _run(argv):
    parser = argparse.ArgumentParser(prog="sortie")
    sub = parser.add_subparsers(dest="command", required=True)
    add_mesh_parser(sub.add_parser("terrain").add_subparsers(dest="terrain_command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_end_to_end(tmp_path, hgt_alps, capsys):
    argv = ["terrain", "mesh", "--dem", str(hgt_alps), "--bbox", "47.20", "9.25", "47.30", "9.40",
            "--spacing-m", "150"]
    assert _run(argv + ["-o", str(tmp_path / "a.glb")]) == 0
    out = capsys.readouterr().out
    assert "triangles" in out and "RMS" in out and "textured for 2026-06-21T11:22:42Z" in out
    gltf = _glb_json((tmp_path / "a.glb").read_bytes())
    assert gltf["images"] and gltf["scenes"][0]["extras"]["sortie"]["time_utc"] == "2026-06-21T11:22:42Z"
    # The same command writes the same bytes.
    assert _run(argv + ["-o", str(tmp_path / "b.glb")]) == 0
    assert (tmp_path / "a.glb").read_bytes() == (tmp_path / "b.glb").read_bytes()
    assert _run(argv + ["--no-texture", "-o", str(tmp_path / "c.glb")]) == 0
    assert "images" not in _glb_json((tmp_path / "c.glb").read_bytes())


def test_local_noon():
    assert local_noon(0.0) == "2026-06-21T12:00:00Z"
    assert local_noon(-90.0) == "2026-06-21T18:00:00Z"
    assert local_noon(9.325) == "2026-06-21T11:22:42Z"


@pytest.mark.parametrize("extra, field, text", [
    (["--bbox", "47.3", "9.25", "47.2", "9.40"], "--bbox", "inverted"),
    (["--size", "3000x2000"], "--size", "4,194,304"),
    (["--spacing-m", "0"], "--spacing-m", "positive"),
    (["--geoid-undulation-m", "nan"], "--geoid-undulation-m", "within"),
    (["--time", "noon"], "--time", "ISO 8601"),
    (["-o", "x.dae"], "output", ".glb"),
    (["--geoid-undulation-m", "1e300"], "--geoid-undulation-m", "200"),
    (["--bbox", "45.0", "9.0", "46.0", "10.0"], "--bbox", "no terrain data"),
    (["-o", "/proc/no/m.glb"], "output", "cannot be written"),
])
def test_cli_rejects_bad_input(tmp_path, hgt_alps, extra, field, text):
    opts = {"--bbox": ["47.20", "9.25", "47.30", "9.40"], "-o": [str(tmp_path / "m.glb")]}
    opts[extra[0]] = extra[1:]
    argv = ["terrain", "mesh", "--dem", str(hgt_alps)]
    for k, v in opts.items():
        argv += [k, *v]
    with pytest.raises(InvalidArgument) as err:
        _run(argv)
    assert err.value.field == field and text in str(err.value)
    assert not (tmp_path / "m.glb").exists()


# --------------------------------------------------------------------------- hard cases

def test_a_box_across_the_antimeridian_is_one_piece():
    """Longitudes past 180 (as --bbox takes them) give a mesh with no seam: east grows
    steadily across the columns, and no triangle edge is longer than the cell's diagonal."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    terrain = Terrain([ProceduralTerrain(seed=7)])
    lat = np.linspace(-16.4, -16.6, 21)
    lon = np.linspace(179.9, 180.1, 23)
    h = terrain.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size)).height_msl_m.reshape(lat.size, lon.size)
    mesh = build_mesh(h, lat, lon)
    east = mesh.vertices[:, 0].reshape(lat.size, lon.size)
    assert np.all(np.diff(east, axis=1) > 0.0)
    north = mesh.vertices[:, 1].reshape(lat.size, lon.size)
    diagonal = np.hypot(np.diff(east, axis=1).max(), np.abs(np.diff(north, axis=0)).max())
    v = mesh.vertices[mesh.faces][:, :, :2]
    assert np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2).max() <= diagonal * 1.001
    # Same ground, written west of the antimeridian: the same mesh to float64 rounding.
    west = build_mesh(h, lat, lon - 360.0, frame=mesh.frame)
    assert np.abs(west.vertices - mesh.vertices).max() < 1e-6


def test_a_polar_cap():
    """A box up to the pole: every vertex within the box's 0.5 degrees of the pole (55.8 km of
    meridian arc), the pole row at one point, and the caps' triangles facing up."""
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    terrain = Terrain([ProceduralTerrain(seed=7)])
    lat = np.linspace(90.0, 89.5, 11)
    lon = np.linspace(-180.0, 180.0, 25)
    h = terrain.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size)).height_msl_m.reshape(lat.size, lon.size)
    mesh = build_mesh(h, lat, lon, frame=LocalFrame.at(90.0, 0.0))
    horizontal = np.hypot(mesh.vertices[:, 0], mesh.vertices[:, 1])
    assert horizontal.max() < 55_900.0
    pole = mesh.vertices[:lon.size]
    assert np.ptp(pole[:, :2], axis=0).max() < 1e-6  # the pole row is one point (its heights may differ)
    v = mesh.vertices[mesh.faces]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = np.linalg.norm(normals, axis=1)
    real = area > 1e-6  # the pole row's cells are triangles with one edge of zero length
    assert np.all(normals[real, 2] > 0.0)
    la, lo, hh = mesh_geodetic(mesh)
    assert np.abs(la - np.repeat(lat, lon.size)).max() < 1e-9


def test_cli_over_a_terrain_service_writes_the_same_bytes(tmp_path, hgt_alps, alps):
    """`--address` asks a running terrain service (real gRPC on loopback) instead of loading the
    DEM: heights come over the wire bit for bit, so the files are identical."""
    from server.terrain_service import create_server

    server, port = create_server(alps, "127.0.0.1:0", max_workers=2)
    server.start()
    try:
        box = ["--bbox", "47.20", "9.25", "47.30", "9.40", "--size", "80x60"]
        assert _run(["terrain", "mesh", "--dem", str(hgt_alps), *box, "-o", str(tmp_path / "file.glb")]) == 0
        assert _run(["terrain", "mesh", "--address", f"127.0.0.1:{port}", *box, "-o", str(tmp_path / "svc.glb")]) == 0
        assert (tmp_path / "file.glb").read_bytes() == (tmp_path / "svc.glb").read_bytes()
        with pytest.raises(InvalidArgument, match="not both"):
            _run(["terrain", "mesh", "--address", f"127.0.0.1:{port}", "--dem", str(hgt_alps), *box,
                  "-o", str(tmp_path / "x.glb")])
    finally:
        server.stop(0.5)


# --------------------------------------------------------------------------- adaptive meshes

def test_adaptive_mesh_on_the_posts(tmp_path, hgt_alps):
    """An RTIN of a 129 x 129 window of the Alps' posts: its vertices are the regular mesh's at
    their grid points, with their texels; every post is within the bound of it (terrain/rtin.py
    and tests/test_rtin.py hold the bound; here the pieces fit together), and its faces are the
    fewer."""
    from terrain.mesh import build_adaptive_mesh

    posts = _hgt_posts(hgt_alps)
    lat, lon = _post_grid(700, 400, 129, 129)
    h = posts[700:829, 400:529]
    full = build_mesh(h, lat, lon)
    mesh = build_adaptive_mesh(h, lat, lon, 5.0)
    assert np.array_equal(mesh.vertices, full.vertices[mesh.grid_index])
    assert np.array_equal(mesh.uv, full.uv[mesh.grid_index])
    assert len(mesh.faces) < 0.6 * len(full.faces)
    # The mesh at every post: interpolate each face over the posts it covers.
    g = mesh.grid_faces
    ya, xa = np.divmod(g[:, 0], 129)
    yb, xb = np.divmod(g[:, 1], 129)
    yc, xc = np.divmod(g[:, 2], 129)
    worst = 0.0
    for k in range(len(g)):
        gy, gx = np.mgrid[min(ya[k], yb[k], yc[k]):max(ya[k], yb[k], yc[k]) + 1,
                          min(xa[k], xb[k], xc[k]):max(xa[k], xb[k], xc[k]) + 1]
        d = (xb[k] - xa[k]) * (yc[k] - ya[k]) - (yb[k] - ya[k]) * (xc[k] - xa[k])
        wa = ((xb[k] - gx) * (yc[k] - gy) - (yb[k] - gy) * (xc[k] - gx)) / d
        wb = ((xc[k] - gx) * (ya[k] - gy) - (yc[k] - gy) * (xa[k] - gx)) / d
        inside = (wa >= 0) & (wb >= 0) & (wa + wb <= 1)
        plane = wa * h[ya[k], xa[k]] + wb * h[yb[k], xb[k]] + (1 - wa - wb) * h[yc[k], xc[k]]
        worst = max(worst, float(np.abs(h[gy, gx] - plane)[inside].max()))
    assert worst <= 5.0
    image = np.random.default_rng(3).integers(0, 256, (129, 129, 3), dtype=np.uint8)
    ply = trimesh.load(write_mesh(mesh, tmp_path / "a.ply", image), process=False)
    assert np.array_equal(ply.visual.vertex_colors[:, :3], image.reshape(-1, 3)[mesh.grid_index])
    glb = trimesh.load(write_mesh(mesh, tmp_path / "a.glb", image), force="scene").geometry["terrain"]
    assert np.array_equal(glb.faces, mesh.faces)


def test_cli_adaptive(tmp_path, hgt_alps, capsys):
    box = ["--bbox", "47.20", "9.25", "47.30", "9.40", "--spacing-m", "100"]
    assert _run(["terrain", "mesh", "--dem", str(hgt_alps), *box, "--max-error-m", "5",
                 "-o", str(tmp_path / "a.glb")]) == 0
    out = capsys.readouterr().out
    assert "of a 129x129 grid" in out  # 2^k + 1 posts a side, at least the 113 x 111 asked
    with pytest.raises(InvalidArgument) as err:
        _run(["terrain", "mesh", "--dem", str(hgt_alps), *box, "--max-error-m", "-1", "-o", str(tmp_path / "b.glb")])
    assert err.value.field == "--max-error-m"
    with pytest.raises(InvalidArgument) as err:
        _run(["terrain", "mesh", "--dem", str(hgt_alps), "--bbox", "47.0", "9.0", "48.0", "10.0", "--spacing-m", "50",
              "--max-error-m", "5", "-o", str(tmp_path / "b.glb")])
    assert err.value.field == "--spacing-m" and "2049" in str(err.value)
    assert not (tmp_path / "b.glb").exists()


def test_centre_error_leaves_out_holes_in_the_terrain(alps):
    """A centre where the terrain has no height (here: the Alps with a hole cut round one
    centre, a stand-in for a DEM's unfilled gap) is left out, not NaN."""
    lat, lon = np.linspace(47.30, 47.25, 6), np.linspace(9.30, 9.36, 7)
    h = alps.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size)).height_msl_m.reshape(6, 7)
    mesh = build_mesh(h, lat, lon)
    hole = (0.5 * (lat[2] + lat[3]), 0.5 * (lon[3] + lon[4]))

    class Holed:
        def heights(self, la, lo):
            res = alps.heights(la, lo)
            res.height_msl_m[(np.abs(la - hole[0]) < 1e-9) & (np.abs(lo - hole[1]) < 1e-9)] = np.nan
            return res

    err = centre_error(mesh, Holed())
    assert err.size == 5 * 6 - 1 and np.isfinite(err).all()
