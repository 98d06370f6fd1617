from . import events_pb2 as _events_pb2
from . import vpr_pb2 as _vpr_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class StepRequest(_message.Message):
    __slots__ = ("step",)
    STEP_FIELD_NUMBER: _ClassVar[int]
    step: int
    def __init__(self, step: _Optional[int] = ...) -> None: ...

class StepReply(_message.Message):
    __slots__ = ("robot_id", "step", "finished", "report", "place")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    FINISHED_FIELD_NUMBER: _ClassVar[int]
    REPORT_FIELD_NUMBER: _ClassVar[int]
    PLACE_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    step: int
    finished: bool
    report: _events_pb2.QueryReport
    place: _vpr_pb2.PlaceReport
    def __init__(self, robot_id: _Optional[int] = ..., step: _Optional[int] = ..., finished: _Optional[bool] = ..., report: _Optional[_Union[_events_pb2.QueryReport, _Mapping]] = ..., place: _Optional[_Union[_vpr_pb2.PlaceReport, _Mapping]] = ...) -> None: ...

class ReplayRequest(_message.Message):
    __slots__ = ("rate_hz",)
    RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    rate_hz: float
    def __init__(self, rate_hz: _Optional[float] = ...) -> None: ...

class ReplayReply(_message.Message):
    __slots__ = ("robot_id", "n_frames")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    N_FRAMES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    n_frames: int
    def __init__(self, robot_id: _Optional[int] = ..., n_frames: _Optional[int] = ...) -> None: ...

class StoreReply(_message.Message):
    __slots__ = ("stored_frames",)
    STORED_FRAMES_FIELD_NUMBER: _ClassVar[int]
    stored_frames: int
    def __init__(self, stored_frames: _Optional[int] = ...) -> None: ...

class LoopClosuresRequest(_message.Message):
    __slots__ = ("min_score",)
    MIN_SCORE_FIELD_NUMBER: _ClassVar[int]
    min_score: float
    def __init__(self, min_score: _Optional[float] = ...) -> None: ...

class LoopClosureList(_message.Message):
    __slots__ = ("robot_id", "loop_closures")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    LOOP_CLOSURES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    loop_closures: _containers.RepeatedCompositeFieldContainer[_events_pb2.LoopClosure]
    def __init__(self, robot_id: _Optional[int] = ..., loop_closures: _Optional[_Iterable[_Union[_events_pb2.LoopClosure, _Mapping]]] = ...) -> None: ...
