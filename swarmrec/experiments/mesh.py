"""A run on a mesh (a router per robot, docs/mesh.md), whatever the method: the radio
graph planned from the robots' own positions, each lock-step step's links put in place
and converged before the step, and the bytes each link carried during the replay."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from swarmrec.core.types import Trajectory
from swarmrec.deployments.base import Deployment, RadioMesh
from swarmrec.deployments.mesh import MeshOperator, MeshReport, mesh_report
from swarmrec.deployments.radio import Pair, robot_positions
from swarmrec.errors import ConfigError

__all__ = ["MeshRun", "plan_mesh"]


@dataclass
class MeshRun:
    """One run's mesh: the step hook, and what it recorded."""

    mesh: RadioMesh
    events: list[tuple[int, str]] = field(default_factory=list)
    converge_s: list[float] = field(default_factory=list)
    before: dict[Pair, tuple[float, float]] = field(default_factory=dict)
    #: Bytes each link carried while the links changed (the harness's), left out of the report.
    harness: dict[Pair, tuple[float, float]] = field(default_factory=dict)

    def before_step(self, operator: MeshOperator) -> Callable[[int], None]:
        """What puts step ``t``'s links in place, converged, before the step starts."""

        def hook(t: int) -> None:
            if self.mesh.radio is None or t == 0 or t not in self.mesh.radio.changes():
                return
            # What crosses the links while they change is the harness's (closing links, the
            # convergence checks' asks): measured and left out of the replay's link bytes.
            before = self.mesh.link_bytes()
            changed, waited = self.mesh.step_links(t, operator)
            _add(self.harness, before, self.mesh.link_bytes())
            self.events.extend((t, e) for e in changed)
            if waited is not None:
                self.converge_s.append(waited)

        return hook

    def start_counting(self) -> None:
        """The links' byte counters as the replay starts."""
        self.before = self.mesh.link_bytes()

    def report(self, queries: int) -> MeshReport:
        """What the links carried since :meth:`start_counting`, over ``queries``."""
        assert self.mesh.radio is not None  # planned before the start
        after = self.mesh.link_bytes()
        # The replay's own traffic: the links' bytes since the start, less the harness's.
        for pair, (ab, ba) in self.harness.items():
            a, b = after.get(pair, (0.0, 0.0))
            after[pair] = (a - ab, b - ba)
        return mesh_report(
            self.mesh.radio,
            self.before,
            after,
            queries,
            self.events,
            self.converge_s,
            self.mesh.mesh_start,
        )


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
    split = [t for t in range(graph.steps) if len(graph.components_at(t)) > 1]
    if split:
        first, parts = split[0], [sorted(c) for c in graph.components_at(split[0])]
        last = next((t - 1 for t in range(first + 1, graph.steps) if t not in split), graph.steps - 1)
        raise ConfigError(
            f"the radio graph splits the team at steps {first}-{last} into {parts}: what each method "
            "does while the team is split is not built yet (docs/mesh.md, 'Partitions'); choose a "
            "radio range or schedule that keeps the team connected"
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
