"""Geomipmapping (de Boer 2000) of a target area's inset: a terrain layer of the renderer.

Willem H. de Boer, "Fast Terrain Rendering Using Geometrical MipMapping"
(E-mersion Project, October 2000). Followed here:

- **GeoMipMaps** (§2.3): the terrain is cut into square blocks ("patches") of
  2^k + 1 posts (``patch_posts``, default 33) sharing their border posts;
  level l of a patch keeps every 2^l-th post, down to its four corners.
- **Choosing the level** (§2.3.1, "Choosing the appropriate GeoMipMap level"): per
  patch and level the largest geometric error delta of dropping to that level
  is precomputed; a level is good while delta, projected, stays within tau
  pixels. de Boer precomputes D_n = |delta| C, C = A / T, A = n / |t|,
  T = 2 tau / v_res; equivalently the projected error is
  eps = delta K / d, K = v_res / (2 tan(fov_y / 2)) pixels, and the coarsest
  level with eps <= tau is drawn. d is the distance from the camera to the
  nearest point of the patch's bounding box (so eps bounds the error of every
  post in it). tau defaults to 1 pixel (``DEFAULT_TAU_PX``). eps is de Boer's
  measure, a displacement seen square-on: off the optical axis by theta a
  displacement can project up to 1 / cos^2(theta) larger (1.44 at the corner
  of a 60 degree wide 16:9 view; the tests measure it).
- **Cracks** (§2.3, between blocks of different levels): where a patch meets
  a coarser neighbour, its border keeps only the coarser neighbour's posts
  (de Boer's fix: the finer block leaves out its in-between border vertices,
  so no T-junction is left). We take that approach over skirts: the mesh stays
  watertight and exact on the shared edge (both patches hold the very same
  vertices there: same posts, same float32 bits), draws no extra vertical
  faces (skirts cost llvmpipe fill on every patch edge, and shade as cliffs
  at grazing views), and needs no depth-bias tuning.

Our triangulation of a patch at level l (step s = 2^l) with edge steps
e_side >= s (the coarser of the two patches' levels on that side):
the inner square [s, n - s]^2 as regular cells (two triangles each,
counter-clockwise seen from above), and on each side a trapezoid strip from
the outer edge (posts every e_side) to the inner square's edge (posts every
s), triangulated by merging the two rows in order along the side (a
"zipper"). Neighbouring strips share the diagonal from the patch corner to the
inner square's corner, so the four strips and the inner square tile the
patch. Each strip depends only on (l, e_side): errors are tabulated per piece.

**Stitching keeps the error bound.** The stitched strip of a fine patch
next to a coarse one has its own error; it is tabulated (exactly: the drawn
triangles evaluated at every post of the strip) for every (l, e), and when a
patch's stitched error would exceed its budget tau d / K the neighbour is made
finer until it does not (levels only go down, so this ends; level 0 stitched
to level 0 has error 0). Every drawn patch then meets eps <= tau with the
triangles actually drawn (tested independently). Errors are vertical, in the
(lat, lon, h) parameterisation of the lattice, plus the chord sag of a
triangle's edge below the ellipsoid, (2^l c)^2 / (8 R), c the cell diagonal.

**Only the area.** Patches wholly farther than a patch diagonal outside the
polygon are never uploaded; on the others, a triangle is dropped when a vertex
lies farther outside the polygon than the triangle's diameter (so it cannot
reach inside). What is drawn covers the polygon, and ends just outside it,
where the clipmap's uncut terrain takes over (terrain/inset.py's cut-out).

Geometry: posts placed in ECEF from (lat, lon, h + N) (N the scenario's geoid
undulation), uploaded as float32 ENU offsets of the renderer's float64 origin
(client/render/camera.py), re-uploaded on a rebase; normals are central
differences of the full-resolution ECEF post grid (one per post at every
level: coarse patches keep fine shading, a per-vertex normal map).
Frustum culling by each patch's bounding box. One VBO per layer (one block of
(n + 1)^2 vertices per patch), one index buffer rebuilt only when the levels
or the visible set change, one draw call.

Meeting the clipmap (client/render/clipmap_layer.py "Insets"). Shading: the
clipmap's (terrain_mesh's colour and lighting, client/render/shading.py's sun
and fog, then clipmap_layer.DETAIL_GLSL's detail textures at the same ECEF
texture coordinates, and with ``land_classes`` each post's land-class colour,
classified as the clipmap classifies its normal texels), so where the two draw
the same ground (the DEM along the polygon's border, where the inset has no
detail) they have the same colour; the Renderer gives the inset its terrain
layer's detail strength (0 beside the reference mesh, which has none). Depth:
the vertex shader scales the window depth by INSET_DEPTH_SCALE = 1 + 2^-14, so
the inset lies 6.1e-5 of its distance nearer than it is: a relative bias, as
float32 reversed-Z depth resolves relative distances (1.2e-7 d, client/render/
gl.py), so it wins every tie with the clipmap at every distance by 500 times
the depth buffer's resolution (6 cm at 1 km, 6 m at 100 km), and it keeps the
early depth test (no gl_FragDepth; glPolygonOffset's units for a float depth
buffer depend on the primitive's largest depth exponent, OpenGL 4.5 §14.6.5,
and its slope factor on the implementation). Ground within 6e-5 d of the
inset along the ray (an entity's wheels) may be hidden: 1 cm at 1 km seen 10
degrees down. Inside the polygon the clipmap's fragments are pushed far behind
the inset (the clipmap's side of the same fix).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from client.render.camera import Camera, LocalOrigin
from client.render.clipmap_layer import DETAIL_GLSL, DETAIL_STRENGTH, DETAIL_TILE_M, detail_texture_object
from client.render.gl import check_gl_error
from client.render.shading import GLSL_COMMON, Frame
from client.render.terrain_mesh import TERRAIN_COLOUR_GLSL, interleave
from sortie.errors import InvalidArgument, LimitExceeded
from terrain.geodesy import enu_basis, geodetic_to_ecef

log = logging.getLogger(__name__)

DEFAULT_PATCH_POSTS = 33  # de Boer's blocks of 2^k + 1 posts; 33: 2048 triangles at level 0
DEFAULT_TAU_PX = 1.0  # projected geometric error allowed, pixels
MAX_VERTICES = 1 << 23  # 8.4M vertices: 256 MiB of vertex buffer
MIN_RADIUS_OF_CURVATURE_M = 6_335_439.0  # WGS84 meridian radius at the equator (chord sag bound)
N_SIDE, E_SIDE, S_SIDE, W_SIDE = 0, 1, 2, 3
SIDE_NAMES = ("north", "east", "south", "west")
_MAX_STITCH_ROUNDS = 64
# The inset is drawn 2^-14 (6.1e-5) of its distance nearer than it is (reversed-Z: window depth
# near/d, scaled in the vertex shader, so the early depth test stays). Where the inset and the
# clipmap are the same surface (the DEM, along the polygon's border) the inset wins the depth test
# instead of a tie: 500 times float32 depth's 1.2e-7 d resolution, 6 cm at 1 km. Module docstring.
INSET_DEPTH_SCALE = 1.0 + 2.0 ** -14

INSET_VERTEX_SHADER = "#version 330 core\n" + GLSL_COMMON + """
uniform mat3 u_rot;            // ECEF axes -> local ENU
uniform vec3 u_origin_mod;     // renderer origin ECEF modulo the detail tile, metres
in vec3 in_position;           // local ENU metres (float32 offsets from the origin)
in vec3 in_normal;             // local ENU unit vector
in float in_height;            // metres MSL
in float in_cos_slope;
out vec3 v_world;
out vec3 v_normal;
out float v_height;
out float v_cos_slope;
out vec3 v_ecef_mod;
#ifdef CLASSES
in vec3 in_class;              // the post's land-class colour (terrain/texture.py)
out vec3 v_class;
#endif
void main() {
    v_world = in_position;
    v_normal = in_normal;
    v_height = in_height;
    v_cos_slope = in_cos_slope;
    v_ecef_mod = u_origin_mod + transpose(u_rot) * in_position;
#ifdef CLASSES
    v_class = in_class;
#endif
    gl_Position = u_projection * (u_view * vec4(in_position, 1.0));
    gl_Position.z *= INSET_DEPTH_SCALE;
}
"""

# The clipmap's shading (client/render/clipmap_layer.py FRAGMENT_SHADER) with per-post normals and
# land classes: the same colour, lighting, fog and detail textures at the same point.
INSET_FRAGMENT_SHADER = "#version 330 core\n" + GLSL_COMMON + TERRAIN_COLOUR_GLSL + DETAIL_GLSL + """
uniform mat3 u_rot;
in vec3 v_world;
in vec3 v_normal;
in float v_height;
in float v_cos_slope;
in vec3 v_ecef_mod;
#ifdef CLASSES
in vec3 v_class;
#endif
out vec4 out_colour;
void main() {
    vec3 n = normalize(v_normal);
    vec3 c = terrain_colour(v_world, n, v_height, v_cos_slope);
#ifdef CLASSES
    if (v_height > u_water_level) c = fogged(lambert(v_class, n), v_world);
#endif
#ifdef DETAIL
    c = detailed(c, transpose(u_rot) * n, v_cos_slope, v_height, v_ecef_mod);
#endif
    out_colour = vec4(c, 1.0);
}
"""


def inset_shader(source: str, detail: bool, classes: bool) -> str:
    """A variant of INSET_VERTEX_SHADER / INSET_FRAGMENT_SHADER: with the detail textures, with
    the land-class base colour (compiled in or out, as the clipmap's, client/render/clipmap_layer.py
    shader_variant)."""
    head, rest = source.split("\n", 1)
    defines = "#define INSET_DEPTH_SCALE %r\n" % INSET_DEPTH_SCALE
    defines += ("#define DETAIL\n" if detail else "") + ("#define CLASSES\n" if classes else "")
    return head + "\n" + defines + rest


# -- patch templates (pure) ----------------------------------------------------------------------

def _orient_ccw(tris: np.ndarray, n: int) -> np.ndarray:
    """Flip triangles (m, 3) of flat local indices r (n + 1) + c to counter-clockwise seen from
    above (x = column east, y = row north)."""
    r, c = np.divmod(tris, n + 1)
    area2 = (c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0]) - (c[:, 2] - c[:, 0]) * (r[:, 1] - r[:, 0])
    out = tris.copy()
    out[area2 < 0, 1], out[area2 < 0, 2] = tris[area2 < 0, 2], tris[area2 < 0, 1]
    return out


def _side_rows(n: int, s: int, e: int, side: int):
    """(outer, inner) post lists (r, c) of a side's strip, both ordered along the side."""
    t_out = range(0, n + 1, e)
    t_in = range(s, n - s + 1, s)
    if side == S_SIDE:
        return [(0, t) for t in t_out], [(s, t) for t in t_in]
    if side == N_SIDE:
        return [(n, t) for t in t_out], [(n - s, t) for t in t_in]
    if side == W_SIDE:
        return [(t, 0) for t in t_out], [(t, s) for t in t_in]
    return [(t, n) for t in t_out], [(t, n - s) for t in t_in]


