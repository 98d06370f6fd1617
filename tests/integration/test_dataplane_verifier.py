"""The compiled verifier (dataplane/, ``data_plane = compiled``) against the reference.

Real processes over a real router: the verifier runs as ``swarmrec-dataplane`` started by
``swarmrec serve``/``swarmrec host``, and every answer is compared with the Python core
(:func:`swarmrec.core.verification.verify`, the reference the offline evaluation and the
published scripts agree with):

* random frames built to tie (few labels, positions on a coarse grid, so surroundings
  distances repeat and nearest-vector ties are common) give the same matches, counts,
  object pairs and order, with and without candidate lists, distance thresholds and
  max_matches, queries ranked before and after the verifier's robot (which decides the
  association's argument order);
* a record log written by one implementation is served identically by the other after a
  restart, both ways (the log format is shared);
* a ``swarmrec host`` mixing Python kinds and compiled ones lists both in its readiness
  line and serves both.

The lock-step whole-swarm runs with the compiled verifier are in
test_swarm_matches_offline.py; the bad-input suite runs against it in test_bad_input.py.
"""

from __future__ import annotations

import random
from contextlib import AbstractContextManager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh

from swarmrec.core.presets import get_preset
from swarmrec.core.verification import verify
from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.settings import PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import answering, endpoint_key, metric, metrics_url, reply_of
from tests.integration.support import request as ask

N_ROBOTS, N_LABELS, OWN = 2, 80, 1


def random_frame(rng: random.Random, robot: int, frame: int) -> pb.Constellation:
    """0-12 objects of 6 labels on a 0.5 m grid (positions in mm): ties everywhere."""
    n = rng.randint(0, 12)
    labels = [rng.randrange(6) for _ in range(n)]
    mm = [rng.randrange(-4, 5) * 500 for _ in range(3 * n)]
    return pb.Constellation(robot_id=robot, frame_index=frame, labels=labels, positions_mm=mm)


def expected(
    req: pb.VerifyRequest, stored: dict[int, pb.Constellation], own: int
) -> list[tuple[int, int, int, int, tuple[int, ...]]]:
    """The reference's answer: the Python core's verify, as the Python verifier cuts it."""
    preset = get_preset("paper")
    if req.HasField("distance_threshold_m"):
        preset = preset.with_(d=float(req.distance_threshold_m))
    if req.candidate_frame_indices:
        wanted = sorted(set(req.candidate_frame_indices) & set(stored))
    else:
        wanted = [f for f, c in stored.items() if len(c.labels) >= preset.min_common]
    frames = [(f, constellation_from_proto(stored[f], N_LABELS)) for f in wanted]
    query = constellation_from_proto(req.query, N_LABELS)
    key = (req.query.robot_id, req.query.frame_index)
    found = [m for m in verify(query, key, own, frames, N_LABELS, preset) if m.score > 0]
    if req.max_matches:
        found = found[: req.max_matches]
    return [
        (m.frame, m.pairs.shape[0], m.n_common, m.n_union, tuple(np.asarray(m.pairs).ravel().tolist()))
        for m in found
    ]


def got(reply: pb.VerifyReply) -> list[tuple[int, int, int, int, tuple[int, ...]]]:
    return [(m.frame_index, m.n_matched, m.n_common, m.n_union, tuple(m.object_pairs)) for m in reply.matches]


def verifiers(tmp: Path, name: str, **bus: object) -> AbstractContextManager[LocalDeployment]:
    """Two robots' verifiers alone (plaintext: the test stores and asks as anyone)."""
    return running_swarm(
        tmp,
        name,
        PlaceSettings(n_labels=N_LABELS),
        robots=N_ROBOTS,
        kinds=("verifier",),
        swarm_kinds=(),
        security="insecure",
        **bus,
    )


