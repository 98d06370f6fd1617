"""Experiments: pipelines that take a deployment and wire the stages of one method.

* :mod:`.places`: place recognition with constellations (``swarmrec run``);
* :mod:`.vpr`: place recognition from full-image descriptors routed to cluster owners
  (``swarmrec run --method dvpr|both``);
* :mod:`.landmarks`: cooperative landmark recognition (``swarmrec landmarks``);
* :mod:`.slam`: the distributed Gauss-Seidel as one slam service per robot
  (``swarmrec slam run``) and the maps of a place-recognition run merged
  (``swarmrec slam merge``).

Each is a package with ``main(settings, ...)``; a new method is a new package beside them.
"""
