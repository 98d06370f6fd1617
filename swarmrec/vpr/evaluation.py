"""The offline evaluation of decentralized place recognition from full-image descriptors.

``main(EvaluationSettings(...)) -> EvaluationSummary`` renders a held-out deployment world
(the default office of ``deployment_seed``, every frame), describes it with the descriptor
model, describes *other* worlds (varied offices, :mod:`swarmrec.vpr.data`) for k-means and
product quantisation, and then runs, on the same deployment descriptors,

* **Fig. 6**: for ``n`` robots in ``robots`` and each of ``runs`` seeds, k = n centres (one
  per robot) trained on the other descriptors with the run's seed, the paper's random
  assignment, the lock-step queries through real owner indexes: relative AUC (decentralized
  over centralized, :mod:`swarmrec.vpr.simulation` for the protocol) and worst balance ratio;
* **Fig. 7**: the same with ``fig7_robots`` robots and ``c`` clusters per robot;
* **balance** (:mod:`swarmrec.vpr.balance`): the paper's random start with
  ``balance_clusters_per_robot`` clusters per robot, re-assigned from the load observed in each
  period of ``rebalance_share`` of the queries, with boundary copies, against one cluster per robot;
* **quantisation** (:mod:`swarmrec.vpr.quantize`): recall@1/5 and AUC of the decoded
  descriptors with the model card's protocol (:mod:`swarmrec.vpr.places`: every frame
  against the whole sequence outside a 100-frame window), and the bytes;
* the byte model for every configuration.

Everything needed to re-check the figures is written to ``settings.out``:

``descriptors.npz``
    ``deployment`` (N, 128) float32 in frame order, ``frames``, ``positions``, ``directions``;
    ``other`` (M, 128) float32, the k-means / PQ training descriptors, ``other_worlds`` (seeds).
``runs.npz``
    the centres of every run, ``<run name>`` -> (k, 128) float32.
``runs.json``
    one record per run: its name, experiment, robots, clusters per robot, seed, the
    assignment table (:meth:`swarmrec.vpr.clusters.Assignment.to_json`), AUCs, relative AUC,
    worst balance ratio, load per robot, bytes per query.
``summary.json``, ``fig6.png``, ``fig7.png``
    the aggregated numbers and the figures (:mod:`swarmrec.vpr.figures`).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from swarmrec.errors import ConfigError
from swarmrec.vpr.balance import RebalanceRule, schedule
from swarmrec.vpr.centres import other_descriptors
from swarmrec.vpr.clusters import Assignment, Router, random_assignment, train_centres
from swarmrec.vpr.data import RenderedWorld, render_world
from swarmrec.vpr.figures import plot_sweep
from swarmrec.vpr.index import set_faiss_threads
from swarmrec.vpr.model import DescriptorModel
from swarmrec.vpr.places import (
    PlaceThresholds,
    eligible_pairs,
    retrieval_metrics,
    same_place,
)
from swarmrec.vpr.quantize import Int8Quantizer, PQQuantizer, Quantizer
from swarmrec.vpr.simulation import (
    QUERY_HEADER_BYTES,
    Answers,
    answers_curve,
    arrival_order,
    bytes_per_query,
    eligible,
    robot_of_frames,
    run_queries,
    worst_balance_ratio,
)

__all__ = [
    "EvaluationSettings",
    "EvaluationSummary",
    "RunResult",
    "Team",
    "main",
    "make_team",
    "random_run",
    "rebalanced_run",
    "team_auc",
]

Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

FLOAT_BYTES = 4


@dataclass(frozen=True)
class EvaluationSettings:
    """What the evaluation runs; validated on construction."""

    out: Path
    model: Path | None = None
    #: The deployment: the default office of this seed (held out from training), every frame.
    deployment_seed: int = 15_000
    deployment_frames: int = 2500
    #: The other data (k-means, PQ): varied offices ``other_seed_base + j``, every ``other_stride``-th frame.
    other_worlds: int = 8
    other_seed_base: int = 14_000
    other_stride: int = 4
    robots: tuple[int, ...] = tuple(range(2, 21))
    fig7_robots: int = 20
    clusters_per_robot: tuple[int, ...] = (1, 2, 3, 4, 6, 8, 12, 16)
    runs: int = 10
    #: Re-balancing: the random start's clusters per robot, the observed share, the capacity slack.
    balance_clusters_per_robot: int = 8
    rebalance_share: float = 0.05
    #: Share of a period's queries near a cell boundary that set the copy margin (1: every descriptor).
    replica_share: float = 1.0
    slack: float = 0.25
    #: Boundary copies go to the owners of up to this many next-nearest cells.
    copy_neighbours: int = 2
    #: Product-quantisation code sizes (bytes) to measure beside int8.
    pq_bytes: tuple[int, ...] = (16, 32)
    max_distance_m: float = 0.5
    max_angle_deg: float = 30.0
    threads: int = 1
    #: A progress bar on stderr (rendering, then the runs).
    progress: bool = False

    def __post_init__(self) -> None:
        if not self.robots or min(self.robots) < 2:
            raise ConfigError(f"robots must be counts >= 2, got {self.robots}")
        if not self.clusters_per_robot or min(self.clusters_per_robot) < 1:
            raise ConfigError(f"clusters_per_robot must be >= 1, got {self.clusters_per_robot}")
        for name in ("runs", "other_worlds", "other_stride", "threads", "balance_clusters_per_robot"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.fig7_robots < 2:
            raise ConfigError(f"fig7_robots must be >= 2, got {self.fig7_robots}")
        if not 300 <= self.deployment_frames <= 20000:
            raise ConfigError(f"deployment_frames must be in [300, 20000], got {self.deployment_frames}")
        largest = max(max(self.robots), self.fig7_robots)
        if largest * max(self.clusters_per_robot) > self.other_worlds * 300:
            raise ConfigError("too few other descriptors for the largest k: add other_worlds")
        if not 0.0 < self.rebalance_share < 1.0:
            raise ConfigError(f"rebalance_share must be in (0, 1), got {self.rebalance_share}")
        if not 0.0 <= self.replica_share <= 1.0:
            raise ConfigError(f"replica_share must be in [0, 1], got {self.replica_share}")
        if not (math.isfinite(self.slack) and self.slack >= 0):
            raise ConfigError(f"slack must be >= 0, got {self.slack}")
        if self.copy_neighbours < 1:
            raise ConfigError(f"copy_neighbours must be >= 1, got {self.copy_neighbours}")
        if any(b < 1 or 128 % b for b in self.pq_bytes):
            raise ConfigError(f"pq_bytes must divide 128, got {self.pq_bytes}")
        PlaceThresholds(self.max_distance_m, self.max_angle_deg, 0)

    def rebalance_rule(self) -> RebalanceRule:
        """The re-balancing knobs as the rule :func:`swarmrec.vpr.balance.schedule` plays."""
        return RebalanceRule(
            clusters_per_robot=self.balance_clusters_per_robot,
            period_share=self.rebalance_share,
            slack=self.slack,
            replica_share=self.replica_share,
            neighbours=self.copy_neighbours,
        )


@dataclass(frozen=True)
class RunResult:
    """One run of one configuration."""

    name: str
    experiment: str
    n_robots: int
    clusters_per_robot: int
    seed: int
    auc: float
    centralized_auc: float
    relative_auc: float
    worst_balance_ratio: float
    load: tuple[int, ...]
    bytes_per_query: dict[str, float]
    assignment: dict[str, Any] = field(repr=False)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class EvaluationSummary:
    """The aggregated results (``summary.json`` holds the same) and where the files are."""

    out: Path
    centralized_auc: dict[int, float]
    fig6: list[dict[str, Any]]
    fig7: list[dict[str, Any]]
    balance: dict[str, Any]
    quantisation: list[dict[str, Any]]
    runs: list[RunResult] = field(repr=False)
    seconds: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            "centralized_auc": {str(k): v for k, v in self.centralized_auc.items()},
            "fig6": self.fig6,
            "fig7": self.fig7,
            "balance": self.balance,
            "quantisation": self.quantisation,
            "seconds": self.seconds,
        }


@dataclass(frozen=True, eq=False)
class Team:
    """The deployment cut among ``n`` robots: who owns what, the order, what could match."""

    n_robots: int
    robots: IntArray
    order: IntArray
    eligible: BoolArray
    closures: BoolArray


def make_team(n_robots: int, same: BoolArray) -> Team:
    """The deployment whose same-place matrix is ``same``, cut among ``n_robots`` robots."""
    robots = robot_of_frames(len(same), n_robots)
    order = arrival_order(robots)
    pairs = eligible(robots, order)
    return Team(n_robots, robots, order, pairs, same & pairs)


def team_auc(team: Team, answers: Answers) -> float:
    """The AUC of ``answers`` under the module's protocol (:func:`answers_curve`)."""
    return answers_curve(answers, team.closures, team.eligible).auc


