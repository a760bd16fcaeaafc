"""Minimum/maximum pyramid (maximum mipmap) over a raster's bilinear cells.

A bilinear cell never leaves the range of its four corner posts, so the
per-cell minimum and maximum of the corners bound the surface exactly; a 2x2
reduction of those bounds bounds a 2x2 block of cells, and so on up to one
block covering the raster. Ray casters skip every block the ray passes above
(maximum mipmaps: Tevs, Ihrke & Seidel 2008, "Maximum mipmaps for fast,
accurate, and scalable dynamic height field rendering", I3D).

Layout: level k, block (bi, bj) covers the cells (rows bi*2**k ..
(bi+1)*2**k - 1, cols bj*2**k .. (bj+1)*2**k - 1) clipped to the raster;
level 0 is the cells themselves, shape (ny - 1, nx - 1); the last level is
1 x 1. Odd sizes are padded with the reduction's neutral element (+inf for
the minimum, -inf for the maximum), so a block's bounds come from its real
cells only. A cell with a NaN corner (a hole in coverage) has bounds
(-inf, +inf): no test ever skips it, so the caster always reaches the hole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np


@dataclass(frozen=True, eq=False)
class Pyramid:
    """Per-level bounds of the bilinear surface, stored flat for numba kernels.

    mins[k], maxs[k]: (ny_k, nx_k) float32 metres, in the raster's vertical
    datum; read-only views into min_flat / max_flat. Float32 values are
    rounded outward (minimum down, maximum up) from the float64 extremes.
    filled[k]: (ny_k, nx_k) uint8, 1 where a block holds a filled-void post;
    an empty tuple when the raster has none.
    offsets: (n_levels + 1,) int64, start of level k in the flat arrays;
    shapes: (n_levels, 2) int64, (ny_k, nx_k).
    """

    min_flat: np.ndarray
    max_flat: np.ndarray
    filled_flat: np.ndarray
    offsets: np.ndarray
    shapes: np.ndarray

    @property
    def n_levels(self) -> int:
        return int(self.shapes.shape[0])

    def _views(self, flat):
        if flat.size == 0:
            return ()
        return tuple(flat[self.offsets[k]:self.offsets[k + 1]].reshape(self.shapes[k])
                     for k in range(self.n_levels))

    @property
    def mins(self) -> tuple[np.ndarray, ...]:
        return self._views(self.min_flat)

    @property
    def maxs(self) -> tuple[np.ndarray, ...]:
        return self._views(self.max_flat)

    @property
    def filled(self) -> tuple[np.ndarray, ...]:
        return self._views(self.filled_flat)


def to_float32_outward(values: np.ndarray, direction: float) -> np.ndarray:
    """float64 -> float32 rounded toward ``direction`` (-inf: down, +inf: up)."""
    f32 = values.astype(np.float32)
    wrong = f32 > values if direction < 0 else f32 < values
    f32[wrong] = np.nextafter(f32[wrong], np.float32(direction))
    return f32


def cell_bounds(heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level 0: min and max over each cell's four corner posts.

    heights: (ny, nx) float32/float64 metres, NaN for holes. Returns two
    (ny - 1, nx - 1) float32 arrays; cells with a NaN corner get (-inf, +inf).
    """
    h = np.asarray(heights)
    if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
        raise ValueError(f"heights must be (ny>=2, nx>=2), got shape {h.shape}")
    if h.dtype not in (np.float32, np.float64):
        h = h.astype(np.float64)
    lo = np.zeros((h.shape[0] - 1, h.shape[1] - 1), np.float32)
    hi = np.zeros_like(lo)
    _cell_bounds_into(h, lo, hi)
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _cell_bounds_into(h, lo, hi):
    """:func:`cell_bounds` in one compiled pass: each cell's corner minimum and maximum (in float64),
    rounded outward to float32 as :func:`to_float32_outward` does; (-inf, +inf) where a corner is
    NaN."""
    ny, nx = lo.shape
    for i in range(ny):
        for j in range(nx):
            a = np.float64(h[i, j])
            b = np.float64(h[i, j + 1])
            c = np.float64(h[i + 1, j])
            d = np.float64(h[i + 1, j + 1])
            if a != a or b != b or c != c or d != d:
                lo[i, j] = -np.inf
                hi[i, j] = np.inf
                continue
            mn = min(min(a, b), min(c, d))
            mx = max(max(a, b), max(c, d))
            f = np.float32(mn)
            if f > mn:
                f = np.nextafter(f, np.float32(-np.inf))
            lo[i, j] = f
            f = np.float32(mx)
            if f < mx:
                f = np.nextafter(f, np.float32(np.inf))
            hi[i, j] = f


