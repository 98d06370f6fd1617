"""The swarm's Zenoh services and the runner they share.

Data flow, one robot::

    detector --Constellation--> descriptor --PartialQuery--> index-shard (each robot's, by label range)
                                           --VerifyRequest--> verifier (the chosen robots')
                                           --LoopClosure event-->
    classifier output --start_round--> fusion --ClassifierOutput--> fusion of each neighbour (flooding)

``python -m swarmrec serve <kind>`` runs one service (see :data:`SERVICES`).
"""

from __future__ import annotations

from collections.abc import Callable

from swarmrec.services.runner import Service, ServiceContext

__all__ = ["SERVICES", "service_factory"]

SERVICES = ("router", "detector", "descriptor", "index-shard", "verifier", "fusion")


def service_factory(kind: str) -> Callable[[ServiceContext], Service]:
    """The class that implements ``kind`` (imported on demand: a shard need not load numba);
    for the detector, a factory that picks the class of its ``detector_mode``."""
    if kind == "detector":
        from swarmrec.services.detector import make_detector

        return make_detector
    if kind == "descriptor":
        from swarmrec.services.descriptor import Descriptor

        return Descriptor
    if kind == "index-shard":
        from swarmrec.services.index_shard import IndexShard

        return IndexShard
    if kind == "verifier":
        from swarmrec.services.verifier import Verifier

        return Verifier
    if kind == "fusion":
        from swarmrec.services.fusion import FusionService

        return FusionService
    raise ValueError(f"unknown service {kind!r}; services: {', '.join(SERVICES)}")
