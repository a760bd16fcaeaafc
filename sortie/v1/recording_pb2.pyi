from sortie.v1 import simulation_pb2 as _simulation_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class TerrainFile(_message.Message):
    __slots__ = ("path", "size_bytes", "sha256")
    PATH_FIELD_NUMBER: _ClassVar[int]
    SIZE_BYTES_FIELD_NUMBER: _ClassVar[int]
    SHA256_FIELD_NUMBER: _ClassVar[int]
    path: str
    size_bytes: int
    sha256: str
    def __init__(self, path: _Optional[str] = ..., size_bytes: _Optional[int] = ..., sha256: _Optional[str] = ...) -> None: ...

class TerrainIdentity(_message.Message):
    __slots__ = ("description", "files", "sources_json")
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    FILES_FIELD_NUMBER: _ClassVar[int]
    SOURCES_JSON_FIELD_NUMBER: _ClassVar[int]
    description: str
    files: _containers.RepeatedCompositeFieldContainer[TerrainFile]
    sources_json: str
    def __init__(self, description: _Optional[str] = ..., files: _Optional[_Iterable[_Union[TerrainFile, _Mapping]]] = ..., sources_json: _Optional[str] = ...) -> None: ...

class Quantization(_message.Message):
    __slots__ = ("position_m", "velocity_mps", "acceleration_mps2", "quaternion", "body_rate_rps")
    POSITION_M_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_MPS_FIELD_NUMBER: _ClassVar[int]
    ACCELERATION_MPS2_FIELD_NUMBER: _ClassVar[int]
    QUATERNION_FIELD_NUMBER: _ClassVar[int]
    BODY_RATE_RPS_FIELD_NUMBER: _ClassVar[int]
    position_m: float
    velocity_mps: float
    acceleration_mps2: float
    quaternion: float
    body_rate_rps: float
    def __init__(self, position_m: _Optional[float] = ..., velocity_mps: _Optional[float] = ..., acceleration_mps2: _Optional[float] = ..., quaternion: _Optional[float] = ..., body_rate_rps: _Optional[float] = ...) -> None: ...

class RecordingHeader(_message.Message):
    __slots__ = ("format_version", "sortie_version", "jsbsim_version", "build_id", "exercise_name", "start_time", "world_rate_hz", "fdm_rate_hz", "scenario_toml", "scenario_path", "scenario_sha256", "terrain", "created_unix_s", "quantization", "chunk_s", "geoid_undulation_m", "header_crc32")
    FORMAT_VERSION_FIELD_NUMBER: _ClassVar[int]
    SORTIE_VERSION_FIELD_NUMBER: _ClassVar[int]
    JSBSIM_VERSION_FIELD_NUMBER: _ClassVar[int]
    BUILD_ID_FIELD_NUMBER: _ClassVar[int]
    EXERCISE_NAME_FIELD_NUMBER: _ClassVar[int]
    START_TIME_FIELD_NUMBER: _ClassVar[int]
    WORLD_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    FDM_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    SCENARIO_TOML_FIELD_NUMBER: _ClassVar[int]
    SCENARIO_PATH_FIELD_NUMBER: _ClassVar[int]
    SCENARIO_SHA256_FIELD_NUMBER: _ClassVar[int]
    TERRAIN_FIELD_NUMBER: _ClassVar[int]
    CREATED_UNIX_S_FIELD_NUMBER: _ClassVar[int]
    QUANTIZATION_FIELD_NUMBER: _ClassVar[int]
    CHUNK_S_FIELD_NUMBER: _ClassVar[int]
    GEOID_UNDULATION_M_FIELD_NUMBER: _ClassVar[int]
    HEADER_CRC32_FIELD_NUMBER: _ClassVar[int]
    format_version: int
    sortie_version: str
    jsbsim_version: str
    build_id: str
    exercise_name: str
    start_time: str
    world_rate_hz: float
    fdm_rate_hz: float
    scenario_toml: str
    scenario_path: str
    scenario_sha256: str
    terrain: TerrainIdentity
    created_unix_s: float
    quantization: Quantization
    chunk_s: float
    geoid_undulation_m: float
    header_crc32: int
    def __init__(self, format_version: _Optional[int] = ..., sortie_version: _Optional[str] = ..., jsbsim_version: _Optional[str] = ..., build_id: _Optional[str] = ..., exercise_name: _Optional[str] = ..., start_time: _Optional[str] = ..., world_rate_hz: _Optional[float] = ..., fdm_rate_hz: _Optional[float] = ..., scenario_toml: _Optional[str] = ..., scenario_path: _Optional[str] = ..., scenario_sha256: _Optional[str] = ..., terrain: _Optional[_Union[TerrainIdentity, _Mapping]] = ..., created_unix_s: _Optional[float] = ..., quantization: _Optional[_Union[Quantization, _Mapping]] = ..., chunk_s: _Optional[float] = ..., geoid_undulation_m: _Optional[float] = ..., header_crc32: _Optional[int] = ...) -> None: ...

