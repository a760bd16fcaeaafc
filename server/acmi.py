"""Tacview ACMI 2.2 export of a recording (``sortie export acmi``).

ACMI is Tacview's text format (https://www.tacview.net/documentation/acmi/en/):
a header of global properties on object 0, then time frames ``#<seconds>``
(relative to ``ReferenceTime``) holding object lines
``<hex id>,T=lon|lat|alt|roll|pitch|yaw,Prop=value,...``, removals ``-<hex id>``
and events ``0,Event=Kind|<hex id>|text``. A reader keeps each property's last
value, so a line carries only what changed.

What we write:

- **Header**: ``ReferenceTime`` = the recording's world time 0 (header
  ``start_time``), ``ReferenceLongitude/Latitude`` = the whole degrees nearest
  the median position of the first recorded tick (object longitudes and
  latitudes are offsets from them), ``Title`` = the exercise name,
  ``DataSource`` = the Sortie version that recorded, ``DataRecorder`` = this
  exporter, ``RecordingTime`` = when the recording was started (wall clock).
- **Objects**: id = the entity id in hexadecimal (Sortie ids start at 1, and 0
  is the global object). The first line of an object carries its static
  properties: ``Type`` (:func:`acmi_type`), ``Name`` = its scenario name,
  ``LongName`` = its type name (the JSBSim model, vehicle type or static
  type: LongName is a detail name, so Tacview keeps labelling the object by
  its Name), ``Coalition`` (Blue, Red, Neutrals) and ``Color`` (Blue, Red, Grey).
- **Coordinates**: ``T=lon|lat|alt|roll|pitch|yaw``: longitude and latitude
  (WGS84, degrees, as offsets from the reference, 7 decimals: ~1 cm; a
  longitude offset is unwrapped into (-180, 180], so across the antimeridian
  it runs on past +-180 instead of jumping by 360, :func:`lon_offset_deg`),
  altitude (m above MSL = ellipsoid height - the recording's geoid
  undulation, 2 decimals), roll, pitch and yaw (degrees, 1 decimal; yaw is the
  true heading in [0, 360), roll in (-180, 180]), the z-y-x Euler angles of the
  body relative to local NED (:func:`attitude_deg`). Numbers are the state
  rounded to those decimals, written without trailing zeros.
- **Only changes**: a component is written when its rounded value differs from
  the one last written for that object, an unchanged component is left empty
  (``T=|||0.1||``), and an object with nothing changed writes no line; a
  frame with no lines is left out (except the last tick's, which marks the end).
- **Removals**: an object present at one exported tick and absent at the
  next gets ``-id``; one that comes back is a new object (full line again).
  Entities present at no exported tick are not written.
- **Events** (Sortie kind -> ACMI): crash -> ``Destroyed``, takeoff ->
  ``TakenOff``, touchdown -> ``Landed``, out_of_fuel, join, leave, vanished
  and any other -> ``Message``; spawn and remove are the object lines and
  removals themselves. An event goes in the frame of its tick (its world
  time): that tick's frame when the tick is exported, else a frame of its
  own. Text is escaped (``\\,``; a ``|`` in free text becomes ``/``,
  since ``|`` separates the event's fields).
- **Rate**: every recorded tick by default; ``rate_hz`` keeps the first
  recorded tick of each 1/rate_hz interval of world time (and always the
  first and the last tick); a rate at or above the world rate keeps every tick.
- **Files**: ``.acmi`` is the UTF-8 text (with a BOM, as Tacview writes it);
  ``.zip.acmi`` a zip archive holding that same text as one ``.txt.acmi``
  member, as Tacview saves compressed recordings. Written to a temporary name
  beside the output and renamed when complete.

Speed: the states of a whole recording chunk (every tick and entity in it) go
through geodesy, attitude, rounding, change detection and number formatting
as numpy arrays; the text is assembled as a byte matrix (one row per line, a
column per character, a mask of the characters kept) and compacted with one
boolean index, so no Python code runs per number or per line.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import re
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from server import recording_codec as codec
from server.dead_reckoning import ecef_to_ned_quat, quat_conjugate, quat_multiply
from sortie import __version__
from sortie.errors import DataFormatError, InvalidArgument, NotFound
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic

log = logging.getLogger(__name__)

FILE_HEADER = "\ufeffFileType=text/acmi/tacview\nFileVersion=2.2\n"
PLAIN_SUFFIX = ".acmi"
ZIP_SUFFIX = ".zip.acmi"
ZIP_MEMBER_SUFFIX = ".txt.acmi"

# T= components, in file order: lon, lat (offsets, degrees), alt (m MSL), roll, pitch, yaw (degrees).
T_DECIMALS = (7, 7, 2, 1, 1, 1)
_T_SCALE = np.array([10.0 ** d for d in T_DECIMALS])
_TENTHS_PER_TURN = 3600  # yaw wraps at 360.0 degrees, roll's -180.0 is written as 180.0
_MAX_WRITTEN = 1e17  # integers in units of the last decimal: far beyond any real state

AIRCRAFT, GROUND, STATIC = 1, 2, 3  # sortie.v1.EntityKind
COALITIONS = {"blue": ("Blue", "Blue"), "red": ("Red", "Red"), "neutral": ("Neutrals", "Grey")}

# Catalogued ground vehicles (fdm/vehicle_types.py) by what they are; free text by its words.
VEHICLE_TYPES = {
    "m1a2": "Ground+Heavy+Armor+Vehicle+Tank",  # main battle tank
    "m2a3": "Ground+Heavy+Armor+Vehicle",  # infantry fighting vehicle
    "hmmwv": "Ground+Vehicle",
    "m1083": "Ground+Vehicle",  # 5-ton truck
}
_TANK_WORDS = {"tank", "mbt"}
_ARMOR_WORDS = {"armor", "armour", "armored", "armoured", "apc", "ifv"}
_AIR_DEFENCE_WORDS = {"sam", "aaa", "flak", "manpads", "airdefense", "airdefence"}

EVENT_KINDS = {"crash": "Destroyed", "destroyed": "Destroyed", "takeoff": "TakenOff", "touchdown": "Landed"}
NO_EVENT = {"spawn", "remove"}  # these are object lines and removals


# -- pure functions -------------------------------------------------------------------------------

def attitude_deg(quat_ecef2body, lat_deg, lon_deg):
    """(roll, pitch, yaw) degrees of ECEF -> body quaternions at geodetic (lat, lon).

    quat_ecef2body: (..., 4) float64 (w, x, y, z), as recorded; lat_deg, lon_deg:
    (...) degrees, broadcast. The NED -> body rotation is
    q_nb = conj(q_en) * q_eb (server.dead_reckoning.ned_to_ecef_quat builds
    q_eb = q_en * q_nb); its z-y-x Euler angles come from its matrix R (body
    components -> NED): yaw = atan2(R10, R00), pitch = atan2(-R20, hypot(R00,
    R10)), roll = atan2(R21, R22). The atan2 forms keep pitch accurate near
    +-90 degrees (where asin loses half the digits); at exactly +-90 roll and
    yaw are not separable and the split is atan2's. Returns roll in
    [-180, 180], pitch in [-90, 90], yaw in [0, 360).
    """
    q_nb = quat_multiply(quat_conjugate(ecef_to_ned_quat(lat_deg, lon_deg)), quat_ecef2body)
    w, x, y, z = q_nb[..., 0], q_nb[..., 1], q_nb[..., 2], q_nb[..., 3]
    n2 = w * w + x * x + y * y + z * z  # recorded quaternions are rounded: normalise inside R
    r00 = n2 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + w * z)
    r20 = 2.0 * (x * z - w * y)
    r21 = 2.0 * (y * z + w * x)
    r22 = n2 - 2.0 * (x * x + y * y)
    yaw = np.degrees(np.arctan2(r10, r00)) % 360.0
    yaw = np.where(yaw < 360.0, yaw, 0.0)  # -1e-15 % 360 is 360.0 in floating point
    pitch = np.degrees(np.arctan2(-r20, np.hypot(r00, r10)))
    roll = np.degrees(np.arctan2(r21, r22))
    return roll, pitch, yaw


def pose_of_states(states, geoid_undulation_m: float = 0.0) -> np.ndarray:
    """(..., 6) float64 (lon deg, lat deg, alt m MSL, roll, pitch, yaw deg) of recorded states.

    states: (..., 16) float64 in recording_codec column order (ECEF position m,
    ..., quaternion ECEF -> body); MSL = ellipsoid height - geoid_undulation_m.
    """
    states = np.asarray(states, dtype=np.float64)
    if states.shape[-1] != codec.FIELDS:
        raise ValueError(f"states must have shape (..., {codec.FIELDS}), got {states.shape}")
    lat, lon, h = ecef_to_geodetic(states[..., codec.POS])
    roll, pitch, yaw = attitude_deg(states[..., codec.QUAT], lat, lon)
    return np.stack([lon, lat, h - geoid_undulation_m, roll, pitch, yaw], axis=-1)


def pose_integers(pose, ref_lon_deg: int, ref_lat_deg: int) -> np.ndarray:
    """(..., 6) int64: a pose rounded to the written decimals (T_DECIMALS), in units of the
    last decimal; longitude and latitude as offsets from the reference."""
    p = np.array(pose, dtype=np.float64)
    p[..., 0] = lon_offset_deg(p[..., 0], ref_lon_deg)
    p[..., 1] -= ref_lat_deg
    scaled = np.clip(np.nan_to_num(p * _T_SCALE), -_MAX_WRITTEN, _MAX_WRITTEN)  # keep int64 text sane
    v = np.rint(scaled).astype(np.int64)
    v[..., 5] %= _TENTHS_PER_TURN
    roll = v[..., 3]
    roll[roll == -_TENTHS_PER_TURN // 2] = _TENTHS_PER_TURN // 2
    return v


def lon_offset_deg(lon_deg, ref_lon_deg) -> np.ndarray:
    """Longitudes as offsets from the reference, unwrapped into (-180, 180]: with
    ReferenceLongitude=180 an object just east of the antimeridian (-179.75) is +0.25, not
    -359.75, so one crossing it moves on smoothly (Tacview interpolates the offsets)."""
    d = np.asarray(lon_deg, dtype=np.float64) - ref_lon_deg
    out = (d > 180.0) | (d <= -180.0)
    if out.any():
        d = np.where(out, 180.0 - np.mod(180.0 - d, 360.0), d)
    return d


def reference_point(lat_deg, lon_deg) -> tuple[int, int]:
    """(longitude, latitude) whole degrees nearest the median position (0, 0 for none).
    Longitudes spread over more than 180 degrees (an exercise across the antimeridian) take
    their median in [0, 360), so the reference falls among them (180, not 0), within
    (-180, 180]."""
    if np.size(lat_deg) == 0:
        return 0, 0
    lon = np.asarray(lon_deg, dtype=np.float64).reshape(-1)
    if np.ptp(lon) <= 180.0:
        ref_lon = int(np.rint(np.median(lon)))
    else:
        ref_lon = int(np.rint(np.median(np.mod(lon, 360.0))))
        ref_lon = ref_lon - 360 if ref_lon > 180 else ref_lon
    return ref_lon, int(np.rint(np.median(lat_deg)))


def acmi_type(kind: int, type_name: str) -> str:
    """Tacview type tags of an entity of ``kind`` (1 aircraft, 2 ground, 3 static) and type;
    "Misc+Minor" for an entity the recording does not describe (kind 0)."""
    words = set(re.split(r"[^a-z0-9]+", type_name.lower()))
    if kind == AIRCRAFT:
        return "Air+FixedWing"
    if kind not in (GROUND, STATIC):
        return "Misc+Minor"
    if words & _AIR_DEFENCE_WORDS:
        return "Ground+AntiAircraft"
    if kind == GROUND:
        if type_name.lower() in VEHICLE_TYPES:
            return VEHICLE_TYPES[type_name.lower()]
        if words & _TANK_WORDS:
            return "Ground+Heavy+Armor+Vehicle+Tank"
        if words & _ARMOR_WORDS:
            return "Ground+Heavy+Armor+Vehicle"
        return "Ground+Vehicle"
    return "Ground+Static+Building"


def escape(text: str) -> str:
    """A property value as ACMI needs it: commas and line ends escaped with a backslash
    (ACMI has no escape for a backslash itself, so one becomes '/')."""
    return text.replace("\\", "/").replace(",", "\\,").replace("\r\n", "\n").replace("\n", "\\\n")


def object_properties(info) -> str:
    """The static properties of an entity (its first line), each as ``,Prop=value``.

    info: sortie.v1.EntityInfo (entity_id, name, kind, type, coalition)."""
    coalition, color = COALITIONS.get(info.coalition, COALITIONS["neutral"])
    props = [("Type", acmi_type(int(info.kind), info.type)), ("Name", info.name or f"entity {info.entity_id}"),
             ("LongName", info.type), ("Coalition", coalition), ("Color", color)]
    return "".join(f",{k}={escape(v)}" for k, v in props if v)


def event_line(event, object_hex: str | None, name: str) -> str | None:
    """The ``0,Event=...`` line of a sortie.v1.WorldEvent (None for spawn and remove).

    object_hex: the ACMI id of the entity concerned, or None when it is not
    (or not yet) an object of the file; name: how the text calls it."""
    if event.kind in NO_EVENT:
        return None
    try:
        detail = json.loads(event.detail_json) if event.detail_json else {}
    except ValueError:
        detail = {}
    if event.kind == "crash":
        text = f"{name} crashed" + (f": {detail['reason']}" if detail.get("reason") else "")
    elif event.kind == "destroyed":
        text = f"{name} destroyed" + (f": {detail['reason']}" if detail.get("reason") else "")
    elif event.kind == "takeoff":
        text = f"{name} took off"
    elif event.kind == "touchdown":
        text = f"{name} touched down"
    elif event.kind == "out_of_fuel":
        text = f"{name} is out of fuel"
    elif event.kind == "collision":
        speed = detail.get("relative_speed_mps")
        text = f"{name} collided with {detail.get('other_name', 'another entity')}" + (
            f" at {speed:.1f} m/s" if isinstance(speed, (int, float)) else "")
    elif event.kind in ("join", "leave", "vanished"):
        verb = {"join": "joined", "leave": "left", "vanished": "vanished from"}[event.kind]
        role = f" as {detail['role'].lower()}" if detail.get("role") and event.kind == "join" else ""
        text = f"{detail.get('client', 'a client')} {verb} {name}{role}"
    else:
        text = f"{event.kind}: {name}" + (f" {event.detail_json}" if detail else "")
    kind = EVENT_KINDS.get(event.kind, "Message")
    fields = [kind] + ([object_hex] if object_hex else []) + [escape(text.replace("|", "/"))]
    return "0,Event=" + "|".join(fields)


def iso_utc(value: str, what: str) -> str:
    """ISO 8601 UTC with a 'Z' (milliseconds when there are any), as ACMI dates are; a
    time without a zone is taken as UTC. DataFormatError naming ``what`` if unreadable."""
    try:
        t = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise DataFormatError(f"{what} is not an ISO 8601 time (got {value!r})") from None
    if t.tzinfo is not None:
        try:
            t = t.astimezone(dt.timezone.utc).replace(tzinfo=None)
        except OverflowError:  # 9999-12-31T23:59:59-05:00 is in year 10000 UTC (the scenario refuses it)
            raise DataFormatError(f"{what} is not within years 1..9999 in UTC (got {value!r})") from None
    # ISO 8601 writes the year in four digits (0001..9999; ISO 8601-1:2019, 5.2.2.1), as
    # datetime.isoformat does; strftime("%Y") does not pad years before 1000 with glibc
    # (the Python docs' strftime notes), and "800-03-01T..." is no ISO 8601 date.
    text = t.replace(microsecond=0).isoformat(timespec="seconds")
    if t.microsecond:
        text += f".{t.microsecond // 1000:03d}"
    return text + "Z"


def time_text(t_s: float, decimals: int) -> str:
    """Seconds with at most ``decimals`` decimals, without trailing zeros."""
    text = f"{t_s:.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


# Frame times are written to the microsecond at least: Tacview derives speed, acceleration and
# g from the track and the frame times, and at 30 Hz times rounded to 1 ms (0.033 / 0.034 s
# apart) made an f16 holding 200 m/s read 196-202 m/s and 18 g (an acceptance probe). Rounded
# to 1 us a frame time is off by at most 0.5 us: 3 mm/s at 200 m/s over a 1/30 s frame, under
# what the positions' 1 cm does to a speed.
MIN_TIME_DECIMALS = 6


def time_decimals(dt_s: float) -> int:
    """Decimals of frame times dt_s apart: MIN_TIME_DECIMALS, more where frames are closer than
    that keeps distinct (10^-d <= dt_s / 2)."""
    return max(MIN_TIME_DECIMALS, int(np.ceil(-np.log10(dt_s / 2.0))))


def selected_ticks(ticks: np.ndarray, world_rate_hz: float, rate_hz: float | None,
                   first_tick: int, last_tick: int) -> np.ndarray:
    """Bool mask over ``ticks`` (ascending ints): those exported at ``rate_hz``.

    A tick is kept when it is the first of its 1/rate_hz interval of world time
    (floor(tick * rate / world_rate) differs from the previous tick's); the
    recording's first and last ticks are always kept."""
    ticks = np.asarray(ticks, dtype=np.int64)
    if rate_hz is None or rate_hz >= world_rate_hz:
        return np.ones(ticks.shape, bool)
    bucket = np.floor(ticks * rate_hz / world_rate_hz + 1e-9)
    before = np.floor((ticks - 1) * rate_hz / world_rate_hz + 1e-9)
    return (bucket != before) | (ticks == first_tick) | (ticks == last_tick)


# -- the text of object lines (a numba kernel) ---------------------------------------------------

_COMMA_T = np.frombuffer(b",T=", np.uint8)
_T_DECIMALS = np.array(T_DECIMALS, np.int64)
_MAX_NUMBER_CHARS = 21  # '-', 19 digits of int64, '.'


@numba.njit(cache=True, nogil=True)
def _put_fixed(out, pos, v, decimals):
    """Write v / 10^decimals at out[pos:] ('-', integer part, '.' and the decimals up to the
    last non-zero one); return the position after it."""
    if v < 0:
        out[pos] = 45  # '-'
        pos += 1
        v = -v
    scale = 1
    for _ in range(decimals):
        scale *= 10
    whole = v // scale
    frac = v - whole * scale
    start = pos
    while True:  # digits least significant first, then reversed
        out[pos] = 48 + whole % 10
        whole //= 10
        pos += 1
        if whole == 0:
            break
    lo, hi = start, pos - 1
    while lo < hi:
        out[lo], out[hi] = out[hi], out[lo]
        lo += 1
        hi -= 1
    if frac:
        out[pos] = 46  # '.'
        pos += 1
        kept = decimals
        while frac % 10 == 0:
            frac //= 10
            kept -= 1
        for k in range(kept - 1, -1, -1):
            out[pos + k] = 48 + frac % 10
            frac //= 10
        pos += kept
    return pos


@numba.njit(cache=True, nogil=True)
def _object_lines(rows_slot, values, changed, id_chars, id_len, suffix_chars, suffix_len, with_suffix,
                  decimals, comma_t, out, ends):
    pos = 0
    for i in range(rows_slot.size):
        s = rows_slot[i]
        for c in range(id_len[s]):
            out[pos] = id_chars[s, c]
            pos += 1
        for c in range(comma_t.size):
            out[pos] = comma_t[c]
            pos += 1
        for j in range(values.shape[1]):
            if j:
                out[pos] = 124  # '|'
                pos += 1
            if changed[i, j]:
                pos = _put_fixed(out, pos, values[i, j], decimals[j])
        if with_suffix:
            for c in range(suffix_len[s]):
                out[pos] = suffix_chars[s, c]
                pos += 1
        out[pos] = 10  # '\n'
        pos += 1
        ends[i] = pos
    return pos


def text_table(texts: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """(chars (n, w) uint8, lengths (n,) int64) of byte strings, padded to the longest."""
    width = max((len(t) for t in texts), default=0)
    chars = np.zeros((len(texts), max(width, 1)), np.uint8)
    for i, t in enumerate(texts):
        chars[i, :len(t)] = np.frombuffer(t, np.uint8)
    return chars, np.array([len(t) for t in texts], np.int64)


def object_lines(rows_slot, values, changed, ids, suffixes=None) -> tuple[bytes, np.ndarray]:
    """ACMI object lines ``<id>,T=a|b|c|d|e|f<suffix>\\n``, one per row, and where each ends.

    rows_slot: (n,) int64, the row's object in ``ids`` (and ``suffixes``);
    values: (n, 6) int64 T components in units of their last decimal
    (:func:`pose_integers`), written as decimals without trailing zeros
    ("12.5", "-0.25", "3"); changed: (n, 6) bool, the components written (the
    others are left empty); ids, suffixes: text_table()s of each object's hex
    id and of the text put before the line end (static properties).
    Returns (the lines' bytes, (n,) int64 end offsets).
    """
    rows_slot = np.ascontiguousarray(rows_slot, dtype=np.int64)
    values = np.ascontiguousarray(values, dtype=np.int64)
    changed = np.ascontiguousarray(changed, dtype=np.bool_)
    n = rows_slot.size
    if values.shape != (n, len(T_DECIMALS)) or changed.shape != values.shape:
        raise ValueError(f"values and changed must have shape ({n}, {len(T_DECIMALS)}), "
                         f"got {values.shape} and {changed.shape}")
    suffix_chars, suffix_len = suffixes if suffixes is not None else (np.zeros((1, 1), np.uint8),
                                                                      np.zeros(1, np.int64))
    width = (ids[0].shape[1] + _COMMA_T.size + len(T_DECIMALS) * (_MAX_NUMBER_CHARS + 1)
             + int(_T_DECIMALS.sum()) + (suffix_chars.shape[1] if suffixes is not None else 0) + 1)
    out = np.zeros(n * width, np.uint8)
    ends = np.zeros(n, np.int64)
    size = _object_lines(rows_slot, values, changed, ids[0], ids[1], suffix_chars, suffix_len,
                         suffixes is not None, _T_DECIMALS, _COMMA_T, out, ends)
    return out[:size].tobytes(), ends


# -- the export -----------------------------------------------------------------------------------

@dataclass
class ExportStats:
    """What an export wrote and how long it took."""

    path: str
    bytes_written: int  # the output file (zipped or not)
    text_bytes: int  # the ACMI text
    frames: int  # time frames written
    ticks: int  # recorded ticks exported (at the chosen rate)
    states: int  # entity states exported (present entities x exported ticks)
    objects: int  # distinct objects written
    lines: int  # object lines written
    removals: int
    events: int
    seconds: float
    skipped: list = field(default_factory=list)  # the damaged chunks left out, each problem named

    @property
    def states_per_s(self) -> float:
        return self.states / self.seconds if self.seconds > 0 else float("inf")


class _Objects:
    """Per entity (a slot each): its id text, static properties and what was last written."""

    def __init__(self, entities: dict):
        self.entities = entities
        self.slot_of: dict[int, int] = {}
        self.hex: list[str] = []
        self.props: list[bytes] = []
        self.last = np.zeros((0, 6), np.int64)  # values last written
        self.alive = np.zeros(0, bool)  # present at the last exported tick
        self.written = np.zeros(0, bool)  # ever written
        self.id_table = text_table([])  # the hex ids and static properties as text_table()s
        self.props_table = text_table([])

    def slots(self, ids: np.ndarray) -> np.ndarray:
        fresh = [int(i) for i in ids if int(i) not in self.slot_of]
        for i in fresh:
            self.slot_of[i] = len(self.hex)
            self.hex.append(f"{i:x}")
            described = self.entities.get(i) or pb.EntityInfo(entity_id=i, coalition="neutral")
            self.props.append(object_properties(described).encode())
        if fresh:
            k = len(fresh)
            self.last = np.concatenate([self.last, np.zeros((k, 6), np.int64)])
            self.alive = np.concatenate([self.alive, np.zeros(k, bool)])
            self.written = np.concatenate([self.written, np.zeros(k, bool)])
            self.id_table = text_table([h.encode() for h in self.hex])
            self.props_table = text_table(self.props)
        return np.array([self.slot_of[int(i)] for i in ids], np.int64)

    def name(self, entity_id: int) -> str:
        info = self.entities.get(entity_id)
        return info.name if info is not None and info.name else f"entity {entity_id}"


def output_kind(path) -> str:
    """"zip" for a ``.zip.acmi`` name, "plain" for ``.acmi``; InvalidArgument otherwise."""
    name = Path(path).name.lower()
    if name.endswith(ZIP_SUFFIX):
        return "zip"
    if name.endswith(PLAIN_SUFFIX):
        return "plain"
    raise InvalidArgument("output", f"must end in {PLAIN_SUFFIX} or {ZIP_SUFFIX}", value=str(path))


def check_rate(rate_hz) -> float | None:
    """The export rate (None: every tick); InvalidArgument unless a finite number > 0."""
    if rate_hz is None:
        return None
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise InvalidArgument("rate", "must be a number of frames per second", value=rate_hz) from None
    if not np.isfinite(rate) or rate <= 0.0:
        raise InvalidArgument("rate", "must be a finite number of frames per second > 0", value=rate_hz)
    return rate


def export_acmi(recording, out_path, rate_hz: float | None = None) -> ExportStats:
    """Write ``recording`` (server.recording.Recording, open) as an ACMI file at ``out_path``.

    ``.zip.acmi`` writes a zip archive, ``.acmi`` plain text (see the module
    docstring); rate_hz: frames per second of world time (None: every tick).
    """
    rate = check_rate(rate_hz)
    kind = output_kind(out_path)
    out_path = Path(out_path)
    if not out_path.parent.is_dir():
        raise NotFound(f"output folder {str(out_path.parent)!r} does not exist")
    tmp = out_path.with_name(out_path.name + ".part")
    t0 = time.perf_counter()
    try:
        with open(tmp, "wb") as raw:
            if kind == "zip":
                member = out_path.name[:-len(ZIP_SUFFIX)] + ZIP_MEMBER_SUFFIX
                with zipfile.ZipFile(raw, "w", zipfile.ZIP_DEFLATED) as zf, \
                        zf.open(member, "w", force_zip64=True) as stream:
                    stats = _write(recording, stream, rate)
            else:
                stats = _write(recording, raw, rate)  # written a chunk at a time: no buffer needed
        os.replace(tmp, out_path)
    finally:
        tmp.unlink(missing_ok=True)
    stats.path = str(out_path)
    stats.bytes_written = out_path.stat().st_size
    stats.seconds = time.perf_counter() - t0
    log.info("exported %s: %d states in %.2f s (%.0f states/s), %d bytes", out_path, stats.states,
             stats.seconds, stats.states_per_s, stats.bytes_written)
    return stats


def header_text(recording, ref_lon: int, ref_lat: int) -> str:
    """The file header and the global properties (object 0)."""
    h = recording.header
    lines = [f"0,ReferenceTime={iso_utc(h.start_time, f'{recording.path.name}: header start_time')}",
             f"0,ReferenceLongitude={ref_lon}", f"0,ReferenceLatitude={ref_lat}"]
    if h.exercise_name:
        lines.append(f"0,Title={escape(h.exercise_name)}")
    lines.append(f"0,DataSource=Sortie {escape(h.sortie_version or 'unknown')}")
    lines.append(f"0,DataRecorder=Sortie {__version__} (sortie export acmi)")
    if h.created_unix_s > 0:
        created = dt.datetime.fromtimestamp(h.created_unix_s, dt.timezone.utc)
        lines.append(f"0,RecordingTime={iso_utc(created.isoformat(), 'created_unix_s')}")
    return FILE_HEADER + "".join(line + "\n" for line in lines)


def _write(r, stream, rate: float | None) -> ExportStats:
    """Write the whole ACMI text of recording ``r`` to the binary ``stream``."""
    out = _AcmiText(r, rate)
    stream.write(out.header())
    for _, c in r.readable_chunks(out.stats.skipped):
        stream.write(out.chunk(c))
    stream.write(out.finish())
    return out.stats


class _AcmiText:
    """The ACMI text of one recording, a chunk at a time (see the module docstring)."""

    def __init__(self, r, rate: float | None):
        self.r = r
        self.rate = rate
        self.stats = ExportStats("", 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.0)
        self.objects = _Objects(r.entities)
        self.decimals = time_decimals(r.dt)
        self.steps = r.steps.vector()
        self.pending_events: list = []  # EventRecords not yet written
        self.header_tick = None  # the tick of the last frame header written
        self.ref = (0, 0)

    def _emit(self, parts: list[bytes]) -> bytes:
        data = b"".join(parts)
        self.stats.text_bytes += len(data)
        return data

    def header(self) -> bytes:
        """The header, its reference point from the first tick that reads (a damaged first
        chunk is left out of the export, as any other: the chunks are named by the export)."""
        r = self.r
        for k in range(r.chunk_count if r.index.ticks else 0):
            first, last = r.chunk_ticks(k)
            if last < first:
                continue
            try:
                states = r.frame(first).states
            except DataFormatError:
                continue
            lat, lon, _ = ecef_to_geodetic(states[:, codec.POS])
            self.ref = reference_point(lat, lon)
            break
        return self._emit([header_text(r, *self.ref).encode()])

    def chunk(self, c) -> bytes:
        """The frames of a decoded chunk (server.recording.Chunk) at the export rate."""
        r, objects = self.r, self.objects
        self.pending_events.extend(c.events)
        ticks = c.first_tick + np.arange(c.ticks)
        sel = np.flatnonzero(selected_ticks(ticks, r.rate_hz, self.rate, r.first_tick, r.last_tick))
        slots = objects.slots(c.entity_ids)
        if sel.size == 0:
            return b""
        gone = objects.alive.copy()
        gone[slots] = False  # alive objects that this chunk does not hold at all
        present = c.present[sel]
        values = pose_integers(pose_of_states(c.q[sel] * self.steps, r.header.geoid_undulation_m), *self.ref)
        prev_values = np.concatenate([objects.last[slots][None], values[:-1]])
        prev_alive = np.concatenate([objects.alive[slots][None], present[:-1]])
        new = present & ~prev_alive
        changed = (values != prev_values) & (present & prev_alive)[..., None]
        update = changed.any(axis=-1)
        removed = prev_alive & ~present
        new_text = _lines(objects, slots, values, new, np.ones_like(changed), with_props=True)
        update_text = _lines(objects, slots, values, update, changed, with_props=False)
        parts = []
        for j, tick in enumerate(ticks[sel].tolist()):
            parts.extend(self._events_before(tick))
            objects.written[slots[new[j]]] = True
            body = [new_text[0][new_text[1][j]:new_text[1][j + 1]],
                    update_text[0][update_text[1][j]:update_text[1][j + 1]]]
            leaving = np.concatenate([np.flatnonzero(gone), slots[removed[j]]]) if j == 0 else slots[removed[j]]
            body.extend(f"-{objects.hex[s]}\n".encode() for s in leaving)
            self.stats.removals += leaving.size
            body.extend(self._events_at(tick))
            if any(body) or tick == r.last_tick:
                parts.append(self._frame_header(tick))
                parts.extend(body)
        self.stats.ticks += sel.size
        self.stats.states += int(present.sum())
        self.stats.lines += int(new.sum() + update.sum())
        objects.last[slots] = values[-1]
        objects.alive[gone] = False
        objects.alive[slots] = present[-1]
        return self._emit(parts)

    def _frame_header(self, tick: int) -> bytes:
        self.header_tick = tick
        self.stats.frames += 1
        return f"#{time_text(tick * self.r.dt, self.decimals)}\n".encode()

    def _events_at(self, tick: int) -> list[bytes]:
        """The lines of the pending events of ``tick`` (they go in its frame)."""
        due = [e for e in self.pending_events if e.tick == tick]
        if not due:
            return []
        self.pending_events = [e for e in self.pending_events if e.tick != tick]
        return _event_lines(due, self.objects, self.stats)

    def _events_before(self, tick: float) -> list[bytes]:
        """Frames of the pending events of ticks before ``tick`` (not exported ticks): each
        at its own tick's time, or in the frame last written when that is not earlier (an
        event recorded just after the last tick of a chunk comes with the next chunk)."""
        due = sorted((e for e in self.pending_events if e.tick < tick), key=lambda e: e.tick)
        if not due:
            return []
        self.pending_events = [e for e in self.pending_events if e.tick >= tick]
        out = []
        for e in due:
            lines = _event_lines([e], self.objects, self.stats)
            if lines and (self.header_tick is None or e.tick > self.header_tick):
                out.append(self._frame_header(e.tick))
            out.extend(lines)
        return out

    def finish(self) -> bytes:
        """Events emitted after the last exported tick (they close the file)."""
        parts = self._events_before(float("inf"))
        self.stats.objects = int(self.objects.written.sum())
        return self._emit(parts)


def _lines(objects: _Objects, slots, values, rows, changed, with_props: bool):
    """(bytes, (ticks + 1,) offsets): the lines of the (tick, entity) cells where ``rows``
    is set, tick-major, and where each tick's lines start in the bytes."""
    t_idx, e_idx = np.nonzero(rows)
    offsets = np.zeros(rows.shape[0] + 1, np.int64)
    if t_idx.size == 0:
        return b"", offsets
    data, ends = object_lines(slots[e_idx], values[t_idx, e_idx], changed[t_idx, e_idx], objects.id_table,
                              objects.props_table if with_props else None)
    last_row = np.cumsum(np.bincount(t_idx, minlength=rows.shape[0])) - 1  # of each tick (-1: none yet)
    offsets[1:] = np.where(last_row >= 0, ends[np.maximum(last_row, 0)], 0)
    return data, offsets


def _event_lines(events, objects: _Objects, stats: ExportStats) -> list[bytes]:
    out = []
    for rec in events:
        ev = rec.event
        slot = objects.slot_of.get(int(ev.entity_id))
        object_hex = objects.hex[slot] if slot is not None and objects.written[slot] else None
        line = event_line(ev, object_hex, objects.name(int(ev.entity_id)) if ev.entity_id else "the world")
        if line is not None:
            out.append((line + "\n").encode())
            stats.events += 1
    return out
