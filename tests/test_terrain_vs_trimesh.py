"""Terrain.intersect and Terrain.line_of_sight against trimesh's ray/triangle test on a real DEM.

The oracle is independent of Sortie's ray code: the posts of an 80 x 80 window of
the SRTM3 tile N47E009 (47.03-47.10 N, 9.30-9.37 E, 438-2396 m, read through
terrain.dem) are triangulated here with trimesh, two triangles per cell, each
vertex geodetic_to_ecef(lat, lon, h_msl) taken into a local ENU frame (terrain.los
builds its segments the same way: MSL heights used as ellipsoidal, the geoid
undulation being constant along a ray). Rays are cast by
trimesh.ray.ray_triangle.RayMeshIntersector (numpy + rtree). No Sortie mesh code.

Bound. Sortie intersects the bilinear surface S of the posts, the mesh T is a
triangulation of them; vertically, in each cell,

    |S - T| <= |h00 - h10 - h01 + h11| / 4 + GEOM + EPS <= delta_cell = |d| / 4 + 2 GEOM + EPS

* Twist, |d| / 4. In unit cell coordinates S = a + b x + c y + d x y. A triangle
  of either diagonal interpolates S at its three corners, so S minus its plane is
  d times a quadratic vanishing there: -y (1 - x) and -x (1 - y) for the diagonal
  x = y, x y and (1 - x)(1 - y) for x + y = 1, each at most 1/4 on its triangle
  (at the cell centre).
* Chords, GEOM (4 cm here). T's triangles are flat in ECEF, not in (lat, lon, h).
  Expanding P = geodetic_to_ecef to second order about a point q of a triangle
  with corners q_i (barycentric weights w_i, horizontal offsets s_i = q_i - q,
  height offsets dh_i), the linear terms cancel in sum w_i P(q_i), so
  |P(q) - sum w_i P(q_i)| <= 1/2 sum w_i (c_ss |s_i|^2 + 2 c_sh |s_i| |dh_i|)
  <= (c_ss L^2 + 2 c_sh L H) / 2, L the longest edge, H the triangle's height
  range. Per horizontal metre P's second derivatives are the meridian curvature
  1/M, the parallel's 1/(N cos lat) and tan(lat)/M across, so c_ss = sqrt(2 + 3
  tan^2 lat) / R (+10 % for dM/dlat and h/R, about 1 %); the mixed ones are the
  tilt of the vertical, 1/M and 1/N, so c_sh = 1 / R; d2P/dh2 = 0. R = a (1 - e^2)
  is the least radius of curvature of WGS84. (At an edge's midpoint alone the
  same expansion is the sagitta L^2 / (8 R).) A displacement e between
  corresponding points is a vertical gap of at most |e| sqrt(1 + g^2), g the
  steepest slope.
* EPS = 1 mm: float64 rounding (1 nm at ECEF magnitudes) and Sortie's model error
  (terrain.los.MODEL_ERROR_M = 1 um times the slope, < 20 um).

Along a ray. To first order a vertical gap delta moves a crossing along the unit
ray d (ENU) by delta / |d_up - grad(h) . d_horizontal|, the rate at which the
ray's clearance changes; that is reported. It fails where the clearance is not
linear over the gap (grazing rays, ridges), so the test asserts the exact form:
meshes U and L are T with each vertex shifted up / down by delta_v, the largest
delta_cell of the cells it touches, so these continuous meshes are at least
delta_cell above / below T's geodetic triangles in every cell; GEOM counted
twice (U's chords and T's) leaves EPS to spare in L <= S <= U and L <= T <= U.
For a segment starting above U and ending below L, Sortie's first hit on S and
trimesh's first hit on T both lie between the first hits on U and on L: that
bracket is the per-ray bound. A segment between points above U surely clears S
if it misses U, is surely blocked if it meets L, and is ambiguous otherwise (its
least clearance above S is within the bound).
"""

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_triangle import RayMeshIntersector

from terrain.dem import read_dem
from terrain.geodesy import WGS84_A_M, WGS84_E2, enu_basis, geodetic_to_ecef, radii_of_curvature
from terrain.los import ENDPOINT_TOLERANCE_M
from terrain.raster import STATUS_OK
from terrain.terrain import Terrain

