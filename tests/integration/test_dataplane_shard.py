"""The compiled index shard (dataplane/, ``data_plane = compiled``) against the reference.

Real processes over a real router, the Python shard and the compiled one each in a swarm
of their own, fed the same seeded stream of requests, tie-heavy (two or three labels a
slice, counts of 1 to 3, so equal partial scores straddle ``n_ret`` all the time):

* queries that store (in lock-step, with a step ahead of the frame sometimes), ShardStores
  to the other owner, read-only lookups (which search everything), and bad requests
  (a slice that is not a group, a frame stored again with another slice, counts over the
  bounds, an empty slice, a stale placement version): every answer, reply or refusal, is
  the same bytes and the same code and message;
* a record log and placement state written by one implementation are served identically
  by the other after a restart, both ways.
"""

from __future__ import annotations

import os
import random
import signal
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np
import pytest

from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.compiled import COORDINATORS_ONLY
from swarmrec.services.settings import IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import partial_descriptor_to_proto
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import endpoint_key, wait_until
from tests.integration.support import request as ask

N_ROBOTS, N_LABELS = 2, 40
#: Every group on both shards (two groups of 20 labels; replicas 2).
GROUPS = ((0, 20), (20, 40))


def shards(tmp: Path, name: str, data_plane: str) -> AbstractContextManager[LocalDeployment]:
    """Two index shards alone, lock-step, plaintext (the test stores as any robot)."""
    return running_swarm(
        tmp,
        name,
        PlaceSettings(n_labels=N_LABELS, lockstep=True, max_objects_per_label=3, max_objects_per_frame=30),
        IndexSettings(placement_tick_s=0.2),
        robots=N_ROBOTS,
        kinds=("index-shard",),
        swarm_kinds=(),
        security="insecure",
        data_plane=data_plane,
    )


def _slice(rng: random.Random, robot: int, frame: int, step: int, group: int) -> pb.PartialDescriptor:
    lo, hi = GROUPS[group]
    dense = np.zeros(N_LABELS, np.int64)
    for label in rng.sample(range(lo, lo + 4), rng.randint(1, 3)):
        dense[label] = rng.randint(1, 3)
    return partial_descriptor_to_proto(dense, lo, hi, robot=robot, frame=frame, query_step=step)


def stream(seed: int) -> list[tuple[str, int, pb.PartialQuery | pb.ShardStore]]:
    """(endpoint, shard, request): the same for both implementations."""
    rng = random.Random(seed)
    out: list[tuple[str, int, pb.PartialQuery | pb.ShardStore]] = []
    frames = [0] * N_ROBOTS
    for i in range(500):
        robot = rng.randrange(N_ROBOTS)
        frame = frames[robot]
        frames[robot] += 1
        group = rng.randrange(len(GROUPS))
        step = frame + rng.choice([0, 0, 0, 2, 7])  # the querier's replay ahead of the frame
        desc = _slice(rng, robot, frame, 0 if step == frame else step, group)
        serving = rng.randrange(N_ROBOTS)
        store = pb.PartialDescriptor()
        store.CopyFrom(desc)
        store.query_step = 0
        if rng.random() < 0.2:
            # A replica's store got to the shard before the query did (a querier's stores
            # leave with its queries, and a query retried goes to another owner).
            out.append(("store", serving, pb.ShardStore(descriptor=store)))
        out.append(("query", serving, pb.PartialQuery(query_id=i, descriptor=desc, include_scores=True)))
        out.append(("store", 1 - serving, pb.ShardStore(descriptor=store)))
        if rng.random() < 0.3:
            probe = _slice(rng, robot, frame, 0, rng.randrange(len(GROUPS)))
            n_ret = rng.choice([0, 1, 3, 30])
            lookup = pb.PartialQuery(descriptor=probe, read_only=True, n_ret=n_ret)
            out.append(("lookup", rng.randrange(N_ROBOTS), lookup))
        if rng.random() < 0.1:
            out.append(("query", serving, _bad(rng, desc, i)))
    return out


def _bad(rng: random.Random, desc: pb.PartialDescriptor, i: int) -> pb.PartialQuery:
    """A request the shard must refuse (or answer as stored already), one way or another."""
    bad = pb.PartialDescriptor()
    bad.CopyFrom(desc)
    kind = rng.randrange(5)
    if kind == 0:
        bad.label_hi -= 1  # not a group
    elif kind == 1:
        bad.counts[0] += 1  # the same frame with another slice
    elif kind == 2:
        bad.counts[0] = 9  # over max_objects_per_label
    elif kind == 3:
        del bad.label_offsets[:]
        del bad.counts[:]  # empty
    else:
        return pb.PartialQuery(query_id=i, descriptor=bad, placement_version=3)  # stale
    return pb.PartialQuery(query_id=i, descriptor=bad)


def answers(swarm: LocalDeployment, seed: int) -> list[tuple[bytes | None, str, str]]:
    with swarm.client(5.0) as client:
        client.wait_index_settled(30.0)
        out = []
        for endpoint, shard, req in stream(seed):
            a = ask(client.session, endpoint_key(swarm, "index-shard", shard, endpoint), req)
            out.append((a.ok, a.code, a.error.message if a.error is not None else ""))
        # The load each shard reports (what the placement rebalances on): the robots' queries
        # it answered, never a client's lookups.
        loads = {st.shard_id: sum(st.served_queries) for st in client.shard_states(5.0)}
        answered = [0] * N_ROBOTS
        for (endpoint, shard, _), (ok, code, _) in zip(stream(seed), out, strict=True):
            answered[shard] += endpoint == "query" and ok is not None and not code
        assert loads == dict(enumerate(answered)), (loads, answered)
        return out


