"""Where a swarm runs: one small interface, one implementation per place.

* :class:`~swarmrec.deployments.local.LocalDeployment`: every service a process on
  this machine (no container engine needed);
* :class:`~swarmrec.deployments.compose.ComposeDeployment`: a compose project's
  containers, with a real Prometheus (``swarmrec compose up``);
* :class:`~swarmrec.deployments.kubernetes.KubernetesDeployment`: the ``k8s/``
  manifests in a namespace of a cluster, with Secrets for every identity
  (``swarmrec run --deployment k8s``, ``swarmrec k8s up``).

A swarm left running is attached to again from its ``swarm.json``
(:func:`~swarmrec.deployments.attach.attach`, ``swarmrec run --attach DIR``).

Each takes a :class:`~swarmrec.deployments.base.SwarmSpec` (bus settings, each
robot's service kinds from the registry, shared settings) and implements
:class:`~swarmrec.deployments.base.Deployment`. Experiments take a deployment and
never know which one it is.
"""

from swarmrec.deployments.attach import attach
from swarmrec.deployments.base import AttachFile, Deployment, DeploymentError, SwarmSpec, SwarmStartError
from swarmrec.deployments.compose import ComposeDeployment, ComposeError
from swarmrec.deployments.kubernetes import KubernetesDeployment, KubernetesError, KubernetesSettings
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import Scrape

__all__ = [
    "AttachFile",
    "ComposeDeployment",
    "ComposeError",
    "Deployment",
    "DeploymentError",
    "KubernetesDeployment",
    "KubernetesError",
    "KubernetesSettings",
    "LocalDeployment",
    "Scrape",
    "SwarmSpec",
    "SwarmStartError",
    "attach",
]
