"""The client command line against a running swarm, as a user runs it.

A 2-robot swarm (router, and detector, descriptor, index-shard and verifier
per robot, all real processes) replays the first steps of the synthetic
office in lock-step; then ``python -m swarmrec members|query|loop-closures``
run as separate processes with ``--connect`` pointing at the swarm's router.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm
from tests.integration.support import write_office

N_ROBOTS, STEPS = 2, 5
KINDS = ("detector", "descriptor", "index-shard", "verifier")


@dataclass
class Running:
    swarm: LocalDeployment
    dataset: Path
    reports: list[pb.QueryReport]


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    tmp = tmp_path_factory.mktemp("cli")
    dataset = write_office(tmp / "dataset", n_frames=200)
    parts = (PlaceSettings(lockstep=True), DetectorSettings(dataset=str(dataset)))
    with running_swarm(tmp, "cli-swarm", *parts, robots=N_ROBOTS) as swarm:
        reports: list[pb.QueryReport] = []
        with swarm.client() as client:
            for t in range(STEPS):
                replies = client.step(t, timeout_s=10)
                assert all(isinstance(r, pb.StepReply) for r in replies), replies
                assert sorted(r.robot_id for r in replies if isinstance(r, pb.StepReply)) == [0, 1]
                reports += [r.report for r in replies if isinstance(r, pb.StepReply)]
        yield Running(swarm, dataset, reports)


def cli(
    running: Running, *args: str, swarm: str | None = None, connect: str | None = None
) -> subprocess.CompletedProcess[str]:
    """``python -m swarmrec <args> --connect <router> --swarm <name>``, as a separate process."""
    return subprocess.run(
        [
            sys.executable, "-m", "swarmrec", *args,
            "--connect", connect or running.swarm.endpoint,
            "--swarm", swarm or running.swarm.spec_swarm,
            "--pki-dir", str(running.swarm.pki_dir),
            "--identity", f"client.cli.{running.swarm.spec_swarm}",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )  # fmt: skip


def test_members_lists_every_service_and_the_shard_ranges_cover_the_label_list(running: Running) -> None:
    done = cli(running, "members", "--json")

    assert done.returncode == 0, done.stderr
    members = json.loads(done.stdout)
    assert sorted((m["kind"], m["robot"]) for m in members) == sorted(
        [("router", 0), ("gateway", 0)] + [(k, r) for k in KINDS for r in range(N_ROBOTS)]
    )
    # Two replicas a group (the default): each shard of the two owns both label groups.
    ranges = [sorted(tuple(r) for r in m["label_ranges"]) for m in members if m["kind"] == "index-shard"]
    assert ranges == [[(0, 40), (40, 80)], [(0, 40), (40, 80)]]
    assert all(m["label_range"] is None for m in members if m["kind"] != "index-shard")
    assert {m["n_labels"] for m in members if m["kind"] not in ("router", "gateway")} == {80}
    assert all(m["metrics_url"].startswith("http://127.0.0.1:") for m in members)


def test_members_prints_a_table_by_default(running: Running) -> None:
    done = cli(running, "members")

    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].split() == ["service", "robot", "labels", "stored", "version", "metrics"]
    assert len(lines) == 1 + 4 * N_ROBOTS + 2  # and the router and the gateway
    assert any(line.split()[:3] == ["index-shard", "1", "0-40,40-80"] for line in lines)
    # Each verifier holds its own robot's replayed frames, one a step.
    verifiers = [line.split() for line in lines if line.startswith("verifier")]
    assert [(v[1], v[2]) for v in verifiers] == [(str(r), str(STEPS)) for r in range(N_ROBOTS)]


def _replayed_frame(running: Running) -> tuple[int, int, Path]:
    """A replayed frame with >= min_objects objects whose descriptor no other
    replayed frame shares, as (robot, frame index, its constellation file)."""
    seq = read_constellations(running.dataset)
    blocks = split_frames(len(seq), N_ROBOTS)
    replayed = [(r, t, blocks[r][t]) for r in range(N_ROBOTS) for t in range(STEPS)]
    descs = {g: tuple(semantic_descriptor(seq.constellations[g], seq.n_labels)) for _, _, g in replayed}
    min_objects = get_preset("paper").min_objects
    for r, t, g in replayed:
        unique = sum(d == descs[g] for d in descs.values()) == 1
        if len(seq.constellations[g]) >= min_objects and unique:
            return r, t, running.dataset / "constellations" / f"{seq.frame_ids[g]}.txt"
    pytest.fail("no replayed frame with a unique descriptor")


def test_query_of_a_replayed_frame_ranks_its_own_stored_frame_first_with_score_one(
    running: Running,
) -> None:
    robot, frame, path = _replayed_frame(running)
    assert any(rep.robot_id == robot and rep.frame_index == frame and rep.queried for rep in running.reports)

    done = cli(running, "query", str(path), "--json")

    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    matches = result["matches"]
    assert matches, result
    assert (matches[0]["robot"], matches[0]["frame"]) == (robot, frame), matches
    assert matches[0]["score"] == 1.0 and matches[0]["semantic_score"] == 1.0
    assert matches[0]["n_matched"] == len([ln for ln in path.read_text().splitlines() if ln.strip()])
    scores = [m["score"] for m in matches]
    assert scores == sorted(scores, reverse=True)
    assert result["candidates"] > 0 and robot in result["verified_robots"]
    assert result["failed_shards"] == [] and result["failed_verifiers"] == []


def test_query_stores_nothing(running: Running) -> None:
    _, _, path = _replayed_frame(running)
    first = json.loads(cli(running, "query", str(path), "--json").stdout)
    again = json.loads(cli(running, "query", str(path), "--json").stdout)
    for result in (first, again):
        del result["duration_ms"]
    assert again == first


def test_loop_closures_of_a_robot_exits_zero_with_what_the_library_returns(running: Running) -> None:
    done = cli(running, "loop-closures", "0", "--json")
    none = cli(running, "loop-closures", "0", "--json", "--min-score", "1.5")
    table = cli(running, "loop-closures", "1")

    assert done.returncode == none.returncode == table.returncode == 0, (
        done.stderr + none.stderr + table.stderr
    )
    with running.swarm.client() as client:
        expected = client.loop_closures(0)
    assert json.loads(done.stdout) == [
        {
            "query_frame": c.query_frame_index,
            "match_robot": c.match_robot_id,
            "match_frame": c.match_frame_index,
            "score": c.score,
            "n_matched": c.n_matched,
        }
        for c in expected
    ]
    assert json.loads(none.stdout) == []
    assert table.stdout.startswith("robot 1: ") and "loop closures" in table.stdout.splitlines()[0]


def test_a_query_to_a_swarm_with_nobody_in_it_fails_with_a_clear_message(
    running: Running, tmp_path: Path
) -> None:
    path = tmp_path / "1.0.txt"
    path.write_text("cup 0.1 0.2 1.5\nchair 1 2 3\nbook 0 0 1\n")

    done = cli(running, "query", str(path), "--timeout", "1", swarm="nobody-here")

    assert done.returncode != 0
    assert done.stdout == ""
    assert "swarmrec query: error:" in done.stderr and "no index shard is alive" in done.stderr
    assert "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_members_of_a_swarm_with_nobody_in_it_says_so(running: Running) -> None:
    done = cli(running, "members", "--timeout", "1", swarm="nobody-here")

    assert done.returncode != 0
    assert "no live member in swarm 'nobody-here'" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_query_of_a_file_that_does_not_parse_names_the_file_and_line(
    running: Running, tmp_path: Path
) -> None:
    path = tmp_path / "bad.txt"
    path.write_text("cup 0.1 0.2 1.5\nunicorn 1 2 3\n")

    done = cli(running, "query", str(path))

    assert done.returncode == 2
    assert f"{path}:2" in done.stderr and "unicorn" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize(
    "args",
    [("members",), ("loop-closures", "0"), ("query", "QUERY")],
    ids=["members", "loop-closures", "query"],
)
def test_with_no_router_listening_every_command_says_so_in_one_line(
    running: Running, tmp_path: Path, args: tuple[str, ...]
) -> None:
    """The swarm's PKI, but an address where no router listens (the swarm's port, stopped:
    a port taken and released by this test): one line naming the address and what to check,
    exit code 2, as the gRPC path answers."""
    path = tmp_path / "q.txt"
    path.write_text("cup 0.1 0.2 1.5\nchair 1 2 3\nbook 0 0 1\n")
    args = tuple(str(path) if a == "QUERY" else a for a in args)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    done = cli(running, *args, connect=f"tls/127.0.0.1:{port}")

    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert f"tls/127.0.0.1:{port}" in lines[0] and "is the swarm running" in lines[0]
    assert "Traceback" not in done.stderr and "ZError" not in done.stderr
