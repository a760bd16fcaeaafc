"""The terrain as a triangle mesh in a local frame, for export (glTF, OBJ, PLY, STL).

Analysts and debriefs take terrain into other tools: a glTF viewer, Blender, Cesium, a
3-D printer. This module holds the pure array part (a lat/lon grid of heights -> vertices,
triangles, texture coordinates in a local frame) and writes the files through trimesh.

**The grid.** Heights on a regular lat/lon grid, row 0 north, column 0 west (the layout of
``terrain.texture.grid_latlon`` and of ``sortie terrain texture``): one vertex per grid
point, two triangles per cell whose four corners have data, none where a corner has none
(NaN: no source covers it). Each cell is cut along its NW-SE diagonal. Against the terrain's
own surface (bilinear between posts: ``terrain.raster``), a triangle pair z = a + bx + cy
(two planes) differs from the bilinear patch z = a + bx + cy + dxy by at most |d| / 4 at the
cell's centre, d = h_NW - h_NE - h_SW + h_SE, whichever diagonal is cut: the mesh is exact at
its vertices and within a quarter of each cell's twist in between.

**Adaptive meshes** (:func:`build_adaptive_mesh`): on a (2^k + 1)^2 grid, the right-triangulated
irregular network of terrain/rtin.py keeps only the triangles an error bound at every grid post
needs; its vertices are a subset of the grid's (``TerrainMesh.grid_index``). The bound holds in
the frame below: each post's vertex within it of its triangles' planes along the frame's up, so
the curved Earth under a flat triangle counts (a triangle's chord of length L sags about
L^2 / (8R) below the ground: 15 m for 28 km, R = 6371 km), as does the terrain's own relief.

**The frame.** Vertices are float64 metres east, north and up (ENU) from an origin on the
WGS84 ellipsoid (``terrain.geodesy``); files hold float32 offsets from it, within 2^-24 of
the distance (a millimetre at 17 km, 8 mm at 130 km). Heights are MSL (the terrain's); a
vertex's ellipsoidal height is the MSL height plus ``geoid_undulation_m``, the constant the
simulation world uses (``server.world.World``), so a recorded track and the mesh meet where the
world had them meet.

**Axes in the files.** glTF is Y up (glTF 2.0 specification, "Coordinate System and Units":
right-handed, +Y up, metres), so .glb/.gltf files carry (x, y, z) = (east, up, -north). OBJ,
PLY and STL carry ENU as it is (z up, the convention of GIS, CAD and slicers). The origin's
latitude, longitude and height go with the scene (glTF: the scene's ``extras``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from sortie.errors import DataFormatError, InvalidArgument
from terrain.geodesy import ecef_to_geodetic, enu_basis, geodetic_to_ecef

# The largest mesh one call builds: 4 Mi vertices (2048 x 2048), about 8 Mi triangles,
# some 150 MB as glTF; past that a viewer struggles and the grid should be coarser.
MAX_VERTICES = 2048 * 2048
# The largest grid an adaptive mesh samples: 2049 x 2049 posts (2^11 + 1, the RTIN grid of
# terrain/rtin.py nearest MAX_VERTICES). What MAX_VERTICES bounds is the memory and time of the
# build, which holds every grid post (heights, ECEF, ENU, uv; the texture a pixel a post) in either
# kind: this grid has 0.1 % more posts than 2048 x 2048, while the next one down, 1025 x 1025,
# would cap an adaptive mesh at a quarter of a regular one's. The mesh written keeps only the
# posts its triangles use (far fewer on real terrain; at worst, --max-error-m 0 on rough ground,
# all 4,198,401). Measured, `sortie terrain mesh` of 0.1 x 0.1 degree of the Alps, textured:
# peak 1.52 GB regular at 2048 x 2048, 1.32 GB adaptive (5 m) at 2049 x 2049.
MAX_ADAPTIVE_SIDE = 2049
# The geoid stays within about -107 and +86 m of WGS84 (EGM96; NGA); a larger undulation is a mistake.
MAX_GEOID_UNDULATION_M = 200.0
# Output formats by file suffix (trimesh's exporters).
FORMATS = {".glb": "glb", ".gltf": "gltf", ".obj": "obj", ".ply": "ply", ".stl": "stl"}


@dataclass(frozen=True)
class LocalFrame:
    """An ENU frame at a point of the ellipsoid: what mesh vertices are offsets from."""

    lat_deg: float
    lon_deg: float
    h_m: float  # above the ellipsoid
    origin_ecef: np.ndarray  # (3,)
    basis: np.ndarray  # (3, 3) rows east, north, up in ECEF

    @classmethod
    def at(cls, lat_deg: float, lon_deg: float, h_m: float = 0.0) -> "LocalFrame":
        values = {"lat_deg": lat_deg, "lon_deg": lon_deg, "h_m": h_m}
        for name, v in values.items():
            if not np.isfinite(v):
                raise InvalidArgument(name, "must be finite", value=v)
        if abs(lat_deg) > 90.0:
            raise InvalidArgument("lat_deg", "must be within [-90, 90]", value=lat_deg)
        return cls(float(lat_deg), float(lon_deg), float(h_m),
                   geodetic_to_ecef(lat_deg, lon_deg, h_m).reshape(3), np.stack(enu_basis(lat_deg, lon_deg)))

    def to_local(self, points_ecef) -> np.ndarray:
        """(..., 3) ECEF metres -> (..., 3) ENU metres from the origin (float64)."""
        return (np.asarray(points_ecef, dtype=np.float64) - self.origin_ecef) @ self.basis.T

    def to_ecef(self, points_enu) -> np.ndarray:
        """(..., 3) ENU metres from the origin -> (..., 3) ECEF metres (float64)."""
        return np.asarray(points_enu, dtype=np.float64) @ self.basis + self.origin_ecef

    def as_dict(self) -> dict:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "h_m": self.h_m, "datum": "WGS84",
                "axes": "east, north, up (metres)"}


def enu_to_gltf(points_enu) -> np.ndarray:
    """ENU (x east, y north, z up) -> glTF axes (east, up, -north): right-handed, Y up."""
    p = np.asarray(points_enu, dtype=np.float64)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def gltf_to_enu(points_gltf) -> np.ndarray:
    """The inverse of :func:`enu_to_gltf`."""
    p = np.asarray(points_gltf, dtype=np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def grid_faces(valid) -> np.ndarray:
    """(m, 3) int64 triangles of a (rows, cols) vertex grid (vertex index i * cols + j), two a
    cell whose four corners are ``valid``, cut NW-SE, counter-clockwise seen from above (+up)
    when row 0 is north and column 0 west."""
    valid = np.asarray(valid, dtype=bool)
    if valid.ndim != 2:
        raise InvalidArgument("valid", f"must be a 2-D grid, got shape {valid.shape}")
    rows, cols = valid.shape
    if rows < 2 or cols < 2:
        return np.zeros((0, 3), np.int64)
    cell = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    i, j = np.nonzero(cell)
    nw = i * cols + j
    ne, sw, se = nw + 1, nw + cols, nw + cols + 1
    # East is +x and north +y: NW -> SW -> SE turns left (counter-clockwise), as does NW -> SE -> NE.
    return np.stack([np.stack([nw, sw, se], -1), np.stack([nw, se, ne], -1)], axis=1).reshape(-1, 3)


@dataclass(frozen=True)
class TerrainMesh:
    """Vertices (k, 3) ENU float64 in ``frame`` (a regular mesh: every grid point, k = rows x
    cols); ``faces`` (m, 3) int64; ``uv`` (k, 2) at the vertices' pixel centres of a (rows, cols)
    image of the grid (OpenGL's convention, v up: trimesh flips it for glTF); the grid's ``lat``
    (rows,) north to south, ``lon`` (cols,) west to east and ``heights_msl_m`` (rows, cols; NaN:
    no data)."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    heights_msl_m: np.ndarray
    frame: LocalFrame
    geoid_undulation_m: float = 0.0
    # Each vertex's grid point (row * cols + col); None: every grid point, in that order.
    grid_index: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights_msl_m.shape

    @property
    def grid_faces(self) -> np.ndarray:
        """The faces as grid points (row * cols + col)."""
        return self.faces if self.grid_index is None else self.grid_index[self.faces]

    def max_twist_m(self) -> float:
        """The largest |d| / 4 over the meshed cells: the mesh's largest vertical distance
        from the bilinear surface through its vertices (module docstring)."""
        h = self.heights_msl_m
        d = np.abs(h[:-1, :-1] - h[:-1, 1:] - h[1:, :-1] + h[1:, 1:]) / 4.0
        d = d[np.isfinite(d)]
        return float(d.max()) if d.size else 0.0


def build_mesh(heights_msl_m, lat, lon, *, frame: LocalFrame | None = None,
               geoid_undulation_m: float = 0.0, max_vertices: int = MAX_VERTICES) -> TerrainMesh:
    """The mesh of heights (rows, cols) m MSL (NaN: no data) at latitudes ``lat`` (rows,) and
    longitudes ``lon`` (cols,) degrees, (lat, lon) order. ``frame``: default an origin at the
    grid's centre on the ellipsoid. Vertices where the height is NaN are kept (every grid
    point has one, so indices stay i * cols + j) at the origin's height; no face uses them.
    At most ``max_vertices`` grid points (:func:`build_adaptive_mesh` allows MAX_ADAPTIVE_SIDE^2)."""
    h = np.asarray(heights_msl_m, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    if h.ndim != 2 or h.shape != (lat.size, lon.size):
        raise InvalidArgument("heights_msl_m", f"must have shape (len(lat), len(lon)) = ({lat.size}, {lon.size})",
                              value=list(h.shape))
    if h.size > max_vertices:
        raise InvalidArgument("heights_msl_m", f"a {h.shape[1]}x{h.shape[0]} grid = {h.size:,} vertices is over the "
                                               f"limit of {max_vertices:,}", value=h.size)
    for name, a, limit in (("lat", lat, 90.0), ("lon", lon, 540.0)):
        bad = np.flatnonzero(~(np.isfinite(a) & (np.abs(a) <= limit)))
        if bad.size:
            raise InvalidArgument(f"{name}[{bad[0]}]", f"must be finite and within +-{limit:g} degrees",
                                  value=float(a[bad[0]]))
    if not (np.isfinite(geoid_undulation_m) and abs(geoid_undulation_m) <= MAX_GEOID_UNDULATION_M):
        raise InvalidArgument("geoid_undulation_m", f"must be within +-{MAX_GEOID_UNDULATION_M:g} m",
                              value=geoid_undulation_m)
    if frame is None:
        frame = LocalFrame.at(0.5 * (lat[0] + lat[-1]), 0.5 * (lon[0] + lon[-1]), 0.0)
    valid = np.isfinite(h)
    ellipsoidal = np.where(valid, h + geoid_undulation_m, frame.h_m)
    ecef = geodetic_to_ecef(lat[:, None], lon[None, :], ellipsoidal)
    vertices = frame.to_local(ecef.reshape(-1, 3))
    rows, cols = h.shape
    u = (np.arange(cols) + 0.5) / cols
    v = 1.0 - (np.arange(rows) + 0.5) / rows
    uv = np.stack(np.broadcast_arrays(u[None, :], v[:, None]), axis=-1).reshape(-1, 2)
    return TerrainMesh(vertices, grid_faces(valid), uv, lat, lon, h, frame, float(geoid_undulation_m))


def build_adaptive_mesh(heights_msl_m, lat, lon, max_error_m: float, *, frame: LocalFrame | None = None,
                        geoid_undulation_m: float = 0.0) -> TerrainMesh:
    """The right-triangulated irregular network (terrain/rtin.py) of a (2^k + 1) x (2^k + 1) grid
    (as :func:`build_mesh` takes it): every grid post's vertex (its true position in ``frame``)
    within ``max_error_m`` of the plane of each triangle holding it, measured along the frame's
    up at the post's own east and north (exactly; Earth's curvature included), with the vertices
    its triangles use (``grid_index`` says which grid points they are)."""
    from terrain.rtin import rtin_faces

    mesh = build_mesh(heights_msl_m, lat, lon, frame=frame, geoid_undulation_m=geoid_undulation_m,
                      max_vertices=MAX_ADAPTIVE_SIDE ** 2)
    # The error in the frame the vertices are in: each post's up, which carries Earth's curvature,
    # against its triangle's plane at the post's own east and north (terrain/rtin.py).
    enu = mesh.vertices.reshape(mesh.shape + (3,))
    up = np.where(np.isfinite(mesh.heights_msl_m), enu[..., 2], np.nan)
    return with_grid_faces(mesh, rtin_faces(up, max_error_m, enu[..., :2]))


def with_grid_faces(mesh: TerrainMesh, faces: np.ndarray) -> TerrainMesh:
    """The regular ``mesh``'s grid with other triangles, ``faces`` (m, 3) of grid points (row *
    cols + col): only the vertices they use are kept (``grid_index`` says which)."""
    used, local = np.unique(faces, return_inverse=True)
    return TerrainMesh(mesh.vertices[used], local.reshape(faces.shape), mesh.uv[used], mesh.lat, mesh.lon,
                       mesh.heights_msl_m, mesh.frame, mesh.geoid_undulation_m, used)


def centre_error(mesh: TerrainMesh, terrain) -> np.ndarray:
    """|mesh - terrain| (m) at the centre of every grid cell the mesh covers, in the frame the
    vertices are in: the terrain's point at the centre's latitude and longitude (its MSL height
    plus ``geoid_undulation_m``) against the plane of the triangle holding that centre on the
    grid, along the frame's up at the point's own east and north. So a mesh whose flat triangles
    cut under the curved Earth says so (a chord of length L sags about L^2 / (8R) below the
    surface: 15 m for 28 km), as does one off the bilinear surface between its posts (a regular
    mesh: each cell's twist |d| / 4, plus its diagonal's sag, under a millimetre for 100 m cells).
    Centres where the terrain has no height are left out. ``terrain``: anything with
    ``heights(lat, lon)`` (terrain.terrain.Terrain, the terrain client)."""
    rows, cols = mesh.shape
    owner = np.full((max(rows - 1, 0), max(cols - 1, 0)), -1, np.int64)
    if owner.size and len(mesh.faces):
        _centre_faces_kernel(np.ascontiguousarray(mesh.grid_faces, np.int64), cols, owner)
    i, j = np.nonzero(owner >= 0)
    lat_c = 0.5 * (mesh.lat[:-1] + mesh.lat[1:])[i]
    lon_c = 0.5 * (mesh.lon[:-1] + mesh.lon[1:])[j]
    truth = np.asarray(terrain.heights(lat_c, lon_c).height_msl_m, dtype=np.float64)
    point = mesh.frame.to_local(geodetic_to_ecef(lat_c, lon_c, truth + mesh.geoid_undulation_m).reshape(-1, 3))
    corners = mesh.vertices[mesh.faces[owner[i, j]]]  # (n, 3 corners, 3) ENU
    err = np.abs(point[:, 2] - plane_up(corners, point[:, :2]))
    return err[np.isfinite(err)]  # a centre in a hole of the terrain has no error to measure


def plane_up(corners, east_north) -> np.ndarray:
    """(n,) float64 m: the up of the plane through each triangle's ``corners`` ((n, 3, 3) ENU m)
    at ``east_north`` ((n, 2) m, the same frame); NaN where the corners' east and north lie on a
    line."""
    c = np.asarray(corners, dtype=np.float64)
    p = np.asarray(east_north, dtype=np.float64)
    (xa, ya, za), (xb, yb, zb), (xc, yc, zc) = (np.moveaxis(c[:, k], -1, 0) for k in range(3))
    px, py = p[:, 0], p[:, 1]
    d = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
    wa = (xb - px) * (yc - py) - (yb - py) * (xc - px)
    wb = (xc - px) * (ya - py) - (yc - py) * (xa - px)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d != 0.0, (wa * za + wb * zb + (d - wa - wb) * zc) / d, np.nan)


@numba.njit(cache=True, nogil=True)
def _centre_faces_kernel(faces, cols, out):
    """out[row, col]: the face (of grid points) holding the cell centre (row + 1/2, col + 1/2)."""
    for f in range(faces.shape[0]):
        ya, xa = divmod(faces[f, 0], cols)
        yb, xb = divmod(faces[f, 1], cols)
        yc, xc = divmod(faces[f, 2], cols)
        d = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        for y in range(min(ya, yb, yc), max(ya, yb, yc)):
            py = y + 0.5
            for x in range(min(xa, xb, xc), max(xa, xb, xc)):
                px = x + 0.5
                wa = ((xb - px) * (yc - py) - (yb - py) * (xc - px)) / d
                wb = ((xc - px) * (ya - py) - (yc - py) * (xa - px)) / d
                wc = 1.0 - wa - wb
                if wa >= -1e-12 and wb >= -1e-12 and wc >= -1e-12:
                    out[y, x] = f


def mesh_geodetic(mesh: TerrainMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat, lon, h_msl) of every vertex back from its ENU position (the round trip tests use)."""
    lat, lon, h = ecef_to_geodetic(mesh.frame.to_ecef(mesh.vertices))
    return lat, lon, h - mesh.geoid_undulation_m


def output_format(path) -> str:
    """trimesh's file type for an output path, by suffix; InvalidArgument naming it otherwise."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InvalidArgument("output", f"must end in one of {', '.join(FORMATS)}", value=str(path))
    return FORMATS[suffix]


def to_trimesh(mesh: TerrainMesh, image=None, *, gltf_axes: bool = False):
    """A trimesh.Trimesh of the mesh (unprocessed: vertex order kept), textured with ``image``
    ((rows, cols, 3) uint8 on the mesh's grid, or None), in glTF axes or ENU."""
    import trimesh
    from PIL import Image

    vertices = enu_to_gltf(mesh.vertices) if gltf_axes else mesh.vertices
    visual = None
    if image is not None:
        img = np.asarray(image)
        if img.shape[:2] != mesh.shape:
            raise InvalidArgument("image", f"must be on the mesh's grid {mesh.shape}", value=list(img.shape))
        visual = trimesh.visual.TextureVisuals(uv=mesh.uv, image=Image.fromarray(np.ascontiguousarray(img)))
    return trimesh.Trimesh(vertices=vertices, faces=mesh.faces, visual=visual, process=False, validate=False)


def vertex_colours(image) -> np.ndarray:
    """(rows x cols, 4) uint8 RGBA of an image on the mesh's grid: one pixel a vertex."""
    img = np.asarray(image, dtype=np.uint8).reshape(-1, 3)
    return np.concatenate([img, np.full((img.shape[0], 1), 255, np.uint8)], axis=1)


def write_mesh(mesh: TerrainMesh, path, image=None, *, name: str = "terrain", extras: dict | None = None) -> Path:
    """Write the mesh to ``path`` (its suffix picks the format, :data:`FORMATS`): glTF with
    ``image`` as its base colour texture, PLY with it as vertex colours, OBJ with a
    material beside it, STL as geometry alone. ``extras`` (JSON-able) go into glTF's scene
    extras with the frame. Returns the path."""
    import trimesh

    kind = output_format(path)
    out = Path(path)
    if len(mesh.faces) == 0:
        raise InvalidArgument("mesh", "has no triangles: no terrain data under any of its cells")
    if kind in ("glb", "gltf"):
        scene = trimesh.Scene()
        scene.add_geometry(to_trimesh(mesh, image, gltf_axes=True), node_name=name, geom_name=name)
        scene.metadata.update(scene_extras(mesh.frame, extras))
        write_scene(scene, out)
        return out
    tm = to_trimesh(mesh, image if kind == "obj" else None)
    if kind == "ply" and image is not None:
        colours = vertex_colours(image)
        tm.visual = trimesh.visual.ColorVisuals(
            tm, vertex_colors=colours if mesh.grid_index is None else colours[mesh.grid_index])
    if kind == "obj":  # its material and texture beside it, named after it: NAME.mtl, NAME.png
        if image is not None:
            tm.visual.material.name = out.stem
        data = tm.export(file_type="obj", mtl_name=f"{out.stem}.mtl", return_texture=True)
        text, files = data if isinstance(data, tuple) else (data, {})
        for side, content in files.items():
            write_atomically(out.parent / side, content)
        write_atomically(out, text.encode() if isinstance(text, str) else text)
        return out
    write_atomically(out, tm.export(file_type=kind))
    return out


def write_atomically(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through ``path.part`` and a rename, so that a reader never
    sees half a file; the folder is made if missing (InvalidArgument naming the output where
    it cannot be)."""
    path = Path(path)
    part = path.with_name(path.name + ".part")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        part.write_bytes(data)
        part.replace(path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            part.unlink(missing_ok=True)
        raise InvalidArgument("output", f"cannot be written: {exc.strerror or exc}", value=str(path)) from None


def scene_extras(frame: LocalFrame, extras: dict | None = None) -> dict:
    """What a glTF scene says about itself: its frame (origin, axes) and the caller's extras."""
    out = {"sortie": {"frame": {**frame.as_dict(), "gltf_axes": "x east, y up, z south (-north)"}}}
    if extras:
        out["sortie"].update(extras)
    return out


def write_scene(scene, path) -> None:
    """Write a trimesh.Scene as .glb (one binary file) or .gltf (JSON with the buffer embedded)."""
    path = Path(path)
    kind = output_format(path)
    if kind not in ("glb", "gltf"):
        raise InvalidArgument("output", "a scene is written as .glb or .gltf", value=str(path))
    gltf, binary = read_glb(scene.export(file_type="glb"))
    write_atomically(path, glb_bytes(gltf, binary) if kind == "glb" else gltf_bytes(gltf, binary))


# -- glTF containers ------------------------------------------------------------------------------
# trimesh writes a scene as GLB; these read it back and write it as GLB or .gltf, and let a caller
# add accessors (the debrief scene's animated markers: server/gltf.py).

# glTF component types and buffer view targets (glTF 2.0 specification, "Accessors", "Buffer Views").
FLOAT, UNSIGNED_SHORT = 5126, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


def read_glb(data: bytes) -> tuple[dict, bytearray]:
    """(the JSON, the binary chunk) of a GLB container (glTF 2.0 specification, "Binary glTF
    Layout": a 12-byte header, a JSON chunk, an optional BIN chunk, each 4-byte aligned)."""
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or length != len(data):
        raise DataFormatError("not a GLB 2.0 container (glTF 2.0 binary)")
    n, kind = struct.unpack_from("<II", data, 12)
    gltf = json.loads(data[20:20 + n])
    binary = bytearray()
    at = 20 + n
    if at + 8 <= len(data):
        m, kind = struct.unpack_from("<II", data, at)
        if kind == GLB_BIN:
            binary = bytearray(data[at + 8:at + 8 + m])
    return gltf, binary


def _padded(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def glb_bytes(gltf: dict, binary: bytes) -> bytes:
    """A GLB container of the JSON and the binary chunk."""
    gltf.pop("buffers", None)
    if binary:  # an empty buffer is not valid glTF
        gltf["buffers"] = [{"byteLength": len(binary)}]
    text = _padded(json.dumps(gltf, separators=(",", ":"), allow_nan=False).encode(), b" ")
    chunks = struct.pack("<II", len(text), GLB_JSON) + text
    if binary:
        data = _padded(bytes(binary), b"\0")
        chunks += struct.pack("<II", len(data), GLB_BIN) + data
    return struct.pack("<III", GLB_MAGIC, 2, 12 + len(chunks)) + chunks


def gltf_bytes(gltf: dict, binary: bytes) -> bytes:
    """A .gltf file: the JSON with the binary chunk as a base64 data URI."""
    gltf.pop("buffers", None)
    if binary:  # an empty buffer is not valid glTF
        gltf["buffers"] = [{"byteLength": len(binary), "uri": "data:application/octet-stream;base64,"
                            + base64.b64encode(bytes(binary)).decode()}]
    return json.dumps(gltf, separators=(",", ":"), allow_nan=False).encode()


def append_accessor(gltf: dict, binary: bytearray, values: np.ndarray, kind: str, component: int = FLOAT,
              target: int | None = None, bounds: bool = False) -> int:
    """Append ``values`` (little-endian, 4-byte aligned) to the binary chunk as a buffer view
    and an accessor of glTF type ``kind``; its index. ``bounds``: with min and max (required
    for positions and animation inputs)."""
    binary.extend(b"\0" * (-len(binary) % 4))
    data = np.ascontiguousarray(values).astype(values.dtype.newbyteorder("<"), copy=False)
    view = {"buffer": 0, "byteOffset": len(binary), "byteLength": data.nbytes}
    if target is not None:
        view["target"] = target
    binary.extend(data.tobytes())
    gltf.setdefault("bufferViews", []).append(view)
    accessor = {"bufferView": len(gltf["bufferViews"]) - 1, "componentType": component,
                "count": int(data.shape[0]), "type": kind}
    if bounds:
        flat = data.reshape(data.shape[0], -1)
        accessor["min"] = flat.min(axis=0).tolist()
        accessor["max"] = flat.max(axis=0).tolist()
    gltf.setdefault("accessors", []).append(accessor)
    return len(gltf["accessors"]) - 1


