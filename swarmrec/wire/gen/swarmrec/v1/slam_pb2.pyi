from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class SlamStage(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SLAM_STAGE_UNSPECIFIED: _ClassVar[SlamStage]
    SLAM_STAGE_ROTATION: _ClassVar[SlamStage]
    SLAM_STAGE_POSE: _ClassVar[SlamStage]

class SlamState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SLAM_STATE_UNSPECIFIED: _ClassVar[SlamState]
    SLAM_STATE_IDLE: _ClassVar[SlamState]
    SLAM_STATE_LOADED: _ClassVar[SlamState]
    SLAM_STATE_GREETING: _ClassVar[SlamState]
    SLAM_STATE_SOLVING: _ClassVar[SlamState]
    SLAM_STATE_DONE: _ClassVar[SlamState]
    SLAM_STATE_ABORTING: _ClassVar[SlamState]
    SLAM_STATE_ABORTED: _ClassVar[SlamState]
    SLAM_STATE_FAILED: _ClassVar[SlamState]
SLAM_STAGE_UNSPECIFIED: SlamStage
SLAM_STAGE_ROTATION: SlamStage
SLAM_STAGE_POSE: SlamStage
SLAM_STATE_UNSPECIFIED: SlamState
SLAM_STATE_IDLE: SlamState
SLAM_STATE_LOADED: SlamState
SLAM_STATE_GREETING: SlamState
SLAM_STATE_SOLVING: SlamState
SLAM_STATE_DONE: SlamState
SLAM_STATE_ABORTING: SlamState
SLAM_STATE_ABORTED: SlamState
SLAM_STATE_FAILED: SlamState

class SlamSolverSettings(_message.Message):
    __slots__ = ("mode", "order", "gamma", "eta_rotation", "eta_pose", "max_iterations", "pose_linearisations")
    MODE_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    GAMMA_FIELD_NUMBER: _ClassVar[int]
    ETA_ROTATION_FIELD_NUMBER: _ClassVar[int]
    ETA_POSE_FIELD_NUMBER: _ClassVar[int]
    MAX_ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    POSE_LINEARISATIONS_FIELD_NUMBER: _ClassVar[int]
    mode: str
    order: str
    gamma: float
    eta_rotation: float
    eta_pose: float
    max_iterations: int
    pose_linearisations: int
    def __init__(self, mode: _Optional[str] = ..., order: _Optional[str] = ..., gamma: _Optional[float] = ..., eta_rotation: _Optional[float] = ..., eta_pose: _Optional[float] = ..., max_iterations: _Optional[int] = ..., pose_linearisations: _Optional[int] = ...) -> None: ...

class SlamLoadRequest(_message.Message):
    __slots__ = ("solve_id", "settings")
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    SETTINGS_FIELD_NUMBER: _ClassVar[int]
    solve_id: int
    settings: SlamSolverSettings
    def __init__(self, solve_id: _Optional[int] = ..., settings: _Optional[_Union[SlamSolverSettings, _Mapping]] = ...) -> None: ...

class SeparatorCount(_message.Message):
    __slots__ = ("robot_id", "separators")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SEPARATORS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    separators: int
    def __init__(self, robot_id: _Optional[int] = ..., separators: _Optional[int] = ...) -> None: ...

class SlamProblem(_message.Message):
    __slots__ = ("robot_id", "solve_id", "vertices", "edges", "separators", "anchor")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    VERTICES_FIELD_NUMBER: _ClassVar[int]
    EDGES_FIELD_NUMBER: _ClassVar[int]
    SEPARATORS_FIELD_NUMBER: _ClassVar[int]
    ANCHOR_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    solve_id: int
    vertices: int
    edges: int
    separators: _containers.RepeatedCompositeFieldContainer[SeparatorCount]
    anchor: bool
    def __init__(self, robot_id: _Optional[int] = ..., solve_id: _Optional[int] = ..., vertices: _Optional[int] = ..., edges: _Optional[int] = ..., separators: _Optional[_Iterable[_Union[SeparatorCount, _Mapping]]] = ..., anchor: _Optional[bool] = ...) -> None: ...

class SlamSolveRequest(_message.Message):
    __slots__ = ("solve_id",)
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    solve_id: int
    def __init__(self, solve_id: _Optional[int] = ...) -> None: ...

class SlamSolveStarted(_message.Message):
    __slots__ = ("robot_id", "solve_id")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    solve_id: int
    def __init__(self, robot_id: _Optional[int] = ..., solve_id: _Optional[int] = ...) -> None: ...

class SlamHello(_message.Message):
    __slots__ = ("separators",)
    SEPARATORS_FIELD_NUMBER: _ClassVar[int]
    separators: _containers.RepeatedCompositeFieldContainer[SeparatorCount]
    def __init__(self, separators: _Optional[_Iterable[_Union[SeparatorCount, _Mapping]]] = ...) -> None: ...

class SlamAbort(_message.Message):
    __slots__ = ("vanished_robot_ids", "consistent_linearisation", "consistent_iteration", "reason")
    VANISHED_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    CONSISTENT_LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    CONSISTENT_ITERATION_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    vanished_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    consistent_linearisation: int
    consistent_iteration: int
    reason: str
    def __init__(self, vanished_robot_ids: _Optional[_Iterable[int]] = ..., consistent_linearisation: _Optional[int] = ..., consistent_iteration: _Optional[int] = ..., reason: _Optional[str] = ...) -> None: ...

class SlamControl(_message.Message):
    __slots__ = ("solve_id", "sender_robot_id", "receiver_robot_id", "hello", "abort")
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    SENDER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    RECEIVER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    HELLO_FIELD_NUMBER: _ClassVar[int]
    ABORT_FIELD_NUMBER: _ClassVar[int]
    solve_id: int
    sender_robot_id: int
    receiver_robot_id: int
    hello: SlamHello
    abort: SlamAbort
    def __init__(self, solve_id: _Optional[int] = ..., sender_robot_id: _Optional[int] = ..., receiver_robot_id: _Optional[int] = ..., hello: _Optional[_Union[SlamHello, _Mapping]] = ..., abort: _Optional[_Union[SlamAbort, _Mapping]] = ...) -> None: ...

class SlamStep(_message.Message):
    __slots__ = ("solve_id", "sender_robot_id", "receiver_robot_id", "stage", "linearisation", "iteration", "solved", "change", "keys", "values")
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    SENDER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    RECEIVER_ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    STAGE_FIELD_NUMBER: _ClassVar[int]
    LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    ITERATION_FIELD_NUMBER: _ClassVar[int]
    SOLVED_FIELD_NUMBER: _ClassVar[int]
    CHANGE_FIELD_NUMBER: _ClassVar[int]
    KEYS_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    solve_id: int
    sender_robot_id: int
    receiver_robot_id: int
    stage: SlamStage
    linearisation: int
    iteration: int
    solved: bool
    change: float
    keys: _containers.RepeatedScalarFieldContainer[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, solve_id: _Optional[int] = ..., sender_robot_id: _Optional[int] = ..., receiver_robot_id: _Optional[int] = ..., stage: _Optional[_Union[SlamStage, str]] = ..., linearisation: _Optional[int] = ..., iteration: _Optional[int] = ..., solved: _Optional[bool] = ..., change: _Optional[float] = ..., keys: _Optional[_Iterable[int]] = ..., values: _Optional[_Iterable[float]] = ...) -> None: ...

class SlamStatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SlamStageSummary(_message.Message):
    __slots__ = ("stage", "linearisation", "iterations", "converged", "max_change", "floats")
    STAGE_FIELD_NUMBER: _ClassVar[int]
    LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    CONVERGED_FIELD_NUMBER: _ClassVar[int]
    MAX_CHANGE_FIELD_NUMBER: _ClassVar[int]
    FLOATS_FIELD_NUMBER: _ClassVar[int]
    stage: SlamStage
    linearisation: int
    iterations: int
    converged: bool
    max_change: _containers.RepeatedScalarFieldContainer[float]
    floats: int
    def __init__(self, stage: _Optional[_Union[SlamStage, str]] = ..., linearisation: _Optional[int] = ..., iterations: _Optional[int] = ..., converged: _Optional[bool] = ..., max_change: _Optional[_Iterable[float]] = ..., floats: _Optional[int] = ...) -> None: ...

class SlamReport(_message.Message):
    __slots__ = ("stage", "linearisation", "iteration", "solved", "change")
    STAGE_FIELD_NUMBER: _ClassVar[int]
    LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    ITERATION_FIELD_NUMBER: _ClassVar[int]
    SOLVED_FIELD_NUMBER: _ClassVar[int]
    CHANGE_FIELD_NUMBER: _ClassVar[int]
    stage: SlamStage
    linearisation: int
    iteration: int
    solved: bool
    change: float
    def __init__(self, stage: _Optional[_Union[SlamStage, str]] = ..., linearisation: _Optional[int] = ..., iteration: _Optional[int] = ..., solved: _Optional[bool] = ..., change: _Optional[float] = ...) -> None: ...

class SlamStatus(_message.Message):
    __slots__ = ("robot_id", "solve_id", "state", "stage", "linearisation", "iteration", "order", "stages", "converged", "reason", "vanished_robot_ids", "consistent_linearisation", "consistent_iteration", "reports", "rejected")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STAGE_FIELD_NUMBER: _ClassVar[int]
    LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    ITERATION_FIELD_NUMBER: _ClassVar[int]
    ORDER_FIELD_NUMBER: _ClassVar[int]
    STAGES_FIELD_NUMBER: _ClassVar[int]
    CONVERGED_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    VANISHED_ROBOT_IDS_FIELD_NUMBER: _ClassVar[int]
    CONSISTENT_LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    CONSISTENT_ITERATION_FIELD_NUMBER: _ClassVar[int]
    REPORTS_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    solve_id: int
    state: SlamState
    stage: SlamStage
    linearisation: int
    iteration: int
    order: _containers.RepeatedScalarFieldContainer[int]
    stages: _containers.RepeatedCompositeFieldContainer[SlamStageSummary]
    converged: bool
    reason: str
    vanished_robot_ids: _containers.RepeatedScalarFieldContainer[int]
    consistent_linearisation: int
    consistent_iteration: int
    reports: _containers.RepeatedCompositeFieldContainer[SlamReport]
    rejected: int
    def __init__(self, robot_id: _Optional[int] = ..., solve_id: _Optional[int] = ..., state: _Optional[_Union[SlamState, str]] = ..., stage: _Optional[_Union[SlamStage, str]] = ..., linearisation: _Optional[int] = ..., iteration: _Optional[int] = ..., order: _Optional[_Iterable[int]] = ..., stages: _Optional[_Iterable[_Union[SlamStageSummary, _Mapping]]] = ..., converged: _Optional[bool] = ..., reason: _Optional[str] = ..., vanished_robot_ids: _Optional[_Iterable[int]] = ..., consistent_linearisation: _Optional[int] = ..., consistent_iteration: _Optional[int] = ..., reports: _Optional[_Iterable[_Union[SlamReport, _Mapping]]] = ..., rejected: _Optional[int] = ...) -> None: ...

class SlamEstimateRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SlamEstimate(_message.Message):
    __slots__ = ("robot_id", "solve_id", "state", "linearisation", "iteration", "keys", "values")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    LINEARISATION_FIELD_NUMBER: _ClassVar[int]
    ITERATION_FIELD_NUMBER: _ClassVar[int]
    KEYS_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    solve_id: int
    state: SlamState
    linearisation: int
    iteration: int
    keys: _containers.RepeatedScalarFieldContainer[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, robot_id: _Optional[int] = ..., solve_id: _Optional[int] = ..., state: _Optional[_Union[SlamState, str]] = ..., linearisation: _Optional[int] = ..., iteration: _Optional[int] = ..., keys: _Optional[_Iterable[int]] = ..., values: _Optional[_Iterable[float]] = ...) -> None: ...

class SlamSentRequest(_message.Message):
    __slots__ = ("offset",)
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    offset: int
    def __init__(self, offset: _Optional[int] = ...) -> None: ...

class SlamSentPage(_message.Message):
    __slots__ = ("robot_id", "solve_id", "total", "offset", "steps")
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    SOLVE_ID_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    robot_id: int
    solve_id: int
    total: int
    offset: int
    steps: _containers.RepeatedCompositeFieldContainer[SlamStep]
    def __init__(self, robot_id: _Optional[int] = ..., solve_id: _Optional[int] = ..., total: _Optional[int] = ..., offset: _Optional[int] = ..., steps: _Optional[_Iterable[_Union[SlamStep, _Mapping]]] = ...) -> None: ...
