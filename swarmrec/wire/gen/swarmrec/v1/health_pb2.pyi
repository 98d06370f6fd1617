from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ServiceKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SERVICE_KIND_UNSPECIFIED: _ClassVar[ServiceKind]
    SERVICE_KIND_DETECTOR: _ClassVar[ServiceKind]
    SERVICE_KIND_DESCRIPTOR: _ClassVar[ServiceKind]
    SERVICE_KIND_INDEX_SHARD: _ClassVar[ServiceKind]
    SERVICE_KIND_VERIFIER: _ClassVar[ServiceKind]
    SERVICE_KIND_FUSION: _ClassVar[ServiceKind]
    SERVICE_KIND_ROUTER: _ClassVar[ServiceKind]
    SERVICE_KIND_GATEWAY: _ClassVar[ServiceKind]
    SERVICE_KIND_PLACE_OWNER: _ClassVar[ServiceKind]
    SERVICE_KIND_SLAM: _ClassVar[ServiceKind]
SERVICE_KIND_UNSPECIFIED: ServiceKind
SERVICE_KIND_DETECTOR: ServiceKind
SERVICE_KIND_DESCRIPTOR: ServiceKind
SERVICE_KIND_INDEX_SHARD: ServiceKind
SERVICE_KIND_VERIFIER: ServiceKind
SERVICE_KIND_FUSION: ServiceKind
SERVICE_KIND_ROUTER: ServiceKind
SERVICE_KIND_GATEWAY: ServiceKind
SERVICE_KIND_PLACE_OWNER: ServiceKind
SERVICE_KIND_SLAM: ServiceKind

class MemberInfo(_message.Message):
    __slots__ = ("kind", "robot_id", "label_lo", "label_hi", "version", "n_labels", "metrics_url", "swarm", "stored_items", "pending_items", "label_ranges", "pending_passes")
    KIND_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    LABEL_LO_FIELD_NUMBER: _ClassVar[int]
    LABEL_HI_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    N_LABELS_FIELD_NUMBER: _ClassVar[int]
    METRICS_URL_FIELD_NUMBER: _ClassVar[int]
    SWARM_FIELD_NUMBER: _ClassVar[int]
    STORED_ITEMS_FIELD_NUMBER: _ClassVar[int]
    PENDING_ITEMS_FIELD_NUMBER: _ClassVar[int]
    LABEL_RANGES_FIELD_NUMBER: _ClassVar[int]
    PENDING_PASSES_FIELD_NUMBER: _ClassVar[int]
    kind: ServiceKind
    robot_id: int
    label_lo: int
    label_hi: int
    version: str
    n_labels: int
    metrics_url: str
    swarm: str
    stored_items: int
    pending_items: int
    label_ranges: _containers.RepeatedScalarFieldContainer[int]
    pending_passes: int
    def __init__(self, kind: _Optional[_Union[ServiceKind, str]] = ..., robot_id: _Optional[int] = ..., label_lo: _Optional[int] = ..., label_hi: _Optional[int] = ..., version: _Optional[str] = ..., n_labels: _Optional[int] = ..., metrics_url: _Optional[str] = ..., swarm: _Optional[str] = ..., stored_items: _Optional[int] = ..., pending_items: _Optional[int] = ..., label_ranges: _Optional[_Iterable[int]] = ..., pending_passes: _Optional[int] = ...) -> None: ...
