"""The elastic index on live local swarms: shards killed, added and frozen mid-run.

Every label group lives on two shards (the default). The checks are the issue's:

* a shard killed mid-run (SIGKILL) and a brand-new shard (empty disk) added later
  lose no stored descriptor: after the run every owner of every group holds every
  slice the queried frames put in that group (read back through the shards' own
  ``transfer`` pages), every query was answered (no failed shard), and the lock-step
  pair scores are identical to the offline evaluation;
* a shard frozen (SIGSTOP) for a few seconds costs no store: the descriptors queue
  what it did not acknowledge and store it once it answers again;
* a request routed with an old placement version is refused with FAILED_PRECONDITION
  (and one far ahead at once); a placement from a shard that is not the lowest live
  one is refused.

The expected holdings are computed from the dataset (each frame with enough objects
stores its non-empty slices), not from anything the swarm says.
"""

from __future__ import annotations

import shutil
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from swarmrec.client import ZenohClient
from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.placement import Placement, ring
from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.errors import ErrorCode, NoReply, RemoteError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.coordinator import MAX_STORE_WEIGHT
from swarmrec.services.settings import IndexSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import partial_descriptor_to_proto
from swarmrec.wire.placement import placement_from_proto
from tests.integration.conftest import index_shards
from tests.integration.support import group_rows, request, wait_until

ROBOTS, FRAMES = 4, 400
STEPS = FRAMES // ROBOTS


def _as_shard(swarm: LocalDeployment, shard: int) -> ZenohClient:
    """A session with shard ``shard``'s certificate (shards may page through each other's groups)."""
    assert swarm.pki_dir is not None
    cn = f"r{shard}.index-shard.{swarm.spec_swarm}"
    return ZenohClient(
        [swarm.endpoint], swarm.spec_swarm, timeout_s=5.0, tls=TlsFiles.in_dir(swarm.pki_dir, cn)
    )


def expected_rows(dataset: Path, placement: Placement) -> dict[int, set[tuple[int, int]]]:
    """Per group, the (robot, frame) of every queried frame with objects of that group."""
    return _expected(dataset, placement, ROBOTS)


def _expected(dataset: Path, placement: Placement, robots: int) -> dict[int, set[tuple[int, int]]]:
    seq = read_constellations(dataset)
    preset = get_preset("paper")
    out: dict[int, set[tuple[int, int]]] = {g: set() for g in range(len(placement.groups))}
    for robot, block in enumerate(split_frames(len(seq), robots)):
        for frame, i in enumerate(block):
            c = seq.constellations[i]
            if len(c) < preset.min_objects:
                continue
            desc = semantic_descriptor(c, seq.n_labels)
            for g, (lo, hi) in enumerate(placement.groups):
                if desc[lo:hi].any():
                    out[g].add((robot, frame))
    return out


def check_holdings(swarm: LocalDeployment, dataset: Path) -> Placement:
    """Every owner of every group holds exactly the slices the dataset says; the placement."""
    with swarm.client(5.0) as client:
        state = client.index_state()
    assert state.settled, state
    placement = state.placement
    assert placement is not None
    expected = expected_rows(dataset, placement)
    asker = min(m for g in placement.owners for m in g)
    with _as_shard(swarm, asker) as c:
        caller = Caller(c.session, asker, 5.0)
        for g, owners in enumerate(placement.owners):
            assert len(owners) == 2, (g, owners)  # back to two replicas everywhere
            for shard in owners:
                assert group_rows(caller, swarm.spec_swarm, shard, g) == expected[g], (g, shard)
    return placement


def members(swarm: LocalDeployment) -> tuple[int, ...] | None:
    """The members of the placement the live shards follow (None: no shard answered;
    a caller waiting for a member to leave reads None as "not yet")."""
    with swarm.client(5.0) as c:
        placement = c.index_state().placement
    return None if placement is None else placement.members


def _settings(tmp_path: Path, swarm: str, **index: object) -> PlacesSettings:
    return PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=tmp_path / "run",
        swarm=swarm,
        request_timeout_s=1.0,
        progress=False,
        plots=False,
        # Quick to give up on a gone shard; no rebalancing, so only membership moves groups.
        index=IndexSettings(member_grace_s=1.0, placement_tick_s=0.25, rebalance_target=1000.0, **index),  # type: ignore[arg-type]
    )


