"""Why was this frame not closed with that one: a query's loop-closure funnel, explained.

Two sources, one answer (:class:`Explanation`, text or JSON):

* a finished run's folder (``swarmrec run``'s ``--out``): ``funnel.csv`` and
  ``funnel_queries.csv`` hold every query's funnel, ``summary.json`` the rule;
  a frame that was never a candidate is explained from the run's data, by
  recomputing the shards' answers (:func:`swarmrec.evaluation.funnel.shard_cuts`,
  exact in a lock-step run);
* a live swarm: the robot's descriptor keeps its last reports (``explain``
  endpoint); it keeps no shard scores, so a frame no shard returned is only
  "never a candidate", without the scores.

A pair is looked at both ways: the query of the first frame (where the second
stopped in its funnel), and the query of the second frame (where the first
stopped), since either query may close the pair.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from swarmrec.client import SwarmClient
from swarmrec.core.descriptor import semantic_descriptors
from swarmrec.core.funnel import CandidateOutcome, Reason, Stage
from swarmrec.core.split import split_frames
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import label_names
from swarmrec.errors import ConfigError, DatasetError
from swarmrec.evaluation.funnel import ShardCut, shard_cuts
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import outcomes_from_proto

__all__ = [
    "Explanation",
    "PairAnswer",
    "QueryFunnel",
    "Rule",
    "RunFolder",
    "explain_live",
    "explain_run",
]

Frame = tuple[int, int]
#: Why a frame was no candidate of a query (it is in no outcome of the query).
NeverReturned = Callable[["QueryFunnel", Frame], "PairAnswer"]


@dataclass(frozen=True)
class Rule:
    """The parameters the funnel's stages applied."""

    loop_closure_min_score: float
    exclusion: int
    min_objects: int
    n_ret: int
    n_fq: int


@dataclass(frozen=True)
class QueryFunnel:
    """One frame's query as its report recorded it."""

    robot: int
    frame: int
    queried: bool
    n_objects: int
    n_candidates: int
    #: Candidates each shard that answered returned, by shard robot (summed over its groups).
    shards: dict[int, int]
    failed_shards: list[int]
    verified_robots: list[int]
    failed_verifiers: list[int]
    outcomes: list[CandidateOutcome]
    frame_id: str = ""
    #: Per label group answered: (the shard that answered, candidates it returned).
    groups: dict[int, tuple[int, int]] = field(default_factory=dict)

    @classmethod
    def from_report(cls, report: pb.QueryReport) -> QueryFunnel:
        return cls(
            robot=report.robot_id,
            frame=report.frame_index,
            queried=report.queried,
            n_objects=report.n_objects,
            n_candidates=report.n_candidates,
            shards=_by_shard((s.robot_id, s.n_candidates) for s in report.shard_candidates),
            failed_shards=list(report.failed_shard_robot_ids),
            verified_robots=list(report.verified_robot_ids),
            failed_verifiers=list(report.failed_verifier_robot_ids),
            outcomes=outcomes_from_proto(report),
            groups={s.group: (s.robot_id, s.n_candidates) for s in report.shard_candidates},
        )

    def outcome_of(self, robot: int, frame: int) -> CandidateOutcome | None:
        return next((o for o in self.outcomes if (o.robot, o.frame) == (robot, frame)), None)

    @property
    def closure(self) -> CandidateOutcome | None:
        """The candidate that became the loop closure (accepted, or kept from before)."""
        return next((o for o in self.outcomes if o.reason in (Reason.ACCEPTED, Reason.ALREADY_CLOSED)), None)

    def to_dict(self) -> dict[str, Any]:
        return {
            "robot": self.robot,
            "frame": self.frame,
            "frame_id": self.frame_id,
            "queried": self.queried,
            "n_objects": self.n_objects,
            "n_candidates": self.n_candidates,
            "shards": {str(k): v for k, v in self.shards.items()},
            "failed_shards": self.failed_shards,
            "verified_robots": self.verified_robots,
            "failed_verifiers": self.failed_verifiers,
        }


