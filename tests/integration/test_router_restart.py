"""The index through a router restart: a real router process killed and started again.

Every shard's session loses its link and sees no other shard for as long as the router
is down; the sessions reconnect one by one, each after its own retry delay. None of the
shards went anywhere, so none may be dropped: after the restart every shard follows one
and the same placement, the one of before, and a partial query routed with it is answered
by every owner. (A shard cut off used to coordinate alone: the first back published a
placement of its own that the others never followed, and queries routed with it failed;
CI saw it in the container-faults test.)
"""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from swarmrec.deployments.local import LocalDeployment
from swarmrec.runtime import keys
from swarmrec.wire import messages as pb
from swarmrec.wire.placement import placement_from_proto
from tests.integration.conftest import index_shards
from tests.integration.support import wait_until

SHARDS, N_LABELS = 4, 40
#: Far longer than the member grace: a shard cut off this long would drop every other.
DOWN_S = 4.0


@pytest.fixture
def shards(tmp_path: Path) -> Iterator[LocalDeployment]:
    with index_shards(tmp_path, "router-restart", shards=SHARDS, n_labels=N_LABELS) as swarm:
        yield swarm


def _placements(swarm: LocalDeployment) -> dict[int, tuple[int, tuple[tuple[int, ...], ...]]]:
    """Each answering shard's (version, owners), read whole (no known version)."""
    with swarm.client(2.0) as client:
        states = client.shard_states()
    out = {}
    for st in states:
        p = placement_from_proto(st.placement, N_LABELS)
        out[st.shard_id] = (p.version, p.owners) if st.confirmed else (-1, p.owners)
    return out


@pytest.mark.slow
def test_after_a_router_restart_every_shard_follows_the_placement_of_before(shards: LocalDeployment) -> None:
    with shards.client(5.0) as client:
        before = client.wait_index_settled(30.0, shards=SHARDS).placement
    assert before is not None and set(before.members) == set(range(SHARDS))
    assert set(_placements(shards).values()) == {(before.version, before.owners)}

    router = shards.router
    assert router is not None
    router.proc.send_signal(signal.SIGKILL)  # a crash: no goodbye to anyone
    router.proc.wait()
    router.release()
    time.sleep(DOWN_S)
    assert shards.spec is not None
    shards.start_router(shards.spec)  # the same port: every session reconnects by itself

    # Every shard answers again, and they agree.
    wait_until(
        lambda: len(_placements(shards)) == SHARDS, timeout_s=60.0, what="every shard back", every_s=0.5
    )
    wait_until(
        lambda: len(set(_placements(shards).values())) == 1, timeout_s=30.0, what="one placement", every_s=0.5
    )
    # Settled for a while: no shard was dropped, nothing moved.
    time.sleep(2.0)
    after = _placements(shards)
    assert set(after.values()) == {(before.version, before.owners)}, after

    # A partial query routed with it is answered by every owner of its group.
    with shards.client(5.0) as client:
        assert client.caller is not None
        for g, (lo, hi) in enumerate(before.groups):
            for shard in before.owners[g]:
                request = pb.PartialQuery(
                    descriptor=pb.PartialDescriptor(
                        robot_id=0, frame_index=0, label_lo=lo, label_hi=hi, label_offsets=[0], counts=[1]
                    ),
                    read_only=True,
                    placement_version=before.version,
                )
                key = keys.endpoint(shards.spec_swarm, "index-shard", shard, "lookup")
                client.caller.call(key, request, pb.CandidatesReply, target_robot=shard)
