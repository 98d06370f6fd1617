"""The loop-closure funnel's classification, on hand-built queries whose outcomes are
written out by hand (swarmrec.core.funnel)."""

from __future__ import annotations

import pytest

from swarmrec.core.funnel import (
    STAGE_OF,
    CandidateOutcome,
    ClosureRule,
    Reason,
    Stage,
    classify,
    passed_stages,
    settle,
    verifier_failure,
)
from swarmrec.errors import NoReply, RemoteError, ReplyTimeout
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import outcomes_from_proto, outcomes_to_proto
from tests.conftest import REPO

R = Reason


def test_every_candidate_of_a_query_ends_in_the_stage_its_verifier_and_robot_put_it() -> None:
    # Shards returned robot 1's frames 10 and 11 (11 twice: two label ranges), robot 2's
    # frame 5, robot 3's frame 7 and robot 4's frame 2. Robots 1, 2 and 3 were asked;
    # robot 3's verifier timed out; robot 1 answered frame 10 with 0.5, nothing for 11.
    got = classify(
        [(1, 11), (2, 5), (1, 10), (1, 11), (3, 7), (4, 2)],
        asked={1, 2, 3},
        failures={3: R.VERIFIER_TIMEOUT},
        matches=[(1, 10, 0.5)],
    )
    assert got == [
        CandidateOutcome(1, 10, R.MATCHED, 0.5),
        CandidateOutcome(1, 11, R.TOO_FEW_MATCHES),
        CandidateOutcome(2, 5, R.TOO_FEW_MATCHES),
        CandidateOutcome(3, 7, R.VERIFIER_TIMEOUT),
        CandidateOutcome(4, 2, R.ROBOT_NOT_CHOSEN),
    ]


def test_a_query_without_candidates_has_no_outcome() -> None:
    assert classify([], asked={0}, failures={}, matches=[]) == []


def test_a_failure_that_is_not_a_verifier_failure_is_refused() -> None:
    with pytest.raises(ValueError, match="not reasons a verifier fails for"):
        classify([(1, 1)], asked={1}, failures={1: R.ACCEPTED}, matches=[])


@pytest.mark.parametrize(
    ("error", "reason"),
    [
        (NoReply("k", "gone"), R.VERIFIER_UNREACHABLE),
        (ReplyTimeout("k", "slow"), R.VERIFIER_TIMEOUT),
        (RemoteError("k", 4, "too large"), R.VERIFIER_ERROR),
    ],
)
def test_a_failed_call_names_its_verifier_reason(error: Exception, reason: Reason) -> None:
    assert verifier_failure(error) == reason  # type: ignore[arg-type]


RULE = ClosureRule(min_score=0.3, exclusion=100)


def test_the_closure_is_the_best_match_that_passes_the_rule() -> None:
    # Robot 2 queries its frame 500. Best first: its own frame 450 (too recent), robot 1's
    # frame 9 (accepted), robot 0's frame 3 (good enough, but second), its own frame 10
    # (old enough, but third), robot 5's frame 1 below 0.3.
    matches = [(2, 450, 0.9), (1, 9, 0.8), (0, 3, 0.4), (2, 10, 0.35), (5, 1, 0.29)]
    assert RULE.verdicts(2, 500, matches) == [
        R.OWN_RECENT_FRAME,
        R.ACCEPTED,
        R.OUTRANKED,
        R.OUTRANKED,
        R.BELOW_SCORE_THRESHOLD,
    ]


def test_the_exclusion_counts_frames_on_the_querying_robot_only_and_includes_its_edge() -> None:
    # 100 frames back is within the exclusion (|i - j| <= exclusion); 101 is not.
    assert RULE.verdicts(2, 500, [(2, 400, 0.9)]) == [R.OWN_RECENT_FRAME]
    assert RULE.verdicts(2, 500, [(2, 399, 0.9)]) == [R.ACCEPTED]
    # Another robot's frame 450 is no own frame, whatever its index.
    assert RULE.verdicts(2, 500, [(3, 450, 0.9)]) == [R.ACCEPTED]


def test_a_score_equal_to_the_threshold_passes_and_nan_never_does() -> None:
    assert RULE.verdicts(0, 500, [(1, 1, 0.3)]) == [R.ACCEPTED]
    assert RULE.verdicts(0, 500, [(1, 1, float("nan")), (1, 2, 0.31)]) == [
        R.BELOW_SCORE_THRESHOLD,
        R.ACCEPTED,
    ]


def test_a_frame_processed_again_keeps_its_closure_and_says_so() -> None:
    assert RULE.verdicts(1, 300, [(0, 5, 0.6), (0, 6, 0.5)], already_closed=True) == [
        R.ALREADY_CLOSED,
        R.OUTRANKED,
    ]


def test_no_match_passing_the_rule_means_no_closure() -> None:
    assert RULE.verdicts(1, 300, [(1, 250, 0.9), (0, 6, 0.1)]) == [
        R.OWN_RECENT_FRAME,
        R.BELOW_SCORE_THRESHOLD,
    ]
    assert RULE.verdicts(1, 300, []) == []


