from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class HeightEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HEIGHT_ENCODING_UNSPECIFIED: _ClassVar[HeightEncoding]
    HEIGHT_ENCODING_FLOAT32: _ClassVar[HeightEncoding]
    HEIGHT_ENCODING_ZSTD_CM: _ClassVar[HeightEncoding]

class PointStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POINT_STATUS_UNSPECIFIED: _ClassVar[PointStatus]
    POINT_STATUS_OK: _ClassVar[PointStatus]
    POINT_STATUS_FILLED: _ClassVar[PointStatus]
    POINT_STATUS_OUTSIDE: _ClassVar[PointStatus]
HEIGHT_ENCODING_UNSPECIFIED: HeightEncoding
HEIGHT_ENCODING_FLOAT32: HeightEncoding
HEIGHT_ENCODING_ZSTD_CM: HeightEncoding
POINT_STATUS_UNSPECIFIED: PointStatus
POINT_STATUS_OK: PointStatus
POINT_STATUS_FILLED: PointStatus
POINT_STATUS_OUTSIDE: PointStatus

class GetTileRequest(_message.Message):
    __slots__ = ("cell_id", "encoding")
    CELL_ID_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    cell_id: int
    encoding: HeightEncoding
    def __init__(self, cell_id: _Optional[int] = ..., encoding: _Optional[_Union[HeightEncoding, str]] = ...) -> None: ...

class GetRegionRequest(_message.Message):
    __slots__ = ("level", "lat_min_deg", "lon_min_deg", "lat_max_deg", "lon_max_deg", "encoding")
    LEVEL_FIELD_NUMBER: _ClassVar[int]
    LAT_MIN_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_MIN_DEG_FIELD_NUMBER: _ClassVar[int]
    LAT_MAX_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_MAX_DEG_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    level: int
    lat_min_deg: float
    lon_min_deg: float
    lat_max_deg: float
    lon_max_deg: float
    encoding: HeightEncoding
    def __init__(self, level: _Optional[int] = ..., lat_min_deg: _Optional[float] = ..., lon_min_deg: _Optional[float] = ..., lat_max_deg: _Optional[float] = ..., lon_max_deg: _Optional[float] = ..., encoding: _Optional[_Union[HeightEncoding, str]] = ...) -> None: ...

class HeightGrid(_message.Message):
    __slots__ = ("level", "depth", "rows", "cols", "lat_north_deg", "lon_west_deg", "dlat_deg", "dlon_deg", "heights_f32", "post_class", "max_error_m", "cell_id", "heights_zstd")
    LEVEL_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    LAT_NORTH_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_WEST_DEG_FIELD_NUMBER: _ClassVar[int]
    DLAT_DEG_FIELD_NUMBER: _ClassVar[int]
    DLON_DEG_FIELD_NUMBER: _ClassVar[int]
    HEIGHTS_F32_FIELD_NUMBER: _ClassVar[int]
    POST_CLASS_FIELD_NUMBER: _ClassVar[int]
    MAX_ERROR_M_FIELD_NUMBER: _ClassVar[int]
    CELL_ID_FIELD_NUMBER: _ClassVar[int]
    HEIGHTS_ZSTD_FIELD_NUMBER: _ClassVar[int]
    level: int
    depth: int
    rows: int
    cols: int
    lat_north_deg: float
    lon_west_deg: float
    dlat_deg: float
    dlon_deg: float
    heights_f32: bytes
    post_class: bytes
    max_error_m: float
    cell_id: int
    heights_zstd: bytes
    def __init__(self, level: _Optional[int] = ..., depth: _Optional[int] = ..., rows: _Optional[int] = ..., cols: _Optional[int] = ..., lat_north_deg: _Optional[float] = ..., lon_west_deg: _Optional[float] = ..., dlat_deg: _Optional[float] = ..., dlon_deg: _Optional[float] = ..., heights_f32: _Optional[bytes] = ..., post_class: _Optional[bytes] = ..., max_error_m: _Optional[float] = ..., cell_id: _Optional[int] = ..., heights_zstd: _Optional[bytes] = ...) -> None: ...

class GetMetadataRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GetMetadataResponse(_message.Message):
    __slots__ = ("sources", "height_reference", "limits", "server_version", "dem_files")
    SOURCES_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    LIMITS_FIELD_NUMBER: _ClassVar[int]
    SERVER_VERSION_FIELD_NUMBER: _ClassVar[int]
    DEM_FILES_FIELD_NUMBER: _ClassVar[int]
    sources: _containers.RepeatedCompositeFieldContainer[TerrainSource]
    height_reference: str
    limits: Limits
    server_version: str
    dem_files: _containers.RepeatedCompositeFieldContainer[DemFile]
    def __init__(self, sources: _Optional[_Iterable[_Union[TerrainSource, _Mapping]]] = ..., height_reference: _Optional[str] = ..., limits: _Optional[_Union[Limits, _Mapping]] = ..., server_version: _Optional[str] = ..., dem_files: _Optional[_Iterable[_Union[DemFile, _Mapping]]] = ...) -> None: ...

class DemFile(_message.Message):
    __slots__ = ("path", "size_bytes", "sha256")
    PATH_FIELD_NUMBER: _ClassVar[int]
    SIZE_BYTES_FIELD_NUMBER: _ClassVar[int]
    SHA256_FIELD_NUMBER: _ClassVar[int]
    path: str
    size_bytes: int
    sha256: str
    def __init__(self, path: _Optional[str] = ..., size_bytes: _Optional[int] = ..., sha256: _Optional[str] = ...) -> None: ...

class TerrainSource(_message.Message):
    __slots__ = ("name", "kind", "source", "crs", "lat_min_deg", "lon_min_deg", "lat_max_deg", "lon_max_deg", "rows", "cols", "spacing_east_m", "spacing_north_m", "vertical_datum", "filled_posts", "details")
    class DetailsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    CRS_FIELD_NUMBER: _ClassVar[int]
    LAT_MIN_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_MIN_DEG_FIELD_NUMBER: _ClassVar[int]
    LAT_MAX_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_MAX_DEG_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    SPACING_EAST_M_FIELD_NUMBER: _ClassVar[int]
    SPACING_NORTH_M_FIELD_NUMBER: _ClassVar[int]
    VERTICAL_DATUM_FIELD_NUMBER: _ClassVar[int]
    FILLED_POSTS_FIELD_NUMBER: _ClassVar[int]
    DETAILS_FIELD_NUMBER: _ClassVar[int]
    name: str
    kind: str
    source: str
    crs: str
    lat_min_deg: float
    lon_min_deg: float
    lat_max_deg: float
    lon_max_deg: float
    rows: int
    cols: int
    spacing_east_m: float
    spacing_north_m: float
    vertical_datum: str
    filled_posts: int
    details: _containers.ScalarMap[str, str]
    def __init__(self, name: _Optional[str] = ..., kind: _Optional[str] = ..., source: _Optional[str] = ..., crs: _Optional[str] = ..., lat_min_deg: _Optional[float] = ..., lon_min_deg: _Optional[float] = ..., lat_max_deg: _Optional[float] = ..., lon_max_deg: _Optional[float] = ..., rows: _Optional[int] = ..., cols: _Optional[int] = ..., spacing_east_m: _Optional[float] = ..., spacing_north_m: _Optional[float] = ..., vertical_datum: _Optional[str] = ..., filled_posts: _Optional[int] = ..., details: _Optional[_Mapping[str, str]] = ...) -> None: ...

class Limits(_message.Message):
    __slots__ = ("max_height_points", "max_normal_points", "max_profile_samples", "max_line_of_sight_rays", "max_segments", "max_message_bytes", "max_region_posts")
    MAX_HEIGHT_POINTS_FIELD_NUMBER: _ClassVar[int]
    MAX_NORMAL_POINTS_FIELD_NUMBER: _ClassVar[int]
    MAX_PROFILE_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    MAX_LINE_OF_SIGHT_RAYS_FIELD_NUMBER: _ClassVar[int]
    MAX_SEGMENTS_FIELD_NUMBER: _ClassVar[int]
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_REGION_POSTS_FIELD_NUMBER: _ClassVar[int]
    max_height_points: int
    max_normal_points: int
    max_profile_samples: int
    max_line_of_sight_rays: int
    max_segments: int
    max_message_bytes: int
    max_region_posts: int
    def __init__(self, max_height_points: _Optional[int] = ..., max_normal_points: _Optional[int] = ..., max_profile_samples: _Optional[int] = ..., max_line_of_sight_rays: _Optional[int] = ..., max_segments: _Optional[int] = ..., max_message_bytes: _Optional[int] = ..., max_region_posts: _Optional[int] = ...) -> None: ...

