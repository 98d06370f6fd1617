"""The compiled descriptor (dataplane/, ``data_plane = compiled``) against the reference.

Real processes over a real router, a swarm of Python services and one of compiled
services, each fed the same seeded stream of frames (places revisited by other robots,
with noise; frames of too few objects; a frame processed again; bad frames of every kind)
one at a time, five robots with ``n_fq`` 4 so the robot selection chooses:

* every answer is the same: the query report (its timing aside) with its candidates,
  funnel, matches and verdicts, or the refusal with the same code and message; then
  every robot's loop closures (their clock aside) and ``explain`` of its frames;
* slices no shard acknowledged wait in the descriptor's queue on disk, and the other
  implementation, started on the same data folders with the shards back, stores them all,
  both ways.
"""

from __future__ import annotations

import random
from contextlib import AbstractContextManager
from pathlib import Path

import pytest

from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.settings import ExplainSettings, IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import endpoint_key, metric, wait_until
from tests.integration.support import request as ask

N_ROBOTS, N_LABELS = 5, 30
KINDS = ("descriptor", "verifier", "index-shard")


def swarm(
    tmp: Path,
    name: str,
    plane: str,
    kinds: tuple[str, ...] = KINDS,
    index: IndexSettings | None = None,
) -> AbstractContextManager[LocalDeployment]:
    """Every robot's services in one process (calls to a robot's own services stay in it,
    calls to others cross the router), plaintext, the shards in lock-step."""
    return running_swarm(
        tmp,
        name,
        PlaceSettings(n_labels=N_LABELS, lockstep=True),
        index or IndexSettings(retry_interval_s=0.2),
        ExplainSettings(explain_reports=40),
        robots=N_ROBOTS,
        kinds=kinds,
        swarm_kinds=(),
        hosting=f"robots:{N_ROBOTS}",
        security="insecure",
        data_plane=plane,
    )


def frames(seed: int, n: int = 240, first: int = 0) -> list[pb.Constellation]:
    """Frames of robots taking turns, each a view of one of a dozen places (objects
    dropped, positions jittered by a few cm), a few with too few objects, and bad ones."""
    rng = random.Random(seed)
    places = [
        [
            (rng.randrange(N_LABELS), [rng.uniform(-4.0, 4.0) for _ in range(3)])
            for _ in range(rng.randint(4, 9))
        ]
        for _ in range(12)
    ]
    out: list[pb.Constellation] = []
    next_frame = [first] * N_ROBOTS
    for i in range(n):
        robot = i % N_ROBOTS
        frame = next_frame[robot]
        next_frame[robot] += 1
        objs = [o for o in rng.choice(places) if rng.random() > 0.15]
        if rng.random() < 0.08:
            objs = objs[:2]  # too few objects to query
        msg = pb.Constellation(
            robot_id=robot,
            frame_index=frame,
            labels=[label for label, _ in objs],
            positions_mm=[round((v + rng.gauss(0.0, 0.03)) * 1000) for _, p in objs for v in p],
            frame_id=f"r{robot}/f{frame}",
        )
        out.append(msg)
        roll = rng.random()
        if roll < 0.04:
            out.append(msg)  # the same frame again: processed again, stored once, closed once
        elif roll < 0.08 and len(msg.labels) > 1:
            other = pb.Constellation()
            other.CopyFrom(msg)
            del other.labels[0]
            del other.positions_mm[:3]
            out.append(other)  # the frame again with other content: ALREADY_EXISTS
        elif roll < 0.14:
            out.append(_bad(rng, msg))
    return out


def _bad(rng: random.Random, good: pb.Constellation) -> pb.Constellation:
    bad = pb.Constellation()
    bad.CopyFrom(good)
    kind = rng.randrange(5)
    if kind == 0:
        bad.robot_id = (good.robot_id + 1) % N_ROBOTS  # another robot's frame
    elif kind == 1:
        bad.ClearField("frame_index")
    elif kind == 2:
        bad.labels.append(N_LABELS)  # outside the label list
        bad.positions_mm.extend([0, 0, 0])
    elif kind == 3:
        bad.positions_mm.append(7)  # not 3 coordinates an object
    else:
        bad.frame_index = 1 << 20
    return bad


def timeless(report: pb.QueryReport) -> pb.QueryReport:
    report.duration_us = 0
    return report


def answers(
    d: LocalDeployment, stream: list[pb.Constellation], plane: str
) -> list[tuple[bytes | None, str, str]]:
    with d.client(10.0) as client:
        client.wait_index_settled(30.0)
        for r in range(N_ROBOTS):
            sp = d.find("descriptor", r)
            assert sp.info.get("dispatch") == ("compiled" if plane == "compiled" else "channel"), sp.info
        out: list[tuple[bytes | None, str, str]] = []
        for msg in stream:
            key = endpoint_key(d, "descriptor", msg.robot_id % N_ROBOTS, "process")
            a = ask(client.session, key, msg, timeout_s=10.0)
            ok = timeless(pb.QueryReport.FromString(a.ok)).SerializeToString() if a.ok is not None else None
            out.append((ok, a.code, a.error.message if a.error is not None else ""))
        for r in range(N_ROBOTS):
            a = ask(
                client.session, endpoint_key(d, "descriptor", r, "loop_closures"), pb.LoopClosuresRequest()
            )
            assert a.ok is not None, a.error
            closures = pb.LoopClosureList.FromString(a.ok)
            for c in closures.loop_closures:
                c.unix_time_ns = 0
            out.append((closures.SerializeToString(), a.code, ""))
            for f in range(0, 60, 3):
                a = ask(
                    client.session,
                    endpoint_key(d, "descriptor", r, "explain"),
                    pb.ExplainRequest(frame_index=f),
                )
                assert a.ok is not None, a.error
                reply = pb.ExplainReply.FromString(a.ok)
                if reply.HasField("report"):
                    timeless(reply.report)
                out.append((reply.SerializeToString(), a.code, ""))
        return out