@dataclass
class PairAnswer:
    """What happened to one candidate frame in one query: its stage, reason and why."""

    query: Frame
    candidate: Frame
    stage: str
    reason: str
    score: float | None
    why: str
    #: A frame no shard returned: each shard asked where it shares a label (run folders only).
    shards: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "query": {"robot": self.query[0], "frame": self.query[1]},
            "candidate": {"robot": self.candidate[0], "frame": self.candidate[1]},
            "stage": self.stage,
            "reason": self.reason,
            "score": self.score,
            "why": self.why,
            "shards": self.shards,
        }


@dataclass
class Explanation:
    """The answer of ``swarmrec explain``: one frame's funnel, and a pair's fate when asked."""

    robot: int
    frame: int
    source: str
    #: held, aged_out, not_seen (live), not_in_run (run folder)
    status: str
    note: str = ""
    rule: Rule | None = None
    query: QueryFunnel | None = None
    pair: PairAnswer | None = None
    #: The other frame's query, about this frame (None: not asked, or no report of it).
    reverse: PairAnswer | None = None
    reverse_note: str = ""

    @property
    def found(self) -> bool:
        return self.query is not None

    def candidates(self) -> list[dict[str, Any]]:
        if self.query is None or self.rule is None:
            return []
        return [
            {
                "robot": o.robot,
                "frame": o.frame,
                "stage": o.stage.label,
                "reason": o.reason.label,
                "score": _score(o),
                "why": why(o, self.query, self.rule),
            }
            for o in self.query.outcomes
        ]

    def to_dict(self) -> dict[str, Any]:
        closure = self.query.closure if self.query else None
        return {
            "robot": self.robot,
            "frame": self.frame,
            "source": self.source,
            "status": self.status,
            "note": self.note,
            "rule": None if self.rule is None else self.rule.__dict__,
            "query": None if self.query is None else self.query.to_dict(),
            "loop_closure": None if closure is None else {"robot": closure.robot, "frame": closure.frame},
            "candidates": self.candidates(),
            "pair": None if self.pair is None else self.pair.to_dict(),
            "reverse": None if self.reverse is None else self.reverse.to_dict(),
            "reverse_note": self.reverse_note,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    def lines(self) -> list[str]:
        """The explanation as text, for a terminal."""
        head = f"robot {self.robot} frame {self.frame}"
        q = self.query
        if q is None:
            return [f"{head} ({self.source}): {self.note}"]
        out = [f"{head}{f' (frame id {q.frame_id})' if q.frame_id else ''}, {self.source}"]
        if not q.queried:
            out.append(f"  not queried: {self._not_queried()}")
        else:
            closure = q.closure
            closed = "none" if closure is None else f"robot {closure.robot} frame {closure.frame}"
            out.append(
                f"  queried with {q.n_objects} objects: {q.n_candidates} candidates returned, "
                f"{len(q.outcomes)} distinct; loop closure: {closed}"
            )
            answered = ", ".join(f"{k} ({n})" for k, n in sorted(q.shards.items())) or "none"
            out.append(f"  shards answered (candidates): {answered}")
            if q.failed_shards:
                out.append(f"  shards that did not answer: {' '.join(map(str, q.failed_shards))}")
            verified = " ".join(map(str, q.verified_robots)) or "none"
            out.append(f"  verified by robots {verified}")
            if q.failed_verifiers:
                out.append(f"  verifiers that did not answer: {' '.join(map(str, q.failed_verifiers))}")
        if self.pair is not None:
            out += _pair_lines(self.pair)
            if self.reverse is not None:
                out.append("  the other way:")
                out += ["  " + line for line in _pair_lines(self.reverse)]
            elif self.reverse_note:
                out.append(f"  the other way: {self.reverse_note}")
        elif q.queried:
            out.append(f"  {'robot':>5} {'frame':>6}  {'stage':<13} {'reason':<22} {'score':>7}  why")
            for c in self.candidates():
                score = "" if c["score"] is None else f"{c['score']:.4f}"
                where = f"{c['robot']:>5} {c['frame']:>6}  {c['stage']:<13} {c['reason']:<22}"
                out.append(f"  {where} {score:>7}  {c['why']}")
        if self.note:
            out.append(f"  note: {self.note}")
        return out

    def _not_queried(self) -> str:
        q, rule = self.query, self.rule
        assert q is not None
        if rule is not None and q.n_objects < rule.min_objects:
            return f"{q.n_objects} objects, fewer than min_objects ({rule.min_objects}); nothing was sent"
        return f"{q.n_objects} objects; nothing was sent"


def _pair_lines(p: PairAnswer) -> list[str]:
    q, c = p.query, p.candidate
    out = [f"  robot {q[0]} frame {q[1]}'s query, robot {c[0]} frame {c[1]}: {p.stage} / {p.reason}: {p.why}"]
    for s in p.shards:
        out.append(f"    {s['text']}")
    return out


#: Reasons of a candidate that was never scored.
_NOT_SCORED = frozenset(
    {
        Reason.BELOW_SHARD_CUT,
        Reason.ROBOT_NOT_CHOSEN,
        Reason.VERIFIER_UNREACHABLE,
        Reason.VERIFIER_TIMEOUT,
        Reason.VERIFIER_ERROR,
    }
)


def _score(o: CandidateOutcome) -> float | None:
    return None if o.reason in _NOT_SCORED else o.score


def why(o: CandidateOutcome, q: QueryFunnel, rule: Rule) -> str:
    """Why candidate ``o`` of query ``q`` stopped where it did, in words."""
    r = o.robot
    match o.reason:
        case Reason.ROBOT_NOT_CHOSEN:
            verified = " ".join(map(str, q.verified_robots)) or "none"
            return (
                f"robot {r} was not among the n_fq = {rule.n_fq} robots with the most candidates "
                f"(verified: {verified})"
            )
        case Reason.VERIFIER_UNREACHABLE:
            return f"robot {r}'s verifier was asked and nobody answered (gone, crashed, not discovered)"
        case Reason.VERIFIER_TIMEOUT:
            return f"robot {r}'s verifier did not answer within the request timeout"
        case Reason.VERIFIER_ERROR:
            return f"robot {r}'s verifier answered with an error (or an undecodable answer): its log says why"
        case Reason.TOO_FEW_MATCHES:
            return "verified, score 0: fewer than min_common objects in common, or none associated within d"
        case Reason.MATCHED:
            return f"verified, score {o.score:.4f} (a client's query: no loop-closure rule)"
        case Reason.BELOW_SCORE_THRESHOLD:
            return f"verified, score {o.score:.4f} < loop_closure_min_score {rule.loop_closure_min_score:g}"
        case Reason.OWN_RECENT_FRAME:
            apart = abs(o.frame - q.frame)
            return (
                f"the robot's own frame, {apart} frame{'s' if apart != 1 else ''} from the query: within "
                f"the exclusion of {rule.exclusion}"
            )
        case Reason.OUTRANKED:
            best = q.closure
            better = "" if best is None else f"robot {best.robot} frame {best.frame} ({best.score:.4f}) "
            return f"passed the rule with {o.score:.4f}, but {better}scored higher: the loop closure"
        case Reason.ALREADY_CLOSED:
            return "the best match passing the rule, but the frame had its loop closure already (sent again)"
        case Reason.ACCEPTED:
            return f"the loop closure of robot {q.robot} frame {q.frame}, score {o.score:.4f}"
        case _:
            return "a reason this version does not know"


# --- a finished run's folder -----------------------------------------------------------


def _by_shard(items: Iterable[tuple[int, int]]) -> dict[int, int]:
    """Candidates by shard, summed over the groups each answered for."""
    out: dict[int, int] = {}
    for shard, n in items:
        out[shard] = out.get(shard, 0) + n
    return out


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split()]


