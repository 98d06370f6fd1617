"""The v1 wire messages, gathered in one namespace.

    from swarmrec.wire import messages as pb

    query = pb.PartialQuery(query_id=7, n_ret=10)

The classes are generated from ``proto/swarmrec/v1/`` into
``swarmrec/wire/gen/`` (see the README there); this module spares services
the generated layout and maps the schema names that zenoh encodings carry
back to classes.
"""

from __future__ import annotations

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.errors import WireError
from swarmrec.wire.codec import schema_name
from swarmrec.wire.gen.swarmrec.v1.constellation_pb2 import Constellation
from swarmrec.wire.gen.swarmrec.v1.descriptor_pb2 import PartialDescriptor, SemanticDescriptor
from swarmrec.wire.gen.swarmrec.v1.errors_pb2 import ErrorCode, ErrorReply
from swarmrec.wire.gen.swarmrec.v1.events_pb2 import (
    CandidateOutcome,
    FunnelReason,
    GroupChange,
    LoopClosure,
    PlacementChange,
    PlacementReason,
    QueryReport,
    ShardCandidates,
    VerifiedPair,
)
from swarmrec.wire.gen.swarmrec.v1.fusion_pb2 import (
    ClassifierOutput,
    ClassifyReply,
    ClassifyRequest,
    FusionPosterior,
    FusionRoundStart,
    FusionRoundStarted,
    FusionStep,
    FusionUpdate,
    PosteriorRequest,
    WeightLaw,
)
from swarmrec.wire.gen.swarmrec.v1.health_pb2 import MemberInfo, ServiceKind
from swarmrec.wire.gen.swarmrec.v1.placement_pb2 import (
    AdoptRequest,
    GroupOwners,
    Placement,
    PlacementRequest,
    ShardState,
    ShardStore,
    TransferReply,
    TransferRequest,
)
from swarmrec.wire.gen.swarmrec.v1.query_pb2 import CandidatesReply, PartialQuery
from swarmrec.wire.gen.swarmrec.v1.replay_pb2 import (
    ExplainReply,
    ExplainRequest,
    LoopClosureList,
    LoopClosuresRequest,
    ReplayReply,
    ReplayRequest,
    ReportStatus,
    StepReply,
    StepRequest,
    StoreReply,
)
from swarmrec.wire.gen.swarmrec.v1.slam_pb2 import (
    SeparatorCount,
    SlamAbort,
    SlamControl,
    SlamEstimate,
    SlamEstimateRequest,
    SlamHello,
    SlamLoadRequest,
    SlamProblem,
    SlamReport,
    SlamSentPage,
    SlamSentRequest,
    SlamSolveRequest,
    SlamSolverSettings,
    SlamSolveStarted,
    SlamStage,
    SlamStageSummary,
    SlamState,
    SlamStatus,
    SlamStatusRequest,
    SlamStep,
)
from swarmrec.wire.gen.swarmrec.v1.verify_pb2 import VerifyMatch, VerifyReply, VerifyRequest
from swarmrec.wire.gen.swarmrec.v1.vpr_pb2 import (
    AdoptTableReply,
    AdoptTableRequest,
    AssignmentReply,
    AssignmentRequest,
    ClusterLoad,
    ClusterLoadRequest,
    ClusterTable,
    DescriptorEncoding,
    PlaceEntry,
    PlaceFrame,
    PlaceMatch,
    PlaceQuery,
    PlaceReport,
    RebalanceReply,
    RebalanceRequest,
    StoreEntriesReply,
    StoreEntriesRequest,
    TableRequest,
)

