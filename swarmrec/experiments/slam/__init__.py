"""Object-based multi-robot SLAM's back end through a swarm: the distributed Gauss-Seidel as services.

:mod:`.pipeline` runs a robot folder (or a simulated world) through one ``slam``
service per robot (``swarmrec slam run``); :mod:`.report` checks it against
:func:`~swarmrec.slam.dgs.run_dgs` and gtsam and measures the bytes;
:mod:`.merge` builds the robots' graphs from a finished place-recognition run
(its verified loop closures) and merges their maps (``swarmrec slam merge``).
"""

from swarmrec.experiments.slam.pipeline import main
from swarmrec.experiments.slam.report import LiveSlamSummary, format_summary
from swarmrec.experiments.slam.settings import LiveSlamSettings

__all__ = ["LiveSlamSettings", "LiveSlamSummary", "format_summary", "main"]
