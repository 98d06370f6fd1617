"""Stateful services keep what they acknowledged across a restart.

Robot 0's index shard and verifier run with a data dir (LocalDeployment gives each
robot's services one). Frames of the synthetic office are stored through the
services' own endpoints; a fixed set of read-only shard queries and
verifications is recorded; the processes are stopped (SIGTERM, or SIGKILL
while idle or while frames are arriving) and started again from the same
data dir. The same requests must get identical answers, the stored counts
must be the same, and no acknowledged frame may be missing.

The test speaks as robot 0's descriptor (its certificate: it may store into
robot 0's verifier and query the shards), and the index keeps one replica a
group, the paper's layout: robot 1 never starts, and shard 0 holds labels
[0, 40) alone at placement version 0.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from swarmrec.client import ZenohClient
from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.local import LocalDeployment, ServiceProcess
from swarmrec.errors import NoReply
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.settings import IndexSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto, constellation_to_proto, partial_descriptor_to_proto
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import (
    answering,
    endpoint_key,
    metric,
    metrics_url,
    reply_of,
    request,
    wait_until,
    write_office,
)

N_LABELS, LO, HI = 80, 0, 40  # robot 0's shard owns labels [0, 40) of 80 (2 robots)
KINDS = ("index-shard", "verifier")


@pytest.fixture
def frames(tmp_path: Path) -> list[pb.Constellation]:
    """60 synthetic frames as robot 0's, in wire form (positions in mm)."""
    seq = read_constellations(write_office(tmp_path / "dataset", n_frames=60))
    return [constellation_to_proto(c, 0, t) for t, c in enumerate(seq.constellations)]


def shard_query(frame: pb.Constellation, *, read_only: bool, n_ret: int = 16) -> pb.PartialQuery | None:
    """Shard 0's partial query for ``frame``; None when the frame has no label in [LO, HI)."""
    desc = semantic_descriptor(constellation_from_proto(frame, N_LABELS), N_LABELS)
    if not desc[LO:HI].any():
        return None
    return pb.PartialQuery(
        read_only=read_only,
        include_scores=True,
        n_ret=n_ret,
        descriptor=partial_descriptor_to_proto(
            desc, LO, HI, robot=frame.robot_id, frame=frame.frame_index, query_step=0
        ),
    )


@dataclass
class Robot0:
    """Robot 0's shard and verifier, reached through one client session."""

    swarm: LocalDeployment
    client: ZenohClient

    def key(self, kind: str, endpoint: str) -> str:
        return endpoint_key(self.swarm, kind, 0, endpoint)

    def start(self) -> list[ServiceProcess]:
        procs = self.swarm.start_robot(0, kinds=KINDS)
        # (Bounds for a busy machine: make test runs other swarms and a cluster beside it.)
        self.swarm.wait_started(procs, 120)
        # A shard answers once its coordinator confirmed the placement it loaded (the
        # readiness line comes first: the compiled shard's coordinator is a process it starts).
        wait_until(self.confirmed, 120, "shard 0's placement confirmed")
        return procs

    def confirmed(self) -> bool:
        answer = answering(self.client.session, self.key("index-shard", "placement"), pb.PlacementRequest())
        return answer.ok is not None and pb.ShardState.FromString(answer.ok).confirmed

    def store_frame(self, frame: pb.Constellation) -> None:
        stored = reply_of(request(self.client.session, self.key("verifier", "store"), frame), pb.StoreReply)
        assert stored.stored_frames == frame.frame_index + 1

    def store_slice(self, frame: pb.Constellation) -> bool:
        """Store the frame's shard-0 slice; False when it has none."""
        query = shard_query(frame, read_only=False)
        if query is None:
            return False
        reply_of(request(self.client.session, self.key("index-shard", "query"), query), pb.CandidatesReply)
        return True

    def stored(self) -> dict[str, float]:
        return {
            "slices": metric(
                metrics_url(self.swarm.find("index-shard", 0)), "swarmrec_shard_stored_descriptors"
            ),
            "frames": metric(metrics_url(self.swarm.find("verifier", 0)), "swarmrec_verifier_stored_frames"),
        }

    def answers(self, probes: list[pb.Constellation]) -> dict[str, Any]:
        """Read-only answers to a fixed set of requests, plus the stored counts.

        Each request is retried while nobody answers: a restarted service is
        routed to a moment after its readiness line.
        """
        out: dict[str, Any] = {}
        for i, frame in enumerate(probes):
            query = shard_query(frame, read_only=True)
            assert query is not None
            key = self.key("index-shard", "query")
            out[f"shard answer {i}"] = reply_of(
                answering(self.client.session, key, query), pb.CandidatesReply
            ).SerializeToString()
            # Verified against every stored frame (no candidate list), as another robot's query.
            verify = pb.VerifyRequest(
                query=pb.Constellation(
                    robot_id=1,
                    frame_index=frame.frame_index,
                    labels=frame.labels,
                    positions_mm=frame.positions_mm,
                ),
                include_pairs=True,
            )
            key = self.key("verifier", "verify")
            out[f"verifier answer {i}"] = reply_of(
                answering(self.client.session, key, verify), pb.VerifyReply
            ).SerializeToString()
        out.update(self.stored())
        return out


