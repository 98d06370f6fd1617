"""The compiled range index (dataplane/src/index.rs) against the reference.

The compiled index shard will keep its label groups in this index; here it is checked
alone, through ``swarmrec-dataplane compute``, against :class:`swarmrec.core.index.RangeIndex`
(the Python shard's index, which the offline evaluation and the published scripts agree
with). Random indexes built to tie (a few bins of counts 0-3, so equal partial scores are
everywhere, frames replaced in place, robots with gaps) are fed the same stores in the
same order and asked the same queries, in lock-step (``before``: the published dense
layout, numpy's argsort deciding ties at the cut) and free-running (ties at the cut in
slot order): every candidate list, in order, with every score to the bit, and the rows
read back (arrival order), frame counts and stored slices must be the reference's.
"""

from __future__ import annotations

import itertools
import random
from typing import Any

import numpy as np
import pytest

from swarmrec.core.index import RangeIndex
from tests.integration.support import compute


def random_case(rng: random.Random) -> dict[str, Any]:
    lo = rng.randrange(0, 60)
    width = rng.randint(1, 7)
    n_robots = rng.randint(1, 6)
    stores: list[list[Any]] = []
    for _ in range(rng.randint(0, 120)):
        robot = rng.randrange(n_robots)
        frame = rng.randrange(rng.choice([5, 40, 300]))
        counts = [float(rng.choice([0, 0, 1, 1, 2, 3])) for _ in range(width)]
        stores.append([robot, frame, counts])
    frames = max((f for _, f, _ in stores), default=0) + 1
    queries = []
    for _ in range(12):
        counts = [float(rng.choice([0, 1, 1, 2])) for _ in range(width)]
        before = rng.choice([None, None, rng.randint(0, frames + 3)])
        queries.append({"counts": counts, "n_ret": rng.choice([1, 2, 3, 4, 10]), "before": before})
    gets = [[rng.randrange(n_robots + 1), rng.randrange(frames + 2)] for _ in range(10)]
    return {
        "op": "range_index",
        "lo": lo,
        "hi": lo + width,
        "n_robots": n_robots,
        "stores": stores,
        "queries": queries,
        "gets": gets,
    }


def reference(case: dict[str, Any]) -> dict[str, Any]:
    index = RangeIndex(case["lo"], case["hi"], case["n_robots"])
    for robot, frame, counts in case["stores"]:
        index.add(robot, frame, counts)
    candidates = [
        [[c.robot, c.frame, c.score] for c in index.candidates(q["counts"], q["n_ret"], before=q["before"])]
        for q in case["queries"]
    ]
    rows = [[r, f, counts.tolist()] for r, f, counts in index.rows(0, index.size)]
    gets = []
    for robot, frame in case["gets"]:
        got = index.get(robot, frame) if robot < case["n_robots"] else None
        gets.append(None if got is None else got.tolist())
    frames_of = [index.frames_of(r) for r in range(case["n_robots"])]
    return {"candidates": candidates, "rows": rows, "frames_of": frames_of, "get": gets}


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_index_answers_as_the_reference(seed: int) -> None:
    rng = random.Random(seed)
    cases = [random_case(rng) for _ in range(60)]
    for case, got in zip(cases, compute(cases), strict=True):
        want = reference(case)
        # Candidates compared as lists of [robot, frame, score]: order and every bit of the score.
        assert got["candidates"] == want["candidates"], case
        assert got["rows"] == want["rows"]
        assert got["frames_of"] == want["frames_of"]
        assert got["get"] == want["get"]


def test_the_cases_exercise_ties_at_the_cut_in_lock_step() -> None:
    """Most lock-step queries with more positive scores than n_ret have equal scores at the
    cut, so numpy's argsort of the dense layout decides (else the comparison proves little)."""
    rng = random.Random(0)
    straddled = busy = 0
    for case in (random_case(rng) for _ in range(60)):
        index = RangeIndex(case["lo"], case["hi"], case["n_robots"])
        for robot, frame, counts in case["stores"]:
            index.add(robot, frame, counts)
        for q in case["queries"]:
            if q["before"] is None or q["before"] <= 0:
                continue
            everything = index.candidates(q["counts"], 10_000, before=q["before"])
            scores = np.array([c.score for c in everything])
            if scores.shape[0] > q["n_ret"]:
                busy += 1
                straddled += int(scores[q["n_ret"] - 1] == scores[q["n_ret"]])
    assert busy > 50 and straddled > busy // 2, (busy, straddled)