class RunFolder:
    """A finished run's funnel files and, for the shards' answers, its data."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.summary: dict[str, Any] = json.loads((path / "summary.json").read_text(encoding="utf-8"))
            queries = (path / "funnel_queries.csv").read_text(encoding="utf-8").splitlines()
            rows = (path / "funnel.csv").read_text(encoding="utf-8").splitlines()
        except FileNotFoundError as e:
            if (path / "constellations" / "summary.json").is_file():
                # A `--method both` run keeps each method's report in a folder of its own.
                raise ConfigError(
                    f"{path} holds the reports of both methods: the constellation funnel is in "
                    f"{path / 'constellations'} (--run {path / 'constellations'})"
                ) from None
            raise ConfigError(
                f"{path} is not a finished run with a loop-closure funnel (no {Path(e.filename).name}); "
                "`swarmrec run --out DIR` writes one"
            ) from None
        swarm, preset = self.summary["swarm"], self.summary["swarm"]["preset"]
        self.rule = Rule(
            loop_closure_min_score=float(self.summary["loop_closures"]["min_score"]),
            exclusion=int(preset["exclusion"]),
            min_objects=int(preset["min_objects"]),
            n_ret=int(preset["n_ret"]),
            n_fq=int(preset["n_fq"]),
        )
        self.robots = int(swarm["robots"])
        self.lockstep = swarm["pace"] == "lockstep"
        self.bounds = [int(b) for b in swarm["label_bounds"]]
        self.blocks = split_frames(int(self.summary["dataset"]["frames"]), self.robots)
        outcomes: dict[Frame, list[CandidateOutcome]] = {}
        for row in csv.DictReader(rows):
            reason = Reason.from_label(row["reason"])
            score = float(row["score"]) if row["score"] else 0.0
            key = (int(row["query_robot"]), int(row["query_frame"]))
            cand = CandidateOutcome(int(row["candidate_robot"]), int(row["candidate_frame"]), reason, score)
            outcomes.setdefault(key, []).append(cand)
        self.queries: dict[Frame, QueryFunnel] = {}
        for row in csv.DictReader(queries):
            key = (int(row["robot"]), int(row["frame"]))
            # "group/shard:candidates" for each group the query asked and a shard answered.
            groups = {}
            for item in row["shard_candidates"].split():
                where, _, n = item.partition(":")
                g, _, s = where.partition("/")
                groups[int(g)] = (int(s), int(n))
            shards = _by_shard(groups.values())
            self.queries[key] = QueryFunnel(
                robot=key[0],
                frame=key[1],
                queried=row["queried"] == "1",
                n_objects=int(row["n_objects"]),
                n_candidates=int(row["n_candidates"]),
                shards=shards,
                failed_shards=_ints(row["failed_shards"]),
                verified_robots=_ints(row["verified_robots"]),
                failed_verifiers=_ints(row["failed_verifiers"]),
                outcomes=outcomes.get(key, []),
                frame_id=row["frame_id"],
                groups=groups,
            )

    @property
    def source(self) -> str:
        return f"run {self.path} ({self.summary['swarm']['pace']})"

    @cached_property
    def _data(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]] | str:
        """The label histograms of every frame and which frames the shards stored; or why
        they cannot be had."""
        dataset = self.summary["dataset"]
        folder = dataset.get("folder") or str(self.path / "dataset")
        labels = dataset.get("labels_file") or None
        try:
            seq = read_constellations(folder, label_names(labels))
        except (DatasetError, OSError) as e:
            return f"the run's constellations cannot be read ({e})"
        if len(seq) != int(dataset["frames"]):
            return f"{folder} holds {len(seq)} frames, the run replayed {dataset['frames']}"
        stored = np.zeros(len(seq), np.bool_)
        for (r, f), q in self.queries.items():
            if q.queried and r < len(self.blocks) and f < len(self.blocks[r]):
                stored[self.blocks[r][f]] = True
        return semantic_descriptors(seq.constellations, seq.n_labels), stored

    def frame_exists(self, robot: int, frame: int) -> bool:
        return 0 <= robot < len(self.blocks) and 0 <= frame < len(self.blocks[robot])

    def never_returned(self, query: QueryFunnel, other: Frame) -> PairAnswer:
        """Why ``other`` was no candidate of ``query``, from the run's data."""
        shard, cut = Stage.SHARD.label, Reason.BELOW_SHARD_CUT.label
        base = PairAnswer((query.robot, query.frame), other, shard, cut, None, "")
        other_q = self.queries.get(other)
        if other_q is not None and not other_q.queried:
            base.why = (
                f"never a candidate: robot {other[0]} frame {other[1]} had {other_q.n_objects} objects, "
                f"fewer than min_objects ({self.rule.min_objects}); it never queried, so no shard stored it"
            )
            return base
        if other_q is None:
            base.why = "never a candidate: the run has no report of that frame (a missing slot)"
            return base
        if self.lockstep and other[1] >= query.frame:
            base.why = (
                f"never a candidate: in lock-step, step {query.frame}'s shards search only frames of earlier "
                f"steps, and robot {other[0]} frame {other[1]} came at step {other[1]}"
            )
            return base
        data = self._data
        if isinstance(data, str):
            base.why = f"never a candidate: no shard returned it in its top n_ret = {self.rule.n_ret}; {data}"
            return base
        descriptors, stored = data
        cuts = shard_cuts(
            descriptors,
            self.blocks,
            self.bounds,
            stored,
            self.rule.n_ret,
            (query.robot, query.frame),
            other,
            lockstep=self.lockstep,
        )
        if not cuts:
            base.why = "never a candidate: it shares no label with the query frame (every partial score is 0)"
            return base
        base.shards = [_cut_dict(c, query) for c in cuts]
        if not self.lockstep:
            base.why = (
                f"never a candidate: no shard returned it in its top n_ret = {self.rule.n_ret}. Its "
                "partial scores are below; in a paced run which frames the shards held at the query is not "
                "recorded, so their cuts are not known"
            )
        else:
            base.why = (
                f"never a candidate: its descriptor scored below the shard's top n_ret = {self.rule.n_ret} "
                f"on every shard the query asked where it shares a label"
            )
        return base


