"""DIS (IEEE 1278.1) Entity State PDUs: a pure codec and Sortie's conversions (no I/O).

Wire format (IEEE 1278.1-2012 §7.2.2, Entity State PDU; network byte order,
big-endian; offsets in bytes):

====== ==== ============================================================================
offset size field
====== ==== ============================================================================
0      1    protocol version (5: IEEE 1278.1-1995, 6: IEEE 1278.1a-1998, 7: IEEE 1278.1-2012)
1      1    exercise id
2      1    PDU type (1: Entity State)
3      1    protocol family (1: Entity Information/Interaction)
4      4    timestamp (see below)
8      2    length of the whole PDU, bytes
10     1    v7: PDU status; v6: padding
11     1    padding                          -- PDU Header record, §6.2.66, 12 bytes
12     6    entity id: site, application, entity (u16 each)
18     1    force id
19     1    number of variable parameter records
20     8    entity type: kind, domain (u8), country (u16), category, subcategory,
            specific, extra (u8) -- Entity Type record, §6.2.30
28     8    alternative entity type (same layout)
36     12   linear velocity: 3 x float32, m/s
48     24   location: 3 x float64, ECEF (DIS world coordinates) metres
72     12   orientation psi, theta, phi: 3 x float32, rad
84     4    appearance (u32)
88     1    dead reckoning algorithm
89     15   other dead reckoning parameters
104    12   linear acceleration: 3 x float32, m/s^2
116    12   angular velocity: 3 x float32, rad/s, body (entity) axes
128    1    marking character set (1: ASCII)
129    11   marking characters                -- Entity Marking record, §6.2.29
140    4    capabilities (u32)
144    16n  variable parameter records       -- §6.2.94.1 (articulated part: §6.2.94.2)
====== ==== ============================================================================

Versions 5 and 6 lay the PDU out the same way except the PDU status byte, which is
padding there (the 1995 and 1998 headers have two bytes of padding; IEEE
1278.1a-1998 added PDUs, not Entity State fields); all three decode, and
:func:`encode_pdu` writes any (version 7 by default). Version 4 and older
(SISO-REF-010: the DIS 2.0 drafts, IEEE 1278-1993, DIS 1.0) are refused.

Frames. DIS world coordinates are WGS84 ECEF, the entity's axes x forward, y
right, z down (IEEE 1278.1-2012 §1.6.3), as Sortie's. The orientation is the
z-y-x Tait-Bryan angles of the body relative to the ECEF axes: from the ECEF
axes, turn by psi about z, then theta about the new y, then phi about the new
x. The matrix whose columns are the body axes in ECEF is therefore
R = Rz(psi) Ry(theta) Rx(phi), which is exactly the matrix of Sortie's
quaternion (w, x, y, z) "ECEF -> body" (server/dead_reckoning.py: it maps body
components to ECEF ones). :func:`dis_euler_from_quat` reads the angles off
that matrix; :func:`quat_from_dis_euler` composes the three turns.

Timestamp (IEEE 1278.1-2012, Timestamp record): the 31 high bits count units
of 3600 / 2^31 s (about 1.676 us) past the hour; the least significant bit is
1 for an absolute timestamp (synchronised to UTC), 0 for a relative one.

Entity types: a documented table (:data:`ENTITY_TYPES`) of SISO-REF-010
enumerations for the catalog aircraft and vehicles SISO lists; anything else
becomes a generic platform of its domain (:func:`entity_type_of`). Force ids
(SISO-REF-010 "Force ID"): 1 friendly = blue, 2 opposing = red, 3 neutral.

Dead reckoning: Sortie sends algorithms 1-5 (world axes) as they are. An
ingested PDU keeps its algorithm, body axes (6-9) included: the world
dead-reckons it natively (server/external.py); :func:`external_dead_reckoning`
drops only what the algorithm does not use.

Datagrams: :func:`read_datagram` reads the PDUs of one datagram one by one and
keeps every readable one; :func:`split_datagram` is its strict form.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from fdm.state import euler_to_quaternion
from sortie.errors import DataFormatError, InvalidArgument

# -- constants (IEEE 1278.1-2012 and SISO-REF-010) ------------------------------------------------

# SISO-REF-010 "DIS Protocol Version" (UID 3): 5 IEEE 1278.1-1995, 6 IEEE 1278.1a-1998,
# 7 IEEE 1278.1-2012 (the Entity State and Collision PDUs have one layout in all three).
PROTOCOL_VERSION_1995 = 5
PROTOCOL_VERSION_1998 = 6
PROTOCOL_VERSION_2012 = 7
SUPPORTED_VERSIONS = (PROTOCOL_VERSION_1995, PROTOCOL_VERSION_1998, PROTOCOL_VERSION_2012)
VERSION_NAMES = {PROTOCOL_VERSION_1995: "IEEE 1278.1-1995", PROTOCOL_VERSION_1998: "IEEE 1278.1a-1998",
                 PROTOCOL_VERSION_2012: "IEEE 1278.1-2012"}
# SISO-REF-010 "PDU Type" (UID 4) and "Protocol Family" (UID 5).
PDU_TYPE_ENTITY_STATE = 1
FAMILY_ENTITY_INFORMATION = 1
# Record sizes: PDU Header (§6.2.66), the fixed part of the ESPDU (§7.2.2), one Variable
# Parameter record (§6.2.94.1).
HEADER_BYTES = 12
ESPDU_BYTES = 144
VARIABLE_PARAMETER_BYTES = 16
MAX_VARIABLE_PARAMETERS = 255  # the count is a u8
# UDP port 3000: the common DIS port, and the one Wireshark's DIS dissector listens on.
DEFAULT_PORT = 3000

# SISO-REF-010 "Entity Marking Character Set" (UID 45): 1 ASCII; the Entity Marking record
# (§6.2.29) holds 11 characters after the set.
MARKING_ASCII = 1
MARKING_CHARS = 11

# SISO-REF-010 "Force ID" (UID 6).
FORCE_OTHER, FORCE_FRIENDLY, FORCE_OPPOSING, FORCE_NEUTRAL = 0, 1, 2, 3
FORCE_OF_COALITION = {"blue": FORCE_FRIENDLY, "red": FORCE_OPPOSING, "neutral": FORCE_NEUTRAL}
COALITION_OF_FORCE = {v: k for k, v in FORCE_OF_COALITION.items()}

# SISO-REF-010 platform appearance records (land, air, surface, ...): bit 23 "State",
# 0 active, 1 deactivated. A deactivated ESPDU is the entity's last (its removal).
APPEARANCE_DEACTIVATED = 1 << 23
# The same records' bits 3-4, "Damage": 0 no damage, 1 slight, 2 moderate, 3 destroyed -- in
# the platform records of every domain, the munition and cultural feature records; the life
# form record's bits 3-4 are its "Health", 3 fatal (:func:`appearance_destroyed`).
APPEARANCE_DAMAGE_SHIFT = 3
APPEARANCE_DAMAGE_MASK = 3 << APPEARANCE_DAMAGE_SHIFT
APPEARANCE_DESTROYED = 3 << APPEARANCE_DAMAGE_SHIFT

# The Collision PDU (IEEE 1278.1-2012 §7.2.3; SISO-REF-010 PDU Type 4, Entity
# Information/Interaction family): the header, issuing and colliding Entity IDs, the Event
# ID (site, application, event number), the collision type (SISO-REF-010 UID 65:
# 0 inelastic, 1 elastic) and a padding byte, the issuing entity's velocity (world
# coordinates, m/s, 3 x float32), its mass (kg, float32) and the collision's location in
# its own entity coordinates (m, 3 x float32): 60 bytes.
PDU_TYPE_COLLISION = 4
COLLISION_BYTES = 60
COLLISION_INELASTIC, COLLISION_ELASTIC = 0, 1

# SISO-REF-010 "Dead Reckoning Algorithm" (UID 44) = IEEE 1278.1-2012 Annex E numbering.
DR_OTHER, DR_STATIC, DR_FPW, DR_RPW, DR_RVW, DR_FVW, DR_FPB, DR_RPB, DR_RVB, DR_FVB = range(10)
# What each algorithm extrapolates with besides the velocity (Annex E): an acceleration, a
# rotation at the body rates.
DR_ACCELERATING = (DR_RVW, DR_FVW, DR_RVB, DR_FVB)
DR_ROTATING = (DR_RPW, DR_RVW, DR_RPB, DR_RVB)

# IEEE 1278.1-2012 §6.2.28 Entity Identifier record: site and application 0 (NO_SITE,
# NO_APPLIC) and 65535 (ALL_SITES, ALL_APPLIC), entity number 0 (NO_ENTITY) and 65535
# (ALL_ENTITIES) name no one entity (:func:`reserved_entity_id`).
RESERVED_ID_NAMES = (("site", {0: "NO_SITE", 0xFFFF: "ALL_SITES"}),
                     ("application", {0: "NO_APPLIC", 0xFFFF: "ALL_APPLIC"}),
                     ("entity", {0: "NO_ENTITY", 0xFFFF: "ALL_ENTITIES"}))

# SISO-REF-010 "Entity Kind" (UID 7) and platform "Domain" (UID 8).
KIND_PLATFORM, KIND_MUNITION, KIND_LIFE_FORM, KIND_CULTURAL_FEATURE = 1, 2, 3, 5
# The kinds whose appearance record has the damage (health) field in bits 3-4 (see above).
KINDS_WITH_DAMAGE = (KIND_PLATFORM, KIND_MUNITION, KIND_LIFE_FORM, KIND_CULTURAL_FEATURE)
DOMAIN_LAND, DOMAIN_AIR, DOMAIN_SPACE = 1, 2, 5

# Timestamp: 2^31 units per hour (the 31 high bits of the u32).
TIMESTAMP_UNITS_PER_HOUR = 1 << 31
SECONDS_PER_HOUR = 3600.0

# Below this |cos(theta)| the orientation is taken as gimbal-locked (theta = +-90 degrees):
# psi and phi are then one angle; phi is set to 0 (error at most ~1e-7 rad of rotation).
GIMBAL_LOCK_COS = 1e-7

_HEADER = struct.Struct(">BBBBIHBB")
_BODY = struct.Struct(">HHHBB" "BBHBBBB" "BBHBBBB" "3f" "3d" "3f" "I" "B15s" "3f" "3f" "B11s" "I")
_COLLISION = struct.Struct(">HHH" "HHH" "HHH" "BB" "3f" "f" "3f")
_RECORD = struct.Struct(">B15s")
_ARTICULATED = struct.Struct(">BHIf4x")  # the 15 bytes after the record type, §6.2.94.2

# Where each field starts, for error messages.
OFFSETS = {"protocol_version": 0, "exercise_id": 1, "pdu_type": 2, "protocol_family": 3, "timestamp": 4,
           "length": 8, "pdu_status": 10, "entity_id": 12, "force_id": 18, "variable_parameters": 19,
           "entity_type": 20, "alternative_entity_type": 28, "linear_velocity": 36, "location": 48,
           "orientation": 72, "appearance": 84, "dr_algorithm": 88, "dr_parameters": 89,
           "dr_linear_acceleration": 104, "dr_angular_velocity": 116, "marking": 128, "capabilities": 140}


# -- records --------------------------------------------------------------------------------------

class EntityType(NamedTuple):
    """The Entity Type record (§6.2.30): SISO-REF-010 enumerations, written k.d.c.c.s.s.e."""

    kind: int = 0
    domain: int = 0
    country: int = 0
    category: int = 0
    subcategory: int = 0
    specific: int = 0
    extra: int = 0

    def __str__(self) -> str:
        return ".".join(str(v) for v in self)


class ArticulatedPart(NamedTuple):
    """The fields of an Articulated Part variable parameter record (§6.2.94.2).

    parameter_type = type class (a multiple of 32, SISO-REF-010 "Articulated Parts-Type
    Class") + type metric (0-31, "Articulated Parts-Type Metric"); value float32 in the
    metric's unit (e.g. rad for azimuth).
    """

    change_indicator: int
    part_attached_to: int
    parameter_type: int
    value: float

    @property
    def type_class(self) -> int:
        return self.parameter_type & ~0x1F

    @property
    def type_metric(self) -> int:
        return self.parameter_type & 0x1F


@dataclass(frozen=True)
class VariableParameter:
    """One 16-byte Variable Parameter record (§6.2.94.1): its type (SISO-REF-010
    "Variable Parameter Record Type": 0 articulated part, 1 attached part, ...) and the
    15 bytes that follow, kept as sent."""

    record_type: int
    data: bytes

    ARTICULATED_PART = 0
    ATTACHED_PART = 1

    @classmethod
    def articulated_part(cls, part: ArticulatedPart) -> VariableParameter:
        return cls(cls.ARTICULATED_PART, _ARTICULATED.pack(*part))

    @property
    def articulated(self) -> ArticulatedPart | None:
        """The record's fields if it is an articulated part, else None."""
        if self.record_type != self.ARTICULATED_PART:
            return None
        return ArticulatedPart(*_ARTICULATED.unpack(self.data))


@dataclass(frozen=True)
class PduHeader:
    """The PDU Header record (§6.2.66). pdu_status is 0 for version 6 (padding there)."""

    protocol_version: int
    exercise_id: int
    pdu_type: int
    protocol_family: int
    timestamp: int
    length: int
    pdu_status: int = 0


@dataclass(frozen=True)
class OtherPdu:
    """A PDU of a type this codec does not decode: its header and the bytes after it."""

    header: PduHeader
    body: bytes


@dataclass(frozen=True)
class EntityStatePdu:
    """Every field of an Entity State PDU (§7.2.2); units and frames as the table in the
    module docstring. Floats hold the values the wire carries (float32 fields rounded to
    float32), so a decoded PDU encodes to the same bytes and an encoded one decodes equal."""

    exercise_id: int
    entity_id: tuple[int, int, int]  # site, application, entity
    entity_type: EntityType
    location: tuple[float, float, float]  # ECEF m
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)  # psi, theta, phi rad
    linear_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s (frame: dr_algorithm)
    force_id: int = FORCE_OTHER
    alternative_entity_type: EntityType = EntityType()
    appearance: int = 0
    dr_algorithm: int = DR_FPW
    dr_parameters: bytes = bytes(15)
    dr_linear_acceleration: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s^2 (frame: dr_algorithm)
    dr_angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # body axes, rad/s
    marking: bytes = bytes(MARKING_CHARS)  # the 11 characters as sent (marking_text: the text)
    marking_charset: int = MARKING_ASCII
    capabilities: int = 0
    variable_parameters: tuple[VariableParameter, ...] = field(default=())
    timestamp: int = 0
    protocol_version: int = PROTOCOL_VERSION_2012
    pdu_status: int = 0

    @property
    def marking_text(self) -> str:
        """The marking's text (:func:`decode_marking`)."""
        return decode_marking(self.marking)

    @property
    def deactivated(self) -> bool:
        """Whether the appearance says the entity is deactivated (its last PDU)."""
        return bool(self.appearance & APPEARANCE_DEACTIVATED)

    @property
    def destroyed(self) -> bool:
        """Whether the appearance says the entity is destroyed (:func:`appearance_destroyed`)."""
        return appearance_destroyed(self.entity_type.kind, self.appearance)


