"""The offline job: the distributed solve of a folder of per-robot g2o files, checked against gtsam.

:func:`solve_folder` reads ``0.g2o, 1.g2o, ...`` (:func:`~swarmrec.slam.g2o.read_robot_folder`),
runs the distributed two-stage Gauss-Seidel with one in-process agent per
robot, solves the same graph centrally with gtsam, and writes to ``out``:

- ``<r>.g2o``: robot ``r``'s vertices at the distributed estimate and every edge touching them;
- ``merged.g2o``: the whole team at the distributed estimate; ``centralized.g2o``: at gtsam's;
- ``summary.json``: :class:`SolveSummary` (iterations per stage, costs, ATE*/ARE* against
  gtsam, floats and bytes per link by the 9/6-float model, timings).

:func:`main` is what ``swarmrec slam`` calls: it solves and prints a short report.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from swarmrec.errors import ConfigError
from swarmrec.slam.centralized import METHODS, Method, solve_centralized
from swarmrec.slam.dgs import (
    DgsSettings,
    DistributedResult,
    run_dgs,
)
from swarmrec.slam.g2o import read_robot_folder, robot_file_name, write_g2o
from swarmrec.slam.metrics import Accuracy, accuracy

__all__ = ["LinkTraffic", "SlamSettings", "SolveSummary", "StageReport", "Timings", "main", "solve_folder"]

SUMMARY_NAME = "summary.json"


@dataclass(frozen=True)
class SlamSettings:
    """Settings of the offline distributed solve (``swarmrec slam``), validated on construction.

    - ``folder``: the robot folder (``0.g2o``, ``1.g2o``, ..., optional ``fullGraph.g2o``).
    - ``out``: where the estimates and ``summary.json`` are written.
    - ``solver``: the distributed solver's settings (:class:`~swarmrec.slam.dgs.DgsSettings`, the
      one class every SLAM command takes them in). :meth:`paper` gives the paper's method.
    - ``centralized``: gtsam's reference method, ``gauss-newton`` or ``levenberg-marquardt``.
    - ``bytes_per_float``: 8 (float64, what the agents compute in) or 4, for the byte model.
    - ``overwrite``: replace an earlier result in ``out``.
    """

    folder: Path
    out: Path
    solver: DgsSettings = field(default_factory=DgsSettings)
    centralized: Method = "gauss-newton"
    bytes_per_float: int = 8
    overwrite: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "folder", Path(self.folder))
        object.__setattr__(self, "out", Path(self.out))
        if not self.folder.is_dir():
            raise ConfigError(f"folder {self.folder} is not a directory of robot g2o files")
        if self.out.exists() and not self.out.is_dir():
            raise ConfigError(f"out {self.out} exists and is not a directory")
        if (self.out / SUMMARY_NAME).exists() and not self.overwrite:
            raise ConfigError(
                f"{self.out / SUMMARY_NAME} exists: add --overwrite to replace it (Python: overwrite=True)"
            )
        if self.centralized not in METHODS:
            raise ConfigError(f"centralized must be one of {METHODS}, got {self.centralized!r}")
        if self.bytes_per_float not in (4, 8):
            raise ConfigError(f"bytes_per_float must be 4 or 8, got {self.bytes_per_float}")

    @staticmethod
    def paper(folder: Path, out: Path, *, eta: float = 1e-1, overwrite: bool = False) -> SlamSettings:
        """The paper's method: plain Gauss-Seidel, one linearisation, eta 0.1 (or 0.01)."""
        return SlamSettings(folder, out, solver=DgsSettings.paper(eta), overwrite=overwrite)


@dataclass(frozen=True)
class StageReport:
    stage: str
    linearisation: int
    iterations: int
    converged: bool
    floats: int


@dataclass(frozen=True)
class LinkTraffic:
    """What one robot sent another over the whole solve (floats by the 9/6 model, and bytes)."""

    sender: int
    receiver: int
    floats: int
    bytes: int


@dataclass(frozen=True)
class Timings:
    """Seconds spent reading, solving distributed (all agents, one process), solving in gtsam, writing."""

    read: float
    distributed: float
    centralized: float
    write: float


