"""Cooperative landmark recognition through a swarm: the pipeline behind ``swarmrec landmarks``.

``main(settings, deployment)`` runs the simulation (:mod:`.simulation`: street
configurations, rendered views, rounds through the detectors and fusion services,
the check against the core) on ``deployment`` (local processes by default, or a
compose swarm with ``--attach``) and writes the paper's figures and the report
(:mod:`.report`).
"""

from __future__ import annotations

from swarmrec.deployments.base import Deployment
from swarmrec.experiments.landmarks.report import LandmarksSummary, write_landmark_report
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, run_simulation

__all__ = ["main"]


def main(
    settings: LandmarkSettings, deployment: Deployment, *, figure_law: str | None = None
) -> LandmarksSummary:
    """Simulate on ``deployment`` and write the report; returns the summary."""
    settings.out.mkdir(parents=True, exist_ok=True)
    return write_landmark_report(run_simulation(settings, deployment), figure_law)
