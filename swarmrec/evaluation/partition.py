"""What a split team's index holds, step by step: the offline side of a mesh's partitions.

In a mesh (docs/mesh.md, "Partitions") the team may split into components that cannot
reach each other, and heal. The constellation method then does, by definition:

* **A store** of robot ``j``'s slice of group ``g`` at step ``s`` reaches the owners of
  ``g`` in ``j``'s component at ``s``. For every other owner it waits on robot ``j``
  (the descriptor's pending stores) and is delivered before the first later step at
  which ``j`` and that owner are in one component again.
* **A query** of robot ``r`` at step ``t`` for group ``g`` goes to one owner of ``g`` in
  ``r``'s component, the serving owner among those
  (:func:`~swarmrec.core.placement.serving_owner`, the rule every querier computes), and
  sees what that owner holds. A group with no owner in the component gives no
  candidates.
* **Verification**: the querier picks its robots from the candidates as always
  (:func:`~swarmrec.core.selection.select_robots`); a picked robot outside its component
  cannot verify, and its candidates give no pair.
* **The placement does not change while the team is split** (no coordinator moves a
  group of a robot it cannot reach), so the owners of a split stretch are the placement
  in force when it began, made (its handoffs done) while the team was whole: its owners
  hold every slice stored before. While the team is whole, every owner holds every
  earlier slice (pending stores are delivered first), so which owner answers, and the
  placement, change nothing.

:class:`Reach` is the schedule (components per step, placements by step) and
:class:`Holdings` what each owner holds; :func:`~swarmrec.evaluation.scoring.score_decentralized`
uses them when given a ``reach``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.placement import Placement, groups_from_bounds, ring, serving_owner
from swarmrec.errors import ConfigError

__all__ = ["Holdings", "Reach"]

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Reach:
    """Who reaches whom at each lock-step step, and where the label groups live.

    ``components[t, r]`` names robot ``r``'s component at step ``t`` (two robots with
    the same name reach each other, directly or through relays). ``placements`` are
    (first step, placement) pairs, the first from step 0; a step beyond the last row of
    ``components`` keeps the last row's components."""

    components: IntArray
    placements: tuple[tuple[int, Placement], ...]

    def __post_init__(self) -> None:
        comps = np.asarray(self.components, np.int64)
        if comps.ndim != 2 or comps.shape[0] < 1:
            raise ConfigError(f"components must be (steps, robots), got shape {comps.shape}")
        if not self.placements or self.placements[0][0] != 0:
            raise ConfigError("the placements must start at step 0")
        starts = [s for s, _ in self.placements]
        if starts != sorted(starts):
            raise ConfigError(f"the placements' first steps must be in order, got {starts}")
        object.__setattr__(self, "components", comps)
        made_apart = [s for s in starts[1:] if self.split_at(s - 1)]
        if made_apart:
            raise ConfigError(
                f"placements come into force only after a step of the whole team, not at steps {made_apart}"
            )

    @classmethod
    def of(
        cls,
        components: Sequence[Sequence[Sequence[int]]],
        n_robots: int,
        bounds: Sequence[int],
        *,
        replicas: int,
        placements: Sequence[tuple[int, Placement]] = (),
    ) -> Reach:
        """From each step's components as lists of robots; without ``placements``, the
        placement every swarm starts from (version 0) for the whole run."""
        rows = np.full((len(components), n_robots), -1, np.int64)
        for t, comps in enumerate(components):
            for c, members in enumerate(comps):
                rows[t, list(members)] = c
        if (rows < 0).any():
            raise ConfigError("every robot must be in one component at every step")
        start = ring(groups_from_bounds([int(b) for b in bounds]), range(n_robots), replicas=replicas)
        return cls(rows, tuple(placements) or ((0, start),))

    @property
    def n_robots(self) -> int:
        return int(self.components.shape[1])

    def at(self, t: int) -> IntArray:
        """Each robot's component at step ``t``."""
        row: IntArray = self.components[min(t, self.components.shape[0] - 1)]
        return row

    def placement_at(self, t: int) -> Placement:
        current = self.placements[0][1]
        for start, p in self.placements:
            if start > t:
                break
            current = p
        return current

    def split_at(self, t: int) -> bool:
        """Whether the team is in more than one component at step ``t``."""
        return len(set(self.at(t).tolist())) > 1


