"""Experiments: pipelines that take a deployment and wire the stages of one method.

* :mod:`.places`: place recognition with constellations (``swarmrec run``);
* :mod:`.landmarks`: cooperative landmark recognition (``swarmrec landmarks``).

Each is a package with ``main(settings, deployment)``; a new method (full-image
descriptors routed to cluster owners, object-based multi-robot SLAM) is a new
package beside them.
"""
