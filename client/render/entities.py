"""Entities as simple procedural meshes at their (dead-reckoned) poses.

Meshes are built in the body frame (x forward, y right, z down; metres) and
drawn instanced, one draw call per kind, each instance placed by its ECEF
position and ECEF -> body orientation, converted to the local origin's frame
in float64 and handed to the GPU as float32 (the model matrix's translation
is the entity's offset from the local origin).

Sizes are true to scale up close and magnified far away: an entity is drawn
at scale max(1, MIN_ENTITY_PIXELS x pixel angle x distance / its length), so
it is never shorter than MIN_ENTITY_PIXELS (24) pixels on screen - a 15 m
aircraft at 5 km in a 960-pixel, 60 degree view (1.1 mrad a pixel) is drawn
8.8 times its size, about 130 m. Ground vehicles and statics stand on their
reference point (``fdm.ground``: on the terrain), so they grow upwards.

Lifted onto the drawn ground (:func:`ground_lifts`): ``fdm.ground`` puts a vehicle on the
terrain's bilinear surface, but the terrain layer draws each cell as two flat triangles, which
stand above that surface by up to a quarter of the cell's twist (terrain_mesh.cell_corner_weights;
more than 2.7 m in 4.4 % of the Alps tile's cells), and a coarser clipmap level or a decimated
block draws the ground elsewhere again. Each frame a ground vehicle or static whose reference
point lies under the surface drawn there is raised along its local vertical onto it; an
aircraft is raised until its lowest point, at its drawn scale and attitude, is on it (a marker
magnified about its reference point would otherwise sink its lower half into the ground). Never
lowered: only the drawing moves, not the entity.

Colours: blue, red and neutral (yellow) coalitions, lit by the same sun and
ambient as the terrain, and fogged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client.render.camera import LocalOrigin, quat_to_matrix
from client.render.gl import check_gl_error
from client.render.shading import GLSL_COMMON, Frame, rgb
from sortie.errors import InvalidArgument
from terrain.geodesy import ecef_to_geodetic, enu_basis

KIND_AIRCRAFT, KIND_GROUND, KIND_STATIC = 1, 2, 3  # sortie.v1.EntityKind numbers
KIND_NAMES = {KIND_AIRCRAFT: "aircraft", KIND_GROUND: "ground", KIND_STATIC: "static"}
COALITION_RGB = {"blue": (40, 100, 235), "red": (225, 40, 35), "neutral": (235, 200, 40)}
MIN_ENTITY_PIXELS = 24.0
ENTITY_AMBIENT_BOOST = 0.15  # entities stay readable on their shadowed side


# -- procedural meshes, body frame ---------------------------------------------------------------

def _box(x0, x1, y0, y1, z0, z1) -> np.ndarray:
    """(12, 3, 3) triangles of an axis-aligned box, body metres."""
    c = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[c[q[0]], c[q[1]], c[q[2]]] for q in quads] + [[c[q[0]], c[q[2]], c[q[3]]] for q in quads])


def _pyramid(base_x, base_y, z_base, z_apex, x_apex=0.0) -> np.ndarray:
    """(6, 3, 3) triangles: a rectangular pyramid (base at z_base, apex at z_apex), body metres."""
    hx, hy = 0.5 * base_x, 0.5 * base_y
    b = np.array([[-hx, -hy, z_base], [hx, -hy, z_base], [hx, hy, z_base], [-hx, hy, z_base]])
    apex = np.array([x_apex, 0.0, z_apex])
    sides = [[b[k], b[(k + 1) % 4], apex] for k in range(4)]
    return np.array(sides + [[b[0], b[1], b[2]], [b[0], b[2], b[3]]])


def _nose(x0, x1, half_width, half_height) -> np.ndarray:
    """(4, 3, 3) triangles: a four-sided cone from a rectangle at x0 to a point at x1."""
    r = np.array([[x0, -half_width, -half_height], [x0, half_width, -half_height],
                  [x0, half_width, half_height], [x0, -half_width, half_height]])
    tip = np.array([x1, 0.0, 0.0])
    return np.array([[r[k], r[(k + 1) % 4], tip] for k in range(4)])


def _flat_shaded(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3, 3) triangles -> (3m, 3) vertices and (3m, 3) face normals (by winding)."""
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return triangles.reshape(-1, 3), np.repeat(normals, 3, axis=0)