class GetHeightsRequest(_message.Message):
    __slots__ = ("lat_deg", "lon_deg")
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    lat_deg: _containers.RepeatedScalarFieldContainer[float]
    lon_deg: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, lat_deg: _Optional[_Iterable[float]] = ..., lon_deg: _Optional[_Iterable[float]] = ...) -> None: ...

class GetHeightsResponse(_message.Message):
    __slots__ = ("height_msl_m", "status")
    HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    status: _containers.RepeatedScalarFieldContainer[PointStatus]
    def __init__(self, height_msl_m: _Optional[_Iterable[float]] = ..., status: _Optional[_Iterable[_Union[PointStatus, str]]] = ...) -> None: ...

class GetNormalsRequest(_message.Message):
    __slots__ = ("lat_deg", "lon_deg")
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    lat_deg: _containers.RepeatedScalarFieldContainer[float]
    lon_deg: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, lat_deg: _Optional[_Iterable[float]] = ..., lon_deg: _Optional[_Iterable[float]] = ...) -> None: ...

class GetNormalsResponse(_message.Message):
    __slots__ = ("normal_east", "normal_north", "normal_up", "slope_deg", "status")
    NORMAL_EAST_FIELD_NUMBER: _ClassVar[int]
    NORMAL_NORTH_FIELD_NUMBER: _ClassVar[int]
    NORMAL_UP_FIELD_NUMBER: _ClassVar[int]
    SLOPE_DEG_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    normal_east: _containers.RepeatedScalarFieldContainer[float]
    normal_north: _containers.RepeatedScalarFieldContainer[float]
    normal_up: _containers.RepeatedScalarFieldContainer[float]
    slope_deg: _containers.RepeatedScalarFieldContainer[float]
    status: _containers.RepeatedScalarFieldContainer[PointStatus]
    def __init__(self, normal_east: _Optional[_Iterable[float]] = ..., normal_north: _Optional[_Iterable[float]] = ..., normal_up: _Optional[_Iterable[float]] = ..., slope_deg: _Optional[_Iterable[float]] = ..., status: _Optional[_Iterable[_Union[PointStatus, str]]] = ...) -> None: ...

class GetProfileRequest(_message.Message):
    __slots__ = ("start_lat_deg", "start_lon_deg", "end_lat_deg", "end_lon_deg", "n_samples")
    START_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    START_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    END_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    END_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    N_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    start_lat_deg: float
    start_lon_deg: float
    end_lat_deg: float
    end_lon_deg: float
    n_samples: int
    def __init__(self, start_lat_deg: _Optional[float] = ..., start_lon_deg: _Optional[float] = ..., end_lat_deg: _Optional[float] = ..., end_lon_deg: _Optional[float] = ..., n_samples: _Optional[int] = ...) -> None: ...

class GetProfileResponse(_message.Message):
    __slots__ = ("lat_deg", "lon_deg", "distance_m", "height_msl_m", "status")
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_M_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    lat_deg: _containers.RepeatedScalarFieldContainer[float]
    lon_deg: _containers.RepeatedScalarFieldContainer[float]
    distance_m: _containers.RepeatedScalarFieldContainer[float]
    height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    status: _containers.RepeatedScalarFieldContainer[PointStatus]
    def __init__(self, lat_deg: _Optional[_Iterable[float]] = ..., lon_deg: _Optional[_Iterable[float]] = ..., distance_m: _Optional[_Iterable[float]] = ..., height_msl_m: _Optional[_Iterable[float]] = ..., status: _Optional[_Iterable[_Union[PointStatus, str]]] = ...) -> None: ...

