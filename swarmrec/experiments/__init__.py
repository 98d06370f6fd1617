"""Experiments: pipelines that take a deployment and wire the stages of one method.

* :mod:`.places`: place recognition with constellations (``swarmrec run``);
* :mod:`.vpr`: place recognition from full-image descriptors routed to cluster owners
  (``swarmrec run --method dvpr|both``);
* :mod:`.landmarks`: cooperative landmark recognition (``swarmrec landmarks``).

Each is a package with ``main(settings, ...)``; a new method (object-based multi-robot
SLAM) is a new package beside them.
"""
