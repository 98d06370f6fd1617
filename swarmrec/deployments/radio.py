"""Who hears whom: the radio graph of a mesh swarm at each lock-step step (docs/mesh.md).

A mesh swarm runs a router per robot, and two robots' routers are linked only while
the robots hear each other. That comes from two sources, both set by the user:

* a **radio range** (``--radio-range M``): robots ``a`` and ``b`` hear each other at
  step ``t`` when the robots' own positions at that step (the pose of the frame each
  replays then; every dataset here has poses) are at most ``M`` metres apart. No range:
  every robot hears every other (the full mesh);
* the **link schedule** (``--link-schedule``, :func:`~swarmrec.deployments.links.read_schedule`):
  a ``robot`` row is about all that robot's links (an outage cuts every one), a
  ``robot_a, robot_b`` row about one link. A schedule only takes away or slows what
  the range gives; it never links robots the range keeps apart.

The graph is computed ahead for the whole run, so the deployment knows which pairs
ever need a link and the report can list the components over time. Everything here is
plain computation: the same graph drives the live emulator and the offline simulation.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.deployments.links import LinkSpec, Schedule
from swarmrec.errors import ConfigError

__all__ = ["Pair", "RadioGraph", "components", "robot_positions"]

Pair = tuple[int, int]
FloatArray = npt.NDArray[np.float64]


def robot_positions(positions: FloatArray, blocks: Sequence[range]) -> FloatArray:
    """Each robot's position at each lock-step step, ``(steps, robots, 3)``: at step ``t``
    robot ``r`` is where the frame it replays then was taken (``positions`` per frame);
    after its last frame it stays where it was. A robot with no frames has NaN (it hears
    nobody)."""
    steps = max((len(b) for b in blocks), default=0)
    out = np.full((steps, len(blocks), 3), np.nan)
    for r, block in enumerate(blocks):
        if len(block) == 0:
            continue
        frames = [block[min(t, len(block) - 1)] for t in range(steps)]
        out[:, r, :] = positions[frames]
    return out


def components(robots: int, links: Iterable[Pair]) -> list[frozenset[int]]:
    """The connected components of ``robots`` under ``links``, each ordered by its lowest
    robot (the same order everywhere: the components are compared and reported)."""
    parent = list(range(robots))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in links:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, set[int]] = {}
    for r in range(robots):
        groups.setdefault(root(r), set()).add(r)
    return [frozenset(groups[k]) for k in sorted(groups)]


@dataclass(frozen=True)
class RadioGraph:
    """The links between robots at every step (see the module docstring)."""

    robots: int
    #: ``links[t]``: the pairs (lower id first) linked at step ``t``, with each link's spec.
    links: tuple[dict[Pair, LinkSpec], ...]
    range_m: float | None = None

    @classmethod
    def build(
        cls,
        robots: int,
        steps: int,
        *,
        positions: FloatArray | None = None,
        range_m: float | None = None,
        schedule: Schedule | None = None,
        default: LinkSpec | None = None,
    ) -> RadioGraph:
        """The graph of ``steps`` steps. ``positions`` ``(steps, robots, 3)`` are needed with
        ``range_m``; ``schedule`` must be in steps; ``default`` is every link's spec when
        no row changes it."""
        if robots < 1:
            raise ConfigError(f"a radio graph needs at least one robot, got {robots}")
        if range_m is not None:
            if not (math.isfinite(range_m) and range_m > 0):
                raise ConfigError(f"the radio range must be a distance > 0 in metres, got {range_m}")
            if positions is None or positions.shape[:2] != (steps, robots):
                raise ConfigError("a radio range needs every robot's position at every step")
        if schedule is not None:
            if schedule.unit != "step":
                raise ConfigError("a mesh's link schedule is in lock-step steps (--schedule-unit step)")
            schedule.check(robots)
        default = default or LinkSpec()
        everyone = [(a, b) for a in range(robots) for b in range(a + 1, robots)]
        out: list[dict[Pair, LinkSpec]] = []
        for t in range(max(steps, 1)):
            heard = everyone
            if range_m is not None:
                assert positions is not None
                p = positions[min(t, steps - 1)] if steps else np.full((robots, 3), np.nan)
                d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
                # NaN (a robot without a pose) compares False: it hears nobody.
                heard = [(a, b) for a, b in everyone if d[a, b] <= range_m]
            robot_rows = schedule.state_at(float(t)) if schedule is not None else {}
            pair_rows = schedule.pairs_at(float(t)) if schedule is not None else {}
            step: dict[Pair, LinkSpec] = {}
            for pair in heard:
                spec: LinkSpec | None = default
                for r in pair:
                    if r in robot_rows:
                        spec = _slower(spec, robot_rows[r])
                if pair in pair_rows:
                    spec = _slower(spec, pair_rows[pair])
                if spec is not None:
                    step[pair] = spec
            out.append(step)
        return cls(robots, tuple(out), range_m)

    @property
    def steps(self) -> int:
        return len(self.links)

    def at(self, t: int) -> dict[Pair, LinkSpec]:
        """The links at step ``t`` (the last step's after the end)."""
        return self.links[min(max(t, 0), len(self.links) - 1)]

    def pairs(self) -> list[Pair]:
        """Every pair linked at some step: the links the deployment must be able to make."""
        return sorted({p for step in self.links for p in step})

    def components_at(self, t: int) -> list[frozenset[int]]:
        return components(self.robots, self.at(t))

    def component_of(self, t: int) -> dict[int, frozenset[int]]:
        """Each robot's component at step ``t``."""
        return {r: c for c in self.components_at(t) for r in c}

    def changes(self) -> list[int]:
        """The steps (after 0) whose links differ from the step before."""
        return [t for t in range(1, len(self.links)) if self.links[t] != self.links[t - 1]]

    def hops_at(self, t: int) -> dict[Pair, int]:
        """The fewest links between every two robots of one component at step ``t``
        (the path zenoh's routers take: shortest by hop count)."""
        adj: dict[int, list[int]] = {r: [] for r in range(self.robots)}
        for a, b in self.at(t):
            adj[a].append(b)
            adj[b].append(a)
        out: dict[Pair, int] = {}
        for src in range(self.robots):
            dist = {src: 0}
            frontier = [src]
            while frontier:
                nxt = []
                for u in frontier:
                    for v in adj[u]:
                        if v not in dist:
                            dist[v] = dist[u] + 1
                            nxt.append(v)
                frontier = nxt
            out.update(((src, v), d) for v, d in dist.items() if v > src)
        return out

    def timeline(self) -> list[dict[str, object]]:
        """The components over time, one entry per run of steps with the same ones."""
        out: list[dict[str, object]] = []
        for t in range(self.steps):
            comps = [sorted(c) for c in self.components_at(t)]
            links = len(self.at(t))
            if out and out[-1]["components"] == comps and out[-1]["links"] == links:
                out[-1]["end"] = t + 1
            else:
                out.append({"start": t, "end": t + 1, "components": comps, "links": links})
        return out


def _slower(current: LinkSpec | None, row: LinkSpec | None) -> LinkSpec | None:
    """A link with a row applied: an outage cuts it, a changed link replaces each value it sets."""
    if current is None or row is None:
        return None
    return LinkSpec(
        row.rate_kbps if row.rate_kbps is not None else current.rate_kbps,
        row.latency_ms if row.latency_ms is not None else current.latency_ms,
    )
