from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FunnelReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FUNNEL_REASON_UNSPECIFIED: _ClassVar[FunnelReason]
    FUNNEL_REASON_BELOW_SHARD_CUT: _ClassVar[FunnelReason]
    FUNNEL_REASON_ROBOT_NOT_CHOSEN: _ClassVar[FunnelReason]
    FUNNEL_REASON_VERIFIER_UNREACHABLE: _ClassVar[FunnelReason]
    FUNNEL_REASON_VERIFIER_TIMEOUT: _ClassVar[FunnelReason]
    FUNNEL_REASON_VERIFIER_ERROR: _ClassVar[FunnelReason]
    FUNNEL_REASON_TOO_FEW_MATCHES: _ClassVar[FunnelReason]
    FUNNEL_REASON_MATCHED: _ClassVar[FunnelReason]
    FUNNEL_REASON_BELOW_SCORE_THRESHOLD: _ClassVar[FunnelReason]
    FUNNEL_REASON_OWN_RECENT_FRAME: _ClassVar[FunnelReason]
    FUNNEL_REASON_OUTRANKED: _ClassVar[FunnelReason]
    FUNNEL_REASON_ALREADY_CLOSED: _ClassVar[FunnelReason]
    FUNNEL_REASON_ACCEPTED: _ClassVar[FunnelReason]

class PlacementReason(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PLACEMENT_REASON_UNSPECIFIED: _ClassVar[PlacementReason]
    PLACEMENT_REASON_MEMBERS: _ClassVar[PlacementReason]
    PLACEMENT_REASON_REBALANCE: _ClassVar[PlacementReason]
    PLACEMENT_REASON_HANDOFF_DONE: _ClassVar[PlacementReason]
FUNNEL_REASON_UNSPECIFIED: FunnelReason
FUNNEL_REASON_BELOW_SHARD_CUT: FunnelReason
FUNNEL_REASON_ROBOT_NOT_CHOSEN: FunnelReason
FUNNEL_REASON_VERIFIER_UNREACHABLE: FunnelReason
FUNNEL_REASON_VERIFIER_TIMEOUT: FunnelReason
FUNNEL_REASON_VERIFIER_ERROR: FunnelReason
FUNNEL_REASON_TOO_FEW_MATCHES: FunnelReason
FUNNEL_REASON_MATCHED: FunnelReason
FUNNEL_REASON_BELOW_SCORE_THRESHOLD: FunnelReason
FUNNEL_REASON_OWN_RECENT_FRAME: FunnelReason
FUNNEL_REASON_OUTRANKED: FunnelReason
FUNNEL_REASON_ALREADY_CLOSED: FunnelReason
FUNNEL_REASON_ACCEPTED: FunnelReason
PLACEMENT_REASON_UNSPECIFIED: PlacementReason
PLACEMENT_REASON_MEMBERS: PlacementReason
PLACEMENT_REASON_REBALANCE: PlacementReason
PLACEMENT_REASON_HANDOFF_DONE: PlacementReason

class LoopClosure(_message.Message):
    __slots__ = ("query_robot_id", "query_frame_index", "match_robot_id", "match_frame_index", "score", "semantic_score", "n_matched", "unix_time_ns")
    QUERY_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    QUERY_FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    MATCH_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    MATCH_FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    SEMANTIC_SCORE_FIELD_NUMBER: _ClassVar[int]
    N_MATCHED_FIELD_NUMBER: _ClassVar[int]
    UNIX_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    query_robot_id: int
    query_frame_index: int
    match_robot_id: int
    match_frame_index: int
    score: float
    semantic_score: float
    n_matched: int
    unix_time_ns: int
    def __init__(self, query_robot_id: _Optional[int] = ..., query_frame_index: _Optional[int] = ..., match_robot_id: _Optional[int] = ..., match_frame_index: _Optional[int] = ..., score: _Optional[float] = ..., semantic_score: _Optional[float] = ..., n_matched: _Optional[int] = ..., unix_time_ns: _Optional[int] = ...) -> None: ...

class VerifiedPair(_message.Message):
    __slots__ = ("match_robot_id", "match_frame_index", "score", "semantic_score", "n_matched")
    MATCH_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    MATCH_FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    SEMANTIC_SCORE_FIELD_NUMBER: _ClassVar[int]
    N_MATCHED_FIELD_NUMBER: _ClassVar[int]
    match_robot_id: int
    match_frame_index: int
    score: float
    semantic_score: float
    n_matched: int
    def __init__(self, match_robot_id: _Optional[int] = ..., match_frame_index: _Optional[int] = ..., score: _Optional[float] = ..., semantic_score: _Optional[float] = ..., n_matched: _Optional[int] = ...) -> None: ...

class QueryReport(_message.Message):
    __slots__ = ("robot_id", "frame_index", "queried", "matches", "verified_robot_ids", "failed_shard_robot_ids", "failed_verifier_robot_ids", "n_candidates", "duration_us", "n_objects", "shard_candidates", "candidates")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    QUERIED_FIELD_NUMBER: _ClassVar[int]
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    VERIFIED_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    FAILED_SHARD_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    FAILED_VERIFIER_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    N_CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    DURATION_US_FIELD_NUMBER: _ClassVar[int]
    N_OBJECTS_FIELD_NUMBER: _ClassVar[int]
    SHARD_CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    queried: bool
    matches: _containers.RepeatedCompositeFieldContainer[VerifiedPair]
    verified_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    failed_shard_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    failed_verifier_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    n_candidates: int
    duration_us: int
    n_objects: int
    shard_candidates: _containers.RepeatedCompositeFieldContainer[ShardCandidates]
    candidates: _containers.RepeatedCompositeFieldContainer[CandidateOutcome]
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., queried: _Optional[bool] = ..., matches: _Optional[_Iterable[_Union[VerifiedPair, _Mapping]]] = ..., verified_robot_ids: _Optional[_Iterable[int]] = ..., failed_shard_robot_ids: _Optional[_Iterable[int]] = ..., failed_verifier_robot_ids: _Optional[_Iterable[int]] = ..., n_candidates: _Optional[int] = ..., duration_us: _Optional[int] = ..., n_objects: _Optional[int] = ..., shard_candidates: _Optional[_Iterable[_Union[ShardCandidates, _Mapping]]] = ..., candidates: _Optional[_Iterable[_Union[CandidateOutcome, _Mapping]]] = ...) -> None: ...

