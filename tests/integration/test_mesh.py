"""The mesh (docs/mesh.md): a compiled router per robot, each linked by a Toxiproxy proxy
of its own to the robots it hears, under mutual TLS.

* A chain: four robots hear each other all, except for steps 10-29 where the schedule
  cuts links 0-2, 0-3 and 1-3, leaving the chain 0 - 1 - 2 - 3. Robot 0's queries then
  reach robot 3's shards and verifier only through the routers of robots 1 and 2. The
  lock-step run must give the offline evaluation's pair scores, every router must
  follow each step's graph (its links, its link state, its routes), the cut links must
  carry nothing while cut, and the chain's links must carry what was relayed.
* A split that heals: for steps 10-29 the schedule cuts every link between robots 0-1
  and robots 2-3, so the team is two parts. Each part goes on on its own (a query reaches
  the owners in its part; a store owed to an owner away waits on its robot), no
  placement is made while split, and once healed every pending store is delivered
  before the next step. The lock-step run must give, pair for pair, the scores of the
  offline simulation of the same schedule (swarmrec.evaluation.partition).
* A router killed mid-run: robot 3's router is SIGKILLed after step 15; robot 3 drops
  out, the others go on with every slot answered, and the frames robots 0-2 stored are
  all in their verifiers.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.services.routing import version_of
from swarmrec.services.settings import IndexSettings

ROBOTS, FRAMES = 4, 160
STEPS = FRAMES // ROBOTS
CHAIN_FROM, CHAIN_TO = 10, 30
CUT = [(0, 2), (0, 3), (1, 3)]
CHAIN = [(0, 1), (1, 2), (2, 3)]


def _settings(tmp_path: Path, swarm: str, index: IndexSettings | None = None) -> PlacesSettings:
    return PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=tmp_path / "run",
        swarm=swarm,
        progress=False,
        plots=False,
        index=index or IndexSettings(),
    )


@pytest.mark.slow
def test_a_chain_relays_every_query_and_the_run_equals_the_offline_evaluation(tmp_path: Path) -> None:
    schedule = tmp_path / "links.csv"
    rows = "".join(f"{CHAIN_FROM},{CHAIN_TO},{a},{b}\n" for a, b in CUT)
    schedule.write_text("# the team in a chain for steps 10-29\nstart,end,robot_a,robot_b\n" + rows)
    held: list[LocalDeployment] = []
    bytes_at: dict[int, dict[tuple[int, int], tuple[float, float]]] = {}
    reached: dict[int, set[int]] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment) and d.mesh is not None
        held.append(d)

    def on_step(t: int) -> None:
        mesh = held[0]
        if t in (CHAIN_FROM, CHAIN_TO - 1):
            bytes_at[t] = mesh.link_bytes()
        if t == CHAIN_FROM:
            # Robot 0's router knows the chain, and its routes reach robot 3's router over it.
            views = mesh._router_views()
            assert all(v.graph == frozenset(CHAIN) for v in views.values()), views
            assert views[0].neighbours == {1} and views[3].neighbours == {2}
            with mesh.operator(5.0) as operator:
                reached[0] = operator.routers_answering(0)
                assert {("verifier", 3), ("index-shard", 3)} <= operator.alive_at(0)

    settings = _settings(tmp_path, "chain")
    local = LocalSettings(hosting="robot", topology="mesh", schedule=schedule)
    summary = main(settings, LocalDeployment.for_run(settings.out, local), swarm_hook=hook, on_step=on_step)

    assert summary.offline_check is not None and summary.offline_check.identical, summary.offline_check
    assert summary.queries.missing_slots == 0 and summary.queries.failed_shard_requests == 0
    assert summary.peer_failures.get("no_reply", 0) == 0
    assert reached[0] == {0, 1, 2, 3}
    mesh = summary.mesh
    assert mesh is not None and mesh.routers == ROBOTS and mesh.max_hops == 3
    assert mesh.events == [(CHAIN_FROM, f"link {a}-{b} cut") for a, b in CUT] + [
        (CHAIN_TO, f"link {a}-{b} up") for a, b in CUT
    ]
    assert len(mesh.converge_s) == 2
    assert [(c["start"], c["end"], c["links"]) for c in mesh.components] == [
        (0, CHAIN_FROM, 6),
        (CHAIN_FROM, CHAIN_TO, 3),
        (CHAIN_TO, STEPS, 6),
    ]
    # While cut, a link carries nothing; the chain's links carry what was relayed over them.
    before, after = bytes_at[CHAIN_FROM], bytes_at[CHAIN_TO - 1]  # (steps 11-29)
    for pair in CUT:
        assert after[pair] == before[pair], pair
    for pair in CHAIN:
        assert min(a - b for a, b in zip(after[pair], before[pair], strict=True)) > 1000, pair
    # Every link carried traffic over the whole run, measured by both of its routers.
    assert set(mesh.link_bytes) == {f"{a}-{b}" for a, b in CUT + CHAIN}
    assert all(v["a_to_b"] > 0 and v["b_to_a"] > 0 for v in mesh.link_bytes.values())
    assert mesh.link_bytes_per_query > 0
    # Each message type's payload bytes, summed over the links it crossed (zenoh's per-key
    # counts): the two-step query's requests and replies are there, and all of them
    # together are less than the links carried (framing, keys, control are not payload).
    by_type = mesh.type_bytes_per_query
    for name in ("index-shard query query", "index-shard query reply", "verifier verify query"):
        assert by_type.get(name, 0) > 0, by_type
    assert sum(by_type.values()) < mesh.link_bytes_per_query, by_type


SPLIT = [(0, 2), (0, 3), (1, 2), (1, 3)]


@pytest.mark.slow
def test_a_team_that_splits_and_heals_equals_the_offline_simulation_of_its_schedule(tmp_path: Path) -> None:
    schedule = tmp_path / "links.csv"
    rows = "".join(f"{CHAIN_FROM},{CHAIN_TO},{a},{b}\n" for a, b in SPLIT)
    schedule.write_text("# robots 0-1 and 2-3 apart for steps 10-29\nstart,end,robot_a,robot_b\n" + rows)
    held: list[LocalDeployment] = []
    seen: dict[int, object] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment) and d.mesh is not None
        held.append(d)

    def on_step(t: int) -> None:
        if t not in (CHAIN_FROM, CHAIN_TO - 1):
            return
        with held[0].operator(5.0) as operator:
            if t == CHAIN_FROM:
                seen["routers"] = (operator.routers_answering(0), operator.routers_answering(3))
            infos = [operator.descriptor_info(r) for r in range(ROBOTS)]
            seen[t] = [i.pending_items if i is not None else None for i in infos]
            if t == CHAIN_TO - 1:  # the last step split: both parts still on the one placement
                states = operator.shard_states_at(0) + operator.shard_states_at(2)
                assert sorted(st.shard_id for st in states) == list(range(ROBOTS))
                seen["versions"] = {version_of(st) for st in states}

    # A member gone for 0.2 s loses its groups (were it gone, not away): the split, about a
    # second here, is long enough that each part's coordinator acts, and must hold.
    settings = _settings(tmp_path, "split", IndexSettings(member_grace_s=0.2, placement_tick_s=0.1))
    local = LocalSettings(hosting="robot", topology="mesh", schedule=schedule)
    summary = main(settings, LocalDeployment.for_run(settings.out, local), swarm_hook=hook, on_step=on_step)

    check = summary.offline_check
    assert check is not None and check.identical, check
    assert check.split_steps == CHAIN_TO - CHAIN_FROM
    # The split changed what the swarm found: some picked verifiers were across it.
    assert check.unreachable_verifications > 0
    assert summary.queries.missing_slots == 0
    # Each part reached only its own routers.
    assert seen["routers"] == ({0, 1}, {2, 3})
    # Stores owed across the split waited on the robots, and were all delivered on healing.
    assert sum(n or 0 for n in seen[CHAIN_TO - 1]) > 0, seen  # type: ignore[arg-type]
    index = summary.index
    assert index is not None and index.settled and index.pending_stores == 0
    mesh = summary.mesh
    assert mesh is not None
    assert [(c["start"], c["end"], c["components"]) for c in mesh.components] == [
        (0, CHAIN_FROM, [[0, 1, 2, 3]]),
        (CHAIN_FROM, CHAIN_TO, [[0, 1], [2, 3]]),
        (CHAIN_TO, STEPS, [[0, 1, 2, 3]]),
    ]
    # One placement, held by every shard of both parts; none made while split.
    assert len(mesh.held_placements) == 1 and mesh.split_disagreements == []
    assert seen["versions"] == {mesh.held_placements[0]["version"]}, seen
    assert len(mesh.deliver_s) == 2
    # Both parts' coordinators saw the other part away, and held.
    logs = "".join(p.read_text() for p in (settings.out / "logs").glob("*.log"))
    held_by = {json.loads(line)["robot"] for line in logs.splitlines() if "placement held" in line}
    assert held_by == {0, 2}, held_by


@pytest.mark.slow
def test_a_robot_whose_router_is_killed_drops_out_and_the_others_go_on(tmp_path: Path) -> None:
    kill_after, dead = 15, 3
    held: list[LocalDeployment] = []
    stored: dict[str, int] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    def on_step(t: int) -> None:
        if t == kill_after:
            held[0].routers[dead].proc.send_signal(signal.SIGKILL)
            held[0].routers[dead].proc.wait(10)

    def after_replay(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        with d.client(5.0) as operator:
            for m in operator.members():
                stored[f"{m.kind}-{m.robot}"] = m.stored_items

    settings = _settings(tmp_path, "killed")
    local = LocalSettings(hosting="robot", topology="mesh")
    summary = main(
        settings,
        LocalDeployment.for_run(settings.out, local),
        swarm_hook=hook,
        on_step=on_step,
        after_replay=after_replay,
    )
    q = summary.queries
    assert q.missing_by_robot == {str(dead): STEPS - kill_after - 1}
    # Every frame robots 0-2 replayed was stored by their own verifier; nothing they had
    # acknowledged was lost with robot 3's router.
    assert [stored[f"verifier-{r}"] for r in range(3)] == [STEPS] * 3
    assert summary.exit_codes[f"router-{dead}"] == -signal.SIGKILL
    assert all(summary.exit_codes[f"router-{r}"] == 0 for r in range(3))