def _cut_dict(c: ShardCut, q: QueryFunnel) -> dict[str, Any]:
    answered = q.groups.get(c.group)
    by = f", answered by shard {answered[0]}" if answered is not None else ""
    where = f"label group {c.group} (labels {c.lo}-{c.hi - 1}{by})"
    if answered is None:
        text = f"{where}: no shard answered this query; partial score {c.score:.4f}"
    elif c.returned is None:
        text = f"{where}: partial score {c.score:.4f}; its cut is not known"
    elif c.returned_it:
        text = f"{where}: partial score {c.score:.4f}, returned (rank {c.rank})"
    elif c.cut is None:
        text = f"{where}: partial score {c.score:.4f}; the shard returned {len(c.returned)} < n_ret frames"
    elif c.score == c.cut:
        text = (
            f"{where}: partial score {c.score:.4f}, tied with the {c.n_ret}th best (rank {c.rank}); "
            "the tie order (the published unstable argsort) left it out"
        )
    else:
        text = (
            f"{where}: partial score {c.score:.4f}, rank {c.rank}; the shard returned its {c.n_ret} best, "
            f"down to {c.cut:.4f}"
        )
    return {
        "group": c.group,
        "shard": answered[0] if answered is not None else None,
        "labels": [c.lo, c.hi],
        "score": c.score,
        "rank": c.rank,
        "cut": c.cut,
        "returned": c.returned_it,
        "text": text,
    }


