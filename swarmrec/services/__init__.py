"""The swarm's services, one per pipeline stage, each a thin adapter around the core.

Data flow, one robot::

    detector --Constellation--> descriptor --PartialQuery--> index-shard (each robot's, by label range)
                                           --VerifyRequest--> verifier (the chosen robots')
                                           --LoopClosure event-->
    classifier view --classify--> detector --start_round--> fusion --ClassifierOutput--> neighbours' fusion

Every kind is an entry of :mod:`swarmrec.services.registry` (its class, settings
components, metrics, scope); ``swarmrec serve <kind>`` runs one on the shared
runner (:mod:`swarmrec.runtime`). The operator-facing contract of each kind
(endpoints, settings, metrics) is generated from the registry into the
repository's top-level ``services/`` folder.
"""