@pytest.fixture(params=["python", "compiled"])
def local_swarm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LocalDeployment]:
    """A router of a 2-robot swarm, one replica a label group; robot 0 is started by the test.
    Every case runs with the verifier in Python and compiled (``data_plane``)."""
    with running_swarm(
        tmp_path, swarm_name(request), IndexSettings(replicas=1), start=False, data_plane=request.param
    ) as swarm:
        yield swarm


@pytest.fixture
def client(local_swarm: LocalDeployment) -> Iterator[ZenohClient]:
    """A session with robot 0's descriptor certificate."""
    assert local_swarm.pki_dir is not None
    cn = f"r0.descriptor.{local_swarm.spec_swarm}"
    tls = TlsFiles.in_dir(local_swarm.pki_dir, cn)
    with ZenohClient([local_swarm.endpoint], local_swarm.spec_swarm, timeout_s=2.0, tls=tls) as c:
        yield c


@pytest.fixture
def robot0(local_swarm: LocalDeployment, client: ZenohClient) -> Robot0:
    r = Robot0(local_swarm, client)
    r.start()
    return r


def _probes(frames: list[pb.Constellation]) -> list[pb.Constellation]:
    chosen = [f for f in frames[::5] if shard_query(f, read_only=True) is not None and len(f.labels) >= 3]
    assert len(chosen) >= 5
    return chosen


def _store_all(robot0: Robot0, frames: list[pb.Constellation]) -> int:
    slices = 0
    for frame in frames:
        robot0.store_frame(frame)
        slices += robot0.store_slice(frame)
    return slices


def test_a_shard_and_a_verifier_stopped_with_sigterm_answer_identically_after_restart(
    robot0: Robot0, frames: list[pb.Constellation]
) -> None:
    slices = _store_all(robot0, frames)
    probes = _probes(frames)
    before = robot0.answers(probes)
    assert (before["slices"], before["frames"]) == (slices, len(frames))
    assert any(pb.VerifyReply.FromString(v).matches for k, v in before.items() if k.startswith("verifier"))

    for kind in KINDS:
        # A clean exit (SIGKILL after 30 s would say -9: a busy machine, not a slow drain, is given time).
        assert robot0.swarm.stop_process(robot0.swarm.find(kind, 0), timeout_s=30.0) == 0
    with pytest.raises(KeyError):
        robot0.swarm.find("index-shard", 0)
    robot0.start()

    assert robot0.answers(probes) == before


def test_a_shard_and_a_verifier_killed_while_idle_lose_nothing_they_acknowledged(
    robot0: Robot0, frames: list[pb.Constellation]
) -> None:
    slices = _store_all(robot0, frames)
    probes = _probes(frames)
    before = robot0.answers(probes)
    assert (before["slices"], before["frames"]) == (slices, len(frames))

    for kind in KINDS:
        sp = robot0.swarm.find(kind, 0)
        sp.proc.kill()  # SIGKILL: no handler runs, nothing is flushed or closed
        assert sp.proc.wait(timeout=10) == -9
        sp.release()
    robot0.start()

    assert robot0.answers(probes) == before


def test_a_shard_killed_while_frames_arrive_keeps_every_acknowledged_frame(
    robot0: Robot0, frames: list[pb.Constellation]
) -> None:
    queries = [q for f in frames if (q := shard_query(f, read_only=False)) is not None]
    acked: list[int] = []
    sent: list[int] = []
    failure: list[BaseException] = []
    key = robot0.key("index-shard", "query")

    def feed() -> None:
        # One request at a time: a frame is acknowledged once its reply is here.
        # Stops at the first request the dying shard does not answer.
        for q in queries:
            sent.append(q.descriptor.frame_index)
            try:
                answer = request(robot0.client.session, key, q, timeout_s=5.0)
            except (NoReply, AssertionError) as e:
                failure.append(e)
                return
            if answer.error is not None:
                failure.append(RuntimeError(answer.code))
                return
            acked.append(q.descriptor.frame_index)

    feeder = threading.Thread(target=feed, name="feed-shard")
    feeder.start()
    try:
        wait_until(lambda: len(acked) >= len(queries) // 2, 30, "half the frames acknowledged", every_s=0.002)
        shard = robot0.swarm.find("index-shard", 0)
        shard.proc.kill()
        assert shard.proc.wait(timeout=10) == -9
        shard.release()
    finally:
        feeder.join(timeout=30)
    assert not feeder.is_alive()
    assert failure or len(acked) == len(queries)  # it died mid-stream (or the feed won the race)
    robot0.start()

    # Every acknowledged slice is back; at most the one in flight may also be.
    probe = shard_query(frames[0], read_only=True, n_ret=256)
    assert probe is not None
    answering(robot0.client.session, key, probe)
    stored = robot0.stored()["slices"]
    assert len(acked) <= stored <= len(sent)
    for frame in frames:
        if frame.frame_index not in acked:
            continue
        own = shard_query(frame, read_only=True, n_ret=256)
        assert own is not None
        found = reply_of(request(robot0.client.session, key, own), pb.CandidatesReply)
        hits = dict(zip(zip(found.robot_ids, found.frame_indices, strict=True), found.scores, strict=True))
        assert hits.get((0, frame.frame_index)) == pytest.approx(1.0), f"frame {frame.frame_index} lost"