def _answer(q: QueryFunnel, other: Frame, rule: Rule) -> PairAnswer | None:
    o = q.outcome_of(*other)
    if o is None:
        return None
    return PairAnswer((q.robot, q.frame), other, o.stage.label, o.reason.label, _score(o), why(o, q, rule))


def _not_queried_answer(q: QueryFunnel, other: Frame, rule: Rule) -> PairAnswer:
    return PairAnswer(
        (q.robot, q.frame),
        other,
        "query",
        "too_few_objects",
        None,
        f"robot {q.robot} frame {q.frame} was not queried: {q.n_objects} objects, fewer than "
        f"min_objects ({rule.min_objects})",
    )


def explain_run(run: RunFolder, robot: int, frame: int, other: Frame | None = None) -> Explanation:
    """``robot``'s ``frame`` in a finished run, and its pair with ``other`` when given."""
    if not run.frame_exists(robot, frame):
        raise ConfigError(f"the run has no frame {frame} of robot {robot} ({len(run.blocks)} robots)")
    if other is not None and not run.frame_exists(*other):
        raise ConfigError(f"the run has no frame {other[1]} of robot {other[0]}")
    q = run.queries.get((robot, frame))
    if q is None:
        note = "no report of this frame: its robot did not answer that step"
        return Explanation(robot, frame, run.source, "not_in_run", note)
    ex = Explanation(robot, frame, run.source, "held", rule=run.rule, query=q)
    if other is None:
        return ex
    ex.pair = _pair(q, other, run.rule, run.never_returned)
    back = run.queries.get(other)
    if back is None:
        ex.reverse_note = f"no report of robot {other[0]} frame {other[1]}'s query"
    else:
        ex.reverse = _pair(back, (robot, frame), run.rule, run.never_returned)
    return ex