def test_the_compiled_verifier_answers_random_frames_as_the_python_reference(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    rng = random.Random(20261127)
    with (
        verifiers(tmp_path, swarm_name(request), data_plane="compiled") as swarm,
        swarm.client(5.0) as client,
    ):
        assert swarm.find("verifier", OWN).info.get("dispatch") == "compiled"
        session = client.session
        key = endpoint_key(swarm, "verifier", OWN, "verify")
        stored: dict[int, pb.Constellation] = {}
        for f in range(120):
            frame = random_frame(rng, OWN, f)
            reply = reply_of(
                ask(session, endpoint_key(swarm, "verifier", OWN, "store"), frame), pb.StoreReply
            )
            stored[f] = frame
            assert reply.stored_frames == len(stored)
        checked = with_matches = 0
        for _ in range(300):
            # Queries from robot 0 (ranked before every stored frame) and robot 1 (before some).
            query = random_frame(rng, rng.randrange(N_ROBOTS), rng.randrange(150))
            req = pb.VerifyRequest(query_id=rng.randrange(1 << 32), query=query, include_pairs=True)
            if rng.random() < 0.7:
                req.candidate_frame_indices.extend(rng.randrange(130) for _ in range(rng.randint(1, 12)))
            if rng.random() < 0.3:
                req.distance_threshold_m = rng.choice([0.1, 0.25, 0.7, 3.0])
            if rng.random() < 0.3:
                req.max_matches = rng.randint(1, 3)
            reply = reply_of(ask(session, key, req), pb.VerifyReply)
            assert (reply.query_id, reply.robot_id) == (req.query_id, OWN)
            want = expected(req, stored, OWN)
            assert got(reply) == want, req
            checked += 1
            with_matches += bool(want)
        assert checked == 300 and with_matches > 50  # the comparison is about something


@pytest.mark.parametrize(("first", "then"), [("python", "compiled"), ("compiled", "python")])
def test_a_record_log_written_by_one_implementation_is_served_identically_by_the_other(
    tmp_path: Path, request: pytest.FixtureRequest, first: str, then: str
) -> None:
    rng = random.Random(7)
    frames = [random_frame(rng, OWN, f) for f in range(60)]
    probes = [pb.VerifyRequest(query=random_frame(rng, 0, 200 + i), include_pairs=True) for i in range(40)]
    with verifiers(tmp_path, swarm_name(request), data_plane=first) as swarm, swarm.client(5.0) as client:
        session = client.session
        verify_key = endpoint_key(swarm, "verifier", OWN, "verify")
        for frame in frames:
            reply_of(ask(session, endpoint_key(swarm, "verifier", OWN, "store"), frame), pb.StoreReply)
        before = [reply_of(ask(session, verify_key, p), pb.VerifyReply).SerializeToString() for p in probes]
        assert any(pb.VerifyReply.FromString(b).matches for b in before)
        sp = swarm.find("verifier", OWN)
        assert sp.info.get("dispatch") == ("compiled" if first == "compiled" else "channel")
        assert swarm.stop_process(sp) == 0  # a clean exit
        # The same robot, data dir and settings, the other implementation.
        spec = swarm._spec()
        swarm.spec = replace(spec, bus=spec.bus.with_(data_plane=then))
        procs = swarm.start_robot(OWN, kinds=("verifier",))
        swarm.wait_started(procs, 60)
        assert swarm.find("verifier", OWN).info.get("dispatch") == (
            "compiled" if then == "compiled" else "channel"
        )
        after = [answering(session, verify_key, p).ok for p in probes]
        assert after == before
        url = metrics_url(swarm.find("verifier", OWN))
        assert metric(url, "swarmrec_verifier_stored_frames") == len(frames)
        # A frame stored again is accepted as before, another one at a stored index is not.
        again = ask(session, endpoint_key(swarm, "verifier", OWN, "store"), frames[3])
        assert reply_of(again, pb.StoreReply).stored_frames == len(frames)
        changed = pb.Constellation()
        changed.CopyFrom(frames[3])
        changed.frame_id = "another"
        refused = ask(session, endpoint_key(swarm, "verifier", OWN, "store"), changed)
        assert refused.code == "ERROR_CODE_ALREADY_EXISTS"


def test_a_host_mixing_python_and_compiled_kinds_serves_both(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    with running_swarm(
        tmp_path,
        swarm_name(request),
        PlaceSettings(n_labels=N_LABELS),
        robots=N_ROBOTS,
        kinds=("index-shard", "verifier", "descriptor", "slam"),
        swarm_kinds=(),
        hosting="robots:2",
        data_plane="compiled",
    ) as swarm:
        host = swarm.procs[0]
        kinds = ("index-shard", "verifier", "descriptor", "slam")
        assert set(host.urls) == {(k, r) for k in kinds for r in range(N_ROBOTS)}
        # The compiled kinds' metrics are the child's; the SLAM services' the host's own.
        server = {k: host.urls[(k, 0)].split("/metrics")[0] for k in kinds}
        assert server["verifier"] == server["index-shard"] == server["descriptor"] != server["slam"]
        with swarm.client(5.0) as client:
            client.wait_for({(k, r) for k in kinds for r in range(N_ROBOTS)}, 30)
            # The compiled shards' coordinators run in the host (Python): the placement is confirmed.
            assert client.wait_index_settled(30.0).placement is not None
        for r in range(N_ROBOTS):
            for k in kinds:
                assert metric(host.urls[(k, r)], "swarmrec_service_ready") == 1
        codes = swarm.stop()
        assert set(codes.values()) == {0}, codes


def _replies(session: zenoh.Session, key: str) -> tuple[list[str], list[str]]:
    """Every reply to a query on ``key`` (all matching services, none consolidated): the
    keys of the answers, and the codes of the refusals."""
    answers, refusals = [], []
    payload = pb.StoreReply(stored_frames=1).SerializeToString()
    for reply in session.get(
        key,
        payload=payload,
        encoding="application/protobuf;swarmrec.v1.StoreReply",
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=5.0,
    ):
        if reply.ok is not None:
            answers.append(str(reply.ok.key_expr))
        else:
            err = pb.ErrorReply()
            err.ParseFromString(reply.err.payload.to_bytes())
            refusals.append(pb.ErrorCode.Name(err.code))
    return sorted(answers), sorted(refusals)


def test_wildcard_and_unknown_endpoint_queries_get_the_python_services_answers(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    # The compiled host declares one queryable a service (`<kind>/<robot>/*`) where Python
    # declares one an endpoint: the answers must not tell them apart.
    seen = {}
    for plane in ("python", "compiled"):
        with (
            verifiers(tmp_path / plane, swarm_name(request), data_plane=plane) as swarm,
            swarm.client(5.0) as client,
        ):
            assert (swarm.find("verifier", OWN).info.get("dispatch") == "compiled") == (plane == "compiled")
            s = client.session
            seen[plane] = (
                _replies(s, endpoint_key(swarm, "verifier", OWN, "*")),
                _replies(s, endpoint_key(swarm, "*", OWN, "info")),
                _replies(s, endpoint_key(swarm, "verifier", OWN, "no-such-endpoint")),
                _replies(s, endpoint_key(swarm, "verifier", OWN, "sto$*")),
            )
            swarm_prefix = endpoint_key(swarm, "verifier", OWN, "")
    everything, infos, unknown, partial = seen["compiled"]
    # Every endpoint of the verifier answered the wildcard: `info` with its MemberInfo, the
    # others refusing a StoreReply where they take another message.
    assert everything[0] == [swarm_prefix + "info"] and len(everything[1]) >= 2
    assert infos == ([swarm_prefix + "info"], [])
    assert unknown == ([], [])
    assert partial[0] == [] and len(partial[1]) == 1  # `store` alone, refusing the schema
    assert seen["compiled"] == seen["python"]
