"""Five fusion services on a line graph 0-1-2-3-4, over a real router, as real processes.

Each robot gets known class probabilities and a yaw and hears only its line
neighbours. The robots are started last-first, so every robot but the last gets
messages of the round before it starts it (kept and processed at the start).
Before the round, bad messages are put on three robots' inboxes: bytes that do not
decode, a payload of another schema, a sender that lies about who it is, a vector
with a NaN from a neighbour, a good-looking message from a robot out of range (both
signed by their robot: faulty, not forged), and relays of robot 1's output made up
by robot 4: unsigned, signed with robot 4's own key, and signed by robot 1 for other
probabilities than those it carries (the statement signed is built here by hand).

Checked: each robot folds in the 4 others (waited for on the published events), at
exactly ``|i - j|`` hops, each first delivered by one of its neighbours; its
posterior equals what swarmrec.fusion's FusionState computes from the same vectors
in the order the robot recorded (so the service's wiring is checked against the
core, not against itself); every duplicate a broadcast flood must produce on a line
is counted; each robot sends each of the 5 outputs once to each neighbour; the bad
messages are counted by reason and the round still completes.
"""

from __future__ import annotations

import math
import queue
import struct
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
import zenoh
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec

from swarmrec.client import ZenohClient
from swarmrec.deployments.local import LocalDeployment
from swarmrec.fusion import FusionState, make_weight_law
from swarmrec.runtime import keys
from swarmrec.runtime.tls import TlsFiles
from swarmrec.security.identity import Identity
from swarmrec.security.pki import ensure_identity
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import schema_name
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import (
    endpoint_key,
    metric,
    metrics_url,
    protobuf,
    reply_of,
    request,
    wait_until,
)

N = 5
N_CLASSES = 19
ROUND = 3
LAW = "agreement"  # its weight depends on the posterior, so the order of messages matters
LINE = [[j for j in (i - 1, i + 1) if 0 <= j < N] for i in range(N)]
RNG = np.random.default_rng(11)
# float32 as on the wire, so the core below sees exactly what the services see.
PROBS = RNG.dirichlet(np.full(N_CLASSES, 0.3), size=N).astype(np.float32)
YAWS = RNG.uniform(-math.pi, math.pi, N).astype(np.float32)
CLASSIFIER = schema_name(pb.ClassifierOutput)


