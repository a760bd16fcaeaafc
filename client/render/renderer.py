"""The reference renderer: terrain, sea, entities and sky into a numpy image, headless.

    with Renderer(terrain, 960, 540) as r:
        image = r.render(Camera.from_geodetic(47.25, 9.34, 3500.0, 90.0, -10.0), entities)
        r.stats.frame_ms, r.stats.triangles

A frame, in draw order (reversed-Z float depth, client/render/gl.py):

1. **terrain layer** (``TerrainLayer``: ``update(camera)``, ``draw(frame)``,
   ``fog_range_m``, ``triangles``, ``vertices``, ``release()``; ``surface_height_msl``,
   ``ground_height_msl`` and ``fog_range_for(camera, width, height)`` (its reach within a
   view, for a layer not centred on the camera) where it has them: the eye is kept over the first,
   :meth:`Renderer.above_drawn_ground`, the near plane clear of the second): by default the
   full-resolution mesh of client/render/terrain_mesh.py; issue #5's geometry
   clipmap plugs in through ``terrain_layer_factory``;
2. **sea shell**: sea level (MSL 0 = ellipsoid height N, SEA_SHELL_BELOW_M
   lower so terrain at 0 m wins the depth test) as a polar grid around the
   camera's nadir out past its horizon (sea beyond the geometric horizon is
   hidden by the sea itself), 16k vertices, rebuilt when the camera has
   moved 5 % of its reach or climbed past it. Where the terrain layer
   surely covers the ground (``solid_bounds``) the shell is left out: hidden
   there anyway, it would cost llvmpipe a third of the frame in rejected
   fragments.
   It is the water wherever the terrain has no data or ends, and the horizon
   line; terrain at or below the water level (0 m MSL; half the step over a lossy
   terrain store, client/render/shading.py) is itself shaded as water;
3. **entities** (client/render/entities.py), instanced, each lifted onto the terrain surface
   drawn under it where it would stand below it (:meth:`Renderer.drawn_ground_m`);
4. **sky**: one full-screen triangle at depth 0 (infinitely far) that only
   fills the pixels nothing else covered (depth test >=, early-rejected
   elsewhere): the gradient of client/render/shading.py.

Shading, fog and sky formulas: client/render/shading.py. Every GL call runs
with the renderer's context current, and a GL error after a frame raises
``GLError``. Stats of the last frame: :class:`FrameStats`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from client.render.camera import REBASE_DISTANCE_M, Camera, LocalOrigin, near_plane_m
from client.render.entities import EntityLayer, EntitySet
from client.render.gl import check_gl_error, create_context, enable_reversed_z, float_depth_texture
from client.render.shading import (DEFAULT_SUN_AZIMUTH_DEG, DEFAULT_SUN_ELEVATION_DEG, SKY_EXPONENT, SKY_HORIZON_RGB,
                                   SKY_ZENITH_RGB, SUN_RGB, EphemerisSun, Frame, fog_density_per_m, instant_s, rgb,
                                   sun_direction_local, sun_in_sky_deg, water_level_m)
from client.render.terrain_mesh import (DEFAULT_HORIZON_M, DEFAULT_HORIZON_STRIDE, DEFAULT_WINDOW_M,
                                        TERRAIN_FRAGMENT_SHADER, TERRAIN_VERTEX_SHADER, TerrainMeshLayer, interleave)
from sortie.errors import InvalidArgument
from terrain.geodesy import WGS84_A_M, ecef_to_geodetic, enu_basis, geodetic_to_ecef

MAX_IMAGE_SIDE = 8192
SEA_SHELL_BELOW_M = 1.0
SEA_SHELL_RINGS = 128  # radii from SEA_SHELL_MIN_M out, geometric
SEA_SHELL_AZIMUTHS = 128
SEA_SHELL_MIN_M = 20.0
SEA_SHELL_MIN_REACH_M = 1000.0
SEA_SHELL_REBUILD_FRACTION = 0.05
HORIZON_MARGIN = 1.5  # the shell is built out to this many times the geometric horizon distance
# The least height of the eye over the terrain surface drawn under it (Renderer.render lifts it
# there): docs/RENDERING.md's "no see-through from 5 cm up", now of the drawn triangles.
EYE_CLEARANCE_M = 0.05


class TerrainLayer(Protocol):
    """What the renderer needs of a terrain layer (the mesh now, a clipmap later)."""

    fog_range_m: float  # least distance from the camera to where the terrain ends
    solid_bounds: tuple | None  # (lat_min, lat_max, lon_min, lon_max) it surely covers (the sea skips it)
    triangles: int
    vertices: int

    def update(self, camera: Camera) -> None: ...

    def draw(self, frame: Frame) -> None: ...

    def release(self) -> None: ...


@dataclass
class FrameStats:
    """frame_ms: wall time of render() (update, draw, read back); update_ms: the layers'
    updates (mesh rebuilds, uploads) within it; triangles and vertices submitted; entities_drawn; rebased:
    the local origin moved this frame; mesh_rebuilds: the terrain layer's rebuilds so far (a clipmap's:
    its polar mesh's); terrain_samples: terrain samples the layer took this frame (a clipmap's updates,
    the posts of a mesh installed this frame); levels_active:
    the clipmap levels drawn (0 for the mesh); eye_lift_m: how far the eye was raised to stand
    EYE_CLEARANCE_M over the terrain surface drawn under it (0 where it stood higher);
    sun_azimuth_deg, sun_elevation_deg: the sun the frame was lit by, in the camera's sky
    (at or below 0 degrees: ambient light only)."""

    frame_ms: float = 0.0
    update_ms: float = 0.0
    triangles: int = 0
    vertices: int = 0
    entities_drawn: int = 0
    rebased: bool = False
    mesh_rebuilds: int = 0
    terrain_samples: int = 0
    levels_active: int = 0
    eye_lift_m: float = 0.0
    sun_azimuth_deg: float = 0.0
    sun_elevation_deg: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


# -- sea shell -----------------------------------------------------------------------------------

def sea_shell(nadir_lat: float, nadir_lon: float, radius_m: float, geoid_undulation_m: float,
              solid_bounds: tuple | None = None, rings: int = SEA_SHELL_RINGS, azimuths: int = SEA_SHELL_AZIMUTHS):
    """A polar grid on the sea surface around (lat, lon) out to radius_m.

    Returns (positions (n, 3) float64 ECEF, up (n, 3) unit ECEF, triangles (m, 3) uint32,
    counter-clockwise from above). Radii are geometric from SEA_SHELL_MIN_M; points are laid
    out in the nadir's tangent plane and dropped onto the ellipsoid at MSL - SEA_SHELL_BELOW_M.
    Triangles whose three corners lie inside solid_bounds (lat_min, lat_max, lon_min, lon_max:
    where the terrain covers the ground) are left out.
    """
    radii = np.concatenate([[0.0], np.geomspace(SEA_SHELL_MIN_M, max(radius_m, 2 * SEA_SHELL_MIN_M), rings)])
    theta = np.linspace(0.0, 2.0 * np.pi, azimuths, endpoint=False)
    e, n, u = enu_basis(nadir_lat, nadir_lon)
    centre = geodetic_to_ecef(nadir_lat, nadir_lon, 0.0)
    plane = centre + radii[:, None, None] * (np.cos(theta)[None, :, None] * e + np.sin(theta)[None, :, None] * n)
    lat, lon, _ = ecef_to_geodetic(plane)
    pos = geodetic_to_ecef(lat, lon, geoid_undulation_m - SEA_SHELL_BELOW_M).reshape(-1, 3)
    up = enu_basis(lat, lon)[2].reshape(-1, 3)
    r, a = np.meshgrid(np.arange(rings), np.arange(azimuths), indexing="ij")
    a1 = (a + 1) % azimuths
    p00, p10 = r * azimuths + a, (r + 1) * azimuths + a
    p11, p01 = (r + 1) * azimuths + a1, r * azimuths + a1
    tris = np.concatenate([np.stack([p00, p10, p11], -1).reshape(-1, 3), np.stack([p00, p11, p01], -1).reshape(-1, 3)])
    if solid_bounds is not None:
        lat_min, lat_max, lon_min, lon_max = solid_bounds
        dlon = (lon.ravel() - lon_min + 180.0) % 360.0 - 180.0
        inside = ((lat.ravel() > lat_min) & (lat.ravel() < lat_max) & (dlon > 0) & (dlon < lon_max - lon_min))
        tris = tris[~inside[tris].all(axis=1)]
    return pos, up, tris.astype(np.uint32)


def horizon_distance_m(height_m: float) -> float:
    """Distance to the geometric horizon from height_m above a sphere of radius a (m)."""
    h = max(height_m, 0.0)
    return math.sqrt(2.0 * WGS84_A_M * h + h * h)


class SeaShellLayer:
    """The sea shell as a layer: rebuilt when the camera's nadir has moved more than
    SEA_SHELL_REBUILD_FRACTION of the shell's reach, its horizon has outgrown it, or the
    terrain's solid bounds changed; re-uploaded after a rebase of the local origin."""

    def __init__(self, ctx, origin: LocalOrigin, geoid_undulation_m: float):
        self.ctx = ctx
        self.origin = origin
        self.geoid_undulation_m = geoid_undulation_m
        self.program = ctx.program(vertex_shader=TERRAIN_VERTEX_SHADER, fragment_shader=TERRAIN_FRAGMENT_SHADER)
        self._centre_ecef = None
        self._reach_m = 0.0
        self._solid_bounds = None
        self._mesh = None
        self._generation = None
        self._objects = ()
        self.triangles = self.vertices = 0

    def update(self, camera: Camera, solid_bounds: tuple | None = None) -> None:
        """solid_bounds: where the terrain layer covers the ground (the shell leaves it out)."""
        lat, lon, h = camera.geodetic()
        reach = max(horizon_distance_m(h - self.geoid_undulation_m), SEA_SHELL_MIN_REACH_M)
        nadir = geodetic_to_ecef(lat, lon, 0.0)
        if (self._mesh is None or reach > self._reach_m or solid_bounds != self._solid_bounds
                or np.linalg.norm(nadir - self._centre_ecef) > SEA_SHELL_REBUILD_FRACTION * self._reach_m):
            self._reach_m = reach * HORIZON_MARGIN
            self._centre_ecef = nadir
            self._solid_bounds = solid_bounds
            self._mesh = sea_shell(lat, lon, self._reach_m, self.geoid_undulation_m, solid_bounds)
            self._generation = None
        if self._generation != self.origin.generation:
            self._upload()

    def _upload(self) -> None:
        pos, up, tris = self._mesh
        self._release_buffers()
        self._generation = self.origin.generation
        self.triangles = self.vertices = 0
        if len(tris) == 0:  # the terrain covers all the shell would: nothing to draw
            return
        data = interleave(self.origin, pos, up, np.full(len(pos), -SEA_SHELL_BELOW_M), np.ones(len(pos)))
        vbo, ibo = self.ctx.buffer(data.tobytes()), self.ctx.buffer(tris.tobytes())
        vao = self.ctx.vertex_array(self.program, [(vbo, "3f 3f 1f 1f", "in_position", "in_normal", "in_height",
                                                    "in_cos_slope")], index_buffer=ibo, index_element_size=4)
        self._objects = (vao, vbo, ibo)
        self._generation = self.origin.generation
        self.triangles, self.vertices = len(tris), len(pos)

    def draw(self, frame: Frame) -> None:
        import moderngl

        if not self._objects:
            return
        frame.write_common(self.program)
        self.ctx.enable(moderngl.CULL_FACE)
        self._objects[0].render(moderngl.TRIANGLES)
        self.ctx.disable(moderngl.CULL_FACE)

    def _release_buffers(self) -> None:
        for obj in self._objects:
            obj.release()
        self._objects = ()

    def release(self) -> None:
        self._release_buffers()
        self.program.release()


