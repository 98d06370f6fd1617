from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class ClassifierOutput(_message.Message):
    __slots__ = ("origin_robot_id", "round_id", "probabilities", "yaw_rad", "hop_count", "sender_robot_id")
    ORIGIN_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    HOP_COUNT_FIELD_NUMBER: _ClassVar[int]
    SENDER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    origin_robot_id: int
    round_id: int
    probabilities: _containers.RepeatedScalarFieldContainer[float]
    yaw_rad: float
    hop_count: int
    sender_robot_id: int
    def __init__(self, origin_robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., probabilities: _Optional[_Iterable[float]] = ..., yaw_rad: _Optional[float] = ..., hop_count: _Optional[int] = ..., sender_robot_id: _Optional[int] = ...) -> None: ...
