"""Re-balancing a live full-image swarm's cluster owners (docs/vpr.md, "Re-balancing a live
swarm"), with real processes over a real router.

Four robots, each a verifier and a place-owner, the shipped k = 20 centres with 5 clusters
per robot. Every robot's frames are seeded descriptors near a few of the centres, so a few
clusters are hot: the first re-balancing splits them and plans a new table, later ones
repair it, and from the first one on every query is also stored as a copy at the owner of
its next-nearest cell of another robot. The frames go through the owners' own ``process``
endpoints in lock-step order (step t of robots 0, 1, 2, 3, then step t + 1), and the
coordinator (robot 0, the lowest live owner) is asked to re-balance between steps.

What each frame got back must equal the offline simulation of the *same table sequence*:
:func:`swarmrec.vpr.simulation.run_queries` with one :class:`Reassignment` per rolled-out
table, built here from the tables the coordinator answered with and the offline code alone
(:class:`~swarmrec.vpr.clusters.Router` for owners, :func:`~swarmrec.vpr.balance.replica_owners`
for copies): a query is routed by its float32 descriptor, as the querier routes it; a stored
descriptor (the int8 code decoded, as owners store it) moves to the owner and copy holders
of its decoded value, as its holder computes them. Equal answers mean every stored
descriptor was where the offline model put it at every step: nothing lost, nothing left
behind, no copy missing.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from swarmrec.client import ZenohClient
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import read_metrics
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.services.settings import PlaceSettings, VprSettings
from swarmrec.vpr.balance import replica_owners
from swarmrec.vpr.clusters import Assignment, Router, load_centres, random_assignment
from swarmrec.vpr.simulation import Answers, Reassignment, run_queries
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm
from tests.integration.support import answering, endpoint_key, metrics_url, reply_of, request, wait_until

ROBOTS, C, D = 4, 5, 128
K = ROBOTS * C
STEPS = 36
#: Steps after which the coordinator is asked to re-balance.
REBALANCE_AFTER = (9, 18, 27)
FLOAT32 = pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32
#: Most frames lie near these centres (hot clusters), the rest anywhere.
HOT = (3, 11, 17)


def descriptors() -> np.ndarray:
    """Frame (robot r, step t) is row ``t * ROBOTS + r`` (arrival order): seeded, unit norm."""
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), K)
    rng = np.random.default_rng(2026)
    rows = []
    for _ in range(STEPS * ROBOTS):
        base = centres[rng.choice(HOT)] if rng.random() < 0.8 else centres[rng.integers(K)]
        v = base + rng.normal(scale=0.06, size=D).astype(np.float32)
        rows.append(v / np.linalg.norm(v))
    return np.stack(rows).astype(np.float32)


def decoded(x: np.ndarray) -> np.ndarray:
    """The int8 wire code decoded, written out here: float32 scale, round(x / scale) as int8."""
    out = []
    for row in x:
        scale = np.float32(np.abs(row).max() / np.float32(127))
        q = np.clip(np.rint(row / scale), -127, 127).astype(np.int8)
        data = struct.pack("<f", float(scale)) + q.tobytes()
        s = np.frombuffer(data[:4], "<f4")[0]
        out.append(np.frombuffer(data[4:], np.int8).astype(np.float32) * s)
    return np.stack(out).astype(np.float32)


def frame(robot: int, t: int, x: np.ndarray) -> pb.PlaceFrame:
    c = pb.Constellation(labels=[0, 41, 56], positions_mm=[100 * t, 20, 1500, -300, 10, 2000, 250, -40, 1800])
    return pb.PlaceFrame(
        robot_id=robot,
        frame_index=t,
        frame_id=f"f{t}",
        descriptor=x.astype("<f4").tobytes(),
        encoding=FLOAT32,
        constellation=c,
    )


@dataclass
class Run:
    """What a replay through the live swarm gave: each frame's report, the tables rolled out
    (with the arrival position they took effect at)."""

    reports: dict[int, pb.PlaceReport] = field(default_factory=dict)
    tables: list[tuple[int, pb.ClusterTable]] = field(default_factory=list)


def key(local: LocalDeployment, robot: int, endpoint: str) -> str:
    return endpoint_key(local, "place-owner", robot, endpoint)


def rebalance(local: LocalDeployment, client: ZenohClient, run: Run, position: int) -> pb.RebalanceReply:
    reply = reply_of(
        request(client.session, key(local, 0, "rebalance"), pb.RebalanceRequest(), 60.0), pb.RebalanceReply
    )
    assert reply.changed and reply.pending == 0, reply
    run.tables.append((position, reply.table))
    return reply


def replay(
    local: LocalDeployment, client: ZenohClient, x: np.ndarray, steps: range, run: Run, between=None
) -> None:  # type: ignore[no-untyped-def]
    for t in steps:
        for r in range(ROBOTS):
            i = t * ROBOTS + r
            answer = request(client.session, key(local, r, "process"), frame(r, t, x[i]), 30.0)
            run.reports[i] = reply_of(answer, pb.PlaceReport)
        if t + 1 in REBALANCE_AFTER:
            rebalance(local, client, run, (t + 1) * ROBOTS)
        if between is not None:
            between(t)


def offline(x: np.ndarray, run: Run) -> tuple[Answers, np.ndarray]:
    """The offline simulation of the tables ``run`` rolled out (module docstring), and how
    many descriptors each robot holds at the end under it (each frame at its last owner and
    copy holders)."""
    stored = decoded(x)
    n = len(x)
    robots = np.arange(n, dtype=np.int64) % ROBOTS  # row t * ROBOTS + r is robot r's
    order = np.arange(n, dtype=np.int64)  # rows are in arrival order already
    start = Router(load_centres(shipped_model(DESCRIPTOR_CENTRES), K), random_assignment(ROBOTS, C, 0))
    switches = []
    for at, table in run.tables:
        k = len(table.owners)
        centres = np.frombuffer(table.centres, "<f4").reshape(k, D)
        assignment = Assignment(tuple(table.owners), ROBOTS, version=table.version)
        router = Router(centres, assignment)
        arrived = order < at
        owners = np.where(arrived, router.route_many(stored)[1], router.route_many(x)[1])
        margin = table.copy_margin
        copies = replica_owners(centres, assignment, stored, margin, table.copy_neighbours)
        switches.append(Reassignment(at, owners, copies))
    # Frame indices in the answers are global rows; the live reports name (robot, step).
    answers = run_queries(stored, robots, start.route_many(x)[1], order, switches)
    last = switches[-1]
    held = np.zeros(ROBOTS, np.int64)
    for i in range(n):
        for robot in {int(last.owners[i])} | {int(r) for r in np.ravel(last.replicas[i]) if r >= 0}:
            held[robot] += 1
    return answers, held


def check_equal(run: Run, expected: Answers, n: int) -> None:
    assert sorted(run.reports) == list(range(n))
    wrong = []
    for i in range(n):
        rep = run.reports[i]
        want_frame = int(expected.matches[i])
        matched = rep.match.frame_index * ROBOTS + rep.match.robot_id if rep.match.found else -1
        got = (rep.owner_robot_id, rep.match.found, matched)
        want = (int(expected.owners[i]), want_frame >= 0, want_frame)
        if (
            not rep.answered
            or got != want
            or (rep.match.found and np.float32(rep.match.distance) != np.float32(expected.distances[i]))
        ):
            wrong.append((i, got, want, rep.failure))
    assert not wrong, f"{len(wrong)} of {n} frames differ from the offline simulation: {wrong[:5]}"


@pytest.fixture()
def swarm(tmp_path: Path) -> Iterator[tuple[LocalDeployment, ZenohClient]]:
    vpr = VprSettings(vpr_clusters_per_robot=C, vpr_snapshot_every=16)
    with (
        running_swarm(
            tmp_path,
            "rebalance",
            PlaceSettings(),
            vpr,
            robots=ROBOTS,
            kinds=("verifier", "place-owner"),
            security="insecure",
            swarm_kinds=(),
        ) as local,
        local.client(5.0) as client,
    ):
        for r in range(ROBOTS):
            answering(client.session, key(local, r, "table"), pb.TableRequest())
        yield local, client


def held(local: LocalDeployment) -> list[int]:
    """How many descriptors each owner holds (its stored-descriptors gauge)."""
    out = []
    for r in range(ROBOTS):
        values = read_metrics(metrics_url(local.find("place-owner", r)))
        out.append(int(values[("swarmrec_place_owner_stored_descriptors", ())]))
    return out


@pytest.mark.slow
def test_moves_under_replay_answer_every_frame_as_the_offline_simulation_of_the_same_tables(
    swarm: tuple[LocalDeployment, ZenohClient],
) -> None:
    local, client = swarm
    x = descriptors()
    run = Run()
    replay(local, client, x, range(STEPS), run)
    expected, holdings = offline(x, run)
    check_equal(run, expected, len(x))
    # Nothing left behind where a move took it from, no copy missing.
    assert held(local) == holdings.tolist()
    # The re-balancing did what it is for: hot clusters split, copies stored, load spread.
    first = run.tables[0][1]
    assert len(first.owners) > K and first.copy_margin == float("inf")
    assert [t.version for _, t in run.tables] == [1, 2, 3]
    before = np.bincount(expected.owners[: REBALANCE_AFTER[0] * ROBOTS], minlength=ROBOTS)
    after = np.bincount(expected.owners[REBALANCE_AFTER[0] * ROBOTS :], minlength=ROBOTS)
    assert after.max() / after.mean() < before.max() / before.mean()
    # Every owner follows the last table, and holds what the offline model put there.
    for r in range(ROBOTS):
        table = reply_of(request(client.session, key(local, r, "table"), pb.TableRequest()), pb.ClusterTable)
        assert table.version == 3
    assert sum(holdings) == 3 * len(x)  # every frame at its owner and two copies (the default)
    # A client's place query (the gateway's code) routes by the re-balanced table, whose
    # centres are no file's: it reads them from an owner, and finds a stored frame.
    last = run.tables[-1][1]
    router = Router(
        np.frombuffer(last.centres, "<f4").reshape(len(last.owners), D),
        Assignment(tuple(last.owners), ROBOTS),
    )
    reply = client.place_query(x[5])
    assert reply.assignment_version == 3 and (reply.cluster, reply.owner_robot_id) == tuple(
        int(v) for v in (router.route(x[5]).cluster, router.route(x[5]).owner)
    )
    assert reply.match.found and (reply.match.robot_id, reply.match.frame_index) == (5 % ROBOTS, 5 // ROBOTS)


def table_of(local: LocalDeployment, client: ZenohClient, robot: int) -> pb.ClusterTable:
    answer = answering(client.session, key(local, robot, "table"), pb.TableRequest())
    return reply_of(answer, pb.ClusterTable)


@pytest.mark.slow
def test_a_killed_owner_stops_a_rebalancing_and_restarted_without_its_table_catches_up_losing_nothing(
    swarm: tuple[LocalDeployment, ZenohClient],
) -> None:
    local, client = swarm
    x = descriptors()
    run = Run()
    victim = 2

    def kill_and_restart(t: int) -> None:
        if t != 20:
            return
        sp = local.find("place-owner", victim)
        sp.proc.kill()  # SIGKILL: no chance to save anything
        sp.proc.wait()
        sp.release()
        # With an owner gone the coordinator cannot move what it holds: it refuses, and the
        # swarm keeps its table.
        answer = request(client.session, key(local, 0, "rebalance"), pb.RebalanceRequest(), 60.0)
        assert answer.code == "ERROR_CODE_UNAVAILABLE", answer
        assert f"place-owner {victim} did not answer" in answer.error.message
        assert {table_of(local, client, r).version for r in range(ROBOTS) if r != victim} == {2}
        # It comes back without the table it followed: it starts on the settings' table and
        # must catch up with the coordinator's before it routes or owns anything by it.
        (path,) = (local.data_dir / f"robot{victim}").rglob("cluster-table.pb")
        path.unlink()
        (restarted,) = local.start_robot(victim, ["place-owner"])
        local.wait_started([restarted])

    replay(local, client, x, range(STEPS), run, between=kill_and_restart)
    expected, holdings = offline(x, run)
    check_equal(run, expected, len(x))
    assert held(local) == holdings.tolist()
    assert [t.version for _, t in run.tables] == [1, 2, 3]
    assert table_of(local, client, victim).version == 3


@pytest.mark.slow
def test_a_query_routed_with_an_old_table_is_refused_and_stores_nothing(
    swarm: tuple[LocalDeployment, ZenohClient],
) -> None:
    local, client = swarm
    x = descriptors()
    run = Run()
    replay(local, client, x, range(REBALANCE_AFTER[0]), run)
    assert [t.version for _, t in run.tables] == [1]
    before = held(local)
    table = run.tables[0][1]
    start = Router(load_centres(shipped_model(DESCRIPTOR_CENTRES), K), random_assignment(ROBOTS, C, 0))
    y = x[-1]
    route = start.route(y)
    stale = pb.PlaceQuery(
        robot_id=1, frame_index=900, descriptor=y.astype("<f4").tobytes(), encoding=FLOAT32,
        cluster=route.cluster, assignment_version=0,
    )  # fmt: skip
    for owner in range(ROBOTS):
        answer = request(client.session, key(local, owner, "query"), stale, caller=1)
        assert answer.code == "ERROR_CODE_FAILED_PRECONDITION", answer
        assert "routed with assignment version 0; this owner follows version 1" in answer.error.message
    # A copy for the old table, and a table that is not the coordinator's, are refused too.
    answer = request(client.session, key(local, 2, "store_copy"), stale, caller=1)
    assert answer.code == "ERROR_CODE_FAILED_PRECONDITION", answer
    forged = pb.AdoptTableRequest(table=table)
    forged.table.version = 9
    answer = request(client.session, key(local, 2, "adopt_table"), forged, caller=1)
    assert answer.code == "ERROR_CODE_PERMISSION_DENIED", answer
    # A holder cannot park entries where the table does not put them, nor send removals.
    live = Router(
        np.frombuffer(table.centres, "<f4").reshape(len(table.owners), D),
        Assignment(tuple(table.owners), ROBOTS, version=1),
    )
    target = int(live.route(y).owner)
    copies = replica_owners(live.centres, live.assignment, y[None], table.copy_margin, table.copy_neighbours)[
        0
    ]
    elsewhere = next(r for r in range(ROBOTS) if r != target and r not in copies)
    entry = pb.PlaceEntry(robot_id=3, frame_index=901, descriptor=y.astype("<f4").tobytes(), encoding=FLOAT32)
    parked = pb.StoreEntriesRequest(version=1, entries=[entry])
    answer = request(client.session, key(local, elsewhere, "store_entries"), parked, caller=target)
    assert answer.code == "ERROR_CODE_FAILED_PRECONDITION" and "elsewhere" in answer.error.message, answer
    removal = pb.StoreEntriesRequest(
        version=1, entries=[pb.PlaceEntry(robot_id=3, frame_index=901, removed=True)]
    )
    answer = request(client.session, key(local, target, "store_entries"), removal, caller=elsewhere)
    assert answer.code == "ERROR_CODE_INVALID_ARGUMENT", answer
    assert held(local) == before
    assert {table_of(local, client, r).version for r in range(ROBOTS)} == {1}


@pytest.mark.slow
def test_a_free_running_swarm_rebalances_on_its_own_and_every_frame_stays_findable(tmp_path: Path) -> None:
    vpr = VprSettings(vpr_clusters_per_robot=C, vpr_rebalance_every_s=0.5, vpr_rebalance_min_queries=40)
    x = descriptors()
    reports: dict[int, pb.PlaceReport] = {}
    with (
        running_swarm(
            tmp_path, "rebalance-timed", PlaceSettings(), vpr, robots=ROBOTS,
            kinds=("verifier", "place-owner"), security="insecure", swarm_kinds=(),
        ) as local,
        local.client(5.0) as client,
    ):  # fmt: skip
        for r in range(ROBOTS):
            answering(client.session, key(local, r, "table"), pb.TableRequest())

        def robot(r: int) -> None:
            # Each robot on its own, as fast as its owners answer; the coordinator re-balances
            # in between whenever its timer fires.
            for t in range(STEPS):
                i = t * ROBOTS + r
                answer = request(client.session, key(local, r, "process"), frame(r, t, x[i]), 30.0)
                reports[i] = reply_of(answer, pb.PlaceReport)
                time.sleep(0.03)

        threads = [threading.Thread(target=robot, args=(r,)) for r in range(ROBOTS)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        assert all(rep.answered for rep in reports.values()) and len(reports) == len(x)
        # The timer may still fire once on what the last frames left (>= 40 queries since the
        # last table): wait until every owner follows one re-balanced table for 2 s (4 ticks).
        seen: list[tuple[float, list[int]]] = []

        def settled() -> list[int] | None:
            v = [table_of(local, client, r).version for r in range(ROBOTS)]
            if not seen or seen[-1][1] != v:
                seen.append((time.monotonic(), v))
            steady = time.monotonic() - seen[-1][0] >= 2.0
            return v if steady and min(v) >= 1 and len(set(v)) == 1 else None

        wait_until(settled, 30.0, "every owner on one re-balanced table", every_s=0.25)
        table = table_of(local, client, 0)
        k = len(table.owners)
        router = Router(
            np.frombuffer(table.centres, "<f4").reshape(k, D), Assignment(tuple(table.owners), ROBOTS)
        )
        lost = []
        for i, y in enumerate(x):
            found = False
            for v in (y, decoded(y[None])[0]):
                route = router.route(v)
                q = pb.PlaceQuery(
                    descriptor=y.astype("<f4").tobytes(),
                    encoding=FLOAT32,
                    cluster=route.cluster,
                    assignment_version=table.version,
                )
                m = reply_of(request(client.session, key(local, route.owner, "lookup"), q), pb.PlaceMatch)
                found |= m.found and (m.robot_id, m.frame_index) == (i % ROBOTS, i // ROBOTS)
            if not found:
                lost.append(i)
        assert not lost, (
            f"{len(lost)} frames not found at their owner under table {table.version}: {lost[:10]}"
        )