class InputRecord(_message.Message):
    __slots__ = ("tick", "kind", "entity_id", "command", "values_json", "client", "vanished", "reason")
    TICK_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    ENTITY_ID_FIELD_NUMBER: _ClassVar[int]
    COMMAND_FIELD_NUMBER: _ClassVar[int]
    VALUES_JSON_FIELD_NUMBER: _ClassVar[int]
    CLIENT_FIELD_NUMBER: _ClassVar[int]
    VANISHED_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    tick: int
    kind: str
    entity_id: int
    command: str
    values_json: str
    client: str
    vanished: bool
    reason: str
    def __init__(self, tick: _Optional[int] = ..., kind: _Optional[str] = ..., entity_id: _Optional[int] = ..., command: _Optional[str] = ..., values_json: _Optional[str] = ..., client: _Optional[str] = ..., vanished: _Optional[bool] = ..., reason: _Optional[str] = ...) -> None: ...

class EventRecord(_message.Message):
    __slots__ = ("tick", "event")
    TICK_FIELD_NUMBER: _ClassVar[int]
    EVENT_FIELD_NUMBER: _ClassVar[int]
    tick: int
    event: _simulation_pb2.WorldEvent
    def __init__(self, tick: _Optional[int] = ..., event: _Optional[_Union[_simulation_pb2.WorldEvent, _Mapping]] = ...) -> None: ...

class ChunkHead(_message.Message):
    __slots__ = ("first_tick", "ticks", "first_time_s", "last_time_s", "new_entities", "entity_count", "event_count", "input_count", "recent_entities", "head_crc32")
    FIRST_TICK_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    FIRST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    LAST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    NEW_ENTITIES_FIELD_NUMBER: _ClassVar[int]
    ENTITY_COUNT_FIELD_NUMBER: _ClassVar[int]
    EVENT_COUNT_FIELD_NUMBER: _ClassVar[int]
    INPUT_COUNT_FIELD_NUMBER: _ClassVar[int]
    RECENT_ENTITIES_FIELD_NUMBER: _ClassVar[int]
    HEAD_CRC32_FIELD_NUMBER: _ClassVar[int]
    first_tick: int
    ticks: int
    first_time_s: float
    last_time_s: float
    new_entities: _containers.RepeatedCompositeFieldContainer[_simulation_pb2.EntityInfo]
    entity_count: int
    event_count: int
    input_count: int
    recent_entities: _containers.RepeatedCompositeFieldContainer[_simulation_pb2.EntityInfo]
    head_crc32: int
    def __init__(self, first_tick: _Optional[int] = ..., ticks: _Optional[int] = ..., first_time_s: _Optional[float] = ..., last_time_s: _Optional[float] = ..., new_entities: _Optional[_Iterable[_Union[_simulation_pb2.EntityInfo, _Mapping]]] = ..., entity_count: _Optional[int] = ..., event_count: _Optional[int] = ..., input_count: _Optional[int] = ..., recent_entities: _Optional[_Iterable[_Union[_simulation_pb2.EntityInfo, _Mapping]]] = ..., head_crc32: _Optional[int] = ...) -> None: ...

