"""Right-triangulated irregular networks (RTIN): an error-bounded adaptive triangulation of a
(2^k + 1) x (2^k + 1) height grid, for terrain meshes that keep their error with fewer triangles.

**The hierarchy** (Evans, Kirkpatrick and Townsend 2001, "Right-triangulated irregular networks",
Algorithmica 30(2); the numbering after Agafonkin's Martini). The square is cut along a diagonal
into two right isosceles triangles; a triangle (a, b, c), hypotenuse a-b and right angle at c,
splits at the hypotenuse's midpoint m into (c, a, m) and (b, c, m), down to triangles whose legs
join neighbouring posts. Triangle ids: 2 and 3 are the two halves of the square, and the children
of id t are 2t and 2t + 1, so a deeper triangle always has a larger id. A triangulation is the
leaves where the splitting stops. It is conforming (no T-junction, so no crack) when a triangle
and the one across its hypotenuse split together: both halve the same hypotenuse, so the decision
is taken once, at the midpoint post.

**The error is exact.** err(T) is the largest |z(p) - plane_T(x(p), y(p))| over the grid posts p
in T (its edges included), plane_T the plane through T's three corners (x, y, z), each post at
its own horizontal position (x(p), y(p)): its vertical distance from T's plane. The positions are
the caller's. By default (x, y) are a post's column and row and z the grid's value; a terrain
mesh (terrain/mesh.py) passes each post's east, north and up in its local ENU frame, so the bound
holds in the frame the vertices are drawn in, Earth's curvature included (the up of a post at a
distance L from the frame's origin drops by about L^2 / (2R), 255 m at 57 km, which a bound on
the heights alone never sees). Vertical is at least the perpendicular distance, so each post is
within the bound of its triangles' planes in 3-D too. Martini instead compares each midpoint
with its hypotenuse's interpolation, which is not the final mesh's error. A midpoint's E is the
largest err of the triangles whose hypotenuse it halves and the E of their children's midpoints,
computed finest level first. A leaf T then has err(T) <= E(m_T) <= max_error, so every grid post
is within max_error of the mesh; and a post's E >= any E below it, so a triangle splits whenever
a descendant must (the forced splits that keep the mesh conforming). Posts without data (NaN)
make their triangles' error infinite, as does a triangle whose corners' (x, y) lie on a line (no
height over it): they split to the finest triangles, and those with a corner without data are
left out.

Cost: every level's triangles cover the square once, and each row of a triangle visits only the
posts inside it, so the error pass visits about (2^k + 1)^2 posts a level over 2k levels, each
post's (x, y, z) held together (1025^2 posts: 0.5-0.8 s in one compiled pass, measured on a
loaded 2-core machine where the grid-only pass before took 0.35-0.5 s).
"""

from __future__ import annotations

import numba
import numpy as np

from sortie.errors import InvalidArgument


def grid_size_for(points: int) -> int:
    """The side 2^k + 1 (k >= 1) of the smallest RTIN grid with at least ``points`` posts a side."""
    k = 1
    while (1 << k) + 1 < points:
        k += 1
    return (1 << k) + 1


@numba.njit(cache=True, nogil=True)
def _corners(tid, size):
    """(ax, ay, bx, by, cx, cy) of triangle ``tid`` (x a column, y a row; hypotenuse a-b)."""
    nbits = 0
    t = tid
    while t > 1:
        t >>= 1
        nbits += 1
    if (tid >> (nbits - 1)) & 1 == 0:
        ax, ay, bx, by, cx, cy = 0, 0, size, size, size, 0
    else:
        ax, ay, bx, by, cx, cy = size, size, 0, 0, 0, size
    for i in range(nbits - 2, -1, -1):
        mx = (ax + bx) // 2
        my = (ay + by) // 2
        if (tid >> i) & 1 == 0:
            ax, ay, bx, by, cx, cy = cx, cy, ax, ay, mx, my
        else:
            ax, ay, bx, by, cx, cy = bx, by, cx, cy, mx, my
    return ax, ay, bx, by, cx, cy