def test_the_compiled_descriptor_answers_a_stream_of_frames_as_the_python_reference(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    stream = frames(20261127)
    got: dict[str, list[tuple[bytes | None, str, str]]] = {}
    for plane in ("python", "compiled"):
        with swarm(tmp_path / plane, swarm_name(request) + plane[0], plane) as d:
            got[plane] = answers(d, stream, plane)
    python, compiled = got["python"], got["compiled"]
    assert len(python) == len(compiled) > len(stream)
    for i, (p, c) in enumerate(zip(python, compiled, strict=True)):
        assert p == c, (i, p, c)
    # About something: closures taken and refused for every reason, robots left out, refusals.
    reports = [pb.QueryReport.FromString(ok) for ok, code, _ in python[: len(stream)] if ok and not code]
    reasons = {o.reason for r in reports for o in r.candidates}
    assert {
        pb.FunnelReason.FUNNEL_REASON_ACCEPTED,
        pb.FunnelReason.FUNNEL_REASON_ALREADY_CLOSED,
        pb.FunnelReason.FUNNEL_REASON_OUTRANKED,
        pb.FunnelReason.FUNNEL_REASON_ROBOT_NOT_CHOSEN,
        pb.FunnelReason.FUNNEL_REASON_TOO_FEW_MATCHES,
    } <= reasons
    assert any(not r.queried for r in reports) and sum(len(r.matches) for r in reports) > 100
    codes = {code for _, code, _ in python if code}
    assert {"ERROR_CODE_INVALID_ARGUMENT", "ERROR_CODE_ALREADY_EXISTS", "ERROR_CODE_UNKNOWN_LABEL"} <= codes


def _total(d: LocalDeployment, kind: str, name: str) -> float:
    """``name`` summed over every robot's ``kind`` (each at its own path of the host's endpoint)."""
    return sum(metric(d.find(kind, r).urls[(kind, r)], name) for r in range(N_ROBOTS))


def _pending(d: LocalDeployment) -> float:
    return _total(d, "descriptor", "swarmrec_descriptor_pending_stores")


def _stored(d: LocalDeployment) -> float:
    return _total(d, "index-shard", "swarmrec_shard_stored_descriptors")


@pytest.mark.parametrize(("first", "then"), [("python", "compiled"), ("compiled", "python")])
def test_slices_no_shard_acknowledged_wait_on_disk_and_the_other_implementation_stores_them(
    tmp_path: Path, request: pytest.FixtureRequest, first: str, then: str
) -> None:
    name = swarm_name(request)
    stream = [m for m in frames(7, n=40) if m.frame_index < 1 << 20 and m.HasField("frame_index")]
    with swarm(tmp_path, name, first, kinds=("descriptor", "verifier")) as d:
        with d.client(5.0) as client:
            queried: set[tuple[int, int]] = set()
            for msg in stream:
                a = ask(
                    client.session, endpoint_key(d, "descriptor", msg.robot_id % N_ROBOTS, "process"), msg
                )
                if a.ok is not None:
                    report = pb.QueryReport.FromString(a.ok)
                    if report.queried:
                        queried.add((report.robot_id, report.frame_index))
                    assert report.failed_shard_robot_ids or not report.queried  # no shard to ask
        waiting = _pending(d)
    assert len(queried) > 20 and waiting >= len(queried)
    with swarm(tmp_path, name, then) as d:
        wait_until(lambda: _pending(d) == 0, 30.0, "the pending stores were stored")
        # Every slice on both owners of its group (2 replicas), none twice.
        wait_until(lambda: _stored(d) == 2 * waiting, 10.0, "every slice on each of its owners")
        assert _stored(d) == 2 * waiting


def test_a_full_queue_of_pending_stores_refuses_new_frames_in_both_implementations(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    """No shard at all and room for 12 waiting slices: each implementation takes frames
    until fewer than a frame's worth of slices (one a group) fit, then refuses them alike."""
    stream = [m for m in frames(11, n=60) if m.frame_index < 1 << 20 and m.HasField("frame_index")]
    stream = [m for m in stream if m.robot_id == 0 and len(m.labels) >= 3]
    got: dict[str, list[tuple[str, str]]] = {}
    for plane in ("python", "compiled"):
        index = IndexSettings(retry_interval_s=0.2, pending_capacity=12)
        with (
            swarm(
                tmp_path / plane, swarm_name(request) + plane[0], plane, ("descriptor", "verifier"), index
            ) as d,
            d.client(5.0) as client,
        ):
            key = endpoint_key(d, "descriptor", 0, "process")
            got[plane] = [
                (a.code, a.error.message if a.error else "")
                for a in (ask(client.session, key, m) for m in stream)
            ]
    assert got["python"] == got["compiled"]
    refused = [message for code, message in got["python"] if code == "ERROR_CODE_UNAVAILABLE"]
    assert refused and all("waiting for index shards" in m for m in refused)
    assert got["python"][0] == ("", "")
