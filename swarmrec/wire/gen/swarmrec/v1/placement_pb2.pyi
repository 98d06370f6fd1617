from . import descriptor_pb2 as _descriptor_pb2
from . import events_pb2 as _events_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Placement(_message.Message):
    __slots__ = ("version", "group_bounds", "groups", "members", "replicas")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    GROUP_BOUNDS_FIELD_NUMBER: _ClassVar[int]
    GROUPS_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    REPLICAS_FIELD_NUMBER: _ClassVar[int]
    version: int
    group_bounds: _containers.RepeatedScalarFieldContainer[int]
    groups: _containers.RepeatedCompositeFieldContainer[GroupOwners]
    members: _containers.RepeatedScalarFieldContainer[int]
    replicas: int
    def __init__(self, version: _Optional[int] = ..., group_bounds: _Optional[_Iterable[int]] = ..., groups: _Optional[_Iterable[_Union[GroupOwners, _Mapping]]] = ..., members: _Optional[_Iterable[int]] = ..., replicas: _Optional[int] = ...) -> None: ...

class GroupOwners(_message.Message):
    __slots__ = ("owners", "learners", "leaving")
    OWNERS_FIELD_NUMBER: _ClassVar[int]
    LEARNERS_FIELD_NUMBER: _ClassVar[int]
    LEAVING_FIELD_NUMBER: _ClassVar[int]
    owners: _containers.RepeatedScalarFieldContainer[int]
    learners: _containers.RepeatedScalarFieldContainer[int]
    leaving: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, owners: _Optional[_Iterable[int]] = ..., learners: _Optional[_Iterable[int]] = ..., leaving: _Optional[_Iterable[int]] = ...) -> None: ...

class PlacementRequest(_message.Message):
    __slots__ = ("known_version",)
    KNOWN_VERSION_FIELD_NUMBER: _ClassVar[int]
    known_version: int
    def __init__(self, known_version: _Optional[int] = ...) -> None: ...

class ShardState(_message.Message):
    __slots__ = ("placement", "shard_id", "ready_groups", "confirmed", "draining", "query_calls", "query_cpu_s", "store_calls", "store_cpu_s", "placement_version", "served_groups", "served_queries")
    PLACEMENT_FIELD_NUMBER: _ClassVar[int]
    SHARD_ID_FIELD_NUMBER: _ClassVar[int]
    READY_GROUPS_FIELD_NUMBER: _ClassVar[int]
    CONFIRMED_FIELD_NUMBER: _ClassVar[int]
    DRAINING_FIELD_NUMBER: _ClassVar[int]
    QUERY_CALLS_FIELD_NUMBER: _ClassVar[int]
    QUERY_CPU_S_FIELD_NUMBER: _ClassVar[int]
    STORE_CALLS_FIELD_NUMBER: _ClassVar[int]
    STORE_CPU_S_FIELD_NUMBER: _ClassVar[int]
    PLACEMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    SERVED_GROUPS_FIELD_NUMBER: _ClassVar[int]
    SERVED_QUERIES_FIELD_NUMBER: _ClassVar[int]
    placement: Placement
    shard_id: int
    ready_groups: _containers.RepeatedScalarFieldContainer[int]
    confirmed: bool
    draining: bool
    query_calls: int
    query_cpu_s: float
    store_calls: int
    store_cpu_s: float
    placement_version: int
    served_groups: _containers.RepeatedScalarFieldContainer[int]
    served_queries: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, placement: _Optional[_Union[Placement, _Mapping]] = ..., shard_id: _Optional[int] = ..., ready_groups: _Optional[_Iterable[int]] = ..., confirmed: _Optional[bool] = ..., draining: _Optional[bool] = ..., query_calls: _Optional[int] = ..., query_cpu_s: _Optional[float] = ..., store_calls: _Optional[int] = ..., store_cpu_s: _Optional[float] = ..., placement_version: _Optional[int] = ..., served_groups: _Optional[_Iterable[int]] = ..., served_queries: _Optional[_Iterable[int]] = ...) -> None: ...

class AdoptRequest(_message.Message):
    __slots__ = ("placement", "publish", "reason")
    PLACEMENT_FIELD_NUMBER: _ClassVar[int]
    PUBLISH_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    placement: Placement
    publish: bool
    reason: _events_pb2.PlacementReason
    def __init__(self, placement: _Optional[_Union[Placement, _Mapping]] = ..., publish: _Optional[bool] = ..., reason: _Optional[_Union[_events_pb2.PlacementReason, str]] = ...) -> None: ...

class ShardStore(_message.Message):
    __slots__ = ("descriptor", "placement_version")
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    PLACEMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    descriptor: _descriptor_pb2.PartialDescriptor
    placement_version: int
    def __init__(self, descriptor: _Optional[_Union[_descriptor_pb2.PartialDescriptor, _Mapping]] = ..., placement_version: _Optional[int] = ...) -> None: ...

class TransferRequest(_message.Message):
    __slots__ = ("group", "placement_version", "start_row", "max_records")
    GROUP_FIELD_NUMBER: _ClassVar[int]
    PLACEMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    START_ROW_FIELD_NUMBER: _ClassVar[int]
    MAX_RECORDS_FIELD_NUMBER: _ClassVar[int]
    group: int
    placement_version: int
    start_row: int
    max_records: int
    def __init__(self, group: _Optional[int] = ..., placement_version: _Optional[int] = ..., start_row: _Optional[int] = ..., max_records: _Optional[int] = ...) -> None: ...

class TransferReply(_message.Message):
    __slots__ = ("group", "records", "next_row", "done")
    GROUP_FIELD_NUMBER: _ClassVar[int]
    RECORDS_FIELD_NUMBER: _ClassVar[int]
    NEXT_ROW_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    group: int
    records: _containers.RepeatedCompositeFieldContainer[_descriptor_pb2.PartialDescriptor]
    next_row: int
    done: bool
    def __init__(self, group: _Optional[int] = ..., records: _Optional[_Iterable[_Union[_descriptor_pb2.PartialDescriptor, _Mapping]]] = ..., next_row: _Optional[int] = ..., done: _Optional[bool] = ...) -> None: ...