class LineOfSightRequest(_message.Message):
    __slots__ = ("a_lat_deg", "a_lon_deg", "a_height_msl_m", "b_lat_deg", "b_lon_deg", "b_height_msl_m")
    A_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    A_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    A_HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    B_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    B_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    B_HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    a_lat_deg: _containers.RepeatedScalarFieldContainer[float]
    a_lon_deg: _containers.RepeatedScalarFieldContainer[float]
    a_height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    b_lat_deg: _containers.RepeatedScalarFieldContainer[float]
    b_lon_deg: _containers.RepeatedScalarFieldContainer[float]
    b_height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, a_lat_deg: _Optional[_Iterable[float]] = ..., a_lon_deg: _Optional[_Iterable[float]] = ..., a_height_msl_m: _Optional[_Iterable[float]] = ..., b_lat_deg: _Optional[_Iterable[float]] = ..., b_lon_deg: _Optional[_Iterable[float]] = ..., b_height_msl_m: _Optional[_Iterable[float]] = ...) -> None: ...

class LineOfSightResponse(_message.Message):
    __slots__ = ("visible", "status")
    VISIBLE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    visible: _containers.RepeatedScalarFieldContainer[bool]
    status: _containers.RepeatedScalarFieldContainer[PointStatus]
    def __init__(self, visible: _Optional[_Iterable[bool]] = ..., status: _Optional[_Iterable[_Union[PointStatus, str]]] = ...) -> None: ...

class IntersectSegmentsRequest(_message.Message):
    __slots__ = ("a_lat_deg", "a_lon_deg", "a_height_msl_m", "b_lat_deg", "b_lon_deg", "b_height_msl_m")
    A_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    A_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    A_HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    B_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    B_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    B_HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    a_lat_deg: _containers.RepeatedScalarFieldContainer[float]
    a_lon_deg: _containers.RepeatedScalarFieldContainer[float]
    a_height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    b_lat_deg: _containers.RepeatedScalarFieldContainer[float]
    b_lon_deg: _containers.RepeatedScalarFieldContainer[float]
    b_height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, a_lat_deg: _Optional[_Iterable[float]] = ..., a_lon_deg: _Optional[_Iterable[float]] = ..., a_height_msl_m: _Optional[_Iterable[float]] = ..., b_lat_deg: _Optional[_Iterable[float]] = ..., b_lon_deg: _Optional[_Iterable[float]] = ..., b_height_msl_m: _Optional[_Iterable[float]] = ...) -> None: ...

class IntersectSegmentsResponse(_message.Message):
    __slots__ = ("hit", "distance_m", "lat_deg", "lon_deg", "height_msl_m", "normal_east", "normal_north", "normal_up", "status")
    HIT_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_M_FIELD_NUMBER: _ClassVar[int]
    LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    LON_DEG_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_MSL_M_FIELD_NUMBER: _ClassVar[int]
    NORMAL_EAST_FIELD_NUMBER: _ClassVar[int]
    NORMAL_NORTH_FIELD_NUMBER: _ClassVar[int]
    NORMAL_UP_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    hit: _containers.RepeatedScalarFieldContainer[bool]
    distance_m: _containers.RepeatedScalarFieldContainer[float]
    lat_deg: _containers.RepeatedScalarFieldContainer[float]
    lon_deg: _containers.RepeatedScalarFieldContainer[float]
    height_msl_m: _containers.RepeatedScalarFieldContainer[float]
    normal_east: _containers.RepeatedScalarFieldContainer[float]
    normal_north: _containers.RepeatedScalarFieldContainer[float]
    normal_up: _containers.RepeatedScalarFieldContainer[float]
    status: _containers.RepeatedScalarFieldContainer[PointStatus]
    def __init__(self, hit: _Optional[_Iterable[bool]] = ..., distance_m: _Optional[_Iterable[float]] = ..., lat_deg: _Optional[_Iterable[float]] = ..., lon_deg: _Optional[_Iterable[float]] = ..., height_msl_m: _Optional[_Iterable[float]] = ..., normal_east: _Optional[_Iterable[float]] = ..., normal_north: _Optional[_Iterable[float]] = ..., normal_up: _Optional[_Iterable[float]] = ..., status: _Optional[_Iterable[_Union[PointStatus, str]]] = ...) -> None: ...
