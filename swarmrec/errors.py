"""Exceptions raised by swarmrec.

Every error the project raises on purpose derives from :class:`SwarmrecError`,
so a caller can catch the whole family in one place::

    SwarmrecError
    ├── ConfigError                a setting is missing, out of range or inconsistent
    ├── DatasetError               input data cannot be read (names the file and line)
    │   ├── MalformedLineError     a line of a text file does not parse
    │   ├── UnknownLabelError      a label is not in the label list
    │   ├── datasets.tum_rgbd.RgbdImageError  a frame's RGB or depth image is missing, corrupt or mismatched
    │   └── slam.G2oError                    a g2o file or robot folder cannot be used
    │       ├── G2oQuaternionError           a quaternion too far from unit norm (norm)
    │       ├── G2oInformationError          an information matrix not symmetric positive definite
    │       └── G2oKeyError                  a vertex declared twice or an edge to no vertex (key)
    ├── WireError                  a message on the bus does not decode or validate   [INVALID_ARGUMENT]
    │   ├── MalformedMessageError  the bytes do not parse as the expected message     [MALFORMED]
    │   ├── MessageTooLargeError   the payload exceeds the receiver's size limit      [TOO_LARGE]
    │   ├── LimitExceededError     it asks for more work than the receiver's bounds   [TOO_LARGE]
    │   ├── MissingFieldError      a required field is absent                         [INVALID_ARGUMENT]
    │   └── LabelOutOfRangeError   a label index past the receiver's label list       [UNKNOWN_LABEL]
    ├── RequestError               a service refuses a request; the reply carries .code
    │   ├── InvalidArgument        [INVALID_ARGUMENT]
    │   ├── NotFound               [NOT_FOUND]
    │   ├── Unavailable            [UNAVAILABLE]
    │   ├── FailedPrecondition     [FAILED_PRECONDITION]
    │   ├── AlreadyExists          [ALREADY_EXISTS] stored already, with other content
    │   ├── PermissionDenied       [PERMISSION_DENIED] the caller may not act for whom it names
    │   └── Internal               [INTERNAL]
    ├── CallError                  a request to a peer did not get the expected answer
    │   ├── NoReply                nobody answered (gone, crashed, not discovered yet)
    │   ├── ReplyTimeout           the peer did not answer in time
    │   └── RemoteError            the peer answered with an error reply (.code, .message)
    ├── SecurityError              a certificate, key or security setting cannot be used
    │   ├── PkiConflictError       a file of the PKI differs from what was asked (nothing is overwritten)
    │   └── CertificateExpiredError  a certificate is past (or before) its validity
    ├── detection.DetectionError   an image, a model or its output cannot be used
    │   ├── ModelError             the ONNX model cannot be loaded or has unusable inputs/outputs
    │   └── OutputLayoutError      a model output is neither YOLO layout (or both)
    ├── fusion.LikelihoodError     a classifier output is not a usable probability vector
    ├── fusion.robot.RoundError    a fusion round that cannot start (answered INVALID_ARGUMENT)
    ├── fusion.classifier.ClassifierError   views the landmark classifier cannot take
    │   └── ClassifierModelError            its ONNX file is missing, does not load or is not a 19-way softmax
    ├── models.ModelNotFound       a shipped model is in none of the places models are looked up
    ├── slam.SlamError             a pose graph or message the SLAM back end cannot use
    │   ├── GraphError             a graph that cannot be solved as given (disconnected, no anchor)
    │   ├── MessageError           a distributed Gauss-Seidel message that does not fit its receiver
    │   │   └── TurnRejected       a live team member's message refused (reason), nothing changed
    │   └── AlignmentError         points that cannot be rigidly aligned
    ├── vpr.errors.VprError        place recognition cannot use this input
    │   ├── DescriptorError        a descriptor of the wrong shape or dtype, or with NaN/inf
    │   ├── DescriptorModelError   the descriptor ONNX file is missing, does not load or is not one
    │   └── StateFileError         a saved index, assignment or centres file cannot be read back
    └── deployments.DeploymentError        a deployment could not start, reach or stop its swarm
        ├── SwarmStartError                a service process exited or never became ready
        ├── ComposeError                   the compose tool failed or containers did not become healthy
        └── KubernetesError                kubectl failed, or the swarm did not come up on the cluster

The families below the bus errors live beside the code that raises them
(``swarmrec.detection.errors``, ``swarmrec.fusion``, ``swarmrec.models``,
``swarmrec.deployments``, ``swarmrec.slam.errors``, ``swarmrec.vpr.errors``); a test
checks that every subclass of :class:`SwarmrecError` in the package is named in this tree.

Errors a service answers with carry their wire code (:class:`ErrorCode`, the
same numbers as ``swarmrec.v1.ErrorCode``; a test checks them against the
schema): the runner replies with ``type(error).code`` and never reads the
message text to decide.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import ClassVar

__all__ = [
    "TRANSIENT_CODES",
    "AlreadyExists",
    "CallError",
    "CertificateExpiredError",
    "ConfigError",
    "DatasetError",
    "ErrorCode",
    "FailedPrecondition",
    "Internal",
    "InvalidArgument",
    "LabelOutOfRangeError",
    "LimitExceededError",
    "MalformedLineError",
    "MalformedMessageError",
    "MessageTooLargeError",
    "MissingFieldError",
    "NoReply",
    "NotFound",
    "PermissionDenied",
    "PkiConflictError",
    "RemoteError",
    "ReplyTimeout",
    "RequestError",
    "SecurityError",
    "SwarmrecError",
    "Unavailable",
    "UnknownLabelError",
    "WireError",
]


class ErrorCode(IntEnum):
    """Why a request failed: ``swarmrec.v1.ErrorCode`` without its prefix (connect-rpc's codes)."""

    UNSPECIFIED = 0
    INVALID_ARGUMENT = 1
    MALFORMED = 2
    UNKNOWN_LABEL = 3
    TOO_LARGE = 4
    NOT_FOUND = 5
    UNAVAILABLE = 6
    TIMEOUT = 7
    INTERNAL = 8
    FAILED_PRECONDITION = 9
    ALREADY_EXISTS = 10
    PERMISSION_DENIED = 11

    @property
    def wire_name(self) -> str:
        """The schema's name of the value, ``ERROR_CODE_...`` (the metrics' ``code`` label)."""
        return f"ERROR_CODE_{self.name}"

    @classmethod
    def of(cls, value: int) -> ErrorCode:
        """The code of a wire value; a value this version does not know reads as UNSPECIFIED."""
        try:
            return cls(value)
        except ValueError:
            return cls.UNSPECIFIED


#: Codes that say "not now" rather than "not this": a request refused with one may
#: succeed when sent again (a peer unreachable, frozen, behind, restarting).
TRANSIENT_CODES = frozenset(
    {
        ErrorCode.UNAVAILABLE,
        ErrorCode.TIMEOUT,
        ErrorCode.FAILED_PRECONDITION,
        ErrorCode.INTERNAL,
        ErrorCode.UNSPECIFIED,
    }
)


class SwarmrecError(Exception):
    """Base class of every error swarmrec raises on purpose."""


class ConfigError(SwarmrecError, ValueError):
    """A setting is missing, out of range or inconsistent with another one."""


@dataclass
class DatasetError(SwarmrecError):
    """Input data cannot be read.

    ``source`` is the file (or ``archive.zip:member``) and ``line`` the 1-based
    line number when the problem is on one line, so the message always points
    the user at the exact place to fix.
    """

    source: str | Path
    reason: str
    line: int | None = None

    def __str__(self) -> str:
        where = f"{self.source}:{self.line}" if self.line is not None else str(self.source)
        return f"{where}: {self.reason}"


@dataclass
class MalformedLineError(DatasetError):
    """A line of a text file does not parse (wrong column count, not a number, NaN...)."""


@dataclass
class UnknownLabelError(DatasetError):
    """A label that is not in the label list."""


# --- the bus ------------------------------------------------------------------


class WireError(SwarmrecError, ValueError):
    """A message on the bus does not decode or does not validate."""

    code: ClassVar[ErrorCode] = ErrorCode.INVALID_ARGUMENT


class MalformedMessageError(WireError):
    """The bytes do not parse as the expected message."""

    code = ErrorCode.MALFORMED


class MessageTooLargeError(WireError):
    """A payload larger than the receiver accepts (checked before parsing)."""

    code = ErrorCode.TOO_LARGE

    def __init__(self, size: int, max_size: int) -> None:
        super().__init__(f"message of {size} bytes exceeds the limit of {max_size}")
        self.size = size
        self.max_size = max_size


class LimitExceededError(WireError):
    """A message that decodes but asks for more than the receiver's bounds allow:
    objects in a frame, objects of one label, frames or object pairs to verify.

    Checked before the work starts, so refusing costs next to nothing.
    """

    code = ErrorCode.TOO_LARGE

    def __init__(self, what: str, value: int, limit: int, setting: str) -> None:
        super().__init__(f"{what}: {value}, more than the limit of {limit} (setting {setting})")
        self.what = what
        self.value = value
        self.limit = limit
        self.setting = setting


class MissingFieldError(WireError):
    """A required field is absent: proto3 would read it as 0 (robot 0, frame 0, step 0),
    so an empty payload or another message's bytes would pass for a real request."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(f"{message} has no {field}; it is required")
        self.message_name = message
        self.field = field


class LabelOutOfRangeError(WireError):
    """A label index (or a label range) past the end of the receiver's label list."""

    code = ErrorCode.UNKNOWN_LABEL


class RequestError(SwarmrecError):
    """Raised by a service's handler to answer with an error reply of ``code``.

    The subclasses fix the code; ``RequestError(message, code=...)`` passes on a
    code received from a peer (a forwarded refusal keeps its code).
    """

    code: ErrorCode = ErrorCode.INTERNAL

    def __init__(self, message: str, *, code: ErrorCode | None = None) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code


class InvalidArgument(RequestError):
    """The request decoded but a field is out of range or inconsistent."""

    code = ErrorCode.INVALID_ARGUMENT


class NotFound(RequestError):
    """A requested frame, round or robot is not known to the service."""

    code = ErrorCode.NOT_FOUND


class Unavailable(RequestError):
    """The service cannot serve now (a peer it depends on is gone, a replay runs)."""

    code = ErrorCode.UNAVAILABLE


class FailedPrecondition(RequestError):
    """The request is well formed but the service is not in the mode or state to serve it."""

    code = ErrorCode.FAILED_PRECONDITION


class AlreadyExists(RequestError):
    """A store of a frame (robot, frame index) that is already stored with other content.

    Stores are idempotent: the same content again is accepted and answered as
    before; other content would silently replace what peers already matched
    against, so it is refused and nothing changes.
    """

    code = ErrorCode.ALREADY_EXISTS


class PermissionDenied(RequestError):
    """A request that acts for another robot than its caller (a slice of robot 2 stored by
    robot 3), or a placement from a shard that is not the coordinator: the caller is the
    robot its key names, which the router lets each certificate name for itself only."""

    code = ErrorCode.PERMISSION_DENIED


class Internal(RequestError):
    """A failure inside the service (a model misbehaving), not the caller's fault."""

    code = ErrorCode.INTERNAL


class CallError(SwarmrecError):
    """A request to a peer did not get the expected answer.

    ``reason`` is the ``reason`` label of ``swarmrec_peer_failures_total``.
    """

    reason: ClassVar[str] = "error"

    def __init__(self, key: str, detail: str) -> None:
        super().__init__(f"{key}: {detail}")
        self.key = key


class NoReply(CallError):
    """Nobody answered: the peer is gone, crashed or not discovered yet."""

    reason = "no_reply"


class ReplyTimeout(CallError):
    """The peer did not answer in time."""

    reason = "timeout"


class RemoteError(CallError):
    """The peer answered with an ErrorReply (or an answer that does not decode)."""

    reason = "error"

    def __init__(self, key: str, code: int, message: str) -> None:
        self.code = ErrorCode.of(code)
        super().__init__(key, f"{self.code.wire_name}: {message}")
        self.message = message


# --- security -----------------------------------------------------------------


class SecurityError(SwarmrecError):
    """A certificate, a private key or a security setting cannot be used."""


class PkiConflictError(SecurityError):
    """A file of the swarm's PKI exists but is not what was asked for.

    Raised instead of overwriting it: a certificate signed by another CA, for
    another name, with another key, or a key without its certificate.
    """

    def __init__(self, path: str | Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = Path(path)
        self.reason = reason


class CertificateExpiredError(SecurityError):
    """A certificate is outside its validity period (expired or not yet valid)."""

    def __init__(self, path: str | Path, not_before: str, not_after: str) -> None:
        super().__init__(f"{path}: valid only from {not_before} to {not_after}")
        self.path = Path(path)
        self.not_before = not_before
        self.not_after = not_after
