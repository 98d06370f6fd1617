"""A run on a mesh (a router per robot, docs/mesh.md), whatever the method: the radio
graph planned from the robots' own positions, each lock-step step's links put in place
and converged before the step, and the bytes each link carried during the replay.

When the links change, the step also waits until every robot's descriptor has made a
whole pass over its pending stores (each is delivered to every owner now in reach), and,
while the team is split, reads the placement every part follows (it is held while split:
the offline simulation of the schedule, :class:`~swarmrec.evaluation.partition.Reach`,
uses it)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from swarmrec.core.placement import Placement
from swarmrec.core.types import Trajectory
from swarmrec.deployments.base import Deployment, RadioMesh
from swarmrec.deployments.errors import DeploymentError
from swarmrec.deployments.mesh import MeshOperator, MeshReport, mesh_report
from swarmrec.deployments.radio import Pair, robot_positions
from swarmrec.errors import ConfigError
from swarmrec.evaluation.partition import Reach
from swarmrec.services.routing import newest_placement, version_of

__all__ = ["DELIVER_TIMEOUT_S", "MeshRun", "plan_mesh"]

#: How long a step waits, after its links changed, for the descriptors' pending stores.
DELIVER_TIMEOUT_S = 60.0
#: Between two looks at them.
DELIVER_POLL_S = 0.05


@dataclass
class MeshRun:
    """One run's mesh: the step hook, and what it recorded."""

    mesh: RadioMesh
    events: list[tuple[int, str]] = field(default_factory=list)
    converge_s: list[float] = field(default_factory=list)
    before: dict[Pair, tuple[float, float]] = field(default_factory=dict)
    #: Bytes each link carried while the links changed (the harness's), left out of the report.
    harness: dict[Pair, tuple[float, float]] = field(default_factory=dict)
    #: Payload bytes by (message type, zenoh message) summed over the links, as the replay starts.
    before_types: dict[tuple[str, str], float] = field(default_factory=dict)
    #: Seconds each link change waited for the pending stores' pass.
    deliver_s: list[float] = field(default_factory=list)
    #: (step, placement) every part of the split team followed from that step.
    held: list[tuple[int, Placement]] = field(default_factory=list)
    #: (step, {shard: version}) where the parts of a split team did not all follow one.
    disagreed: list[tuple[int, dict[int, int]]] = field(default_factory=list)

    def before_step(self, operator: MeshOperator) -> Callable[[int], None]:
        """What puts step ``t``'s links in place, converged, before the step starts."""

        def hook(t: int) -> None:
            if self.mesh.radio is None or t == 0 or t not in self.mesh.radio.changes():
                return
            # What crosses the links while they change is the harness's (closing links, the
            # convergence checks' asks): measured and left out of the replay's link bytes.
            before = self.mesh.link_bytes()
            changed, waited = self.mesh.step_links(t, operator)
            if waited is not None:
                self.converge_s.append(waited)
                t0 = time.perf_counter()
                self._deliver(operator)
                self.deliver_s.append(time.perf_counter() - t0)
                assert self.mesh.radio is not None
                if len(self.mesh.radio.components_at(t)) > 1:
                    self._hold(operator, t)
            _add(self.harness, before, self.mesh.link_bytes())
            self.events.extend((t, e) for e in changed)

        return hook

    def _deliver(self, operator: MeshOperator) -> None:
        """Wait until every robot's descriptor owes no store or has finished a pass over its
        pending stores begun after the links changed (the one under way may have begun
        before): every slice owed to an owner now in reach is then delivered."""
        assert self.mesh.radio is not None
        robots = range(self.mesh.radio.robots)
        first = {r: operator.descriptor_info(r) for r in robots}
        waiting = {r for r, info in first.items() if info is not None and info.pending_items}
        deadline = time.monotonic() + DELIVER_TIMEOUT_S
        while waiting:
            for r in sorted(waiting):
                now, then = operator.descriptor_info(r), first[r]
                assert then is not None
                if now is not None and (
                    not now.pending_items or now.pending_passes >= then.pending_passes + 2
                ):
                    waiting.discard(r)
            if not waiting:
                return
            if time.monotonic() > deadline:
                raise DeploymentError(
                    f"robots {sorted(waiting)}' descriptors did not finish a pass over their pending "
                    f"stores within {DELIVER_TIMEOUT_S:.0f} s of the links changing"
                )
            time.sleep(DELIVER_POLL_S)

    def _hold(self, operator: MeshOperator, t: int) -> None:
        """The placement each part of the split team follows at step ``t``: one, held by every
        shard (the coordinators change nothing while the team is split); recorded for the
        offline simulation, and any disagreement kept for the report."""
        assert self.mesh.radio is not None
        states = []
        for part in self.mesh.radio.components_at(t):
            states += operator.shard_states_at(min(part))
        versions = {st.shard_id: version_of(st) if st.confirmed else -1 for st in states}
        placement = newest_placement(states)
        held = placement is not None and placement.settled and len(set(versions.values())) == 1
        # A placement comes into force only while the team is whole (after step t - 1): a
        # new one in the middle of a split was made apart.
        apart = len(self.mesh.radio.components_at(t - 1)) > 1
        new = placement is not None and (not self.held or self.held[-1][1].version != placement.version)
        if not held or (new and apart):
            self.disagreed.append((t, versions))
        elif new:
            assert placement is not None
            self.held.append((t, placement))

    def reach(self, bounds: Sequence[int], replicas: int) -> Reach | None:
        """The offline simulation's schedule of this run: each step's components and the
        placements held while split; None when the team was never split."""
        radio = self.mesh.radio
        assert radio is not None
        parts = [[sorted(c) for c in radio.components_at(t)] for t in range(radio.steps)]
        if all(len(p) == 1 for p in parts):
            return None
        start = Reach.of(parts, radio.robots, bounds, replicas=replicas)
        return Reach(start.components, (start.placements[0], *self.held))

    def start_counting(self) -> None:
        """The links' byte counters as the replay starts."""
        self.before, self.before_types = self.mesh.link_bytes(), self.mesh.type_bytes()

    def report(self, queries: int) -> MeshReport:
        """What the links carried since :meth:`start_counting`, over ``queries``."""
        assert self.mesh.radio is not None  # planned before the start
        after, after_types = self.mesh.link_bytes(), self.mesh.type_bytes()
        # The replay's own traffic: the links' bytes since the start, less the harness's.
        for pair, (ab, ba) in self.harness.items():
            a, b = after.get(pair, (0.0, 0.0))
            after[pair] = (a - ab, b - ba)
        # (These include what the harness asked of the index while the team was split.)
        types = {
            f"{name} {message}": (v - self.before_types.get((name, message), 0.0)) / queries
            for (name, message), v in after_types.items()
            if queries
        }
        out = mesh_report(
            self.mesh.radio,
            self.before,
            after,
            queries,
            self.events,
            self.converge_s,
            self.mesh.mesh_start,
        )
        out.type_bytes_per_query = {k: v for k, v in sorted(types.items(), key=lambda kv: -kv[1]) if v > 0}
        out.deliver_s = list(self.deliver_s)
        out.held_placements = [{"step": t, "version": p.version} for t, p in self.held]
        out.split_disagreements = [
            {"step": t, "versions": {str(k): v for k, v in sorted(vs.items())}} for t, vs in self.disagreed
        ]
        return out