def _outward(parts) -> np.ndarray:
    """Concatenate convex parts ((k, 3, 3) each), every triangle wound so its normal points out."""
    out = []
    for tris in parts:
        centre = tris.reshape(-1, 3).mean(axis=0)
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        inward = np.einsum("ij,ij->i", n, tris.mean(axis=1) - centre) < 0
        tris = tris.copy()
        tris[inward] = tris[inward][:, ::-1]
        out.append(tris)
    return np.concatenate(out)


def aircraft_mesh() -> np.ndarray:
    """(m, 3, 3) a 15 m fighter-like shape about its reference point (fuselage, wings, tail)."""
    return _outward([_box(-7.0, 4.0, -0.8, 0.8, -0.8, 0.8), _nose(4.0, 8.0, 0.8, 0.8),
                     _box(-2.5, 1.5, -5.0, 5.0, -0.1, 0.15), _box(-7.0, -5.0, -2.8, 2.8, -0.1, 0.1),
                     _box(-7.0, -4.5, -0.1, 0.1, -3.5, -0.8)])


def ground_vehicle_mesh() -> np.ndarray:
    """(m, 3, 3) a tank-like shape, 9 m with its gun, standing on its reference point."""
    return _outward([_box(-3.5, 3.5, -1.7, 1.7, -1.8, 0.0), _box(-1.5, 1.2, -1.2, 1.2, -2.7, -1.8),
                     _box(1.2, 5.5, -0.12, 0.12, -2.4, -2.15)])


def static_mesh() -> np.ndarray:
    """(m, 3, 3) a 10 m site marker standing on its reference point (a block under a pyramid)."""
    return _outward([_box(-5.0, 5.0, -5.0, 5.0, -3.0, 0.0), _pyramid(10.0, 10.0, -3.0, -9.0)])


MESHES = {KIND_AIRCRAFT: aircraft_mesh, KIND_GROUND: ground_vehicle_mesh, KIND_STATIC: static_mesh}


def mesh_vertices(triangles: np.ndarray) -> np.ndarray:
    """(k, 3) float64 the distinct vertices of a (m, 3, 3) mesh, body metres."""
    return np.unique(triangles.reshape(-1, 3), axis=0)


def mesh_length_m(triangles: np.ndarray) -> float:
    """Largest extent of a (m, 3, 3) mesh along its body axes, metres."""
    p = triangles.reshape(-1, 3)
    return float((p.max(axis=0) - p.min(axis=0)).max())


# -- the entities of a frame ---------------------------------------------------------------------

@dataclass(frozen=True)
class EntitySet:
    """Entities to draw.

    ids: (n,) int64; kinds: (n,) int (1 aircraft, 2 ground, 3 static: sortie.v1.EntityKind);
    positions_ecef: (n, 3) float64 metres ECEF; quats_wxyz: (n, 4) float64 ECEF -> body;
    coalitions: (n,) str ("blue", "red", "neutral"; others draw as neutral).
    """

    ids: np.ndarray
    kinds: np.ndarray
    positions_ecef: np.ndarray
    quats_wxyz: np.ndarray
    coalitions: tuple

    def __post_init__(self):
        n = len(self.ids)
        shapes = {"kinds": (np.shape(self.kinds), (n,)), "positions_ecef": (np.shape(self.positions_ecef), (n, 3)),
                  "quats_wxyz": (np.shape(self.quats_wxyz), (n, 4)), "coalitions": ((len(self.coalitions),), (n,))}
        for name, (got, want) in shapes.items():
            if got != want:
                raise InvalidArgument(name, f"must have shape {want} for {n} ids, got {got}")
        if not np.all(np.isfinite(self.positions_ecef)):
            raise InvalidArgument("positions_ecef", "must be finite")

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls) -> EntitySet:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)), ())

    @classmethod
    def from_picture(cls, picture, t: float | None = None, exclude=()) -> EntitySet:
        """The entities of a ``client.sim_client.Picture`` dead-reckoned to world time t (default
        now), without the ids in ``exclude``."""
        ids, pos, quat = picture.state(t)
        keep = ~np.isin(ids, np.asarray(list(exclude), np.int64))
        ids, pos, quat = ids[keep], pos[keep], quat[keep]
        infos = [picture.infos.get(int(i)) for i in ids]
        kinds = np.array([info.kind if info is not None else KIND_STATIC for info in infos], np.int64)
        coalitions = tuple(info.coalition if info is not None else "neutral" for info in infos)
        return cls(np.asarray(ids, np.int64), kinds, np.asarray(pos, np.float64), np.asarray(quat, np.float64),
                   coalitions)


