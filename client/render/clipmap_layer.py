"""The geometry clipmap as a terrain layer of the renderer (client/render/renderer.py).

Data: client/render/clipmap.py (levels, regions, toroidal storage, budget).
Here: each level's storage as GPU textures (positions + heights RGBA32F,
n x n; normals RGBA16F, 2n x 2n, wrapping), updated with only the uploaded
pieces, and one vertex shader that displaces a small grid block per instance
(thesis §3.2.1: pure vertex-shader displacement):

- **Blocks.** A level's render region (its drawn rectangle minus the finer
  level's, client/render/clipmap.ring_rects: the thesis' index regions) is
  tiled by BLOCK x BLOCK-cell blocks; one static (BLOCK + 1)^2 vertex grid is
  drawn once per visible block (instancing), each vertex clamped to its
  block's rectangle (cells beyond it collapse to nothing).
- **Decimation** (screen-space error, as geomipmapping and Losasso-Hoppe bound it). With
  a ``pixel_error``, a block is drawn with every 4th or 2nd post inside (:func:`decimated_grid`)
  where the largest distance between the level's surface and that mesh's
  (:func:`decimation_errors`: exact, over the vertices of the two meshes' overlay), seen from
  the nearest point of the block's culling box, moves it by at most ``pixel_error`` pixels
  (:func:`block_strides`). Two whole neighbouring blocks draw their shared edge with the
  coarsest stride both allow within the bound (:func:`edge_strides`, decided once a pair:
  no T-junction); a side on the level's drawn border takes the coarser level's posts
  (:func:`border_edges`); other edges keep every post, so the finer level's border and the
  morph band meet as without decimation. A block a ring's edge cuts short is decimated as the
  clamp draws it (:func:`clamped_triangles`). Before a whole block takes its next coarser
  stride, the posts that stride drops morph towards where its mesh draws them (``in_morph``,
  per block; ``in_m0..2``/``in_mw``, :func:`morph_targets`), within the same pixel bound:
  inside the block the switch is seamless; in its edge cells (fans in the coarser mesh) a
  residual pop remains (measured on the Alps: median half the coarser stride's error, at most
  about twice it), and an edge's change of stride pops by at most the bound. Every block mesh
  (VARIANTS) is in one index buffer, and a level is one multi-draw.
- **Culling** (§3.1.6). A block is drawn unless its bounding box lies wholly
  outside one side of the view frustum or behind the camera (the box's 8
  corners against the clip-space planes, every block at once in numpy). The
  box is the local-ENU box of every post the block's vertices can take: its
  own posts and, when it morphs, the coarser level's posts under it (a
  morphed vertex is an average of those), so it holds every vertex for any
  alpha, whatever the curvature; computed when the level's or the coarser
  level's storage changes, not every frame. (The first version padded the
  corner posts by the level's whole height range: every block of a mountain
  level was kilometres taller and wider than its ground.)
- **Geomorphing** (§3.1.5, §3.2.1, §3.2.2). Each vertex also fetches the
  coarser level's posts around it — the post itself (even, even), the two
  ends of its coarse edge (one index odd) or the four corners of its coarse
  cell (both odd): the thesis' vertex cases — and morphs to their average by
  alpha = clamp(alpha_b + alpha_h, 0, 1). alpha_b ramps from 0 to 1 over w =
  n / 10 cells as the vertex's distance from the viewer (in the level's
  cells, the larger axis) grows to (n - 1) / 2 - 1, as the thesis measures it,
  so it moves continuously with the viewer (measuring it from the region's
  edge, which jumps 2 posts when the region moves, popped vertices by up to
  2/w of |z - z_c|: 19-34 m per frame at 300 m/s, found by the bench). On the
  drawn border alpha is 1 (the border vertices are the coarser level's, bit
  for bit). A level that lags behind (its region is not centred on the
  viewer, so distances from the viewer mean nothing to it) ramps from its
  drawn border instead, and is cropped at least w + 2 cells inside the
  coarser level (outside the coarser level's own morph band, whose start
  varies by the 2-cell snapping of regions): no cracks. alpha_h fades a level whose extent is small against the
  viewer's height above the ground (:func:`height_alpha`) before it stops
  being drawn: no popping; the finest level from the ground up (the thesis'
  n = n_max case), the others from where the finer level is gone (HEIGHT_FADE
  says why). Normals are blended by the same alpha.
- **Narrow views** (a zoomed view, a targeting pod's). Centred on the viewer, level k holds the
  ground out to about (n - 1) / 2 x its spacing, so a post there is about 2 f / (n - 1) pixels
  apart on screen at every level, f the focal length in pixels: the profiles are sized for their
  ``design_fov_deg`` (60 degrees, sortie render's default). A view of field of view F magnifies by
  Z = tan(design / 2) / tan(F / 2): centred on the viewer, its posts are Z times as many pixels
  apart (at 1 degree, Z = 66: the screen error was 30 px median where the reference mesh has 1.2).
  So a view narrower than the design is centred on the point w = 1 - 1/Z of the way from the focus
  to the ground point its axis looks at (:meth:`ClipmapLayer.aim_point`: the axis' first hit of
  the levels' surface; where it has none, the ground point nearest the axis in angle within the
  horizon, if that lies in the frame). That point at distance D lies D / Z from the centre, in a
  level whose posts are as many pixels apart as a viewer-centred view at the design field of view
  draws them at D: the design's density (at most the finest level's), and w = 0 at the design
  field of view, so the centre moves continuously as a view zooms in, and wider views are centred
  as before. The height fade (alpha_h, §3.2.2) takes h / Z: from the same height a zoomed view
  sees a level's posts Z times as far apart, as if the levels were log2 Z levels finer. Ground
  much nearer than the aimed point (a ridge across the foreground of a narrow view) is drawn by
  coarser levels than the design's: one clipmap is dense round one point.
- **Precision** (global-terrain-flight-sim §6). Positions are float32 offsets
  from each level's float64 origin; the shader adds the float32 of (level
  origin - renderer origin) in local ENU and rotates the offset by the
  renderer's ENU basis: a vertex's error relative to the camera scales with
  its level's extent, not with the distance to any global origin.
- **Insets** (thesis §3.3.1; terrain/inset.py, client/render/geomipmap.py). Under a
  target area's polygon the geomipmap inset is the terrain; the clipmap there is
  only a backstop. Its posts are lowered by the inset's cut-out, but a level can
  lower only posts at least a cell diagonal inside the polygon (so no triangle
  dents the ground outside), which leaves coarse levels over a small area, and
  every level along the border, at the DEM's height or above the inset's
  troughs. So blocks whose posts' (lat, lon) box meets an inset's polygon box
  are drawn by a variant (``#define INSETS``) that samples each inset's
  coverage mask (terrain/inset.py CoverageMask, one layer a polygon of an R32F
  texture array) at the fragment's lattice position (``v_lattice``: neither
  morph moves a vertex off its post's (lat, lon), so the position is exact, and
  the mask's coordinates are linear in it, :func:`inset_map`); a fragment surely
  inside (mask > 0) writes its depth 2^20 times farther (INSET_BACKSTOP_DEPTH_SCALE).
  It loses the depth test to the inset, at every level and however deep the
  inset's troughs, and to whatever the inset lets the viewer see past it, yet
  fills a pixel nothing else covers (as the continuous clipmap did). A per-
  fragment test, not a discard: discarding would open a crack wherever the
  clipmap at the border stands above the inset. Writing gl_FragDepth costs
  those blocks the early depth test (declared ``depth_less``, which a GPU may
  use; llvmpipe does not), so only blocks near an inset pay it. Within the mask's
  margin of the border (e <= 10 m at 512 texels over a 3 km area; always less
  than a0, where the inset's detail starts) both surfaces are the DEM: the
  inset is drawn 6e-5 of its distance nearer (geomipmap.INSET_DEPTH_SCALE), so
  a tie goes to it and the clipmap wins only where its own triangles stand
  above the DEM's bilinear surface, and both shade alike (DETAIL_GLSL).

Shading: the reference terrain's colour and lighting
(terrain_mesh.TERRAIN_COLOUR_GLSL), with the normal from the normal maps,
then detail textures under masks (thesis §3.2.3): DETAIL_PERIODS_M tilings of
a tileable noise texture (four independent patterns in its channels, made
once by :func:`detail_texture`, mipmapped so distant tiles average out),
planar-projected along the three ECEF axes and blended by the normal's
components (so steep faces take the projection across them, not a smear
along them), masked by height and slope (grass below the tint's mid height,
rock on slopes past ROCK_SLOPE_DEG, snow high up) and combined as
C_n = C_(n-1) (1 - M_n + 2 M_n Cd_n): the "modulate 2x" blend the thesis'
formula describes (a detail texture of mean 1/2 leaves the mean colour as it
is; the thesis' printed form, 2 C M Cd + (1 - M) / 2, would grey out unmasked
ground, which is not what its text or figure describe). Texture coordinates
are the ECEF position modulo DETAIL_TILE_M (the renderer origin's float64
ECEF reduced on the CPU, plus the fragment's float32 offset), so they do not
move when the origin is rebased.
"""

from __future__ import annotations

import functools
import itertools
import math
import os
import time
from dataclasses import dataclass

import numba
import numpy as np

from client.render.camera import DEFAULT_FOV_X_DEG, FOV_X_RANGE_DEG, Camera, LocalOrigin
from client.render.clipmap import (Clipmap, Rect, active_origin, blocks, clip_region, drawn_regions, globe_levels,
                                   ring_rects)
from client.render.gl import check_gl_error
from client.render.shading import GLSL_COMMON, Frame
from client.render.terrain_mesh import (DEFAULT_HORIZON_M, DEFAULT_WINDOW_M, REBUILD_FRACTION, TERRAIN_COLOUR_GLSL,
                                        TerrainMeshLayer, cell_corner_weights, lattice_for)
from terrain.texture import CLASS_COLOURS_RGB, N_CLASSES
from sortie.errors import InvalidArgument
from terrain.geodesy import WGS84_A_M, ecef_to_geodetic, enu_basis, geodetic_to_ecef
from terrain.threads import cpu_count, map_shared

BLOCK = 8  # cells a side of an instanced block
MORPH_WIDTH_FRACTION = 0.1  # w = n / 10 (thesis §3.1.5)
# Level clipping by height (§3.2.2): a level fades out as the viewer's height above the ground
# grows from HEIGHT_FADE[0] to HEIGHT_FADE[1] times the level's edge (its clip region's longer side,
# ClipmapLayer.edge_m), then is not drawn. The finest level fades from the ground up, as the
# thesis' n = n_max case has it: alpha_h = h / (FINEST_HEIGHT_FADE edge(n)). The other levels depart
# from the thesis' h / (0.4 edge(n + 1) - 1), a ramp from the ground as wide as ours (0.4 of the
# finer level's edge is 0.2 of the level's own): a level's drawn border is the coarser level's posts
# (alpha 1 there), so a level that morphed while the finer one inside it is still drawn would part
# from that border (cracks). Ours starts where the finer level is gone (its HEIGHT_FADE[1] x its
# edge, half the level's: HEIGHT_FADE[0] x the level's), and so does the finest's end.
HEIGHT_FADE = (0.2, 0.4)
FINEST_HEIGHT_FADE = 0.4  # thesis §3.2.2, n = n_max; at most 2 HEIGHT_FADE[0] (no cracks, above)
# Near a pole the layer draws the reference mesh (terrain_mesh.TerrainMeshLayer) instead: a level is
# n x n posts of the lat/lon lattice, so east-west it spans cos(latitude) of its north-south
# metres, and at 89.99 degrees the coarsest level was a strip some metres wide with open sea
# beside it. It switches to the mesh where latitude has narrowed the clipmap's cells east-west to
# less than POLAR_ASPECT of their north-south size (not a clipmap made small on purpose) and it
# would reach less far (its fog range at the focus) than the mesh does; it switches back where
# both are POLAR_MESH_HYSTERESIS times over those bounds (no flapping on the boundary). With the
# default mesh (+-80 km) and fast_jet on a 3" DEM: poleward of about 78 degrees, back equatorward
# of about 75.
POLAR_ASPECT = 0.25
POLAR_MESH_HYSTERESIS = 1.25
# Narrow views ("Narrow views" in the module docstring): the point the view's axis looks at is
# found by marching AIM_SAMPLES points along it, geometrically spaced from AIM_MIN_M out to the
# far side of the coarsest level (1.4 % of the distance apart over 1 m - 1000 km; the first hit is
# then placed on the levels' surface between two of them). A narrow view's first load is aimed
# again from the levels it loaded, at most AIM_FIRST_LOAD_PASSES times (a single frame, sortie
# render, is drawn aimed).
AIM_SAMPLES = 1024
AIM_MIN_M = 1.0
AIM_FIRST_LOAD_PASSES = 3
E2_COMPLEMENT_INV = 1.0 / (1.0 - 6.69437999014e-3)  # 1 / (1 - e^2), WGS84: geodetic normal from ECEF
DETAIL_TILE_M = 1024.0  # texture coordinates are ECEF modulo this; every period below divides it
DETAIL_PERIODS_M = (128.0, 32.0, 8.0)  # the detail tilings, coarse to fine
DETAIL_TEXTURE_SIZE = 256
DETAIL_STRENGTH = 0.3  # 0: no detail; the masks' weight scale
# A border triangle's fragments lie 1e-5 of their distance behind its provoking vertex
# (reversed-Z: depth near/d), so where a level's own surface is drawn too it wins.
BORDER_DEPTH_SCALE = 1.0 - 1e-5
# A fragment under a target area's inset (terrain/inset.py CoverageMask) lies 2^20 times farther
# than it is (reversed-Z: depth near/d): it loses the depth test to the inset, and to anything
# the inset's own surface lets the viewer see past its troughs, yet still fills a pixel nothing
# else covers.
INSET_BACKSTOP_DEPTH_SCALE = 2.0 ** -20
CLASS_COLOURS_F32 = (np.asarray(CLASS_COLOURS_RGB, np.float32) / 255.0).tobytes()  # the u_class_colour uniform

# a mod m in [0, m) for any int a and m > 0, in integers only. GLSL's % is defined for
# non-negative operands alone (GLSL 3.30 §5.9), hence the mirror for negative a. A float form,
# a - m floor(a / m), is wrong twice: beyond 2^24 float(a) rounds, and GPUs divide as a x rcp(m)
# with an ulp or two of error, so at exact multiples of m floor() can land one below, on texel m
# (out of range, fetched as 0). On an NVIDIA H200 every n = 255 setting drew spikes (screen error
# p99 46 px where llvmpipe's exact division gave 1.7 px) until this integer form
# (docs/BENCHMARKS.md).
GLSL_PMOD = "int pmod(int a, int m) { return a >= 0 ? a % m : m - 1 - (-1 - a) % m; }"