def reduce_2x2(level: np.ndarray, op, neutral) -> np.ndarray:
    """One pyramid step: op over 2x2 blocks, odd edges padded with ``neutral``."""
    ny, nx = level.shape
    padded = np.pad(level, ((0, ny % 2), (0, nx % 2)), constant_values=neutral)
    return op(padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2), axis=(1, 3))


@numba.njit(cache=True, nogil=True)
def _reduce_levels(flat, offsets, shapes, take_max):
    """Levels 1.. of a pyramid in place: each block of level k is the minimum (or the maximum, with
    ``take_max``) of the 2x2 blocks of level k - 1 it covers, those past an odd edge left out (what
    :func:`reduce_2x2` gives with the neutral padding: the same values, bit for bit). flat: every
    level, level 0 filled in; offsets, shapes as :class:`Pyramid` holds them. One compiled pass
    where the numpy steps cost some 0.2 ms a level whatever its size (small ray rasters)."""
    for k in range(1, shapes.shape[0]):
        py, px = shapes[k - 1, 0], shapes[k - 1, 1]
        ny, nx = shapes[k, 0], shapes[k, 1]
        src, dst = offsets[k - 1], offsets[k]
        for i in range(ny):
            r0 = src + 2 * i * px
            two_rows = 2 * i + 1 < py
            for j in range(nx):
                c = 2 * j
                v = flat[r0 + c]
                two_cols = c + 1 < px
                if two_cols:
                    w = flat[r0 + c + 1]
                    v = max(v, w) if take_max else min(v, w)
                if two_rows:
                    w = flat[r0 + px + c]
                    v = max(v, w) if take_max else min(v, w)
                    if two_cols:
                        w = flat[r0 + px + c + 1]
                        v = max(v, w) if take_max else min(v, w)
                flat[dst + i * nx + j] = v


def build_pyramid(heights: np.ndarray, filled: np.ndarray | None = None) -> Pyramid:
    """The min/max pyramid of a raster's bilinear surface.

    heights: (ny, nx) float32/float64 metres, NaN for holes; filled: (ny, nx)
    bool/uint8 marking filled-void posts, or None. Levels past the first come from
    :func:`_reduce_levels` (the values :func:`reduce_2x2` gives, level by level).
    """
    lo, hi = cell_bounds(heights)
    fill0 = None
    if filled is not None and np.any(filled):
        f = np.asarray(filled, dtype=np.uint8)
        if f.shape != np.shape(heights):
            raise ValueError(f"filled must have shape {np.shape(heights)}, got {f.shape}")
        fill0 = f[:-1, :-1] | f[:-1, 1:] | f[1:, :-1] | f[1:, 1:]
    shapes = [lo.shape]
    while shapes[-1] != (1, 1):
        shapes.append(((shapes[-1][0] + 1) // 2, (shapes[-1][1] + 1) // 2))
    shapes = np.array(shapes, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(shapes[:, 0] * shapes[:, 1])]).astype(np.int64)
    flats = []
    for level0, take_max in ((lo, False), (hi, True), (fill0, True)):
        if level0 is None:
            flats.append(np.zeros(0, np.uint8))
            continue
        flat = np.zeros(offsets[-1], level0.dtype)
        flat[:offsets[1]] = level0.ravel()
        _reduce_levels(flat, offsets, shapes, take_max)
        flats.append(flat)
    for a in (*flats, offsets, shapes):
        a.flags.writeable = False
    return Pyramid(flats[0], flats[1], flats[2], offsets, shapes)
