"""The loop-closure funnel: where each candidate of a query stopped, and why.

A queried frame's candidates pass four stages (docs/swarm.md, "Why was a loop
closure not found"); each distinct candidate frame ends at exactly one of them,
with exactly one reason::

    shard         the index shards return their n_ret best frames per label range
                  (a frame they did not return was never a candidate: BELOW_SHARD_CUT,
                  known only offline, from the run's data)
    selection     the n_fq robots with the most candidates, plus the querying robot,
                  are chosen to verify theirs (ROBOT_NOT_CHOSEN)
    verification  the chosen robot's verifier scores its candidates geometrically
                  (VERIFIER_UNREACHABLE, VERIFIER_TIMEOUT, VERIFIER_ERROR, TOO_FEW_MATCHES;
                  MATCHED: a score > 0, where no loop-closure rule applies: a client's query)
    closure       the loop-closure rule on the verified matches, best first
                  (BELOW_SCORE_THRESHOLD, OWN_RECENT_FRAME, OUTRANKED, ALREADY_CLOSED, ACCEPTED)

:class:`ClosureRule` is the one place the rule lives: the descriptor service
takes its loop closure from :meth:`ClosureRule.verdicts` and the funnel
records the same verdicts, so the two cannot drift apart. :class:`Reason`
has the numbers of ``swarmrec.v1.FunnelReason`` (a test checks them against
the schema); the stage is not sent, each reason implies its own (:data:`STAGE_OF`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from enum import IntEnum

from swarmrec.errors import CallError, NoReply, ReplyTimeout

__all__ = [
    "STAGE_OF",
    "CandidateOutcome",
    "ClosureRule",
    "Reason",
    "Stage",
    "classify",
    "passed_stages",
    "settle",
    "verifier_failure",
]


class Stage(IntEnum):
    """A stage of the funnel, in the order a candidate passes them."""

    UNSPECIFIED = 0
    SHARD = 1
    SELECTION = 2
    VERIFICATION = 3
    CLOSURE = 4

    @property
    def label(self) -> str:
        """The name in files, metrics' labels and JSON: ``verification``."""
        return self.name.lower()


class Reason(IntEnum):
    """Why a candidate stopped where it did: ``swarmrec.v1.FunnelReason`` without its prefix."""

    UNSPECIFIED = 0
    BELOW_SHARD_CUT = 1
    ROBOT_NOT_CHOSEN = 2
    VERIFIER_UNREACHABLE = 3
    VERIFIER_TIMEOUT = 4
    VERIFIER_ERROR = 5
    TOO_FEW_MATCHES = 6
    MATCHED = 7
    BELOW_SCORE_THRESHOLD = 8
    OWN_RECENT_FRAME = 9
    OUTRANKED = 10
    ALREADY_CLOSED = 11
    ACCEPTED = 12

    @property
    def stage(self) -> Stage:
        return STAGE_OF[self]

    @property
    def label(self) -> str:
        """The name in files, metrics' labels and JSON: ``too_few_matches``."""
        return self.name.lower()

    @property
    def wire_name(self) -> str:
        """The schema's name of the value, ``FUNNEL_REASON_...``."""
        return f"FUNNEL_REASON_{self.name}"

    @classmethod
    def of(cls, value: int) -> Reason:
        """The reason of a wire value; a value this version does not know reads as UNSPECIFIED."""
        try:
            return cls(value)
        except ValueError:
            return cls.UNSPECIFIED

    @classmethod
    def from_label(cls, label: str) -> Reason:
        """The reason named ``label`` (as :attr:`label` writes it); ValueError for another name."""
        try:
            return cls[label.upper()]
        except KeyError:
            raise ValueError(f"unknown funnel reason {label!r}") from None


#: The stage each reason stops a candidate at: the one table.
STAGE_OF: Mapping[Reason, Stage] = {
    Reason.UNSPECIFIED: Stage.UNSPECIFIED,
    Reason.BELOW_SHARD_CUT: Stage.SHARD,
    Reason.ROBOT_NOT_CHOSEN: Stage.SELECTION,
    Reason.VERIFIER_UNREACHABLE: Stage.VERIFICATION,
    Reason.VERIFIER_TIMEOUT: Stage.VERIFICATION,
    Reason.VERIFIER_ERROR: Stage.VERIFICATION,
    Reason.TOO_FEW_MATCHES: Stage.VERIFICATION,
    Reason.MATCHED: Stage.VERIFICATION,
    Reason.BELOW_SCORE_THRESHOLD: Stage.CLOSURE,
    Reason.OWN_RECENT_FRAME: Stage.CLOSURE,
    Reason.OUTRANKED: Stage.CLOSURE,
    Reason.ALREADY_CLOSED: Stage.CLOSURE,
    Reason.ACCEPTED: Stage.CLOSURE,
}

_VERIFIER_FAILURES = frozenset({Reason.VERIFIER_UNREACHABLE, Reason.VERIFIER_TIMEOUT, Reason.VERIFIER_ERROR})