@functools.lru_cache(maxsize=None)
def piece_triangles(n: int, level: int, edge_level: int, side: int) -> np.ndarray:
    """Triangles (m, 3) int64, flat local post indices r (n + 1) + c, of one piece of a patch of
    n cells at ``level``: side -1 the inner square (or, at the coarsest level, the whole patch),
    else the strip of ``side`` whose outer edge keeps every 2^edge_level-th post. Read-only."""
    s = 1 << level
    if s > n // 2:  # the coarsest level: one cell, two triangles; no strips
        tris = [] if side >= 0 else [(0, n, n * (n + 1) + n), (0, n * (n + 1) + n, n * (n + 1))]
    elif side < 0:
        r, c = np.meshgrid(np.arange(s, n - s, s), np.arange(s, n - s, s), indexing="ij")
        sw = (r * (n + 1) + c).ravel()
        se, nw = sw + s, sw + s * (n + 1)
        tris = np.concatenate([np.stack([sw, se, nw + s], -1), np.stack([sw, nw + s, nw], -1)]).tolist()
    else:
        outer, inner = _side_rows(n, s, 1 << edge_level, side)
        along = (lambda p: p[1]) if side in (S_SIDE, N_SIDE) else (lambda p: p[0])
        i = j = 0
        tris = []
        while i < len(outer) - 1 or j < len(inner) - 1:
            if j == len(inner) - 1 or (i < len(outer) - 1 and along(outer[i + 1]) <= along(inner[j + 1])):
                tris.append((outer[i], outer[i + 1], inner[j]))
                i += 1
            else:
                tris.append((outer[i], inner[j + 1], inner[j]))
                j += 1
        tris = [[p[0] * (n + 1) + p[1] for p in t] for t in tris]
    out = _orient_ccw(np.array(tris, dtype=np.int64).reshape(-1, 3), n)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4096)
