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

**The error is exact.** err(T) is the largest |h(p) - plane_T(p)| over the grid posts p in T
(its edges included), plane_T the plane through T's corners. Martini instead compares each
midpoint with its hypotenuse's interpolation, which is not the final mesh's error. A midpoint's
E is the largest err of the triangles whose hypotenuse it halves and the E of their children's
midpoints, computed finest level first. A leaf T then has err(T) <= E(m_T) <= max_error, so every
grid post is within max_error of the mesh; and a post's E >= any E below it, so a triangle splits
whenever a descendant must (the forced splits that keep the mesh conforming). Posts without data
(NaN) make their triangles' error infinite: they split to the finest triangles, and those with a
corner without data are left out.

Cost: every level's triangles cover the square once, so the error pass visits about
2 (2^k + 1)^2 posts a level over 2k levels (1025^2 posts: about 0.1-0.3 s, one compiled pass).
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
def _triangle_error(h, ax, ay, bx, by, cx, cy):
    """Largest |h(p) - plane(p)| over the posts p in the triangle (edges included); inf if a
    post there has no data."""
    ha, hb, hc = h[ay, ax], h[by, bx], h[cy, cx]
    d = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)  # twice the signed area
    worst = 0.0
    for y in range(min(ay, by, cy), max(ay, by, cy) + 1):
        for x in range(min(ax, bx, cx), max(ax, bx, cx) + 1):
            na = (bx - x) * (cy - y) - (by - y) * (cx - x)
            nb = (cx - x) * (ay - y) - (cy - y) * (ax - x)
            nc = d - na - nb
            if d > 0:
                inside = na >= 0 and nb >= 0 and nc >= 0
            else:
                inside = na <= 0 and nb <= 0 and nc <= 0
            if not inside:
                continue
            v = h[y, x]
            if v != v:
                return np.inf
            e = abs(v - (na * ha + nb * hb + nc * hc) / d)
            if e > worst:
                worst = e
    return worst


@numba.njit(cache=True, nogil=True)
def midpoint_errors(h):
    """E (the grid's shape) of a (2^k + 1)^2 height grid: at each triangle's hypotenuse
    midpoint, the largest exact error of the triangles that split there and below."""
    size = h.shape[0] - 1
    E = np.zeros(h.shape)
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
        e = _triangle_error(h, ax, ay, bx, by, cx, cy)
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


def rtin_faces(heights, max_error_m: float) -> np.ndarray:
    """(m, 3) int64 triangles (grid indices row * cols + col) of the RTIN of ``heights`` ((2^k + 1)
    square, row 0 north; NaN: no data) within ``max_error_m`` of every post, counter-clockwise
    seen from above when row 0 is north and column 0 west (as terrain.mesh.grid_faces)."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    size = h.shape[0] - 1
    if h.ndim != 2 or h.shape[0] != h.shape[1] or size < 2 or size & (size - 1):
        raise InvalidArgument("heights", "an RTIN grid is (2^k + 1) x (2^k + 1) posts, k >= 1", value=list(h.shape))
    if not (np.isfinite(max_error_m) and max_error_m >= 0.0):
        raise InvalidArgument("max_error_m", "must be a finite number of metres, 0 or more", value=max_error_m)
    faces = _leaves(h, midpoint_errors(h), float(max_error_m))
    # Counter-clockwise with x east (the column) and y north (minus the row).
    cols = size + 1
    x, y = faces % cols, -(faces // cols)
    turn = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
    faces[turn < 0] = faces[turn < 0][:, [0, 2, 1]]
    return faces