def test_the_compiled_shard_answers_a_tie_heavy_stream_as_the_python_reference(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    got: dict[str, list[tuple[bytes | None, str, str]]] = {}
    for plane in ("python", "compiled"):
        with shards(tmp_path / plane, swarm_name(request) + plane[0], plane) as swarm:
            sp = swarm.find("index-shard", 0)
            assert sp.info.get("dispatch") == ("compiled" if plane == "compiled" else "channel")
            got[plane] = answers(swarm, 20261127)
    python, compiled = got["python"], got["compiled"]
    assert len(python) == len(compiled) > 1000
    for i, (p, c) in enumerate(zip(python, compiled, strict=True)):
        assert p == c, (i, p, c)
    # A frame is never its own candidate, its slice stored there before its query or not
    # (in range of its own query where the querier's step is ahead of the frame).
    requests = stream(20261127)
    stored_first = 0
    previous = [None, *requests]
    for before, (endpoint, shard, req), (ok, code, _) in zip(previous, requests, python, strict=False):
        if endpoint != "query" or not ok or code:
            continue
        assert isinstance(req, pb.PartialQuery)
        reply = pb.CandidatesReply.FromString(ok)
        own = (req.descriptor.robot_id, req.descriptor.frame_index)
        assert own not in set(zip(reply.robot_ids, reply.frame_indices, strict=True)), (req, reply)
        ahead = req.descriptor.query_step > own[1]
        stored_first += ahead and before is not None and before[:2] == ("store", shard)
    assert stored_first > 10
    # About something: candidates with ties at the cut, and refusals of every kind.
    replies = [pb.CandidatesReply.FromString(ok) for ok, code, _ in python if ok and not code]
    full = [r for r in replies if len(r.robot_ids) >= 3]
    assert len(full) > 100 and any(len(set(r.scores)) < len(r.scores) for r in full)
    codes = {code for _, code, _ in python if code}
    assert {"ERROR_CODE_FAILED_PRECONDITION", "ERROR_CODE_ALREADY_EXISTS", "ERROR_CODE_TOO_LARGE"} <= codes
    assert "ERROR_CODE_INVALID_ARGUMENT" in codes


@pytest.mark.parametrize(("first", "then"), [("python", "compiled"), ("compiled", "python")])
def test_a_shards_log_and_placement_state_move_between_the_implementations(
    tmp_path: Path, request: pytest.FixtureRequest, first: str, then: str
) -> None:
    """The whole index stopped (SIGTERM: nobody stays, so nothing is handed on) and started
    again on the same data folders with the other implementation."""
    probes = [
        pb.PartialQuery(descriptor=_slice(random.Random(i), 1, 900 + i, 0, i % 2), read_only=True, n_ret=5)
        for i in range(40)
    ]
    name = swarm_name(request)

    def look(swarm: LocalDeployment, plane: str) -> list[bytes | None]:
        """Every probe asked of an owner of its group, routed with the placement followed (a
        whole index stopping may have moved groups first: its shards stop at nearly the same
        moment, and the first to drain can see the others still staying)."""
        with swarm.client(5.0) as client:
            placement = client.wait_index_settled(30.0).placement
            assert placement is not None
            for shard in range(N_ROBOTS):
                sp = swarm.find("index-shard", shard)
                assert sp.info.get("dispatch") == ("compiled" if plane == "compiled" else "channel")
            answered = []
            for i, p in enumerate(probes):
                q = pb.PartialQuery()
                q.CopyFrom(p)
                q.placement_version = placement.version
                owners = placement.owners[i % 2]
                key = endpoint_key(swarm, "index-shard", owners[i % len(owners)], "lookup")
                answered.append(ask(client.session, key, q))
            assert not answered[0].error, answered[0].error
            return [a.ok for a in answered]

    with shards(tmp_path, name, first) as swarm:
        answers(swarm, 5)
        before = look(swarm, first)
        assert all(before) and sum(len(pb.CandidatesReply.FromString(b).robot_ids) for b in before if b) > 100
    assert (tmp_path / "data" / "robot0" / "index-shard" / "placement.state").is_file()
    with shards(tmp_path, name, then) as swarm:
        after = look(swarm, then)
    assert after == before


def _children(pid: int) -> list[int]:
    return [int(c) for t in Path(f"/proc/{pid}/task").glob("*/children") for c in t.read_text().split()]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_compiled_shards_coordinator_is_started_again_and_dies_with_its_host(
    tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    """`swarmrec serve index-shard` becomes the compiled host, which runs the shard's
    coordinator (Python) as its child: one that ends is started again, and a host killed
    takes it along (nothing of a killed shard goes on acting in the swarm)."""
    with shards(tmp_path, swarm_name(request), "compiled") as swarm:
        sp = swarm.find("index-shard", 1)
        (first,) = wait_until(lambda: _children(sp.proc.pid) or None, 30, "the coordinator started")
        environ = Path(f"/proc/{first}/environ").read_bytes().split(b"\0")
        assert f"{COORDINATORS_ONLY}=1".encode() in environ
        assert b"index-shard" in Path(f"/proc/{first}/cmdline").read_bytes()  # the same command line
        os.kill(first, signal.SIGKILL)
        (second,) = wait_until(
            lambda: [c for c in _children(sp.proc.pid) if c != first] or None, 30, "the coordinator again"
        )
        wait_until(lambda: "starting it again" in sp.log_path.read_text(), 10, "the restart logged")
        # The coordinator again confirms and acts: a placement request still finds it all well.
        with swarm.client(5.0) as client:
            assert client.wait_index_settled(30.0).placement is not None
        sp.proc.send_signal(signal.SIGKILL)
        sp.proc.wait(timeout=10)
        wait_until(lambda: not _alive(second), 10, "the coordinator gone with its host")