@pytest.fixture
def fusion_swarm(
    request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[LocalDeployment]:
    """A router and one fusion service per robot; the weight law comes from the
    environment, as a robot's would."""
    monkeypatch.setenv("SWARMREC_FUSION_LAW", LAW)
    with running_swarm(tmp_path, swarm_name(request), robots=N, kinds=["fusion"], timeout_s=60.0) as swarm:
        yield swarm


def speaking_as(swarm: LocalDeployment, kind: str, robot: int) -> ZenohClient:
    """A session with robot ``robot``'s ``kind`` certificate (issued by the swarm's CA if the
    deployment did not): under mutual TLS only a robot's fusion may put on another robot's
    inbox, and only its detector may start its round."""
    assert swarm.pki_dir is not None
    ident = Identity.service(swarm.spec_swarm, kind, robot)
    ensure_identity(swarm.pki_dir, ident)
    tls = TlsFiles.in_dir(swarm.pki_dir, ident.common_name)
    return ZenohClient([swarm.endpoint], swarm.spec_swarm, timeout_s=5.0, tls=tls)


def put(
    session: zenoh.Session,
    swarm: str,
    robot: int,
    payload: bytes,
    schema: str,
    *,
    key_sender: int,
    attachment: int | None = None,
) -> None:
    """A raw put on a robot's inbox (``inbox/<key_sender>``), as a faulty or lying robot
    would send it."""
    session.put(
        keys.endpoint(swarm, "fusion", robot, f"inbox/{key_sender}"),
        payload,
        encoding=protobuf(schema),
        attachment=None if attachment is None else str(attachment).encode(),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def output(origin: int, sender: int, hops: int, probs: list[float], signature: bytes = b"") -> bytes:
    msg = pb.ClassifierOutput(
        origin_robot_id=origin,
        round_id=ROUND,
        probabilities=probs,
        yaw_rad=0.0,
        hop_count=hops,
        sender_robot_id=sender,
        origin_signature=signature,
    )
    return bytes(msg.SerializeToString())


def signature(swarm: LocalDeployment, key_robot: int, origin: int, probs: list[float]) -> bytes:
    """Robot ``key_robot``'s fusion key's ECDSA signature of what ``origin`` says in round
    ROUND with yaw 0: the documented statement (docs/fusion.md), laid out here by hand."""
    assert swarm.pki_dir is not None
    name = Identity.service(swarm.spec_swarm, "fusion", key_robot).common_name
    key = serialization.load_pem_private_key((swarm.pki_dir / f"{name}.key").read_bytes(), password=None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    statement = (
        b"swarmrec.v1.ClassifierOutput.origin\x00"
        + swarm.spec_swarm.encode()
        + b"\x00"
        + struct.pack("<III", origin, ROUND, len(probs))
        + struct.pack(f"<{len(probs)}f", *probs)
        + struct.pack("<f", 0.0)
    )
    return key.sign(statement, ec.ECDSA(hashes.SHA256()))


def rejected(url: str, reason: str) -> float:
    return metric(url, "swarmrec_fusion_rejected_total", reason=reason)


def refused(url: str, code: str) -> float:
    """Inbox messages the runner refused before the robot saw them (bytes, schema, size)."""
    return metric(url, "swarmrec_rejected_requests_total", endpoint="inbox/*", code=code)


def test_five_robots_on_a_line_flood_to_neighbours_only_and_fuse_as_the_core_does(
    fusion_swarm: LocalDeployment,
) -> None:
    t0 = time.monotonic()
    swarm = fusion_swarm.spec_swarm
    urls = [metrics_url(fusion_swarm.find("fusion", r)) for r in range(N)]
    events: queue.Queue[pb.FusionUpdate] = queue.Queue()
    with ExitStack() as stack:
        client = stack.enter_context(fusion_swarm.client(5.0))
        robot4 = stack.enter_context(speaking_as(fusion_swarm, "fusion", 4))
        robot1, robot3 = (stack.enter_context(speaking_as(fusion_swarm, "fusion", r)) for r in (1, 3))
        detectors = [stack.enter_context(speaking_as(fusion_swarm, "detector", r)) for r in range(N)]
        session = client.session
        # The bad messages come from robot 4's fusion: a faulty or lying robot of the swarm.
        radio = robot4.session
        # The token is declared after the inbox subscriber: once the router shows it,
        # puts to that inbox are routed.
        client.wait_for({("fusion", r) for r in range(N)})
        sub = session.declare_subscriber(
            keys.event(swarm, "fusion", "*"),
            lambda s: events.put(pb.FusionUpdate.FromString(s.payload.to_bytes())),
        )
        try:
            # --- bad messages, before any round starts ---------------------------------
            good = [float(p) for p in PROBS[1]]
            put(radio, swarm, 2, b"\x1a\x05\x00", CLASSIFIER, key_sender=4)  # truncated: does not decode
            put(radio, swarm, 2, output(1, 1, 0, good), schema_name(pb.FusionUpdate), key_sender=4)
            # Robot 4 claims to be robot 1: in the body, in the attachment (refused by robot 2),
            # and in the key (dropped by the router: robot 4's certificate names robot 4 only).
            put(radio, swarm, 2, output(1, 1, 0, good), CLASSIFIER, key_sender=4)
            put(radio, swarm, 2, output(4, 4, 0, good), CLASSIFIER, key_sender=4, attachment=1)
            put(radio, swarm, 2, output(1, 1, 0, good), CLASSIFIER, key_sender=1)
            nans = [math.nan] * N_CLASSES
            nan = output(1, 1, 0, nans, signature(fusion_swarm, 1, 1, nans))
            put(robot1.session, swarm, 0, nan, CLASSIFIER, key_sender=1)  # from a neighbour
            far = output(3, 3, 0, good, signature(fusion_swarm, 3, 3, good))
            put(robot3.session, swarm, 0, far, CLASSIFIER, key_sender=3)  # out of range
            # Robot 4 relays an output of robot 1's it made up, to its neighbour robot 3.
            other = [float(p) for p in PROBS[4]]
            for forged in (
                output(1, 4, 1, good),  # unsigned
                output(1, 4, 1, good, signature(fusion_swarm, 4, 1, good)),  # robot 4's key
                output(1, 4, 1, good, signature(fusion_swarm, 1, 1, other)),  # robot 1's, other values
            ):
                put(radio, swarm, 3, forged, CLASSIFIER, key_sender=4)

            def bad_counts() -> tuple[float, ...]:
                return (
                    refused(urls[2], "ERROR_CODE_MALFORMED"),
                    refused(urls[2], "ERROR_CODE_INVALID_ARGUMENT"),  # another message's schema
                    rejected(urls[2], "sender_mismatch"),
                    metric(urls[2], "swarmrec_fusion_early_messages_total"),  # the one the router dropped
                    metric(urls[0], "swarmrec_fusion_early_messages_total"),
                    rejected(urls[3], "unsigned"),
                    rejected(urls[3], "bad_signature"),
                    metric(urls[3], "swarmrec_fusion_early_messages_total"),
                )

            try:
                wait_until(lambda: bad_counts() == (1, 1, 2, 0, 2, 1, 2, 0), 10.0, "bad messages counted")
            except AssertionError as e:
                raise AssertionError(
                    f"{e}: (malformed, schema, sender_mismatch, early at 2, early at 0, unsigned at 3, "
                    f"bad signature at 3, early at 3) = {bad_counts()}"
                ) from None

            # --- the round, last robot first ---------------------------------------------
            for i in reversed(range(N)):
                start = pb.FusionRoundStart(
                    round_id=ROUND,
                    probabilities=[float(p) for p in PROBS[i]],
                    yaw_rad=float(YAWS[i]),
                    neighbour_robot_ids=LINE[i],
                )
                started = reply_of(
                    request(
                        detectors[i].session, endpoint_key(fusion_swarm, "fusion", i, "start_round"), start
                    ),
                    pb.FusionRoundStarted,
                )
                assert (started.robot_id, started.round_id, started.sent) == (i, ROUND, len(LINE[i]))
                if i == N - 1:
                    assert started.early_messages == 0  # nobody had started before it
                if i == 0:
                    assert started.early_messages >= 2  # the two bad ones, at least

            seen: dict[int, list[pb.FusionUpdate]] = {r: [] for r in range(N)}
            deadline = time.monotonic() + 15.0
            while any(len(seen[r]) < N - 1 for r in range(N)):
                ev = events.get(timeout=max(deadline - time.monotonic(), 0.01))
                seen[ev.robot_id].append(ev)
        finally:
            sub.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub

        law = make_weight_law(LAW)
        for i in range(N):
            key = endpoint_key(fusion_swarm, "fusion", i, "posterior")
            expected_duplicates = N * len(LINE[i]) - (N - 1)

            def settled(key: str = key, expected: int = expected_duplicates) -> pb.FusionPosterior | None:
                # Copies of heard origins may still arrive after the 4th new one.
                post = reply_of(request(session, key, pb.PosteriorRequest()), pb.FusionPosterior)
                return post if post.duplicates == expected else None

            post = wait_until(settled, 10.0, f"robot {i}'s duplicates counted")
            history = list(post.history)
            assert (post.robot_id, post.round_id, post.incorporated, post.heard_all) == (
                i,
                ROUND,
                N - 1,
                True,
            )
            assert list(post.neighbour_robot_ids) == LINE[i]
            assert {s.origin_robot_id: s.hops for s in history} == {j: abs(i - j) for j in range(N) if j != i}
            assert all(s.sender_robot_id in LINE[i] for s in history), history

            # The core, fed the same float32 vectors and yaws in the recorded order.
            core = FusionState(PROBS[i].astype(np.float64), float(YAWS[i]), law, own_id=i)
            for s in history:
                step = core.incorporate(
                    s.origin_robot_id,
                    PROBS[s.origin_robot_id].astype(np.float64),
                    s.hops,
                    float(YAWS[s.origin_robot_id]),
                )
                assert step is not None and step.weight == s.weight
                assert s.decision_after == int(np.argmax(step.posterior))
            assert np.array_equal(core.posterior, np.array(post.posterior))
            assert post.decision == core.decision

            # The events said the same, in the same order.
            assert [e.step.origin_robot_id for e in seen[i]] == [s.origin_robot_id for s in history]
            assert [e.incorporated for e in seen[i]] == list(range(1, N))
            assert np.array_equal(np.array(seen[i][-1].posterior), core.posterior)

            # Metrics: each output goes once to each neighbour, robot to robot.
            url = urls[i]
            assert metric(url, "swarmrec_fusion_incorporated_total") == N - 1
            assert metric(url, "swarmrec_fusion_duplicates_total") == expected_duplicates
            sent = metric(url, "swarmrec_messages_sent_total", message="ClassifierOutput", scope="swarm")
            got = metric(url, "swarmrec_messages_received_total", message="ClassifierOutput", scope="swarm")
            assert sent == N * len(LINE[i])
            # Robot 2 also got the put whose attachment said robot 4 (radio traffic, though refused;
            # the puts without an attachment, robot 4's made-up relays among them, are not counted
            # as from a robot).
            assert got == N * len(LINE[i]) + (i == 2)
            assert (
                metric(url, "swarmrec_message_bytes_sent_total", message="ClassifierOutput", scope="swarm")
                > 0
            )

        # The bad messages: counted by reason, and the rounds completed regardless.
        assert rejected(urls[0], "not_finite") == 1
        assert rejected(urls[0], "not_neighbour") == 1
        assert (
            reply_of(
                request(session, endpoint_key(fusion_swarm, "fusion", 0, "posterior"), pb.PosteriorRequest()),
                pb.FusionPosterior,
            ).rejected
            == 2
        )
        assert refused(urls[2], "ERROR_CODE_MALFORMED") == 1
        # Robot 4's made-up relays: refused at robot 3 before its robot saw them.
        assert rejected(urls[3], "unsigned") == 1 and rejected(urls[3], "bad_signature") == 2
        assert metric(urls[3], "swarmrec_fusion_rejected_total") == 3
        for i in (1, 3, 4):
            if i != 3:
                assert metric(urls[i], "swarmrec_fusion_rejected_total") == 0
            assert metric(urls[i], "swarmrec_rejected_requests_total") == 0

        # A round that was never started here is reported as NOT_FOUND, not as an empty posterior.
        missing = request(
            session,
            endpoint_key(fusion_swarm, "fusion", 0, "posterior"),
            pb.PosteriorRequest(round_id=ROUND + 1),
        )
        assert missing.code == "ERROR_CODE_NOT_FOUND"
    # SIGTERM: subscriber undeclared, inbox worker drained, session closed, exit 0.
    codes = fusion_swarm.stop()
    assert all(code == 0 for code in codes.values()), codes
    assert time.monotonic() - t0 < 30.0
