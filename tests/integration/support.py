"""Helpers the integration tests share: raw requests, metrics, polling, datasets.

Nothing here sleeps to synchronise: :func:`wait_until` polls a condition
against a deadline, and requests wait on zenoh's own reply stream.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import zenoh

# protobuf ships no type stubs (see swarmrec/services/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.deployments.local import LocalDeployment, ServiceProcess
from swarmrec.deployments.metrics import read_metrics
from swarmrec.errors import NoReply
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.services.compiled import binary
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import schema_name

T = TypeVar("T")

ERROR_SCHEMA = schema_name(pb.ErrorReply)


@dataclass(frozen=True)
class Answer:
    """What one raw request got back: a reply payload or an ErrorReply."""

    ok: bytes | None
    schema: str
    error: pb.ErrorReply | None

    @property
    def code(self) -> str:
        """The ErrorCode name of an error answer; "" for a reply."""
        return pb.ErrorCode.Name(self.error.code) if self.error is not None else ""


def protobuf(schema: str) -> zenoh.Encoding:
    """``application/protobuf;<schema>``, the encoding every v1 payload travels with."""
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(schema)


def raw_request(
    session: zenoh.Session,
    key: str,
    payload: bytes,
    encoding: zenoh.Encoding | None,
    timeout_s: float = 5.0,
    caller: int | None = None,
    attachment: bytes | None = None,
) -> Answer:
    """Send ``payload`` as is to ``key``; exactly one answer is expected. ``caller``: the
    robot a caller-bound endpoint's key names as the sender (``keys.CALLER_BOUND``);
    ``attachment``: what the request says of its sender besides (a robot's id).

    Zero replies raise NoReply (never read as success), a zenoh timeout raises
    AssertionError; an error reply must carry a decodable ErrorReply.
    """
    key = keys.request_key(key, caller)
    replies = list(
        session.get(key, payload=payload, encoding=encoding, timeout=timeout_s, attachment=attachment)
    )
    if not replies:
        raise NoReply(key, "no service answered")
    assert len(replies) == 1, f"{key}: {len(replies)} replies to one request"
    rep = replies[0]
    if rep.ok is not None:
        return Answer(rep.ok.payload.to_bytes(), str(rep.ok.encoding).partition(";")[2], None)
    err = rep.err
    assert err is not None
    schema = str(err.encoding).partition(";")[2]
    data = err.payload.to_bytes()
    assert schema == ERROR_SCHEMA, f"{key}: error reply {data[:200]!r} with encoding {err.encoding}"
    return Answer(None, schema, pb.ErrorReply.FromString(data))


def request(
    session: zenoh.Session,
    key: str,
    msg: Message,
    timeout_s: float = 5.0,
    caller: int | None = None,
    attachment: bytes | None = None,
) -> Answer:
    """A well-formed request: ``msg`` with its schema in the encoding. To a caller-bound
    endpoint it goes as ``caller``, by default the robot whose frame it carries (a test
    client speaks for that robot, as its descriptor or place owner would)."""
    if caller is None:
        caller = carried_robot(msg)
    payload, encoding = msg.SerializeToString(), protobuf(schema_name(msg))
    return raw_request(session, key, payload, encoding, timeout_s, caller, attachment)


def carried_robot(msg: Message) -> int | None:
    """The robot whose frame a shard's or place owner's request carries, if any."""
    if isinstance(msg, pb.PartialQuery | pb.ShardStore) and msg.HasField("descriptor"):
        return int(msg.descriptor.robot_id)
    if isinstance(msg, pb.PlaceQuery):
        return int(msg.robot_id)
    return None


def reply_of(answer: Answer, cls: type[T]) -> T:
    """The decoded reply of a successful answer; fails the test on an error."""
    assert answer.error is None, f"expected a {cls.__name__}, got {answer.code}: {answer.error.message}"
    assert answer.ok is not None
    assert answer.schema == schema_name(cls), answer.schema
    msg: T = cls.FromString(answer.ok)  # type: ignore[attr-defined]
    return msg


def metric(url: str, name: str, **labels: str) -> float:
    """Sum of ``name`` over the series whose labels include ``labels`` (0 when none)."""
    return sum(
        v
        for (n, lab), v in read_metrics(url).items()
        if n == name and all(dict(lab).get(k) == val for k, val in labels.items())
    )


def metrics_url(sp: ServiceProcess) -> str:
    url = sp.metrics_url
    assert url, f"{sp.name} printed no metrics_url: {sp.info}"
    return url


def bound_locators(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """Where a session that listens (port 0 replaced by the port the OS gave) is reached,
    from its own admin space (the session's config enables ``adminspace``)."""
    zid = session.info.zid()
    for reply in session.get(f"@/{zid}/*", timeout=timeout_s):
        if reply.ok is not None and str(reply.ok.key_expr).rsplit("/", 1)[-1] in ("peer", "router"):
            found = json.loads(reply.ok.payload.to_string()).get("locators", [])
            if found:
                return [str(x) for x in found]
    raise AssertionError(f"session {zid} names no locator in its admin space")


def wait_until(condition: Callable[[], T | None], timeout_s: float, what: str, every_s: float = 0.05) -> T:
    """Poll ``condition`` until it returns something truthy; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not {what} after {timeout_s:g} s")
        time.sleep(every_s)


def answering(session: zenoh.Session, key: str, msg: Message, timeout_s: float = 30.0) -> Answer:
    """``request`` retried while nobody answers yet (a service just (re)started
    is discovered by the router a moment after its readiness line)."""

    def attempt() -> Answer | None:
        try:
            return request(session, key, msg)
        except NoReply:
            return None

    return wait_until(attempt, timeout_s, f"answered at {key}", every_s=0.1)


def endpoint_key(swarm: LocalDeployment, kind: str, robot: int, name: str) -> str:
    return keys.endpoint(swarm.spec_swarm, kind, robot, name)


def write_office(folder: Path, n_frames: int = 200) -> Path:
    """The synthetic office world as constellation files (what ``swarmrec synth`` writes)."""
    write_dataset(generate_office(OfficeConfig(n_frames=n_frames)), folder)
    return folder


def group_rows(caller: Caller, swarm: str, shard: int, group: int) -> set[tuple[int, int]]:
    """Every (robot, frame) ``shard`` holds for ``group``, paged through its ``transfer``."""
    rows: set[tuple[int, int]] = set()
    start = 0
    while True:
        reply = caller.call(
            keys.endpoint(swarm, "index-shard", shard, "transfer"),
            pb.TransferRequest(group=group, start_row=start),
            pb.TransferReply,
            target_robot=shard,
        )
        rows |= {(r.robot_id, r.frame_index) for r in reply.records}
        start = reply.next_row
        if reply.done:
            return rows


def compute(requests: list[dict[str, Any]], env: dict[str, str] | None = None) -> list[Any]:
    """The compiled data plane's answers to ``requests`` (``swarmrec-dataplane compute``, one
    JSON line each; dataplane/src/compute.rs), in order; none may be an error."""
    lines = "".join(json.dumps(r) + "\n" for r in requests)
    done = subprocess.run(
        [str(binary()), "compute"],
        input=lines,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=True,
    )
    answers = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(answers) == len(requests), done.stderr
    errors = [a["error"] for a in answers if "error" in a]
    assert not errors, errors[:3]
    return [a["result"] for a in answers]