def patch_template(n: int, level: int, edges: tuple) -> np.ndarray:
    """(m, 3) int64 triangles of a whole patch at ``level`` with edge levels (north, east, south,
    west), each >= level. Read-only."""
    if any(e < level for e in edges):
        raise ValueError(f"edge levels {edges} must be >= the level {level}")
    parts = [piece_triangles(n, level, level, -1)] + [piece_triangles(n, level, e, side)
                                                      for side, e in enumerate(edges)]
    out = np.concatenate(parts)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=None)
def piece_samples(n: int, level: int, edge_level: int, side: int):
    """Where the drawn surface of a piece is evaluated: every post of the patch inside or on one
    of its triangles, as (posts (k,), vertices (k, 3), barycentric weights (k, 3)) in flat local
    indices. Exact for integer coordinates (weights are ratios of small integers)."""
    tris = piece_triangles(n, level, edge_level, side)
    got_post, got_v, got_w = [], [], []
    for t in tris:
        r, c = np.divmod(t, n + 1)
        ri, ci = np.meshgrid(np.arange(r.min(), r.max() + 1), np.arange(c.min(), c.max() + 1), indexing="ij")
        ri, ci = ri.ravel(), ci.ravel()
        den = (r[1] - r[2]) * (c[0] - c[2]) + (c[2] - c[1]) * (r[0] - r[2])
        l0 = ((r[1] - r[2]) * (ci - c[2]) + (c[2] - c[1]) * (ri - r[2])) / den
        l1 = ((r[2] - r[0]) * (ci - c[2]) + (c[0] - c[2]) * (ri - r[2])) / den
        l2 = 1.0 - l0 - l1
        inside = (l0 >= -1e-12) & (l1 >= -1e-12) & (l2 >= -1e-12)
        got_post.append(ri[inside] * (n + 1) + ci[inside])
        got_v.append(np.broadcast_to(t, (int(inside.sum()), 3)))
        got_w.append(np.stack([l0[inside], l1[inside], l2[inside]], -1))
    if not got_post:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    post, first = np.unique(np.concatenate(got_post), return_index=True)
    out = post, np.concatenate(got_v)[first], np.concatenate(got_w)[first]
    for a in out:
        a.flags.writeable = False
    return out


