"""Bad input to every queryable of every robot service, over a real router.

One 2-robot swarm (all four services per robot, real processes, a 4096-byte
request limit) is started for the module and fed six lock-step steps of the
synthetic office, so shards and verifiers hold data. Each case then sends one
bad request and checks that

* it comes back as an ErrorReply (encoding ``swarmrec.v1.ErrorReply``) with
  the expected ErrorCode,
* the rejection is counted in ``swarmrec_rejected_requests_total{endpoint,code}``
  on the service's own metrics endpoint (and nothing else is),
* nothing stored changed: stored-count gauges, the frames queried, every
  shard's full candidate list, every verifier's answer and the bytes of every
  record log on disk are identical,
* every service still answers a valid request.

The swarm runs in the explicit insecure mode: these cases send every endpoint
bad payloads as whoever they need to be, which the router's access control would
drop before any service saw them (who may call what is tested in
test_swarm_mtls.py and test_zenoh_mtls.py).

An empty payload is no request: the fields a request cannot do without have
presence on the wire and are required (an empty Constellation used to be robot
0's frame 0 with nothing in it, which wiped a stored frame). Another message's
bytes sent without an encoding parse more often than not; their fields are
unknown to the schema and refused as MALFORMED. Stores are idempotent: the same
frame again is accepted, another one at a stored index is ALREADY_EXISTS. What a
frame may cost is bounded (objects per frame and per label, frames and object
pairs a verify compares: TOO_LARGE); the heavy cases (a 100,000-object frame,
claimed frame indices, fusion round ids) are in test_hostile_input.py.

Positions are integer millimetres on the wire, so a NaN cannot travel in a
Constellation; a dataset with a non-finite coordinate is refused when the
detector loads it (the last tests). NaN does travel in float fields
(VerifyRequest.distance_threshold_m, ReplayRequest.rate_hz,
LoopClosuresRequest.min_score) and is refused there.
"""

from __future__ import annotations

import functools
import math
import random
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import DecodeError, Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.client import ZenohClient
from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.base import SwarmStartError
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import read_metrics
from swarmrec.runtime.runner import WARNING_BURST
from swarmrec.services.limits import MAX_FRAME_GAP, MAX_FRAME_INDEX, MAX_N_RET
from swarmrec.services.registry import WORKLOADS, spec
from swarmrec.services.settings import DetectorSettings, IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    constellation_from_proto,
    constellation_to_proto,
    partial_descriptor_to_proto,
    schema_name,
)
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import (
    Answer,
    carried_robot,
    endpoint_key,
    metric,
    metrics_url,
    protobuf,
    raw_request,
    reply_of,
    request,
    write_office,
)

N_ROBOTS, N_LABELS, LIMIT = 2, 80, 4096
#: Object pairs a verify may compare: above the swarm's own verifies (at most ~1,200
#: here), below a 100-object query against robot 1's six seeded frames (58 objects).
PAIRS_LIMIT = 3000
BOUNDS = (0, 40, 80)  # even ranges of 80 labels over 2 robots
SEEDED_STEPS = 6
PROBE_STEP = 2  # each robot's frame used to probe its verifier


@dataclass
class Swarm:
    """The module's running swarm and what the cases need to know about it."""

    local: LocalDeployment
    client: ZenohClient
    frames: dict[int, pb.Constellation]  # robot -> wire form of its PROBE_STEP frame

    @property
    def session(self) -> zenoh.Session:
        return self.client.session

    def key(self, kind: str, robot: int, endpoint: str) -> str:
        return endpoint_key(self.local, kind, robot, endpoint)

    def url(self, kind: str, robot: int) -> str:
        return metrics_url(self.local.find(kind, robot))


@contextmanager
def seeded_swarm(tmp: Path, name: str, place: PlaceSettings, **bus: object) -> Iterator[Swarm]:
    """A running 2-robot places swarm fed SEEDED_STEPS lock-step steps of the synthetic office."""
    dataset = write_office(tmp / "dataset", n_frames=200)
    # One replica a group: shard r holds label range r alone (the paper's layout), so a shard
    # refuses the other's range.
    parts = (place, IndexSettings(replicas=1), DetectorSettings(dataset=str(dataset)))
    with (
        running_swarm(tmp, name, *parts, robots=N_ROBOTS, security="insecure", **bus) as local,
        local.client(5.0) as client,
    ):
        for t in range(SEEDED_STEPS):
            replies = client.step(t, timeout_s=10)
            assert sorted(r.robot_id for r in replies if isinstance(r, pb.StepReply)) == [0, 1], replies
        seq = read_constellations(dataset)
        blocks = split_frames(len(seq), N_ROBOTS)
        # Exactly as the detector sent them (positions as the swarm's settings put them on the wire).
        probe = {r: blocks[r][PROBE_STEP] for r in range(N_ROBOTS)}
        frames = {
            r: constellation_to_proto(
                seq.constellations[g], r, PROBE_STEP, seq.frame_ids[g], exact=place.exact_positions
            )
            for r, g in probe.items()
        }
        assert all(len(f.labels) >= 3 for f in frames.values())  # they verify against themselves
        yield Swarm(local, client, frames)