@pytest.mark.slow
def test_a_shard_killed_and_a_new_one_added_mid_run_lose_nothing_and_scores_stay_identical(
    tmp_path: Path,
) -> None:
    settings = _settings(tmp_path, "elastic-kill-add")
    held: list[LocalDeployment] = []
    events: list[str] = []
    seen: dict[str, Placement] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    victim: list[int] = []

    def on_step(t: int) -> None:
        swarm = held[0]
        if t == 25:
            # A shard that owns groups, and not the coordinator (the lowest): shard 2 unless
            # the placement the swarm settled on at start gave it none (rendezvous can).
            with swarm.client(5.0) as c:
                placement = c.index_state().placement
            assert placement is not None
            owning = [m for m in placement.members if m != min(placement.members) and placement.groups_of(m)]
            victim.append(2 if 2 in owning else owning[0])
            sp = swarm.find("index-shard", victim[0])
            sp.proc.send_signal(signal.SIGKILL)
            sp.proc.wait(timeout=10)
            # The coordinator drops it after the grace (1 s); a fast replay could reach step
            # 60 first, and the test would then restart a shard the swarm never lost.
            wait_until(lambda: victim[0] not in (members(swarm) or (victim[0],)), 30, "removal")
            events.append("killed")
        if t == 60:
            # A brand-new shard of the same robot: nothing on its disk.
            shutil.rmtree(swarm.data_dir / f"robot{victim[0]}" / "index-shard", ignore_errors=True)
            started = swarm.start_robot(victim[0], ["index-shard"])
            assert started
            swarm.wait_ready(60.0)
            wait_until(lambda: victim[0] in (members(swarm) or ()), 30, "the new shard a member")
            events.append("added")

    def after(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        seen["final"] = check_holdings(d, settings.out / "dataset")

    summary = main(
        settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step, after_replay=after
    )

    assert events == ["killed", "added"]
    assert summary.offline_check is not None and summary.offline_check.identical, summary.offline_check
    assert summary.queries.failed_shard_requests == 0  # every group kept an owner that answered
    assert summary.index is not None and summary.index.settled
    assert summary.index.version >= 4  # removal and re-replication, then the new shard's handoff
    assert summary.index.handoff_records > 0
    # The shards measured what a query and a store cost them (the rebalancing's weight).
    assert summary.index.store_weight is not None and 0.0 < summary.index.store_weight < MAX_STORE_WEIGHT
    final = seen["final"]
    assert victim[0] in final.members and final.groups_of(victim[0]), "the new shard took groups"
    # The report's history is every placement published, and explains the last one: from
    # version 0 (every shard's ring), each change's gained and lost holders give its owners.
    history = summary.index.history
    assert [h["version"] for h in history] == list(range(1, summary.index.version + 1)), history
    assert {h["reason"] for h in history} == {"members", "handoff_done"}  # no rebalancing here
    held = [set(own) for own in ring(final.groups, range(ROBOTS), replicas=2).owners]
    for h in history:
        for g, change in h["groups"].items():
            held[int(g)] = (held[int(g)] | set(change["gained"])) - set(change["lost"])
    assert held == [set(own) for own in final.owners]


@pytest.mark.slow
def test_a_frozen_shard_costs_no_store_the_descriptors_queue_and_retry(tmp_path: Path) -> None:
    settings = _settings(tmp_path, "elastic-frozen")
    held: list[LocalDeployment] = []
    frozen: list[float] = []

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    def on_step(t: int) -> None:
        sp = held[0].find("index-shard", 1)
        if t == 20:
            sp.proc.send_signal(signal.SIGSTOP)
            frozen.append(time.monotonic())
        if t == 30:
            # At least 3 s frozen, so stores to it time out (1 s) and wait in the queues.
            time.sleep(max(0.0, 3.0 - (time.monotonic() - frozen[0])))
            sp.proc.send_signal(signal.SIGCONT)

    retries: list[float] = []

    def after(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        check_holdings(d, settings.out / "dataset")
        retries.append(d.metrics().total("swarmrec_descriptor_store_retries_total"))

    summary = main(
        settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step, after_replay=after
    )

    assert summary.queries.failed_shard_requests == 0  # the other owner answered meanwhile
    assert summary.index is not None and summary.index.settled and summary.index.pending_stores == 0
    assert retries[0] > 0  # stores to the frozen shard timed out, waited in the queues, were sent again


@pytest.fixture
def shards(tmp_path: Path) -> Iterator[LocalDeployment]:
    """Three index shards alone (version 0: groups on (0, 1), (1, 2), (2, 0))."""
    with index_shards(tmp_path, "elastic-shards", shards=3, n_labels=30) as swarm:
        yield swarm


def _slice(version: int) -> pb.PartialQuery:
    desc = partial_descriptor_to_proto(np.asarray([1, 2] + [0] * 28), 0, 10, robot=0, frame=0, query_step=0)
    return pb.PartialQuery(descriptor=desc, read_only=True, placement_version=version)


def test_stale_and_far_ahead_placement_versions_are_refused_and_placements_come_only_from_the_lowest(
    shards: LocalDeployment,
) -> None:
    s = shards.spec_swarm
    with shards.client(5.0) as client:
        caller = client.caller
        assert caller is not None
        lookup0 = keys.endpoint(s, "index-shard", 0, "lookup")
        start = client.wait_index_settled(30.0).placement
        assert start is not None
        caller.call(lookup0, _slice(start.version), pb.CandidatesReply, target_robot=0)  # the current one
        # Shard 2 goes: after the grace the coordinator (shard 0) moves its groups on.
        shards.find("index-shard", 2).proc.send_signal(signal.SIGKILL)
        moved = start.version + 2  # the dead owner dropped with learners, then the learners own
        wait_until(lambda: client.index_state().placement.version >= moved, 30, "placement moved on")  # type: ignore[union-attr]
        version = client.index_state().placement.version  # type: ignore[union-attr]
        with pytest.raises(RemoteError) as stale:
            caller.call(lookup0, _slice(start.version), pb.CandidatesReply, target_robot=0)
        assert stale.value.code == ErrorCode.FAILED_PRECONDITION and "refresh" in stale.value.message
        t0 = time.perf_counter()
        with pytest.raises(RemoteError) as ahead:
            caller.call(lookup0, _slice(version + 100), pb.CandidatesReply, target_robot=0)
        assert ahead.value.code == ErrorCode.FAILED_PRECONDITION
        assert time.perf_counter() - t0 < 0.5  # refused at once, no wait for an adoption
        caller.call(lookup0, _slice(version), pb.CandidatesReply, target_robot=0)
        state = next(st for st in client.shard_states() if st.shard_id == 1)
    # Shard 1 sends shard 0 a placement: refused, shard 0 is the lowest live shard.
    with _as_shard(shards, 1) as c:
        bogus = pb.AdoptRequest(placement=state.placement)
        bogus.placement.version += 5
        with pytest.raises(RemoteError) as refused:
            Caller(c.session, 1, 5.0).call(
                keys.endpoint(s, "index-shard", 0, "adopt"), bogus, pb.ShardState, target_robot=0
            )
        assert refused.value.code == ErrorCode.FAILED_PRECONDITION and "coordinator" in refused.value.message
        # Posing as the coordinator: in shard 0's name the router never delivers it (the key
        # names the sender, and shard 1's certificate may name robot 1 only) ...
        with pytest.raises(NoReply):
            Caller(c.session, 0, 5.0).call(
                keys.endpoint(s, "index-shard", 0, "adopt"), bogus, pb.ShardState, target_robot=0
            )
        # ... and an attachment that says shard 0 under shard 1's key is refused unread.
        adopt0 = keys.endpoint(s, "index-shard", 0, "adopt")
        forged = request(c.session, adopt0, bogus, caller=1, attachment=b"0")
        assert forged.code == "ERROR_CODE_PERMISSION_DENIED", forged
    with shards.client(5.0) as client:
        after = {st.shard_id: placement_from_proto(st.placement, 30).version for st in client.shard_states()}
    assert after == {0: version, 1: version}


def test_a_shard_leaves_out_the_placement_the_asker_says_it_knows(shards: LocalDeployment) -> None:
    """The coordinator asks every shard for its state at every tick; a shard that follows
    the version it already holds answers with the version alone (a hundred shards'
    placements a second were most of a large swarm's index traffic)."""
    s = shards.spec_swarm
    with shards.client(5.0) as client:
        caller = client.caller
        assert caller is not None
        current = client.wait_index_settled(30.0).placement
        assert current is not None
        key = keys.endpoint(s, "index-shard", 1, "placement")

        def ask(**known: int) -> pb.ShardState:
            return caller.call(key, pb.PlacementRequest(**known), pb.ShardState, target_robot=1)

        known = ask(known_version=current.version)
        assert not known.HasField("placement") and known.placement_version == current.version
        assert known.confirmed and list(known.ready_groups)  # the rest of the state is there
        # An asker ahead of the shard learns only its version: an older placement is no news.
        ahead = ask(known_version=current.version + 1)
        assert not ahead.HasField("placement") and ahead.placement_version == current.version
        full = ask()
        assert full.HasField("placement") and full.placement.version == current.version
        assert full.placement_version == current.version
        assert known.ByteSize() < full.ByteSize() / 2


@pytest.mark.slow
def test_shards_scaled_from_3_to_6_to_2_mid_run_lose_nothing_and_scores_stay_identical(
    tmp_path: Path,
) -> None:
    """The scale-up and scale-down a StatefulSet would do, on local processes: three more
    shards (ids beyond the robots) join at step 20; at step 55 four of the six are told to
    stop at once (SIGTERM), and they hand their groups over before they exit."""
    robots, frames = 3, 330
    settings = PlacesSettings(
        source=DatasetSource(frames=frames),
        robots=robots,
        out=tmp_path / "run",
        swarm="elastic-scale",
        request_timeout_s=1.0,
        progress=False,
        plots=False,
        index=IndexSettings(
            member_grace_s=1.0,
            placement_tick_s=0.25,
            rebalance_target=1000.0,
            max_shards=6,
            drain_timeout_s=60.0,
        ),
    )
    held: list[LocalDeployment] = []
    stopped: dict[int, int] = {}
    seen: dict[str, Placement] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    def placed(client: ZenohClient) -> bool:
        state = client.index_state()
        return state.settled and state.placement is not None and 5 in state.placement.members

    def on_step(t: int) -> None:
        swarm = held[0]
        if t == 20:
            for shard in (3, 4, 5):
                swarm.start_robot(shard, ["index-shard"])
            swarm.wait_ready(60.0)
            with swarm.client(5.0) as client:
                wait_until(lambda: placed(client), 60, "the 3 new shards placed")
                placement = client.index_state().placement
                assert placement is not None
                seen["six"] = placement
        if t == 55:
            going = [swarm.find("index-shard", s) for s in (2, 3, 4, 5)]
            for sp in going:
                sp.proc.send_signal(signal.SIGTERM)
            for sp in going:
                stopped[sp.robot] = sp.proc.wait(timeout=90)

    def after(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        with d.client(5.0) as client:
            state = client.index_state()
        assert state.settled and state.placement is not None
        placement = state.placement
        assert {m for own in placement.owners for m in own} == {0, 1}
        expected = _expected(settings.out / "dataset", placement, robots)
        with _as_shard(d, 0) as c:
            caller = Caller(c.session, 0, 5.0)
            for g, owners in enumerate(placement.owners):
                for shard in owners:
                    assert group_rows(caller, d.spec_swarm, shard, g) == expected[g], (g, shard)

    summary = main(
        settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step, after_replay=after
    )

    assert stopped == {2: 0, 3: 0, 4: 0, 5: 0}  # each drained and exited cleanly
    six = seen["six"]
    # The new shards took groups (three groups of two replicas: six places over six shards,
    # as rendezvous hashing deals them).
    assert {3, 4, 5} & {m for own in six.owners for m in own}
    assert summary.offline_check is not None and summary.offline_check.identical, summary.offline_check
    assert summary.queries.failed_shard_requests == 0
    assert summary.index is not None and summary.index.handoff_records > 0