def appearance_destroyed(kind: int, appearance: int) -> bool:
    """Whether an appearance (u32) of an entity of SISO-REF-010 ``kind`` says it is destroyed:
    its damage (a life form's health) field, bits 3-4, is 3 (destroyed, fatal), for the kinds
    whose appearance record has that field (KINDS_WITH_DAMAGE); never for the others."""
    return kind in KINDS_WITH_DAMAGE and appearance & APPEARANCE_DAMAGE_MASK == APPEARANCE_DESTROYED


def reserved_entity_id(entity_id) -> str | None:
    """Why a DIS Entity ID (site, application, entity) names no one entity (e.g. "site 0 is
    NO_SITE"), None when it names one (RESERVED_ID_NAMES)."""
    for (part, names), value in zip(RESERVED_ID_NAMES, entity_id):
        if value in names:
            return f"{part} {value} is {names[value]}"
    return None


# -- decoding -------------------------------------------------------------------------------------

def _fail(name: str, problem: str, offset: int | None = None) -> DataFormatError:
    at = OFFSETS.get(name) if offset is None else offset
    return DataFormatError(f"DIS {name} at byte {at}: {problem}")


def decode_header(data: bytes) -> PduHeader:
    """The PDU header of ``data`` (one PDU or more); DataFormatError names a bad field."""
    if len(data) < HEADER_BYTES:
        raise _fail("header", f"truncated: {len(data)} bytes, a PDU header has {HEADER_BYTES}", 0)
    version, exercise, pdu_type, family, ts, length, status, _ = _HEADER.unpack_from(data)
    if version not in SUPPORTED_VERSIONS:
        names = ", ".join(f"{v}: {n}" for v, n in VERSION_NAMES.items())
        raise _fail("protocol_version", f"version {version} is not supported ({names})")
    if length < HEADER_BYTES:
        raise _fail("length", f"{length} bytes is shorter than the {HEADER_BYTES}-byte header")
    return PduHeader(version, exercise, pdu_type, family, ts, length,
                     status if version >= PROTOCOL_VERSION_2012 else 0)