# -- the GL layer --------------------------------------------------------------------------------

ENTITY_VERTEX_SHADER = "#version 330 core\n" + GLSL_COMMON + """
in vec3 in_position;  // body metres
in vec3 in_normal;    // body
in vec3 in_axis_x;    // per instance: body x, y, z axes in local ENU, times the scale
in vec3 in_axis_y;
in vec3 in_axis_z;
in vec3 in_offset;    // per instance: local ENU metres
in vec3 in_colour;
out vec3 v_world;
out vec3 v_normal;
out vec3 v_colour;
void main() {
    mat3 m = mat3(in_axis_x, in_axis_y, in_axis_z);
    v_world = m * in_position + in_offset;
    v_normal = m * in_normal;  // uniform scale: the direction is right, normalised below
    v_colour = in_colour;
    gl_Position = u_projection * (u_view * vec4(v_world, 1.0));
}
"""

ENTITY_FRAGMENT_SHADER = "#version 330 core\n" + GLSL_COMMON + f"""
in vec3 v_world;
in vec3 v_normal;
in vec3 v_colour;
out vec4 out_colour;
void main() {{
    vec3 c = lambert(v_colour, normalize(v_normal)) + {ENTITY_AMBIENT_BOOST} * v_colour;
    out_colour = vec4(fogged(c, v_world), 1.0);
}}
"""


def instance_records(origin: LocalOrigin, entities: EntitySet, scales: np.ndarray) -> np.ndarray:
    """(n, 15) float32 per-instance records: scaled body axes (3 x 3) and offset in local ENU,
    colour - the GPU boundary. scales: (n,) float64."""
    r_local_body = origin.basis @ quat_to_matrix(entities.quats_wxyz)  # (n, 3, 3), columns body axes
    out = np.empty((len(entities), 15), dtype="f4")
    out[:, 0:9] = (np.swapaxes(r_local_body, 1, 2) * scales[:, None, None]).reshape(-1, 9)
    out[:, 9:12] = origin.to_local(entities.positions_ecef)
    out[:, 12:15] = [rgb(COALITION_RGB.get(c, COALITION_RGB["neutral"])) for c in entities.coalitions]
    return out


def apparent_scales(entities: EntitySet, lengths_m: np.ndarray, camera_ecef, pixel_angle_rad: float) -> np.ndarray:
    """(n,) scale factors: max(1, MIN_ENTITY_PIXELS x pixel angle x distance / length)."""
    dist = np.linalg.norm(entities.positions_ecef - np.asarray(camera_ecef, np.float64), axis=-1)
    return np.maximum(1.0, MIN_ENTITY_PIXELS * pixel_angle_rad * dist / lengths_m)


def depth_below_reference_m(vertices_body: np.ndarray, quats_wxyz: np.ndarray, up_ecef: np.ndarray) -> np.ndarray:
    """(n,) float64 metres: how far a mesh's lowest vertex lies below its reference point along
    the local vertical, at true scale (0 where none is below). vertices_body: (k, 3) float64 body
    metres; quats_wxyz: (n, 4) ECEF -> body; up_ecef: (n, 3) unit local verticals, ECEF."""
    up_body = np.einsum("nij,ni->nj", quat_to_matrix(quats_wxyz), up_ecef)  # R^T up: the vertical in body axes
    return np.maximum(0.0, (-(vertices_body @ up_body.T)).max(axis=0))


def ground_lifts(kinds: np.ndarray, heights_m: np.ndarray, depths_m: np.ndarray, scales: np.ndarray,
                 ground_m: np.ndarray) -> np.ndarray:
    """(n,) float64 metres to raise each entity along its local vertical so that it is not drawn
    under the ground: a ground vehicle or static (it stands on its reference point and grows
    upwards) until its reference point is on the drawn ground; an aircraft (magnified about its
    reference point) until its lowest point, scales x depths_m below it, is. 0 where it stands
    higher or where no ground is drawn (NaN). kinds: (n,) int EntityKind; heights_m: (n,)
    ellipsoid heights of the reference points; depths_m: (n,) :func:`depth_below_reference_m`;
    scales: (n,) drawn scales; ground_m: (n,) ellipsoid height of the surface drawn under each."""
    lowest = heights_m - np.where(kinds == KIND_AIRCRAFT, scales * depths_m, 0.0)
    lift = ground_m - lowest
    return np.where(lift > 0.0, lift, 0.0)  # (NaN: no ground drawn there -> 0)