def _pair(q: QueryFunnel, other: Frame, rule: Rule, never: NeverReturned) -> PairAnswer:
    if not q.queried:
        return _not_queried_answer(q, other, rule)
    return _answer(q, other, rule) or never(q, other)


# --- a live swarm -------------------------------------------------------------------------

_STATUS: Mapping[int, str] = {
    pb.ReportStatus.REPORT_STATUS_HELD: "held",
    pb.ReportStatus.REPORT_STATUS_AGED_OUT: "aged_out",
    pb.ReportStatus.REPORT_STATUS_NOT_SEEN: "not_seen",
}


def _live_rule(reply: pb.ExplainReply) -> Rule:
    return Rule(reply.loop_closure_min_score, reply.exclusion, reply.min_objects, reply.n_ret, reply.n_fq)


def _live_note(reply: pb.ExplainReply, frame: int) -> str:
    held = (
        f"it holds the last {reply.reports_held} reports (frames {reply.oldest_frame_index} to "
        f"{reply.newest_frame_index}; explain_reports = {reply.reports_kept})"
        if reply.reports_held
        else f"it holds no report (explain_reports = {reply.reports_kept})"
    )
    status = _STATUS.get(reply.status, "unknown")
    if status == "aged_out":
        return f"frame {frame} has aged out of robot {reply.robot_id}'s descriptor memory: {held}"
    if status == "not_seen":
        return (
            f"robot {reply.robot_id}'s descriptor has not processed frame {frame} since it started "
            f"(not yet, refused, or before a restart); {held}"
        )
    return ""


def _live_never(q: QueryFunnel, other: Frame, rule: Rule) -> PairAnswer:
    failed = ""
    if q.failed_shards:
        failed = f" Shards {' '.join(map(str, q.failed_shards))} did not answer this query."
    return PairAnswer(
        (q.robot, q.frame),
        other,
        Stage.SHARD.label,
        Reason.BELOW_SHARD_CUT.label,
        None,
        f"never a candidate: no shard returned it among its top n_ret = {rule.n_ret} (or it was not stored "
        f"yet).{failed} A live swarm keeps no shard scores; `swarmrec explain --run` on the finished run "
        "computes them",
    )


def explain_live(client: SwarmClient, robot: int, frame: int, other: Frame | None = None) -> Explanation:
    """``robot``'s ``frame`` from its live descriptor, and its pair with ``other`` when given
    (the other robot's descriptor is asked for the other way)."""
    reply = client.explain(robot, frame)
    source = f"live, robot {robot}'s descriptor"
    rule = _live_rule(reply)
    status = _STATUS.get(reply.status, "unknown")
    if not reply.HasField("report"):
        return Explanation(robot, frame, source, status, _live_note(reply, frame), rule=rule)
    q = QueryFunnel.from_report(reply.report)
    ex = Explanation(robot, frame, source, status, rule=rule, query=q)
    if other is None:
        return ex

    def never(query: QueryFunnel, candidate: Frame) -> PairAnswer:
        return _live_never(query, candidate, rule)

    ex.pair = _pair(q, other, rule, never)
    back = client.explain(*other)
    if back.HasField("report"):
        ex.reverse = _pair(QueryFunnel.from_report(back.report), (robot, frame), rule, never)
    else:
        ex.reverse_note = _live_note(back, other[1])
    return ex
