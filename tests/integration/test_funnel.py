"""The loop-closure funnel of a real lock-step swarm adds up, and ``swarmrec explain``
answers from the finished run's folder and from the live swarm.

Five robots (21 processes and a router) replay 500 synthetic frames in lock-step.
Each query's funnel is checked against what the offline evaluation says of the same
query, computed here from the frames: the candidates the shards return (partial
Jaccard, the published selection), the robots chosen (``checked_robots``); and
against the loop closures the descriptors hold and the counters they export. At the
last step, before the swarm stops, its descriptors are asked live (zenoh, the
gateway, the command line).
"""

from __future__ import annotations

import csv
import io
import json
from collections import Counter
from contextlib import redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.cli import main as cli_main
from swarmrec.core.descriptor import semantic_descriptors
from swarmrec.core.index import PARTIAL_EPSILON
from swarmrec.core.presets import get_preset
from swarmrec.core.selection import select_candidates
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.funnel import shard_cuts
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, PlacesSummary, main
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.wire import messages as pb

ROBOTS, FRAMES = 5, 500
STEPS = FRAMES // ROBOTS
PRESET = get_preset("paper")
MIN_SCORE = 0.3  # PlaceSettings' default loop_closure_min_score


@dataclass
class Live:
    """What the live swarm answered at its last step."""

    zenoh: dict[int, pb.ExplainReply] = field(default_factory=dict)
    gateway: pb.ExplainReply | None = None
    cli_pair: dict[str, Any] | None = None
    pair: tuple[int, int, int, int] | None = None
    cli_unseen: tuple[int, str] | None = None


@dataclass
class Finished:
    out: Path
    summary: PlacesSummary
    live: Live


def cli(*args: str) -> tuple[int, str]:
    """``swarmrec <args>`` in this process: (exit code, stdout)."""
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = cli_main(list(args))
    return code, buffer.getvalue()


def connection(swarm: LocalDeployment) -> list[str]:
    assert swarm.pki_dir is not None
    return ["--connect", swarm.endpoint, "--swarm", swarm.spec_swarm, "--pki-dir", str(swarm.pki_dir)]


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Finished:
    out = tmp_path_factory.mktemp("funnel") / "run"
    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=out,
        swarm="funnel",
        progress=False,
        plots=True,
    )
    held: list[LocalDeployment] = []
    live = Live()

    def hook(swarm: Deployment) -> None:
        assert isinstance(swarm, LocalDeployment)
        held.append(swarm)

    def on_step(t: int) -> None:
        if t != STEPS - 1:
            return
        swarm = held[0]
        with swarm.client(role="client") as client:
            live.zenoh = {f: client.explain(0, f) for f in range(STEPS)}
        with swarm.gateway_client() as gateway:
            live.gateway = gateway.explain(1, STEPS - 1)
        closed = [
            r
            for r in live.zenoh.values()
            if any(c.reason == pb.FunnelReason.FUNNEL_REASON_ACCEPTED for c in r.report.candidates)
        ]
        first = closed[0].report
        match = next(c for c in first.candidates if c.reason == pb.FunnelReason.FUNNEL_REASON_ACCEPTED)
        live.pair = (0, first.frame_index, match.robot_id, match.frame_index)
        code, text = cli(
            "explain",
            *map(str, live.pair[:2]),
            "--with",
            *map(str, live.pair[2:]),
            "--json",
            *connection(swarm),
        )
        assert code == 0, text
        live.cli_pair = json.loads(text)
        live.cli_unseen = cli("explain", "0", str(STEPS + 50), *connection(swarm))

    summary = main(settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step)
    return Finished(out, summary, live)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


@dataclass(frozen=True)
class Offline:
    """What the offline evaluation does at each query, recomputed from the frames."""

    candidates: dict[tuple[int, int], set[tuple[int, int]]]
    counts: dict[tuple[int, int], int]
    checked: dict[tuple[int, int], set[int]]