class ChunkBody(_message.Message):
    __slots__ = ("entity_ids", "present", "states", "digests", "inputs", "events")
    ENTITY_IDS_FIELD_NUMBER: _ClassVar[int]
    PRESENT_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    DIGESTS_FIELD_NUMBER: _ClassVar[int]
    INPUTS_FIELD_NUMBER: _ClassVar[int]
    EVENTS_FIELD_NUMBER: _ClassVar[int]
    entity_ids: _containers.RepeatedScalarFieldContainer[int]
    present: bytes
    states: bytes
    digests: _containers.RepeatedScalarFieldContainer[int]
    inputs: _containers.RepeatedCompositeFieldContainer[InputRecord]
    events: _containers.RepeatedCompositeFieldContainer[EventRecord]
    def __init__(self, entity_ids: _Optional[_Iterable[int]] = ..., present: _Optional[bytes] = ..., states: _Optional[bytes] = ..., digests: _Optional[_Iterable[int]] = ..., inputs: _Optional[_Iterable[_Union[InputRecord, _Mapping]]] = ..., events: _Optional[_Iterable[_Union[EventRecord, _Mapping]]] = ...) -> None: ...

class RecordingIndex(_message.Message):
    __slots__ = ("chunk_first_tick", "chunk_offset", "chunk_time_s", "ticks", "first_time_s", "last_time_s", "entities", "event_count", "input_count")
    CHUNK_FIRST_TICK_FIELD_NUMBER: _ClassVar[int]
    CHUNK_OFFSET_FIELD_NUMBER: _ClassVar[int]
    CHUNK_TIME_S_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    FIRST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    LAST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    ENTITIES_FIELD_NUMBER: _ClassVar[int]
    EVENT_COUNT_FIELD_NUMBER: _ClassVar[int]
    INPUT_COUNT_FIELD_NUMBER: _ClassVar[int]
    chunk_first_tick: _containers.RepeatedScalarFieldContainer[int]
    chunk_offset: _containers.RepeatedScalarFieldContainer[int]
    chunk_time_s: _containers.RepeatedScalarFieldContainer[float]
    ticks: int
    first_time_s: float
    last_time_s: float
    entities: _containers.RepeatedCompositeFieldContainer[_simulation_pb2.EntityInfo]
    event_count: int
    input_count: int
    def __init__(self, chunk_first_tick: _Optional[_Iterable[int]] = ..., chunk_offset: _Optional[_Iterable[int]] = ..., chunk_time_s: _Optional[_Iterable[float]] = ..., ticks: _Optional[int] = ..., first_time_s: _Optional[float] = ..., last_time_s: _Optional[float] = ..., entities: _Optional[_Iterable[_Union[_simulation_pb2.EntityInfo, _Mapping]]] = ..., event_count: _Optional[int] = ..., input_count: _Optional[int] = ...) -> None: ...

class ReplayControl(_message.Message):
    __slots__ = ("play", "pause", "speed", "seek_time_s", "step_ticks")
    PLAY_FIELD_NUMBER: _ClassVar[int]
    PAUSE_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    SEEK_TIME_S_FIELD_NUMBER: _ClassVar[int]
    STEP_TICKS_FIELD_NUMBER: _ClassVar[int]
    play: bool
    pause: bool
    speed: float
    seek_time_s: float
    step_ticks: int
    def __init__(self, play: _Optional[bool] = ..., pause: _Optional[bool] = ..., speed: _Optional[float] = ..., seek_time_s: _Optional[float] = ..., step_ticks: _Optional[int] = ...) -> None: ...

class GetReplayStatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ReplayStatus(_message.Message):
    __slots__ = ("time_s", "tick", "first_time_s", "last_time_s", "playing", "speed", "recording")
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    FIRST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    LAST_TIME_S_FIELD_NUMBER: _ClassVar[int]
    PLAYING_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    time_s: float
    tick: int
    first_time_s: float
    last_time_s: float
    playing: bool
    speed: float
    recording: str
    def __init__(self, time_s: _Optional[float] = ..., tick: _Optional[int] = ..., first_time_s: _Optional[float] = ..., last_time_s: _Optional[float] = ..., playing: _Optional[bool] = ..., speed: _Optional[float] = ..., recording: _Optional[str] = ...) -> None: ...