ROW0, COL0, N_POSTS = 40, 360, 80  # window of N47E009 (row 0 south, col 0 west)
EPS_M = 1.0e-3
R_MIN_M = WGS84_A_M * (1.0 - WGS84_E2)  # meridian radius at the equator: the least on WGS84
MARGIN_POSTS = 2  # segment ends stay this far inside the window
N_RAYS, N_PAIRS = 400, 400


class Window:
    """The window's posts, its bounds, the three meshes and the frame they live in."""

    def __init__(self, raster):
        g = raster.georef
        self.lat = g.y0 + (ROW0 + np.arange(N_POSTS)) * g.dy
        self.lon = g.x0 + (COL0 + np.arange(N_POSTS)) * g.dx
        self.dy, self.dx = g.dy, g.dx
        self.h = raster.heights[ROW0:ROW0 + N_POSTS, COL0:COL0 + N_POSTS].astype(np.float64)
        assert raster.filled is None or not raster.filled[ROW0:ROW0 + N_POSTS, COL0:COL0 + N_POSTS].any()
        h00, h01, h10, h11 = self.h[:-1, :-1], self.h[:-1, 1:], self.h[1:, :-1], self.h[1:, 1:]
        self.twist = np.abs(h00 - h10 - h01 + h11) / 4.0

        lat_c, lon_c = self.lat.mean(), self.lon.mean()
        self.origin = geodetic_to_ecef(lat_c, lon_c, 0.0)
        self.rot = np.stack(enu_basis(lat_c, lon_c))  # rows east, north, up
        lat2, lon2 = np.meshgrid(self.lat, self.lon, indexing="ij")
        xy = self.enu(lat2, lon2, self.h)

        # GEOM (module docstring) with every quantity at its worst over the window and the
        # shifted meshes, whose corners move by at most max twist + 1 m (asserted below).
        lat_max = np.radians(self.lat.max())
        c_ss = 1.1 * np.sqrt(2.0 + 3.0 * np.tan(lat_max) ** 2) / R_MIN_M
        c_sh = 1.0 / R_MIN_M
        edge = max(np.hypot(*(xy[1:, 1:, :2] - xy[:-1, :-1, :2]).T).max(),
                   np.hypot(*(xy[1:, :-1, :2] - xy[:-1, 1:, :2]).T).max())  # diagonals: longest edges
        rise = np.maximum.reduce([h00, h01, h10, h11]) - np.minimum.reduce([h00, h01, h10, h11])
        rise_max = rise.max() + 2.0 * (self.twist.max() + 1.0)
        post_min = min(np.hypot(*(xy[:, 1:, :2] - xy[:, :-1, :2]).T).min(),
                       np.hypot(*(xy[1:, :, :2] - xy[:-1, :, :2]).T).min())
        slope_max = np.sqrt(2.0) * rise_max / post_min  # each gradient component <= rise / post
        self.post_min = post_min
        self.geom = 0.5 * (c_ss * edge**2 + 2.0 * c_sh * edge * rise_max) * np.hypot(1.0, slope_max)
        assert self.geom < 0.1, self.geom

        self.delta_cell = self.twist + 2.0 * self.geom + EPS_M
        pad = np.pad(self.delta_cell, 1)  # cells outside the window count 0
        self.delta_v = np.maximum.reduce([pad[:-1, :-1], pad[:-1, 1:], pad[1:, :-1], pad[1:, 1:]])
        assert self.delta_v.max() < self.twist.max() + 1.0

        k = np.arange(N_POSTS * N_POSTS).reshape(N_POSTS, N_POSTS)
        v00, v01, v10, v11 = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
        faces = np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)])  # up-facing

        def mesh(shift):
            v = self.enu(lat2, lon2, self.h + shift).reshape(-1, 3)
            return RayMeshIntersector(trimesh.Trimesh(v, faces, process=False))

        self.mesh, self.upper, self.lower = mesh(0.0), mesh(self.delta_v), mesh(-self.delta_v)

    def enu(self, lat, lon, h):
        """(lat, lon, h) -> (..., 3) metres in the window's ENU frame."""
        return (geodetic_to_ecef(lat, lon, h) - self.origin) @ self.rot.T

    def cell(self, lat, lon):
        """Fractional (row, col) in the window of each point."""
        return (lat - self.lat[0]) / self.dy, (lon - self.lon[0]) / self.dx

    def corners(self, lat, lon, post_values):
        """(4, n) values at the corners of each point's cell."""
        r, c = self.cell(lat, lon)
        i = np.clip(np.floor(r).astype(int), 0, N_POSTS - 2)
        j = np.clip(np.floor(c).astype(int), 0, N_POSTS - 2)
        return np.stack([post_values[i, j], post_values[i, j + 1], post_values[i + 1, j], post_values[i + 1, j + 1]])

    def above_upper(self, lat, lon):
        """Least height (m) above which a point is above U: its cell's highest shifted corner
        (U is flat between corners), plus GEOM for the chords and 1 m to spare."""
        return self.corners(lat, lon, self.h + self.delta_v).max(0) + self.geom + 1.0

    def below_lower(self, lat, lon):
        return self.corners(lat, lon, self.h - self.delta_v).min(0) - self.geom - 1.0

    def delta_at(self, lat, lon):
        """delta_cell of the cell holding each point, the larger of two where it is on a border."""
        r, c = self.cell(lat, lon)
        out = np.zeros(np.size(lat))
        for dr in (-1e-9, 1e-9):
            for dc in (-1e-9, 1e-9):
                i = np.clip(np.floor(r + dr).astype(int), 0, N_POSTS - 2)
                j = np.clip(np.floor(c + dc).astype(int), 0, N_POSTS - 2)
                out = np.maximum(out, self.delta_cell[i, j])
        return out

    def random_points(self, rng, n):
        m = MARGIN_POSTS
        return (rng.uniform(self.lat[m], self.lat[-1 - m], n), rng.uniform(self.lon[m], self.lon[-1 - m], n))

    def inside(self, lat, lon):
        m = MARGIN_POSTS
        return (lat > self.lat[m]) & (lat < self.lat[-1 - m]) & (lon > self.lon[m]) & (lon < self.lon[-1 - m])


