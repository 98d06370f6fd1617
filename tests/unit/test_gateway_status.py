"""The gateway answers every swarm error code with a gRPC status (a new code without a row
would reach clients as UNKNOWN)."""

from __future__ import annotations

import grpc

from swarmrec.errors import AlreadyExists, ErrorCode, FailedPrecondition, InvalidArgument
from swarmrec.services.gateway import GRPC_STATUS, grpc_status_of


def test_every_error_code_has_a_grpc_status() -> None:
    assert set(GRPC_STATUS) == set(ErrorCode)


def test_request_errors_keep_their_meaning_across_the_gateway() -> None:
    assert grpc_status_of(InvalidArgument("x")) == (
        grpc.StatusCode.INVALID_ARGUMENT,
        ErrorCode.INVALID_ARGUMENT,
    )
    assert grpc_status_of(AlreadyExists("x")) == (grpc.StatusCode.ALREADY_EXISTS, ErrorCode.ALREADY_EXISTS)
    assert grpc_status_of(FailedPrecondition("x"))[0] == grpc.StatusCode.FAILED_PRECONDITION