def plan_mesh(
    deployment: Deployment, blocks: Sequence[range], trajectory: Trajectory | None, *, lockstep: bool
) -> MeshRun | None:
    """The mesh of a run whose robots replay ``blocks`` of a dataset with ``trajectory``
    (None: the deployment has one router); its radio graph planned now, before the
    swarm starts, so that a bad schedule is refused before anything runs."""
    mesh = deployment.mesh
    if mesh is None:
        return None
    steps = max((len(b) for b in blocks), default=0)
    n_frames = sum(len(b) for b in blocks)
    positions = None
    if trajectory is not None and len(trajectory) == n_frames:
        positions = robot_positions(trajectory.positions, blocks)
    graph = mesh.plan_radio(len(blocks), steps, positions)
    if graph.range_m is not None and positions is None:
        raise ConfigError(
            "a radio range needs the robots' positions: this dataset has no pose for every frame"
        )
    if graph.steps and len(graph.components_at(0)) > 1:
        parts = [sorted(c) for c in graph.components_at(0)]
        raise ConfigError(
            f"the radio graph splits the team at step 0 into {parts}: a team starts whole (its index "
            "settles on one placement first); split it later in the schedule"
        )
    if not lockstep and graph.changes():
        raise ConfigError(
            "the mesh's links change during the run (radio range or schedule): they follow lock-step "
            "steps, so use --pace lockstep"
        )
    return MeshRun(mesh)


def _add(
    into: dict[Pair, tuple[float, float]],
    before: dict[Pair, tuple[float, float]],
    after: dict[Pair, tuple[float, float]],
) -> None:
    """Add each link's bytes from ``before`` to ``after`` into ``into``."""
    for pair, (ab, ba) in after.items():
        b0 = before.get(pair, (0.0, 0.0))
        i0 = into.get(pair, (0.0, 0.0))
        into[pair] = (i0[0] + ab - b0[0], i0[1] + ba - b0[1])