def test_settle_puts_the_closure_verdicts_on_the_matched_candidates_only() -> None:
    outcomes = [
        CandidateOutcome(0, 5, R.MATCHED, 0.6),
        CandidateOutcome(0, 6, R.TOO_FEW_MATCHES),
        CandidateOutcome(3, 1, R.MATCHED, 0.2),
        CandidateOutcome(4, 4, R.ROBOT_NOT_CHOSEN),
    ]
    verdicts = {(0, 5): R.ACCEPTED, (3, 1): R.BELOW_SCORE_THRESHOLD, (0, 6): R.OUTRANKED}
    assert settle(outcomes, verdicts) == [
        CandidateOutcome(0, 5, R.ACCEPTED, 0.6),
        CandidateOutcome(0, 6, R.TOO_FEW_MATCHES),  # not matched: the verdict cannot apply
        CandidateOutcome(3, 1, R.BELOW_SCORE_THRESHOLD, 0.2),
        CandidateOutcome(4, 4, R.ROBOT_NOT_CHOSEN),
    ]
    with pytest.raises(ValueError, match="not closure-stage verdicts"):
        settle(outcomes, {(0, 5): R.TOO_FEW_MATCHES})


def test_each_reason_belongs_to_one_stage_as_the_schema_comments_say() -> None:
    assert {r: s for r, s in STAGE_OF.items() if s != Stage.UNSPECIFIED} == {
        R.BELOW_SHARD_CUT: Stage.SHARD,
        R.ROBOT_NOT_CHOSEN: Stage.SELECTION,
        R.VERIFIER_UNREACHABLE: Stage.VERIFICATION,
        R.VERIFIER_TIMEOUT: Stage.VERIFICATION,
        R.VERIFIER_ERROR: Stage.VERIFICATION,
        R.TOO_FEW_MATCHES: Stage.VERIFICATION,
        R.MATCHED: Stage.VERIFICATION,
        R.BELOW_SCORE_THRESHOLD: Stage.CLOSURE,
        R.OWN_RECENT_FRAME: Stage.CLOSURE,
        R.OUTRANKED: Stage.CLOSURE,
        R.ALREADY_CLOSED: Stage.CLOSURE,
        R.ACCEPTED: Stage.CLOSURE,
    }
    assert set(STAGE_OF) == set(Reason)
    # The schema's comment on each value names its stage first.
    proto = (REPO / "proto/swarmrec/v1/events.proto").read_text()
    for reason in Reason:
        if reason == R.UNSPECIFIED:
            continue
        before = proto.split(f"  {reason.wire_name} =")[0]
        comment = before.rsplit(";", 1)[-1]  # from the previous value's end
        assert f"// {reason.stage.label.capitalize()}:" in comment, reason


def test_the_reasons_are_the_schemas() -> None:
    assert {r.wire_name: int(r) for r in Reason} == dict(pb.FunnelReason.items())


def test_outcomes_travel_in_the_report_with_their_scores_from_its_matches() -> None:
    outcomes = [CandidateOutcome(0, 0, R.ACCEPTED, 0.75), CandidateOutcome(9, 1234, R.ROBOT_NOT_CHOSEN)]
    match = pb.VerifiedPair(match_robot_id=0, match_frame_index=0, score=0.75)
    report = pb.QueryReport(matches=[match], candidates=outcomes_to_proto(outcomes))
    assert outcomes_from_proto(pb.QueryReport.FromString(report.SerializeToString())) == outcomes
    # The score is the match's, not sent twice: robot 0, frame 0 cost nothing, so the
    # outcome is 2 bytes of sub-message header and 2 of reason.
    one = pb.QueryReport(candidates=outcomes_to_proto([CandidateOutcome(0, 0, R.OUTRANKED, 0.5)]))
    assert len(one.SerializeToString()) == 4
    # A reason of a newer sender reads as unspecified, never as another one.
    newer = pb.QueryReport(candidates=[pb.CandidateOutcome(robot_id=1, frame_index=2, reason=99)])  # type: ignore[list-item]
    assert outcomes_from_proto(newer) == [CandidateOutcome(1, 2, R.UNSPECIFIED)]


def test_the_funnels_levels_count_what_passed_each_stage() -> None:
    reasons = [
        R.ROBOT_NOT_CHOSEN,
        R.ROBOT_NOT_CHOSEN,
        R.VERIFIER_TIMEOUT,
        R.TOO_FEW_MATCHES,
        R.TOO_FEW_MATCHES,
        R.TOO_FEW_MATCHES,
        R.BELOW_SCORE_THRESHOLD,
        R.OUTRANKED,
        R.ACCEPTED,
        R.BELOW_SHARD_CUT,  # never returned: not in the funnel's levels
    ]
    assert passed_stages(reasons) == [
        ("returned by a shard", 9),
        ("robot chosen", 7),
        ("verifier answered", 6),
        ("matched (score > 0)", 3),
        ("accepted", 1),
    ]
