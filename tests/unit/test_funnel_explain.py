"""Explaining a pair from a run's files: the shards' answers recomputed offline
(swarmrec.evaluation.funnel) and the explanation of hand-written funnel files
(swarmrec.experiments.places.explain). Every expected number is worked out by hand."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.evaluation.funnel import shard_cuts
from swarmrec.experiments.places.explain import RunFolder, explain_run

# Two robots of three frames (robot 1's frame f is global frame 3 + f), four labels in
# two ranges: shard 0 owns labels 0-1, shard 1 labels 2-3.
BLOCKS = [range(0, 3), range(3, 6)]
BOUNDS = [0, 2, 4]
DESCRIPTORS = np.array(
    [
        [2, 0, 1, 0],  # robot 0 frame 0
        [1, 1, 0, 0],  # robot 0 frame 1
        [2, 1, 0, 1],  # robot 0 frame 2: the query, at lock-step step 2
        [2, 1, 0, 0],  # robot 1 frame 0
        [0, 1, 0, 1],  # robot 1 frame 1
        [2, 1, 0, 1],  # robot 1 frame 2: same step as the query, not stored yet
    ],
    np.int64,
)
STORED = np.ones(6, np.bool_)
QUERY = (0, 2)


def test_a_frame_below_the_cut_gets_its_partial_score_rank_and_the_cut() -> None:
    # Shard 0 sees the query's [2, 1] against frames of steps 0 and 1:
    #   robot 0 frame 0 [2, 0]: common 2, total 2 + 3 - 2 = 3 -> 2/3
    #   robot 0 frame 1 [1, 1]: common 2, total 3 -> 2/3
    #   robot 1 frame 0 [2, 1]: common 3, total 3 -> 1, the one returned (n_ret = 1)
    #   robot 1 frame 1 [0, 1]: common 1, total 3 -> 1/3
    # Robot 0 frame 0 shares no label of shard 1 with the query ([1, 0] against [0, 1]).
    (cut,) = shard_cuts(DESCRIPTORS, BLOCKS, BOUNDS, STORED, 1, QUERY, (0, 0), lockstep=True)
    assert (cut.group, cut.lo, cut.hi) == (0, 0, 2)
    assert cut.score == pytest.approx(2 / 3)
    # Equal scores rank in (robot, frame) order: robot 0 frame 0 before frame 1.
    assert cut.rank == 2
    assert cut.returned_it is False
    assert cut.cut == pytest.approx(1.0)
    assert cut.returned is not None and [(c.robot, c.frame) for c in cut.returned] == [(1, 0)]


def test_a_frame_the_shard_returned_is_returned_on_that_shard_only() -> None:
    # Robot 1 frame 1 [0, 1 | 0, 1]: shard 0 1/3 (rank 4 of 4); on shard 1, [0, 1] against
    # the query's [0, 1] is 1, and robot 0 frame 0's [1, 0] scores 0: robot 1 frame 1 is returned.
    cuts = shard_cuts(DESCRIPTORS, BLOCKS, BOUNDS, STORED, 1, QUERY, (1, 1), lockstep=True)
    assert [(c.group, c.rank, c.returned_it) for c in cuts] == [(0, 4, False), (1, 1, True)]
    assert [c.score for c in cuts] == pytest.approx([1 / 3, 1.0])
    assert cuts[1].cut == pytest.approx(1.0)


def test_a_frame_of_the_same_step_is_not_stored_yet_in_lock_step() -> None:
    # Robot 1 frame 2 equals the query ([2, 1] on shard 0: score 1), but step 2's shards
    # search only steps 0 and 1.
    cuts = shard_cuts(DESCRIPTORS, BLOCKS, BOUNDS, STORED, 1, QUERY, (1, 2), lockstep=True)
    assert [(c.group, c.rank, c.returned_it) for c in cuts] == [(0, None, False), (1, None, False)]
    assert [c.score for c in cuts] == pytest.approx([1.0, 1.0])


def test_a_frame_that_was_not_stored_is_never_ranked() -> None:
    stored = STORED.copy()
    stored[3] = False  # robot 1 frame 0 did not query: no shard holds it
    (cut, _) = shard_cuts(DESCRIPTORS, BLOCKS, BOUNDS, stored, 1, QUERY, (1, 1), lockstep=True)
    # Without robot 1 frame 0, shard 0 returns robot 0 frame 0 (2/3, first of the tie).
    assert cut.returned is not None and [(c.robot, c.frame) for c in cut.returned] == [(0, 0)]
    assert cut.cut == pytest.approx(2 / 3) and cut.rank == 3


def test_a_paced_run_knows_the_partial_scores_but_not_the_cut() -> None:
    (cut,) = shard_cuts(DESCRIPTORS, BLOCKS, BOUNDS, STORED, 1, QUERY, (0, 0), lockstep=False)
    assert cut.score == pytest.approx(2 / 3)
    assert cut.returned is None and cut.returned_it is None and cut.cut is None and cut.rank is None


# --- explaining hand-written run files ----------------------------------------------------


def _run(tmp: Path, pace: str = "lockstep") -> Path:
    """A 3-robot run of 12 frames (4 per robot) whose funnel files are written by hand."""
    summary = {
        "dataset": {"frames": 12, "folder": str(tmp / "absent")},
        "swarm": {
            "robots": 3,
            "pace": pace,
            "label_bounds": [0, 26, 53, 80],
            "preset": {"min_objects": 3, "exclusion": 100, "n_ret": 4, "n_fq": 1},
        },
        "loop_closures": {"min_score": 0.3},
    }
    (tmp / "summary.json").write_text(json.dumps(summary))
    (tmp / "funnel_queries.csv").write_text(
        "robot,frame,frame_id,queried,n_objects,n_candidates,shard_candidates,failed_shards,"
        "verified_robots,failed_verifiers,loop_closure\n"
        "0,0,t00,1,4,0,,,,,\n"
        "0,3,t03,1,7,5,0/0:2 1/1:3,2,0 1,,1:1\n"
        "1,1,t11,1,5,0,,,,,\n"
        "2,2,t22,0,2,0,,,,,\n"
    )
    (tmp / "funnel.csv").write_text(
        "query_robot,query_frame,candidate_robot,candidate_frame,stage,reason,score,query_frame_id,"
        "candidate_frame_id\n"
        "0,3,0,1,closure,own_recent_frame,0.9,t03,t01\n"
        "0,3,1,1,closure,accepted,0.5,t03,t11\n"
        "0,3,1,2,closure,outranked,0.4,t03,t12\n"
        "0,3,2,0,selection,robot_not_chosen,,t03,t20\n"
    )
    return tmp


def test_every_candidate_of_a_run_frame_is_explained_with_its_stage(tmp_path: Path) -> None:
    ex = explain_run(RunFolder(_run(tmp_path)), 0, 3)
    got = [(c["robot"], c["frame"], c["stage"], c["reason"], c["score"]) for c in ex.candidates()]
    assert got == [
        (0, 1, "closure", "own_recent_frame", 0.9),
        (1, 1, "closure", "accepted", 0.5),
        (1, 2, "closure", "outranked", 0.4),
        (2, 0, "selection", "robot_not_chosen", None),
    ]
    whys = [c["why"] for c in ex.candidates()]
    assert whys[0] == "the robot's own frame, 2 frames from the query: within the exclusion of 100"
    assert whys[1] == "the loop closure of robot 0 frame 3, score 0.5000"
    assert whys[2] == (
        "passed the rule with 0.4000, but robot 1 frame 1 (0.5000) scored higher: the loop closure"
    )
    assert whys[3] == "robot 2 was not among the n_fq = 1 robots with the most candidates (verified: 0 1)"
    text = "\n".join(ex.lines())
    assert "loop closure: robot 1 frame 1" in text
    assert "shards answered (candidates): 0 (2), 1 (3)" in text
    assert "shards that did not answer: 2" in text


def test_a_pair_is_explained_both_ways(tmp_path: Path) -> None:
    ex = explain_run(RunFolder(_run(tmp_path)), 0, 3, (1, 1))
    assert ex.pair is not None and (ex.pair.stage, ex.pair.reason) == ("closure", "accepted")
    # Robot 1 frame 1 queried at step 1, before robot 0 frame 3 came (step 3).
    assert ex.reverse is not None and (ex.reverse.stage, ex.reverse.reason) == ("shard", "below_shard_cut")
    assert "step 1's shards search only frames of earlier steps" in ex.reverse.why


def test_a_pair_with_a_frame_of_too_few_objects_was_never_a_candidate(tmp_path: Path) -> None:
    ex = explain_run(RunFolder(_run(tmp_path)), 0, 3, (2, 2))
    assert ex.pair is not None and ex.pair.reason == "below_shard_cut"
    assert ex.pair.why == (
        "never a candidate: robot 2 frame 2 had 2 objects, fewer than min_objects (3); "
        "it never queried, so no shard stored it"
    )
    # And its own query never ran.
    assert ex.reverse is not None and (ex.reverse.stage, ex.reverse.reason) == ("query", "too_few_objects")


def test_a_missing_dataset_is_said_not_raised(tmp_path: Path) -> None:
    # Robot 0 frame 0 queried at step 0, before robot 1 frame 1, and is no candidate of it:
    # the shards' scores need the run's constellations, which this run folder does not have.
    ex = explain_run(RunFolder(_run(tmp_path)), 1, 1, (0, 0))
    assert ex.pair is not None and ex.pair.reason == "below_shard_cut"
    assert "the run's constellations cannot be read" in ex.pair.why


def test_a_frame_without_a_report_and_a_frame_outside_the_run(tmp_path: Path) -> None:
    run = RunFolder(_run(tmp_path))
    ex = explain_run(run, 2, 3)
    assert not ex.found and ex.status == "not_in_run"
    with pytest.raises(ConfigError, match="no frame 4 of robot 0"):
        explain_run(run, 0, 4)
    with pytest.raises(ConfigError, match="not a finished run"):
        RunFolder(tmp_path / "elsewhere")


def test_a_folder_of_both_methods_points_to_the_constellation_report(tmp_path: Path) -> None:
    (tmp_path / "constellations").mkdir()
    (tmp_path / "constellations" / "summary.json").write_text("{}")

    with pytest.raises(ConfigError, match=r"reports of both methods: .*--run .*constellations\)"):
        RunFolder(tmp_path)


def test_a_folder_that_is_no_run_says_which_file_is_missing(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"a loop-closure funnel \(no summary\.json\)"):
        RunFolder(tmp_path)