def mesh_hits(intersector, a, b, lo=0.0, hi=0.0):
    """First distance t from a where segment a -> b (ENU, (n, 3)) meets the mesh, t in
    [lo, |b - a| - hi]; inf where it does not."""
    length = np.linalg.norm(b - a, axis=1)
    d = (b - a) / length[:, None]
    _, ray, loc = intersector.intersects_id(a, d, multiple_hits=True, return_locations=True)
    ray = np.asarray(ray, dtype=np.int64)
    t = np.einsum("ij,ij->i", np.reshape(loc, (-1, 3)) - a[ray], d[ray])
    keep = (t >= lo) & (t <= length[ray] - hi)
    first = np.full(len(a), np.inf)
    np.minimum.at(first, ray[keep], t[keep])
    return first


@pytest.fixture(scope="module")
def window(hgt_alps):
    raster = read_dem(hgt_alps)
    return Window(raster), Terrain([raster])


def test_window_is_rugged_and_bound_small(window):
    w, _ = window
    assert w.h.max() - w.h.min() > 1500.0
    assert np.median(w.delta_cell) < 2.0, (np.median(w.delta_cell), w.geom)


def test_intersect_matches_trimesh_within_twist_bound(window):
    w, terrain = window
    rng = np.random.default_rng(20240611)
    n = 6000  # candidates; segments whose start is not above U are dropped
    b_lat, b_lon = w.random_points(rng, n)
    b_h = w.below_lower(b_lat, b_lon) - rng.uniform(0.0, 100.0, n)
    dip = np.radians(rng.uniform(10.0, 80.0, n))
    az = rng.uniform(0.0, 2.0 * np.pi, n)
    run = rng.uniform(100.0, 3000.0, n)  # horizontal metres from a to b
    m, nn = radii_of_curvature(b_lat)
    a_lat = b_lat - np.degrees(run * np.cos(az) / m)
    a_lon = b_lon - np.degrees(run * np.sin(az) / (nn * np.cos(np.radians(b_lat))))
    a_h = b_h + run * np.tan(dip)
    ok = w.inside(a_lat, a_lon)
    ok[ok] = a_h[ok] > w.above_upper(a_lat[ok], a_lon[ok])
    assert ok.sum() >= N_RAYS
    keep = np.flatnonzero(ok)[:N_RAYS]
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = (x[keep] for x in (a_lat, a_lon, a_h, b_lat, b_lon, b_h))

    res = terrain.intersect(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    assert res.hit.all() and (res.status == STATUS_OK).all()
    a, b = w.enu(a_lat, a_lon, a_h), w.enu(b_lat, b_lon, b_h)
    t_ours = res.distance_m
    t_mesh, t_up, t_low = (mesh_hits(x, a, b) for x in (w.mesh, w.upper, w.lower))
    # Every segment starts above U and ends below L, so all are unambiguous.
    assert np.isfinite(t_low).all() and (t_up > 0.0).all() and np.isfinite(t_mesh).all()
    bound = t_low - t_up
    assert ((t_up <= t_ours) & (t_ours <= t_low)).all(), np.flatnonzero((t_ours < t_up) | (t_ours > t_low))
    diff = np.abs(t_ours - t_mesh)
    assert (diff <= bound).all(), np.flatnonzero(diff > bound)

    # Ours lies on T within its cell's bound: T's height on the vertical through our hit.
    up = enu_basis(res.lat_deg, res.lon_deg)[2]  # ECEF unit normal: lat, lon constant along it
    top = w.enu(res.lat_deg, res.lon_deg, res.height_msl_m + 1000.0)
    t_vert = mesh_hits(w.mesh, top, top - 2000.0 * (up @ w.rot.T))
    gap = np.abs(1000.0 - t_vert)
    delta = w.delta_at(res.lat_deg, res.lon_deg)
    assert (gap <= delta).all(), np.flatnonzero(gap > delta)

    # First order (module docstring): delta / |d_up - grad(h) . d_h| at our hit; reported only.
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    grad = -res.normal_enu[:, :2] / res.normal_enu[:, 2:]
    first_order = delta / np.abs(d[:, 2] - np.sum(grad * d[:, :2], axis=1))
    msg = (f"along-ray |ours - trimesh| median {np.median(diff):.3g} m, max {diff.max():.3g} m; exact bound "
           f"median {np.median(bound):.3g} m; first-order bound median {np.median(first_order):.3g} m, held by "
           f"{np.mean(diff <= first_order):.1%}; vertical gap median {np.median(gap):.3g} m, max {gap.max():.3g} m, "
           f"at most {np.max(gap / delta):.0%} of its bound")
    print(msg)
    # Not vacuous: the vertical bound is nearly attained, and the along-ray bound is typically
    # a fraction of a post (a hit one cell off, or on the wrong side of a ridge, would fail).
    assert np.max(gap / delta) > 0.5 and np.median(bound) < w.post_min / 4.0, msg


def test_line_of_sight_matches_trimesh_outside_ambiguous_band(window):
    w, terrain = window
    rng = np.random.default_rng(7)
    p_lat, p_lon = w.random_points(rng, N_PAIRS)
    q_lat, q_lon = w.random_points(rng, N_PAIRS)
    p_h = w.above_upper(p_lat, p_lon) + rng.uniform(0.0, 300.0, N_PAIRS)
    q_h = w.above_upper(q_lat, q_lon) + rng.uniform(0.0, 300.0, N_PAIRS)

    los = terrain.line_of_sight(p_lat, p_lon, p_h, q_lat, q_lon, q_h)
    assert (los.status == STATUS_OK).all()
    p, q = w.enu(p_lat, p_lon, p_h), w.enu(q_lat, q_lon, q_h)
    tol = ENDPOINT_TOLERANCE_M
    blocked_mesh, blocked_up, blocked_low = (np.isfinite(mesh_hits(x, p, q, tol, tol))
                                             for x in (w.mesh, w.upper, w.lower))
    assert not (blocked_low & ~blocked_mesh).any() and not (blocked_mesh & ~blocked_up).any()  # L <= T <= U
    clear, blocked = ~blocked_up, blocked_low
    ambiguous = ~clear & ~blocked
    msg = (f"{clear.sum()} surely clear, {blocked.sum()} surely blocked, {ambiguous.sum()} ambiguous "
           f"of {N_PAIRS}; ours visible {los.visible.sum()}, trimesh clear {(~blocked_mesh).sum()}")
    print(msg)
    assert los.visible[clear].all(), msg
    assert not los.visible[blocked].any(), msg
    assert (los.visible == ~blocked_mesh)[~ambiguous].all(), msg
    assert ambiguous.mean() < 0.05 and clear.mean() > 0.2 and blocked.mean() > 0.2, msg
