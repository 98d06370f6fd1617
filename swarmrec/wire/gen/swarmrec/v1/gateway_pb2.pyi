from . import constellation_pb2 as _constellation_pb2
from . import events_pb2 as _events_pb2
from . import fusion_pb2 as _fusion_pb2
from . import health_pb2 as _health_pb2
from . import replay_pb2 as _replay_pb2
from . import slam_pb2 as _slam_pb2
from . import vpr_pb2 as _vpr_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MembersRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class MembersReply(_message.Message):
    __slots__ = ("members",)
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    members: _containers.RepeatedCompositeFieldContainer[_health_pb2.MemberInfo]
    def __init__(self, members: _Optional[_Iterable[_Union[_health_pb2.MemberInfo, _Mapping]]] = ...) -> None: ...

class QueryRequest(_message.Message):
    __slots__ = ("constellation", "preset")
    CONSTELLATION_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    constellation: _constellation_pb2.Constellation
    preset: str
    def __init__(self, constellation: _Optional[_Union[_constellation_pb2.Constellation, _Mapping]] = ..., preset: _Optional[str] = ...) -> None: ...

class QueryReply(_message.Message):
    __slots__ = ("matches", "n_candidates", "verified_robot_ids", "failed_shard_robot_ids", "failed_verifier_robot_ids", "duration_us")
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    N_CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    VERIFIED_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    FAILED_SHARD_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    FAILED_VERIFIER_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    DURATION_US_FIELD_NUMBER: _ClassVar[int]
    matches: _containers.RepeatedCompositeFieldContainer[_events_pb2.VerifiedPair]
    n_candidates: int
    verified_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    failed_shard_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    failed_verifier_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    duration_us: int
    def __init__(self, matches: _Optional[_Iterable[_Union[_events_pb2.VerifiedPair, _Mapping]]] = ..., n_candidates: _Optional[int] = ..., verified_robot_ids: _Optional[_Iterable[int]] = ..., failed_shard_robot_ids: _Optional[_Iterable[int]] = ..., failed_verifier_robot_ids: _Optional[_Iterable[int]] = ..., duration_us: _Optional[int] = ...) -> None: ...

class RobotLoopClosuresRequest(_message.Message):
    __slots__ = ("robot_id", "min_score")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    MIN_SCORE_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    min_score: float
    def __init__(self, robot_id: _Optional[int] = ..., min_score: _Optional[float] = ...) -> None: ...

class RobotExplainRequest(_message.Message):
    __slots__ = ("robot_id", "frame_index")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    frame_index: int
    def __init__(self, robot_id: _Optional[int] = ..., frame_index: _Optional[int] = ...) -> None: ...

class StatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class StatusReply(_message.Message):
    __slots__ = ("swarm", "version", "serving", "n_robots", "services_by_kind", "zenoh_security", "open_streams")
    class ServicesByKindEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    SWARM_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SERVING_FIELD_NUMBER: _ClassVar[int]
    N_ROBOTS_FIELD_NUMBER: _ClassVar[int]
    SERVICES_BY_KIND_FIELD_NUMBER: _ClassVar[int]
    ZENOH_SECURITY_FIELD_NUMBER: _ClassVar[int]
    OPEN_STREAMS_FIELD_NUMBER: _ClassVar[int]
    swarm: str
    version: str
    serving: bool
    n_robots: int
    services_by_kind: _containers.ScalarMap[str, int]
    zenoh_security: str
    open_streams: int
    def __init__(self, swarm: _Optional[str] = ..., version: _Optional[str] = ..., serving: _Optional[bool] = ..., n_robots: _Optional[int] = ..., services_by_kind: _Optional[_Mapping[str, int]] = ..., zenoh_security: _Optional[str] = ..., open_streams: _Optional[int] = ...) -> None: ...

class WatchRequest(_message.Message):
    __slots__ = ("robot_ids",)
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, robot_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class MembershipChange(_message.Message):
    __slots__ = ("kind", "robot_id", "alive")
    KIND_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ALIVE_FIELD_NUMBER: _ClassVar[int]
    kind: str
    robot_id: int
    alive: bool
    def __init__(self, kind: _Optional[str] = ..., robot_id: _Optional[int] = ..., alive: _Optional[bool] = ...) -> None: ...

class PlaceQueryRequest(_message.Message):
    __slots__ = ("descriptor", "image", "exclude_robot_id")
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    EXCLUDE_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    descriptor: _containers.RepeatedScalarFieldContainer[float]
    image: bytes
    exclude_robot_id: int
    def __init__(self, descriptor: _Optional[_Iterable[float]] = ..., image: _Optional[bytes] = ..., exclude_robot_id: _Optional[int] = ...) -> None: ...

