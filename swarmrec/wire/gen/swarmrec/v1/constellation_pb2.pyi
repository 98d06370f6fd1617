from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class Constellation(_message.Message):
    __slots__ = ("robot_id", "frame_index", "labels", "positions_mm", "frame_id", "positions_m")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    LABELS_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_MM_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSITIONS_M_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    labels: _containers.RepeatedScalarFieldContainer[int]
    positions_mm: _containers.RepeatedScalarFieldContainer[int]
    frame_id: str
    positions_m: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ..., labels: _Optional[_Iterable[int]] = ..., positions_mm: _Optional[_Iterable[int]] = ..., frame_id: _Optional[str] = ..., positions_m: _Optional[_Iterable[float]] = ...) -> None: ...