def _record(
    name: str, experiment: str, team: Team, c: int, seed: int, answers: Answers,
    centralized: float, assignment: Assignment, code_bytes: int, extra: dict[str, Any] | None = None,
) -> RunResult:  # fmt: skip
    auc = team_auc(team, answers)
    return RunResult(
        name=name,
        experiment=experiment,
        n_robots=team.n_robots,
        clusters_per_robot=c,
        seed=seed,
        auc=auc,
        centralized_auc=centralized,
        relative_auc=auc / centralized if centralized > 0 else float("nan"),
        worst_balance_ratio=worst_balance_ratio(answers.owners, team.n_robots),
        load=tuple(int(v) for v in np.bincount(answers.owners, minlength=team.n_robots)),
        bytes_per_query=bytes_per_query(answers, team.robots, code_bytes),
        assignment=assignment.to_json(),
        extra=extra or {},
    )


def _aggregate(runs: list[RunResult], key: str) -> list[dict[str, Any]]:
    """Mean and every run's values of relative AUC and worst balance ratio, per ``key``."""
    groups: dict[int, list[RunResult]] = {}
    for r in runs:
        groups.setdefault(getattr(r, key), []).append(r)
    rows = []
    for value, members in sorted(groups.items()):
        rel = [r.relative_auc for r in members]
        bal = [r.worst_balance_ratio for r in members]
        rows.append(
            {
                key: value,
                "relative_auc_mean": float(np.mean(rel)),
                "relative_auc_runs": rel,
                "worst_balance_ratio_mean": float(np.mean(bal)),
                "worst_balance_ratio_runs": bal,
                "centralized_auc": members[0].centralized_auc,
                "bytes_per_query_mean": float(np.mean([r.bytes_per_query["total"] for r in members])),
            }
        )
    return rows


