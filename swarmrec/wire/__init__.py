"""The wire format: v1 protobuf messages and the codec to and from the core types.

    from swarmrec.wire import constellation_to_proto, encode, schema_name
    from swarmrec.wire import messages as pb

Schemas live in ``proto/swarmrec/v1/``; the generated code in
``swarmrec/wire/gen/`` is reached through :mod:`swarmrec.wire.messages`.
"""

from swarmrec.wire import messages
from swarmrec.wire.codec import (
    MAX_ERROR_MESSAGE_CHARS,
    MM_PER_M,
    Candidate,
    DescriptorSlice,
    candidates_from_proto,
    candidates_to_proto,
    constellation_from_proto,
    constellation_to_proto,
    decode,
    descriptor_from_proto,
    descriptor_to_proto,
    encode,
    error_reply,
    matched_pairs_from_proto,
    partial_descriptor_from_proto,
    partial_descriptor_to_proto,
    schema_name,
    verify_match_to_proto,
)
from swarmrec.wire.messages import message_class

__all__ = [
    "MAX_ERROR_MESSAGE_CHARS",
    "MM_PER_M",
    "Candidate",
    "DescriptorSlice",
    "candidates_from_proto",
    "candidates_to_proto",
    "constellation_from_proto",
    "constellation_to_proto",
    "decode",
    "descriptor_from_proto",
    "descriptor_to_proto",
    "encode",
    "error_reply",
    "matched_pairs_from_proto",
    "message_class",
    "messages",
    "partial_descriptor_from_proto",
    "partial_descriptor_to_proto",
    "schema_name",
    "verify_match_to_proto",
]