# --- the placement a compiled shard follows ----------------------------------------------


def random_placement(rng: random.Random) -> tuple[dict[str, Any], int]:
    """A placement message (as JSON) for ``n_labels``: valid, then often broken one way."""
    n_labels = rng.randint(1, 90)
    cuts = (
        sorted(rng.sample(range(1, n_labels), min(n_labels - 1, rng.randint(0, 6)))) if n_labels > 1 else []
    )
    bounds = [0, *cuts, n_labels]
    members = rng.sample(range(12), rng.randint(1, 6))
    groups = []
    for _ in range(len(bounds) - 1):
        owners = rng.sample(members, rng.randint(1, len(members)))
        others = [m for m in members if m not in owners]
        learners = rng.sample(others, rng.randint(0, len(others))) if others and rng.random() < 0.4 else []
        leaving = (
            rng.sample(owners, rng.randint(0, len(owners) - (0 if learners else 1)))
            if rng.random() < 0.3
            else []
        )
        groups.append({"owners": owners, "learners": learners, "leaving": leaving})
    msg = {
        "version": rng.randrange(50),
        "group_bounds": bounds,
        "groups": groups,
        "members": members,
        "replicas": 2,
    }
    g = rng.randrange(len(groups))
    match rng.choice(["valid"] * 4 + ["no owner", "twice", "outsider", "learner owns", "member twice",
                                       "leaving outsider", "all leave", "gap", "cover", "count",
                                       "replicas", "big id", "empty"]):  # fmt: skip
        case "no owner":
            groups[g]["owners"] = []
        case "twice":
            groups[g]["owners"] = groups[g]["owners"] * 2
        case "outsider":
            groups[g]["owners"].append(rng.randrange(100, 200))
        case "learner owns":
            groups[g]["learners"].append(groups[g]["owners"][0])
        case "member twice":
            msg["members"] = members + members[:1]
        case "leaving outsider":
            groups[g]["leaving"].append(rng.randrange(100, 200))
        case "all leave":
            groups[g]["leaving"], groups[g]["learners"] = list(groups[g]["owners"]), []
        case "gap" if len(bounds) > 2:
            bounds[1], bounds[2] = bounds[2], bounds[1]
        case "cover":
            bounds[-1] += 1
        case "count":
            groups.append({"owners": [members[0]], "learners": [], "leaving": []})
        case "replicas":
            msg["replicas"] = rng.choice([0, 65])
        case "big id":
            msg["members"] = [*members, 1_000_000]
        case "empty":
            msg["group_bounds"] = []
    return msg, n_labels


def placement_reference(
    msg: dict[str, Any], n_labels: int, shards: list[int], ranges: list[list[int]]
) -> Any:
    from swarmrec.errors import MalformedMessageError
    from swarmrec.wire import messages as pb
    from swarmrec.wire.placement import placement_from_proto

    wire = pb.Placement(
        version=msg["version"],
        group_bounds=msg["group_bounds"],
        groups=[pb.GroupOwners(**g) for g in msg["groups"]],
        members=msg["members"],
        replicas=msg["replicas"],
    )
    try:
        p = placement_from_proto(wire, n_labels)
    except MalformedMessageError as e:
        return {"refused": str(e)}
    return {
        "groups_of": [p.groups_of(s) for s in shards],
        "learning": [p.learning(s) for s in shards],
        "store_targets": [list(p.store_targets(g)) for g in range(len(p.groups))],
        "settled": p.settled,
        "group_of_range": [p.group_of_range(lo, hi) for lo, hi in ranges],
        "round_trip": True,
    }


def test_the_compiled_placement_checks_and_answers_as_the_reference() -> None:
    rng = random.Random(7)
    cases, expected = [], []
    for _ in range(400):
        msg, n_labels = random_placement(rng)
        shards = list(range(13))
        bounds = msg["group_bounds"]
        ranges = [[lo, hi] for lo, hi in itertools.pairwise(bounds)] + [[0, n_labels], [1, 2]]
        cases.append(
            {"op": "placement", "placement": msg, "n_labels": n_labels, "shards": shards, "ranges": ranges}
        )
        expected.append(placement_reference(msg, n_labels, shards, ranges))
    got = compute(cases)
    refused = sum(1 for e in expected if "refused" in e)
    assert 100 < refused < 350  # both kinds are well represented
    for case, g, e in zip(cases, got, expected, strict=True):
        assert g == e, case