# -- sky -----------------------------------------------------------------------------------------

SKY_VERTEX_SHADER = """#version 330 core
void main() {  // one triangle covering the screen, at depth 0 (infinitely far, reversed-Z)
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
"""

SKY_FRAGMENT_SHADER = f"""#version 330 core
uniform vec2 u_size;       // pixels
uniform mat3 u_ray_basis;  // columns: right / fx, up / fy, forward, local ENU
uniform vec3 u_up;         // the camera's vertical, local ENU
uniform vec3 u_sun;
uniform float u_sun_light;  // 0: the sun is down, no disc
uniform int u_flat;
uniform vec3 u_flat_rgb;
out vec4 out_colour;
const vec3 ZENITH = vec3{rgb(SKY_ZENITH_RGB)};
const vec3 HORIZON = vec3{rgb(SKY_HORIZON_RGB)};
const vec3 SUN = vec3{rgb(SUN_RGB)};
void main() {{
    if (u_flat != 0) {{ out_colour = vec4(u_flat_rgb, 1.0); return; }}
    vec2 ndc = gl_FragCoord.xy / u_size * 2.0 - 1.0;
    vec3 ray = normalize(u_ray_basis * vec3(ndc, 1.0));
    float t = pow(clamp(dot(ray, u_up), 0.0, 1.0), {SKY_EXPONENT});
    float s = max(dot(ray, u_sun), 0.0);
    vec3 c = mix(HORIZON, ZENITH, t) + SUN * u_sun_light * (0.25 * pow(s, 64.0) + pow(s, 4000.0));
    out_colour = vec4(min(c, 1.0), 1.0);
}}
"""


