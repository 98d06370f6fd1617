"""The mesh's radio graph, its schedule rows and refusals, and what is read back from the
routers (docs/mesh.md). The live mesh is tests/integration/test_mesh.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmrec.core.split import split_frames
from swarmrec.core.types import Trajectory
from swarmrec.deployments.links import LinkSpec, Outage, Schedule, read_schedule
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.deployments.mesh import key_bytes, link_bytes, mesh_report, message_types, router_views
from swarmrec.deployments.metrics import Scrape
from swarmrec.deployments.radio import RadioGraph, components, robot_positions
from swarmrec.errors import ConfigError, MalformedLineError
from swarmrec.experiments.mesh import plan_mesh
from swarmrec.security.acl import access_control, grants
from swarmrec.security.identity import Identity


def _line(xs: list[float]) -> np.ndarray:
    """One step of robots on the x axis at ``xs``."""
    return np.array([[[x, 0.0, 0.0] for x in xs]])


def test_components_are_ordered_by_their_lowest_robot() -> None:
    assert components(5, [(3, 4), (0, 2)]) == [frozenset({0, 2}), frozenset({1}), frozenset({3, 4})]
    assert components(3, []) == [frozenset({0}), frozenset({1}), frozenset({2})]


def test_robots_within_range_hear_each_other_and_a_chain_has_hops() -> None:
    # 0 - 1 - 2 - 3, 1 m apart, range 1.5 m: a chain of three links.
    g = RadioGraph.build(4, 1, positions=_line([0, 1, 2, 3]), range_m=1.5)
    assert sorted(g.at(0)) == [(0, 1), (1, 2), (2, 3)]
    assert g.hops_at(0)[(0, 3)] == 3
    assert g.components_at(0) == [frozenset({0, 1, 2, 3})]
    # No range: everyone hears everyone.
    assert len(RadioGraph.build(4, 1).at(0)) == 6


def test_a_robot_without_a_pose_hears_nobody() -> None:
    g = RadioGraph.build(3, 1, positions=_line([0, float("nan"), 0.5]), range_m=1.0)
    assert list(g.at(0)) == [(0, 2)]


def test_positions_follow_each_robots_frames_and_stay_after_its_last() -> None:
    positions = np.arange(15, dtype=float).reshape(5, 3)  # frame i at (3i, 3i+1, 3i+2)
    blocks = split_frames(5, 2)  # robot 0: frames 0-2, robot 1: frames 3-4
    p = robot_positions(positions, blocks)
    assert p.shape == (3, 2, 3)
    assert p[2, 1].tolist() == positions[4].tolist()  # robot 1 stays at its last frame
    assert p[1, 0].tolist() == positions[1].tolist()


def test_schedule_rows_take_links_away_and_slow_them_but_never_add_one() -> None:
    rows = (
        Outage(1, 3, 0, None, 1),  # link 0-1 cut at steps 1-2
        Outage(2, 3, 2),  # robot 2 out of range at step 2
        Outage(0, 4, 1, LinkSpec(rate_kbps=5.0)),  # robot 1's links slow
        Outage(0, 4, 0, LinkSpec(latency_ms=50.0), 2),  # and link 0-2 delayed
    )
    g = RadioGraph.build(3, 4, schedule=Schedule(rows, "step"), default=LinkSpec(latency_ms=10.0))
    assert g.at(0)[(0, 1)] == LinkSpec(5.0, 10.0)
    assert g.at(0)[(0, 2)] == LinkSpec(None, 50.0)
    assert (0, 1) not in g.at(1)
    assert list(g.at(2)) == []  # 0-1 cut, and robot 2 away
    assert g.changes() == [1, 2, 3]
    assert [e["components"] for e in g.timeline()][2] == [[0], [1], [2]]
    # Robots out of range of each other stay unlinked whatever the schedule says.
    far = RadioGraph.build(
        2,
        1,
        positions=_line([0, 10]),
        range_m=1.0,
        schedule=Schedule((Outage(0, 1, 0, LinkSpec(1.0), 1),), "step"),
    )
    assert far.pairs() == []


def test_a_pair_schedule_reads_both_kinds_of_row(tmp_path: Path) -> None:
    path = tmp_path / "links.csv"
    path.write_text("start,end,robot,robot_a,robot_b,rate_kbps\n0,5,,3,1,\n2,4,2,,,8\n")
    s = read_schedule(path, unit="step")
    assert s.intervals == (Outage(0, 5, 1, None, 3), Outage(2, 4, 2, LinkSpec(8.0, None)))
    assert s.has_pairs
    assert s.pairs_at(1) == {(1, 3): None}
    assert s.state_at(3) == {2: LinkSpec(8.0, None)}


@pytest.mark.parametrize(
    "row",
    ["0,5,1,1,2", "0,5,,1,1", "0,5,,,", "0,5,,1,"],
    ids=["both kinds", "a robot with itself", "neither", "half a pair"],
)
def test_a_row_that_names_no_single_robot_or_pair_is_refused(tmp_path: Path, row: str) -> None:
    path = tmp_path / "links.csv"
    path.write_text(f"start,end,robot,robot_a,robot_b\n{row}\n")
    with pytest.raises(MalformedLineError, match=r"links\.csv:2: not a schedule row"):
        read_schedule(path, unit="step")


def test_unknown_robots_and_overlapping_rows_are_refused_in_one_line() -> None:
    with pytest.raises(ConfigError, match=r"names robot 4, but the swarm has robots 0\.\.3"):
        Schedule((Outage(0, 2, 1, None, 4),), "step").check(4)
    with pytest.raises(ConfigError, match=r"overlapping rows for robots 1-2: \[0, 5\) and \[3, 6\)"):
        Schedule((Outage(0, 5, 1, None, 2), Outage(3, 6, 1, None, 2)), "step").check(4)
    with pytest.raises(ConfigError, match="overlapping rows for robot 0"):
        Schedule((Outage(0, 5, 0), Outage(4, 6, 0, LinkSpec(1.0))), "step").check(4)
    # Back to back is not overlapping; a robot row and a pair row are about different things.
    Schedule((Outage(0, 5, 0), Outage(5, 6, 0), Outage(0, 6, 0, None, 1)), "step").check(2)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"radio_range_m": 5.0}, "needs --topology mesh"),
        ({"topology": "mesh", "radio_range_m": -1.0}, "distance > 0"),
        ({"topology": "mesh", "hosting": "robots:2"}, "its own router"),
        ({"topology": "ring"}, "star or mesh"),
    ],
)
def test_settings_a_mesh_cannot_honour_are_refused(settings: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        LocalSettings(**settings)  # type: ignore[arg-type]


def test_pair_rows_need_a_mesh(tmp_path: Path) -> None:
    schedule = Schedule((Outage(0, 2, 0, None, 1),), "step")
    with pytest.raises(ConfigError, match="need --topology mesh"):
        LocalDeployment(data_dir=tmp_path, log_dir=tmp_path, schedule=schedule)


def _trajectory(xs: list[float]) -> Trajectory:
    n = len(xs)
    return Trajectory(
        np.arange(n, dtype=float), np.array([[x, 0.0, 0.0] for x in xs]), np.tile([0, 0, 0, 1.0], (n, 1))
    )


def test_a_team_may_split_during_a_run_but_starts_whole(tmp_path: Path) -> None:
    mesh = LocalDeployment(data_dir=tmp_path, log_dir=tmp_path, topology="mesh", radio_range_m=1.5)
    blocks = split_frames(4, 2)
    # Robot 0 at x = 0, 1; robot 1 at x = 5, 2: apart at step 0.
    with pytest.raises(ConfigError, match=r"splits the team at step 0 into \[\[0\], \[1\]\]"):
        plan_mesh(mesh, blocks, _trajectory([0, 1, 5, 2]), lockstep=True)
    # Robot 1 at x = 1, 5: together at step 0, apart at step 1.
    split = plan_mesh(mesh, blocks, _trajectory([0, 1, 1, 5]), lockstep=True)
    assert split is not None and mesh.radio is not None
    assert [len(mesh.radio.components_at(t)) for t in range(2)] == [1, 2]
    # Connected all along: planned, and the links change between steps.
    run = plan_mesh(mesh, blocks, _trajectory([0, 1, 1, 2]), lockstep=True)
    assert run is not None and mesh.radio is not None and mesh.radio.steps == 2
    star = LocalDeployment(data_dir=tmp_path, log_dir=tmp_path)
    assert plan_mesh(star, blocks, None, lockstep=True) is None


def test_links_that_change_need_a_lock_step_run(tmp_path: Path) -> None:
    schedule = Schedule((Outage(1, 2, 0, LinkSpec(rate_kbps=2.0), 1),), "step")
    mesh = LocalDeployment(data_dir=tmp_path, log_dir=tmp_path, topology="mesh", schedule=schedule)
    with pytest.raises(ConfigError, match="--pace lockstep"):
        plan_mesh(mesh, split_frames(6, 2), None, lockstep=False)


def test_a_radio_range_needs_a_pose_for_every_frame(tmp_path: Path) -> None:
    mesh = LocalDeployment(data_dir=tmp_path, log_dir=tmp_path, topology="mesh", radio_range_m=3.0)
    with pytest.raises(ConfigError, match="position"):
        plan_mesh(mesh, split_frames(6, 2), None, lockstep=True)


def test_a_robots_router_relays_everything_of_its_swarm_and_nothing_else() -> None:
    g = grants(Identity.router("lab", 2), [0, 1, 2])
    assert {(x.flow, x.key_exprs) for x in g} == {
        ("egress", ("swarmrec/v1/lab/**",)),
        ("ingress", ("swarmrec/v1/lab/**",)),
    }
    assert all("declare_queryable" in x.messages and "reply" in x.messages for x in g)
    assert grants(Identity.router("lab"), [0, 1, 2]) == []  # the star's router dials no one
    acl = access_control("lab", 3, robot_routers=True)
    names = {s["id"] for s in acl["subjects"]}
    assert {"r0.router.lab", "r1.router.lab", "r2.router.lab"} <= names
    assert "r0.router.lab" not in {s["id"] for s in access_control("lab", 3)["subjects"]}


def test_router_views_name_robots_by_their_routers_zenoh_ids() -> None:
    pages = Scrape(
        {
            ("router", 0): {
                ("swarmrec_router_zid", (("zid", "aa"),)): 1.0,
                ("swarmrec_router_neighbours", (("peer_zid", "bb"),)): 1.0,
                ("swarmrec_router_neighbours", (("peer_zid", "cc"),)): 0.0,  # a link it had
                ("swarmrec_router_graph_links", (("a", "aa"), ("b", "bb"))): 1.0,
                ("swarmrec_router_graph_links", (("a", "bb"), ("b", "cc"))): 0.0,
            },
            ("router", 1): {
                ("swarmrec_router_zid", (("zid", "bb"),)): 1.0,
                ("swarmrec_router_neighbours", (("peer_zid", "aa"),)): 1.0,
                ("swarmrec_router_graph_links", (("a", "aa"), ("b", "zz"))): 1.0,  # a router unread
            },
        }
    )
    views = router_views(pages)
    assert views[0].neighbours == {1} and views[0].graph == {(0, 1)}
    assert views[1].neighbours == {0} and views[1].graph is None


def test_link_bytes_are_what_each_side_sent_to_the_other() -> None:
    def sent(peer: str, v: float) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
        return {("swarmrec_router_link_bytes_total", (("direction", "sent"), ("peer", peer))): v}

    pages = Scrape(
        {
            ("router", 0): {**sent("r1.router.lab", 100.0), **sent("zid:ff", 7.0)},
            ("router", 1): {
                **sent("r0.router.lab", 40.0),
                **sent("r2.router.lab", 5.0),
                (
                    "swarmrec_router_link_bytes_total",
                    (("direction", "received"), ("peer", "r0.router.lab")),
                ): 99.0,
            },
            ("router", 2): sent("r1.router.other", 9.0),  # another swarm's name: not this link
        }
    )
    before = link_bytes(pages, "lab")
    assert before == {(0, 1): (100.0, 40.0), (1, 2): (5.0, 0.0)}
    after = {(0, 1): (160.0, 50.0), (1, 2): (25.0, 0.0)}
    report = mesh_report(RadioGraph.build(3, 1), before, after, 4, [(0, "link 1-2 up")], [0.2])
    assert report.link_bytes == {
        "0-1": {"a_to_b": 60.0, "b_to_a": 10.0},
        "1-2": {"a_to_b": 20.0, "b_to_a": 0.0},
    }
    assert report.link_bytes_per_query == 90.0 / 4
    assert report.max_hops == 1 and report.components == [
        {"start": 0, "end": 1, "components": [[0, 1, 2]], "links": 3}
    ]


def test_a_message_types_bytes_are_summed_over_every_link_it_crossed() -> None:
    types = message_types("lab")
    # Every endpoint a kind calls of another, and the events.
    assert types["index-shard query"] == "swarmrec/v1/lab/index-shard/*/query/**"
    assert types["verifier verify"] == "swarmrec/v1/lab/verifier/*/verify/**"
    assert types["events"] == "swarmrec/v1/lab/events/**"

    def sent(
        peer: str, key: str, message: str, v: float
    ) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
        labels = (("direction", "sent"), ("key", key), ("message", message), ("peer", peer))
        return {("swarmrec_router_key_bytes_total", labels): v}

    query = types["index-shard query"]
    pages = Scrape(
        {
            # A query relayed 0 -> 1 -> 2 is counted on both links; its reply on both too.
            ("router", 0): sent("r1.router.lab", query, "query", 30.0),
            ("router", 1): {
                **sent("r2.router.lab", query, "query", 30.0),
                **sent("r0.router.lab", query, "reply", 12.0),
                **sent("r0.router.lab", "swarmrec/v1/lab/unknown/**", "put", 5.0),  # not a type of ours
                **sent("zid:ff", query, "query", 7.0),  # an unnamed peer: not attributable
            },
            ("router", 2): sent("r1.router.lab", query, "reply", 12.0),
        }
    )
    assert key_bytes(pages, "lab") == {
        ("index-shard query", "query"): 60.0,
        ("index-shard query", "reply"): 24.0,
    }