def read_datagram(data: bytes) -> tuple[list[bytes], list[DataFormatError]]:
    """(the PDUs, what could not be read) of one UDP datagram, PDU by PDU by their length
    fields (IEEE 1278.1-2012 allows several PDUs in one datagram), so one bad PDU never
    costs the others: a PDU of a version not supported (:func:`decode_header`) is skipped
    by its length field; a length shorter than a header or past the datagram's end, or a
    trailing fragment shorter than a header, ends the reading, with the PDUs before it
    kept. Each problem is a DataFormatError naming the field and its byte in the datagram."""
    pdus, problems, at = [], [], 0
    while at < len(data):
        left = len(data) - at
        if left < HEADER_BYTES:
            problems.append(_fail("header", f"truncated: a trailing fragment of {left} bytes, a PDU header has "
                                            f"{HEADER_BYTES}", at))
            break
        length = int.from_bytes(data[at + 8:at + 10], "big")
        if not HEADER_BYTES <= length <= left:
            problems.append(_fail("length", f"says {length} bytes, the datagram has {left} left (a PDU has at "
                                            f"least the {HEADER_BYTES}-byte header)", at + 8))
            break
        try:
            decode_header(data[at:at + length])
        except DataFormatError as exc:  # its version: the length field still says where the next one starts
            problems.append(exc if at == 0 else DataFormatError(f"{exc} (the PDU at byte {at} of the datagram)"))
        else:
            pdus.append(data[at:at + length])
        at += length
    return pdus, problems