@dataclass(frozen=True)
class CandidateOutcome:
    """Where one candidate frame of a query stopped; ``score`` is its verification
    score (0 when it was not verified, or verified without a match)."""

    robot: int
    frame: int
    reason: Reason
    score: float = 0.0

    @property
    def stage(self) -> Stage:
        return self.reason.stage


def verifier_failure(error: CallError) -> Reason:
    """The reason for the candidates of a verifier that did not answer as asked."""
    if isinstance(error, ReplyTimeout):
        return Reason.VERIFIER_TIMEOUT
    if isinstance(error, NoReply):
        return Reason.VERIFIER_UNREACHABLE
    return Reason.VERIFIER_ERROR


def classify(
    candidates: Iterable[tuple[int, int]],
    asked: Collection[int],
    failures: Mapping[int, Reason],
    matches: Iterable[tuple[int, int, float]],
) -> list[CandidateOutcome]:
    """Each distinct candidate frame up to the verification stage, in (robot, frame) order.

    ``candidates``: (robot, frame) as the shards returned them (a frame two shards
    returned counts once here); ``asked``: robots whose verifier was sent the query;
    ``failures``: asked robots whose verifier gave no usable answer, with the reason
    (:func:`verifier_failure`); ``matches``: (robot, frame, score) of every frame a
    verifier answered with a score > 0. A verified candidate is MATCHED; the
    closure stage (:func:`settle`) decides the rest.
    """
    bad = {r: why for r, why in failures.items() if why not in _VERIFIER_FAILURES}
    if bad:
        raise ValueError(f"not reasons a verifier fails for: {bad}")
    scores = {(r, f): s for r, f, s in matches}
    out = []
    for r, f in sorted(set(candidates) | scores.keys()):
        if r not in asked:
            out.append(CandidateOutcome(r, f, Reason.ROBOT_NOT_CHOSEN))
        elif r in failures:
            out.append(CandidateOutcome(r, f, failures[r]))
        elif (r, f) in scores:
            out.append(CandidateOutcome(r, f, Reason.MATCHED, scores[(r, f)]))
        else:
            # The verifier answered, and its answer holds no score > 0 for this frame.
            out.append(CandidateOutcome(r, f, Reason.TOO_FEW_MATCHES))
    return out


@dataclass(frozen=True)
class ClosureRule:
    """When a verified match becomes its query's loop closure.

    The first match, best first, at least ``min_score`` good that is not one of
    the querying robot's own frames within ``exclusion`` frames of the query.
    """

    min_score: float
    exclusion: int

    def verdicts(
        self,
        query_robot: int,
        query_frame: int,
        matches: Sequence[tuple[int, int, float]],
        *,
        already_closed: bool = False,
    ) -> list[Reason]:
        """One closure-stage reason per (robot, frame, score) of ``matches``, in the order
        given (best first, as a query report orders them): at most one ACCEPTED, or
        ALREADY_CLOSED for it when the query frame holds its loop closure already (it
        was processed before). A reason the match has on its own (below the threshold,
        an own recent frame) comes before OUTRANKED."""
        out: list[Reason] = []
        taken = False
        for robot, frame, score in matches:
            if not score >= self.min_score:  # NaN too: never a closure
                out.append(Reason.BELOW_SCORE_THRESHOLD)
            elif robot == query_robot and abs(frame - query_frame) <= self.exclusion:
                out.append(Reason.OWN_RECENT_FRAME)
            elif taken:
                out.append(Reason.OUTRANKED)
            else:
                taken = True
                out.append(Reason.ALREADY_CLOSED if already_closed else Reason.ACCEPTED)
        return out


def settle(
    outcomes: Sequence[CandidateOutcome], verdicts: Mapping[tuple[int, int], Reason]
) -> list[CandidateOutcome]:
    """``outcomes`` with the closure stage's verdict on each MATCHED (robot, frame) that has one."""
    wrong = {k: v for k, v in verdicts.items() if v.stage != Stage.CLOSURE}
    if wrong:
        raise ValueError(f"not closure-stage verdicts: {wrong}")
    return [
        replace(o, reason=verdicts[(o.robot, o.frame)])
        if o.reason == Reason.MATCHED and (o.robot, o.frame) in verdicts
        else o
        for o in outcomes
    ]


def passed_stages(reasons: Iterable[Reason]) -> list[tuple[str, int]]:
    """The funnel's levels: of the candidates the shards returned (BELOW_SHARD_CUT, a
    frame never returned, is left out), how many had their robot chosen, got a
    verifier's answer, matched (a score > 0) and were accepted."""
    counts = Counter(r for r in reasons if r.stage not in (Stage.SHARD, Stage.UNSPECIFIED))
    returned = sum(counts.values())
    chosen = returned - counts[Reason.ROBOT_NOT_CHOSEN]
    answered = chosen - sum(counts[r] for r in _VERIFIER_FAILURES)
    matched = answered - counts[Reason.TOO_FEW_MATCHES]
    return [
        ("returned by a shard", returned),
        ("robot chosen", chosen),
        ("verifier answered", answered),
        ("matched (score > 0)", matched),
        ("accepted", counts[Reason.ACCEPTED]),
    ]
