"""Pyramid compression of height grids: interpolatory prediction, uniform
quantisation, context-split entropy coding.

The scheme is the one the geometry-clipmap papers use (thesis §3.1.8; Losasso &
Hoppe 2004, §3; Asirvatham & Hoppe, GPU Gems 2 ch. 2): each level of a pyramid
is predicted from the decoded coarser level by interpolatory subdivision, and
only the quantised residuals are stored, so a region can be decoded at any
power-of-two level without touching the finer ones.

Grids are integers in a vertical ``unit`` chosen by the caller (the store uses
centimetres; SRTM's metres are already integers). Choices, each measured in
``sortie bench store``:

* **Levels are point decimations.** Level k + 1 holds the even rows and even
  columns of level k, so every post of level k + 1 *is* a post of level k and
  only the other three quarters carry residuals: the pyramid codes exactly as
  many residuals as the grid has posts (a filtered pyramid codes 4/3 as many).
* **Prediction** is separable and done in two passes, each the four-point mask
  (-1, 9, 9, -1) / 16 of GPU Gems 2 ch. 2 (Dyn, Levin & Gregory 1987):
  pass 1 fills the odd columns of the even rows from the coarse posts on the
  row; pass 2 fills every odd row from the even rows above and below it, using
  the pass-1 values already decoded inside the tile (so half the stencils see
  the finer data the coarse level lacked). Stencils clamp at the level's edge.
* **Closed-loop uniform quantisation.** Residual r = v - P is sent as
  q = round(r / s) with s the step in units, and the decoder rebuilds
  P + q s, from which later predictions are made (the encoder predicts from
  the same decoded values). Every post of every level is therefore within
  s / 2 of its true value: the bound holds for the maximum, not only the RMS,
  and does not grow down the pyramid. s = 1 is lossless.
* **Entropy coding.** The residuals of each pass are split into buckets by a
  context the decoder knows before it reads them: the local roughness of the
  stencil (|b - c| + 2 |a - b - c + d| for stencil values a b c d, in steps,
  bucketed by bit length), because residuals are larger where the terrain
  bends. Each bucket is zig-zag mapped to bytes (255 escapes to a uint32
  side stream) and compressed by zstandard as its own frame, whose Huffman
  literal table then fits that bucket's distribution.

Tiles are independent given the coarser level: a tile's pass 2 uses its own
pass-1 rows and, beyond its edge, the pass-1 *predictions* (no residual) of
its neighbours' rows, so decoding a region touches only the tiles that
overlap it at each level, plus a two-post ring of the coarser level.
"""

from __future__ import annotations

import struct
import threading
from dataclasses import dataclass

import numba
import numpy as np
import zstandard

# Four-point interpolatory subdivision mask (-1, 9, 9, -1) / 16 (Dyn, Levin &
# Gregory 1987; the mask GPU Gems 2 ch. 2 uses to upsample clipmap levels).
MASK = (-1, 9, 9, -1)
MASK_SHIFT = 4  # divide by 16

N_BUCKETS = 8  # contexts per pass: bit length of the roughness, capped
ESCAPE = 255  # a zig-zag value >= 255 is written as 255 + uint32 in the side stream
ZSTD_LEVEL = 19
BLOB_VERSION = 1
# Largest |value| a grid may hold, in units: a residual is then at most
# 2.25 x this (the mask's weights sum to 20/16 in absolute value), and its
# zig-zag code under 2^32, the escape code's range. At 1 cm, 5,368 km.
MAX_ABS_UNITS = 1 << 29

_cctx_cache: dict[int, zstandard.ZstdCompressor] = {}
_dctx = zstandard.ZstdDecompressor()


@dataclass(frozen=True)
class LevelRect:
    """Where one level's coded grid lies in that level's lattice (tile-aligned).

    row0, col0: lattice index of the first row/column; rows, cols: extent,
    both multiples of the tile size.
    """

    row0: int
    col0: int
    rows: int
    cols: int

    @property
    def row1(self) -> int:
        return self.row0 + self.rows

    @property
    def col1(self) -> int:
        return self.col0 + self.cols