class EntityLayer:
    """Draws an EntitySet: one instanced draw call per kind. ``lifts_m``: (n,) float64, how far
    each entity of the last draw was raised onto the drawn ground (:func:`ground_lifts`)."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=ENTITY_VERTEX_SHADER, fragment_shader=ENTITY_FRAGMENT_SHADER)
        self._meshes = {}
        self._aircraft_vertices = mesh_vertices(aircraft_mesh())  # its lowest point: ground_lifts
        for kind, make in MESHES.items():
            tris = make()
            vertices, normals = _flat_shaded(tris)
            data = np.hstack([vertices, normals]).astype("f4")
            self._meshes[kind] = (self.ctx.buffer(data.tobytes()), len(vertices), mesh_length_m(tris))
        self.lifts_m = np.zeros(0)
        self.triangles = 0
        self.vertices = 0
        self.drawn = 0

    def draw(self, frame: Frame, entities: EntitySet, ground=None) -> None:
        """Draw every entity in front of the near plane. ground(lats, lons) -> (n,) float64: the
        ellipsoid height (metres) of the terrain surface drawn at (n,) degrees (NaN where none),
        onto which entities are lifted (:func:`ground_lifts`); None: none is drawn."""
        self.triangles = self.vertices = self.drawn = 0
        self.lifts_m = np.zeros(len(entities))
        if len(entities) == 0:
            return
        frame.write_common(self.program)
        pixel = frame.camera.pixel_footprint_rad(frame.width)
        kinds = np.where(np.isin(entities.kinds, list(MESHES)), entities.kinds, KIND_STATIC)  # unknown: static
        lengths = np.zeros(len(entities))
        for kind, (_, _, length) in self._meshes.items():
            lengths[kinds == kind] = length
        scales = apparent_scales(entities, lengths, frame.camera.position_ecef, pixel)
        positions = entities.positions_ecef
        if ground is not None:
            lat, lon, h = ecef_to_geodetic(positions)
            up = enu_basis(lat, lon)[2]
            depths = np.zeros(len(entities))
            air = np.flatnonzero(kinds == KIND_AIRCRAFT)
            if air.size:
                depths[air] = depth_below_reference_m(self._aircraft_vertices, entities.quats_wxyz[air], up[air])
            self.lifts_m = ground_lifts(kinds, h, depths, scales, np.asarray(ground(lat, lon), np.float64))
            positions = positions + self.lifts_m[:, None] * up
        for kind, (vbo, n_vertices, _) in self._meshes.items():
            sel = np.flatnonzero(kinds == kind)
            if sel.size == 0:
                continue
            subset = EntitySet(entities.ids[sel], entities.kinds[sel], positions[sel],
                               entities.quats_wxyz[sel], tuple(entities.coalitions[k] for k in sel))
            instances = self.ctx.buffer(instance_records(frame.origin, subset, scales[sel]).tobytes())
            vao = self.ctx.vertex_array(self.program, [
                (vbo, "3f 3f", "in_position", "in_normal"),
                (instances, "3f 3f 3f 3f 3f/i", "in_axis_x", "in_axis_y", "in_axis_z", "in_offset", "in_colour")])
            vao.render(instances=sel.size)
            vao.release()
            instances.release()
            self.triangles += sel.size * n_vertices // 3
            self.vertices += sel.size * n_vertices
            self.drawn += sel.size
        check_gl_error(self.ctx, "entities")

    def release(self) -> None:
        for vbo, _, _ in self._meshes.values():
            vbo.release()
        self.program.release()


def kind_from_name(name: str) -> int:
    """"aircraft" | "ground" | "static" -> the EntityKind number."""
    for k, v in KIND_NAMES.items():
        if v == name:
            return k
    raise InvalidArgument("kind", f"must be one of {', '.join(KIND_NAMES.values())}", value=name)

