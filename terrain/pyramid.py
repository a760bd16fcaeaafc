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
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
        raise ValueError(f"heights must be (ny>=2, nx>=2), got shape {h.shape}")
    corners = (h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:])
    lo = np.minimum(np.minimum(corners[0], corners[1]), np.minimum(corners[2], corners[3]))
    hi = np.maximum(np.maximum(corners[0], corners[1]), np.maximum(corners[2], corners[3]))
    hole = np.isnan(lo)  # np.minimum propagates NaN from any corner
    lo[hole] = -np.inf
    hi[hole] = np.inf
    return to_float32_outward(lo, -np.inf), to_float32_outward(hi, np.inf)


def reduce_2x2(level: np.ndarray, op, neutral) -> np.ndarray:
    """One pyramid step: op over 2x2 blocks, odd edges padded with ``neutral``."""
    ny, nx = level.shape
    padded = np.pad(level, ((0, ny % 2), (0, nx % 2)), constant_values=neutral)
    return op(padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2), axis=(1, 3))


def build_pyramid(heights: np.ndarray, filled: np.ndarray | None = None) -> Pyramid:
    """The min/max pyramid of a raster's bilinear surface.

    heights: (ny, nx) float32/float64 metres, NaN for holes; filled: (ny, nx)
    bool/uint8 marking filled-void posts, or None.
    """
    lo, hi = cell_bounds(heights)
    mins, maxs = [lo], [hi]
    fills = []
    if filled is not None and np.any(filled):
        f = np.asarray(filled, dtype=np.uint8)
        if f.shape != np.shape(heights):
            raise ValueError(f"filled must have shape {np.shape(heights)}, got {f.shape}")
        fills.append(f[:-1, :-1] | f[:-1, 1:] | f[1:, :-1] | f[1:, 1:])
    while mins[-1].shape != (1, 1):
        mins.append(reduce_2x2(mins[-1], np.min, np.float32(np.inf)))
        maxs.append(reduce_2x2(maxs[-1], np.max, np.float32(-np.inf)))
        if fills:
            fills.append(reduce_2x2(fills[-1], np.max, 0))
    shapes = np.array([m.shape for m in mins], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(shapes[:, 0] * shapes[:, 1])]).astype(np.int64)
    flats = [np.concatenate([a.ravel() for a in levels]) if levels else np.zeros(0, np.uint8)
             for levels in (mins, maxs, fills)]
    for a in (*flats, offsets, shapes):
        a.flags.writeable = False
    return Pyramid(flats[0], flats[1], flats[2], offsets, shapes)
