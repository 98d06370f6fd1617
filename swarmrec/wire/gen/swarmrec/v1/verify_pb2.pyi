from . import constellation_pb2 as _constellation_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class VerifyRequest(_message.Message):
    __slots__ = ("query_id", "query", "candidate_frame_indices", "distance_threshold_m", "max_matches", "include_pairs")
    QUERY_ID_FIELD_NUMBER: _ClassVar[int]
    QUERY_FIELD_NUMBER: _ClassVar[int]
    CANDIDATE_FRAME_INDICES_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_THRESHOLD_M_FIELD_NUMBER: _ClassVar[int]
    MAX_MATCHES_FIELD_NUMBER: _ClassVar[int]
    INCLUDE_PAIRS_FIELD_NUMBER: _ClassVar[int]
    query_id: int
    query: _constellation_pb2.Constellation
    candidate_frame_indices: _containers.RepeatedScalarFieldContainer[int]
    distance_threshold_m: float
    max_matches: int
    include_pairs: bool
    def __init__(self, query_id: _Optional[int] = ..., query: _Optional[_Union[_constellation_pb2.Constellation, _Mapping]] = ..., candidate_frame_indices: _Optional[_Iterable[int]] = ..., distance_threshold_m: _Optional[float] = ..., max_matches: _Optional[int] = ..., include_pairs: _Optional[bool] = ...) -> None: ...

class VerifyMatch(_message.Message):
    __slots__ = ("frame_index", "n_matched", "object_pairs", "n_common", "n_union")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    N_MATCHED_FIELD_NUMBER: _ClassVar[int]
    OBJECT_PAIRS_FIELD_NUMBER: _ClassVar[int]
    N_COMMON_FIELD_NUMBER: _ClassVar[int]
    N_UNION_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    n_matched: int
    object_pairs: _containers.RepeatedScalarFieldContainer[int]
    n_common: int
    n_union: int
    def __init__(self, frame_index: _Optional[int] = ..., n_matched: _Optional[int] = ..., object_pairs: _Optional[_Iterable[int]] = ..., n_common: _Optional[int] = ..., n_union: _Optional[int] = ...) -> None: ...

class VerifyReply(_message.Message):
    __slots__ = ("query_id", "robot_id", "matches")
    QUERY_ID_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    query_id: int
    robot_id: int
    matches: _containers.RepeatedCompositeFieldContainer[VerifyMatch]
    def __init__(self, query_id: _Optional[int] = ..., robot_id: _Optional[int] = ..., matches: _Optional[_Iterable[_Union[VerifyMatch, _Mapping]]] = ...) -> None: ...