class ShardCandidates(_message.Message):
    __slots__ = ("robot_id", "n_candidates", "group")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    N_CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    n_candidates: int
    group: int
    def __init__(self, robot_id: _Optional[int] = ..., n_candidates: _Optional[int] = ..., group: _Optional[int] = ...) -> None: ...

class CandidateOutcome(_message.Message):
    __slots__ = ("robot_id", "frame_index", "reason")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    reason: FunnelReason
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., reason: _Optional[_Union[FunnelReason, str]] = ...) -> None: ...

class GroupChange(_message.Message):
    __slots__ = ("group", "gained", "lost")
    GROUP_FIELD_NUMBER: _ClassVar[int]
    GAINED_FIELD_NUMBER: _ClassVar[int]
    LOST_FIELD_NUMBER: _ClassVar[int]
    group: int
    gained: _containers.RepeatedScalarFieldContainer[int]
    lost: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, group: _Optional[int] = ..., gained: _Optional[_Iterable[int]] = ..., lost: _Optional[_Iterable[int]] = ...) -> None: ...

class PlacementChange(_message.Message):
    __slots__ = ("version", "coordinator", "reason", "changes", "queries", "store_weight", "busiest_before", "busiest_after", "mean_load", "unix_time_ns")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    COORDINATOR_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    CHANGES_FIELD_NUMBER: _ClassVar[int]
    QUERIES_FIELD_NUMBER: _ClassVar[int]
    STORE_WEIGHT_FIELD_NUMBER: _ClassVar[int]
    BUSIEST_BEFORE_FIELD_NUMBER: _ClassVar[int]
    BUSIEST_AFTER_FIELD_NUMBER: _ClassVar[int]
    MEAN_LOAD_FIELD_NUMBER: _ClassVar[int]
    UNIX_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    version: int
    coordinator: int
    reason: PlacementReason
    changes: _containers.RepeatedCompositeFieldContainer[GroupChange]
    queries: int
    store_weight: float
    busiest_before: float
    busiest_after: float
    mean_load: float
    unix_time_ns: int
    def __init__(self, version: _Optional[int] = ..., coordinator: _Optional[int] = ..., reason: _Optional[_Union[PlacementReason, str]] = ..., changes: _Optional[_Iterable[_Union[GroupChange, _Mapping]]] = ..., queries: _Optional[int] = ..., store_weight: _Optional[float] = ..., busiest_before: _Optional[float] = ..., busiest_after: _Optional[float] = ..., mean_load: _Optional[float] = ..., unix_time_ns: _Optional[int] = ...) -> None: ...