def piece_error_m(heights: np.ndarray, n: int, level: int, edge_level: int, side: int) -> np.ndarray:
    """(P,) float64: the largest |drawn surface - post height| (m) over a piece's posts, for
    patches heights (P, (n + 1)^2) float64 metres; inf where a post involved is NaN."""
    post, v, w = piece_samples(n, level, edge_level, side)
    if post.size == 0:
        return np.zeros(heights.shape[0])
    drawn = np.einsum("pkj,kj->pk", heights[:, v], w)
    err = np.abs(drawn - heights[:, post])
    return np.where(np.isnan(err), np.inf, err).max(axis=1)


# -- the layer -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Selection:
    """One frame's choice, per active patch (A,): level, edge levels (A, 4) (north, east, south,
    west), visible (in the frustum), distance_m to its bounding box, budget_m = tau d / K,
    error_m of the triangles drawn (tabulated), projected_px = error_m K / d."""

    level: np.ndarray
    edges: np.ndarray
    visible: np.ndarray
    distance_m: np.ndarray
    budget_m: np.ndarray
    error_m: np.ndarray
    projected_px: np.ndarray
    pixels_per_radian: float  # K


@dataclass
class GeomipmapStats:
    """Last frame: patches uploaded (active), drawn, culled by the frustum; drawn patches per
    level (tuple, level 0 first); triangles and vertices submitted; the largest projected error
    of a drawn patch (px); select_ms (levels), index_ms (index build + upload, 0 when reused)."""

    patches: int = 0
    patches_drawn: int = 0
    patches_culled: int = 0
    patches_per_lod: tuple = ()
    triangles: int = 0
    vertices: int = 0
    max_error_px: float = 0.0
    select_ms: float = 0.0
    index_ms: float = 0.0