@numba.njit(cache=True, nogil=True)
def _triangle_error(p, ax, ay, bx, by, cx, cy):
    """Largest |z - plane(x, y)| over the posts (x, y, z) = p[row, col] in the triangle whose
    corners are the grid posts (ax, ay), (bx, by), (cx, cy) (a column, a row; edges included),
    the plane through the corners' (x, y, z); inf if a post there has no data (z NaN) or the
    corners' (x, y) lie on a line."""
    xa, ya, za = p[ay, ax, 0], p[ay, ax, 1], p[ay, ax, 2]
    ub, vb, wb = p[by, bx, 0] - xa, p[by, bx, 1] - ya, p[by, bx, 2] - za
    uc, vc, wc = p[cy, cx, 0] - xa, p[cy, cx, 1] - ya, p[cy, cx, 2] - za
    dp = ub * vc - vb * uc  # twice the signed area in (x, y)
    if dp == 0.0:
        return np.inf
    # The plane z = za + gx (x - xa) + gy (y - ya) through the three corners (Cramer's rule).
    gx = (wb * vc - vb * wc) / dp
    gy = (ub * wc - wb * uc) / dp
    d = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)  # twice the signed area on the grid
    sign = 1 if d > 0 else -1
    worst = 0.0
    for j in range(min(ay, by, cy), max(ay, by, cy) + 1):
        # The row's posts inside: each edge function s * n(i) = s * (n0 + k i) >= 0 bounds i.
        lo = min(ax, bx, cx)
        hi = max(ax, bx, cx)
        for n0, k in (((bx * (cy - j) - (by - j) * cx), (by - cy)),
                      ((cx * (ay - j) - (cy - j) * ax), (cy - ay)),
                      ((ax * (by - j) - (ay - j) * bx), (ay - by))):
            n0 *= sign
            k *= sign
            if k > 0:
                lo = max(lo, -(n0 // k))  # the least i with n0 + k i >= 0: ceil(-n0 / k)
            elif k < 0:
                hi = min(hi, n0 // -k)  # the greatest: floor(n0 / -k)
            elif n0 < 0:
                hi = lo - 1
        for i in range(lo, hi + 1):
            v = p[j, i, 2]
            if v != v:
                return np.inf
            e = abs(v - za - gx * (p[j, i, 0] - xa) - gy * (p[j, i, 1] - ya))
            if e > worst:
                worst = e
    return worst


@numba.njit(cache=True, nogil=True)
def midpoint_errors(p):
    """E (the grid's shape) of a (2^k + 1)^2 grid of posts at p[row, col] = (x, y, z): at each
    triangle's hypotenuse midpoint, the largest exact error of the triangles that split there
    and below."""
    size = p.shape[0] - 1
    E = np.zeros(p.shape[:2])
    depth = 0
    while (1 << depth) < size:
        depth += 1
    last = (1 << (2 * depth + 2)) - 1  # the finest triangles: legs one post long
    for tid in range(last, 1, -1):
        ax, ay, bx, by, cx, cy = _corners(tid, size)
        if abs(ax - cx) + abs(ay - cy) <= 1:
            continue  # no post inside but its corners
        mx = (ax + bx) // 2
        my = (ay + by) // 2
        e = _triangle_error(p, ax, ay, bx, by, cx, cy)
        if abs(mx - cx) + abs(my - cy) > 1:  # its children split too: their midpoints' E
            e = max(e, E[(ay + cy) // 2, (ax + cx) // 2], E[(by + cy) // 2, (bx + cx) // 2])
        if e > E[my, mx]:
            E[my, mx] = e
    return E


@numba.njit(cache=True, nogil=True)
def _leaves(h, E, max_error):
    size = h.shape[0] - 1
    cols = size + 1
    out = np.empty((2 * size * size, 3), np.int64)
    n = 0
    stack = np.empty((8 * 64 + 8, 6), np.int64)
    stack[0] = (0, 0, size, size, size, 0)
    stack[1] = (size, size, 0, 0, 0, size)
    sp = 2
    while sp > 0:
        sp -= 1
        ax, ay, bx, by, cx, cy = stack[sp]
        mx = (ax + bx) // 2
        my = (ay + by) // 2
        if abs(ax - cx) + abs(ay - cy) > 1 and E[my, mx] > max_error:
            stack[sp] = (bx, by, cx, cy, mx, my)
            stack[sp + 1] = (cx, cy, ax, ay, mx, my)
            sp += 2
            continue
        if h[ay, ax] == h[ay, ax] and h[by, bx] == h[by, bx] and h[cy, cx] == h[cy, cx]:
            out[n, 0] = ay * cols + ax
            out[n, 1] = by * cols + bx
            out[n, 2] = cy * cols + cx
            n += 1
    return out[:n]


def rtin_faces(heights, max_error_m: float, east_north=None) -> np.ndarray:
    """(m, 3) int64 triangles (grid indices row * cols + col) of the RTIN of ``heights`` ((2^k + 1)
    square float64 m, row 0 north; NaN: no data) within ``max_error_m`` of every post, measured
    along the heights' axis, counter-clockwise seen from above when row 0 is north and column 0
    west (as terrain.mesh.grid_faces). ``east_north``: (2^k + 1, 2^k + 1, 2) float64 m, each post's
    horizontal position in the frame whose up ``heights`` is (terrain.mesh: ENU), so the error is
    its vertical distance from the triangle's plane there; None: the grid's own (column, row)."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    size = h.shape[0] - 1
    if h.ndim != 2 or h.shape[0] != h.shape[1] or size < 2 or size & (size - 1):
        raise InvalidArgument("heights", "an RTIN grid is (2^k + 1) x (2^k + 1) posts, k >= 1", value=list(h.shape))
    if not (np.isfinite(max_error_m) and max_error_m >= 0.0):
        raise InvalidArgument("max_error_m", "must be a finite number of metres, 0 or more", value=max_error_m)
    points = np.zeros(h.shape + (3,))  # (x, y, z) a post, together: one cache line
    points[..., 2] = h
    if east_north is None:
        points[..., 1], points[..., 0] = np.mgrid[0:size + 1, 0:size + 1]
    else:
        xy = np.asarray(east_north, dtype=np.float64)
        if xy.shape != h.shape + (2,):
            raise InvalidArgument("east_north", f"must have shape {h.shape + (2,)}, one (east, north) a post",
                                  value=list(xy.shape))
        bad = np.flatnonzero(~np.isfinite(xy).all(axis=-1) & np.isfinite(h))
        if bad.size:
            row, col = divmod(int(bad[0]), size + 1)
            raise InvalidArgument(f"east_north[{row}, {col}]", "must be finite where the post has a height",
                                  value=xy[row, col].tolist())
        points[..., :2] = xy
    faces = _leaves(h, midpoint_errors(points), float(max_error_m))
    # Counter-clockwise with x east (the column) and y north (minus the row).
    cols = size + 1
    x, y = faces % cols, -(faces // cols)
    turn = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
    faces[turn < 0] = faces[turn < 0][:, [0, 2, 1]]
    return faces