def split_datagram(data: bytes) -> list[bytes]:
    """The PDUs of one UDP datagram (:func:`read_datagram`), all of them: the first problem
    raises its DataFormatError."""
    pdus, problems = read_datagram(data)
    if problems:
        raise problems[0]
    return pdus


def decode_pdu(data: bytes) -> EntityStatePdu | OtherPdu:
    """One PDU (``data`` is exactly its bytes): an :class:`EntityStatePdu` (versions 5 to
    7), or an :class:`OtherPdu` for any other type. DataFormatError names the field and
    its byte offset when the data is truncated or inconsistent."""
    data = bytes(data)
    header = decode_header(data)
    if header.length != len(data):
        raise _fail("length", f"says {header.length} bytes, the data has {len(data)}")
    if header.pdu_type != PDU_TYPE_ENTITY_STATE:
        return OtherPdu(header, data[HEADER_BYTES:])
    if header.protocol_family != FAMILY_ENTITY_INFORMATION:
        raise _fail("protocol_family", f"an Entity State PDU is of family {FAMILY_ENTITY_INFORMATION}, "
                                       f"got {header.protocol_family}")
    if len(data) < ESPDU_BYTES:
        raise _fail("length", f"{len(data)} bytes is shorter than an Entity State PDU ({ESPDU_BYTES})")
    v = _BODY.unpack_from(data, HEADER_BYTES)
    n = v[4]
    if len(data) != ESPDU_BYTES + n * VARIABLE_PARAMETER_BYTES:
        raise _fail("variable_parameters", f"{n} records need {ESPDU_BYTES + n * VARIABLE_PARAMETER_BYTES} "
                                           f"bytes, length says {len(data)}")
    pdu = EntityStatePdu(
        exercise_id=header.exercise_id, entity_id=(v[0], v[1], v[2]), force_id=v[3],
        entity_type=EntityType(*v[5:12]), alternative_entity_type=EntityType(*v[12:19]),
        linear_velocity=v[19:22], location=v[22:25], orientation=v[25:28], appearance=v[28],
        dr_algorithm=v[29], dr_parameters=v[30], dr_linear_acceleration=v[31:34], dr_angular_velocity=v[34:37],
        marking_charset=v[37], marking=v[38], capabilities=v[39],
        variable_parameters=tuple(VariableParameter(*_RECORD.unpack_from(data, ESPDU_BYTES + k * 16))
                                  for k in range(n)),
        timestamp=header.timestamp, protocol_version=header.protocol_version, pdu_status=header.pdu_status)
    for name in ("linear_velocity", "location", "orientation", "dr_linear_acceleration", "dr_angular_velocity"):
        if not all(math.isfinite(x) for x in getattr(pdu, name)):
            raise _fail(name, f"not finite: {getattr(pdu, name)}")
    return pdu


# -- encoding -------------------------------------------------------------------------------------