def pyramid_rects(row0: int, col0: int, rows: int, cols: int, tile: int, max_levels: int) -> list[LevelRect]:
    """The rectangles of every level, finest first, for a grid at (row0, col0).

    Level 0 is the tile-aligned box around the grid; level k + 1 the
    tile-aligned box around level k's even posts. Levels stop when one tile
    holds the whole level or after ``max_levels``.
    """
    if tile < 4 or tile % 2:
        raise ValueError(f"tile must be even and >= 4, got {tile}")
    r0, c0 = (row0 // tile) * tile, (col0 // tile) * tile
    r1, c1 = -(-(row0 + rows) // tile) * tile, -(-(col0 + cols) // tile) * tile
    rects = [LevelRect(r0, c0, r1 - r0, c1 - c0)]
    while len(rects) < max_levels and (rects[-1].rows > tile or rects[-1].cols > tile):
        f = rects[-1]
        # Even fine posts f.row0 .. f.row1 - 2 are coarse posts f.row0/2 .. f.row1/2 - 1.
        a, b = f.row0 // 2, f.row1 // 2
        c, d = f.col0 // 2, f.col1 // 2
        ra, ca = (a // tile) * tile, (c // tile) * tile
        rects.append(LevelRect(ra, ca, -(-b // tile) * tile - ra, -(-d // tile) * tile - ca))
    return rects


def decimate_into(fine: np.ndarray, f: LevelRect, c: LevelRect) -> np.ndarray:
    """Level k + 1 over rect c from level k over rect f: the even posts, edge-replicated
    out to c's tile-aligned box (those posts are never used as predictors)."""
    sub = fine[::2, ::2]
    top, left = f.row0 // 2 - c.row0, f.col0 // 2 - c.col0
    bottom, right = c.rows - top - sub.shape[0], c.cols - left - sub.shape[1]
    return np.pad(sub, ((top, bottom), (left, right)), mode="edge")


# --------------------------------------------------------------------------- prediction

def _four_point(a, b, c, d):
    """Integer four-point prediction between b and c, rounded to nearest (ties up)."""
    return (MASK[0] * a + MASK[1] * b + MASK[2] * c + MASK[3] * d + (1 << (MASK_SHIFT - 1))) >> MASK_SHIFT


def _roughness_bucket(a, b, c, d, step: int):
    """Context of a residual from its stencil: bit length of the local roughness in steps."""
    rough = (np.abs(b - c) + 2 * np.abs(a - b - c + d)) // step
    return np.minimum(np.ceil(np.log2(rough + 1.0)).astype(np.int64), N_BUCKETS - 1)


def _quantise(r: np.ndarray, step: int) -> np.ndarray:
    """Symmetric rounding of r / step to the nearest integer (ties away from zero)."""
    if step == 1:
        return r
    return np.sign(r) * ((np.abs(r) + step // 2) // step)


class _TileStencils:
    """Index arithmetic of one tile's two passes (shared by encoder and decoder).

    tile_r0, tile_c0: the tile's first fine-lattice row/col; rect: the fine
    level; the coarse values come as an array ``coarse`` whose [0, 0] is coarse
    lattice (cr0, cc0).
    """

    def __init__(self, tile: int, tile_r0: int, tile_c0: int, rect: LevelRect, cr0: int, cc0: int):
        half = tile // 2
        # Even fine rows the tile needs: its own plus one above and two below
        # (pass 2's stencil rows -2, T, T + 2), clamped to the level's even rows.
        lo_e, hi_e = rect.row0 // 2, rect.row1 // 2 - 1  # even rows as coarse indices
        lo_c, hi_c = rect.col0 // 2, rect.col1 // 2 - 1
        tr, tc = tile_r0 // 2, tile_c0 // 2
        self.even_rows = np.clip(np.arange(tr - 1, tr + half + 2), lo_e, hi_e) - cr0  # (half + 3,)
        self.own_rows = slice(1, half + 1)  # which of even_rows are the tile's
        cols = np.arange(tc, tc + half)  # coarse column of each even fine column
        # Pass 1: odd fine column 2j + 1 lies between coarse j and j + 1.
        self.p1 = [np.clip(cols + k, lo_c, hi_c) - cc0 for k in (-1, 0, 1, 2)]
        self.even_cols = np.clip(cols, lo_c, hi_c) - cc0
        # Pass 2: odd row 2i + 1 (local) uses even rows i - 1 .. i + 2 (local), i.e.
        # positions i .. i + 3 in even_rows (which starts one row above the tile).
        self.p2 = [np.arange(half) + k for k in (0, 1, 2, 3)]
        self.half = half

    def even_row_values(self, coarse: np.ndarray, step: int, q1_own: np.ndarray | None = None):
        """Decoded values of the even rows (tile's own rows with residuals q1_own; the
        others are predictions), plus pass 1's prediction P1 and context for own rows."""
        rows = coarse[self.even_rows]  # (half + 3, coarse cols)
        a, b, c, d = (rows[:, k] for k in self.p1)
        p1 = _four_point(a, b, c, d)  # (half + 3, half): odd columns
        evens = rows[:, self.even_cols]
        return evens, p1, (a, b, c, d)

    @staticmethod
    def interleave(evens: np.ndarray, odds: np.ndarray) -> np.ndarray:
        out = np.empty((evens.shape[0], evens.shape[1] * 2), dtype=np.int64)
        out[:, 0::2] = evens
        out[:, 1::2] = odds
        return out


def encode_tile(fine: np.ndarray, coarse: np.ndarray, tile_r0: int, tile_c0: int, rect: LevelRect,
                cr0: int, cc0: int, step: int) -> tuple[bytes, np.ndarray]:
    """Code one tile of a level against its decoded coarser level.

    fine: (T, T) int64 true values of the tile; coarse: decoded coarse values
    whose [0, 0] is coarse lattice (cr0, cc0), covering the tile's footprint
    and a two-post ring (clamped to the level). Returns (blob, decoded tile).
    """
    tile = fine.shape[0]
    st = _TileStencils(tile, tile_r0, tile_c0, rect, cr0, cc0)
    evens, p1, ctx1 = st.even_row_values(coarse, step)
    own = st.own_rows
    q1 = _quantise(fine[0::2, 1::2] - p1[own], step)
    odd1 = p1.copy()
    odd1[own] += q1 * step
    full_even = st.interleave(evens, odd1)  # (half + 3, T): decoded even rows (own) + predicted (ring)
    a, b, c, d = (full_even[idx] for idx in st.p2)
    p2 = _four_point(a, b, c, d)
    q2 = _quantise(fine[1::2, :] - p2, step)
    decoded = np.empty((tile, tile), np.int64)
    decoded[0::2] = full_even[own]
    decoded[1::2] = p2 + q2 * step
    b1 = _roughness_bucket(*(x[own] for x in ctx1), step)
    b2 = _roughness_bucket(a, b, c, d, step)
    blob = _pack_streams([_code_buckets(q1, b1), _code_buckets(q2, b2)])
    return blob, decoded


def decode_tile(blob: bytes, coarse: np.ndarray, tile: int, tile_r0: int, tile_c0: int, rect: LevelRect,
                cr0: int, cc0: int, step: int) -> np.ndarray:
    """Inverse of :func:`encode_tile`: the decoded (T, T) int64 tile.

    The arithmetic is the encoder's, sample by sample, in one numba kernel
    (the vectorised form spent 90 % of its time in temporaries).
    """
    half = tile // 2
    raw, offs = _decompress_parts(_unpack_streams(blob, 2), 2)
    q1 = np.empty(2 * half * half, np.int32)
    q2 = np.empty(2 * half * tile, np.int32)
    out = np.empty((tile, tile), np.int64)
    _decode_tile_kernel(coarse, tile_r0 // 2, tile_c0 // 2, rect.row0 // 2 - cr0, rect.row1 // 2 - 1 - cr0,
                        rect.col0 // 2 - cc0, rect.col1 // 2 - 1 - cc0, cr0, cc0, step, raw, offs, q1, q2, out)
    return out


def _decompress_parts(streams, n_streams):
    """Every bucket of n_streams bucket streams decompressed into one byte array, with
    the offsets of the buckets in it (n_streams * N_BUCKETS + 1 of them)."""
    chunks = []
    for s in streams:
        for part in _unpack_streams(s, N_BUCKETS):
            chunks.append(_decompressor().decompress(part) if part else b"")
    offs = np.zeros(len(chunks) + 1, np.int64)
    np.cumsum([len(c) for c in chunks], out=offs[1:])
    return np.frombuffer(b"".join(chunks), np.uint8), offs


_tls = threading.local()


def _decompressor() -> zstandard.ZstdDecompressor:
    """This thread's zstd decompressor (python-zstandard's are not thread-safe)."""
    d = getattr(_tls, "dctx", None)
    if d is None:
        d = _tls.dctx = zstandard.ZstdDecompressor()
    return d


@numba.njit(cache=True, nogil=True)
def _expand_buckets(raw, offs, first, n_expected, q, starts):
    """Residuals (steps) of one pass from its decompressed buckets offs[first .. first + N_BUCKETS]
    of raw, bucket after bucket into q; starts[k] is where bucket k begins, starts[N_BUCKETS]
    the end. Raises unless the pass holds exactly n_expected residuals."""
    n = 0
    for k in range(N_BUCKETS):
        starts[k] = n
        a = offs[first + k]
        b = offs[first + k + 1]
        if a == b:
            continue
        if b - a < 4:
            raise ValueError("tile blob: a bucket is shorter than its header")
        n_esc = np.int64(raw[a]) | (np.int64(raw[a + 1]) << 8) | (np.int64(raw[a + 2]) << 16) \
            | (np.int64(raw[a + 3]) << 24)
        e = a + 4
        s0 = e + 4 * n_esc
        if s0 > b or n + (b - s0) > n_expected:
            raise ValueError("tile blob: a bucket does not fit its pass")
        for p in range(s0, b):
            z = np.int64(raw[p])
            if z == ESCAPE:
                if e >= s0:
                    raise ValueError("tile blob: an escape stream is shorter than its bucket")
                z = (np.int64(raw[e]) | (np.int64(raw[e + 1]) << 8) | (np.int64(raw[e + 2]) << 16)
                     | (np.int64(raw[e + 3]) << 24)) + ESCAPE
                e += 4
            q[n] = (z >> 1) ^ -(z & 1)  # zig-zag inverse
            n += 1
        if e != s0:
            raise ValueError("tile blob: an escape stream is longer than its bucket")
    starts[N_BUCKETS] = n
    if n != n_expected:
        raise ValueError("tile blob: a pass holds fewer residuals than its samples")


@numba.njit(cache=True, nogil=True, inline="always")
def _bucket(a, b, c, d, t0, t1, t2, t3, t4, t5, t6):
    """Bucket of a stencil: bit length of floor(roughness / step), capped at N_BUCKETS - 1,
    as the number of thresholds step * 2^k (k < N_BUCKETS - 1) it reaches (no division)."""
    r = abs(b - c) + 2 * abs(a - b - c + d)
    return (np.int64(r >= t0) + np.int64(r >= t1) + np.int64(r >= t2) + np.int64(r >= t3)
            + np.int64(r >= t4) + np.int64(r >= t5) + np.int64(r >= t6))


@numba.njit(cache=True, nogil=True)
def _decode_tile_kernel(coarse, tr, tc, lo_r, hi_r, lo_c, hi_c, cr0, cc0, step, raw, offs, q1, q2, out):
    """One tile, both passes. tr, tc: the tile's first coarse row/col (lattice); lo_r .. hi_r,
    lo_c .. hi_c: the fine level's even rows/cols as indices into coarse (clamping bounds)."""
    half = out.shape[0] // 2
    width = 2 * half
    n1 = half * half
    n2 = half * width
    starts = np.empty(N_BUCKETS + 1, np.int64)
    _expand_buckets(raw, offs, 0, n1, q1, starts)
    ptr1 = starts[:N_BUCKETS].copy()
    end1 = starts[1:].copy()
    _expand_buckets(raw, offs, N_BUCKETS, n2, q2, starts)
    ptr2 = starts[:N_BUCKETS].copy()
    end2 = starts[1:].copy()
    t0, t1, t2, t3, t4, t5, t6 = step, step << 1, step << 2, step << 3, step << 4, step << 5, step << 6
    # Pass 1 over the tile's even rows plus one above and two below (clamped).
    full = np.empty((half + 3, width), np.int64)
    ext = np.empty(half + 3, np.int64)
    pred = np.empty(width, np.int64)
    kb = np.empty(width, np.int64)
    for i in range(half + 3):
        row = coarse[min(max(tr - 1 + i - cr0, lo_r), hi_r)]
        for m in range(half + 3):
            ext[m] = row[min(max(tc - 1 + m - cc0, lo_c), hi_c)]
        dst = full[i]
        for j in range(half):
            a = ext[j]
            b = ext[j + 1]
            c = ext[j + 2]
            d = ext[j + 3]
            pred[j] = (-a + 9 * b + 9 * c - d + 8) >> 4
            kb[j] = _bucket(a, b, c, d, t0, t1, t2, t3, t4, t5, t6)
        if 1 <= i <= half:
            for j in range(half):
                k = kb[j]
                p = ptr1[k]
                pred[j] += q1[p] * step
                ptr1[k] = p + 1
        for j in range(half):
            dst[2 * j] = ext[j + 1]
            dst[2 * j + 1] = pred[j]
    # Pass 2: every odd row from the even rows above and below.
    for i in range(half):
        r0 = full[i]
        r1 = full[i + 1]
        r2 = full[i + 2]
        r3 = full[i + 3]
        for j in range(width):
            a = r0[j]
            b = r1[j]
            c = r2[j]
            d = r3[j]
            pred[j] = (-a + 9 * b + 9 * c - d + 8) >> 4
            kb[j] = _bucket(a, b, c, d, t0, t1, t2, t3, t4, t5, t6)
        even = out[2 * i]
        odd = out[2 * i + 1]
        for j in range(width):
            k = kb[j]
            p = ptr2[k]
            odd[j] = pred[j] + q2[p] * step
            ptr2[k] = p + 1
            even[j] = r1[j]
    for k in range(N_BUCKETS):
        if ptr1[k] != end1[k] or ptr2[k] != end2[k]:
            raise ValueError("tile blob: a bucket holds more residuals than its samples")


def encode_top(values: np.ndarray, step: int) -> tuple[bytes, np.ndarray]:
    """The coarsest level's tile: quantised directly, then coded as differences from
    the west neighbour (the north one in column 0). Returns (blob, decoded)."""
    q = _quantise(values.astype(np.int64), step)
    return _pack_streams([_code_buckets(_dpcm(q), np.zeros(q.shape, np.int64))]), q * step


def decode_top(blob: bytes, shape: tuple[int, int], step: int) -> np.ndarray:
    raw, offs = _decompress_parts(_unpack_streams(blob, 1), 1)
    n = shape[0] * shape[1]
    d = np.empty(n, np.int32)
    starts = np.empty(N_BUCKETS + 1, np.int64)
    _expand_buckets(raw, offs, 0, n, d, starts)
    if starts[1] != n:
        raise ValueError("tile blob: the top level's residuals are not all in its one bucket")
    return _undpcm(d.astype(np.int64).reshape(shape)) * step


def _dpcm(q):
    d = q.copy()
    d[:, 1:] = q[:, 1:] - q[:, :-1]
    d[1:, 0] = q[1:, 0] - q[:-1, 0]
    return d


def _undpcm(d):
    first = np.cumsum(d[:, 0])
    out = np.cumsum(d, axis=1)
    return out - d[:, :1] + first[:, None]


# --------------------------------------------------------------------------- entropy coding

def _zigzag(q):
    return np.where(q >= 0, 2 * q, -2 * q - 1)


def _compressor(level: int) -> zstandard.ZstdCompressor:
    c = _cctx_cache.get(level)
    if c is None:
        c = _cctx_cache[level] = zstandard.ZstdCompressor(level=level)
    return c


def _code_buckets(q: np.ndarray, bucket: np.ndarray) -> bytes:
    """Residuals q split by bucket (row-major order kept inside each), each bucket one
    zstd frame: the number of escapes (u32), the escapes (uint32 each, value - 255), then
    the zig-zag values as bytes (255: take the next escape). Little-endian."""
    z = _zigzag(q.ravel())
    bucket = bucket.ravel()
    parts = []
    for k in range(N_BUCKETS):
        zk = z[bucket == k]
        if zk.size == 0:
            parts.append(b"")
            continue
        small = np.minimum(zk, ESCAPE).astype(np.uint8)
        esc = zk[zk >= ESCAPE] - ESCAPE
        if esc.size and esc.max() > np.iinfo(np.uint32).max:
            raise ValueError(f"a residual of {int(esc.max())} steps does not fit the escape code")
        parts.append(_compressor(ZSTD_LEVEL).compress(struct.pack("<I", esc.size) + esc.astype("<u4").tobytes()
                                                      + small.tobytes()))
    return _pack_streams(parts)


def _pack_streams(parts: list[bytes]) -> bytes:
    head = struct.pack(f"<B{len(parts)}I", BLOB_VERSION, *(len(p) for p in parts))
    return head + b"".join(parts)


def _unpack_streams(blob: bytes, n: int) -> list[bytes]:
    head = struct.calcsize(f"<B{n}I")
    if len(blob) < head:
        raise ValueError(f"tile blob of {len(blob)} bytes is shorter than its {head}-byte header")
    version, *sizes = struct.unpack_from(f"<B{n}I", blob)
    if version != BLOB_VERSION:
        raise ValueError(f"tile blob version {version}, this build reads {BLOB_VERSION}")
    if head + sum(sizes) != len(blob):
        raise ValueError(f"tile blob sizes {sizes} do not add up to its {len(blob)} bytes")
    out, at = [], head
    for size in sizes:
        out.append(blob[at:at + size])
        at += size
    return out


# --------------------------------------------------------------------------- whole pyramids

def encode_pyramid(values: np.ndarray, row0: int, col0: int, tile: int, step: int, max_levels: int,
                   progress=None) -> tuple[list[LevelRect], dict[tuple[int, int, int], bytes]]:
    """Code a grid whose [0, 0] is lattice post (row0, col0) as a pyramid of tiles.

    values: (rows, cols) integers (units); step: quantisation step in units
    (1 = lossless). Returns the level rectangles and a blob per tile keyed by
    (level, tile row, tile col) in the level's lattice (row // tile, col // tile).
    progress(n_tiles_done) is called after each tile when given.
    """
    values = np.asarray(values)
    if values.ndim != 2 or values.dtype.kind not in "iu":
        raise ValueError(f"values must be a 2-D integer grid, got {values.dtype} {values.shape}")
    if step < 1:
        raise ValueError(f"step must be a positive integer number of units, got {step}")
    if values.size and int(np.abs(values).max()) > MAX_ABS_UNITS:
        raise ValueError(f"values must lie within +-{MAX_ABS_UNITS} units, got {int(np.abs(values).max())}")
    rects = pyramid_rects(row0, col0, values.shape[0], values.shape[1], tile, max_levels)
    r = rects[0]
    top, left = row0 - r.row0, col0 - r.col0
    levels = [np.pad(values.astype(np.int64), ((top, r.rows - top - values.shape[0]),
                                                (left, r.cols - left - values.shape[1])), mode="edge")]
    for f, c in zip(rects, rects[1:]):
        levels.append(decimate_into(levels[-1], f, c))
    blobs: dict[tuple[int, int, int], bytes] = {}
    k_top = len(rects) - 1
    decoded = np.empty_like(levels[k_top])
    t = rects[k_top]
    for i in range(0, t.rows, tile):
        for j in range(0, t.cols, tile):
            blob, dec = encode_top(levels[k_top][i:i + tile, j:j + tile], step)
            blobs[(k_top, (t.row0 + i) // tile, (t.col0 + j) // tile)] = blob
            decoded[i:i + tile, j:j + tile] = dec
            if progress:
                progress(1)
    for k in range(k_top - 1, -1, -1):
        f, c = rects[k], rects[k + 1]
        fine = levels[k]
        out = np.empty_like(fine)
        for i in range(0, f.rows, tile):
            for j in range(0, f.cols, tile):
                tr0, tc0 = f.row0 + i, f.col0 + j
                blob, dec = encode_tile(fine[i:i + tile, j:j + tile], decoded, tr0, tc0, f,
                                        c.row0, c.col0, step)
                blobs[(k, tr0 // tile, tc0 // tile)] = blob
                out[i:i + tile, j:j + tile] = dec
                if progress:
                    progress(1)
        decoded = out
    return rects, blobs


class PyramidReader:
    """Region-of-interest decoding of a coded pyramid at any level.

    get_blob(level, tile_row, tile_col) -> bytes fetches one tile's blob;
    decoded tiles are kept in a bounded LRU cache (``cache_tiles`` of them
    over all levels), so neighbouring regions and repeated queries decode
    each tile once.
    """

    def __init__(self, rects: list[LevelRect], tile: int, step: int, get_blob, cache_tiles: int = 256):
        from collections import OrderedDict

        self.rects = list(rects)
        self.tile = tile
        self.step = step
        self._get_blob = get_blob
        self._cache: OrderedDict = OrderedDict()
        self.cache_tiles = cache_tiles
        self.tiles_decoded = 0

    @property
    def levels(self) -> int:
        return len(self.rects)

    def decode_region(self, level: int, row_a: int, row_b: int, col_a: int, col_b: int) -> np.ndarray:
        """Decoded values (int64) of lattice rows [row_a, row_b) and cols [col_a, col_b)
        of a level; the region must lie inside that level's rectangle."""
        rect = self.rects[level]
        if not (rect.row0 <= row_a < row_b <= rect.row1 and rect.col0 <= col_a < col_b <= rect.col1):
            raise ValueError(f"region rows [{row_a}, {row_b}) cols [{col_a}, {col_b}) is outside level "
                             f"{level}'s rows [{rect.row0}, {rect.row1}) cols [{rect.col0}, {rect.col1})")
        T = self.tile
        ti0, ti1 = row_a // T, -(-row_b // T)
        tj0, tj1 = col_a // T, -(-col_b // T)
        out = np.empty((row_b - row_a, col_b - col_a), np.int64)
        missing = [(ti, tj) for ti in range(ti0, ti1) for tj in range(tj0, tj1)
                   if (level, ti, tj) not in self._cache]
        coarse = cr0 = cc0 = None
        if missing and level < self.levels - 1:
            # One coarse region for every tile still to decode: its footprint plus a two-post ring.
            c = self.rects[level + 1]
            lo_e, hi_e = rect.row0 // 2, rect.row1 // 2 - 1
            lo_c, hi_c = rect.col0 // 2, rect.col1 // 2 - 1
            rs = [ti * T // 2 for ti, _ in missing]
            cs = [tj * T // 2 for _, tj in missing]
            cr0, cr1 = max(min(rs) - 1, lo_e), min(max(rs) + T // 2 + 1, hi_e) + 1
            cc0, cc1 = max(min(cs) - 1, lo_c), min(max(cs) + T // 2 + 1, hi_c) + 1
            assert c.row0 <= cr0 and cr1 <= c.row1 and c.col0 <= cc0 and cc1 <= c.col1
            coarse = self.decode_region(level + 1, cr0, cr1, cc0, cc1)
        for ti in range(ti0, ti1):
            for tj in range(tj0, tj1):
                dec = self._tile(level, ti, tj, coarse, cr0, cc0)
                r_a, r_b = max(row_a, ti * T), min(row_b, (ti + 1) * T)
                c_a, c_b = max(col_a, tj * T), min(col_b, (tj + 1) * T)
                out[r_a - row_a:r_b - row_a, c_a - col_a:c_b - col_a] = \
                    dec[r_a - ti * T:r_b - ti * T, c_a - tj * T:c_b - tj * T]
        return out

    def _tile(self, level, ti, tj, coarse, cr0, cc0) -> np.ndarray:
        key = (level, ti, tj)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        blob = self._get_blob(level, ti, tj)
        T = self.tile
        if level == self.levels - 1:
            dec = decode_top(blob, (T, T), self.step)
        else:
            dec = decode_tile(blob, coarse, T, ti * T, tj * T, self.rects[level], cr0, cc0, self.step)
        dec.setflags(write=False)
        self.tiles_decoded += 1
        self._cache[key] = dec
        while len(self._cache) > self.cache_tiles:
            self._cache.popitem(last=False)
        return dec