class Renderer:
    """Headless renderer of terrain, sea, entities and sky.

    terrain: ``Terrain``, ``TerrainClient`` or None (sea, entities and sky only). width,
    height: pixels. window_m, horizon_m, horizon_stride, spacing_m: the terrain mesh
    (client/render/terrain_mesh.py). geoid_undulation_m: N, ellipsoid height = MSL + N, as the
    simulation server's scenario says. sun_azimuth_deg, sun_elevation_deg: the fixed sun, in the
    local origin's sky, degrees; sun_time: an instant (timezone-aware datetime or numpy
    datetime64, UTC), or None for the fixed sun: the sun of that instant in the camera's sky
    (client/render/shading.py; settable between frames, ``Renderer.sun_time``). fog: on/off;
    its density hides the terrain's far edge. sea: the sea shell. flat_sky_rgb: test mode, a
    flat sky of this 0-255 colour (and no fog). terrain_layer_factory(ctx, origin) -> a
    TerrainLayer, in place of the mesh. insets: terrain.inset.InsetSource objects (the target
    areas' high-detail data), each drawn as a geomipmap (client/render/geomipmap.py) over the
    terrain layer, which a clipmap lowers beneath them.
    """

    def __init__(self, terrain, width: int, height: int, *, window_m: float = DEFAULT_WINDOW_M,
                 horizon_m: float = DEFAULT_HORIZON_M, horizon_stride: int = DEFAULT_HORIZON_STRIDE,
                 spacing_m: float | None = None, geoid_undulation_m: float = 0.0,
                 sun_azimuth_deg: float = DEFAULT_SUN_AZIMUTH_DEG, sun_elevation_deg: float = DEFAULT_SUN_ELEVATION_DEG,
                 fog: bool = True, sea: bool = True, flat_sky_rgb=None, rebase_distance_m: float = REBASE_DISTANCE_M,
                 terrain_layer_factory=None, ctx=None, insets=(), sun_time=None):
        for name, v in (("width", width), ("height", height)):
            if not (isinstance(v, int) and 1 <= v <= MAX_IMAGE_SIDE):
                raise InvalidArgument(name, f"must be an integer in [1, {MAX_IMAGE_SIDE}] pixels", value=v)
        from server.scenario import GEOID_UNDULATION_ABS_MAX_M as limit  # the scenario's bound, one constant

        if not (math.isfinite(geoid_undulation_m) and abs(geoid_undulation_m) <= limit):
            raise InvalidArgument("geoid_undulation_m", f"must be within [-{limit:g}, {limit:g}] m",
                                  value=geoid_undulation_m)
        if not (-90.0 <= sun_elevation_deg <= 90.0):
            raise InvalidArgument("sun_elevation_deg", "must be within [-90, 90]", value=sun_elevation_deg)
        if flat_sky_rgb is not None and (len(flat_sky_rgb) != 3 or not all(0 <= c <= 255 for c in flat_sky_rgb)):
            raise InvalidArgument("flat_sky_rgb", "must be three values in [0, 255]", value=flat_sky_rgb)
        self.width, self.height = width, height
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.sun_azimuth_deg, self.sun_elevation_deg = float(sun_azimuth_deg), float(sun_elevation_deg)
        self.ephemeris = EphemerisSun()
        self.sun_time = sun_time
        self.fog = bool(fog) and flat_sky_rgb is None
        self.sea = bool(sea)
        self.flat_sky_rgb = None if flat_sky_rgb is None else tuple(int(c) for c in flat_sky_rgb)
        self.stats = FrameStats()
        self._last_near = 1.0
        self._owns_ctx = ctx is None
        self.ctx = create_context() if ctx is None else ctx
        self.origin = LocalOrigin(geodetic_to_ecef(0.0, 0.0, 0.0), rebase_distance_m)
        try:
            with self.ctx:
                enable_reversed_z(self.ctx)
                self._colour = self.ctx.renderbuffer((width, height), 4)
                self._depth = float_depth_texture(self.ctx, (width, height))
                self._fbo = self.ctx.framebuffer([self._colour], self._depth)
                if terrain_layer_factory is not None:
                    self.terrain_layer = terrain_layer_factory(self.ctx, self.origin)
                elif terrain is not None:
                    self.terrain_layer = TerrainMeshLayer(self.ctx, terrain, self.origin, window_m=window_m,
                                                          horizon_m=horizon_m, horizon_stride=horizon_stride,
                                                          spacing_m=spacing_m, geoid_undulation_m=geoid_undulation_m)
                else:
                    self.terrain_layer = None
                # Terrain at or below this height MSL is water: 0, or over a lossy store half its
                # step (shading.water_level_m; its sea decodes anywhere within that of 0 m).
                self._terrain = terrain if terrain is not None else getattr(self.terrain_layer, "terrain", None)
                self.water_level_m = water_level_m(self._terrain)
                from client.render.geomipmap import GeomipmapInset

                # Shaded as the terrain layer beside them (the clipmap's detail textures and land
                # classes; none for the reference mesh), so the two meet without a seam.
                shading = {"detail_strength": float(getattr(self.terrain_layer, "detail_strength", 0.0)),
                           "land_classes": bool(getattr(self.terrain_layer, "land_classes", False))}
                self.inset_layers = [GeomipmapInset(self.ctx, s, self.origin, geoid_undulation_m=geoid_undulation_m,
                                                    **shading) for s in insets]
                self.sea_layer = SeaShellLayer(self.ctx, self.origin, geoid_undulation_m) if self.sea else None
                self.entity_layer = EntityLayer(self.ctx)
                self._sky_program = self.ctx.program(vertex_shader=SKY_VERTEX_SHADER,
                                                     fragment_shader=SKY_FRAGMENT_SHADER)
                self._sky_vao = self.ctx.vertex_array(self._sky_program, [])
                check_gl_error(self.ctx, "renderer set-up")
        except BaseException:  # a half-built renderer: its GL objects go with its context
            if self._owns_ctx:
                self.ctx.release()
            self.ctx = None
            raise

    # -- lifecycle

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        """Release every GL object, and the context if the renderer made it."""
        if self.ctx is None:
            return
        with self.ctx:
            if not self._owns_ctx:  # leave the shared context on its default framebuffer, not a deleted one
                self.ctx.detect_framebuffer(0).use()
            if self.terrain_layer is not None:
                self.terrain_layer.release()
            for layer in self.inset_layers:
                layer.release()
            if self.sea_layer is not None:
                self.sea_layer.release()
            self.entity_layer.release()
            for obj in (self._sky_vao, self._sky_program, self._fbo, self._depth, self._colour):
                obj.release()
        if self._owns_ctx:
            self.ctx.release()
        self.ctx = None

    @property
    def sun_time(self):
        """The instant whose sun lights the frames (shading.EphemerisSun), or None: the fixed sun."""
        return self._sun_time

    @sun_time.setter
    def sun_time(self, when) -> None:
        if when is not None:
            instant_s("sun_time", when)  # checked here, not at the next frame
        self._sun_time = when

    # -- a frame

    def _sun(self, camera: Camera) -> tuple[np.ndarray, float, tuple[float, float]]:
        """(sun_local (3,) unit vector in the origin's ENU, sun_light 1 or 0, (azimuth, elevation)
        degrees in the camera's sky): the fixed sun, or the sun of ``sun_time`` at the camera's
        position; its direct light only while it is above the camera's horizon."""
        lat, lon, _ = camera.geodetic()
        if self._sun_time is None:
            sun_local = sun_direction_local(self.sun_azimuth_deg, self.sun_elevation_deg)
            sun_ecef = sun_local @ self.origin.basis  # (the basis' rows: east, north, up in ECEF)
        else:
            sun_ecef = self.ephemeris.direction_ecef(self._sun_time, lat, lon)
            sun_local = self.origin.vectors_to_local(sun_ecef)
        azimuth, elevation = sun_in_sky_deg(sun_ecef, lat, lon)
        return sun_local, float(elevation > 0.0), (azimuth, elevation)

    def _frame(self, camera: Camera) -> Frame:
        o = self.origin
        lat, lon, alt = camera.geodetic()
        fog_density = 0.0
        if self.fog and self.terrain_layer is not None:
            # The fog hides where the terrain ends round the camera (shading.py). From as high as that
            # edge is far, it is seen from above, and haze is a low layer: the fog thins with the
            # camera's height h over that range, as 1 / (1 + (h / range)^2) (under 0.4 % at a
            # twentieth of it; none to speak of from orbit, where fog hid the whole Earth).
            # (h / range) squared by multiplication: inf, hence no fog, for a huge h, where ** raises
            # OverflowError.
            # (A layer centred away from the camera, a clipmap aimed by a narrow view, says how far
            # its terrain reaches within this view: fog_range_for.)
            range_for = getattr(self.terrain_layer, "fog_range_for", None)
            edge = (self.terrain_layer.fog_range_m if range_for is None
                    else range_for(camera, self.width, self.height))
            ratio = max(float(alt), 0.0) / edge
            fog_density = fog_density_per_m(edge) / (1.0 + ratio * ratio)
        sun_local, sun_light, self._sun_sky_deg = self._sun(camera)
        return Frame(camera=camera, origin=o, width=self.width, height=self.height, view=camera.view_matrix(o),
                     projection=camera.projection(self.width, self.height),
                     camera_local=o.to_local(camera.position_ecef),
                     up_local=o.vectors_to_local(enu_basis(lat, lon)[2]),
                     sun_local=sun_local, sun_light=sun_light,
                     fog_density=fog_density, fog_rgb=rgb(SKY_HORIZON_RGB), flat_sky_rgb=self.flat_sky_rgb,
                     water_level_m=self.water_level_m)

    def render(self, camera: Camera, entities: EntitySet | None = None) -> np.ndarray:
        """One frame -> (height, width, 3) uint8 RGB, row 0 at the top. Stats in ``self.stats``."""
        if self.ctx is None:
            raise InvalidArgument("renderer", "has been released")
        entities = EntitySet.empty() if entities is None else entities
        t0 = time.perf_counter()
        with self.ctx:
            rebased = self.origin.rebase_if_far(camera.position_ecef)
            if self.terrain_layer is not None:
                self.terrain_layer.update(camera)  # (where its levels or mesh lie: not the near plane)
            camera, lift = self.above_drawn_ground(camera)
            near = near_plane_m(camera, self.width, self.height, self.height_above_ground_m(camera))
            if near != camera.near_m:
                camera = dataclasses.replace(camera, near_m=near)
            self._last_near = camera.near_m
            for layer in self.inset_layers:
                layer.update(camera)
            if self.sea_layer is not None:
                self.sea_layer.update(camera, getattr(self.terrain_layer, "solid_bounds", None))
            t1 = time.perf_counter()
            frame = self._frame(camera)
            self._fbo.use()
            self._fbo.clear(0.0, 0.0, 0.0, 1.0, depth=0.0)
            triangles = vertices = 0
            if self.terrain_layer is not None:
                self.terrain_layer.draw(frame)
                triangles, vertices = self.terrain_layer.triangles, self.terrain_layer.vertices
            for layer in self.inset_layers:
                layer.draw(frame)
                triangles, vertices = triangles + layer.triangles, vertices + layer.vertices
            if self.sea_layer is not None:
                self.sea_layer.draw(frame)
                triangles, vertices = triangles + self.sea_layer.triangles, vertices + self.sea_layer.vertices
            self.entity_layer.draw(frame, entities, self.drawn_ground_m if self.terrain_layer is not None else None)
            self._draw_sky(frame)
            check_gl_error(self.ctx, "frame")
            data = self._fbo.read(components=3, alignment=1)
        image = np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3)[::-1].copy()
        self.stats = FrameStats(frame_ms=(time.perf_counter() - t0) * 1e3, update_ms=(t1 - t0) * 1e3,
                                triangles=triangles + self.entity_layer.triangles + 1,
                                vertices=vertices + self.entity_layer.vertices + 3,
                                entities_drawn=self.entity_layer.drawn, rebased=rebased,
                                mesh_rebuilds=getattr(self.terrain_layer, "rebuilds", 0),
                                terrain_samples=getattr(self.terrain_layer, "samples", 0),
                                levels_active=getattr(self.terrain_layer, "levels_active", 0), eye_lift_m=lift,
                                sun_azimuth_deg=self._sun_sky_deg[0], sun_elevation_deg=self._sun_sky_deg[1])
        return image

    def above_drawn_ground(self, camera: Camera) -> tuple[Camera, float]:
        """(camera, lift m): the camera, raised along the vertical to EYE_CLEARANCE_M over the
        terrain layer's surface drawn under it (``surface_height_msl``) where it is lower. That
        surface is the cells' triangles, not the terrain's bilinear surface that queries answer and
        vehicles sit on: a cell split along one diagonal stands above the bilinear surface by up
        to a quarter of its twist (h_SW + h_NE - h_SE - h_NW) / 4 (terrain_mesh.cell_corner_weights),
        60 m in a cell of the Alps tile, so an eye a few metres over the terrain could be under
        the triangles, which face away from it: the frame showed the world from below, sky where
        the ground is. Raised, the eye sees that surface from above, as the camera over the
        bilinear one would see the ground. (Insets are drawn as their own triangles, not counted
        here; the near plane allows for them.)"""
        surface_of = getattr(self.terrain_layer, "surface_height_msl", None)
        if surface_of is None:
            return camera, 0.0
        lat, lon, h = camera.geodetic()
        surface = float(surface_of(lat, lon))
        lift = surface + EYE_CLEARANCE_M - (h - self.geoid_undulation_m)
        if not (lift > 0.0):  # (NaN: no surface drawn there)
            return camera, 0.0
        up = enu_basis(lat, lon)[2]
        return dataclasses.replace(camera, position_ecef=camera.position_ecef + lift * up), lift

    def drawn_ground_m(self, lats, lons) -> np.ndarray:
        """(n,) float64: the ellipsoid height (metres; MSL + N) of the terrain layer's surface drawn
        at (n,) degrees, the surface :meth:`above_drawn_ground` keeps the eye over; NaN where it draws
        none. Entities are lifted onto it (entities.ground_lifts). One call for all where the layer
        answers many points at once (``surface_heights_msl``), else a call a point."""
        lats, lons = np.asarray(lats, np.float64), np.asarray(lons, np.float64)
        many = getattr(self.terrain_layer, "surface_heights_msl", None)
        one = getattr(self.terrain_layer, "surface_height_msl", None)
        if many is not None:
            surface = np.asarray(many(lats, lons), np.float64)
        elif one is not None:
            surface = np.fromiter((one(float(a), float(b)) for a, b in zip(lats, lons)), np.float64, len(lats))
        else:
            surface = np.full(len(lats), math.nan)
        return surface + self.geoid_undulation_m

    def height_above_ground_m(self, camera: Camera) -> float:
        """The camera's height above the highest surface drawn under it (metres; negative
        below it), for the near plane (camera.near_plane_m): each layer's ``ground_height_msl``
        (the clipmap's, the mesh's and the insets': the highest post of the cell under the camera), else, or
        where the layer holds no post there, the terrain's height there; where nothing has data,
        sea level (the sea shell and no-data posts are drawn at 0 m MSL, the shell a metre lower)."""
        lat, lon, h = camera.geodetic()
        ground_of = getattr(self.terrain_layer, "ground_height_msl", None)
        ground = math.nan if ground_of is None else float(ground_of(lat, lon))
        if math.isnan(ground) and self._terrain is not None:
            ground = float(np.asarray(self._terrain.heights(np.array([lat]), np.array([lon])).height_msl_m)[0])
        grounds = [ground] + [layer.ground_height_msl(lat, lon) for layer in self.inset_layers]
        grounds = [g for g in grounds if math.isfinite(g)]
        return h - self.geoid_undulation_m - (max(grounds) if grounds else 0.0)

    def depth_m(self) -> np.ndarray:
        """(height, width) float64 view depth of the last frame (metres along the optical axis,
        row 0 at the top); inf where only sky was drawn."""
        with self.ctx:
            d = np.frombuffer(self._depth.read(), np.float32).reshape(self.height, self.width)[::-1]
        with np.errstate(divide="ignore"):
            return np.where(d > 0, self._last_near / d.astype(np.float64), np.inf)

    def _draw_sky(self, frame: Frame) -> None:
        import moderngl

        cam = frame.camera
        fx, fy = cam.focal(self.width, self.height)
        r_local_body = frame.origin.basis @ cam.r_ecef_body
        basis = np.stack([r_local_body[:, 1] / fx, -r_local_body[:, 2] / fy, r_local_body[:, 0]], axis=-1)
        p = self._sky_program
        p["u_size"].value = (float(self.width), float(self.height))
        p["u_ray_basis"].write(basis.T.astype("f4").tobytes())  # GLSL matrices are column-major
        p["u_up"].write(frame.up_local.astype("f4").tobytes())
        p["u_sun"].write(frame.sun_local.astype("f4").tobytes())
        p["u_sun_light"].value = float(frame.sun_light)
        p["u_flat"].value = int(frame.flat_sky_rgb is not None)
        p["u_flat_rgb"].value = rgb(frame.flat_sky_rgb or (0, 0, 0))
        self.ctx.depth_func = ">="  # only where the depth is still the cleared 0 (writes 0: no change)
        self._sky_vao.render(moderngl.TRIANGLES, vertices=3)
        self.ctx.depth_func = ">"
