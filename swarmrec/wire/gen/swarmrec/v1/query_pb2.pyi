from . import descriptor_pb2 as _descriptor_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PartialQuery(_message.Message):
    __slots__ = ("query_id", "n_ret", "descriptor", "read_only", "include_scores", "placement_version")
    QUERY_ID_FIELD_NUMBER: _ClassVar[int]
    N_RET_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    READ_ONLY_FIELD_NUMBER: _ClassVar[int]
    INCLUDE_SCORES_FIELD_NUMBER: _ClassVar[int]
    PLACEMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    query_id: int
    n_ret: int
    descriptor: _descriptor_pb2.PartialDescriptor
    read_only: bool
    include_scores: bool
    placement_version: int
    def __init__(self, query_id: _Optional[int] = ..., n_ret: _Optional[int] = ..., descriptor: _Optional[_Union[_descriptor_pb2.PartialDescriptor, _Mapping]] = ..., read_only: _Optional[bool] = ..., include_scores: _Optional[bool] = ..., placement_version: _Optional[int] = ...) -> None: ...

class CandidatesReply(_message.Message):
    __slots__ = ("query_id", "label_lo", "label_hi", "robot_ids", "frame_indices", "scores")
    QUERY_ID_FIELD_NUMBER: _ClassVar[int]
    LABEL_LO_FIELD_NUMBER: _ClassVar[int]
    LABEL_HI_FIELD_NUMBER: _ClassVar[int]
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDICES_FIELD_NUMBER: _ClassVar[int]
    SCORES_FIELD_NUMBER: _ClassVar[int]
    query_id: int
    label_lo: int
    label_hi: int
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    frame_indices: _containers.RepeatedScalarFieldContainer[int]
    scores: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, query_id: _Optional[int] = ..., label_lo: _Optional[int] = ..., label_hi: _Optional[int] = ..., robot_ids: _Optional[_Iterable[int]] = ..., frame_indices: _Optional[_Iterable[int]] = ..., scores: _Optional[_Iterable[float]] = ...) -> None: ...