@dataclass(frozen=True)
class SolveSummary:
    """Everything ``summary.json`` holds (:meth:`to_json`)."""

    folder: str
    robots: int
    vertices: int
    edges: int
    separators: int
    order: tuple[int, ...]
    mode: str
    gamma: float
    eta_rotation: float
    eta_pose: float
    pose_linearisations: int
    stages: tuple[StageReport, ...]
    rotation_iterations: int
    pose_iterations: tuple[int, ...]
    converged: bool
    centralized_method: str
    centralized_iterations: int
    cost_initial: float
    accuracy: Accuracy
    bytes_per_float: int
    links: tuple[LinkTraffic, ...]
    total_floats: int
    total_bytes: int
    timings: Timings
    files: tuple[str, ...]

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN, e.g. ATE* of objects when there are none, becomes null)."""
        out: dict[str, Any] = finite_json(asdict(self))
        return out


def finite_json(value: Any) -> Any:
    """``value`` (dicts, lists, floats) with every NaN or infinity as None: JSON has neither."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(v) for v in value]
    return value


def _links(result: DistributedResult, bytes_per_float: int) -> tuple[LinkTraffic, ...]:
    return tuple(LinkTraffic(s, r, n, n * bytes_per_float) for (s, r), n in result.floats_per_link().items())


def solve_folder(settings: SlamSettings) -> SolveSummary:
    """Solve ``settings.folder`` distributed and centrally, write the estimates and ``summary.json``."""
    t0 = time.perf_counter()
    team = read_robot_folder(settings.folder)
    graph = team.graph
    t1 = time.perf_counter()
    result = run_dgs(graph, settings.solver)
    t2 = time.perf_counter()
    reference = solve_centralized(graph, method=settings.centralized, anchor=result.anchor)
    t3 = time.perf_counter()
    out = settings.out
    files = []
    for robot in graph.robots:
        files.append(
            write_g2o(
                out / robot_file_name(robot),
                graph,
                result.poses,
                keys=graph.robot_keys(robot),
                edges=graph.robot_edges(robot),
            )
        )
    files.append(write_g2o(out / "merged.g2o", graph, result.poses))
    files.append(write_g2o(out / "centralized.g2o", graph, reference.poses))
    t4 = time.perf_counter()
    summary = SolveSummary(
        folder=str(settings.folder),
        robots=len(graph.robots),
        vertices=len(graph.poses),
        edges=len(graph.edges),
        separators=len(graph.separators()),
        order=result.order,
        mode=settings.solver.mode,
        gamma=settings.solver.over_relaxation,
        eta_rotation=settings.solver.eta_rotation,
        eta_pose=settings.solver.eta_pose,
        pose_linearisations=settings.solver.pose_linearisations,
        stages=tuple(
            StageReport(s.stage, s.linearisation, s.iterations, s.converged, s.floats) for s in result.stages
        ),
        rotation_iterations=result.rotation_iterations,
        pose_iterations=result.pose_iterations,
        converged=result.converged,
        centralized_method=settings.centralized,
        centralized_iterations=reference.iterations,
        cost_initial=graph.cost(),
        accuracy=accuracy(graph, result.poses, reference.poses),
        bytes_per_float=settings.bytes_per_float,
        links=_links(result, settings.bytes_per_float),
        total_floats=result.total_floats,
        total_bytes=result.total_floats * settings.bytes_per_float,
        timings=Timings(t1 - t0, t2 - t1, t3 - t2, t4 - t3),
        files=tuple(str(f) for f in files),
    )
    (out / SUMMARY_NAME).write_text(json.dumps(summary.to_json(), indent=2) + "\n", encoding="utf-8")
    return summary


def format_summary(summary: SolveSummary) -> str:
    """A few lines for a terminal."""
    a = summary.accuracy
    return "\n".join(
        [
            f"distributed Gauss-Seidel on {summary.folder}: {summary.robots} robots, "
            f"{summary.vertices} vertices, "
            f"{summary.edges} edges ({summary.separators} separators), order {list(summary.order)}",
            f"  iterations: rotation {summary.rotation_iterations}, pose {list(summary.pose_iterations)}"
            f"{'' if summary.converged else ' (a stage hit max_iterations)'}",
            f"  cost: initial {summary.cost_initial:.4g}, distributed {a.cost:.6g}, "
            f"centralized {summary.centralized_method} {a.reference_cost:.6g}",
            f"  ATE* poses {a.ate_poses:.3g} m, ARE* poses {a.are_poses_deg:.3g} deg (vs centralized)",
            f"  sent {summary.total_floats} floats = {summary.total_bytes} B "
            f"over {len(summary.links)} directed links",
        ]
    )


def main(settings: SlamSettings) -> SolveSummary:
    """Solve, write, print a short report; returns the summary (``swarmrec slam``)."""
    summary = solve_folder(settings)
    print(format_summary(summary))
    print(f"  written to {settings.out}")
    return summary