def _uint(name: str, value, bits: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value < (1 << bits):
        raise InvalidArgument(name, f"must be an integer in [0, {(1 << bits) - 1}]", value=value)
    return int(value)


def _floats(name: str, values, n: int = 3) -> tuple:
    t = tuple(float(x) for x in values)
    if len(t) != n or not all(math.isfinite(x) for x in t):
        raise InvalidArgument(name, f"must be {n} finite numbers", value=values)
    return t


def encode_pdu(pdu: EntityStatePdu) -> bytes:
    """The wire bytes of an Entity State PDU, as protocol version ``pdu.protocol_version``
    (7 unless set to 6). InvalidArgument names a field out of its range."""
    version = pdu.protocol_version
    if version not in SUPPORTED_VERSIONS:
        raise InvalidArgument("protocol_version", f"must be one of {SUPPORTED_VERSIONS}", value=version)
    records = tuple(pdu.variable_parameters)
    if len(records) > MAX_VARIABLE_PARAMETERS:
        raise InvalidArgument("variable_parameters", f"at most {MAX_VARIABLE_PARAMETERS} records", value=len(records))
    length = ESPDU_BYTES + VARIABLE_PARAMETER_BYTES * len(records)
    status = _uint("pdu_status", pdu.pdu_status, 8) if version >= PROTOCOL_VERSION_2012 else 0
    head = _HEADER.pack(version, _uint("exercise_id", pdu.exercise_id, 8), PDU_TYPE_ENTITY_STATE,
                        FAMILY_ENTITY_INFORMATION, _uint("timestamp", pdu.timestamp, 32), length, status, 0)
    if len(pdu.entity_id) != 3:
        raise InvalidArgument("entity_id", "must be (site, application, entity)", value=pdu.entity_id)
    ids = [_uint(f"entity_id.{n}", x, 16) for n, x in zip(("site", "application", "entity"), pdu.entity_id)]
    types = [_entity_type_fields(name, getattr(pdu, name)) for name in ("entity_type", "alternative_entity_type")]
    if len(pdu.dr_parameters) != 15:
        raise InvalidArgument("dr_parameters", "must be 15 bytes", value=len(pdu.dr_parameters))
    body = _BODY.pack(*ids, _uint("force_id", pdu.force_id, 8), len(records), *types[0], *types[1],
                      *_floats("linear_velocity", pdu.linear_velocity), *_floats("location", pdu.location),
                      *_floats("orientation", pdu.orientation), _uint("appearance", pdu.appearance, 32),
                      _uint("dr_algorithm", pdu.dr_algorithm, 8), bytes(pdu.dr_parameters),
                      *_floats("dr_linear_acceleration", pdu.dr_linear_acceleration),
                      *_floats("dr_angular_velocity", pdu.dr_angular_velocity),
                      _uint("marking_charset", pdu.marking_charset, 8), _marking_bytes(pdu.marking),
                      _uint("capabilities", pdu.capabilities, 32))
    return head + body + b"".join(_record_bytes(k, r) for k, r in enumerate(records))


@dataclass(frozen=True)
class CollisionPdu:
    """Every field of a Collision PDU (§7.2.3): issued by ``issuing_entity_id`` about its
    collision with ``colliding_entity_id`` ((0, 0, 0) for terrain or an unknown entity)."""

    exercise_id: int
    issuing_entity_id: tuple[int, int, int]
    colliding_entity_id: tuple[int, int, int]
    event_id: tuple[int, int, int]  # (site, application, event number)
    collision_type: int = COLLISION_INELASTIC
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the issuing entity's, ECEF m/s
    mass_kg: float = 0.0  # the issuing entity's (0: not known)
    location: tuple[float, float, float] = (0.0, 0.0, 0.0)  # entity coordinates, m
    timestamp: int = 0
    protocol_version: int = PROTOCOL_VERSION_2012


def encode_collision_pdu(pdu: CollisionPdu) -> bytes:
    """The wire bytes of a Collision PDU; InvalidArgument names a field out of its range."""
    version = pdu.protocol_version
    if version not in SUPPORTED_VERSIONS:
        raise InvalidArgument("protocol_version", f"must be one of {SUPPORTED_VERSIONS}", value=version)
    head = _HEADER.pack(version, _uint("exercise_id", pdu.exercise_id, 8), PDU_TYPE_COLLISION,
                        FAMILY_ENTITY_INFORMATION, _uint("timestamp", pdu.timestamp, 32), COLLISION_BYTES, 0, 0)
    ids = []
    for name, value, parts in (("issuing_entity_id", pdu.issuing_entity_id, ("site", "application", "entity")),
                               ("colliding_entity_id", pdu.colliding_entity_id, ("site", "application", "entity")),
                               ("event_id", pdu.event_id, ("site", "application", "event_number"))):
        if len(value) != 3:
            raise InvalidArgument(name, f"must be ({', '.join(parts)})", value=value)
        ids += [_uint(f"{name}.{n}", x, 16) for n, x in zip(parts, value)]
    mass = _floats("mass_kg", (pdu.mass_kg,), 1)
    return head + _COLLISION.pack(*ids, _uint("collision_type", pdu.collision_type, 8), 0,
                                  *_floats("velocity", pdu.velocity), *mass, *_floats("location", pdu.location))


def decode_collision_pdu(data: bytes) -> CollisionPdu:
    """A Collision PDU from its bytes; DataFormatError names what does not fit."""
    data = bytes(data)
    header = decode_header(data)
    if header.pdu_type != PDU_TYPE_COLLISION:
        raise _fail("pdu_type", f"{header.pdu_type} is not a Collision PDU ({PDU_TYPE_COLLISION})")
    if header.length != len(data) or len(data) < COLLISION_BYTES:
        raise _fail("length", f"says {header.length} bytes, the data has {len(data)}; a Collision PDU has "
                              f"{COLLISION_BYTES}")
    v = _COLLISION.unpack_from(data, HEADER_BYTES)
    return CollisionPdu(exercise_id=header.exercise_id, issuing_entity_id=v[0:3], colliding_entity_id=v[3:6],
                        event_id=v[6:9], collision_type=v[9], velocity=v[11:14], mass_kg=v[14], location=v[15:18],
                        timestamp=header.timestamp, protocol_version=header.protocol_version)


def _marking_bytes(marking) -> bytes:
    if not isinstance(marking, (bytes, bytearray)) or len(marking) != MARKING_CHARS:
        raise InvalidArgument("marking", f"must be {MARKING_CHARS} bytes (encode_marking makes them from text)",
                              value=marking)
    return bytes(marking)


def _entity_type_fields(name: str, t) -> tuple:
    if len(t) != 7:
        raise InvalidArgument(name, "must have 7 fields (kind, domain, country, category, subcategory, "
                                    "specific, extra)", value=t)
    return tuple(_uint(f"{name}.{f}", x, 16 if f == "country" else 8) for f, x in zip(EntityType._fields, t))


def _record_bytes(k: int, r: VariableParameter) -> bytes:
    if len(r.data) != 15:
        raise InvalidArgument("variable_parameters", "a record's data must be 15 bytes", index=k, value=len(r.data))
    return _RECORD.pack(_uint("variable_parameters.record_type", r.record_type, 8), bytes(r.data))


# -- marking and timestamp ------------------------------------------------------------------------

def encode_marking(text: str) -> bytes:
    """The 11 marking characters (ASCII, §6.2.29) of ``text``: truncated, padded with NULs,
    anything outside printable ASCII replaced by '?'."""
    chars = "".join(c if " " <= c <= "~" else "?" for c in str(text)[:MARKING_CHARS])
    return chars.encode("ascii").ljust(MARKING_CHARS, b"\0")


def decode_marking(raw: bytes) -> str:
    """The text of marking characters: up to the first NUL, non-ASCII bytes as U+FFFD."""
    return bytes(raw).split(b"\0", 1)[0].decode("ascii", errors="replace")


def dis_timestamp(seconds_past_hour: float, absolute: bool) -> int:
    """The u32 timestamp of a time ``seconds_past_hour`` (taken modulo one hour), absolute
    (synchronised to UTC: least significant bit 1) or relative (0)."""
    units = int(math.floor((float(seconds_past_hour) % SECONDS_PER_HOUR) / SECONDS_PER_HOUR
                           * TIMESTAMP_UNITS_PER_HOUR))
    return (min(units, TIMESTAMP_UNITS_PER_HOUR - 1) << 1) | int(bool(absolute))


def timestamp_seconds(timestamp: int) -> tuple[float, bool]:
    """(seconds past the hour, absolute?) of a u32 DIS timestamp."""
    return (timestamp >> 1) * SECONDS_PER_HOUR / TIMESTAMP_UNITS_PER_HOUR, bool(timestamp & 1)


# -- orientation ----------------------------------------------------------------------------------

def _matrix(quat) -> np.ndarray:
    """(..., 3, 3) matrices (body components -> ECEF) of (..., 4) quaternions, normalised inside."""
    q = np.asarray(quat, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    n2 = w * w + x * x + y * y + z * z
    s = 2.0 / n2
    return np.stack([np.stack([1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)], -1),
                     np.stack([s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)], -1),
                     np.stack([s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)], -1)], -2)