class GeomipmapInset:
    """A target area's inset drawn by geomipmapping: a terrain layer of the renderer.

    ctx: the renderer's moderngl context (current while calling); inset_source: a
    terrain.inset.InsetSource (its lattice, heights and signed distances); origin: the
    renderer's LocalOrigin; geoid_undulation_m: N (ellipsoid height = MSL + N); tau_px: the
    projected error allowed; patch_posts: 2^k + 1, 3..65; stitch: False leaves the cracks
    between levels open (for tests); frustum_cull: skip patches outside the view.
    detail_strength, land_classes: shade as the terrain layer beside it does (the clipmap's
    detail textures, 0 for none; its land-class base colour), so the two meet without a seam.
    """

    def __init__(self, ctx, inset_source, origin: LocalOrigin, *, geoid_undulation_m: float = 0.0,
                 tau_px: float = DEFAULT_TAU_PX, patch_posts: int = DEFAULT_PATCH_POSTS, stitch: bool = True,
                 frustum_cull: bool = True, detail_strength: float = DETAIL_STRENGTH, land_classes: bool = False):
        n = patch_posts - 1
        if not (isinstance(patch_posts, int) and 2 <= n <= 64 and n & (n - 1) == 0):
            raise InvalidArgument("patch_posts", "must be 2^k + 1 posts, 3..65", value=patch_posts)
        if not (math.isfinite(tau_px) and tau_px > 0):
            raise InvalidArgument("tau_px", "must be finite and > 0", value=tau_px)
        if not (math.isfinite(geoid_undulation_m) and abs(geoid_undulation_m) <= 120.0):
            raise InvalidArgument("geoid_undulation_m", "must be within [-120, 120] m", value=geoid_undulation_m)
        if not (math.isfinite(detail_strength) and 0.0 <= detail_strength <= 1.0):
            raise InvalidArgument("detail_strength", "must be within [0, 1]", value=detail_strength)
        rows, cols = inset_source.shape
        if (rows - 1) % n or (cols - 1) % n:
            raise InvalidArgument("patch_posts", f"must tile the inset's {rows} x {cols} posts", value=patch_posts)
        self.ctx = ctx
        self.inset = inset_source
        self.origin = origin
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.tau_px = float(tau_px)
        self.n = n
        self.levels = int(math.log2(n)) + 1  # 0 .. log2(n)
        self.stitch = bool(stitch)
        self.frustum_cull = bool(frustum_cull)
        self.detail_strength = float(detail_strength)  # the u_detail_strength uniform, set every frame
        self.land_classes = bool(land_classes)
        self.stats = GeomipmapStats()
        self.selection: Selection | None = None
        t0 = time.perf_counter()
        self._build_cpu()
        self.build_ms = (time.perf_counter() - t0) * 1e3
        detail = self.detail_strength > 0.0
        self.program = ctx.program(vertex_shader=inset_shader(INSET_VERTEX_SHADER, detail, self.land_classes),
                                   fragment_shader=inset_shader(INSET_FRAGMENT_SHADER, detail, self.land_classes))
        self._detail = detail_texture_object(ctx) if detail else None
        self._class_vbo = None
        if self.land_classes:
            self._class_vbo = ctx.buffer(self._class_colours().astype("f4").tobytes())
        self._vbo = self._ibo = self._vao = None
        self._ibo_bytes = 0
        self._generation = None
        self._index_key = None
        self._index_count = 0
        self.indices = np.zeros((0, 3), np.uint32)  # the last frame's triangles, vertex ids (CPU copy)
        self._border_cache: dict = {}
        log.info("geomipmap inset %r: %d of %d patches active, %d vertices, built in %.0f ms", inset_source.name,
                 self.active.size, self.patch_grid[0] * self.patch_grid[1], self.vertices, self.build_ms)

    # -- CPU build: patches, vertices, error tables

    def _build_cpu(self) -> None:
        inset, n = self.inset, self.n
        rows, cols = inset.shape
        pr, pc = (rows - 1) // n, (cols - 1) // n
        self.patch_grid = (pr, pc)
        h_all = np.asarray(inset.heights, dtype=np.float64)
        sd_all = np.asarray(inset.signed_distance, dtype=np.float64)
        k = np.arange(n + 1)
        ri = (np.arange(pr) * n)[:, None, None, None] + k[None, None, :, None]
        ci = (np.arange(pc) * n)[None, :, None, None] + k[None, None, None, :]
        h = h_all[ri, ci].reshape(pr * pc, (n + 1) ** 2)
        sd = sd_all[ri, ci].reshape(pr * pc, (n + 1) ** 2)
        spacing_e, spacing_n = inset.spacing_m
        self.cell_diagonal_m = math.hypot(spacing_e, spacing_n)
        patch_diag_m = n * self.cell_diagonal_m
        active = (sd.max(axis=1) >= -patch_diag_m) & np.isfinite(h).any(axis=1)
        self.active = np.flatnonzero(active)  # patch ids (row-major in the patch grid) of the slots
        if self.active.size * (n + 1) ** 2 > MAX_VERTICES:
            raise LimitExceeded(f"geomipmap vertices of target area {inset.name!r}", self.active.size * (n + 1) ** 2,
                                MAX_VERTICES)
        self.heights = h[self.active]
        self.signed_distance = sd[self.active]
        self.full = (sd[self.active].min(axis=1) >= 0.0) & np.isfinite(self.heights).all(axis=1)
        a_r, a_c = np.divmod(self.active, pc)
        self.patch_rc = np.stack([a_r, a_c], axis=-1)
        slot = np.full(pr * pc, -1, np.int64)
        slot[self.active] = np.arange(self.active.size)
        grid = slot.reshape(pr, pc)
        padded = np.full((pr + 2, pc + 2), -1, np.int64)
        padded[1:-1, 1:-1] = grid
        self.neighbours = np.stack([padded[a_r + 2, a_c + 1], padded[a_r + 1, a_c + 2], padded[a_r, a_c + 1],
                                    padded[a_r + 1, a_c]], axis=-1)  # (A, 4) slots north, east, south, west
        self._build_vertices(a_r, a_c)
        self._build_errors()

    def _build_vertices(self, a_r: np.ndarray, a_c: np.ndarray) -> None:
        inset, n = self.inset, self.n
        rows, cols = inset.shape
        g = inset.georef
        k = np.arange(-1, n + 2)  # one post of halo for the central differences
        ri = np.clip(a_r[:, None] * n + k[None, :], 0, rows - 1)[:, :, None]
        ci = np.clip(a_c[:, None] * n + k[None, :], 0, cols - 1)[:, None, :]
        lat = g.y0 + ri * g.dy + 0.0 * ci
        lon = g.x0 + ci * g.dx + 0.0 * ri
        h = np.asarray(inset.heights, dtype=np.float64)[ri, ci]
        p = geodetic_to_ecef(lat, lon, h + self.geoid_undulation_m)  # (A, n + 3, n + 3, 3)
        d_east = 0.5 * (p[:, 1:-1, 2:] - p[:, 1:-1, :-2])
        d_north = 0.5 * (p[:, 2:, 1:-1] - p[:, :-2, 1:-1])
        normals = np.cross(d_east, d_north)
        with np.errstate(invalid="ignore", divide="ignore"):
            normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        up = enu_basis(lat[:, 1:-1, 1:-1], lon[:, 1:-1, 1:-1])[2]
        cos_slope = np.einsum("...k,...k->...", normals, up)
        bad = ~np.isfinite(cos_slope)
        normals[bad], cos_slope[bad] = up[bad], 1.0
        pos = p[:, 1:-1, 1:-1]
        self.positions_ecef = pos.reshape(-1, 3)
        self.normals_ecef = normals.reshape(-1, 3)
        self.height_msl_m = h[:, 1:-1, 1:-1].reshape(-1)
        self.cos_slope = cos_slope.reshape(-1)
        # Bounding boxes in an ENU frame at the lattice's centre (float64, fixed).
        rows_c, cols_c = (rows - 1) / 2, (cols - 1) / 2
        lat_c, lon_c = g.y0 + rows_c * g.dy, g.x0 + cols_c * g.dx
        self.frame_ecef = geodetic_to_ecef(lat_c, lon_c, 0.0)
        self.frame_basis = np.stack(enu_basis(lat_c, lon_c))  # rows east, north, up
        local = (pos - self.frame_ecef) @ self.frame_basis.T
        self.box_min = np.nanmin(local.reshape(len(a_r), -1, 3), axis=1)
        self.box_max = np.nanmax(local.reshape(len(a_r), -1, 3), axis=1)

    def _build_errors(self) -> None:
        """inner_error_m (A, L), strip_error_m (A, 4, L, L) [slot, side, level, edge level], with the
        chord sag of the coarser step; plain_error_m (A, L): the patch at a level next to equal
        neighbours, made non-decreasing in the level (so a finer level never has more)."""
        n, levels, h = self.n, self.levels, self.heights
        sag = (np.exp2(np.arange(levels)) * self.cell_diagonal_m) ** 2 / (8.0 * MIN_RADIUS_OF_CURVATURE_M)
        inner = np.zeros((h.shape[0], levels))
        strip = np.full((h.shape[0], 4, levels, levels), np.inf)
        for lv in range(levels):
            inner[:, lv] = piece_error_m(h, n, lv, lv, -1) + sag[lv]
            for e in range(lv, levels):
                for side in range(4):
                    strip[:, side, lv, e] = piece_error_m(h, n, lv, e, side) + sag[e]
        self.inner_error_m = inner
        self.strip_error_m = strip
        diag = np.diagonal(strip, axis1=2, axis2=3)  # (A, 4, L): each side at the patch's own level
        self.plain_error_m = np.maximum.accumulate(np.maximum(inner, diag.max(axis=1)), axis=1)

    # -- level selection

    def select(self, camera: Camera, width: int, height: int) -> Selection:
        """Levels for a view (pure CPU, float64): the coarsest level whose projected error is
        within tau, then neighbours made finer until every stitched strip is within it too."""
        fx, fy = camera.focal(width, height)
        k_px = 0.5 * height * fy  # K = v_res / (2 tan(fov_y / 2))
        cam = (camera.position_ecef - self.frame_ecef) @ self.frame_basis.T
        nearest = np.clip(cam, self.box_min, self.box_max)
        dist = np.linalg.norm(nearest - cam, axis=1)
        budget = self.tau_px * dist / k_px
        ok = self.plain_error_m <= budget[:, None]
        level = np.maximum(ok.sum(axis=1) - 1, 0)
        if self.stitch:
            level = self._stitch_levels(level, budget)
        edges = np.repeat(level[:, None], 4, axis=1)
        if self.stitch:
            has = self.neighbours >= 0
            nb_level = np.where(has, level[np.maximum(self.neighbours, 0)], level[:, None])
            edges = np.maximum(edges, nb_level)
        slots = np.arange(level.size)
        err = self.inner_error_m[slots, level]
        for side in range(4):
            err = np.maximum(err, self.strip_error_m[slots, side, level, edges[:, side]])
        with np.errstate(divide="ignore", invalid="ignore"):
            projected = np.where(dist > 0, err * k_px / dist, np.where(err > 0, np.inf, 0.0))
        visible = self._in_frustum(camera, fx, fy) if self.frustum_cull else np.ones(level.size, bool)
        return Selection(level, edges, visible, dist, budget, err, projected, k_px)

    def _stitch_levels(self, level: np.ndarray, budget: np.ndarray) -> np.ndarray:
        level = level.copy()
        for _ in range(_MAX_STITCH_ROUNDS * self.levels):
            changed = False
            for side in range(4):
                q = self.neighbours[:, side]
                p = np.flatnonzero(q >= 0)
                q = q[p]
                lp, lq = level[p], level[q]
                coarser = lq > lp
                p, q, lp, lq = p[coarser], q[coarser], lp[coarser], lq[coarser]
                bad = self.strip_error_m[p, side, lp, lq] > budget[p]
                if not bad.any():
                    continue
                p, q, lp, lq = p[bad], q[bad], lp[bad], lq[bad]
                new = lp.copy()  # level lp next to lp always fits (plain error <= budget)
                for e in range(self.levels - 1, -1, -1):
                    fits = (e >= lp) & (e < lq) & (new == lp) & (self.strip_error_m[p, side, lp, e] <= budget[p])
                    new[fits] = e
                np.minimum.at(level, q, new)
                changed = True
            if not changed:
                return level
        raise RuntimeError("geomipmap stitching did not settle")  # unreachable: levels only go down

    def _in_frustum(self, camera: Camera, fx: float, fy: float) -> np.ndarray:
        """(A,) bool: the patch's bounding box is not wholly outside one plane of the view frustum."""
        corners = np.stack([np.where(np.array([i & 1, i & 2, i & 4], bool), self.box_max, self.box_min)
                            for i in range(8)], axis=1)  # (A, 8, 3) local
        v = camera.to_view(self.frame_ecef + corners @ self.frame_basis)
        x, y, d = v[..., 0], v[..., 1], -v[..., 2]
        out = ((fx * x > d).all(1) | (-fx * x > d).all(1) | (fy * y > d).all(1) | (-fy * y > d).all(1)
               | (d < camera.near_m).all(1))
        return ~out

    # -- indices

    def _template_diameters(self, tri: np.ndarray) -> np.ndarray:
        r, c = np.divmod(tri, self.n + 1)
        se, sn = self.inset.spacing_m
        lengths = [np.hypot((c[:, a] - c[:, b]) * se, (r[:, a] - r[:, b]) * sn) for a, b in ((0, 1), (1, 2), (2, 0))]
        return np.maximum.reduce(lengths)

    def _border_template(self, slot: int, level: int, edges: tuple) -> np.ndarray:
        key = (slot, level, edges)
        got = self._border_cache.get(key)
        if got is None:
            tri = patch_template(self.n, level, edges)
            s = self.signed_distance[slot][tri]
            finite = np.isfinite(self.heights[slot][tri]).all(axis=1)
            keep = (s >= -self._template_diameters(tri)[:, None]).all(axis=1) & finite
            got = tri[keep]
            if len(self._border_cache) > 65536:
                self._border_cache.clear()
            self._border_cache[key] = got
        return got

    def build_indices(self, sel: Selection) -> np.ndarray:
        """(m, 3) uint32 vertex ids of the visible patches' triangles for a selection."""
        per_patch = (self.n + 1) ** 2
        draw = np.flatnonzero(sel.visible)
        parts = []
        full = draw[self.full[draw]]
        if full.size:
            keys = np.concatenate([sel.level[full, None], sel.edges[full]], axis=1)
            uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
            for u, key in enumerate(uniq):
                slots = full[inverse.ravel() == u]
                tri = patch_template(self.n, int(key[0]), tuple(int(e) for e in key[1:]))
                parts.append((tri[None] + (slots * per_patch)[:, None, None]).reshape(-1, 3))
        for slot in draw[~self.full[draw]]:
            tri = self._border_template(int(slot), int(sel.level[slot]), tuple(int(e) for e in sel.edges[slot]))
            parts.append(tri + slot * per_patch)
        if not parts:
            return np.zeros((0, 3), np.uint32)
        return np.concatenate(parts).astype(np.uint32)

    def vertex_lattice_index(self, vertex_ids) -> np.ndarray:
        """(..., 2) int64 inset lattice (row, col) of vertex ids."""
        slot, local = np.divmod(np.asarray(vertex_ids, dtype=np.int64), (self.n + 1) ** 2)
        lr, lc = np.divmod(local, self.n + 1)
        return np.stack([self.patch_rc[slot, 0] * self.n + lr, self.patch_rc[slot, 1] * self.n + lc], axis=-1)

    # -- the layer interface

    @property
    def fog_range_m(self) -> float:
        return math.inf  # the inset never ends where fog must hide an edge

    @property
    def solid_bounds(self):
        return None

    @property
    def triangles(self) -> int:
        return self.stats.triangles

    @property
    def vertices(self) -> int:
        return self.stats.vertices

    def ground_height_msl(self, lat: float, lon: float) -> float:
        """At least the height MSL of the inset's surface at (lat, lon), for the renderer's near
        plane: the highest corner of the lattice cell holding it (a coarser patch level departs from
        it by at most its tabulated error, under tau_px pixels: a few millimetres a metre of the
        distance to the patch, less than the near plane's margin). NaN off the lattice or its data."""
        g, (rows, cols) = self.inset.georef, self.inset.shape
        fr = (lat - g.y0) / g.dy
        fc = ((lon - g.x0 + 180.0) % 360.0 - 180.0) / g.dx
        if not (0.0 <= fr <= rows - 1 and 0.0 <= fc <= cols - 1):
            return math.nan
        r, c = min(int(fr), rows - 2), min(int(fc), cols - 2)
        corners = np.asarray(self.inset.heights, dtype=np.float64)[r:r + 2, c:c + 2]
        return float(corners.max()) if np.isfinite(corners).all() else math.nan

    def update(self, camera: Camera) -> None:
        """Re-upload the vertices after a rebase of the local origin (levels are chosen in draw,
        which knows the viewport)."""
        if self._generation != self.origin.generation:
            self._upload_vertices()

    def _upload_vertices(self) -> None:
        data = interleave(self.origin, self.positions_ecef, self.normals_ecef, self.height_msl_m, self.cos_slope)
        if self._vbo is None:
            self._vbo = self.ctx.buffer(data.tobytes())
        else:
            self._vbo.write(data.tobytes())
        self._generation = self.origin.generation
        check_gl_error(self.ctx, "geomipmap vertex upload")

    def _upload_indices(self, indices: np.ndarray) -> None:
        data = indices.tobytes()
        if self._ibo is None or len(data) > self._ibo_bytes:
            for obj in (self._vao, self._ibo):
                if obj is not None:
                    obj.release()
            self._ibo_bytes = max(len(data), 2 * self._ibo_bytes, 4096)
            self._ibo = self.ctx.buffer(reserve=self._ibo_bytes)
            content = [(self._vbo, "3f 3f 1f 1f", "in_position", "in_normal", "in_height", "in_cos_slope")]
            if self._class_vbo is not None:
                content.append((self._class_vbo, "3f", "in_class"))
            self._vao = self.ctx.vertex_array(self.program, content, index_buffer=self._ibo, index_element_size=4)
        if data:
            self._ibo.write(data)
        self._index_count = indices.size

    def draw(self, frame: Frame) -> None:
        """Choose the levels for this frame's camera and viewport, rebuild the indices if they
        changed, draw (back faces culled)."""
        import moderngl

        if self._vbo is None or self._generation != self.origin.generation:
            self._upload_vertices()
        t0 = time.perf_counter()
        sel = self.select(frame.camera, frame.width, frame.height)
        self.selection = sel
        t1 = time.perf_counter()
        key = (sel.level.tobytes(), sel.edges.tobytes(), sel.visible.tobytes())
        index_ms = 0.0
        if key != self._index_key:
            self.indices = self.build_indices(sel)
            self._upload_indices(self.indices)
            self._index_key = key
            index_ms = (time.perf_counter() - t1) * 1e3
        drawn = sel.visible
        self.stats = GeomipmapStats(
            patches=int(sel.level.size), patches_drawn=int(drawn.sum()), patches_culled=int((~drawn).sum()),
            patches_per_lod=tuple(int(c) for c in np.bincount(sel.level[drawn], minlength=self.levels)),
            triangles=int(len(self.indices)), vertices=int(self.positions_ecef.shape[0]),
            max_error_px=float(sel.projected_px[drawn].max()) if drawn.any() else 0.0,
            select_ms=(t1 - t0) * 1e3, index_ms=index_ms)
        if self._index_count == 0:
            return
        frame.write_common(self.program)
        values = {"u_rot": self.origin.basis.T.astype("f4").tobytes(),
                  "u_origin_mod": np.mod(self.origin.ecef, DETAIL_TILE_M).astype("f4").tobytes()}
        for name, value in values.items():
            member = self.program.get(name, None)
            if member is not None:
                member.write(value)
        if self._detail is not None:
            self.program["u_detail_strength"].value = self.detail_strength
            self.program["u_detail"].value = 0
            self._detail.use(0)
        self.ctx.enable(moderngl.CULL_FACE)
        self._vao.render(moderngl.TRIANGLES, vertices=self._index_count)
        self.ctx.disable(moderngl.CULL_FACE)

    def _class_colours(self) -> np.ndarray:
        """(vertices, 3) float64 0-1 land-class colour of each vertex's post: terrain.texture's
        class_map of the inset's posts, as the clipmap classifies its normal texels
        (client/render/clipmap.py classes_of: the height, the slope, band noise placed by world
        position), over the whole lattice (beaches look along rows and columns). The slope is
        the DEM's (:meth:`_dem_slope_deg`), not the synthetic detail's: the classes' slope bins
        (12, 25, 38 degrees) are for real landforms, and the detail's metre-scale slopes would
        turn a flat field into a mottle of grass, forest and rock where the clipmap beside it,
        classifying at its own posts, draws farmland."""
        from terrain.texture import CLASS_COLOURS_RGB, class_map, noise_positions

        inset = self.inset
        rows, cols = inset.shape
        g = inset.georef
        r, c = self.vertex_lattice_index(np.arange(self.positions_ecef.shape[0])).T
        slope = self._dem_slope_deg()
        if slope is None:  # not aligned with the DEM: the inset's own normals
            cos_slope = np.ones((rows, cols))
            cos_slope[r, c] = self.cos_slope
            slope = np.degrees(np.arccos(np.clip(cos_slope, -1.0, 1.0)))
        lat = g.y0 + np.arange(rows) * g.dy
        lon = g.x0 + np.arange(cols) * g.dx
        spacing_e, spacing_n = inset.spacing_m
        # The class noise at each post's ECEF position, as the clipmap and `sortie terrain texture`
        # place it (no seam at the antimeridian).
        classes = class_map(np.asarray(inset.heights, np.float64), slope, spacing_e, spacing_n, lat[:, None],
                            noise_xyz_m=noise_positions(lat[:, None], lon[None, :]))
        return np.asarray(CLASS_COLOURS_RGB, np.float64)[classes[r, c]] / 255.0

    def _dem_slope_deg(self) -> np.ndarray | None:
        """(rows, cols) slope (degrees) of the DEM beneath at every inset post, or None when the
        lattice is not the DEM's refined (terrain/inset.py). The detail is 0 at the DEM's posts,
        so the inset's posts there are the DEM's; their central differences (as the clipmap's
        normals, from the terrain's gradient) are interpolated bilinearly to every post."""
        inset = self.inset
        base, (ky, kx) = inset.base, inset.refine
        sy, sx = 1 << ky, 1 << kx
        g = inset.georef
        if not base.exact or (sy == 1 and sx == 1):
            return None
        r0 = -round((g.y0 - base.lat0) / g.dy) % sy  # the first inset row on a DEM row
        c0 = -round((g.x0 - base.lon0) / g.dx) % sx
        h = np.asarray(inset.heights, np.float64)[r0::sy, c0::sx]
        if min(h.shape) < 2:
            return None
        spacing_e, spacing_n = inset.spacing_m
        dn, de = np.gradient(h, spacing_n * sy, spacing_e * sx)
        slope = np.degrees(np.arctan(np.hypot(de, dn)))
        rows, cols = inset.shape

        def along(a, first, step, size, axis):
            f = np.clip((np.arange(size) - first) / step, 0.0, a.shape[axis] - 1.0)
            i = np.minimum(f.astype(np.intp), a.shape[axis] - 2)
            t = np.expand_dims(f - i, 1 - axis)
            return np.take(a, i, axis=axis) * (1.0 - t) + np.take(a, i + 1, axis=axis) * t

        return along(along(slope, r0, sy, rows, 0), c0, sx, cols, 1)

    def release(self) -> None:
        for obj in (self._vao, self._ibo, self._vbo, self.program, self._detail, self._class_vbo):
            if obj is not None:
                obj.release()
        self._vao = self._ibo = self._vbo = self.program = self._detail = self._class_vbo = None