VERTEX_SHADER = """#version 330 core
uniform sampler2D u_fine;        // level k: offset from its origin (ECEF axes) + height MSL
uniform sampler2D u_coarse;      // level k + 1
uniform int u_n;
uniform ivec2 u_base;            // lattice index (i, j) of block coordinates (0, 0)
uniform mat3 u_rot;              // ECEF axes -> local ENU
uniform vec3 u_off_fine;         // level k origin - renderer origin, local ENU
uniform vec3 u_off_coarse;
uniform vec3 u_origin_ecef;      // renderer origin (ECEF, float32: for directions only)
uniform vec4 u_region;           // drawn region (i0, j0, i1, j1), relative to u_base
uniform float u_w;               // morph width, cells
uniform vec2 u_viewer;           // the focus in this level's lattice, relative to u_base
uniform float u_half;            // (n - 1) / 2 - 1: viewer distance (cells) where alpha_b reaches 1
uniform int u_lagging;           // the level is not on its active region (it fell behind)
uniform float u_alpha_h;
uniform int u_has_coarse;
uniform mat4 u_view;
uniform mat4 u_projection;
in ivec2 in_cell;                // (row, column) in the block grid, 0..BLOCK
in ivec4 in_block;               // (i0, j0, i1, j1) posts, relative to u_base
in float in_morph;               // decimation morph of the block (block_strides); 0 where not bound
in ivec2 in_m0;                  // where the block's next coarser stride draws this post: the
in ivec2 in_m1;                  // corners (block grid) of its triangle there and their weights
in ivec2 in_m2;                  // (grid_weights); in_mw.x = 1 where that stride keeps the post
in vec3 in_mw;
VARYING out vec3 v_world;
VARYING out float v_height;
VARYING out vec2 v_nuv_fine;
VARYING out vec2 v_nuv_coarse;
VARYING out float v_alpha;
VARYING out vec3 v_up;
VARYING out vec3 v_ecef_mod;
#ifdef BORDER
flat out float v_depth;          // the provoking vertex's window depth
#endif
#ifdef INSETS
VARYING out vec2 v_lattice;      // the post's lattice index relative to u_base (the inset masks' coordinates)
#endif
uniform vec3 u_origin_mod;       // renderer origin ECEF modulo the detail tile, metres

%(PMOD)s
vec4 post(sampler2D t, ivec2 ij) { return texelFetch(t, ivec2(pmod(ij.y, u_n), pmod(ij.x, u_n)), 0); }

// Level k's surface at block-relative post g: its own post morphed towards the coarser level's
// surface by alpha (the thesis' vertex cases).
void surface(ivec2 g, out vec3 world, out float height, out float alpha) {
    ivec2 G = u_base + g;
    vec4 f = post(u_fine, G);
    vec3 p = u_rot * f.xyz + u_off_fine;
    float h = f.w;
    alpha = 0.0;
    vec3 pc = p;
    float hc = h;
    if (u_has_coarse != 0) {
        vec2 d2 = min(vec2(g) - u_region.xy, u_region.zw - vec2(g));
        float d = min(d2.x, d2.y);
        // alpha_b follows the viewer continuously (thesis 3.1.5), so a region move does not
        // step it; it is 1 on the drawn border, and a cropped level also ramps from that border.
        vec2 dv = abs(vec2(g) - u_viewer);
        float a_b = clamp((max(dv.x, dv.y) - (u_half - u_w)) / u_w, 0.0, 1.0);
        float a_edge = clamp((u_w + 1.0 - d) / u_w, 0.0, 1.0);
        a_b = u_lagging != 0 ? a_edge : (d <= 0.0 ? 1.0 : a_b);
        alpha = clamp(a_b + u_alpha_h, 0.0, 1.0);
        ivec2 odd = G & 1;
        ivec2 c = (G - odd) / 2;  // the coarse post at or south-west of this one
        vec4 s = post(u_coarse, c);
        if (odd.x == 1) s += post(u_coarse, c + ivec2(1, 0));
        if (odd.y == 1) s += post(u_coarse, c + ivec2(0, 1));
        if (odd.x == 1 && odd.y == 1) s += post(u_coarse, c + ivec2(1, 1));
        s /= float((1 + odd.x) * (1 + odd.y));
        pc = u_rot * s.xyz + u_off_coarse;
        hc = s.w;
    }
    world = alpha >= 1.0 ? pc : mix(p, pc, alpha);  // exactly the coarse vertex on the border
    height = alpha >= 1.0 ? hc : mix(h, hc, alpha);
}

void main() {
    ivec2 g = clamp(in_block.xy + in_cell, in_block.xy, in_block.zw);
    float alpha;
    surface(g, v_world, v_height, alpha);
    if (in_morph > 0.0 && in_mw.x < 1.0) {
        // A post the block's next coarser stride drops moves towards where that stride's mesh
        // draws it, so the block's switch of stride pops only in its edge cells, whose fans in
        // the coarser mesh do not nest over the finer cells. (A block cut short has morph 0:
        // block_strides.)
        vec3 w0, w1, w2;
        float h0, h1, h2, a0, a1, a2;
        surface(in_block.xy + in_m0, w0, h0, a0);
        surface(in_block.xy + in_m1, w1, h1, a1);
        surface(in_block.xy + in_m2, w2, h2, a2);
        v_world = mix(v_world, in_mw.x * w0 + in_mw.y * w1 + in_mw.z * w2, in_morph);
        v_height = mix(v_height, in_mw.x * h0 + in_mw.y * h1 + in_mw.z * h2, in_morph);
    }
    v_alpha = alpha;
#ifdef INSETS
    // Neither morph moves a vertex off its post's (lat, lon): an odd post's coarse target is the
    // mean of posts on either side of it, a decimated post's a barycentric mean (in_mw) of posts
    // around it, and both are linear in the lattice index.
    v_lattice = vec2(g);
#endif
    // Normal-map coordinates: the fine map has 2 texels a post, the coarse map 1 (its half-posts).
    int n2 = 2 * u_n;
    vec2 hf = vec2(float(2 * g.y + pmod(2 * u_base.y, n2)), float(2 * g.x + pmod(2 * u_base.x, n2)));
    v_nuv_fine = (hf + 0.5) / float(n2);
    vec2 hc2 = vec2(float(g.y + pmod(u_base.y, n2)), float(g.x + pmod(u_base.x, n2)));
    v_nuv_coarse = (hc2 + 0.5) / float(n2);
    vec3 e = u_origin_ecef + transpose(u_rot) * v_world;
    v_ecef_mod = u_origin_mod + transpose(u_rot) * v_world;
    v_up = u_rot * normalize(vec3(e.x, e.y, e.z * %(E2)r));
    gl_Position = u_projection * (u_view * vec4(v_world, 1.0));
#ifdef BORDER
    v_depth = gl_Position.z / gl_Position.w;  // reversed-Z, NDC depth [0, 1] is the window depth
#endif
}
""" % {"E2": E2_COMPLEMENT_INV, "PMOD": GLSL_PMOD}

# The detail textures (thesis §3.2.3, module docstring) on a lit colour: shared by every layer drawn
# beside the clipmap (client/render/geomipmap.py's insets), so their surfaces shade alike.
# ne: the unit normal in ECEF axes; ecef_mod: the point's ECEF position modulo DETAIL_TILE_M.
DETAIL_GLSL = """
uniform sampler2D u_detail;      // four tileable noise patterns, mean 1/2
uniform float u_detail_strength;
const vec3 PERIODS = vec3%(PERIODS)s;

vec4 planar(vec3 p, vec3 w, float period) {  // three planar projections along the ECEF axes
    return w.x * texture(u_detail, p.yz / period) + w.y * texture(u_detail, p.zx / period)
         + w.z * texture(u_detail, p.xy / period);
}

vec3 detailed(vec3 c, vec3 ne, float cos_slope, float height, vec3 ecef_mod) {
    if (u_detail_strength > 0.0 && height > u_water_level) {  // land only (water: terrain_colour)
        vec3 w = ne * ne;
        w *= w;  // |ne|^4, without pow (three exp2/log2 a fragment on llvmpipe)
        w /= (w.x + w.y + w.z);
        float rock = smoothstep(ROCK_COS_START, ROCK_COS_FULL, cos_slope);
        float snow = smoothstep(0.8 * HIGH_M, HIGH_M, height) * (1.0 - rock);
        float grass = (1.0 - smoothstep(0.5 * MID_M, MID_M, height)) * (1.0 - rock);
        vec4 masks = u_detail_strength * vec4(grass, rock, snow, 0.5);  // the last: every surface, lightly
        for (int k = 0; k < 3; k++) {
            vec4 f = 1.0 - masks + 2.0 * masks * planar(ecef_mod, w, PERIODS[k]);
            c *= f.x * f.y * f.z * f.w;  // C_n = C_(n-1) (1 - M + 2 M Cd) per mask (thesis §3.2.3)
        }
    }
    return c;
}
""" % {"PERIODS": str(DETAIL_PERIODS_M)}

FRAGMENT_SHADER = "#version 330 core\n" + GLSL_COMMON + TERRAIN_COLOUR_GLSL + DETAIL_GLSL + """
uniform sampler2D u_nfine;
uniform sampler2D u_ncoarse;
uniform mat3 u_rot;
uniform int u_has_coarse;
#ifdef CLASSES
uniform vec3 u_class_colour[%(N_CLASSES)d];  // land classes in the normal maps' fourth channel (terrain/texture.py)
#endif
VARYING in vec3 v_world;
VARYING in float v_height;
VARYING in vec2 v_nuv_fine;
VARYING in vec2 v_nuv_coarse;
VARYING in float v_alpha;
VARYING in vec3 v_up;
VARYING in vec3 v_ecef_mod;
#ifdef BORDER
flat in float v_depth;
#endif
out vec4 out_colour;

#ifdef INSETS
// Each inset's polygon (terrain/inset.py CoverageMask: signed distance less a margin, metres) in
// one layer; per level draw the insets near its blocks, each with its texture coordinates as
// linear functions of v_lattice: u = map.x * v_lattice.y + map.y, v = map.z * v_lattice.x + map.w.
uniform sampler2DArray u_inset_mask;
uniform int u_inset_count;
uniform int u_inset_layer[INSETS];
uniform vec4 u_inset_map[INSETS];
VARYING in vec2 v_lattice;

bool under_inset() {
    float s = -1.0;
    for (int i = 0; i < u_inset_count; i++) {
        vec4 m = u_inset_map[i];
        vec2 uv = vec2(m.x * v_lattice.y + m.y, m.z * v_lattice.x + m.w);
        s = max(s, texture(u_inset_mask, vec3(uv, float(u_inset_layer[i]))).r);
    }
    return s > 0.0;
}
#endif

#ifdef CLASSES
%(PMOD)s

vec3 class_at(sampler2D t, ivec2 ij, int n2) {
    ivec2 w = ivec2(pmod(ij.x, n2), pmod(ij.y, n2));
    return u_class_colour[clamp(int(texelFetch(t, w, 0).w + 0.5), 0, %(N_CLASSES)d - 1)];
}

vec3 class_colour(sampler2D t, vec2 uv) {
    int n2 = textureSize(t, 0).x;
    vec2 x = uv * float(n2) - 0.5;
    ivec2 i = ivec2(floor(x));
    vec2 f = x - floor(x);
    return mix(mix(class_at(t, i, n2), class_at(t, i + ivec2(1, 0), n2), f.x),
               mix(class_at(t, i + ivec2(0, 1), n2), class_at(t, i + ivec2(1, 1), n2), f.x), f.y);
}
#endif

void main() {
    vec3 ne = texture(u_nfine, v_nuv_fine).xyz;
    if (u_has_coarse != 0) ne = mix(ne, texture(u_ncoarse, v_nuv_coarse).xyz, v_alpha);
    ne = normalize(ne);
    vec3 n = u_rot * ne;
    float cos_slope = dot(n, normalize(v_up));
    vec3 c = terrain_colour(v_world, n, v_height, cos_slope);
#ifdef CLASSES
    if (v_height > u_water_level) {
        // The land-class map is the base colour (FSX §7.1, §7.2): the colours of the four
        // nearest normal texels' classes, blended bilinearly (classes themselves do not
        // interpolate), fine and coarse blended by the morph.
        vec3 base = class_colour(u_nfine, v_nuv_fine);
        if (u_has_coarse != 0) base = mix(base, class_colour(u_ncoarse, v_nuv_coarse), v_alpha);
        c = fogged(lambert(base, n), v_world);
    }
#endif
    out_colour = vec4(detailed(c, ne, cos_slope, v_height, v_ecef_mod), 1.0);
#ifdef BORDER
    float depth = v_depth * BORDER_DEPTH_SCALE;
#else
    float depth = gl_FragCoord.z;
#endif
#ifdef INSETS
    // Under an inset's polygon the clipmap is only a backstop: pushed far behind, it shows where
    // nothing else is drawn (module docstring, "Insets").
    if (under_inset()) depth *= INSET_BACKSTOP_DEPTH_SCALE;
#endif
#if defined(BORDER) || defined(INSETS)
    gl_FragDepth = depth;
#endif
}
""" % {"N_CLASSES": N_CLASSES, "PMOD": GLSL_PMOD}


def shader_variant(source: str, border: bool, classes: bool = False, insets: int = 0) -> str:
    """The clipmap's shader source for the level draws, or (border) for the zero-area border
    triangles: their varyings flat (the provoking vertex's, the border's odd post) and their
    depth that vertex's, a hair farther (BORDER_DEPTH_SCALE). A zero-area triangle's plane
    equations are ill-conditioned: interpolated, its few covered pixels took depths and
    attributes from anywhere (screen errors of thousands of pixels on llvmpipe).

    ``classes``: with the land-class base colour (``#define CLASSES``). A feature is left out
    of the source, not switched off by a uniform: llvmpipe runs both sides of every branch
    under execution masks, so the unused class code cost 14-20 ms a 960 x 540 frame.

    ``insets``: the number of target-area insets the layer was made with; > 0 compiles in the
    test that pushes a fragment under an inset's polygon far behind (``#define INSETS``). It
    writes gl_FragDepth, which costs the early depth test: only blocks near an inset are drawn
    with it (ClipmapLayer.plan)."""
    head, rest = source.split("\n", 1)
    defines = ("#define BORDER\n#define VARYING flat\n#define BORDER_DEPTH_SCALE %r\n" % BORDER_DEPTH_SCALE
               if border else "#define VARYING\n") + ("#define CLASSES\n" if classes else "")
    if insets:
        defines += "#define INSETS %d\n#define INSET_BACKSTOP_DEPTH_SCALE %r\n" % (insets, INSET_BACKSTOP_DEPTH_SCALE)
        if not border and "gl_FragDepth" in rest:
            defines += "#extension GL_ARB_conservative_depth : enable\nlayout(depth_less) out float gl_FragDepth;\n"
    return head + "\n" + defines + rest


def detail_texture(size: int = DETAIL_TEXTURE_SIZE, seed: int = 7) -> np.ndarray:
    """(size, size, 4) uint8 tileable fractal noise, one pattern per channel, mean ~128: sums of
    random-phase sinusoids on the torus's integer frequencies (tileable by construction) with a
    1/f amplitude falloff, normalised to [16, 240]."""
    rng = np.random.default_rng(seed)
    y, x = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    out = np.zeros((size, size, 4))
    for ch in range(4):
        acc = np.zeros((size, size))
        for f in (2, 4, 8, 16, 32, 64):
            for _ in range(3):
                fx, fy = rng.integers(-f, f + 1, 2)
                if fx == 0 and fy == 0:
                    continue
                acc += np.cos(2 * np.pi * (fx * x + fy * y) / size + rng.uniform(0, 2 * np.pi)) / f
        acc = (acc - acc.min()) / (np.ptp(acc) or 1.0)
        out[..., ch] = 16 + 224 * acc
    return out.astype(np.uint8)


@functools.lru_cache(maxsize=1)
def _detail_texture_bytes() -> bytes:
    return detail_texture().tobytes()


def detail_texture_object(ctx):
    """The detail texture on ``ctx`` (current): repeating, mipmapped (distant tiles average out).
    Every layer that shades with DETAIL_GLSL binds one."""
    tex = ctx.texture((DETAIL_TEXTURE_SIZE, DETAIL_TEXTURE_SIZE), 4, _detail_texture_bytes())
    tex.repeat_x = tex.repeat_y = True
    tex.build_mipmaps()
    return tex


# The insets' polygons as one texture array (terrain/inset.py CoverageMask), this many bytes at
# most: with many target areas each mask gets fewer texels (and a wider margin).
INSET_MASK_BUDGET_BYTES = 64 << 20
INSET_MASK_UNIT = 5  # texture unit of the masks (0-4: the levels' storage and the detail texture)


@dataclass(frozen=True)
class InsetMask:
    """Where an inset's mask lies in the layer's texture array, and its polygon's plane:
    layer; x0, y0, texel_m (CoverageMask); size (width, height) of the array's layers;
    lat_ref, lon_ref, k_x, k_y (terrain/inset.py PolygonPlane); box: (lat_min, lat_max, lon_min,
    lon_max) of the polygon, longitudes unwrapped about lon_ref."""

    layer: int
    x0: float
    y0: float
    texel_m: float
    size: tuple
    lat_ref: float
    lon_ref: float
    k_x: float
    k_y: float
    box: tuple


