from . import events_pb2 as _events_pb2
from . import vpr_pb2 as _vpr_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ReportStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    REPORT_STATUS_UNSPECIFIED: _ClassVar[ReportStatus]
    REPORT_STATUS_HELD: _ClassVar[ReportStatus]
    REPORT_STATUS_AGED_OUT: _ClassVar[ReportStatus]
    REPORT_STATUS_NOT_SEEN: _ClassVar[ReportStatus]
REPORT_STATUS_UNSPECIFIED: ReportStatus
REPORT_STATUS_HELD: ReportStatus
REPORT_STATUS_AGED_OUT: ReportStatus
REPORT_STATUS_NOT_SEEN: ReportStatus

class StepRequest(_message.Message):
    __slots__ = ("step",)
    STEP_FIELD_NUMBER: _ClassVar[int]
    step: int
    def __init__(self, step: _Optional[int] = ...) -> None: ...

class StepReply(_message.Message):
    __slots__ = ("robot_id", "step", "finished", "report", "queued", "late_reports", "pending", "place")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    FINISHED_FIELD_NUMBER: _ClassVar[int]
    REPORT_FIELD_NUMBER: _ClassVar[int]
    QUEUED_FIELD_NUMBER: _ClassVar[int]
    LATE_REPORTS_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    PLACE_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    step: int
    finished: bool
    report: _events_pb2.QueryReport
    queued: bool
    late_reports: _containers.RepeatedCompositeFieldContainer[_events_pb2.QueryReport]
    pending: int
    place: _vpr_pb2.PlaceReport
    def __init__(self, robot_id: _Optional[int] = ..., step: _Optional[int] = ..., finished: _Optional[bool] = ..., report: _Optional[_Union[_events_pb2.QueryReport, _Mapping]] = ..., queued: _Optional[bool] = ..., late_reports: _Optional[_Iterable[_Union[_events_pb2.QueryReport, _Mapping]]] = ..., pending: _Optional[int] = ..., place: _Optional[_Union[_vpr_pb2.PlaceReport, _Mapping]] = ...) -> None: ...

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

class ExplainRequest(_message.Message):
    __slots__ = ("frame_index",)
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    def __init__(self, frame_index: _Optional[int] = ...) -> None: ...

class ExplainReply(_message.Message):
    __slots__ = ("robot_id", "status", "report", "reports_kept", "reports_held", "oldest_frame_index", "newest_frame_index", "loop_closure_min_score", "exclusion", "min_objects", "n_ret", "n_fq")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    REPORT_FIELD_NUMBER: _ClassVar[int]
    REPORTS_KEPT_FIELD_NUMBER: _ClassVar[int]
    REPORTS_HELD_FIELD_NUMBER: _ClassVar[int]
    OLDEST_FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    NEWEST_FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    LOOP_CLOSURE_MIN_SCORE_FIELD_NUMBER: _ClassVar[int]
    EXCLUSION_FIELD_NUMBER: _ClassVar[int]
    MIN_OBJECTS_FIELD_NUMBER: _ClassVar[int]
    N_RET_FIELD_NUMBER: _ClassVar[int]
    N_FQ_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    status: ReportStatus
    report: _events_pb2.QueryReport
    reports_kept: int
    reports_held: int
    oldest_frame_index: int
    newest_frame_index: int
    loop_closure_min_score: float
    exclusion: int
    min_objects: int
    n_ret: int
    n_fq: int
    def __init__(self, robot_id: _Optional[int] = ..., status: _Optional[_Union[ReportStatus, str]] = ..., report: _Optional[_Union[_events_pb2.QueryReport, _Mapping]] = ..., reports_kept: _Optional[int] = ..., reports_held: _Optional[int] = ..., oldest_frame_index: _Optional[int] = ..., newest_frame_index: _Optional[int] = ..., loop_closure_min_score: _Optional[float] = ..., exclusion: _Optional[int] = ..., min_objects: _Optional[int] = ..., n_ret: _Optional[int] = ..., n_fq: _Optional[int] = ...) -> None: ...