@pytest.fixture(scope="module", params=["channel", "queue", "compiled"])
def swarm(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Iterator[Swarm]:
    """Every case against both ways requests reach a Python service's workers (``dispatch``),
    and with the kinds that have a compiled implementation served by it (``data_plane``)."""
    place = PlaceSettings(lockstep=True, verify_max_object_pairs=PAIRS_LIMIT)
    mode = request.param
    tmp = tmp_path_factory.mktemp(f"bad-input-{mode}")
    bus: dict[str, object] = (
        {"data_plane": "compiled", "dispatch": "channel"}
        if mode == "compiled"
        else {"data_plane": "python", "dispatch": mode}
    )
    with seeded_swarm(tmp, f"bad-input-{mode}", place, max_message_bytes=LIMIT, **bus) as s:
        served = {(p.kind, p.info.get("dispatch")) for p in s.local.procs}
        compiled = {k for k in WORKLOADS["places"] if spec(k).compiled}
        if mode == "compiled":
            assert compiled and {(k, "compiled") for k in compiled} <= served, served
        assert {d for k, d in served if mode != "compiled" or k not in compiled} == {bus["dispatch"]}
        yield s


# --- what must not change -------------------------------------------------------


def _full_range_query(robot: int) -> pb.PartialQuery:
    """A read-only query holding every label of shard ``robot``'s range once: it
    overlaps every stored slice, so its candidates (n_ret 256) list the shard's content."""
    lo, hi = BOUNDS[robot], BOUNDS[robot + 1]
    return pb.PartialQuery(
        n_ret=MAX_N_RET,
        read_only=True,
        include_scores=True,
        descriptor=partial_descriptor_to_proto([1] * N_LABELS, lo, hi, robot=0, frame=0, query_step=0),
    )


def snapshot(s: Swarm) -> dict[str, Any]:
    """Everything a bad request could have changed, read through valid requests."""
    out: dict[str, Any] = {}
    for r in range(N_ROBOTS):
        cands = reply_of(
            request(s.session, s.key("index-shard", r, "query"), _full_range_query(r)), pb.CandidatesReply
        )
        out[f"shard {r} candidates"] = cands.SerializeToString()
        ver = reply_of(
            request(
                s.session,
                s.key("verifier", r, "verify"),
                pb.VerifyRequest(query=s.frames[r], include_pairs=True),
            ),
            pb.VerifyReply,
        )
        out[f"verifier {r} answer"] = ver.SerializeToString()
        closures = reply_of(
            request(s.session, s.key("descriptor", r, "loop_closures"), pb.LoopClosuresRequest()),
            pb.LoopClosureList,
        )
        out[f"descriptor {r} loop closures"] = closures.SerializeToString()
        explained = reply_of(
            request(s.session, s.key("descriptor", r, "explain"), pb.ExplainRequest(frame_index=STORED)),
            pb.ExplainReply,
        )
        out[f"descriptor {r} explain"] = explained.SerializeToString()
        out[f"shard {r} stored"] = metric(s.url("index-shard", r), "swarmrec_shard_stored_descriptors")
        out[f"shard {r} stored queries"] = metric(
            s.url("index-shard", r), "swarmrec_shard_partial_queries_total"
        )
        out[f"verifier {r} stored"] = metric(s.url("verifier", r), "swarmrec_verifier_stored_frames")
        out[f"descriptor {r} frames queried"] = metric(
            s.url("descriptor", r), "swarmrec_query_duration_seconds_count"
        )
    # Every record log, byte for byte (4-byte length + protobuf per record).
    logs = sorted(s.local.data_dir.rglob("*.log"))
    assert {p.name for p in logs} == {
        "index-shard.log",
        "verifier.log",
        "loop-closures.log",
        "pending-stores.log",  # the descriptors' stores waiting for a shard (none here)
        "outbox.log",  # the detectors' frames waiting for their descriptor
    }
    for path in logs:
        out[f"file {path.relative_to(s.local.data_dir)}"] = path.read_bytes()
    # The seeded frames are really there (the comparison is about something).
    assert out["shard 0 stored"] > 0 and out["shard 1 stored"] > 0
    assert out["verifier 0 stored"] >= SEEDED_STEPS and out["verifier 1 stored"] >= SEEDED_STEPS
    return out


def assert_unchanged(before: dict[str, Any], after: dict[str, Any]) -> None:
    """``after`` is ``before`` but for the one read-only probe snapshot() sent each shard."""
    for r in range(N_ROBOTS):
        after[f"shard {r} stored queries"] -= 1
    assert after == before


def rejected(url: str) -> dict[tuple[str, str], float]:
    """``swarmrec_rejected_requests_total`` of one service by (endpoint, code)."""
    return {
        (dict(labels)["endpoint"], dict(labels)["code"]): v
        for (name, labels), v in read_metrics(url).items()
        if name == "swarmrec_rejected_requests_total"
    }


def still_serves(s: Swarm) -> None:
    """Every service answers a valid request with no side effect."""
    for r in range(N_ROBOTS):
        # A step past the end of the replay answers "finished" and sends nothing.
        step = reply_of(
            request(s.session, s.key("detector", r, "step"), pb.StepRequest(step=10**6)), pb.StepReply
        )
        assert step.finished and step.robot_id == r
    # Shards, verifiers and descriptors answered valid requests in snapshot().


# --- the bad requests ---------------------------------------------------------


def garbage(cls: type[Message], size: int = 64) -> bytes:
    """Seeded random bytes that do not parse as ``cls`` (checked here, not assumed)."""
    rng = random.Random(f"{schema_name(cls)}-{size}")
    while True:
        data = rng.randbytes(size)
        try:
            cls.FromString(data)
        except DecodeError:
            return data


def partial(
    lo: int, hi: int, offsets: list[int], counts: list[int], *, n_ret: int = 0, **fields: int
) -> pb.PartialQuery:
    """A PartialQuery (to be stored) of labels ``[lo, hi)``; ``fields`` set descriptor fields."""
    desc = pb.PartialDescriptor(label_lo=lo, label_hi=hi, label_offsets=offsets, counts=counts, **fields)
    return pb.PartialQuery(descriptor=desc, n_ret=n_ret, read_only=False)


def verify(query: pb.Constellation, **fields: Any) -> pb.VerifyRequest:
    return pb.VerifyRequest(query=query, **fields)


def constellation(
    robot: int, labels: list[int] | None = None, *, frame: int = 3, n_coords: int | None = None
) -> pb.Constellation:
    """Robot ``robot``'s frame with ``labels`` (3 valid ones by default) at made-up positions."""
    labels = [0, 41, 56] if labels is None else labels
    n = 3 * len(labels) if n_coords is None else n_coords
    return pb.Constellation(robot_id=robot, frame_index=frame, labels=labels, positions_mm=list(range(n)))


def big(msg: Message) -> Message:
    assert msg.ByteSize() > LIMIT
    return msg


@dataclass(frozen=True)
class Case:
    kind: str
    robot: int
    endpoint: str
    payload: Callable[[], bytes]
    encoding: str | None  # schema in application/protobuf;<schema>; None: no encoding at all
    code: str
    #: Sent as a client: the key names no robot (a caller-bound endpoint refuses that).
    as_client: bool = False

    def send(self, s: Swarm) -> Answer:
        enc = protobuf(self.encoding) if self.encoding is not None else None
        payload = self.payload()
        key = s.key(self.kind, self.robot, self.endpoint)
        caller = None if self.as_client else self.sender(payload)
        return raw_request(s.session, key, payload, enc, caller=caller)

    def sender(self, payload: bytes) -> int:
        """The robot a caller-bound endpoint's key names: the one whose frame the request
        carries (a request for another robot would be refused before what is tested), else
        the served robot."""
        try:
            carried = carried_robot(REQUEST_OF[(self.kind, self.endpoint)].FromString(payload))
        except DecodeError:
            carried = None
        return self.robot if carried is None else carried


def msg_case(kind: str, robot: int, endpoint: str, make: Callable[[], Message], code: str) -> Case:
    """A message sent with its own schema in the encoding."""
    return Case(kind, robot, endpoint, lambda: make().SerializeToString(), schema_name(make()), code)


REQUEST_OF = {
    ("index-shard", "query"): pb.PartialQuery,
    ("index-shard", "lookup"): pb.PartialQuery,
    ("index-shard", "store"): pb.ShardStore,
    ("index-shard", "placement"): pb.PlacementRequest,
    ("index-shard", "adopt"): pb.AdoptRequest,
    ("index-shard", "transfer"): pb.TransferRequest,
    ("verifier", "store"): pb.Constellation,
    ("verifier", "verify"): pb.VerifyRequest,
    ("descriptor", "process"): pb.Constellation,
    ("descriptor", "loop_closures"): pb.LoopClosuresRequest,
    ("descriptor", "explain"): pb.ExplainRequest,
    ("detector", "step"): pb.StepRequest,
    ("detector", "replay"): pb.ReplayRequest,
    ("detector", "classify"): pb.ClassifyRequest,
}
# Every endpoint of every service a places robot runs, as the registry declares them.
assert {
    (kind, ep.name): ep.request for kind in WORKLOADS["places"] for ep in spec(kind).load().ENDPOINTS
} == REQUEST_OF
# A well-formed message of another endpoint, sent with its schema in the encoding.
WRONG_SCHEMA: dict[type[Message], Message] = {
    pb.PartialQuery: pb.VerifyRequest(query=constellation(1)),
    pb.ShardStore: pb.PartialQuery(descriptor=pb.PartialDescriptor(label_lo=40, label_hi=80)),
    # Not a StepRequest: its step=1 is, byte for byte, a PlacementRequest's known_version=1.
    pb.PlacementRequest: pb.LoopClosuresRequest(min_score=0.5),
    pb.AdoptRequest: pb.StepRequest(step=1),
    pb.TransferRequest: pb.LoopClosuresRequest(min_score=0.5),
    pb.Constellation: pb.PartialQuery(descriptor=pb.PartialDescriptor(label_lo=40, label_hi=80)),
    pb.VerifyRequest: pb.Constellation(robot_id=1, labels=[1], positions_mm=[1, 2, 3]),
    pb.LoopClosuresRequest: pb.StepRequest(step=1),
    # Field 1 as a float: a wire type ExplainRequest's frame_index does not have.
    pb.ExplainRequest: pb.LoopClosuresRequest(min_score=0.5),
    pb.StepRequest: pb.ReplayRequest(rate_hz=1.0),
    pb.ReplayRequest: pb.StepRequest(step=0),
    pb.ClassifyRequest: pb.StepRequest(step=0),
}

# The same bytes with no encoding (the runner has no schema to compare): they parse,
# mostly with fields the schema does not have (a field number or wire type of the other
# message: MALFORMED). A PartialQuery's descriptor parses as a Constellation's labels,
# but the frame has no robot (INVALID_ARGUMENT); a StepRequest(step=0) is a
# ClassifyRequest of round 0, which a replaying detector does not serve.
NO_ENCODING_CODE: dict[type[Message], str] = {
    pb.PartialQuery: "ERROR_CODE_MALFORMED",
    # Field 3 (a PartialQuery's descriptor), field 1 as a varint where a Placement is a
    # message, field 1 as a fixed32 where a version or a group is a varint: fields the
    # schemas do not have.
    pb.ShardStore: "ERROR_CODE_MALFORMED",
    pb.PlacementRequest: "ERROR_CODE_MALFORMED",
    pb.AdoptRequest: "ERROR_CODE_MALFORMED",
    pb.TransferRequest: "ERROR_CODE_MALFORMED",
    pb.Constellation: "ERROR_CODE_INVALID_ARGUMENT",
    pb.VerifyRequest: "ERROR_CODE_MALFORMED",
    pb.LoopClosuresRequest: "ERROR_CODE_MALFORMED",
    pb.ExplainRequest: "ERROR_CODE_MALFORMED",
    pb.StepRequest: "ERROR_CODE_MALFORMED",
    pb.ReplayRequest: "ERROR_CODE_MALFORMED",
    pb.ClassifyRequest: "ERROR_CODE_FAILED_PRECONDITION",
}

CASES: dict[str, Case] = {}
for (_kind, _ep), _cls in REQUEST_OF.items():
    _r = 1
    CASES[f"{_kind} {_r} {_ep}: random bytes"] = Case(
        _kind, _r, _ep, functools.partial(garbage, _cls), schema_name(_cls), "ERROR_CODE_MALFORMED"
    )
    CASES[f"{_kind} {_r} {_ep}: random bytes with no encoding"] = Case(
        _kind, _r, _ep, functools.partial(garbage, _cls, 97), None, "ERROR_CODE_MALFORMED"
    )
    _wrong = WRONG_SCHEMA[_cls]
    CASES[f"{_kind} {_r} {_ep}: a {type(_wrong).__name__} in its encoding"] = Case(
        _kind, _r, _ep, _wrong.SerializeToString, schema_name(_wrong),
        "ERROR_CODE_INVALID_ARGUMENT",
    )  # fmt: skip
    CASES[f"{_kind} {_r} {_ep}: a {type(_wrong).__name__}'s bytes with no encoding"] = Case(
        _kind, _r, _ep, _wrong.SerializeToString, None, NO_ENCODING_CODE[_cls]
    )
    CASES[f"{_kind} {_r} {_ep}: random bytes over the size limit"] = Case(
        _kind, _r, _ep, lambda: random.Random(7).randbytes(LIMIT + 1), schema_name(_cls),
        "ERROR_CODE_TOO_LARGE",
    )  # fmt: skip

INVALID, UNKNOWN, TOO_LARGE, PRECONDITION, EXISTS, MALFORMED = (
    "ERROR_CODE_INVALID_ARGUMENT",
    "ERROR_CODE_UNKNOWN_LABEL",
    "ERROR_CODE_TOO_LARGE",
    "ERROR_CODE_FAILED_PRECONDITION",
    "ERROR_CODE_ALREADY_EXISTS",
    "ERROR_CODE_MALFORMED",
)
MANY = [i % N_LABELS for i in range(301)]  # 301 objects, at most 4 of a label
STORED = 3  # a frame index every robot has stored (seeded steps 0-5)
F20 = MAX_FRAME_INDEX  # 2**20: the first frame index refused
# Well-formed messages that do not validate, by (service, robot, endpoint):
# (what is wrong, the message, the expected code). Shard 1 owns labels [40, 80),
# shard 0 [0, 40). An empty Constellation has no robot and no frame: refused by
# robot 0 too (it used to read as robot 0's frame 0 with nothing detected).
SPECIFIC: dict[tuple[str, int, str], list[tuple[str, Callable[[], Message], str]]] = {
    ("index-shard", 1, "query"): [
        ("empty payload (no descriptor)", lambda: pb.PartialQuery(), INVALID),
        ("a label range past the label list", lambda: partial(40, 90, [45], [1]), UNKNOWN),
        # A group another shard owns (placement version 0, one replica a group).
        ("the other shard's label range", lambda: partial(0, 40, [1], [1]), PRECONDITION),
        ("an empty label range", lambda: partial(40, 40, [], []), INVALID),
        ("a slice with no labels", lambda: partial(40, 80, [], []), INVALID),
        ("more labels than counts", lambda: partial(40, 80, [1, 2], [1]), INVALID),
        ("a zero count", lambda: partial(40, 80, [1], [0]), INVALID),
        ("a label listed twice", lambda: partial(40, 80, [1, 1], [1, 2]), INVALID),
        ("robot id >= n_robots", lambda: partial(40, 80, [1], [1], robot_id=N_ROBOTS), INVALID),
        ("frame index 2**20", lambda: partial(40, 80, [1], [1], frame_index=F20), INVALID),
        ("query step 2**20", lambda: partial(40, 80, [1], [1], query_step=F20), INVALID),
        ("a frame index far past the stored frames",
         lambda: partial(40, 80, [1], [1], frame_index=MAX_FRAME_GAP + 1000), INVALID),
        ("n_ret 257", lambda: partial(40, 80, [1], [1], n_ret=MAX_N_RET + 1), INVALID),
        ("101 objects of one label", lambda: partial(40, 80, [1], [101], frame_index=90), TOO_LARGE),
        ("301 objects", lambda: partial(40, 80, [1, 2, 3, 4], [100, 100, 100, 1], frame_index=90), TOO_LARGE),
        ("a well-formed query over the size limit",
         lambda: big(partial(40, 80, list(range(40)) * 60, [1] * 2400)), TOO_LARGE),
    ],
    ("index-shard", 1, "store"): [
        ("empty payload (no descriptor)", lambda: pb.ShardStore(), INVALID),
        ("a placement version the shard does not follow",
         lambda: pb.ShardStore(descriptor=partial(40, 80, [1], [1], frame_index=90).descriptor,
                               placement_version=7), PRECONDITION),
        ("a label group the shard does not hold",
         lambda: pb.ShardStore(descriptor=partial(0, 40, [1], [1], frame_index=90).descriptor), PRECONDITION),
        ("robot id >= n_robots",
         lambda: pb.ShardStore(descriptor=partial(40, 80, [1], [1], robot_id=N_ROBOTS).descriptor), INVALID),
    ],
    ("index-shard", 1, "adopt"): [
        ("empty payload (no placement)", lambda: pb.AdoptRequest(), INVALID),
    ],
    ("index-shard", 1, "transfer"): [
        ("a group the swarm does not have", lambda: pb.TransferRequest(group=5), INVALID),
        ("a start row past 2**40", lambda: pb.TransferRequest(group=1, start_row=2**40), INVALID),
        ("a group the shard does not own", lambda: pb.TransferRequest(group=0), PRECONDITION),
    ],
    ("index-shard", 0, "query"): [
        ("a label outside the slice's range", lambda: partial(0, 40, [45], [1]), INVALID),
    ],
    ("verifier", 0, "store"): [
        ("empty payload (no robot, no frame)", lambda: pb.Constellation(), INVALID),
        ("robot 0's frame 0 with nothing detected and no frame index",
         lambda: pb.Constellation(robot_id=0), INVALID),
    ],
    ("verifier", 1, "store"): [
        ("empty payload (no robot, no frame)", lambda: pb.Constellation(), INVALID),
        ("a stored frame index with other objects", lambda: constellation(1, frame=STORED), EXISTS),
        ("a stored frame index with nothing detected", lambda: constellation(1, [], frame=STORED), EXISTS),
        ("301 objects", lambda: constellation(1, MANY, frame=90), TOO_LARGE),
        ("101 objects of one label", lambda: constellation(1, [5] * 101, frame=90), TOO_LARGE),
        ("label index 80 of 80", lambda: constellation(1, [1, 80, 2]), UNKNOWN),
        ("7 coordinates for 3 labels", lambda: constellation(1, n_coords=7), INVALID),
        ("robot id >= n_robots", lambda: constellation(N_ROBOTS), INVALID),
        ("frame index 2**20", lambda: constellation(1, frame=F20), INVALID),
        ("a well-formed frame over the size limit", lambda: big(constellation(1, [9] * 999)), TOO_LARGE),
    ],
    ("verifier", 1, "verify"): [
        ("empty payload (no query)", lambda: pb.VerifyRequest(), INVALID),
        ("a query of 301 objects", lambda: verify(constellation(0, MANY)), TOO_LARGE),
        ("1025 candidate frames",
         lambda: verify(constellation(0), candidate_frame_indices=range(1025)), TOO_LARGE),
        (f"more than {PAIRS_LIMIT} object pairs to compare (100 objects x 58)",
         lambda: verify(constellation(0, MANY[:100]), candidate_frame_indices=range(6)), TOO_LARGE),
        ("a query label index 80 of 80", lambda: verify(constellation(0, [80, 1, 2])), UNKNOWN),
        ("2 coordinates for 3 labels", lambda: verify(constellation(0, n_coords=2)), INVALID),
        ("query robot id >= n_robots", lambda: verify(constellation(N_ROBOTS)), INVALID),
        ("query frame index 2**20", lambda: verify(constellation(0, frame=F20)), INVALID),
        ("NaN distance threshold", lambda: verify(constellation(0), distance_threshold_m=math.nan), INVALID),
        ("negative distance threshold", lambda: verify(constellation(0), distance_threshold_m=-1), INVALID),
        ("a well-formed request over the size limit",
         lambda: big(verify(constellation(0), candidate_frame_indices=range(3000))), TOO_LARGE),
    ],
    ("descriptor", 0, "process"): [
        ("empty payload (no robot, no frame)", lambda: pb.Constellation(), INVALID),
    ],
    ("descriptor", 1, "process"): [
        ("empty payload (no robot, no frame)", lambda: pb.Constellation(), INVALID),
        ("a processed frame index with other objects", lambda: constellation(1, frame=STORED), EXISTS),
        ("301 objects", lambda: constellation(1, MANY, frame=90), TOO_LARGE),
        ("label index 80 of 80", lambda: constellation(1, [80, 1, 2]), UNKNOWN),
        ("10 coordinates for 3 labels", lambda: constellation(1, n_coords=10), INVALID),
        ("robot id >= n_robots", lambda: constellation(N_ROBOTS), INVALID),
        ("frame index 2**20", lambda: constellation(1, frame=F20), INVALID),
        ("a well-formed frame over the size limit", lambda: big(constellation(1, [9] * 999)), TOO_LARGE),
    ],
    ("descriptor", 1, "loop_closures"): [
        ("NaN min score", lambda: pb.LoopClosuresRequest(min_score=math.nan), INVALID),
        ("infinite min score (nothing could reach it)",
         lambda: pb.LoopClosuresRequest(min_score=math.inf), INVALID),
        ("-inf min score", lambda: pb.LoopClosuresRequest(min_score=-math.inf), INVALID),
    ],
    ("descriptor", 1, "explain"): [
        ("empty payload (no frame index)", lambda: pb.ExplainRequest(), INVALID),
        ("frame index 2**20", lambda: pb.ExplainRequest(frame_index=F20), INVALID),
    ],
    ("detector", 1, "step"): [
        ("empty payload (no step)", lambda: pb.StepRequest(), INVALID),
    ],
    ("detector", 1, "classify"): [
        ("a view to a detector that replays constellations",
         lambda: pb.ClassifyRequest(round_id=1, image=b"\x89PNG"), PRECONDITION),
    ],
    ("detector", 1, "replay"): [
        ("empty payload (no rate; it used to start a replay)", lambda: pb.ReplayRequest(), INVALID),
        ("NaN rate", lambda: pb.ReplayRequest(rate_hz=math.nan), INVALID),
        ("infinite rate", lambda: pb.ReplayRequest(rate_hz=math.inf), INVALID),
        ("negative rate", lambda: pb.ReplayRequest(rate_hz=-1.0), INVALID),
    ],
}  # fmt: skip
for (_kind, _r, _ep), _cases in SPECIFIC.items():
    for _what, _make, _code in _cases:
        CASES[f"{_kind} {_r} {_ep}: {_what}"] = msg_case(_kind, _r, _ep, _make, _code)
# A placement from a client: a caller-bound endpoint's key must name the sending robot.
_client_placement = pb.AdoptRequest(placement=pb.Placement(
    version=9, group_bounds=[0, 40, 80], members=[1], replicas=1,
    groups=[pb.GroupOwners(owners=[1]), pb.GroupOwners(owners=[1])]))  # fmt: skip
CASES["index-shard 1 adopt: a placement from a client, not from the coordinator"] = Case(
    "index-shard", 1, "adopt", _client_placement.SerializeToString, schema_name(_client_placement),
    "ERROR_CODE_PERMISSION_DENIED", as_client=True,
)  # fmt: skip

# Every queryable of every robot service kind is covered (info is read-only and takes no payload).
assert {(c.kind, c.endpoint) for c in CASES.values()} == set(REQUEST_OF)


@pytest.mark.parametrize("name", list(CASES))
def test_a_bad_request_gets_its_error_code_is_counted_and_changes_nothing(swarm: Swarm, name: str) -> None:
    case = CASES[name]
    url = swarm.url(case.kind, case.robot)
    before, counted_before = snapshot(swarm), rejected(url)

    answer = case.send(swarm)

    assert answer.error is not None, f"{name}: answered with a {answer.schema}, not an ErrorReply"
    assert answer.code == case.code, f"{name}: {answer.code}: {answer.error.message}"
    assert answer.error.message  # says why
    counted = rejected(url)
    key = (case.endpoint, case.code)
    assert counted.get(key, 0) == counted_before.get(key, 0) + 1
    assert sum(counted.values()) == sum(counted_before.values()) + 1
    assert_unchanged(before, snapshot(swarm))
    still_serves(swarm)


#: Counters a valid request moves, which a store-by-store comparison leaves out.
# What a valid request moves without storing anything: counters, and the descriptor's
# memory of the reports it made (explain: a frame processed again is its newest report).
COUNTERS = ("stored queries", "frames queried", "explain")


def stores(snap: dict[str, Any]) -> dict[str, Any]:
    """What a snapshot says of the stores alone (answers, gauges, record logs)."""
    return {k: v for k, v in snap.items() if not k.endswith(COUNTERS)}


def test_storing_a_stored_frame_again_with_the_same_content_is_answered_as_before_and_changes_nothing(
    swarm: Swarm,
) -> None:
    frame = swarm.frames[1]  # robot 1's frame PROBE_STEP, exactly as its detector sent it
    before = snapshot(swarm)
    counted = {kind: rejected(swarm.url(kind, 1)) for kind in ("verifier", "index-shard", "descriptor")}

    stored = reply_of(request(swarm.session, swarm.key("verifier", 1, "store"), frame), pb.StoreReply)
    assert stored.stored_frames == before["verifier 1 stored"]
    desc = semantic_descriptor(constellation_from_proto(frame, N_LABELS), N_LABELS)
    for k in range(N_ROBOTS):
        lo, hi = BOUNDS[k], BOUNDS[k + 1]
        if desc[lo:hi].any():
            again = pb.PartialQuery(
                read_only=False,
                descriptor=partial_descriptor_to_proto(desc, lo, hi, robot=1, frame=PROBE_STEP, query_step=0),
            )
            reply_of(request(swarm.session, swarm.key("index-shard", k, "query"), again), pb.CandidatesReply)
    # The whole frame again through its descriptor: stored nowhere twice, no second closure.
    report = reply_of(request(swarm.session, swarm.key("descriptor", 1, "process"), frame), pb.QueryReport)
    assert report.frame_index == PROBE_STEP and not report.failed_shard_robot_ids

    assert stores(snapshot(swarm)) == stores(before)
    assert {kind: rejected(swarm.url(kind, 1)) for kind in counted} == counted


def test_a_shard_refuses_another_slice_for_a_stored_frame_and_changes_nothing(swarm: Swarm) -> None:
    full = reply_of(
        request(swarm.session, swarm.key("index-shard", 1, "query"), _full_range_query(1)), pb.CandidatesReply
    )
    robot, frame = full.robot_ids[0], full.frame_indices[0]  # a frame shard 1 holds
    other = partial(40, 80, [39], [7], robot_id=robot, frame_index=frame)  # 7 of label 79: no real frame's
    url = swarm.url("index-shard", 1)
    before, counted_before = snapshot(swarm), rejected(url)

    answer = request(swarm.session, swarm.key("index-shard", 1, "query"), other)

    assert answer.code == EXISTS, answer
    assert f"frame {frame} of robot {robot} is already stored" in answer.error.message
    counted = rejected(url)
    assert counted.get(("query", EXISTS), 0) == counted_before.get(("query", EXISTS), 0) + 1
    assert sum(counted.values()) == sum(counted_before.values()) + 1
    assert_unchanged(before, snapshot(swarm))
    still_serves(swarm)


def test_a_step_past_the_end_of_the_replay_answers_finished_and_stores_nothing(swarm: Swarm) -> None:
    before = snapshot(swarm)
    for step in (200, MAX_FRAME_INDEX, 2**32 - 1):
        reply = reply_of(
            request(swarm.session, swarm.key("detector", 0, "step"), pb.StepRequest(step=step)), pb.StepReply
        )
        assert reply.finished and reply.step == step and not reply.HasField("report")
    assert_unchanged(before, snapshot(swarm))


def test_a_flood_of_refused_requests_is_counted_in_full_and_logged_at_a_bounded_rate(swarm: Swarm) -> None:
    # 1,500 refusals were 0.45 MB of warnings; the counter has them all, the log a few.
    url, sp = swarm.url("verifier", 1), swarm.local.find("verifier", 1)
    before = rejected(url).get(("verify", MALFORMED), 0)
    lines_before = sp.log_path.read_text().count("rejected request")
    for _ in range(1500):
        garbage = raw_request(
            swarm.session,
            swarm.key("verifier", 1, "verify"),
            b"\xff" * 8,
            protobuf("swarmrec.v1.VerifyRequest"),
        )
        assert garbage.code == MALFORMED, garbage
    assert rejected(url).get(("verify", MALFORMED), 0) == before + 1500
    logged = sp.log_path.read_text().count("rejected request") - lines_before
    # At most a window's budget, or two if a window turned during the flood (none at all if
    # the requests before this one had spent the window's).
    assert logged <= 2 * WARNING_BURST, logged


def test_after_all_the_bad_input_the_swarm_still_runs_a_lock_step_step(swarm: Swarm) -> None:
    # Last of the module's swarm tests: it stores a frame, so the state the others compare moves on.
    stored_before = {
        r: metric(swarm.url("verifier", r), "swarmrec_verifier_stored_frames") for r in range(N_ROBOTS)
    }
    replies = swarm.client.step(SEEDED_STEPS, timeout_s=10)
    steps = [r for r in replies if isinstance(r, pb.StepReply)]
    assert sorted(r.robot_id for r in steps) == [0, 1], replies
    for reply in steps:
        assert not reply.finished and reply.report.frame_index == SEEDED_STEPS
        assert not reply.report.failed_shard_robot_ids and not reply.report.failed_verifier_robot_ids
    for r in range(N_ROBOTS):
        assert metric(swarm.url("verifier", r), "swarmrec_verifier_stored_frames") == stored_before[r] + 1
    # Every rejection was logged as a warning, none as an internal error.
    for sp in swarm.local.procs:
        log = sp.log_path.read_text()
        assert sp.robot == 0 or "rejected request" in log, sp.name
        assert '"level": "ERROR"' not in log, f"{sp.name} logged an error:\n{sp.tail()}"


# --- a dataset with a non-finite coordinate ------------------------------------


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_a_detector_refuses_a_dataset_with_a_non_finite_coordinate_and_exits_with_a_clear_error(
    tmp_path: Path, request: pytest.FixtureRequest, bad: str
) -> None:
    folder = tmp_path / "dataset"
    folder.mkdir()
    (folder / "1.000.txt").write_text("cup 0.1 0.2 1.5\nchair 1 2 3\nbook 0 0 1\n")
    (folder / "2.000.txt").write_text(f"cup 0.1 0.2 1.5\nchair 1 {bad} 3\n")
    name = swarm_name(request)
    with running_swarm(tmp_path, name, DetectorSettings(dataset=str(folder)), start=False) as local:
        (detector,) = local.start_robot(0, kinds=["detector"])
        with pytest.raises(SwarmStartError, match="exited with code 2 before it was ready"):
            local.wait_started([detector], 60)

    assert detector.proc.wait(timeout=10) == 2
    log = detector.log_path.read_text()
    assert f"2.000.txt:2: non-finite coordinate in 'chair 1 {bad} 3'" in log
    assert "swarmrec serve: error:" in log and "Traceback" not in log
    assert not detector.ready.is_set()
