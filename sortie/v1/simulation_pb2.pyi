from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Role(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ROLE_UNSPECIFIED: _ClassVar[Role]
    ROLE_PILOT: _ClassVar[Role]
    ROLE_DRIVER: _ClassVar[Role]
    ROLE_OBSERVER: _ClassVar[Role]
    ROLE_BOT: _ClassVar[Role]
    ROLE_GATEWAY: _ClassVar[Role]

class EntityKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ENTITY_KIND_UNSPECIFIED: _ClassVar[EntityKind]
    ENTITY_KIND_AIRCRAFT: _ClassVar[EntityKind]
    ENTITY_KIND_GROUND: _ClassVar[EntityKind]
    ENTITY_KIND_STATIC: _ClassVar[EntityKind]

class DeadReckoningAlgorithm(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DEAD_RECKONING_ALGORITHM_UNSPECIFIED: _ClassVar[DeadReckoningAlgorithm]
    DEAD_RECKONING_ALGORITHM_STATIC: _ClassVar[DeadReckoningAlgorithm]
    DEAD_RECKONING_ALGORITHM_FPW: _ClassVar[DeadReckoningAlgorithm]
    DEAD_RECKONING_ALGORITHM_RPW: _ClassVar[DeadReckoningAlgorithm]
    DEAD_RECKONING_ALGORITHM_RVW: _ClassVar[DeadReckoningAlgorithm]
    DEAD_RECKONING_ALGORITHM_FVW: _ClassVar[DeadReckoningAlgorithm]
ROLE_UNSPECIFIED: Role
ROLE_PILOT: Role
ROLE_DRIVER: Role
ROLE_OBSERVER: Role
ROLE_BOT: Role
ROLE_GATEWAY: Role
ENTITY_KIND_UNSPECIFIED: EntityKind
ENTITY_KIND_AIRCRAFT: EntityKind
ENTITY_KIND_GROUND: EntityKind
ENTITY_KIND_STATIC: EntityKind
DEAD_RECKONING_ALGORITHM_UNSPECIFIED: DeadReckoningAlgorithm
DEAD_RECKONING_ALGORITHM_STATIC: DeadReckoningAlgorithm
DEAD_RECKONING_ALGORITHM_FPW: DeadReckoningAlgorithm
DEAD_RECKONING_ALGORITHM_RPW: DeadReckoningAlgorithm
DEAD_RECKONING_ALGORITHM_RVW: DeadReckoningAlgorithm
DEAD_RECKONING_ALGORITHM_FVW: DeadReckoningAlgorithm

class JoinRequest(_message.Message):
    __slots__ = ("client_name", "role", "agent_name", "observer_lat_deg", "observer_lon_deg", "observer_radius_m")
    CLIENT_NAME_FIELD_NUMBER: _ClassVar[int]
    ROLE_FIELD_NUMBER: _ClassVar[int]
    AGENT_NAME_FIELD_NUMBER: _ClassVar[int]
    OBSERVER_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    OBSERVER_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    OBSERVER_RADIUS_M_FIELD_NUMBER: _ClassVar[int]
    client_name: str
    role: Role
    agent_name: str
    observer_lat_deg: float
    observer_lon_deg: float
    observer_radius_m: float
    def __init__(self, client_name: _Optional[str] = ..., role: _Optional[_Union[Role, str]] = ..., agent_name: _Optional[str] = ..., observer_lat_deg: _Optional[float] = ..., observer_lon_deg: _Optional[float] = ..., observer_radius_m: _Optional[float] = ...) -> None: ...

class JoinResponse(_message.Message):
    __slots__ = ("session_token", "agent_id", "world")
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    WORLD_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    agent_id: int
    world: WorldInfo
    def __init__(self, session_token: _Optional[str] = ..., agent_id: _Optional[int] = ..., world: _Optional[_Union[WorldInfo, _Mapping]] = ...) -> None: ...

class LeaveRequest(_message.Message):
    __slots__ = ("session_token",)
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    def __init__(self, session_token: _Optional[str] = ...) -> None: ...

class LeaveResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class StickControls(_message.Message):
    __slots__ = ("pitch", "roll", "yaw", "throttle", "mixture", "flaps", "brakes", "gear_down")
    PITCH_FIELD_NUMBER: _ClassVar[int]
    ROLL_FIELD_NUMBER: _ClassVar[int]
    YAW_FIELD_NUMBER: _ClassVar[int]
    THROTTLE_FIELD_NUMBER: _ClassVar[int]
    MIXTURE_FIELD_NUMBER: _ClassVar[int]
    FLAPS_FIELD_NUMBER: _ClassVar[int]
    BRAKES_FIELD_NUMBER: _ClassVar[int]
    GEAR_DOWN_FIELD_NUMBER: _ClassVar[int]
    pitch: float
    roll: float
    yaw: float
    throttle: float
    mixture: float
    flaps: float
    brakes: float
    gear_down: bool
    def __init__(self, pitch: _Optional[float] = ..., roll: _Optional[float] = ..., yaw: _Optional[float] = ..., throttle: _Optional[float] = ..., mixture: _Optional[float] = ..., flaps: _Optional[float] = ..., brakes: _Optional[float] = ..., gear_down: _Optional[bool] = ...) -> None: ...

class AutopilotTargets(_message.Message):
    __slots__ = ("heading_deg", "alt_msl_m", "speed_mps")
    HEADING_DEG_FIELD_NUMBER: _ClassVar[int]
    ALT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    SPEED_MPS_FIELD_NUMBER: _ClassVar[int]
    heading_deg: float
    alt_msl_m: float
    speed_mps: float
    def __init__(self, heading_deg: _Optional[float] = ..., alt_msl_m: _Optional[float] = ..., speed_mps: _Optional[float] = ...) -> None: ...

class DriveControls(_message.Message):
    __slots__ = ("speed_mps", "yaw_rate_dps")
    SPEED_MPS_FIELD_NUMBER: _ClassVar[int]
    YAW_RATE_DPS_FIELD_NUMBER: _ClassVar[int]
    speed_mps: float
    yaw_rate_dps: float
    def __init__(self, speed_mps: _Optional[float] = ..., yaw_rate_dps: _Optional[float] = ...) -> None: ...

class ControlInput(_message.Message):
    __slots__ = ("session_token", "agent_id", "stick", "autopilot", "drive")
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    STICK_FIELD_NUMBER: _ClassVar[int]
    AUTOPILOT_FIELD_NUMBER: _ClassVar[int]
    DRIVE_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    agent_id: int
    stick: StickControls
    autopilot: AutopilotTargets
    drive: DriveControls
    def __init__(self, session_token: _Optional[str] = ..., agent_id: _Optional[int] = ..., stick: _Optional[_Union[StickControls, _Mapping]] = ..., autopilot: _Optional[_Union[AutopilotTargets, _Mapping]] = ..., drive: _Optional[_Union[DriveControls, _Mapping]] = ...) -> None: ...

class SendControlsResponse(_message.Message):
    __slots__ = ("accepted",)
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    accepted: int
    def __init__(self, accepted: _Optional[int] = ...) -> None: ...

class WatchRequest(_message.Message):
    __slots__ = ("session_token",)
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    def __init__(self, session_token: _Optional[str] = ...) -> None: ...

class EntityState(_message.Message):
    __slots__ = ("entity_id", "time_s", "ecef_x_m", "ecef_y_m", "ecef_z_m", "velocity_ecef_mps", "acceleration_ecef_mps2", "orientation_wxyz", "angular_velocity_body_rps", "dead_reckoning")
    ENTITY_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    ECEF_X_M_FIELD_NUMBER: _ClassVar[int]
    ECEF_Y_M_FIELD_NUMBER: _ClassVar[int]
    ECEF_Z_M_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_ECEF_MPS_FIELD_NUMBER: _ClassVar[int]
    ACCELERATION_ECEF_MPS2_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_WXYZ_FIELD_NUMBER: _ClassVar[int]
    ANGULAR_VELOCITY_BODY_RPS_FIELD_NUMBER: _ClassVar[int]
    DEAD_RECKONING_FIELD_NUMBER: _ClassVar[int]
    entity_id: int
    time_s: float
    ecef_x_m: float
    ecef_y_m: float
    ecef_z_m: float
    velocity_ecef_mps: _containers.RepeatedScalarFieldContainer[float]
    acceleration_ecef_mps2: _containers.RepeatedScalarFieldContainer[float]
    orientation_wxyz: _containers.RepeatedScalarFieldContainer[float]
    angular_velocity_body_rps: _containers.RepeatedScalarFieldContainer[float]
    dead_reckoning: DeadReckoningAlgorithm
    def __init__(self, entity_id: _Optional[int] = ..., time_s: _Optional[float] = ..., ecef_x_m: _Optional[float] = ..., ecef_y_m: _Optional[float] = ..., ecef_z_m: _Optional[float] = ..., velocity_ecef_mps: _Optional[_Iterable[float]] = ..., acceleration_ecef_mps2: _Optional[_Iterable[float]] = ..., orientation_wxyz: _Optional[_Iterable[float]] = ..., angular_velocity_body_rps: _Optional[_Iterable[float]] = ..., dead_reckoning: _Optional[_Union[DeadReckoningAlgorithm, str]] = ...) -> None: ...

class EntityInfo(_message.Message):
    __slots__ = ("entity_id", "name", "kind", "type", "coalition", "state", "external_id", "destroyed")
    ENTITY_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    COALITION_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_ID_FIELD_NUMBER: _ClassVar[int]
    DESTROYED_FIELD_NUMBER: _ClassVar[int]
    entity_id: int
    name: str
    kind: EntityKind
    type: str
    coalition: str
    state: EntityState
    external_id: str
    destroyed: bool
    def __init__(self, entity_id: _Optional[int] = ..., name: _Optional[str] = ..., kind: _Optional[_Union[EntityKind, str]] = ..., type: _Optional[str] = ..., coalition: _Optional[str] = ..., state: _Optional[_Union[EntityState, _Mapping]] = ..., external_id: _Optional[str] = ..., destroyed: _Optional[bool] = ...) -> None: ...

class WatchUpdate(_message.Message):
    __slots__ = ("time_s", "snapshot", "entered", "left", "states", "time_scale")
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    ENTERED_FIELD_NUMBER: _ClassVar[int]
    LEFT_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    TIME_SCALE_FIELD_NUMBER: _ClassVar[int]
    time_s: float
    snapshot: bool
    entered: _containers.RepeatedCompositeFieldContainer[EntityInfo]
    left: _containers.RepeatedScalarFieldContainer[int]
    states: _containers.RepeatedCompositeFieldContainer[EntityState]
    time_scale: float
    def __init__(self, time_s: _Optional[float] = ..., snapshot: _Optional[bool] = ..., entered: _Optional[_Iterable[_Union[EntityInfo, _Mapping]]] = ..., left: _Optional[_Iterable[int]] = ..., states: _Optional[_Iterable[_Union[EntityState, _Mapping]]] = ..., time_scale: _Optional[float] = ...) -> None: ...

class WatchEventsRequest(_message.Message):
    __slots__ = ("session_token",)
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    def __init__(self, session_token: _Optional[str] = ...) -> None: ...

class WorldEvent(_message.Message):
    __slots__ = ("time_s", "kind", "entity_id", "lat_deg", "lon_deg", "alt_msl_m", "detail_json")
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    ENTITY_ID_FIELD_NUMBER: _ClassVar[int]
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    ALT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    DETAIL_JSON_FIELD_NUMBER: _ClassVar[int]
    time_s: float
    kind: str
    entity_id: int
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    detail_json: str
    def __init__(self, time_s: _Optional[float] = ..., kind: _Optional[str] = ..., entity_id: _Optional[int] = ..., lat_deg: _Optional[float] = ..., lon_deg: _Optional[float] = ..., alt_msl_m: _Optional[float] = ..., detail_json: _Optional[str] = ...) -> None: ...

class GetWorldRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class TargetArea(_message.Message):
    __slots__ = ("name", "lat_deg", "lon_deg", "detail_m")
    NAME_FIELD_NUMBER: _ClassVar[int]
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    DETAIL_M_FIELD_NUMBER: _ClassVar[int]
    name: str
    lat_deg: _containers.RepeatedScalarFieldContainer[float]
    lon_deg: _containers.RepeatedScalarFieldContainer[float]
    detail_m: float
    def __init__(self, name: _Optional[str] = ..., lat_deg: _Optional[_Iterable[float]] = ..., lon_deg: _Optional[_Iterable[float]] = ..., detail_m: _Optional[float] = ...) -> None: ...

class WorldInfo(_message.Message):
    __slots__ = ("exercise_name", "start_time", "time_s", "server_unix_time_s", "clock", "time_scale", "world_rate_hz", "network_rate_hz", "target_areas", "terrain", "geoid_undulation_m", "terrain_insets", "observer_radius_max_m", "entity_count", "centre_lat_deg", "centre_lon_deg")
    EXERCISE_NAME_FIELD_NUMBER: _ClassVar[int]
    START_TIME_FIELD_NUMBER: _ClassVar[int]
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    SERVER_UNIX_TIME_S_FIELD_NUMBER: _ClassVar[int]
    CLOCK_FIELD_NUMBER: _ClassVar[int]
    TIME_SCALE_FIELD_NUMBER: _ClassVar[int]
    WORLD_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    NETWORK_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    TARGET_AREAS_FIELD_NUMBER: _ClassVar[int]
    TERRAIN_FIELD_NUMBER: _ClassVar[int]
    GEOID_UNDULATION_M_FIELD_NUMBER: _ClassVar[int]
    TERRAIN_INSETS_FIELD_NUMBER: _ClassVar[int]
    OBSERVER_RADIUS_MAX_M_FIELD_NUMBER: _ClassVar[int]
    ENTITY_COUNT_FIELD_NUMBER: _ClassVar[int]
    CENTRE_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    CENTRE_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    exercise_name: str
    start_time: str
    time_s: float
    server_unix_time_s: float
    clock: str
    time_scale: float
    world_rate_hz: float
    network_rate_hz: float
    target_areas: _containers.RepeatedCompositeFieldContainer[TargetArea]
    terrain: str
    geoid_undulation_m: float
    terrain_insets: bool
    observer_radius_max_m: float
    entity_count: int
    centre_lat_deg: float
    centre_lon_deg: float
    def __init__(self, exercise_name: _Optional[str] = ..., start_time: _Optional[str] = ..., time_s: _Optional[float] = ..., server_unix_time_s: _Optional[float] = ..., clock: _Optional[str] = ..., time_scale: _Optional[float] = ..., world_rate_hz: _Optional[float] = ..., network_rate_hz: _Optional[float] = ..., target_areas: _Optional[_Iterable[_Union[TargetArea, _Mapping]]] = ..., terrain: _Optional[str] = ..., geoid_undulation_m: _Optional[float] = ..., terrain_insets: _Optional[bool] = ..., observer_radius_max_m: _Optional[float] = ..., entity_count: _Optional[int] = ..., centre_lat_deg: _Optional[float] = ..., centre_lon_deg: _Optional[float] = ...) -> None: ...

class ExternalEntityUpdate(_message.Message):
    __slots__ = ("session_token", "external_id", "name", "kind", "type", "coalition", "state", "remove", "destroyed")
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    COALITION_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    REMOVE_FIELD_NUMBER: _ClassVar[int]
    DESTROYED_FIELD_NUMBER: _ClassVar[int]
    session_token: str
    external_id: str
    name: str
    kind: EntityKind
    type: str
    coalition: str
    state: EntityState
    remove: bool
    destroyed: bool
    def __init__(self, session_token: _Optional[str] = ..., external_id: _Optional[str] = ..., name: _Optional[str] = ..., kind: _Optional[_Union[EntityKind, str]] = ..., type: _Optional[str] = ..., coalition: _Optional[str] = ..., state: _Optional[_Union[EntityState, _Mapping]] = ..., remove: _Optional[bool] = ..., destroyed: _Optional[bool] = ...) -> None: ...

class PublishExternalResponse(_message.Message):
    __slots__ = ("accepted",)
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    accepted: int
    def __init__(self, accepted: _Optional[int] = ...) -> None: ...
