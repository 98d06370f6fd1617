from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ClassifierOutput(_message.Message):
    __slots__ = ("origin_robot_id", "round_id", "probabilities", "yaw_rad", "hop_count", "sender_robot_id", "origin_signature")
    ORIGIN_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    HOP_COUNT_FIELD_NUMBER: _ClassVar[int]
    SENDER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_SIGNATURE_FIELD_NUMBER: _ClassVar[int]
    origin_robot_id: int
    round_id: int
    probabilities: _containers.RepeatedScalarFieldContainer[float]
    yaw_rad: float
    hop_count: int
    sender_robot_id: int
    origin_signature: bytes
    def __init__(self, origin_robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., probabilities: _Optional[_Iterable[float]] = ..., yaw_rad: _Optional[float] = ..., hop_count: _Optional[int] = ..., sender_robot_id: _Optional[int] = ..., origin_signature: _Optional[bytes] = ...) -> None: ...

class FusionRoundStart(_message.Message):
    __slots__ = ("round_id", "probabilities", "yaw_rad", "neighbour_robot_ids", "weight_law")
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    NEIGHBOUR_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    WEIGHT_LAW_FIELD_NUMBER: _ClassVar[int]
    round_id: int
    probabilities: _containers.RepeatedScalarFieldContainer[float]
    yaw_rad: float
    neighbour_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    weight_law: WeightLaw
    def __init__(self, round_id: _Optional[int] = ..., probabilities: _Optional[_Iterable[float]] = ..., yaw_rad: _Optional[float] = ..., neighbour_robot_ids: _Optional[_Iterable[int]] = ..., weight_law: _Optional[_Union[WeightLaw, _Mapping]] = ...) -> None: ...

class WeightLaw(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    LAMBDA_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ..., **kwargs) -> None: ...

class FusionRoundStarted(_message.Message):
    __slots__ = ("robot_id", "round_id", "sent", "early_messages")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    SENT_FIELD_NUMBER: _ClassVar[int]
    EARLY_MESSAGES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    round_id: int
    sent: int
    early_messages: int
    def __init__(self, robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., sent: _Optional[int] = ..., early_messages: _Optional[int] = ...) -> None: ...

class PosteriorRequest(_message.Message):
    __slots__ = ("round_id",)
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    round_id: int
    def __init__(self, round_id: _Optional[int] = ...) -> None: ...

class FusionStep(_message.Message):
    __slots__ = ("origin_robot_id", "sender_robot_id", "hops", "yaw_rad", "weight", "decision_after")
    ORIGIN_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SENDER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    HOPS_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    WEIGHT_FIELD_NUMBER: _ClassVar[int]
    DECISION_AFTER_FIELD_NUMBER: _ClassVar[int]
    origin_robot_id: int
    sender_robot_id: int
    hops: int
    yaw_rad: float
    weight: float
    decision_after: int
    def __init__(self, origin_robot_id: _Optional[int] = ..., sender_robot_id: _Optional[int] = ..., hops: _Optional[int] = ..., yaw_rad: _Optional[float] = ..., weight: _Optional[float] = ..., decision_after: _Optional[int] = ...) -> None: ...

class FusionPosterior(_message.Message):
    __slots__ = ("robot_id", "round_id", "posterior", "decision", "incorporated", "duplicates", "rejected", "heard_all", "history", "neighbour_robot_ids")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    POSTERIOR_FIELD_NUMBER: _ClassVar[int]
    DECISION_FIELD_NUMBER: _ClassVar[int]
    INCORPORATED_FIELD_NUMBER: _ClassVar[int]
    DUPLICATES_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    HEARD_ALL_FIELD_NUMBER: _ClassVar[int]
    HISTORY_FIELD_NUMBER: _ClassVar[int]
    NEIGHBOUR_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    round_id: int
    posterior: _containers.RepeatedScalarFieldContainer[float]
    decision: int
    incorporated: int
    duplicates: int
    rejected: int
    heard_all: bool
    history: _containers.RepeatedCompositeFieldContainer[FusionStep]
    neighbour_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., posterior: _Optional[_Iterable[float]] = ..., decision: _Optional[int] = ..., incorporated: _Optional[int] = ..., duplicates: _Optional[int] = ..., rejected: _Optional[int] = ..., heard_all: _Optional[bool] = ..., history: _Optional[_Iterable[_Union[FusionStep, _Mapping]]] = ..., neighbour_robot_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class FusionUpdate(_message.Message):
    __slots__ = ("robot_id", "round_id", "step", "posterior", "decision", "incorporated", "heard_all")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    POSTERIOR_FIELD_NUMBER: _ClassVar[int]
    DECISION_FIELD_NUMBER: _ClassVar[int]
    INCORPORATED_FIELD_NUMBER: _ClassVar[int]
    HEARD_ALL_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    round_id: int
    step: FusionStep
    posterior: _containers.RepeatedScalarFieldContainer[float]
    decision: int
    incorporated: int
    heard_all: bool
    def __init__(self, robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., step: _Optional[_Union[FusionStep, _Mapping]] = ..., posterior: _Optional[_Iterable[float]] = ..., decision: _Optional[int] = ..., incorporated: _Optional[int] = ..., heard_all: _Optional[bool] = ...) -> None: ...

class ClassifyRequest(_message.Message):
    __slots__ = ("round_id", "image", "yaw_rad", "neighbour_robot_ids", "weight_law")
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    NEIGHBOUR_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    WEIGHT_LAW_FIELD_NUMBER: _ClassVar[int]
    round_id: int
    image: bytes
    yaw_rad: float
    neighbour_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    weight_law: WeightLaw
    def __init__(self, round_id: _Optional[int] = ..., image: _Optional[bytes] = ..., yaw_rad: _Optional[float] = ..., neighbour_robot_ids: _Optional[_Iterable[int]] = ..., weight_law: _Optional[_Union[WeightLaw, _Mapping]] = ...) -> None: ...

class ClassifyReply(_message.Message):
    __slots__ = ("robot_id", "round_id", "probabilities", "decision", "fusion")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    PROBABILITIES_FIELD_NUMBER: _ClassVar[int]
    DECISION_FIELD_NUMBER: _ClassVar[int]
    FUSION_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    round_id: int
    probabilities: _containers.RepeatedScalarFieldContainer[float]
    decision: int
    fusion: FusionRoundStarted
    def __init__(self, robot_id: _Optional[int] = ..., round_id: _Optional[int] = ..., probabilities: _Optional[_Iterable[float]] = ..., decision: _Optional[int] = ..., fusion: _Optional[_Union[FusionRoundStarted, _Mapping]] = ...) -> None: ...