def random_run(
    name: str, experiment: str, team: Team, c: int, seed: int, x: Float32Array, other: Float32Array,
    centralized: float, centres_out: dict[str, Any],
) -> RunResult:  # fmt: skip
    """The paper's run: ``n x c`` k-means centres on ``other`` and ``c`` random clusters per robot."""
    centres = train_centres(other, team.n_robots * c, seed)
    assignment = random_assignment(team.n_robots, c, seed)
    _, owners = Router(centres, assignment).route_many(x)
    centres_out[name] = centres
    answers = run_queries(x, team.robots, owners, team.order)
    return _record(
        name, experiment, team, c, seed, answers, centralized, assignment, FLOAT_BYTES * x.shape[1]
    )


def _balanced_run(
    s: EvaluationSettings, team: Team, seed: int, x: Float32Array, other: Float32Array,
    centralized: float, centres_out: dict[str, Any],
) -> RunResult:  # fmt: skip
    """The paper's random start, re-balanced after every period (:func:`swarmrec.vpr.balance.schedule`)."""
    return rebalanced_run(s.rebalance_rule(), team, seed, x, other, centralized, centres_out)


def rebalanced_run(
    rule: RebalanceRule, team: Team, seed: int, x: Float32Array, other: Float32Array,
    centralized: float, centres_out: dict[str, Any],
) -> RunResult:  # fmt: skip
    """One mission under ``rule``: its schedule through real owner indexes, scored and costed."""
    n = team.n_robots
    plan = schedule(rule, x, team.order, other, n, seed)
    answers = run_queries(x, team.robots, plan.owners, team.order, plan.switches)
    name = f"balance_n{n}_run{seed}"
    centres_out[f"{name}_start"] = plan.start_centres
    centres_out[name] = plan.centres
    first = plan.switches[0].at if plan.switches else len(x)
    code_bytes = FLOAT_BYTES * x.shape[1]
    migration = answers.migrated * (code_bytes + QUERY_HEADER_BYTES)
    copies = answers.replicas if answers.replicas is not None else np.full((len(x), 1), -1)
    extra = {
        "start_assignment": plan.start.to_json(),
        "rebalances": len(plan.switches),
        "period_queries": plan.period,
        "split_clusters": len(plan.centres) - len(plan.start_centres),
        "migrated_descriptors": answers.migrated,
        "stored_twice_share": float((copies >= 0).any(1).mean()),
        "copies_per_query": float((copies >= 0).sum() / len(x)),
        "migration_bytes": migration,
        "migration_bytes_per_query": migration / len(x),
        "worst_balance_ratio_after_first_period": worst_balance_ratio(answers.owners[team.order[first:]], n),
    }
    c = rule.clusters_per_robot
    return _record(name, "balance", team, c, seed, answers, centralized, plan.table, code_bytes, extra)