def _inset_masks(ctx, insets) -> tuple[list, object, np.ndarray]:
    """([InsetMask], the R32F texture array (bilinear, clamped to its edges), (N, 4) boxes
    (lat_min, lat_max, lon_min, lon_max)) of ``insets``; every layer the size of the largest."""
    import moderngl

    # 512 texels a side, more where the polygon is so large that its surely-inside distance
    # (CoverageMask: e + t sqrt(2)) would pass a0, where the inset's detail starts; fewer when
    # the budget says so.
    from terrain.inset import COVERAGE_MASK_MARGIN_M, COVERAGE_MASK_MARGIN_TEXELS

    need = 16
    for inset in insets:
        texel = (inset.detail_offset_m - COVERAGE_MASK_MARGIN_M) / (COVERAGE_MASK_MARGIN_TEXELS + math.sqrt(2.0))
        extent = max(np.ptp(inset.plane.x), np.ptp(inset.plane.y))
        need = max(need, int(math.ceil(extent / max(texel, 1.0))) + 9)
    side = int(max(16, min(max(512, need), 2048, math.isqrt(INSET_MASK_BUDGET_BYTES // (4 * len(insets))))))
    masks = [inset.coverage_mask(side) for inset in insets]
    h = max(m.values.shape[0] for m in masks)
    w = max(m.values.shape[1] for m in masks)
    data = np.full((len(insets), h, w), np.float32(-1.0e6))  # padding: far outside
    out, boxes = [], []
    for k, (inset, m) in enumerate(zip(insets, masks)):
        data[k, :m.values.shape[0], :m.values.shape[1]] = m.values
        p = inset.plane
        lon_un = p.lon_ref + p.x / p.k_x
        box = (float(inset.polygon[:, 0].min()), float(inset.polygon[:, 0].max()), float(lon_un.min()),
               float(lon_un.max()))
        boxes.append(box)
        out.append(InsetMask(k, m.x0, m.y0, m.texel_m, (w, h), p.lat_ref, p.lon_ref, p.k_x, p.k_y, box))
    tex = ctx.texture_array((w, h, len(insets)), 1, data.tobytes(), dtype="f4")
    tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
    tex.repeat_x = tex.repeat_y = False
    return out, tex, np.array(boxes, np.float64).reshape(-1, 4)


def blocks_near_insets(blk: np.ndarray, boxes: np.ndarray, lat0: float, lon0: float, dlat: float,
                       dlon: float) -> np.ndarray:
    """(m, N) bool: block (i0, j0, i1, j1) (lattice posts of spacing dlat, dlon from lat0, lon0)
    overlaps inset box (lat_min, lat_max, lon_min, lon_max). A block's fragments lie within its
    posts' (lat, lon) box: the vertex morphs keep each post's (lat, lon)."""
    if len(blk) == 0 or len(boxes) == 0:
        return np.zeros((len(blk), len(boxes)), bool)
    b = blk.astype(np.float64)
    lat_a, lat_b = lat0 + b[:, 0, None] * dlat, lat0 + b[:, 2, None] * dlat
    lon_c = lon0 + 0.5 * (b[:, 1, None] + b[:, 3, None]) * dlon
    half = 0.5 * (b[:, 3, None] - b[:, 1, None]) * dlon
    box_c, box_half = 0.5 * (boxes[:, 2] + boxes[:, 3]), 0.5 * (boxes[:, 3] - boxes[:, 2])
    d_lon = np.abs((lon_c - box_c + 180.0) % 360.0 - 180.0)
    return (lat_a <= boxes[:, 1]) & (lat_b >= boxes[:, 0]) & (d_lon <= half + box_half)


def inset_map(m: InsetMask, lat0: float, lon0: float, dlat: float, dlon: float, half_span_deg: float) -> tuple:
    """(a_u, c_u, a_v, c_v): mask texture coordinates u = a_u j + c_u, v = a_v i + c_v of the
    post (i, j) of a lattice of spacing (dlat, dlon) from (lat0, lon0) (a level's drawn region
    from its first post), in float64; the shader's are float32. The longitude is unwrapped about
    the region's middle (half_span_deg east of lon0), so the part of the region near the polygon
    maps right wherever the antimeridian falls."""
    w, h = m.size
    mid = ((lon0 + half_span_deg - m.lon_ref + 180.0) % 360.0) - 180.0
    x_first = (mid - half_span_deg) * m.k_x
    y_first = (lat0 - m.lat_ref) * m.k_y
    a_u = dlon * m.k_x / (m.texel_m * w)
    c_u = ((x_first - m.x0) / m.texel_m + 0.5) / w
    a_v = dlat * m.k_y / (m.texel_m * h)
    c_v = ((y_first - m.y0) / m.texel_m + 0.5) / h
    return a_u, c_u, a_v, c_v


def height_alpha(height_above_ground_m: float, edge_m: float, finest: bool = False) -> float:
    """alpha_h of a level of this edge (thesis §3.2.2): linear between HEIGHT_FADE x edge; the
    finest level's (``finest``) h / (FINEST_HEIGHT_FADE x edge), from the ground up."""
    a, b = (0.0, FINEST_HEIGHT_FADE) if finest else HEIGHT_FADE
    return min(max((height_above_ground_m / edge_m - a) / (b - a), 0.0), 1.0)


def view_zoom(design_fov_deg: float, fov_deg: float) -> float:
    """Z = tan(design / 2) / tan(fov / 2), at least 1: how many times a view of horizontal field of
    view ``fov_deg`` magnifies over one of ``design_fov_deg`` at the same width (the ratio of their
    focal lengths in pixels, camera.Camera.focal)."""
    return max(1.0, math.tan(math.radians(0.5 * design_fov_deg)) / math.tan(math.radians(0.5 * fov_deg)))


def block_grid(size: int = BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """((size + 1)^2, 2) int32 (row, column) grid vertices and (2 size^2, 3) uint32 triangles,
    counter-clockwise seen from above (row = north, column = east)."""
    r, c = np.meshgrid(np.arange(size + 1), np.arange(size + 1), indexing="ij")
    verts = np.stack([r.ravel(), c.ravel()], -1).astype(np.int32)
    a = (r[:-1, :-1] * (size + 1) + c[:-1, :-1]).ravel()
    b, d, e = a + 1, a + size + 2, a + size + 1  # east, north-east, north
    tris = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, e], -1)]).astype(np.uint32)
    return verts, tris


# Decimation by screen-space error: a whole block (BLOCK x BLOCK cells) whose surface, drawn with
# every stride-th post inside a border of every post, stays within the layer's pixel_error of the
# level's own surface at the block's distance, is drawn so (DECIMATION_STRIDES, coarse to fine).
DECIMATION_STRIDES = (4, 2)


def edge_choices(stride: int, size: int = BLOCK) -> tuple:
    """The strides an edge of a ``stride`` block can take (:func:`decimated_grid`'s ``edges``):
    the divisors of the stride, and for a block of two cells a side (stride = size / 2, fanned from
    its centre) also the whole side, corner to corner."""
    out = tuple(e for e in (1, 2, 4, 8, 16, 32) if e <= stride and stride % e == 0)
    return out + ((size,) if stride > 1 and 2 * stride == size else ())


def decimated_grid(stride: int, size: int = BLOCK, edges: tuple = (1, 1, 1, 1)) -> np.ndarray:
    """(t, 3) uint32 triangles over :func:`block_grid`'s (size + 1)^2 vertices that draw the block
    with every ``stride``-th post inside and every ``edges``-th post on its four edges (south,
    east, north, west; each of :func:`edge_choices`), counter-clockwise seen from above. Inner
    cells of stride x stride posts split along the south-west to north-east diagonal, as the full
    grid's cells are; a cell on the block's edge is a convex polygon (its edge sides carry their
    edge's posts) fanned from its one corner on no edge of the block.

    With every edge 1 (the default) the edges are the full grid's whatever the stride, so blocks of
    any strides meet without a T-junction, and the level's borders (its morph to the coarser level,
    the finer level's border on it) are as without decimation. Two blocks that give their shared
    edge the same stride (``ClipmapLayer``: the lesser of theirs, where the error allows) meet so
    too, with fewer triangles: such a mesh is the all-1 mesh with some edge posts taken out of its
    fans, so it parts from it by at most how far those posts lie from the coarser edge
    (:func:`edge_deviations`). ``stride`` 1: the full grid."""
    if stride == 1:
        if any(e != 1 for e in edges):
            raise ValueError(f"edges {edges} of a stride-1 block must be 1")
        return block_grid(size)[1]
    m = size // stride
    if m * stride != size or m < 2:
        raise ValueError(f"stride {stride} must divide the block's {size} cells at least twice")
    if len(edges) != 4 or any(e not in edge_choices(stride, size) for e in edges):
        raise ValueError(f"edges {edges} must be four of {edge_choices(stride, size)} for stride {stride}")
    e_s, e_e, e_n, e_w = edges

    def idx(rc):
        return rc[0] * (size + 1) + rc[1]

    if m == 2:
        # Four corner cells, each fanned from the block's centre: one fan of the block's outline
        # around the centre, which lets an edge drop its middle post too (edge stride = size).
        outline = ([(0, c) for c in range(0, size, e_s)] + [(r, size) for r in range(0, size, e_e)]
                   + [(size, c) for c in range(size, 0, -e_n)] + [(r, 0) for r in range(size, 0, -e_w)])
        centre = (stride, stride)
        return np.array([(idx(centre), idx(p), idx(q)) for p, q in zip(outline, outline[1:] + outline[:1])],
                        np.uint32)
    tris = []
    for rr in range(m):
        for cc in range(m):
            r0, c0, r1, c1 = rr * stride, cc * stride, (rr + 1) * stride, (cc + 1) * stride
            south, north, west, east = rr == 0, rr == m - 1, cc == 0, cc == m - 1
            if not (south or north or west or east):
                a, b, d, e = idx((r0, c0)), idx((r0, c1)), idx((r1, c1)), idx((r1, c0))
                tris += [(a, b, d), (a, d, e)]
                continue
            # The cell's outline, counter-clockwise (x = column, y = row): its south side eastwards,
            # east side northwards, north side westwards, west side southwards; the edge's posts on
            # an edge side, the corners only on the others.
            ring = ([(r0, c) for c in (range(c0, c1, e_s) if south else (c0,))]
                    + [(r, c1) for r in (range(r0, r1, e_e) if east else (r0,))]
                    + [(r1, c) for c in (range(c1, c0, -e_n) if north else (c1,))]
                    + [(r, c0) for r in (range(r1, r0, -e_w) if west else (r1,))])
            # The apex: a corner on no edge side, on the cell's south-west to north-east diagonal
            # where one is (NE, then SW): its fan's long edge then runs along the fine cells'
            # diagonals instead of across them, so the two surfaces part less.
            on_edge = {(r1, c1): north or east, (r0, c0): south or west, (r0, c1): south or east,
                       (r1, c0): north or west}
            apex = ring.index(next(p for p, edge in on_edge.items() if not edge))
            ring = ring[apex:] + ring[:apex]
            tris += [(idx(ring[0]), idx(p), idx(q)) for p, q in zip(ring[1:-1], ring[2:])]
    return np.array(tris, np.uint32)


def grid_weights(tris: np.ndarray, size: int = BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """((V, 3) vertex indices, (V, 3) weights): each of the (size + 1)^2 grid vertices as the
    barycentric combination of the corners of a triangle of ``tris`` that holds it, so that
    ``(posts[idx] * w[..., None]).sum(1)`` is where the triangles draw each post."""
    verts = block_grid(size)[0].astype(np.float64)[:, ::-1]  # (x, y) = (column, row)
    return _weights_at(tris, verts, verts)


def _edges(tris: np.ndarray) -> np.ndarray:
    """(e, 2) unique undirected edges (vertex indices) of triangles."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def clamp_map(h: int, w: int, size: int = BLOCK) -> np.ndarray:
    """(V,) the block grid vertex each of the (size + 1)^2 vertices becomes in a block of h x w
    cells: (min(row, h), min(column, w)), as the vertex shader clamps a ring's cut-short blocks."""
    r, c = np.meshgrid(np.arange(size + 1), np.arange(size + 1), indexing="ij")
    return (np.minimum(r, h) * (size + 1) + np.minimum(c, w)).ravel()


def clamped_triangles(stride: int, h: int = BLOCK, w: int = BLOCK, size: int = BLOCK) -> np.ndarray:
    """(t, 3) the triangles of :func:`decimated_grid` that an h x w block draws after the clamp
    (:func:`clamp_map`), those whose three corners are three posts: the others collapse to a
    point or a segment and cover nothing. Some that remain have no area in plan: where the clamp
    lays a decimated inner column (row) onto the block's edge, triangles between it and the edge's
    every post stand upright and close the gap between the decimated side and the edge (what the
    zero-area border triangles do at a level's edge). What a block of a stride costs."""
    tris = clamp_map(h, w, size)[decimated_grid(stride, size)]
    distinct = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    return tris[distinct]


def _flat(tris: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Triangles of ``tris`` with area in plan."""
    a, b, c = (verts[tris[:, i]] for i in range(3))
    area = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    return tris[np.abs(area) > 1e-12]


def overlay_rows(stride: int, size: int = BLOCK, h: int | None = None, w: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((K, 6) vertex indices, (K, 6) weights) over the block grid: at each vertex of the overlay
    of the full grid's triangles and :func:`decimated_grid`'s (the posts, and every point where an
    edge of one crosses an edge of the other), the full surface minus the decimated one as a
    combination of posts (3 weights summing to 1, then 3 summing to -1). The two surfaces are
    linear on each cell of the overlay, so the largest distance between them is the largest
    norm of these combinations: at a post it is the post's own error, but where a decimated
    edge crosses a fine edge it can be several times that (measured on the Alps: up to 5x for
    stride 2 at 8-cell blocks, 1.4x at the 99th percentile).

    ``h``, ``w``: for a block cut short to h x w cells, both meshes as the clamp draws them
    (:func:`clamped_triangles`; the upright triangles, with no area in plan, lie between the two
    surfaces and are left out)."""
    h, w = size if h is None else h, size if w is None else w
    verts = block_grid(size)[0].astype(np.float64)[:, ::-1]  # (x, y) = (column, row)
    fine = _flat(clamped_triangles(1, h, w, size), verts)
    dec = _flat(clamped_triangles(stride, h, w, size), verts)
    pts = [verts[np.unique(fine)]]
    ef, ed = _edges(fine), _edges(dec)
    a, b = verts[ef[:, 0]][:, None], verts[ef[:, 1]][:, None]  # (F, 1, 2)
    c, d = verts[ed[:, 0]][None], verts[ed[:, 1]][None]  # (1, D, 2)
    r, q = b - a, d - c
    den = r[..., 0] * q[..., 1] - r[..., 1] * q[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c - a)[..., 0] * q[..., 1] - (c - a)[..., 1] * q[..., 0]) / den
        u = ((c - a)[..., 0] * r[..., 1] - (c - a)[..., 1] * r[..., 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 1e-9) & (t < 1 - 1e-9) & (u > 1e-9) & (u < 1 - 1e-9)
    pts.append((a + np.where(hit, t, 0.0)[..., None] * r)[hit])
    pts = np.unique(np.round(np.concatenate(pts), 9), axis=0)
    fi, fw = _weights_at(fine, verts, pts)
    di, dw = _weights_at(dec, verts, pts)
    return np.concatenate([fi, di], 1), np.concatenate([fw, -dw], 1)


def _weights_at(tris: np.ndarray, verts: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((P, 3) vertex indices, (P, 3) barycentric weights) of points (P, 2) in triangles holding them."""
    a, b, c = (verts[tris[:, i]] for i in range(3))
    p = pts[:, None, :]
    det = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    wb = ((p - a)[..., 0] * (c - a)[:, 1] - (p - a)[..., 1] * (c - a)[:, 0]) / det
    wc = ((b - a)[:, 0] * (p - a)[..., 1] - (b - a)[:, 1] * (p - a)[..., 0]) / det
    w = np.stack([1.0 - wb - wc, wb, wc], -1)  # (P, T, 3)
    inside = (w >= -1e-9).all(-1)  # grid coordinates are small integers: 1e-9 is rounding
    t = inside.argmax(axis=1)
    assert inside[np.arange(len(pts)), t].all(), "the triangles do not cover the points"
    return tris[t].astype(np.int64), w[np.arange(len(pts)), t]


_GRID_WEIGHTS = {s: grid_weights(decimated_grid(s)) for s in DECIMATION_STRIDES}


@numba.njit(cache=True, nogil=True)
def _overlay_errors(pos, blk, n, size, idx, w, terms, out, col):
    """out[b, col] = the largest norm over overlay rows (idx, w; the first terms[k] of row k) of
    block b's combination of posts (each block's posts taken relative to its first, so the
    float64 ECEF magnitudes cancel first). Every block of ``blk`` has the shape the rows were
    made for."""
    side = size + 1
    local = np.empty((side * side, 3))
    for b in range(blk.shape[0]):
        i0, j0 = blk[b, 0], blk[b, 1]
        o = pos[i0 % n, j0 % n]
        for r in range(blk[b, 2] - i0 + 1):  # the block's own posts: the rows index no others
            for c in range(blk[b, 3] - j0 + 1):
                p = pos[(i0 + r) % n, (j0 + c) % n]
                for a in range(3):
                    local[r * side + c, a] = p[a] - o[a]
        best = 0.0
        for k in range(idx.shape[0]):
            x = y = z = 0.0
            for j in range(terms[k]):
                v, wk = idx[k, j], w[k, j]
                x += wk * local[v, 0]
                y += wk * local[v, 1]
                z += wk * local[v, 2]
            best = max(best, x * x + y * y + z * z)
        out[b, col] = math.sqrt(best)


def morph_targets(stride: int) -> np.ndarray:
    """(V,) records (m0, m1, m2: (row, column) of the block grid; w: 3 weights) of the block
    grid's vertices: where the next coarser stride than ``stride`` (1 or one of
    DECIMATION_STRIDES) draws each post, for the vertex shader's morph (in_m0, in_m1, in_m2,
    in_mw). A post that stride keeps, and every post of the coarsest, has itself with weight 1."""
    order = sorted((1, *DECIMATION_STRIDES))
    if stride == order[-1]:  # the coarsest: every post stays
        idx, w = np.zeros(((BLOCK + 1) ** 2, 3), np.int64), np.ones(((BLOCK + 1) ** 2, 3))
    else:
        idx, w = _GRID_WEIGHTS[order[order.index(stride) + 1]]
    kept = (w == 1.0).any(axis=1)
    idx, w = idx.copy(), w.copy()
    idx[kept] = np.arange(len(idx))[kept, None]
    w[kept] = (1.0, 0.0, 0.0)  # in_mw.x = 1: the shader leaves the post where it is
    out = np.zeros(len(idx), dtype=[("m", "<i4", (3, 2)), ("w", "<f4", 3)])
    out["m"] = np.stack([idx // (BLOCK + 1), idx % (BLOCK + 1)], -1)
    out["w"] = w
    return out


@functools.lru_cache(maxsize=None)
def _overlay(stride: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`overlay_rows` for :func:`_overlay_errors`: (idx, w, terms) with each row's terms of
    weight zero dropped (the others kept in order, first), and the rows that are one post minus
    itself (a post both meshes keep: exactly zero) left out. The same sums, bit for bit, with
    about half the work (stride 2: 109 rows of 6 terms -> 68 of 3.2; stride 4: 233 -> 200 of 4.3)."""
    idx, w = overlay_rows(stride, BLOCK, h, w)
    keep = [k for k in range(len(w)) if not (len(set(idx[k][w[k] != 0.0])) == 1 and w[k].sum() == 0.0)]
    out_i, out_w = np.zeros((len(keep), idx.shape[1]), np.int64), np.zeros((len(keep), idx.shape[1]))
    terms = np.zeros(len(keep), np.int64)
    for r, k in enumerate(keep):
        nz = w[k] != 0.0
        terms[r] = nz.sum()
        out_i[r, :terms[r]], out_w[r, :terms[r]] = idx[k][nz], w[k][nz]
    return out_i, out_w, terms


def _shape_triangles() -> np.ndarray:
    """(BLOCK + 1, BLOCK + 1, 1 + len(DECIMATION_STRIDES)) int: triangles an h x w block draws at
    each stride (1, then DECIMATION_STRIDES), :func:`clamped_triangles`."""
    out = np.zeros((BLOCK + 1, BLOCK + 1, 1 + len(DECIMATION_STRIDES)), np.int64)
    for h in range(1, BLOCK + 1):
        for w in range(1, BLOCK + 1):
            out[h, w] = [len(clamped_triangles(s, h, w)) for s in (1, *DECIMATION_STRIDES)]
    return out


SHAPE_TRIANGLES = _shape_triangles()
_STRIDE_COLUMN = np.full(max(DECIMATION_STRIDES) + 1, -1, np.int64)  # stride -> its SHAPE_TRIANGLES column
_STRIDE_COLUMN[[1, *DECIMATION_STRIDES]] = np.arange(1 + len(DECIMATION_STRIDES))


def block_triangles(blk: np.ndarray) -> np.ndarray:
    """(m, 1 + len(DECIMATION_STRIDES)) triangles each block (m, 4) draws at stride 1, then at each
    of DECIMATION_STRIDES."""
    return SHAPE_TRIANGLES[blk[:, 2] - blk[:, 0], blk[:, 3] - blk[:, 1]]


def decimation_errors(blk: np.ndarray, level, n: int, water_level_m: float = 0.0) -> np.ndarray:
    """(m, len(DECIMATION_STRIDES)) metres: for each block (m, 4) of a level and each stride, the
    largest distance between the level's full surface over the block and what
    :func:`decimated_grid` draws (exact: over the vertices of the two meshes' overlay,
    :func:`overlay_rows`). A block a ring's edge cuts short is measured as the clamp draws it.
    For a block whose posts straddle the water level (:func:`straddles_sea_level`;
    ``water_level_m``: the clipmap's, 0 m MSL or a lossy store's quantisation bound), when the
    level holds heights (``texel``; ``pos_ecef`` alone: distances only), at least how far a stride
    can move the coastline (:func:`coastline_shift_m`), so it is decimated only where that is
    within the pixel bound too."""
    out = np.empty((len(blk), len(DECIMATION_STRIDES)))
    if len(blk) == 0:
        return out
    shape = (blk[:, 2] - blk[:, 0]) * (BLOCK + 1) + (blk[:, 3] - blk[:, 1])
    for key in np.unique(shape):
        h, w = divmod(int(key), BLOCK + 1)
        sel = shape == key
        errs = np.empty((int(sel.sum()), len(DECIMATION_STRIDES)))
        sub = np.ascontiguousarray(blk[sel], dtype=np.int64)
        for s_i, s in enumerate(DECIMATION_STRIDES):
            _overlay_errors(level.pos_ecef, sub, n, BLOCK, *_overlay(s, h, w), errs, s_i)
        out[sel] = errs
    if getattr(level, "texel", None) is not None:
        wet = straddles_sea_level(blk, level, n, water_level_m)
        if wet.any():
            out[wet] = np.maximum(out[wet], coastline_shift_m(blk[wet], level, n))
    return out


def coastline_shift_m(blk: np.ndarray, level, n: int) -> np.ndarray:
    """(m, len(DECIMATION_STRIDES)) metres: how far each stride can move the coastline in blocks
    (m, 4) whose posts straddle sea level. Colour tells land from water by the interpolated
    height's sign, and a stride-s mesh draws each s x s cell of posts from its corners alone: a
    sign change inside the cell moves, or an islet or inlet smaller than the cell vanishes, by at
    most the cell's diagonal, s sqrt(2) times the larger post spacing (the block's first row and
    column: a level's spacing changes by far less across a block)."""
    i0, j0 = blk[:, 0] % n, blk[:, 1] % n
    p = level.pos_ecef
    spacing = np.maximum(np.linalg.norm(p[(i0 + 1) % n, j0] - p[i0, j0], axis=-1),
                         np.linalg.norm(p[i0, (j0 + 1) % n] - p[i0, j0], axis=-1))
    return spacing[:, None] * (math.sqrt(2.0) * np.asarray(DECIMATION_STRIDES, np.float64))[None, :]


def straddles_sea_level(blk: np.ndarray, level, n: int, water_level_m: float = 0.0) -> np.ndarray:
    """(m,) bool: block (m, 4)'s posts hold heights both at or below the water level
    (``water_level_m``: 0 m MSL; over a lossy store half its step, shading.water_level_m) and
    above. Such a block is decimated only where the coastline's shift is within the pixel bound too
    (:func:`decimation_errors`, :func:`coastline_shift_m`): colour tells land from water by the
    interpolated height against the water level (terrain_mesh TERRAIN_COLOUR_GLSL), and a coarser mesh there moves
    the coastline by up to the stride's span whatever its vertical error (the Kattegat's
    skerries, 0-20 m high, merged into kilometres of land at 2 px when only height counted).
    Elsewhere every post of a block, and so every convex combination of them a coarser mesh or
    its morph draws, lies on one side of the water level: decimation never turns land into
    water or back."""
    if len(blk) == 0:
        return np.zeros(0, bool)
    return _straddles_kernel(level.texel, np.ascontiguousarray(blk, dtype=np.int64), n, float(water_level_m))


@numba.njit(cache=True, nogil=True)
def _straddles_kernel(texel, blk, n, water_level_m):
    """(m,) bool: block b's posts (its heights MSL, texel[..., 3]) hold both h <= water_level_m
    and h > water_level_m."""
    out = np.zeros(blk.shape[0], np.bool_)
    for b in range(blk.shape[0]):
        wet = dry = False
        for i in range(blk[b, 0], blk[b, 2] + 1):
            for j in range(blk[b, 1], blk[b, 3] + 1):
                if texel[i % n, j % n, 3] <= water_level_m:
                    wet = True
                else:
                    dry = True
        out[b] = wet and dry
    return out


def block_strides(err_m: np.ndarray, lo: np.ndarray, hi: np.ndarray, camera_local: np.ndarray,
                  focal_px: float, pixel_error: float, triangles: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """((m,) int32 strides, (m,) float32 morphs) of blocks: each block's stride is the coarsest of
    DECIMATION_STRIDES whose error (:func:`decimation_errors`), and every finer stride's, seen
    from the nearest point of the block's box (lo, hi, local ENU) at ``focal_px`` pixels per
    radian, stays within ``pixel_error`` pixels; else 1. A displacement e at distance d moves a
    point at most e x focal / d pixels on screen.

    The morph moves the posts the next coarser stride drops towards where its mesh draws them
    (the vertex shader): 0 while that stride's error r is 2 x pixel_error pixels or more, rising
    to 1 as r falls to pixel_error, where the block takes that stride. The posts move by at most
    morph x r = (2 - r / pixel_error) r <= pixel_error pixels, so the bound holds throughout.

    ``triangles`` ((m, 1 + len(DECIMATION_STRIDES)), :func:`block_triangles`): a block a ring's
    edge cuts short takes, of the strides within the bound, the one that draws the fewest
    triangles (a coarser one can draw more: the clamp keeps every post of the cut edge), coarser
    on a tie, without a morph (it pops by at most pixel_error pixels when it changes).

    One compiled pass (:func:`_strides_kernel`): on the frame's path, for every level."""
    m = len(err_m)
    strides = np.ones(m, np.int32)
    morph = np.zeros(m, np.float32)
    if m:
        tri = np.zeros((0, 1 + len(DECIMATION_STRIDES)), np.int64) if triangles is None else triangles
        _strides_kernel(np.ascontiguousarray(err_m, np.float64), lo, hi, np.asarray(camera_local, np.float64),
                        float(focal_px), float(pixel_error), np.ascontiguousarray(tri, np.int64),
                        triangles is not None, _DECIMATION_STRIDES_ARRAY, 2 * BLOCK * BLOCK, strides, morph)
    return strides, morph


_DECIMATION_STRIDES_ARRAY = np.array(DECIMATION_STRIDES, np.int32)


@numba.njit(cache=True, nogil=True, inline="always")
def _box_distance(lo, hi, b, cam):
    """Distance from cam (3,) to the nearest point of box b of (lo, hi) (m, 3)."""
    d2 = 0.0
    for a in range(3):
        g = max(max(lo[b, a] - cam[a], cam[a] - hi[b, a]), 0.0)
        d2 += g * g
    return math.sqrt(d2)


@numba.njit(cache=True, nogil=True)
def _strides_kernel(err, lo, hi, cam, focal_px, pixel_error, triangles, cut_rule, ds, whole_triangles,
                    strides, morph):
    """:func:`block_strides` into strides, morph, block by block."""
    n_s = ds.shape[0]
    oks = np.empty(n_s + 1, np.bool_)
    for b in range(err.shape[0]):
        dist = max(_box_distance(lo, hi, b, cam), 1e-9)
        stride = 1
        mo = 0.0
        ok = True
        oks[0] = True
        for s_i in range(n_s - 1, -1, -1):  # fine to coarse
            r = err[b, s_i] * focal_px / dist
            if ok:
                mo = min(max(2.0 - r / pixel_error, 0.0), 1.0)  # towards this stride
            ok = ok and r <= pixel_error
            oks[1 + s_i] = ok
            if ok:
                stride = ds[s_i]
        if stride == ds[0]:  # the coarsest
            mo = 0.0
        if cut_rule and triangles[b, 0] != whole_triangles:
            best = -1  # coarse to fine, stride 1 last: the first of the fewest triangles
            for c in range(1, n_s + 2):
                col = c if c <= n_s else 0
                if oks[col] and (best < 0 or triangles[b, col] < triangles[b, best]):
                    best = col
            stride = 1 if best == 0 else ds[best - 1]
            mo = 0.0
        strides[b] = stride
        morph[b] = mo


# -- stitched edges: two neighbouring decimated blocks draw their shared edge with fewer posts

def _whole(blk: np.ndarray) -> np.ndarray:
    """Mask of the blocks (m, 4) of BLOCK x BLOCK cells (not cut short by a ring's edge)."""
    return ((blk[:, 2] - blk[:, 0]) == BLOCK) & ((blk[:, 3] - blk[:, 1]) == BLOCK)


def block_neighbours(blk: np.ndarray) -> np.ndarray:
    """(m, 2) the index of each block's north and east neighbour among ``blk`` (m, 4): a whole
    (BLOCK x BLOCK) block that shares the whole edge; -1 where there is none (the ring's outer
    border, the hole, a block cut short, on either side)."""
    out = np.full((len(blk), 2), -1, np.int64)
    whole = _whole(blk)
    if not whole.any():
        return out
    key = (blk[:, 0].astype(np.int64) << 32) + blk[:, 1].astype(np.int64)  # (i0, j0): indices within 2^31
    ids = np.flatnonzero(whole)
    order = np.argsort(key[ids])
    sorted_keys, sorted_ids = key[ids][order], ids[order]
    for side, (di, dj) in enumerate(((BLOCK, 0), (0, BLOCK))):
        want = key + (di << 32) + dj
        at = np.minimum(np.searchsorted(sorted_keys, want), len(sorted_keys) - 1)
        hit = whole & (sorted_keys[at] == want)
        out[hit, side] = sorted_ids[at[hit]]
    return out


@numba.njit(cache=True, nogil=True)
def _edge_kernel(pos, blk, n, size, strides, out):
    """out[b, side, s_i]: the largest distance of a post of block b's north (side 0) or east
    (side 1) edge from the straight line between the posts at the multiples of strides[s_i]
    around it (float64, relative to the edge's first post)."""
    line = np.empty((size + 1, 3))
    for b in range(blk.shape[0]):
        for side in range(2):
            i, j = (blk[b, 2], blk[b, 1]) if side == 0 else (blk[b, 0], blk[b, 3])
            di, dj = (0, 1) if side == 0 else (1, 0)
            o = pos[i % n, j % n]
            for t in range(size + 1):
                p = pos[(i + di * t) % n, (j + dj * t) % n]
                for a in range(3):
                    line[t, a] = p[a] - o[a]
            for s_i in range(strides.shape[0]):
                e = strides[s_i]
                best = 0.0
                for t in range(size + 1):
                    r = t % e
                    if r == 0:
                        continue
                    t0 = t - r
                    f = r / e
                    d2 = 0.0
                    for a in range(3):
                        x = line[t, a] - ((1.0 - f) * line[t0, a] + f * line[t0 + e, a])
                        d2 += x * x
                    best = max(best, d2)
                out[b, side, s_i] = math.sqrt(best)


# The strides an edge can take beyond 1, coarse to fine (edge_choices of every stride).
EDGE_STRIDES = tuple(sorted({e for s in DECIMATION_STRIDES for e in edge_choices(s)} - {1}, reverse=True))
# A straight edge of length L between two posts sags L^2 / 8R below the ellipsoid between them.
# The pixel bound covers how far it is drawn from the surface, but where that edge is the far
# horizon a sag shows sky below it: a corner-to-corner edge (BLOCK cells) is drawn only where it
# sags at most this much (levels whose BLOCK cells span at most ~23 km). Found by the render
# bench's hole count at n = 127: L = 7's coarsest level, 46 km edges, sagged 41 m.
MAX_CORNER_EDGE_SAG_M = 10.0


def edge_deviations(blk: np.ndarray, level, n: int) -> np.ndarray:
    """(m, 2, len(EDGE_STRIDES)) metres: how far the posts of each block's north and east edge
    lie from that edge drawn with every stride-th post (:func:`decimated_grid`'s ``edges``).
    Infinite for a block cut short (its edges keep every post)."""
    out = np.full((len(blk), 2, len(EDGE_STRIDES)), np.inf)
    whole = _whole(blk)
    if whole.any():
        dev = np.empty((int(whole.sum()), 2, len(EDGE_STRIDES)))
        _edge_kernel(level.pos_ecef, np.ascontiguousarray(blk[whole], dtype=np.int64), n, BLOCK,
                     np.array(EDGE_STRIDES, np.int64), dev)
        out[whole] = dev
    return out


def _distances(lo: np.ndarray, hi: np.ndarray, camera_local: np.ndarray) -> np.ndarray:
    """(m,) distance from the camera to the nearest point of each box (lo, hi)."""
    out = np.empty(len(lo))
    _distances_kernel(lo, hi, np.asarray(camera_local, np.float64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _distances_kernel(lo, hi, cam, out):
    for b in range(lo.shape[0]):
        out[b] = _box_distance(lo, hi, b, cam)


def _allowed_edges(corner_to_corner: bool) -> np.ndarray:
    """(max stride + 1, len(EDGE_STRIDES)) bool: whether a block of stride s may draw an edge
    with EDGE_STRIDES[i] (:func:`edge_choices`; not BLOCK unless ``corner_to_corner``)."""
    out = np.zeros((max(DECIMATION_STRIDES) + 1, len(EDGE_STRIDES)), bool)
    for s in DECIMATION_STRIDES:
        for i, e in enumerate(EDGE_STRIDES):
            out[s, i] = e in edge_choices(s) and (corner_to_corner or e < BLOCK)
    return out


_ALLOWED_EDGES = {c: _allowed_edges(c) for c in (False, True)}
_EDGE_STRIDES_ARRAY = np.array(EDGE_STRIDES, np.int32)


def edge_strides(strides: np.ndarray, err_m: np.ndarray, dev_m: np.ndarray, neighbours: np.ndarray,
                 dist: np.ndarray, focal_px: float, pixel_error: float, corner_to_corner: bool = True) -> np.ndarray:
    """(m, 4) int32 strides of each block's south, east, north and west edges (decimated_grid's
    ``edges``). A shared edge takes the coarsest of EDGE_STRIDES that both blocks' strides allow
    (:func:`edge_choices`) and that keeps each block within the bound: its own stride's error
    (err_m, ``strides``) plus the edge's deviation (dev_m, :func:`edge_deviations`) at that
    block's distance, at most ``pixel_error`` pixels (decimated_grid: the two add at most). Else
    1, as every edge without a neighbour (``neighbours``, :func:`block_neighbours`). Each edge is
    decided once, from its south or west block, and written to both blocks: they draw it alike,
    watertight. ``corner_to_corner`` False: no edge of BLOCK cells (MAX_CORNER_EDGE_SAG_M).
    One compiled pass (:func:`_edges_kernel`)."""
    m = len(strides)
    edges = np.ones((m, 4), np.int32)
    if m:
        _edges_kernel(np.asarray(strides, np.int64), np.ascontiguousarray(err_m, np.float64),
                      np.ascontiguousarray(dev_m, np.float64), np.ascontiguousarray(neighbours, np.int64),
                      np.asarray(dist, np.float64), float(focal_px), float(pixel_error),
                      _DECIMATION_STRIDES_ARRAY, _EDGE_STRIDES_ARRAY, _ALLOWED_EDGES[bool(corner_to_corner)], edges)
    return edges


@numba.njit(cache=True, nogil=True)
def _edges_kernel(strides, err, dev, neighbours, dist, focal_px, pixel_error, ds, es, allowed, edges):
    """:func:`edge_strides` into edges (m, 4), ones on entry."""
    m = strides.shape[0]
    own = np.zeros(m)
    scale = np.empty(m)
    for b in range(m):
        scale[b] = focal_px / max(dist[b], 1e-9)
        for i in range(ds.shape[0]):
            if strides[b] == ds[i]:
                own[b] = err[b, i] * scale[b]
    for side in range(2):  # north: my N (2) = their S (0); east: my E (1) = their W (3)
        mine, theirs = (2, 0) if side == 0 else (1, 3)
        for a in range(m):
            b = neighbours[a, side]
            if b < 0:
                continue
            e = 1
            sa, sb = strides[a], strides[b]
            for s_i in range(es.shape[0]):  # coarse to fine: the first that holds
                d = dev[a, side, s_i]
                if (sa < allowed.shape[0] and sb < allowed.shape[0] and allowed[sa, s_i] and allowed[sb, s_i]
                        and own[a] + d * scale[a] <= pixel_error and own[b] + d * scale[b] <= pixel_error):
                    e = es[s_i]
                    break
            edges[a, mine] = e
            edges[b, theirs] = e


def border_edges(blk: np.ndarray, region: Rect, strides: np.ndarray, edges: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(``edges`` (m, 4) with 2 on the sides below, (m, 4) mask of those sides): each side that
    lies on the level's drawn border where the block (whole, of stride 2 or more) starts on an
    even post and the border row (column) is even. There the morph puts every post on the
    coarser level's edge (alpha = 1), the odd ones halfway between two coarser posts, so the edge
    drawn with the even posts alone is the same surface and meets the coarser level's vertices
    exactly, with no T-junction for the border triangles to fill (``border_segments_left``)."""
    out = np.array(edges, dtype=edges.dtype, copy=True)
    sides = np.zeros((len(blk), 4), bool)
    if len(blk):
        _border_edges_kernel(blk, region.i0, region.j0, region.i1, region.j1, strides, BLOCK, out, sides)
    return out, sides


@numba.njit(cache=True, nogil=True)
def _border_edges_kernel(blk, i0, j0, i1, j1, strides, size, edges, sides):
    for b in range(blk.shape[0]):
        if not (blk[b, 2] - blk[b, 0] == size and blk[b, 3] - blk[b, 1] == size and strides[b] >= 2):
            continue
        even_j, even_i = blk[b, 1] % 2 == 0, blk[b, 0] % 2 == 0
        sides[b, 0] = even_j and blk[b, 0] == i0 and i0 % 2 == 0  # south
        sides[b, 1] = even_i and blk[b, 3] == j1 and j1 % 2 == 0  # east
        sides[b, 2] = even_j and blk[b, 2] == i1 and i1 % 2 == 0  # north
        sides[b, 3] = even_i and blk[b, 1] == j0 and j0 % 2 == 0  # west
        for side in range(4):
            if sides[b, side]:
                edges[b, side] = 2


def border_segments_left(region: Rect, blk: np.ndarray, sides: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`border_segments` of ``region`` without those whose every cell lies on a block's
    border side drawn with the coarser level's posts alone (``sides``, (m, 4) south, east,
    north, west: :func:`border_edges`' mask): nothing there for a border triangle to fill."""
    rows, cols = border_segments(region)
    if not sides.any():
        return rows, cols
    h, w = region.i1 - region.i0, region.j1 - region.j0
    out = []
    # (segments, their length along the border, ((side, at, column of segments holding at), ...))
    for segments, length, along in ((rows, w, ((0, 0, 0), (2, h, 2))), (cols, h, ((3, 0, 1), (1, w, 3)))):
        keep = np.ones(len(segments), bool)
        for side, at, col in along:
            by_cols = side in (0, 2)  # a row's segments run along columns
            _spare_kernel(segments, blk, sides, side, 1 if by_cols else 0, region.j0 if by_cols else region.i0,
                          at, col, length, BLOCK, keep)
        out.append(segments[keep])
    return out[0], out[1]


@numba.njit(cache=True, nogil=True)
def _spare_kernel(segments, blk, sides, side, start_col, offset, at, col, length, size, keep):
    """Clear keep[s] for the segments (columns col == at) whose every cell along the border a
    block's side ``side`` covers (its cells from blk[:, start_col] - offset, size of them)."""
    covered = np.zeros(length + 1, np.bool_)
    found = False
    for b in range(blk.shape[0]):
        if sides[b, side]:
            found = True
            first = blk[b, start_col] - offset
            for t in range(size):
                covered[first + t] = True
    if not found:
        return
    gaps = np.zeros(length + 1, np.int64)  # uncovered cells before each post
    for t in range(length):
        gaps[t + 1] = gaps[t] + (0 if covered[t] else 1)
    a_col, b_col = (1, 3) if start_col == 1 else (0, 2)
    for s in range(segments.shape[0]):
        if segments[s, col] == at and gaps[segments[s, b_col]] == gaps[segments[s, a_col]]:
            keep[s] = False


def _variants() -> tuple[list, np.ndarray]:
    """([(stride, edges)], table): every block mesh the layer draws, stride 1 first, and the
    table (log2 stride, log2 of each edge's stride) -> its index (-1: none)."""
    strides = sorted((1, *DECIMATION_STRIDES))
    out = []
    table = np.full((max(strides).bit_length(), *[BLOCK.bit_length()] * 4), -1, np.int64)
    for stride in strides:
        for edges in itertools.product(edge_choices(stride), repeat=4):
            table[(stride.bit_length() - 1, *[e.bit_length() - 1 for e in edges])] = len(out)
            out.append((stride, edges))
    return out, table


VARIANTS, _VARIANT_TABLE = _variants()
VARIANT_TRIANGLES = np.array([len(decimated_grid(s, BLOCK, e)) for s, e in VARIANTS], np.int64)


def block_variants(strides: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(m,) index into VARIANTS of each block's (stride, edges)."""
    out = np.empty(len(strides), np.int64)
    _variants_kernel(strides, edges, _VARIANT_TABLE, out)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _log2(x):
    """log2 of a power of two."""
    k = 0
    while (1 << k) < x:
        k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _variants_kernel(strides, edges, table, out):
    for b in range(strides.shape[0]):
        out[b] = table[_log2(strides[b]), _log2(edges[b, 0]), _log2(edges[b, 1]), _log2(edges[b, 2]),
                       _log2(edges[b, 3])]


# Culling boxes are padded by this (metres) plus BOX_PAD_RELATIVE of the block's distance from
# the origin: float32 vertex offsets round to ~6e-8 of their level's extent.
BOX_PAD_M = 1.0
BOX_PAD_RELATIVE = 1e-6


# A moved level's blocks are measured (decimation errors, edge deviations, culling boxes) in
# up to this many parts at once, each of at least PLAN_PART_MIN_BLOCKS blocks: the kernels
# release the GIL, so the parts run on helper threads (terrain.threads). At most 2 by default:
# a move's kernels are a few milliseconds of work, and on a 16-core host more threads cost more
# in hand-offs than they share (--quick render on an H200's host, move median / worst step:
# 1 thread 8.1 / 13.9 ms, 2: 9.1-10.4 / 16-17, 8: 10.4-11.5 / 26-29; on this 2-core VM 2 threads
# beat 1, 5.1 / 7.6-9.2 against 5.5-5.7 / 7.4-7.5). SORTIE_PLAN_THREADS (a positive integer) sets it.
PLAN_THREADS_DEFAULT_MAX = 2


def _plan_threads() -> int:
    text = os.environ.get("SORTIE_PLAN_THREADS", "").strip()
    if not text:
        return min(cpu_count(), PLAN_THREADS_DEFAULT_MAX)
    if not text.isdigit() or int(text) < 1:
        raise InvalidArgument("SORTIE_PLAN_THREADS", "must be a positive integer", value=text)
    return int(text)


PLAN_THREADS = _plan_threads()
PLAN_PART_MIN_BLOCKS = 64


def by_parts(fn, blk: np.ndarray, threads: int | None = None):
    """fn(blk) for a per-block fn (its results arrays, or a tuple of arrays, with a row per
    block): computed over contiguous parts of ``blk`` on up to ``threads`` threads (default
    PLAN_THREADS) and joined, the same arrays as one call gives."""
    threads = PLAN_THREADS if threads is None else threads
    parts = max(1, min(threads, len(blk) // PLAN_PART_MIN_BLOCKS))
    if parts == 1:
        return fn(blk)
    cuts = np.linspace(0, len(blk), parts + 1).astype(np.int64).tolist()
    outs = map_shared(fn, [blk[a:b] for a, b in zip(cuts[:-1], cuts[1:])], parts)
    if isinstance(outs[0], tuple):
        return tuple(np.concatenate(arrays) for arrays in zip(*outs))
    return np.concatenate(outs)


def coarse_footprints(blk: np.ndarray) -> np.ndarray:
    """(m, 4) inclusive rectangles of the coarser level's posts :func:`block_bounds` may read
    under each block (m, 4) (rows i0 // 2 .. ceil(i1 / 2), the same for columns)."""
    b = blk.astype(np.int64)
    return np.stack([b[:, 0] // 2, b[:, 1] // 2, -(-b[:, 2] // 2), -(-b[:, 3] // 2)], -1)


def posts_unchanged(footprints: np.ndarray, level, since: int) -> np.ndarray:
    """Mask of the rectangles (m, 4: i0, j0, i1, j1 inclusive posts) whose posts ``level``
    (client.render.clipmap.LevelStore) holds now, unchanged since its version ``since``:
    inside its region and clear of every post written after that version."""
    written = level.written_since(since)
    if written is None or level.region is None:
        return np.zeros(len(footprints), bool)
    f, r = footprints, level.region
    ok = (f[:, 0] >= r.i0) & (f[:, 1] >= r.j0) & (f[:, 2] <= r.i1) & (f[:, 3] <= r.j1)
    for w in written:
        ok &= (f[:, 2] < w.i0) | (f[:, 0] > w.i1) | (f[:, 3] < w.j0) | (f[:, 1] > w.j1)
    return ok


def same_blocks(blk: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows of blk, rows of other) of the blocks (m, 4) both hold (each block once in each):
    every block packed into one int64 (its corner from the two arrays' least, and its size;
    blocks at most BLOCK cells a side)."""
    if not len(blk) or not len(other):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    a, b = blk.astype(np.int64), other.astype(np.int64)
    i_min, j_min = min(a[:, 0].min(), b[:, 0].min()), min(a[:, 1].min(), b[:, 1].min())
    if max(a[:, 0].max(), b[:, 0].max()) - i_min >= 1 << 27 or max(a[:, 1].max(), b[:, 1].max()) - j_min >= 1 << 24:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)  # too far apart to pack: none shared

    def keys(x):
        corner = ((x[:, 0] - i_min) << 36) | ((x[:, 1] - j_min) << 12)
        return corner | ((x[:, 2] - x[:, 0]) << 6) | (x[:, 3] - x[:, 1])

    _, rows, other_rows = np.intersect1d(keys(a), keys(b), assume_unique=True, return_indices=True)
    return rows, other_rows


def remeasure(measure, blk: np.ndarray, previous=None) -> tuple:
    """measure(blk) (a tuple of arrays with a row per block, :func:`by_parts`), reusing earlier
    rows: ``previous`` (old_blk, old, unchanged) gives the arrays ``old`` measured for the
    blocks ``old_blk``, and a block that ``blk`` has again (the same rectangle) keeps its rows
    where ``unchanged`` (blocks (m, 4) -> mask) says it reads the same posts; the others (all,
    without ``previous``) are measured anew. The same arrays as measuring every block, bit for
    bit: each row depends only on the posts under its block."""
    if previous is None:
        return by_parts(measure, blk)
    old_blk, old, unchanged = previous
    new_rows, old_rows = same_blocks(blk, old_blk)
    keep = unchanged(blk[new_rows]) if len(new_rows) else np.zeros(0, bool)
    rows = np.stack([new_rows[keep], old_rows[keep]], -1)
    out = tuple(np.empty((len(blk), *a.shape[1:]), a.dtype) for a in old)
    for o, a in zip(out, old):
        o[rows[:, 0]] = a[rows[:, 1]]
    todo = np.ones(len(blk), bool)
    todo[rows[:, 0]] = False
    if todo.any():
        for o, a in zip(out, by_parts(measure, blk[todo])):
            o[todo] = a
    return out


def block_bounds(blk: np.ndarray, level, coarse, n: int, origin: LocalOrigin) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (m, 3) local-ENU boxes of blocks (m, 4) of a level: over the block's own posts
    (clamped to the block as the vertex shader clamps them) and, when ``coarse`` (the coarser
    level's storage) is given, the coarser posts under the block, the morph targets' corners.
    One compiled pass (a ring of 768 blocks: 19 ms in numpy, recomputed at every move of the
    level, on the frame's draw path)."""
    lo, hi = np.full((len(blk), 3), np.inf), np.full((len(blk), 3), -np.inf)
    if len(blk) == 0:
        return lo, hi
    b64 = np.ascontiguousarray(blk, dtype=np.int64)
    _box_kernel(level.pos_ecef, b64, n, BLOCK, False, origin.ecef, origin.basis, lo, hi)
    if coarse is not None:
        _box_kernel(coarse.pos_ecef, b64, n, BLOCK, True, origin.ecef, origin.basis, lo, hi)
    pad = BOX_PAD_M + BOX_PAD_RELATIVE * np.linalg.norm(lo + hi, axis=1) / 2.0
    return lo - pad[:, None], hi + pad[:, None]


@numba.njit(cache=True, nogil=True)
def _box_kernel(pos, blk, n, size, coarser, origin, basis, lo, hi):
    """Grow boxes lo/hi (m, 3) by the local-ENU positions (origin, basis) of each block's posts:
    its own (rows i0..i1, columns j0..j1, clamped) or the coarser level's under it (rows i0 // 2
    .. ceil(i1 / 2), size // 2 + 2 of them, clamped)."""
    for b in range(blk.shape[0]):
        if coarser:
            r0, r1, c0, c1, count = blk[b, 0] // 2, -(-blk[b, 2] // 2), blk[b, 1] // 2, -(-blk[b, 3] // 2), size // 2 + 2
        else:
            r0, r1, c0, c1, count = blk[b, 0], blk[b, 2], blk[b, 1], blk[b, 3], size + 1
        for ii in range(count):
            r = min(r0 + ii, r1) % n
            for jj in range(count):
                c = min(c0 + jj, c1) % n
                d0, d1, d2 = pos[r, c, 0] - origin[0], pos[r, c, 1] - origin[1], pos[r, c, 2] - origin[2]
                for a in range(3):
                    v = basis[a, 0] * d0 + basis[a, 1] * d1 + basis[a, 2] * d2
                    if v < lo[b, a]:
                        lo[b, a] = v
                    if v > hi[b, a]:
                        hi[b, a] = v


def visible_blocks(lo: np.ndarray, hi: np.ndarray, view_proj: np.ndarray) -> np.ndarray:
    """Mask of the blocks whose boxes (lo, hi) (m, 3), local ENU, may be in the view frustum: not
    all eight corners beyond one of the left, right, bottom and top planes or behind the eye."""
    out = np.zeros(len(lo), bool)
    if len(lo):
        _frustum_kernel(lo, hi, np.ascontiguousarray(view_proj, np.float64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _frustum_kernel(lo, hi, m, out):
    for b in range(lo.shape[0]):
        right = left = above = below = behind = True  # every corner beyond that plane so far
        for k in range(8):
            x = hi[b, 0] if k & 1 else lo[b, 0]
            y = hi[b, 1] if k & 2 else lo[b, 1]
            z = hi[b, 2] if k & 4 else lo[b, 2]
            cx = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
            cy = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
            cw = m[3, 0] * x + m[3, 1] * y + m[3, 2] * z + m[3, 3]
            right = right and cx > cw
            left = left and cx < -cw
            above = above and cy > cw
            below = below and cy < -cw
            behind = behind and cw <= 0.0
        out[b] = not (right or left or above or below or behind)


@dataclass
class LevelDraw:
    k: int
    region: Rect
    alpha_h: float
    blocks: np.ndarray  # (m, 4) visible blocks, lattice posts
    cells: int
    strides: np.ndarray | None = None  # (m,) each block's stride (decimated_grid); None: all 1
    triangles: int = 0  # what the blocks draw (without the border triangles)
    morph: np.ndarray | None = None  # (m,) each block's morph towards its next stride (block_strides)
    variants: np.ndarray | None = None  # (m,) each block's mesh, an index into VARIANTS; None: all 0 (stride 1)
    border: tuple | None = None  # (rows, columns) border-triangle segments to draw (with the coarser level); None: all
    near_insets: np.ndarray | None = None  # (m,) bool: the block may lie under an inset (drawn by the inset variant)
    insets: tuple = ()  # the insets (indices into ClipmapLayer.insets) near any of the level's blocks


class ClipmapLayer:
    """A geometry clipmap around a focus (the camera, or ``focus`` set by the caller).

    terrain: Terrain or TerrainClient. levels, n, budget: the clipmap (client/render/clipmap.py;
    budget = terrain samples per frame). finest_spacing_factor: the finest level's spacing over the
    terrain's post spacing (a power of two: 1 = the DEM's own posts, 1/2 = twice as fine).
    pixel_error: draw a block with fewer posts (:func:`decimated_grid`) where that moves its
    surface by at most this many pixels on screen (:func:`block_strides`); None: every post.
    polar_window_m, polar_horizon_m: the reference mesh drawn instead near a pole (the window and
    horizon ring of terrain_mesh.TerrainMeshLayer; POLAR_MESH_HYSTERESIS says where), rebuilt on a
    helper thread while the current one is drawn. design_fov_deg: the horizontal field of view the
    levels are sized for; a narrower view is centred towards what it looks at (module docstring,
    "Narrow views"). focus_lat_lon: the centre (degrees) for views at least that wide; None: the
    camera's position.
    """

    def __init__(self, ctx, terrain, origin: LocalOrigin, *, levels: int = 7, n: int = 127,
                 budget: int = 100_000, finest_spacing_factor: float = 1.0, geoid_undulation_m: float = 0.0,
                 lattice=None, focus_lat_lon=None, insets=(), land_classes: bool = False,
                 pixel_error: float | None = None, polar_window_m: float = DEFAULT_WINDOW_M,
                 polar_horizon_m: float = DEFAULT_HORIZON_M, design_fov_deg: float = DEFAULT_FOV_X_DEG):
        lo, hi = FOV_X_RANGE_DEG
        if not (isinstance(design_fov_deg, (int, float)) and lo <= design_fov_deg <= hi):
            raise InvalidArgument("design_fov_deg", f"must be within [{lo:g}, {hi:g}] degrees", value=design_fov_deg)
        self.design_fov_deg = float(design_fov_deg)
        e = math.log2(finest_spacing_factor) if finest_spacing_factor > 0 else math.nan
        if not (math.isfinite(e) and e == round(e) and -8 <= e <= 8):
            raise InvalidArgument("finest_spacing_factor", "must be a power of two in [1/256, 256]",
                                  value=finest_spacing_factor)
        if pixel_error is not None and not (isinstance(pixel_error, (int, float)) and not isinstance(pixel_error, bool)
                                            and 0 < pixel_error <= 100):
            raise InvalidArgument("pixel_error", "must be None or a number of pixels in (0, 100]", value=pixel_error)
        self.pixel_error = None if pixel_error is None else float(pixel_error)
        if self.pixel_error is not None:  # every cut-short block's overlay, once a process (0.4 s), not mid-flight
            for s, h, w in itertools.product(DECIMATION_STRIDES, range(1, BLOCK + 1), range(1, BLOCK + 1)):
                _overlay(s, h, w)
        self.ctx = ctx
        self.terrain = terrain
        self.origin = origin
        # The polar fallback, made when first needed; its arguments checked now.
        self._polar_args = dict(window_m=polar_window_m, horizon_m=polar_horizon_m,
                                geoid_undulation_m=geoid_undulation_m)
        if not (0 < polar_window_m <= 1_000_000 and (polar_horizon_m == 0 or polar_window_m < polar_horizon_m
                                                     <= 2_000_000)):
            raise InvalidArgument("polar_window_m", "must be in (0, 1000 km], and polar_horizon_m 0 or in "
                                                    "(polar_window_m, 2000 km] (TerrainMeshLayer's window_m, horizon_m)",
                                  value=(polar_window_m, polar_horizon_m))
        self.polar_mesh: TerrainMeshLayer | None = None
        self.polar = False  # drawing the polar mesh this frame
        self._finest_factor = finest_spacing_factor
        self._lattice = lattice
        self._args = (levels, n, budget, geoid_undulation_m)
        self.clipmap: Clipmap | None = None
        self.focus_lat_lon = focus_lat_lon  # None: the camera's position
        self.insets = list(insets)  # terrain.inset.InsetSource: the clipmap is lowered beneath them
        self._land_classes = bool(land_classes)  # base colour from terrain/texture.py's land classes
        n_insets = len(self.insets)
        self.program, self._border_program = (
            ctx.program(vertex_shader=shader_variant(VERTEX_SHADER, border, insets=n_insets if border else 0),
                        fragment_shader=shader_variant(FRAGMENT_SHADER, border, self._land_classes,
                                                       n_insets if border else 0))
            for border in (False, True))
        # Blocks near an inset are drawn by a variant that tests each fragment against the insets'
        # polygons (module docstring, "Insets"); the border program always does (it writes its
        # depth anyway).
        self._inset_program = None if not n_insets else ctx.program(
            vertex_shader=shader_variant(VERTEX_SHADER, False, insets=n_insets),
            fragment_shader=shader_variant(FRAGMENT_SHADER, False, self._land_classes, n_insets))
        # Every block mesh (VARIANTS: a stride and its edges' strides) in one index buffer, over
        # one vertex buffer that holds the block grid once a stride, each copy with its posts'
        # morph targets towards the next coarser stride. A level is one multi-draw
        # (glMultiDrawElementsIndirect, OpenGL 4.3): a command a mesh in use, whose blocks'
        # instance records ((i0, j0, i1, j1), morph) lie together from its base instance on.
        order = sorted((1, *DECIMATION_STRIDES))
        grid = block_grid()[0]
        self._grid_vbo = ctx.buffer(np.tile(grid, (len(order), 1)).tobytes())
        self._targets_vbo = ctx.buffer(np.concatenate([morph_targets(st) for st in order]).tobytes())
        meshes = [decimated_grid(st, BLOCK, e).astype(np.int64) + order.index(st) * len(grid) for st, e in VARIANTS]
        self._index_count = np.array([3 * len(t) for t in meshes], np.int64)
        self._first_index = np.concatenate([[0], np.cumsum(self._index_count)[:-1]])
        self._block_ibo = ctx.buffer(np.concatenate(meshes).astype(np.uint32).tobytes())
        self._inst = ctx.buffer(reserve=16 * 1024)
        self._indirect = ctx.buffer(reserve=20 * len(VARIANTS))
        self._block_vao, self._inset_block_vao = (None if prog is None else ctx.vertex_array(
            prog, [(self._grid_vbo, "2i", "in_cell"),
                   (self._targets_vbo, "2i 2i 2i 3f", "in_m0", "in_m1", "in_m2", "in_mw"),
                   (self._inst, "4i 1f/i", "in_block", "in_morph")],
            index_buffer=self._block_ibo, index_element_size=4) for prog in (self.program, self._inset_program))
        self._inset_masks = self._inset_boxes = None
        if n_insets:
            self._inset_masks, self._inset_mask_texture, self._inset_boxes = _inset_masks(ctx, self.insets)
        # Zero-area triangles along each level's outer border (GPU Gems 2 ch. 2): (even, even, odd)
        # posts of a border row or column, which the morph puts on the coarser level's edge; drawn,
        # they fill the float32 slivers of the T-junctions there. The odd post is the provoking
        # (last) vertex, whose attributes and depth the flat border program takes. One VAO per direction.
        line = np.arange(BLOCK + 1, dtype=np.int32)
        zero = np.zeros_like(line)
        fan = np.array([(j, j + 2, j + 1) for j in range(0, BLOCK - 1, 2)], np.uint32)
        self._border_ibo = ctx.buffer(fan.tobytes())
        self._border_vbos = [ctx.buffer(np.stack([zero, line], -1).astype(np.int32).tobytes()),  # along a row
                             ctx.buffer(np.stack([line, zero], -1).astype(np.int32).tobytes())]  # along a column
        self._border_inst = ctx.buffer(reserve=16 * 1024)
        self._border_vaos = [ctx.vertex_array(self._border_program,
                                              [(vbo, "2i", "in_cell"), (self._border_inst, "4i/i", "in_block")],
                                              index_buffer=self._border_ibo, index_element_size=4)
                             for vbo in self._border_vbos]
        self.border_triangles = True  # False: draw without them (to compare)
        self._tex: list = []  # per level: (texel texture, normal texture)
        self.detail_strength = DETAIL_STRENGTH
        self._detail = detail_texture_object(ctx)
        self.draws: list[LevelDraw] = []
        # level -> (key, ...) of its ring: (blocks, neighbours, triangles a stride); (decimation
        # errors, edge deviations) when pixel_error is set; (lo, hi) culling boxes. See plan().
        self._rings: dict[int, tuple] = {}
        self._errors: dict[int, tuple] = {}
        self._bounds: dict[int, tuple] = {}
        self.triangles = self.vertices = 0
        self.update_ms = 0.0
        self.plan_ms = 0.0  # CPU time of the last draw's plan (culling, strides, edges: every level)
        self._height_above_ground = 0.0  # the viewer's height over the ground, over the view's zoom (update)
        self._focus = (0.0, 0.0)
        self.zoom = 1.0  # tan(design_fov_deg / 2) / tan(fov / 2) of the last update's view, at least 1
        self._samples = 0  # terrain samples taken by the last update

    @property
    def land_classes(self) -> bool:
        """Whether the base colour comes from the land classes (fixed when the layer is made: its
        shaders are built with or without the class code)."""
        return self._land_classes

    # -- set-up on the first update (the lattice depends on where the camera is)

    def _setup(self, lat: float, lon: float) -> None:
        import moderngl

        levels, n, budget, undulation = self._args
        lattice = self._lattice
        if lattice is None:
            base = lattice_for(self.terrain.describe(), lat, lon)
            f = self._finest_factor
            lattice = type(base)(base.lat0, base.lon0, base.dlat * f, base.dlon * f, base.exact and f >= 1)
        # A coarse lattice (a global 0.25-degree grid) would give coarse levels spanning the globe
        # more than once: the levels stop at the first whose n - 1 cells span 360 degrees of longitude.
        levels = max(1, min(levels, globe_levels(lattice.dlon, n)))
        self.clipmap = Clipmap(self.terrain, lattice, levels, n, budget, undulation)
        self.clipmap.land_classes = self._land_classes
        if self.insets:
            from terrain.inset import cutout_depth_m

            self.clipmap.cutout = lambda lat, lon, spacing_m: cutout_depth_m(self.insets, lat, lon, spacing_m)
        for _ in range(levels):
            t = self.ctx.texture((n, n), 4, dtype="f4")
            t.filter = (moderngl.NEAREST, moderngl.NEAREST)
            nm = self.ctx.texture((2 * n, 2 * n), 4, dtype="f2")
            nm.filter = (moderngl.LINEAR, moderngl.LINEAR)
            nm.repeat_x = nm.repeat_y = True
            self._tex.append((t, nm))

    # -- the TerrainLayer interface

    @property
    def fog_range_m(self) -> float:
        """Half the coarsest level's extent, less two posts, along its shorter side: a level
        is n x n posts of the lattice, so east-west it spans cos(latitude) of its north-south
        metres, and at high latitudes the terrain would end inside the fog there (the polar
        mesh's own where it is drawn)."""
        if self.polar:
            return self.polar_mesh.fog_range_m
        if self.clipmap is None:
            return 1e5
        return self.reach_m(self._focus[0])

    def fog_range_for(self, camera: Camera, width: int, height: int) -> float:
        """The least horizontal distance from ``camera`` to where the terrain ends within its view of
        width x height pixels (the renderer's fog hides it there). Centred on the camera, the
        levels reach :attr:`fog_range_m` (R) all round. Centred a horizontal distance D away (a
        narrow view's aim, :meth:`aimed_focus`), a ray at angle psi from the direction of the
        centre leaves the disc of radius R round it at D cos psi + sqrt(R^2 - D^2 sin^2 psi)
        (sqrt(D^2 - R^2) where it passes by), least at the widest psi in the frame: the axis'
        angle from that direction plus the frustum's half diagonal. The disc's edge behind a
        narrow view, R - D away, is out of its frame: fogging the terrain there would hide the
        very ground it looks at."""
        reach = self.fog_range_m
        if self.polar or self.clipmap is None or self.zoom <= 1.0:  # (a wide view: R, as it always was)
            return reach
        lat, lon, _ = camera.geodetic()
        east, north, _ = enu_basis(lat, lon)
        to_focus = np.asarray(geodetic_to_ecef(*self._focus, 0.0), np.float64).reshape(3) - camera.position_ecef
        fe, fn = float(to_focus @ east), float(to_focus @ north)
        d = math.hypot(fe, fn)
        if d <= 1e-6 * reach:
            return reach
        axis = camera.r_ecef_body[:, 0]
        ae, an = float(axis @ east), float(axis @ north)
        fx, fy = camera.focal(width, height)
        half_diagonal = math.atan(math.sqrt(1.0 / (fx * fx) + 1.0 / (fy * fy)))
        phi = math.pi if math.hypot(ae, an) < 1e-9 else abs(
            (math.atan2(ae, an) - math.atan2(fe, fn) + math.pi) % (2.0 * math.pi) - math.pi)
        psi = min(phi + half_diagonal, math.pi)
        across = d * math.sin(psi)
        if across >= reach:
            return max(math.sqrt(max(d * d - reach * reach, 0.0)), reach - d, 1.0)
        return max(d * math.cos(psi) + math.sqrt(reach * reach - across * across), 1.0)

    def reach_m(self, lat: float) -> float:
        """The clipmap's fog range (:attr:`fog_range_m`) with its focus at latitude ``lat``."""
        k = len(self.clipmap.levels) - 1
        return (0.5 * (self.clipmap.n - 1) - 2.0) * min(self.clipmap.spacing_m(k), self._east_spacing_m(k, lat))

    def _east_spacing_m(self, k: int, lat: float) -> float:
        """Level k's east-west post spacing at latitude ``lat``, metres (the mean Earth radius: for sizes)."""
        return (math.radians(self.clipmap.spacing_deg(k)[1]) * 6_371_000.0
                * math.cos(math.radians(min(abs(lat), 89.999))))

    def _is_polar(self, lat: float) -> bool:
        """Whether to draw the polar mesh with the focus at ``lat`` (POLAR_ASPECT, POLAR_MESH_HYSTERESIS)."""
        k = len(self.clipmap.levels) - 1
        aspect = self._east_spacing_m(k, lat) / self.clipmap.spacing_m(k)
        reach, polar_reach = self.reach_m(lat), self._polar_reach_m()
        slack = POLAR_MESH_HYSTERESIS if self.polar else 1.0
        return aspect < slack * POLAR_ASPECT and reach < slack * polar_reach

    def _polar_reach_m(self) -> float:
        """How far the polar mesh reaches (TerrainMeshLayer.fog_range_m), without building it."""
        window, horizon = self._polar_args["window_m"], self._polar_args["horizon_m"]
        return (horizon if horizon > 0 else window) - REBUILD_FRACTION * window

    @property
    def solid_bounds(self) -> tuple | None:
        """The coarsest level's region, in (lat_min, lat_max, lon_min, lon_max): the clipmap covers
        it (no-data posts draw as water at sea level); the polar mesh's where it is drawn."""
        if self.polar:
            return self.polar_mesh.solid_bounds
        if self.clipmap is None or not self.clipmap.levels[-1].valid:
            return None
        c = self.clipmap
        r = c.levels[-1].region
        lat0, lon0 = c.latlon(len(c.levels) - 1, r.i0 + 1, r.j0 + 1)
        lat1, lon1 = c.latlon(len(c.levels) - 1, r.i1 - 1, r.j1 - 1)
        return (float(max(lat0, -90.0)), float(min(lat1, 90.0)), float(lon0), float(lon1))

    def update(self, camera: Camera) -> None:
        t0 = time.perf_counter()
        lat, lon, h = camera.geodetic()
        if self.clipmap is None:
            self._setup(lat, lon)
        base = self.focus_lat_lon if self.focus_lat_lon is not None else (lat, lon)
        self.zoom = view_zoom(self.design_fov_deg, camera.fov_x_deg)
        first = not any(lv.valid for lv in self.clipmap.levels)
        self._focus = base if first else self.aimed_focus(camera, base)
        self._samples = 0
        self.polar = self._is_polar(self._focus[0])
        if self.polar:  # the clipmap keeps its levels, to catch up from when it is drawn again
            if self.polar_mesh is None:
                self.polar_mesh = TerrainMeshLayer(self.ctx, self.terrain, self.origin, background=True,
                                                   **self._polar_args)
            self.polar_mesh.update(camera)
            self._samples = self.polar_mesh.samples
            self.update_ms = (time.perf_counter() - t0) * 1e3
            return
        if self.polar_mesh is not None:  # left the pole: its next mesh is of no use
            self.polar_mesh.cancel_build()
        self._move(self._focus, unlimited=first)
        if first and self.zoom > 1.0:  # a narrow view: aimed from the levels just loaded, loaded there
            for _ in range(AIM_FIRST_LOAD_PASSES):
                self._focus = self.aimed_focus(camera, base)
                if not self._move(self._focus, unlimited=True):
                    break
        # The height fade (§3.2.2) of a view zoomed Z times: as from Z times lower ("Narrow views").
        agl = max(h - self.clipmap.geoid_undulation_m - self._ground_height(lat, lon), 0.0)
        self._height_above_ground = agl / self.zoom
        self.update_ms = (time.perf_counter() - t0) * 1e3

    def _move(self, focus: tuple[float, float], unlimited: bool) -> bool:
        """Move the levels onto ``focus`` (within the budget unless ``unlimited``) and upload
        what changed; whether any level moved."""
        uploads = self.clipmap.update(*focus, unlimited=unlimited)
        for u in uploads:
            self._upload(u)
        self._samples += self.clipmap.stats.samples
        return bool(uploads)

    def aimed_focus(self, camera: Camera, base: tuple[float, float]) -> tuple[float, float]:
        """The levels' centre (lat, lon degrees) for ``camera``: ``base`` for a view at least as
        wide as design_fov_deg (:attr:`zoom` 1); for a narrower one, the point w = 1 - 1/zoom of
        the way from ``base`` to :meth:`aim_point` (base where there is none): the aimed ground
        then lies in a level whose posts are as many pixels apart as at the design field of view
        (module docstring, "Narrow views")."""
        if self.zoom <= 1.0:
            return base
        target = self.aim_point(camera)
        if target is None:
            return base
        _, _, h = ecef_to_geodetic(target)
        b = np.asarray(geodetic_to_ecef(base[0], base[1], float(h)), np.float64).reshape(3)
        lat, lon, _ = ecef_to_geodetic(b + (1.0 - 1.0 / self.zoom) * (target - b))
        return float(lat), float(lon)

    def aim_point(self, camera: Camera) -> np.ndarray | None:
        """(3,) ECEF: the ground point ``camera``'s optical axis looks at, on the levels' surface
        (Clipmap.heights_at: what is drawn, no terrain query): its first hit of the surface, else
        the ground point nearest the axis in angle (vertical clearance over distance) out to the
        far side of the coarsest level, if that lies within half the horizontal field of view of
        the axis (in the frame); None where neither is, or before the first load."""
        c = self.clipmap
        if c is None or not c.levels[-1].valid:
            return None
        eye, axis = camera.position_ecef, camera.r_ecef_body[:, 0]
        top = c.levels[-1]
        r = top.region
        centre = np.asarray(top.pos_ecef[((r.i0 + r.i1) // 2) % c.n, ((r.j0 + r.j1) // 2) % c.n], np.float64)
        far = float(np.linalg.norm(centre - eye)) + math.sqrt(2.0) * 0.5 * c.extent_m(top.k)
        t = np.geomspace(AIM_MIN_M, max(far, 2.0 * AIM_MIN_M), AIM_SAMPLES)
        points = eye + t[:, None] * axis
        lat, lon, h = ecef_to_geodetic(points)
        ground = c.heights_at(lat, lon)
        clear = h - c.geoid_undulation_m - ground  # NaN where no level holds the point
        with np.errstate(invalid="ignore"):
            cross = np.flatnonzero((clear[:-1] > 0.0) & (clear[1:] <= 0.0))
        if cross.size:  # the first descent through the surface, placed on it between the two samples
            i = int(cross[0])
            return points[i] + clear[i] / (clear[i] - clear[i + 1]) * (points[i + 1] - points[i])
        angle = clear / t
        if not np.isfinite(angle).any():
            return None
        i = int(np.nanargmin(angle))
        if angle[i] > math.tan(math.radians(0.5 * camera.fov_x_deg)):
            return None
        return np.asarray(geodetic_to_ecef(float(lat[i]), float(lon[i]), float(ground[i]) + c.geoid_undulation_m),
                          np.float64).reshape(3)

    @property
    def samples(self) -> int:
        """Terrain samples taken by the last update: the levels' (heights + normals), or, near a
        pole, the posts of the polar mesh installed this frame (TerrainMeshLayer.samples)."""
        return self._samples

    @property
    def rebuilds(self) -> int:
        """Builds of the polar mesh so far (the levels themselves are never rebuilt: they move)."""
        return 0 if self.polar_mesh is None else self.polar_mesh.rebuilds

    @property
    def levels_active(self) -> int:
        return len(self.draws)

    def _ground_height(self, lat: float, lon: float) -> float:
        """MSL height under (lat, lon) from the finest level holding it (no terrain query)."""
        c = self.clipmap
        for level in c.levels:
            if not level.valid:
                continue
            fi, fj = c.focus_index(level.k, lat, lon)
            i, j = round(fi), round(fj)
            r = level.region
            if r.i0 <= i <= r.i1 and r.j0 <= j <= r.j1:
                return float(level.texel[i % c.n, j % c.n, 3])
        return 0.0

    def ground_height_msl(self, lat: float, lon: float) -> float:
        """At least the height MSL of the surface drawn at (lat, lon), for the renderer's near plane
        (renderer.Renderer): the highest corner of the cell holding it in the finest level that
        does, and in the next coarser (a morph moves the finer surface towards it), since every
        point drawn there is a convex combination of those posts (the polar mesh's cell where it
        is drawn). NaN before the first update or where no level holds it."""
        if self.polar:
            return self.polar_mesh.ground_height_msl(lat, lon)
        c = self.clipmap
        if c is None:
            return math.nan
        top, found = math.nan, 0
        for level in c.levels:
            if not level.valid:
                continue
            fi, fj = c.focus_index(level.k, lat, lon)
            i, j = math.floor(fi), math.floor(fj)
            r = level.region
            if not (r.i0 <= i and i + 1 <= r.i1 and r.j0 <= j and j + 1 <= r.j1):
                continue
            corners = level.texel[np.array([i, i, i + 1, i + 1]) % c.n, np.array([j, j + 1, j, j + 1]) % c.n, 3]
            top = float(np.max(corners)) if found == 0 else max(top, float(np.max(corners)))
            found += 1
            if found == 2:
                break
        return top

    def surface_height_msl(self, lat: float, lon: float) -> float:
        """The height MSL of the surface drawn at (lat, lon), as the vertex shader places it: the
        finest drawn level holding it (:meth:`drawn_level_regions`), on its cell's triangle there
        (terrain_mesh.cell_corner_weights: not the bilinear surface, which the triangles part
        from by up to a quarter of the cell's twist), each corner morphed towards the coarser
        level by its alpha (:meth:`vertex_alpha`). A block drawn decimated parts from this by at
        most its pixel_error at the block's distance (block_strides), a small fraction of the
        height of a camera over it (pixel_error / focal length in pixels: 0.0024 at the profiles'
        2 px, 60 degrees across 960 px); the renderer keeps the camera clear of this surface. NaN
        before the first update or where no drawn level holds it."""
        if self.polar:
            return self.polar_mesh.surface_height_msl(lat, lon)
        c = self.clipmap
        if c is None:
            return math.nan
        regions = self.drawn_level_regions()
        for k in sorted(regions):
            r = regions[k]
            fi, fj = c.focus_index(k, lat, lon)
            i, j = math.floor(fi), math.floor(fj)
            if not (r.i0 <= i and i + 1 <= r.i1 and r.j0 <= j and j + 1 <= r.j1):
                continue
            coarse = c.levels[k + 1] if k + 1 in regions else None
            weights = cell_corner_weights(fi - i, fj - j)
            corners = ((i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j))  # SW, SE, NE, NW
            return float(sum(w * self._vertex_height(k, r, coarse, g) for w, g in zip(weights, corners) if w > 0))
        return math.nan

    def surface_heights_msl(self, lats: np.ndarray, lons: np.ndarray) -> np.ndarray:
        """(n,) float64 :meth:`surface_height_msl` at (n,) degrees at once, a pass a drawn level
        (the renderer lifts entities onto it: entities.ground_lifts)."""
        lats, lons = np.asarray(lats, np.float64), np.asarray(lons, np.float64)
        if self.polar:
            return self.polar_mesh.surface_heights_msl(lats, lons)
        out = np.full(lats.shape, math.nan)
        c = self.clipmap
        if c is None:
            return out
        regions = self.drawn_level_regions()
        todo = np.ones(lats.shape, bool)
        for k in sorted(regions):
            r = regions[k]
            fi, fj = c.focus_index(k, lats, lons)
            i, j = np.floor(fi).astype(np.int64), np.floor(fj).astype(np.int64)
            here = todo & (r.i0 <= i) & (i + 1 <= r.i1) & (r.j0 <= j) & (j + 1 <= r.j1)
            if not here.any():
                continue
            coarse = c.levels[k + 1] if k + 1 in regions else None
            i, j, y, x = i[here], j[here], fi[here] - i[here], fj[here] - j[here]
            lower = x >= y  # cell_corner_weights: SW-SE-NE, else SW-NE-NW
            weights = (np.where(lower, 1.0 - x, 1.0 - y), np.where(lower, x - y, 0.0), np.where(lower, y, x),
                       np.where(lower, 0.0, y - x))
            corners = ((i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j))  # SW, SE, NE, NW
            out[here] = sum(w * self._vertex_heights(k, r, coarse, gi, gj) for w, (gi, gj) in zip(weights, corners))
            todo &= ~here
        return out

    def _vertex_heights(self, k: int, region: Rect, coarse, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(n,) float64 :meth:`_vertex_height` of level k's posts (i, j), (n,) int64 each."""
        c = self.clipmap
        h = c.levels[k].texel[i % c.n, j % c.n, 3].astype(np.float64)
        if coarse is None:
            return h
        oi, oj = i & 1, j & 1
        ci, cj = (i - oi) // 2, (j - oj) // 2

        def post(a, b):
            return coarse.texel[a % c.n, b % c.n, 3].astype(np.float64)

        # The mean of the 1, 2 or 4 coarser posts around (i, j), as _vertex_height takes it.
        hc = 0.25 * (post(ci, cj) + post(ci + oi, cj) + post(ci, cj + oj) + post(ci + oi, cj + oj))
        alpha = self._vertex_alphas(k, region, i, j)
        return np.where(alpha >= 1.0, hc, h + alpha * (hc - h))

    def _vertex_alphas(self, k: int, region: Rect, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """(n,) float64 :meth:`vertex_alpha` of level k's posts (i, j), (n,) int64 each."""
        c = self.clipmap
        fi, fj = c.focus_index(k, *self._focus)
        w, half = max(MORPH_WIDTH_FRACTION * c.n, 1.0), (c.n - 1) / 2.0 - 1.0
        gi, gj = i - region.i0, j - region.j0
        d = np.minimum.reduce([gi, gj, region.i1 - region.i0 - gi, region.j1 - region.j0 - gj])
        if c.levels[k].region != clip_region(*active_origin(fi, fj, c.n), c.n):  # lagging
            a_b = np.clip((w + 1.0 - d) / w, 0.0, 1.0)
        else:
            dv = np.maximum(np.abs(gi - (fi - region.i0)), np.abs(gj - (fj - region.j0)))
            a_b = np.where(d <= 0, 1.0, np.clip((dv - (half - w)) / w, 0.0, 1.0))
        return np.clip(a_b + self.level_alpha_h(k), 0.0, 1.0)

    def _vertex_height(self, k: int, region: Rect, coarse, g: tuple[int, int]) -> float:
        """The vertex shader's height MSL (``surface``) of level k's post g = (i, j) drawn in region."""
        c = self.clipmap
        i, j = g
        h = float(c.levels[k].texel[i % c.n, j % c.n, 3])
        if coarse is None:
            return h
        oi, oj = i & 1, j & 1
        ci, cj = (i - oi) // 2, (j - oj) // 2
        posts = [(ci + a, cj + b) for a in range(1 + oi) for b in range(1 + oj)]
        hc = float(np.mean([coarse.texel[a % c.n, b % c.n, 3] for a, b in posts]))
        alpha = self.vertex_alpha(k, region, g)
        return hc if alpha >= 1.0 else h + alpha * (hc - h)

    def vertex_alpha(self, k: int, region: Rect, g: tuple[int, int]) -> float:
        """The vertex shader's morph alpha of level k's post g = (i, j) drawn in region (with the
        coarser level): alpha_b from the viewer's distance (the drawn border's, for a lagging
        level) plus alpha_h (:meth:`level_uniforms` gives the shader the same numbers)."""
        c = self.clipmap
        fi, fj = c.focus_index(k, *self._focus)
        w, half = max(MORPH_WIDTH_FRACTION * c.n, 1.0), (c.n - 1) / 2.0 - 1.0
        gi, gj = g[0] - region.i0, g[1] - region.j0
        d = min(gi, gj, region.i1 - region.i0 - gi, region.j1 - region.j0 - gj)
        if c.levels[k].region != clip_region(*active_origin(fi, fj, c.n), c.n):  # lagging
            a_b = min(max((w + 1.0 - d) / w, 0.0), 1.0)
        elif d <= 0:
            a_b = 1.0
        else:
            dv = max(abs(gi - (fi - region.i0)), abs(gj - (fj - region.j0)))
            a_b = min(max((dv - (half - w)) / w, 0.0), 1.0)
        return min(max(a_b + self.level_alpha_h(k), 0.0), 1.0)

    def drawn_level_regions(self) -> dict[int, Rect]:
        """The levels drawn this frame and their regions (posts): every valid level the viewer's
        height leaves visible (height_alpha < 1; the coarsest always), cropped inside the coarser
        (clipmap.drawn_regions)."""
        c = self.clipmap
        top = len(c.levels) - 1
        drawn = [lv.k for lv in c.levels if lv.valid and
                 (lv.k == top or height_alpha(self._height_above_ground, self.edge_m(lv.k), lv.k == 0) < 1.0)]
        return drawn_regions(c, drawn, margin_cells=math.ceil(max(MORPH_WIDTH_FRACTION * c.n, 1.0)) + 2)

    def level_alpha_h(self, k: int) -> float:
        """Level k's fade by the viewer's height (0 for the coarsest, always drawn; the finest
        level, k = 0, is the thesis' n_max)."""
        c = self.clipmap
        return 0.0 if k == len(c.levels) - 1 else height_alpha(self._height_above_ground, self.edge_m(k), k == 0)

    def edge_m(self, k: int) -> float:
        """Level k's edge(n) (thesis §3.2.2: max(edge_x, edge_y), the sides of its clip region),
        metres, the east-west side at the focus's latitude (the mean Earth radius: for sizes)."""
        c = self.clipmap
        return (c.n - 1) * max(c.spacing_m(k), self._east_spacing_m(k, self._focus[0]))

    def _upload(self, u) -> None:
        level = self.clipmap.levels[u.k]
        tex, nmap = self._tex[u.k]
        if u.what == "texel":
            data = level.texel[u.r0:u.r0 + u.rows, u.c0:u.c0 + u.cols]
            tex.write(np.ascontiguousarray(data).tobytes(), viewport=(u.c0, u.r0, u.cols, u.rows))
        else:
            data = level.normal[u.r0:u.r0 + u.rows, u.c0:u.c0 + u.cols]
            nmap.write(np.ascontiguousarray(data).tobytes(), viewport=(u.c0, u.r0, u.cols, u.rows))

    def plan(self, frame: Frame) -> list[LevelDraw]:
        """What to draw this frame: levels (coarse to fine; drawn in reverse), their regions, alpha_h, visible blocks."""
        c = self.clipmap
        regions = self.drawn_level_regions()
        view_proj = frame.projection @ frame.view
        out = []
        for k in sorted(regions, reverse=True):
            hole = regions.get(k - 1)
            hole_k = None if hole is None else Rect(hole.i0 // 2, hole.j0 // 2, hole.i1 // 2, hole.j1 // 2)
            # Three caches, each recomputed only when what it depends on changes: the ring's blocks
            # (its region and hole), their decimation errors (also the level's posts), their
            # culling boxes (also the coarser level's posts and the origin).
            ring_key = (regions[k], hole_k)
            ring = self._rings.get(k)
            if ring is None or ring[0] != ring_key:
                blk = blocks(ring_rects(regions[k], hole_k), BLOCK)
                ring = self._rings[k] = (ring_key, blk, block_neighbours(blk), block_triangles(blk))
            _, blk, neighbours, counts = ring
            level = c.levels[k]
            coarse = c.levels[k + 1] if k + 1 in regions else None
            errors = deviations = None
            if self.pixel_error is not None:
                # Measured again when the ring or the level's posts change: only the blocks
                # that are new, or whose posts changed (remeasure), in parts on helper
                # threads (by_parts). A finer level's move changes this ring's hole, not
                # its posts; this level's own move shifts every block.
                key = (ring_key, level.version)
                cached = self._errors.get(k)
                if cached is None or cached[0] != key:
                    def measure(b, level=level):
                        return decimation_errors(b, level, c.n, c.water_level_m), edge_deviations(b, level, c.n)

                    previous = None if cached is None else (
                        cached[3], cached[1:3], lambda b, since=cached[0][1]: posts_unchanged(b, level, since))
                    cached = self._errors[k] = (key, *remeasure(measure, blk, previous), blk)
                _, errors, deviations, _ = cached
            # The culling boxes also read the coarser level's posts under each block, and are
            # in the renderer's local frame: a coarser level's move changes few of them.
            key = (ring_key, level.version, None if coarse is None else coarse.version,
                   self.origin.ecef.tobytes())
            bounds = self._bounds.get(k)
            if bounds is None or bounds[0] != key:
                def measure(b, level=level, coarse=coarse):
                    return block_bounds(b, level, coarse, c.n, self.origin)

                previous = None
                # Boxes of another origin, or made with(out) the coarser level, are of no use.
                if bounds is not None and bounds[0][3] == key[3] and (bounds[0][2] is None) == (coarse is None):
                    def unchanged(b, old_key=bounds[0]):
                        ok = posts_unchanged(b, level, old_key[1])
                        if coarse is not None:
                            ok &= posts_unchanged(coarse_footprints(b), coarse, old_key[2])
                        return ok

                    previous = (bounds[3], bounds[1:3], unchanged)
                bounds = self._bounds[k] = (key, *remeasure(measure, blk, previous), blk)
            _, lo, hi, _ = bounds
            seen = visible_blocks(lo, hi, view_proj)
            cells = int(((blk[seen, 2] - blk[seen, 0]) * (blk[seen, 3] - blk[seen, 1])).sum())
            alpha_h = self.level_alpha_h(k)
            strides = morph = variants = None
            triangles = 2 * cells
            border = None  # draw(): every border segment
            if errors is not None:
                # Strides and edges of the whole ring (an edge depends on the block beyond it,
                # seen or not), then the seen blocks'.
                focal_px = frame.camera.focal(frame.width, frame.height)[0] * frame.width / 2.0
                strides, morph = block_strides(errors, lo, hi, frame.camera_local, focal_px, self.pixel_error, counts)
                chord_m = BLOCK * c.spacing_m(k)
                edges = edge_strides(strides, errors, deviations, neighbours, _distances(lo, hi, frame.camera_local),
                                     focal_px, self.pixel_error,
                                     chord_m ** 2 / (8.0 * WGS84_A_M) <= MAX_CORNER_EDGE_SAG_M)
                if k + 1 in regions:
                    edges, spared = border_edges(blk, regions[k], strides, edges)
                    border = border_segments_left(regions[k], blk, spared)
                variants = block_variants(strides, edges)
                tris = np.where(_whole(blk), VARIANT_TRIANGLES[variants],
                                counts[np.arange(len(blk)), _STRIDE_COLUMN[strides]])
                strides, morph, variants = strides[seen], morph[seen], variants[seen]
                triangles = int(tris[seen].sum())
            near, listed = None, ()
            if self._inset_boxes is not None:
                dlat, dlon = c.spacing_deg(k)
                over = blocks_near_insets(blk[seen], self._inset_boxes, c.lattice.lat0, c.lattice.lon0, dlat, dlon)
                near = over.any(axis=1)
                listed = tuple(int(i) for i in np.flatnonzero(over.any(axis=0)))
            out.append(LevelDraw(k, regions[k], alpha_h, blk[seen], cells, strides, triangles, morph, variants, border,
                                 near, listed))
        return out

    def level_uniforms(self, d: LevelDraw, coarse: bool) -> dict:
        """The vertex shader's per-level uniforms for drawing ``d`` (with the coarser level or
        not): {name: value}, bytes for vectors and matrices. What :meth:`draw` sets; tests
        capture the shader's output with the same values."""
        c, o = self.clipmap, self.origin
        r = d.region
        fi, fj = c.focus_index(d.k, *self._focus)
        out = {
            "u_rot": o.basis.T.astype("f4").tobytes(),  # rows E, N, U in ECEF, column-major in GLSL
            "u_origin_ecef": o.ecef.astype("f4").tobytes(),
            "u_origin_mod": np.mod(o.ecef, DETAIL_TILE_M).astype("f4").tobytes(),
            "u_n": c.n, "u_w": max(MORPH_WIDTH_FRACTION * c.n, 1.0), "u_base": (r.i0, r.j0),
            "u_off_fine": o.to_local(c.levels[d.k].origin_ecef).astype("f4").tobytes(),
            "u_has_coarse": int(coarse), "u_region": (0.0, 0.0, float(r.i1 - r.i0), float(r.j1 - r.j0)),
            "u_viewer": (float(fi - r.i0), float(fj - r.j0)), "u_half": (c.n - 1) / 2.0 - 1.0,
            "u_lagging": int(c.levels[d.k].region != clip_region(*active_origin(fi, fj, c.n), c.n)),
            "u_alpha_h": d.alpha_h,
            "u_fine": 0, "u_coarse": 1, "u_nfine": 2, "u_ncoarse": 3, "u_detail": 4,
        }
        if coarse:
            out["u_off_coarse"] = o.to_local(c.levels[d.k + 1].origin_ecef).astype("f4").tobytes()
        if self._inset_masks is not None:
            out.update(self.inset_uniforms(d))
        return out

    def inset_uniforms(self, d: LevelDraw) -> dict:
        """The inset variant's uniforms for drawing ``d``: the insets near its blocks, each with
        the linear map from the lattice index (relative to the region's first post) to its mask's
        texture coordinates (:func:`inset_map`)."""
        c, r, n = self.clipmap, d.region, len(self._inset_masks)
        dlat, dlon = c.spacing_deg(d.k)
        lat0, lon0 = c.latlon(d.k, r.i0, r.j0)
        maps = np.zeros((n, 4), np.float32)
        layers = np.zeros(n, np.int32)
        for slot, i in enumerate(d.insets):
            maps[slot] = inset_map(self._inset_masks[i], float(lat0), float(lon0), dlat, dlon,
                                   0.5 * (r.j1 - r.j0) * dlon)
            layers[slot] = self._inset_masks[i].layer
        return {"u_inset_count": len(d.insets), "u_inset_map": maps.tobytes(), "u_inset_layer": layers.tobytes(),
                "u_inset_mask": INSET_MASK_UNIT}

    @staticmethod
    def set_uniforms(program, values: dict) -> None:
        for name, value in values.items():
            member = program.get(name, None)  # one lookup (``name in program`` walks every member)
            if member is not None:
                if isinstance(value, bytes):
                    member.write(value)
                else:
                    member.value = value

    def draw(self, frame: Frame) -> None:
        import moderngl

        if self.clipmap is None:
            return
        if self.polar:
            self.draws = []
            self.polar_mesh.draw(frame)
            self.triangles, self.vertices = self.polar_mesh.triangles, self.polar_mesh.vertices
            return
        t0 = time.perf_counter()
        self.draws = self.plan(frame)
        self.plan_ms = (time.perf_counter() - t0) * 1e3
        p, bp, ip = self.program, self._border_program, self._inset_program
        for prog in (p, bp) if ip is None else (p, bp, ip):
            frame.write_common(prog)
            prog["u_detail_strength"].value = float(self.detail_strength)
            if self._land_classes:
                prog["u_class_colour"].write(CLASS_COLOURS_F32)
        self._detail.use(4)
        if ip is not None:
            self._inset_mask_texture.use(INSET_MASK_UNIT)
        self.ctx.enable(moderngl.CULL_FACE)
        self.triangles = self.vertices = 0
        drawn = {x.k for x in self.draws}
        for d in reversed(self.draws):  # fine to coarse: near terrain hides far fragments before shading
            if len(d.blocks) == 0:
                continue
            coarse = d.k + 1 in drawn
            uniforms = self.level_uniforms(d, coarse)
            self.set_uniforms(p, uniforms)
            near = None if d.near_insets is None or not d.near_insets.any() else d.near_insets
            if near is not None:
                self.set_uniforms(ip, uniforms)
            self._tex[d.k][0].use(0)
            self._tex[d.k][1].use(2)
            if coarse:
                self._tex[d.k + 1][0].use(1)
                self._tex[d.k + 1][1].use(3)
            r = d.region
            records = np.zeros(len(d.blocks), dtype=[("block", "<i4", 4), ("morph", "<f4")])
            records["block"] = d.blocks - np.array([r.i0, r.j0, r.i0, r.j0], np.int32)
            if d.morph is not None:
                records["morph"] = d.morph
            variants = np.zeros(len(d.blocks), np.int64) if d.variants is None else d.variants
            # One command a mesh in use, the blocks near an inset's after the others' (their own
            # program): (count, instances, first index, base vertex, base instance).
            group = np.zeros(len(d.blocks), np.int64) if near is None else near.astype(np.int64)
            key = group * len(VARIANTS) + variants
            by_mesh = np.argsort(key, kind="stable")
            used, first, count = np.unique(key[by_mesh], return_index=True, return_counts=True)
            mesh = used % len(VARIANTS)
            commands = np.stack([self._index_count[mesh], count, self._first_index[mesh], np.zeros_like(used),
                                 first], -1).astype(np.uint32)
            _write_instances(self._inst, records[by_mesh])
            _write_instances(self._indirect, commands)
            plain = int(np.count_nonzero(used < len(VARIANTS)))
            if plain:
                self._block_vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=plain)
            if plain < len(commands):
                self._inset_block_vao.render_indirect(self._indirect, moderngl.TRIANGLES, count=len(commands) - plain,
                                                      first=plain)
            self.triangles += d.triangles
            self.vertices += len(d.blocks) * (BLOCK + 1) ** 2
            if coarse and self.border_triangles:
                self.set_uniforms(bp, uniforms)
                self.ctx.disable(moderngl.CULL_FACE)  # zero-area: either winding
                for vao, segments in zip(self._border_vaos, border_segments(r) if d.border is None else d.border):
                    if len(segments):
                        _write_instances(self._border_inst, segments)
                        vao.render(moderngl.TRIANGLES, instances=len(segments))
                        self.triangles += len(segments) * (BLOCK // 2)
                self.ctx.enable(moderngl.CULL_FACE)
        self.ctx.disable(moderngl.CULL_FACE)
        check_gl_error(self.ctx, "clipmap draw")

    def release(self) -> None:
        if self.polar_mesh is not None:
            self.polar_mesh.release()
        self._detail.release()
        for t, nm in self._tex:
            t.release()
            nm.release()
        for obj in (self._block_vao, self._grid_vbo, self._targets_vbo, self._block_ibo, self._inst, self._indirect,
                    *self._border_vaos,
                    *self._border_vbos, self._border_ibo, self._border_inst, self.program, self._border_program,
                    self._inset_block_vao, self._inset_program,
                    None if self._inset_masks is None else self._inset_mask_texture):
            if obj is not None:
                obj.release()
        self._tex = []


def _write_instances(buffer, instances: np.ndarray) -> None:
    """Instance records (m, 4) int32, or structured records, into a buffer, grown (twice the
    need) when too small."""
    data = (instances if instances.dtype.names else instances.astype(np.int32)).tobytes()
    if len(data) > buffer.size:
        buffer.orphan(len(data) * 2)
    buffer.write(data)


@functools.lru_cache(maxsize=64)
def border_segments(region: Rect) -> tuple[np.ndarray, np.ndarray]:
    """Instances (i0, j0, i1, j1), relative to the region's first post, of the zero-area border
    triangles of a drawn region: along its first and last rows (segments of BLOCK cells starting
    at even lattice columns), then along its first and last columns. Only borders on an even
    lattice row (column) get them: there the morphed border posts lie on the coarser level's
    edges; a border on an odd one (a lagging level cropped inside the coarser) has no such edge,
    and a triangle there would stand out of the surface."""
    rows_out, cols_out = [], []
    h, w = region.i1 - region.i0, region.j1 - region.j0
    first_j = region.j0 & 1  # relative offset of the first even lattice column
    first_i = region.i0 & 1
    for i in (0, h):
        if (region.i0 + i) & 1 == 0:
            for j in range(first_j, w, BLOCK):
                rows_out.append((i, j, i, min(j + BLOCK, w)))
    for j in (0, w):
        if (region.j0 + j) & 1 == 0:
            for i in range(first_i, h, BLOCK):
                cols_out.append((i, j, min(i + BLOCK, h), j))
    rows, cols = np.array(rows_out, np.int32).reshape(-1, 4), np.array(cols_out, np.int32).reshape(-1, 4)
    rows.setflags(write=False)  # cached: shared by every caller
    cols.setflags(write=False)
    return rows, cols


def clipmap_factory(terrain, **kw):
    """``Renderer(terrain_layer_factory=clipmap_factory(terrain, levels=..., n=...))``."""
    return lambda ctx, origin: ClipmapLayer(ctx, terrain, origin, **kw)


def focus_of(position_ecef) -> tuple[float, float]:
    lat, lon, _ = ecef_to_geodetic(np.asarray(position_ecef, float).reshape(3))
    return float(lat), float(lon)
