"""How services share processes changes nothing a user can see but the process count:
the same frames through a swarm of one process per service, one process per robot and
one process for every robot give the same pair scores, equal to the offline evaluation,
and the same bytes between robots; so does feeding the endpoints' workers from queues
instead of zenoh's channels (``dispatch``, which ``auto`` picks by how many services a
process hosts)."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, PlacesSummary, main

ROBOTS, FRAMES = 3, 300


def run(tmp: Path, hosting: str, dispatch: str = "") -> tuple[PlacesSummary, str, set[object]]:
    """The run's summary, pairs.csv and how its robot processes fed their workers."""
    name = hosting.replace(":", "-") + (f"-{dispatch}" if dispatch else "")
    held: list[LocalDeployment] = []

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=tmp / name,
        swarm=f"hosting-{name}",
        progress=False,
        plots=False,
        # The Python runner's hosting and dispatch (a compiled kind's process would say
        # "compiled"; a host mixing both is in test_dataplane_verifier.py).
        data_plane="python",
    )
    # Mutual TLS throughout: a shared process presents its robots' host certificate.
    deployment = LocalDeployment.for_run(settings.out, LocalSettings(hosting=hosting))
    summary = main(settings, deployment, swarm_hook=hook)
    dispatches = {p.info.get("dispatch") for p in held[0].procs}
    return summary, (tmp / name / "pairs.csv").read_text(), dispatches


@pytest.mark.slow
def test_one_process_per_service_per_robot_or_for_all_robots_scores_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    services, pairs, dispatches = run(tmp_path, "service")
    assert dispatches == {"channel"}  # auto: a process of one service
    assert services.offline_check is not None and services.offline_check.identical
    assert services.swarm.processes == 2 + 4 * ROBOTS  # and the router and the gateway
    assert pairs.count("\n") > 20  # the comparison is about something
    variants = [("robot", 2 + ROBOTS, ""), (f"robots:{ROBOTS}", 3, ""), (f"robots:{ROBOTS}", 3, "queue")]
    for hosting, processes, dispatch in variants:
        if dispatch:
            monkeypatch.setenv("SWARMREC_DISPATCH", dispatch)  # the robot processes read it
        summary, same, dispatches = run(tmp_path, hosting, dispatch)
        assert dispatches == {dispatch or "channel"}, (hosting, dispatches)
        assert summary.swarm.processes == processes, hosting
        assert same == pairs, hosting
        assert summary.offline_check is not None and summary.offline_check.identical, hosting
        # The queries' and the replicas' bytes; the index coordinator's own traffic depends
        # on how many of its ticks a run lasts, and a store's reply on how much the shard
        # held when it answered, not on the hosting.
        assert summary.bytes.per_query == services.bytes.per_query, hosting
        shard_stores = summary.bytes.per_query_by_message["ShardStore"]
        assert shard_stores == services.bytes.per_query_by_message["ShardStore"], hosting
        assert summary.shard_load.partial_queries == services.shard_load.partial_queries, hosting
        assert all(code == 0 for code in summary.exit_codes.values()), summary.exit_codes
