"""Cooperative landmark recognition (Brent, Yuan and Stegagno, SAC '21) through a swarm.

:mod:`.simulation` runs street configurations through the robots' detectors
(classifier mode) and fusion services; :mod:`.report` draws the paper's Figs. 3-5;
:mod:`.pipeline` wires them for ``swarmrec landmarks``.
"""

from swarmrec.experiments.landmarks.pipeline import main
from swarmrec.experiments.landmarks.report import LandmarksSummary
from swarmrec.experiments.landmarks.simulation import DEFAULT_LAWS, VIEW_PRESETS, LandmarkSettings, parse_law

__all__ = ["DEFAULT_LAWS", "VIEW_PRESETS", "LandmarkSettings", "LandmarksSummary", "main", "parse_law"]