class PlaceQueryReply(_message.Message):
    __slots__ = ("cluster", "owner_robot_id", "assignment_version", "match", "descriptor", "duration_us")
    CLUSTER_FIELD_NUMBER: _ClassVar[int]
    OWNER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    ASSIGNMENT_VERSION_FIELD_NUMBER: _ClassVar[int]
    MATCH_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTOR_FIELD_NUMBER: _ClassVar[int]
    DURATION_US_FIELD_NUMBER: _ClassVar[int]
    cluster: int
    owner_robot_id: int
    assignment_version: int
    match: _vpr_pb2.PlaceMatch
    descriptor: _containers.RepeatedScalarFieldContainer[float]
    duration_us: int
    def __init__(self, cluster: _Optional[int] = ..., owner_robot_id: _Optional[int] = ..., assignment_version: _Optional[int] = ..., match: _Optional[_Union[_vpr_pb2.PlaceMatch, _Mapping]] = ..., descriptor: _Optional[_Iterable[float]] = ..., duration_us: _Optional[int] = ...) -> None: ...

class ClusterTableRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ClusterTableReply(_message.Message):
    __slots__ = ("version", "table_json", "centres_sha256", "agreed", "owners")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    TABLE_JSON_FIELD_NUMBER: _ClassVar[int]
    CENTRES_SHA256_FIELD_NUMBER: _ClassVar[int]
    AGREED_FIELD_NUMBER: _ClassVar[int]
    OWNERS_FIELD_NUMBER: _ClassVar[int]
    version: int
    table_json: str
    centres_sha256: str
    agreed: bool
    owners: _containers.RepeatedCompositeFieldContainer[_vpr_pb2.AssignmentReply]
    def __init__(self, version: _Optional[int] = ..., table_json: _Optional[str] = ..., centres_sha256: _Optional[str] = ..., agreed: _Optional[bool] = ..., owners: _Optional[_Iterable[_Union[_vpr_pb2.AssignmentReply, _Mapping]]] = ...) -> None: ...

class SlamTeamRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SlamTeamReply(_message.Message):
    __slots__ = ("robots",)
    ROBOTS_FIELD_NUMBER: _ClassVar[int]
    robots: _containers.RepeatedCompositeFieldContainer[_slam_pb2.SlamStatus]
    def __init__(self, robots: _Optional[_Iterable[_Union[_slam_pb2.SlamStatus, _Mapping]]] = ...) -> None: ...

class SlamRobotRequest(_message.Message):
    __slots__ = ("robot_id",)
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    def __init__(self, robot_id: _Optional[int] = ...) -> None: ...

class WatchSlamEstimateRequest(_message.Message):
    __slots__ = ("robot_id", "interval_ms")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    INTERVAL_MS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    interval_ms: int
    def __init__(self, robot_id: _Optional[int] = ..., interval_ms: _Optional[int] = ...) -> None: ...

class SlamMapRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SlamMapReply(_message.Message):
    __slots__ = ("solve_id", "keys", "values", "robot_ids", "states", "missing_robot_ids", "done")
    class StatesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: int
        value: _slam_pb2.SlamState
        def __init__(self, key: _Optional[int] = ..., value: _Optional[_Union[_slam_pb2.SlamState, str]] = ...) -> None: ...
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    KEYS_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    MISSING_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    solve_id: int
    keys: _containers.RepeatedScalarFieldContainer[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    robot_ids: _containers.RepeatedScalarFieldContainer[int]
    states: _containers.ScalarMap[int, _slam_pb2.SlamState]
    missing_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    done: bool
    def __init__(self, solve_id: _Optional[int] = ..., keys: _Optional[_Iterable[int]] = ..., values: _Optional[_Iterable[float]] = ..., robot_ids: _Optional[_Iterable[int]] = ..., states: _Optional[_Mapping[int, _slam_pb2.SlamState]] = ..., missing_robot_ids: _Optional[_Iterable[int]] = ..., done: _Optional[bool] = ...) -> None: ...

class LandmarkRoundRequest(_message.Message):
    __slots__ = ("round_id",)
    ROUND_ID_FIELD_NUMBER: _ClassVar[int]
    round_id: int
    def __init__(self, round_id: _Optional[int] = ...) -> None: ...

class LandmarkRoundReply(_message.Message):
    __slots__ = ("posteriors", "not_held")
    POSTERIORS_FIELD_NUMBER: _ClassVar[int]
    NOT_HELD_FIELD_NUMBER: _ClassVar[int]
    posteriors: _containers.RepeatedCompositeFieldContainer[_fusion_pb2.FusionPosterior]
    not_held: int
    def __init__(self, posteriors: _Optional[_Iterable[_Union[_fusion_pb2.FusionPosterior, _Mapping]]] = ..., not_held: _Optional[int] = ...) -> None: ...