@pytest.fixture(scope="module")
def offline(finished: Finished) -> Offline:
    seq = as_on_the_wire(read_constellations(finished.out / "dataset"))
    blocks = split_frames(len(seq), ROBOTS)
    bounds = np.asarray(finished.summary.swarm.label_bounds)
    run = score_decentralized(seq, ROBOTS, PRESET, bounds=bounds)
    desc = semantic_descriptors(seq.constellations, seq.n_labels).astype(np.float64)
    valid = np.array([len(c) >= PRESET.min_objects for c in seq.constellations])
    candidates: dict[tuple[int, int], set[tuple[int, int]]] = {}
    counts: dict[tuple[int, int], int] = {}
    for r in range(ROBOTS):
        for t in range(1, len(blocks[r])):
            q = desc[blocks[r][t]]
            if not valid[blocks[r][t]]:
                continue
            found: list[tuple[int, int]] = []
            for k in range(len(bounds) - 1):
                lo, hi = bounds[k], bounds[k + 1]
                if not q[lo:hi].any():
                    continue
                # The published partial score over the robot-major n_robots x t slots of step t.
                dense = np.zeros(ROBOTS * t)
                for rr in range(ROBOTS):
                    for f in range(min(t, len(blocks[rr]))):
                        g = blocks[rr][f]
                        if valid[g]:
                            common = np.minimum(desc[g, lo:hi], q[lo:hi]).sum()
                            total = desc[g, lo:hi].sum() + q[lo:hi].sum() - common
                            dense[rr * t + f] = common / (total + PARTIAL_EPSILON)
                found += [(int(s) // t, int(s) % t) for s in select_candidates(dense, PRESET.n_ret)]
            candidates[(r, t)] = set(found)
            counts[(r, t)] = len(found)
    checked = {k: {int(x) for x in v} for k, v in run.checked_robots.items()}
    assert all(counts[k] == run.candidate_counts[k] for k in counts)  # the recomputation is the offline one
    return Offline(candidates, counts, checked)


@pytest.mark.slow
def test_every_candidate_ends_in_one_stage_and_the_funnel_is_the_offline_querys(
    finished: Finished, offline: Offline
) -> None:
    rows = _rows(finished.out / "funnel.csv")
    queries = _rows(finished.out / "funnel_queries.csv")
    by_query: dict[tuple[int, int], list[dict[str, str]]] = {}
    for row in rows:
        by_query.setdefault((int(row["query_robot"]), int(row["query_frame"])), []).append(row)
    assert len(queries) == FRAMES and finished.summary.queries.missing_slots == 0
    reasons = Counter(row["reason"] for row in rows)
    assert reasons["robot_not_chosen"] > 0 and reasons["accepted"] > 0 and reasons["too_few_matches"] > 0
    checked_queries = 0
    for q in queries:
        key = (int(q["robot"]), int(q["frame"]))
        mine = by_query.get(key, [])
        outcomes = {(int(r["candidate_robot"]), int(r["candidate_frame"])) for r in mine}
        assert len(outcomes) == len(mine), key  # one row, so one stage and one reason, per candidate
        if q["queried"] == "0":
            assert int(q["n_objects"]) < PRESET.min_objects and not mine
            continue
        # "group/shard:candidates": one entry per label group asked and answered.
        per_group = [int(item.partition(":")[2]) for item in q["shard_candidates"].split()]
        # Candidates returned = the shards' counts = what the offline query got; the distinct
        # ones are exactly the offline candidates, each in exactly one stage.
        assert sum(per_group) == int(q["n_candidates"]) == offline.counts.get(key, 0), key
        assert outcomes == offline.candidates.get(key, set()), key
        for r in mine:
            chosen = int(r["candidate_robot"]) in offline.checked[key]
            assert (r["reason"] == "robot_not_chosen") == (not chosen), (key, r)
            assert (
                r["stage"]
                == {
                    "robot_not_chosen": "selection",
                    "too_few_matches": "verification",
                    "below_score_threshold": "closure",
                    "own_recent_frame": "closure",
                    "outranked": "closure",
                    "accepted": "closure",
                }[r["reason"]]
            )
        checked_queries += 1
    assert checked_queries > 400


@pytest.mark.slow
def test_the_accepted_candidates_are_the_loop_closures_and_follow_the_rule(finished: Finished) -> None:
    rows = _rows(finished.out / "funnel.csv")
    accepted = {
        (int(r["query_robot"]), int(r["query_frame"]), int(r["candidate_robot"]), int(r["candidate_frame"])):
        float(r["score"])
        for r in rows
        if r["reason"] == "accepted"
    }  # fmt: skip
    closures = {
        (int(r["query_robot"]), int(r["query_frame"]), int(r["match_robot"]), int(r["match_frame"])):
        float(r["score"])
        for r in _rows(finished.out / "loop_closures.csv")
    }  # fmt: skip
    assert len(closures) == finished.summary.loop_closures.count > 10
    assert accepted.keys() == closures.keys()
    assert all(abs(accepted[k] - closures[k]) < 1e-6 for k in closures)  # the csv writes 6 digits
    # The rule, read here from the scores: the first scored candidate (best first, then robot
    # and frame) at least MIN_SCORE good that is no own frame within the exclusion.
    by_query: dict[tuple[int, int], list[tuple[float, int, int, str]]] = {}
    for r in rows:
        if r["stage"] == "closure":
            q = (int(r["query_robot"]), int(r["query_frame"]))
            by_query.setdefault(q, []).append(
                (-float(r["score"]), int(r["candidate_robot"]), int(r["candidate_frame"]), r["reason"])
            )
    for (qr, qf), scored in by_query.items():
        first = True
        for neg, robot, frame, reason in sorted(scored):
            if -neg < MIN_SCORE:
                expected = "below_score_threshold"
            elif robot == qr and abs(frame - qf) <= PRESET.exclusion:
                expected = "own_recent_frame"
            elif first:
                expected, first = "accepted", False
            else:
                expected = "outranked"
            assert reason == expected, (qr, qf, robot, frame)
    funnel = finished.summary.funnel
    assert funnel is not None
    assert funnel.accepted_equals_loop_closures and funnel.inconsistent_queries == 0


@pytest.mark.slow
def test_the_counters_the_descriptors_export_equal_the_funnel(finished: Finished) -> None:
    funnel = finished.summary.funnel
    assert funnel is not None
    rows = _rows(finished.out / "funnel.csv")
    scraped = {k: int(v) for k, v in funnel.scraped_by_reason.items() if v}
    assert scraped == dict(Counter(r["reason"] for r in rows))
    assert funnel.frames == FRAMES and funnel.queried + funnel.too_few_objects == FRAMES
    # The funnel is in the report, not between robots: no report travels between them (the
    # other messages between robots are the query's and the elastic index's).
    between = set(finished.summary.bytes.per_query_by_message)
    assert {"PartialQuery", "CandidatesReply", "VerifyRequest", "VerifyReply"} <= between
    assert "QueryReport" not in between
    assert finished.summary.offline_check is not None and finished.summary.offline_check.identical
    assert funnel.report_bytes_mean > funnel.report_bytes_mean_without_funnel
    assert (finished.out / "funnel.png").stat().st_size > 0


@pytest.mark.slow
def test_the_shards_answers_recomputed_for_explain_are_the_live_ones(finished: Finished) -> None:
    seq = read_constellations(finished.out / "dataset")
    blocks = split_frames(len(seq), ROBOTS)
    desc = semantic_descriptors(seq.constellations, seq.n_labels)
    queries = {(int(q["robot"]), int(q["frame"])): q for q in _rows(finished.out / "funnel_queries.csv")}
    stored = np.zeros(len(seq), np.bool_)
    for (r, f), q in queries.items():
        stored[blocks[r][f]] = q["queried"] == "1"
    rows = _rows(finished.out / "funnel.csv")
    sample = sorted({(int(r["query_robot"]), int(r["query_frame"])) for r in rows})[::25]
    assert len(sample) > 10
    for key in sample:
        groups = {}
        for item in queries[key]["shard_candidates"].split():
            where, _, n = item.partition(":")
            groups[int(where.partition("/")[0])] = int(n)
        seen: dict[int, int] = {}
        for r in rows:
            if (int(r["query_robot"]), int(r["query_frame"])) != key:
                continue
            cand = (int(r["candidate_robot"]), int(r["candidate_frame"]))
            cuts = shard_cuts(
                desc,
                blocks,
                finished.summary.swarm.label_bounds,
                stored,
                PRESET.n_ret,
                key,
                cand,
                lockstep=True,
            )
            assert any(c.returned_it for c in cuts), (key, cand)
            seen |= {c.group: len(c.returned or ()) for c in cuts}
        assert all(groups[k] == n for k, n in seen.items()), (key, groups, seen)


def _explain_run(finished: Finished, *args: str) -> dict[str, Any]:
    code, text = cli("explain", *args, "--run", str(finished.out), "--json")
    assert code == 0, text
    result: dict[str, Any] = json.loads(text)
    return result


@pytest.mark.slow
def test_explain_on_the_run_folder_says_where_each_pair_stopped(finished: Finished) -> None:
    rows = _rows(finished.out / "funnel.csv")
    for reason in ("accepted", "robot_not_chosen", "too_few_matches", "below_score_threshold"):
        row = next(r for r in rows if r["reason"] == reason)
        got = _explain_run(
            finished,
            row["query_robot"],
            row["query_frame"],
            "--with",
            row["candidate_robot"],
            row["candidate_frame"],
        )
        assert (got["pair"]["stage"], got["pair"]["reason"]) == (row["stage"], reason)
    # Without --with, every candidate of the frame, as funnel.csv has them.
    row = next(r for r in rows if r["reason"] == "robot_not_chosen")
    got = _explain_run(finished, row["query_robot"], row["query_frame"])
    mine = [
        r for r in rows if (r["query_robot"], r["query_frame"]) == (row["query_robot"], row["query_frame"])
    ]
    assert [(c["robot"], c["frame"], c["reason"]) for c in got["candidates"]] == [
        (int(r["candidate_robot"]), int(r["candidate_frame"]), r["reason"]) for r in mine
    ]


@pytest.mark.slow
def test_explain_finds_a_never_candidate_below_the_shards_cut(finished: Finished) -> None:
    seq = read_constellations(finished.out / "dataset")
    blocks = split_frames(len(seq), ROBOTS)
    desc = semantic_descriptors(seq.constellations, seq.n_labels)
    rows = _rows(finished.out / "funnel.csv")
    returned = {
        (int(r["query_robot"]), int(r["query_frame"]), int(r["candidate_robot"]), int(r["candidate_frame"]))
        for r in rows
    }
    # A queried frame of robot 1 past step 50, and an earlier frame of robot 0 that queried
    # too, has a label in common with it, and no shard returned.
    queried = {
        (int(q["robot"]), int(q["frame"]))
        for q in _rows(finished.out / "funnel_queries.csv")
        if q["queried"] == "1"
    }
    q = next((1, t) for t in range(50, STEPS) if (1, t) in queried)
    other = next(
        (0, f)
        for f in range(q[1] - 1, 0, -1)
        if (*q, 0, f) not in returned
        and (0, f) in queried
        and np.minimum(desc[blocks[1][q[1]]], desc[blocks[0][f]]).any()
    )
    got = _explain_run(finished, str(q[0]), str(q[1]), "--with", str(other[0]), str(other[1]))
    pair = got["pair"]
    assert (pair["stage"], pair["reason"]) == ("shard", "below_shard_cut")
    assert pair["why"].startswith("never a candidate: its descriptor scored below the shard's top n_ret = 4")
    assert pair["shards"]
    for shard in pair["shards"]:
        assert shard["returned"] is False and shard["cut"] is not None and shard["score"] <= shard["cut"]
    code, text = cli(
        "explain", str(q[0]), str(q[1]), "--with", str(other[0]), str(other[1]), "--run", str(finished.out)
    )
    assert code == 0 and "never a candidate" in text and "the other way:" in text


@pytest.mark.slow
def test_explain_live_answers_the_runs_funnel(finished: Finished) -> None:
    live = finished.live
    rows = _rows(finished.out / "funnel.csv")
    assert len(live.zenoh) == STEPS
    for f, reply in live.zenoh.items():
        assert reply.status == pb.ReportStatus.REPORT_STATUS_HELD and reply.report.frame_index == f
        mine = [
            (int(r["candidate_robot"]), int(r["candidate_frame"]), r["reason"])
            for r in rows
            if (r["query_robot"], r["query_frame"]) == ("0", str(f))
        ]
        got = [
            (c.robot_id, c.frame_index, pb.FunnelReason.Name(c.reason).removeprefix("FUNNEL_REASON_").lower())
            for c in reply.report.candidates
        ]
        assert got == mine, f
    assert live.zenoh[0].reports_held == STEPS and live.zenoh[0].loop_closure_min_score == MIN_SCORE
    # The gateway asks the same descriptor.
    assert live.gateway is not None and live.gateway.status == pb.ReportStatus.REPORT_STATUS_HELD
    assert live.gateway.report.robot_id == 1 and live.gateway.report.frame_index == STEPS - 1
    # The command line, live, on a pair: the run folder says the same.
    assert live.cli_pair is not None and live.pair is not None
    assert (live.cli_pair["pair"]["stage"], live.cli_pair["pair"]["reason"]) == ("closure", "accepted")
    from_run = _explain_run(finished, *map(str, live.pair[:2]), "--with", *map(str, live.pair[2:]))
    assert from_run["pair"] == live.cli_pair["pair"]
    assert from_run["candidates"] == live.cli_pair["candidates"]
    # A frame the descriptor never processed: said, exit code 3.
    assert live.cli_unseen is not None
    code, text = live.cli_unseen
    assert code == 3 and f"has not processed frame {STEPS + 50} since it started" in text
