"""The RTIN triangulation (terrain/rtin.py): within max_error of every grid post, exactly, and
conforming (no T-junction), checked by brute force here on random surfaces and an Alpine window.

- *Error.* For each triangle, every post in it (edges included) against the plane through its
  corners, in float64: at most max_error + 1e-9 m.
- *A partition.* The triangles' areas (index space) sum to the square's, and every edge inside the
  square is shared by exactly two triangles, every edge on its border belongs to one: a T-junction
  would leave a long edge once and its two halves once each.
"""

from __future__ import annotations

import numpy as np
import pytest

from sortie.errors import InvalidArgument
from terrain.rtin import grid_size_for, rtin_faces


def _check(h: np.ndarray, faces: np.ndarray, max_error: float) -> None:
    size = h.shape[0] - 1
    cols = size + 1
    x, y = faces % cols, faces // cols
    # Counter-clockwise with east = +column, north = -row.
    turn = (x[:, 1] - x[:, 0]) * (-(y[:, 2] - y[:, 0])) - (-(y[:, 1] - y[:, 0])) * (x[:, 2] - x[:, 0])
    assert np.all(turn > 0)
    assert turn.sum() == 2 * size * size  # twice the areas: the whole square
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    keys, counts = np.unique(edges[:, 0] * cols * cols + edges[:, 1], return_counts=True)
    a, b = keys // (cols * cols), keys % (cols * cols)
    ax, ay, bx, by = a % cols, a // cols, b % cols, b // cols
    border = ((ax == bx) & ((ax == 0) | (ax == size))) | ((ay == by) & ((ay == 0) | (ay == size)))
    assert np.all(counts[border] == 1) and np.all(counts[~border] == 2)
    worst = 0.0
    for (a, b, c) in faces:
        (xa, ya), (xb, yb), (xc, yc) = ((v % cols, v // cols) for v in (a, b, c))
        gy, gx = np.mgrid[min(ya, yb, yc):max(ya, yb, yc) + 1, min(xa, xb, xc):max(xa, xb, xc) + 1]
        d = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        wa = ((xb - gx) * (yc - gy) - (yb - gy) * (xc - gx)) / d
        wb = ((xc - gx) * (ya - gy) - (yc - gy) * (xa - gx)) / d
        wc = 1.0 - wa - wb
        inside = (wa >= -1e-12) & (wb >= -1e-12) & (wc >= -1e-12)
        plane = wa * h[ya, xa] + wb * h[yb, xb] + wc * h[yc, xc]
        worst = max(worst, float(np.abs(h[gy, gx] - plane)[inside].max()))
    assert worst <= max_error + 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_surfaces_within_the_bound(seed):
    rng = np.random.default_rng(seed)
    h = np.cumsum(np.cumsum(rng.normal(size=(33, 33)), 0), 1)  # rough, large-scale trends
    sizes = []
    for max_error in (0.0, 0.25, 1.0, 4.0, 16.0):
        faces = rtin_faces(h, max_error)
        _check(h, faces, max_error)
        sizes.append(len(faces))
    assert sizes == sorted(sizes, reverse=True) and sizes[0] == 2 * 32 * 32 and sizes[-1] < sizes[0] / 4


def test_an_alpine_window(hgt_alps):
    posts = np.fromfile(hgt_alps, dtype=">i2").reshape(1201, 1201).astype(np.float64)
    h = posts[700:829, 400:529]  # 129 x 129 posts around the Saentis
    for max_error in (1.0, 5.0, 20.0):
        faces = rtin_faces(h, max_error)
        _check(h, faces, max_error)
    assert len(rtin_faces(h, 20.0)) < 0.25 * 2 * 128 * 128  # within 20 m: under a quarter of the full grid


def test_planes_take_two_triangles():
    y, x = np.mgrid[0:17, 0:17].astype(float)
    assert len(rtin_faces(100.0 + 3.0 * x - 2.0 * y, 0.0)) == 2
    assert len(rtin_faces(np.zeros((17, 17)), 0.0)) == 2


def test_posts_without_data():
    rng = np.random.default_rng(4)
    h = np.cumsum(rng.normal(size=(17, 17)), 0)
    h[5:8, 9:12] = np.nan
    faces = rtin_faces(h, 2.0)
    assert np.isfinite(h.ravel()[faces]).all()
    # Every cell with four corners of data is covered: its two finest triangles' area.
    cols = 17
    x, y = faces % cols, faces // cols
    area2 = np.abs((x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0]))
    valid = np.isfinite(h)
    cells = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    assert area2.sum() >= 2 * cells.sum()


def test_bad_input_and_sizes():
    assert [grid_size_for(n) for n in (2, 3, 4, 5, 6, 100, 1025, 1026)] == [3, 3, 5, 5, 9, 129, 1025, 2049]
    with pytest.raises(InvalidArgument, match="heights"):
        rtin_faces(np.zeros((10, 10)), 1.0)
    with pytest.raises(InvalidArgument, match="max_error_m"):
        rtin_faces(np.zeros((9, 9)), -1.0)
