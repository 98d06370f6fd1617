"""The main job: a local swarm of N robots as real processes, its replay and its report.

``swarmrec run`` parses its flags into :class:`SwarmSettings` and calls
:func:`main` (swarmrec.swarm.job); tests call ``main`` directly.
"""

from swarmrec.swarm.job import SwarmSettings, main

__all__ = ["SwarmSettings", "main"]
