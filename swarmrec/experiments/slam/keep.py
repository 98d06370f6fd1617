"""A SLAM team left running for later solves to attach to (``swarmrec compose up --workload
slam``; ``swarmrec slam run --attach DIR`` solves through it).

:func:`compose` prepares the robot folder as the pipeline does (a simulated world written
as ``<r>.g2o`` files, or the folder given) and writes the compose files of the team's spec:
one slam service per robot, each container reading its own file from the folder copied
beside the compose file. :func:`from_record` is the later solve: the team's settings read
back from ``swarm.json``, the solver's own from the command line (each solve sends them).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from swarmrec.deployments.compose import ComposeSettings, SwarmFile, write_compose
from swarmrec.errors import ConfigError
from swarmrec.experiments.slam.pipeline import prepare, swarm_spec
from swarmrec.experiments.slam.settings import LiveSlamSettings

__all__ = ["compose", "from_record"]

#: The record's format: a later version reads the records it knows only.
RECORD = "swarmrec.slam-record/1"
#: Where the compose file keeps the team's robot folder (the containers mount it).
FOLDER = "slam"


def compose(settings: LiveSlamSettings, compose_settings: ComposeSettings) -> SwarmFile:
    """Write the compose files of the team ``settings`` describes under ``compose_settings.out``
    (a simulated world written to ``out/input`` first)."""
    out = compose_settings.out.resolve()
    prepared = prepare(settings.with_(out=out))
    robots = len(prepared.graph.robots)
    record = {
        "format": RECORD,
        # A simulated world is generated again by the attached run (its truth, for the report);
        # a folder given is read from the copy the containers mount.
        "folder": None if prepared.scenario is not None else str(out / FOLDER),
        "world": settings.world,
        "robots": robots,
        "seed": settings.seed,
        "swarm": settings.swarm,
        "request_timeout_s": settings.request_timeout_s,
        "peer_timeout_s": settings.peer_timeout_s,
    }
    info = write_compose(swarm_spec(settings, prepared.folder, robots), compose_settings, experiment=record)
    if prepared.scenario is not None:  # written here only to be copied where the containers mount it
        shutil.rmtree(prepared.folder)
    return info


def from_record(record: dict[str, Any], **changes: Any) -> LiveSlamSettings:
    """The team a compose swarm was composed for, as a live solve's settings (``changes``: out,
    solver, progress ...)."""
    if record.get("format") != RECORD:
        raise ConfigError(f"the swarm file's experiment record is not a SLAM team ({RECORD})")
    try:
        team = {
            "folder": Path(record["folder"]) if record["folder"] else None,
            "world": record["world"],
            "robots": int(record["robots"]),
            "seed": int(record["seed"]),
            "swarm": str(record["swarm"]),
            "request_timeout_s": float(record["request_timeout_s"]),
            "peer_timeout_s": float(record["peer_timeout_s"]),
        }
    except (KeyError, TypeError, ValueError) as e:
        raise ConfigError(f"the swarm file's experiment record is not a SLAM team: {e}") from None
    taken = sorted(set(team) & set(changes))
    if taken:
        raise ConfigError(f"the running team fixes {', '.join(taken)}; a solve through it cannot change them")
    return LiveSlamSettings(**team, **changes)
