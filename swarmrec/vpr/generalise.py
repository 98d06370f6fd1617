"""Choosing a re-balancing rule on some worlds and reporting it on others (issue 26).

A rule tuned on one office can fail on the next: the first rule (one boundary copy at the
second-nearest cell's owner, for half of the queries nearest a boundary) gained 0.05 relative
AUC over one cluster per robot on the deployment it was tuned on and lost 0.06 on another
office. So a rule is chosen on *tuning* worlds and reported on *held-out* worlds that the
choice never saw, each world over several seeds, against one cluster per robot (the paper's
Fig. 6 at the same robots) measured in the same run.

The targets, on every world's mean over its seeds: worst balance ratio at most
:data:`MAX_BALANCE` and relative AUC at least one cluster per robot's minus
:data:`MAX_AUC_DROP`. :func:`choose` takes the candidate with the fewest bytes a query (queries,
boundary copies and moved clusters, under the byte model) that meets both on every tuning world
with ``margin`` to spare; if none does, the one whose worst tuning world is nearest its AUC
target among those within the balance target (or, if none is, the most balanced).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from swarmrec.errors import ConfigError

__all__ = ["MAX_AUC_DROP", "MAX_BALANCE", "Choice", "WorldMean", "choose", "meets_targets", "world_mean"]

#: The issue's targets: worst balance ratio at most this ...
MAX_BALANCE = 1.5
#: ... and relative AUC not below one cluster per robot's minus this.
MAX_AUC_DROP = 0.02


@dataclass(frozen=True)
class WorldMean:
    """One rule on one world: means over its seeds, and one cluster per robot's on the same seeds."""

    world: str
    rule: str
    runs: int
    relative_auc: float
    worst_balance_ratio: float
    copies_per_query: float
    #: Queries, copies and moved descriptors, under the byte model.
    bytes_per_query: float
    baseline_relative_auc: float
    baseline_worst_balance_ratio: float

    @property
    def auc_margin(self) -> float:
        """How far the relative AUC is above its target (negative: below)."""
        return self.relative_auc - (self.baseline_relative_auc - MAX_AUC_DROP)


def world_mean(
    world: str,
    rule: str,
    relative_auc: Sequence[float],
    worst_balance_ratio: Sequence[float],
    copies_per_query: Sequence[float],
    bytes_per_query: Sequence[float],
    baseline_relative_auc: Sequence[float],
    baseline_worst_balance_ratio: Sequence[float],
) -> WorldMean:
    """The means of one rule's runs on one world and of the baseline's on the same seeds."""
    sizes = {len(relative_auc), len(worst_balance_ratio), len(copies_per_query), len(bytes_per_query)}
    base = {len(baseline_relative_auc), len(baseline_worst_balance_ratio)}
    if len(sizes) != 1 or len(base) != 1 or 0 in sizes | base:
        raise ConfigError(f"{world}/{rule}: every list needs the same, non-zero number of runs")
    return WorldMean(
        world,
        rule,
        len(relative_auc),
        float(np.mean(relative_auc)),
        float(np.mean(worst_balance_ratio)),
        float(np.mean(copies_per_query)),
        float(np.mean(bytes_per_query)),
        float(np.mean(baseline_relative_auc)),
        float(np.mean(baseline_worst_balance_ratio)),
    )


def meets_targets(mean: WorldMean, margin: float = 0.0) -> bool:
    """Both targets on this world's mean, each with ``margin`` to spare."""
    return mean.worst_balance_ratio <= MAX_BALANCE - margin and mean.auc_margin >= margin


@dataclass(frozen=True)
class Choice:
    """The chosen rule and why: whether it met both targets on every tuning world."""

    rule: str
    meets_targets: bool
    worst_auc_margin: float
    worst_balance_ratio: float
    copies_per_query: float
    bytes_per_query: float


def choose(means: Sequence[WorldMean], margin: float = 0.0) -> Choice:
    """The rule of the module docstring, from every candidate's means on the tuning worlds
    (each candidate on the same worlds); ties go to the earlier candidate."""
    rules = list(dict.fromkeys(m.rule for m in means))
    if not rules:
        raise ConfigError("no candidate rules to choose from")
    by_rule = {r: [m for m in means if m.rule == r] for r in rules}
    worlds = {r: sorted(m.world for m in ms) for r, ms in by_rule.items()}
    if len({tuple(w) for w in worlds.values()}) != 1:
        raise ConfigError(f"every candidate must be measured on the same worlds, got {worlds}")

    def summary(rule: str, ok: bool) -> Choice:
        ms = by_rule[rule]
        return Choice(
            rule,
            ok,
            min(m.auc_margin for m in ms),
            max(m.worst_balance_ratio for m in ms),
            float(np.mean([m.copies_per_query for m in ms])),
            float(np.mean([m.bytes_per_query for m in ms])),
        )

    passing = [r for r in rules if all(meets_targets(m, margin) for m in by_rule[r])]
    if passing:
        cheapest = min(passing, key=lambda r: summary(r, True).bytes_per_query)
        return summary(cheapest, True)
    balanced = [r for r in rules if all(m.worst_balance_ratio <= MAX_BALANCE for m in by_rule[r])]
    if balanced:
        return summary(max(balanced, key=lambda r: summary(r, False).worst_auc_margin), False)
    return summary(min(rules, key=lambda r: summary(r, False).worst_balance_ratio), False)