def dis_euler_from_quat(quat_wxyz) -> np.ndarray:
    """(..., 3) DIS (psi, theta, phi) rad of (..., 4) quaternions ECEF -> body (w, x, y, z).

    From R = Rz(psi) Ry(theta) Rx(phi) (module docstring): psi = atan2(R10, R00),
    theta = atan2(-R20, hypot(R00, R10)), phi = atan2(R21, R22); atan2 keeps theta
    accurate near +-90 degrees. At gimbal lock (|cos theta| < GIMBAL_LOCK_COS) only
    psi -/+ phi is defined: phi = 0 and psi = atan2(-R01, R11) (R01 = -sin psi,
    R11 = cos psi there). psi, phi in [-pi, pi], theta in [-pi/2, pi/2].
    """
    q = np.asarray(quat_wxyz, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"quat_wxyz must have shape (..., 4), got {q.shape}")
    r = _matrix(q)
    cos_theta = np.hypot(r[..., 0, 0], r[..., 1, 0])
    theta = np.arctan2(-r[..., 2, 0], cos_theta)
    locked = cos_theta < GIMBAL_LOCK_COS
    psi = np.where(locked, np.arctan2(-r[..., 0, 1], r[..., 1, 1]), np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    phi = np.where(locked, 0.0, np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    return np.stack([psi, theta, phi], axis=-1)


def quat_from_dis_euler(euler) -> np.ndarray:
    """(..., 4) unit quaternions ECEF -> body (w, x, y, z), w >= 0, of (..., 3) DIS
    (psi, theta, phi) rad: qz(psi) * qy(theta) * qx(phi), the z-y-x composition
    fdm.state.euler_to_quaternion builds for NED (Stevens & Lewis, 3rd ed., eq. 1.8-17),
    here with the ECEF axes as the reference frame."""
    e = np.asarray(euler, dtype=np.float64)
    if e.shape[-1:] != (3,):
        raise ValueError(f"euler must have shape (..., 3), got {e.shape}")
    return euler_to_quaternion(e[..., 2], e[..., 1], e[..., 0])


# -- dead reckoning -------------------------------------------------------------------------------

def external_dead_reckoning(algorithm: int, velocity, acceleration, omega_body) -> tuple:
    """(algorithm 1-9, velocity (3,), acceleration (3,), body rates (3,)) of a received PDU's
    dead reckoning for the world's extrapolation (server.external.extrapolate_external):
    what the algorithm moves the entity by, and zeros for what it does not use, so the
    world's states show no motion the sender's own receivers do not extrapolate.

    algorithm: the PDU's DIS code; velocity, acceleration (3,) m/s, m/s^2 as sent (ECEF
    for 1-5, body axes for 6-9, IEEE 1278.1-2012 §1.6.3.3 and Annex E); omega_body (3,)
    rad/s, body axes.

    - 1 STATIC: all zeros (a static entity's PDU may carry a velocity: it does not move).
    - 2-9: as sent, in their frames (the world dead-reckons body axes natively); the
      acceleration only for RVW, FVW, RVB, FVB, the body rates only for RPW, RVW, RPB, RVB.
    - 0 (other) and values above 9 (not in SISO-REF-010): FPW on the velocity as sent.
    """
    v = np.asarray(velocity, dtype=np.float64)
    zero = np.zeros(3)
    if algorithm == DR_STATIC:
        return DR_STATIC, zero, zero, zero
    if not DR_FPW <= algorithm <= DR_FVB:
        return DR_FPW, v, zero, zero
    a = np.asarray(acceleration, dtype=np.float64) if algorithm in DR_ACCELERATING else zero
    w = np.asarray(omega_body, dtype=np.float64) if algorithm in DR_ROTATING else zero
    return int(algorithm), v, a, w


# -- entity types (SISO-REF-010) ------------------------------------------------------------------

# (Sortie kind, Sortie type) -> DIS entity type. Values are SISO-REF-010 v29 (2021-05-19)
# entity types, as generated from SISO-REF-010.xml into open-dis/opendis7-java
# (src-generated/edu/nps/moves/dis7/entities/usa/platform/{air,land}/*.java, with the SISO
# uids in the comments). Country 225 = USA; platform domain 1 land, 2 air.
ENTITY_TYPES: dict[tuple[str, str], EntityType] = {
    ("aircraft", "f16"): EntityType(1, 2, 225, 1, 3, 3),  # Fighter/Air Defense, F-16 Fighting Falcon, F-16C (uid 10764)
    ("aircraft", "f15"): EntityType(1, 2, 225, 1, 5, 3),  # Fighter/Air Defense, F-15 Eagle, F-15C (uid 10788)
    ("aircraft", "F4N"): EntityType(1, 2, 225, 1, 4, 10),  # Fighter/Air Defense, F-4 Phantom II, F-4N (uid 10783)
    ("aircraft", "A4"): EntityType(1, 2, 225, 2, 1),  # Attack/Strike, McDonnell-Douglas A-4 Skyhawk (uid 10825)
    ("aircraft", "C130"): EntityType(1, 2, 225, 4, 1, 1),  # Cargo/Tanker, C-130 Hercules, C-130 (uid 10869)
    ("aircraft", "B747"): EntityType(1, 2, 225, 4, 10),  # Cargo/Tanker, Boeing 747 (uid 10928)
    ("aircraft", "737"): EntityType(1, 2, 225, 87, 32, 5),  # Civilian Fixed Wing Large, Twin Jet, B737 (uid 23807)
    # Civilian Fixed Wing Small (<= 5,670 kg), Single Piston Engine, Cessna 172 Skyhawk (uid 23784):
    ("aircraft", "c172p"): EntityType(1, 2, 225, 85, 11, 1),
    ("aircraft", "c172x"): EntityType(1, 2, 225, 85, 11, 1),
    ("aircraft", "c172r"): EntityType(1, 2, 225, 85, 11, 1),
    ("ground", "m1a2"): EntityType(1, 1, 225, 1, 1, 3),  # Tank, M1 Abrams, M1A2 (uid 10022)
    ("ground", "m2a3"): EntityType(1, 1, 225, 2, 1, 9),  # Armored Fighting Vehicle, M2/M3 Bradley, M2A3 (uid 10077)
    ("ground", "hmmwv"): EntityType(1, 1, 225, 6, 1, 1),  # Small Wheeled Utility, HMMWV, M998 (uid 10350)
    # Large Wheeled Utility, Family of Medium Tactical Vehicles (uid 10481); M1083's own
    # specific value was not verified, so the subcategory:
    ("ground", "m1083"): EntityType(1, 1, 225, 7, 12),
    # Statics of the scenarios, as land platforms of their category (country 0 = other):
    ("static", "sam_site"): EntityType(1, 1, 0, 28),  # Air Defense / Missile Defense Unit Equipment
    ("static", "radar"): EntityType(1, 1, 0, 32),  # Surveillance Facility
}
# A DIS type shared by several Sortie types reads back as the first of them (c172p).
SORTIE_OF_ENTITY_TYPE: dict[EntityType, tuple[str, str]] = {}
for _key, _dis in ENTITY_TYPES.items():
    SORTIE_OF_ENTITY_TYPE.setdefault(_dis, _key)

# Types not in the table: a generic platform of the kind's domain, or a cultural feature
# (SISO-REF-010 entity kind 5) for a static.
GENERIC_ENTITY_TYPES = {"aircraft": EntityType(KIND_PLATFORM, DOMAIN_AIR),
                        "ground": EntityType(KIND_PLATFORM, DOMAIN_LAND),
                        "static": EntityType(KIND_CULTURAL_FEATURE, DOMAIN_LAND)}


def entity_type_of(kind: str, type_name: str) -> EntityType:
    """The DIS entity type of a Sortie entity of ``kind`` ("aircraft", "ground", "static")
    and type: :data:`ENTITY_TYPES`, else :data:`GENERIC_ENTITY_TYPES` (an unknown aircraft
    is 1.2.0.0.0.0.0: platform, air, country 0)."""
    if (kind, type_name) in ENTITY_TYPES:
        return ENTITY_TYPES[(kind, type_name)]
    if kind not in GENERIC_ENTITY_TYPES:
        raise InvalidArgument("kind", f"must be one of {', '.join(GENERIC_ENTITY_TYPES)}", value=kind)
    return GENERIC_ENTITY_TYPES[kind]


def sortie_kind_type(entity_type: EntityType) -> tuple[str, str]:
    """(Sortie kind, type) of a DIS entity type: the table's entry, else the kind from the
    domain (air or space: "aircraft"; kind 5 cultural feature: "static"; anything else moves
    on or under the surface: "ground") and the type "dis:k.d.c.c.s.s.e"."""
    entity_type = EntityType(*entity_type)
    if entity_type in SORTIE_OF_ENTITY_TYPE:
        return SORTIE_OF_ENTITY_TYPE[entity_type]
    if entity_type.kind == KIND_CULTURAL_FEATURE:
        kind = "static"
    elif entity_type.domain in (DOMAIN_AIR, DOMAIN_SPACE):
        kind = "aircraft"
    else:
        kind = "ground"
    return kind, f"dis:{entity_type}"


def force_of(coalition: str) -> int:
    """DIS force id of a Sortie coalition (unknown ones: 0, other)."""
    return FORCE_OF_COALITION.get(coalition, FORCE_OTHER)


def coalition_of(force_id: int) -> str:
    """Sortie coalition of a DIS force id (anything but friendly or opposing: neutral)."""
    return COALITION_OF_FORCE.get(force_id, "neutral")


# -- Sortie states <-> PDUs -----------------------------------------------------------------------

def _f32(values) -> tuple:
    return tuple(float(x) for x in np.asarray(values, dtype=np.float64).astype(np.float32))


def entity_state_pdu(*, exercise_id: int, entity_id: tuple[int, int, int], kind: str, type_name: str,
                     coalition: str, name: str, ecef_m, vel_ecef_mps, acc_ecef_mps2, quat_wxyz, body_rates_rps,
                     algorithm: int, timestamp: int, appearance: int = 0) -> EntityStatePdu:
    """The Entity State PDU (version 7) of one Sortie entity state: ECEF position (3,) m,
    velocity (3,) m/s and acceleration (3,) m/s^2 ECEF, quaternion (4,) ECEF -> body, body
    rates (3,) rad/s, a world DR algorithm (1-5). Float32 fields are rounded here, so the
    PDU equals its own decoding."""
    dis_type = entity_type_of(kind, type_name)
    return EntityStatePdu(
        exercise_id=exercise_id, entity_id=tuple(entity_id), entity_type=dis_type, alternative_entity_type=dis_type,
        force_id=force_of(coalition), location=tuple(float(x) for x in ecef_m),
        orientation=_f32(dis_euler_from_quat(quat_wxyz)), linear_velocity=_f32(vel_ecef_mps),
        dr_algorithm=int(algorithm), dr_linear_acceleration=_f32(acc_ecef_mps2),
        dr_angular_velocity=_f32(body_rates_rps), marking=encode_marking(name), appearance=appearance,
        timestamp=timestamp)


def external_id(entity_id) -> str:
    """Sortie's external id of a DIS entity: "dis:<site>.<application>.<entity>"."""
    return "dis:" + ".".join(str(int(x)) for x in entity_id)


def entity_id_of(xid: str) -> tuple[int, int, int] | None:
    """The DIS Entity ID (site, application, entity) of a Sortie external id made by
    :func:`external_id`; None for any other external id."""
    if not xid.startswith("dis:"):
        return None
    try:
        site, app, number = (int(x) for x in xid[4:].split("."))
    except ValueError:
        return None
    return site, app, number


def unique_name(name: str, xid: str, taken) -> str:
    """A world name for the DIS entity ``xid`` ("dis:<site>.<app>.<entity>") whose marking gives
    ``name``, not in ``taken`` (the names of every other entity): DIS markings need not be
    unique (many entities carry the same or none) while the world's names are. The marking
    when free, else the marking and the entity id ("EXT1 900.1.2"), else the external id."""
    for candidate in (name, f"{name} {xid.removeprefix('dis:')}", xid):
        if candidate not in taken:
            return candidate
    n = 2
    while f"{xid}#{n}" in taken:
        n += 1
    return f"{xid}#{n}"


def sortie_state(pdu: EntityStatePdu) -> dict:
    """Keyword arguments of ``ExternalStream.update`` for a received PDU: name (the marking,
    or the external id when it has no printable text), kind, type, coalition and the state
    in Sortie's frames with the PDU's own dead reckoning (:func:`external_dead_reckoning`;
    for a body-axis algorithm "vel_ecef_mps" and "acc_ecef_mps2" are in body axes, as the
    algorithm says)."""
    quat = quat_from_dis_euler(np.array(pdu.orientation))
    algorithm, vel, acc, rates = external_dead_reckoning(pdu.dr_algorithm, pdu.linear_velocity,
                                                         pdu.dr_linear_acceleration, pdu.dr_angular_velocity)
    kind, type_name = sortie_kind_type(pdu.entity_type)
    name = "".join(c if " " <= c <= "~" else "?" for c in pdu.marking_text).strip()
    return {"name": name or external_id(pdu.entity_id), "kind": kind, "type": type_name,
            "coalition": coalition_of(pdu.force_id), "ecef_m": np.array(pdu.location), "vel_ecef_mps": vel,
            "acc_ecef_mps2": acc, "quat_wxyz": quat, "body_rates_rps": rates, "algorithm": algorithm,
            "destroyed": pdu.destroyed}
