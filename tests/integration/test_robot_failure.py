"""A robot dies mid-run: the main job finishes and reports what was lost.

Three robots replay 300 synthetic frames in lock-step; after step 20 every
process of robot 2 is killed with SIGKILL. The run must complete, name robot
2 as missing, count the failed shard and verifier requests, and robots 0
and 1 must keep querying. Every query report the descriptors publish is
collected independently (``events/query/*``) to check that no missing answer
was taken for "no match": each query after the kill that needed robot 2's
label range lists robot 2 among its failed shards, and none before it does.
"""

from __future__ import annotations

import signal
from contextlib import ExitStack
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from swarmrec.cli.run import print_summary
from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.runtime import keys
from swarmrec.services.settings import IndexSettings
from swarmrec.wire import messages as pb
from tests.integration.support import wait_until

ROBOTS, FRAMES, KILL_AFTER, DEAD = 3, 300, 20, 2
STEPS = FRAMES // ROBOTS


@pytest.mark.slow
@pytest.mark.parametrize("replicas", [1, 2])
def test_a_robot_killed_mid_run_is_reported_missing_and_the_others_keep_querying(
    tmp_path: Path, replicas: int, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=out,
        swarm=f"robot-failure-{replicas}",
        request_timeout_s=2.0,
        progress=False,
        plots=False,
        # One replica a group: the dead robot's label range goes with it. Two (the default):
        # the other owner of each of its groups answers, and no query fails at a shard.
        index=IndexSettings(replicas=replicas, rebalance_target=1000.0),
    )
    held: list[LocalDeployment] = []
    reports: list[pb.QueryReport] = []
    killed: list[int] = []

    with ExitStack() as stack:

        def hook(swarm: Deployment) -> None:
            assert isinstance(swarm, LocalDeployment)
            held.append(swarm)
            client = stack.enter_context(swarm.client())
            sub = client.session.declare_subscriber(
                keys.event(settings.swarm, "query", "*"),
                lambda sample: reports.append(pb.QueryReport.FromString(sample.payload.to_bytes())),
            )
            stack.callback(sub.undeclare)
            # The router has the subscription before the first step is asked for:
            # a publisher of another session sees it as matching.
            other = stack.enter_context(swarm.client())
            probe = other.session.declare_publisher(keys.event(settings.swarm, "query", ROBOTS))
            stack.callback(probe.undeclare)
            # matching_status is a snapshot, read anew each poll; zenoh's stub types it as bool,
            # it is a MatchingStatus (../shared/ZENOH.md).
            wait_until(lambda: cast(Any, probe.matching_status).matching, 10, "subscription routed")

        def on_step(t: int) -> None:
            if t != KILL_AFTER:
                return
            for sp in held[0].procs:
                if sp.robot == DEAD and sp.proc.poll() is None:
                    sp.proc.send_signal(signal.SIGKILL)
                    sp.proc.wait(timeout=10)
                    killed.append(sp.proc.pid)

        summary = main(settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step)

    assert len(killed) == 4  # detector, descriptor, index-shard and verifier of robot 2
    q = summary.queries
    # The run completed and names the dead robot: it missed every step after the kill.
    assert q.missing_by_robot == {str(DEAD): STEPS - KILL_AFTER - 1}
    # The summary a user reads says why the scores were not compared, and who missed what.
    missed = STEPS - KILL_AFTER - 1
    capsys.readouterr()
    print_summary(summary, out)
    printed = capsys.readouterr().out
    assert (
        f"pair scores vs offline decentralized evaluation: not compared ({missed} answer slots missing)"
        in (printed)
    )
    assert f"missing answers: {missed} (robot {DEAD}: {missed})" in printed
    assert q.frames_replayed == ROBOTS * STEPS - (STEPS - KILL_AFTER - 1)
    assert any(f"loop closures of robot {DEAD}" in e for e in q.errors)
    # Its processes died by SIGKILL; everyone else exited cleanly.
    codes = summary.exit_codes
    assert {name for name, code in codes.items() if code != 0} == {
        f"{k}-{DEAD}" for k in ("detector", "descriptor", "index-shard", "verifier")
    }
    assert all(
        codes[f"{k}-{DEAD}"] == -signal.SIGKILL for k in ("detector", "descriptor", "index-shard", "verifier")
    )
    if replicas == 1:
        # Its group had no other owner: the stores owed to it wait for it, and the report says so.
        assert summary.index is not None and not summary.index.settled and summary.index.pending_stores > 0
    # Failed requests to the dead robot are counted in the report.
    assert (q.failed_shard_requests > 0) == (replicas == 1)
    assert q.failed_verifier_requests > 0
    assert sum(summary.peer_failures.values()) >= q.failed_shard_requests + q.failed_verifier_requests

    # Robots 0 and 1 kept querying to the end.
    seq = read_constellations(out / "dataset")
    blocks = split_frames(len(seq), ROBOTS)
    bounds = summary.swarm.label_bounds
    lo, hi = bounds[DEAD], bounds[DEAD + 1]
    by_robot = {r: sorted(rep.frame_index for rep in reports if rep.robot_id == r) for r in range(ROBOTS)}
    assert by_robot[0] == by_robot[1] == list(range(STEPS))
    assert by_robot[DEAD] == list(range(KILL_AFTER + 1))

    # No empty answer was taken for "no match".
    needed_dead_shard = 0
    for rep in reports:
        if not rep.queried:
            continue
        c = seq.constellations[blocks[rep.robot_id][rep.frame_index]]
        asks_dead = bool(semantic_descriptor(c, seq.n_labels)[lo:hi].any())
        if rep.frame_index <= KILL_AFTER:
            assert not rep.failed_shard_robot_ids and not rep.failed_verifier_robot_ids, rep
            continue
        expected = [DEAD] if asks_dead and replicas == 1 else []
        assert list(rep.failed_shard_robot_ids) == expected, rep
        assert set(rep.failed_verifier_robot_ids) <= {DEAD}, rep
        assert DEAD not in [m.match_robot_id for m in rep.matches], rep
        needed_dead_shard += asks_dead
    assert needed_dead_shard > 10
    assert q.failed_shard_requests == (needed_dead_shard if replicas == 1 else 0)
    assert q.failed_verifier_requests == sum(len(r.failed_verifier_robot_ids) for r in reports)
    # The survivors still found matches after the kill.
    late = [r for r in reports if r.frame_index > KILL_AFTER and r.matches]
    assert len(late) > 10
    assert np.all([r.robot_id != DEAD for r in late])
