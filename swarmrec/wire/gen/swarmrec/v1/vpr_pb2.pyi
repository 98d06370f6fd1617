from . import constellation_pb2 as _constellation_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DescriptorEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DESCRIPTOR_ENCODING_UNSPECIFIED: _ClassVar[DescriptorEncoding]
    DESCRIPTOR_ENCODING_FLOAT32: _ClassVar[DescriptorEncoding]
    DESCRIPTOR_ENCODING_INT8: _ClassVar[DescriptorEncoding]
DESCRIPTOR_ENCODING_UNSPECIFIED: DescriptorEncoding
DESCRIPTOR_ENCODING_FLOAT32: DescriptorEncoding
DESCRIPTOR_ENCODING_INT8: DescriptorEncoding

class PlaceFrame(_message.Message):
    __slots__ = ("robot_id", "frame_index", "frame_id", "descriptor", "encoding", "constellation")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    CONSTELLATION_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    frame_id: str
    descriptor: bytes
    encoding: DescriptorEncoding
    constellation: _constellation_pb2.Constellation
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., frame_id: _Optional[str] = ..., descriptor: _Optional[bytes] = ..., encoding: _Optional[_Union[DescriptorEncoding, str]] = ..., constellation: _Optional[_Union[_constellation_pb2.Constellation, _Mapping]] = ...) -> None: ...

class PlaceQuery(_message.Message):
    __slots__ = ("robot_id", "frame_index", "descriptor", "encoding", "cluster", "assignment_version")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    CLUSTER_FIELD_NUMBER: _ClassVar[int]
    ASSIGNMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    descriptor: bytes
    encoding: DescriptorEncoding
    cluster: int
    assignment_version: int
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., descriptor: _Optional[bytes] = ..., encoding: _Optional[_Union[DescriptorEncoding, str]] = ..., cluster: _Optional[int] = ..., assignment_version: _Optional[int] = ...) -> None: ...

class PlaceMatch(_message.Message):
    __slots__ = ("found", "distance", "robot_id", "frame_index")
    FOUND_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    found: bool
    distance: float
    robot_id: int
    frame_index: int
    def __init__(self, found: _Optional[bool] = ..., distance: _Optional[float] = ..., robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ...) -> None: ...

class PlaceReport(_message.Message):
    __slots__ = ("robot_id", "frame_index", "cluster", "owner_robot_id", "answered", "match", "verified", "score", "semantic_score", "n_matched", "loop_closure", "n_objects", "duration_us", "failure")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    CLUSTER_FIELD_NUMBER: _ClassVar[int]
    OWNER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ANSWERED_FIELD_NUMBER: _ClassVar[int]
    MATCH_FIELD_NUMBER: _ClassVar[int]
    VERIFIED_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    SEMANTIC_SCORE_FIELD_NUMBER: _ClassVar[int]
    N_MATCHED_FIELD_NUMBER: _ClassVar[int]
    LOOP_CLOSURE_FIELD_NUMBER: _ClassVar[int]
    N_OBJECTS_FIELD_NUMBER: _ClassVar[int]
    DURATION_US_FIELD_NUMBER: _ClassVar[int]
    FAILURE_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    cluster: int
    owner_robot_id: int
    answered: bool
    match: PlaceMatch
    verified: bool
    score: float
    semantic_score: float
    n_matched: int
    loop_closure: bool
    n_objects: int
    duration_us: int
    failure: str
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., cluster: _Optional[int] = ..., owner_robot_id: _Optional[int] = ..., answered: _Optional[bool] = ..., match: _Optional[_Union[PlaceMatch, _Mapping]] = ..., verified: _Optional[bool] = ..., score: _Optional[float] = ..., semantic_score: _Optional[float] = ..., n_matched: _Optional[int] = ..., loop_closure: _Optional[bool] = ..., n_objects: _Optional[int] = ..., duration_us: _Optional[int] = ..., failure: _Optional[str] = ...) -> None: ...

class AssignmentRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class AssignmentReply(_message.Message):
    __slots__ = ("robot_id", "version", "table_json", "owned_clusters", "centres_sha256", "dimension", "wire_encoding")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    TABLE_JSON_FIELD_NUMBER: _ClassVar[int]
    OWNED_CLUSTERS_FIELD_NUMBER: _ClassVar[int]
    CENTRES_SHA256_FIELD_NUMBER: _ClassVar[int]
    DIMENSION_FIELD_NUMBER: _ClassVar[int]
    WIRE_ENCODING_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    version: int
    table_json: str
    owned_clusters: _containers.RepeatedScalarFieldContainer[int]
    centres_sha256: str
    dimension: int
    wire_encoding: DescriptorEncoding
    def __init__(self, robot_id: _Optional[int] = ..., version: _Optional[int] = ..., table_json: _Optional[str] = ..., owned_clusters: _Optional[_Iterable[int]] = ..., centres_sha256: _Optional[str] = ..., dimension: _Optional[int] = ..., wire_encoding: _Optional[_Union[DescriptorEncoding, str]] = ...) -> None: ...

class PlaceEntry(_message.Message):
    __slots__ = ("robot_id", "frame_index", "descriptor", "encoding", "removed")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    descriptor: bytes
    encoding: DescriptorEncoding
    removed: bool
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., descriptor: _Optional[bytes] = ..., encoding: _Optional[_Union[DescriptorEncoding, str]] = ..., removed: _Optional[bool] = ...) -> None: ...

class ClusterTable(_message.Message):
    __slots__ = ("version", "dimension", "centres", "owners", "copy_margin", "copy_neighbours")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    DIMENSION_FIELD_NUMBER: _ClassVar[int]
    CENTRES_FIELD_NUMBER: _ClassVar[int]
    OWNERS_FIELD_NUMBER: _ClassVar[int]
    COPY_MARGIN_FIELD_NUMBER: _ClassVar[int]
    COPY_NEIGHBOURS_FIELD_NUMBER: _ClassVar[int]
    version: int
    dimension: int
    centres: bytes
    owners: _containers.RepeatedScalarFieldContainer[int]
    copy_margin: float
    copy_neighbours: int
    def __init__(self, version: _Optional[int] = ..., dimension: _Optional[int] = ..., centres: _Optional[bytes] = ..., owners: _Optional[_Iterable[int]] = ..., copy_margin: _Optional[float] = ..., copy_neighbours: _Optional[int] = ...) -> None: ...

class TableRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ClusterLoadRequest(_message.Message):
    __slots__ = ("version", "split_above", "seed", "counts_only")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SPLIT_ABOVE_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    COUNTS_ONLY_FIELD_NUMBER: _ClassVar[int]
    version: int
    split_above: float
    seed: int
    counts_only: bool
    def __init__(self, version: _Optional[int] = ..., split_above: _Optional[float] = ..., seed: _Optional[int] = ..., counts_only: _Optional[bool] = ...) -> None: ...

class ClusterLoad(_message.Message):
    __slots__ = ("robot_id", "version", "loads", "replaced", "replaced_centres", "new_centres", "pair_a", "pair_b", "pair_count", "gaps", "queries")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    LOADS_FIELD_NUMBER: _ClassVar[int]
    REPLACED_FIELD_NUMBER: _ClassVar[int]
    REPLACED_CENTRES_FIELD_NUMBER: _ClassVar[int]
    NEW_CENTRES_FIELD_NUMBER: _ClassVar[int]
    PAIR_A_FIELD_NUMBER: _ClassVar[int]
    PAIR_B_FIELD_NUMBER: _ClassVar[int]
    PAIR_COUNT_FIELD_NUMBER: _ClassVar[int]
    GAPS_FIELD_NUMBER: _ClassVar[int]
    QUERIES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    version: int
    loads: _containers.RepeatedScalarFieldContainer[int]
    replaced: _containers.RepeatedScalarFieldContainer[int]
    replaced_centres: bytes
    new_centres: bytes
    pair_a: _containers.RepeatedScalarFieldContainer[int]
    pair_b: _containers.RepeatedScalarFieldContainer[int]
    pair_count: _containers.RepeatedScalarFieldContainer[int]
    gaps: _containers.RepeatedScalarFieldContainer[float]
    queries: int
    def __init__(self, robot_id: _Optional[int] = ..., version: _Optional[int] = ..., loads: _Optional[_Iterable[int]] = ..., replaced: _Optional[_Iterable[int]] = ..., replaced_centres: _Optional[bytes] = ..., new_centres: _Optional[bytes] = ..., pair_a: _Optional[_Iterable[int]] = ..., pair_b: _Optional[_Iterable[int]] = ..., pair_count: _Optional[_Iterable[int]] = ..., gaps: _Optional[_Iterable[float]] = ..., queries: _Optional[int] = ...) -> None: ...

class RebalanceRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class RebalanceReply(_message.Message):
    __slots__ = ("changed", "table", "observed_queries", "moved", "pending")
    CHANGED_FIELD_NUMBER: _ClassVar[int]
    TABLE_FIELD_NUMBER: _ClassVar[int]
    OBSERVED_QUERIES_FIELD_NUMBER: _ClassVar[int]
    MOVED_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    changed: bool
    table: ClusterTable
    observed_queries: int
    moved: int
    pending: int
    def __init__(self, changed: _Optional[bool] = ..., table: _Optional[_Union[ClusterTable, _Mapping]] = ..., observed_queries: _Optional[int] = ..., moved: _Optional[int] = ..., pending: _Optional[int] = ...) -> None: ...

class AdoptTableRequest(_message.Message):
    __slots__ = ("table", "base_version", "replaced", "replaced_centres", "appended_centres", "hold_moves", "centres_encoding")
    TABLE_FIELD_NUMBER: _ClassVar[int]
    BASE_VERSION_FIELD_NUMBER: _ClassVar[int]
    REPLACED_FIELD_NUMBER: _ClassVar[int]
    REPLACED_CENTRES_FIELD_NUMBER: _ClassVar[int]
    APPENDED_CENTRES_FIELD_NUMBER: _ClassVar[int]
    HOLD_MOVES_FIELD_NUMBER: _ClassVar[int]
    CENTRES_ENCODING_FIELD_NUMBER: _ClassVar[int]
    table: ClusterTable
    base_version: int
    replaced: _containers.RepeatedScalarFieldContainer[int]
    replaced_centres: bytes
    appended_centres: bytes
    hold_moves: bool
    centres_encoding: DescriptorEncoding
    def __init__(self, table: _Optional[_Union[ClusterTable, _Mapping]] = ..., base_version: _Optional[int] = ..., replaced: _Optional[_Iterable[int]] = ..., replaced_centres: _Optional[bytes] = ..., appended_centres: _Optional[bytes] = ..., hold_moves: _Optional[bool] = ..., centres_encoding: _Optional[_Union[DescriptorEncoding, str]] = ...) -> None: ...

class AdoptTableReply(_message.Message):
    __slots__ = ("robot_id", "version", "sent", "removed", "pending")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SENT_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    version: int
    sent: int
    removed: int
    pending: int
    def __init__(self, robot_id: _Optional[int] = ..., version: _Optional[int] = ..., sent: _Optional[int] = ..., removed: _Optional[int] = ..., pending: _Optional[int] = ...) -> None: ...

class StoreEntriesRequest(_message.Message):
    __slots__ = ("version", "entries")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    ENTRIES_FIELD_NUMBER: _ClassVar[int]
    version: int
    entries: _containers.RepeatedCompositeFieldContainer[PlaceEntry]
    def __init__(self, version: _Optional[int] = ..., entries: _Optional[_Iterable[_Union[PlaceEntry, _Mapping]]] = ...) -> None: ...

class StoreEntriesReply(_message.Message):
    __slots__ = ("stored",)
    STORED_FIELD_NUMBER: _ClassVar[int]
    stored: int
    def __init__(self, stored: _Optional[int] = ...) -> None: ...
