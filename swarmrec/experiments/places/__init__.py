"""Place recognition with constellations (Ramtoula et al., CAPRICORN) through a swarm.

:mod:`.settings` says what a run is; :mod:`.pipeline` prepares the data and the
swarm's spec, deploys, replays (:mod:`.replay`), collects and reports
(:mod:`.report`); :mod:`.pixels` starts from RGB-D frames.
"""

from swarmrec.experiments.places.pipeline import main
from swarmrec.experiments.places.report import PlacesSummary
from swarmrec.experiments.places.settings import PixelSettings, PlacesSettings

__all__ = ["PixelSettings", "PlacesSettings", "PlacesSummary", "main"]