class Holdings:
    """Which stored slices each owner of each group holds (see the module docstring).

    ``stored[j, s, k]``: robot ``j`` stores a slice of label range ``k`` at step ``s``.
    ``range_groups[k]``: the placement's group of range ``k`` (None for an empty range).
    Call :meth:`deliver` before a step's queries and :meth:`store` after them."""

    def __init__(self, reach: Reach, stored: BoolArray, range_groups: Sequence[int | None]) -> None:
        if stored.shape[0] != reach.n_robots:
            raise ConfigError(f"{stored.shape[0]} robots stored, the schedule has {reach.n_robots}")
        self.reach, self.stored = reach, stored
        self.range_groups = list(range_groups)
        n, per, _ = stored.shape
        self._shape = (n, per)
        self._held: dict[tuple[int, int], BoolArray] = {}
        #: Queries (robot, step, range) that found no owner of the range in their component.
        self.unreached: list[tuple[int, int, int]] = []
        #: (robot, step, robot) verifications a querier could not reach.
        self.unverified: list[tuple[int, int, int]] = []

    def _owners(self, t: int, k: int) -> tuple[int, ...]:
        g = self.range_groups[k]
        return () if g is None else self.reach.placement_at(t).owners[g]

    def held(self, owner: int, k: int) -> BoolArray:
        """(robots, steps): the slices of range ``k`` that ``owner`` holds."""
        key = (owner, k)
        if key not in self._held:
            self._held[key] = np.zeros(self._shape, bool)
        return self._held[key]

    def deliver(self, t: int) -> None:
        """Before step ``t``: every owner holds every earlier slice of the robots in its
        component (what it got when stored, and the pending stores delivered now). A
        placement that comes into force at ``t`` was made, and its handoffs done, while
        the team was whole: its new owners copied every earlier slice."""
        comp = self.reach.at(t)
        for k in range(len(self.range_groups)):
            before = set(self._owners(t - 1, k)) if t > 0 else set()
            for o in self._owners(t, k):
                if t > 0 and o not in before:
                    self.held(o, k)[:, :t] = self.stored[:, :t, k]
                mates = comp == comp[o]
                self.held(o, k)[mates, :t] = self.stored[mates, :t, k]

    def store(self, t: int) -> None:
        """Step ``t``'s slices, at the owners in each storing robot's component."""
        comp = self.reach.at(t)
        for k in range(len(self.range_groups)):
            storing: list[int] = np.flatnonzero(self.stored[:, t, k]).tolist() if t < self._shape[1] else []
            for o in self._owners(t, k):
                for r in storing:
                    if comp[r] == comp[o]:
                        self.held(o, k)[r, t] = True

    def visible(self, robot: int, k: int, t: int) -> BoolArray | None:
        """The robot-major slots (robots x ``t``) that robot ``robot``'s query of range ``k``
        at step ``t`` sees: the serving owner's in its component; None when the component
        has no owner of the range (recorded in :attr:`unreached`)."""
        comp = self.reach.at(t)
        owners = self._owners(t, k)
        g = self.range_groups[k]
        here = [o for o in owners if comp[o] == comp[robot]]
        o = None if g is None else serving_owner(self.reach.placement_at(t), g, robot, t, here)
        if o is None:
            self.unreached.append((robot, t, k))
            return None
        return self.held(o, k)[:, :t].reshape(-1)

    def reachable(self, robot: int, t: int, others: IntArray) -> BoolArray:
        """Which of ``others`` (robot ids) ``robot`` reaches at step ``t``."""
        comp = self.reach.at(t)
        out: BoolArray = comp[others] == comp[robot]
        return out
