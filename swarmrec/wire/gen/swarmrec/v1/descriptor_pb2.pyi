from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class SemanticDescriptor(_message.Message):
    __slots__ = ("n_labels", "labels", "counts")
    N_LABELS_FIELD_NUMBER: _ClassVar[int]
    LABELS_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    n_labels: int
    labels: _containers.RepeatedScalarFieldContainer[int]
    counts: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, n_labels: _Optional[int] = ..., labels: _Optional[_Iterable[int]] = ..., counts: _Optional[_Iterable[int]] = ...) -> None: ...

class PartialDescriptor(_message.Message):
    __slots__ = ("robot_id", "frame_index", "query_step", "label_lo", "label_hi", "label_offsets", "counts")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    QUERY_STEP_FIELD_NUMBER: _ClassVar[int]
    LABEL_LO_FIELD_NUMBER: _ClassVar[int]
    LABEL_HI_FIELD_NUMBER: _ClassVar[int]
    LABEL_OFFSETS_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    query_step: int
    label_lo: int
    label_hi: int
    label_offsets: _containers.RepeatedScalarFieldContainer[int]
    counts: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., query_step: _Optional[int] = ..., label_lo: _Optional[int] = ..., label_hi: _Optional[int] = ..., label_offsets: _Optional[_Iterable[int]] = ..., counts: _Optional[_Iterable[int]] = ...) -> None: ...