def _quantisation(
    s: EvaluationSettings, x: Float32Array, other: Float32Array, world: RenderedWorld
) -> list[dict[str, Any]]:
    """Recall@1/5 and AUC of the decoded descriptors against float32, the model card's protocol."""
    thresholds = PlaceThresholds(s.max_distance_m, s.max_angle_deg)
    closures = same_place(world.positions, world.directions, world.frames, thresholds)
    pairs = eligible_pairs(world.frames, thresholds.exclusion_frames)
    quantizers: list[tuple[str, Quantizer | None]] = [("float32", None), ("int8", Int8Quantizer(x.shape[1]))]
    quantizers += [(f"pq{m}", PQQuantizer(x.shape[1], m).train(other, seed=0)) for m in s.pq_bytes]
    rows = []
    for name, q in quantizers:
        decoded = x if q is None else q.decode(q.encode(x))
        metrics, _ = retrieval_metrics(decoded, closures, pairs)
        wire = FLOAT_BYTES * x.shape[1] if q is None else q.code_bytes
        rows.append({"code": name, "descriptor_bytes": wire, "query_bytes": wire + 5, **asdict(metrics)})
    return rows


def main(settings: EvaluationSettings) -> EvaluationSummary:
    """Run every experiment of the module docstring and write its files to ``settings.out``."""
    s = settings
    started = time.perf_counter()
    out = Path(s.out)
    out.mkdir(parents=True, exist_ok=True)
    set_faiss_threads(s.threads)
    model = DescriptorModel(s.model, intra_op_threads=s.threads)
    if s.progress:
        print(
            f"rendering and describing {s.deployment_frames} frames of office {s.deployment_seed} and "
            f"every {s.other_stride}th frame of {s.other_worlds} other offices ...",
            file=sys.stderr,
            flush=True,
        )
    deployment = render_world(s.deployment_seed, s.deployment_frames, 1, vary=False, offset=False)
    x = model.describe(deployment.images)
    other, other_seeds = other_descriptors(model, s.other_worlds, s.other_seed_base, s.other_stride)
    describe_s = time.perf_counter() - started
    np.savez_compressed(
        out / "descriptors.npz",
        deployment=x,
        frames=deployment.frames,
        positions=deployment.positions,
        directions=deployment.directions,
        deployment_seed=np.int64(s.deployment_seed),
        other=other,
        other_worlds=np.array(other_seeds, np.int64),
    )
    same = same_place(
        deployment.positions,
        deployment.directions,
        deployment.frames,
        PlaceThresholds(s.max_distance_m, s.max_angle_deg, 0),
    )
    runs: list[RunResult] = []
    centres_out: dict[str, Any] = {}  # Any: np.savez's keyword parameters are typed too
    centralized: dict[int, float] = {}
    teams: dict[int, Team] = {}
    for n in sorted({*s.robots, s.fig7_robots}):
        team = teams[n] = make_team(n, same)
        answers = run_queries(x, team.robots, np.zeros(len(x), np.int64), team.order)
        centralized[n] = team_auc(team, answers)
    total = (len(s.robots) + len(s.clusters_per_robot) + 1) * s.runs
    with tqdm(total=total, desc="runs", unit="run", disable=not s.progress, leave=False) as bar:
        for n in s.robots:
            for seed in range(s.runs):
                runs.append(random_run(f"fig6_n{n}_run{seed}", "fig6", teams[n], 1, seed, x, other,
                                        centralized[n], centres_out))  # fmt: skip
                bar.update()
        for c in s.clusters_per_robot:
            n = s.fig7_robots
            for seed in range(s.runs):
                runs.append(random_run(f"fig7_c{c}_run{seed}", "fig7", teams[n], c, seed, x, other,
                                        centralized[n], centres_out))  # fmt: skip
                bar.update()
        n = s.fig7_robots
        balanced = []
        for seed in range(s.runs):
            balanced.append(_balanced_run(s, teams[n], seed, x, other, centralized[n], centres_out))
            bar.update()
    runs += balanced
    sweep_s = time.perf_counter() - started - describe_s
    quantisation = _quantisation(s, x, other, deployment)

    fig6 = _aggregate([r for r in runs if r.experiment == "fig6"], "n_robots")
    fig7 = _aggregate([r for r in runs if r.experiment == "fig7"], "clusters_per_robot")
    one = next((row for row in fig7 if row["clusters_per_robot"] == 1), None)
    balance = {
        "n_robots": n,
        "clusters_per_robot_start": s.balance_clusters_per_robot,
        "rebalance_share": s.rebalance_share,
        "replica_share": s.replica_share,
        "slack": s.slack,
        "copy_neighbours": s.copy_neighbours,
        **_aggregate(balanced, "n_robots")[0],
        "worst_balance_ratio_after_first_period_runs": [
            r.extra["worst_balance_ratio_after_first_period"] for r in balanced
        ],
        "migration_bytes_per_query_mean": float(
            np.mean([r.extra["migration_bytes_per_query"] for r in balanced])
        ),
        "copies_per_query_mean": float(np.mean([r.extra["copies_per_query"] for r in balanced])),
        "split_clusters_runs": [r.extra["split_clusters"] for r in balanced],
        "one_cluster_per_robot": one,
    }
    np.savez_compressed(out / "runs.npz", **centres_out)
    (out / "runs.json").write_text(json.dumps([asdict(r) for r in runs], indent=1) + "\n")
    seconds = {"render_and_describe": describe_s, "sweeps": sweep_s}
    seconds["total"] = time.perf_counter() - started
    summary = EvaluationSummary(out, centralized, fig6, fig7, balance, quantisation, runs, seconds)
    (out / "summary.json").write_text(json.dumps(summary.to_json(), indent=1) + "\n")
    plot_sweep(fig6, "n_robots", "robots", out / "fig6.png", "Fig. 6: one cluster per robot")
    plot_sweep(fig7, "clusters_per_robot", "clusters per robot", out / "fig7.png",
               f"Fig. 7: {s.fig7_robots} robots", balance)  # fmt: skip
    return summary
