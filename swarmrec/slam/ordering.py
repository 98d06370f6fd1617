"""The order in which robots take their Gauss-Seidel turn.

``"flagged"`` is the public distributed Gauss-Seidel implementation's order
for flagged initialisation (``orderRobots`` in CogRob/distributed-mapper):
the robot holding the anchor first; then, repeatedly, every robot not yet
ordered that has at least one separator to the ordered ones, appended all at
once by decreasing number of such separators (equal counts: the higher robot
number first, as that implementation's reverse walk of a multimap gives);
robots never reached are appended at the end in increasing order. With two
robots the order is simply ``[anchor robot, other]``.

``"greedy"`` appends one robot at a time, the one with the most separators to
the robots already ordered (equal counts: the lower number), recounting after
each: every robot then starts next to the most already-estimated neighbours.
``"natural"`` is ``0, 1, 2, ...``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Literal

from swarmrec.errors import ConfigError

__all__ = ["ORDERINGS", "Ordering", "order_robots"]

Ordering = Literal["flagged", "greedy", "natural"]
ORDERINGS: tuple[Ordering, ...] = ("flagged", "greedy", "natural")


def _links(counts: Mapping[tuple[int, int], int], robot: int, ordered: Iterable[int]) -> int:
    return sum(counts.get((min(robot, o), max(robot, o)), 0) for o in ordered)


def order_robots(
    robots: Iterable[int],
    separator_counts: Mapping[tuple[int, int], int],
    *,
    first: int,
    method: Ordering = "flagged",
) -> tuple[int, ...]:
    """The Gauss-Seidel order of ``robots``; ``separator_counts[(a, b)]`` (``a < b``) separators per pair."""
    team = sorted(set(robots))
    if first not in team:
        raise ConfigError(f"the first robot {first} is not in the team {team}")
    if method not in ORDERINGS:
        raise ConfigError(f"ordering must be one of {ORDERINGS}, got {method!r}")
    if method == "natural":
        return (first, *[r for r in team if r != first])
    ordered = [first]
    if len(team) == 2:
        return (first, *[r for r in team if r != first])
    while True:
        candidates = [(r, _links(separator_counts, r, ordered)) for r in team if r not in ordered]
        candidates = [(r, n) for r, n in candidates if n > 0]
        if not candidates:
            break
        if method == "flagged":
            ordered.extend(r for r, _ in sorted(candidates, key=lambda c: (c[1], c[0]), reverse=True))
        else:
            ordered.append(max(candidates, key=lambda c: (c[1], -c[0]))[0])
    ordered.extend(r for r in team if r not in ordered)
    return tuple(ordered)