__all__ = [
    "MESSAGE_TYPES",
    "AdoptRequest",
    "AdoptTableReply",
    "AdoptTableRequest",
    "AssignmentReply",
    "AssignmentRequest",
    "CandidateOutcome",
    "CandidatesReply",
    "ClassifierOutput",
    "ClassifyReply",
    "ClassifyRequest",
    "ClusterLoad",
    "ClusterLoadRequest",
    "ClusterTable",
    "Constellation",
    "DescriptorEncoding",
    "ErrorCode",
    "ErrorReply",
    "ExplainReply",
    "ExplainRequest",
    "FunnelReason",
    "FusionPosterior",
    "FusionRoundStart",
    "FusionRoundStarted",
    "FusionStep",
    "FusionUpdate",
    "GroupChange",
    "GroupOwners",
    "LoopClosure",
    "LoopClosureList",
    "LoopClosuresRequest",
    "MemberInfo",
    "PartialDescriptor",
    "PartialQuery",
    "PlaceEntry",
    "PlaceFrame",
    "PlaceMatch",
    "PlaceQuery",
    "PlaceReport",
    "Placement",
    "PlacementChange",
    "PlacementReason",
    "PlacementRequest",
    "PosteriorRequest",
    "QueryReport",
    "RebalanceReply",
    "RebalanceRequest",
    "ReplayReply",
    "ReplayRequest",
    "ReportStatus",
    "SemanticDescriptor",
    "SeparatorCount",
    "ServiceKind",
    "ShardCandidates",
    "ShardState",
    "ShardStore",
    "SlamAbort",
    "SlamControl",
    "SlamEstimate",
    "SlamEstimateRequest",
    "SlamHello",
    "SlamLoadRequest",
    "SlamProblem",
    "SlamReport",
    "SlamSentPage",
    "SlamSentRequest",
    "SlamSolveRequest",
    "SlamSolveStarted",
    "SlamSolverSettings",
    "SlamStage",
    "SlamStageSummary",
    "SlamState",
    "SlamStatus",
    "SlamStatusRequest",
    "SlamStep",
    "StepReply",
    "StepRequest",
    "StoreEntriesReply",
    "StoreEntriesRequest",
    "StoreReply",
    "TableRequest",
    "TransferReply",
    "TransferRequest",
    "VerifiedPair",
    "VerifyMatch",
    "VerifyReply",
    "VerifyRequest",
    "WeightLaw",
    "message_class",
]

MESSAGE_TYPES: dict[str, type[Message]] = {
    schema_name(cls): cls
    for cls in (
        AdoptRequest,
        CandidateOutcome,
        AssignmentReply,
        AssignmentRequest,
        CandidatesReply,
        ClassifierOutput,
        ClassifyReply,
        ClassifyRequest,
        Constellation,
        ErrorReply,
        ExplainReply,
        ExplainRequest,
        FusionPosterior,
        FusionRoundStart,
        FusionRoundStarted,
        FusionStep,
        FusionUpdate,
        GroupChange,
        GroupOwners,
        LoopClosure,
        LoopClosureList,
        LoopClosuresRequest,
        MemberInfo,
        PartialDescriptor,
        PartialQuery,
        PlaceEntry,
        PlaceFrame,
        PlaceMatch,
        PlaceQuery,
        PlaceReport,
        TableRequest,
        StoreEntriesRequest,
        StoreEntriesReply,
        RebalanceRequest,
        RebalanceReply,
        ClusterTable,
        ClusterLoadRequest,
        ClusterLoad,
        AdoptTableRequest,
        AdoptTableReply,
        Placement,
        PlacementChange,
        PlacementRequest,
        PosteriorRequest,
        QueryReport,
        ReplayReply,
        ReplayRequest,
        SemanticDescriptor,
        SeparatorCount,
        ShardState,
        ShardStore,
        ShardCandidates,
        SlamAbort,
        SlamControl,
        SlamEstimate,
        SlamEstimateRequest,
        SlamHello,
        SlamLoadRequest,
        SlamProblem,
        SlamReport,
        SlamSentPage,
        SlamSentRequest,
        SlamSolveRequest,
        SlamSolveStarted,
        SlamSolverSettings,
        SlamStageSummary,
        SlamStatus,
        SlamStatusRequest,
        SlamStep,
        StepReply,
        StepRequest,
        StoreReply,
        TransferReply,
        TransferRequest,
        VerifiedPair,
        VerifyMatch,
        VerifyReply,
        VerifyRequest,
        WeightLaw,
    )
}
"""Every v1 message class by its full schema name (``swarmrec.v1.PartialQuery``)."""


def message_class(name: str) -> type[Message]:
    """The message class of a schema name; WireError for a name v1 does not define.

    A receiver uses it on the schema of a payload's encoding, e.g. to tell an
    ``ErrorReply`` from the reply it asked for.
    """
    try:
        return MESSAGE_TYPES[name]
    except KeyError:
        raise WireError(f"unknown message schema {name!r}") from None
