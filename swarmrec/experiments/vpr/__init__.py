"""Full-image place recognition (Cieslewski and Scaramuzza) through a swarm.

:mod:`.settings` says what a run is (``swarmrec run --method dvpr|both``); :mod:`.pipeline`
prepares the frames, the centres and the assignment, deploys the ``dvpr`` workload
(verifier, place-owner, detector per robot), replays (:mod:`.replay`), collects and reports
(:mod:`.report`), and for ``both`` runs the constellation method on the same frames and
puts the two side by side. docs/vpr.md, "The live swarm".
"""

from swarmrec.experiments.vpr.pipeline import BothSummary, main
from swarmrec.experiments.vpr.report import Comparison, DvprSummary
from swarmrec.experiments.vpr.settings import DvprSettings, VprRunSettings

__all__ = ["BothSummary", "Comparison", "DvprSettings", "DvprSummary", "VprRunSettings", "main"]
