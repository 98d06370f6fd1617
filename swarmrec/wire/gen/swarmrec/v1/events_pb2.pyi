from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

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
