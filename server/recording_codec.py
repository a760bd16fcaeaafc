"""The recorded states: canonical order, quantisation, residual coding, digests.

Pure array functions; server/recording.py frames their bytes into a file.

A recorded state is 16 numbers per entity per tick, in this column order:
ECEF position (3), ECEF velocity (3), ECEF acceleration (3), orientation
quaternion ECEF -> body w, x, y, z (4), body rates p, q, r (3) -- the
EntityState of simulation.proto. Entities are in ascending id order.

**Quantisation** (the steps go in each file's header; defaults below). The
steps are finer than anything a receiver uses: the Watch stream sends
velocities, accelerations, quaternions and rates as float32 and dead
reckoning thresholds are 0.5-1 m and 3 degrees, so a replayed state is
within 0.5 mm, 0.5 mm/s, 5 mm/s^2, 1.6e-5 rad and 5e-5 rad/s of the live
one. Exactness is kept separately: each tick's digest is of the exact
float64 states, so re-simulation checks bit for bit (server/resim.py).

**Residuals** (per chunk, every series starting from its absolute value, so
a chunk decodes alone and seeking needs one chunk):

- velocity, quaternion, body rates: first differences in time;
- position: the difference from the trapezoid prediction
  ``P[t-1] + (V[t-1] + V[t]) dt / 2`` (JSBSim and the ground model
  integrate position from velocity, so the residual is the integration's
  own small disagreement with the trapezoid, ~0 mm);
- acceleration: the difference from ``(V[t] - V[t-1]) / dt`` (the world
  defines acceleration as exactly that, so only the quantisation is left).

Predictions are computed in float64 from integers and rounded; the decoder
computes the same expressions on the same integers, so decoding is exact.
Residuals are zigzag-mapped to unsigned and split into byte planes per
field, the first tick's (absolute) values apart from the later ticks'
residuals, with all-zero high planes dropped: residuals mostly need one
plane, and zstd compresses the chunk body as a whole.
Measured on the alps scenario (12 entities, 1 s chunks): 144 bytes per
entity second before the chunk framing, a quarter of it the chunk's first
(absolute) tick.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import xxhash

from sortie.errors import DataFormatError

FIELDS = 16
POS, VEL, ACC, QUAT, RATE = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 13), slice(13, 16)
# The largest quantised magnitude recorded: 2^52 steps, the last power of two below which
# float64 holds every integer (IEEE 754 binary64, 52-bit fraction), so x / step rounds to
# the right integer, and far enough below int64's 2^63 that the residuals' sums and
# differences (velocity x 2, acceleration x 3 with the default steps) cannot overflow.
# At the default steps: 4.5e12 m, 4.5e12 m/s, 4.5e13 m/s^2. A state beyond it (NaN too) is
# recorded as +-QUANTUM_LIMIT, which readers see as out of range (:func:`out_of_range`),
# instead of int64 conversion's undefined wrap (INT64_MIN for 1e30 m on x86).
QUANTUM_LIMIT = 1 << 52


@dataclass(frozen=True)
class Steps:
    """Quantisation steps (units as in simulation.proto's EntityState)."""

    position_m: float = 1e-3
    velocity_mps: float = 1e-3
    acceleration_mps2: float = 1e-2
    quaternion: float = 2.0 ** -16
    body_rate_rps: float = 1e-4

    def vector(self) -> np.ndarray:
        return np.array([self.position_m] * 3 + [self.velocity_mps] * 3 + [self.acceleration_mps2] * 3
                        + [self.quaternion] * 4 + [self.body_rate_rps] * 3)


DEFAULT_STEPS = Steps()


def state_matrix(snapshot) -> tuple[np.ndarray, np.ndarray]:
    """(ids ascending, (n, 16) float64 states) of a server.world.Snapshot."""
    ids = snapshot.ids
    parts = [snapshot.ecef_m, snapshot.vel_ecef_mps, snapshot.acc_ecef_mps2, snapshot.quat_ecef2body,
             snapshot.body_rates_rps]
    if ids.size > 1 and not np.all(ids[1:] > ids[:-1]):  # usually in order already: no gathers then
        order = np.argsort(ids, kind="stable")
        ids, parts = ids[order], [a[order] for a in parts]
    return ids, np.concatenate(parts, axis=1).astype(np.float64, copy=False)


def gather_states(snapshots) -> tuple[np.ndarray, np.ndarray]:
    """(ids ascending, (T, E, 16) float64 states) of snapshots that all hold the same ids:
    :func:`state_matrix` of each, stacked, by a compiled copy (no temporaries)."""
    ids = snapshots[0].ids if snapshots else np.zeros(0, np.int64)
    order = np.arange(ids.size) if ids.size < 2 or np.all(ids[1:] > ids[:-1]) else np.argsort(ids, kind="stable")
    out = np.empty((len(snapshots), ids.size, FIELDS))
    for t, s in enumerate(snapshots):
        _gather_kernel(order, s.ecef_m, s.vel_ecef_mps, s.acc_ecef_mps2, s.quat_ecef2body, s.body_rates_rps, out[t])
    return ids[order], out


@numba.njit(cache=True, nogil=True)
def _gather_kernel(order, pos, vel, acc, quat, rates, out):
    for i in range(order.size):
        k = order[i]
        for j in range(3):
            out[i, j] = pos[k, j]
            out[i, 3 + j] = vel[k, j]
            out[i, 6 + j] = acc[k, j]
            out[i, 13 + j] = rates[k, j]
        for j in range(4):
            out[i, 9 + j] = quat[k, j]


def digest(ids: np.ndarray, states: np.ndarray) -> int:
    """XXH3-64 (seed 0) of the ids (int64) then the exact float64 states, as bytes.

    A check that re-simulation repeats the states bit for bit, not a defence
    against forgery: XXH3 is ~80x faster than BLAKE2b (1.6 us against 125 us
    for 500 entities' 64 KB) and any divergence shows at every later tick."""
    h = xxhash.xxh3_64(np.ascontiguousarray(ids, np.int64))
    h.update(np.ascontiguousarray(states, np.float64))
    return h.intdigest()


def quantize(states: np.ndarray, steps: Steps = DEFAULT_STEPS) -> np.ndarray:
    """float64 (..., 16) -> int64 multiples of the steps: x times 1/step (exact for the
    default steps, whose inverses are integers; a multiply is half a divide's cost),
    rounded half to even; the coding kernel of :func:`encode_states` computes the same
    IEEE expression. Values beyond +-QUANTUM_LIMIT steps (and NaN, as +) are clamped to it."""
    x = np.rint(states * (1.0 / steps.vector()))
    x = np.where(np.isnan(x), float(QUANTUM_LIMIT), np.clip(x, -float(QUANTUM_LIMIT), float(QUANTUM_LIMIT)))
    return x.astype(np.int64)


def out_of_range(q: np.ndarray) -> np.ndarray:
    """Where quantised states (..., 16) int64 sit at +-QUANTUM_LIMIT: the state was beyond what a
    recording holds and was clamped (bool, the same shape)."""
    return np.abs(q) >= QUANTUM_LIMIT


def dequantize(q: np.ndarray, steps: Steps = DEFAULT_STEPS) -> np.ndarray:
    return q * steps.vector()


def _factors(steps: Steps, rate_hz: float) -> tuple[float, float]:
    """(velocity integers -> half a tick's displacement integers, velocity change
    integers per tick -> acceleration integers)."""
    return (steps.velocity_mps / (steps.position_m * 2.0 * rate_hz),
            steps.velocity_mps * rate_hz / steps.acceleration_mps2)


def _predictions(v: np.ndarray, steps: Steps, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """(position step, acceleration) predicted from velocities v (3, E, T) ints, for ticks 1.."""
    kp, ka = _factors(steps, rate_hz)
    return (np.rint((v[..., :-1] + v[..., 1:]) * kp).astype(np.int64),
            np.rint((v[..., 1:] - v[..., :-1]) * ka).astype(np.int64))


def residuals(q: np.ndarray, steps: Steps, rate_hz: float) -> np.ndarray:
    """(16, E, T) quantised states, field-major -> residuals (see the module docstring)."""
    r = q.copy()
    for s in (VEL, QUAT, RATE):
        r[s, :, 1:] -= q[s, :, :-1]
    if q.shape[2] > 1:
        step, acc = _predictions(q[VEL], steps, rate_hz)
        r[POS, :, 1:] -= q[POS, :, :-1] + step
        r[ACC, :, 1:] -= acc
    return r


def restore(r: np.ndarray, steps: Steps, rate_hz: float) -> np.ndarray:
    """Inverse of :func:`residuals`."""
    q = r.copy()
    for s in (VEL, QUAT, RATE):
        np.cumsum(q[s], axis=2, out=q[s])
    if q.shape[2] > 1:
        step, acc = _predictions(q[VEL], steps, rate_hz)
        q[ACC, :, 1:] += acc
        q[POS, :, 1:] += step
        np.cumsum(q[POS], axis=2, out=q[POS])
    return q


def fill_absent(q: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Absent entries (an entity not yet or no longer there) take the nearest present
    value in time (forward, then backward), so they cost no residuals."""
    if present.all():
        return q
    q = q.copy()
    t_count = q.shape[0]
    idx = np.where(present, np.arange(t_count)[:, None], -1)
    np.maximum.accumulate(idx, axis=0, out=idx)  # last present tick at or before t
    first = np.argmax(present, axis=0)  # the first present tick, for the leading gap
    idx = np.where(idx < 0, first[None, :], idx)
    cols = np.arange(q.shape[1])[None, :]
    return q[idx, cols]


def _zigzag(x: np.ndarray) -> np.ndarray:
    return ((x << 1) ^ (x >> 63)).view(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> np.uint64(1)).view(np.int64) ^ -(u & np.uint64(1)).view(np.int64)


def _planes(values: np.ndarray) -> bytes:
    """One byte (planes kept, k), then k byte planes (least significant first) of the
    zigzagged values: k is the fewest bytes that hold the largest."""
    u = _zigzag(np.ascontiguousarray(values, np.int64).reshape(-1))
    k = (int(u.max()).bit_length() + 7) // 8 if u.size else 0
    out = np.empty((k, u.size), np.uint8)
    for j in range(k):
        out[j] = (u >> np.uint64(8 * j)).astype(np.uint8)  # the low byte
    return bytes([k]) + out.tobytes()


def _unplanes(buf: np.ndarray, pos: int, n: int, what: str) -> tuple[np.ndarray, int]:
    """Inverse of :func:`_planes` for n values at buf[pos:]; (int64 values, new pos)."""
    if pos >= buf.size:
        raise DataFormatError(f"chunk states end before {what}")
    k = int(buf[pos])
    pos += 1
    if k > 8 or pos + k * n > buf.size:
        raise DataFormatError(f"chunk states: {what} claims {k} planes of {n} bytes, {buf.size - pos} bytes left")
    u = np.zeros(n, np.uint64)
    for j in range(k):  # small residuals need one or two planes
        u |= buf[pos + j * n:pos + (j + 1) * n].astype(np.uint64) << np.uint64(8 * j)
    return _unzigzag(u), pos + k * n


def encode(q: np.ndarray, steps: Steps, rate_hz: float) -> bytes:
    """(T, E, 16) int64 -> bytes: per field, the first tick's values (absolute) then the
    later ticks' residuals, each as :func:`_planes` (entity-major: each series contiguous).
    The reference for :func:`encode_states` (same bytes, tested)."""
    r = residuals(np.ascontiguousarray(q.transpose(2, 1, 0)), steps, rate_hz)  # (16, E, T)
    out = []
    for f in range(FIELDS):
        out.append(_planes(r[f, :, :1]))
        out.append(_planes(r[f, :, 1:]))
    return b"".join(out)


def encode_states(states: np.ndarray, steps: Steps, rate_hz: float) -> bytes:
    """(T, E, 16) float64 states -> the bytes of ``encode(quantize(states))``, by one
    compiled pass that releases the GIL: the recorder's thread codes a chunk while the
    clock thread runs (measured at 500 entities: the numpy path held the GIL for ~10 ms
    a chunk and made the clock's ticks ~10-25 % slower on two cores)."""
    return encode_states_counted(states, steps, rate_hz)[0]


def encode_states_counted(states: np.ndarray, steps: Steps, rate_hz: float) -> tuple[bytes, int]:
    """(:func:`encode_states`'s bytes, how many values were clamped to +-QUANTUM_LIMIT steps)."""
    t_count, e_count = states.shape[0], states.shape[1]
    kp, ka = _factors(steps, rate_hz)
    q = np.empty((FIELDS, e_count, t_count), np.int64)
    out = np.empty(2 * FIELDS + 8 * FIELDS * e_count * t_count, np.uint8)
    clamped = np.zeros(1, np.int64)
    n = _encode_kernel(np.ascontiguousarray(states, np.float64), 1.0 / steps.vector(), kp, ka, q, out, clamped)
    return out[:n].tobytes(), int(clamped[0])


@numba.njit(cache=True, nogil=True)
def _encode_kernel(states, inverse_steps, kp, ka, q, out, clamped):
    """Quantise states (T, E, 16) into q (16, E, T) (as :func:`quantize`, counting in
    clamped[0] the values clamped), turn q into its residuals in place (as
    :func:`residuals`: later ticks first, so each prediction reads quantised values), then
    write :func:`encode`'s bytes to out; the number written."""
    t_count, e_count = states.shape[0], states.shape[1]
    limit = np.float64(QUANTUM_LIMIT)
    for e in range(e_count):  # each series' ticks are adjacent in q: write them in order
        for t in range(t_count):
            for f in range(FIELDS):
                x = np.rint(states[t, e, f] * inverse_steps[f])
                if not -limit <= x <= limit:
                    x = -limit if x < -limit else limit  # NaN too: above
                    clamped[0] += 1
                q[f, e, t] = np.int64(x)
    for e in range(e_count):
        for t in range(t_count - 1, 0, -1):
            for f in range(3):  # position: from the trapezoid of the velocities
                step = np.int64(np.rint(np.float64(q[f + 3, e, t - 1] + q[f + 3, e, t]) * kp))
                q[f, e, t] -= q[f, e, t - 1] + step
            for f in range(6, 9):  # acceleration: from the velocity change
                q[f, e, t] -= np.int64(np.rint(np.float64(q[f - 3, e, t] - q[f - 3, e, t - 1]) * ka))
            for f in range(3, 6):
                q[f, e, t] -= q[f, e, t - 1]
            for f in range(9, FIELDS):
                q[f, e, t] -= q[f, e, t - 1]
    pos = 0
    for f in range(FIELDS):
        for group in range(2):  # the first tick's values, then the later ticks' residuals
            t0, t1 = (0, min(1, t_count)) if group == 0 else (1, t_count)
            n = e_count * max(t1 - t0, 0)
            top = np.uint64(0)
            for e in range(e_count):
                for t in range(t0, t1):
                    r = q[f, e, t]
                    z = np.uint64((r << 1) ^ (r >> 63))
                    q[f, e, t] = np.int64(z)  # zigzagged, kept for the planes
                    if z > top:
                        top = z
            k = 0
            while top > 0:
                top >>= np.uint64(8)
                k += 1
            out[pos] = k
            pos += 1
            for j in range(k):
                shift = np.uint64(8 * j)
                i = pos + j * n
                for e in range(e_count):
                    for t in range(t0, t1):
                        out[i] = np.uint8((np.uint64(q[f, e, t]) >> shift) & np.uint64(255))
                        i += 1
            pos += k * n
    return pos


def decode(data: bytes, ticks: int, entities: int, steps: Steps, rate_hz: float) -> np.ndarray:
    """Inverse of :func:`encode`; DataFormatError when the bytes do not fit the shape."""
    r = np.empty((FIELDS, entities, ticks), np.int64)
    buf = np.frombuffer(data, np.uint8)
    pos = 0
    for f in range(FIELDS):
        first, pos = _unplanes(buf, pos, entities if ticks else 0, f"field {f}'s first tick")
        rest, pos = _unplanes(buf, pos, entities * max(ticks - 1, 0), f"field {f}'s residuals")
        if ticks:
            r[f, :, 0] = first
            r[f, :, 1:] = rest.reshape(entities, ticks - 1)
    if pos != buf.size:
        raise DataFormatError(f"chunk states: {buf.size - pos} bytes left over")
    return restore(r, steps, rate_hz).transpose(2, 1, 0)
