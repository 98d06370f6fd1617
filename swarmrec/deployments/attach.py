"""Attach to a swarm that runs, whatever runs it: ``swarmrec run --attach DIR``.

A deployment that leaves its swarm running (``swarmrec up``, ``swarmrec compose up``,
``swarmrec k8s up``) writes ``DIR/swarm.json``, an :class:`~swarmrec.deployments.base.AttachFile`
whose ``deployment`` field names the deployment that wrote it. :func:`attach`
reads it and returns that deployment, attached: its ``start(spec)`` checks that the
running swarm is the spec instead of starting one, and its ``stop()`` leaves it
running.
"""

from __future__ import annotations

from pathlib import Path

from swarmrec.deployments.base import AttachFile, read_attach_json
from swarmrec.deployments.compose import ComposeDeployment
from swarmrec.deployments.kubernetes import KubernetesDeployment
from swarmrec.deployments.local_up import AttachedLocal
from swarmrec.errors import ConfigError

__all__ = ["DEPLOYMENTS", "attach", "deployment_of"]

#: The deployments that write an attach file, by the name in its ``deployment`` field.
DEPLOYMENTS = ("local", "compose", "kubernetes")


def deployment_of(folder: Path) -> str:
    """Which deployment wrote ``folder/swarm.json`` (files of older versions: compose)."""
    data = read_attach_json(folder)
    kind = data.get("deployment", "compose")
    if kind not in DEPLOYMENTS:
        raise ConfigError(
            f"{folder / 'swarm.json'}: unknown deployment {kind!r} (known: {', '.join(DEPLOYMENTS)})"
        )
    return str(kind)


def attach(folder: Path) -> tuple[AttachedLocal | ComposeDeployment | KubernetesDeployment, AttachFile]:
    """The running swarm ``folder/swarm.json`` describes, as a deployment, and the file."""
    kind = deployment_of(folder)
    if kind == "local":
        local = AttachedLocal(folder)
        return local, local.info
    if kind == "kubernetes":
        k8s = KubernetesDeployment.attached(folder)
        assert k8s.info is not None  # read from the file
        return k8s, k8s.info
    compose = ComposeDeployment(folder)
    return compose, compose.info
