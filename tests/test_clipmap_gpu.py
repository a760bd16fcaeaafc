"""The clipmap's vertex shader on the GPU (issue #5, "Tests"): what it computes, captured by
transform feedback, against float64 truth. Real EGL (Mesa llvmpipe without a GPU), the Alps
SRTM tile (and the procedural world beyond it for the 1000 km move).

**Capture.** The layer's own vertex shader source (clipmap_layer.VERTEX_SHADER) is compiled a
second time with transform-feedback varyings (v_world, v_height, v_alpha, gl_Position) and run
over the same block grid and per-level uniforms that ClipmapLayer.draw sets, for each level of
the last frame's plan (``layer.draws``; optionally every block of the level, unculled), as
points: one record per (instance, grid vertex), instance by instance (OpenGL 4.5 core,
"Transform Feedback": primitives are recorded in the order they are processed; the first test
checks the order against float64). The lattice index of each record
is the shader's own arithmetic, ``G = base + clamp(block.xy + cell, block.xy, block.zw)``, done
in numpy. The uniform set-up mirrors ClipmapLayer.draw (a method there setting a level's uniforms
on any program would let this test share it instead).

**Bounds.**

- *Morph continuity.* A vertex of level k is v = (1 - a) p + a p_c, p its own post and p_c the
  coarser level's surface there (the thesis' vertex cases, §3.2.1), a = clamp(a_b + a_h). Its
  posts do not change between frames (the storage is the terrain's; toroidal moves write other
  texels), so from one frame to the next it moves along p -> p_c by |p - p_c| |da|. The border
  blend a_b is measured from the level's *drawn* region, which moves in steps of two posts, so
  a_b steps by at most 2 / w (w = n / 10 cells); a_h follows the viewer's height. Per frame:
  |da| <= 2 / w + |da_h| and |dv| <= |p - p_c| (2 / w + |da_h|) + eps, eps the float32 rounding of
  the positions (below). (The thesis' a_b follows the viewer continuously: |da_b| <= v dt / (w s_k),
  about 0.011 for level 0 in the test below; docs/BENCHMARKS.md.)
- *Float32 rounding of a vertex* computed as R f + o (R the float32 ENU rotation, f the texel
  offset from its level's origin, o the level origin's offset from the renderer's origin, both
  float32): each float32 operation rounds to 2^-24 of its magnitude, and there are at most a few
  of them per term, so |v - v64| <= F32_TERMS x 2^-24 x (|f| + |o|), F32_TERMS = 8 (stated
  generously; the measured errors are below a quarter of it).
- *No cracks.* A vertex on the border of level k's drawn region has a = 1, so it lies on the
  coarser level's surface: at an even post the coarse post itself, at an odd one the midpoint of
  the two coarse posts beside it. Against the coarse level's own vertices (what it draws there)
  the gap is within the rounding of both: the bound above for each, summed.
- *Rebasing.* 1000 km from the first origin, after the rebase, vertices relative to the camera
  (gl_Position's view coordinates) are within 1 cm of float64 (Clipmap.levels[k].pos_ecef and
  the same morph) for every vertex within REBASE_RADIUS_M of the camera; farther out the
  float32 view coordinates themselves round to 2^-24 of the distance (as for the reference
  mesh, tests/test_render.py), so they are checked against 8 x 2^-24 x distance.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap import Rect, blocks, ring_rects
from client.render.clipmap_layer import BLOCK, MORPH_WIDTH_FRACTION, VERTEX_SHADER, clipmap_factory, shader_variant
from client.render.gl import check_gl_error
from client.render.renderer import Renderer
from terrain.geodesy import radii_of_curvature

W, H = 96, 54  # the capture does not depend on the image; small frames keep the tests quick
F32_TERMS = 8.0
EPS32 = 2.0 ** -24
SPEED_M_S, DT_S = 300.0, 1.0 / 60.0
REBASE_RADIUS_M = 20_000.0


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


# -- capture ---------------------------------------------------------------------------------------

class Capture:
    """Transform feedback of ClipmapLayer's vertex shader (module docstring)."""

    VARYINGS = ("v_world", "v_height", "v_alpha", "gl_Position")
    FLOATS = 3 + 1 + 1 + 4

    def __init__(self, renderer: Renderer):
        self.r = renderer
        ctx = renderer.ctx
        with ctx:
            self.program = ctx.program(vertex_shader=shader_variant(VERTEX_SHADER, False), varyings=list(self.VARYINGS))
            r, c = np.meshgrid(np.arange(BLOCK + 1), np.arange(BLOCK + 1), indexing="ij")
            self.cells = np.stack([r.ravel(), c.ravel()], -1).astype(np.int32)  # (V, 2) (row, column)
            self.grid = ctx.buffer(self.cells.tobytes())

    def release(self) -> None:
        with self.r.ctx:
            self.grid.release()
            self.program.release()

    def levels(self, cull: bool = True, overrides: dict | None = None) -> dict:
        """{k: dict(G (m, 2) int64 lattice (i, j), world (m, 3) float64 local ENU from the shader's float32,
        height (m,), alpha (m,), view (m, 3) view-space x, y, z from gl_Position)} of the last frame's
        plan, one record per lattice vertex (duplicates at block seams dropped), and "blocks" (the
        level's blocks drawn, or every block of its ring when not ``cull``). ``overrides``: uniforms
        set over the layer's own."""
        layer = self.r.terrain_layer
        draws = layer.draws
        drawn = {d.k for d in draws}
        regions = {d.k: d.region for d in draws}
        out = {}
        with self.r.ctx:
            for d in draws:
                blk = d.blocks
                if not cull:
                    hole = regions.get(d.k - 1)
                    hole_k = None if hole is None else Rect(hole.i0 // 2, hole.j0 // 2, hole.i1 // 2, hole.j1 // 2)
                    blk = blocks(ring_rects(d.region, hole_k), BLOCK)
                if len(blk) == 0:
                    continue
                out[d.k] = self._level(d, blk, d.k + 1 in drawn, overrides or {})
                out[d.k]["blocks"] = blk
            check_gl_error(self.r.ctx, "transform feedback capture")
        return out

    def _level(self, d, blk: np.ndarray, coarse: bool, overrides: dict) -> dict:
        """Set the uniforms ClipmapLayer.draw sets for level d.k, and capture its vertices."""
        import moderngl

        layer, p = self.r.terrain_layer, self.program
        origin, cam = layer.origin, self.last_camera
        layer.set_uniforms(p, {"u_view": cam.view_matrix(origin).T.astype("f4").tobytes(),
                               "u_projection": cam.projection(self.r.width, self.r.height).T.astype("f4").tobytes(),
                               **layer.level_uniforms(d, coarse), **overrides})
        r = d.region
        layer._tex[d.k][0].use(0)
        if coarse:
            layer._tex[d.k + 1][0].use(1)
        inst = (blk - np.array([r.i0, r.j0, r.i0, r.j0])).astype(np.int32)
        ctx = self.r.ctx
        ibuf = ctx.buffer(inst.tobytes())
        n_out = len(inst) * len(self.cells)
        obuf = ctx.buffer(reserve=n_out * self.FLOATS * 4)
        vao = ctx.vertex_array(p, [(self.grid, "2i", "in_cell"), (ibuf, "4i/i", "in_block")])
        vao.transform(obuf, mode=moderngl.POINTS, vertices=len(self.cells), instances=len(inst))
        rec = np.frombuffer(obuf.read(), np.float32).reshape(n_out, self.FLOATS).astype(np.float64)
        for obj in (vao, ibuf, obuf):
            obj.release()
        g = np.clip(blk[:, None, :2] + self.cells[None], blk[:, None, :2], blk[:, None, 2:]).reshape(-1, 2)
        lattice = g.astype(np.int64)  # region-relative g is already base-relative: blocks hold lattice posts
        _, first = np.unique(lattice[:, 0] * (1 << 32) + lattice[:, 1], return_index=True)
        rec, lattice = rec[first], lattice[first]
        fx, fy = self.last_camera.focal(self.r.width, self.r.height)
        clip = rec[:, 5:9]
        view = np.stack([clip[:, 0] / fx, clip[:, 1] / fy, -clip[:, 3]], -1)
        return {"G": lattice, "world": rec[:, 0:3], "height": rec[:, 3], "alpha": rec[:, 4], "view": view}

    def render(self, camera: Camera):
        self.last_camera = camera
        return self.r.render(camera)


def truth_ecef(layer, k: int, G: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fine post p, coarse surface p_c, morphed v = (1 - a) p + a p_c), each (m, 3) float64 ECEF, of level k's
    lattice vertices G (m, 2) from the CPU storage (pos_ecef): the thesis' vertex cases in float64."""
    c = layer.clipmap
    n = c.n
    p = c.levels[k].pos_ecef[G[:, 0] % n, G[:, 1] % n]
    if k + 1 >= len(c.levels) or not c.levels[k + 1].valid:
        return p, p, p
    odd = G & 1
    base = (G - odd) // 2
    coarse = c.levels[k + 1].pos_ecef
    s = coarse[base[:, 0] % n, base[:, 1] % n].copy()
    s += np.where(odd[:, :1] == 1, coarse[(base[:, 0] + 1) % n, base[:, 1] % n], 0.0)
    s += np.where(odd[:, 1:] == 1, coarse[base[:, 0] % n, (base[:, 1] + 1) % n], 0.0)
    s += np.where((odd[:, :1] == 1) & (odd[:, 1:] == 1), coarse[(base[:, 0] + 1) % n, (base[:, 1] + 1) % n], 0.0)
    pc = s / ((1 + odd[:, :1]) * (1 + odd[:, 1:]))
    a = alpha[:, None]
    return p, pc, (1.0 - a) * p + a * pc


def to_ecef(origin, local: np.ndarray) -> np.ndarray:
    return origin.ecef + local @ origin.basis


def rounding_bound_m(layer, k: int) -> float:
    """F32_TERMS x 2^-24 x (largest texel offset of level k and k + 1 + their origins' offsets), metres."""
    c, o = layer.clipmap, layer.origin
    ks = [k] + ([k + 1] if k + 1 < len(c.levels) and c.levels[k + 1].valid else [])
    f = max(float(np.abs(c.levels[j].texel[..., :3]).max()) for j in ks)
    off = max(float(np.linalg.norm(o.to_local(c.levels[j].origin_ecef))) for j in ks)
    return F32_TERMS * EPS32 * (math.sqrt(3.0) * f + off)


def straight_path(lat: float, lon: float, alt_msl: float, heading: float, pitch: float, steps: int) -> list:
    out = []
    for _ in range(steps):
        out.append(Camera.from_geodetic(lat, lon, alt_msl, heading, pitch, fov_x_deg=90.0))
        m, n = radii_of_curvature(lat)
        d = SPEED_M_S * DT_S
        lat += math.degrees(d * math.cos(math.radians(heading)) / float(m))
        lon += math.degrees(d * math.sin(math.radians(heading)) / (float(n) * math.cos(math.radians(lat))))
    return out


# -- the tests -------------------------------------------------------------------------------------

def test_capture_reproduces_the_cpu_storage(alps):
    """The capture is the shader's arithmetic: unmorphed vertices are their posts (float64 pos_ecef)
    within the rounding bound, and heights are the stored heights."""
    with Renderer(alps, W, H, terrain_layer_factory=clipmap_factory(alps, levels=5, n=63, budget=10 ** 6)) as r:
        cap = Capture(r)
        try:
            cap.render(Camera.from_geodetic(47.3, 9.4, 3000.0, 30.0, -10.0, fov_x_deg=90.0))
            layer = r.terrain_layer
            got = cap.levels(cull=False)
            assert len(got) >= 3
            for k, v in got.items():
                p, pc, truth = truth_ecef(layer, k, v["G"], v["alpha"])
                err = np.linalg.norm(to_ecef(layer.origin, v["world"]) - truth, axis=1)
                assert err.max() <= rounding_bound_m(layer, k), (k, err.max(), rounding_bound_m(layer, k))
                c = layer.clipmap
                h = c.levels[k].texel[v["G"][:, 0] % c.n, v["G"][:, 1] % c.n, 3]
                still = v["alpha"] == 0
                assert np.array_equal(v["height"][still], h[still])
        finally:
            cap.release()


def lattice_keys(G: np.ndarray) -> np.ndarray:
    """(m,) int64 keys of lattice indices (m, 2) (|i|, |j| < 2^30)."""
    return (G[:, 0] + (1 << 30)) * (1 << 31) + (G[:, 1] + (1 << 30))


def test_morph_is_continuous_at_constant_speed(alps):
    """300 m/s, 1/60 s frames across region moves of levels 0 and 1: every lattice vertex drawn in two
    consecutive frames moves along its morph line by |p - p_c| |da|, with |da| <= 2 / w + |da_h|."""
    cams = straight_path(47.22, 9.30, 3200.0, 60.0, -12.0, 64)  # 320 m: level 0 moves 2-3 times, level 1 once
    n = 63
    w = MORPH_WIDTH_FRACTION * n
    with Renderer(alps, W, H, terrain_layer_factory=clipmap_factory(alps, levels=5, n=n, budget=10 ** 6)) as r:
        cap = Capture(r)
        try:
            layer = r.terrain_layer
            prev, region_moves, worst = None, 0, {}
            for cam in cams:
                cap.render(cam)
                draws = {d.k: d for d in layer.draws}
                now = {k: (v, draws[k], to_ecef(layer.origin, v["world"])) for k, v in cap.levels(cull=False).items()}
                for k, (v, d, e) in now.items() if prev else ():
                    if k not in prev:
                        continue
                    pv, pd, pe = prev[k]
                    region_moves += int(pd.region != d.region)
                    _, a, b = np.intersect1d(lattice_keys(v["G"]), lattice_keys(pv["G"]), return_indices=True)
                    da = np.abs(v["alpha"][a] - pv["alpha"][b])
                    # alpha_b follows the viewer: it changes by (viewer motion in cells) / w a frame
                    # (< 0.01 here), far below the 2 / w step a region move gave when it was measured
                    # from the region's edge (which this bound, half of that, catches).
                    allowed_da = 1.0 / w + abs(d.alpha_h - pd.alpha_h) + 1e-6
                    assert da.max() <= allowed_da, (k, da.max(), allowed_da)
                    p, pc, _ = truth_ecef(layer, k, v["G"][a], v["alpha"][a])
                    moved = np.linalg.norm(e[a] - pe[b], axis=1)
                    bound = np.linalg.norm(p - pc, axis=1) * da + 2.0 * rounding_bound_m(layer, k)
                    assert np.all(moved <= bound), (k, float((moved - bound).max()))
                    wm, wd = worst.get(k, (0.0, 0.0))
                    worst[k] = (max(wm, float(moved.max())), max(wd, float(da.max())))
                prev = now
            check_gl_error(r.ctx, "morph frames")
            assert region_moves >= 3 and {0, 1} <= set(worst)
            assert worst[0][1] > 0  # level 0 did morph between frames
            print("\nmorph, per level: largest vertex move (m), largest |da| (2/w = %.3f):" % (2 / w),
                  {k: (round(m, 2), round(a, 3)) for k, (m, a) in sorted(worst.items())})
        finally:
            cap.release()


def border_gaps(layer, levels: dict) -> dict:
    """{k: (gaps (m,) metres, alpha (m,), bound metres)}: for each level k drawn inside a drawn coarser
    level, the distance from each vertex on its drawn region's border to the coarser level's surface
    there as that level draws it (its captured vertices: the coarse post itself at an even post, the
    midpoint of the two coarse posts beside an odd one), in float64 ECEF from the captured float32."""
    out = {}
    regions = {d.k: d.region for d in layer.draws}
    for k, v in levels.items():
        if k + 1 not in levels:
            continue
        r = regions[k]
        G = v["G"]
        on = (G[:, 0] == r.i0) | (G[:, 0] == r.i1) | (G[:, 1] == r.j0) | (G[:, 1] == r.j1)
        G, fine = G[on], to_ecef(layer.origin, v["world"][on])
        cv = levels[k + 1]
        coarse = to_ecef(layer.origin, cv["world"])
        index = {key: i for i, key in enumerate(lattice_keys(cv["G"]))}
        odd = G & 1
        lo = (G - odd) // 2
        hi = lo + odd
        a = np.array([index[x] for x in lattice_keys(lo)])
        b = np.array([index[x] for x in lattice_keys(hi)])
        gaps = np.linalg.norm(fine - 0.5 * (coarse[a] + coarse[b]), axis=1)
        out[k] = (gaps, v["alpha"][on], rounding_bound_m(layer, k) + rounding_bound_m(layer, k + 1))
    return out


def check_border_gaps(r: Renderer, cap: Capture, camera: Camera, lagging: bool) -> None:
    cap.render(camera)
    layer = r.terrain_layer
    c = layer.clipmap
    assert (c.stats.levels_behind > 0) == lagging, c.stats
    cropped = [d.k for d in layer.draws if d.region != c.levels[d.k].region]
    assert bool(cropped) == lagging, cropped  # a level that lags is cropped by the coarser one
    gaps = border_gaps(layer, cap.levels(cull=False))
    assert len(gaps) >= 2
    print(f"\nborder gaps ({'lagging' if lagging else 'steady'}), per level: largest (m), bound (m):",
          {k: (float(f"{g.max():.2g}"), float(f"{b:.2g}")) for k, (g, _, b) in sorted(gaps.items())})
    for k, (gap, alpha, bound) in gaps.items():
        assert np.all(alpha == 1.0), (k, alpha.min())
        assert gap.max() <= bound, (k, gap.max(), bound)
    check_gl_error(r.ctx, "crack frames")


CRACK_CAMERA = Camera.from_geodetic(47.4, 9.6, 2400.0, 200.0, -20.0, fov_x_deg=90.0)
JUMPED_CAMERA = Camera.from_geodetic(47.43, 9.66, 2400.0, 200.0, -20.0, fov_x_deg=90.0)  # 5.7 km on


def test_no_cracks_at_level_borders(alps):
    """Border vertices of every level sit on the coarser level's edges as it draws them (a = 1), within
    the float32 rounding of both."""
    with Renderer(alps, W, H, terrain_layer_factory=clipmap_factory(alps, levels=6, n=63, budget=30_000)) as r:
        cap = Capture(r)
        try:
            check_border_gaps(r, cap, CRACK_CAMERA, lagging=False)
        finally:
            cap.release()


def test_no_cracks_when_finer_levels_lag_behind(alps):
    """After a 5.7 km jump with a small budget the finer levels lag behind and are cropped by the coarser
    ones (thesis §3.1.4); their borders still sit on the coarser level's surface as it is drawn."""
    with Renderer(alps, W, H, terrain_layer_factory=clipmap_factory(alps, levels=6, n=63, budget=30_000)) as r:
        cap = Capture(r)
        try:
            cap.render(CRACK_CAMERA)
            check_border_gaps(r, cap, JUMPED_CAMERA, lagging=True)
        finally:
            cap.release()


@pytest.mark.parametrize("alpha_h", [None, 1.0])
def test_culling_boxes_hold_every_vertex_of_their_blocks(alps, alpha_h):
    """Every vertex the shader makes of a block, unmorphed, as drawn (None) or fully morphed
    (alpha_h = 1), lies inside the block's culling box (clipmap_layer.block_bounds), on a
    settled clipmap and on one whose finer levels lag behind and are cropped."""
    from client.render.clipmap_layer import block_bounds

    with Renderer(alps, W, H, terrain_layer_factory=clipmap_factory(alps, levels=6, n=63, budget=30_000)) as r:
        cap = Capture(r)
        try:
            for camera in (CRACK_CAMERA, JUMPED_CAMERA):
                cap.render(camera)
                layer = r.terrain_layer
                c = layer.clipmap
                drawn = {d.k for d in layer.draws}
                got = cap.levels(cull=False, overrides=None if alpha_h is None else {"u_alpha_h": alpha_h})
                assert len(got) >= 4
                for k, v in got.items():
                    blk = v["blocks"]
                    coarse = c.levels[k + 1] if k + 1 in drawn else None
                    lo, hi = block_bounds(blk, c.levels[k], coarse, c.n, layer.origin)
                    G, world = v["G"], v["world"]
                    inside = ((blk[:, None, 0] <= G[None, :, 0]) & (G[None, :, 0] <= blk[:, None, 2])
                              & (blk[:, None, 1] <= G[None, :, 1]) & (G[None, :, 1] <= blk[:, None, 3]))
                    assert inside.any(axis=0).all()
                    b, vtx = np.nonzero(inside)
                    out = np.maximum(lo[b] - world[vtx], world[vtx] - hi[b]).max(axis=1)
                    assert out.max() <= 0.0, (k, out.max())
        finally:
            cap.release()


def test_rebasing_1000_km_away_keeps_vertices_within_a_centimetre(hgt_alps):
    """The camera 1000 km from the renderer's first origin (off the Alps tile: the procedural world
    answers there): after the rebase every vertex within REBASE_RADIUS_M of the camera is within 1 cm
    of float64 in view space, and the rest within 8 x 2^-24 of its distance; without rebasing (an origin
    that never moves) the near ones are not."""
    from terrain.dem import read_dem
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    world = Terrain([read_dem(hgt_alps), ProceduralTerrain(seed=11)])
    first = Camera.from_geodetic(47.3, 9.4, 3000.0, 90.0, -10.0, fov_x_deg=90.0)
    lat = 47.3
    _, n_radius = radii_of_curvature(lat)
    lon = 9.4 + math.degrees(1_000_000.0 / (float(n_radius) * math.cos(math.radians(lat))))
    away = Camera.from_geodetic(lat, lon, 3000.0, 90.0, -10.0, fov_x_deg=90.0)
    errors = {}
    for rebase_m in (4000.0, 1e9):
        fac = clipmap_factory(world, levels=5, n=63, budget=10 ** 6)
        with Renderer(world, W, H, terrain_layer_factory=fac, rebase_distance_m=rebase_m) as r:
            cap = Capture(r)
            try:
                cap.render(first)
                origin0 = r.origin.ecef.copy()
                cap.render(away)
                assert r.terrain_layer.clipmap.stats.levels_behind == 0
                if rebase_m < 1e9:
                    assert r.stats.rebased and np.linalg.norm(away.position_ecef - origin0) > 990_000.0
                near, far = [], []
                for k, v in cap.levels(cull=False).items():
                    truth = away.to_view(truth_ecef(r.terrain_layer, k, v["G"], v["alpha"])[2])
                    err = np.linalg.norm(v["view"] - truth, axis=1)
                    dist = np.linalg.norm(truth, axis=1)
                    near.append(err[dist <= REBASE_RADIUS_M])
                    far.append(err[dist > REBASE_RADIUS_M] / dist[dist > REBASE_RADIUS_M])
                check_gl_error(r.ctx, "rebase frames")
                errors[rebase_m] = (float(np.concatenate(near).max()), float(np.concatenate(far).max()))
            finally:
                cap.release()
    (near_m, far_rel), (unrebased_m, _) = errors[4000.0], errors[1e9]
    print(f"\nrebased: near {near_m * 1e3:.2f} mm, far {far_rel / EPS32:.2f} x 2^-24 x distance; "
          f"never rebased: near {unrebased_m * 1e3:.0f} mm")
    assert near_m < 0.01, near_m
    assert far_rel < 8.0 * EPS32, far_rel / EPS32
    assert unrebased_m > 0.01, unrebased_m


def test_shader_modulo_is_exact_for_every_lattice_index():
    """The shaders' toroidal wrap (clipmap_layer.GLSL_PMOD), run on the GPU by transform feedback,
    equals numpy's floor modulo for every n of the profiles and the normal maps (2n) at exact
    multiples of n and one either side, negative indices, and indices past 2^24 (a lattice finer
    than the DEM, or a global one at 1"). Its float form (a - m floor(a / m)) failed here past
    2^24 on llvmpipe, and at multiples of 255 on an NVIDIA H200 (a x rcp(m) one ulp low)."""
    import moderngl

    from client.render.clipmap_layer import GLSL_PMOD
    from client.render.gl import create_context

    ks = np.concatenate([np.arange(-40, 41), np.arange(-2 ** 20, 2 ** 20, 997), 2 ** np.arange(20, 31) // 3])
    ctx = create_context()
    try:
        ctx.simple_framebuffer((1, 1)).use()  # draws, transform feedback too, need a complete framebuffer
        prog = ctx.program(vertex_shader="#version 330 core\n" + GLSL_PMOD + """
            uniform int u_m;
            in int in_a;
            out int v_r;
            void main() { v_r = pmod(in_a, u_m); }""", varyings=["v_r"])
        for m in (63, 127, 255, 511, 126, 254, 510, 1022):
            a = np.unique(np.concatenate([ks * m + d for d in (-1, 0, 1)] + [ks]))
            a = a[np.abs(a) < 2 ** 31 - 1].astype(np.int32)
            prog["u_m"].value = m
            src, dst = ctx.buffer(a.tobytes()), ctx.buffer(reserve=a.nbytes)
            vao = ctx.vertex_array(prog, [(src, "i", "in_a")])
            vao.transform(dst, mode=moderngl.POINTS, vertices=len(a))
            got = np.frombuffer(dst.read(), np.int32)
            want = np.mod(a.astype(np.int64), m)
            bad = np.flatnonzero(got != want)
            assert len(bad) == 0, f"m={m}: pmod({a[bad[:5]].tolist()}) = {got[bad[:5]].tolist()}, want {want[bad[:5]].tolist()}"
            for obj in (vao, src, dst):
                obj.release()
        check_gl_error(ctx, "pmod capture")
    finally:
        ctx.release()
